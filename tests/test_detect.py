"""Segment detection: every static and turn of simulated sessions is found where the simulator put
it (statics trimmed by the settling time), turn angles, rates and constant-rate parts match the
commanded profile, the index positions and full turns are picked for either turn sense, and
sample times follow the counter across lost datagrams and its wrap."""

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest

from calibd import detect
from calibd.frames import r1
from calibd.scenario import load_scenario
from calibd.sim import simulate
from stim300.bulk import decode_capture
from stim300.clock import counter_times
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
SETTLE_S = 1.0
EDGE_S = 0.1  # detected edges vs the truth: the turn threshold is crossed within a smoothing half-window


def counter_sense(scenario):
    """The same session turning the other way."""
    flipped = tuple(replace(s, angle_deg=-s.angle_deg) if s.kind == "turn" else s for s in scenario.segments)
    return replace(scenario, name=scenario.name + "-ccw", seed=scenario.seed + 1, segments=flipped)


def noiseless(scenario):
    """No noise; the warm-up as the scenario has it."""
    return replace(scenario, noise=replace(scenario.noise, enabled=False))


@pytest.fixture(scope="module")
def real():
    return simulate(load_scenario("thesis-real"))


@pytest.fixture(scope="module")
def real_ccw():
    return simulate(counter_sense(load_scenario("thesis-real")))


@pytest.fixture(scope="module")
def bench():
    return simulate(load_scenario("thesis-bench"))


def found(sim, **options):
    s = sim.samples
    return detect.find_segments(s["gyro"], s["acc"], sim.scenario.sensor.sample_rate_hz, **options)


def check_against_truth(segments, schedule, rate_hz, *, angle_tol=0.1, rate_tol=0.01, chi_tol=0.2):
    """Each truth phase (dicts as in a truth file) has its segment, in order, where it should be."""
    assert [s.kind for s in segments] == ["turn" if p["kind"] == "turn" else "static" for p in schedule]
    for k, (seg, p) in enumerate(zip(segments, schedule)):
        assert seg.platform_angle_deg == pytest.approx(p["chi_start_deg"], abs=chi_tol)
        if p["kind"] == "turn":
            assert seg.start_s == pytest.approx(p["start_s"], abs=EDGE_S)
            assert seg.end_s == pytest.approx(p["end_s"], abs=EDGE_S)
            assert seg.angle_deg == pytest.approx(p["angle_deg"], abs=angle_tol)
            assert seg.rate_deg_s == pytest.approx(np.sign(p["angle_deg"]) * p["peak_rate_deg_s"], abs=rate_tol)
            cruise_start, cruise_end = seg.cruise_start / rate_hz, seg.cruise_stop / rate_hz
            assert p["cruise_start_s"] - 1e-9 <= cruise_start < cruise_end <= p["cruise_end_s"] + 1e-9
            assert cruise_end - cruise_start >= 0.9 * (p["cruise_end_s"] - p["cruise_start_s"])
            assert seg.up is None
        else:
            start = p["start_s"] + (SETTLE_S if k > 0 else 0.0)
            end = p["end_s"] - (SETTLE_S if k < len(schedule) - 1 else 0.0)
            assert seg.start_s == pytest.approx(start, abs=EDGE_S)
            assert seg.end_s == pytest.approx(end, abs=EDGE_S)
            assert seg.up == p["up"]
            assert seg.angle_deg is seg.rate_deg_s is seg.cruise_start is None
        assert seg.start_s == pytest.approx(seg.start / rate_hz) and seg.end_s == pytest.approx(seg.stop / rate_hz)


@pytest.mark.parametrize("session", ["real", "real_ccw", "bench"])
def test_simulated_sessions_are_cut_where_the_simulator_put_them(session, request):
    sim = request.getfixturevalue(session)
    check_against_truth(found(sim), [asdict(p) for p in sim.phases], 125)


def test_noise_free_session_gives_the_commanded_profile_exactly():
    sim = simulate(noiseless(load_scenario("thesis-real")))
    check_against_truth(found(sim), [asdict(p) for p in sim.phases], 125, angle_tol=1e-3, rate_tol=1e-4,
                        chi_tol=1e-3)


@pytest.mark.parametrize("sim_name,sense", [("real", -1), ("real_ccw", +1)])
def test_index_positions_are_the_statics_after_the_90_deg_turns(sim_name, sense, request):
    sim = request.getfixturevalue(sim_name)
    segments = found(sim)
    statics = [s for s in segments if s.kind == "static"]
    index = detect.index_positions(segments)
    assert index == statics[1:5]  # the level static, then one after each 90 deg turn
    assert [s.platform_angle_deg for s in index] == pytest.approx([sense * 90 * k for k in (1, 2, 3, 4)], abs=0.2)
    assert detect.level_static(segments) == statics[0]
    turns = detect.full_turns(segments)
    assert len(turns) == 1 and turns[0] == segments[-2]  # the full turn, not the 90 deg ones
    # 360 deg with 30 deg/s^2 ramps: 13 deg of ramp at each end, so less than a period at constant rate
    assert turns[0].angle_deg == pytest.approx(360.0 * sense, abs=0.1)
    assert 325.0 < abs(turns[0].cruise_angle_deg) < 334.1


@pytest.mark.parametrize("angle_deg,role", [(90, "index turn"), (-90, "index turn"), (340, "other turn"),
                                            (-352, "full turn"), (360, "full turn"), (-390, "full turn"),
                                            (720, "full turn")])
def test_a_full_turn_is_judged_on_its_whole_angle_ramps_included(angle_deg, role):
    """As a platform runs it: 27.93 deg/s with 30 deg/s^2 ramps, whatever the constant-rate part."""
    scenario = load_scenario("thesis-real")
    segments = (scenario.segments[0], replace(scenario.segments[-2], angle_deg=angle_deg), scenario.segments[-1])
    found_segments = found(simulate(noiseless(replace(scenario, segments=segments))))
    assert detect.segment_roles(found_segments) == ["static", role, "static"]
    progress = detect.campaign_progress(found_segments)  # what the daemon shows while collecting
    assert f"1 {role}," in progress + "," and progress.count(" 0 ") == 2


def test_bench_positions_come_out_as_separate_statics(bench):
    segments = found(bench)
    ups = [s.up for s in segments if s.kind == "static"]
    assert ups[:7] == ["+Z", "-Z", "-Y", "+Y", "-X", "+X", "+Z"]
    assert len(detect.full_turns(segments)) == 3
    with pytest.raises(ValueError, match=r"none at .*180, 270 deg \(mod 360\)"):
        detect.index_positions(segments)  # no 90 deg turns on the bench


@pytest.mark.parametrize("rotation,up", [(np.diag([1.0, -1.0, -1.0]), "-Z"), (r1(np.radians(60)), "+Y")])
def test_a_tilted_or_upside_down_imu_gives_the_same_turns(real, rotation, up):
    """The turn axis is the gravity direction of the static before, not the IMU Z axis."""
    s = real.samples
    plain = found(real)
    turned = detect.find_segments(s["gyro"].astype(float) @ rotation.T, s["acc"].astype(float) @ rotation.T, 125)
    assert [(t.kind, t.start, t.stop) for t in turned] == [(t.kind, t.start, t.stop) for t in plain]
    assert [t.platform_angle_deg for t in turned] == pytest.approx([t.platform_angle_deg for t in plain], abs=1e-6)
    assert {t.up for t in turned if t.kind == "static"} == {up}


def test_2000hz_capture():
    data = (FIXTURES / "static_turn_2000hz.bin").read_bytes()
    truth = json.loads((FIXTURES / "static_turn_2000hz.bin.truth.json").read_text())
    decoded = decode_capture(data)
    samples, rate = decoded.samples, decoded.info.format.sample_rate_hz
    assert rate == 2000
    time_s = counter_times(samples["counter"], rate).time_s
    segments = detect.find_segments(samples["gyro"], samples["acc"], rate, time_s, min_static_s=3.0)
    check_against_truth(segments, truth["schedule"], rate)


def test_capture_with_lost_datagrams_is_one_static():
    data = (FIXTURES / "faults_125hz.bin").read_bytes()
    truth = json.loads((FIXTURES / "faults_125hz.bin.truth.json").read_text())
    decoded = decode_capture(data)
    samples, rate = decoded.samples, decoded.info.format.sample_rate_hz
    time_s = counter_times(samples["counter"], rate).time_s
    faults = truth["faults"]
    lost = set(faults["dropped_samples"]) | set(faults["bit_flipped_samples"])
    kept = np.array([k for k in range(truth["samples"]) if k not in lost])
    assert len(samples) == len(kept)
    before = kept < faults["restart_at_sample"]  # the restart resets the counter: a constant offset after it
    assert np.allclose(time_s[before], kept[before] / rate)
    offset = time_s[~before] - kept[~before] / rate
    assert np.allclose(offset, offset[0])
    segments = detect.find_segments(samples["gyro"], samples["acc"], rate, time_s)
    assert len(segments) == 1 and segments[0].kind == "static"
    assert (segments[0].start, segments[0].stop) == (0, len(samples))
    assert segments[0].end_s == pytest.approx(time_s[-1] + 1 / rate)


@pytest.mark.parametrize("rate", [125, 2000])
def test_counter_times_follow_the_counter_across_losses_and_the_wrap(rate):
    step = INTERNAL_RATE_HZ // rate
    cycle = COUNTER_MODULUS // step  # sample periods in one counter cycle
    rng = np.random.default_rng(rate)
    gaps = rng.choice([1, 1, 1, 2, 3, cycle - 1, cycle], 30 * cycle)  # periods between received samples
    index = 7 + np.concatenate(([0], np.cumsum(gaps)))  # up to a cycle minus one sample lost, many wraps
    times = counter_times(((index * step) % COUNTER_MODULUS).astype(np.uint8), rate).time_s
    assert np.allclose(times, (index - index[0]) / rate)
    assert np.diff(times).max() == pytest.approx(cycle / rate)
    # a whole cycle lost cannot be seen (documented): it reads as no loss
    aliased = counter_times(np.array([0, (cycle + 1) * step]) % COUNTER_MODULUS, rate).time_s
    assert np.allclose(aliased, [0, 1 / rate])
    assert len(counter_times(np.zeros(0, np.uint8), rate).time_s) == 0


def test_no_static_no_level():
    with pytest.raises(ValueError, match="no static"):
        detect.level_static([])


def test_handling_is_no_turn_and_splits_the_statics():
    """A 90 deg tilt by hand (rotation about a horizontal axis) is motion, not a turn."""
    rate, n = 125, 125 * 30
    gyro = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, 1.0], (n, 1))
    gyro[1500:1750, 0] = -45.0  # 2 s about X: Z up becomes Y up
    acc[1625:] = [0.0, 1.0, 0.0]
    segments = detect.find_segments(gyro, acc, rate)
    assert [(s.kind, s.up) for s in segments] == [("static", "+Z"), ("static", "+Y")]
    assert segments[0].stop < 1500 - 125 + 10 and segments[1].start > 1750 + 125 - 10
    assert segments[1].platform_angle_deg == 0.0


def test_campaign_progress_counts_the_campaign():
    from calibd.detect import campaign_progress
    sim = simulate(load_scenario("thesis-real"))
    s = sim.samples
    segments = detect.find_segments(s["gyro"].astype(float), s["acc"].astype(float), 125)
    assert campaign_progress(segments) == "6 statics at 4/4 index headings, 4 index turns, 1 full turn, 0 other turns"
    # index headings: those of the statics after the level static, as index_positions takes them
    assert campaign_progress(segments[:3]).startswith("2 statics at 1/4 index headings, 1 index turn")


def test_thresholds_follow_the_sensor_noise(real):
    """A sensor 30x noisier than the STIM300 (1 deg/s and 40 mg per sample at 125 Hz): the
    thresholds rise with its noise and the same segments are found; at the STIM300's own floor
    too, as the noise around each sample raises the threshold there (a vibrating static is no
    motion), while a turn stands above it."""
    s = real.samples
    rng = np.random.default_rng(7)
    gyro = s["gyro"].astype(float) + rng.normal(0.0, 1.0, s["gyro"].shape)
    acc = s["acc"].astype(float) + rng.normal(0.0, 0.04, s["acc"].shape)
    turn, remount = detect.motion_thresholds(gyro, acc, 125)
    expected_turn = detect.NOISE_MULTIPLE * np.sqrt(3) / np.sqrt(25)  # 3 axes of 1 deg/s, averaged over 25 samples
    assert turn == pytest.approx(expected_turn, rel=0.05)
    assert remount == pytest.approx(detect.NOISE_MULTIPLE * 0.04 * np.sqrt(3) * np.sqrt(2 / 24), rel=0.05)
    clean = found(real)
    noisy = detect.find_segments(gyro, acc, 125)
    assert [x.kind for x in noisy] == [x.kind for x in clean]
    for a, b in zip(noisy, clean):  # turn angles integrate the noise: ~0.5 deg per 30 s turn
        assert a.platform_angle_deg == pytest.approx(b.platform_angle_deg, abs=2.0)
    floor = detect.find_segments(gyro, acc, 125, turn_threshold_deg_s=detect.MIN_TURN_THRESHOLD_DEG_S)
    assert [x.kind for x in floor] == [x.kind for x in clean]


def test_quiet_sensor_keeps_the_floor(real):
    s = real.samples
    assert detect.motion_thresholds(s["gyro"], s["acc"], 125) == (detect.MIN_TURN_THRESHOLD_DEG_S,
                                                                  detect.MIN_REMOUNT_G)


@pytest.mark.parametrize("minutes", [0.5, 1.0, 3.7])
def test_tracker_finds_what_a_whole_pass_finds(real, minutes):
    """Fed a growing session in steps, the incremental tracker ends with the segments of one pass
    over the whole session, though it re-scans only the part after the second-to-last static."""
    s = real.samples
    gyro, acc = s["gyro"].astype(float), s["acc"].astype(float)
    whole = detect.find_segments(gyro, acc, 125)
    tracker = detect.SegmentTracker(125)
    step = int(minutes * 60 * 125)
    for n in range(step, len(gyro) + step, step):
        segments = tracker.update(gyro[:n], acc[:n])
    assert tracker._tail_start > len(gyro) // 2  # most of the session was final before the last update
    assert [(x.kind, x.start, x.stop, x.cruise_start, x.cruise_stop) for x in segments] == \
        [(x.kind, x.start, x.stop, x.cruise_start, x.cruise_stop) for x in whole]
    for a, b in zip(segments, whole):
        assert a.platform_angle_deg == pytest.approx(b.platform_angle_deg, abs=1e-9)
        assert a.start_s == pytest.approx(b.start_s, abs=1e-9)
        if a.kind == "turn":
            assert a.angle_deg == pytest.approx(b.angle_deg, abs=1e-9)

"""Simulator: noise-free captures reproduce the model exactly, turns integrate to their angle,
truth angles round-trip, noise has the configured Allan deviation, faults show in the stats."""

import json
from dataclasses import replace

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from calibd.frames import EARTH_RATE, STANDARD_GRAVITY, Site, euler_321, int_to_imu, nav_to_imu, nav_to_int
from calibd.allan import FLICKER_TAUS_S, allan_deviation, allan_gm, flicker_sigma
from calibd.scenario import ScenarioError, Segment, load_scenario, parse_scenario
from calibd.sim import capture_bytes, sensor_noise, simulate, truth_record
from calibd.units import DEG
from captures import quiet
from stim300.bulk import decode_capture
from stim300.protocol import Status

GYRO_LSB, ACC_LSB, INCL_LSB = 2.0**-14, 2.0**-19, 2.0**-22


def decoded(scenario):
    sim = simulate(scenario)
    data, faults = capture_bytes(sim)
    capture = decode_capture(data)
    return sim, capture.samples, capture.info, faults


@pytest.fixture(scope="module")
def thesis():
    return load_scenario("thesis-real")


def test_noise_free_statics_are_the_model_to_the_count(thesis):
    scenario = quiet(thesis)
    sim, samples, info, _ = decoded(scenario)
    t = scenario.truth
    r = nav_to_imu(t.yaw_deg * DEG, t.pitch_deg * DEG, t.roll_deg * DEG)
    gyro = r @ scenario.site.earth_rate_nav / DEG + np.array(t.gyro_bias_deg_h) / 3600
    force = r @ [0, 0, 9.79956] / STANDARD_GRAVITY
    acc = force + np.array(t.acc_bias_mg) / 1000
    incl = force + np.array(t.incl_bias_mg) / 1000
    level = slice(0, int(sim.phases[0].end_s * 125) - 1)  # the level static, before the first turn
    # every sample is the model rounded to the nearest count (1e-9 of full scale is below one count)
    assert np.array_equal(samples["gyro"][level], np.broadcast_to(np.rint(gyro / GYRO_LSB) * GYRO_LSB,
                                                                  samples["gyro"][level].shape).astype(np.float32))
    assert np.abs(samples["acc"][level].astype(np.float64).mean(0) - acc).max() <= ACC_LSB / 2
    assert np.abs(samples["incl"][level].astype(np.float64).mean(0) - incl).max() <= INCL_LSB / 2
    assert info.stats.datagrams == len(sim.samples)


@pytest.mark.parametrize("angle,rate,accel", [(-90, 20, 20), (90, 20, 20), (360, 27.93, 30), (-5, 20, 20)])
def test_turns_integrate_to_the_commanded_angle(thesis, angle, rate, accel):
    segments = (Segment("static", duration_s=2), Segment("turn", angle_deg=angle, peak_rate_deg_s=rate,
                                                         accel_deg_s2=accel), Segment("static", duration_s=2))
    scenario = replace(quiet(thesis, yaw_deg=0, pitch_deg=0, roll_deg=0, alpha_deg=0, beta_deg=0,
                             gyro_bias_deg_h=(0, 0, 0)), segments=segments)
    sim, samples, _, _ = decoded(scenario)
    turn = sim.phases[1]
    inside = (sim.time_s > turn.start_s) & (sim.time_s <= turn.end_s + 1 / 125)
    earth_z = EARTH_RATE * np.sin(scenario.site.latitude_deg * DEG) / DEG  # deg/s
    integral = (samples["gyro"][inside, 2].astype(np.float64) - earth_z).sum() / 125
    assert integral == pytest.approx(angle, abs=inside.sum() * GYRO_LSB / 125)
    cruise = (sim.time_s > turn.cruise_start_s + 0.01) & (sim.time_s < turn.cruise_end_s - 0.01)
    if cruise.any():  # the constant-rate part has the peak rate, with the sign of the turn
        assert samples["gyro"][cruise, 2].mean() - earth_z == pytest.approx(np.sign(angle) * rate, abs=1e-4)


def test_truth_angles_round_trip_through_the_rotation_matrix(thesis):
    rng = np.random.default_rng(3)
    angles = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], (200, 3))
    back = np.stack(euler_321(nav_to_imu(*angles.T)), axis=1)
    assert np.allclose(back, angles, atol=1e-12)
    record = truth_record(simulate(quiet(thesis)), {})
    t = record["truth"]
    home = int_to_imu(t["alpha_deg"] * DEG, t["beta_deg"] * DEG) @ nav_to_int(
        t["gamma1_deg"] * DEG, t["gamma2_deg"] * DEG, t["gamma3_deg"] * DEG)
    assert np.allclose(np.array(euler_321(home)) / DEG, [t["yaw_deg"], t["pitch_deg"], t["roll_deg"]], atol=1e-10)


def test_arbitrary_heading_and_bench_positions(thesis):
    scenario = replace(quiet(thesis, yaw_deg=137.0, gyro_bias_deg_h=(0, 0, 0), acc_bias_mg=(0, 0, 0)),
                       site=Site(-33.9), segments=tuple(Segment("position", duration_s=1, up=u)
                                                        for u in ("+Z", "-Z", "+Y", "-Y", "+X", "-X")))
    sim, samples, _, _ = decoded(scenario)
    g = Site(-33.9).gravity / STANDARD_GRAVITY
    up = {"+Z": [0, 0, 1], "-Z": [0, 0, -1], "+Y": [0, 1, 0], "-Y": [0, -1, 0], "+X": [1, 0, 0], "-X": [-1, 0, 0]}
    t = scenario.truth
    home = int_to_imu(t.alpha_deg * DEG, t.beta_deg * DEG) @ int_to_imu(0, 0)
    for k, phase in enumerate(sim.phases):
        mean = samples["acc"][k * 125 + 10:(k + 1) * 125 - 10].mean(0)
        tilt = np.radians(1.2)  # pitch, roll and the interface tilt move gravity off the axis a little
        assert np.dot(mean, up[phase.up]) / g > np.cos(tilt), phase.up
    assert home.shape == (3, 3)
    # the horizontal Earth rate appears at the heading: north is 137 deg clockwise from X
    heading = np.degrees(np.arctan2(-samples["gyro"][:125, 1].mean(), samples["gyro"][:125, 0].mean()))
    assert heading == pytest.approx(137.0, abs=0.5)


def test_noise_matches_the_configured_allan_deviation():
    density, instability = 0.15 * 60 / 3600, 0.3 / 3600  # deg/s*sqrt(s), deg/s
    rng = np.random.default_rng(11)
    rate_hz = 4.0
    noise, _ = sensor_noise(rng, int(30 * 3600 * rate_hz), rate_hz, density, instability)
    taus, adev = allan_deviation(noise, rate_hz, [1, 10, 100, 1000, 3000])
    assert adev[0] == pytest.approx(np.full(3, 9.0 / 3600), rel=0.05)  # ARW: 9 deg/h at 1 s
    expected = np.sqrt(density**2 / taus + sum(allan_gm(taus, flicker_sigma(density, instability), c)
                                               for c in FLICKER_TAUS_S))
    assert np.allclose(adev, expected[:, None], rtol=0.3)
    assert adev[-2:].min() * 3600 == pytest.approx(0.3, rel=0.35)  # the floor is the bias instability


def test_noise_at_the_sample_rate_keeps_the_density(thesis):
    scenario = replace(thesis, warmup=replace(thesis.warmup, power_on_s=1e7),
                       segments=(Segment("static", duration_s=120),),
                       sensor=replace(thesis.sensor, sample_rate_hz=2000))
    sim, samples, _, _ = decoded(scenario)
    _, adev = allan_deviation(samples["gyro"].astype(np.float64), 2000, [1.0])
    assert adev[0] * 3600 == pytest.approx(np.full(3, 9.0), rel=0.15)


def test_warm_up_moves_the_biases(thesis):
    scenario = replace(thesis, noise=replace(thesis.noise, enabled=False),
                       warmup=replace(thesis.warmup, power_on_s=0), segments=(Segment("static", duration_s=60),))
    sim, samples, _, _ = decoded(scenario)
    record = truth_record(sim, {})
    first = np.array(record["bias_during_capture"]["gyro_bias_deg_h"]["first"])
    assert np.abs(first - scenario.truth.gyro_bias_deg_h).max() > 10  # 16 degC below settled at power-on
    assert samples["temp_acc"][0, 0] == pytest.approx(22.0, abs=0.1)
    assert (samples["status_gyro"][:87] == Status.START_UP).all() and (samples["status_gyro"][88:] == 0).all()


def test_faults_show_in_the_decoder_statistics(thesis):
    scenario = replace(thesis, segments=(Segment("static", duration_s=60),),
                       faults=replace(thesis.faults, drop=7, garbage_bursts=3, bit_flips=5, restart_at_s=30.0))
    sim, samples, info, faults = decoded(scenario)
    s = info.stats
    lost = set(faults["dropped_samples"]) | set(faults["bit_flipped_samples"])
    assert s.datagrams == len(sim.samples) - len(lost)
    assert s.restarts == 1
    assert s.crc_errors >= len(set(faults["bit_flipped_samples"]) - set(faults["dropped_samples"]))
    assert s.skipped_bytes >= faults["garbage_bytes"]
    assert s.lost_samples == len(lost)  # small gaps: the counter tells them all
    assert faults["restart_at_sample"] == 30 * 125 - 1


def test_scenario_errors_name_the_place(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[site]\nlatitude_deg = 95\n[[segments]]\ntype = "static"\nduration_s = 10\n')
    with pytest.raises(ScenarioError, match=r"bad.toml \[site\] latitude_deg: 95.0 is not a latitude"):
        load_scenario(str(bad))
    with pytest.raises(ScenarioError, match=r"\[\[segments\]\] #1 angle_deg: missing"):
        parse_scenario({"site": {"latitude_deg": 10}, "segments": [{"type": "turn"}]}, "x.toml")
    with pytest.raises(ScenarioError, match=r"\[sensor\] sampl_rate_hz: unknown key"):
        parse_scenario({"site": {"latitude_deg": 10}, "sensor": {"sampl_rate_hz": 125},
                        "segments": [{"type": "static", "duration_s": 1}]}, "x.toml")
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(str(tmp_path / "none.toml"))


def test_calibd_simulate_writes_capture_and_truth(tmp_path, capsys):
    scenario = tmp_path / "short.toml"
    scenario.write_text('seed = 4\n[site]\nlatitude_deg = 45\n[sensor]\ndatagram = "0x93"\ncrlf = true\n'
                        '[[segments]]\ntype = "static"\nduration_s = 4\n')
    out = tmp_path / "short.bin"
    assert calibd_main(["simulate", str(scenario), "-o", str(out)]) == 0
    truth = json.loads((tmp_path / "short.bin.truth.json").read_text())
    capture = decode_capture(out.read_bytes())
    samples, info = capture.samples, capture.info
    assert len(samples) == truth["samples"] == 500
    assert info.format.datagram_id == 0x93 and info.format.crlf
    assert truth["site"]["g0"] == pytest.approx(9.80619, abs=1e-4)  # normal gravity at 45 deg
    assert calibd_main(["simulate", str(tmp_path / "nope.toml"), "-o", str(out)]) == 2
    assert "no such scenario file" in capsys.readouterr().err


@pytest.mark.parametrize("sensor, message", [
    ({"part_number": "84167-440000"}, r"\[sensor\] part_number: part number must look like"),
    ({"part_number": "84167-440000X-321"}, r"\[sensor\] part_number: part number digit"),
    ({"serial_number": "N123"}, r"\[sensor\] serial_number: serial number must be 'N' \+ 14 digits"),
    ({"serial_number": "N2558240500200Z"}, r"\[sensor\] serial_number: serial number digit"),
    ({"revision": "KK"}, r"\[sensor\] revision: 'KK' is not one character"),
    ({"revision": "\u0394"}, r"\[sensor\] revision: .* is not one character U\+0000..U\+00FF"),
])
def test_sensor_identity_the_datagrams_cannot_carry_is_refused(sensor, message):
    """The part and serial number datagrams' own rules, at load time, not as a traceback mid-simulation."""
    with pytest.raises(ScenarioError, match=message):
        parse_scenario({"site": {"latitude_deg": 10}, "sensor": sensor,
                        "segments": [{"type": "static", "duration_s": 1}]}, "x.toml")


def test_simulation_size_and_drop_are_bounded(thesis):
    """A turn of 1e9 deg would need 1e9 s of samples: refused before any array is made; dropping
    every sample is refused, as a capture with no datagram would be no capture."""
    huge = replace(thesis, segments=(Segment("turn", angle_deg=1e9, peak_rate_deg_s=1, accel_deg_s2=1),))
    with pytest.raises(ScenarioError, match=r"1e\+09 s at 125 Hz is more than the simulator's 10,000,000 samples"):
        simulate(huge)
    short = replace(thesis, segments=(Segment("static", duration_s=2.0),))
    with pytest.raises(ScenarioError, match=r"\[faults\] drop: 250 is not fewer than the 250 samples"):
        simulate(replace(short, faults=replace(short.faults, drop=250)))
    assert len(simulate(replace(short, faults=replace(short.faults, drop=249))).samples) == 250


def test_simulate_refuses_a_truth_json_cannot_hold(tmp_path, capsys, monkeypatch):
    """A truth record with NaN or infinity (once written for a scenario that dropped every sample)
    is refused: strict JSON has neither, and neither the capture nor its truth is written."""
    import calibd.sim
    monkeypatch.setattr(calibd.sim, "truth_record", lambda sim, faults: {"samples": 1, "duration_s": float("nan")})
    scenario = tmp_path / "nan.toml"
    scenario.write_text('[site]\nlatitude_deg = 45\n[[segments]]\ntype = "static"\nduration_s = 1\n')
    assert calibd_main(["simulate", str(scenario), "-o", str(tmp_path / "nan.bin")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nan.toml: the truth is not finite" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nan.toml"]


@pytest.mark.parametrize("table, key, value, message", [
    ("segments", "peak_rate_deg_s", 1e308, r"peak_rate_deg_s: 1e\+308 is not a rate in \(0, 400\] deg/s"),
    ("segments", "accel_deg_s2", 1e9, r"accel_deg_s2: 1000000000.0 is not an acceleration in \(0, 10000\] deg/s\^2"),
    ("warmup", "power_on_s", -1e308, r"\[warmup\] power_on_s: -1e\+308 is not in \[0, 1e\+09\] s"),
    ("warmup", "time_constant_s", 0.0, r"\[warmup\] time_constant_s: 0.0 is not in \[1, 1e\+07\] s"),
    ("warmup", "settled_c", 1e6, r"\[warmup\] settled_c: 1000000.0 is not in \[-60, 100\] degC"),
    ("warmup", "gyro_tempco_deg_h_per_c", [1e308, 0, 0], r"gyro_tempco_deg_h_per_c: \(1e\+308, 0.0, 0.0\) is not in"),
    ("truth", "gyro_bias_deg_h", [1e308, 0, 0], r"\[truth\] gyro_bias_deg_h: .* is not in \[-36000, 36000\] deg/h"),
    ("noise", "gyro_bias_instability_deg_h", 1e308, r"\[noise\] gyro_bias_instability_deg_h: 1e\+308 is not in"),
    ("faults", "garbage_max_bytes", 2**62, r"\[faults\] garbage_max_bytes: 4611686018427387904 is not a size in"),
])
def test_values_out_of_range_are_refused(table, key, value, message):
    """A peak rate of 1e308 deg/s overflowed the turn's profile, a power-on time of -1e308 s the
    temperature's exponential, a bias instability of 1e308 deg/h the noise model, a garbage burst
    of 2**62 B the memory: refused with the key and the range."""
    turn = {"type": "turn", "angle_deg": 90.0, "peak_rate_deg_s": 10.0, "accel_deg_s2": 5.0}
    data = {"site": {"latitude_deg": 10}, "segments": [turn]}
    if table == "segments":
        turn[key] = value
    else:
        data[table] = {key: value}
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(data, "x.toml")

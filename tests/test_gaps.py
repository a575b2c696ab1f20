"""Datagram losses the counter cannot see (whole 0.128 s cycles) during a turn: found from the
tilt the accelerometers and inclinometers see, corrected, and named; clean sessions untouched."""

from dataclasses import replace

import numpy as np
import pytest

from calibd import gaps
from calibd.allan import FLICKER_TAUS_S
from calibd.methods.joint import joint_real_case
from calibd.captures import load_session
from calibd.estimators.joint import JointInput, NoiseModel
from calibd.frames import Site, int_to_imu, r3
from calibd.results import CalibrationResult
from calibd.scenario import load_scenario
from calibd.sim import capture_bytes, simulate, truth_record
from calibd.units import DEG

THESIS = load_scenario("thesis-real")
CYCLE_DATAGRAMS = 16  # the counter's 256 internal samples at 125 Hz (step 16)
LOST_WARNING = "datagrams lost unseen by the counter"


def test_tilt_check_recovers_a_known_turn_angle():
    """Noise-free static forces of a platform whose third turn went 3 deg further than the gyros
    say: that turn's correction is 3 deg, the others 0, and the correction restores the angle."""
    g0, a, u = 9.8, int_to_imu(0.01, -0.002), np.array([0.004, -0.007, 0.0])
    u[2] = np.sqrt(1 - u @ u)
    static_n, turn_n = 2000, 100
    statics = tuple((k * (static_n + turn_n), k * (static_n + turn_n) + static_n) for k in range(5))
    chi = np.zeros(statics[-1][1])
    for k, (start, stop) in enumerate(statics):
        chi[start:stop] = -k * np.pi / 2
        if k:
            chi[start - turn_n:start] = np.linspace(chi[start - turn_n - 1], chi[start], turn_n + 1)[1:]
    turned = chi.copy()
    turned[statics[3][0]:] -= 3 * DEG
    force = np.stack([g0 * (a @ r3(c) @ u) for c in turned]) + [0.01, -0.02, 0.005]
    inp = JointInput(np.arange(len(chi)) / 125, np.zeros_like(force), force, force + 0.001, statics, 125)
    noise = NoiseModel(white=1e-6, flicker=0.0)
    check = gaps.check_turn_angles(inp, chi, a, g0, noise, noise, np.zeros(2))
    corrections = np.array([t.correction_rad for t in check.turns]) / DEG
    assert corrections == pytest.approx([0, 0, -3, 0], abs=1e-6)
    assert [t.found for t in check.turns] == [False, False, True, False]
    assert check.chi2 > 1e3  # with the gyros' angles, the statics' forces do not fit
    corrected = chi + gaps.chi_correction(inp, chi, [t for t in check.turns if t.found])
    for start, stop in statics:
        assert corrected[start:stop] == pytest.approx(turned[start:stop], abs=1e-12)


def test_static_means_covariance_matches_the_samples_covariance():
    """Flicker correlates the statics' means: against the covariance of the samples themselves
    (white plus the four Gauss-Markov components), averaged over each static."""
    rate, statics = 20, ((0, 100), (160, 220), (400, 500))
    noise = NoiseModel(white=0.3, flicker=0.7)
    t = np.arange(500) / rate
    samples = noise.white[0] * np.eye(len(t)) + noise.flicker[0] * sum(
        np.exp(-np.abs(t[:, None] - t[None, :]) / c) for c in FLICKER_TAUS_S[:4])
    averaging = np.zeros((len(statics), len(t)))
    for k, (start, stop) in enumerate(statics):
        averaging[k, start:stop] = 1 / (stop - start)
    inp = JointInput(t, *(np.zeros((len(t), 3)),) * 3, statics, rate)
    for channel in gaps.static_means_covariance(noise, inp):  # the same model on each of the three
        assert channel == pytest.approx(averaging @ samples @ averaging.T, rel=0.01)


@pytest.fixture(scope="module")
def thesis_sim():
    return simulate(replace(THESIS, seed=1))


def truth(sim) -> dict:
    """The scenario's attitude and the biases the capture carries (bias-instability wander included)."""
    out = sim.scenario.truth.estimates()
    carried = truth_record(sim, {})["bias_during_capture"]
    for name, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg"), ("incl_bias", "incl_bias_mg")):
        out |= {f"{name}_{a}": v for a, v in zip("xyz", carried[key]["session"])}
    return out


def calibrate_without(sim, first: int, count: int) -> CalibrationResult:
    """The joint result on the capture's bytes with `count` datagrams from `first` on never sent."""
    cut = replace(sim, samples=np.delete(sim.samples, np.arange(first, first + count)))
    return joint_real_case(load_session("cut.bin", data=capture_bytes(cut)[0]), sim.scenario.site)


def assert_unflagged_within_3_sigma(result: CalibrationResult, expected: dict) -> None:
    for name, e in result.estimates.items():
        if e.quality != "poor":
            assert abs(e.value - expected[name]) < 3 * e.sigma, (name, e, expected[name])


@pytest.mark.parametrize("turn,lost", [(0, 16), (1, 64), (2, 188), (4, 16), (4, 188)])
@pytest.mark.slow
def test_an_unseen_loss_in_a_turn_is_found_corrected_and_named(thesis_sim, turn, lost):
    """Index turns (20 deg/s) and the full turn (27.93 deg/s) losing 1, 4 and 11.75 counter cycles in
    their constant-rate part: the counter sees 0, 0 and 12 datagrams lost, the gyros 2.6 to 39 deg
    short. The tilt finds that turn's missing angle within its sigma, and the corrected session
    gives every estimate within 3 sigma of the truth."""
    phase = [p for p in thesis_sim.phases if p.kind == "turn"][turn]
    first = int((phase.cruise_start_s + 0.5) * 125)
    result = calibrate_without(thesis_sim, first, lost)
    unseen_s = (lost - lost % CYCLE_DATAGRAMS) / 125
    missing_deg = np.sign(phase.angle_deg) * phase.peak_rate_deg_s * unseen_s
    checked = result.checks["turn_angles"]
    assert [t["corrected"] for t in checked] == [k == turn for k in range(len(checked))]
    found = checked[turn]
    assert found["tilt_minus_gyro_deg"] == pytest.approx(missing_deg, abs=3 * found["sigma_deg"])
    named = [w for w in result.warnings if LOST_WARNING in w]
    assert len(named) == 1 and f"the turn from {found['start_s']:.1f} s" in named[0]
    assert result.checks["force_static_chi2"]["p_value"] > 1e-3
    assert not any(e.quality for e in result.estimates.values())
    assert_unflagged_within_3_sigma(result, truth(thesis_sim))


@pytest.mark.slow
def test_a_clean_session_is_left_as_it_is(thesis_sim):
    result = calibrate_without(thesis_sim, 0, 0)
    assert not any(t["corrected"] for t in result.checks["turn_angles"])
    assert all(t["sigma_deg"] < 0.5 for t in result.checks["turn_angles"])  # the tilt did check every turn
    assert not any(LOST_WARNING in w or "could not be checked" in w for w in result.warnings)
    assert result.checks["force_static_chi2"]["p_value"] > 1e-3
    assert_unflagged_within_3_sigma(result, truth(thesis_sim))


@pytest.mark.slow
def test_shipped_capture_raises_no_gap_warning():
    result = joint_real_case(load_session("fixtures/thesis_real_cw_125hz.bin"), Site(40.59129, g0=9.79956))
    assert not any(t["corrected"] for t in result.checks["turn_angles"])
    assert not any(LOST_WARNING in w for w in result.warnings)


@pytest.mark.slow
def test_statics_forces_that_do_not_fit_flag_the_estimates_poor(thesis_sim):
    """A 2 mg jump of the Z accelerometer during one index static: no platform angle explains it,
    so the force chi-square fails and what rests on the statics' forces and angles is flagged."""
    session = load_session("jump.bin", data=capture_bytes(thesis_sim)[0])
    phase = [p for p in thesis_sim.phases if p.kind == "static"][2]
    inside = (session.time_s > phase.start_s) & (session.time_s < phase.end_s)
    session.acc[inside, 2] += 2e-3 * 9.80665
    result = joint_real_case(session, thesis_sim.scenario.site)
    assert result.checks["force_static_chi2"]["p_value"] < 1e-3
    assert any("accelerometer and inclinometer means do not fit" in w for w in result.warnings)
    assert {n for n, e in result.estimates.items() if e.quality == "poor"} >= {"pitch", "roll", "acc_bias_z"}
    assert result.estimates["alpha"].quality is None


@pytest.mark.slow
def test_a_platform_axis_along_up_leaves_the_turns_unchecked():
    """No interface or IMU tilt: the platform axis is Up, the statics' forces do not turn with the
    platform, and the result says the turns' angles could not be checked."""
    level = replace(THESIS, seed=4, truth=replace(THESIS.truth, pitch_deg=0.0, roll_deg=0.0, alpha_deg=0.0,
                                                  beta_deg=0.0))
    sim = simulate(level)
    result = joint_real_case(load_session("level.bin", data=capture_bytes(sim)[0]), level.site)
    assert not any(t["corrected"] for t in result.checks["turn_angles"])
    assert all(t["sigma_deg"] is None for t in result.checks["turn_angles"])
    assert any("5 of 5 turns' angles could not be checked" in w for w in result.warnings)


@pytest.mark.slow
def test_continuous_rotation_says_the_turns_went_unchecked():
    """Two statics (before and after ten turns) cannot pin a turn's angle: the result says so."""
    scenario = load_scenario("continuous")
    sim = simulate(replace(scenario, noise=replace(scenario.noise, enabled=False)))
    result = joint_real_case(load_session("continuous.bin", data=capture_bytes(sim)[0]), scenario.site)
    assert "turn_angles" not in result.checks
    assert any("the statics do not pin the turns' angles" in w for w in result.warnings)


def test_headings_are_counted_modulo_a_turn():
    assert gaps.distinct_headings(np.radians([0, -90, -180, -270, -360, -720])) == 4
    assert gaps.distinct_headings(np.radians([0, 90, 450])) == 2
    assert gaps.distinct_headings(np.radians([0, 10, 355])) == 1


@pytest.mark.slow
def test_one_index_position_leaves_the_turns_unchecked_and_is_solved():
    """Statics at two headings (level, one index position, and again after a full turn): one
    difference of tilt directions fits any turn angle, so none is corrected; the result says so
    and stays within its sigma."""
    segments = THESIS.segments[:3] + THESIS.segments[-2:]
    scenario = replace(THESIS, seed=7, segments=segments)
    sim = simulate(scenario)
    result = joint_real_case(load_session("one-index.bin", data=capture_bytes(sim)[0]), scenario.site)
    assert any("statics at fewer than 3 headings" in w for w in result.warnings)
    assert not any(LOST_WARNING in w for w in result.warnings)
    truth = scenario.truth
    for name in ("pitch", "roll", "yaw"):
        e = result.estimates[name]
        assert abs(e.value - getattr(truth, f"{name}_deg")) < 3 * e.sigma, name

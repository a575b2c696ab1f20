"""The thesis's estimators: its reference numbers, exact algebra on model data, the chain on
noise-free sessions within stated bounds, its known model errors, and its error pattern with noise."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibd import detect
from calibd.methods import CampaignIncomplete
from calibd.methods.bench import thesis_bench
from calibd.methods.common import one_period
from calibd.methods.thesis import thesis_real_case
from calibd.captures import load_session
from calibd.cli import main as calibd_main
from calibd.segments import session_segments
from calibd.session import Session
from calibd.estimators import thesis
from calibd.frames import EARTH_RATE, STANDARD_GRAVITY, Site, int_to_imu, nav_to_imu
from calibd.scenario import Segment, load_scenario
from calibd.sim import write_capture
from calibd.units import DEG
from captures import quiet, with_sense

SITE = Site(40.59129, g0=9.79956)  # thesis Table 7.1
H = EARTH_RATE * np.cos(np.radians(SITE.latitude_deg))  # horizontal Earth rate, rad/s
V = EARTH_RATE * np.sin(np.radians(SITE.latitude_deg))
GYRO_LSB = 2.0**-14 * DEG  # rad/s: a noise-free constant rate is off its mean by up to half of it


# ---------------------------------------------------------------- the thesis's own numbers

def test_alpha_beta_and_norm_from_table_7_2():
    rate = np.array([-0.0583, -0.2891, -27.9187])  # deg/s, clockwise turn
    alpha, beta = thesis.interface_tilt(rate * DEG)
    assert round(alpha / DEG, 4) == 0.5933 and round(beta / DEG, 4) == -0.1196
    assert round(float(np.linalg.norm(rate)), 4) == 27.9203
    assert thesis.interface_tilt(-rate * DEG) == pytest.approx((alpha, beta))  # either sense, same tilt


def test_sensitivity_of_section_7_1():
    s = thesis.sensitivity(0.0030 * DEG, 0.0071 * DEG, 27.9295 * DEG, SITE)
    assert s["incl_bias_x"] / STANDARD_GRAVITY * 1000 == pytest.approx(0.1239, abs=1e-4)  # mg
    assert s["gyro_bias_y"] / DEG * 3600 == pytest.approx(5.26, abs=0.005)  # deg/h
    one = thesis.sensitivity(0.0, 0.0, 0.0, SITE)
    assert one["yaw"] == 0.0
    per_deg_h = (1 / 3600 * DEG) / H / DEG  # deg of yaw per deg/h of gyro Y bias
    assert per_deg_h == pytest.approx(5.0, abs=0.02)
    assert s["yaw"] / DEG == pytest.approx(s["gyro_bias_y"] / DEG * 3600 * per_deg_h)


# ---------------------------------------------------------------- algebra on exact model data

def test_pitch_roll_and_acc_biases_invert_the_model_exactly():
    pitch, roll = -0.3205 * DEG, 0.8193 * DEG
    gravity = nav_to_imu(0.7, pitch, roll) @ [0, 0, SITE.gravity]
    assert thesis.pitch_roll(gravity) == pytest.approx((pitch, roll), abs=1e-15)
    bias = np.array([-1.2811, 7.0304, 0.5056]) * STANDARD_GRAVITY / 1000
    assert thesis.acc_biases(gravity + bias, pitch, roll, SITE.gravity) == pytest.approx(bias, abs=1e-15)


def test_gyro_biases_invert_the_full_earth_rate_projection():
    yaw, pitch, roll = 37 * DEG, -0.3 * DEG, 0.8 * DEG
    bias = np.array([98.6, -34.7, -27.4]) / 3600 * DEG
    static = nav_to_imu(yaw, pitch, roll) @ SITE.earth_rate_nav + bias
    assert thesis.gyro_biases(static, yaw, pitch, roll, SITE) == pytest.approx(bias, abs=1e-18)


def test_incl_biases_cancel_gamma_to_second_order():
    alpha, beta, gammas = 0.5934 * DEG, -0.1196 * DEG, (0.3 * DEG, -0.2 * DEG, 0.23 * DEG)
    bias = np.array([-0.899, -0.6567, -0.2351]) * STANDARD_GRAVITY / 1000
    r_int_imu = int_to_imu(alpha, beta)
    from calibd.frames import nav_to_int, r3
    means = np.array([r_int_imu @ r3(k * np.pi / 2) @ nav_to_int(*gammas) @ [0, 0, SITE.gravity] + bias
                      for k in range(4)])
    bx, by = thesis.incl_bias_xy(means, alpha, beta, SITE.gravity)
    second_order = SITE.gravity * sum(g * g for g in gammas)  # what the linearisation (6.5) leaves
    assert abs(bx - bias[0]) <= second_order and abs(by - bias[1]) <= second_order


def test_six_position_biases_cancel_the_reference():
    bias = np.array([0.1, -0.2, 0.3])
    means = {f"{s}{a}": bias + (1 if s == "+" else -1) * 9.8 * np.eye(3)[i]
             for i, a in enumerate("XYZ") for s in "+-"}
    assert thesis.six_position_biases(means) == pytest.approx(bias)
    del means["-Y"]
    with pytest.raises(ValueError, match="missing -Y up"):
        thesis.six_position_biases(means)


# ---------------------------------------------------------------- the chain on simulated sessions

def errors(result, scenario) -> dict:
    truth = scenario.truth.estimates()
    return {k: e.value - truth[k] for k, e in result.estimates.items()}


def model_yaw_deg(truth) -> float:
    """The nominal chain's own yaw error: the turn's Y average keeps alpha*Omega_v where eq. 6.29
    removes roll*Omega_v, a gyro Y error (roll - alpha) Omega_v, plus half a count of the static Y
    mean, over Omega_h."""
    return (abs(truth.roll_deg - truth.alpha_deg) * DEG * V + GYRO_LSB / 2) / H / DEG


def covered_deg(data) -> float:
    """The platform angle of the full turn's constant-rate part (less than 360 deg with ramps)."""
    return abs(detect.full_turns(session_segments(data))[0].cruise_angle_deg)


def unaveraged_bound(data) -> float:
    """The warning's bound on the horizontal Earth rate left in the turn's mean gyro, rad/s."""
    return thesis.unaveraged_earth_rate(min(covered_deg(data), 360.0) * DEG, SITE)


@pytest.fixture(scope="module", params=[-1, +1], ids=["clockwise", "counter-clockwise"])
def session(request, tmp_path_factory):
    scenario = with_sense(quiet(load_scenario("thesis-real")), request.param)
    path = tmp_path_factory.mktemp("s") / "session.bin"
    write_capture(scenario, path)
    return scenario, load_session(str(path)), request.param


def test_nominal_chain_recovers_the_truth_within_its_model_error(session):
    """With the true alpha/beta, every estimate is the truth up to the chain's small-angle model
    and the output quantisation (a noise-free constant rate is up to half a count off):
    - pitch/roll: second order in the 1 deg angles, and b_Z^i = 0 -> |phi| b_Z / g: 1e-3 deg;
    - yaw: `model_yaw_deg`, plus the Earth rate the 360 deg turn's constant-rate part leaves
      unaveraged (its warning's bound);
    - gyro biases: half a count plus that yaw error's projection (tiny);
    - acc biases: g times the pitch/roll error; incl X/Y: second order (gamma^2 g0 = 0.04 mg)."""
    scenario, data, _ = session
    t = scenario.truth
    result = thesis_real_case(data, SITE, (t.alpha_deg, t.beta_deg))
    e = errors(result, scenario)
    assert abs(e["pitch"]) < 1e-3 and abs(e["roll"]) < 1e-3
    assert abs(e["yaw"]) < model_yaw_deg(t) + unaveraged_bound(data) / H / DEG
    for a in "xyz":
        assert abs(e[f"gyro_bias_{a}"]) < (GYRO_LSB / 2 + 0.01 / 3600 * DEG) / DEG * 3600
        assert abs(e[f"acc_bias_{a}"]) < 0.01  # mg
    assert abs(e["incl_bias_x"]) < 0.04 and abs(e["incl_bias_y"]) < 0.04
    assert e["incl_bias_z"] == pytest.approx(-scenario.truth.incl_bias_mg[2])  # assumed 0
    assert result.method == "thesis-nominal" and result.schema == "calibd.result/7"
    assert all(e.sigma is None for e in result.estimates.values())


def test_linear_chain_has_the_thesis_model_errors(session):
    """Eq. 7.3 neglects that the horizontal Earth rate averages out over a turn but not over the
    static: alpha absorbs psi*Omega_h/w, beta is off by Omega_h cos(psi)/w (sign of the turn),
    which moves b_X^i by g0 sin(d_beta); and yaw comes out 0 by construction. The Earth rate left
    unaveraged by the 360 deg turn's constant-rate part goes into alpha and beta (its bound / w)."""
    scenario, data, sense = session
    t = scenario.truth
    w = 27.93 * DEG * sense
    result = thesis_real_case(data, SITE)
    e = errors(result, scenario)
    assert result.estimates["yaw"].value == pytest.approx(0.0, abs=1e-9)
    assert any("yaw is not observable" in warning for warning in result.warnings)
    d_alpha = (t.yaw_deg * DEG) * H / w  # rad
    d_beta = H * np.cos(t.yaw_deg * DEG) / w
    partial = unaveraged_bound(data) / abs(w) / DEG
    assert 0 < partial < 1e-3
    assert any(f"up to {partial:.4f} deg on alpha and beta" in warning for warning in result.warnings)
    assert e["alpha"] == pytest.approx(d_alpha / DEG, abs=5e-5 + partial)
    assert e["beta"] == pytest.approx(d_beta / DEG, abs=5e-4 + partial)
    d_incl_x = SITE.gravity * np.sin(e["beta"] * DEG) / STANDARD_GRAVITY * 1000  # mg, from the beta it has
    assert e["incl_bias_x"] == pytest.approx(d_incl_x, abs=0.01)
    assert e["acc_bias_x"] == pytest.approx(d_incl_x, abs=0.01)  # through pitch


def test_platform_rate_from_the_gyros_matches_the_command(session):
    scenario, data, sense = session
    result = thesis_real_case(data, SITE)
    assert result.platform_rate_deg_s == pytest.approx(27.93 * sense, abs=2e-4)
    roles = [s["role"] for s in result.segments]
    assert roles == ["level static"] + [f"index position {k}" for k in range(1, 5)] + ["full turn"]


def test_bench_chain(tmp_path):
    scenario = with_sense(quiet(load_scenario("thesis-bench")), +1)
    write_capture(scenario, tmp_path / "bench.bin")
    result = thesis_bench(load_session(str(tmp_path / "bench.bin")), SITE)
    e = errors(result, scenario)
    for a in "xyz":
        # up/down pairs are tilted by the same ~1 deg: the reference cancels to second order
        assert abs(e[f"acc_bias_{a}"]) < 0.01 and abs(e[f"incl_bias_{a}"]) < 0.01  # mg
        assert abs(e[f"gyro_bias_{a}"]) < 0.2  # deg/h: half a count plus tilt terms
    # eq. 5.7 removes Omega_h from X although it averages out over a whole turn: beta off by
    # Omega_h/w, plus what the 360 deg turns' constant-rate parts leave unaveraged (bound / w)
    partial = unaveraged_bound(load_session(str(tmp_path / "bench.bin")))
    assert abs(e["alpha"]) < 0.002
    assert abs(e["beta"]) < ((H + partial) / (27.93 * DEG) + 1e-5) / DEG
    assert sum("not a whole revolution" in warning for warning in result.warnings) == 3
    assert len(result.turns_alpha_beta_deg) == 3


def test_earth_rate_is_a_line_at_the_turn_frequency(session):
    scenario, data, sense = session
    turn_result = thesis_real_case(data, SITE)
    turn = turn_result.segments[-1]
    rate_hz = data.rate_hz
    window = data.gyro[int(turn["start_s"] * rate_hz) + 200:int(turn["end_s"] * rate_hz) - 200]
    report = thesis.earth_rate_diagnostic(window, rate_hz, SITE, sigma_s=0.2)
    turn_hz = 27.93 / 360
    resolution_hz = rate_hz / len(window)  # a window shorter than a period: one spectral bin
    assert report["peak_frequency_hz"][0] == pytest.approx(turn_hz, abs=resolution_hz)
    assert report["peak_amplitude"][0] == pytest.approx(H, rel=0.3)
    assert report["visible"]


# ---------------------------------------------------------------- a full turn as a platform runs it

@pytest.mark.parametrize("covered", [30.0, 180.0, 331.8, 359.0, 360.0, 500.0, 720.0])
def test_unaveraged_earth_rate_is_the_worst_mean_of_the_sinusoid(covered):
    chi = np.linspace(0, covered * DEG, 20001)
    means = [np.trapezoid(H * np.sin(phase + chi), chi) / chi[-1] for phase in np.linspace(0, 2 * np.pi, 721)]
    assert thesis.unaveraged_earth_rate(covered * DEG, SITE) == pytest.approx(max(np.abs(means)), rel=1e-4, abs=1e-12)


def turn_across(angle_deg: float, accel_deg_s2: float = 30.0):
    """A noise-free real-case session whose full turn starts 90 deg from home (after three index
    turns), where the ramps cut the Earth-rate period short on the Y gyro: the unaveraged part
    is near its bound there, while from home it is on X only."""
    index = Segment("turn", angle_deg=-90, peak_rate_deg_s=20, accel_deg_s2=20)
    static = Segment("static", duration_s=60)
    full = Segment("turn", angle_deg=angle_deg, peak_rate_deg_s=27.93, accel_deg_s2=accel_deg_s2)
    base = load_scenario("thesis-real")
    return with_sense(quiet(replace(base, segments=(static, index) * 3 + (static, full, static, index, static))), -1)


def nominal_run(scenario, tmp_path):
    write_capture(scenario, tmp_path / "s.bin")
    data = load_session(str(tmp_path / "s.bin"))
    return data, thesis_real_case(data, SITE, (scenario.truth.alpha_deg, scenario.truth.beta_deg))


def test_a_360_deg_turn_with_ramps_gives_a_result_and_bounds_its_earth_rate_term(tmp_path):
    """27.93 deg/s with 30 deg/s^2 ramps: ~332 deg at constant rate. The thesis's chain runs on
    it and says how far the unaveraged Earth rate can move the gyro Y bias and yaw; the error
    it makes is that large (not a loose bound) and no larger."""
    scenario = turn_across(360)
    data, result = nominal_run(scenario, tmp_path)
    covered = covered_deg(data)
    bias_bound = thesis.unaveraged_earth_rate(covered * DEG, SITE)
    yaw_bound = bias_bound / H / DEG
    assert 325 < covered < 334 and yaw_bound == pytest.approx(4.8, abs=0.1)
    assert any(f"covers {covered:.0f} deg, not a whole revolution" in w and
               f"up to {bias_bound / DEG * 3600:.2f} deg/h on the gyro Y bias, so up to {yaw_bound:.1f} deg on yaw" in w
               for w in result.warnings)
    e = errors(result, scenario)
    assert 0.8 * yaw_bound < abs(e["yaw"]) < yaw_bound + model_yaw_deg(scenario.truth)
    assert result.estimates["yaw"].quality is None  # a bound under 5 deg: the thesis's yaw as it is


def test_a_turn_covering_a_period_at_constant_rate_needs_no_warning(tmp_path):
    scenario = turn_across(720)
    _, result = nominal_run(scenario, tmp_path)
    assert not any("not a whole revolution" in w for w in result.warnings)
    assert abs(errors(result, scenario)["yaw"]) < model_yaw_deg(scenario.truth)


def test_one_period_is_timed_by_the_sample_clock_across_lost_datagrams():
    """A 720 deg constant-rate part at 30 deg/s with 2 s of datagrams lost inside its first
    revolution: the window still spans 12 s of data time (fewer samples), not 12 s of samples."""
    rate_hz = 125
    time_s = np.arange(40 * rate_hz) / rate_hz
    time_s = np.concatenate((time_s[:5 * rate_hz], time_s[7 * rate_hz:]))  # 2 s lost at 5 s
    data = Session(time_s, np.zeros((len(time_s), 3)), np.zeros((len(time_s), 3)), np.zeros((len(time_s), 3)),
                   None, rate_hz, {}, {})
    turn = detect.Segment("turn", 0, len(time_s), 0.0, 40.0, 0.0, angle_deg=720.0, rate_deg_s=30.0,
                          cruise_start=rate_hz, cruise_stop=len(time_s) - rate_hz, cruise_angle_deg=720.0)
    window, covered = one_period(data, turn)
    assert covered == 360.0 and window.start == rate_hz
    assert time_s[window.stop - 1] - time_s[window.start] == pytest.approx(12.0 - 1 / rate_hz)
    assert window.stop - window.start == 10 * rate_hz


def test_a_turn_short_of_350_deg_is_no_full_turn_and_the_refusal_says_so(tmp_path):
    base = with_sense(quiet(load_scenario("thesis-real")), -1)
    scenario = replace(base, segments=base.segments[:-2] + (replace(base.segments[-2], angle_deg=-300),
                                                             base.segments[-1]))
    write_capture(scenario, tmp_path / "s.bin")
    with pytest.raises(CampaignIncomplete) as refusal:
        thesis_real_case(load_session(str(tmp_path / "s.bin")), SITE)
    assert "it lacks a full turn (at least 350 deg) after the level static" in str(refusal.value)
    assert refusal.value.found.endswith("4 index turns, 0 full turns, 1 other turn")


def test_slow_ramps_leave_too_little_constant_rate_and_flag_yaw_and_gyro_y(tmp_path):
    """5 deg/s^2 ramps take 78 deg each: ~204 deg at constant rate, up to ~31 deg of yaw."""
    scenario = turn_across(360, accel_deg_s2=5)
    data, result = nominal_run(scenario, tmp_path)
    yaw_bound = thesis.unaveraged_earth_rate(covered_deg(data) * DEG, SITE) / H / DEG
    assert yaw_bound > 25
    assert [n for n, e in result.estimates.items() if e.quality == "poor"] == ["yaw", "gyro_bias_y"]
    assert any(f"so up to {yaw_bound:.1f} deg on yaw" in w for w in result.warnings)
    assert abs(errors(result, scenario)["yaw"]) < yaw_bound + model_yaw_deg(scenario.truth)


# ---------------------------------------------------------------- with noise: the thesis's pattern

@pytest.mark.slow
def test_with_noise_yaw_and_gyro_y_are_poor_and_pitch_roll_good(tmp_path):
    """A few seeds of the thesis session with the thesis's lab alpha/beta (0.003 and 0.007 deg
    off the truth): its Tables 7.5-7.8 pattern. The long Monte Carlo is benchmarks/thesis.py."""
    base = load_scenario("thesis-real")
    worst_pitch, yaw_errors = 0.0, []
    for seed in (1, 2, 3):
        scenario = replace(base, seed=seed)
        write_capture(scenario, tmp_path / "s.bin")
        result = thesis_real_case(load_session(str(tmp_path / "s.bin")), SITE, (0.5964, -0.1125))
        e = errors(result, scenario)
        worst_pitch = max(worst_pitch, abs(e["pitch"]), abs(e["roll"]))
        yaw_errors.append(abs(e["yaw"]))
    assert worst_pitch < 0.03  # deg: good, as the thesis's 0.0186 / 0.0076
    assert min(yaw_errors) > 5.0  # deg: poor, as the thesis's 27.9 (5 deg per deg/h of gyro Y bias)


# ---------------------------------------------------------------- the command

FIXTURE = "fixtures/thesis_real_cw_125hz.bin"


def test_calibrate_command_writes_the_result_schema(tmp_path, capsys):
    out = tmp_path / "result.json"
    code = calibd_main(["calibrate", FIXTURE, "--method", "thesis", "--latitude", "40.59129", "--g0", "9.79956",
                        "--alpha", "0.5934", "--beta", "-0.1196", "-o", str(out)])
    assert code == 0, capsys.readouterr().err
    result = json.loads(out.read_text())
    assert result["schema"] == "calibd.result/7" and result["method"] == "thesis-nominal"
    assert set(result["estimates"]) == {"pitch", "roll", "yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y",
                                        "gyro_bias_z", "acc_bias_x", "acc_bias_y", "acc_bias_z", "incl_bias_x",
                                        "incl_bias_y", "incl_bias_z"}
    assert result["estimates"]["pitch"]["unit"] == "deg" and result["estimates"]["gyro_bias_y"]["unit"] == "deg/h"
    assert result["estimates"]["acc_bias_y"]["unit"] == "mg"
    assert result["site"] == {"latitude_deg": 40.59129, "height_m": 0.0, "g0_m_s2": 9.79956, "g0_given": True,
                              "g0_sigma_m_s2": 0.0, "earth_rate_deg_h": pytest.approx(15.0411, abs=1e-4),
                              "earth_rate_rad_s": 7.2921150e-5}
    assert result["sensor"]["serial_number"] == "N25582405002002" and result["sensor"]["datagram_id"] == "0xA7"
    assert result["estimates"]["pitch"]["value"] == pytest.approx(-0.3205, abs=0.03)
    printed = capsys.readouterr().out
    assert "pitch" in printed and "deg/h" in printed and "mg" in printed


def test_bench_fixture_calibrates_with_its_three_360_deg_turns():
    """The shipped bench session (six positions, three 360 deg turns with ramps): alpha and beta
    within the chain's model error (beta off by Omega_h/w plus the unaveraged rest, bound / w)
    plus 0.001 deg of noise (the three turns agree within 0.0003 deg); biases within 1.5 deg/h
    and 0.15 mg of those the data carry: each position's 120 s mean keeps its own share of the
    bias instability (0.3 deg/h, 0.04 mg), which the six-position sum does not cancel."""
    path = Path(__file__).resolve().parents[1] / "fixtures/thesis_bench_125hz.bin"
    truth = json.loads(Path(f"{path}.truth.json").read_text())
    data = load_session(str(path))
    result = thesis_bench(data, SITE)
    assert [s["role"] for s in result.segments][-3:] == ["full turn"] * 3
    bound = unaveraged_bound(data)
    assert sum(f"up to {bound / DEG * 3600:.2f} deg/h" in w for w in result.warnings) == 3
    value = {k: e.value for k, e in result.estimates.items()}
    assert abs(value["alpha"] - truth["truth"]["alpha_deg"]) < 0.001 + bound / (27.93 * DEG) / DEG
    assert abs(value["beta"] - truth["truth"]["beta_deg"]) < 0.001 + (H + bound) / (27.93 * DEG) / DEG
    carried = truth["bias_during_capture"]
    for k, a in enumerate("xyz"):
        assert value[f"gyro_bias_{a}"] == pytest.approx(carried["gyro_bias_deg_h"]["session"][k], abs=1.5)
        assert value[f"acc_bias_{a}"] == pytest.approx(carried["acc_bias_mg"]["session"][k], abs=0.15)
        assert value[f"incl_bias_{a}"] == pytest.approx(carried["incl_bias_mg"]["session"][k], abs=0.15)


@pytest.mark.parametrize("argv,message", [
    (["calibrate", FIXTURE, "-o", "r.json"], "required: --latitude"),
    (["calibrate", FIXTURE, "--method", "thesis", "--latitude", "40", "--alpha", "0.5", "-o", "r.json"],
     "both --alpha and --beta"),
    (["calibrate", FIXTURE, "--latitude", "91", "-o", "r.json"], "91.0 is not a latitude in [-90, 90] deg"),
    (["calibrate", "fixtures/faults_125hz.bin", "--method", "thesis", "--latitude", "40", "-o", "r.json"],
     "not the thesis real-case"),
    (["calibrate", "fixtures/thesis_real_cw_125hz.bin", "--method", "thesis", "--bench", "--latitude", "40", "-o",
      "r.json"], "not the bench campaign"),
    (["calibrate", "nope.bin", "--latitude", "40", "-o", "r.json"], "nope.bin: no such file"),
])
def test_calibrate_errors_are_one_line(argv, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = [a if not a.startswith("fixtures/") else str(__import__("pathlib").Path(__file__).parents[1] / a)
            for a in argv]
    assert calibd_main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r.json").exists()


def test_sensitivity_report(capsys):
    assert calibd_main(["sensitivity", "--alpha-error", "0.0030", "--beta-error", "0.0071", "--platform-rate",
                        "27.9295", "--latitude", "40.59129", "--g0", "9.79956"]) == 0
    out = capsys.readouterr().out
    assert "0.1238 mg" in out and "5.265 deg/h" in out and "26.41 deg" in out


def test_result_carries_the_earth_rate_diagnostic(session):
    _, data, _ = session
    report = thesis_real_case(data, SITE).earth_rate_diagnostic["full turn"]
    window_s = covered_deg(data) / 27.93  # the constant-rate part: one spectral bin is 1 / window_s
    assert report["peak_frequency_hz"][0] == pytest.approx(27.93 / 360, abs=1 / window_s)
    assert report["expected_amplitude_deg_h"] == pytest.approx(11.4217, abs=1e-3)
    assert report["visible"]

"""A second mounting: the housing turned 180 deg about its own Z axis between two campaigns. Its
tilt mirrors the first's, the gyro triad's misalignment does not, so the sum of the two shows the
misalignment that tilts the platform axis (calibd.estimators.remount): on exact data it is found
exactly and pitch, roll, alpha and beta lose the factory residuals' error; on noisy data each
stays within its sigma, whose parts add up; through `calibd calibrate --remounted` the terms are
reported estimated and taken out by the correction; a capture that is not the unit turned is
refused in one line."""

import json
from dataclasses import replace

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from calibd.estimators import joint
from calibd.estimators.remount import REMOUNT_PART, tilt, tilt_jacobian, two_mountings
from calibd.frames import STANDARD_GRAVITY
from calibd.methods.joint import joint_fit
from calibd.results import load_result
from calibd.scenario import load_scenario
from calibd.sim import remounted, simulate, write_capture
from calibd.units import DEG
from test_factory import QUIET, THESIS, session_of

# a unit with each gyro element on the datasheet's 2-sigma, the other triads too, on a tilted interface
RESIDUALS = {"gyro_misalignment_mrad": (0.3, 0.6, -0.4, -0.7, 0.5, 0.2),
             "acc_misalignment_mrad": (0.2, -0.5, 0.3, 0.4, -0.2, 0.1),
             "incl_misalignment_mrad": (-0.3, 0.4, 0.2, -0.6, 0.3, -0.1),
             "gyro_scale_ppm": (200.0, -150.0, 300.0), "acc_scale_ppm": (80.0, -60.0, 120.0),
             "incl_scale_ppm": (-200.0, 250.0, 150.0)}
TRUTH = replace(THESIS.truth, alpha_deg=0.4, beta_deg=-0.3, **RESIDUALS)
ANGLES = ("pitch", "roll", "alpha", "beta")


def _fits(scenario, truth=TRUTH, second_truth=None):
    """The joint fits of a first mounting and of the unit turned (exact data)."""
    first = joint_fit(session_of(simulate(replace(scenario, truth=truth))), scenario.site).fit
    second = joint_fit(session_of(simulate(replace(scenario, truth=second_truth or remounted(truth)))),
                       scenario.site).fit
    return first, second


@pytest.fixture(scope="module")
def exact():
    first, second = _fits(QUIET)
    return first, second, *two_mountings(first, second, 0.0)


def _term(fit: joint.JointResult, name: str) -> tuple[float, float]:
    """A factory term's value and sigma after the data, dimensionless."""
    k = next(i for i, t in enumerate(fit.factory.terms) if t.name == name)
    term = fit.factory.terms[k]
    return fit.factory.posterior.z[k] * term.sigma, np.sqrt(fit.factory.posterior.cov[k, k]) * term.sigma


def test_the_tilt_is_the_platform_axis_over_its_z_and_its_jacobian_is_right():
    alpha, beta = 0.3, -0.2
    k = np.array([-np.sin(beta), np.sin(alpha) * np.cos(beta), np.cos(alpha) * np.cos(beta)])
    assert tilt(alpha, beta) == pytest.approx(k[:2] / k[2], rel=1e-12)
    h = 1e-7
    numeric = np.column_stack([(tilt(alpha + h, beta) - tilt(alpha - h, beta)) / (2 * h),
                               (tilt(alpha, beta + h) - tilt(alpha, beta - h)) / (2 * h)])
    assert tilt_jacobian(alpha, beta) == pytest.approx(numeric, rel=1e-6)


def test_the_simulated_second_mounting_mirrors_the_tilt_and_keeps_the_residuals():
    turned = remounted(TRUTH)
    assert (turned.alpha_deg, turned.beta_deg) == pytest.approx((-TRUTH.alpha_deg, -TRUTH.beta_deg), abs=1e-12)
    assert turned.gyro_misalignment_mrad == TRUTH.gyro_misalignment_mrad
    assert remounted(turned).yaw_deg == pytest.approx(TRUTH.yaw_deg, abs=1e-9)  # twice is the first mounting


@pytest.mark.slow
def test_exact_data_give_the_tilting_gyro_misalignment_and_the_angles_back(exact):
    first, _, both, check = exact
    gyro = TRUTH.triad_error("gyro")
    for name, (row, col) in (("gyro_misalignment_xz", (0, 2)), ("gyro_misalignment_yz", (1, 2))):
        value, sigma = _term(both, name)
        assert value == pytest.approx(gyro[row, col], abs=0.01 * abs(gyro[row, col]))
        assert sigma < 0.05 * 0.5e-3  # a twentieth of the datasheet's prior
    truth = TRUTH.estimates()
    for name in ANGLES:
        alone = abs(first.estimates[name] / DEG - truth[name])
        assert alone > 0.01  # the gyro misalignment tilts them by a large part of a mrad
        assert abs(both.estimates[name] / DEG - truth[name]) < 0.02 * alone
    # the gyros' axis is (I + E) times the true one: the tilts' sum is twice E's X and Y sensing of Z
    assert check.tilt_sum == pytest.approx(2 * gyro[:2, 2], rel=0.02)
    # the second mounting's own tilt: the first's mirrored, moved by the same misalignment as the first's
    moved = {name: first.estimates[name] - TRUTH.estimates()[name] * DEG for name in ("alpha", "beta")}
    assert check.second == pytest.approx({name: -TRUTH.estimates()[name] * DEG + moved[name] for name in moved},
                                         abs=0.05 * 0.7e-3)  # to a twentieth of the move


@pytest.mark.slow
def test_the_budget_parts_add_up_and_the_factory_part_of_the_angles_is_gone(exact):
    first, _, both, _ = exact
    assert sum(both.budget.values()) == pytest.approx(both.covariance, rel=1e-12, abs=1e-30)
    assert REMOUNT_PART in both.budget and "factory_residuals" in both.budget
    for name in ANGLES:
        i = list(both.estimates).index(name)
        assert np.sqrt(both.budget["factory_residuals"][i, i]) < 0.1 * np.sqrt(first.budget["factory_residuals"][i, i])
    i = list(both.estimates).index("yaw")  # the misalignment barely moves yaw: it keeps its sigma
    assert both.sigmas["yaw"] == pytest.approx(first.sigmas["yaw"], rel=0.02)
    assert np.all(np.linalg.eigvalsh(both.covariance) > -1e-30)


def test_a_fixture_turn_error_enters_as_the_tilt_times_its_sigma(exact):
    first, second, both, _ = exact
    turned, check = two_mountings(first, second, 0.2 * DEG)
    i = list(turned.estimates).index("alpha")
    assert turned.budget[REMOUNT_PART][i, i] > 0
    # the turn error moves the tilt's sum across the tilt: |tau| times the turn's sigma
    assert np.sqrt(np.trace(check.cov) - np.trace(two_mountings(first, second, 0.0)[1].cov)) == pytest.approx(
        0.2 * DEG * np.linalg.norm(tilt(first.estimates["alpha"], first.estimates["beta"])), rel=0.05)


@pytest.mark.slow
def test_noisy_mountings_keep_every_estimate_within_its_sigma():
    first, second = (joint_fit(_noisy(simulate(replace(THESIS, truth=t, seed=THESIS.seed + k))), THESIS.site).fit
                     for k, t in ((11, TRUTH), (12, remounted(TRUTH))))
    both, check = two_mountings(first, second, 0.0)
    assert check.p_value > 1e-3
    truth = TRUTH.estimates()
    for name in ANGLES:
        error = both.estimates[name] / DEG - truth[name]
        assert abs(error) < 3 * both.sigmas[name] / DEG
        assert both.sigmas[name] < 0.25 * first.sigmas[name]  # the noise's, no longer the prior's
    value, sigma = _term(both, "gyro_misalignment_xz")
    assert abs(value - TRUTH.triad_error("gyro")[0, 2]) < 3 * sigma


def _noisy(sim):
    from calibd.results import ResultStream
    from calibd.session import Session
    from stim300.records import SensorRecord

    s, rate = sim.samples, sim.scenario.sensor.sample_rate_hz
    return Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                   acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                   temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Captures of one unit, its second mounting turned, the unit not turned, and another unit turned."""
    folder = tmp_path_factory.mktemp("mountings")
    scenario = replace(load_scenario("thesis-real"), warmup=replace(THESIS.warmup, power_on_s=1e7))
    paths = {}
    other_unit = replace(scenario.sensor, serial_number="N25582405002999")
    for name, truth, seed, sensor in (("first", TRUTH, 21, scenario.sensor),
                                      ("turned", remounted(TRUTH), 22, scenario.sensor),
                                      ("unturned", TRUTH, 23, scenario.sensor),
                                      ("other unit", remounted(TRUTH), 24, other_unit)):
        paths[name] = folder / f"{name.replace(' ', '_')}.bin"
        write_capture(replace(scenario, truth=truth, seed=scenario.seed + seed, sensor=sensor), paths[name])
    bench = load_scenario("thesis-bench")  # the unit re-mounted on each face: its force triads' terms
    paths["bench"] = folder / "bench.bin"
    write_capture(replace(bench, truth=replace(bench.truth, **RESIDUALS), seed=bench.seed + 25), paths["bench"])
    return paths


@pytest.fixture(scope="module")
def earlier(captures, tmp_path_factory):
    """The unit's intrinsics as two earlier results: its bench campaign and its two mountings."""
    folder = tmp_path_factory.mktemp("earlier")
    assert _calibrate(captures, folder, "--method", "thesis", "--bench", capture="bench", out="bench.json")[0] == 0
    assert _calibrate(captures, folder, "--remounted", captures["turned"], out="two.json")[0] == 0
    return folder / "bench.json", folder / "two.json"


def _calibrate(paths, tmp_path, *argv, capture="first", out="r.json"):
    out = tmp_path / out
    code = calibd_main(["calibrate", str(paths[capture]), "--latitude", str(THESIS.site.latitude_deg), "--g0",
                        str(THESIS.site.g0), "-o", str(out), *map(str, argv)])
    return code, out


@pytest.mark.slow
def test_calibrate_remounted_reports_the_terms_estimated_and_the_correction_takes_them_out(captures, tmp_path,
                                                                                           capsys):
    code, out = _calibrate(captures, tmp_path, "--remounted", captures["turned"])
    assert code == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    check = doc["checks"]["second_mounting"]
    assert check["path"] == str(captures["turned"]) and check["power_up"] == 1 and check["p_value"] > 1e-3
    assert check["remount_sigma_deg"] == 0.1 and check["alpha_deg"] == pytest.approx(-0.4, abs=0.05)
    assert "remounting" in doc["error_budget"]["parts"]
    terms = doc["error_budget"]["factory_residuals"]["terms"]
    for name, (row, col) in (("gyro_misalignment_xz", (0, 2)), ("gyro_misalignment_yz", (1, 2))):
        term = terms[name]
        assert term["source"] == "estimated" and term["unit"] == "mrad"
        assert abs(term["value"] - TRUTH.triad_error("gyro")[row, col] * 1e3) < 3 * term["sigma"]
    truth = TRUTH.estimates()
    for name in ANGLES:
        estimate = doc["estimates"][name]
        assert abs(estimate["value"] - truth[name]) < 3 * estimate["sigma"] and estimate["sigma"] < 0.006
    from calibd.correction import estimated_maps
    gyro_map = estimated_maps(load_result(out))["gyro"]  # (I + E)^-1 of the estimated terms
    assert np.linalg.inv(gyro_map)[0, 2] == pytest.approx(terms["gyro_misalignment_xz"]["value"] / 1e3, rel=1e-9)
    assert any("rest on the second mounting" in w for w in doc["warnings"])
    from calibd.report import _checks  # the report's Checks list says what the second mounting saw
    assert f"second mounting {captures['turned']} (power-up 1), the housing turned 180 deg" in _checks(load_result(out))


@pytest.mark.slow
@pytest.mark.parametrize("other, argv, message", [
    ("unturned", (), "the two mountings' platform axes do not mirror each other"),
    ("first", (), "is the capture being calibrated"),
    ("other unit", (), "is of serial number N25582405002999, the first mounting's of N25582405002002"),
    ("turned", ("--method", "thesis"), "--remounted belongs to --method joint"),
])
def test_a_second_mounting_that_is_not_the_unit_turned_is_refused_in_one_line(captures, tmp_path, capsys, other,
                                                                             argv, message):
    code, out = _calibrate(captures, tmp_path, "--remounted", captures[other], *argv)
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_remount_sigma_needs_remounted(tmp_path, capsys):
    code = calibd_main(["calibrate", "fixtures/warmup_then_protocol_125hz.bin", "--latitude", "40", "-o",
                        str(tmp_path / "r.json"), "--remount-sigma", "0.05"])
    err = capsys.readouterr().err
    assert code == 2 and "--remount-sigma is the second mounting's 1-sigma: give --remounted too" in err


@pytest.mark.slow
def test_factory_terms_of_a_bench_and_a_second_mounting_bring_a_later_calibration_to_the_noise(captures, earlier,
                                                                                              tmp_path, capsys):
    """The unit's bench campaign (its force triads' terms from six positions) and its two
    mountings (the gyro triad's that tilt the axis), taken as known by a later single-mounting
    calibration of other data (`--intrinsics`): pitch, roll, alpha, beta and the horizontal biases
    fall to the noise and stay within their sigma of the truth."""
    bench, two = earlier
    assert _calibrate(captures, tmp_path, capture="unturned", out="alone.json")[0] == 0
    code, out = _calibrate(captures, tmp_path, "--intrinsics", bench, "--intrinsics", two, capture="unturned",
                           out="known.json")
    assert code == 0, capsys.readouterr().err
    alone, known = (json.loads((tmp_path / name).read_text()) for name in ("alone.json", "known.json"))
    assert known["options"]["intrinsics"]["path"] == f"{bench}, {two}"
    assert {"acc_misalignment_xz", "gyro_misalignment_xz"} <= set(known["options"]["intrinsics"]["terms"])
    truth = TRUTH.estimates()
    # the bench sees the accelerometers' terms to about 0.01 mrad, the noisier inclinometers' to 0.1 to 0.16
    for name, share in {**dict.fromkeys((*ANGLES, "acc_bias_x", "acc_bias_y"), 0.1),
                        "incl_bias_x": 0.35, "incl_bias_y": 0.35}.items():
        estimate = known["estimates"][name]
        assert estimate["sigma"] < share * alone["estimates"][name]["sigma"], name
        assert abs(estimate["value"] - truth[name]) < 3 * estimate["sigma"], name
    terms = known["error_budget"]["factory_residuals"]["terms"]
    assert terms["acc_misalignment_xz"]["source"] == terms["gyro_misalignment_yz"]["source"] == "estimated"


@pytest.mark.slow
@pytest.mark.parametrize("given, message", [
    ("first", "rests on the same data as the capture calibrated: its terms would be counted twice"),
    ("other", "are of serial number N25582405002999, this sensor is N25582405002002: factory terms are one unit's"),
    ("none", "estimates no factory term"),
])
def test_intrinsics_that_are_not_this_units_other_data_are_refused_in_one_line(captures, tmp_path, capsys, given,
                                                                              message):
    made = {"first": ("first", ()), "other": ("other unit", ()), "none": ("unturned", ("--method", "thesis"))}
    capture, argv = made[given]
    assert _calibrate(captures, tmp_path, *argv, capture=capture, out="earlier.json")[0] == 0
    capsys.readouterr()
    code, out = _calibrate(captures, tmp_path, "--intrinsics", tmp_path / "earlier.json")
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.slow
def test_a_second_mounting_that_never_warmed_flags_what_its_tilt_sets(exact):
    from calibd.methods.joint import SecondMounting, joint_real_case

    _, second, _, _ = exact
    session = session_of(simulate(replace(QUIET, truth=TRUTH)))
    cold = SecondMounting(second, {"path": "turned.bin", "size_bytes": 1, "sha256": "0" * 64, "power_up": 1}, 0.0,
                          "was taken while the IMU warmed up (its temperature never settled)")
    result = joint_real_case(session, THESIS.site, second=cold)
    assert sorted(n for n, e in result.estimates.items() if e.quality == "poor") == sorted(ANGLES)
    words = "the second mounting's power-up was taken while the IMU warmed up"
    assert any(w.startswith(words) for w in result.warnings)


@pytest.mark.slow
def test_the_daemon_takes_intrinsics_from_its_configuration(captures, earlier, tmp_path, capsys):
    """`[method] intrinsics` in the daemon's configuration: every result it solves takes the
    unit's factory terms as known (here through `calibd replay`, the daemon's own pipeline); a
    list naming one result twice is refused at start in one line."""
    bench, two = earlier
    config = tmp_path / "calibd.toml"
    files = f'["{bench}", "{two}"]'
    config.write_text(f'[serial]\nport = "/dev/null"\n[site]\nlatitude_deg = {THESIS.site.latitude_deg}\n'
                      f'g0 = {THESIS.site.g0}\n[output]\nstate_dir = "{tmp_path / "state"}"\n'
                      f'[method]\nintrinsics = {files}\n')
    capsys.readouterr()
    assert calibd_main(["replay", str(captures["unturned"]), "--config", str(config), "--state-dir",
                        str(tmp_path / "state")]) == 0, capsys.readouterr().err
    result = json.loads((tmp_path / "state" / "result.json").read_text())
    assert result["options"]["intrinsics"]["terms"] and result["estimates"]["alpha"]["sigma"] < 0.003
    assert result["estimates"]["acc_bias_x"]["sigma"] < 0.06
    config.write_text(config.read_text().replace(files, f'["{two}", "{two}"]'))
    capsys.readouterr()
    assert calibd_main(["replay", str(captures["unturned"]), "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "[method] intrinsics:" in err and "rests on the same data as" in err and err.count("\n") == 1, err


@pytest.mark.slow
def test_plan_shows_what_known_intrinsics_buy(earlier, capsys):
    bench, two = earlier
    code = calibd_main(["plan", "--campaign", "thesis", "--latitude", "40.59129", "--g0", "9.79956",
                        "--intrinsics", str(bench), "--intrinsics", str(two)])
    out = capsys.readouterr().out
    assert code == 0 and f"factory terms known from {bench}, {two}" in out.splitlines()[0]
    pitch = next(line for line in out.splitlines() if line.strip().startswith("pitch"))
    acc_x = next(line for line in out.splitlines() if line.strip().startswith("acc_bias_x"))
    assert float(pitch.split()[1]) < 0.003 and float(acc_x.split()[1]) < 0.06, out


@pytest.mark.slow
def test_known_terms_enter_a_pair_of_mountings_once(earlier):
    """Planned on two mountings with the gyro terms already known, the terms' information is the
    prior's, the known result's and the pair's, each once: the second mounting's fit leaves the
    known terms to the first's posterior (JointOptions.for_second_mounting)."""
    from calibd import planner
    from calibd.estimators.joint import JointOptions
    from calibd.methods.joint import measured_terms
    from calibd.scenario import Noise

    known = JointOptions(known_terms=measured_terms(load_result(earlier[1])))
    name, prior = "gyro_misalignment_xz", 0.5
    pair = planner.plan("thesis", THESIS.site, Noise(), remount_sigma=0.1 * DEG).estimated_terms[name][0]
    alone = planner.plan("thesis", THESIS.site, Noise(), options=known).estimated_terms[name][0]
    both = planner.plan("thesis", THESIS.site, Noise(), options=known, remount_sigma=0.1 * DEG).estimated_terms[name][0]
    assert both == pytest.approx((1 / pair**2 + 1 / alone**2 - 1 / prior**2) ** -0.5, rel=0.03)
    assert known.for_second_mounting().known_terms == ()


@pytest.mark.slow
def test_a_unit_misaligned_beyond_its_datasheet_is_measured_and_flagged_not_refused():
    """A gyro triad 2.5 mrad off (2.5 times the datasheet's limit): the tilts' sum is beyond what the
    prior allows, but not beyond what a unit can be, so it is measured (alpha and beta to 2 % of
    the move) and what it sets is flagged poor with why; a housing not turned is refused (above)."""
    from calibd.methods.joint import SecondMounting, joint_real_case

    truth = replace(TRUTH, gyro_misalignment_mrad=(0.0, 2.5, 0.0, -0.5, 0.0, 0.0))
    _, second = _fits(QUIET, truth)
    source = {"path": "turned.bin", "size_bytes": 1, "sha256": "0" * 64, "power_up": 1}
    result = joint_real_case(session_of(simulate(replace(QUIET, truth=truth))), THESIS.site,
                             second=SecondMounting(second, source, 0.0))
    assert result.checks["second_mounting"]["p_value"] < 1e-3
    assert {n for n, e in result.estimates.items() if e.quality == "poor"} >= set(ANGLES)
    assert any("beyond what the datasheet's residuals allow" in w for w in result.warnings)
    for name in ("alpha", "beta"):
        assert result.estimates[name].value == pytest.approx(truth.estimates()[name], abs=0.02 * 0.143)
    term = result.error_budget["factory_residuals"]["terms"]["gyro_misalignment_xz"]
    assert term["value"] == pytest.approx(2.5, rel=0.02)

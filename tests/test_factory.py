"""The sensor as its datasheet describes it: factory residuals (each triad's misalignment to the
housing and scale factors), the joint fit's error budget that carries them, and the datasheet's
noise. Each residual alone moves the estimates as first-order physics says, the budget predicts
that move, and the reported sigma covers it; on a tilted platform axis the statics' forces
estimate what they see (the gyro Z scale factor)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from calibd import spec
from calibd.methods.joint import joint_fit, joint_real_case
from calibd.captures import load_session
from calibd.estimators import joint
from calibd.frames import STANDARD_GRAVITY
from calibd.errors import CalibrationError
from calibd.estimators.joint import JointOptions
from calibd.results import ResultStream, parse_result, result_json
from calibd.scenario import Noise, ScenarioError, Truth, load_scenario, parse_scenario
from calibd.session import Session
from calibd.sim import simulate, write_capture
from calibd.units import DEG
from stim300.records import SensorRecord
from test_joint import exact_input

MG = STANDARD_GRAVITY / 1000
THESIS = load_scenario("thesis-real")
QUIET = replace(THESIS, noise=replace(THESIS.noise, enabled=False), warmup=replace(THESIS.warmup, power_on_s=1e7))


def session_of(sim) -> Session:
    s, rate = sim.samples, sim.scenario.sensor.sample_rate_hz
    return Session(time_s=np.arange(len(s)) / rate, gyro=sim.exact["gyro"] * DEG,
                   acc=sim.exact["acc"] * STANDARD_GRAVITY, incl=sim.exact["incl"] * STANDARD_GRAVITY,
                   temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))


def fitted(truth: Truth, scenario=QUIET):
    """The joint fit of a noise-free session (exact values, no quantisation) with this truth, as
    the fit itself gives it (before the statics' forces are asked about the residuals)."""
    sim = simulate(replace(scenario, truth=truth))
    return joint.solve(exact_input(sim), scenario.site)


@pytest.fixture(scope="module")
def perfect():
    return fitted(THESIS.truth)


# (truth field, index, value) of one residual, the estimate it moves and by how much (SI) at
# first order: a gyro triad sensing housing Z on its X axis tilts the platform axis it sees, so
# beta by -E_xz; the accelerometers' X reading g0 E_xz more is a bias; a Z scale factor reads
# g0 s more along gravity, a bias too.
FIRST_ORDER = [
    ("gyro_misalignment_mrad", 1, 0.5, "beta", -0.5e-3),
    ("gyro_misalignment_mrad", 3, 0.5, "alpha", 0.5e-3),
    ("acc_misalignment_mrad", 1, 0.5, "acc_bias_x", 0.5e-3 * THESIS.site.gravity),
    ("incl_misalignment_mrad", 3, -0.5, "incl_bias_y", -0.5e-3 * THESIS.site.gravity),
    ("incl_scale_ppm", 2, 250.0, "incl_bias_z", 250e-6 * THESIS.site.gravity),
    ("acc_scale_ppm", 2, -100.0, "acc_bias_z", -100e-6 * THESIS.site.gravity),
]


@pytest.mark.parametrize("field, index, value, estimate, move", FIRST_ORDER)
@pytest.mark.slow
def test_one_residual_moves_its_estimate_as_first_order_physics_says_and_the_budget_predicts(
        perfect, field, index, value, estimate, move):
    values = [0.0] * len(getattr(THESIS.truth, field))
    values[index] = value
    fit = fitted(replace(THESIS.truth, **{field: tuple(values)}))
    moved = fit.estimates[estimate] - perfect.estimates[estimate]
    assert moved == pytest.approx(move, rel=0.03)
    # the budget's own prediction for this term at `value`, from the fit of the perfect session
    sensor = field.split("_")[0]
    row, col = ((index, index) if "scale" in field else spec.OFF_DIAGONAL[index])
    k = next(i for i, t in enumerate(perfect.factory.terms) if (t.sensor, t.row, t.col) == (sensor, row, col))
    term = perfect.factory.terms[k]
    predicted = perfect.factory.estimates[list(perfect.estimates).index(estimate), k] * value / term.sigma_in_unit
    assert predicted == pytest.approx(moved, rel=0.03)
    # at 1 (misalignment 0.5 mrad) or 1.25 sigma of the prior, the sigma covers it
    assert abs(moved) < 2 * fit.sigmas[estimate]


def noisy_session(scenario) -> Session:
    sim = simulate(scenario)
    s, rate = sim.samples, scenario.sensor.sample_rate_hz
    return Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                   acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                   temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))


@pytest.mark.parametrize("seed", [3, 4])
@pytest.mark.slow
def test_a_tilted_platform_axis_estimates_the_gyro_z_scale_factor(seed):
    """With the platform axis 5.8 deg from Up the accelerometers see the statics' angles turned
    by the gyro Z scale factor (s chi): estimated to about a tenth of its prior, within 2 sigma
    of the simulated 400 ppm (the angle walk of the gyros' white noise through the turns is in
    the check's covariance: without it the error was 3 sigma). An axis 0.07 deg from Up leaves
    it to its prior."""
    truth = replace(THESIS.truth, pitch_deg=5.0, roll_deg=3.0, gyro_scale_ppm=(0.0, 0.0, 400.0))
    scenario = replace(THESIS, seed=seed, truth=truth, warmup=replace(THESIS.warmup, power_on_s=1e7))
    terms = joint_real_case(noisy_session(scenario), THESIS.site).error_budget["factory_residuals"]["terms"]
    scale = terms["gyro_scale_z"]
    assert scale["source"] == "estimated" and scale["sigma"] < 0.2 * scale["prior_sigma"]
    assert abs(scale["value"] - 400.0) < 2 * scale["sigma"], scale
    upright = replace(truth, pitch_deg=0.05, roll_deg=0.05, alpha_deg=0.0, beta_deg=0.0)
    terms = joint_real_case(noisy_session(replace(scenario, truth=upright)), THESIS.site).error_budget
    assert terms["factory_residuals"]["terms"]["gyro_scale_z"]["source"] == "prior"  # 0.07 deg from Up: unseen


@pytest.mark.slow
def test_the_moved_estimates_are_only_those_the_physics_names(perfect):
    """A misaligned gyro triad moves alpha, beta and (through the axis) pitch and roll and the
    horizontal biases; yaw and the gyro biases barely (well under their noise sigma)."""
    effects = dict(zip(perfect.estimates, perfect.factory.estimates))
    noise_only = {name: np.sqrt(perfect.budget["white_noise"][i, i] + perfect.budget["bias_instability"][i, i])
                  for i, name in enumerate(perfect.estimates)}
    for name in ("yaw", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z"):
        assert np.linalg.norm(effects[name]) < 0.1 * noise_only[name], name
    for name in ("pitch", "roll", "alpha", "beta", "acc_bias_x", "acc_bias_y", "incl_bias_x", "incl_bias_y"):
        assert np.linalg.norm(effects[name]) > 5 * noise_only[name], name


@pytest.mark.slow
def test_the_budget_parts_add_up_to_the_sigma_in_the_result_document():
    sim = simulate(THESIS)
    s, rate = sim.samples, THESIS.sensor.sample_rate_hz
    session = Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                      acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                      temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))
    doc = json.loads(result_json(joint_real_case(session, THESIS.site)))
    budget = doc["error_budget"]
    assert budget["frame"] == "housing" and doc["schema"] == "calibd.result/7"
    for name, estimate in doc["estimates"].items():
        parts = budget["sigma"][name]
        assert set(parts) == set(budget["parts"]) >= {"white_noise", "bias_instability", "gravity", "factory_residuals"}
        assert sum(v**2 for v in parts.values()) == pytest.approx(estimate["sigma"] ** 2, rel=1e-9)
    terms = budget["factory_residuals"]["terms"]
    # a platform axis 0.9 deg from Up: the statics' forces narrow some terms a little, set none
    assert len(terms) == 27 and all(t["source"] == "prior" and t["sigma"] <= t["prior_sigma"] for t in terms.values())
    assert terms["gyro_scale_z"]["prior_sigma"] == 250.0 and terms["gyro_scale_z"]["unit"] == "ppm"
    assert terms["acc_misalignment_xz"]["prior_sigma"] == 0.5 and terms["incl_scale_x"]["prior_sigma"] == 250.0
    assert terms["incl_scale_x"]["sigma"] == pytest.approx(250.0, rel=0.01)  # what no static sees keeps its prior
    # what a single vertical axis cannot see sets alpha's sigma: the gyro triad's 0.5 mrad, a
    # little less where the statics see the gyro triad against the accelerometers'
    assert 0.8 < budget["sigma"]["alpha"]["factory_residuals"] / np.degrees(0.5e-3) < 1.0


@pytest.mark.slow
def test_without_the_prior_the_fit_is_that_of_a_perfect_sensor(perfect):
    session = session_of(simulate(QUIET))
    bare = joint_fit(session, QUIET.site, joint.JointOptions(factory_residuals=False)).fit
    assert bare.factory is None and "factory_residuals" not in bare.budget
    assert bare.estimates == pytest.approx(perfect.estimates, abs=1e-12)
    assert bare.sigmas["alpha"] < 0.1 * perfect.sigmas["alpha"]


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.slow
def test_residuals_at_the_datasheet_limits_are_flagged_or_within_three_sigma(seed):
    """Every residual at its limit with a random sign, datasheet noise: no confident wrong answer."""
    rng = np.random.default_rng(seed)
    residuals = {}
    for sensor, triad in spec.triads().items():
        residuals[f"{sensor}_scale_ppm"] = tuple(rng.choice([-1, 1], 3) * triad.scale_factor_ppm)
        residuals[f"{sensor}_misalignment_mrad"] = tuple(rng.choice([-1, 1], 6) * triad.misalignment_mrad)
    scenario = replace(THESIS, seed=seed, truth=replace(THESIS.truth, **residuals))
    sim = simulate(scenario)
    s, rate = sim.samples, scenario.sensor.sample_rate_hz
    session = Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                      acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                      temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))
    result = joint_real_case(session, scenario.site)
    truth = scenario.truth.estimates()
    for name, e in result.estimates.items():
        if name.endswith(("_x", "_y", "_z")):
            continue  # biases: their turn-on truth needs the warm-up; the angles carry the point
        assert e.quality == "poor" or abs(e.value - truth[name]) < 3 * e.sigma, (name, e, truth[name])


@pytest.mark.slow
def test_a_clean_capture_with_the_datasheet_noise_raises_no_vibration_warning():
    """The inclinometers' 0.08 m/s/sqrt(h) at 0 g and 35 % more along gravity, the 10 g
    accelerometers' 0.024: the sensor as specified is not vibrating."""
    assert (THESIS.noise.incl_vrw_m_s_sqrt_h, THESIS.noise.acc_vrw_m_s_sqrt_h) == (0.08, 0.024)
    sim = simulate(replace(THESIS, seed=5))
    s, rate = sim.samples, THESIS.sensor.sample_rate_hz
    session = Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                      acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                      temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))
    result = joint_real_case(session, THESIS.site)
    assert not [w for w in result.warnings if "per sample" in w], result.warnings


def test_the_simulated_inclinometer_is_noisier_along_gravity():
    sim = simulate(replace(THESIS, segments=THESIS.segments[:1]))
    steps = np.diff(sim.exact["incl"], axis=0)
    ratio = steps[:, 2].std() / steps[:, :2].std()
    assert ratio == pytest.approx(spec.INCL_NOISE_AT_1G, rel=0.03)


@pytest.mark.parametrize("range_g, vrw, scale_ppm", [(5, 0.024, 200), (30, 0.04, 300), (80, 0.15, 1000)])
def test_the_noise_defaults_follow_the_sensors_range(range_g, vrw, scale_ppm):
    scenario = parse_scenario({"sensor": {"acc_range_g": range_g}, "site": {"latitude_deg": 45.0},
                               "segments": [{"type": "static", "duration_s": 10}]}, "s.toml")
    assert scenario.noise == Noise.datasheet(range_g) and scenario.noise.acc_vrw_m_s_sqrt_h == vrw
    assert spec.triads(range_g)["acc"].scale_factor_ppm == scale_ppm


def test_a_scenario_takes_each_triads_residuals_and_refuses_the_wrong_shape():
    base = {"site": {"latitude_deg": 45.0}, "segments": [{"type": "static", "duration_s": 10}]}
    truth = {"gyro_misalignment_mrad": [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], "incl_scale_ppm": [100, -200, 300]}
    scenario = parse_scenario(base | {"truth": truth}, "s.toml")
    error = scenario.truth.triad_error("gyro")
    assert error[0, 1] == 0.1e-3 and error[2, 1] == 0.6e-3 and np.all(np.diag(error) == 0)
    assert np.diag(scenario.truth.triad_error("incl")) == pytest.approx([100e-6, -200e-6, 300e-6])
    with pytest.raises(ScenarioError, match=r"s.toml \[truth\] acc_misalignment_mrad: \[1, 2, 3\] is not a list of 6"):
        parse_scenario(base | {"truth": {"acc_misalignment_mrad": [1, 2, 3]}}, "s.toml")
    with pytest.raises(ScenarioError, match=r"gyro_scale_ppm: .* is not in \[-10000, 10000\] ppm"):
        parse_scenario(base | {"truth": {"gyro_scale_ppm": [0, 0, 2e4]}}, "s.toml")


@pytest.mark.slow
def test_an_80_g_unit_is_held_to_its_own_datasheet_figures(tmp_path):
    """The configuration datagram names the accelerometers' range: its noise (0.15 m/s/sqrt(h))
    raises no vibration warning, and its 1000 ppm scale factor sets the Z bias's prior."""
    scenario = replace(THESIS, sensor=replace(THESIS.sensor, acc_range_g=80), noise=Noise.datasheet(80))
    path = tmp_path / "80g.bin"
    write_capture(scenario, path)
    result = joint_real_case(load_session(str(path)), THESIS.site)
    assert result.sensor.acc_range_g == 80
    assert not [w for w in result.warnings if "per sample" in w], result.warnings
    budget = result.error_budget
    assert budget["factory_residuals"]["acc_range_g"] == 80
    assert budget["factory_residuals"]["terms"]["acc_scale_z"]["prior_sigma"] == 500.0
    assert budget["sigma"]["acc_bias_z"]["factory_residuals"] == pytest.approx(0.5e-3 * 1000 * THESIS.site.gravity
                                                                               / STANDARD_GRAVITY, rel=0.02)


def test_the_factory_prior_check_counts_only_the_directions_the_data_saw():
    posterior = joint.FactoryPosterior(z=np.array([1.0, 2.0, 0.1]), cov=np.diag([0.5, 0.2, 0.95]))
    chi2, dof = posterior.against_prior()  # I - cov: 0.5, 0.8 seen; 0.05 below SEEN_SHARE
    assert dof == 2 and chi2 == pytest.approx(1.0 / 0.5 + 4.0 / 0.8)


LIMIT_SEED = 4  # signs whose unit the check flags (as 43 % of units with every element at +-limit)
TILTED_1_DEG = dict(pitch_deg=1.0, roll_deg=-0.9, alpha_deg=0.8, beta_deg=0.7)  # the statics see more tilted


def at_limits(seed: int) -> Truth:
    """Every factory residual at its datasheet limit, signs drawn from `seed`, on a unit tilted
    by about a degree."""
    rng = np.random.default_rng(seed)
    fields = {}
    for sensor, triad in spec.triads(spec.DEFAULT_ACC_RANGE_G).items():
        fields[f"{sensor}_scale_ppm"] = tuple(rng.choice([-1, 1], 3) * triad.scale_factor_ppm)
        fields[f"{sensor}_misalignment_mrad"] = tuple(rng.choice([-1, 1], 6) * triad.misalignment_mrad)
    return replace(THESIS.truth, **fields, **TILTED_1_DEG)


@pytest.mark.slow
@pytest.mark.parametrize("truth, flagged",
                         [(replace(THESIS.truth, **TILTED_1_DEG), False), (at_limits(LIMIT_SEED), True)],
                         ids=["perfect unit", "every residual at its limit"])
def test_a_unit_whose_visible_residuals_lie_beyond_the_datasheet_has_what_they_limit_flagged(truth, flagged):
    result = joint_real_case(noisy_session(replace(THESIS, truth=truth)), THESIS.site)
    check = result.checks["factory_prior_chi2"]
    assert check["dof"] > 0
    poor = [n for n, e in result.estimates.items() if e.quality == "poor"]
    if not flagged:
        assert check["p_value"] > 0.05 and poor == []
        return
    assert check["p_value"] < 0.01
    limited = [n for n in result.estimates if n not in ("yaw", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z")]
    assert poor == limited  # pitch, roll, alpha, beta, the force biases: what the residuals limit
    assert any("beyond the STIM300 datasheet's spread" in w for w in result.warnings)


@pytest.mark.parametrize("range_g", spec.ACC_RANGES_G)
def test_a_unit_at_the_datasheet_limits_has_each_axis_and_each_pair_at_its_limit(range_g):
    """What the datasheet bounds (TS1524 rev.31, Tables 5-3 to 5-8): each sensing axis's angle to
    its housing reference (the two off-diagonal elements of its row) and each pair's deviation
    from 90 deg (E_ij + E_ji). `spec.limit_misalignment` puts both at their limits."""
    rng = np.random.default_rng(range_g)
    for triad in spec.triads(range_g).values():
        for _ in range(20):
            error = spec.triad_error(np.zeros(3), spec.limit_misalignment(rng, triad))
            axes = [np.hypot(*np.delete(error[i], i)) * 1e3 for i in range(3)]
            pairs = [abs(error[i, j] + error[j, i]) * 1e3 for i, j in ((0, 1), (0, 2), (1, 2))]
            assert np.allclose(pairs, triad.orthogonality_mrad)
            assert all(abs(a - triad.misalignment_mrad) <= triad.orthogonality_mrad + 1e-12 for a in axes), axes
            limit, orthogonality = triad.misalignment_mrad, triad.orthogonality_mrad
            assert np.isclose(np.mean(np.square(axes)), limit ** 2 + orthogonality ** 2 / 2)


INDEXED = JointOptions(index_step=90 * DEG, index_sigma=0.01 * DEG)
UPRIGHT = replace(THESIS.truth, pitch_deg=0.05, roll_deg=0.05, alpha_deg=0.0, beta_deg=0.0,
                  gyro_scale_ppm=(0.0, 0.0, 400.0))


def test_indexed_turns_give_the_gyro_z_scale_factor_exactly_on_exact_data():
    """An axis 0.07 deg from Up, whose statics' forces see nothing of the gyro Z scale factor:
    with the statics at an indexing table's stops (90 deg), each turn's integral less its stop's
    angle is the scale factor times the angle. On exact data: 400 ppm to a millionth, and yaw
    and the attitude as simulated."""
    sim = simulate(replace(QUIET, truth=UPRIGHT))
    result = joint_real_case(session_of(sim), THESIS.site, INDEXED)
    check = result.checks["indexed_turns"]
    assert check["static_angles_deg"] == [0.0, -90.0, -180.0, -270.0, -360.0, -720.0]
    assert check["gyro_minus_stop_deg"] == pytest.approx([400e-6 * a for a in check["static_angles_deg"]], abs=1e-7)
    assert check["scale_along_axis_ppm"] == pytest.approx(400.0, abs=1e-3)
    term = result.error_budget["factory_residuals"]["terms"]["gyro_scale_z"]
    assert term["source"] == "estimated" and term["value"] == pytest.approx(400.0, rel=0.02)
    assert result.estimates["yaw"].value == pytest.approx(UPRIGHT.yaw_deg, abs=1e-6)
    assert result.options == {"fixed_amplitude": False, "drift": False, "index_step_deg": 90.0,
                              "index_sigma_deg": 0.01}
    assert any("each static's platform angle is its stop's (index step 90 deg" in w for w in result.warnings)


@pytest.mark.slow
def test_indexed_turns_estimate_the_gyro_z_scale_factor_within_its_sigma_and_carry_the_stops_error():
    """With the sensor's noise: the scale factor to about an eighth of its prior, within 2 sigma
    of the simulated 400 ppm (without the index it keeps its prior); the stops' own 1-sigma moves
    the estimates through the turn_angles part of the budget."""
    scenario = replace(THESIS, seed=3, truth=UPRIGHT, warmup=replace(THESIS.warmup, power_on_s=1e7))
    session = noisy_session(scenario)
    result = joint_real_case(session, THESIS.site, INDEXED)
    term = result.error_budget["factory_residuals"]["terms"]["gyro_scale_z"]
    assert term["source"] == "estimated" and term["sigma"] < 0.2 * term["prior_sigma"]
    assert abs(term["value"] - 400.0) < 2 * term["sigma"], term
    assert result.error_budget["sigma"]["yaw"]["turn_angles"] > 0
    exact = joint_real_case(session, THESIS.site, replace(INDEXED, index_sigma=0.0))
    assert exact.error_budget["sigma"]["yaw"]["turn_angles"] == 0
    unindexed = joint_real_case(session, THESIS.site).error_budget["factory_residuals"]["terms"]["gyro_scale_z"]
    assert unindexed["source"] == "prior"
    again = parse_result(result_json(result), "result")
    assert again.checks["indexed_turns"] == result.checks["indexed_turns"] and again.options == result.options


def test_a_campaign_whose_statics_are_not_at_the_steps_stops_is_refused():
    sim = simulate(replace(QUIET, truth=UPRIGHT))
    with pytest.raises(CalibrationError) as refused:
        joint_real_case(session_of(sim), THESIS.site, replace(INDEXED, index_step=60 * DEG))
    assert str(refused.value) == ("static 2 of the fit sits at -90.04 deg by the gyros, 29.96 deg from the nearest "
                                  "multiple of the index step 60 deg: the turns are not indexed by that step")


@pytest.mark.slow
def test_turns_that_do_not_end_at_the_stops_are_named_and_what_they_move_is_flagged():
    """A platform driven by time, not stopped at detents: the simulator's 2 % rate ripple ends
    each 90 deg turn 1.15 deg beyond it. Taken as indexed, the turns show a scale factor far
    beyond the datasheet's 500 ppm: a warning says the platform may not stop at the steps, and
    the factory check flags what the factory terms limit."""
    rippled = tuple(replace(s, ripple=0.02) if s.kind == "turn" else s for s in QUIET.segments)
    sim = simulate(replace(QUIET, truth=UPRIGHT, segments=rippled))
    result = joint_real_case(session_of(sim), THESIS.site, INDEXED)
    assert any("beyond the gyro scale factor the STIM300 datasheet allows (500 ppm): the platform may not stop at "
               "whole multiples of 90 deg (--index-step)" in w for w in result.warnings)
    assert result.estimates["yaw"].quality == "poor"


@pytest.mark.slow
def test_a_hidden_loss_mid_turn_is_named_and_left_out_of_the_scale_factor_with_the_statics_at_their_stops():
    """A whole 0.128 s cycle lost in the second index turn, which the counter cannot see: the
    turn's integral is 2.5 deg short, far more than a scale factor makes. Its statics keep their
    stops' angles, the turn is named and left out, and the other turns still give the simulated
    400 ppm; the estimates are those of the lossless session."""
    sim = simulate(replace(QUIET, truth=UPRIGHT))
    whole = session_of(sim)
    turn = [p for p in sim.phases if p.kind == "turn"][1]
    cut = int((turn.start_s + turn.end_s) / 2 * whole.rate_hz)
    kept = np.r_[0:cut, cut + 16:len(whole.time_s)]  # 16 samples at 125 Hz: one counter cycle
    lossy = replace(whole, time_s=np.arange(len(kept)) / whole.rate_hz, gyro=whole.gyro[kept], acc=whole.acc[kept],
                    incl=whole.incl[kept])
    clean, result = (joint_real_case(s, THESIS.site, INDEXED) for s in (whole, lossy))
    check = result.checks["indexed_turns"]
    assert check["turns_left_out"] == [2] and clean.checks["indexed_turns"]["turns_left_out"] == []
    assert check["scale_along_axis_ppm"] == pytest.approx(400.0, abs=0.01)
    named = [w for w in result.warnings if "left out of the scale factor" in w]
    assert len(named) == 1 and "ended +2.53 deg from its stop" in named[0]
    assert not [n for n, e in result.estimates.items() if e.quality == "poor"]
    for name in ("yaw", "pitch", "roll", "alpha", "beta"):
        assert result.estimates[name].value == pytest.approx(clean.estimates[name].value, abs=1e-3)

"""The campaign planner: the joint estimator's own covariance under given noise figures (checked
against the estimator on a noisy session, the white-noise Cramer-Rao bound and the measured Monte
Carlo), the analytic scalings with data time and latitude, the time-to-target search, the command."""

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibd import detect, planner
from calibd.methods.joint import checked_by_statics
from calibd.cli import main as calibd_main
from calibd.estimators.joint import JointInput, JointOptions, datasheet_noise, solve, white_noise_bound
from calibd.frames import STANDARD_GRAVITY, Site
from calibd.scenario import Noise, load_scenario
from calibd.sim import simulate
from calibd.units import DEG

THESIS = load_scenario("thesis-real")
SITE = THESIS.site
STIM300 = Noise()
WHITE_GYRO_ONLY = Noise(gyro_bias_instability_deg_h=0, acc_vrw_m_s_sqrt_h=0, acc_bias_instability_mg=0,
                        incl_vrw_m_s_sqrt_h=0, incl_bias_instability_mg=0)
WHITE_ONLY = Noise(gyro_bias_instability_deg_h=0, acc_bias_instability_mg=0, incl_bias_instability_mg=0)


PERFECT = JointOptions(factory_residuals=False)  # the noise terms alone: the scalings they follow


@pytest.fixture(scope="module")
def thesis_plan():
    return planner.plan("thesis", SITE, STIM300)


@pytest.fixture(scope="module")
def noise_plan():
    return planner.plan("thesis", SITE, STIM300, options=PERFECT)


def detected_input(sim) -> JointInput:
    """A simulated session as calibrate hands it to the joint estimator: statics found by
    detection, from the level static on, 125 Hz."""
    rate = sim.scenario.sensor.sample_rate_hz
    gyro, acc, incl = (sim.exact[k] for k in ("gyro", "acc", "incl"))
    t = np.arange(len(gyro)) / rate
    statics = [(s.start, s.stop) for s in detect.find_segments(gyro, acc, rate, t) if s.kind == "static"]
    first = statics[0][0]
    return JointInput(t[first:] - t[first], gyro[first:] * DEG, acc[first:] * STANDARD_GRAVITY,
                      incl[first:] * STANDARD_GRAVITY, tuple((a - first, b - first) for a, b in statics), rate)


@pytest.mark.slow
def test_plan_is_the_estimators_sigma_on_a_real_session(thesis_plan):
    """A noisy 125 Hz thesis session, its statics found by detection, solved with the noise model
    of the same figures: the estimator reports the planner's sigmas (the planner's session is
    noise-free, scheduled and at 5 Hz; none of that moves a sigma by 0.2 %). Yaw's sigma is the
    Earth-rate direction's over the fitted Earth-rate amplitude, which the noise moves by a few
    percent (3 % per sigma): scaled to the noise-free amplitude, it agrees too."""
    inp = detected_input(simulate(replace(THESIS, seed=11)))
    along = inp.incl[slice(*inp.statics[0])].mean(axis=0) / STANDARD_GRAVITY  # the inclinometer axis along gravity
    result = solve(inp, SITE, noise=datasheet_noise(STIM300, inp.rate_hz, along))
    result = checked_by_statics(inp, result, SITE)  # as the plan and calibrate take it
    noise_free = solve(thesis_plan.session, SITE, noise=thesis_plan.noise)
    amplitude_ratio = result.gyro.amplitude_check[0] / noise_free.gyro.amplitude_check[0]
    assert abs(amplitude_ratio - 1) > 0.02  # this seed's noise moves it: the scaling matters
    reported = result.sigmas | {"yaw": result.sigmas["yaw"] * amplitude_ratio}
    for name, sigma in thesis_plan.sigmas.items():
        assert sigma == pytest.approx(reported[name], rel=2e-3), name


def test_white_gyro_noise_gives_the_cramer_rao_bound():
    """Only white gyro noise, perfect accelerometers: the gyro-driven sigmas are the white-noise
    Cramer-Rao bound (`white_noise_bound`, its own covariance code)."""
    planned = planner.plan("thesis", SITE, WHITE_GYRO_ONLY, options=PERFECT)
    result = solve(planned.session, SITE, PERFECT, noise=planned.noise)
    bound = white_noise_bound(planned.session, result, SITE, WHITE_GYRO_ONLY.gyro_arw_deg_sqrt_h / 60 * DEG)
    for name in ("yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z"):
        assert planned.sigmas[name] == pytest.approx(bound[name], rel=1e-6), name


def test_yaw_sigma_matches_the_measured_monte_carlo(thesis_plan):
    """docs/accuracy.md: 120 noisy thesis sessions (random heading, sense, alpha/beta) through
    the joint estimator. The planned yaw 1-sigma is within 25 % of their yaw RMS error."""
    table = (Path(__file__).parents[1] / "docs" / "accuracy.md").read_text()
    row = re.search(r"^\| yaw \| deg \|([^\n]*)$", table, re.M).group(1).split("|")
    measured_rms = float(row[0])  # the first table (g0 given); columns: joint RMS error, RMS(error / sigma), ...
    assert thesis_plan.sigmas["yaw"] / DEG == pytest.approx(measured_rms, rel=0.25)


@pytest.mark.slow
def test_white_noise_sigma_falls_as_one_over_root_time():
    """White noise only: doubling the statics of the index campaign (nearly all its data)
    divides the sigma of what the statics determine by sqrt of the data time ratio; alpha and
    beta come from the turns, which are kept, and stay, and so does most of the horizontal
    accelerometer biases' sigma (g0 d_beta); bias instability does not average so."""
    one, two = (planner.plan("index", SITE, WHITE_ONLY, scale, PERFECT) for scale in (1, 2))
    ratio = math.sqrt(one.duration_s / two.duration_s)
    assert ratio == pytest.approx(1 / math.sqrt(2), rel=0.02)
    for name in ("yaw", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "incl_bias_z"):
        assert two.sigmas[name] / one.sigmas[name] == pytest.approx(ratio, rel=0.01), name
    # the Z biases carry alpha/beta at second order (g0 sin(beta) d_beta), seen on the quiet accelerometers
    assert two.sigmas["acc_bias_z"] / one.sigmas["acc_bias_z"] == pytest.approx(ratio, rel=0.05)
    assert two.sigmas["alpha"] / one.sigmas["alpha"] == pytest.approx(1, abs=0.01)
    assert two.sigmas["acc_bias_x"] / one.sigmas["acc_bias_x"] == pytest.approx(1, abs=0.02)
    flicker = [planner.plan("index", SITE, STIM300, scale).floor_yaw() for scale in (1, 2)]
    assert flicker[1] / flicker[0] > 0.95  # the floor: more data barely lowers it


@pytest.mark.parametrize("latitude", [0.0, -33.9, 70.0])
def test_yaw_sigma_grows_as_one_over_cos_latitude(noise_plan, latitude):
    """Yaw comes from the horizontal Earth rate Omega_E cos(lat); nothing else in the campaign's
    information depends on latitude."""
    other = planner.plan("thesis", Site(latitude, g0=SITE.g0), STIM300, options=PERFECT)
    expected = noise_plan.sigmas["yaw"] * math.cos(math.radians(SITE.latitude_deg)) / math.cos(math.radians(latitude))
    assert other.sigmas["yaw"] == pytest.approx(expected, rel=1e-4)


@pytest.mark.slow
def test_time_to_target_is_the_shortest_meeting_it():
    target = 2.5 * DEG  # the nominal index campaign gives 1.87 deg: shorter statics do
    reach = planner.time_to_target("index", SITE, STIM300, target)
    got, short = reach.reached, reach.short_of_it
    assert got.sigmas["yaw"] <= target < short.sigmas["yaw"]
    assert got.duration_s - short.duration_s <= planner.TIME_TOLERANCE * got.duration_s
    again = planner.plan("index", SITE, STIM300, planner.scale_for_duration("index", 0.99 * got.duration_s))
    assert again.sigmas["yaw"] > target  # a session 1 % shorter does not make it, recomputed
    assert got.duration_s < planner.duration_s("index", 1.0)


@pytest.mark.slow
def test_whole_turns_are_searched_one_revolution_apart():
    target = 2.0 * DEG  # the nominal continuous campaign (ten turns) gives 2.17 deg
    reach = planner.time_to_target("continuous", SITE, STIM300, target)
    got, short = reach.reached, reach.short_of_it
    assert got.sigmas["yaw"] <= target < short.sigmas["yaw"]
    assert abs(got.segments[1].angle_deg) - abs(short.segments[1].angle_deg) == 360
    assert abs(got.segments[1].angle_deg) % 360 == 90  # the last static a quarter turn from the first


@pytest.mark.slow
def test_a_target_below_the_flicker_floor_is_not_reachable():
    reach = planner.time_to_target("index", SITE, STIM300, 0.8 * DEG, max_session_s=1800)
    longest = reach.short_of_it
    assert reach.reached is None and 1750 < longest.duration_s <= 1800
    assert 0.8 * DEG < longest.floor_yaw() < longest.sigmas["yaw"]


def test_continuous_campaign_ends_a_quarter_turn_on():
    """Statics at one platform angle cannot separate the accelerometer tilt from the biases: the
    continuous scenario, and the planner's scaled versions of it, end a quarter turn on."""
    assert load_scenario("continuous").segments[1].angle_deg == 3690
    assert planner.campaign_segments("continuous", 1.0)[1].angle_deg == 3690
    assert planner.campaign_segments("continuous", 2.0)[1].angle_deg == 20 * 360 + 90


def noise_file(tmp_path, drop=None, **change) -> Path:
    figures = {"gyro": ({"value": 0.15, "unit": "deg/sqrt(h)"}, {"value": 0.3, "unit": "deg/h"}),
               "acc": ({"value": 0.024, "unit": "m/s/sqrt(h)"}, {"value": 0.005, "unit": "mg"}),
               "incl": ({"value": 0.08, "unit": "m/s/sqrt(h)"}, {"value": 0.06, "unit": "mg"})}
    channels = {f"{sensor}_{axis}": {"random_walk": dict(walk), "bias_instability": dict(instability)}
                for sensor, (walk, instability) in figures.items() for axis in "xyz"}
    for key, value in change.items():
        channel, figure, field = key.split("__")
        channels[channel][figure][field] = value
    channels.pop(drop, None)
    path = tmp_path / "noise.json"
    path.write_text(json.dumps({"schema": "calibd.noise/1", "channels": channels}))
    return path


def test_noise_file_axes_are_pooled_as_the_estimator_pools_them(tmp_path):
    path = noise_file(tmp_path, gyro_x__random_walk__value=0.1, gyro_y__random_walk__value=0.2)
    figures = planner.noise_from_json(path.read_bytes(), str(path))
    assert figures.gyro_arw_deg_sqrt_h == pytest.approx(math.sqrt((0.1**2 + 0.2**2 + 0.15**2) / 3))
    others = {name: value for name, value in vars(figures).items() if name != "gyro_arw_deg_sqrt_h"}
    assert others == pytest.approx({name: vars(STIM300)[name] for name in others})


def test_a_noise_file_gives_the_inclinometers_figure_at_0_g_from_x_and_y(tmp_path):
    """A capture's statics have the inclinometer Z axis along gravity, 35 % noisier: the plan
    adds that itself, so the file's figure is that of X and Y."""
    path = noise_file(tmp_path, incl_z__random_walk__value=0.108, incl_z__bias_instability__value=0.081)
    figures = planner.noise_from_json(path.read_bytes(), str(path))
    assert (figures.incl_vrw_m_s_sqrt_h, figures.incl_bias_instability_mg) == pytest.approx((0.08, 0.06))


@pytest.mark.slow
def test_plan_command_prints_every_sigma_and_the_time(tmp_path, run_main):
    argv = ["plan", "--latitude", "40.59129", "--g0", "9.79956", "--campaign", "index", "--target-yaw-deg", "2.5"]
    code, out, err = run_main(calibd_main, argv)
    assert code == 0, err
    for name, unit in (("yaw", "deg"), ("gyro_bias_y", "deg/h"), ("acc_bias_z", "mg"), ("incl_bias_x", "mg")):
        assert re.search(rf"^  {name} +[0-9.e-]+ {re.escape(unit)} +\([0-9.e-]+ {re.escape(unit)}\)$", out, re.M), name
    assert "nominal: 18.4 min of data: static 10.0 min, 4 x (turn -90 deg at 20 deg/s, static 2.0 min)" in out
    assert re.search(r"time to a yaw 1-sigma of 2.5 deg \(static durations scaled, turns kept\):\n"
                     r"  [0-9.]+ min of data: static [0-9.]+ min, 4 x", out)
    assert run_main(calibd_main, [*argv, "--noise", noise_file(tmp_path)])[1] == out  # the file's figures: the defaults


@pytest.mark.parametrize("argv,message", [
    (["--campaign", "carousel"], "unknown campaign 'carousel'"),
    (["--campaign", "thesis", "--latitude", "90"], "latitude 90 deg: the horizontal Earth rate"),
    (["--campaign", "thesis", "--noise", "missing.json"], "missing.json: no such file"),
    (["--campaign", "thesis", "--noise", "NOISE", "--arw", "0.2"], "not both"),
    (["--campaign", "thesis", "--arw", "-1"], "outside"),
])
def test_plan_command_errors_are_one_line(argv, message, tmp_path, run_main, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("NOISE").write_text("{}")
    code, _, err = run_main(calibd_main, ["plan", "--latitude", "40", *argv])
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def test_campaign_is_also_taken_by_its_former_name_protocol(run_main):
    from calibd.cli import build_parser

    for option in ("--campaign", "--protocol"):
        assert build_parser().parse_args(["plan", "--latitude", "40", option, "index"]).campaign == "index"
        code, _, err = run_main(calibd_main, ["plan", "--latitude", "40", option, "carousel"])
        assert code == 2 and "unknown campaign 'carousel'" in err, err
    plan_help = build_parser()._subparsers._group_actions[0].choices["plan"].format_help()
    assert "--campaign" in plan_help and "--protocol" not in plan_help


@pytest.mark.parametrize("content,message", [
    ("not json", "noise.json: not a JSON noise file"),
    ({"schema": "calibd.result/1"}, "noise.json: schema is 'calibd.result/1', not a calibd.noise file"),
    ({"schema": "calibd.noise/2"}, "noise.json: schema is calibd.noise/2, newer than this calibd reads (up to 1)"),
    ([1, 2], "noise.json: not a JSON object, expected a calibd.noise file"),
    ({"schema": "calibd.noise/1"}, "noise.json: channels is missing"),
    ("drop:gyro_y", "noise.json: channels.gyro_y is missing"),
    ("drop:incl_y", "noise.json: channels.incl_y is missing (a unit with inclinometers has all three)"),
    ("acc_z__bias_instability__unit=ug", "noise.json: channels.acc_z.bias_instability.unit is 'ug', expected 'mg'"),
    ("incl_x__random_walk__value=None",
     "noise.json: channels.incl_x.random_walk.value is null, expected a number in [0, 1000]"),
    ("gyro_x__random_walk__value=1e308",
     "noise.json: channels.gyro_x.random_walk.value is 1e+308, expected a number in [0, 1000]"),
])
def test_bad_noise_files_are_one_line(content, message, tmp_path, run_main):
    if isinstance(content, (dict, list)) or content == "not json":
        path = tmp_path / "noise.json"
        path.write_text(content if isinstance(content, str) else json.dumps(content))
    elif content.startswith("drop:"):
        path = noise_file(tmp_path, drop=content[5:])
    else:
        key, value = content.split("=")
        value = None if value == "None" else float(value) if value[0].isdigit() else value
        path = noise_file(tmp_path, **{key: value})
    code, _, err = run_main(calibd_main, ["plan", "--latitude", "40", "--campaign", "thesis", "--noise", path])
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


def scenario_file(tmp_path, source="thesis-real", name="mine.toml", **replacements) -> Path:
    """A ready-made scenario's TOML copied to a file, each `old=new` text replaced."""
    text = (Path(planner.__file__).parent / "scenarios" / f"{source}.toml").read_text()
    for old, new in replacements.values():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_scenario_equal_to_a_builtin_campaign_plans_the_same(tmp_path, thesis_plan):
    """The planner reads a scenario's steps as the built-in campaigns' are read: a copy of the
    thesis-real scenario is the thesis campaign, of the continuous one the continuous campaign
    (its whole turns scale)."""
    path = scenario_file(tmp_path)
    mine = planner.campaign_from_scenario(load_scenario(str(path)), str(path))
    assert mine.scales == planner.STATICS and mine.figures == STIM300
    assert planner.plan(mine, SITE, mine.figures).sigmas == thesis_plan.sigmas
    carousel = planner.campaign_from_scenario(load_scenario(str(scenario_file(tmp_path, "continuous"))), "carousel")
    assert carousel.scales == planner.TURNS
    for scale in (0.5, 1.0, 3.0):
        assert planner.campaign_segments(carousel, scale) == planner.campaign_segments("continuous", scale)
    assert planner.duration_s(carousel, 3.0) == planner.duration_s("continuous", 3.0)


@pytest.mark.slow
def test_plan_command_takes_a_scenario_file(tmp_path, run_main):
    """`calibd plan --scenario` prints what `--campaign` prints for the same steps (its site from
    the scenario's [site]); only the name differs."""
    path = scenario_file(tmp_path, index=("duration_s = 120\n\n[[segments]]\ntype = \"turn\"\nangle_deg = -360",
                                          "duration_s = 120\n\n[[segments]]\ntype = \"turn\"\nangle_deg = -90"))
    index = ["plan", "--latitude", "40.59129", "--g0", "9.79956", "--campaign", "index", "--target-yaw-deg", "2.5"]
    code, builtin, err = run_main(calibd_main, index)
    assert code == 0, err
    text = path.read_text().split("[[segments]]")
    path.write_text("[[segments]]".join(text[:10]))  # level static, four index turns and statics: the index campaign
    code, out, err = run_main(calibd_main, ["plan", "--scenario", path, "--target-yaw-deg", "2.5"])
    assert code == 0, err
    assert out.splitlines()[0] == f"{path} campaign at latitude 40.5913 deg, g0 9.79956 m/s^2"
    assert out.splitlines()[1:] == builtin.splitlines()[1:]


def test_longer_statics_in_a_scenario_give_smaller_sigmas(tmp_path, noise_plan, thesis_plan):
    """The noise's part falls with more data; the factory residuals' share barely (only as far as
    the statics' forces see them better)."""
    path = scenario_file(tmp_path, level=("duration_s = 600\n", "duration_s = 1200\n"),
                         index=("duration_s = 120\n", "duration_s = 240\n"))
    campaign = planner.campaign_from_scenario(load_scenario(str(path)), "longer")
    longer = planner.plan(campaign, SITE, STIM300, options=PERFECT)
    assert longer.duration_s == pytest.approx(noise_plan.duration_s + 600 + 4 * 120)
    for name, sigma in noise_plan.sigmas.items():  # flicker keeps most of them far from 1 / sqrt(2)
        assert longer.sigmas[name] < (0.92 if name == "yaw" or name.startswith("gyro") else 1.0) * sigma, name
    with_prior = planner.plan(campaign, SITE, STIM300)  # the statics see the residuals a little better
    assert 0.9 * thesis_plan.factory["alpha"] < with_prior.factory["alpha"] <= thesis_plan.factory["alpha"]
    assert 0.9 * thesis_plan.sigmas["alpha"] < with_prior.sigmas["alpha"] <= thesis_plan.sigmas["alpha"]



def test_the_plan_names_the_factory_terms_a_tilted_axis_estimates(thesis_plan):
    """The thesis's axis, 0.64 deg from Up, leaves every factory term at more than half its
    prior (the gyro Z scale factor at about 150 of 250 ppm): none estimated. 5.8 deg from Up the
    statics' forces see the angle that scale factor adds to every turn: it is estimated, and
    the report says to what."""
    tilted = replace(THESIS, truth=replace(THESIS.truth, pitch_deg=5.0, roll_deg=3.0))
    plan = planner.plan(planner.campaign_from_scenario(tilted, "tilted"), SITE, STIM300)
    assert thesis_plan.estimated_terms == {}
    assert list(plan.estimated_terms) == ["gyro_scale_z"]
    sigma, prior = plan.estimated_terms["gyro_scale_z"]
    assert prior == pytest.approx(250) and 15 < sigma < 35
    lines = planner.report(planner.Reach(DEG, plan, plan, None), STIM300).splitlines()
    assert f"gyro_scale_z {sigma:.3g} ppm (prior 250 ppm)" in next(line for line in lines if "factory terms" in line)
    nominal = planner.report(planner.Reach(DEG, thesis_plan, thesis_plan, None), STIM300)
    assert "factory terms the campaign estimates (sigma at most half the prior's): none" in nominal

@pytest.mark.slow
def test_a_scenario_gives_the_plan_its_site_noise_and_sensor(tmp_path, run_main):
    """The scenario's [site] and [noise] are the plan's unless options replace them; a unit
    without inclinometers (datagram 0x91) is planned without them."""
    path = scenario_file(tmp_path, site=("latitude_deg = 40.59129", "latitude_deg = -33.9"),
                         noise=("[warmup]", "[noise]\ngyro_arw_deg_sqrt_h = 0.3\n\n[warmup]"),
                         datagram=('datagram = "0xA7"', 'datagram = "0x91"'))
    argv = ["plan", "--scenario", path, "--target-yaw-deg", "5"]
    code, out, err = run_main(calibd_main, argv)
    assert code == 0, err
    assert "at latitude -33.9 deg, g0 9.79956 m/s^2" in out
    assert "noise: gyro 0.3 deg/sqrt(h), 0.3 deg/h; acc 0.024 m/s/sqrt(h), 0.005 mg; no inclinometers" in out
    assert "incl_bias" not in out and re.search(r"^  pitch +[0-9.e-]+ deg +\([0-9.e-]+ deg\)$", out, re.M)
    code, out, err = run_main(calibd_main, argv + ["--latitude", "10", "--arw", "0.2"])
    assert code == 0, err
    assert "at latitude 10 deg" in out and "noise: gyro 0.2 deg/sqrt(h)" in out


@pytest.mark.parametrize("segments,message", [
    ('[[segments]]\ntype = "static"\nduration_s = 300\n', "no turn: yaw and the interface tilt need the platform"),
    ('[[segments]]\ntype = "turn"\nangle_deg = 90\npeak_rate_deg_s = 20\naccel_deg_s2 = 20\n'
     '[[segments]]\ntype = "static"\nduration_s = 60\n', "[[segments]] #1: the campaign must start with a static"),
    ('[[segments]]\ntype = "static"\nduration_s = 300\n[[segments]]\ntype = "turn"\nangle_deg = 360\n'
     'peak_rate_deg_s = 20\naccel_deg_s2 = 20\n[[segments]]\ntype = "static"\nduration_s = 60\n',
     "the statics cover too few platform angles"),
    ('[[segments]]\ntype = "position"\nup = "-Z"\nduration_s = 60\n', "#1: a position segment re-mounts the IMU"),
    ('[[segments]]\ntype = "static"\nduration_s = -1\n', "[[segments]] #1 duration_s: -1.0 is not a duration in (0, "),
    ('[[segments]]\ntype = "static"\nduration_s = 300\n[[segments]]\ntype = "turn"\nangle_deg = 1e308\n'
     'peak_rate_deg_s = 20\naccel_deg_s2 = 20\n', "[[segments]] #2 angle_deg: 1e+308 is not a non-zero angle within"),
    ('[[segments]]\ntype = "static"\nduration_s = 300\n[[segments]]\ntype = "turn"\nangle_deg = 1e9\n'
     'peak_rate_deg_s = 20\naccel_deg_s2 = 20\n', "s at 125 Hz is more than the simulator's 10,000,000 samples"),
    ("[[segments]\n", "not valid TOML"),
])
def test_bad_scenario_files_are_one_line(segments, message, tmp_path, run_main):
    path = tmp_path / "mine.toml"
    path.write_text(f"[site]\nlatitude_deg = 45\n{segments}")
    code, _, err = run_main(calibd_main, ["plan", "--scenario", path])
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"calibd: {path}") and "Traceback" not in err


@pytest.mark.parametrize("argv,message", [
    (["--scenario", "missing.toml"], "missing.toml: no such scenario file"),
    (["--scenario", "thesis-real", "--campaign", "thesis"], "not allowed with argument --scenario"),
    (["--latitude", "40"], "one of the arguments --campaign --scenario is required"),
    (["--campaign", "thesis"], "--latitude is needed with --campaign"),
    (["--scenario", "thesis-real", "--g0", "9.8"], "--latitude is needed with --campaign, --height or --g0"),
])
def test_plan_command_scenario_usage_errors(argv, message, tmp_path, run_main, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_main(calibd_main, ["plan", *argv])
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err


INDEXED = JointOptions(index_step=90 * DEG, index_sigma=0.01 * DEG)


def test_an_indexing_table_estimates_the_gyro_z_scale_factor_and_lowers_yaws_factory_share(thesis_plan):
    """With the statics at 90 deg stops the turns show the gyro Z scale factor on the thesis's
    near-vertical axis (about 30 ppm against 250), and the statics' angles no longer carry it:
    yaw's factory share falls by a third; what the stops cannot see stays."""
    indexed = planner.plan("thesis", SITE, STIM300, options=INDEXED)
    sigma, prior = indexed.estimated_terms["gyro_scale_z"]
    assert 20 < sigma < 40 and prior == pytest.approx(250)
    assert indexed.factory["yaw"] < 0.8 * thesis_plan.factory["yaw"]
    assert indexed.sigmas["alpha"] == pytest.approx(thesis_plan.sigmas["alpha"], rel=0.02)
    assert "statics at an indexing table's stops every 90 deg (1-sigma 0.01 deg)" in planner.report(
        planner.Reach(DEG, indexed, indexed, None), STIM300).splitlines()[0]


@pytest.mark.slow
def test_continuous_rotation_ending_at_a_stop_reaches_a_degree_of_yaw(run_main):
    """Without stops the gyro Z scale factor's prior turns every later angle and leaves a floor
    near 9 deg; a final static at a known stop pins it, and a degree is reached in minutes."""
    code, out, err = run_main(calibd_main, ["plan", "--latitude", "40.59129", "--campaign", "continuous",
                                            "--index-step", "90"])
    assert code == 0, err
    reached = out.splitlines()[-1]
    assert re.fullmatch(r"  \(yaw 1-sigma 0\.99\d+ deg; .*\)", reached), out


def test_plan_refuses_statics_off_the_index_steps_stops_and_a_sigma_without_a_step(run_main):
    code, out, err = run_main(calibd_main, ["plan", "--latitude", "40", "--campaign", "thesis", "--index-step", "60"])
    assert code == 2 and err.count("\n") == 1 and "thesis: static 2 of the fit sits at -90.00 deg" in err, err
    code, out, err = run_main(calibd_main, ["plan", "--latitude", "40", "--campaign", "thesis", "--index-sigma", "0.1"])
    assert code == 2 and "give --index-step too" in err


def test_a_second_mounting_takes_the_gyro_misalignment_out_of_the_angles(thesis_plan):
    """Planned on the unit turned 180 deg about its Z axis too, the two tilts estimate the gyro
    triad's E_xz and E_yz: pitch, roll, alpha and beta fall from the 0.5 mrad prior's 0.026 deg
    to the noise's 0.001 deg; the horizontal biases lose the gyro triad's share (g0 E_g), not
    the force triad's own; yaw keeps its sigma; a looser fixture costs the angles across the tilt."""
    both = planner.plan("thesis", SITE, STIM300, remount_sigma=0.1 * DEG)
    for name in ("pitch", "roll", "alpha", "beta"):
        assert both.sigmas[name] < 0.06 * thesis_plan.sigmas[name]
    assert {"gyro_misalignment_xz", "gyro_misalignment_yz"} <= set(both.estimated_terms)
    assert both.sigmas["yaw"] == pytest.approx(thesis_plan.sigmas["yaw"], rel=0.02)
    mg = STANDARD_GRAVITY / 1000
    assert both.sigmas["acc_bias_x"] == pytest.approx(0.5 * mg, rel=0.02)
    assert both.sigmas["acc_bias_x"] < 0.8 * thesis_plan.sigmas["acc_bias_x"]
    loose = planner.plan("thesis", SITE, STIM300, remount_sigma=0.5 * DEG)
    assert loose.sigmas["beta"] > 2 * both.sigmas["beta"]
    assert "run again on a second mounting (the housing turned 180 deg about its Z axis, 1-sigma 0.1 deg)" in \
        planner.report(planner.Reach(DEG, both, both, None), STIM300).splitlines()[0]


def test_plan_refuses_a_remount_sigma_without_a_second_mounting(run_main):
    code, out, err = run_main(calibd_main, ["plan", "--latitude", "40", "--campaign", "thesis", "--remount-sigma",
                                            "0.2"])
    assert code == 2 and err.count("\n") == 1 and "plan: --remount-sigma is the second mounting's 1-sigma" in err

"""Campaign planner: the 1-sigma every joint estimate will have for a campaign, a site and a noise
model, and the data time a target yaw 1-sigma needs.

The sigmas come from the joint estimator itself, not from a formula beside it: the campaign's
session is simulated without noise (`calibd.sim`, the scenario machinery), block-averaged to
PLAN_RATE_HZ, and solved by `estimators.joint.solve` with the noise model it would fit to the
residuals replaced by the given figures (white + flicker per sensor). Its design, its white +
flicker covariance and the Jacobian of its chain then give every sigma. For a given noise density
the sigmas do not depend on the sample rate (white variance per sample = density^2 x rate; flicker
is binned at 0.1 s), so planning at 5 Hz gives the 125 Hz sigmas to 1e-4 at a tenth of the cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from stim300.protocol import NORMAL_LAYOUTS

from .methods.joint import checked_by_statics
from . import spec
from .documents import NoiseDoc, SchemaError, decode_json, schema_version, validate
from .errors import CalibdError, CalibrationError
from .estimators.joint import (JointInput, JointOptions, JointResult, SensorNoise, Underdetermined, datasheet_noise,
                               solve)
from .estimators.remount import two_mountings
from .frames import STANDARD_GRAVITY, Site
from .noise import NOISE_SCHEMA, NOISE_VERSION
from .results import ESTIMATES
from .scenario import Faults, Noise, Scenario, ScenarioError, Segment, Sensor, load_scenario
from .sim import remounted, schedule, simulate
from .units import DEG

MG = STANDARD_GRAVITY / 1000
CAMPAIGNS = ("thesis", "continuous", "index")
STATICS, TURNS = "statics", "turns"  # what a campaign scales to reach a target
WHAT_SCALES = {STATICS: "static durations scaled, turns kept", TURNS: "number of whole turns scaled, statics kept"}
CAROUSEL_DEG = 720.0  # a turn of two revolutions or more is continuous rotation: its whole turns scale
PLAN_RATE_HZ = 5  # the sigmas match 125 Hz to 1e-4 (see the module docstring)
MAX_SESSION_S = 7200.0  # beyond hours, flicker slower than the model's slowest component (30000 s) matters
MIN_SCALE = 0.1  # shortest layout searched: a tenth of the nominal statics (1 min level static), or one turn
TIME_TOLERANCE = 0.01  # the time to a target is found to 1 % of itself
MIN_COS_LATITUDE = 0.01  # nearer the poles the horizontal Earth rate that yaw comes from vanishes
NOISE_FILE_FIGURES = {  # sensor -> (random walk field, its unit, bias instability field, its unit)
    "gyro": ("gyro_arw_deg_sqrt_h", "deg/sqrt(h)", "gyro_bias_instability_deg_h", "deg/h"),
    "acc": ("acc_vrw_m_s_sqrt_h", "m/s/sqrt(h)", "acc_bias_instability_mg", "mg"),
    "incl": ("incl_vrw_m_s_sqrt_h", "m/s/sqrt(h)", "incl_bias_instability_mg", "mg"),
}


class PlanError(CalibdError):
    """Input the planner cannot use; the message says what and where in one line."""


# ---------------------------------------------------------------- campaigns

@dataclass(frozen=True)
class Campaign:
    """What is planned: a scenario's steps (statics and turns in order, the first the level
    static) with its truth and site, and which part scales with the data time. The planner
    simulates it without noise, warm-up or faults at 125 Hz: for given noise densities the
    sigmas depend on neither the sensor's rate nor its datagram, only on whether it has
    inclinometers."""

    name: str
    scenario: Scenario
    scales: str  # STATICS or TURNS
    figures: Noise  # the scenario's noise figures: the default noise of the plan
    inclinometers: bool


def campaign_from_scenario(scenario: Scenario, name: str) -> Campaign:
    """The campaign a scenario's steps make; PlanError when the joint estimator cannot plan them
    (a bench re-mount, no level static first, no turn). Turns of two revolutions or more make it
    a continuous-rotation campaign, whose whole turns scale; otherwise its statics scale."""
    segments = scenario.segments
    for number, segment in enumerate(segments, 1):
        if segment.kind == "position":
            raise PlanError(f"{name}: [[segments]] #{number}: a position segment re-mounts the IMU; the planner "
                            f"plans the joint estimator on a mounted IMU (statics and turns)")
    if segments[0].kind != "static":
        raise PlanError(f"{name}: [[segments]] #1: the campaign must start with a static (the level static)")
    if not any(s.kind == "turn" for s in segments):
        raise PlanError(f"{name}: no turn: yaw and the interface tilt need the platform to turn")
    carousel = any(s.kind == "turn" and abs(s.angle_deg) >= CAROUSEL_DEG for s in segments)
    quiet = replace(scenario, sensor=Sensor(), noise=replace(scenario.noise, enabled=False),
                    warmup=replace(scenario.warmup, power_on_s=1e9), faults=Faults())
    inclinometers = "incl" in NORMAL_LAYOUTS[scenario.sensor.datagram_id].clusters
    figures = scenario.noise if inclinometers else \
        replace(scenario.noise, incl_vrw_m_s_sqrt_h=None, incl_bias_instability_mg=None)
    return Campaign(name, quiet, TURNS if carousel else STATICS, figures, inclinometers)


def builtin_campaign(name: str) -> Campaign:
    """thesis: the thesis-real scenario (10 min level static, four -90 deg index turns each
    followed by 2 min static, a full turn of -360 deg, 30 s static). index: the same without the
    full turn and its static. continuous: the continuous scenario (2 min static, ten and a
    quarter turns at 10 deg/s, 1 min static: the last static 90 deg from the first, as the
    estimator separates the accelerometer tilt from the biases only with statics at platform
    angles apart)."""
    if name not in CAMPAIGNS:
        raise PlanError(f"unknown campaign {name!r} (known: {', '.join(CAMPAIGNS)})")
    scenario = load_scenario("continuous" if name == "continuous" else "thesis-real")
    if name == "index":
        scenario = replace(scenario, segments=scenario.segments[:9])
    return campaign_from_scenario(scenario, name)


def _campaign(campaign: Campaign | str) -> Campaign:
    return campaign if isinstance(campaign, Campaign) else builtin_campaign(campaign)


def _whole_turns(segment: Segment, scale: float) -> Segment:
    """A continuous-rotation turn with its number of whole turns times `scale` (at least one), the
    part of a revolution beyond them kept (so the last static stays where it was)."""
    whole = abs(segment.angle_deg) // 360
    turns = max(1, round(whole * scale))
    return replace(segment, angle_deg=math.copysign(360 * turns + abs(segment.angle_deg) - 360 * whole,
                                                     segment.angle_deg))


def campaign_segments(campaign: Campaign | str, scale: float) -> tuple[Segment, ...]:
    """The campaign's segments with its scalable part times `scale` (1 = nominal): every static's
    duration, or the whole turns of its continuous-rotation turns."""
    campaign = _campaign(campaign)
    if campaign.scales == TURNS:
        return tuple(_whole_turns(s, scale) if s.kind == "turn" and abs(s.angle_deg) >= CAROUSEL_DEG else s
                     for s in campaign.scenario.segments)
    return tuple(replace(s, duration_s=s.duration_s * scale) if s.kind == "static" else s
                 for s in campaign.scenario.segments)


def _scenario(campaign: Campaign, scale: float, site: Site, turned: bool = False):
    """The campaign's scenario, scaled, without noise, warm-up or temperature drift, at `site`;
    `turned`: on the unit's second mounting (`sim.remounted`)."""
    scenario = replace(campaign.scenario, site=site, segments=campaign_segments(campaign, scale))
    return replace(scenario, truth=remounted(scenario.truth)) if turned else scenario


def duration_s(campaign: Campaign | str, scale: float) -> float:
    """Data time of the scaled campaign, from the level static to the end (no simulation)."""
    return schedule(_scenario(_campaign(campaign), scale, Site(0.0)))[-1].end_s


def _resolution_s(campaign: Campaign) -> float:
    """The step the campaign's data time takes as its scale changes, at most: one revolution of
    each continuous-rotation turn for whole turns; statics scale continuously."""
    if campaign.scales != TURNS:
        return 0.0
    return sum(360.0 / s.peak_rate_deg_s for s in campaign.scenario.segments
               if s.kind == "turn" and abs(s.angle_deg) >= CAROUSEL_DEG)


def describe(segments: tuple[Segment, ...]) -> str:
    """The layout in words, repeated (turn, static) pairs counted: 'static 10.0 min,
    4 x (turn -90 deg, static 2.0 min), ...'."""
    def one(s: Segment) -> str:
        if s.kind == "static":
            return f"static {s.duration_s / 60:.1f} min"
        turns = f" ({abs(s.angle_deg) / 360:g} turns)" if abs(s.angle_deg) >= 720 else ""
        return f"turn {s.angle_deg:+g} deg{turns} at {s.peak_rate_deg_s:g} deg/s"

    parts, i = [], 0
    while i < len(segments):
        pair = segments[i:i + 2]
        repeats = 1
        while len(pair) == 2 and segments[i + 2 * repeats:i + 2 * repeats + 2] == pair:
            repeats += 1
        if repeats > 1:
            parts.append(f"{repeats} x ({one(pair[0])}, {one(pair[1])})")
            i += 2 * repeats
        else:
            parts.append(one(segments[i]))
            i += 1
    return ", ".join(parts)


# ---------------------------------------------------------------- noise

def noise_from_json(data: bytes, where: str) -> Noise:
    """Figures from a `calibd.noise/1` file (written by `calibd noise`; its schema is
    calibd.documents.NoiseDoc): one per sensor, the root mean square of the three axes' (the
    estimator fits each channel's own; a plan takes a sensor's axes alike), but the inclinometers'
    of X and Y alone: the plan takes their figure at 0 g and makes the axis along gravity noisier
    itself, and a capture's statics have Z along gravity. A file without inclinometer channels is
    a unit's without inclinometers: its figures have none (None)."""
    doc = decode_json(data, where, NoiseDoc, PlanError, noun="a JSON noise file")
    if not isinstance(doc, dict):
        raise PlanError(f"{where}: not a JSON object, expected a {NOISE_SCHEMA} file")
    try:  # the version policy of result and truth files
        schema_version(doc.get("schema"), NOISE_SCHEMA, NOISE_VERSION, f"{where}: schema")
    except SchemaError as exc:
        raise PlanError(str(exc)) from None
    channels = validate(doc, NoiseDoc, where, PlanError).channels
    figures = {}
    for sensor, (walk_field, walk_unit, instability_field, instability_unit) in NOISE_FILE_FIGURES.items():
        axes = {axis: getattr(channels, f"{sensor}_{axis}") for axis in "xyz"}
        if sensor == "incl" and not any(axes.values()):
            figures[walk_field] = figures[instability_field] = None
            continue
        for name, field, unit in (("random_walk", walk_field, walk_unit),
                                  ("bias_instability", instability_field, instability_unit)):
            values = [_figure(axes, sensor, axis, name, unit, where) for axis in ("xy" if sensor == "incl" else "xyz")]
            figures[field] = math.sqrt(sum(v * v for v in values) / len(values))
    return Noise(**figures)


def _figure(axes: dict, sensor: str, axis: str, name: str, unit: str, where: str) -> float:
    """One axis's figure, in the unit the plan takes it in (its range the schema's)."""
    if axes[axis] is None:
        raise PlanError(f"{where}: channels.{sensor}_{axis} is missing (a unit with inclinometers has all three)")
    figure = getattr(axes[axis], name)
    if figure.unit != unit:
        raise PlanError(f"{where}: channels.{sensor}_{axis}.{name}.unit is {figure.unit!r}, expected {unit!r}")
    return float(figure.value)


# ---------------------------------------------------------------- the plan

@dataclass
class Plan:
    campaign: Campaign
    scale: float
    segments: tuple[Segment, ...]
    duration_s: float
    sigmas: dict[str, float]  # SI (rad, rad/s, m/s^2), 1-sigma of every joint estimate
    factory: dict[str, float]  # SI, the part of each sigma the factory residuals' prior makes (none: 0)
    estimated_terms: dict[str, tuple[float, float]]  # factory terms the campaign estimates: (sigma, prior
    # sigma) in the term's unit (ppm, mrad)
    site: Site
    session: JointInput  # the noise-free session the sigmas come from, at PLAN_RATE_HZ
    noise: SensorNoise
    options: JointOptions = JointOptions()  # as solved (an index step: each static at its stop)
    remount_sigma: float | None = None  # rad: with a second mounting, its fixture's turn 1-sigma; None: one

    def floor_yaw(self) -> float:
        """The yaw 1-sigma bias instability and the factory residuals' prior leave (white noise
        removed), rad: the floor that more data of this layout barely lowers (and more turns of
        continuous rotation raise: the gyro Z scale factor turns every later angle). A second
        mounting leaves yaw as it is: the first mounting's alone gives it."""
        noise = self.noise
        flicker = SensorNoise(*(m and replace(m, white=0.0) for m in (noise.gyro, noise.acc, noise.incl)))
        result = solve(self.session, self.site, self.options, noise=flicker)
        return checked_by_statics(self.session, result, self.site, self.options, flicker).sigmas["yaw"]


def _session(campaign: Campaign, scale: float, site: Site, inclinometers: bool,
             turned: bool = False) -> tuple[JointInput, float]:
    """The scaled campaign's noise-free session as the joint estimator takes it, block-averaged
    to PLAN_RATE_HZ (averages of interval averages: the model stays exact); statics are the
    whole blocks inside the scheduled static segments. Without `inclinometers` the session is a
    gyro + accelerometer unit's; `turned`: on the unit's second mounting."""
    sim = simulate(_scenario(campaign, scale, site, turned))
    rate = sim.scenario.sensor.sample_rate_hz
    block = max(1, round(rate / PLAN_RATE_HZ))
    n = len(sim.time_s) // block

    def averaged(values):
        return values[:n * block].reshape(n, block, 3).mean(axis=1)

    statics = tuple((math.ceil(p.start_s * rate / block), math.floor(p.end_s * rate / block))
                    for p in sim.phases if p.kind == "static")
    plan_rate = rate / block
    inp = JointInput(time_s=np.arange(n) / plan_rate, gyro=averaged(sim.exact["gyro"]) * DEG,
                     acc=averaged(sim.exact["acc"]) * STANDARD_GRAVITY,
                     incl=averaged(sim.exact["incl"]) * STANDARD_GRAVITY if inclinometers else None,
                     statics=tuple(s for s in statics if s[1] > s[0]), rate_hz=plan_rate)
    return inp, sim.phases[-1].end_s


def check_site(site: Site) -> None:
    """Yaw comes from the horizontal Earth rate, Omega_E cos(lat): refuse where it vanishes."""
    if math.cos(math.radians(site.latitude_deg)) < MIN_COS_LATITUDE:
        raise PlanError(f"latitude {site.latitude_deg:g} deg: the horizontal Earth rate yaw comes from is "
                        f"(nearly) zero there; the planner needs |latitude| <= "
                        f"{math.degrees(math.acos(MIN_COS_LATITUDE)):.1f} deg")


def plan(campaign: Campaign | str, site: Site, figures: Noise, scale: float = 1.0,
         options: JointOptions = JointOptions(), remount_sigma: float | None = None) -> Plan:
    """Every estimate's expected 1-sigma for the campaign at `scale`, from the joint estimator
    (with the factory residuals' prior unless `options` leaves it out); for a unit without
    inclinometers when the campaign's sensor or `figures` has none. The inclinometer figures
    are taken at 0 g and made larger on the axis along gravity, as the estimator takes them.
    `remount_sigma` (rad): the campaign run again on the unit's second mounting, the fixture's
    turn that exact (calibd.estimators.remount); None: one mounting."""
    check_site(site)
    campaign = _campaign(campaign)
    segments = campaign_segments(campaign, scale)
    inclinometers = campaign.inclinometers and figures.incl_vrw_m_s_sqrt_h is not None

    def solved(turned: bool) -> tuple[JointInput, float, SensorNoise, JointResult]:
        used = options.for_second_mounting() if turned else options
        try:
            inp, seconds = _session(campaign, scale, site, inclinometers, turned)
        except ScenarioError as exc:  # what only the simulation finds: a session too long to hold
            raise PlanError(f"{campaign.name}: {exc}") from None
        along = None if inp.incl is None else inp.incl[slice(*inp.statics[0])].mean(axis=0) / STANDARD_GRAVITY
        noise = datasheet_noise(figures if inclinometers else replace(
            figures, incl_vrw_m_s_sqrt_h=None, incl_bias_instability_mg=None), inp.rate_hz, along)
        try:
            result = solve(inp, site, used, noise=noise)
        except Underdetermined as exc:  # what the campaign lacks, said for the campaign
            raise PlanError(f"{campaign.name}: {exc}") from None
        try:  # as calibrate does: a tilted axis sees more
            return inp, seconds, noise, checked_by_statics(inp, result, site, used, noise)
        except CalibrationError as exc:  # statics not at the index step's stops
            raise PlanError(f"{campaign.name}: {exc}") from None

    inp, seconds, noise, result = solved(False)
    if remount_sigma is not None:
        result = two_mountings(result, solved(True)[3], remount_sigma)[0]
    factory = {name: parts.get("factory_residuals", 0.0) for name, parts in result.sigma_budget().items()}
    return Plan(campaign, scale, segments, seconds, result.sigmas, factory, estimated_terms(result), site, inp, noise,
                options, remount_sigma)


def estimated_terms(result: JointResult) -> dict[str, tuple[float, float]]:
    """The factory terms whose sigma the statics' forces (and an indexing table's turns) bring to
    half the prior's or less (as a calibration reports them "estimated"): name -> (sigma, prior
    sigma), in the term's unit."""
    factory = result.factory
    if factory is None or factory.posterior is None:
        return {}
    cov = factory.posterior.cov
    return {term.name: (math.sqrt(cov[k, k]) * term.sigma_in_unit, term.sigma_in_unit)
            for k, term in enumerate(factory.terms) if factory.posterior.estimated(k)}


@dataclass
class Reach:
    """The search for a target yaw 1-sigma: the nominal layout it starts from, the shortest
    layout found to meet the target (None: not reachable within the longest session searched)
    and the longest found not to (None: the shortest layout searched meets it already)."""

    target_yaw: float  # rad
    nominal: Plan
    reached: Plan | None
    short_of_it: Plan | None


def scale_for_duration(campaign: Campaign | str, seconds: float) -> float:
    """The largest scale whose data time is at most `seconds` (bisection on the schedule)."""
    campaign = _campaign(campaign)
    lo, hi = MIN_SCALE, MIN_SCALE
    while duration_s(campaign, hi) <= seconds:
        lo, hi = hi, 2 * hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if duration_s(campaign, mid) <= seconds else (lo, mid)
    return lo


def time_to_target(campaign: Campaign | str, site: Site, figures: Noise, target_yaw: float,
                   max_session_s: float = MAX_SESSION_S, options: JointOptions = JointOptions(),
                   remount_sigma: float | None = None) -> Reach:
    """The shortest scaled campaign (WHAT_SCALES) whose yaw 1-sigma is at most `target_yaw` (rad).
    From the nominal layout the scale halves down to MIN_SCALE or doubles up to the longest
    layout within `max_session_s` until the target is bracketed, then bisection narrows the
    bracket to TIME_TOLERANCE of the data time (one revolution for whole turns; the data time is
    an increasing affine function of the scale). More data of the same layout never raises the
    sigma here, so the search is monotone. `options`, `remount_sigma`: as `plan` takes them."""
    campaign = _campaign(campaign)

    def planned(scale: float) -> Plan:
        return plan(campaign, site, figures, scale, options, remount_sigma)

    nominal = planned(1.0)
    longest_scale = scale_for_duration(campaign, max_session_s)
    if nominal.sigmas["yaw"] <= target_yaw:
        low, high = planned(MIN_SCALE), nominal
        if low.sigmas["yaw"] <= target_yaw:
            return Reach(target_yaw, nominal, low, None)
    else:
        low = nominal if nominal.scale <= longest_scale else planned(longest_scale)
        high = None
        while high is None and low.scale < longest_scale:
            longer = planned(min(2 * low.scale, longest_scale))
            low, high = (low, longer) if longer.sigmas["yaw"] <= target_yaw else (longer, None)
        if high is None:
            return Reach(target_yaw, nominal, None, low)
    step = _resolution_s(campaign)
    while high.duration_s - low.duration_s > max(TIME_TOLERANCE * high.duration_s, step * 1.001):
        mid = planned(0.5 * (low.scale + high.scale))
        low, high = (low, mid) if mid.sigmas["yaw"] <= target_yaw else (mid, high)
    return Reach(target_yaw, nominal, high, low)


# ---------------------------------------------------------------- the report

def _figures_text(figures: Noise, inclinometers: bool) -> str:
    incl = ("no inclinometers" if not inclinometers else
            f"incl {figures.incl_vrw_m_s_sqrt_h:.3g} m/s/sqrt(h), {figures.incl_bias_instability_mg:.3g} mg")
    return (f"gyro {figures.gyro_arw_deg_sqrt_h:.3g} deg/sqrt(h), {figures.gyro_bias_instability_deg_h:.3g} deg/h; "
            f"acc {figures.acc_vrw_m_s_sqrt_h:.3g} m/s/sqrt(h), {figures.acc_bias_instability_mg:.3g} mg; "
            f"{incl} (random walk, bias instability)")


def report(reach: Reach, figures: Noise) -> str:
    """What `calibd plan` prints: the nominal layout and its sigmas, then the time to the target."""
    nominal, site = reach.nominal, reach.nominal.site
    campaign = nominal.campaign
    index = nominal.options.index_step
    stops = "" if index is None else (f", statics at an indexing table's stops every {index / DEG:g} deg "
                                      f"(1-sigma {nominal.options.index_sigma / DEG:g} deg)")
    if nominal.remount_sigma is not None:
        stops += (f", run again on a second mounting (the housing turned 180 deg about its Z axis, 1-sigma "
                  f"{nominal.remount_sigma / DEG:g} deg)")
    if nominal.options.known_terms:
        stops += f", {len(nominal.options.known_terms)} factory terms known from {nominal.options.known_from}"
    lines = [f"{campaign.name} campaign at latitude {site.latitude_deg:g} deg, g0 {site.gravity:.5f} m/s^2{stops}",
             f"noise: {_figures_text(figures, nominal.session.incl is not None)}",
             f"nominal: {nominal.duration_s / 60:.1f} min of data: {describe(nominal.segments)}",
             "expected 1-sigma of the joint estimates (of it, the factory residuals' prior: what more data "
             "cannot lower):"]
    for name, sigma in nominal.sigmas.items():
        factor, unit = ESTIMATES[name]
        lines.append(f"  {name:12s} {sigma * factor:10.3g} {unit:6s} ({nominal.factory[name] * factor:.3g} {unit})")
    terms = nominal.estimated_terms
    lines.append("factory terms the campaign estimates (sigma at most half the prior's): " + (
        ", ".join(f"{name} {sigma:.3g} {unit} (prior {prior:.3g} {unit})" for name, (sigma, prior), unit in
                  ((name, value, spec.FactoryTerm.named(name).unit) for name, value in terms.items()))
        if terms else "none (a tilted platform axis, an indexing table's stops or a second mounting would: "
                      "docs/planner.md)"))
    target = reach.target_yaw / DEG
    lines.append(f"time to a yaw 1-sigma of {target:g} deg ({WHAT_SCALES[campaign.scales]}):")
    if reach.reached is None:
        longest = reach.short_of_it
        floor, there, minutes = longest.floor_yaw() / DEG, longest.sigmas["yaw"] / DEG, longest.duration_s / 60
        if floor >= target:
            lines.append(f"  not reachable: bias instability and the factory residuals' prior leave {floor:.4g} deg "
                         f"at {minutes:.1f} min, the floor more data does not lower ({there:.4g} deg with the white "
                         "noise too)")
        else:
            lines.append(f"  not reachable within {minutes:.1f} min, the longest searched: {there:.4g} deg there; "
                         f"bias instability and the factory residuals' prior would leave {floor:.4g} deg")
        if campaign.scales != TURNS and index is None:
            lines.append("  (continuous rotation averages bias instability away, but the gyro Z scale factor's "
                         "prior grows its yaw with every turn: --campaign continuous)")
    else:
        got = reach.reached
        lines.append(f"  {got.duration_s / 60:.1f} min of data: {describe(got.segments)}")
        short = reach.short_of_it
        shorter = ("; the shortest layout searched" if short is None else
                   f"; {short.duration_s / 60:.1f} min gives {short.sigmas['yaw'] / DEG:.4g} deg")
        lines.append(f"  (yaw 1-sigma {got.sigmas['yaw'] / DEG:.4g} deg{shorter})")
    return "\n".join(lines)

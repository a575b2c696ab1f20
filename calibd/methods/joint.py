"""The joint method (`joint`, the default): every static and turning sample from the level static
to the last static of the same mounting in one fit, with 1-sigma and its error budget, the turns'
angles checked against the tilt the statics see (docs/method.md, Estimators). The maths is
calibd.estimators.joint; the turn-angle check is calibd.gaps."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import detect, gaps, spec
from ..correction import estimated_terms
from ..errors import CalibrationError
from ..estimators import joint, remount
from ..estimators.joint import JointOptions
from ..frames import STANDARD_GRAVITY, Site, int_to_imu
from ..results import ESTIMATES, CalibrationResult, ResultError, load_result, make_result
from ..segments import segment_record, session_segments
from ..session import Session
from ..units import DEG
from . import bench
from .base import DEFAULT_INDEX_SIGMA_DEG, INDEX_SIGMA_DEG, INDEX_STEP_DEG, OptionError, Setting, refusal
from .common import YAW_SIGMA_POOR_DEG, judged_once_stopped, session_warnings

CAMPAIGN = "joint method's campaign"


def _mounted(segments: list[detect.Segment]) -> list[detect.Segment]:
    """The segments from the first (the level static) to before the first static on another
    mounting: a re-mounting ends the single-axis model."""
    level = segments[0]
    return segments[:next((k for k, s in enumerate(segments) if s.kind == "static" and s.up != level.up),
                          len(segments))]


def _lacking(segments: list[detect.Segment]) -> str:
    """What the joint fit lacks in segments that may end on a turn under way; "" when nothing."""
    statics = [s for s in segments if s.kind == "static"]
    if not statics:
        return "a level static, then a turn and a static after it on the same mounting"
    level = statics[0]
    kinds = [s.kind for s in _mounted(segments[segments.index(level):])]
    if "turn" not in kinds:
        return f"a turn and a static after it on the level static's mounting ({level.up} up)"
    return "" if "static" in kinds[kinds.index("turn"):] else "a static after the turn"


class Joint:
    """Every static and turning sample in one fit, with 1-sigma (the default method)."""

    name = "joint"
    settings = {"fixed_amplitude": Setting(bool), "drift": Setting(bool),
                "index_step_deg": Setting(float, lambda v: INDEX_STEP_DEG[0] <= v <= INDEX_STEP_DEG[1],
                                          f"an indexing table's step in [{INDEX_STEP_DEG[0]:g}, "
                                          f"{INDEX_STEP_DEG[1]:g}] deg"),
                "index_sigma_deg": Setting(float, lambda v: INDEX_SIGMA_DEG[0] <= v <= INDEX_SIGMA_DEG[1],
                                           f"a 1-sigma in [{INDEX_SIGMA_DEG[0]:g}, {INDEX_SIGMA_DEG[1]:g}] deg"),
                "intrinsics": Setting(list, lambda v: bool(v) and all(isinstance(p, str) and p.strip() for p in v),
                                      "a list of result files of this unit (RESULT.json)")}

    def options(self, settings: Mapping[str, Any]) -> JointOptions:
        step, sigma = settings.get("index_step_deg"), settings.get("index_sigma_deg")
        if sigma is not None and step is None:
            raise OptionError("index_sigma_deg", "is the index's 1-sigma: give index_step_deg too")
        return JointOptions(bool(settings.get("fixed_amplitude")), bool(settings.get("drift")),
                            index_step=None if step is None else step * DEG,
                            index_sigma=0.0 if step is None else (DEFAULT_INDEX_SIGMA_DEG if sigma is None
                                                                  else sigma) * DEG,
                            **intrinsics(settings.get("intrinsics") or ()))

    def missing(self, segments: list[detect.Segment]) -> str | None:
        return judged_once_stopped(segments, _lacking)

    def solve(self, session, site, segments, options: JointOptions):
        return joint_real_case(session, site, options, segments)


METHOD = Joint()


@dataclass
class JointFit:
    """The joint estimator's input and fit on a session, kept for figures that show how the
    estimates came about (the Earth-rate sinusoid against the platform angle)."""

    segments: list[detect.Segment]  # those used: from the level static to the last static of its mounting
    first: int  # the session sample where the fit's input starts (the level static's first)
    inp: joint.JointInput
    fit: joint.JointResult
    options: joint.JointOptions  # as solved: the accelerometer range the sensor's configuration gave
    turn_angles: gaps.TiltCheck | None = None  # each turn's angle against the tilt, before any correction
    final_tilt: gaps.TiltCheck | None = None  # the same check on the fit as returned
    index: IndexedTurns | None = None  # the statics' angles from an indexing table's stops; None: the gyros'


def joint_input(session: Session, segments: list[detect.Segment]) -> tuple[list[detect.Segment], int,
                                                                          joint.JointInput]:
    """What the joint fit takes of a session whose segments hold its campaign: the segments used
    (from the level static to the last static of its mounting), the session sample the input
    starts at (the level static's first) and the input."""
    level = detect.level_static(segments)
    used = _mounted(segments[segments.index(level):])
    while used[-1].kind != "static":
        used.pop()
    first, stop = level.start, used[-1].stop
    inp = joint.JointInput(
        time_s=session.time_s[first:stop] - session.time_s[first], gyro=session.gyro[first:stop],
        acc=session.acc[first:stop], incl=None if session.incl is None else session.incl[first:stop],
        statics=tuple((s.start - first, s.stop - first) for s in used if s.kind == "static"),
        rate_hz=session.rate_hz,
        temperature_c=None if session.temperature_c is None else session.temperature_c[first:stop])
    return used, first, inp


def joint_fit(session: Session, site: Site, options: joint.JointOptions = joint.JointOptions(),
              segments: list[detect.Segment] | None = None) -> JointFit:
    """The joint estimator's fit on every static and turning sample from the level static to the
    last static of the same mounting. `segments`: the session's, when already found. The
    datasheet figures are those of the sensor's accelerometer range, when its configuration
    datagram gave it (else `options`')."""
    segments = session_segments(session) if segments is None else segments
    if session.sensor.acc_range_g in spec.ACC:
        options = replace(options, acc_range_g=session.sensor.acc_range_g)
    ours = session.sensor.serial_number
    if options.known_serial and ours and ours != options.known_serial:
        raise CalibrationError(f"the factory terms of {options.known_from} are of serial number "
                               f"{options.known_serial}, this sensor is {ours}: factory terms are one unit's")
    if lacking := METHOD.missing(segments):
        raise refusal(CAMPAIGN, lacking, segments, bench.hint(segments))
    used, first, inp = joint_input(session, segments)
    try:
        fit = joint.solve(inp, site, options)
    except joint.Underdetermined as exc:
        raise refusal(CAMPAIGN, f"what determines every parameter ({exc})", segments) from None
    except np.linalg.LinAlgError:
        raise refusal(CAMPAIGN, "what determines every parameter (too few platform angles)", segments) from None
    check = tilt_check(inp, fit, site)
    if options.index_step is not None:
        return _indexed(used, first, inp, fit, site, options, check)
    found = [t for t in check.turns if t.found] if check else []
    if not found:
        return JointFit(used, first, inp, seen_by_statics(fit, check, options), options, check, check)
    try:
        inp, fit = _corrected(inp, fit, site, options, found)
    except (joint.Underdetermined, np.linalg.LinAlgError) as exc:
        raise CalibrationError(f"the tilt the accelerometers and inclinometers see disagrees with the gyros' turn "
                               f"angles, and the corrected angles leave no usable fit ({exc})") from None
    final = tilt_check(inp, fit, site)
    return JointFit(used, first, inp, seen_by_statics(fit, final, options), options, check, final)


INDEX_TOLERANCE = 0.25  # of the step: a static farther from every stop than this is not at one
SLIP_SIGMAS = 5.0  # a turn off its stops by the scale factor's limit and this many sigma more lost data


@dataclass(frozen=True)
class IndexedTurns:
    """What the stops of an indexing table say: each static's angle, and the gyro Z scale factor
    (along the platform axis) the gyros' integral shows against them."""

    step: float  # rad
    sigma: float  # rad, each static's angle's 1-sigma
    known: np.ndarray  # (statics,) rad, the level static's 0
    integrated: np.ndarray  # (statics,) rad, the gyros' integral
    scale: float  # the gyros' integral over the stops' angles, less 1, along the platform axis
    scale_sigma: float
    left_out: tuple[int, ...] = ()  # turns (k: from static k to k + 1) off their stops by more than a scale factor

    def record(self) -> dict:
        """The result's check: the stops, the gyros' angles against them, the scale factor seen."""
        return {"step_deg": self.step / DEG, "sigma_deg": self.sigma / DEG,
                "static_angles_deg": (self.known / DEG).tolist(),
                "gyro_minus_stop_deg": ((self.integrated - self.known) / DEG).tolist(),
                "scale_along_axis_ppm": self.scale * 1e6, "scale_sigma_ppm": self.scale_sigma * 1e6,
                "turns_left_out": [k + 1 for k in self.left_out]}


def indexed_turns(inp: joint.JointInput, fit: joint.JointResult, step: float, sigma: float) -> IndexedTurns:
    """Each static's angle at its stop (the whole multiple of `step` nearest the gyros' integral),
    and the scale factor the turns show: per turn, the integral less the stops' angle is the
    scale factor times the angle, plus the gyros' white noise integrated through the turn, the
    offset's error times the turn's time and the two stops' own error (a generalised least-squares
    fit through all turns). A turn off its stops by more than the datasheet's scale factor and
    SLIP_SIGMAS of that noise lost datagrams the counter cannot see (or its stop slipped): its
    statics keep their stops, and it is left out of the fit, unless most turns are (a platform
    that does not stop at the steps: the warnings say so). CalibrationError when a static is not
    at a stop."""
    integrated = np.array([fit.gyro.chi[a:b].mean() for a, b in inp.statics])
    integrated -= integrated[0]
    known = np.round(integrated / step) * step
    off = np.abs(integrated - known)
    if off.max() > INDEX_TOLERANCE * step:
        k = int(np.argmax(off))
        raise CalibrationError(f"static {k + 1} of the fit sits at {integrated[k] / DEG:.2f} deg by the gyros, "
                               f"{off[k] / DEG:.2f} deg from the nearest multiple of the index step "
                               f"{step / DEG:g} deg: the turns are not indexed by that step")
    k_axis = fit.gyro.params[joint.AXIS_PARAMS] / np.linalg.norm(fit.gyro.params[joint.AXIS_PARAMS])
    turned = np.diff(known)
    seconds = np.array([inp.time_s[inp.statics[j + 1][0]] - inp.time_s[inp.statics[j][1] - 1]
                        for j in range(len(turned))])
    white = float(k_axis**2 @ fit.gyro.noise.white) / inp.rate_hz  # angle variance per second turning, rad^2/s
    offset_cov = fit.gyro.cov[joint.OFFSET_PARAMS, joint.OFFSET_PARAMS]
    between = np.diff(np.eye(len(known)), axis=0)  # each turn's angle from the statics'
    cov = (np.diag(white * seconds) + float(k_axis @ offset_cov @ k_axis) * np.outer(seconds, seconds)
           + sigma**2 * between @ between.T)
    excess = np.diff(integrated - known)
    slipped = np.abs(excess) > spec.GYRO.scale_factor_ppm * 1e-6 * np.abs(turned) + SLIP_SIGMAS * np.sqrt(np.diag(cov))
    use = ~slipped if 2 * slipped.sum() < len(slipped) else np.ones_like(slipped)
    weights = np.linalg.solve(cov[np.ix_(use, use)], turned[use])
    information = float(turned[use] @ weights)
    return IndexedTurns(step, sigma, known, integrated, float(weights @ excess[use]) / information,
                        float(np.sqrt(1.0 / information)), tuple(int(k) for k in np.flatnonzero(~use)))


def _indexed(used: list[detect.Segment], first: int, inp: joint.JointInput, fit: joint.JointResult, site: Site,
             options: JointOptions, check: gaps.TiltCheck | None) -> JointFit:
    """The joint fit with each static at its stop (`at_stops`)."""
    pinned_inp, pinned, final, index = at_stops(inp, fit, site, options)
    return JointFit(used, first, pinned_inp, pinned, options, check, final, index)


def at_stops(inp: joint.JointInput, fit: joint.JointResult, site: Site, options: JointOptions,
             noise: joint.SensorNoise | None = None
             ) -> tuple[joint.JointInput, joint.JointResult, gaps.TiltCheck | None, IndexedTurns]:
    """The joint fit (`fit`, of `inp` as the gyros integrate it) redone with each static at its
    stop (`indexed_turns`): the platform angle no longer carries the gyro Z scale factor, lost
    datagrams or the gyros' noise through the turns, and the scale factor the turns show joins
    what the statics' forces see of the factory residuals. The stops' own error is carried into
    the covariance through a fit redone with each moved by it. `noise`: as `joint.solve` takes
    it. The input, the fit, its turn-angle check and the stops."""
    index = indexed_turns(inp, fit, options.index_step, options.index_sigma)

    def solved(known: np.ndarray) -> tuple[joint.JointInput, joint.JointResult]:
        pinned_inp = replace(inp, static_angles=known)
        return pinned_inp, joint.solve(pinned_inp, site, options, noise=noise)

    pinned_inp, pinned = solved(index.known)
    stops = np.zeros_like(pinned.covariance)
    if index.sigma > 0:
        for k in range(1, len(index.known)):
            _, moved = solved(index.known + index.sigma * (np.arange(len(index.known)) == k))
            shift = np.array([moved.estimates[name] - value for name, value in pinned.estimates.items()])
            stops += np.outer(shift, shift)
    pinned = replace(pinned, budget=pinned.budget | {"turn_angles": stops})
    final = tilt_check(pinned_inp, pinned, site)
    if pinned.factory is None:
        return pinned_inp, pinned, final, index
    terms = pinned.factory.terms
    statics = final.factory if final and final.factory else joint.FactoryPosterior(np.zeros(len(terms)),
                                                                                   np.eye(len(terms)))
    posterior = statics.observed(_scale_row(terms, pinned), index.scale, index.scale_sigma)
    return pinned_inp, pinned.with_factory_posterior(with_known_terms(posterior, terms, options)), final, index


def _scale_row(terms: tuple[spec.FactoryTerm, ...], fit: joint.JointResult) -> np.ndarray:
    """How each factory term at its 1-sigma moves the gyros' scale along the platform axis k:
    k' E k, the gyro triad's terms only."""
    k = fit.gyro.params[joint.AXIS_PARAMS] / np.linalg.norm(fit.gyro.params[joint.AXIS_PARAMS])
    return np.array([k[t.row] * k[t.col] * t.sigma if t.sensor == "gyro" else 0.0 for t in terms])


def checked_by_statics(inp: joint.JointInput, fit: joint.JointResult, site: Site,
                       options: JointOptions = JointOptions(), noise: joint.SensorNoise | None = None
                       ) -> joint.JointResult:
    """The fit with what the turn-angle check of its statics sees of the factory residuals, and
    with each static at its stop when `options` gives an index step (the planner's view of a
    session; calibrate keeps the check too). `noise`: as the fit was solved with it."""
    if options.index_step is not None:
        return at_stops(inp, fit, site, options, noise)[1]
    return seen_by_statics(fit, tilt_check(inp, fit, site), options)


def seen_by_statics(fit: joint.JointResult, check: gaps.TiltCheck | None,
                    options: JointOptions = JointOptions()) -> joint.JointResult:
    """The fit with what the statics' forces saw of the factory residuals, where they were checked,
    and the terms `options` says an earlier calibration of the unit estimated."""
    if fit.factory is None:
        return fit
    seen = None if check is None else check.factory
    if seen is None and not options.known_terms:
        return fit
    terms = fit.factory.terms
    seen = seen or joint.FactoryPosterior(np.zeros(len(terms)), np.eye(len(terms)))
    return fit.with_factory_posterior(with_known_terms(seen, terms, options))


def intrinsics(paths) -> dict:
    """JointOptions' known_terms, known_from and known_serial from the results at `paths` (the
    `intrinsics` setting): the factory terms each estimated (`measured_terms`). OptionError (one
    line naming the file) for a file that is not a result, one that estimates no term, results of
    two serial numbers, or two that rest on the same data (their terms would count twice)."""
    if not paths:
        return {}
    known, serials, data = [], set(), {}
    for path in paths:
        try:
            earlier = load_result(path)
            terms = measured_terms(earlier)
        except ResultError as exc:
            raise OptionError("intrinsics", str(exc)) from None
        except (ValueError, KeyError, TypeError, ZeroDivisionError):
            raise OptionError("intrinsics", f"{path}: error_budget.factory_residuals is not as calibd writes it (a "
                                            "term's name, value, sigma or prior_sigma)") from None
        if not terms:
            raise OptionError("intrinsics", f"{path}: estimates no factory term (a bench campaign's result, "
                                            "--method thesis --bench, or one made with --remounted has them)")
        rests_on = (earlier.session_id or "").split("/")[0]
        if rests_on and rests_on in data:
            raise OptionError("intrinsics", f"{path}: rests on the same data as {data[rests_on]}: its terms would be "
                                            "counted twice")
        data[rests_on] = path
        serials.add((earlier.capture or {}).get("serial_number") or earlier.sensor.serial_number)
        known += terms
    serials.discard(None)
    if len(serials) > 1:
        raise OptionError("intrinsics", f"the results are of serial numbers {', '.join(sorted(serials))}: factory "
                                        "terms are one unit's")
    return {"known_terms": tuple(known), "known_from": ", ".join(map(str, paths)),
            "known_serial": serials.pop() if serials else None}


def measured_terms(result: CalibrationResult) -> tuple[tuple[str, float, float], ...]:
    """What an earlier result's data alone said of each factory term it estimated: (name, value,
    1-sigma), dimensionless, for `JointOptions.known_terms`. A bench's six positions fit the
    terms without a prior, so their value and sigma are that; a joint result's are a posterior,
    so the datasheet's prior is taken out of each (term by term: the document keeps no
    correlations), lest a later fit count the prior twice."""
    factory = (result.error_budget or {}).get("factory_residuals") or {}
    with_prior = factory.get("from") != bench.SIX_POSITIONS
    out = []
    for name, (value, sigma) in estimated_terms(result).items():
        if with_prior:
            prior = factory["terms"][name]["prior_sigma"] / spec.FactoryTerm.named(name).to_unit
            precision = 1 / sigma**2 - 1 / prior**2  # an estimated term's sigma is at most half its prior's
            value, sigma = value / sigma**2 / precision, 1 / np.sqrt(precision)
        out.append((name, float(value), float(sigma)))
    return tuple(out)


def with_known_terms(posterior: joint.FactoryPosterior, terms: tuple[spec.FactoryTerm, ...],
                     options: JointOptions) -> joint.FactoryPosterior:
    """The posterior with each factory term an earlier calibration estimated (`known_terms`: its
    value and sigma, from other data, so independent of these) taken as one more measurement. A
    term this fit does not have (an inclinometer's, on a unit without them) is passed over."""
    names = [t.name for t in terms]
    for name, value, sigma in options.known_terms:
        if name in names:
            k = names.index(name)
            posterior = posterior.observed(np.eye(len(terms))[k], value / terms[k].sigma, sigma / terms[k].sigma)
    return posterior


def tilt_check(inp: joint.JointInput, fit: joint.JointResult, site: Site) -> gaps.TiltCheck | None:
    """The turns' angles against the tilt; None when the statics cannot tell them."""
    a = int_to_imu(fit.estimates["alpha"], fit.estimates["beta"])
    try:
        return gaps.check_turn_angles(inp, fit.gyro.chi, a, site.gravity, fit.acc.noise, fit.incl and fit.incl.noise,
                                      fit.tilt.params[joint.TILT_PARAMS], fit.factory, fit.gyro.noise,
                                      fit.temperature)
    except (joint.Underdetermined, np.linalg.LinAlgError):
        return None


def _corrected(inp: joint.JointInput, fit: joint.JointResult, site: Site, options: joint.JointOptions,
               found: list[gaps.TurnAngle]) -> tuple[joint.JointInput, joint.JointResult]:
    """The joint fit redone with the turns' angles corrected to the tilt's; each correction's
    1-sigma is carried into the covariance through a fit redone with that correction moved by it."""
    def solved(turns):
        corrected_inp = replace(inp, chi_correction=gaps.chi_correction(inp, fit.gyro.chi, turns))
        return corrected_inp, joint.solve(corrected_inp, site, options)

    inp, corrected = solved(found)
    turn_angles = np.zeros_like(corrected.covariance)
    for k, turn in enumerate(found):
        _, moved = solved(found[:k] + [replace(turn, correction_rad=turn.correction_rad + turn.sigma_rad)]
                          + found[k + 1:])
        shift = np.array([moved.estimates[name] - value for name, value in corrected.estimates.items()])
        turn_angles += np.outer(shift, shift)  # one correction's error moves every estimate together
    return inp, replace(corrected, budget=corrected.budget | {"turn_angles": turn_angles})


@dataclass(frozen=True)
class SecondMounting:
    """The same unit's campaign with its housing turned 180 deg about its own Z axis on the
    interface (calibd.estimators.remount): its fit, where it came from, and how exactly the
    fixture turns the housing."""

    fit: joint.JointResult
    source: dict  # the result's checks.second_mounting: the capture's path, size_bytes, sha256, power_up
    sigma: float  # rad, 1-sigma of the fixture's turn about 180 deg
    unsettled: str | None = None  # words when its power-up's temperature never settled


REMOUNT_ALARM_P = 1e-3  # p-value below which the two mountings' tilts are beyond what the prior allows
# times the datasheet's misalignment limit: a sum that needs a gyro triad misaligned more is not a unit
# turned 180 deg (a housing not turned reads as twice its tilt), and is refused
PLAUSIBLE_MISALIGNMENT = 3.0
REMOUNTED = ("pitch", "roll", "alpha", "beta")  # what the second mounting's tilt sets


def _remounted(fitted: JointFit, second: SecondMounting) -> tuple[JointFit, dict, str | None]:
    """The first mounting's fit with what the two mountings' tilts show of the factory residuals
    taken out, the result's check, and why what the sum sets is flagged poor (None: it is not);
    CalibrationError when the tilts do not mirror each other."""
    try:
        fit, check = remount.two_mountings(fitted.fit, second.fit, second.sigma)
    except ValueError:
        raise CalibrationError("the second mounting's fit estimates other things than the first's (a datagram "
                               "format without inclinometers, or another accelerometer range?)") from None
    sigma = np.sqrt(np.diag(check.cov))
    record = second.source | {
        "remount_sigma_deg": second.sigma / DEG,
        "alpha_deg": check.second["alpha"] / DEG, "beta_deg": check.second["beta"] / DEG,
        "tilt_sum_mrad": (check.tilt_sum * 1e3).tolist(), "predicted_mrad": (check.predicted * 1e3).tolist(),
        "sigma_mrad": (sigma * 1e3).tolist(), "chi2": check.chi2, "p_value": check.p_value}
    words = (f"their tilts in the housing sum to ({check.tilt_sum[0] * 1e3:.3f}, {check.tilt_sum[1] * 1e3:.3f}) "
             f"mrad where the factory residuals and the noise allow ({check.predicted[0] * 1e3:.3f} +- "
             f"{sigma[0] * 1e3:.3f}, {check.predicted[1] * 1e3:.3f} +- {sigma[1] * 1e3:.3f}) mrad "
             f"(p = {check.p_value:.2g})")
    misaligned = np.abs(check.tilt_sum - check.predicted) / 2  # what the gyro triad would need beyond the prior's
    plausible = PLAUSIBLE_MISALIGNMENT * spec.GYRO.misalignment_mrad * 1e-3
    if check.p_value < REMOUNT_ALARM_P and np.any(misaligned > plausible):
        raise CalibrationError(
            f"the two mountings' platform axes do not mirror each other: {words}, more than a gyro triad "
            f"{PLAUSIBLE_MISALIGNMENT:g} times the datasheet's misalignment would make: is the housing turned 180 "
            f"deg about its own Z axis between this capture and {second.source.get('path')}?")
    beyond = None if check.p_value >= REMOUNT_ALARM_P else (
        f"the two mountings' tilts are beyond what the datasheet's residuals allow: {words}; the gyro triad may be "
        "misaligned beyond its specification (the sum still measures it), or the housing not turned exactly 180 "
        "deg: pitch, roll, alpha and beta, which the sum sets, are flagged poor")
    return replace(fitted, fit=fit), record, beyond


def joint_real_case(session: Session, site: Site, options: joint.JointOptions = joint.JointOptions(),
                    segments: list[detect.Segment] | None = None,
                    second: SecondMounting | None = None) -> CalibrationResult:
    """The joint estimator (docs/method.md, Estimators) on every static and turning sample from the level
    static to the last static of the same mounting. `segments`: the session's, when already found;
    `second`: the unit's second mounting, whose tilt takes out the factory terms it shows."""
    fitted = joint_fit(session, site, options, segments)
    remounting = beyond = None
    if second is not None:
        fitted, remounting, beyond = _remounted(fitted, second)
    used, fit = fitted.segments, fitted.fit
    warnings = (session_warnings(session) + _vibration_warnings(fitted, session) + _joint_warnings(fit, site)
                + _turn_angle_warnings(fitted, session))
    if remounting is not None:
        warnings.append(f"pitch, roll, alpha and beta rest on the second mounting too ({second.source['path']}, "
                        "the housing turned 180 deg about its Z axis): its tilt estimates the gyro triad's "
                        "misalignment that tilts the platform axis (checks.second_mounting)")
    estimates = {name: (fit.estimates[name], fit.sigmas[name]) for name in joint.ESTIMATE_NAMES
                 if name in fit.estimates}  # the order of fit.estimates, which is the covariance's
    result = make_result("joint", site, estimates, [segment_record(s, s.kind) for s in used], warnings,
                         session.sensor, fit.covariance, stream=session.stream,
                         options={"fixed_amplitude": options.fixed_amplitude, "drift": options.drift} | (
                             {} if fitted.index is None else {"index_step_deg": options.index_step / DEG,
                                                              "index_sigma_deg": options.index_sigma / DEG}) | (
                             {} if not options.known_terms else {"intrinsics": {
                                 "path": options.known_from, "terms": [name for name, _, _ in options.known_terms]}}),
                         checks=_joint_checks(fit, site) | _turn_angle_checks(fitted, session)
                         | ({} if fitted.index is None else {"indexed_turns": fitted.index.record()})
                         | ({} if remounting is None else {"second_mounting": remounting}),
                         bias_reference="turn-on", error_budget=error_budget_record(fit, fitted.options))
    if beyond is not None:
        result = result.flag_poor(REMOUNTED, beyond)
    if second is not None and second.unsettled:
        result = result.flag_poor(REMOUNTED, f"the second mounting's power-up {second.unsettled}: pitch, roll, "
                                             "alpha and beta, which its tilt sets, are flagged poor")
    if fit.sigmas["yaw"] / DEG > YAW_SIGMA_POOR_DEG:
        result = result.flag_poor(("yaw",))
    if fitted.final_tilt and fitted.final_tilt.p_value < CHI2_ALARM_P:
        return result.flag_poor(PLATFORM_ANGLE_ESTIMATES)  # the forces' model fails: the factory check means nothing
    return _judged_by_factory_prior(result)


FACTORY_ALARM_P = 0.01  # p-value below which the factory residuals the statics see are beyond the datasheet's
FACTORY_LIMITED_SHARE = 0.5  # an estimate whose factory part is this share of its sigma is limited by them


def _judged_by_factory_prior(result: CalibrationResult) -> CalibrationResult:
    """A unit whose factory residuals, as far as the statics see them, lie beyond the
    datasheet's spread (`FactoryPosterior.against_prior`, p < FACTORY_ALARM_P; 1 % of units
    within the datasheet) may be outside its specification in what they cannot see too (a
    triad's misalignment to the housing): the estimates the residuals limit are flagged poor.
    Asked only when the statics' forces fit their model: a bias jump would pass for residuals."""
    check = result.checks.get("factory_prior_chi2")
    if check is None or check["p_value"] >= FACTORY_ALARM_P:
        return result
    parts = result.error_budget["sigma"]
    limited = [name for name, e in result.estimates.items()
               if e.sigma and parts[name].get("factory_residuals", 0.0) >= FACTORY_LIMITED_SHARE * e.sigma]
    return result.flag_poor(limited, (
        f"the factory residuals the statics see lie beyond the STIM300 datasheet's spread (chi-square "
        f"{check['chi2']:.1f} for {check['dof']} directions seen, p = {check['p_value']:.2g}): the unit may be "
        "outside its specification, in what the data cannot see too (each triad's misalignment to the housing); "
        f"the estimates they limit are flagged poor: {', '.join(limited)}"))


def error_budget_record(fit: joint.JointResult, options: joint.JointOptions) -> dict:
    """The result's error_budget: each estimate's sigma by its parts (display units; their squares
    add up to the sigma's square) and the factory residuals' prior, term by term."""
    sigma = {name: {part: value * ESTIMATES[name][0] for part, value in parts.items()}
             for name, parts in fit.sigma_budget().items()}
    factory = None
    if fit.factory is not None:
        factory = {"reference": spec.SPECIFICATIONS,
                   "acc_range_g": options.acc_range_g,
                   "terms": {t.name: _term_record(t, fit.factory.posterior, k)
                             for k, t in enumerate(fit.factory.terms)}}
    return {"frame": "housing", "tilt_from": "inclinometers" if fit.tilt is fit.incl else "accelerometers",
            "parts": list(next(iter(sigma.values()))), "sigma": sigma, "factory_residuals": factory}


def _term_record(term, posterior: joint.FactoryPosterior | None, k: int) -> dict:
    """One factory term: its value and sigma after the data (in ppm or mrad), the prior's sigma,
    and whether the data set it (`estimated`) or its prior did."""
    if posterior is None:
        return {"value": 0.0, "sigma": term.sigma_in_unit, "prior_sigma": term.sigma_in_unit, "unit": term.unit,
                "source": "prior"}
    return {"value": float(posterior.z[k]) * term.sigma_in_unit,
            "sigma": float(np.sqrt(posterior.cov[k, k])) * term.sigma_in_unit, "prior_sigma": term.sigma_in_unit,
            "unit": term.unit, "source": "estimated" if posterior.estimated(k) else "prior"}


VIBRATION_FACTOR = 3.0  # a static whose noise per sample exceeds the specified this many times is named
_SPEC_WORDS = {"gyro": ("gyro", 1 / DEG, "deg/s", "ARW", 60 / DEG, "deg/sqrt(h)"),
               "acc": ("accelerometer", 1000 / STANDARD_GRAVITY, "mg", "VRW", 60, "m/s/sqrt(h)"),
               "incl": ("inclinometer", 1000 / STANDARD_GRAVITY, "mg", "VRW", 60, "m/s/sqrt(h)")}


def _vibration_warnings(fitted: JointFit, session: Session) -> list[str]:
    """Statics whose noise per sample is VIBRATION_FACTOR times the sensor's specified noise (its
    datasheet random walk at the session's rate, `joint.datasheet_noise`) or more: vibration (an
    engine running) or a platform that is not still. The fits weigh each static by its own
    measured noise (`joint.static_inflation`), so the estimates and sigmas stay honest; the
    warning says what the data are worth."""
    inp = fitted.inp
    warnings = []
    for k, (start, stop) in enumerate(inp.statics):
        # the datasheet's inclinometer figures are at 0 g: an axis along gravity is noisier
        along = None if inp.incl is None else inp.incl[start:stop].mean(axis=0, dtype=np.float64) / STANDARD_GRAVITY
        figures = joint.datasheet_noise(spec.NoiseFigures.datasheet(fitted.options.acc_range_g), inp.rate_hz, along)
        loud = []
        for sensor, values in (("gyro", inp.gyro), ("acc", inp.acc), ("incl", inp.incl)):
            if values is None:
                continue
            measured = np.sqrt(joint.sample_variance(values, [(start, stop)])[0])
            specified = np.sqrt(np.mean(getattr(figures, sensor).white))  # as measured: the channels' mean
            if measured > VIBRATION_FACTOR * specified:
                name, factor, unit, walk, walk_factor, walk_unit = _SPEC_WORDS[sensor]
                density = specified / np.sqrt(inp.rate_hz) * walk_factor
                loud.append(f"{name} noise {measured * factor:.3g} {unit} per sample, {measured / specified:.0f}x "
                            f"the specified {specified * factor:.2g} {unit} ({walk} {density:.3g} {walk_unit} at "
                            f"{inp.rate_hz:g} Hz)")
        if loud:
            begin_s = session.time_s[fitted.first + start]
            warnings.append(f"static {k + 1} ({begin_s:.1f} s to {begin_s + (stop - start) / inp.rate_hz:.1f} s): "
                            f"{'; '.join(loud)}: vibration (an engine running?) or a platform not at rest; the "
                            "fits weigh it by its measured noise")
    return warnings


# what a wrong platform angle at the statics moves (alpha and beta come from the turns' rates)
PLATFORM_ANGLE_ESTIMATES = ("pitch", "roll", "yaw", *(f"{s}_bias_{a}" for s in ("acc", "incl") for a in "xyz"))


def _turn_window_s(fitted: JointFit, session: Session, turn: gaps.TurnAngle) -> tuple[float, float]:
    """The turn's start and end on the session's time base."""
    return float(session.time_s[fitted.first + turn.start]), float(session.time_s[fitted.first + turn.stop])


def _turn_angle_checks(fitted: JointFit, session: Session) -> dict:
    if fitted.turn_angles is None:
        return {}
    turns = []
    for t in fitted.turn_angles.turns:
        start_s, end_s = _turn_window_s(fitted, session, t)
        turns.append({"start_s": round(start_s, 3), "end_s": round(end_s, 3), "gyro_deg": t.gyro_rad / DEG,
                      "tilt_minus_gyro_deg": t.correction_rad / DEG,
                      "sigma_deg": t.sigma_rad / DEG if t.checkable else None, "corrected": t.found})
    final = fitted.final_tilt
    chi2 = {"force_static_chi2": {"chi2": final.chi2, "dof": final.dof, "p_value": final.p_value}} if final else {}
    if fitted.fit.factory is not None and fitted.fit.factory.posterior is not None:
        value, dof = fitted.fit.factory.posterior.against_prior()
        chi2["factory_prior_chi2"] = {"chi2": value, "dof": dof, "p_value": _survival(value, dof)}
    return {"turn_angles": turns} | chi2


def _turn_angle_warnings(fitted: JointFit, session: Session) -> list[str]:
    """Turns whose angle the tilt corrected, turns it could not check, statics' forces that do
    not fit."""
    unseen = ("a datagram loss the counter cannot see (whole 0.128 s cycles) during a turn would go unnoticed "
              "except by the gyro chi-square")
    warnings = []
    if fitted.index is not None:
        index = fitted.index
        off = np.abs(index.integrated - index.known) / DEG
        warnings.append(f"each static's platform angle is its stop's (index step {index.step / DEG:g} deg, "
                        f"1-sigma {index.sigma / DEG:g} deg), not the gyros' integral, which was at most "
                        f"{off.max():.3f} deg off; the turns show the gyro scale factor along the platform axis "
                        f"at {index.scale * 1e6:+.0f} +- {index.scale_sigma * 1e6:.0f} ppm")
        for k in index.left_out:
            a, b = fitted.inp.statics[k][1], fitted.inp.statics[k + 1][0]
            excess = (index.integrated[k + 1] - index.known[k + 1]) - (index.integrated[k] - index.known[k])
            warnings.append(f"the turn from {session.time_s[fitted.first + a - 1]:.1f} s to "
                            f"{session.time_s[fitted.first + b]:.1f} s ended {excess / DEG:+.2f} deg from its stop, "
                            "more than the gyro scale factor can make: datagrams lost unseen by the counter, or a stop "
                            "that slipped; its statics keep their stops' angles, and it is left out of the scale "
                            "factor")
        limit = spec.GYRO.scale_factor_ppm * 1e-6
        if abs(index.scale) > limit + 3 * index.scale_sigma:
            warnings.append(f"the turns differ from the stops' angles by {index.scale * 1e6:+.0f} ppm of the angle "
                            f"turned, beyond the gyro scale factor the STIM300 datasheet allows ({limit * 1e6:.0f} "
                            f"ppm): the platform may not stop at whole multiples of {index.step / DEG:g} deg "
                            "(--index-step)")
    if fitted.turn_angles is None:
        return warnings or [f"the statics do not pin the turns' angles (statics at fewer than {gaps.MIN_HEADINGS} "
                            f"headings): {unseen}"]
    for t in fitted.turn_angles.turns:
        start_s, end_s = _turn_window_s(fitted, session, t)
        if t.found and fitted.index is None:
            top_rate = np.max(np.abs(fitted.fit.gyro.chi_rate[t.start:t.stop]))
            warnings.append(
                f"the turn from {start_s:.1f} s to {end_s:.1f} s: the tilt the accelerometers and inclinometers "
                f"see turned {(t.gyro_rad + t.correction_rad) / DEG:+.2f} deg where the gyros integrated "
                f"{t.gyro_rad / DEG:+.2f} deg (off by {t.correction_rad / DEG:+.2f} +- {t.sigma_rad / DEG:.2f} deg): "
                f"datagrams lost unseen by the counter (at least {abs(t.correction_rad) / top_rate:.2f} s at the "
                "turn's top rate); the platform angle from that turn on is corrected and the correction's "
                "uncertainty is in the sigmas")
    unchecked = [t for t in fitted.turn_angles.turns if not t.checkable]
    if unchecked:
        tilt_deg = np.degrees(np.arcsin(min(np.hypot(*fitted.fit.tilt.params[joint.TILT_PARAMS]), 1.0)))
        warnings.append(f"{len(unchecked)} of {len(fitted.turn_angles.turns)} turns' angles could not be "
                        f"checked against the tilt (platform axis {tilt_deg:.3f} deg from Up, too little to see "
                        f"the angle to {np.degrees(gaps.CHECKABLE_SIGMA_RAD):.0f} deg): {unseen}")
    final = fitted.final_tilt
    if final and final.p_value < CHI2_ALARM_P:
        warnings.append(f"the static segments' accelerometer and inclinometer means do not fit the model "
                        f"(chi-square {final.chi2:.0f} for {final.dof} degrees of freedom): a platform angle off "
                        "(datagrams lost during a turn), a platform that moved during a static, or a bias jump; "
                        "pitch, roll, yaw and the accelerometer and inclinometer biases are flagged poor")
    return warnings


def _joint_checks(fit: joint.JointResult, site: Site) -> dict:
    fitted, sigma = fit.gyro.amplitude_check
    expected = joint.EARTH_RATE * np.cos(np.radians(site.latitude_deg))
    to_deg_h = 3600 / DEG
    return {"earth_rate_horizontal_deg_h": {"fitted": fitted * to_deg_h, "sigma": sigma * to_deg_h,
                                            "expected": expected * to_deg_h},
            "static_chi2": _chi2_record(fit),
            "gyro_residual_rms_deg_s": (fit.gyro.residual_rms / DEG).tolist(),
            # the platform axis as the gyro triad sees it (unit): what taking the platform's rate out of
            # the gyros' outputs needs, known far better than the housing's alpha and beta
            "platform_axis_in_gyro_axes": (fit.gyro.params[joint.AXIS_PARAMS]
                                           / np.linalg.norm(fit.gyro.params[joint.AXIS_PARAMS])).tolist(),
            "noise_excess_over_white": {"gyro": fit.gyro.noise_scale, "acc": fit.acc.noise_scale,
                                        **({} if fit.incl is None else {"incl": fit.incl.noise_scale})}}


CHI2_ALARM_P = 1e-3  # p-value below which the statics' residuals say the model does not hold


def _chi2_record(fit: joint.JointResult) -> dict:
    value, dof = fit.gyro.static_chi2
    return {"chi2": value, "dof": dof, "p_value": _survival(value, dof)}


def _survival(chi2: float, dof: int) -> float:
    """P(a chi-square of `dof` degrees of freedom >= chi2); 1 with no degree of freedom."""
    from scipy.special import gammaincc  # when used: start-up (docs/architecture.md)
    return float(gammaincc(dof / 2, chi2 / 2)) if dof > 0 else 1.0


def _joint_warnings(fit: joint.JointResult, site: Site) -> list[str]:
    forces = "accelerometer" if fit.incl is None else "accelerometer and inclinometer"
    warnings = ["biases are turn-on biases (the sensor's at this power-up): their 1-sigma includes the "
                "bias-instability wander over the session, which moves the bias the data carry away from them",
                f"horizontal {forces} biases rest on the gyro-derived alpha and beta "
                "(a single rotation axis cannot separate them from the IMU tilt otherwise): an error "
                "d_beta moves the X biases by g0 d_beta, and their 1-sigma carries it"]
    if fit.factory is not None:
        warnings.append("every 1-sigma carries the factory residuals the STIM300 datasheet allows (each triad's "
                        "misalignment to the housing and scale factors, as a prior the statics narrow only where "
                        "they see them): they limit pitch, roll, alpha, beta and the accelerometer and "
                        "inclinometer biases (the result's error_budget says how much and what was estimated)")
    if site.g0 is None:
        warnings.append(f"Z {forces} biases rest on normal gravity: their 1-sigma includes "
                        f"{site.gravity_sigma / STANDARD_GRAVITY * 1000:.3f} mg for a typical local gravity anomaly, "
                        "more where it is large (give --g0 when it is measured)")
    if fit.sigmas["yaw"] / DEG > YAW_SIGMA_POOR_DEG:
        warnings.append(f"yaw is too poor to use: 1-sigma {fit.sigmas['yaw'] / DEG:.1f} deg (more static time "
                        "at several headings, or more turning, would help)")
    chi2_check = _chi2_record(fit)
    if chi2_check["p_value"] < CHI2_ALARM_P:
        warnings.append(f"the static segments' gyro means do not fit the model (chi-square {chi2_check['chi2']:.0f} "
                        f"for {chi2_check['dof']} degrees of freedom): a bias jump, a platform that moved during a "
                        "static, or warm-up drift; the estimates and their sigma are not to be trusted")
    fitted, sigma = fit.gyro.amplitude_check
    expected = joint.EARTH_RATE * np.cos(np.radians(site.latitude_deg))
    if abs(fitted - expected) > 3 * sigma + 0.05 * expected:
        warnings.append(f"the gyros see a horizontal Earth rate of {fitted / DEG * 3600:.2f} +- "
                        f"{sigma / DEG * 3600:.2f} deg/h where {expected / DEG * 3600:.2f} deg/h is expected: "
                        "model mismatch (platform disturbed, wrong latitude, scale error?)")
    return warnings

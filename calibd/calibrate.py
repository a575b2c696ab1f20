"""Calibration of a session: find the segments, run a method, build the result.

The same functions serve `calibd calibrate` and the daemon on live data: the methods take a
session (calibd.session), never bytes. Of a capture, one power-up is calibrated, from where its
warm-up ends.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.special import gammaincc

from stim300.clock import CYCLE_S

from . import detect, gaps, spec
from .errors import CalibrationError
from .estimators import joint, thesis
from .frames import EARTH_RATE, STANDARD_GRAVITY, Site, int_to_imu
from .results import ESTIMATES, CalibrationResult, make_result
from .scenario import Noise
from .segments import segment_record, session_segments
from .session import CaptureSessions, Session, power_up_session
from .units import DEG
from .warmup import NOT_WARMED_UP, record_settling, warm_up_warnings


class ProtocolIncomplete(CalibrationError):
    """The session lacks segments a method needs: why (`reason`) and what it has (`found`)."""

    def __init__(self, reason: str, found: str):
        super().__init__(f"{reason}; found {found}")
        self.reason, self.found = reason, found


def calibrate_capture(capture: CaptureSessions, solve, power_up: int | None = None,
                      start_s: float | None = None) -> CalibrationResult:
    """`solve(session) -> result` on power-up `power_up`, or on the last power-up that has what
    the method needs. Estimates of a power-up whose temperature never settles are flagged."""
    count = len(capture.power_ups)
    numbers = [power_up] if power_up is not None else range(count, 0, -1)
    refusals = []
    for number in numbers:
        session = power_up_session(capture, number, start_s)
        try:
            result = solve(session)
        except CalibrationError as exc:
            refusals.append(f"power-up {number} of {count}: {exc}" if count > 1 else str(exc))
            continue
        if number < count:
            passed_over = f"; the later ones lack what the method needs ({'; '.join(refusals)})" if refusals else ""
            result = result.with_warning(
                f"the sensor restarted after this power-up ({number} of {count}){passed_over}: these biases are "
                "this power-up's, turn-on biases change at every restart")
        verdict = record_settling(session.time_s, session.temperature_c)
        if verdict is not None and not verdict.settled:
            result = result.flag_poor(result.estimates, NOT_WARMED_UP)
        return replace(result, session_id=capture_session_id(capture, number, session),
                       capture={"path": capture.path, **capture.identity,
                                "serial_number": capture.sensor.get("serial_number")})
    raise CalibrationError("; ".join(refusals))


def capture_session_id(capture: CaptureSessions, number: int, session: Session) -> str:
    """The data a result of a capture rests on, as "SHA256[:16]/pN/tSTART": the file's first 16
    hex digits of SHA-256, the power-up and the start (s into it). The same capture and start
    options give the same id, whatever the method."""
    return f"{capture.identity['sha256'][:16]}/p{number}/t{session.stream['start_s']:.3f}"


BENCH_HINT = "this looks like the bench campaign: use --method thesis --bench"


def _lacking(what: str, segments: list[detect.Segment]) -> ProtocolIncomplete:
    """The refusal of a method whose protocol the segments lack; when they hold the whole bench
    campaign instead (a single-mounting method meets six mountings), it says which method fits."""
    found = detect.protocol_progress(segments)
    return ProtocolIncomplete(what, f"{found}; {BENCH_HINT}" if not bench_lacking(segments) else found)


def _session_warnings(session: Session) -> list[str]:
    """What is wrong with the data itself: faults the sensor flagged, gaps the time base had to
    be corrected for, a warm-up not over."""
    flagged = session.stream.get("flagged_datagrams", 0)
    faults = [f"{flagged} datagrams carry fault flags ({', '.join(session.stream['fault_flags'])}): their samples "
              "are in the fit; an overload or channel error biases the statics they fall in"] if flagged else []
    hidden = session.stream.get("hidden_gaps", 0)
    if hidden:
        faults.append(f"time base corrected: the host clock shows {session.stream['hidden_gap_s']:.3f} s of data "
                      f"lost in {hidden} gap{'s' if hidden > 1 else ''} the datagram counter could not see (whole "
                      f"{CYCLE_S:.3f} s counter cycles); that time was added")
    if session.incl is None:
        faults.append(NO_INCLINOMETERS)
    from_capture = "power_up" in session.stream  # calibd calibrate's --start can move its start; the daemon's cannot
    return faults + warm_up_warnings(session.time_s, session.temperature_c, start_hint=from_capture)


THESIS_DOC = "docs/thesis-estimators.md"  # where a user reads what the thesis method's warnings mean
NO_INCLINOMETERS = ("the unit has no inclinometers: pitch, roll and the accelerometer biases come from the "
                    "accelerometers alone, and no inclinometer bias is estimated")


def _needs_inclinometers(session: Session, method: str) -> None:
    """The thesis's chains take pitch and roll, and their own biases, from the inclinometers."""
    if session.incl is None:
        raise CalibrationError(f"method {method} needs inclinometers, and the unit has none (its datagrams carry "
                               "gyros and accelerometers only): use the joint method")


def _one_period(session: Session, turn: detect.Segment) -> tuple[slice, float]:
    """The samples eq. 6.31 averages over and the platform angle they cover (deg): the first whole
    revolution of the turn's constant-rate part, timed by the sample clock (a lost datagram
    does not lengthen it); the whole constant-rate part when it is shorter, as for a 360 deg turn
    with ramps (the thesis's own case)."""
    covered_deg = abs(turn.cruise_angle_deg)
    if covered_deg < 360.0:
        return slice(turn.cruise_start, turn.cruise_stop), covered_deg
    t = session.time_s
    end_s = t[turn.cruise_start] + 360.0 / abs(turn.rate_deg_s) - 0.5 / session.rate_hz
    return slice(turn.cruise_start, int(np.searchsorted(t, end_s))), 360.0


def _partial_period(covered_deg: float, site: Site) -> tuple[float, str]:
    """(bound on the unaveraged horizontal Earth rate, rad/s; the start of the warning that says
    so) for a window covering `covered_deg` of platform angle; (0, "") for a whole revolution."""
    if covered_deg >= 360.0:
        return 0.0, ""
    bound = thesis.unaveraged_earth_rate(covered_deg * DEG, site)
    return bound, (f"the full turn's constant-rate part covers {covered_deg:.0f} deg, not a whole revolution: the "
                   f"horizontal Earth rate does not average out of the turn's mean gyro; at "
                   f"{site.latitude_deg:.2f} deg latitude the rest is up to {bound / DEG * 3600:.2f} deg/h")


def _static_mean(values: np.ndarray, seg: detect.Segment) -> np.ndarray:
    return values[seg.start:seg.stop].mean(axis=0)


def thesis_real_case(session: Session, site: Site, alpha_beta_deg: tuple[float, float] | None = None,
                     platform_rate_deg_s: float | None = None,
                     segments: list[detect.Segment] | None = None) -> CalibrationResult:
    """The thesis's real-case chain on a session: nominal with alpha/beta given, else linear.
    `segments`: the session's, when already found."""
    _needs_inclinometers(session, "thesis")
    segments = session_segments(session) if segments is None else segments
    try:
        level = detect.level_static(segments)
        index = detect.index_positions(segments)
        turns = [t for t in detect.full_turns(segments) if t.start >= level.stop]
    except ValueError as exc:
        raise _lacking(f"not the thesis real-case protocol: {exc}", segments) from None
    if not turns:
        raise _lacking(f"not the thesis real-case protocol: no full turn (at least {detect.FULL_TURN_MIN_DEG:.0f} "
                       "deg) after the level static", segments)
    turn = turns[0]
    window, covered_deg = _one_period(session, turn)
    data = thesis.RealCaseData(
        level_gyro=_static_mean(session.gyro, level), level_acc=_static_mean(session.acc, level),
        level_incl=_static_mean(session.incl, level),
        index_incl=np.array([_static_mean(session.incl, s) for s in index]),
        turn_gyro=session.gyro[window])
    alpha_beta = None if alpha_beta_deg is None else (alpha_beta_deg[0] * DEG, alpha_beta_deg[1] * DEG)
    rate = None if platform_rate_deg_s is None else platform_rate_deg_s * DEG
    est = thesis.real_case(data, site, alpha_beta, rate)
    earth_bound, partial = _partial_period(covered_deg, site)
    yaw_bound_deg = earth_bound / (EARTH_RATE * np.cos(np.radians(site.latitude_deg))) / DEG  # eq. 6.32
    if partial and alpha_beta is None:  # eq. 7.3 puts the turn's Y and X means into alpha and beta
        tilt_bound_deg = earth_bound / abs(est["platform_rate"]) / DEG
        partial += f", which the linear run takes for interface tilt: up to {tilt_bound_deg:.4f} deg on alpha and beta"
    elif partial:
        partial += f" on the gyro Y bias, so up to {yaw_bound_deg:.1f} deg on yaw (yaw rests on that bias)"
    if partial:
        partial += f" ({THESIS_DOC}, the full turn as a platform runs it)"
    warnings = ([partial] if partial else []) + _session_warnings(session)
    warnings.append(f"incl_bias_z is assumed 0: rotations about the vertical cannot observe it ({THESIS_DOC})")
    if alpha_beta is not None:
        warnings.append("alpha and beta are a-priori values given by the user, not estimates")
    else:
        warnings.append("yaw is not observable with same-dataset (linear) alpha and beta: the linear tilt takes the "
                        "level static's Earth-rate term into alpha, so the yaw step returns 0 up to platform-rate "
                        f"errors; this yaw is not an estimate ({THESIS_DOC})")
    if rate is None:
        warnings.append("platform rate taken from the gyros (no telemetry given)")
    estimates = {"pitch": (est["pitch"], None), "roll": (est["roll"], None), "yaw": (est["yaw"], None),
                 "alpha": (est["alpha"], None), "beta": (est["beta"], None)}
    for name in ("gyro_bias", "acc_bias", "incl_bias"):
        estimates |= {f"{name}_{a}": (est[name][k], None) for k, a in enumerate("xyz")}
    records = ([segment_record(level, "level static")]
               + [segment_record(s, f"index position {k + 1}") for k, s in enumerate(index)]
               + [segment_record(turn, "full turn")])
    diagnostics = {role: _earth_rate_report(values, session.rate_hz, site)
                   for role, values in (("level static", session.gyro[level.start:level.stop]),
                                        ("full turn", session.gyro[window]))}
    result = make_result(est["method"], site, estimates, records, warnings, session.sensor,
                         stream=session.stream, platform_rate_deg_s=est["platform_rate"] / DEG,
                         earth_rate_diagnostic=diagnostics)
    if alpha_beta is None:  # not an estimate (the warning says why): flagged, so the rotation says so too
        result = result.flag_poor(("yaw",))
    elif yaw_bound_deg > YAW_SIGMA_POOR_DEG:  # can be as far off as a poor joint yaw
        result = result.flag_poor(("gyro_bias_y", "yaw"))
    return result


def _earth_rate_report(gyro: np.ndarray, rate_hz: int, site: Site) -> dict:
    """The section 6.3 diagnostic in display units (deg/h, Hz), without the spectra."""
    report = thesis.earth_rate_diagnostic(gyro, rate_hz, site)
    to_deg_h = 3600 / DEG
    return {"expected_amplitude_deg_h": report["expected_amplitude"] * to_deg_h,
            "peak_amplitude_deg_h": [a * to_deg_h for a in report["peak_amplitude"]],
            "peak_frequency_hz": report["peak_frequency_hz"], "visible": report["visible"]}


def bench_positions(segments: list[detect.Segment]) -> dict[str, detect.Segment]:
    """The bench protocol's six positions: the first static with each axis up, by axis ("+Z")."""
    positions = {}
    for s in segments:
        if s.kind == "static":
            positions.setdefault(s.up, s)
    return positions


def bench_lacking(segments: list[detect.Segment]) -> list[str]:
    """What the bench campaign lacks in these segments: a static with each axis up, a full turn."""
    positions = bench_positions(segments)
    lacking = [f"a static with {axis} up" for axis in thesis.UP_AXES if axis not in positions]
    if not detect.full_turns(segments):
        lacking.append(f"a full turn (at least {detect.FULL_TURN_MIN_DEG:.0f} deg)")
    return lacking


def thesis_bench(session: Session, site: Site, segments: list[detect.Segment] | None = None) -> CalibrationResult:
    """The bench campaign: six-position biases of every channel (eq. 5.3) and alpha/beta from
    every full turn (eqs. 5.6-5.8), averaged. `segments`: the session's, when already found."""
    _needs_inclinometers(session, "thesis-bench")
    segments = session_segments(session) if segments is None else segments
    statics = [s for s in segments if s.kind == "static"]
    positions = bench_positions(segments)
    missing = [axis for axis in thesis.UP_AXES if axis not in positions]
    if missing:
        raise CalibrationError(f"not the bench protocol: no static with {', '.join(missing)} up")
    biases = {name: thesis.six_position_biases({axis: _static_mean(values, seg) for axis, seg in positions.items()})
              for name, values in (("gyro", session.gyro), ("acc", session.acc), ("incl", session.incl))}
    turns = detect.full_turns(segments)
    if not turns:
        raise _lacking("not the bench protocol: no full turn for alpha and beta", segments)
    warnings, tilts = _session_warnings(session), []
    for turn in turns:
        before = [s for s in statics if s.stop <= turn.start and s.up == "+Z"]
        level = before[-1] if before else positions["+Z"]
        pitch, roll = thesis.pitch_roll(_static_mean(session.incl, level) - biases["incl"])
        window, covered_deg = _one_period(session, turn)
        earth_bound, partial = _partial_period(covered_deg, site)
        if partial:  # eq. 5.7 assumes the yaw term averaged out; its rest tilts the platform-rate vector
            warnings.append(f"{partial} in the turn at {turn.start_s:.0f} s, up to "
                            f"{earth_bound / abs(turn.rate_deg_s * DEG) / DEG:.4f} deg on its alpha and beta")
        rate = thesis.bench_platform_rate(session.gyro[window].mean(axis=0), biases["gyro"], pitch, roll, site)
        tilts.append(thesis.interface_tilt(rate))
    alpha, beta = np.mean(tilts, axis=0)
    estimates = {"alpha": (alpha, None), "beta": (beta, None)}
    for name, values in biases.items():
        estimates |= {f"{name}_bias_{a}": (values[k], None) for k, a in enumerate("xyz")}
    records = ([segment_record(positions[axis], f"{axis} up") for axis in thesis.UP_AXES]
               + [segment_record(t, "full turn") for t in turns])
    return make_result("thesis-bench", site, estimates, records, warnings, session.sensor, stream=session.stream,
                       turns_alpha_beta_deg=[[a / DEG, b / DEG] for a, b in tilts])


YAW_SIGMA_POOR_DEG = 5.0  # a yaw with a larger 1-sigma is flagged, not presented as usable


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


def joint_fit(session: Session, site: Site, options: joint.JointOptions = joint.JointOptions(),
              segments: list[detect.Segment] | None = None) -> JointFit:
    """The joint estimator's fit on every static and turning sample from the level static to the
    last static of the same mounting. `segments`: the session's, when already found. The
    datasheet figures are those of the sensor's accelerometer range, when its configuration
    datagram gave it (else `options`')."""
    segments = session_segments(session) if segments is None else segments
    if session.sensor.get("acc_range_g") in spec.ACC:
        options = replace(options, acc_range_g=session.sensor["acc_range_g"])
    try:
        level = detect.level_static(segments)
    except ValueError as exc:
        raise _lacking(str(exc), segments) from None
    used = [s for s in segments if s.start >= level.start]
    moved = next((k for k, s in enumerate(used) if s.kind == "static" and s.up != level.up), len(used))
    used = used[:moved]  # a re-mounting ends the single-axis model
    while used and used[-1].kind != "static":
        used.pop()
    statics = [s for s in used if s.kind == "static"]
    if not any(s.kind == "turn" for s in used):
        raise _lacking("no turn after the level static: yaw needs the platform to turn", segments)
    first, stop = level.start, used[-1].stop
    inp = joint.JointInput(
        time_s=session.time_s[first:stop] - session.time_s[first], gyro=session.gyro[first:stop],
        acc=session.acc[first:stop], incl=None if session.incl is None else session.incl[first:stop],
        statics=tuple((s.start - first, s.stop - first) for s in statics), rate_hz=session.rate_hz)
    try:
        fit = joint.solve(inp, site, options)
    except joint.Underdetermined as exc:
        raise _lacking(str(exc), segments) from None
    except np.linalg.LinAlgError:
        raise _lacking("the segments do not determine every parameter (too few platform angles)", segments) from None
    check = tilt_check(inp, fit, site)
    found = [t for t in check.turns if t.found] if check else []
    if not found:
        return JointFit(used, first, inp, seen_by_statics(fit, check), options, check, check)
    try:
        inp, fit = _corrected(inp, fit, site, options, found)
    except (joint.Underdetermined, np.linalg.LinAlgError) as exc:
        raise CalibrationError(f"the tilt the accelerometers and inclinometers see disagrees with the gyros' turn "
                               f"angles, and the corrected angles leave no usable fit ({exc})") from None
    final = tilt_check(inp, fit, site)
    return JointFit(used, first, inp, seen_by_statics(fit, final), options, check, final)


def checked_by_statics(inp: joint.JointInput, fit: joint.JointResult, site: Site) -> joint.JointResult:
    """The fit with what the turn-angle check of its statics sees of the factory residuals (the
    planner's view of a session; calibrate keeps the check too)."""
    return seen_by_statics(fit, tilt_check(inp, fit, site))


def seen_by_statics(fit: joint.JointResult, check: gaps.TiltCheck | None) -> joint.JointResult:
    """The fit with what the statics' forces saw of the factory residuals, where they were checked."""
    if check is None or check.factory is None:
        return fit
    return fit.with_factory_posterior(check.factory)


def tilt_check(inp: joint.JointInput, fit: joint.JointResult, site: Site) -> gaps.TiltCheck | None:
    """The turns' angles against the tilt; None when the statics cannot tell them."""
    a = int_to_imu(fit.estimates["alpha"], fit.estimates["beta"])
    try:
        return gaps.check_turn_angles(inp, fit.gyro.chi, a, site.gravity, fit.acc.noise, fit.incl and fit.incl.noise,
                                      fit.tilt.params[joint.TILT_PARAMS], fit.factory, fit.gyro.noise)
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


def joint_real_case(session: Session, site: Site, options: joint.JointOptions = joint.JointOptions(),
                    segments: list[detect.Segment] | None = None) -> CalibrationResult:
    """The joint estimator (docs/method.md, Estimators) on every static and turning sample from the level
    static to the last static of the same mounting. `segments`: the session's, when already found."""
    fitted = joint_fit(session, site, options, segments)
    used, fit = fitted.segments, fitted.fit
    warnings = (_session_warnings(session) + _vibration_warnings(fitted, session) + _joint_warnings(fit, site)
                + _turn_angle_warnings(fitted, session))
    estimates = {name: (fit.estimates[name], fit.sigmas[name]) for name in joint.ESTIMATE_NAMES
                 if name in fit.estimates}  # the order of fit.estimates, which is the covariance's
    result = make_result("joint", site, estimates, [segment_record(s, s.kind) for s in used], warnings,
                         session.sensor, fit.covariance, stream=session.stream,
                         options={"fixed_amplitude": options.fixed_amplitude, "drift": options.drift},
                         checks=_joint_checks(fit, site) | _turn_angle_checks(fitted, session),
                         bias_reference="turn-on", error_budget=error_budget_record(fit, fitted.options))
    if fit.sigmas["yaw"] / DEG > YAW_SIGMA_POOR_DEG:
        result = result.flag_poor(("yaw",))
    if fitted.final_tilt and fitted.final_tilt.p_value < CHI2_ALARM_P:
        result = result.flag_poor(PLATFORM_ANGLE_ESTIMATES)
    return result


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
        along = None if inp.incl is None else inp.incl[start:stop].mean(axis=0) / STANDARD_GRAVITY
        figures = joint.datasheet_noise(Noise.datasheet(fitted.options.acc_range_g), inp.rate_hz, along)
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
    return {"turn_angles": turns} | chi2


def _turn_angle_warnings(fitted: JointFit, session: Session) -> list[str]:
    """Turns whose angle the tilt corrected, turns it could not check, statics' forces that do
    not fit."""
    unseen = ("a datagram loss the counter cannot see (whole 0.128 s cycles) during a turn would go unnoticed "
              "except by the gyro chi-square")
    if fitted.turn_angles is None:
        return [f"the statics do not pin the turns' angles (statics at fewer than {gaps.MIN_HEADINGS} "
                f"headings): {unseen}"]
    warnings = []
    for t in fitted.turn_angles.turns:
        start_s, end_s = _turn_window_s(fitted, session, t)
        if t.found:
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
    return {"chi2": value, "dof": dof, "p_value": float(gammaincc(dof / 2, value / 2))}  # chi-square survival


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

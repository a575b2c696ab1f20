"""One-shot calibration of a capture: decode, find the segments, run a method, build the result.

The same functions serve `calibd calibrate` and, later, the daemon on live data: they take
decoded samples, never bytes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaincc

from stim300.bulk import decode_capture
from stim300.codec import fault_bits
from stim300.protocol import status_names

from . import detect
from .config import WarmupConfig
from .estimators import joint, thesis
from .frames import STANDARD_GRAVITY, Site
from .results import make_result

DEG = np.pi / 180
WARM_SLOPE_C_PER_H = WarmupConfig().max_slope_c_per_h  # the daemon's default warm-up criterion


class CalibrationError(ValueError):
    """The data cannot give this calibration (missing segments, wrong protocol); one line."""


class ProtocolIncomplete(CalibrationError):
    """The session lacks segments a method needs: why (`reason`) and what it has (`found`)."""

    def __init__(self, reason: str, found: str):
        super().__init__(f"{reason}; found {found}")
        self.reason, self.found = reason, found


@dataclass
class Session:
    """Decoded data in SI, with what is known of the sensor and the stream."""

    time_s: np.ndarray
    gyro: np.ndarray  # rad/s
    acc: np.ndarray  # m/s^2
    incl: np.ndarray  # m/s^2
    temperature_c: np.ndarray | None  # mean of the gyro temperatures, when the datagram has them
    rate_hz: int
    sensor: dict
    stream: dict


def load_session(path: str, start_s: float = 0.0, data: bytes | None = None) -> Session:
    """Decode a capture (the file at `path`, or its bytes already read); drop what comes before
    `start_s` (e.g. a warm-up)."""
    if data is None:
        with open(path, "rb") as f:
            data = f.read()
    samples, scanner = decode_capture(data)
    if not len(samples):
        raise CalibrationError(f"{path}: no STIM300 datagram found")
    fmt = scanner.format
    if fmt.gyro_unit.is_angle or fmt.acc_unit.is_velocity:
        raise CalibrationError(f"{path}: calibration needs rate and acceleration outputs, "
                               f"not {fmt.gyro_unit.name} / {fmt.acc_unit.name}")
    if np.isnan(samples["acc"][0, 0]) or np.isnan(samples["incl"][0, 0]):
        raise CalibrationError(f"{path}: datagram 0x{fmt.datagram_id:02X} lacks accelerometers or inclinometers")
    rate = fmt.sample_rate_hz or 2000 // scanner.stats.counter_step
    time_s = detect.sample_times(samples["counter"], rate)
    keep = time_s >= start_s
    temps = samples["temp_gyro"][keep].mean(axis=1)
    stats = scanner.stats
    return Session(
        time_s=time_s[keep], gyro=samples["gyro"][keep].astype(np.float64) * DEG,
        acc=samples["acc"][keep].astype(np.float64) * STANDARD_GRAVITY,
        incl=samples["incl"][keep].astype(np.float64) * STANDARD_GRAVITY,
        temperature_c=None if np.isnan(temps).all() else temps.astype(np.float64), rate_hz=rate,
        sensor={"serial_number": scanner.serial_number.text if scanner.serial_number else None,
                "part_number": str(scanner.part_number) if scanner.part_number else None,
                "datagram_id": f"0x{fmt.datagram_id:02X}", "sample_rate_hz": rate},
        stream={"capture": str(path), "start_s": float(start_s), "datagrams": stats.datagrams,
                "lost_samples": stats.lost_samples,
                "crc_errors": stats.crc_errors, "restarts": stats.restarts,
                **fault_record(*fault_summary(samples[keep]))})


def fault_summary(samples: np.ndarray) -> tuple[int, int]:
    """(samples the sensor flagged as faulty, the union of their fault bits)."""
    bits = fault_bits(samples)
    return int(np.count_nonzero(bits)), int(np.bitwise_or.reduce(bits)) if len(bits) else 0


def fault_record(count: int, bits: int) -> dict:
    return {"flagged_datagrams": count, "fault_flags": status_names(bits)}


def session_segments(session: Session) -> list[detect.Segment]:
    """The statics and turns of a whole session (the daemon tracks them incrementally instead)."""
    return detect.find_segments(session.gyro / DEG, session.acc / STANDARD_GRAVITY, session.rate_hz, session.time_s)


def _lacking(what: str, segments: list[detect.Segment]) -> ProtocolIncomplete:
    return ProtocolIncomplete(what, detect.protocol_progress(segments))


def _session_warnings(session: Session) -> list[str]:
    """What is wrong with the data itself: faults the sensor flagged, a warm-up not over."""
    flagged = session.stream.get("flagged_datagrams", 0)
    faults = [f"{flagged} datagrams carry fault flags ({', '.join(session.stream['fault_flags'])}): their samples "
              "are in the fit; an overload or channel error biases the statics they fall in"] if flagged else []
    return faults + _warm_up_warning(session)


def _warm_up_warning(session: Session) -> list[str]:
    t = session.temperature_c
    if t is None or len(t) < 2:
        return ["no temperatures in the datagram: warm-up cannot be checked"]
    slope = detect.temperature_trend_c_per_h(session.time_s, t)
    if abs(slope) > WARM_SLOPE_C_PER_H:
        return [f"temperature still moving {slope:+.1f} degC/h over the data: the IMU is not warmed up, biases "
                "drift (use --start to skip the warm-up)"]
    return []


def _segment_record(seg: detect.Segment, role: str) -> dict:
    record = {"kind": seg.kind, "role": role, "start_s": round(seg.start_s, 3), "end_s": round(seg.end_s, 3),
              "platform_angle_deg": round(seg.platform_angle_deg, 3)}
    if seg.kind == "turn":
        record |= {"angle_deg": round(seg.angle_deg, 3), "rate_deg_s": round(seg.rate_deg_s, 4)}
    elif seg.up:
        record["up"] = seg.up
    return record


def _one_period(session: Session, turn: detect.Segment) -> tuple[slice, list[str]]:
    """The first whole revolution of the turn's constant-rate part (eq. 6.31 integrates over
    one period); the whole constant-rate part, with a warning, when it is shorter."""
    period = int(round(360.0 / abs(turn.rate_deg_s) * session.rate_hz))
    have = turn.cruise_stop - turn.cruise_start
    if have >= period:
        return slice(turn.cruise_start, turn.cruise_start + period), []
    covered = have / session.rate_hz * abs(turn.rate_deg_s)
    return slice(turn.cruise_start, turn.cruise_stop), [
        f"the full turn's constant-rate part covers {covered:.0f} deg, not a whole revolution: the Earth-rate "
        f"term does not average out of the gyro Y bias (eq. 6.31)"]


def _static_mean(values: np.ndarray, seg: detect.Segment) -> np.ndarray:
    return values[seg.start:seg.stop].mean(axis=0)


def thesis_real_case(session: Session, site: Site, alpha_beta_deg: tuple[float, float] | None = None,
                     platform_rate_deg_s: float | None = None, segments: list[detect.Segment] | None = None) -> dict:
    """The thesis's real-case chain on a session: nominal with alpha/beta given, else linear.
    `segments`: the session's, when already found."""
    segments = session_segments(session) if segments is None else segments
    try:
        level = detect.level_static(segments)
        index = detect.index_positions(segments)
        turns = [t for t in detect.full_turns(segments) if t.start >= level.stop]
    except ValueError as exc:
        raise _lacking(f"not the thesis real-case protocol: {exc}", segments) from None
    if not turns:
        raise _lacking("not the thesis real-case protocol: no full turn (a constant-rate part of at "
                       "least 350 deg) after the level static", segments)
    turn = turns[0]
    window, warnings = _one_period(session, turn)
    data = thesis.RealCaseData(
        level_gyro=_static_mean(session.gyro, level), level_acc=_static_mean(session.acc, level),
        level_incl=_static_mean(session.incl, level),
        index_incl=np.array([_static_mean(session.incl, s) for s in index]),
        turn_gyro=session.gyro[window])
    alpha_beta = None if alpha_beta_deg is None else (alpha_beta_deg[0] * DEG, alpha_beta_deg[1] * DEG)
    rate = None if platform_rate_deg_s is None else platform_rate_deg_s * DEG
    est = thesis.real_case(data, site, alpha_beta, rate)
    warnings += _session_warnings(session)
    warnings.append("incl_bias_z is assumed 0: rotations about the vertical cannot observe it (thesis 6.1)")
    if alpha_beta is not None:
        warnings.append("alpha and beta are a-priori values given by the user, not estimates")
    else:
        warnings.append("yaw is not observable with same-dataset (linear) alpha and beta: eq. 7.3 folds the "
                        "level static's Earth-rate term into alpha, so eq. 6.32 returns 0 up to platform-rate "
                        "errors; this yaw is not an estimate")
    if rate is None:
        warnings.append("platform rate taken from the gyros (no telemetry given)")
    estimates = {"pitch": (est["pitch"], None), "roll": (est["roll"], None), "yaw": (est["yaw"], None),
                 "alpha": (est["alpha"], None), "beta": (est["beta"], None)}
    for name in ("gyro_bias", "acc_bias", "incl_bias"):
        estimates |= {f"{name}_{a}": (est[name][k], None) for k, a in enumerate("xyz")}
    records = ([_segment_record(level, "level static")]
               + [_segment_record(s, f"index position {k + 1}") for k, s in enumerate(index)]
               + [_segment_record(turn, "full turn")])
    diagnostics = {role: _earth_rate_report(values, session.rate_hz, site)
                   for role, values in (("level static", session.gyro[level.start:level.stop]),
                                        ("full turn", session.gyro[window]))}
    return make_result(est["method"], site, estimates, records, warnings, session.sensor,
                       stream=session.stream, platform_rate_deg_s=est["platform_rate"] / DEG,
                       earth_rate_diagnostic=diagnostics)


def _earth_rate_report(gyro: np.ndarray, rate_hz: int, site: Site) -> dict:
    """The section 6.3 diagnostic in display units (deg/h, Hz), without the spectra."""
    report = thesis.earth_rate_diagnostic(gyro, rate_hz, site)
    to_deg_h = 3600 / DEG
    return {"expected_amplitude_deg_h": report["expected_amplitude"] * to_deg_h,
            "peak_amplitude_deg_h": [a * to_deg_h for a in report["peak_amplitude"]],
            "peak_frequency_hz": report["peak_frequency_hz"], "visible": report["visible"]}


def thesis_bench(session: Session, site: Site) -> dict:
    """The bench campaign: six-position biases of every channel (eq. 5.3) and alpha/beta from
    every full turn (eqs. 5.6-5.8), averaged."""
    segments = session_segments(session)
    statics = [s for s in segments if s.kind == "static"]
    positions = {}
    for s in statics:  # the first static with each axis up
        positions.setdefault(s.up, s)
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
        window, notes = _one_period(session, turn)
        warnings += notes
        rate = thesis.bench_platform_rate(session.gyro[window].mean(axis=0), biases["gyro"], pitch, roll, site)
        tilts.append(thesis.interface_tilt(rate))
    alpha, beta = np.mean(tilts, axis=0)
    estimates = {"alpha": (alpha, None), "beta": (beta, None)}
    for name, values in biases.items():
        estimates |= {f"{name}_bias_{a}": (values[k], None) for k, a in enumerate("xyz")}
    records = ([_segment_record(positions[axis], f"{axis} up") for axis in thesis.UP_AXES]
               + [_segment_record(t, "full turn") for t in turns])
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


def joint_fit(session: Session, site: Site, options: joint.JointOptions = joint.JointOptions(),
              segments: list[detect.Segment] | None = None) -> JointFit:
    """The joint estimator's fit on every static and turning sample from the level static to the
    last static of the same mounting. `segments`: the session's, when already found."""
    segments = session_segments(session) if segments is None else segments
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
        acc=session.acc[first:stop], incl=session.incl[first:stop],
        statics=tuple((s.start - first, s.stop - first) for s in statics), rate_hz=session.rate_hz)
    try:
        fit = joint.solve(inp, site, options)
    except ValueError as exc:
        raise _lacking(str(exc), segments) from None
    except np.linalg.LinAlgError:
        raise _lacking("the segments do not determine every parameter (too few platform angles)", segments) from None
    return JointFit(used, first, inp, fit)


def joint_real_case(session: Session, site: Site, options: joint.JointOptions = joint.JointOptions(),
                    segments: list[detect.Segment] | None = None) -> dict:
    """The joint estimator (method.md §6) on every static and turning sample from the level
    static to the last static of the same mounting. `segments`: the session's, when already found."""
    fitted = joint_fit(session, site, options, segments)
    used, fit = fitted.segments, fitted.fit
    warnings = _session_warnings(session) + _joint_warnings(fit, site)
    estimates = {name: (fit.estimates[name], fit.sigmas[name]) for name in joint.ESTIMATE_NAMES}
    result = make_result("joint", site, estimates, [_segment_record(s, s.kind) for s in used], warnings,
                         session.sensor, stream=session.stream,
                         options={"fixed_amplitude": options.fixed_amplitude, "drift": options.drift},
                         checks=_joint_checks(fit, site), bias_reference="turn-on")
    if fit.sigmas["yaw"] / DEG > YAW_SIGMA_POOR_DEG:
        result["estimates"]["yaw"]["quality"] = "poor"
    return result


def _joint_checks(fit: joint.JointResult, site: Site) -> dict:
    fitted, sigma = fit.gyro.amplitude_check
    expected = joint.EARTH_RATE * np.cos(np.radians(site.latitude_deg))
    to_deg_h = 3600 / DEG
    return {"earth_rate_horizontal_deg_h": {"fitted": fitted * to_deg_h, "sigma": sigma * to_deg_h,
                                            "expected": expected * to_deg_h},
            "static_chi2": _chi2_record(fit),
            "gyro_residual_rms_deg_s": (fit.gyro.residual_rms / DEG).tolist(),
            "noise_excess_over_white": {"gyro": fit.gyro.noise_scale, "acc": fit.acc.noise_scale,
                                        "incl": fit.incl.noise_scale}}


CHI2_ALARM_P = 1e-3  # p-value below which the statics' residuals say the model does not hold


def _chi2_record(fit: joint.JointResult) -> dict:
    value, dof = fit.gyro.static_chi2
    return {"chi2": value, "dof": dof, "p_value": float(gammaincc(dof / 2, value / 2))}  # chi-square survival


def _joint_warnings(fit: joint.JointResult, site: Site) -> list[str]:
    warnings = ["biases are turn-on biases (the sensor's at this power-up): their 1-sigma includes the "
                "bias-instability wander over the session, which moves the bias the data carry away from them",
                "horizontal accelerometer and inclinometer biases rest on the gyro-derived alpha and beta "
                "(a single rotation axis cannot separate them from the IMU tilt otherwise): an error "
                "d_beta moves the X biases by g0 d_beta, and their 1-sigma carries it"]
    if site.g0 is None:
        warnings.append(f"Z accelerometer and inclinometer biases rest on normal gravity: their 1-sigma includes "
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

"""The thesis's real-case chain (`thesis`): a level static, statics at the four index headings and
a full turn after it, then a static, on one mounting; nominal with the interface tilt given,
else linear (docs/thesis-estimators.md). The maths is calibd.estimators.thesis."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import detect
from ..estimators import thesis
from ..frames import EARTH_RATE, Site
from ..results import CalibrationResult, make_result
from ..segments import segment_record, session_segments
from ..session import Session
from ..units import DEG
from . import bench
from .base import OptionError, Setting, refusal
from .common import (THESIS_DOC, YAW_SIGMA_POOR_DEG, judged_once_stopped, needs_inclinometers, one_period,
                     partial_period, session_warnings, static_mean)

CAMPAIGN = "thesis real-case campaign"
FULL_TURN = f"a full turn (at least {detect.FULL_TURN_MIN_DEG:.0f} deg)"


def _lacking(segments: list[detect.Segment]) -> str:
    """What the campaign lacks in segments that may end on a turn under way; "" when nothing."""
    statics = [s for s in segments if s.kind == "static"]
    if not statics:
        return f"a level static, statics at four platform headings 90 deg apart and {FULL_TURN} after it, then a static"
    absent = [str(90 * q) for q in range(4) if q not in detect.index_headings(segments)]
    turned = any(t.start >= statics[0].stop for t in detect.full_turns(segments))
    parts = ([f"{'a static at heading' if len(absent) == 1 else 'statics at headings'} {', '.join(absent)} deg"]
             if absent else []) + ([] if turned else [FULL_TURN])
    if parts:
        return " and ".join(parts) + " after the level static" + ("" if turned else ", then a static")
    return "" if segments[-1].kind == "static" else "a static after the last turn"


@dataclass(frozen=True)
class ThesisOptions:
    """The thesis real case: nominal with the interface tilt given, else linear."""

    alpha_beta_deg: tuple[float, float] | None = None  # a-priori interface tilt alpha, beta (deg)
    platform_rate_deg_s: float | None = None  # the full turn's rate from telemetry (default: from the gyros)


class Thesis:
    """The thesis's real-case chain: level static, four index positions, a full turn."""

    name = "thesis"
    settings = {key: Setting(float, lambda a: -10 <= a <= 10, "an interface tilt in [-10, 10] deg")
                for key in ("alpha_deg", "beta_deg")}

    def options(self, settings: Mapping[str, Any]) -> ThesisOptions:
        alpha, beta = settings.get("alpha_deg"), settings.get("beta_deg")
        if (alpha is None) != (beta is None):
            given, other, value = ("alpha_deg", "beta_deg", alpha) if beta is None else ("beta_deg", "alpha_deg", beta)
            raise OptionError(given, f"{value!r} given without {other}: give both (a-priori tilt) or neither "
                                     "(tilt estimated from the data)")
        return ThesisOptions(None if alpha is None or beta is None else (alpha, beta),
                             settings.get("platform_rate_deg_s"))

    def missing(self, segments: list[detect.Segment]) -> str | None:
        return judged_once_stopped(segments, _lacking)

    def solve(self, session, site, segments, options: ThesisOptions):
        return thesis_real_case(session, site, options.alpha_beta_deg, options.platform_rate_deg_s, segments)


METHOD = Thesis()


def thesis_real_case(session: Session, site: Site, alpha_beta_deg: tuple[float, float] | None = None,
                     platform_rate_deg_s: float | None = None,
                     segments: list[detect.Segment] | None = None) -> CalibrationResult:
    """The thesis's real-case chain on a session: nominal with alpha/beta given, else linear.
    `segments`: the session's, when already found."""
    needs_inclinometers(session, "thesis")
    segments = session_segments(session) if segments is None else segments
    if lacking := METHOD.missing(segments):
        raise refusal(CAMPAIGN, lacking, segments, bench.hint(segments))
    level = detect.level_static(segments)
    index = detect.index_positions(segments)
    turn = next(t for t in detect.full_turns(segments) if t.start >= level.stop)
    window, covered_deg = one_period(session, turn)
    data = thesis.RealCaseData(
        level_gyro=static_mean(session.gyro, level), level_acc=static_mean(session.acc, level),
        level_incl=static_mean(session.incl, level),
        index_incl=np.array([static_mean(session.incl, s) for s in index]),
        turn_gyro=np.asarray(session.gyro[window], dtype=np.float64))
    alpha_beta = None if alpha_beta_deg is None else (alpha_beta_deg[0] * DEG, alpha_beta_deg[1] * DEG)
    rate = None if platform_rate_deg_s is None else platform_rate_deg_s * DEG
    est = thesis.real_case(data, site, alpha_beta, rate)
    earth_bound, partial = partial_period(covered_deg, site)
    yaw_bound_deg = earth_bound / (EARTH_RATE * np.cos(np.radians(site.latitude_deg))) / DEG  # eq. 6.32
    if partial and alpha_beta is None:  # eq. 7.3 puts the turn's Y and X means into alpha and beta
        tilt_bound_deg = earth_bound / abs(est["platform_rate"]) / DEG
        partial += f", which the linear run takes for interface tilt: up to {tilt_bound_deg:.4f} deg on alpha and beta"
    elif partial:
        partial += f" on the gyro Y bias, so up to {yaw_bound_deg:.1f} deg on yaw (yaw rests on that bias)"
    if partial:
        partial += f" ({THESIS_DOC}, the full turn as a platform runs it)"
    warnings = ([partial] if partial else []) + session_warnings(session)
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
    diagnostics = {role: _earth_rate_report(np.asarray(values, dtype=np.float64), session.rate_hz, site)
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

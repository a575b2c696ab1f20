"""One solve of the session being collected: the method from the estimator registry (looked up
at every solve, so a reload's method applies at once), the result decorated with the daemon's
session record; and a result marked stale when it no longer applies (a restart after it, a trim
changed under it)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime, timezone

import structlog

from .. import detect
from ..config import MethodConfig
from ..errors import CalibrationError
from ..frames import Site
from ..methods import estimator, progress
from ..results import CalibrationResult, SessionRecord, StaleRecord
from ..session import Session
from ..units import value_sigma

log = structlog.get_logger("calibd")


@dataclass(frozen=True)
class Attempt:
    """What a solve gave: a result, or none and why (what the campaign lacks, what the data
    cannot give, or a fault of calibd: `failed`); `detail` is what the status says, in the words
    of `progress`, the session's progress record (STATE's `progress`)."""

    result: CalibrationResult | None
    detail: str
    progress: detect.Progress
    failed: bool = False


def solve(session: Session, segments: list[detect.Segment], site: Site, method: MethodConfig, options,
          number: int, session_id: str | None = None) -> Attempt:
    """Solve session `number` (its segments found) with the configured method and its `options`
    (`Estimator.options` of the configuration's settings, made once per configuration: the joint
    method's read the intrinsics' files); `session_id`: the daemon session's id, written in every
    result of it."""
    duration_s = float(session.time_s[-1])
    chosen = estimator(method.name)
    record = progress(method.name, segments)
    if not record.complete:
        return Attempt(None, f"collecting: {duration_s:.0f} s of data, {record.words()}", record)
    try:
        result = chosen.solve(session, site, segments, options)
    except CalibrationError as exc:
        return Attempt(None, f"collecting: {duration_s:.0f} s of data; {exc}", record)
    except Exception as exc:  # a fault of calibd, not of the data: said as such, and the daemon runs on
        log.exception("solve_failed")
        return Attempt(None, f"solve failed: {type(exc).__name__}: {exc} (a fault in calibd; the log has its "
                             "traceback)", record, failed=True)
    solved_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
    result = replace(result, session_id=session_id, session=SessionRecord(number, duration_s, solved_at))
    yaw = result.estimates["yaw"]
    return Attempt(result, f"solved on {duration_s:.0f} s: yaw {value_sigma(yaw.value, yaw.sigma, yaw.unit)}; "
                           f"{record.words()}", record)


def stale_result(result: CalibrationResult, reason: str, power_up: str = "previous") -> CalibrationResult:
    """The result marked as no longer applying: a `stale` record (why, since when, and which
    power-up it belongs to: "previous" after a restart, "current" when the trim changed under it,
    "unknown") and the reason first among the warnings, so a consumer reading only result.json
    can tell."""
    since = datetime.now(timezone.utc).isoformat(timespec="seconds")
    return replace(result, stale=StaleRecord(power_up, reason, since)).with_warning(
        f"stale: {reason}", first=True)

"""Calibration of a capture: one power-up, from where its warm-up ends, solved by a method
(calibd.methods), the result identified by the capture and flagged where the power-up never warmed."""

from __future__ import annotations

from dataclasses import replace

from .errors import CalibrationError
from .results import CalibrationResult
from .session import CaptureSessions, Session, power_up_session
from .warmup import NOT_WARMED_UP, record_settling


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
                                "serial_number": capture.sensor.serial_number})
    raise CalibrationError("; ".join(refusals))


def capture_session_id(capture: CaptureSessions, number: int, session: Session) -> str:
    """The data a result of a capture rests on, as "SHA256[:16]/pN/tSTART": the file's first 16
    hex digits of SHA-256, the power-up and the start (s into it). The same capture and start
    options give the same id, whatever the method."""
    return f"{capture.identity['sha256'][:16]}/p{number}/t{session.stream['start_s']:.3f}"

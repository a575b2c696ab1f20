"""Calibration of a capture: one power-up, from where its warm-up ends, solved by a method
(calibd.methods), the result identified by the capture and flagged where the power-up never warmed."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from .errors import CalibrationError
from .results import CalibrationResult
from .session import CaptureSessions, Session, power_up_session
from .warmup import NOT_WARMED_UP, TEMPERATURE_POOR_SHARE, Settling, ramp_carried, ramp_words, record_settling


def solved_power_up(capture: CaptureSessions, solve, power_up: int | None = None,
                    start_s: float | None = None) -> tuple[int, Session, Any, list[str]]:
    """(number, session, solve(session), the later power-ups' refusals) of power-up `power_up`, or
    of the last power-up whose `solve` does not refuse; CalibrationError naming every refusal when
    none is left."""
    count = len(capture.power_ups)
    refusals = []
    for number in [power_up] if power_up is not None else range(count, 0, -1):
        session = power_up_session(capture, number, start_s)
        try:
            return number, session, solve(session), refusals
        except CalibrationError as exc:
            refusals.append(f"power-up {number} of {count}: {exc}" if count > 1 else str(exc))
    raise CalibrationError("; ".join(refusals))


def calibrate_capture(capture: CaptureSessions, solve, power_up: int | None = None,
                      start_s: float | None = None) -> CalibrationResult:
    """`solve(session) -> result` on power-up `power_up`, or on the last power-up that has what
    the method needs. Estimates of a power-up whose temperature never settles are flagged."""
    number, session, result, refusals = solved_power_up(capture, solve, power_up, start_s)
    count = len(capture.power_ups)
    if number < count:
        passed_over = f"; the later ones lack what the method needs ({'; '.join(refusals)})" if refusals else ""
        result = result.with_warning(
            f"the sensor restarted after this power-up ({number} of {count}){passed_over}: these biases are "
            "this power-up's, turn-on biases change at every restart")
    result = judged_by_temperature(result, record_settling(session.time_s, session.temperature_c))
    return replace(result, session_id=capture_session_id(capture, number, session),
                   capture={"path": capture.path, **capture.identity, "serial_number": capture.sensor.serial_number})


def judged_by_temperature(result: CalibrationResult, verdict: Settling | None) -> CalibrationResult:
    """A power-up whose temperature never settles: a slow ramp (RAMP_MODELLED_C_PER_H) that the
    result's sigma carries flags only the estimates it moves; a faster one, or a method whose
    sigma carries no temperature, every estimate."""
    if verdict is None or verdict.settled:
        return result
    budget = (result.error_budget or {}).get("sigma", {})
    if not ramp_carried(verdict) or not budget or \
            not all("temperature" in parts for parts in budget.values()):
        return result.flag_poor(result.estimates, NOT_WARMED_UP)
    moved = [name for name, e in result.estimates.items()
             if e.sigma and budget[name]["temperature"] >= TEMPERATURE_POOR_SHARE * e.sigma]
    return result.flag_poor(moved, ramp_words(verdict, moved))


def capture_session_id(capture: CaptureSessions, number: int, session: Session) -> str:
    """The data a result of a capture rests on, as "SHA256[:16]/pN/tSTART": the file's first 16
    hex digits of SHA-256, the power-up and the start (s into it). The same capture and start
    options give the same id, whatever the method."""
    return f"{capture.identity['sha256'][:16]}/p{number}/t{session.stream.start_s:.3f}"


def second_mounting(first: CaptureSessions, capture: CaptureSessions, site, options, sigma: float):
    """The joint fit of `capture`'s last power-up that holds the campaign, as the second mounting
    of the unit `first` holds (methods.joint.SecondMounting; `sigma`: rad, the fixture's turn's
    1-sigma about 180 deg). CalibrationError when it is another unit or the same capture."""
    from .methods.joint import SecondMounting, joint_fit

    if capture.identity["sha256"] == first.identity["sha256"]:
        raise CalibrationError("is the capture being calibrated: the second mounting is a capture of its own")
    ours, theirs = first.sensor.serial_number, capture.sensor.serial_number
    if ours and theirs and ours != theirs:
        raise CalibrationError(f"is of serial number {theirs}, the first mounting's of {ours}: a second mounting "
                               "is the same unit")
    alone = options.for_second_mounting()
    number, session, fitted, _ = solved_power_up(capture, lambda s: joint_fit(s, site, alone))
    verdict = record_settling(session.time_s, session.temperature_c)
    unsettled = None  # a slow ramp is in its fit's temperature part, which the budget carries through
    if verdict is not None and not verdict.settled and not ramp_carried(verdict):
        unsettled = "was taken while the IMU warmed up (its temperature never settled)"
    return SecondMounting(fitted.fit, {"path": capture.path, **capture.identity, "power_up": number}, sigma, unsettled)


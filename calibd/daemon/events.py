"""What the calibrator tells the world: its states, and the listeners it tells them to.

Listeners are given to the Calibrator when it is made (the result store, systemd's status line,
the structured log, a replay's printout), so every consumer of states and results is in view
where the daemon is wired, and none is set afterwards.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import structlog

from ..results import CalibrationResult

log = structlog.get_logger("calibd")


class State(str, Enum):
    STARTING = "STARTING"
    WARMING_UP = "WARMING_UP"
    COLLECTING = "COLLECTING"
    SOLVED = "SOLVED"
    RESTARTED = "RESTARTED"
    FAULT = "FAULT"


class Listener(Protocol):
    """One consumer of the calibrator's events; a class deriving from it hears nothing it does not
    define."""

    def on_state(self, state: State, detail: str, progress: dict | None = None) -> None:
        """The state, at every transition and whenever its detail changes, with the session's
        progress (STATE's `progress` fields, docs/protocol.md; None where a caller has none)."""

    def on_result(self, result: CalibrationResult) -> None:
        """A new result."""

    def on_stale(self, result: CalibrationResult) -> None:
        """The last result, now marked stale (the sensor restarted, or another sensor is on the port)."""


@dataclass(frozen=True)
class Callbacks(Listener):
    """A listener made of plain functions, for the events one cares about."""

    state: Callable[[State, str], None] = lambda state, detail: None
    result: Callable[[CalibrationResult], None] = lambda result: None
    stale: Callable[[CalibrationResult], None] = lambda result: None

    def on_state(self, state: State, detail: str, progress: dict | None = None) -> None:
        self.state(state, detail)

    def on_result(self, result: CalibrationResult) -> None:
        self.result(result)

    def on_stale(self, result: CalibrationResult) -> None:
        self.stale(result)


class StateLog(Listener):
    """The structured log: a `state` event at each change of state (FAULT at warning level: the
    data stopped), a `solved` event per result, a `result_stale` warning when the last result
    stops applying (a restart, or another sensor on the port: the state need not change)."""

    def __init__(self) -> None:
        self._state = State.STARTING

    def on_state(self, state: State, detail: str, progress: dict | None = None) -> None:
        if state != self._state:
            (log.warning if state == State.FAULT else log.info)("state", state=state.value, detail=detail)
        self._state = state

    def on_result(self, result: CalibrationResult) -> None:
        log.info("solved", **{name: round(e.value, 6) for name, e in result.estimates.items()},
                 units={name: e.unit for name, e in result.estimates.items()})

    def on_stale(self, result: CalibrationResult) -> None:
        log.warning("result_stale", reason=result.stale.reason)

"""One power-up's data as the daemon collects it (where a power-up ends is
`calibd.session.PowerUpCuts`, the rule captures are cut by too).

`Collector` keeps one power-up: its counter clock, its block-averaged store, the gaps the counter could not see, and
the session collected from it with its segments (each logged once it is final).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import structlog

from stim300.clock import CounterClock
from stim300.records import SensorRecord

from .. import detect
from ..config import DetectionConfig
from ..frames import STANDARD_GRAVITY
from ..results import ResultStream
from ..segments import segment_record
from ..session import Session, SessionBuilder, fault_record, hidden_gap_record, inclinometers, stored_rate_hz
from ..units import DEG

log = structlog.get_logger("calibd")
MAX_SESSION_S = 3600  # beyond this a session stops growing: bias instability floors yaw near 0.9 deg
# for static campaigns (calibd plan: 1.28 deg at 1 h for the thesis layout), and memory stays bounded


class Collector:
    """One power-up's data: times from its counter (`stim300.clock`), samples block-averaged
    (`SessionBuilder`), hidden gaps, and the session being collected (from `session_start_s`)."""

    def __init__(self) -> None:
        self.data = SessionBuilder()  # block-averaged to calibd.session.STORE_RATE_HZ
        self._clock = CounterClock()
        self._hidden: list[tuple[float, float]] = []  # gaps the counter could not see: (time, seconds added)
        self._unchecked_until_s = -np.inf  # the end of the last batch without host times to look for them
        self.session_start_s: float | None = None
        self.tracker: detect.SegmentTracker | None = None
        self.rate_hz = 0

    @property
    def end_s(self) -> float:
        """Data time of the last stored sample (s since power-up)."""
        return self.data.end_s

    @property
    def stored_rate_hz(self) -> int:
        return stored_rate_hz(self.rate_hz)

    def times(self, samples: np.ndarray, rate_hz: int) -> np.ndarray:
        """Seconds since the first sample after power-up, from the counter and the host read
        times: lost datagrams, within a batch or between batches, leave gaps, whole counter
        cycles included. The clock proves whole cycles lost only SETTLE_S after them (a host
        stall looks alike until the reader has caught up), so the samples stored since move."""
        self.rate_hz = rate_hz
        times = self._clock.times(samples["counter"], rate_hz, samples["t_host"])
        if not times.checked:
            self._unchecked_until_s = float(times.time_s[-1])
        for at, seconds in times.moved:  # found after the samples from `at` on were stored: they move
            self.data.shift(at, seconds)
            self._hidden_gap(at + seconds, seconds)
        for index, seconds in zip(times.gap_index, times.gap_s):
            self._hidden_gap(float(times.time_s[index]), float(seconds))
        return times.time_s

    def _hidden_gap(self, at: float, seconds: float) -> None:
        self._hidden.append((at, seconds))
        log.warning("hidden_gap", at_s=round(at, 3), added_s=round(seconds, 3),
                    detail="datagrams lost for whole counter cycles: the host clock's time added")

    def store(self, samples: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Keep a batch timed by `times`; returns the times (s) and gyro samples (deg/s) stored,
        or None once the session is MAX_SESSION_S long (it has said what it can: memory stays
        bounded)."""
        if self.session_start_s is not None and time_s[-1] - self.session_start_s > MAX_SESSION_S:
            return None
        return self.data.add(samples, time_s, self.rate_hz)

    def start_session(self, start_s: float, detection: DetectionConfig) -> None:
        """Collect a session from `start_s` on: older data are forgotten, segments found afresh."""
        self.data.trim(start_s)
        self._hidden = [h for h in self._hidden if h[0] >= start_s]
        self.session_start_s = start_s
        self.tracker = detect.SegmentTracker(self.stored_rate_hz, **detection.options())

    def session(self, sensor: SensorRecord, stream: ResultStream) -> Session:
        """The session so far, in its own time; `stream` gains the session's fault records."""
        d = self.data.arrays(since_s=self.session_start_s)
        return Session(time_s=d["time_s"] - d["time_s"][0], gyro=d["gyro"], acc=d["acc"], incl=inclinometers(d["incl"]),
                       temperature_c=None if np.isnan(d["temp"]).all() else d["temp"], rate_hz=self.stored_rate_hz,
                       sensor=sensor, stream=replace(stream, **self._fault_record()))

    def _fault_record(self) -> dict:
        hidden = [seconds for t, seconds in self._hidden if t > self.session_start_s]
        return fault_record(*self.data.fault_summary(self.session_start_s)) \
            | hidden_gap_record(None if self._unchecked_until_s >= self.session_start_s else hidden)

    def segments(self, session: Session) -> list[detect.Segment]:
        """The session's segments so far; each is logged once it is final."""
        logged = len(self.tracker.final)
        segments = self.tracker.update(session.gyro / DEG, session.acc / STANDARD_GRAVITY, session.time_s)
        for seg in self.tracker.final[logged:]:  # final: no later data changes them
            _log_segment(seg)
        return segments


def _log_segment(seg: detect.Segment) -> None:
    """One event per segment of the session, in the session's time and platform angle."""
    turn = {"cruise_angle_deg": round(seg.cruise_angle_deg, 3)} if seg.kind == "turn" else {}
    log.info("segment", **segment_record(seg), duration_s=round(seg.end_s - seg.start_s, 3), **turn)

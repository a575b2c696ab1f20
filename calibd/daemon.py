"""The calibration daemon's logic: decoded samples in, states and results out.

`Calibrator` holds no I/O: the live loop (`calibd run`), the replay of a capture and the tests
feed it the same batches of samples. States: STARTING -> WARMING_UP -> COLLECTING -> SOLVED,
with RESTARTED (the sensor power-cycled: turn-on biases changed, a new session starts) and FAULT
(no data). Once warmed up, it solves as soon as the method's protocol is complete (the platform
stopped after a turn, and the session's segments hold what the method needs), again every
`resolve_every_s` of new data, and once more at the end of the data (`finish`: the end of a
replay, or a sensor restart, which ends the previous power-up's data). A restart marks the
previous power-up's result stale at once (`stale_result`).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path

import numpy as np
import structlog

from stim300.atomic import write_atomic
from stim300.clock import CounterClock
from stim300.codec import start_up_flags, start_up_rises

from . import detect
from .config import DetectionConfig, MethodConfig, WarmupConfig
from .errors import CalibrationError
from .methods import estimator
from .frames import STANDARD_GRAVITY, Site
from .results import CalibrationResult, result_json
from .segments import segment_record
from .session import Session, SessionBuilder, fault_record, hidden_gap_record, stored_rate_hz
from .units import DEG
from .warmup import settling

log = structlog.get_logger("calibd")
MAX_SESSION_S = 3600  # beyond this a session stops growing: bias instability floors yaw near 0.9 deg
# for static protocols (calibd plan: 1.28 deg at 1 h for the thesis layout), and memory stays bounded
WARM_CHECK_EVERY_S = 10.0  # how often (data time) the warm-up rule is evaluated


class State(str, Enum):
    STARTING = "STARTING"
    WARMING_UP = "WARMING_UP"
    COLLECTING = "COLLECTING"
    SOLVED = "SOLVED"
    RESTARTED = "RESTARTED"
    FAULT = "FAULT"


class Calibrator:
    """The daemon's state machine and online estimation; `on_result(result)` (a new result),
    `on_stale(result)` (the last result, now marked as the previous power-up's) and
    `on_state(state, detail)` are called as things happen."""

    def __init__(self, site: Site, warmup: WarmupConfig = WarmupConfig(), method: MethodConfig = MethodConfig(),
                 on_result=None, on_state=None, source: str = "live", detection: DetectionConfig = DetectionConfig(),
                 on_stale=None):
        self.site, self.warmup, self.method, self.detection = site, warmup, method, detection
        self.source = source  # the port or capture, named in results
        self.on_result = on_result or (lambda result: None)
        self.on_state = on_state or (lambda state, detail: None)
        self.on_stale = on_stale or (lambda result: None)
        self.state = State.STARTING
        self.detail = "waiting for data"
        self.result: CalibrationResult | None = None
        self.sessions = 0
        self.sensor: dict = {}
        self._restarts_seen = 0
        self._start_up_before = True  # whether the last sample fed had the start-up bit (none yet: as if)
        self._reset_time()

    # ------------------------------------------------------------------ feeding
    def configure(self, site: Site, warmup: WarmupConfig, method: MethodConfig,
                  detection: DetectionConfig = DetectionConfig()) -> None:
        """New settings (SIGHUP): they apply from the next solution on (detection: the next session)."""
        self.site, self.warmup, self.method, self.detection = site, warmup, method, detection

    def sensor_seen(self, identity: dict) -> None:
        """The sensor as the stream names it (serial and part number, datagram, rate): results carry it."""
        self.sensor = identity

    def feed(self, samples: np.ndarray, rate_hz: int, restarts: int = 0) -> None:
        """A batch of decoded samples (stim300.codec.SAMPLE_DTYPE) in stream order; `restarts` is
        the stream parser's running count of sensor restarts."""
        if restarts > self._restarts_seen:
            self._restarts_seen = restarts
            self._power_cycled()
            self._start_up_before = True  # the new power-up's start-up bit is not a second restart
        rises = start_up_rises(samples, self._start_up_before)
        if len(rises):  # a restart whose power-up datagrams were lost: the start-up bit tells
            self.feed(samples[:rises[0]], rate_hz, restarts)
            self._power_cycled()
            self._start_up_before = True
            self.feed(samples[rises[0]:], rate_hz, restarts)
            return
        if not len(samples):
            return
        self._start_up_before = bool(start_up_flags(samples[-1:])[0])
        if np.isnan(samples["acc"][0, 0]) or np.isnan(samples["incl"][0, 0]):
            self._set(State.FAULT, f"datagram 0x{samples['datagram_id'][0]:02X} has no accelerometers or "
                                   "inclinometers: nothing to calibrate with")
            return
        self.rate_hz = rate_hz
        t = self._times(samples, rate_hz)
        if self._gap and self._session_start is not None:
            self._start_session(float(t[0]), "data again after a gap: the platform angle was lost, "
                                             "collecting a new session (warm-up stands)")
        elif self.state in (State.STARTING, State.RESTARTED, State.FAULT):
            self._set(State.WARMING_UP if self._session_start is None else State.COLLECTING,
                      "waiting for the temperature to settle" if self._session_start is None else "data again")
        self._gap = False
        if self._session_start is not None and t[-1] - self._session_start > MAX_SESSION_S:
            return  # a session this long has said what it can: memory stays bounded
        stored_t, stored_gyro = self._buffer.add(samples, t, rate_hz)
        now = self._buffer.end_s
        if self.state == State.WARMING_UP and now >= self._next_check:
            self._next_check = now + WARM_CHECK_EVERY_S
            self._check_warm_up()
        elif self.state in (State.COLLECTING, State.SOLVED):
            if now >= self._next_solve:
                self._solve()
            elif self._stopped_moving(stored_t, stored_gyro):
                self._solve_if_complete()

    def finish(self) -> None:
        """The end of the data (a replay's last byte, or the sensor's power-up before a restart):
        solve once more on all of the session, so its last segments (the full turn, the final
        static) count, not only those of the last re-solve."""
        if self._session_start is not None and self._buffer.end_s > self._solved_until:
            self._solve()

    def data_lost(self, seconds: float) -> None:
        """The live loop saw no data for `seconds`: a fault until data flows again. The platform
        may have turned meanwhile, so the platform angle is lost: a session being collected
        starts again when data returns (the warm-up stands unless the sensor restarted)."""
        self._set(State.FAULT, f"no data for {seconds:.0f} s (port lost or sensor off)")
        self._gap = True

    # ------------------------------------------------------------------ internals
    def _reset_time(self) -> None:
        self._buffer = SessionBuilder()  # block-averaged to calibd.session.STORE_RATE_HZ
        self._clock = CounterClock()
        self._hidden: list[tuple[float, float]] = []  # gaps the counter could not see: (time, seconds added)
        self._unchecked_until = -np.inf  # the end of the last batch without host times to look for them
        self._session_start: float | None = None
        self._tracker: detect.SegmentTracker | None = None
        self._gap = False
        self._next_solve = 0.0
        self._next_check = 0.0
        self._solved_until = -np.inf  # data time of the last solve attempt
        self._moved = False  # the platform moved since the last look at the segments
        self._last_motion_s = -np.inf  # data time of the end of the last motion seen
        self.rate_hz = 0

    def _power_cycled(self) -> None:
        """A restart ends the previous power-up's data: solve it to its end, mark its result as
        belonging to that power-up (turn-on biases change at every power-up), start afresh."""
        self.finish()
        reason = "sensor restarted: turn-on biases changed, starting a new session"
        if self.result is not None and self.result.stale is None:
            self.result = stale_result(self.result, "the sensor restarted after this result: it belongs to the "
                                                    "previous power-up (turn-on biases change at every power-up)")
            self.on_stale(self.result)
            reason += "; the last result is the previous power-up's, marked stale"
        self._set(State.RESTARTED, reason)
        self._reset_time()

    def _times(self, samples: np.ndarray, rate_hz: int) -> np.ndarray:
        """Seconds since the first sample after power-up, from the counter and the host read
        times (`stim300.clock`): lost datagrams, within a batch or between batches, leave gaps,
        whole counter cycles included."""
        times = self._clock.times(samples["counter"], rate_hz, samples["t_host"])
        if not times.checked:
            self._unchecked_until = float(times.time_s[-1])
        for index, seconds in zip(times.gap_index, times.gap_s):
            at = float(times.time_s[index])
            self._hidden.append((at, float(seconds)))
            log.warning("hidden_gap", at_s=round(at, 3), added_s=round(float(seconds), 3),
                        detail="datagrams lost for whole counter cycles: the host clock's time added")
        return times.time_s

    def _stopped_moving(self, t: np.ndarray, gyro_deg_s: np.ndarray) -> bool:
        """Whether the platform moved since the segments were last looked at and has been quiet
        since for the settle time plus the minimum static, the least after which the detector
        shows a new static. Moving: a gyro average over the detector's smoothing window above
        its turn threshold (its floor before the tracker's first update)."""
        settings = self._tracker.settings
        if len(t):
            threshold = settings["turn_threshold_deg_s"] or detect.MIN_TURN_THRESHOLD_DEG_S
            k = min(len(t), max(1, round(settings["smooth_s"] * self._stored_rate)))
            edges = np.arange(0, len(t) - k + 1, k)  # a short remainder joins the last window
            sizes = np.diff(np.append(edges, len(t)))
            means = np.add.reduceat(gyro_deg_s, edges, axis=0) / sizes[:, None]
            moving = np.flatnonzero(np.linalg.norm(means, axis=1) > threshold)
            if len(moving):
                self._moved = True
                self._last_motion_s = float(t[edges[moving[-1]] + sizes[moving[-1]] - 1])
        quiet_s = self._buffer.end_s - self._last_motion_s
        return self._moved and quiet_s >= settings["settle_s"] + settings["min_static_s"]

    def _solve_if_complete(self) -> None:
        """Once the platform has stopped: solve if the segments now end on a static (it lasted the
        settle time and the minimum static) and hold what the method needs."""
        session, segments = self._segments()
        if not segments or segments[-1].kind != "static":
            return  # the static after the motion is not long enough yet: look again next batch
        self._moved = False
        if detect.protocol_complete(segments, self.method.name):
            self._solve((session, segments))

    @property
    def _stored_rate(self) -> int:
        return stored_rate_hz(self.rate_hz)

    def _check_warm_up(self) -> None:
        """The warm-up rule (calibd.warmup) on the data since the last check's window: the session
        starts at the first window that settled."""
        rule, data = self.warmup, self._buffer
        elapsed = data.end_s
        data.trim(elapsed - rule.window_s - WARM_CHECK_EVERY_S - 1.0)
        if elapsed < max(rule.window_s, rule.min_time_s):
            self._set(State.WARMING_UP, f"warming up: {elapsed:.0f} s since power-up")
            return
        recent = data.arrays()
        no_temperature = np.isnan(recent["temp"]).all()
        verdict = settling(recent["time_s"], None if no_temperature else recent["temp"], rule)
        if not verdict.settled:
            self._set(State.WARMING_UP, f"warming up: temperature moving {verdict.trend_c_per_h:+.2f} degC/h")
            return
        how = (f"{rule.window_s:.0f} s since power-up (no temperatures in the datagram: time since power-up only)"
               if no_temperature else f"{verdict.trend_c_per_h:+.2f} degC/h over {rule.window_s:.0f} s")
        self._start_session(verdict.start_s, f"warmed up ({how})")
        self._solve()

    def _start_session(self, start_s: float, detail: str) -> None:
        self._buffer.trim(start_s)
        self._hidden = [h for h in self._hidden if h[0] >= start_s]
        self._session_start = start_s
        self._tracker = detect.SegmentTracker(self._stored_rate, **self.detection.options())
        self._next_solve = self._buffer.end_s + self.method.resolve_every_s
        self._moved = False
        self.sessions += 1
        self._set(State.COLLECTING, detail)

    def _session(self) -> Session:
        d = self._buffer.arrays(since_s=self._session_start)
        return Session(time_s=d["time_s"] - d["time_s"][0], gyro=d["gyro"], acc=d["acc"], incl=d["incl"],
                       temperature_c=None if np.isnan(d["temp"]).all() else d["temp"], rate_hz=self._stored_rate,
                       sensor=self.sensor, stream={"capture": self.source, "session": self.sessions,
                                                   **self._fault_record()})

    def _fault_record(self) -> dict:
        hidden = [seconds for t, seconds in self._hidden if t > self._session_start]
        return fault_record(*self._buffer.fault_summary(self._session_start)) \
            | hidden_gap_record(None if self._unchecked_until >= self._session_start else hidden)

    def _segments(self) -> tuple[Session, list[detect.Segment]]:
        """The session so far and its segments; each segment is logged once it is final."""
        session = self._session()
        logged = len(self._tracker.final)
        segments = self._tracker.update(session.gyro / DEG, session.acc / STANDARD_GRAVITY, session.time_s)
        for seg in self._tracker.final[logged:]:  # final: no later data changes them
            _log_segment(seg)
        return session, segments

    def _solve(self, found: tuple[Session, list[detect.Segment]] | None = None) -> None:
        """Solve on the session so far (`found`: it and its segments, when just looked at)."""
        session, segments = found or self._segments()
        self._solved_until = self._buffer.end_s
        self._next_solve = self._solved_until + self.method.resolve_every_s
        method = estimator(self.method.name)
        lacking = method.missing(segments)
        if lacking is not None:
            if self.state != State.SOLVED:
                self._set(State.COLLECTING, f"collecting: {session.time_s[-1]:.0f} s of data, "
                                            f"{detect.protocol_progress(segments)}; waiting for: {lacking}")
            return
        try:
            result = method.solve(session, self.site, segments, method.options(asdict(self.method)))
        except CalibrationError as exc:
            if self.state != State.SOLVED:
                self._set(State.COLLECTING, f"collecting: {session.time_s[-1]:.0f} s of data; {exc}")
            return
        except Exception as exc:  # a fault of calibd, not of the data: said as such, and the daemon runs on
            log.exception("solve_failed")
            self._set(self.state, f"solve failed: {type(exc).__name__}: {exc} (a fault in calibd; the log "
                                  "has its traceback)")
            return
        result = replace(result, session={"number": self.sessions, "duration_s": float(session.time_s[-1]),
                                          "solved_at": datetime.now(timezone.utc).isoformat(timespec="seconds")})
        self.result = result
        yaw = result.estimates["yaw"]
        sigma = f" +- {yaw.sigma:.2f}" if yaw.sigma is not None else ""
        self._set(State.SOLVED, f"solved on {session.time_s[-1]:.0f} s: yaw {yaw.value:.2f}{sigma} deg")
        log.info("solved", **{name: round(e.value, 6) for name, e in result.estimates.items()},
                 units={name: e.unit for name, e in result.estimates.items()})
        self.on_result(result)

    def _set(self, state: State, detail: str) -> None:
        changed = state != self.state
        self.state, self.detail = state, detail
        if changed:
            log.info("state", state=state.value, detail=detail)
        self.on_state(state, detail)


def _log_segment(seg: detect.Segment) -> None:
    """One event per segment of the session, in the session's time and platform angle."""
    turn = {"cruise_angle_deg": round(seg.cruise_angle_deg, 3)} if seg.kind == "turn" else {}
    log.info("segment", **segment_record(seg), duration_s=round(seg.end_s - seg.start_s, 3), **turn)


def stale_result(result: CalibrationResult, reason: str) -> CalibrationResult:
    """The result marked as no longer applying: a `stale` record (why, since when, and that it
    belongs to the previous power-up) and the reason first among the warnings, so a consumer
    reading only result.json can tell."""
    since = datetime.now(timezone.utc).isoformat(timespec="seconds")
    return replace(result, stale={"power_up": "previous", "reason": reason, "since": since}).with_warning(
        f"stale: {reason}", first=True)


class ResultStore:
    """The state directory: result.json (the last good result, replaced atomically and synced,
    so a crash at any moment leaves it readable), history/ (every result, timestamped) and
    state.json (what `calibd status` shows)."""

    def __init__(self, state_dir):
        self.dir = Path(state_dir)
        (self.dir / "history").mkdir(parents=True, exist_ok=True)

    def write_result(self, result: CalibrationResult) -> Path:
        text = result_json(result)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
        write_atomic(self.dir / "history" / f"result-{stamp}.json", text)
        write_atomic(self.dir / "result.json", text)
        return self.dir / "result.json"

    def replace_result(self, result: CalibrationResult) -> Path:
        """Rewrite result.json only (the last result marked stale): history keeps it as it was made."""
        write_atomic(self.dir / "result.json", result_json(result))
        return self.dir / "result.json"

    def write_state(self, state: State, detail: str, extra: dict | None = None) -> None:
        record = {"state": state.value, "detail": detail, "updated": time.time(), **(extra or {})}
        write_atomic(self.dir / "state.json", (json.dumps(record) + "\n").encode(), durable=False)

"""The calibration daemon's state machine: decoded samples in, states and results out.

`Calibrator` holds no I/O: the live loop (`calibd run`), the replay of a capture and the tests
feed it the same batches of samples. States: STARTING -> WARMING_UP -> COLLECTING -> SOLVED,
with RESTARTED (the sensor power-cycled: turn-on biases changed, a new session starts) and FAULT
(no data). Once warmed up, it solves as soon as the method's campaign is complete (the platform
stopped after a turn, and the session's segments hold what the method needs), again every
`resolve_every_s` of new data, and once more at the end of the data (`finish`: the end of a
replay, or a sensor restart, which ends the previous power-up's data). A restart marks the
previous power-up's result stale at once (`stale_result`), and so does a stream naming another
sensor than an earlier daemon's result does, or a bias trim in force other than the one a result
records (its biases are of the output under that trim). A trim that changes while a session is
collected moves the output by the difference: a new session starts. A new result goes through
`trim` before anyone hears of it (the daemon's `[trim] apply = "volatile"`, `Trimmer`). The work is
its collaborators':
`Collector` (one power-up's data), `WarmWatch` (the warm-up rule), `SolveTrigger` (when to
solve), `solve` (the method); the listeners hear what happens.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import asdict, replace

import numpy as np
import structlog

from stim300.records import SensorRecord, StreamRecord, TrimRecord
from stim300.stream import TrimSeen

from .. import detect
from ..config import DetectionConfig, MethodConfig
from ..correction import other_sensor
from ..frames import Site
from ..methods import estimator, progress
from ..results import CalibrationResult, ResultStream
from ..session import PowerUpCuts, Session, checked_trim, missing_sensors
from ..warmup import WarmupConfig
from .collector import Collector
from .events import Listener, State
from .solver import solve, stale_result
from .trigger import SolveTrigger
from .warmwatch import Warmth, WarmWatch

log = structlog.get_logger("calibd")


class Calibrator:
    """The daemon's states and their transitions; `listeners` hear every state, result and stale
    result, in their order. `previous` is the result an earlier daemon left (result.json): it
    stands until this one solves, and a sensor restart marks it stale like its own, as does a
    stream whose serial number is not the result's (another unit on the port). `trim(result)`
    returns each new result as it is published and words added to the state's detail ("": none;
    `calibd.daemon.Trimmer` writes it into the sensor)."""

    def __init__(self, site: Site, warmup: WarmupConfig = WarmupConfig(), method: MethodConfig = MethodConfig(),
                 listeners: Sequence[Listener] = (), source: str = "live",
                 detection: DetectionConfig = DetectionConfig(), previous: CalibrationResult | None = None,
                 trim=lambda result: (result, ""), origin: dict | None = None):
        self.configure(site, warmup, method, detection)
        self.listeners = tuple(listeners)
        self._trim = trim
        self.source = source  # the port or capture, named in results
        self.origin = origin or {}  # what else results say of where the data came from (a replayed recording's topic)
        self.state = State.STARTING
        self.detail = "waiting for data"
        self.result = previous  # an earlier daemon's (result.json) until this one solves: a restart marks it stale
        self._inherited = previous  # checked against the stream's sensor while it is the result held
        self.sessions = 0
        self.session_id: str | None = None
        self.progress = progress(self.method.name, [])  # the session's progress record (detect.Progress)
        self.sensor = SensorRecord()
        self.stream_stats = StreamRecord()
        self._cuts = PowerUpCuts()
        self._trims: tuple[TrimSeen, ...] = ()  # the stream's latest BTO datagrams (`sensor_seen`)
        self._trims_taken = 0  # the sequence number of the last one acted on
        self._power_up_first = 0  # the stream number of this power-up's first sample
        self._new_power_up()

    def configure(self, site: Site, warmup: WarmupConfig, method: MethodConfig,
                  detection: DetectionConfig = DetectionConfig()) -> None:
        """New settings (SIGHUP): they apply from the next solution on (detection: the next session).
        The method's options are made here, once: its settings' files are read at a reload, not at
        every solve."""
        options = estimator(method.name).options(asdict(method))  # an OptionError leaves the settings in use
        self.site, self.warmup, self.method, self.detection, self.options = site, warmup, method, detection, options

    def sensor_seen(self, identity: SensorRecord, stream: StreamRecord = StreamRecord(),
                    trims: tuple[TrimSeen, ...] = ()) -> None:
        """The sensor as the stream names it (serial and part number, datagram, rate), the
        stream's statistics since the daemon began reading (StreamInfo.stream_record) and its
        latest Bias Trim Offset datagrams (`stim300.source.Batch.trims`, acted on as the next
        `feed` reaches where each came): results carry them."""
        self.sensor, self.stream_stats, self._trims = identity, stream, trims
        self._check_inherited(identity.serial_number)

    def feed(self, samples: np.ndarray, rate_hz: int, first: int = 0, restart_datagrams=()) -> None:
        """A batch of decoded samples (stim300.codec.SAMPLE_DTYPE) in stream order: `first` is the
        stream number of its first sample, `restart_datagrams` the stream number of each
        restarted sensor's first sample (the stream parser's, so far). A BTO datagram takes
        effect where it came: the samples before it are fed first."""
        at = first
        for restarted, piece in self._cuts.pieces(samples, first, restart_datagrams):
            if restarted:
                self._power_up_first = at
                self._power_cycled()
            for seen in self._trims_before(at + len(piece)):
                before = max(seen.datagram - at, 0)
                if before:
                    self._feed_power_up(piece[:before], rate_hz)
                piece, at = piece[before:], at + before
                self._trim_seen(seen.trim)
            if len(piece):
                self._feed_power_up(piece, rate_hz)
            at += len(piece)

    def finish(self) -> None:
        """The end of the data (a replay's last byte, or the sensor's power-up before a restart):
        solve once more on all of the session, so its last segments (the full turn, the final
        static) count, not only those of the last re-solve."""
        if self.collector.session_start_s is not None and self._trigger.unsolved(self.collector.end_s):
            self._solve()

    def data_lost(self, seconds: float) -> None:
        """The live loop saw no data for `seconds`: a fault until data flows again. The platform
        may have turned meanwhile, so the platform angle is lost: a session being collected
        starts again when data returns (the warm-up stands unless the sensor restarted)."""
        self._set(State.FAULT, f"no data for {seconds:.0f} s (port lost or sensor off)")
        self._fresh = "data again after a gap: the platform angle was lost, collecting a new session (warm-up stands)"

    def _feed_power_up(self, samples: np.ndarray, rate_hz: int) -> None:
        lacking = missing_sensors(samples, "the sensor")
        if lacking:
            self._set(State.FAULT, lacking)
            return
        t = self.collector.times(samples, rate_hz)
        in_session = self.collector.session_start_s is not None
        if self._fresh and in_session:
            self._start_session(float(t[0]), self._fresh)
        elif self.state in (State.STARTING, State.RESTARTED, State.FAULT):
            self._set(*((State.COLLECTING, "data again") if in_session
                        else (State.WARMING_UP, "waiting for the temperature to settle")))
        self._fresh = None
        stored = self.collector.store(samples, t)
        if stored is None:
            return
        now_s = self.collector.end_s
        if self.state == State.WARMING_UP:
            self._warmed(self._warm.look(self.collector.data, self.warmup))
        elif self.state in (State.COLLECTING, State.SOLVED):
            if self._trigger.timer_due(now_s):
                self._solve()
            elif self._trigger.stopped_moving(*stored, now_s, self.collector.tracker.settings,
                                              self.collector.stored_rate_hz):
                session, segments = self._look()
                if self._trigger.campaign_done(segments, estimator(self.method.name)):
                    self._solve((session, segments))

    def _warmed(self, warmth: Warmth | None) -> None:
        if warmth is None:
            return
        if warmth.start_s is None:
            self._set(State.WARMING_UP, warmth.detail)
            return
        self._start_session(warmth.start_s, warmth.detail)
        self._solve()

    def progress_fields(self) -> dict:
        """STATE's `progress` (docs/protocol.md): whether warmed up, the sessions so far, the
        session's length (s) and the fields of its progress record, the one the detail words."""
        start_s = self.collector.session_start_s
        if start_s is None:
            return {"warm": False, "sessions": self.sessions}
        return {"warm": True, "sessions": self.sessions, "session_s": round(self.collector.end_s - start_s, 1),
                **self.progress.fields()}

    def _new_power_up(self) -> None:
        self.collector = Collector()  # this power-up's data
        self._warm = WarmWatch()
        self._trigger = SolveTrigger()
        self._fresh: str | None = None  # why the next data start a new session (a gap, a trim changed)
        self.trim: TrimRecord | None = None  # the trim in force in this power-up; None until its stream says

    def _trims_before(self, end: int):
        """The BTO datagrams not yet acted on that came before stream number `end`, this
        power-up's (a previous power-up's, met late, say nothing of this one's)."""
        for seen in self._trims:
            if seen.sequence > self._trims_taken and seen.datagram < end:
                self._trims_taken = seen.sequence
                if seen.datagram >= self._power_up_first:
                    yield seen

    def _trim_seen(self, trim: TrimRecord) -> None:
        """The trim in force now, as a BTO datagram says: results carry it (sensor.trim). One that
        changed moves the output: a new session, and a result of the other trim is stale."""
        trim, refused = checked_trim(trim, self.sensor.acc_range_g)
        if trim is None:
            log.warning("bias_trim_refused", detail=refused[0])
            return
        changed = self.trim is not None and not self.trim.same_offsets(trim)
        if self.trim is None or changed:
            log.info("bias_trim", **trim.to_dict(), detail="changed" if changed else "in force")
        if changed:
            self._fresh = "the bias trim offsets changed: the output moved by the difference, collecting a new " \
                          "session (warm-up stands)"
        self.trim = trim
        held = None if self.result is None else self.result.sensor.trim
        if held is not None and not held.same_offsets(trim):  # of an earlier daemon's, a power-cycle may lie between
            self._mark_stale("the bias trim offsets in force changed since this result: its biases are of the "
                             "output under the trim it records (sensor.trim), not the one in force now",
                             "unknown" if self.result is self._inherited else "current")

    def _check_inherited(self, serial: str | None) -> None:
        """An earlier daemon's result of another sensor (a unit swapped on the port) is stale at
        once. A serial number comes only in the sensor's power-up datagrams: when the daemon
        started after them, or the result names none, nothing is known, and only a restart tells."""
        if self._inherited is None or self.result is not self._inherited:
            return
        theirs = self._inherited.sensor.serial_number
        if other_sensor(theirs, serial):
            self._mark_stale(f"the sensor on the port is {serial}, the result is of sensor {theirs}")

    def _power_cycled(self) -> None:
        """A restart ends the previous power-up's data: solve it to its end, mark its result as
        belonging to that power-up (turn-on biases change at every power-up), start afresh."""
        self.finish()
        reason = "sensor restarted: turn-on biases changed, starting a new session"
        if self._mark_stale("the sensor restarted after this result: it belongs to the previous power-up "
                            "(turn-on biases change at every power-up)"):
            reason += "; the last result is the previous power-up's, marked stale"
        self._set(State.RESTARTED, reason)
        self._new_power_up()

    def _mark_stale(self, reason: str, power_up: str = "previous") -> bool:
        """The result held no longer applies: marked stale (once) and the listeners told, so
        result.json, POLL and the corrected pty stop serving it as current. False: nothing to mark."""
        if self.result is None or self.result.stale is not None:
            return False
        self.result = stale_result(self.result, reason, power_up)
        for listener in self.listeners:
            listener.on_stale(self.result)
        return True

    def _start_session(self, start_s: float, detail: str) -> None:
        self.collector.start_session(start_s, self.detection)
        self.progress = progress(self.method.name, [])  # the session's record, until its first look
        self._trigger.session_started(self.collector.end_s, self.method.resolve_every_s)
        self.sessions += 1
        self.session_id = str(uuid.uuid4())  # unique to this session, in every result of it
        self._set(State.COLLECTING, detail)

    def _look(self) -> tuple[Session, list[detect.Segment]]:
        """The session so far and its segments."""
        session = self.collector.session(replace(self.sensor, trim=self.trim),
                                         ResultStream.of(self.stream_stats, capture=self.source, **self.origin,
                                                         session=self.sessions))
        return session, self.collector.segments(session)

    def _solve(self, looked: tuple[Session, list[detect.Segment]] | None = None) -> None:
        """Solve on the session so far (`looked`: it and its segments, when just looked at)."""
        session, segments = looked or self._look()
        self._trigger.solved(self.collector.end_s, self.method.resolve_every_s)
        attempt = solve(session, segments, self.site, self.method, self.options, self.sessions, self.session_id)
        self.progress = attempt.progress
        if attempt.result is not None:
            self.result, trimmed = self._trim(attempt.result)
            self._set(State.SOLVED, f"{attempt.detail}; {trimmed}" if trimmed else attempt.detail)
            for listener in self.listeners:
                listener.on_result(self.result)
        elif attempt.failed:
            self._set(self.state, attempt.detail)
        elif self.state != State.SOLVED:
            self._set(State.COLLECTING, attempt.detail)

    def _set(self, state: State, detail: str) -> None:
        self.state, self.detail = state, detail
        progress = self.progress_fields()
        for listener in self.listeners:
            listener.on_state(state, detail, progress)

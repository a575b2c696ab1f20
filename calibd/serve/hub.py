"""Everything the daemon serves, built from the `[serve]` table: the raw and corrected ptys, the
socket server and the result's group-readable copy, behind one object.

`Hub` is a listener of the Calibrator (states and results, pump thread), hears the stream's
faults and identity from the daemon's loop (`stream_seen`) and every settled byte from the
parser's tap (`tap`, reader thread). The tap only queues the decoded samples; the socket
server's thread cuts them into SAMPLES batches, times them with the counter clock (the rule
the daemon's Collector times by), encodes each batch once per kind and shares the bytes among
the clients watching that kind.
"""

from __future__ import annotations

import grp
import os
import stat
import threading

import numpy as np
import structlog

from stim300.atomic import atomic_file
from stim300.capture import StreamInfo
from stim300.clock import CounterClock

from .. import detect
from ..config import ServeConfig
from ..daemon import Calibrator, Listener, State
from ..methods import estimator
from ..results import CalibrationResult, result_json
from ..session import PowerUpCuts
from .protocol import (SAMPLES_MAX_S, Command, ProtocolError, device_message, fault_message, poll_message,
                       result_message, samples_line, state_message)
from .correct import result_biases, sample_units, samples_correctable
from .ptys import CorrectedPty, PtyError, RawPty
from .sockets import ServeError, SocketServer

log = structlog.get_logger("calibd")

RESULT_COPY_MODE = 0o640
PENDING_SAMPLES = 8000  # samples the tap keeps for the server thread at most (4 s at 2000 Hz)


class Hub(Listener):
    """What `config` serves for the sensor at `port` (`previous`: the result an earlier daemon
    left in the state directory, shown until this one has a result of its own). Construction
    starts it all or raises ServeError (one line) having started nothing; `close()` removes the
    socket file and the pty links."""

    def __init__(self, config: ServeConfig, port: str, previous: CalibrationResult | None = None):
        self.config, self.port = config, port
        self.gid = _group_id(config.group)
        self.port_writer = None  # the port's writer, for requests written into the raw pty (`calibd run` sets it)
        self._calibrator: Calibrator | None = None
        self._state = {"state": State.STARTING.value, "detail": "waiting for data", "progress": {}}
        self._result = previous
        self._bias: dict[str, np.ndarray] | None = None  # this power-up's, in the sensor's base units
        self._cuts = PowerUpCuts()  # the tap's: where the sensor restarted
        self._restart_unheard = False  # the tap saw a restart the calibrator has not yet said (RESTARTED)
        self._info: StreamInfo | None = None
        self._overrun = 0
        self._pending: list[np.ndarray] = []
        self._pending_count = 0
        self.dropped_samples = 0  # samples the tap let go because the server thread lagged
        self._episode_dropped = 0  # of them, since the server thread last took the queue
        self._lock = threading.Lock()
        self._clock = CounterClock()  # the server thread's: SAMPLES "t"
        self.raw_pty = self.corrected_pty = self.server = None
        try:
            if config.result_copy is not None:
                if not config.result_copy.parent.is_dir():
                    raise ServeError(f"result_copy {config.result_copy}: no such directory "
                                     f"{config.result_copy.parent}")
                if self._result is not None:
                    self._write_copy(self._result, at_start=True)
            if config.raw_pty is not None:
                self.raw_pty = _pty("raw_pty", lambda: RawPty(
                    config.raw_pty, self._forward, config.allow_service_mode, self.gid))
            if config.corrected_pty is not None:
                self.corrected_pty = _pty("corrected_pty", lambda: CorrectedPty(
                    config.corrected_pty, config.corrected_before_result, self.gid))
            if config.socket is not None or config.tcp is not None:
                self.server = SocketServer(config.socket, config.tcp, self.gid, self._answer,
                                           self._cut_samples).start()
        except BaseException:
            self.close()
            raise

    def watch(self, calibrator: Calibrator) -> None:
        """The calibrator whose protocol progress STATE and POLL report (it has this hub among its listeners)."""
        self._calibrator = calibrator

    def close(self) -> None:
        for part in (self.server, self.raw_pty, self.corrected_pty):
            if part is not None:
                part.close()

    # ------------------------------------------------------------------ the calibrator's events (pump thread)
    def on_state(self, state: State, detail: str) -> None:
        if state == State.RESTARTED:
            with self._lock:
                self._bias, self._restart_unheard = None, False
                if self.corrected_pty is not None:
                    self.corrected_pty.set_result(None)
        self._state = {"state": state.value, "detail": detail, "progress": self._progress()}
        self._publish(state_message(**self._state))

    def on_result(self, result: CalibrationResult) -> None:
        """Always published; its biases are subtracted only when the tap has seen no restart the
        calibrator has not yet said (the calibrator solves the old power-up to its end after the
        tap has seen the new one: that result's biases are the old power-up's)."""
        bias = {block: bias.astype(np.float32) for block, bias in result_biases(result).items()} or None
        self._new_result(result, bias)

    def on_stale(self, result: CalibrationResult) -> None:
        self._new_result(result, None)

    def _new_result(self, result: CalibrationResult, bias: dict[str, np.ndarray] | None) -> None:
        self._result = result
        with self._lock:  # not between the tap's restart check and its own dropping of the biases
            armed = not (self._restart_unheard or result.stale)
            self._bias = bias if armed else None
            if self.corrected_pty is not None:
                self.corrected_pty.set_result(result if armed else None)
        if self.config.result_copy is not None:
            self._write_copy(result)
        self._publish(result_message(result.to_dict()))

    def _progress(self) -> dict:
        """The protocol's progress, from what the calibrator shows of its session."""
        calibrator = self._calibrator
        if calibrator is None:
            return {}
        collector = calibrator.collector
        start_s = collector.session_start_s
        if start_s is None:
            return {"warm": False, "sessions": calibrator.sessions}
        final = list(collector.tracker.final)
        roles = detect.segment_roles(final)
        return {"warm": True, "sessions": calibrator.sessions, "session_s": round(collector.end_s - start_s, 1),
                "statics": roles.count("static"), "index_headings": len(detect.index_headings(final)),
                "index_turns": roles.count("index turn"),
                "full_turns": roles.count("full turn"), "other_turns": roles.count("other turn"),
                "missing": estimator(calibrator.method.name).missing(final)}

    def stream_seen(self, info: StreamInfo, counts: dict, increases: dict) -> None:
        """The daemon's loop after each batch: the stream as it is (DEVICE) and the faults that
        grew (FAULT; "overrun": samples the loop read too late)."""
        self._info = info
        if increases:
            self._overrun += increases.get("overrun", 0)
            self._publish(fault_message({**counts, "overrun": self._overrun}, increases))

    def _publish(self, message: dict) -> None:
        if self.server is not None:
            self.server.publish(message)

    def _write_copy(self, result: CalibrationResult, at_start: bool = False) -> None:
        """result_copy, replaced atomically, mode 0640 and the group; a failure while running is
        logged (the daemon calibrates on), at start it is the start's failure."""
        path = self.config.result_copy
        try:
            with atomic_file(path, durable=False) as f:
                f.write(result_json(result))
                if stat.S_ISREG(os.fstat(f.fileno()).st_mode):  # never the mode of a device written in place
                    os.fchmod(f.fileno(), RESULT_COPY_MODE)
                    if self.gid is not None:
                        os.fchown(f.fileno(), -1, self.gid)
        except OSError as exc:
            if at_start:
                raise ServeError(f"result_copy {path}: {(exc.strerror or str(exc)).lower()}") from None
            log.error("result_copy_failed", path=str(path), error=exc.strerror or str(exc))

    # ------------------------------------------------------------------ the parser's tap (reader thread)
    def tap(self, settled) -> None:
        """Each settled feed: its bytes to the ptys, its samples queued for the server thread.
        Never blocks or raises (the oldest queued samples go when the server thread lags).
        A sensor restart (`PowerUpCuts`, the calibrator's rule) ends the corrections here, before
        the calibrator hears of it: the new power-up's turn-on biases are not the last result's."""
        pieces = self._cuts.pieces(settled.samples, settled.first, settled.restart_datagrams)
        if any(restarted for restarted, _ in pieces):
            with self._lock:
                self._bias, self._restart_unheard = None, True
                if self.corrected_pty is not None:
                    self.corrected_pty.set_result(None)
        if self.raw_pty is not None:
            self.raw_pty.tap(settled)
        if self.corrected_pty is not None:
            self.corrected_pty.tap(settled)
        if self.server is not None and len(settled.samples):
            dropped = 0
            with self._lock:
                self._pending.append(settled.samples)
                self._pending_count += len(settled.samples)
                while self._pending_count > PENDING_SAMPLES and len(self._pending) > 1:
                    dropped += len(self._pending.pop(0))
                self._pending_count -= dropped
                begins = dropped and not self._episode_dropped
                self._episode_dropped += dropped
                self.dropped_samples += dropped
            if begins:
                log.warning("samples_dropping", why="the socket server's thread lags: the oldest queued samples go")

    def _forward(self, request: bytes) -> None:
        if self.port_writer is None:
            log.warning("request_not_forwarded", request=request.decode("ascii", "replace"),
                        detail="this source has no port to write to")
        else:
            self.port_writer(request)

    # ------------------------------------------------------------------ the socket server's thread
    def _cut_samples(self, kinds: set) -> list[tuple[str, bytes]]:
        """The samples queued since the last cut, timed, as SAMPLES batches of at most
        SAMPLES_MAX_S, each encoded once per kind in `kinds`."""
        info = self._info
        if info is None or not info.rate_hz:
            return []  # until the rate is known nothing can be timed: the samples wait (bounded)
        with self._lock:
            pending, self._pending, self._pending_count = self._pending, [], 0
            ended, self._episode_dropped = self._episode_dropped, 0
        if ended:
            log.info("samples_drops_ended", dropped_samples=ended)
        if not pending:
            return []
        samples = np.concatenate(pending)
        time_s = self._clock.times(samples["counter"], info.rate_hz, samples["t_host"]).time_s
        bias, hold = self._bias, self.config.corrected_before_result == "hold"
        if not samples_correctable(info.format):
            bias = None  # incremental or integrated units: not corrected (docs/serving.md)
        batches = []
        step = max(1, int(SAMPLES_MAX_S * info.rate_hz))
        for lo in range(0, len(samples), step):
            piece, t = samples[lo:lo + step], time_s[lo:lo + step]
            raw = None
            if "raw" in kinds or ("corrected" in kinds and bias is None and not hold):
                raw = samples_line(False, t, piece["t_host"], piece["counter"], piece["gyro"], piece["acc"],
                                   piece["incl"])
            if "raw" in kinds:
                batches.append(("raw", raw))
            if "corrected" in kinds and bias is not None:
                batches.append(("corrected", samples_line(
                    True, t, piece["t_host"], piece["counter"], *(piece[block] - bias.get(block, 0)
                                                                  for block in ("gyro", "acc", "incl")))))
            elif "corrected" in kinds and not hold:
                batches.append(("corrected", raw))
        return batches

    def _answer(self, command: Command) -> dict:
        if command.name == "POLL":
            return poll_message(self._state, None if self._result is None else self._result.to_dict())
        if command.name == "DEVICE":
            info = self._info
            if info is None:
                return device_message(self.port, {}, None, None)
            configuration = None if info.configuration is None else info.configuration.as_dict()
            return device_message(self.port, info.sensor_record(), sample_units(info.format), configuration)
        raise ProtocolError(f"?{command.name} takes no part in this server")


def _group_id(name: str | None) -> int | None:
    if name is None:
        return None
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        raise ServeError(f"group {name!r}: no such group (create it, or drop group from [serve])") from None


def _pty(key: str, make):
    """A pty made by `make()`, its failure one ServeError line naming the key (a PtyError names
    the link)."""
    try:
        return make()
    except PtyError as exc:
        raise ServeError(f"{key} {exc}") from None

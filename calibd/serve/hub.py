"""Everything the daemon serves, built from the `[serve]` table: the raw and corrected ptys, the
socket server and the result's group-readable copy, behind one object.

`Hub` is a listener of the Calibrator (states and results, pump thread), hears the stream's
faults and identity from the daemon's loop (`stream_seen`) and every settled byte from the
parser's tap (`tap`, reader thread). The tap only queues the decoded samples; the socket
server's thread cuts them into SAMPLES batches, times them with the counter clock (the rule
the daemon's Collector times by), encodes each batch once per kind and shares the bytes among
the clients watching that kind.

Which result's biases the corrected outputs subtract ([serve] `correction`) is decided when a
result comes (`calibd.correction.replaces`), taken from the next read on by the corrected pty and the
corrected SAMPLES alike, and told by the server thread (CORRECTION, with the stream time of that
read's first sample) before the first SAMPLES carrying it.
"""

from __future__ import annotations

import grp
import os
import secrets
import stat
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import structlog

from stim300.capture import StreamInfo
from stim300.clock import CounterClock
from stim300.codec import join_samples
from stim300.records import TrimRecord
from stim300.errors import os_reason

from ..config import FoxgloveConfig, RecordConfig, Ros2Config, ServeConfig
from ..daemon import Listener, State
from ..results import CalibrationResult, result_json
from ..session import PowerUpCuts
from . import protocol
from .protocol import (BYTES, MAX_TOKEN_BYTES, RAW_MAX_BYTES, SAMPLES_MAX_S, Command, ProtocolError, encode,
                       samples_line, token_of)
from ..correction import ServedCorrection, replaces, sample_units, uncorrectable
from .feeds import Feed, Feeds
from .ptys import CorrectedPty, PtyError, RawPty, Throttle
from .queue import SampleQueue
from .recorder import Recorder
from .sockets import ServeError, SocketServer

log = structlog.get_logger("calibd")

RESULT_COPY_MODE = 0o640
PENDING_BYTES = 1 << 20  # the sensor's bytes the tap keeps for RAW watchers at most (13 s at 2000 Hz)


class Hub(Listener):
    """What `config` serves for the sensor at `port` (`previous`: the result an earlier daemon
    left in the state directory, shown until this one has a result of its own). Construction
    starts it all or raises ServeError (one line) having started nothing; `close()` removes the
    socket file and the pty links."""

    def __init__(self, config: ServeConfig, port: str, previous: CalibrationResult | None = None,
                 feeds: dict[str, Feed] | None = None, paced: bool = True, record: RecordConfig | None = None):
        self.config, self.port = config, port
        self.feeds = Feeds(feeds, paced) if feeds else None  # ROS 2, Foxglove: the hub's from here on
        self.recorder: Recorder | None = None
        self.gid = _group_id(config.group)
        self.port_writer = None  # the port's writer, for requests written into the raw pty (`calibd run` sets it)
        self._state = protocol.StateFields(State.STARTING.value, "waiting for data")
        self._result = previous
        self._kept: ServedCorrection | None = None  # what this power-up's corrected outputs subtract
        self._pty_kept: ServedCorrection | None = None  # the reader thread's: what the corrected pty was given
        self._announced: ServedCorrection | None = None  # the server thread's: what the last CORRECTION said
        self._held: list[tuple[np.ndarray, np.ndarray, ServedCorrection | None]] = []  # timed, after a change
        self._cuts = PowerUpCuts()  # the tap's: where the sensor restarted
        self._restart_unheard = False  # the tap saw a restart the calibrator has not yet said (RESTARTED)
        self._info: StreamInfo | None = None
        self._overrun = 0
        self.queue = SampleQueue("the socket server's thread lags")  # each read's samples, what they subtract
        self._bytes_wanted = False  # a client watches RAW (the server thread says so at each cut)
        self._bytes_seen = 0  # the stream's bytes so far: a RAW message's offset
        self._raw: list[tuple[int, float, bytes]] = []  # (offset, host time, bytes) of each read, for RAW
        self._raw_bytes = 0
        self.dropped_bytes = 0  # bytes for RAW the tap let go because the server thread lagged
        self._lock = threading.Lock()
        self._clock = CounterClock()  # the server thread's: SAMPLES "t"
        self._copy_failing = False  # the result copy's last write failed (logged once until one succeeds)
        self.raw_ptys: list[RawPty] = []
        self.corrected_pty = self.server = None
        try:
            if config.result_copy is not None:
                if not config.result_copy.parent.is_dir():
                    raise ServeError(f"result_copy {config.result_copy}: no such directory "
                                     f"{config.result_copy.parent}")
                _check_copy_path(config.result_copy)
                if self._result is not None:
                    self._write_copy(self._result, at_start=True)
            token = None
            if config.tcp is not None and not config.tcp_open:
                if config.tcp_token_file is None:
                    raise ServeError("tcp: needs tcp_token_file or tcp_open = true in [serve]")
                token = _read_token(config.tcp_token_file)
            throttle = Throttle()  # the raw ptys share the sensor, so one rate of requests
            for link in config.raw_ptys:
                self.raw_ptys.append(_pty("raw_pty", lambda: RawPty(
                    link, self._forward, config.allow_service_mode, self.gid, throttle)))
            if config.corrected_pty is not None:
                self.corrected_pty = _pty("corrected_pty", lambda: CorrectedPty(
                    config.corrected_pty, config.corrected_before_result, self.gid))
            if config.socket is not None or config.tcp is not None:
                self.server = SocketServer(config.socket, config.tcp, self.gid, self._answer, self._cut_samples,
                                           token, config.idle_timeout_s, config.max_clients_per_uid).start()
            if self.feeds is not None:
                self.feeds.start()
            if record is not None:
                self.recorder = Recorder(record).start()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for part in (self.server, *self.raw_ptys, self.corrected_pty, self.feeds, self.recorder):
            if part is not None:
                part.close()

    # ------------------------------------------------------------------ the calibrator's events (pump thread)
    def on_state(self, state: State, detail: str, progress: dict | None = None) -> None:
        if state == State.RESTARTED:
            with self._lock:
                self._kept, self._restart_unheard = None, False
        self._state = protocol.StateFields(state.value, detail, progress or {})
        self._publish(protocol.State(state.value, detail, progress or {}))
        if self.feeds is not None:
            self.feeds.state(state.value, detail, progress or {})

    def on_result(self, result: CalibrationResult) -> None:
        """Always published; its biases are subtracted only when the tap has seen no restart the
        calibrator has not yet said (the calibrator solves the old power-up to its end after the
        tap has seen the new one: that result's biases are the old power-up's), and when [serve]
        `correction` prefers it to the power-up's kept one (`replaces`)."""
        self._new_result(result, ServedCorrection.of(result))

    def on_stale(self, result: CalibrationResult) -> None:
        self._new_result(result, None)

    def _new_result(self, result: CalibrationResult, correction: ServedCorrection | None) -> None:
        """The corrected outputs take the new biases at the next read (the tap); the socket
        announces them (CORRECTION) as its SAMPLES reach them."""
        self._result = result
        changed = None
        with self._lock:  # not between the tap's restart check and its own dropping of the biases
            kept = self._kept
            if self._restart_unheard or result.stale:
                self._kept = None
            elif correction is not None and replaces(self.config.correction, None if kept is None else kept.result,
                                                     result):
                if kept is None or not kept.same_as(correction):
                    self._kept = changed = correction
        if changed is not None and self.server is None:  # nothing times the stream: said without from_t
            self._say_correction(kept, changed, None)
        if self.config.result_copy is not None:
            self._write_copy(result)
        self._publish(protocol.Result(result.to_dict()))
        if self.feeds is not None:
            self.feeds.result(result)

    def stream_seen(self, info: StreamInfo, counts: dict, increases: dict) -> None:
        """The daemon's loop after each batch: the stream as it is (DEVICE) and the faults that
        grew (FAULT; "overrun": samples the loop read too late)."""
        self._info = info
        if increases:
            self._overrun += increases.get("overrun", 0)
            self._publish(protocol.Fault({**counts, "overrun": self._overrun}, increases))
        if self.feeds is not None:
            self.feeds.stream_seen(info, {**counts, "overrun": self._overrun})

    def _publish(self, message: dict) -> None:
        if self.server is not None:
            self.server.publish(message)

    def _write_copy(self, result: CalibrationResult, at_start: bool = False) -> None:
        """result_copy, replaced atomically by a new file of mode 0640 and the group, never written
        through a symbolic link nor onto anything but a regular file; a failure while running is
        logged once until a write succeeds (the daemon calibrates on), at start it is the
        start's failure."""
        path = self.config.result_copy
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part")
        try:
            _check_copy_path(path)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, RESULT_COPY_MODE)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(result_json(result))
                    os.fchmod(f.fileno(), RESULT_COPY_MODE)
                    if self.gid is not None:
                        os.fchown(f.fileno(), -1, self.gid)
                os.replace(tmp, path)  # replaces the name: never follows a link put there meanwhile
            finally:
                if os.path.lexists(tmp):
                    os.unlink(tmp)
        except (OSError, ServeError) as exc:
            error = str(exc) if isinstance(exc, ServeError) else \
                f"result_copy {path}: {os_reason(exc)}"
            if at_start:
                raise ServeError(error) from None
            if not self._copy_failing:
                log.error("result_copy_failed", error=error, detail="logged once until a write succeeds")
            self._copy_failing = True
            return
        if self._copy_failing:
            log.info("result_copy_recovered", path=str(path))
        self._copy_failing = False

    # ------------------------------------------------------------------ the parser's tap (reader thread)
    def tap(self, settled) -> None:
        """Each settled feed: its bytes to the ptys, its samples queued for the server thread.
        Never blocks or raises (the oldest queued samples go when the server thread lags).
        A sensor restart (`PowerUpCuts`, the calibrator's rule) ends the corrections here, before
        the calibrator hears of it: the new power-up's turn-on biases are not the last result's.
        So does a Bias Trim Offset datagram whose offsets are not those the result was made under
        (its `sensor.trim`): the output from that read on carries the new ones."""
        pieces = self._cuts.pieces(settled.samples, settled.first, settled.restart_datagrams)
        with self._lock:
            if any(restarted for restarted, _ in pieces):
                self._kept, self._restart_unheard = None, True
            elif self._kept is not None and _trim_changed(self._kept.result, settled.trims):
                self._kept = None  # the output moved by the new offsets: the calibrator marks the result stale next
            kept = self._kept  # what this read's corrected outputs take, pty and SAMPLES alike
        if self.corrected_pty is not None and kept is not self._pty_kept:
            self._pty_kept = kept
            self.corrected_pty.set_result(None if kept is None else kept.result)
        for raw_pty in self.raw_ptys:
            raw_pty.tap(settled)
        if self.recorder is not None:
            self.recorder.tap(settled.data)
        if self._bytes_wanted and settled.data:
            self._keep_bytes(settled.data)
        self._bytes_seen += len(settled.data)
        if self.corrected_pty is not None:
            self.corrected_pty.tap(settled)
        if self.server is not None and len(settled.samples):
            self.queue.put(settled.samples, kept)
        if self.feeds is not None and len(settled.samples):
            self.feeds.tap(settled.samples, kept)

    def _keep_bytes(self, data: bytes) -> None:
        """A read's bytes kept for the RAW watchers (reader thread); the oldest go, counted, when
        the server thread lags by more than PENDING_BYTES."""
        with self._lock:
            self._raw.append((self._bytes_seen, time.monotonic(), data))
            self._raw_bytes += len(data)
            while self._raw_bytes > PENDING_BYTES and len(self._raw) > 1:
                lost = len(self._raw.pop(0)[2])
                self._raw_bytes -= lost
                self.dropped_bytes += lost

    def _raw_lines(self) -> list[tuple[str, bytes]]:
        """The bytes kept since the last cut as RAW messages: consecutive reads together, at most
        RAW_MAX_BYTES a message (a longer read in pieces)."""
        with self._lock:
            kept, self._raw, self._raw_bytes = self._raw, [], 0
        lines, k = [], 0
        while k < len(kept):
            offset, t_host, first = kept[k]
            parts, size, k = [first], len(first), k + 1
            while k < len(kept) and kept[k][0] == offset + size and size + len(kept[k][2]) <= RAW_MAX_BYTES:
                parts.append(kept[k][2])
                size, k = size + len(kept[k][2]), k + 1
            data = b"".join(parts)
            lines += [(BYTES, encode(protocol.Raw.of(offset + at, t_host, data[at:at + RAW_MAX_BYTES])))
                      for at in range(0, len(data), RAW_MAX_BYTES)]
        return lines

    def _forward(self, request: bytes) -> None:
        if self.port_writer is None:
            log.warning("request_not_forwarded", request=request.decode("ascii", "replace"),
                        detail="this source has no port to write to")
        else:
            self.port_writer(request)

    # ------------------------------------------------------------------ the socket server's thread
    def _cut_samples(self, kinds: set) -> list[tuple[str, bytes]]:
        """The sensor's bytes kept since the last cut as RAW messages (kind BYTES, while a client
        watches them), and the samples queued, timed, as SAMPLES batches of at most
        SAMPLES_MAX_S, each encoded once per kind in `kinds`. At a change of the biases the cut
        ends: CORRECTION is published, and the samples from the change wait for the next cut, so
        a client has it before the first SAMPLES carrying the new biases."""
        self._bytes_wanted = BYTES in kinds
        raw = self._raw_lines()
        info = self._info
        if info is None or not info.rate_hz:
            return raw  # until the rate is known nothing can be timed: the samples wait (bounded)
        pending = self.queue.take()
        timed, self._held = self._held, []
        if pending:
            samples = join_samples([piece for piece, _ in pending])
            time_s = self._clock.times(samples["counter"], info.rate_hz, samples["t_host"]).time_s
            lo = 0
            for piece, kept in pending:
                timed.append((samples[lo:lo + len(piece)], time_s[lo:lo + len(piece)], kept))
                lo += len(piece)
        batches = raw
        i = 0
        while i < len(timed):
            kept = timed[i][2]
            if kept is not None and kept is not self._announced:
                self._say_correction(self._announced, kept, float(timed[i][1][0]))
                self._announced, self._held = kept, timed[i:]
                break
            self._announced = kept  # None: the power-up ended, its next CORRECTION has no "old"
            j = i + 1
            while j < len(timed) and timed[j][2] is kept:
                j += 1
            run = timed[i:j]
            batches += self._batches(kinds, info, join_samples([p[0] for p in run]),
                                     np.concatenate([p[1] for p in run]), kept)
            i = j
        return batches

    def _batches(self, kinds: set, info: StreamInfo, samples: np.ndarray, time_s: np.ndarray,
                 kept: ServedCorrection | None) -> list[tuple[str, bytes]]:
        """Timed samples that take the same biases (`kept`) as SAMPLES batches of each kind."""
        correction, hold = kept, self.config.corrected_before_result == "hold"
        if uncorrectable(info.format):
            correction = None  # incremental or integrated units: not corrected (docs/serving.md)
        batches = []
        step = max(1, int(SAMPLES_MAX_S * info.rate_hz))
        for lo in range(0, len(samples), step):
            piece, t = samples[lo:lo + step], time_s[lo:lo + step]
            raw = None
            if "raw" in kinds or ("corrected" in kinds and correction is None and not hold):
                raw = samples_line(False, t, piece["t_host"], piece["counter"], piece["gyro"], piece["acc"],
                                   piece["incl"])
            if "raw" in kinds:
                batches.append(("raw", raw))
            if "corrected" in kinds and correction is not None:
                batches.append(("corrected", samples_line(
                    True, t, piece["t_host"], piece["counter"], *(correction.take_out(block, piece[block])
                                                                  for block in ("gyro", "acc", "incl")))))
            elif "corrected" in kinds and not hold:
                batches.append(("corrected", raw))
        return batches

    def _say_correction(self, old: ServedCorrection | None, new: ServedCorrection, from_t_s: float | None) -> None:
        """CORRECTION to every watcher and `correction_changed` in the log: the subtracted biases
        changed from `old` (None: the power-up's first) to `new` at stream time `from_t_s` (s)."""
        message = protocol.Correction.of(self.config.correction, new.result.session_id, from_t_s,
                                         None if old is None else old.biases(), new.biases())
        log.info("correction_changed", **{k: v for k, v in msgspec.to_builtins(message).items() if k != "class"})
        self._publish(message)

    def _answer(self, command: Command) -> protocol.Message:
        if command.name == "POLL":
            return protocol.Poll(self._state, None if self._result is None else self._result.to_dict())
        if command.name == "DEVICE":
            info = self._info
            if info is None:
                return protocol.Device(self.port)
            configuration = None if info.configuration is None else info.configuration.as_dict()
            return protocol.Device.of(self.port, info.sensor_record(), sample_units(info.format), configuration)
        raise ProtocolError(f"?{command.name} takes no part in this server")


def make_feeds(ros2: Ros2Config | None, foxglove: FoxgloveConfig | None, mcap: Path | None = None
               ) -> dict[str, Feed]:
    """The feeds the [ros2] and [foxglove] tables ask for (None: the table is absent), and the
    Foxglove view recorded into `mcap` (replay --mcap; without a [foxglove] table, a view with
    no server), started; ServeError (one line, before the daemon says it is ready) when one
    cannot start, those made before it closed. Their packages are loaded only here, when asked for."""
    from ..ros2.messages import Ros2Error

    feeds: dict[str, Feed] = {}
    try:
        if ros2 is not None:
            from .rosfeed import Ros2Feed  # here: the ros2 extra is loaded only when [ros2] is given

            feeds["ros2"] = Ros2Feed(ros2)
        if foxglove is not None or mcap is not None:
            from .foxglove import FoxgloveView

            view = foxglove or FoxgloveConfig()
            feeds["foxglove"] = FoxgloveView(view.host if foxglove else None, view.port, view.rate_hz, mcap)
    except Ros2Error as exc:
        _close_all(feeds)
        raise ServeError(f"[ros2] {exc}") from None
    except BaseException:
        _close_all(feeds)
        raise
    return feeds


def _close_all(feeds: dict[str, Feed]) -> None:
    for feed in feeds.values():
        feed.close()


def _trim_changed(result: CalibrationResult, trims: tuple[TrimRecord, ...]) -> bool:
    """Whether a Bias Trim Offset datagram of a read holds offsets other than the result's
    `sensor.trim` (the calibrator's rule: a result that records none is not judged by them)."""
    held = result.sensor.trim
    return held is not None and any(not held.same_offsets(trim) for trim in trims)


def _group_id(name: str | None) -> int | None:
    if name is None:
        return None
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        raise ServeError(f"group {name!r}: no such group (create it, or drop group from [serve])") from None


def _check_copy_path(path: Path) -> None:
    """ServeError unless result_copy is absent or a regular file: a symbolic link would have the
    daemon write where the link points."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ServeError(f"result_copy {path}: {os_reason(exc)}") from None
    if stat.S_ISLNK(mode):
        raise ServeError(f"result_copy {path}: is a symbolic link; never written through (remove it)")
    if not stat.S_ISREG(mode):
        raise ServeError(f"result_copy {path}: is not a regular file; not replaced")


def _read_token(path: Path) -> bytes:
    """tcp_token_file's token (its text without surrounding white space), read once at start;
    refused unless a regular file itself (no symbolic link), not readable or writable by other
    users, not empty."""
    where = f"tcp_token_file {path}"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY)
    except OSError as exc:
        if os.path.islink(path):
            raise ServeError(f"{where}: is a symbolic link; give the file itself") from None
        raise ServeError(f"{where}: {os_reason(exc)}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ServeError(f"{where}: is not a regular file")
        if st.st_mode & (stat.S_IROTH | stat.S_IWOTH):
            raise ServeError(f"{where}: other users may read or write it (mode {stat.S_IMODE(st.st_mode):04o}); "
                             "make it 0640 for the group")
        data = os.read(fd, MAX_TOKEN_BYTES + 1)
    finally:
        os.close(fd)
    try:
        return token_of(data).encode()
    except ProtocolError as exc:
        raise ServeError(f"{where}: {exc}") from None


def _pty(key: str, make):
    """A pty made by `make()`, its failure one ServeError line naming the key (a PtyError names
    the link)."""
    try:
        return make()
    except PtyError as exc:
        raise ServeError(f"{key} {exc}") from None

"""Pseudo-terminals that pass the sensor's datagram stream on: raw, and bias-corrected.

Each is a pty whose slave node is linked at a path of the configuration, so any STIM300 driver
opens that path as it would the sensor's port. The daemon writes into the master from the port
reader thread (the parser's tap): a reader that is slow never holds the daemon up, the bytes the
pty does not take are dropped and counted; while no process has the slave open nothing is
written, so a driver that opens it starts at the present. Request lines a client writes
(`N<CR>`, `C<CR>`, ...) are read by a small thread per pty: those of a raw pty are forwarded to
the sensor, at most one of each kind a second over all raw ptys; those of the corrected pty are
answered there, from the special datagrams the stream last carried, as the sensor answers them.
Refusals, drops and over-long lines are logged once per episode with a count.
"""

from __future__ import annotations

import collections
import errno
import os
import select
import termios
import threading
import time
import tty
import uuid
from collections.abc import Callable
from pathlib import Path

import structlog

from stim300.protocol import (BIAS_TRIM, CONFIGURATION, EXTENDED_ERROR, PART_NUMBER, SERIAL_NUMBER,
                              SPECIAL_IDS, SpecialKind)
from stim300.stream import Settled
from stim300.errors import os_reason

from ..config import BEFORE_RESULT
from ..errors import CalibdError
from ..results import CalibrationResult
from .correct import Corrector

log = structlog.get_logger("calibd")

SLAVE_MODE = 0o660
MAX_REQUEST_BYTES = 32  # a longer line is no request of the sensor's (the longest is UTILITYMODE)
QUIET_S = 5.0  # an episode (of drops, refusals, ...) ends after this long without one
REQUEST_INTERVAL_S = 1.0  # at most one request of each kind a second: each answer replaces a datagram
READ_BYTES = 256
ABSENT_POLL_S = 0.5  # how often the request thread looks for a reader while the slave is closed
# each Normal-mode query asks for one special datagram (protocol §9)
QUERY_KINDS: dict[bytes, SpecialKind] = {kind.request.removesuffix(b"\r"): kind for kind in (
    PART_NUMBER, SERIAL_NUMBER, CONFIGURATION, BIAS_TRIM, EXTENDED_ERROR)}
QUERIES = frozenset(QUERY_KINDS)
POWER_UP = (PART_NUMBER, SERIAL_NUMBER, CONFIGURATION)  # what the sensor sends when it starts, in order
MODE_CHANGES = frozenset({b"SERVICEMODE", b"UTILITYMODE", b"R"})  # each stops the stream for every reader


class PtyError(CalibdError):
    """A pty or its link the daemon cannot set up (a path that is not a symlink, a missing
    directory, a group the node cannot be given); one line."""


def request_refusal(line: bytes, allow_mode_changes: bool) -> str | None:
    """Why a request line (without its CR) is not sent to the sensor; None: send it.

    Only the Normal-mode queries, upper case as the sensor reads them, go: their answers are
    datagrams every reader can take. A mode change or reset stops the stream for all readers."""
    if line in QUERIES:
        return None
    if line in MODE_CHANGES:
        return None if allow_mode_changes else "service mode, utility mode and reset are not allowed"
    return "not a request the sensor answers in Normal mode (N, I, C, T, E)"


class Episode:
    """Events of one kind on one link, logged when an episode of them begins (`begins`, with what
    the first was) and when it ends, QUIET_S after the last, with its count (`ends`): a flood is
    two lines, not one an event. `count` is every event's, over all episodes."""

    def __init__(self, link: Path, begins: str, ends: str, counted: str):
        self.link, self.begins, self.ends, self.counted = str(link), begins, ends, counted
        self.count = 0
        self._in_episode = 0
        self._last_s: float | None = None  # the last event's time; None: no episode under way

    def add(self, n: int = 1, **first) -> None:
        self.count += n
        self._in_episode += n
        if self._last_s is None:
            log.warning(self.begins, link=self.link, **first)
        self._last_s = time.monotonic()

    def end_if_quiet(self) -> float | None:
        """End the episode once QUIET_S has passed without an event; else the seconds left (None: none under way)."""
        if self._last_s is None:
            return None
        left = self._last_s + QUIET_S - time.monotonic()
        if left > 0:
            return left
        self.end()
        return None

    def end(self) -> None:
        """End the episode under way, saying its count (nothing when none is)."""
        if self._last_s is not None:
            log.info(self.ends, link=self.link, **{self.counted: self._in_episode})
        self._last_s, self._in_episode = None, 0


class LinkedPty:
    """A pty whose slave is linked at `link`: `write` never blocks (what the pty does not take is
    dropped and counted in `dropped_bytes`), and each line a client writes (CR or CR LF ended)
    goes to `on_line` from a reader thread; a line longer than MAX_REQUEST_BYTES is discarded
    (counted in `long_lines`). The reader thread also ends the `episodes` of its owner once they
    are quiet. The slave node gets group `gid` (None: the daemon's).

    The daemon does not hold the slave open: the master then reports a hang-up exactly while no
    process has it open, which `write` looks at. With nobody there it writes nothing (no stale
    bytes wait for the next reader); when a reader has arrived, `greeting()` (when given) goes
    before the data; when the reader has left, what it did not read is flushed."""

    def __init__(self, link: Path, gid: int | None, on_line: Callable[[bytes], None], episodes=(),
                 greeting: Callable[[], bytes] | None = None):
        self.link = Path(link)
        self._on_line = on_line
        self._greeting = greeting
        self._drops = Episode(link, "pty_dropping", "pty_drops_ended", "dropped_bytes")
        self._long = Episode(link, "pty_request_too_long", "pty_long_lines_ended", "lines")
        self._episodes = (self._long, *episodes)
        _check_link(self.link)
        self._write_lock = threading.Lock()  # the master fd is not closed under a write
        self._master = self._wake_r = self._wake_w = None
        self._present = False  # a reader had the slave open at the last write
        try:
            slave = None
            try:
                self._master, slave = os.openpty()
                self._wake_r, self._wake_w = os.pipe()
                os.set_blocking(self._wake_w, False)
                tty.setraw(self._master)
                tty.setraw(slave)  # the modes stay with the pty while the master is open
                os.set_blocking(self._master, False)
                self.path = os.ttyname(slave)
            except OSError as exc:
                raise PtyError(f"{link}: cannot open a pty: {os_reason(exc)}") from None
            finally:
                if slave is not None:
                    os.close(slave)
            self._hangup = select.poll()
            self._hangup.register(self._master, 0)  # POLLHUP is reported whatever the mask
            _prepare_node(self.path, gid)
            _replace_link(self.link, self.path)
        except BaseException:
            self._close_fds()
            raise
        self._thread = threading.Thread(target=self._read_lines, name=f"pty requests {self.link}", daemon=True)
        self._thread.start()

    def write(self, data) -> None:
        """Put `data` into the pty, or as much as it takes now, if a reader has it open (after
        the greeting when it has just opened it); never blocks, never raises."""
        with self._write_lock:
            if self._master is None:
                return
            present = not any(events & select.POLLHUP for _, events in self._hangup.poll(0))
            arrived, left = present and not self._present, self._present and not present
            self._present = present
            if left:
                self._flush_unread()
            if arrived:
                try:
                    os.write(self._wake_w, b"o")  # the request thread reads again at once
                except BlockingIOError:
                    pass  # it has wake-ups enough waiting
                if self._greeting is not None:
                    data = self._greeting() + bytes(data)
            if not present or not data:
                return
            try:
                taken = os.write(self._master, data)
            except OSError:  # BlockingIOError: full, the reader is slow
                taken = 0
        lost = len(data) - taken
        if lost:
            self._drops.add(lost, why="its reader is slow")
        else:  # the writer thread owns the drops' episode: it ends once writes have gone through
            self._drops.end_if_quiet()

    def _flush_unread(self) -> None:
        """Drop what the reader that left did not read, so the next one starts at the present:
        only the slave's side can flush it."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            try:
                termios.tcflush(fd, termios.TCIFLUSH)
            finally:
                os.close(fd)
        except (OSError, termios.error):
            pass  # the next reader may read old bytes; a driver resynchronises on a datagram

    @property
    def dropped_bytes(self) -> int:
        return self._drops.count

    @property
    def long_lines(self) -> int:
        return self._long.count

    def _read_lines(self) -> None:
        pending, discarding, absent = b"", False, False
        while True:
            waits = [left for left in (e.end_if_quiet() for e in self._episodes) if left is not None]
            if absent:  # the master reports a hang-up, always readable: look again later, or when woken
                waits.append(ABSENT_POLL_S)
            ready = select.select([self._wake_r] if absent else [self._master, self._wake_r], [], [],
                                  min(waits, default=None))[0]
            if self._wake_r in ready:
                if b"x" in os.read(self._wake_r, 64):
                    return
                absent = False  # a reader arrived
                continue
            if absent:
                absent = False
                continue
            if not ready:  # an episode's quiet has passed
                continue
            try:
                pending += os.read(self._master, READ_BYTES)
            except BlockingIOError:  # woken for nothing
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:  # no process has the slave open
                    absent = True
                    continue
                log.warning("pty_requests_unread", link=str(self.link), error=exc.strerror)
                return
            *lines, pending = pending.split(b"\r")
            for line in lines:
                if discarding:  # the end of a line too long to be a request
                    discarding = False
                    continue
                line = line.removeprefix(b"\n")  # the LF of the previous line's CR LF
                if len(line) > MAX_REQUEST_BYTES:
                    self._long.add(start=_text(line[:MAX_REQUEST_BYTES]))
                elif line:
                    self._line(line)
            if len(pending) > MAX_REQUEST_BYTES:
                if not discarding:
                    self._long.add(start=_text(pending[:MAX_REQUEST_BYTES]))
                pending, discarding = b"", True

    def _line(self, line: bytes) -> None:
        try:
            self._on_line(line)
        except Exception:  # noqa: BLE001 - a client's request must not end the thread that reads them
            log.exception("pty_request_failed", link=str(self.link), request=_text(line))

    def close(self) -> None:
        """Stop reading requests, remove the link if it is still ours, close the pty; safe to call again."""
        if self._thread.is_alive():
            os.write(self._wake_w, b"x")
            self._thread.join()
            for episode in self._episodes:  # the reader thread's, which has ended: no race
                episode.end()
        try:
            if os.readlink(self.link) == self.path:
                self.link.unlink()
        except OSError:
            pass  # gone or replaced by someone else: not ours to remove
        self._close_fds()

    def _close_fds(self) -> None:
        with self._write_lock:
            for fd in (self._master, self._wake_r, self._wake_w):
                if fd is not None:
                    os.close(fd)
            self._master = self._wake_r = self._wake_w = None


def _text(data: bytes) -> str:
    return data.decode("ascii", "backslashreplace")


def _check_link(link: Path) -> None:
    if not link.parent.is_dir():
        raise PtyError(f"{link}: directory {link.parent} does not exist")
    if os.path.lexists(link) and not link.is_symlink():
        raise PtyError(f"{link}: exists and is not a symlink; refusing to replace it with a pty link")


def _prepare_node(path: str, gid: int | None) -> None:
    """Mode 0660 and the group, so members of the group read and write the slave."""
    try:
        os.chmod(path, SLAVE_MODE)
        if gid is not None:
            os.chown(path, -1, gid)
    except OSError as exc:
        raise PtyError(f"{path}: cannot give it mode 0660{'' if gid is None else f' and group id {gid}'}: "
                       f"{os_reason(exc)}") from None


def _replace_link(link: Path, target: str) -> None:
    """`link` -> `target` in one step: a reader never finds the link missing or half made."""
    temp = link.with_name(f".{link.name}.{uuid.uuid4().hex[:8]}")
    try:
        os.symlink(target, temp)
        os.replace(temp, link)
    except OSError as exc:
        try:
            os.unlink(temp)
        except OSError:
            pass  # never made
        raise PtyError(f"{link}: cannot link it to {target}: {os_reason(exc)}") from None


class Throttle:
    """At most one request of each kind every REQUEST_INTERVAL_S: each answer replaces a normal
    datagram of the sensor's, so a flood of requests would eat the stream. The raw ptys share
    one, as they share the sensor."""

    def __init__(self):
        self._last_s: dict[bytes, float] = {}  # each kind's last request let through
        self._lock = threading.Lock()  # each pty's request thread asks

    def allow(self, request: bytes) -> bool:
        with self._lock:
            now_s = time.monotonic()
            if now_s - self._last_s.get(request, -REQUEST_INTERVAL_S) < REQUEST_INTERVAL_S:
                return False
            self._last_s[request] = now_s
            return True


class RawPty:
    """A pty whose slave is linked at `link`: every settled byte of the sensor's stream, unchanged
    and in order, while a reader has it open; the requests `request_refusal` allows, written by a
    client, go to `forward` (e.g. `PortReader.write`), with a CR, as `throttle` lets them (one
    Throttle shared by every raw pty: they share the sensor). Counted: `requests_forwarded`,
    `requests_refused`, `requests_throttled` (allowed, but too soon), and `long_lines` (no request)."""

    def __init__(self, link: Path, forward: Callable[[bytes], object], allow_service_mode: bool = False,
                 gid: int | None = None, throttle: Throttle | None = None):
        self.forward = forward
        self.allow_service_mode = allow_service_mode
        self.requests_forwarded = 0
        self._throttle = throttle or Throttle()
        self._refused = Episode(link, "pty_request_refused", "pty_refusals_ended", "refused")
        self._throttled = Episode(link, "pty_request_throttled", "pty_throttling_ended", "throttled")
        self._pty = LinkedPty(link, gid, self._request, episodes=(self._refused, self._throttled))

    @property
    def requests_refused(self) -> int:
        return self._refused.count

    @property
    def requests_throttled(self) -> int:
        return self._throttled.count

    @property
    def long_lines(self) -> int:
        return self._pty.long_lines

    @property
    def dropped_bytes(self) -> int:
        return self._pty.dropped_bytes

    def tap(self, settled: Settled) -> None:
        """The parser's tap (reader thread): never blocks, never raises."""
        self._pty.write(settled.data)

    def _request(self, line: bytes) -> None:
        why = request_refusal(line, self.allow_service_mode)
        if why is not None:
            self._refused.add(request=_text(line), why=why)
            return
        if not self._throttle.allow(line):
            self._throttled.add(request=_text(line), why=f"at most one {_text(line)} every {REQUEST_INTERVAL_S:g} s")
            return
        self.requests_forwarded += 1
        log.info("pty_request", link=str(self._pty.link), request=_text(line))
        self.forward(line + b"\r")

    def close(self) -> None:
        self._pty.close()


class CorrectedPty:
    """A pty whose slave is linked at `link`: the stream with the current power-up's result's
    biases taken off each normal datagram's values (`calibd.serve.correct`), talking as the
    sensor talks.

    Before a result of this power-up (`before_result`): "hold" carries only special datagrams,
    "raw" the bytes unchanged. The hub ends the result (`set_result(None)`) in the same tap that
    brings a sensor restart, before the new power-up's first datagram is written.

    The latest special datagram of each kind the stream carried is kept: a reader that opens the
    pty is first sent the power-up ones (part number, serial number, configuration), and a query
    written into it (N, I, C, T, E) is answered here with the kept datagram of its kind, in place
    of the next normal datagram, as the sensor answers; nothing reaches the sensor, so the
    calibration loses no sample. A query of a kind already waiting shares its answer. Anything
    else, and a query of a kind the stream has not carried, is refused (`requests_refused`)."""

    def __init__(self, link: Path, before_result: str = "hold", gid: int | None = None):
        if before_result not in BEFORE_RESULT:
            raise PtyError(f"corrected_before_result = {before_result!r}: expected one of {', '.join(BEFORE_RESULT)}")
        self.before_result = before_result
        self._corrector: Corrector | None = None
        self._failing = False
        self._specials: dict[SpecialKind, bytes] = {}  # the latest datagram of each kind the stream carried
        self._answers: collections.deque[SpecialKind] = collections.deque()  # queries waiting for a datagram
        self._lock = threading.Lock()  # the request thread queues answers, the tap takes them
        self.requests_answered = 0
        self._refused = Episode(link, "pty_request_refused", "pty_refusals_ended", "refused")
        self._pty = LinkedPty(link, gid, self._request, episodes=(self._refused,), greeting=self._greeting)

    @property
    def requests_refused(self) -> int:
        return self._refused.count

    @property
    def dropped_bytes(self) -> int:
        return self._pty.dropped_bytes

    def set_result(self, result: CalibrationResult | None) -> None:
        """The result whose biases to subtract (None: none of this power-up yet)."""
        self._corrector = None if result is None else Corrector(result)

    def tap(self, settled: Settled) -> None:
        """The parser's tap (reader thread): never blocks, never raises."""
        corrector = self._corrector  # one read: set_result runs in another thread
        try:
            specials = settled.specials  # found by the parser, as sent
            if corrector is not None:
                data = self._answered(corrector.apply(settled), settled)
            elif self.before_result == "raw":
                data = self._answered(settled.data, settled)
            else:
                data = b"".join(specials) + self._answered(b"", settled)
        except Exception:  # noqa: BLE001 - the reader thread must go on; the bytes are held back
            if not self._failing:
                log.exception("corrected_pty_failed", link=str(self._pty.link))
            self._failing = True
            return
        self._failing = False
        self._pty.write(data)  # a reader that opened it just now is greeted with the specials seen before these
        with self._lock:
            for frame in specials:
                self._specials[SPECIAL_IDS[frame[0]][0]] = frame

    def _answered(self, data, settled: Settled) -> bytes:
        """`data` (the feed's bytes, corrected or not; empty: held) with the waiting answers in
        place of its first normal datagrams, one each."""
        with self._lock:
            if not self._answers:
                return data
            spans = [(offset, layout.wire_length(bool(fmt.crlf))) for layout, fmt, offsets, _, _ in settled.runs
                     for offset in offsets[:len(self._answers)].tolist()][:len(self._answers)]
            answers = [self._specials[self._answers.popleft()] for _ in spans]
        self.requests_answered += len(answers)
        if not data:
            return b"".join(answers)
        pieces, last = [], 0
        for (offset, size), answer in zip(spans, answers):
            pieces += (data[last:offset], answer)
            last = offset + size
        pieces.append(data[last:])
        return b"".join(pieces)

    def _greeting(self) -> bytes:
        """What a reader that has just opened the pty gets first: the power-up datagrams."""
        with self._lock:
            return b"".join(self._specials[kind] for kind in POWER_UP if kind in self._specials)

    def _request(self, line: bytes) -> None:
        kind = QUERY_KINDS.get(line)
        if kind is None:
            self._refused.add(request=_text(line), why=request_refusal(line, False))
            return
        with self._lock:
            seen = kind in self._specials
            if seen and kind not in self._answers:
                self._answers.append(kind)
        if not seen:
            self._refused.add(request=_text(line), why=f"the stream has carried no {kind.name.replace('_', ' ')} "
                                                       "datagram to answer with")

    def close(self) -> None:
        self._pty.close()

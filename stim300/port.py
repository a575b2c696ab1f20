"""The serial side of the driver: open a port, read it into a ring, record it.

`PortReader` is what the daemon runs: a thread that reads whatever the port has, stamps each
read with the host clock, feeds one `StreamParser` (kept across reopens, so its statistics
cover the whole session) and pushes the samples into a `RingBuffer`. A vanished device is
closed and reopened with exponential backoff, and every (re)open asks for the configuration
datagram (`C<CR>`, protocol doc §12) so the parser re-adopts the sensor's format. `write`
sends a request to the sensor from any thread (a daemon forwarding its clients' requests);
`lend` pauses the reading and hands the open port to a function for Service Mode (a daemon
trimming the sensor between batches).

Service Mode (talking to the unit instead of reading it) is `stim300.service`.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager, suppress
from pathlib import Path

import numpy as np
import serial
import structlog

from .atomic import atomic_file
from .errors import PortError, UsageError, os_reason
from .protocol import CONFIGURATION, DEFAULT_BIT_RATE
from .reads import ReadLog, reads_path
from .ringbuffer import RingBuffer
from .serialread import READ_MOST, read_available, read_waited
from .stream import StreamParser

log = structlog.get_logger(__name__)

WRITE_TIMEOUT_S = 1.0  # a command write that blocks longer means the port is dead

_ERRNO_TEXT = {
    errno.ENOENT: "no such device",
    errno.ENODEV: "no such device",
    errno.ENXIO: "no such device",
    errno.EACCES: "permission denied (is the user in the dialout group?)",
    errno.EPERM: "permission denied (is the user in the dialout group?)",
    errno.EBUSY: "device busy",
    errno.EAGAIN: "in use by another process",  # the exclusive lock is taken
    errno.EIO: "input/output error (device unplugged?)",
}


def describe_error(exc: BaseException) -> str:
    code = getattr(exc, "errno", None)
    if code in _ERRNO_TEXT:
        return _ERRNO_TEXT[code]
    if code:
        return os.strerror(code).lower()
    return " ".join(str(exc).split()) or type(exc).__name__


def open_serial(url: str, baudrate: int = DEFAULT_BIT_RATE, timeout: float = 0.05) -> serial.Serial:
    """Open a device path or pyserial URL at 8N1, locked against a second reader.

    Rates that are not termios constants (374400, 1843200, user-defined) are set by pyserial
    (BOTHER / termios2 on Linux). Raises `PortError` with a one-line reason.
    """
    try:
        return serial.serial_for_url(url, baudrate=baudrate, bytesize=8, parity="N", stopbits=1, timeout=timeout,
                                     write_timeout=WRITE_TIMEOUT_S, exclusive=True, do_not_open=False)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise PortError(f"{url}: {describe_error(exc)}") from exc


SERVED_BATCH_S = 0.004  # a reader whose reads are served as they come (a tap) reads this often while bytes
# flow, and parses each read at once
UNSERVED_BATCH_S = 0.05  # one whose samples wait in the ring for a consumer that polls (the daemon: every 0.2 s)
# reads this often: a datagram's host time is at most this late, under half a counter cycle (CYCLE_S / 2), so
# the host clock still proves a lost cycle (`stim300.clock`); 50 ms of a 1843200 bit/s port (9 kB) waits in the
# tty's flip buffers (64 kB or more on Linux; a pty's writer blocks)
UNSERVED_PARSE_S = 0.2  # ... and parses its reads together this often: a parse costs about the same whatever
# its size, several times a read's wake-up
PARSE_MOST = 65536  # unparsed bytes parsed whatever their age (a full-speed replay): 1 100 datagrams


class PortReader:
    """A thread: serial port -> `StreamParser` -> `RingBuffer`, surviving unplug/replug.

    `start()` opens the port (raising `PortError` if that fails) and starts the thread; later
    read errors close the port and reopen it, waiting reopen_backoff[0] s, doubling up to
    reopen_backoff[1] s, until it opens or `stop()` is called. `on_raw(bytes)` sees every read
    before the parser (e.g. to record it); `tap` is given to the parser (`StreamParser.tap`).

    Each read takes everything the port holds (at an empty port, the bytes that arrive together)
    and is stamped with `clock()` as it returns. A parse and a wake-up each have a fixed cost
    (~0.3 ms and ~0.1 ms cold) whatever the bytes' number, so while bytes flow the thread reads
    every `batch_s` and parses its reads together once the oldest is `parse_s` old, each datagram
    stamped with its own read's time (`StreamParser.feed_reads`). Served (`served`: a tap), it
    parses every read at once (the tap passes the stream on as it comes), and bytes it had to
    wait for (a low rate, a port that delivers in bursts) are served at once and the thread goes
    back to waiting; by default SERVED_BATCH_S, else UNSERVED_BATCH_S and UNSERVED_PARSE_S.
    Unserved, after a full read (READ_MOST) the thread reads on: the port holds more.

    `lend(use)` pauses the thread between two reads, parses what it has read, and calls
    `use(port)` with the open port; what `use` reads is its own, never fed to the parser, and
    reading goes on when it returns (a partial datagram before the loan and the datagrams the
    loan took show as skipped bytes and lost samples). `write` refuses meanwhile, so no request
    lands in the borrower's exchange.

    Counters: `reopens`, `read_errors`, `bytes_read`, `parser.stats`; `connected` is False while
    the port is being reopened. An unexpected exception (e.g. from `on_raw`) ends the thread and
    is kept in `error`.
    """

    def __init__(self, url: str, ring: RingBuffer, fmt=None, baudrate: int = DEFAULT_BIT_RATE,
                 request_config: bool = True, reopen_backoff: tuple[float, float] = (0.1, 2.0), on_raw=None,
                 clock=time.monotonic, batch_s: float | None = None, parse_s: float | None = None, tap=None):
        self.url = url
        self.ring = ring
        self.baudrate = baudrate
        self.request_config = request_config
        self.reopen_backoff = reopen_backoff
        self.on_raw = on_raw
        self.clock = clock
        self.served = tap is not None  # the parser's settled reads go to a tap as they come
        self.batch_s = batch_s if batch_s is not None else SERVED_BATCH_S if self.served else UNSERVED_BATCH_S
        self.parse_s = parse_s if parse_s is not None else 0.0 if self.served else UNSERVED_PARSE_S
        self.parser = StreamParser(fmt, tap=tap)
        self.reopens = 0
        self.read_errors = 0
        self.bytes_read = 0
        self.connected = False
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._port: serial.Serial | None = None  # the open port, for `write`; swapped under _port_lock
        self._port_lock = threading.Lock()
        self._reading = threading.Lock()  # held by the thread for each read, by a borrower for its loan
        self._not_lent = threading.Event()  # cleared while a borrower waits for the port or holds it
        self._not_lent.set()
        self._loans = threading.Lock()  # one borrower at a time
        self._unparsed: list[bytes] = []  # reads not parsed yet, and their log (where each ended, when it
        self._unparsed_log = ReadLog()  # returned): whoever holds `_reading` parses them (`_parse`)

    def start(self) -> PortReader:
        if self._thread is not None:
            raise RuntimeError("PortReader.start() called twice")
        ser = self._open()
        self._thread = threading.Thread(target=self._run, args=(ser,), name=f"stim300 reader {self.url}",
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop reading and close the port (within one port timeout); safe to call again."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def write(self, request: bytes) -> bool:
        """Send `request` (e.g. b"C\\r") to the sensor, from any thread; the reader thread keeps
        reading meanwhile. False, logged, when the port is closed or the write fails: the caller
        is a client's request, which must not break on a sensor that is gone."""
        with self._port_lock:
            ser = self._port
            if ser is None or not self._not_lent.is_set():
                log.warning("request_not_sent", port=self.url, request=request.decode("ascii", "replace"),
                            error="port not open" if ser is None else "port lent to Service Mode")
                return False
            try:
                ser.write(request)
            except (serial.SerialException, OSError) as exc:
                log.warning("request_not_sent", port=self.url, request=request.decode("ascii", "replace"),
                            error=describe_error(exc))
                return False
        return True

    def lend(self, use):
        """`use(port)` with the reading paused between two whole reads (what the last read gave
        is in the ring, nothing more comes to the parser until `use` returns), from any thread
        but the reader's; its return value. PortError when the port is not open (being
        reopened, or the thread ended)."""
        with self._loans:
            self._not_lent.clear()  # the thread stops before its next read and waits
            try:
                with self._reading:  # a read under way ends first
                    self._parse()
                    with self._port_lock:
                        ser = self._port
                    if ser is None:
                        raise PortError(f"{self.url}: port not open")
                    return use(ser)
            finally:
                self._not_lent.set()

    def _publish(self, ser: serial.Serial | None) -> None:
        """The port `write` uses from now on (None: none open)."""
        with self._port_lock:
            self._port = ser

    def is_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self) -> PortReader:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _open(self) -> serial.Serial:
        ser = open_serial(self.url, self.baudrate)
        if self.request_config:
            try:
                ser.reset_input_buffer()
                ser.write(CONFIGURATION.request)
            except (serial.SerialException, OSError) as exc:
                ser.close()
                raise PortError(f"{self.url}: {describe_error(exc)}") from exc
        self.connected = True
        log.info("port_opened", port=self.url, baudrate=self.baudrate, config_requested=self.request_config)
        return ser

    def _keep(self, data: bytes, t_host: float) -> None:
        """A read's bytes (returned at `t_host`) to the raw hook, and kept for the next parse."""
        self.bytes_read += len(data)
        if self.on_raw is not None:
            self.on_raw(data)
        self._unparsed.append(data)
        self._unparsed_log.add(self._unparsed_log.end + len(data), t_host)

    def _parse(self) -> None:
        """The reads kept so far through the parser into the ring (by whoever holds `_reading`)."""
        reads, log = self._unparsed, self._unparsed_log
        if not reads:
            return
        if len(reads) == 1:
            samples = self.parser.feed(reads[0], log.first_s)
        else:
            samples = self.parser.feed_reads(b"".join(reads), log.table())
        reads.clear()
        self._unparsed_log = ReadLog()
        if len(samples):
            self.ring.push(samples)

    @property
    def unparsed_bytes(self) -> int:
        """Bytes read that wait for the next parse: the ring does not have their samples yet."""
        return self._unparsed_log.end

    def _parse_due(self) -> bool:
        return bool(self._unparsed) and (self._unparsed_log.end >= PARSE_MOST
                                         or self.clock() - self._unparsed_log.first_s >= self.parse_s)

    def _run(self, ser: serial.Serial) -> None:
        self._publish(ser)
        try:
            while not self._stop.is_set():
                if not self._not_lent.wait(0.1):
                    continue  # lent: `stop` is still heard
                with self._reading:  # a loan waits for a whole read: its bytes read, and parsed when due
                    try:
                        data, waited = read_waited(ser)
                    except (serial.SerialException, OSError) as exc:
                        failed = exc
                        self._parse()
                    else:
                        failed = None
                        if data:
                            self._keep(data, self.clock())
                        if self._parse_due():
                            self._parse()
                if failed is not None:
                    ser = self._reopen(ser, failed)
                    if ser is None:
                        return
                    continue
                if data and (not waited if self.served else len(data) < READ_MOST):
                    time.sleep(self.batch_s)  # served: not after a wait; unserved: not after a full read
        except Exception as exc:  # noqa: BLE001 - the thread must report, not vanish silently
            self.error = exc
            log.exception("reader_failed", port=self.url)
        finally:
            if self.error is None:  # stopped, or the port could not be reopened: what was read is parsed
                with self._reading:
                    self._parse()
            self.connected = False
            self._publish(None)
            if ser is not None:
                ser.close()

    def _reopen(self, ser: serial.Serial, exc: BaseException) -> serial.Serial | None:
        """Close the failed port and reopen it with backoff; None if stopped meanwhile."""
        self.connected = False
        self._publish(None)
        self.read_errors += 1
        log.warning("port_error", port=self.url, error=describe_error(exc))
        try:
            ser.close()
        except (serial.SerialException, OSError):
            pass  # the device is gone: nothing left to release but the fd, which close() drops
        delay, longest = self.reopen_backoff
        while not self._stop.wait(delay):
            try:
                ser = self._open()
            except PortError as err:
                delay = min(2 * delay, longest)
                log.debug("port_reopen_failed", port=self.url, error=str(err), retry_in_s=delay)
                continue
            self.reopens += 1
            self._publish(ser)
            log.info("port_reopened", port=self.url, reopens=self.reopens)
            return ser
        return None


def record(url: str, output_path, baudrate: int = DEFAULT_BIT_RATE, duration_s: float | None = None,
           max_bytes: int | None = None) -> int:
    """Copy raw bytes from the port to `output_path` until duration, max_bytes, Ctrl-C or SIGTERM.

    Bytes go to OUT.part, renamed to OUT at the end whatever stopped the recording (a port
    error included), so a file named OUT is always complete. The host time of every read goes
    to OUT.reads.npy (`stim300.reads`), put in place just before OUT; an OUT named .mcap holds
    the bytes, their read times and the samples as sensor_msgs/Imu itself (`stim300.mcaprec`,
    the `recordings` extra). An OUT that is a symbolic
    link is followed, as every output named on the command line: the recording (and its read
    log) go where it points. OUT.part is the program's own: a file or link of that name is
    removed, never written through. Progress goes to stderr about once a second. Returns the
    exit status: 0, 1 after a port or file error (a full disk: no OUT.part is left), 2 for an OUT
    that is a directory, device or FIFO (renaming onto it would replace it); errors are one line
    on stderr.
    """
    out = Path(output_path)
    if out.is_symlink():
        out = Path(os.path.realpath(out))
    part = out.with_name(out.name + ".part")
    if out.exists() and not out.is_file():  # renaming OUT.part onto a device would replace the node
        kind = "a directory" if out.is_dir() else "not a regular file (a device or FIFO)"
        print(f"stim300 record: {output_path}: {kind}: a recording goes to a new or regular file", file=sys.stderr)
        return 2
    if out.suffix.lower() == ".mcap":
        from .mcaprec import mcap_modules

        try:
            mcap_modules()
        except UsageError as exc:
            print(f"stim300 record: {exc}", file=sys.stderr)
            return 2
    try:
        ser = open_serial(url, baudrate)
    except PortError as exc:
        print(f"stim300 record: {exc}", file=sys.stderr)
        return 1
    with sigterm_as_ctrl_c():
        return _record(ser, url, out, part, duration_s, max_bytes)


def _create(part: Path):
    """OUT.part as a new file: one a killed recording left (or a link of that name) is removed
    first, and O_EXCL creates a file, never opening a link, FIFO or device."""
    with suppress(FileNotFoundError):
        part.unlink()
    return os.fdopen(os.open(part, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb")


@contextmanager
def sigterm_as_ctrl_c():
    """SIGTERM (kill, systemd stopping a unit) ends a recording as Ctrl-C does: the bytes read so
    far are written and the file put in place, not lost in a buffer of a killed process. Only
    the first: a second one while the file is being finished is ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers belong to the main thread
        return

    def interrupt(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _CaptureFile:
    """A recording as a raw capture: the bytes to OUT.part as read, the read log beside OUT
    (OUT.reads.npy) when it is done."""

    def __init__(self, f):
        self.f, self.reads, self.total = f, ReadLog(), 0

    def add(self, data: bytes, returned: float) -> None:
        self.f.write(data)
        self.total += len(data)
        self.reads.add(self.total, returned)

    def finish(self, out: Path) -> None:
        with atomic_file(reads_path(out)) as f:
            np.save(f, self.reads.table())


class _McapFile:
    """A recording as an MCAP (OUT.mcap): the bytes with their read times, and the samples as
    sensor_msgs/Imu (`stim300.mcaprec`)."""

    def __init__(self, f):
        from .mcaprec import McapRecorder

        self.recorder, self.total = McapRecorder(f, library="stim300 record"), 0

    def add(self, data: bytes, returned: float) -> None:
        self.recorder.add(data, returned)
        self.total += len(data)

    def finish(self, out: Path) -> None:
        self.recorder.finish()


def _record(ser: serial.Serial, url: str, out: Path, part: Path, duration_s: float | None,
            max_bytes: int | None) -> int:
    status = 0
    start = time.monotonic()
    next_report = start + 1.0
    kind = _McapFile if out.suffix.lower() == ".mcap" else _CaptureFile
    try:
        with ser, _create(part) as f:
            sink = kind(f)
            try:
                while max_bytes is None or sink.total < max_bytes:
                    now = time.monotonic()
                    if duration_s is not None and now - start >= duration_s:
                        break
                    if now >= next_report:
                        print(f"recorded {sink.total} B in {now - start:.1f} s", file=sys.stderr, flush=True)
                        next_report += 1.0
                    try:
                        data = read_available(ser, None if max_bytes is None else max_bytes - sink.total)
                        returned = time.monotonic()
                    except (serial.SerialException, OSError) as exc:
                        print(f"stim300 record: {url}: {describe_error(exc)}", file=sys.stderr)
                        status = 1
                        break
                    if data:
                        sink.add(data, returned)
            except KeyboardInterrupt:
                pass  # Ctrl-C (or SIGTERM) is how an open-ended recording ends: keep what we have
            sink.finish(out)
        part.replace(out)
    except OSError as exc:
        with suppress(OSError):  # a directory of that name is not ours to remove
            part.unlink()
        print(f"stim300 record: {out}: cannot write: {os_reason(exc)}", file=sys.stderr)
        return 1
    print(f"recorded {sink.total} B in {time.monotonic() - start:.1f} s to {out}", file=sys.stderr)
    return status

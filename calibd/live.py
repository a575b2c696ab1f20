"""The daemon's I/O: the serial port or a capture in, the state directory, systemd and logs out.

`run` is `calibd run`: a PortReader fills a ring, this loop drains it into the Calibrator,
reports to systemd (READY, STATUS, WATCHDOG over $NOTIFY_SOCKET) and stops cleanly on SIGTERM;
SIGHUP reloads the configuration. `replay` runs the same Calibrator on a capture file, through
the same StreamParser, as fast as possible or paced; `replay_pty` goes through a pseudo-terminal
and the daemon's own port reader and loop instead.
"""

from __future__ import annotations

import bisect
import logging
import os
import signal
import socket
import sys
import threading
import time
import tty

import numpy as np
import structlog

from stim300.codec import SAMPLE_DTYPE, fault_bits
from stim300.port import PortError, PortReader
from stim300.ringbuffer import RingBuffer
from stim300.stream import StreamParser

from .config import ConfigError
from .daemon import Calibrator, ResultStore, State

log = structlog.get_logger("calibd")
POLL_S = 0.2  # how often the loop drains the ring
NO_DATA_S = 3.0  # silence that counts as a fault
RING_S = 30  # seconds of samples the ring holds at 2000 Hz


class _Stderr:
    """Whatever sys.stderr is at the time of writing (it may be replaced after configuration)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


def configure_logging(level: int = logging.INFO) -> None:
    """JSON lines on stderr for journald when not on a terminal (a traceback as a field of its
    line), readable lines on one (the console renderer prints tracebacks itself)."""
    renderers = [structlog.dev.ConsoleRenderer()] if sys.stderr.isatty() else \
        [structlog.processors.format_exc_info, structlog.processors.JSONRenderer()]
    structlog.configure(processors=[structlog.processors.add_log_level, structlog.processors.TimeStamper("iso"),
                                    *renderers],
                        wrapper_class=structlog.make_filtering_bound_logger(level),
                        logger_factory=structlog.PrintLoggerFactory(_Stderr()))


def sd_notify(message: str) -> bool:
    """Tell systemd (Type=notify) something; a no-op outside systemd."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        try:
            sock.sendto(message.encode(), address)
        except OSError:
            return False
    return True


def _rate(parser: StreamParser) -> int | None:
    step = parser.stats.counter_step
    return parser.format.sample_rate_hz or (2000 // step if step else None)


def _sensor(parser: StreamParser) -> dict:
    s = parser.scanner
    fmt = parser.format
    return {"serial_number": s.serial_number.text if s.serial_number else None,
            "part_number": str(s.part_number) if s.part_number else None,
            "datagram_id": f"0x{fmt.datagram_id:02X}" if fmt.datagram_id is not None else None,
            "sample_rate_hz": _rate(parser)}


def stream_faults(stats, before: dict, samples) -> tuple[dict, dict]:
    """What went wrong on the stream since `before` (CRC errors, lost samples, skipped bytes, and
    datagrams whose status bytes flag a fault): (counts now, increases)."""
    now = {"crc_errors": stats.crc_errors, "lost_samples": stats.lost_samples, "skipped_bytes": stats.skipped_bytes}
    increases = {k: v - before.get(k, 0) for k, v in now.items() if v > before.get(k, 0)}
    if len(samples):
        flagged = fault_bits(samples)
        if np.any(flagged):
            increases["flagged_datagrams"] = int(np.count_nonzero(flagged))
    return now, increases


def replay(data: bytes, calibrator: Calibrator, speed: float | None = None, chunk_bytes: int = 65536,
           progress=None) -> None:
    """Feed a capture's bytes through a StreamParser into the calibrator, as the live loop does,
    then tell it the data ended; `speed` N paces it at N times real time (None: as fast as possible)."""
    parser = StreamParser()
    started = time.monotonic()
    data_time = 0.0
    for offset in range(0, len(data) + 1, chunk_bytes):
        chunk = data[offset:offset + chunk_bytes]
        samples = parser.feed(chunk) if chunk else parser.finish()
        rate = _rate(parser)
        if len(samples) and rate:
            calibrator.sensor = _sensor(parser)
            feed_power_ups(calibrator, samples, parser.stats.datagrams - len(samples), rate,
                           parser.stats.restart_datagrams)
            data_time += len(samples) / rate
        if speed:
            time.sleep(max(0.0, started + data_time / speed - time.monotonic()))
        if progress:
            progress(min(offset + chunk_bytes, len(data)), len(data))
    calibrator.finish()


def feed_power_ups(calibrator: Calibrator, samples: np.ndarray, first: int, rate: int,
                   restart_datagrams: list[int]) -> None:
    """Feed a batch whose first sample is the stream's sample number `first`, cut where the sensor
    restarted inside it (`restart_datagrams`: each restarted sensor's first sample number), so the
    old power-up's last samples end its session instead of opening the new one's warm-up."""
    cuts = [i - first for i in restart_datagrams if first < i < first + len(samples)]
    for lo, hi in zip([0, *cuts], [*cuts, len(samples)]):
        calibrator.feed(samples[lo:hi], rate, bisect.bisect_right(restart_datagrams, first + lo))


class _Pump:
    """Ring -> calibrator, with the bookkeeping the live loop and the pty replay share: stream
    faults logged as they grow, overruns, and silence reported as a fault."""

    def __init__(self, reader: PortReader, ring: RingBuffer, calibrator: Calibrator):
        self.reader, self.ring, self.calibrator = reader, ring, calibrator
        self.cursor, self.last_data, self.counts = 0, time.monotonic(), {}

    def step(self) -> bool:
        """Feed what arrived since the last step; True if there were samples."""
        samples, self.cursor, lost = self.ring.read_since(self.cursor)
        if lost:
            log.warning("overrun", lost_samples=lost)
        parser = self.reader.parser
        self.counts, faults = stream_faults(parser.stats, self.counts, samples)
        if faults:
            log.warning("stream_faults", **faults)
        rate = _rate(parser)
        if len(samples) and rate:
            self.calibrator.sensor = _sensor(parser)
            feed_power_ups(self.calibrator, samples, self.cursor - len(samples), rate, parser.stats.restart_datagrams)
            self.last_data = time.monotonic()  # after the feed: time spent solving is not silence
            return True
        silent = time.monotonic() - self.last_data
        if silent > NO_DATA_S and self.calibrator.state != State.FAULT:
            self.calibrator.data_lost(silent)
        return False


def _new_ring() -> RingBuffer:
    return RingBuffer(2000 * RING_S, SAMPLE_DTYPE)


def replay_pty(data: bytes, calibrator: Calibrator, speed: float | None = None, progress=None,
               chunk_bytes: int = 4096) -> None:
    """`replay --pty`: the capture written into a pseudo-terminal and read back by the daemon's own
    PortReader (pyserial, framing thread, ring), paced at `speed` times real time or as fast as
    the daemon keeps up: the writer waits while the ring is more than half unread, so nothing
    is lost even when a solve holds the loop. When the capture has been read, the calibrator is
    told the data ended (the writer stopping is no fault)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    ring = _new_ring()
    reader = PortReader(os.ttyname(slave), ring, request_config=False)
    pump = _Pump(reader, ring, calibrator)
    written = [0]

    def write() -> None:
        rate = None
        started = time.monotonic()
        for offset in range(0, len(data), chunk_bytes):
            while ring.total - pump.cursor > ring.capacity // 2:
                time.sleep(0.01)
            if speed:
                rate = rate or _bytes_per_second(reader.parser)
                if rate:
                    time.sleep(max(0.0, started + offset / (rate * speed) - time.monotonic()))
            view = memoryview(data)[offset:offset + chunk_bytes]
            while view:
                view = view[os.write(master, view):]
            written[0] = offset + min(chunk_bytes, len(data) - offset)

    writer = threading.Thread(target=write, name="pty replay writer", daemon=True)
    reader.start()
    try:
        writer.start()
        idle = 0
        while writer.is_alive() or idle < 3:  # three quiet polls after the last byte: all read
            time.sleep(POLL_S)
            idle = 0 if pump.step() else idle + 1
            if progress:
                progress(written[0], len(data))
            if reader.error is not None:
                raise reader.error
        calibrator.finish()
    finally:
        reader.stop()
        os.close(master)
        os.close(slave)


def _bytes_per_second(parser: StreamParser) -> float | None:
    """The stream's byte rate once the parser knows the datagram length and the sample rate."""
    rate, stats = _rate(parser), parser.stats
    if not rate or not stats.datagrams:
        return None
    return rate * stats.bytes_in / max(stats.datagrams + stats.lost_samples, 1)


def run(config, reload_config) -> int:
    """`calibd run`: until SIGTERM. `reload_config()` returns a fresh config (SIGHUP) or raises
    ConfigError, which leaves the daemon running on the configuration it has."""
    store = ResultStore(config.state_dir)
    calibrator = Calibrator(config.site, config.warmup, config.method, on_result=store.write_result,
                            source=config.serial.port, detection=config.detection, on_stale=store.replace_result)

    def on_state(state: State, detail: str) -> None:
        store.write_state(state, detail, {"port": config.serial.port})
        sd_notify(f"STATUS={state.value.lower()}: {detail}")

    calibrator.on_state = on_state
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append("SIGTERM"))
    signal.signal(signal.SIGINT, lambda *_: stopping.append("SIGINT"))
    reload_requested = []
    signal.signal(signal.SIGHUP, lambda *_: reload_requested.append(True))
    ring = _new_ring()
    reader = PortReader(config.serial.port, ring, baudrate=config.serial.baudrate)
    try:
        reader.start()
    except PortError as exc:
        log.error("port_error", error=str(exc))
        print(f"calibd: {exc}", file=sys.stderr)
        return 1
    sd_notify("READY=1")
    log.info("started", port=config.serial.port, state_dir=str(config.state_dir))
    pump = _Pump(reader, ring, calibrator)
    try:
        while not stopping:
            time.sleep(POLL_S)
            if reload_requested:
                reload_requested.clear()
                try:
                    fresh = reload_config()
                    calibrator.configure(fresh.site, fresh.warmup, fresh.method, fresh.detection)
                    log.info("reloaded")
                except ConfigError as exc:
                    log.error("reload_failed", error=str(exc), detail="keeping the configuration in use")
            if pump.step():
                sd_notify("WATCHDOG=1")
            if reader.error is not None:
                log.error("reader_failed", error=str(reader.error))
                return 1
    finally:
        reader.stop()
        sd_notify("STOPPING=1")
        log.info("stopped", reason=stopping[0] if stopping else "error")
    return 0

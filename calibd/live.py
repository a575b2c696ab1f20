"""The daemon's I/O: the serial port or a capture in, the state directory, systemd and logs out.

One loop, `pump`, feeds the Calibrator from a `stim300.source.SampleSource`, whatever the
samples' origin. `run` is `calibd run`: the serial port (`PortSource`), with reports to systemd
(READY, STATUS, WATCHDOG over $NOTIFY_SOCKET), a clean stop on SIGTERM and a configuration
reload on SIGHUP; with a `[serve]` table it serves the sensor (`calibd.serve.hub.Hub`: ptys, the
socket, the result's copy); with `[trim] apply = "volatile"` it writes each good result into the
sensor as volatile bias trims on the port its reader lends (`calibd.daemon.Trimmer`). `replay` is
`calibd replay`: a capture (`CaptureSource`, as fast as possible or paced) or, for `--pty`, the
capture through a pseudo-terminal and the daemon's own port reader (`PtySource`).
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import time

import numpy as np
import structlog

from stim300.codec import fault_bits
from stim300.errors import PortError
from stim300.protocol import SERIAL_NUMBER
from stim300.source import PortSource, SampleSource

from .config import SERVED_TABLES, ConfigError
from .daemon import Calibrator, Listener, State, StateLog, Trimmer
from .methods import OptionError
from .statedir import ResultStore, StateDirError
from .serve.hub import Hub, make_feeds
from .serve.sockets import ServeError

log = structlog.get_logger("calibd")
POLL_S = 0.2  # how long one read of the source waits: batches of about this much data
NO_DATA_S = 3.0  # silence that counts as a fault


class _Stderr:
    """Whatever sys.stderr is at the time of writing (it may be replaced after configuration)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


# syslog priority of each log level: journald files a line by its "<N>" prefix
PRIORITY = {"critical": 2, "exception": 3, "error": 3, "warning": 4, "info": 6, "debug": 7}


def journal_priority(logger, method: str, line: str) -> str:
    """The rendered line prefixed with its syslog priority, so `journalctl -p warning` finds the
    warnings among the JSON lines of stderr."""
    return f"<{PRIORITY.get(method, 6)}>{line}"


def configure_logging(level: int = logging.INFO) -> None:
    """JSON lines on stderr for journald when not on a terminal (a traceback as a field of its
    line), each with its "<N>" priority when stderr is journald's ($JOURNAL_STREAM); readable
    lines on a terminal (the console renderer prints tracebacks itself)."""
    prefix = [journal_priority] if os.environ.get("JOURNAL_STREAM") else []
    renderers = [structlog.dev.ConsoleRenderer()] if sys.stderr.isatty() else \
        [structlog.processors.format_exc_info, structlog.processors.JSONRenderer(), *prefix]
    structlog.configure(processors=[structlog.processors.add_log_level, structlog.processors.TimeStamper("iso"),
                                    *renderers],
                        wrapper_class=structlog.make_filtering_bound_logger(level),
                        logger_factory=structlog.PrintLoggerFactory(_Stderr()))


def sd_notify(message: str) -> bool:
    """Tell systemd (Type=notify) something; a no-op outside systemd. Never blocks: a notify
    socket that is not read (full queue) drops the message rather than stall the loop."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        try:
            sock.sendto(message.encode(), socket.MSG_DONTWAIT, address)
        except OSError:
            return False
    return True


class SystemdStatus(Listener):
    """systemd's status line (`systemctl status`): the state and its detail, and while results
    cannot be written, "degraded: ..." (`degraded`, the ResultStore's `on_health`)."""

    def __init__(self) -> None:
        self._line = ""
        self._degraded: str | None = None

    def on_state(self, state: State, detail: str, progress: dict | None = None) -> None:
        self._line = f"{state.value.lower()}: {detail}"
        self._send()

    def degraded(self, why: str | None) -> None:
        self._degraded = why
        self._send()

    def _send(self) -> None:
        sd_notify(f"STATUS={self._line}" + (f"; degraded: {self._degraded}" if self._degraded else ""))


class Watchdog:
    """systemd's watchdog proves the loop alive, data or not: WATCHDOG=1 at a `kick` once half
    of $WATCHDOG_USEC (set by systemd when the unit has WatchdogSec=) has passed since the last.
    Silence of the sensor is the FAULT state, not a hung daemon."""

    def __init__(self, clock=time.monotonic) -> None:
        usec = os.environ.get("WATCHDOG_USEC", "")
        pid = os.environ.get("WATCHDOG_PID", "")
        mine = usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid()))
        self.interval_s = int(usec) / 2e6 if mine else None  # None: no watchdog
        self._clock = clock
        self._last_s = -float("inf")

    def kick(self) -> None:
        now_s = self._clock()
        if self.interval_s is not None and now_s - self._last_s >= self.interval_s:
            sd_notify("WATCHDOG=1")
            self._last_s = now_s


def stream_faults(stats, before: dict, samples) -> tuple[dict, dict]:
    """What went wrong on the stream since `before` (CRC errors, lost samples, skipped bytes, and
    datagrams whose status bytes flag a fault): (counts now, increases). `stats` has the running
    counts (a StreamInfo's stats, or a parser's Stats)."""
    now = {"crc_errors": stats.crc_errors, "lost_samples": stats.lost_samples, "skipped_bytes": stats.skipped_bytes}
    increases = {k: v - before.get(k, 0) for k, v in now.items() if v > before.get(k, 0)}
    if len(samples):
        flagged = fault_bits(samples)
        if np.any(flagged):
            increases["flagged_datagrams"] = int(np.count_nonzero(flagged))
    return now, increases


def pump(source: SampleSource, calibrator: Calibrator, stop=lambda: False, on_step=None, on_stream=None) -> None:
    """Source -> calibrator until `stop()` or the end of the stream, the one loop of `calibd run`
    and `calibd replay`: stream faults logged as they grow, ring overruns, silence beyond
    NO_DATA_S reported as a fault, and at the end of the data one last solve.
    `on_step(fed)` is called after every read (`fed`: samples reached the calibrator);
    `on_stream(info, counts, increases)` after every batch (the faults as `stream_faults` counts
    them, "overrun" among the increases when the ring overran)."""
    counts: dict = {}
    warned = 0  # the stream's warnings logged so far (they only grow)
    while not stop() and not source.ended:
        batch = source.read(POLL_S)
        fed = False
        if batch is not None:
            if batch.overrun_samples:
                log.warning("overrun", lost_samples=batch.overrun_samples)
            counts, faults = stream_faults(batch.info.stats, counts, batch.samples)
            if faults:
                log.warning("stream_faults", **faults)
            if on_stream:
                on_stream(batch.info, counts, {**faults, **({"overrun": batch.overrun_samples}
                                                            if batch.overrun_samples else {})})
            info = batch.info
            for text in info.warnings[warned:]:  # a configuration refused, or a code kept as read
                log.warning("stream_warning", detail=text)
            warned = len(info.warnings)
            if len(batch.samples) and info.rate_hz:
                calibrator.sensor_seen(info.sensor_record(), info.stream_record(), batch.trims)
                calibrator.feed(batch.samples, info.rate_hz, batch.first, info.stats.restart_datagrams)
                fed = True
        silent_s = source.silent_s
        if not fed and not source.ended and silent_s > NO_DATA_S and calibrator.state != State.FAULT:
            calibrator.data_lost(silent_s)
        if on_step:
            on_step(fed)
    if source.ended and source.error is None:
        calibrator.finish()


def replay(source: SampleSource, calibrator: Calibrator, progress=None, hub: Hub | None = None) -> None:
    """`calibd replay`: a capture's source (CaptureSource, or PtySource for `--pty` and `--serve`)
    through the daemon's loop to its end; `progress(done, total)` in bytes; `hub` (among the
    calibrator's listeners) serves the replayed sensor and is closed at the end. A failed port
    reader raises."""
    try:
        with source:
            pump(source, calibrator, on_step=progress and (lambda fed: progress(source.done_bytes, source.total_bytes)),
                 on_stream=hub and hub.stream_seen)
    finally:
        if hub is not None:
            hub.close()
    if source.error is not None:
        raise source.error


def run(config, reload_config) -> int:
    """`calibd run`: until SIGTERM. `reload_config()` returns a fresh config (SIGHUP) or raises
    ConfigError, which leaves the daemon running on the configuration it has."""
    status = SystemdStatus()
    try:
        store = ResultStore(config.state_dir, {"port": config.serial.port}, on_health=status.degraded)
        previous = store.previous()
        hub = Hub(config.serve, config.serial.port, previous, make_feeds(config.ros2, config.foxglove),
                  record=config.record) if config.serving else None
        try:
            source = PortSource(config.serial.port, config.serial.baudrate, tap=hub and hub.tap)
        except BaseException:
            if hub is not None:
                hub.close()
            raise
    except (StateDirError, PortError, ServeError) as exc:  # before READY=1: systemd sees the start fail
        log.error("start_failed", error=str(exc))
        print(f"calibd: {exc}", file=sys.stderr)
        return 1
    trimmer = Trimmer(config.trim, config.state_dir, config.serial.port, source.reader.lend)
    calibrator = Calibrator(config.site, config.warmup, config.method,
                            [StateLog(), store, status, *([hub] if hub else [])],
                            source=config.serial.port, detection=config.detection, previous=previous, trim=trimmer)

    def use_trim(trim) -> None:
        """[trim] from now on; when on and the stream has not named the unit yet, the unit is asked
        (I): a trim is checked against the unit its result names."""
        trimmer.config = trim
        if trim.apply != "off" and calibrator.sensor.serial_number is None:
            source.reader.write(SERIAL_NUMBER.request)

    use_trim(config.trim)
    if hub is not None:
        hub.port_writer = source.reader.write  # requests written into the raw pty go to the sensor
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append("SIGTERM"))
    signal.signal(signal.SIGINT, lambda *_: stopping.append("SIGINT"))
    reload_requested = []
    signal.signal(signal.SIGHUP, lambda *_: reload_requested.append(True))
    watchdog = Watchdog()
    sd_notify("READY=1")
    log.info("started", port=config.serial.port, state_dir=str(config.state_dir))

    def on_step(fed: bool) -> None:
        watchdog.kick()
        if store.degraded:
            store.retry()
        if reload_requested:
            reload_requested.clear()
            try:
                fresh = reload_config()
                calibrator.configure(fresh.site, fresh.warmup, fresh.method, fresh.detection)
                use_trim(fresh.trim)
                served = [f"[{name}]" for name in SERVED_TABLES if getattr(fresh, name) != getattr(config, name)]
                log.info("reloaded", serve=f"changed, kept as started: {', '.join(served)} (a change needs a restart)"
                         if served else "unchanged")
            except (ConfigError, OptionError) as exc:  # OptionError: an intrinsics file changed since it was read
                log.error("reload_failed", error=str(exc), detail="keeping the configuration in use")

    try:
        with source:
            pump(source, calibrator, stop=lambda: bool(stopping), on_step=on_step,
                 on_stream=hub and hub.stream_seen)
        if source.error is not None:
            log.error("reader_failed", error=str(source.error))
            return 1
    finally:
        sd_notify("STOPPING=1")
        if hub is not None:
            hub.close()
        log.info("stopped", reason=stopping[0] if stopping else "error")
    return 0

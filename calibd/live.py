"""The daemon's I/O: the serial port or a capture in, the state directory, systemd and logs out.

One loop, `pump`, feeds the Calibrator from a `stim300.source.SampleSource`, whatever the
samples' origin. `run` is `calibd run`: the serial port (`PortSource`), with reports to systemd
(READY, STATUS, WATCHDOG over $NOTIFY_SOCKET), a clean stop on SIGTERM and a configuration
reload on SIGHUP. `replay` is `calibd replay`: a capture (`CaptureSource`, as fast as possible
or paced) or, for `--pty`, the capture through a pseudo-terminal and the daemon's own port
reader (`PtySource`).
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys

import numpy as np
import structlog

from stim300.codec import fault_bits
from stim300.errors import PortError
from stim300.source import PortSource, SampleSource

from .config import ConfigError
from .daemon import Calibrator, Listener, State, StateLog
from .results import ResultStore

log = structlog.get_logger("calibd")
POLL_S = 0.2  # how long one read of the source waits: batches of about this much data
NO_DATA_S = 3.0  # silence that counts as a fault


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


class SystemdStatus(Listener):
    """systemd's status line (`systemctl status`): the state and its detail."""

    def on_state(self, state: State, detail: str) -> None:
        sd_notify(f"STATUS={state.value.lower()}: {detail}")


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


def pump(source: SampleSource, calibrator: Calibrator, stop=lambda: False, on_step=None) -> None:
    """Source -> calibrator until `stop()` or the end of the stream, the one loop of `calibd run`
    and `calibd replay`: stream faults logged as they grow, ring overruns, silence beyond
    NO_DATA_S reported as a fault, and at the end of the data one last solve.
    `on_step(fed)` is called after every read (`fed`: samples reached the calibrator)."""
    counts: dict = {}
    while not stop() and not source.ended:
        batch = source.read(POLL_S)
        fed = False
        if batch is not None:
            if batch.overrun_samples:
                log.warning("overrun", lost_samples=batch.overrun_samples)
            counts, faults = stream_faults(batch.info.stats, counts, batch.samples)
            if faults:
                log.warning("stream_faults", **faults)
            info = batch.info
            if len(batch.samples) and info.rate_hz:
                calibrator.sensor_seen(info.sensor_record())
                calibrator.feed(batch.samples, info.rate_hz, batch.first, info.stats.restart_datagrams)
                fed = True
        silent_s = source.silent_s
        if not fed and not source.ended and silent_s > NO_DATA_S and calibrator.state != State.FAULT:
            calibrator.data_lost(silent_s)
        if on_step:
            on_step(fed)
    if source.ended and source.error is None:
        calibrator.finish()


def replay(source: SampleSource, calibrator: Calibrator, progress=None) -> None:
    """`calibd replay`: a capture's source (CaptureSource, or PtySource for `--pty`) through the
    daemon's loop to its end; `progress(done, total)` in bytes. A failed port reader raises."""
    with source:
        pump(source, calibrator, on_step=progress and (lambda fed: progress(source.done_bytes, source.total_bytes)))
    if source.error is not None:
        raise source.error


def run(config, reload_config) -> int:
    """`calibd run`: until SIGTERM. `reload_config()` returns a fresh config (SIGHUP) or raises
    ConfigError, which leaves the daemon running on the configuration it has."""
    listeners = [StateLog(), ResultStore(config.state_dir, {"port": config.serial.port}), SystemdStatus()]
    calibrator = Calibrator(config.site, config.warmup, config.method, listeners, source=config.serial.port,
                            detection=config.detection)
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_: stopping.append("SIGTERM"))
    signal.signal(signal.SIGINT, lambda *_: stopping.append("SIGINT"))
    reload_requested = []
    signal.signal(signal.SIGHUP, lambda *_: reload_requested.append(True))
    try:
        source = PortSource(config.serial.port, config.serial.baudrate)
    except PortError as exc:
        log.error("port_error", error=str(exc))
        print(f"calibd: {exc}", file=sys.stderr)
        return 1
    sd_notify("READY=1")
    log.info("started", port=config.serial.port, state_dir=str(config.state_dir))

    def on_step(fed: bool) -> None:
        if fed:
            sd_notify("WATCHDOG=1")
        if reload_requested:
            reload_requested.clear()
            try:
                fresh = reload_config()
                calibrator.configure(fresh.site, fresh.warmup, fresh.method, fresh.detection)
                log.info("reloaded")
            except ConfigError as exc:
                log.error("reload_failed", error=str(exc), detail="keeping the configuration in use")

    try:
        with source:
            pump(source, calibrator, stop=lambda: bool(stopping), on_step=on_step)
        if source.error is not None:
            log.error("reader_failed", error=str(source.error))
            return 1
    finally:
        sd_notify("STOPPING=1")
        log.info("stopped", reason=stopping[0] if stopping else "error")
    return 0

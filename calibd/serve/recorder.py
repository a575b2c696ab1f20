"""The daemon's recording ([record]; docs/recordings.md): the sensor's bytes as read, with their
read times, and its samples as sensor_msgs/Imu, into MCAP files (`stim300.mcaprec`, the file
`stim300 record -o OUT.mcap` writes), a new file every `rotate_s` or `rotate_mb`.

The reader thread only hands each settled read over (`tap`: a bounded queue, never blocking);
a thread of its own writes. A file is written as NAME.mcap.part and renamed to NAME.mcap when it
is complete (rotation, stop), so a file named .mcap is always whole; a read is never split
between files (a settled read ends on a datagram's end). The newest `keep` files are kept. If
the writer falls behind by more than PENDING_BYTES the oldest reads go, counted, and the episode
is logged once with its count; a file that cannot be written is logged once and recording stops
until the next rotation tries again.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from datetime import datetime, timezone
from pathlib import Path

import structlog

from stim300.errors import UsageError
from stim300.mcaprec import McapRecorder, mcap_modules

from ..config import RecordConfig
from .sockets import ServeError

log = structlog.get_logger("calibd")

PENDING_BYTES = 16 << 20  # reads waiting for the writer: about 100 s of a 2000 Hz stream
PREFIX = "stim300-"
SUFFIX = ".mcap"


class Recorder:
    """Records what the reader thread taps into `config.directory`; `close()` finishes the file.
    The directory is made when its parent exists; one that cannot be made or written, or the
    recordings extra missing, is a ServeError (one line) at construction, before the daemon says
    it is ready."""

    def __init__(self, config: RecordConfig, library: str = "calibd"):
        try:
            mcap_modules()
        except UsageError as exc:
            raise ServeError(f"[record] {exc}") from None
        directory = config.directory
        try:
            if not os.path.lexists(directory):
                directory.mkdir(mode=0o750)  # its parent must exist (the state directory, say)
        except OSError as exc:
            raise ServeError(f"[record] directory {directory}: cannot be made: {exc.strerror or exc}") from None
        if not directory.is_dir() or directory.is_symlink():
            raise ServeError(f"[record] directory {directory}: not a directory")
        if not os.access(directory, os.W_OK | os.X_OK):
            raise ServeError(f"[record] directory {directory}: not writable")
        self.config, self.library = config, library
        self._queue: deque[tuple[bytes, float, int]] = deque()
        self._pending = 0
        self.dropped_bytes = 0
        self._dropping = False
        self._ready = threading.Condition()
        self._stop = False
        self._file = None  # (the open file, its McapRecorder, its .part path, when it started)
        self._failing = False
        self._thread = threading.Thread(target=self._run, name="calibd-record", daemon=True)

    def start(self) -> Recorder:
        self._thread.start()
        return self

    # ------------------------------------------------------------------ the reader thread
    def tap(self, data: bytes) -> None:
        """One settled read's bytes, stamped now (the read returned microseconds ago)."""
        if not data:
            return
        with self._ready:
            self._queue.append((data, time.monotonic(), time.time_ns()))
            self._pending += len(data)
            while self._pending > PENDING_BYTES and len(self._queue) > 1:
                lost = len(self._queue.popleft()[0])
                self._pending -= lost
                self.dropped_bytes += lost
                self._dropping = True
            self._ready.notify()

    def close(self) -> None:
        with self._ready:
            self._stop = True
            self._ready.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)
        self._finish_file()

    # ------------------------------------------------------------------ the recording thread
    def _run(self) -> None:
        episode = 0  # bytes let go in the present episode of falling behind
        while True:
            with self._ready:
                if not self._queue and not self._stop:
                    self._ready.wait(1.0)
                reads, self._queue = list(self._queue), deque()
                self._pending = 0
                dropped, self._dropping = self._dropping, False
                stopping = self._stop
            if dropped and not episode:
                log.warning("record_dropped", why="the recording fell behind the sensor: its oldest reads are let "
                                                  "go; the count is said when it has caught up")
            if dropped:
                episode = self.dropped_bytes
            elif episode:
                log.info("record_caught_up", dropped_bytes=episode)
                episode = 0
            self._rotate_if_due(0)
            for data, t_host, realtime_ns in reads:
                self._write(data, t_host, realtime_ns)
            if stopping:
                return

    def _write(self, data: bytes, t_host: float, realtime_ns: int) -> None:
        self._rotate_if_due(len(data))
        if self._file is None and not self._open(realtime_ns):
            return
        _, recorder, part, _ = self._file
        try:
            recorder.add(data, t_host, realtime_ns)
        except Exception as exc:  # noqa: BLE001 (a full disk, or anything else: logged once, never the daemon's end)
            self._fail(part, exc)

    def _rotate_if_due(self, coming: int) -> None:
        if self._file is None:
            return
        f, _, _, started = self._file
        if time.monotonic() - started >= self.config.rotate_s or f.tell() + coming > self.config.rotate_mb * 1e6:
            self._finish_file()  # the size written so far: the MCAP writer's chunks (1 MB) reach the file whole

    def _open(self, realtime_ns: int) -> bool:
        when = datetime.fromtimestamp(realtime_ns / 1e9, timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
        part = self.config.directory / f"{PREFIX}{when}{SUFFIX}.part"
        try:
            f = os.fdopen(os.open(part, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644), "wb")
            recorder = McapRecorder(f, self.config.frame_id, self.library)
        except OSError as exc:
            self._fail(part, exc)
            return False
        self._file = (f, recorder, part, time.monotonic())
        if self._failing:
            log.info("record_recovered", file=str(part.with_suffix("")))
        self._failing = False
        return True

    def _finish_file(self) -> None:
        if self._file is None:
            return
        f, recorder, part, _ = self._file
        self._file = None
        try:
            recorder.finish()
            f.close()
            os.replace(part, part.with_suffix(""))
        except Exception as exc:  # noqa: BLE001
            self._fail(part, exc)
            return
        log.info("recorded", file=str(part.with_suffix("")))
        self._prune()

    def _prune(self) -> None:
        """All but the newest `keep` recordings removed (their names sort by time)."""
        if not self.config.keep:
            return
        files = sorted(p for p in self.config.directory.glob(f"{PREFIX}*{SUFFIX}")
                       if p.is_file() and not p.is_symlink())
        for old in files[:-self.config.keep]:
            old.unlink(missing_ok=True)

    def _fail(self, part: Path, exc: Exception) -> None:
        if self._file is not None:
            self._file[0].close()
            self._file = None
        if not self._failing:
            log.error("record_failed", file=str(part), error=getattr(exc, "strerror", None) or str(exc),
                      detail="not recording until the next file can be written")
        self._failing = True

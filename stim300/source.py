"""Where decoded samples come from: one `SampleSource` seam over a port, a capture or a pty.

A consumer (the calibration daemon's loop) asks `source.read(timeout_s)` for the next `Batch`
whatever the samples' origin. As in python-can's bus classes, the public `read` owns the policy
every backend shares, pacing (`speed`: N times real time by the samples' rate, None as fast as
possible) and silence accounting (`silent_s`), while a backend implements `_read_internal` only:

- `PortSource`: a serial port (a `PortReader` thread filling a `RingBuffer`); ring overruns are
  reported in the batch.
- `CaptureSource`: a capture's bytes, decoded window by window through a `StreamParser`, so a
  long capture never holds all its samples at once.
- `PtySource`: a capture written into a pseudo-terminal and read back by a `PortSource`: the
  daemon's own serial path, without a sensor.

A port (and so a pty) takes an optional `tap`, given to its parser (`StreamParser.tap`): every
byte it reads, settled, for whoever passes the stream on. A port asks the sensor for its bias trim
offsets (`T`) once per power-up, when the power-up's own datagrams carried none (`request_trim`):
the answer takes one normal datagram's place, a gap the counter shows as one datagram lost.

A source that knows its stream ended returns None with `ended` True; a port never ends unless
its reader thread failed (then `error` holds why).
"""

from __future__ import annotations

import fcntl
import os
import struct
import termios
import threading
import time
import tty
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from .capture import StreamInfo, stream_info
from .codec import SAMPLE_DTYPE, join_samples
from .port import PortReader
from .protocol import BIAS_TRIM, DEFAULT_BIT_RATE, INTERNAL_RATE_HZ
from .ringbuffer import RingBuffer
from .stream import StreamParser, TrimSeen

RING_S = 30  # seconds of samples a port's ring holds at the internal rate
IDLE_READS_AT_END = 3  # a pty whose writer is done and that holds no unread byte has been read out after
# this many empty reads
PACE_BYTES = 1 << 20  # a paced pty writer takes the capture's byte rate from this much of its start (at least
# 8 s of a 2000 Hz stream)


@dataclass(frozen=True)
class Batch:
    """Samples in stream order with what the stream said about itself so far.

    `first` is the stream index of samples[0] (samples count from 0 since the source opened);
    `info` the stream as of this batch (`stim300.capture.StreamInfo`: rate, running fault
    counts, each restarted sensor's first stream index, the sensor's identity);
    `overrun_samples` were lost just before this batch because the consumer read the ring too late;
    `trims` the stream's latest Bias Trim Offset datagrams with where they came (`Scanner.bias_trims`).
    """

    samples: np.ndarray
    first: int
    info: StreamInfo
    overrun_samples: int = 0
    trims: tuple[TrimSeen, ...] = ()


def _batch(parser: StreamParser, samples: np.ndarray, first: int, overrun_samples: int = 0) -> Batch:
    return Batch(samples, first, stream_info(parser), overrun_samples, parser.scanner.bias_trims)


class Pacer:
    """Holds a stream to `speed` times real time: what is `data_s` into the stream goes out no
    earlier than `data_s / speed` after the pacer started (None: no waiting)."""

    def __init__(self, speed: float | None):
        self.speed = speed
        self.started = time.monotonic()

    def wait(self, data_s: float) -> None:
        if self.speed:
            time.sleep(max(0.0, self.started + data_s / self.speed - time.monotonic()))


class SampleSource(ABC):
    """`read(timeout_s) -> Batch | None`, a context manager; backends implement `_read_internal`.

    Silence (`silent_s`) counts from the first read after the last batch with samples, so time
    the consumer spends on a batch (a long solve) is not silence; whether silence is a fault is
    the consumer's call.
    """

    def __init__(self, speed: float | None = None):
        self.speed = speed
        self.ended = False
        self.error: BaseException | None = None
        self._pacer = Pacer(speed)
        self._data_s = 0.0
        self._quiet_since = time.monotonic()
        self._delivered = False

    def read(self, timeout_s: float) -> Batch | None:
        """The next batch, waiting up to about `timeout_s` for it; None when nothing came (or the
        stream ended: `ended`)."""
        if self._delivered:
            self._quiet_since, self._delivered = time.monotonic(), False
        if self.ended:
            return None
        batch = self._read_internal(timeout_s)
        if batch is None or not len(batch.samples):
            return batch
        if batch.info.rate_hz:
            self._data_s += len(batch.samples) / batch.info.rate_hz
            self._pacer.wait(self._data_s)
        self._delivered = True
        return batch

    @property
    def silent_s(self) -> float:
        """Seconds without samples (0 until the consumer comes back for more after a batch)."""
        return 0.0 if self._delivered else time.monotonic() - self._quiet_since

    @abstractmethod
    def _read_internal(self, timeout_s: float) -> Batch | None:
        """The backend's next batch (None: nothing this time; set `ended` at the stream's end)."""

    def close(self) -> None:
        """Release what the source holds (threads, ports); safe to call again."""

    def __enter__(self) -> SampleSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PortSource(SampleSource):
    """A serial port: a `PortReader` thread decodes into a ring of `ring_s` seconds at the internal
    rate; each read drains what arrived over `timeout_s`, so batches hold about that much data
    (the consumer's cost per batch is fixed). Opening fails with `PortError`. With `request_trim`,
    T is asked for once per power-up whose datagrams carried no BTO datagram (`_ask_trim`)."""

    def __init__(self, url: str, baudrate: int = DEFAULT_BIT_RATE, request_config: bool = True,
                 ring_s: float = RING_S, tap=None, request_trim: bool = True):
        super().__init__(speed=None)  # a port's samples arrive at their own pace
        self.ring = RingBuffer(int(INTERNAL_RATE_HZ * ring_s), SAMPLE_DTYPE)
        self.reader = PortReader(url, self.ring, baudrate=baudrate, request_config=request_config, tap=tap)
        self.request_trim = request_trim
        self._trim_asked: int | None = None  # the stream number of the power-up start T was asked for
        self._cursor = 0
        self._bytes_seen = 0
        self.reader.start()

    @property
    def unread(self) -> int:
        """Samples in the ring that no read has returned yet."""
        return self.ring.total - self._cursor

    def _ask_trim(self) -> None:
        """Write T once the configuration is known (its range scales the answer's accelerometer
        offsets) and the power-up's first normal datagram has come without a BTO datagram before
        it (a unit configured to send one at start-up has sent it): once per power-up whose
        datagrams the stream shows (the port opened on a running unit counts as one)."""
        scanner = self.reader.parser.scanner
        restarts = scanner.stats.restart_datagrams
        start = restarts[-1] if restarts else 0
        if (not self.request_trim or self._trim_asked == start or scanner.configuration is None
                or scanner.stats.datagrams <= start or any(t.datagram >= start for t in scanner.bias_trims)):
            return
        self._trim_asked = start
        self.reader.write(BIAS_TRIM.request)

    def _read_internal(self, timeout_s: float) -> Batch | None:
        time.sleep(timeout_s)
        self._ask_trim()
        samples, self._cursor, lost = self.ring.read_since(self._cursor)
        bytes_read = self.reader.bytes_read
        arrived, self._bytes_seen = bytes_read != self._bytes_seen, bytes_read
        if len(samples) or lost or arrived:  # bytes without samples can still be faults to report
            return _batch(self.reader.parser, samples, self._cursor - len(samples), lost)
        if self.reader.error is not None:
            self.error, self.ended = self.reader.error, True
        return None

    def close(self) -> None:
        self.reader.stop()


class CaptureSource(SampleSource):
    """A capture's bytes (bytes, bytearray, mmap) through a `StreamParser`, `chunk_bytes` at a
    time: memory holds one chunk's samples, however long the capture. With the capture's read
    log (`stim300.reads`), each sample gets the host time of the read that completed it, as
    the port reader stamped it live; without one, `t_host` is NaN."""

    def __init__(self, data, speed: float | None = None, reads: np.ndarray | None = None,
                 chunk_bytes: int = 65536):
        super().__init__(speed)
        self._data = memoryview(data).cast("B")
        self._reads = reads
        self._chunk_bytes = chunk_bytes
        self.parser = StreamParser()
        self.done_bytes = 0
        self.total_bytes = len(self._data)

    def _read_internal(self, timeout_s: float) -> Batch | None:
        while not self.ended:
            start, stop = self.done_bytes, min(self.done_bytes + self._chunk_bytes, self.total_bytes)
            if start < stop:
                samples = self._feed(start, stop)
            else:
                samples, self.ended = self.parser.finish(), True
            self.done_bytes = stop
            if len(samples):
                return _batch(self.parser, samples, self.parser.stats.datagrams - len(samples))
        return None

    def _feed(self, start: int, stop: int) -> np.ndarray:
        """Bytes [start, stop) into the parser, split where reads ended so each piece carries its
        read's host time."""
        if self._reads is None:
            return self.parser.feed(self._data[start:stop])
        ends = self._reads["end"]
        first, last = np.searchsorted(ends, [start, stop], side="right")
        cuts = [start, *ends[first:last].tolist()]
        if cuts[-1] != stop:
            cuts.append(stop)
        times = self._reads["t_host_s"]
        pieces = [self.parser.feed(self._data[lo:hi], float(times[k]) if k < len(times) else np.nan)
                  for k, lo, hi in zip(range(first, first + len(cuts)), cuts, cuts[1:]) if hi > lo]
        return join_samples(pieces) if pieces else np.empty(0, SAMPLE_DTYPE)

    def close(self) -> None:
        self._data.release()


class PtySource(SampleSource):
    """A capture written into a pseudo-terminal and read back by a `PortSource` (pyserial, the
    reader thread, the ring). Pacing happens where the bytes enter the pty, as a real port's
    bytes arrive paced, at the byte rate the capture's start gives (PACE_BYTES: its sample rate
    and bytes per sample), known before the first write whatever the reader's pace; a start that
    does not tell it is written unpaced. The writer waits while the ring is more than half
    unread, so nothing is lost even when the consumer is slow; the stream has ended once the
    writer is done and the port has been read out."""

    def __init__(self, data, speed: float | None = None, chunk_bytes: int = 4096, tap=None):
        super().__init__(speed=None)  # reads follow the bytes' arrival
        self._writer_pacer = Pacer(speed)
        self._data = data
        self._chunk_bytes = chunk_bytes
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        try:
            self._port = PortSource(os.ttyname(self._slave), request_config=False, tap=tap, request_trim=False)
        except BaseException:
            self._close_pty()
            raise
        self._stop = threading.Event()
        self._write_error: OSError | None = None
        self._idle_reads = 0
        self.done_bytes = 0
        self.total_bytes = len(data)
        self._writer = threading.Thread(target=self._write, name="pty source writer", daemon=True)
        self._writer.start()

    def _write(self) -> None:
        port, data, size = self._port, self._data, self._chunk_bytes
        half = port.ring.capacity // 2
        bytes_per_s = _bytes_per_second(data) if self._writer_pacer.speed else None
        for offset in range(0, len(data), size):
            while port.unread > half and not self._stop.is_set():
                time.sleep(0.01)
            if self._stop.is_set():
                return
            if bytes_per_s:
                self._writer_pacer.wait(offset / bytes_per_s)
            view = memoryview(data)[offset:offset + size]
            try:
                while view:
                    view = view[os.write(self._master, view):]
            except OSError as exc:
                if not self._stop.is_set():  # else closed under the writer: nobody reads any more
                    self._write_error = exc
                return
            self.done_bytes = min(offset + size, len(data))

    def _read_internal(self, timeout_s: float) -> Batch | None:
        batch = self._port.read(timeout_s)
        if self._port.ended or self._write_error is not None:
            self.error, self.ended = self._port.error or self._write_error, True
        elif batch is not None and len(batch.samples):
            self._idle_reads = 0
        elif not self._writer.is_alive() and not self._unread():
            self._idle_reads += 1
            self.ended = self._idle_reads >= IDLE_READS_AT_END
        return batch

    def _unread(self) -> int:
        """Bytes whose samples the ring does not have yet: in the pty, not read yet (a reader
        starved of CPU on a loaded host can leave some while reads come back empty), or read and
        waiting for the reader's next parse."""
        try:
            waiting = struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]
        except OSError:
            waiting = 0
        return waiting + self._port.reader.unparsed_bytes

    def close(self) -> None:
        self._stop.set()
        self._port.close()
        self._close_pty()

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass  # closed already: close() may be called again


def _bytes_per_second(data) -> float | None:
    """A capture's byte rate by its first PACE_BYTES: its sample rate (configured, or measured from
    the counter) times its bytes per datagram sent or lost; None when they do not tell it."""
    parser = StreamParser()
    parser.feed(data[:PACE_BYTES])
    rate, stats = stream_info(parser).rate_hz, parser.stats
    if not rate or not stats.datagrams:
        return None
    return rate * stats.bytes_in / max(stats.datagrams + stats.lost_samples, 1)

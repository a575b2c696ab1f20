"""What publishes the sensor beyond the socket (ROS 2 topics, the Foxglove view), on a thread of
its own so that no subscriber can slow the daemon.

The parser's tap (reader thread) only queues each read's samples, bounded (`SampleQueue`);
the calibrator's events (pump thread) and the stream's counts are handed over as they come.
Every TICK_S the feeds thread times the queued samples on the sensor's clock and stamps them on
the host's realtime clock (`stim300.wallclock`), and gives them, the events and, once a second,
the stream's health to each `Feed`. A feed that raises is logged once per episode with a count
of the failed calls, and called again at the next tick (a DDS or WebSocket error retries).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import structlog

from stim300.capture import StreamInfo
from stim300.clock import CounterClock
from stim300.codec import fault_bits, join_samples
from stim300.protocol import status_names
from stim300.wallclock import WallClock

from ..correction import ServedCorrection, uncorrectable
from ..results import CalibrationResult
from .queue import SampleQueue

log = structlog.get_logger("calibd")

TICK_S = 0.04  # how often queued samples are published: 25 batches a second, 80 samples each at 2000 Hz
HEALTH_S = 1.0  # how often the stream's health is published
# the stream's running counts Health carries (each grows with a fault of the stream)
STREAM_COUNTS = ("crc_errors", "lost_samples", "skipped_bytes", "overrun", "inferred_missing", "restarts",
                 "hidden_gaps", "dropped_samples")
RESETS_QUIET_S = 10.0  # without a reset of the stamps' mapping this long, an episode of resets has ended


@dataclass(frozen=True)
class FeedBatch:
    """Samples of one read or more, with their realtime stamps (int64 ns since the Unix epoch)
    and the result whose biases their corrected form subtracts (None: no corrected form: no
    result yet, or the stream's units cannot take a constant bias)."""

    samples: np.ndarray  # SAMPLE_DTYPE rows, the sensor's units
    stamp_ns: np.ndarray
    correction: ServedCorrection | None
    info: StreamInfo


@dataclass(frozen=True)
class Health:
    """The stream's health as the feeds publish it once a second: the daemon's state, the
    stream's running counts (CRC errors, lost, inferred-missing and dropped samples, restarts,
    hidden gaps, overruns) and the datagrams whose status bytes flagged a fault since the last."""

    state: str
    detail: str
    counts: dict[str, int]  # STREAM_COUNTS
    flagged_datagrams: int = 0
    faults: tuple[str, ...] = ()


class Feed(Protocol):
    """A publisher of the sensor; every call comes from the feeds thread."""

    def samples(self, batch: FeedBatch) -> None: ...

    def state(self, state: str, detail: str, progress: dict) -> None: ...

    def result(self, result: CalibrationResult) -> None: ...

    def health(self, health: Health) -> None: ...

    def close(self) -> None: ...


@dataclass
class _Events:
    """What the pump thread handed over since the last tick, in order: each state change (two in
    one tick are two messages) and each result."""

    states: list[tuple[str, str, dict]] = field(default_factory=list)
    results: list[CalibrationResult] = field(default_factory=list)


class Feeds:
    """The feeds thread over `feeds` (names: how the log calls them, e.g. "ros2"). `paced`: the
    stream comes at the sensor's pace (a port, a replay in real time), so the stamps follow the
    host's clock; a replay at another speed keeps the sensor's time scale from its start."""

    def __init__(self, feeds: dict[str, Feed], paced: bool = True):
        self.feeds = feeds
        self.queue = SampleQueue("the feeds thread lags (a ROS 2 or Foxglove subscriber?)")
        self._events = _Events()
        self._lock = threading.Lock()
        self._info: StreamInfo | None = None
        self._counts: dict[str, int] = {}
        self._state = ("STARTING", "waiting for data")
        self._clock, self._wall = CounterClock(), WallClock(follow=paced)
        self._hidden_gaps = 0
        self._resets, self._last_reset = 0, 0.0  # resets of the stamps' mapping in the present episode, the last
        self._fault_bits, self._flagged = 0, 0
        self._failing: dict[tuple[str, str], int] = {}  # (feed, call) -> calls failed in its present episode
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="calibd-feeds", daemon=True)

    def start(self) -> Feeds:
        self._thread.start()
        return self

    # ------------------------------------------------------------------ other threads hand over
    def tap(self, samples: np.ndarray, kept) -> None:
        """A read's samples and the correction they take (a ServedCorrection or None); reader thread."""
        self.queue.put(samples, kept)

    def state(self, state: str, detail: str, progress: dict) -> None:
        with self._lock:
            self._events.states.append((state, detail, progress))

    def result(self, result: CalibrationResult) -> None:
        with self._lock:
            self._events.results.append(result)

    def stream_seen(self, info: StreamInfo, counts: dict[str, int]) -> None:
        """The stream as the daemon's loop sees it after each batch (pump thread)."""
        self._info, self._counts = info, counts

    def close(self) -> None:
        """Stop the thread (after one last tick) and close every feed."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        for name in self.feeds:
            self._call(name, "close")

    # ------------------------------------------------------------------ the feeds thread
    def _run(self) -> None:
        next_health = time.monotonic() + HEALTH_S
        while True:
            stopping = self._stop.wait(TICK_S)
            self._tick()
            if time.monotonic() >= next_health or stopping:
                next_health = time.monotonic() + HEALTH_S
                self._publish_health()
            if stopping:
                return

    def _tick(self) -> None:
        with self._lock:
            events, self._events = self._events, _Events()
        for state in events.states:
            self._state = state[:2]
            self._each("state", *state)
        for result in events.results:
            self._each("result", result)
        info = self._info
        if info is None or not info.rate_hz:
            return  # until the rate is known nothing can be timed: the samples wait (bounded)
        pending = self.queue.take()
        if not pending:
            return
        samples = join_samples([piece for piece, _ in pending])
        times = self._clock.times(samples["counter"], info.rate_hz, samples["t_host"])
        self._hidden_gaps += times.hidden_gaps
        stamp_ns, step = self._wall.stamps(times.time_s, samples["t_host"])
        self._say_reset(step)
        bits = fault_bits(samples)
        self._flagged += int(np.count_nonzero(bits))
        self._fault_bits |= int(np.bitwise_or.reduce(bits)) if len(bits) else 0
        corrects = not uncorrectable(info.format)
        ends = np.cumsum([len(piece) for piece, _ in pending])
        lo = 0
        for i, (_, kept) in enumerate(pending):  # one batch per run of reads taking the same correction
            if i + 1 < len(pending) and pending[i + 1][1] is kept:
                continue
            correction = kept if corrects else None
            self._each("samples", FeedBatch(samples[lo:ends[i]], stamp_ns[lo:ends[i]], correction, info))
            lo = ends[i]

    def _say_reset(self, step: float | None) -> None:
        """A reset of the stamps' mapping logged at the first of an episode (resets again and
        again: a host clock being set repeatedly, a stream not at the sensor's pace), its end
        with the count once RESETS_QUIET_S go by without one."""
        now = time.monotonic()
        if step is not None:
            if not self._resets:
                log.warning("stamps_reset", step_ms=round(step * 1e3, 3),
                            why="the sensor's clock was mapped onto the host's realtime clock again")
            self._resets, self._last_reset = self._resets + 1, now
        elif self._resets and now - self._last_reset > RESETS_QUIET_S:
            if self._resets > 1:
                log.info("stamps_steady", resets=self._resets, detail="the stamps follow the host clock smoothly again")
            self._resets = 0

    def _publish_health(self) -> None:
        info = self._info
        counts = {name: 0 for name in STREAM_COUNTS} | self._counts
        if info is not None:
            counts |= {"inferred_missing": info.stats.inferred_missing, "restarts": info.stats.restarts}
        counts |= {"hidden_gaps": self._hidden_gaps, "dropped_samples": self.queue.dropped}
        health = Health(*self._state, counts, self._flagged, tuple(status_names(self._fault_bits)))
        self._flagged, self._fault_bits = 0, 0
        self._each("health", health)

    def _each(self, method: str, *args) -> None:
        for name in self.feeds:
            self._call(name, method, *args)

    def _call(self, name: str, method: str, *args) -> None:
        """One call of a feed: a failure logged at the first of an episode of that call (the
        feed's samples may fail while its health goes through), its recovery with the count of
        calls that failed."""
        try:
            getattr(self.feeds[name], method)(*args)
        except Exception as exc:  # a subscriber's trouble (DDS, WebSocket) must not stop the daemon
            if (name, method) not in self._failing:
                log.error("feed_failing", feed=name, call=method, error=f"{type(exc).__name__}: {exc}",
                          detail="logged once until it works again; retried at each call")
            self._failing[(name, method)] = self._failing.get((name, method), 0) + 1
            return
        failed = self._failing.pop((name, method), None)
        if failed is not None:
            log.info("feed_recovered", feed=name, call=method, failed_calls=failed)


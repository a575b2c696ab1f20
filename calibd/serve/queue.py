"""Each read's samples handed from the reader thread to a consumer thread (the socket server's,
the feeds'), bounded: a consumer that lags loses the oldest reads first, counted, and the log
says when dropping begins and how many went when it ends (once per episode, not per read)."""

from __future__ import annotations

import threading

import numpy as np
import structlog

log = structlog.get_logger("calibd")

PENDING_SAMPLES = 8000  # samples a queue keeps at most (4 s at 2000 Hz)


class SampleQueue:
    """At most PENDING_SAMPLES samples (a read longer than that is kept whole); `why`: the log's
    words for a lagging consumer."""

    def __init__(self, why: str):
        self.limit, self.why = PENDING_SAMPLES, why
        self.dropped = 0  # samples let go since the start
        self._pending: list[tuple[np.ndarray, object]] = []
        self._count = 0
        self._episode = 0  # of them, since the consumer last took the queue
        self._lock = threading.Lock()

    def put(self, samples: np.ndarray, tag) -> None:
        """A read's samples and what they take (`tag`); never blocks."""
        dropped = 0
        with self._lock:
            self._pending.append((samples, tag))
            self._count += len(samples)
            while self._count > self.limit and len(self._pending) > 1:
                dropped += len(self._pending.pop(0)[0])
            self._count -= dropped
            begins = dropped and not self._episode
            self._episode += dropped
            self.dropped += dropped
        if begins:
            log.warning("samples_dropping", why=f"{self.why}: the oldest queued samples go")

    def take(self) -> list[tuple[np.ndarray, object]]:
        """Every read queued, oldest first, and the queue emptied."""
        with self._lock:
            pending, self._pending, self._count = self._pending, [], 0
            ended, self._episode = self._episode, 0
        if ended:
            log.info("samples_drops_ended", dropped_samples=ended, why=self.why)
        return pending

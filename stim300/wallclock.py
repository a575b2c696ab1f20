"""Sample times on the host's realtime clock, from the sensor's own clock.

A message stamped with the arrival time of its read carries the read's jitter: several
datagrams share one read, and a loaded host reads late in bursts. The sensor's counter
(`stim300.clock.CounterClock`) times every sample exactly on the sensor's crystal. What is left
is where that time scale sits on the host's clock: the host time of a read minus the counter
time of its newest datagram is the true offset plus a latency that is never negative. So the
offset is the lower envelope of those differences: the lowest of each second (BIN_S), over the
last ENVELOPE_S, after taking out the drift between the two crystals (the median slope between
those minima, tens of ppm). The offset used follows that envelope at most SLEW, so a stamp
never moves with one read; an envelope more than STEP_S away (the host's realtime clock was set,
a stall longer than the window) resets it at once, and the step is reported.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

BIN_S = 1.0  # sensor seconds whose lowest host-minus-counter offset is one point of the envelope
ENVELOPE_S = 10.0  # the envelope's span: many reads, while drift and host stalls are told apart
SLEW = 500e-6  # the most the offset used moves per sensor second (500 ppm)
STEP_S = 0.02  # an envelope this far from the offset used is a new mapping, not drift


class WallClock:
    """Counter times (s, `CounterClock`) and their reads' host monotonic times -> realtime
    stamps in integer nanoseconds since the Unix epoch. `realtime` gives (realtime ns,
    monotonic s) read together (the host's clocks; a test's own). `follow=False` for a stream
    that does not come at the sensor's pace (a capture replayed faster): the offset found at
    the start is kept, so the stamps keep the sensor's time scale from there."""

    def __init__(self, realtime=None, follow: bool = True) -> None:
        self._realtime = realtime or _host_clocks
        self._follow_host = follow
        self._minima: deque[tuple[float, float]] = deque()  # (counter time, lowest offset of a batch)
        self._offset: float | None = None  # host monotonic minus counter time in use (s)
        self._last_s = 0.0  # the counter time the offset was last moved at
        self._epoch_ns: int | None = None  # realtime minus monotonic (ns), as last read

    def stamps(self, time_s: np.ndarray, t_host: np.ndarray) -> tuple[np.ndarray, float | None]:
        """The batch's realtime stamps (int64 ns), and the step (s) by which the mapping was
        reset before it (None: it went on smoothly). Samples without a host time (NaN) take the
        offset as it stands."""
        realtime_ns, monotonic_s = self._realtime()
        epoch_ns = realtime_ns - round(monotonic_s * 1e9)
        step = None
        if self._epoch_ns is not None and abs(epoch_ns - self._epoch_ns) > STEP_S * 1e9:
            step = (epoch_ns - self._epoch_ns) / 1e9  # the realtime clock was set
        self._epoch_ns = epoch_ns
        moved = self._follow(np.asarray(time_s, np.float64), np.asarray(t_host, np.float64))
        if moved is not None:
            step = moved if step is None else step + moved
        if self._offset is None:  # no host time seen yet: the batch is stamped as it is read
            self._offset = monotonic_s - float(time_s[-1]) if len(time_s) else 0.0
        return epoch_ns + np.rint((time_s + self._offset) * 1e9).astype(np.int64), step

    def _follow(self, time_s: np.ndarray, t_host: np.ndarray) -> float | None:
        """Move the offset in use towards the envelope; the step when it was reset."""
        finite = np.isfinite(t_host)
        if not finite.any() or (self._offset is not None and not self._follow_host):
            return None
        offsets = t_host[finite] - time_s[finite]
        low = int(np.argmin(offsets))
        point = (float(time_s[finite][low]), float(offsets[low]))
        now = float(time_s[finite][-1])
        if self._minima and self._minima[-1][0] > now - BIN_S:  # the second so far: keep its lowest
            if point[1] < self._minima[-1][1]:
                self._minima[-1] = point
        else:
            self._minima.append(point)
        while self._minima[0][0] < now - ENVELOPE_S:
            self._minima.popleft()
        envelope = _envelope(self._minima, now)
        if self._offset is None:
            self._offset, self._last_s = envelope, now
            return None
        if abs(envelope - self._offset) > STEP_S:  # a new mapping
            step = envelope - self._offset
            self._minima = deque([point])
            self._offset, self._last_s = point[1], now
            return step
        allowed = SLEW * (now - self._last_s)
        self._offset += float(np.clip(envelope - self._offset, -allowed, allowed))
        self._last_s = now
        return None


def _envelope(minima: deque[tuple[float, float]], now: float) -> float:
    """The offset at counter time `now` below every second's lowest, with the drift between
    the clocks (the median slope between them, at most SLEW) taken out: a slow host clock
    leaves no lag of the window's length."""
    times, offsets = np.array(minima).T
    drift = 0.0
    if len(times) >= 3:
        i, j = np.triu_indices(len(times), 1)
        drift = float(np.clip(np.median((offsets[j] - offsets[i]) / (times[j] - times[i])), -SLEW, SLEW))
    return float(np.min(offsets + drift * (now - times)))


def _host_clocks() -> tuple[int, float]:
    """The host's realtime clock (ns) and monotonic clock (s), read back to back."""
    return time.time_ns(), time.monotonic()

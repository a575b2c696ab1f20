"""Sample times on the host's realtime clock, from the sensor's own clock.

A message stamped with the arrival time of its read carries the read's jitter: several
datagrams share one read, and a loaded host reads late in bursts. The sensor's counter
(`stim300.clock.CounterClock`) times every sample exactly on the sensor's crystal. What is left
is where that time scale sits on the host's clock: the host time of a read minus the counter
time of its newest datagram is the true offset plus a latency that is never negative. So the
offset is the lower envelope of those differences: the lowest of each second (BIN_S), over the
last ENVELOPE_S, after taking out the drift between the two crystals (the median slope between
those minima, tens of ppm).

The offset used is a straight line in counter time, so the stamps step by the sensor's own
intervals: at the end of each second its slope becomes the drift plus what closes the gap to
the envelope over TAU_S (at most SLEW), never a jump, so no read moves a stamp. An envelope
more than STEP_S away (the host's realtime clock was set, a stall longer than the window)
resets it at once, and the step is reported.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

BIN_S = 1.0  # sensor seconds whose lowest host-minus-counter offset is one point of the envelope
ENVELOPE_S = 10.0  # the envelope's span: many reads, while drift and host stalls are told apart
TAU_S = 20.0  # sensor seconds over which the offset used closes its gap to the envelope
SLEW = 500e-6  # the most the offset used moves per sensor second beyond the drift (500 ppm)
STEP_S = 0.02  # an envelope this far from the offset used is a new mapping, not drift
CLOCK_SPREAD_NS = 20_000  # realtime and monotonic reads this close are one instant (a read takes ~100 ns)
CLOCK_TRIES = 8  # reads of the two clocks before the tightest is taken


class WallClock:
    """Counter times (s, `CounterClock`) and their reads' host monotonic times -> realtime
    stamps in integer nanoseconds since the Unix epoch. `realtime` gives (realtime ns,
    monotonic s) read together (the host's clocks; a test's own). `follow=False` for a stream
    that does not come at the sensor's pace (a capture replayed faster): the offset found at
    the start is kept, and the realtime clock's epoch with it unless the clock is set (a
    reported step), so the stamps keep the sensor's time scale from there."""

    def __init__(self, realtime=None, follow: bool = True) -> None:
        self._realtime = realtime or _host_clocks
        self._follow_host = follow
        self._minima: deque[tuple[float, float]] = deque()  # each complete second: (counter time, lowest offset)
        self._bin: tuple[float, float, float] | None = None  # the second so far: (its start, time, lowest offset)
        self._line: tuple[float, float, float] | None = None  # the offset used: (at counter time, offset, slope)
        self._first_s = 0.0  # the counter time of the first host time
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
        elif self._epoch_ns is not None and not self._follow_host:
            epoch_ns = self._epoch_ns  # a slewed realtime clock would bend the sensor's time scale
        self._epoch_ns = epoch_ns
        moved = self._follow(np.asarray(time_s, np.float64), np.asarray(t_host, np.float64))
        if moved is not None:
            step = moved if step is None else step + moved
        if self._line is None:  # no host time seen yet: the batch's last sample is taken as read now
            last_s = float(time_s[-1]) if len(time_s) else 0.0
            self._line = (last_s, monotonic_s - last_s, 0.0)
        at, offset, slope = self._line
        return epoch_ns + np.rint((time_s + offset + slope * (time_s - at)) * 1e9).astype(np.int64), step

    def _follow(self, time_s: np.ndarray, t_host: np.ndarray) -> float | None:
        """Keep each second's lowest offset; at the end of a second, bend the line in use
        towards the envelope. The step when the mapping was reset."""
        finite = np.isfinite(t_host)
        if not finite.any() or (self._line is not None and not self._follow_host):
            return None
        offsets = t_host[finite] - time_s[finite]
        low = int(np.argmin(offsets))
        point = (float(time_s[finite][low]), float(offsets[low]))
        if self._line is None:
            self._line, self._first_s, self._bin = (point[0], point[1], 0.0), point[0], (point[0], *point)
            return None
        if point[0] < self._bin[0] + BIN_S:  # the same second: keep its lowest
            if point[1] < self._bin[2]:
                self._bin = (self._bin[0], *point)
            return None
        self._minima.append(self._bin[1:])
        self._bin = (point[0], *point)
        while self._minima[0][0] < point[0] - ENVELOPE_S:
            self._minima.popleft()
        return self._bend(point[0])

    def _bend(self, now: float) -> float | None:
        """The line in use from counter time `now`: continuous, its slope the drift plus the gap
        to the envelope over TAU_S (the time so far, early on), at most SLEW beyond the drift;
        reset to the envelope when the gap is more than STEP_S (returned)."""
        envelope, drift = _envelope(self._minima, now)
        at, offset, slope = self._line
        used = offset + slope * (now - at)
        gap = envelope - used
        if abs(gap) > STEP_S:  # a new mapping
            self._minima.clear()
            self._line = (now, envelope, drift)
            return gap
        closing = gap / min(TAU_S, max(BIN_S, now - self._first_s))
        self._line = (now, used, drift + float(np.clip(closing, -SLEW, SLEW)))
        return None


def _envelope(minima: deque[tuple[float, float]], now: float) -> tuple[float, float]:
    """(the offset at counter time `now` below every second's lowest, the drift between the
    clocks): the drift is the median slope between the seconds' lowest (at most SLEW), taken out
    so that a slow host clock leaves no lag of the window's length."""
    times, offsets = np.array(minima).T
    drift = 0.0
    if len(times) >= 3:
        i, j = np.triu_indices(len(times), 1)
        drift = float(np.clip(np.median((offsets[j] - offsets[i]) / (times[j] - times[i])), -SLEW, SLEW))
    return float(np.min(offsets + drift * (now - times))), drift


def _host_clocks() -> tuple[int, float]:
    """The host's realtime clock (ns) and monotonic clock (s) at one instant: the realtime read
    between two monotonic reads, the tightest of a few tries. Read plainly back to back, a thread
    preempted between the two reads (a loaded host) puts its wait into the epoch, and so into
    every stamp of the batch, as an unreported step of milliseconds."""
    best = None
    for _ in range(CLOCK_TRIES):
        before = time.monotonic_ns()
        realtime_ns = time.time_ns()
        spread = time.monotonic_ns() - before
        if best is None or spread < best[0]:
            best = (spread, realtime_ns, (before + spread / 2) / 1e9)
        if spread <= CLOCK_SPREAD_NS:
            break
    return best[1], best[2]

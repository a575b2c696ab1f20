"""Sample times from the datagram counter, with the gaps it cannot see found from host read times.

The counter counts the sensor's internal 2000 Hz samples modulo 256: a step of 2000/rate per
datagram at a fixed rate, whatever time passed between triggers when the sensor is externally
triggered. So a sample's time is the running sum of the counter's steps / 2000, at any rate
and any trigger. The counter sees lost datagrams only modulo one counter cycle (256 internal
samples, 0.128 s): a loss of 16 datagrams at 125 Hz looks like none, 188 like 12. A time
base that misses those whole cycles is too short, and everything integrated over it (the
platform angle of a turn) comes out wrong.

The host clock sees them. Each datagram carries `t_host`, when the read that completed it
returned: its true time plus a latency that is never negative and, for the newest datagram of
each read, small (a read returns soon after bytes arrive; several datagrams may share one read).
So the host time minus the counter time, taken at its lower envelope (the minimum over a short
window), is flat apart from the host clock's ppm-level drift, and steps up by a whole number of
cycles where cycles were lost. A step is counted where the envelope after a datagram stands at
least half a cycle above the envelope before it, rounded to whole cycles. Host times that do
not keep pace with the counter (a capture replayed faster than real time) are no evidence: a
step is trusted only where the host clock ran at least as fast as the counter on both sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ

CYCLE_S = COUNTER_MODULUS / INTERNAL_RATE_HZ  # 0.128 s: what the counter cannot see
HOST_WINDOW_S = 0.5  # the envelope's window: many reads, yet far shorter than any drift matters


@dataclass(frozen=True)
class CounterTimes:
    """Seconds from the first sample, and the hidden gaps the host clock proved (`gap_index`:
    the first sample after each; `gap_s`: the time added there, whole counter cycles).
    `checked`: host times were there to look for them and kept pace with the counter (else none
    could be seen)."""

    time_s: np.ndarray
    gap_index: np.ndarray
    gap_s: np.ndarray
    checked: bool

    @property
    def hidden_gaps(self) -> int:
        return len(self.gap_index)

    @property
    def hidden_s(self) -> float:
        return float(self.gap_s.sum())


def counter_times(counter: np.ndarray, rate_hz: float, t_host: np.ndarray | None = None) -> CounterTimes:
    """Times of samples: the counter's steps (lost datagrams leave gaps, modulo a counter cycle),
    plus the whole cycles the host times prove were lost when they are given (all finite). A step
    of 0 counts is a whole cycle. A sensor restart (counter back to 0) looks like a loss.
    `rate_hz` (samples per second, measured when triggered) sizes the host window: a step is
    judged only with a whole window of data after it, so a gap in the last HOST_WINDOW_S stays
    unseen."""
    counter = np.asarray(counter)
    if counter.size == 0:
        return CounterTimes(np.zeros(0), np.zeros(0, np.int64), np.zeros(0), False)
    time_s = np.concatenate(([0.0], np.cumsum(counter_ticks(counter)))) / INTERNAL_RATE_HZ
    if not _evidence(time_s, t_host):
        return CounterTimes(time_s, np.zeros(0, np.int64), np.zeros(0), False)
    cycles = _hidden_cycles(np.asarray(t_host, np.float64) - time_s, host_window(rate_hz))
    gap_index = np.flatnonzero(cycles)
    time_s += np.cumsum(cycles) * CYCLE_S
    return CounterTimes(time_s, gap_index, cycles[gap_index] * CYCLE_S, True)


def counter_ticks(counter: np.ndarray) -> np.ndarray:
    """Internal samples (1/INTERNAL_RATE_HZ s) from each sample to the next, by the counter."""
    counts = np.diff(np.asarray(counter).astype(np.int64)) % COUNTER_MODULUS
    counts[counts == 0] = COUNTER_MODULUS
    return counts


def host_window(rate_hz: float) -> int:
    """Samples in HOST_WINDOW_S."""
    return max(2, int(round(HOST_WINDOW_S * rate_hz)))


def _evidence(time_s: np.ndarray, t_host: np.ndarray | None) -> bool:
    """Host times can show lost cycles: all there, and not arriving faster than real time."""
    return t_host is not None and len(t_host) == len(time_s) and bool(np.isfinite(t_host).all()) \
        and t_host[-1] - t_host[0] >= 0.9 * (time_s[-1] - time_s[0]) - CYCLE_S / 2


def _hidden_cycles(offset_s: np.ndarray, window: int) -> np.ndarray:
    """Whole cycles lost before each sample that has a whole window after it, from
    host-minus-counter offsets (modified in place).

    Gaps are taken in order, each removed from the offsets before the next is judged, so two
    gaps closer than a window do not add up."""
    from scipy.ndimage import minimum_filter1d  # here, not at the top: `import stim300` stays free of scipy

    n = len(offset_s)
    judged = n - window + 1
    cycles = np.zeros(n, np.int64)
    if judged < 2 or np.ptp(offset_s) < CYCLE_S / 2:  # no step can reach half a cycle: nothing to filter
        return cycles
    start = 1
    while start < judged:
        lo = max(0, start - window)
        part = offset_s[lo:]
        before = minimum_filter1d(part, window, mode="nearest", origin=(window - 1) // 2)  # min over [i-W+1, i]
        after = minimum_filter1d(part, window, mode="nearest", origin=-(window // 2))  # min over [i, i+W-1]
        steps = np.rint((after[1:] - before[:-1]) / CYCLE_S)  # steps[m]: before sample lo + m + 1
        found = None
        for m in np.flatnonzero(steps[start - lo - 1:judged - lo - 1] >= 1) + start - lo - 1:
            if _paced(offset_s, lo + m + 1, window):
                found = lo + m + 1
                break
        if found is None:
            break
        cycles[found] = int(steps[found - lo - 1])
        offset_s[found:] -= cycles[found] * CYCLE_S
        start = found + 1
    return cycles


def _paced(offset_s: np.ndarray, j: int, window: int) -> bool:
    """The host clock kept up with the counter over a window on each side of sample j: the
    offsets' envelope does not fall from one half of the window to the next by half a cycle (as
    it does when data come faster than real time; minima, so one late read does not count)."""
    half = max(1, window // 2)
    past, future = offset_s[max(j - 2 * half, 0):j], offset_s[j:j + 2 * half]
    return past[-half:].min() - past[:half].min() > -CYCLE_S / 2 \
        and future[-half:].min() - future[:half].min() > -CYCLE_S / 2


class CounterClock:
    """`counter_times` for a stream arriving in batches: each batch continues the times of the
    last, judged together with the samples before it. A step is judged once a whole window
    follows it, so a gap in a batch's last window is added at the start of the next batch:
    the samples between keep the counter's times, at most HOST_WINDOW_S of them. The counter
    counts the same internal samples at every rate, so a new rate (or a triggered stream's
    measured rate moving) continues the times; only the window's size follows the rate."""

    def __init__(self) -> None:
        self._counter: int | None = None  # the last sample's counter (None: no sample yet)
        self._last_s = 0.0  # the last sample's time
        self._time = np.zeros(0)  # the last samples' times, with every gap found so far,
        self._host = np.zeros(0)  # and their host times

    def times(self, counter: np.ndarray, rate_hz: int, t_host: np.ndarray | None = None) -> CounterTimes:
        """The batch's times (s since the first sample of the stream) and its hidden gaps."""
        if not len(counter):
            return counter_times(counter, rate_hz)
        if t_host is None:
            t_host = np.full(len(counter), np.nan)
        if self._counter is None:  # the stream's first sample at 0
            time_s = np.concatenate([[0.0], np.cumsum(counter_ticks(counter))]) / INTERNAL_RATE_HZ
        else:
            time_s = self._last_s + np.cumsum(counter_ticks(np.r_[self._counter, counter])) / INTERNAL_RATE_HZ
        known = len(self._time)
        time_all, host_all = np.concatenate([self._time, time_s]), np.concatenate([self._host, t_host])
        checked = _evidence(time_all, host_all)
        cycles = _hidden_cycles(host_all - time_all, host_window(rate_hz)) if checked \
            else np.zeros(len(time_all), np.int64)
        earlier = int(cycles[:known].sum())  # judged only now, before this batch: added at its start
        time_s += (earlier + np.cumsum(cycles[known:])) * CYCLE_S
        found = np.flatnonzero(cycles)
        gap_index, gap_s = np.maximum(found - known, 0), cycles[found] * CYCLE_S
        keep = 2 * host_window(rate_hz)  # a window before a step and one after it
        history = self._time + np.cumsum(cycles[:known]) * CYCLE_S  # its steps found: not found again
        self._time, self._host = np.concatenate([history, time_s])[-keep:], host_all[-keep:]
        self._counter, self._last_s = int(counter[-1]), float(time_s[-1])
        return CounterTimes(time_s, gap_index, gap_s, checked)

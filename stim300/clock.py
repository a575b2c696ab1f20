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
each read, small while the reader keeps up (a read returns soon after bytes arrive; several
datagrams may share one read). So the host time minus the counter time, taken at its lower
envelope (the minimum over a short window), is flat apart from the host clock's ppm-level drift,
and steps up by a whole number of cycles where cycles were lost. A step is counted where the
envelope after a datagram stands at least half a cycle above the envelope before it, rounded to
whole cycles, and only where it looks like a loss, not like a host stall:

- the host waited for that datagram: its host time follows the datagram before's by at least
  half a cycle more than its counter time does (datagrams read from a backlog come together);
- the host clock ran at least as fast as the counter before it (a capture replayed faster than
  real time is no evidence);
- the offsets over SETTLE_S of data after it do not fall back by STEADY_S. A stalled reader (a
  loaded host, a stopped process) finds the sensor's bytes waiting in the port's buffer and
  reads them late, in bursts faster than real time: the offsets jump, then fall back as it
  catches up, at many times the sensor's pace with CPU to spare, barely faster on a starved
  host. After a loss the datagrams come at the sensor's pace, a cycle or more short, for good.

So a gap is found SETTLE_S after it, and one in the last SETTLE_S of a stream stays unseen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ

CYCLE_S = COUNTER_MODULUS / INTERNAL_RATE_HZ  # 0.128 s: what the counter cannot see
HOST_WINDOW_S = 0.5  # the envelope's window: many reads, yet far shorter than any drift matters
SETTLE_S = 2.0  # how long the offsets after a step must stay up: a stalled reader catches up sooner
STEADY_S = CYCLE_S / 4  # how far they may fall back meanwhile (read jitter): more is a backlog being read


@dataclass(frozen=True)
class CounterTimes:
    """Seconds from the first sample, and the hidden gaps the host clock proved (`gap_index`:
    the first sample after each; `gap_s`: the time added there, whole counter cycles).
    `checked`: host times were there to look for them and kept pace with the counter (else none
    could be seen). `moved` (CounterClock): gaps found only now before this batch, each as
    (time, seconds): the samples already timed from that time on are `seconds` later, in order."""

    time_s: np.ndarray
    gap_index: np.ndarray
    gap_s: np.ndarray
    checked: bool
    moved: tuple[tuple[float, float], ...] = ()

    @property
    def hidden_gaps(self) -> int:
        return len(self.gap_index) + len(self.moved)

    @property
    def hidden_s(self) -> float:
        return float(self.gap_s.sum()) + sum(seconds for _, seconds in self.moved)


def counter_times(counter: np.ndarray, rate_hz: float, t_host: np.ndarray | None = None) -> CounterTimes:
    """Times of samples: the counter's steps (lost datagrams leave gaps, modulo a counter cycle),
    plus the whole cycles the host times prove were lost when they are given (all finite). A step
    of 0 counts is a whole cycle. A sensor restart (counter back to 0) looks like a loss.
    `rate_hz` (samples per second, measured when triggered) sizes the host windows: a step is
    judged only with SETTLE_S of data after it, so a gap in the last SETTLE_S stays unseen."""
    counter = np.asarray(counter)
    if counter.size == 0:
        return CounterTimes(np.zeros(0), np.zeros(0, np.int64), np.zeros(0), False)
    time_s = np.concatenate(([0.0], np.cumsum(counter_ticks(counter)))) / INTERNAL_RATE_HZ
    if not _evidence(time_s, t_host):
        return CounterTimes(time_s, np.zeros(0, np.int64), np.zeros(0), False)
    cycles = _hidden_cycles(np.asarray(t_host, np.float64) - time_s, host_window(rate_hz), settle_window(rate_hz))
    gap_index = np.flatnonzero(cycles)
    time_s += np.cumsum(cycles) * CYCLE_S
    return CounterTimes(time_s, gap_index, cycles[gap_index] * CYCLE_S, True)


def counter_ticks(counter: np.ndarray, previous: int | None = None) -> np.ndarray:
    """Internal samples (1/INTERNAL_RATE_HZ s) from each sample to the next, by the counter (from
    the `previous` sample's counter to the first, when given)."""
    counter = np.asarray(counter).astype(np.int64)
    counts = (np.diff(counter) if previous is None else np.diff(counter, prepend=previous)) % COUNTER_MODULUS
    counts[counts == 0] = COUNTER_MODULUS
    return counts


def host_window(rate_hz: float) -> int:
    """Samples in HOST_WINDOW_S."""
    return max(2, int(round(HOST_WINDOW_S * rate_hz)))


def settle_window(rate_hz: float) -> int:
    """Samples in SETTLE_S."""
    return max(host_window(rate_hz), int(round(SETTLE_S * rate_hz)))


def _evidence(time_s: np.ndarray, t_host: np.ndarray | None) -> bool:
    """Host times can show lost cycles: all there, and not arriving faster than real time."""
    return t_host is not None and len(t_host) == len(time_s) and _kept_pace(time_s[0], t_host[0], time_s, t_host)


def _kept_pace(first_s: float, first_host: float, time_s: np.ndarray, t_host: np.ndarray) -> bool:
    """`_evidence` of a first sample's (time, host time) followed by `time_s` and `t_host`."""
    return bool(np.isfinite(first_host)) and bool(np.isfinite(t_host).all()) \
        and t_host[-1] - first_host >= 0.9 * (time_s[-1] - first_s) - CYCLE_S / 2


def _hidden_cycles(offset_s: np.ndarray, window: int, settle: int) -> np.ndarray:
    """Whole cycles lost before each sample that has `settle` samples after it, from
    host-minus-counter offsets (modified in place).

    Gaps are taken in order, each removed from the offsets before the next is judged, so two
    gaps closer than a window do not add up."""
    from scipy.ndimage import minimum_filter1d  # here, not at the top: `import stim300` stays free of scipy

    n = len(offset_s)
    judged = n - settle + 1
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
        # a candidate is a step of the envelope where the host also waited for the sample (its
        # offset at least half a cycle above the one before), all taken at once: a host drifting
        # from the counter, as a slowed replay's, makes a step of nearly every sample, none a wait
        waited = np.diff(part) >= CYCLE_S / 2
        found = None
        for m in np.flatnonzero((steps >= 1)[start - lo - 1:judged - lo - 1]
                                & waited[start - lo - 1:judged - lo - 1]) + start - lo - 1:
            if _lost(offset_s, lo + m + 1, window, settle):
                found = lo + m + 1
                break
        if found is None:
            break
        cycles[found] = int(steps[found - lo - 1])
        offset_s[found:] -= cycles[found] * CYCLE_S
        start = found + 1
    return cycles


def _lost(offset_s: np.ndarray, j: int, window: int, settle: int) -> bool:
    """A step of the envelope before sample j, where the host waited for j (`_hidden_cycles`'
    candidates), is a loss, not a host stall: the host kept up with the counter over a whole window
    before it (the envelope does not fall by half a cycle from one half to the next, as it does
    when data come faster than real time), and the offsets over the `settle` samples after it
    never fall STEADY_S below those of its first half window (a backlog read after a stall
    does). Minima, so one late read does not count."""
    half = max(1, window // 2)
    if j < 2 * half:
        return False
    past, future = offset_s[j - 2 * half:j], offset_s[j:j + settle]
    return past[-half:].min() - past[:half].min() > -CYCLE_S / 2 \
        and future[half:].min() - future[:half].min() > -STEADY_S


class CounterClock:
    """`counter_times` for a stream arriving in batches: each batch continues the times of the
    last, judged together with the samples before it. A step is judged once SETTLE_S follows
    it, so most gaps are found after their samples were timed: `moved` says from which time
    those are late, and by how much, for the caller to move what it keeps. The host clock is
    evidence when it kept pace with the counter since the stream's first sample, as offline over
    the whole stream, so the burst that ends a stall does not leave a batch unchecked. The counter
    counts the same internal samples at every rate, so a new rate (or a triggered stream's
    measured rate moving) continues the times; only the windows' sizes follow the rate."""

    def __init__(self) -> None:
        self._counter: int | None = None  # the last sample's counter (None: no sample yet)
        self._last_s = 0.0  # the last sample's time
        self._first = (np.nan, np.nan)  # the first sample with a host time: its time and host time
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
            time_s = self._last_s + np.cumsum(counter_ticks(counter, self._counter)) / INTERNAL_RATE_HZ
        if np.isnan(self._first[1]) and np.isfinite(t_host[0]):
            self._first = (float(time_s[0]), float(t_host[0]))
        known = len(self._time)
        time_all, host_all = np.concatenate([self._time, time_s]), np.concatenate([self._host, t_host])
        checked = _kept_pace(*self._first, time_all, host_all)
        cycles = _hidden_cycles(host_all - time_all, host_window(rate_hz), settle_window(rate_hz)) if checked \
            else np.zeros(len(time_all), np.int64)
        found = np.flatnonzero(cycles)
        moved, history = (), self._time  # most batches: no gap found, nothing moves
        if found.size:
            added = np.cumsum(cycles) * CYCLE_S
            before = found[found < known]  # in samples timed already: each from its time once those before moved
            moved = tuple(zip((self._time + added[:known] - cycles[:known] * CYCLE_S)[before].tolist(),
                              (cycles[before] * CYCLE_S).tolist()))
            time_s += added[known:]
            history = self._time + added[:known]  # its steps found: not found again
        here = found[found >= known]
        keep = host_window(rate_hz) + settle_window(rate_hz)  # a window before a step and SETTLE_S after it
        self._time, self._host = np.concatenate([history, time_s])[-keep:], host_all[-keep:]
        self._counter, self._last_s = int(counter[-1]), float(time_s[-1])
        return CounterTimes(time_s, here - known, cycles[here] * CYCLE_S, checked, moved)

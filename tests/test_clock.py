"""The counter clock: counter steps, plus the whole counter cycles the host read times prove lost."""

import numpy as np
import pytest

from stim300.clock import CYCLE_S, CounterClock, counter_times
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ

RATE_HZ = 125


def host_read_times(true_s: np.ndarray, rng, read_every_s: float = 0.004, stall_every_s: float = 2.0,
                    stall_s: float = 0.06, drift_ppm: float = 80.0) -> np.ndarray:
    """When a host reading in bursts sees each datagram: reads every few ms (USB delivery), now
    and then held up by a loaded host for `stall_s`, on a clock drifting against the sensor's."""
    span = true_s[-1] + 1.0
    reads = np.cumsum(rng.uniform(0.5, 1.5, int(span / read_every_s) + 10) * read_every_s)
    stalls = rng.uniform(0, span, int(span / stall_every_s) + 1)
    for t in stalls:  # no read returns during a stall: the next one comes at its end
        inside = (reads > t) & (reads < t + stall_s)
        reads[inside] = t + stall_s
    reads = np.unique(reads)
    arrived = true_s + 0.0002  # the datagram's bytes are on the wire a little after its sample
    t_read = reads[np.searchsorted(reads, arrived)]
    return 1000.0 + t_read * (1 + drift_ppm * 1e-6)


def stalled_read_times(true_s: np.ndarray, stalls: list[tuple[float, float]], catch_up: float,
                       read_every_s: float = 0.004) -> np.ndarray:
    """When a reader that stops for each (start, seconds) of `stalls` sees each datagram: the
    bytes wait in the port's buffer, and a read takes at most `catch_up` times the sensor's pace
    of them (a reader with CPU to spare catches up fast, a starved one slowly)."""
    t_read, t, read_to = np.empty(len(true_s)), 0.0, 0.0  # read_to: how far into the data it has read
    i = 0
    while i < len(true_s):
        t = next((start + seconds for start, seconds in stalls if start <= t < start + seconds), t)
        read_to = min(t - 0.0002, read_to + catch_up * read_every_s)  # bytes come 0.2 ms after their sample
        ready = int(np.searchsorted(true_s, read_to, side="right"))
        t_read[i:ready] = t
        i = max(i, ready)
        t += read_every_s
    return 1000.0 + t_read


def live_times(counter: np.ndarray, t_host: np.ndarray, batch: int = 25) -> tuple[np.ndarray, int]:
    """The live clock's times in batches as the daemon keeps them (what it kept moves when a gap
    is found after it), and the gaps found."""
    clock, kept, gaps = CounterClock(), np.zeros(0), 0
    for a in range(0, len(counter), batch):
        times = clock.times(counter[a:a + batch], RATE_HZ, t_host[a:a + batch])
        for at, seconds in times.moved:
            kept[kept >= at] += seconds
        kept, gaps = np.r_[kept, times.time_s], gaps + times.hidden_gaps
    return kept, gaps


def stream(n: int, lost: dict[int, int], rate_hz: int = RATE_HZ):
    """Counters and true times of n sent datagrams, with lost[i] datagrams lost before the i-th."""
    index = np.arange(n) + np.cumsum([lost.get(i, 0) for i in range(n)])
    step = INTERNAL_RATE_HZ // rate_hz
    return ((index * step) % COUNTER_MODULUS).astype(np.uint8), index / rate_hz


@pytest.mark.parametrize("cycles", [1, 2, 12])
def test_hidden_gaps_of_whole_cycles_are_restored_exactly(cycles):
    per_cycle = int(round(CYCLE_S * RATE_HZ))
    lost = {700: cycles * per_cycle, 1500: cycles * per_cycle + 3}
    counter, true_s = stream(3000, lost)
    t_host = host_read_times(true_s, np.random.default_rng(cycles))
    result = counter_times(counter, RATE_HZ, t_host)
    np.testing.assert_allclose(result.time_s, true_s, atol=1e-9)
    assert result.gap_index.tolist() == [700, 1500]
    assert result.hidden_s == pytest.approx(2 * cycles * CYCLE_S)


def test_the_counter_alone_is_short_by_the_hidden_cycles():
    counter, true_s = stream(2000, {900: 188})  # 1.5 s lost: the counter sees 12 datagrams
    blind = counter_times(counter, RATE_HZ)
    assert true_s[-1] - blind.time_s[-1] == pytest.approx(11 * CYCLE_S)
    assert blind.hidden_gaps == 0
    fixed = counter_times(counter, RATE_HZ, host_read_times(true_s, np.random.default_rng(5)))
    np.testing.assert_allclose(fixed.time_s, true_s, atol=1e-9)
    assert fixed.hidden_gaps == 1 and fixed.hidden_s == pytest.approx(11 * CYCLE_S)


@pytest.mark.parametrize("seed", range(5))
def test_jitter_stalls_and_drift_alone_find_no_gap(seed):
    counter, true_s = stream(20_000, {3000: 5, 9000: 15})  # visible losses only
    t_host = host_read_times(true_s, np.random.default_rng(seed), stall_every_s=0.5, stall_s=0.06,
                             drift_ppm=200.0)
    result = counter_times(counter, RATE_HZ, t_host)
    assert result.hidden_gaps == 0
    np.testing.assert_allclose(result.time_s, true_s, atol=1e-9)


def test_host_times_faster_than_real_time_are_no_evidence():
    """A capture replayed at full speed, with pauses: the host clock says nothing of lost time."""
    counter, true_s = stream(5000, {})
    t_host = true_s / 200.0
    t_host[2500:] += 0.5  # the replay paused
    result = counter_times(counter, RATE_HZ, t_host)
    assert result.hidden_gaps == 0 and not result.checked
    assert counter_times(counter, RATE_HZ, np.r_[t_host[:2500], t_host[2500:] + 40.0]).hidden_gaps == 0  # a long pause


def test_without_host_times_the_counter_rules_as_before():
    step = INTERNAL_RATE_HZ // RATE_HZ
    sent = np.array([0, 1, 2, 5, 5 + 17, 5 + 17 + 16])  # 2 lost, then 16 (a whole cycle), then 15
    counter = (sent * step % COUNTER_MODULUS).astype(np.uint8)
    expected = np.array([0, 1, 2, 5, 6, 6 + 16]) / RATE_HZ  # the whole cycle is invisible; a step
    # of 0 counts is read as one cycle
    for t_host in (None, np.full(6, np.nan)):
        times = counter_times(counter, RATE_HZ, t_host)
        np.testing.assert_allclose(times.time_s, expected, atol=1e-12)
        assert not times.checked
    assert len(counter_times(np.zeros(0, np.uint8), RATE_HZ).time_s) == 0


def test_the_live_clock_in_batches_finds_each_gap_and_moves_what_was_timed_before():
    counter, true_s = stream(4000, {1000: 16, 1003: 64, 2600: 188})
    t_host = host_read_times(true_s, np.random.default_rng(9))
    clock, kept, gaps = CounterClock(), np.zeros(0), []
    edges = [0, 17, 990, 1000, 1001, 1030, 2600, 2625, 3333, 4000]  # gaps at, just after and before edges
    for a, b in zip(edges, edges[1:]):
        times = clock.times(counter[a:b], RATE_HZ, t_host[a:b])
        for at, seconds in times.moved:  # found SETTLE_S on, after those samples were timed
            kept[kept >= at] += seconds
        kept = np.r_[kept, times.time_s]
        gaps.append(times.hidden_s)
    np.testing.assert_allclose(kept, true_s, atol=1e-9)
    assert sum(gaps) == pytest.approx((1 + 4 + 11) * CYCLE_S)


@pytest.mark.parametrize("seed", range(3))
def test_the_live_clock_finds_no_gap_in_jitter_at_batch_ends(seed):
    """Batches as the daemon drains them (0.2 s): a stalled read at a batch's end is no gap."""
    counter, true_s = stream(10_000, {4000: 5})
    t_host = host_read_times(true_s, np.random.default_rng(seed), stall_every_s=0.3, stall_s=0.06)
    clock = CounterClock()
    times = np.concatenate([clock.times(counter[a:a + 25], RATE_HZ, t_host[a:a + 25]).time_s
                            for a in range(0, len(counter), 25)])
    np.testing.assert_allclose(times, true_s, atol=1e-9)


@pytest.mark.parametrize("step_cycles, found", [(0.49, False), (0.51, True)])
def test_a_step_is_judged_at_half_a_cycle_of_the_offsets_spread(step_cycles, found):
    """Offsets that spread less than half a cycle cannot hold a step and are not filtered at all;
    one just over half a cycle is still found (and rounded to a whole cycle)."""
    counter, true_s = stream(1000, {})
    t_host = 1000.0 + true_s + np.where(np.arange(1000) >= 500, step_cycles * CYCLE_S, 0.0)
    result = counter_times(counter, RATE_HZ, t_host)
    assert result.gap_index.tolist() == ([500] if found else [])
    assert result.hidden_s == pytest.approx(CYCLE_S if found else 0.0)


def test_the_live_clock_goes_on_through_a_moving_rate():
    """An externally triggered stream's measured rate moves from batch to batch: the counter
    counts the same internal samples whatever it is, so the times go on from the counter
    (only the host window follows the rate)."""
    steps = np.random.default_rng(3).choice([3, 5, 7], 3000)
    ticks = np.concatenate(([0], np.cumsum(steps)))
    counter = (ticks % COUNTER_MODULUS).astype(np.uint8)
    clock = CounterClock()
    rates = [390.0, 401.5, 399.0, 402.25]
    times = np.concatenate([clock.times(counter[a:a + 250], rates[k % 4]).time_s
                            for k, a in enumerate(range(0, len(counter), 250))])
    np.testing.assert_allclose(times, ticks / INTERNAL_RATE_HZ, atol=1e-12)
    np.testing.assert_allclose(counter_times(counter, 400.0).time_s, ticks / INTERNAL_RATE_HZ, atol=1e-12)


STALLS = [(4.1, 0.3), (9.7, 2.0), (15.2, 0.8), (21.0, 1.4), (27.5, 0.5)]


@pytest.mark.parametrize("catch_up", [10.0, 1.1])
def test_a_stalled_reader_is_no_hidden_gap(catch_up):
    """Stalls of 0.3 to 2 s: the bytes wait and are read late, in bursts; the offsets jump by the
    stall, then fall back as the reader catches up, at 10 or 1.1 times the sensor's pace (the
    slow one takes 20 s after the 2 s stall). Offline and live alike find nothing."""
    counter, true_s = stream(5000, {})
    t_host = stalled_read_times(true_s, STALLS, catch_up)
    assert np.ptp(t_host - true_s) > 1.5  # the offsets did jump
    result = counter_times(counter, RATE_HZ, t_host)
    assert result.checked and result.hidden_gaps == 0
    kept, gaps = live_times(counter, t_host)
    assert gaps == 0
    np.testing.assert_allclose(kept, true_s, atol=1e-9)


def test_losses_among_stalls_are_still_found():
    """Whole cycles lost while the reader keeps up, between stalls it catches up from at 1.5 times
    the sensor's pace: found offline and live, exactly."""
    counter, true_s = stream(5000, {875: 16, 2360: 188})  # at 7.0 s and 19.0 s
    t_host = stalled_read_times(true_s, STALLS, catch_up=1.5)
    result = counter_times(counter, RATE_HZ, t_host)
    assert result.gap_index.tolist() == [875, 2360]
    np.testing.assert_allclose(result.time_s, true_s, atol=1e-9)
    kept, gaps = live_times(counter, t_host)
    assert gaps == 2
    np.testing.assert_allclose(kept, true_s, atol=1e-9)

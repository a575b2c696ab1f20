"""Realtime stamps from the sensor's counter: jitter-free against the sensor's own time scale
whatever the reads' latency, following a crystal mismatch, and a reported step when the host's
realtime clock is set."""

import numpy as np
import pytest

from stim300.clock import CounterClock
from stim300.wallclock import STEP_S, WallClock

RATE_HZ = 2000
EPOCH_NS = 1_790_000_000 * 10**9  # realtime minus monotonic of the simulated host


def feed(seconds: float, ppm: float = 40.0, seed: int = 1, epoch_jump_at_s: float | None = None):
    """A 2000 Hz sensor whose crystal runs `ppm` fast, read in bursts of random size with
    random latency (mostly under 0.3 ms, sometimes a 30 ms stall): (stamps ns, true host
    times s, steps reported)."""
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE_HZ)
    true_s = 100.0 + np.arange(n) / RATE_HZ / (1 + ppm * 1e-6)  # monotonic seconds of each datagram
    counter = (np.arange(n) * (2000 // RATE_HZ)) % 256
    state = {"mono": 0.0, "epoch": EPOCH_NS}
    wall = WallClock(lambda: (state["epoch"] + round(state["mono"] * 1e9), state["mono"]))
    clock = CounterClock()
    stamps, steps, lo = [], [], 0
    while lo < n:
        hi = min(n, lo + int(rng.integers(1, 40)))
        latency = rng.exponential(0.0001) + (0.03 if rng.random() < 0.002 else 0.0)
        read_at = true_s[hi - 1] + latency
        t_host = np.full(hi - lo, read_at)
        state["mono"] = read_at + 0.0005
        if epoch_jump_at_s is not None and read_at - 100.0 >= epoch_jump_at_s:
            state["epoch"], epoch_jump_at_s = EPOCH_NS + 2 * 10**9, None
        time_s = clock.times(counter[lo:hi], RATE_HZ, t_host).time_s
        got, step = wall.stamps(time_s, t_host)
        stamps.append(got)
        if step is not None:
            steps.append(step)
        lo = hi
    return np.concatenate(stamps), true_s, steps


@pytest.mark.parametrize("ppm", [40.0, -60.0])
def test_stamps_follow_the_sensor_not_the_reads(ppm):
    stamps, true_s, steps = feed(60.0, ppm)
    error_s = (stamps - EPOCH_NS) / 1e9 - true_s
    settled = error_s[RATE_HZ * 10:]  # after the first envelope window
    assert steps == []
    jitter = settled - np.polyval(np.polyfit(true_s[RATE_HZ * 10:], settled, 1), true_s[RATE_HZ * 10:])
    assert np.sqrt(np.mean(jitter ** 2)) < 5e-6  # the reads' latency (0.1 ms, 30 ms stalls) does not reach them
    assert -5e-5 < settled.min() and settled.max() < 2e-4  # on the host clock within tens of us, as it settles
    assert np.all(np.diff(stamps) > 0)


def test_a_realtime_clock_set_is_a_reported_step():
    stamps, true_s, steps = feed(20.0, epoch_jump_at_s=10.0)
    assert len(steps) == 1 and abs(steps[0] - 2.0) < STEP_S
    error_s = (stamps - EPOCH_NS) / 1e9 - true_s
    assert abs(error_s[-1] - 2.0) < 1e-3 and abs(error_s[RATE_HZ * 5]) < 1e-3


def test_a_replay_faster_than_real_time_keeps_the_sensors_time_scale():
    """Not following the host (`follow=False`): the stamps step by the counter, whatever the
    host clock does meanwhile."""
    state = {"mono": 50.0}
    wall = WallClock(lambda: (EPOCH_NS + round(state["mono"] * 1e9), state["mono"]), follow=False)
    clock = CounterClock()
    counter = np.arange(2000 * 60) % 256  # a minute of 2000 Hz data
    stamps = []
    for lo in range(0, len(counter), 400):  # read 100 times faster than real time
        state["mono"] += 0.002
        time_s = clock.times(counter[lo:lo + 400], 2000, np.full(400, state["mono"])).time_s
        got, step = wall.stamps(time_s, np.full(400, state["mono"]))
        assert step is None
        stamps.append(got)
    assert np.all(np.diff(np.concatenate(stamps)) == 500_000)  # ns: exactly the sample interval


def test_the_host_clocks_are_read_at_one_instant_even_when_a_read_is_preempted(monkeypatch):
    """A thread preempted between its realtime and monotonic reads would see the epoch (realtime
    minus monotonic) move by its wait, and every stamp with it: the tightest of a few bracketed
    reads is taken instead."""
    from stim300 import wallclock

    monotonic = iter([10_000_000_000, 10_004_000_000,  # the first try: 4 ms preempted between its reads
                      10_005_000_000, 10_005_000_300])  # the second: 300 ns
    realtime = iter([EPOCH_NS + 10_004_000_000, EPOCH_NS + 10_005_000_150])
    monkeypatch.setattr(wallclock.time, "monotonic_ns", lambda: next(monotonic))
    monkeypatch.setattr(wallclock.time, "time_ns", lambda: next(realtime))
    realtime_ns, monotonic_s = wallclock._host_clocks()
    assert realtime_ns - round(monotonic_s * 1e9) == EPOCH_NS  # the second try's, to the nanosecond


def test_a_replays_stamps_keep_the_sensors_time_scale_while_the_realtime_clock_is_slewed():
    """NTP slews the realtime clock (up to 500 ppm): a live stream's stamps follow it, a replay's
    keep the counter's intervals exactly; a clock set is still a reported step."""
    state = {"mono": 50.0, "epoch": EPOCH_NS}
    wall = WallClock(lambda: (state["epoch"] + round(state["mono"] * 1e9), state["mono"]), follow=False)
    clock = CounterClock()
    counter = np.arange(2000 * 10) % 256
    stamps, steps = [], []
    for lo in range(0, len(counter), 400):
        state["mono"] += 0.002
        state["epoch"] += 1_000 + (2 * 10**9 if lo == 10_000 else 0)  # 1 us a read, and a 2 s set halfway
        time_s = clock.times(counter[lo:lo + 400], 2000, np.full(400, state["mono"])).time_s
        got, step = wall.stamps(time_s, np.full(400, state["mono"]))
        stamps.append(got)
        steps += [] if step is None else [step]
    steps_ns = np.diff(np.concatenate(stamps))
    assert len(steps) == 1 and abs(steps[0] - 2.0) < 1e-3
    assert np.count_nonzero(steps_ns != 500_000) == 1  # ns: the sample interval but at the set

"""RingBuffer: exact order against a reference, zero-copy views, overrun accounting, and a
single-producer / single-consumer stress run that would expose torn or reordered rows."""

import sys
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stim300.codec import SAMPLE_DTYPE
from stim300.ringbuffer import RingBuffer

# A sequence field plus a redundant copy of it: a row mixing two writes disagrees with itself.
ROW = np.dtype([("seq", "<i8"), ("payload", "<f4", (3,)), ("check", "<i8")])


def rows(start: int, n: int) -> np.ndarray:
    out = np.zeros(n, ROW)
    out["seq"] = np.arange(start, start + n)
    out["payload"] = out["seq"][:, None] * np.array([1, -1, 0.5], "f4")
    out["check"] = ~out["seq"]
    return out


def assert_rows(got: np.ndarray, first_seq: int) -> None:
    """`got` must be exactly the rows with sequences first_seq, first_seq + 1, ..."""
    np.testing.assert_array_equal(got, rows(first_seq, len(got)))


def fill(ring: RingBuffer, sizes) -> np.ndarray:
    """Push consecutive batches of `sizes`; return everything pushed (the reference)."""
    pushed = [rows(0, 0)]
    for n in sizes:
        pushed.append(rows(ring.total, n))
        ring.push(pushed[-1])
    return np.concatenate(pushed)


@pytest.mark.parametrize("capacity", [0, -3])
def test_rejects_non_positive_capacity(capacity):
    with pytest.raises(ValueError, match="capacity"):
        RingBuffer(capacity, ROW)


def test_rejects_rows_of_another_dtype():
    """A silent field-by-position cast would store garbage, so a mismatch is an error."""
    ring = RingBuffer(4, ROW)
    with pytest.raises(TypeError):
        ring.push(np.zeros(2, SAMPLE_DTYPE))
    with pytest.raises(TypeError):
        ring.push(list(rows(0, 2)))


@pytest.mark.parametrize("n", [3, 10, 25])
def test_push_smaller_equal_larger_than_capacity(n):
    ring = RingBuffer(10, ROW)
    ring.push(rows(0, n))
    assert ring.total == n
    assert len(ring) == min(n, 10)
    assert_rows(ring.latest_copy(100), max(0, n - 10))


def test_empty_ring_and_empty_push():
    ring = RingBuffer(5, ROW)
    ring.push(rows(0, 0))
    assert (len(ring), ring.total) == (0, 0)
    assert ring.latest(3).shape == (0,)
    got, next_seq, lost = ring.read_since(0)
    assert (len(got), next_seq, lost) == (0, 0, 0)


@settings(max_examples=200, deadline=None)
@given(capacity=st.integers(1, 40), sizes=st.lists(st.integers(0, 100), max_size=25), data=st.data())
def test_latest_is_a_view_of_the_reference_tail(capacity, sizes, data):
    """Whatever the wrap position, latest(n) is one contiguous view equal to the last n rows pushed."""
    ring = RingBuffer(capacity, ROW)
    ref = fill(ring, sizes)
    n = data.draw(st.integers(0, capacity + 5))
    view = ring.latest(n)
    expected = ref[len(ref) - min(n, len(ref), capacity):]
    np.testing.assert_array_equal(view, expected)
    if len(view):
        assert np.shares_memory(view, ring._buf)
        assert not view.flags.writeable
    copy = ring.latest_copy(n)
    np.testing.assert_array_equal(copy, expected)
    assert not np.shares_memory(copy, ring._buf)


@settings(max_examples=200, deadline=None)
@given(capacity=st.integers(1, 40), sizes=st.lists(st.integers(0, 100), max_size=25), data=st.data())
def test_read_since_returns_survivors_and_counts_the_overwritten(capacity, sizes, data):
    ring = RingBuffer(capacity, ROW)
    ref = fill(ring, sizes)
    seq = data.draw(st.integers(0, len(ref)))
    got, next_seq, lost = ring.read_since(seq)
    first = max(seq, len(ref) - capacity)
    np.testing.assert_array_equal(got, ref[first:])
    assert (next_seq, lost, ring.overruns) == (len(ref), first - seq, first - seq)
    assert not np.shares_memory(got, ring._buf)


def test_read_since_cursor_over_several_overruns():
    ring = RingBuffer(10, ROW)
    ring.push(rows(0, 25))
    got, cursor, lost = ring.read_since(0)
    assert_rows(got, 15)
    assert (cursor, lost) == (25, 15)
    ring.push(rows(25, 3))
    got, cursor, lost = ring.read_since(cursor)
    assert_rows(got, 25)
    assert (cursor, lost) == (28, 0)
    ring.push(rows(28, 4))
    ring.push(rows(32, 9))  # the consumer falls 3 rows behind the oldest kept
    got, cursor, lost = ring.read_since(cursor)
    assert_rows(got, 31)
    assert (cursor, lost, ring.overruns) == (41, 3, 18)


def test_read_since_rejects_a_cursor_from_the_future():
    """After clear() the consumer's old cursor is meaningless; better an error than silence."""
    ring = RingBuffer(4, ROW)
    ring.push(rows(0, 3))
    ring.clear()
    assert (len(ring), ring.total, ring.overruns) == (0, 0, 0)
    with pytest.raises(ValueError, match="cursor"):
        ring.read_since(3)


class _Intercepted(np.ndarray):
    """Runs a callback when sliced: push slices a wrapping batch between its writes, which lets a
    test read the ring while a push is half done."""

    def __array_finalize__(self, obj):
        hook = getattr(obj, "hook", None)
        if hook is not None:
            obj.hook = None
            hook()


def test_read_during_a_push_drops_rows_that_are_being_overwritten():
    """The push has begun (total not yet published), so re-reading total would miss it."""
    ring = RingBuffer(8, ROW)
    ring.push(rows(0, 6))
    seen = []
    batch = rows(6, 4).view(_Intercepted)  # wraps: slots 6, 7, 0, 1 (sequences 0 and 1 go)
    batch.hook = lambda: seen.append(ring.read_since(0))
    ring.push(batch)
    [(got, cursor, lost)] = seen
    assert_rows(got, 2)
    assert (cursor, lost) == (6, 2)
    got, cursor, lost = ring.read_since(cursor)
    assert_rows(got, 6)
    assert (cursor, lost, ring.overruns) == (10, 0, 2)


def test_works_with_the_sample_dtype():
    ring = RingBuffer(7, SAMPLE_DTYPE)
    batch = np.zeros(10, SAMPLE_DTYPE)
    batch["counter"] = np.arange(10)
    batch["gyro"] = np.arange(30).reshape(10, 3)
    ring.push(batch[:6])
    ring.push(batch[6:])
    np.testing.assert_array_equal(ring.latest(5), batch[5:])
    got, _, lost = ring.read_since(0)
    np.testing.assert_array_equal(got, batch[3:])
    assert lost == 3


@pytest.fixture
def frequent_thread_switches():
    """Switch threads every microsecond so the consumer lands inside pushes often."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    yield
    sys.setswitchinterval(old)


def test_producer_and_consumer_threads(frequent_thread_switches):
    total_rows, capacity = 200_000, 1024
    source = rows(0, total_rows)
    rng = np.random.default_rng(300)
    sizes = rng.integers(1, 1000, size=total_rows)
    sizes[::50] = 3 * capacity  # now and then a batch bigger than the ring
    ring = RingBuffer(capacity, ROW)
    done = threading.Event()

    def produce():
        start = 0
        for n in sizes:
            ring.push(source[start:start + n])
            start += n
            if start >= total_rows:
                break
        done.set()

    producer = threading.Thread(target=produce)
    received, lost_total, cursor = [], 0, 0
    producer.start()
    while True:
        finished = done.is_set()  # checked before reading, so the last read sees every row
        got, next_seq, lost = ring.read_since(cursor)
        lost_total += lost
        assert_rows(got, next_seq - len(got))  # exact sequences, nothing torn or reordered
        assert len(got) + lost == next_seq - cursor
        received.append(got["seq"])
        cursor = next_seq
        if finished:
            break
    producer.join()

    seqs = np.concatenate(received)
    assert np.all(np.diff(seqs) > 0)
    assert ring.total == total_rows
    assert len(seqs) + lost_total == total_rows
    assert ring.overruns == lost_total > 0

"""Fixed-capacity ring of sample records between the serial reader and the calibration daemon.

One producer appends batches (`push`), one consumer reads either the newest rows (`latest`) or
everything after a cursor (`read_since`). Rows are numbered by a monotonically increasing
sequence; row s lives at slot s % capacity. Storage is 2 * capacity rows and every row is
written to both halves, so any run of up to `capacity` consecutive rows is one contiguous slice:
`latest` is then always a view and `read_since` a single copy, with no wrap-around split.
"""

from __future__ import annotations

import numpy as np


class RingBuffer:
    """Single-producer / single-consumer ring of numpy records with overrun accounting.

    The producer announces the end of the batch it is about to write (`_claimed`), writes the
    rows, and only then publishes `total`; each is a plain int assignment, atomic under the GIL.
    The consumer reads `total` once, copies the rows below it, then re-reads `_claimed`: any row
    with sequence < `_claimed` - capacity may have been overwritten while it copied, so it is
    dropped from the front of the result and counted as lost. (Re-reading `total` instead would
    miss a batch the producer is still writing.)

    `capacity`, `total` (rows ever pushed since construction or `clear`) and `overruns` (rows the
    `read_since` cursor lost) are read-only for callers.
    """

    def __init__(self, capacity: int, dtype):
        if not isinstance(capacity, (int, np.integer)) or capacity <= 0:
            raise ValueError(f"RingBuffer capacity must be a positive integer, got {capacity!r}")
        self.capacity = int(capacity)
        self._buf = np.zeros(2 * self.capacity, dtype=dtype)
        # np.zeros expands a subarray dtype such as ("f4", 3) into extra dimensions: keep both.
        self.dtype = self._buf.dtype
        self._row_shape = self._buf.shape[1:]
        self.total = 0
        self._claimed = 0
        self.overruns = 0

    def __len__(self) -> int:
        """Rows currently available: min(total, capacity)."""
        return min(self.total, self.capacity)

    def push(self, batch: np.ndarray) -> None:
        """Append `batch` (producer only); of a batch longer than capacity only the tail is kept.

        Rows go to slots [i, i + k) of the first half and [i + cap, i + cap + k) of the second; the
        first write may run past the middle into the second half, so a push is two slice
        assignments, or three when the batch wraps. Nothing is allocated beyond slice views.
        """
        if not isinstance(batch, np.ndarray):
            raise TypeError(f"push expects a numpy array, got {type(batch).__name__}")
        if batch.dtype != self.dtype or batch.shape[1:] != self._row_shape:
            raise TypeError(f"push expects rows of {self.dtype} (row shape {self._row_shape}), "
                            f"got {batch.dtype} with shape {batch.shape}")
        n = len(batch)
        if n == 0:
            return
        cap = self.capacity
        end = self.total + n
        if n > cap:
            batch = batch[n - cap:]
        k = len(batch)
        i = (end - k) % cap
        buf = self._buf
        self._claimed = end  # before any write: readers treat sequences < end - cap as clobbered
        buf[i:i + k] = batch
        if i + k <= cap:
            buf[i + cap:i + cap + k] = batch
        else:
            split = cap - i
            buf[i + cap:] = batch[:split]
            buf[:k - split] = batch[split:]
        self.total = end  # publish last: every row below it is now in both halves

    def latest(self, n: int) -> np.ndarray:
        """The newest min(n, len(self)) rows, oldest first, as a read-only view into the ring.

        Zero-copy, so it is only valid until the producer writes over those slots (at the latest
        capacity - n rows later, or at once if a push is in progress): copy it, or use
        `latest_copy`, to keep it.
        """
        t = self.total
        n = self._count(n, t)
        start = (t - n) % self.capacity
        view = self._buf[start:start + n]
        view.flags.writeable = False
        return view

    def latest_copy(self, n: int) -> np.ndarray:
        """A private copy of the newest rows: up to min(n, len(self)), fewer only if the producer
        overwrote the oldest of them while they were being copied. Does not touch `overruns`."""
        t = self.total
        rows, _ = self._copy(t - self._count(n, t), t)
        return rows

    def read_since(self, seq: int) -> tuple[np.ndarray, int, int]:
        """Rows with sequence >= `seq` (a copy, in order), the cursor for the next call, and how
        many rows after `seq` were overwritten before they could be read (added to `overruns`).

        Always len(rows) + lost == next_seq - seq. Start with seq 0. A cursor beyond `total`
        (e.g. one kept across `clear`) is an error.
        """
        t = self.total
        if not 0 <= seq <= t:
            raise ValueError(f"read_since cursor {seq} is outside [0, total={t}]")
        rows, first = self._copy(max(seq, t - self.capacity), t)
        lost = first - seq
        self.overruns += lost
        return rows, t, lost

    def clear(self) -> None:
        """Forget all rows and reset `total` and `overruns` to 0. Not safe while either thread is
        using the ring: stop both first (cursors held by the consumer become invalid)."""
        self.total = 0
        self._claimed = 0
        self.overruns = 0

    def _count(self, n: int, t: int) -> int:
        if n < 0:
            raise ValueError(f"row count must be >= 0, got {n}")
        return min(n, t, self.capacity)

    def _copy(self, lo: int, hi: int) -> tuple[np.ndarray, int]:
        """Copy sequences [lo, hi) (hi <= published total, hi - lo <= capacity), then drop the
        ones a concurrent push may have overwritten. Returns (rows, first sequence kept)."""
        start = lo % self.capacity
        rows = self._buf[start:start + hi - lo].copy()
        first = min(max(lo, self._claimed - self.capacity), hi)
        return rows[first - lo:], first

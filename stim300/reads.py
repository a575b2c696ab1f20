"""The read log beside a recorded capture: when the host read each stretch of its bytes.

`stim300 record` writes CAPTURE and CAPTURE.reads.npy: one row per read, the byte offset just
after the read's last byte (`end`) and the host's monotonic clock when the read returned
(`t_host_s`). Offline decoding gives each datagram the time of the read that completed it,
exactly as a live port reader stamps it, so the counter clock can find the gaps the datagram
counter cannot see (`stim300.clock`).
"""

from __future__ import annotations

from array import array
from pathlib import Path

import numpy as np

READS_DTYPE = np.dtype([("end", "<i8"), ("t_host_s", "<f8")])


def reads_path(capture) -> Path:
    return Path(f"{capture}.reads.npy")


class ReadLog:
    """Reads as they happen, 16 B each (an hour of reads every 4 ms: 14 MB)."""

    def __init__(self) -> None:
        self._end = array("q")
        self._t = array("d")

    def add(self, end: int, t_host_s: float) -> None:
        self._end.append(end)
        self._t.append(t_host_s)

    @property
    def end(self) -> int:
        """The offset after the last read's last byte (0 before any read)."""
        return self._end[-1] if self._end else 0

    @property
    def first_s(self) -> float:
        """When the first read returned (NaN before any read)."""
        return self._t[0] if self._t else float("nan")

    def table(self) -> np.ndarray:
        rows = np.empty(len(self._end), READS_DTYPE)
        rows["end"] = np.frombuffer(self._end, np.int64)
        rows["t_host_s"] = np.frombuffer(self._t, np.float64)
        return rows


def load_reads(capture) -> np.ndarray | None:
    """The capture's read log (READS_DTYPE rows), or None when it has none, it is unreadable, or
    it does not end where the capture does (not this capture's: a capture from elsewhere, or
    one edited since, decodes as before, on the counter alone). Only a regular file is read: a
    FIFO of that name would block, a device never end."""
    path = reads_path(capture)
    if not path.is_file():
        return None
    try:
        rows = np.load(path, allow_pickle=False)
        size = Path(capture).stat().st_size
    except (OSError, ValueError):
        return None
    if rows.dtype != READS_DTYPE or rows.ndim != 1 or not len(rows) or rows["end"][-1] != size:
        return None
    return rows


def read_times(reads: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Host time of the read that brought the byte before each offset of `ends` (where the bytes
    deciding each datagram end: `Scanner.decided`), NaN for bytes the log does not cover."""
    index = np.searchsorted(reads["end"], ends, side="left")
    inside = index < len(reads)
    times = np.full(len(ends), np.nan)
    times[inside] = reads["t_host_s"][index[inside]]
    return times

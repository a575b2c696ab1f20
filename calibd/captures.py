"""Capture files read: a raw STIM300 capture (mapped, its read log beside it) or a recording
(ROS bag, rosbag2, MCAP), decoded into power-ups. Capture files are read here only: the rest of
calibd takes decoded captures and sessions. Cheap to import: what decodes is imported when a
capture is opened (the command line imports this module for every command)."""

from __future__ import annotations

import mmap
import os
from contextlib import contextmanager
from typing import TYPE_CHECKING

from stim300.cliutil import open_regular
from stim300.errors import UsageError

if TYPE_CHECKING:
    from .session import CaptureSessions, Session


@contextmanager
def mapped_input(path: str):
    """The input file at `path` mapped rather than read (b"" when empty), with a function that
    lets go of the pages before an offset once they are decoded: a long capture's pages never
    pile up in memory."""
    with open_regular(path) as f:
        if not os.fstat(f.fileno()).st_size:
            yield b"", lambda offset: None
            return
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
            def let_go(offset: int) -> None:
                done = offset // mmap.PAGESIZE * mmap.PAGESIZE
                if done:
                    mapped.madvise(mmap.MADV_DONTNEED, 0, done)

            yield mapped, let_go


def open_capture(path: str, data: bytes | None = None, topic: str | None = None) -> CaptureSessions:
    """The capture at `path` (its bytes, when already read) decoded, its datagrams stamped by the
    read log recorded beside it (PATH.reads.npy) when there is one; or, when `path` is a recording
    (a ROS bag, rosbag2 or MCAP, by its content), its sensor_msgs/Imu `topic` (None: its only one).
    A file is mapped, not read, and the pages decoded are let go, so a long capture never sits in
    memory whole."""
    from stim300.reads import load_reads

    from .recordings import is_recording, open_recording
    from .session import decode_sessions

    if data is None and is_recording(path):
        return open_recording(path, topic)
    if topic is not None:
        raise UsageError(f"{path}: --topic names a topic of a recording (ROS bag, rosbag2, MCAP), and this is a "
                         "STIM300 capture")
    reads = load_reads(path)
    if data is not None:
        return decode_sessions(data, str(path), reads)
    with mapped_input(path) as (mapped, let_go):
        return decode_sessions(mapped, str(path), reads, let_go)


def load_session(path: str, start_s: float | None = 0.0, data: bytes | None = None,
                 power_up: int | None = None, topic: str | None = None) -> Session:
    """One power-up of a capture (default the last) from `start_s` (None: where the warm-up ends);
    `topic`: a recording's Imu topic (None: its only one)."""
    from .session import power_up_session

    return power_up_session(open_capture(path, data, topic), power_up, start_s)

"""Capture files read: a raw STIM300 capture (mapped, its read log beside it), the MCAP `stim300
record` writes (the bytes and read log it holds) or a recording of Imu messages (ROS bag,
rosbag2, MCAP), decoded into power-ups. Capture files are read here only: the rest of
calibd takes decoded captures and sessions. Cheap to import: what decodes is imported when a
capture is opened (the command line imports this module for every command)."""

from __future__ import annotations

import hashlib
import mmap
import os
import stat
from contextlib import contextmanager
from typing import TYPE_CHECKING

from stim300.cliutil import open_regular
from stim300.errors import UsageError

if TYPE_CHECKING:
    from .session import CaptureSessions, Session

HASH_CHUNK = 1 << 20


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


@contextmanager
def capture_bytes(path: str, topic: str | None = None):
    """A STIM300 capture's bytes, its read log (None: none) and a function that lets go of the
    bytes before an offset once decoded: a file mapped (`mapped_input`) with the read log beside
    it (PATH.reads.npy), or the bytes and read log an MCAP of `stim300 record` holds. A `topic`
    (a recording's --topic) is refused: a capture has none."""
    from stim300.mcaprec import holds_capture, read_capture
    from stim300.reads import load_reads

    if topic is not None:
        raise UsageError(f"{path}: --topic names a topic of a recording of Imu messages (ROS bag, rosbag2, MCAP), "
                         "and this is a STIM300 capture")

    if holds_capture(path):
        data, reads = read_capture(path)
        yield data, reads, lambda offset: None
        return
    reads = load_reads(path)
    with mapped_input(path) as (data, let_go):
        yield data, reads, let_go


def first_stream_info(data):
    """What a capture's first datagrams say of its stream (`stim300.capture.StreamInfo`: the
    rate, the configuration), from its first 256 KiB."""
    from stim300.bulk import decode_capture

    return decode_capture(bytes(data[:1 << 18])).info


def is_imu_recording(path) -> bool:
    """Whether `path` is a recording of Imu messages alone (a ROS bag, rosbag2 or MCAP of
    sensor_msgs/Imu, by its content) rather than a STIM300 capture (raw, or the MCAP of
    `stim300 record`, which holds the sensor's bytes)."""
    from stim300.mcaprec import holds_capture

    from .recordings import is_recording

    return is_recording(path) and not holds_capture(path)


def open_capture(path: str, data: bytes | None = None, topic: str | None = None) -> CaptureSessions:
    """The capture at `path` (its bytes, when already read) decoded (`capture_bytes`: a file and
    its read log, or the MCAP `stim300 record` writes); or, when `path` is another recording (a
    ROS bag, rosbag2 or MCAP of sensor_msgs/Imu, by its content), its Imu `topic` (None: its
    only one). A file is mapped, not read, and the pages decoded are let go, so a long capture
    never sits in memory whole; on a terminal, a progress bar on stderr says how far reading is."""
    from stim300.progress import Progress
    from stim300.reads import load_reads

    from .recordings import open_recording
    from .session import decode_sessions

    if data is not None:
        return decode_sessions(data, str(path), load_reads(path))
    with Progress(f"reading {path}", 1) as bar:  # on a terminal only: a long input is minutes of reading
        if is_imu_recording(path):
            def read(done: int, total: int) -> None:
                bar.total = total
                bar.update(done)
            return open_recording(path, topic, read)
        with capture_bytes(path, topic) as (data, reads, let_go):
            bar.total, bar.unit = len(data) or 1, "B"

            def decoded_to(offset: int) -> None:
                bar.update(offset)
                let_go(offset)
            return decode_sessions(data, str(path), reads, decoded_to)


def load_session(path: str, start_s: float | None = 0.0, data: bytes | None = None,
                 power_up: int | None = None, topic: str | None = None) -> Session:
    """One power-up of a capture (default the last) from `start_s` (None: where the warm-up ends);
    `topic`: a recording's Imu topic (None: its only one)."""
    from .session import power_up_session

    return power_up_session(open_capture(path, data, topic), power_up, start_s)


def file_identity(path: str) -> tuple[str, int, float]:
    """SHA-256, size (B) and modification time (s since the epoch) of a regular file; OSError otherwise."""
    with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as f:  # a FIFO: no wait for a writer
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise OSError(0, "not a regular file", path)
        digest = hashlib.sha256()
        while chunk := f.read(HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest(), info.st_size, info.st_mtime

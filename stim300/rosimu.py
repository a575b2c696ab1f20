"""The STIM300's samples as ROS 2 sensor_msgs/Imu in CDR, a batch in one numpy step, with no ROS
installation: what calibd publishes on DDS and what `stim300 record -o OUT.mcap` and `calibd
apply -o OUT.mcap` write. A driver's part: a ROS 2 tool reads the sensor through it.

A ROS 2 message is plain (final) XCDR1, little endian: a 4-byte encapsulation header, then the
fields in order, each aligned to its size counted from after the header (doubles to 8). At 2000
Hz the Imu encoding is the cost that matters, so its layout is worked out once per frame_id and
a batch is written as rows of one numpy structured array.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from .errors import FormatError

IMU = "sensor_msgs/msg/Imu"
CDR_LE = b"\x00\x01\x00\x00"  # encapsulation header: plain CDR (XCDR1), little endian, no options
NS_PER_S = 1_000_000_000
MAX_FRAME_ID = 255  # characters of a frame_id
_FRAME_ID = re.compile(r"[!-~]+")  # printable ASCII, no space
ABSENT = np.array([-1.0, *[0.0] * 8])  # a covariance whose first element is -1: the message has no such vector


def check_frame_id(frame_id: str) -> str:
    """The frame_id of every message's header: printable ASCII without spaces, 1 to MAX_FRAME_ID
    characters (a tf frame name); FormatError otherwise."""
    if not (isinstance(frame_id, str) and _FRAME_ID.fullmatch(frame_id) and len(frame_id) <= MAX_FRAME_ID):
        raise FormatError(f"frame_id {frame_id!r}: expected 1 to {MAX_FRAME_ID} printable ASCII characters "
                          "without spaces")
    return frame_id


def stamp(stamp_ns: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
    """Nanoseconds since the epoch -> builtin_interfaces/Time's (sec, nanosec); FormatError for a time
    before the epoch or past int32 seconds (2038)."""
    ns = np.asarray(stamp_ns, dtype=np.int64)
    sec, nanosec = np.divmod(ns, NS_PER_S)
    if ns.size and (sec.min() < 0 or sec.max() > np.iinfo(np.int32).max):
        raise FormatError(f"time stamp {int(ns.min())} ns .. {int(ns.max())} ns: outside 1970 .. 2038 "
                          "(builtin_interfaces/Time holds int32 seconds)")
    return sec, nanosec


# sensor_msgs/Imu's doubles, in order: the columns of ImuEncoder's "doubles" field
_ORIENTATION, _ORIENTATION_COV = slice(0, 4), slice(4, 13)
_GYRO, _GYRO_COV = slice(13, 16), slice(16, 25)
_ACC, _ACC_COV = slice(25, 28), slice(28, 37)
_DOUBLES = 37


class ImuEncoder:
    """sensor_msgs/Imu samples of one frame_id -> their CDR, a batch in one numpy step.

    After the header (stamp, frame_id) every field is a double, so a sample is a fixed row:
    encapsulation, sec, nanosec, the string's length (with its NUL), its bytes, zero padding to
    the next multiple of 8 counted from after the encapsulation, then the 37 doubles. The
    orientation is the identity (0, 0, 0, 1) with covariance[0] = -1: the STIM300 gives none,
    which is how sensor_msgs/Imu says so."""

    def __init__(self, frame_id: str):
        name = check_frame_id(frame_id).encode("ascii") + b"\0"
        doubles_at = 4 + _align8(12 + len(name))  # 4: the encapsulation; 12: sec, nanosec, length
        self.dtype = np.dtype({
            "names": ["encapsulation", "sec", "nanosec", "frame_id_length", "frame_id", "doubles"],
            "formats": ["S4", "<i4", "<u4", "<u4", f"S{len(name)}", ("<f8", (_DOUBLES,))],
            "offsets": [0, 4, 8, 12, 16, doubles_at],
            "itemsize": doubles_at + 8 * _DOUBLES})
        self._template = np.zeros(1, self.dtype)  # padding stays zero
        self._template["encapsulation"] = CDR_LE
        self._template["frame_id_length"] = len(name)
        self._template["frame_id"] = name
        doubles = self._template["doubles"]
        doubles[0, _ORIENTATION] = (0.0, 0.0, 0.0, 1.0)
        doubles[0, _ORIENTATION_COV.start] = -1.0
        self._rows = self._template.copy()  # the template's rows, reused batch after batch (grown as needed)

    def encode(self, stamp_ns: np.ndarray, gyro_rad_s: np.ndarray, acc_m_s2: np.ndarray,
               gyro_cov: Sequence[float], acc_cov: Sequence[float]) -> list[bytes]:
        """One CDR sample per row: stamps (ns since the epoch, N), rates (rad/s, N x 3),
        accelerations (m/s^2, N x 3), and the covariances of both (9 each, row-major, the same
        for the batch)."""
        if len(stamp_ns) > len(self._rows):
            self._rows = np.repeat(self._template, len(stamp_ns))
        rows = self._rows[:len(stamp_ns)]  # what the template sets stays; the rest is written anew
        rows["sec"], rows["nanosec"] = stamp(stamp_ns)
        doubles = rows["doubles"]
        doubles[:, _GYRO] = gyro_rad_s
        doubles[:, _GYRO_COV] = _covariance(gyro_cov, "gyro")
        doubles[:, _ACC] = acc_m_s2
        doubles[:, _ACC_COV] = _covariance(acc_cov, "accelerometer")
        data, size = rows.tobytes(), self.dtype.itemsize
        return [data[start:start + size] for start in range(0, len(data), size)]


def _align8(offset: int) -> int:
    return -(-offset // 8) * 8


def _covariance(values: Sequence[float], what: str) -> np.ndarray:
    """A 3 x 3 covariance as sensor_msgs/Imu holds it: 9 numbers, row-major."""
    cov = np.asarray(values, dtype=np.float64)
    if cov.shape != (9,):
        raise FormatError(f"{what} covariance: expected 9 numbers (3 x 3, row-major), got shape {cov.shape}")
    return cov

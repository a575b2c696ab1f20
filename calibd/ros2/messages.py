"""What calibd's ROS 2 topics are, without DDS: their names, the types' names, the checks of what
the configuration gives, and sensor_msgs/Imu's CDR for a batch of samples in one numpy step.

A ROS 2 node sees a DDS topic "rt/NAME" of type "PACKAGE::msg::dds_::TYPE_" whose samples are
plain (final) XCDR1, little endian: a 4-byte encapsulation header, then the fields in order,
each aligned to its size counted from after the header (doubles to 8). At 2000 Hz on two topics
the Imu encoding is the cost that matters, so its layout is worked out once per frame_id and a
batch is written as rows of one numpy structured array.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Mapping, Sequence

import numpy as np

from ..errors import CalibdError

NEEDS_EXTRA = "ROS 2 publishing needs the ros2 extra: pip install 'stim300-calib[ros2]'"
DDS_PREFIX = "rt/"  # ROS 2's prefix of a topic's DDS name (rmw: "ros topic")
MAX_TOPIC_NAME = 247  # characters of a fully qualified ROS 2 topic name (rmw: 255 less 8 for prefixes)
MAX_FRAME_ID = 255  # characters of a frame_id
MAX_DOMAIN_ID = 232  # the highest DDS domain whose ports fit in 16 bits (ROS_DOMAIN_ID on Linux)
CDR_LE = b"\x00\x01\x00\x00"  # encapsulation header: plain CDR (XCDR1), little endian, no options
NS_PER_S = 1_000_000_000

# ROS 2 type -> its DDS type name (rosidl: PACKAGE::msg::dds_::TYPE_)
IMU = "sensor_msgs/msg/Imu"
STRING = "std_msgs/msg/String"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(?:/[A-Za-z_][A-Za-z0-9_]*)*")
_FRAME_ID = re.compile(r"[!-~]+")  # printable ASCII, no space


class Ros2Error(CalibdError):
    """A ROS 2 topic, frame or domain that cannot be published, or a missing package; one line."""


def dds_type_name(ros_type: str) -> str:
    """"sensor_msgs/msg/Imu" -> "sensor_msgs::msg::dds_::Imu_", the name rmw gives the DDS type."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def dds_topic(name: str, key: str) -> str:
    """A ROS 2 topic name -> its DDS topic ("imu/data" and "/imu/data" -> "rt/imu/data").
    Names are taken absolute (there is no node namespace to resolve them in): tokens of letters,
    digits and underscores not starting with a digit, separated by single slashes, no trailing
    slash, no "__" (ROS 2 reserves it), at most 247 characters with the leading slash (rmw's
    bound). Ros2Error naming `key` otherwise."""
    why = None
    if not _NAME.fullmatch(name):
        why = "expected tokens of A-Z, a-z, 0-9 and _, not starting with a digit, joined by single '/'"
    elif "__" in name:
        why = "'__' is reserved"
    absolute = "/" + name.removeprefix("/")
    if why is None and len(absolute) > MAX_TOPIC_NAME:
        why = f"longer than {MAX_TOPIC_NAME} characters with its leading '/'"
    if why:
        raise Ros2Error(f"ros2 topic {key}: {name!r} is not a ROS 2 topic name ({why})")
    return DDS_PREFIX + absolute[1:]


def check_frame_id(frame_id: str) -> str:
    """The frame_id of every message's header: printable ASCII without spaces, 1 to MAX_FRAME_ID
    characters (a tf frame name); Ros2Error otherwise."""
    if not (isinstance(frame_id, str) and _FRAME_ID.fullmatch(frame_id) and len(frame_id) <= MAX_FRAME_ID):
        raise Ros2Error(f"ros2 frame_id {frame_id!r}: expected 1 to {MAX_FRAME_ID} printable ASCII characters "
                        "without spaces")
    return frame_id


def stamp(stamp_ns: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
    """Nanoseconds since the epoch -> builtin_interfaces/Time's (sec, nanosec); Ros2Error for a time
    before the epoch or past int32 seconds (2038)."""
    ns = np.asarray(stamp_ns, dtype=np.int64)
    sec, nanosec = np.divmod(ns, NS_PER_S)
    if ns.size and (sec.min() < 0 or sec.max() > np.iinfo(np.int32).max):
        raise Ros2Error(f"ros2 time stamp {int(ns.min())} ns .. {int(ns.max())} ns: outside 1970 .. 2038 "
                        "(builtin_interfaces/Time holds int32 seconds)")
    return sec, nanosec


class Level(IntEnum):
    """diagnostic_msgs/DiagnosticStatus's levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class Status:
    """One diagnostic_msgs/DiagnosticStatus: what `name` reports, at `level`, in `message`;
    `values` its key-value pairs (text, units in the keys)."""

    level: Level
    name: str
    message: str
    hardware_id: str = ""
    values: Mapping[str, str] = field(default_factory=dict)


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
        raise Ros2Error(f"ros2 {what} covariance: expected 9 numbers (3 x 3, row-major), got shape {cov.shape}")
    return cov

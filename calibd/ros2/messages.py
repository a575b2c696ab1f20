"""What calibd's ROS 2 topics are, without DDS: their names, the types' names and the checks of
what the configuration gives. A ROS 2 node sees a DDS topic "rt/NAME" of type
"PACKAGE::msg::dds_::TYPE_" whose samples are plain (final) XCDR1; sensor_msgs/Imu's CDR of a
batch, its frame_id rule and its stamps are the driver's (`stim300.rosimu`), which this module
takes as they are.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Mapping


from ..errors import CalibdError

NEEDS_EXTRA = "ROS 2 publishing needs the ros2 extra: pip install 'stim300-calib[ros2]'"
DDS_PREFIX = "rt/"  # ROS 2's prefix of a topic's DDS name (rmw: "ros topic")
MAX_TOPIC_NAME = 247  # characters of a fully qualified ROS 2 topic name (rmw: 255 less 8 for prefixes)
MAX_DOMAIN_ID = 232  # the highest DDS domain whose ports fit in 16 bits (ROS_DOMAIN_ID on Linux)

# ROS 2 type -> its DDS type name (rosidl: PACKAGE::msg::dds_::TYPE_)
STRING = "std_msgs/msg/String"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(?:/[A-Za-z_][A-Za-z0-9_]*)*")


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

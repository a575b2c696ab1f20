"""A ROS 2 subscriber of its own for the tests: the messages as rosidl declares them, with ROS
2's type names and QoS, declared here and not taken from calibd, so a test of what calibd
publishes compares it with what a ROS 2 node would read. DDS on loopback only (LOOPBACK, for
CYCLONEDDS_URI: unicast discovery on 127.0.0.1)."""

import time
from dataclasses import dataclass

LOOPBACK = ("<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
            "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
            "<Peers><Peer address='127.0.0.1'/></Peers></Discovery></Domain></CycloneDDS>")


def ros2_types():
    """The subscriber's types: the ROS 2 messages as rosidl declares them in IDL."""
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import types as t

    @dataclass
    class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: t.int32
        nanosec: t.uint32

    @dataclass
    class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time
        frame_id: str

    @dataclass
    class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
        x: t.float64
        y: t.float64
        z: t.float64
        w: t.float64

    @dataclass
    class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
        x: t.float64
        y: t.float64
        z: t.float64

    @dataclass
    class Imu(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
        header: Header
        orientation: Quaternion
        orientation_covariance: t.array[t.float64, 9]
        angular_velocity: Vector3
        angular_velocity_covariance: t.array[t.float64, 9]
        linear_acceleration: Vector3
        linear_acceleration_covariance: t.array[t.float64, 9]

    @dataclass
    class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
        data: str

    @dataclass
    class QuaternionStamped(IdlStruct, typename="geometry_msgs::msg::dds_::QuaternionStamped_"):
        header: Header
        quaternion: Quaternion

    @dataclass
    class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
        key: str
        value: str

    @dataclass
    class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
        level: t.byte  # ROS 2 "byte" is IDL octet
        name: str
        message: str
        hardware_id: str
        values: t.sequence[KeyValue]

    @dataclass
    class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
        header: Header
        status: t.sequence[DiagnosticStatus]

    return {"imu_raw": Imu, "imu": Imu, "calibration": String, "alignment": QuaternionStamped,
            "diagnostics": DiagnosticArray}


def ros2_qos(key: str):
    """A ROS 2 subscriber's QoS: the sensor-data profile for the Imu topics, latched for the
    calibration and alignment, reliable for diagnostics."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration
    reliable = Policy.Reliability.Reliable(duration(milliseconds=100))
    return {"imu_raw": Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5)),
            "calibration": Qos(reliable, Policy.Durability.TransientLocal, Policy.History.KeepLast(1)),
            "diagnostics": Qos(reliable, Policy.Durability.Volatile, Policy.History.KeepLast(10)),
            }[{"imu": "imu_raw", "alignment": "calibration"}.get(key, key)]


def subscribe(participant, name: str, key: str, depth: int = 0):
    """A reader of the ROS 2 topic `name` carrying what calibd publishes as `key` (its type and
    QoS: "imu_raw", "imu", "calibration", "alignment", "diagnostics"); `depth` in place of the
    QoS's history."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    qos = ros2_qos(key)
    if depth:
        qos = Qos(*[p for p in qos if not isinstance(p, Policy.History.KeepLast)], Policy.History.KeepLast(depth))
    return DataReader(participant, Topic(participant, "rt/" + name.lstrip("/"), ros2_types()[key]), qos)


def valid(samples: list) -> list:
    """The samples that carry data: a writer leaving the domain is told to its readers as an
    invalid sample (no data, only its state)."""
    from cyclonedds.internal import InvalidSample
    return [s for s in samples if not isinstance(s, InvalidSample)]


def take(reader, count: int, timeout_s: float = 2.0) -> list:
    samples, deadline = [], time.monotonic() + timeout_s
    while len(samples) < count and time.monotonic() < deadline:
        samples += reader.take(N=count - len(samples))
        time.sleep(0.005)
    return samples

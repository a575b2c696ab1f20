"""calibd's ROS 2 topics on DDS (Eclipse Cyclone DDS, as ROS 2's default rmw): one participant,
one writer per topic, with the QoS, type names and type hashes a ROS 2 node (Humble to Kilted)
matches, so it subscribes without a bridge.

The message types are declared here as ROS 2 defines them (rosidl's IDL: final structs), so the
writers announce the same types a ROS 2 node's readers ask for. Iron and later read each writer's
type hash from its user data ("typehash=RIHS01_<hex>;", as rmw_cyclonedds writes it); rosbags
computes it from the message definitions. Imu samples are encoded in batches by
`stim300.rosimu.ImuEncoder` and written through `DataWriter.write` as `_Encoded` samples, whose
`serialize` returns those bytes; the low-rate messages are written as the structs below. An Imu
writer batches (`_BatchedWriter`): a batch's samples leave in a few datagrams when it is flushed,
not one sendmsg each.
(No `from __future__ import annotations` here: cyclonedds reads the fields' types from the
annotations as objects.)
"""

import ctypes
import time
from dataclasses import dataclass
from functools import cache
from typing import Sequence

import numpy as np

from stim300.errors import FormatError
from stim300.rosimu import IMU, ImuEncoder, stamp

from .messages import (DIAGNOSTIC_ARRAY, MAX_DOMAIN_ID, NEEDS_EXTRA, QUATERNION_STAMPED, STRING, Ros2Error, Status,
                       dds_topic, dds_type_name)

try:
    from cyclonedds.core import DDSException, Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import types as idl
    from cyclonedds.internal import c_call, dds_c_t
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
    from rosbags.typesys import Stores, get_typestore
except ImportError:
    raise Ros2Error(NEEDS_EXTRA) from None



# ---- the message types, named and laid out as rosidl's IDL declares them

@dataclass
class Time(IdlStruct, typename=dds_type_name("builtin_interfaces/msg/Time")):
    sec: idl.int32
    nanosec: idl.uint32


@dataclass
class Header(IdlStruct, typename=dds_type_name("std_msgs/msg/Header")):
    stamp: Time
    frame_id: str


@dataclass
class Quaternion(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Quaternion")):
    x: idl.float64
    y: idl.float64
    z: idl.float64
    w: idl.float64


@dataclass
class Vector3(IdlStruct, typename=dds_type_name("geometry_msgs/msg/Vector3")):
    x: idl.float64
    y: idl.float64
    z: idl.float64


@dataclass
class Imu(IdlStruct, typename=dds_type_name(IMU)):
    header: Header
    orientation: Quaternion
    orientation_covariance: idl.array[idl.float64, 9]
    angular_velocity: Vector3
    angular_velocity_covariance: idl.array[idl.float64, 9]
    linear_acceleration: Vector3
    linear_acceleration_covariance: idl.array[idl.float64, 9]


@dataclass
class String(IdlStruct, typename=dds_type_name(STRING)):
    data: str


@dataclass
class QuaternionStamped(IdlStruct, typename=dds_type_name(QUATERNION_STAMPED)):
    header: Header
    quaternion: Quaternion


@dataclass
class KeyValue(IdlStruct, typename=dds_type_name("diagnostic_msgs/msg/KeyValue")):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename=dds_type_name("diagnostic_msgs/msg/DiagnosticStatus")):
    level: idl.byte
    name: str
    message: str
    hardware_id: str
    values: idl.sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename=dds_type_name(DIAGNOSTIC_ARRAY)):
    header: Header
    status: idl.sequence[DiagnosticStatus]


class _Encoded(Imu):
    """An Imu sample already in CDR. `DataWriter.write` takes a sample of the topic's type and
    writes what its `serialize` returns: a subclass is that type, and returning the prepared bytes
    is the one public way to write them without decoding them into objects first."""

    def __init__(self, cdr: bytes):
        self.cdr = cdr

    def serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
        return self.cdr


class _BatchedWriter(DataWriter):
    """A DataWriter whose writes wait in Cyclone DDS's write batch until `flush` (or until a
    datagram is full): at 2000 Hz a sample per sendmsg is most of what a write costs. The
    writer-batching QoS and the flush are Cyclone's C API, which the Python binding does not
    wrap: they are bound here the way the binding binds its own calls (`c_call`)."""

    def _create_writer(self, publisher, topic, qos, listener):
        self._qset_writer_batching(qos, True)  # qos: the C copy of the writer's Qos, made for this call
        return DataWriter._create_writer(self, publisher, topic, qos, listener)

    def flush(self) -> None:
        """Send what the batch holds."""
        ret = self._flush(self._ref)
        if ret < 0:
            raise DDSException(ret, f"Occurred while flushing {self!r}")

    @c_call("dds_qset_writer_batching")
    def _qset_writer_batching(self, qos: dds_c_t.qos_p, batch_updates: ctypes.c_bool) -> None:
        pass

    @c_call("dds_write_flush")
    def _flush(self, writer: dds_c_t.entity) -> dds_c_t.returnv:
        pass


# ---- the QoS a ROS 2 reader matches (rmw_qos_profile_sensor_data; a latched topic; diagnostics)

_XCDR1 = Policy.DataRepresentation(use_cdrv0_representation=True)
_RELIABLE = Policy.Reliability.Reliable(duration(milliseconds=100))
SENSOR_QOS = (Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5))
LATCHED_QOS = (_RELIABLE, Policy.Durability.TransientLocal, Policy.History.KeepLast(1))
DIAGNOSTICS_QOS = (_RELIABLE, Policy.Durability.Volatile, Policy.History.KeepLast(10))

MATCH_CHECK_S = 0.5  # how long an Imu writer's count of matched readers is taken as known
# Publisher's topic keys -> (ROS 2 type, its DDS type, QoS)
TOPICS = {
    "imu_raw": (IMU, Imu, SENSOR_QOS),
    "imu": (IMU, Imu, SENSOR_QOS),
    "calibration": (STRING, String, LATCHED_QOS),
    "alignment": (QUATERNION_STAMPED, QuaternionStamped, LATCHED_QOS),
    "diagnostics": (DIAGNOSTIC_ARRAY, DiagnosticArray, DIAGNOSTICS_QOS),
}


@cache
def type_hash(ros_type: str) -> str:
    """The RIHS01 hash of a ROS 2 type ("RIHS01_<64 hex>"), from its definition as Jazzy ships it
    (the hash is of the definition: the same in Iron, Jazzy and Kilted for these types)."""
    return get_typestore(Stores.ROS2_JAZZY).hash_rihs01(ros_type)


def user_data(ros_type: str) -> bytes:
    """A writer's user data as rmw_cyclonedds sets it: "typehash=RIHS01_<hex>;"."""
    return f"typehash={type_hash(ros_type)};".encode("ascii")


def header(stamp_ns: int, frame_id: str) -> Header:
    sec, nanosec = stamp(stamp_ns)
    return Header(Time(int(sec), int(nanosec)), frame_id)


def alignment_message(stamp_ns: int, frame_id: str, q_xyzw: Sequence[float]) -> QuaternionStamped:
    """A rotation (x, y, z, w) at a time (ns since the epoch) as geometry_msgs/QuaternionStamped."""
    x, y, z, w = (float(v) for v in q_xyzw)
    return QuaternionStamped(header(stamp_ns, frame_id), Quaternion(x, y, z, w))


def diagnostics_message(stamp_ns: int, frame_id: str, statuses: Sequence[Status]) -> DiagnosticArray:
    """Statuses at a time (ns since the epoch) as diagnostic_msgs/DiagnosticArray."""
    return DiagnosticArray(header(stamp_ns, frame_id), [
        DiagnosticStatus(int(s.level), s.name, s.message, s.hardware_id, [KeyValue(k, v) for k, v in s.values.items()])
        for s in statuses])


class Publisher:
    """calibd's ROS 2 topics in one DDS domain. `topics` maps the keys of TOPICS to ROS 2 topic
    names; a key left out is not published (its method does nothing, as every method does after
    `close`). Every message's header carries `frame_id`. A write does not wait for readers: each
    writer keeps only its last samples (keep last), and a reliable one waits at most 100 ms for
    room. The Imu topics may be written from one thread while the others are from another."""

    IMU_KEYS = ("imu_raw", "imu")

    def __init__(self, domain_id: int, topics: dict[str, str], frame_id: str):
        unknown = sorted(set(topics) - set(TOPICS))
        if unknown:
            raise Ros2Error(f"ros2 topics: unknown key {unknown[0]!r} (known: {', '.join(TOPICS)})")
        names = {key: dds_topic(name, key) for key, name in topics.items()}
        try:
            self._imu = ImuEncoder(frame_id)
        except FormatError as exc:
            raise Ros2Error(f"ros2 {exc}") from None
        self.frame_id = frame_id
        if type(domain_id) is not int or not 0 <= domain_id <= MAX_DOMAIN_ID:
            raise Ros2Error(f"ros2 domain_id {domain_id!r}: expected an integer 0 to {MAX_DOMAIN_ID}")
        try:
            self._participant = DomainParticipant(domain_id)
            self._writers = {key: self._writer(name, *TOPICS[key], batched=key in self.IMU_KEYS)
                             for key, name in names.items()}
        except DDSException as error:
            code, words = DDSException.error_message_mapping.get(error.code, (str(error.code), "error"))
            raise Ros2Error(f"ros2 domain_id {domain_id}: Cyclone DDS cannot publish there ({words.lower()}, {code}): "
                            "see its own message above, and CYCLONEDDS_URI if set") from None
        self._matched: dict[str, tuple[float, bool]] = {}  # Imu key -> (when checked, monotonic s; a reader matched)

    def _writer(self, name: str, ros_type: str, data_type: type, qos: tuple, batched: bool) -> DataWriter:
        topic = Topic(self._participant, name, data_type)
        return (_BatchedWriter if batched else DataWriter)(
            self._participant, topic, Qos(*qos, _XCDR1, Policy.Userdata(user_data(ros_type))))

    def imu(self, key: str, stamp_ns: np.ndarray, gyro_rad_s: np.ndarray, acc_m_s2: np.ndarray,
            gyro_cov: Sequence[float], acc_cov: Sequence[float]) -> None:
        """A batch of sensor_msgs/Imu on "imu_raw" or "imu": stamps (ns since the epoch, N),
        rates (rad/s, N x 3), accelerations (m/s^2, N x 3), covariances (9 each, row-major).
        Neither encoded nor written while no reader is matched, as last checked within
        MATCH_CHECK_S (best effort, volatile: a reader that comes later gets the samples from
        then on, as it would anyway). The batch is sent when written."""
        writer = self._writers.get(key)
        if writer is not None and self._reader_matched(key, writer):  # none: nothing to do
            for cdr in self._imu.encode(stamp_ns, gyro_rad_s, acc_m_s2, gyro_cov, acc_cov):
                writer.write(_Encoded(cdr))
            writer.flush()

    def _reader_matched(self, key: str, writer: DataWriter) -> bool:
        now = time.monotonic()
        checked, matched = self._matched.get(key, (-MATCH_CHECK_S, False))
        if now - checked >= MATCH_CHECK_S:
            matched = writer.get_publication_matched_status().current_count > 0
            self._matched[key] = (now, matched)
        return matched

    def calibration(self, document_json: str) -> None:
        """The latest calibration result (its JSON document) as std_msgs/String, kept for late
        subscribers."""
        self._write("calibration", String(document_json))

    def alignment(self, stamp_ns: int, q_xyzw: Sequence[float]) -> None:
        """The sensor's alignment as geometry_msgs/QuaternionStamped, kept for late subscribers."""
        self._write("alignment", alignment_message(stamp_ns, self.frame_id, q_xyzw))

    def diagnostics(self, stamp_ns: int, statuses: Sequence[Status]) -> None:
        """diagnostic_msgs/DiagnosticArray of `statuses`."""
        self._write("diagnostics", diagnostics_message(stamp_ns, self.frame_id, statuses))

    def _write(self, key: str, message: IdlStruct) -> None:
        if key in self._writers:
            self._writers[key].write(message)

    def close(self) -> None:
        """Leaves the domain: the writers, their topics and the participant are deleted (each DDS
        entity is deleted when its last reference goes)."""
        self._writers.clear()
        self._participant = None

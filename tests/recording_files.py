"""Recordings of sensor_msgs/Imu for the tests: Imu messages serialised by rosbags (ROS 1 or CDR)
and written as a ROS 1 bag, a rosbag2 directory (SQLite3 or MCAP storage), a plain MCAP file of
ROS 2 messages (the Foxglove SDK's writer) or of ROS 1 messages (the mcap package's writer); the
capture they are made from (a simulated unit without inclinometers, 125 Hz) and its site. The
fixtures built from them are in conftest.py."""

import json
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Bag1Writer
from rosbags.rosbag2 import StoragePlugin, Writer as Bag2Writer
from rosbags.typesys import Stores, get_typestore

from calibd.cli import main as calibd_main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "gyro_acc_125hz.bin"  # 0x91: gyros and accelerometers, no temperatures, 125 Hz
TOPIC = "/imu/data"
FRAME_ID = "stim300_link"
IMU = "sensor_msgs/msg/Imu"
EPOCH_NS = 1_700_000_000_123_456_789  # the first sample's stamp
ROS1 = get_typestore(Stores.ROS1_NOETIC)  # its Header has seq, as a ROS 1 bag's does
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
FORMATS = ("bag", "sqlite3", "mcap", "plain_mcap", "ros1_mcap")


def imu_message(store, stamp_ns: int, gyro_rad_s, acc_m_s2, frame_id: str = FRAME_ID, seq: int = 0,
                acc_covariance: float = 0.0):
    t = store.types
    stamp = t["builtin_interfaces/msg/Time"](stamp_ns // 10**9, stamp_ns % 10**9)
    header = t["std_msgs/msg/Header"](*([seq] if store is ROS1 else []), stamp, frame_id)
    vector = t["geometry_msgs/msg/Vector3"]
    return t[IMU](header, t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0), np.full(9, -1.0),
                  vector(*map(float, gyro_rad_s)), np.zeros(9), vector(*map(float, acc_m_s2)),
                  np.full(9, acc_covariance))


def serialised(kind: str, stamps_ns, gyro_rad_s, acc_m_s2) -> list[bytes]:
    """Each sample an Imu message serialised by rosbags (ROS 1 for a bag, CDR otherwise)."""
    if kind == "bag":
        return [bytes(ROS1.serialize_ros1(imu_message(ROS1, int(t), g, a, seq=k), IMU))
                for k, (t, g, a) in enumerate(zip(stamps_ns, gyro_rad_s, acc_m_s2))]
    return [bytes(ROS2.serialize_cdr(imu_message(ROS2, int(t), g, a), IMU))
            for t, g, a in zip(stamps_ns, gyro_rad_s, acc_m_s2)]


def write_recording(path: Path, kind: str, messages: list[bytes], received_ns, topics: dict | None = None,
                    profile: str = "ros2") -> Path:
    """`messages` on TOPIC (or `topics`: name -> (type, messages)), each recorded at its
    `received_ns` (the recorder's time, not the header stamp), as a ROS 1 bag (kind "bag"), a
    rosbag2 directory ("sqlite3", "mcap") or a plain MCAP file ("plain_mcap", with `profile` in its
    header: ros2 bags say "ros2")."""
    topics = {TOPIC: (IMU, messages)} if topics is None else topics
    if kind == "bag":
        with Bag1Writer(path) as writer:
            for name, (msgtype, data) in topics.items():
                connection = writer.add_connection(name, msgtype, typestore=ROS1)
                for when, raw in zip(received_ns, data):
                    writer.write(connection, int(when), raw)
    elif kind == "ros1_mcap":  # ROS 1 messages in MCAP, as `mcap convert` makes of a bag
        from mcap.writer import Writer as McapWriter

        with open(path, "wb") as f:
            writer = McapWriter(f)
            writer.start(profile="ros1", library="test")
            for name, (msgtype, data) in topics.items():
                ros1_name = msgtype.replace("/msg/", "/")
                schema = writer.register_schema(ros1_name, "ros1msg",
                                                ROS1.generate_msgdef(msgtype, ros_version=1)[0].encode())
                channel = writer.register_channel(name, "ros1", schema)
                for when, raw in zip(received_ns, data):
                    writer.add_message(channel, int(when), raw, int(when))
            writer.finish()
    elif kind == "plain_mcap":
        import foxglove
        from foxglove.mcap import MCAPWriteOptions

        context = foxglove.Context()
        with foxglove.open_mcap(path, context=context, writer_options=MCAPWriteOptions(profile=profile)):
            for name, (msgtype, data) in topics.items():
                schema = foxglove.Schema(name=msgtype, encoding="ros2msg",
                                         data=ROS2.generate_msgdef(msgtype, ros_version=2)[0].encode())
                channel = foxglove.Channel(name, schema=schema, message_encoding="cdr", context=context)
                for when, raw in zip(received_ns, data):
                    channel.log(raw, log_time=int(when))
    else:
        plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
        with Bag2Writer(path, version=9, storage_plugin=plugin) as writer:
            for name, (msgtype, data) in topics.items():
                connection = writer.add_connection(name, msgtype, typestore=ROS2)
                for when, raw in zip(received_ns, data):
                    writer.write(connection, int(when), raw)
    return path


def recording_name(tmp: Path, kind: str, stem: str = "imu") -> Path:
    return tmp / {"bag": f"{stem}.bag", "plain_mcap": f"{stem}.mcap", "ros1_mcap": f"{stem}_ros1.mcap"}.get(
        kind, f"{stem}_{kind}")


def calibrate(path, site, out: Path) -> dict:
    code = calibd_main(["calibrate", str(path), "--latitude", str(site["latitude_deg"]), "--g0", str(site["g0"]),
                        "-o", str(out)])
    assert code == 0
    return json.loads(out.read_text())




def small_imu(kind: str, n: int = 300, stamps_ns=None):
    """n messages of a level unit at rest (SI), stamped at 125 Hz unless `stamps_ns` says otherwise."""
    stamps = EPOCH_NS + np.arange(n, dtype=np.int64) * 8_000_000 if stamps_ns is None else stamps_ns
    gyro, acc = np.zeros((n, 3)), np.tile([0.0, 0.0, 9.8], (n, 1))
    return serialised(kind, stamps, gyro, acc), stamps


def refusal(run_main, argv) -> str:
    code, out, err = run_main(calibd_main, argv)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, (code, out, err)
    return err



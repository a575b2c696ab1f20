"""calibd's ROS 2 topics on the wire: the CDR bytes equal rosbags' (Humble and Jazzy definitions),
a subscriber declared here on its own, with ROS 2's type names and QoS, receives what the
Publisher writes, discovery carries the RIHS01 type hashes rosbags computes, and bad names,
frames and domains are one-line errors.

DDS runs on loopback only (unicast discovery on 127.0.0.1), each test in its own random domain,
so concurrent runs never see each other's samples."""

import random
import subprocess
import sys
import time

import numpy as np
import pytest

from calibd.errors import CalibdError
from calibd.ros2.messages import Level, Ros2Error, Status, dds_topic
from stim300.errors import FormatError, Stim300Error
from stim300.rosimu import ImuEncoder, check_frame_id
from ros2_subscriber import LOOPBACK, ros2_qos, subscribe, take

TOPICS = {"imu_raw": "stim300/imu/data_raw", "imu": "/stim300/imu/data", "calibration": "stim300/calibration",
          "alignment": "stim300/alignment", "diagnostics": "/diagnostics"}
DOC = '{"schema": "calibd.result/4", "note": "größe µ"}'


@pytest.fixture
def domain(monkeypatch):
    """A random DDS domain on loopback only."""
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    return random.randint(1, 200)


def _subscribe(participant, key: str, depth: int = 0):
    return subscribe(participant, TOPICS[key], key, depth)


def _typestore(store: str):
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(getattr(Stores, store))


def _one_line_error(call, *args, says: str, error=Ros2Error) -> str:
    with pytest.raises(error) as caught:
        call(*args)
    message = str(caught.value)
    assert "\n" not in message and says in message, message
    assert isinstance(caught.value, CalibdError if error is Ros2Error else Stim300Error)
    return message


# ---- names

@pytest.mark.parametrize("name, dds", [("imu/data", "rt/imu/data"), ("/imu/data", "rt/imu/data"),
                                       ("_hidden/a1", "rt/_hidden/a1"), ("diagnostics", "rt/diagnostics")])
def test_a_ros_2_name_is_its_dds_topic_with_rt(name, dds):
    assert dds_topic(name, "imu") == dds
    assert dds_topic("a" * 246, "imu") == "rt/" + "a" * 246  # 247 with its leading "/"


@pytest.mark.parametrize("name", ["", "/", "imu/", "imu//data", "1imu", "imu/2nd", "imu data", "imu__data",
                                  "~/imu", "imu/{node}", "ïmu", "a" * 247])
def test_a_bad_topic_name_is_one_line_naming_its_key(name):
    message = _one_line_error(dds_topic, name, "imu_raw", says="ros2 topic imu_raw:")
    assert repr(name) in message


@pytest.mark.parametrize("frame_id", ["", "imu link", "imu\n", "imü", "x" * 256, None])
def test_a_bad_frame_id_is_one_line(frame_id):
    _one_line_error(check_frame_id, frame_id, says="frame_id", error=FormatError)


def test_a_time_before_1970_or_after_2038_is_one_line():
    encoder = ImuEncoder("imu")
    for ns in (-1, (2**31) * 10**9):
        _one_line_error(encoder.encode, np.array([ns]), np.zeros((1, 3)), np.zeros((1, 3)), [0.0] * 9, [0.0] * 9,
                        says="time stamp", error=FormatError)
    _one_line_error(encoder.encode, np.array([0]), np.zeros((1, 3)), np.zeros((1, 3)), [0.0] * 3, [0.0] * 9,
                    says="gyro covariance", error=FormatError)


def test_import_loads_no_dds_and_without_the_extra_publisher_says_how_to_install():
    code = ("import sys\n"
            "import calibd, calibd.ros2\n"
            "assert not {'cyclonedds', 'rosbags'} & set(sys.modules), sorted(sys.modules)\n"
            "sys.modules['cyclonedds'] = None\n"
            "try:\n"
            "    calibd.ros2.Publisher\n"
            "except calibd.ros2.Ros2Error as e:\n"
            "    print(e)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "ROS 2 publishing needs the ros2 extra: pip install 'stim300-calib[ros2]'\n"


# ---- the bytes, against rosbags' CDR of the same messages

def _header(T, stamp_ns: int, frame_id: str):
    time_ = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=time_, frame_id=frame_id)


def _cdr(store, message, ros_type: str) -> bytes:
    return bytes(store.serialize_cdr(message, ros_type))


@pytest.mark.parametrize("store", ["ROS2_HUMBLE", "ROS2_JAZZY"])
def test_imu_batches_are_rosbags_cdr_for_every_frame_id_length(store):
    typestore = _typestore(store)
    T = typestore.types
    stamps = np.array([0, 1, 1_700_000_000_123_456_789, (2**31 - 1) * 10**9 + 999_999_999], dtype=np.int64)
    special = [np.nan, np.inf, -np.inf, -0.0, 5e-324, 1.7976931348623157e308]
    gyro = np.array([[0.1, -0.2, 0.3], special[:3], special[3:], [1e-9, -1e9, 2.5]])
    acc = np.array([[0.0, 0.0, 9.80665], special[3:], special[:3], [-1.0, 2.0, -3.0]])
    gyro_cov, acc_cov = np.arange(9) * 1e-7 - 2e-7, np.linspace(-1, 1, 9)
    for length in range(1, 10):  # every remainder of the string's end modulo 8, and a whole one more
        frame_id = "frame_imu"[:length]
        encoded = ImuEncoder(frame_id).encode(stamps, gyro, acc, gyro_cov, acc_cov)
        assert len(encoded) == len(stamps)
        for i, cdr in enumerate(encoded):
            expected = T["sensor_msgs/msg/Imu"](
                header=_header(T, int(stamps[i]), frame_id),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.array([-1.0] + [0.0] * 8),
                angular_velocity=T["geometry_msgs/msg/Vector3"](*gyro[i]), angular_velocity_covariance=gyro_cov,
                linear_acceleration=T["geometry_msgs/msg/Vector3"](*acc[i]),
                linear_acceleration_covariance=acc_cov)
            assert cdr == _cdr(typestore, expected, "sensor_msgs/msg/Imu"), (frame_id, i)


@pytest.mark.parametrize("store", ["ROS2_HUMBLE", "ROS2_JAZZY"])
def test_every_other_message_is_rosbags_cdr(store):
    from calibd.ros2 import wire
    typestore = _typestore(store)
    T = typestore.types
    stamp_ns = 1_700_000_000_000_000_001
    assert wire.String(DOC).serialize() == _cdr(typestore, T["std_msgs/msg/String"](data=DOC), "std_msgs/msg/String")
    q = (0.1, -0.2, 0.3, np.sqrt(1 - 0.14))
    expected = T["geometry_msgs/msg/QuaternionStamped"](
        header=_header(T, stamp_ns, "imu_link"), quaternion=T["geometry_msgs/msg/Quaternion"](*q))
    assert (wire.alignment_message(stamp_ns, "imu_link", q).serialize()
            == _cdr(typestore, expected, "geometry_msgs/msg/QuaternionStamped"))
    statuses = [Status(Level.OK, "calibd: result", "solved", "STIM300 N25", {"roll_deg": "0.01", "age_s": "3"}),
                Status(Level.STALE, "calibd: stream", "", "", {}), Status(Level.ERROR, "é", "x" * 13, "h")]
    for chosen in ([], statuses[:1], statuses):
        expected = T["diagnostic_msgs/msg/DiagnosticArray"](header=_header(T, stamp_ns, "imu"), status=[
            T["diagnostic_msgs/msg/DiagnosticStatus"](
                level=int(s.level), name=s.name, message=s.message, hardware_id=s.hardware_id,
                values=[T["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in s.values.items()])
            for s in chosen])
        assert (wire.diagnostics_message(stamp_ns, "imu", chosen).serialize()
                == _cdr(typestore, expected, "diagnostic_msgs/msg/DiagnosticArray")), len(chosen)


def test_a_ros_2_subscriber_receives_what_the_publisher_writes(domain):
    from cyclonedds.domain import DomainParticipant
    from calibd.ros2 import Publisher
    participant = DomainParticipant(domain)
    readers = {key: _subscribe(participant, key, depth=100) for key in TOPICS}
    publisher = Publisher(domain, TOPICS, "stim300_link")
    stamps = 1_750_000_000_000_000_000 + np.arange(40) * 500_000
    gyro = np.random.default_rng(1).normal(size=(40, 3))
    acc = np.random.default_rng(2).normal(size=(40, 3))
    gyro_cov, acc_cov = np.diag([1e-8, 2e-8, 3e-8]).ravel(), np.diag([1e-4, 2e-4, 3e-4]).ravel()
    publisher.imu("imu_raw", stamps, gyro, acc, gyro_cov, acc_cov)
    publisher.imu("imu", stamps[:3], -gyro[:3], -acc[:3], gyro_cov, acc_cov)
    publisher.calibration(DOC)
    publisher.alignment(stamps[0], (0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)))
    publisher.diagnostics(stamps[-1], [Status(Level.WARN, "calibd: state", "warming up", "STIM300 N1",
                                              {"remaining_s": "120"})])

    raw = take(readers["imu_raw"], 40)
    assert len(raw) == 40
    for i, sample in enumerate(raw):
        assert (sample.header.stamp.sec, sample.header.stamp.nanosec) == divmod(int(stamps[i]), 10**9)
        assert sample.header.frame_id == "stim300_link"
        o = sample.orientation
        assert (o.x, o.y, o.z, o.w) == (0.0, 0.0, 0.0, 1.0)
        assert list(sample.orientation_covariance) == [-1.0] + [0.0] * 8
        w, a = sample.angular_velocity, sample.linear_acceleration
        assert [w.x, w.y, w.z] == gyro[i].tolist() and [a.x, a.y, a.z] == acc[i].tolist()
        assert list(sample.angular_velocity_covariance) == gyro_cov.tolist()
        assert list(sample.linear_acceleration_covariance) == acc_cov.tolist()
    corrected = take(readers["imu"], 3)
    assert [s.angular_velocity.z for s in corrected] == (-gyro[:3, 2]).tolist()
    assert [s.data for s in take(readers["calibration"], 1)] == [DOC]
    [alignment] = take(readers["alignment"], 1)
    q = alignment.quaternion
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5))
    assert alignment.header.frame_id == "stim300_link"
    [diagnostics] = take(readers["diagnostics"], 1)
    [status] = diagnostics.status
    assert (status.level, status.name, status.message, status.hardware_id) == (1, "calibd: state", "warming up",
                                                                                "STIM300 N1")
    assert [(v.key, v.value) for v in status.values] == [("remaining_s", "120")]
    assert diagnostics.header.stamp.sec == int(stamps[-1]) // 10**9
    publisher.close()


def test_a_late_subscriber_gets_the_latest_calibration_only(domain):
    from cyclonedds.domain import DomainParticipant
    from calibd.ros2 import Publisher
    publisher = Publisher(domain, {"calibration": TOPICS["calibration"]}, "imu")
    publisher.calibration('{"n": 1}')
    publisher.calibration('{"n": 2}')
    late = _subscribe(DomainParticipant(domain), "calibration")
    assert [s.data for s in take(late, 2, timeout_s=0.3)] == ['{"n": 2}']
    publisher.close()


def test_discovery_carries_each_writers_type_and_rihs01_hash(domain):
    """What a ROS 2 node learns of each writer, read back from the builtin DCPSPublication topic."""
    from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
    from cyclonedds.core import Policy
    from cyclonedds.domain import DomainParticipant
    from calibd.ros2 import Publisher
    ros_types = {"imu_raw": "sensor_msgs/msg/Imu", "imu": "sensor_msgs/msg/Imu",
                 "calibration": "std_msgs/msg/String", "alignment": "geometry_msgs/msg/QuaternionStamped",
                 "diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
    publisher = Publisher(domain, TOPICS, "imu")
    participant = DomainParticipant(domain)
    reader = BuiltinDataReader(participant, BuiltinTopicDcpsPublication)
    found = {}
    deadline = time.monotonic() + 2.0
    while len(found) < len(TOPICS) and time.monotonic() < deadline:
        found |= {s.topic_name: s for s in reader.take(N=50)}
        time.sleep(0.01)
    stores = [_typestore(store) for store in ("ROS2_IRON", "ROS2_JAZZY", "ROS2_KILTED")]
    for key, ros_type in ros_types.items():
        sample = found["rt/" + TOPICS[key].lstrip("/")]
        package, _, name = ros_type.split("/")
        assert sample.type_name == f"{package}::msg::dds_::{name}_"
        [rihs01] = {store.hash_rihs01(ros_type) for store in stores}
        assert len(rihs01) == len("RIHS01_") + 64
        assert sample.qos[Policy.Userdata].data == f"typehash={rihs01};".encode()
        expected = ros2_qos(key)
        for policy in (Policy.Reliability, Policy.Durability, Policy.History):
            assert sample.qos[policy] == expected[policy], (key, policy)
    publisher.close()


PUBLISHING_PROCESS = """
import sys, numpy as np
from calibd.ros2 import Publisher
publisher = Publisher(int(sys.argv[1]), {"imu": "/stim300/imu/data", "calibration": "stim300/calibration"}, "imu_link")
publisher.calibration('{"from": "another process"}')
print("ready", flush=True)
for n in range(200):  # 0.05 s apart, until the test has what it needs (it closes stdin) or 10 s pass
    stamps = n * 10**9 + np.arange(4)
    publisher.imu("imu", stamps, np.full((4, 3), n * 0.5), np.full((4, 3), -n * 0.5), [1e-6] * 9, [2e-3] * 9)
    if sys.stdin in __import__("select").select([sys.stdin], [], [], 0.05)[0]:
        break
publisher.close()
"""


def test_another_process_receives_over_udp(domain):
    """Samples between processes go through RTPS over UDP on loopback: the bytes a ROS 2 node reads."""
    from cyclonedds.domain import DomainParticipant
    child = subprocess.Popen([sys.executable, "-c", PUBLISHING_PROCESS, str(domain)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline() == "ready\n"
        participant = DomainParticipant(domain)
        imu, calibration = _subscribe(participant, "imu"), _subscribe(participant, "calibration")
        documents = [s.data for s in take(calibration, 1, timeout_s=5.0)]
        samples = take(imu, 8, timeout_s=5.0)
    finally:
        child.communicate("stop\n", timeout=30)
    assert documents == ['{"from": "another process"}']
    assert len(samples) == 8
    for sample in samples:
        n = sample.header.stamp.sec
        assert sample.header.frame_id == "imu_link" and sample.header.stamp.nanosec < 4
        assert (sample.angular_velocity.y, sample.linear_acceleration.z) == (n * 0.5, -n * 0.5)
        assert list(sample.linear_acceleration_covariance) == [2e-3] * 9
    assert child.returncode == 0


# ---- what the Publisher refuses

def test_bad_domains_names_and_keys_are_one_line(domain):
    from calibd.ros2 import Publisher
    for bad in (-1, 233, 1.0, True, "0"):
        _one_line_error(Publisher, bad, {}, "imu", says=f"ros2 domain_id {bad!r}: expected an integer 0 to 232")
    _one_line_error(Publisher, domain, {"imu": "imu//data"}, "imu", says="ros2 topic imu: 'imu//data'")
    _one_line_error(Publisher, domain, {"gps": "fix"}, "imu", says="ros2 topics: unknown key 'gps'")
    _one_line_error(Publisher, domain, {}, "imu link", says="ros2 frame_id 'imu link'")

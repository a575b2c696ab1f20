"""ROS 2 topics from the daemon's own code path: `calibd replay --serve` with a [ros2] table feeds
a capture through a pty, and a subscriber declared on its own (tests/ros2_subscriber.py: ROS
2's type names and QoS) reads imu/data_raw, imu/data, imu/calibration, imu/alignment and
diagnostics over DDS on loopback. Bad [ros2] tables and a missing extra are one line before
anything starts."""

import json
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibd.frames import STANDARD_GRAVITY
from calibd.units import DEG
from stim300.bulk import decode_capture

from captures import calibd, command_env
from ros2_subscriber import LOOPBACK, subscribe, take, valid

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "warmup_then_protocol_125hz.bin"
RATE_HZ = 125
GYRO_ARW_RAD_S = 0.15 * DEG / 60  # the datasheet's angle random walk, rad/s/sqrt(Hz)
ACC_VRW_M_S2 = 0.024 / 60  # velocity random walk of a 10 g unit, m/s^2/sqrt(Hz)
NWU_TO_ENU = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def write_config(tmp_path: Path, ros2: str) -> Path:
    path = tmp_path / "calibd.toml"
    path.write_text(f'[serial]\nport = "{tmp_path / "tty"}"\n[site]\nlatitude_deg = 40.59129\ng0 = 9.79956\n'
                    f'[output]\nstate_dir = "{tmp_path / "state"}"\n[warmup]\nwindow_s = 100\n[ros2]\n{ros2}')
    return path


def drain(readers: dict, got: dict) -> None:
    for key, reader in readers.items():
        got[key] += valid(reader.take(N=10_000))


@pytest.mark.slow
def test_a_replayed_sensor_reaches_a_ros_2_subscriber_raw_corrected_latched_and_diagnosed(tmp_path, monkeypatch):
    from cyclonedds.domain import DomainParticipant

    domain = random.randint(1, 200)
    config = write_config(tmp_path, f'domain_id = {domain}\nframe_id = "stim300_link"\n')
    topics = {"imu_raw": "imu/data_raw", "imu": "imu/data", "calibration": "imu/calibration",
              "alignment": "imu/alignment", "diagnostics": "diagnostics"}
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    participant = DomainParticipant(domain)
    readers = {key: subscribe(participant, name, key, depth=100_000) for key, name in topics.items()}
    got = {key: [] for key in topics}
    daemon = calibd("replay", CAPTURE, "--config", config, "--serve", "--speed", "100", "--state-dir",
                    tmp_path / "state", env={"CYCLONEDDS_URI": LOOPBACK})
    late = None
    try:
        while daemon.poll() is None:
            drain(readers, got)
            if late is None and got["calibration"]:
                late = subscribe(DomainParticipant(domain), topics["calibration"], "calibration")
                late_documents = [s.data for s in take(late, 1, timeout_s=10.0)]
            time.sleep(0.01)
        drain(readers, got)
        assert daemon.returncode == 0, daemon.stderr.read().decode()[-2000:]
    finally:
        if daemon.poll() is None:
            daemon.kill()

    truth = decode_capture(CAPTURE.read_bytes()).samples
    raw, corrected = got["imu_raw"], got["imu"]
    stamps = np.array([s.header.stamp.sec * 10**9 + s.header.stamp.nanosec for s in raw])
    assert np.all(np.diff(stamps) > 0)  # in order
    steps = np.diff(stamps) * RATE_HZ / 1e9  # the sensor's time scale: whole sample intervals
    assert np.allclose(steps, np.rint(steps), atol=1e-3)
    gyro = np.array([[s.angular_velocity.x, s.angular_velocity.y, s.angular_velocity.z] for s in raw])
    first = np.flatnonzero(np.all(truth["gyro"].astype(np.float64) * DEG == gyro[0], axis=1))[0]
    index = first + np.concatenate([[0], np.cumsum(np.rint(steps).astype(int))])
    assert np.array_equal(gyro, truth["gyro"][index].astype(np.float64) * DEG)
    assert index[0] < 0.2 * len(truth)  # from soon after the start (the subscriber matched)
    assert len(raw) > 0.99 * (index[-1] - index[0] + 1)  # best effort at 100 times real time: a few may go
    acc = np.array([[s.linear_acceleration.x, s.linear_acceleration.y, s.linear_acceleration.z] for s in raw])
    assert np.array_equal(acc, truth["acc"][index].astype(np.float64) * STANDARD_GRAVITY)
    assert all(s.header.frame_id == "stim300_link" and s.orientation_covariance[0] == -1.0 for s in raw)
    noise = np.array([GYRO_ARW_RAD_S ** 2 * RATE_HZ, ACC_VRW_M_S2 ** 2 * RATE_HZ])
    assert np.allclose(np.reshape(raw[0].angular_velocity_covariance, (3, 3)), np.eye(3) * noise[0], rtol=1e-12)
    assert np.allclose(np.reshape(raw[0].linear_acceleration_covariance, (3, 3)), np.eye(3) * noise[1], rtol=1e-12)

    documents = [json.loads(s.data) for s in got["calibration"]]
    assert documents and documents[-1] == json.loads((tmp_path / "state" / "result.json").read_text())
    biases = [np.array([d["estimates"][f"gyro_bias_{a}"]["value"] for a in "xyz"]) * DEG / 3600 for d in documents]
    sigmas = [np.array([d["estimates"][f"gyro_bias_{a}"]["sigma"] for a in "xyz"]) * DEG / 3600 for d in documents]
    by_stamp = dict(zip(stamps.tolist(), gyro))
    first_corrected = corrected[0].header.stamp.sec * 10**9 + corrected[0].header.stamp.nanosec
    assert len(corrected) > 0.95 * np.count_nonzero(stamps >= first_corrected)  # every sample from the first result on
    for sample in corrected:
        stamp = sample.header.stamp.sec * 10**9 + sample.header.stamp.nanosec
        if stamp not in by_stamp:
            continue  # its raw twin was one of the few best effort let go
        w = np.array([sample.angular_velocity.x, sample.angular_velocity.y, sample.angular_velocity.z])
        taken = by_stamp[stamp] - w
        which = [k for k, b in enumerate(biases) if np.allclose(taken, b, rtol=1e-6, atol=1e-15)]
        assert which, f"raw - corrected = {taken} rad/s is none of the results' gyro biases"
        diagonal = np.diag(np.reshape(sample.angular_velocity_covariance, (3, 3)))
        assert np.allclose(diagonal, noise[0] + sigmas[which[0]] ** 2, rtol=1e-6)

    assert late_documents and late_documents[0] in [s.data for s in got["calibration"]]  # the latched latest
    [alignment, *_] = got["alignment"][::-1]
    q = alignment.quaternion
    matrix = np.array(documents[-1]["rotation"]["nav_to_imu"]["matrix"])  # v_IMU = M v_NWU
    x_axis_in_enu = Rotation.from_quat([q.x, q.y, q.z, q.w]).apply([1.0, 0.0, 0.0])
    assert np.allclose(x_axis_in_enu, NWU_TO_ENU @ matrix[0], atol=1e-9)  # the IMU's x axis, in ENU
    statuses = {s.name: s for array in got["diagnostics"] for s in array.status}
    stream = {v.key: v.value for v in statuses["calibd: stream"].values}
    assert {"crc_errors", "lost_samples", "restarts", "hidden_gaps", "dropped_samples"} <= set(stream)
    assert "SOLVED" in {s.message.split(":")[0] for array in got["diagnostics"] for s in array.status}


@pytest.mark.parametrize("table, says", [
    ("domain_id = 233\n", "[ros2] domain_id: 233 is not a DDS domain id in [0, 232]"),
    ('data_topic = "imu data"\n', "[ros2] data_topic: 'imu data' is not a ROS 2 topic name"),
    ('frame_id = ""\n', "[ros2] frame_id: '': expected 1 to 255 printable ASCII characters"),
    ('data_topic = "/diagnostics"\n', "[ros2] diagnostics_topic: 'diagnostics' is also data_topic"),
    ("rate = 2\n", "[ros2] rate: unknown key"),
])
def test_a_bad_ros2_table_is_one_line_naming_the_key(tmp_path, table, says):
    config = write_config(tmp_path, table)
    done = subprocess.run([sys.executable, "-m", "calibd.cli", "replay", str(CAPTURE), "--config", str(config),
                           "--serve"], capture_output=True, text=True, env=command_env(), timeout=60)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and says in done.stderr, done.stderr


def test_without_the_extra_ros2_is_one_line_naming_it_before_anything_starts(tmp_path):
    config = write_config(tmp_path, "")
    code = ("import sys; sys.modules['cyclonedds'] = None; from calibd.cli import main; "
            f"sys.exit(main(['replay', {str(CAPTURE)!r}, '--config', {str(config)!r}, '--serve']))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=command_env(), timeout=60)
    assert done.returncode == 1, done.stderr
    assert done.stderr == "calibd: [ros2] ROS 2 publishing needs the ros2 extra: pip install 'stim300-calib[ros2]'\n"
    assert not (tmp_path / "state").exists()

"""`calibd apply RESULT CAPTURE -o OUT.mcap`: corrected sensor_msgs/Imu in an MCAP of the ROS 2
profile, read back with the mcap package's reader and mcap-ros2-support's decoder (neither
calibd's): the same samples as the NPZ output, the covariances documented, the result attached."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from calibd.cli import main as calibd_main
from calibd.correction import bias_covariance, noise_covariances
from calibd.results import load_result

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "thesis_real_cw_125hz.bin"
SITE = ["--latitude", "40.59129", "--g0", "9.79956"]


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("mcap") / "result.json"
    assert calibd_main(["calibrate", str(CAPTURE), "-o", str(path), *SITE]) == 0
    return path


def read_mcap(path: Path) -> dict:
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header, summary = reader.get_header(), reader.get_summary()
        messages = list(reader.iter_decoded_messages())
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = {a.name: a for a in reader.iter_attachments()}
    imu = [ros for _, _, _, ros in messages]
    return {"profile": header.profile, "channels": list(summary.channels.values()),
            "schemas": list(summary.schemas.values()), "metadata": metadata, "attachments": attachments,
            "log_time": np.array([m.log_time for _, _, m, _ in messages]),
            "stamp_ns": np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in imu]),
            "frame_id": {m.header.frame_id for m in imu},
            "gyro": np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in imu]),
            "acc": np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                             for m in imu]),
            "gyro_cov": {tuple(m.angular_velocity_covariance) for m in imu},
            "acc_cov": {tuple(m.linear_acceleration_covariance) for m in imu},
            "orientation_cov0": {m.orientation_covariance[0] for m in imu}}


@pytest.mark.slow
@pytest.mark.parametrize("frame", [[], ["--frame"]])
def test_the_mcap_holds_the_npz_samples_as_imu_messages(result_file, tmp_path, capsys, frame):
    mcap, npz = tmp_path / "out.mcap", tmp_path / "out.npz"
    assert calibd_main(["apply", str(result_file), str(CAPTURE), "-o", str(mcap), *frame]) == 0
    assert calibd_main(["apply", str(result_file), str(CAPTURE), "-o", str(npz), *frame]) == 0
    capsys.readouterr()
    got, want = read_mcap(mcap), np.load(npz)
    assert got["profile"] == "ros2" and [c.topic for c in got["channels"]] == ["/imu/data"]
    assert got["schemas"][0].name == "sensor_msgs/msg/Imu" and got["schemas"][0].encoding == "ros2msg"
    assert np.array_equal(got["gyro"], want["gyro_rad_s"]) and np.array_equal(got["acc"], want["acc_m_s2"])
    assert np.array_equal(got["stamp_ns"], np.round(want["time_s"] * 1e9).astype(np.int64))
    assert np.array_equal(got["log_time"], got["stamp_ns"])
    assert got["frame_id"] == {"imu_home" if frame else "imu_link"}

    result = load_result(result_file)
    gyro_noise, acc_noise = noise_covariances(125, 10)
    assert got["gyro_cov"] == {tuple((gyro_noise + bias_covariance(result, "gyro")).ravel())}
    assert got["acc_cov"] == {tuple((acc_noise + bias_covariance(result, "acc")).ravel())}
    assert got["orientation_cov0"] == {-1.0}  # no orientation (REP 145)
    assert got["attachments"]["calibd-result.json"].data == result_file.read_bytes()
    applied = got["metadata"]["calibd.applied"]
    assert json.loads(applied["biases_subtracted"]) == json.loads(str(want["meta"]))["biases_subtracted"]
    assert applied["frame"] == ("home" if frame else "imu")


def test_without_the_mcap_package_it_is_one_line_and_nothing_is_written(result_file, tmp_path, monkeypatch,
                                                                       run_main):
    for module in [m for m in sys.modules if m.split(".")[0] == "mcap"]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, "mcap", None)
    out = tmp_path / "out.mcap"
    code, _, err = run_main(calibd_main, ["apply", result_file, CAPTURE, "-o", out])
    assert code == 2 and err.count("\n") == 1 and "pip install 'stim300-calib[recordings]'" in err
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_the_corrected_mcap_calibrates_to_zero_biases(result_file, tmp_path, capsys):
    """The MCAP is a recording calibd reads (rosbags): calibrated again, what is left of the
    biases is nothing but the rounding of the message values."""
    mcap = tmp_path / "out.mcap"
    assert calibd_main(["apply", str(result_file), str(CAPTURE), "-o", str(mcap)]) == 0
    assert calibd_main(["calibrate", str(mcap), "-o", str(tmp_path / "again.json"), *SITE]) == 0
    capsys.readouterr()
    again = load_result(tmp_path / "again.json")
    for name in [f"{sensor}_bias_{axis}" for sensor in ("gyro", "acc") for axis in "xyz"]:
        estimate = again.estimates[name]
        assert abs(estimate.value) < 0.05 * estimate.sigma, (name, estimate)

"""`calibd apply` on recordings of sensor_msgs/Imu: a result taken off the Imu messages of a ROS 1
bag, rosbag2 (SQLite3, MCAP) and a plain MCAP gives the samples apply gives for the STIM300
capture they were made from, timed and stamped by the header stamps, into NPZ, CSV and MCAP; a
result of another frame is refused; gaps are warned about; bad input is one line, nothing
written."""

import io
import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from calibd.cli import main as calibd_main
from recording_files import (CAPTURE, EPOCH_NS, FORMATS, FRAME_ID, IMU, ROS1, TOPIC, calibrate, imu_message,
                             refusal, serialised, small_imu, write_recording)


@pytest.fixture(scope="module")
def result_files(tmp_path_factory, raw_result, recordings):
    """The raw capture's result (of serial N25582405002002), as a file."""
    tmp = tmp_path_factory.mktemp("results")
    (tmp / "raw.json").write_text(json.dumps(raw_result))
    return tmp / "raw.json"


def apply(run_main, result, capture, out, *extra):
    code, stdout, err = run_main(calibd_main, ["apply", result, capture, "-o", out, *extra])
    assert code == 0, err
    return stdout, err


@pytest.fixture(scope="module")
def raw_npz(tmp_path_factory, result_files):
    out = tmp_path_factory.mktemp("raw") / "raw.npz"
    assert calibd_main(["apply", str(result_files), str(CAPTURE), "-o", str(out)]) == 0
    return dict(np.load(out))


@pytest.mark.parametrize("kind", FORMATS)
def test_a_recording_is_corrected_as_its_capture_is(kind, recordings, result_files, raw_npz, fixture_samples,
                                                    run_main, tmp_path):
    out, err = apply(run_main, result_files, recordings[kind], tmp_path / "o.npz")
    assert f"{len(raw_npz['time_s'])} messages of topic {TOPIC}, biases of" in out
    assert "a recording names no serial number: cannot check the result (of sensor N25582405002002)" in err
    got = np.load(tmp_path / "o.npz")
    for name in ("gyro_rad_s", "acc_m_s2"):  # the messages hold the samples in float32 precision
        np.testing.assert_allclose(got[name], raw_npz[name], rtol=0, atol=2e-6 * np.abs(raw_npz[name]).max())
    assert np.abs(got["gyro_rad_s"].mean(axis=0) - raw_npz["gyro_rad_s"].mean(axis=0)).max() < 1e-9
    np.testing.assert_allclose(got["time_s"], raw_npz["time_s"], atol=1e-9)
    np.testing.assert_array_equal(got["stamp_ns"], fixture_samples[0])
    assert set(got) == {"time_s", "gyro_rad_s", "acc_m_s2", "stamp_ns", "meta"}
    assert json.loads(str(got["meta"]))["capture"] == str(recordings[kind])


def test_csv_of_a_recording_names_its_columns_and_units(recordings, result_files, run_main, tmp_path):
    apply(run_main, result_files, recordings["bag"], tmp_path / "o.csv", "--force")
    lines = (tmp_path / "o.csv").read_text().splitlines()
    assert lines[1].startswith("# units: time_s s since the first message's header stamp")
    assert "ns since the epoch" in lines[1]
    assert lines[2] == ("time_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s,acc_x_m_s2,acc_y_m_s2,acc_z_m_s2,stamp_ns")
    first, second = (row.split(",") for row in lines[3:5])
    assert first[0] == "0.0000" and second[0] == "0.0080"
    assert int(first[-1]) == EPOCH_NS and int(second[-1]) == EPOCH_NS + 8_000_000
    npz = tmp_path / "o.npz"
    apply(run_main, result_files, recordings["bag"], npz)
    table = np.loadtxt(io.StringIO("\n".join(lines[3:])), delimiter=",")
    np.testing.assert_allclose(table[:, 1:7], np.hstack([np.load(npz)["gyro_rad_s"], np.load(npz)["acc_m_s2"]]),
                               rtol=1e-8)


@pytest.mark.slow
def test_mcap_of_a_recording_keeps_its_stamps_and_frame(recordings, result_files, run_main, tmp_path):
    apply(run_main, result_files, recordings["mcap"], tmp_path / "o.mcap")
    apply(run_main, result_files, recordings["mcap"], tmp_path / "o.npz")
    npz = np.load(tmp_path / "o.npz")
    with open(tmp_path / "o.mcap", "rb") as f:
        decoded = [(message.log_time, ros) for _, _, message, ros in
                   make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    assert len(decoded) == len(npz["time_s"])
    assert [when for when, _ in decoded[:3]] == npz["stamp_ns"][:3].tolist()
    ros = decoded[100][1]
    assert ros.header.frame_id == FRAME_ID
    assert ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec == npz["stamp_ns"][100]
    v = ros.angular_velocity
    assert [v.x, v.y, v.z] == npz["gyro_rad_s"][100].tolist()
    assert ros.angular_velocity_covariance[0] > 0 and ros.orientation_covariance[0] == -1


def test_home_frame_of_a_recording_is_imu_home(recordings, result_files, run_main, tmp_path):
    out, _ = apply(run_main, result_files, recordings["sqlite3"], tmp_path / "o.mcap", "--frame")
    with open(tmp_path / "o.mcap", "rb") as f:
        _, _, _, ros = next(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert ros.header.frame_id == "imu_home" and "in the home frame" in out


def test_a_result_of_a_recording_of_another_frame_is_refused(recordings, site, fixture_samples, run_main, tmp_path):
    result = calibrate(recordings["sqlite3"], site, tmp_path / "r.json")
    assert result["sensor"]["serial_number"] is None and result["stream"]["frame_id"] == FRAME_ID
    out, err = apply(run_main, tmp_path / "r.json", recordings["bag"], tmp_path / "same.npz")
    assert err == ""  # the same frame: nothing to warn of
    stamps, gyro, acc, received = (a[:3000] for a in fixture_samples)
    messages = [bytes(ROS1.serialize_ros1(imu_message(ROS1, int(t), g, a, frame_id="imu_2_link"), IMU))
                for t, g, a in zip(stamps, gyro, acc)]
    other = write_recording(tmp_path / "other.bag", "bag", messages, received)
    err = refusal(run_main, ["apply", tmp_path / "r.json", other, "-o", tmp_path / "o.npz"])
    assert "the recording's frame id is 'imu_2_link', the result's 'stim300_link'" in err and "--force" in err
    assert not (tmp_path / "o.npz").exists()
    _, err = apply(run_main, tmp_path / "r.json", other, tmp_path / "o.npz", "--force")
    assert "applied anyway (--force)" in err


def test_gaps_in_the_stamps_are_warned_and_keep_their_time(result_files, fixture_samples, run_main, tmp_path):
    stamps, gyro, acc, received = (a[:3000] for a in fixture_samples)
    keep = np.r_[0:1000, 1040:3000]
    path = write_recording(tmp_path / "gap.bag", "bag", serialised("bag", stamps[keep], gyro[keep], acc[keep]),
                           received[keep])
    _, err = apply(run_main, result_files, path, tmp_path / "o.npz")
    assert "1 gap(s) in the header stamps: 40 sample(s) missing: no row stands for them" in err
    time_s = np.load(tmp_path / "o.npz")["time_s"]
    assert len(time_s) == 2960 and time_s[1000] - time_s[999] == pytest.approx(41 * 0.008)


def test_bad_recordings_for_apply_are_one_line_and_write_nothing(result_files, run_main, tmp_path):
    out = tmp_path / "o.npz"
    err = refusal(run_main, ["apply", result_files, CAPTURE, "-o", out, "--topic", TOPIC])
    assert "--topic names a topic of a recording" in err
    messages, stamps = small_imu("bag")
    other = write_recording(tmp_path / "none.bag", "bag", [], stamps, {"/chatter": ("std_msgs/msg/String", [])})
    assert "no sensor_msgs/msg/Imu topic" in refusal(run_main, ["apply", result_files, other, "-o", out])
    two = write_recording(tmp_path / "two.bag", "bag", [], stamps, {TOPIC: (IMU, messages), "/b": (IMU, messages)})
    assert "choose one with --topic" in refusal(run_main, ["apply", result_files, two, "-o", out])
    fast_messages = small_imu("bag", stamps_ns=EPOCH_NS + np.arange(300) * 100_000)[0]
    fast = write_recording(tmp_path / "fast.bag", "bag", fast_messages, stamps)
    assert "faster than a STIM300 samples" in refusal(run_main, ["apply", result_files, fast, "-o", out])
    assert not out.exists() and not list(tmp_path.glob("*.tmp*"))
    _, err = apply(run_main, result_files, two, out, "--topic", "/b")
    assert out.exists()


def test_a_recordings_result_names_the_topic_apply_takes_among_several(recordings, site, fixture_samples,
                                                                      run_main, tmp_path):
    result = calibrate(recordings["bag"], site, tmp_path / "r.json")  # of topic /imu/data
    stamps, gyro, acc, received = (a[:500] for a in fixture_samples)
    messages = serialised("bag", stamps, gyro, acc)
    two = write_recording(tmp_path / "two.bag", "bag", [], received, {"/a": (IMU, messages[:100]),
                                                                      TOPIC: (IMU, messages)})
    out, _ = apply(run_main, tmp_path / "r.json", two, tmp_path / "o.npz")
    assert f"500 messages of topic {TOPIC}" in out and result["stream"]["topic"] == TOPIC
    other = write_recording(tmp_path / "other.bag", "bag", [], received,
                            {"/a": (IMU, messages), "/b": (IMU, messages)})
    err = refusal(run_main, ["apply", tmp_path / "r.json", other, "-o", tmp_path / "p.npz"])
    assert "choose one with --topic" in err


def test_a_results_recording_fields_are_checked(tmp_path, site, recordings):
    from calibd.results import ResultError, parse_result

    result = calibrate(recordings["bag"], site, tmp_path / "r.json")
    assert parse_result(json.dumps(result).encode(), "r.json").stream.topic == TOPIC
    for key, bad in (("topic", 5), ("messages", -1), ("frame_id", ["x"])):
        doc = json.loads(json.dumps(result))
        doc["stream"][key] = bad
        with pytest.raises(ResultError, match=rf"r.json: stream\.{key} is "):
            parse_result(json.dumps(doc).encode(), "r.json")

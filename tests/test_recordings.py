"""Recordings of sensor_msgs/Imu (calibd.recordings): a simulated capture of a unit without
inclinometers, written as a ROS 1 bag, rosbag2 SQLite3 and MCAP directories and plain MCAP files
of ROS 2 and ROS 1 messages (tests/recording_files.py), calibrates as the capture itself does;
gaps in the header stamps are counted; what cannot be read is one line and exit 2."""

import json
import shutil
import sys

import numpy as np
import pytest

from calibd.captures import open_capture
from calibd.cli import main as calibd_main
from calibd.errors import CalibrationError
from calibd.recordings import decode_imu, is_recording
from calibd.session import power_up_session

from recording_files import (CAPTURE, EPOCH_NS, FIXTURES, FORMATS, FRAME_ID, IMU, ROS1, ROS2, TOPIC, calibrate,
                             imu_message, refusal, serialised, small_imu, write_recording)


def test_recordings_are_told_from_captures_by_content(recordings, tmp_path):
    assert all(is_recording(path) for path in recordings.values())
    assert not is_recording(CAPTURE)
    renamed = tmp_path / "capture.bag"  # a name says nothing: a STIM300 capture named .bag is a capture
    shutil.copy(CAPTURE, renamed)
    assert not is_recording(renamed)
    assert not is_recording(tmp_path)  # a directory without metadata.yaml


@pytest.mark.parametrize("kind", FORMATS)
def test_a_recording_calibrates_as_its_capture_does(recordings, kind, site, raw_result, tmp_path):
    result = calibrate(recordings[kind], site, tmp_path / "result.json")
    truth = json.loads((FIXTURES / "gyro_acc_125hz.bin.truth.json").read_text())
    expected = {"pitch": truth["truth"]["pitch_deg"], "roll": truth["truth"]["roll_deg"],
                "yaw": truth["truth"]["yaw_deg"], "alpha": truth["truth"]["alpha_deg"],
                "beta": truth["truth"]["beta_deg"]}
    for name, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg")):
        # the biases the data carry: the settled ones moved by the session's mean bias wander (docs/accuracy.md)
        expected |= {f"{name}_{a}": v for a, v in zip("xyz", truth["bias_during_capture"][key]["session"])}
    assert set(result["estimates"]) == set(raw_result["estimates"]) == set(expected)
    for name, e in result["estimates"].items():
        raw = raw_result["estimates"][name]
        assert abs(e["value"] - raw["value"]) <= 0.1 * raw["sigma"], (name, e, raw)
        assert abs(e["sigma"] - raw["sigma"]) <= 0.1 * raw["sigma"], (name, e, raw)
        assert abs(e["value"] - expected[name]) <= e["sigma"], (name, e, expected[name])
    stream = result["stream"]
    assert stream["topic"] == TOPIC and stream["frame_id"] == FRAME_ID and stream["capture"] == str(recordings[kind])
    assert stream["messages"] == raw_result["stream"]["datagrams"] and stream["lost_samples"] == 0
    assert (stream["crc_errors"], stream["restarts"], stream["inferred_missing"]) == (0, 0, 0)  # none: no datagrams
    assert result["sensor"]["sample_rate_hz"] == 125 and result["sensor"]["serial_number"] is None
    assert result["capture"]["path"] == str(recordings[kind]) and len(result["capture"]["sha256"]) == 64


def test_times_are_the_header_stamps_not_the_receive_times(recordings, fixture_samples):
    capture = open_capture(str(recordings["bag"]))
    session = power_up_session(capture)
    assert capture.rate_hz == 125  # the stamps' step exactly; the jittered receive times would not give it
    assert np.allclose(session.time_s, np.arange(len(session.time_s)) * 0.008, rtol=0, atol=1e-9)


def test_the_identity_of_a_rosbag2_directory_is_its_metadata_then_its_storage_files(recordings):
    import hashlib

    directory = recordings["sqlite3"]
    files = [directory / "metadata.yaml", directory / f"{directory.name}.db3"]
    data = b"".join(f.read_bytes() for f in files)
    identity = open_capture(str(directory)).identity
    assert identity == {"size_bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


@pytest.mark.parametrize("encoding", ["ros1", "cdr"])
def test_decoding_agrees_with_rosbags_deserialiser(encoding):
    """Every frame id length (0-9 characters: each CDR alignment), values of every kind."""
    rng = np.random.default_rng(1)
    store = ROS1 if encoding == "ros1" else ROS2
    messages, expected = [], []
    for k in range(40):
        stamp = int(rng.integers(0, 2**31 - 1)) * 10**9 + int(rng.integers(0, 10**9))
        gyro, acc = rng.normal(size=3) * 10.0 ** rng.integers(-12, 3), rng.normal(size=3) * 10
        message = imu_message(store, stamp, gyro, acc, frame_id="f" * (k % 10), seq=k)
        raw = bytes(store.serialize_ros1(message, IMU) if encoding == "ros1" else store.serialize_cdr(message, IMU))
        messages.append(raw)
        back = store.deserialize_ros1(raw, IMU) if encoding == "ros1" else store.deserialize_cdr(raw, IMU)
        expected.append((back.header.stamp.sec * 10**9 + back.header.stamp.nanosec,
                         [back.angular_velocity.x, back.angular_velocity.y, back.angular_velocity.z],
                         [back.linear_acceleration.x, back.linear_acceleration.y, back.linear_acceleration.z]))
    stamps, gyro, acc, frame_id = decode_imu(messages, encoding, "test")
    assert stamps.tolist() == [e[0] for e in expected]
    assert np.array_equal(gyro, [e[1] for e in expected]) and np.array_equal(acc, [e[2] for e in expected])
    assert frame_id == ""  # the first message's


def test_messages_without_accelerometers_with_nan_or_in_big_endian_cdr_are_refused():
    level = imu_message(ROS2, EPOCH_NS, [0, 0, 0], [0, 0, 9.8])
    no_acc = imu_message(ROS2, EPOCH_NS, [0, 0, 0], [0, 0, 0], acc_covariance=-1.0)
    with pytest.raises(CalibrationError, match=r"no linear acceleration \(its covariance is -1\)"):
        decode_imu([bytes(ROS2.serialize_cdr(no_acc, IMU))] * 2, "cdr", "test")
    no_value = imu_message(ROS2, EPOCH_NS, [0, np.nan, 0], [0, 0, 9.8])
    with pytest.raises(CalibrationError, match=r"message 8 has angular velocity \[0.0, nan, 0.0\] rad/s"):
        decode_imu([bytes(ROS2.serialize_cdr(level, IMU))] * 2 + [bytes(ROS2.serialize_cdr(no_value, IMU))], "cdr",
                   "test", first=5)
    big_endian = bytes(ROS2.serialize_cdr(level, IMU, little_endian=False))
    with pytest.raises(CalibrationError, match="message 2 has CDR encapsulation 0x0000: only little-endian"):
        decode_imu([bytes(ROS2.serialize_cdr(level, IMU)), big_endian], "cdr", "test")


def test_noise_of_a_recording_is_the_noise_of_its_capture(recordings, run_main):
    code, raw, _ = run_main(calibd_main, ["noise", CAPTURE])
    assert code == 0
    code, recorded, _ = run_main(calibd_main, ["noise", recordings["sqlite3"]])
    assert code == 0 and recorded.split(": ", 1)[1] == raw.split(": ", 1)[1]


def test_the_kalibr_file_of_a_recording_names_its_topic(recordings, run_main, tmp_path):
    code, _, _ = run_main(calibd_main, ["noise", recordings["sqlite3"], "--kalibr", tmp_path / "imu.yaml"])
    assert code == 0 and f"rostopic: {TOPIC}" in (tmp_path / "imu.yaml").read_text()


def test_a_dropped_run_of_messages_is_a_gap_in_the_stream_record(tmp_path, fixture_samples):
    stamps, gyro, acc, received = (a[:6000] for a in fixture_samples)
    keep = np.r_[0:2000, 2050:4000, 4003:6000]  # 50 and 3 messages dropped
    path = write_recording(tmp_path / "gap.bag", "bag", serialised("bag", stamps[keep], gyro[keep], acc[keep]),
                           received[keep])
    capture = open_capture(str(path))
    assert capture.stream.gaps == 2 and capture.stream.lost_samples == 53
    assert capture.stream.messages == len(keep) and capture.rate_hz == 125
    assert capture.stream.warnings == ("2 gap(s) in the header stamps: 53 sample(s) missing",)
    session = power_up_session(capture)
    assert session.stream.lost_samples == 53
    assert session.time_s[-1] == pytest.approx(5999 * 0.008, abs=1e-9)  # the gaps keep their time


def test_several_imu_topics_need_topic_and_topic_chooses(tmp_path, run_main):
    messages, stamps = small_imu("bag")
    path = write_recording(tmp_path / "two.bag", "bag", [], stamps, {TOPIC: (IMU, messages), "/imu2": (IMU, messages)})
    err = refusal(run_main, ["noise", path])
    assert "2 sensor_msgs/msg/Imu topics (/imu/data, /imu2): choose one with --topic" in err
    capture = open_capture(str(path), topic="/imu2")
    assert capture.stream.topic == "/imu2" and capture.stream.messages == len(messages)


def test_topic_on_a_capture_is_refused(tmp_path, run_main):
    err = refusal(run_main, ["calibrate", CAPTURE, "--latitude", "40", "--topic", TOPIC, "-o", tmp_path / "r.json"])
    assert "--topic names a topic of a recording" in err
    assert not (tmp_path / "r.json").exists()


def test_bad_recordings_are_one_line_and_exit_2(tmp_path, run_main):
    messages, stamps = small_imu("bag")
    string = [bytes(ROS1.serialize_ros1(ROS1.types["std_msgs/msg/String"]("hello"), "std_msgs/msg/String"))] * 3
    cases = {}
    chatter = write_recording(tmp_path / "chatter.bag", "bag", [], stamps,
                              {"/chatter": ("std_msgs/msg/String", string)})
    cases["no Imu topic"] = (chatter, [], "no sensor_msgs/msg/Imu topic (the recording has /chatter)")
    cases["wrong type"] = (chatter, ["--topic", "/chatter"],
                           "topic /chatter is std_msgs/msg/String, not sensor_msgs/msg/Imu")
    cases["no such topic"] = (chatter, ["--topic", "/imu"], "no topic /imu (its sensor_msgs/msg/Imu topics: none)")
    empty = write_recording(tmp_path / "empty.bag", "bag", [], stamps,
                            {TOPIC: (IMU, []), "/chatter": ("std_msgs/msg/String", string)})
    cases["no messages"] = (empty, [], f"topic {TOPIC} has no messages")
    whole = write_recording(tmp_path / "whole.bag", "bag", messages, stamps)
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(whole.read_bytes()[:whole.stat().st_size // 2])
    cases["truncated bag"] = (truncated, [], "cannot read the ROS 1 bag")
    plain = write_recording(tmp_path / "plain.mcap", "plain_mcap", *small_imu("cdr"))
    data = bytearray(plain.read_bytes())
    middle = len(data) // 3  # inside the one chunk's compressed messages
    data[middle:middle + 64] = bytes(64)
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(bytes(data))
    cases["corrupt chunk"] = (corrupt, [], "cannot read the MCAP file")
    unsummed = tmp_path / "unsummed.mcap"  # cut short, its summary never written
    unsummed.write_bytes(plain.read_bytes()[:plain.stat().st_size * 2 // 3] + plain.read_bytes()[-8:])
    cases["MCAP without a summary"] = (unsummed, [], "cannot read the MCAP file")
    truncated_mcap = tmp_path / "truncated.mcap"
    truncated_mcap.write_bytes(plain.read_bytes()[:plain.stat().st_size // 2])
    cases["truncated MCAP"] = (truncated_mcap, [], "cannot read the MCAP file")
    json_imu = tmp_path / "json.mcap"
    with open(json_imu, "wb") as f:
        from mcap.writer import Writer as McapWriter

        writer = McapWriter(f)
        writer.start(profile="", library="test")
        channel = writer.register_channel(TOPIC, "json", writer.register_schema(IMU, "jsonschema", b"{}"))
        for when in stamps[:3]:
            writer.add_message(channel, int(when), b"{}", int(when))
        writer.finish()
    cases["JSON messages"] = (json_imu, [], f"topic {TOPIC} is encoded as json: only cdr or ros1 is read")
    sqlite = write_recording(tmp_path / "db", "sqlite3", *small_imu("cdr")) / "db.db3"
    damaged = tmp_path / "damaged.db3"
    damaged.write_bytes(sqlite.read_bytes()[:4096] + bytes(8192))
    cases["damaged SQLite3"] = (damaged, [], "cannot read the rosbag2 SQLite3 file")
    messages_back, stamps_back = small_imu("bag")
    messages_back[100], messages_back[101] = messages_back[101], messages_back[100]
    back = write_recording(tmp_path / "back.bag", "bag", messages_back, stamps_back)
    cases["stamps back"] = (back, [], "message 102's header stamp is -8 ms after the one before")
    reads = EPOCH_NS + np.arange(300) // 5 * 40_000_000 + np.arange(300) % 5 * 10_000  # 5 stamped 10 us apart
    bursts = write_recording(tmp_path / "bursts.bag", "bag", *small_imu("bag", stamps_ns=reads))
    cases["stamps of reads"] = (bursts, [], "faster than a STIM300 samples (2000 Hz): they do not time the samples")
    single = write_recording(tmp_path / "single.bag", "bag", messages[:1], stamps)
    cases["one message"] = (single, [], "1 message: too few to tell the sample rate")
    renamed = tmp_path / "recording.bin"
    shutil.copy(sqlite, renamed)
    cases["misnamed"] = (renamed, [], "a rosbag2 SQLite3 file by its content, but recordings are read by the name "
                                      "ending .db3")
    for read_by_content in (whole, plain):  # calibd's own readers: the name does not matter
        shutil.copy(read_by_content, tmp_path / "imu.bin")
        assert open_capture(str(tmp_path / "imu.bin")).stream.messages == 300
    for what, (path, options, words) in cases.items():
        out = tmp_path / f"{what}.json"
        for command in (["calibrate", path, "--latitude", "40", "-o", out], ["noise", path, "-o", out]):
            err = refusal(run_main, [*command, *options])
            assert err.startswith(f"calibd: {path}: ") and words in err, (what, err)
            assert not out.exists()


def test_an_mcap_of_any_profile_is_read(tmp_path):
    messages, stamps = small_imu("cdr")
    for profile in ("", "ros2", "x-own"):
        path = write_recording(tmp_path / f"p{profile}.mcap", "plain_mcap", messages, stamps, profile=profile)
        capture = open_capture(str(path))
        assert capture.stream.messages == 300 and capture.stream.frame_id == FRAME_ID, profile


def test_without_the_extra_a_recording_is_one_line_naming_it(tmp_path, run_main, monkeypatch):
    messages, stamps = small_imu("bag")
    bag = write_recording(tmp_path / "imu.bag", "bag", messages, stamps)
    for module in [m for m in sys.modules if m.split(".")[0] == "rosbags"]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, "rosbags", None)
    err = refusal(run_main, ["calibrate", bag, "--latitude", "40", "-o", tmp_path / "r.json"])
    assert err == f"calibd: {bag}: reading a recording needs the recordings extra: pip install " \
                  "'stim300-calib[recordings]'\n"


def test_reading_shows_a_progress_bar_on_a_terminal_only(recordings, monkeypatch):
    import io

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    for path, unit in ((recordings["bag"], "56978/56978"), (CAPTURE, f"{CAPTURE.stat().st_size} B")):
        terminal = Terminal()
        monkeypatch.setattr(sys, "stderr", terminal)
        open_capture(str(path))
        assert terminal.getvalue().startswith(f"\rreading {path} [") and unit in terminal.getvalue(), path
        piped = io.StringIO()
        monkeypatch.setattr(sys, "stderr", piped)
        open_capture(str(path))
        assert piped.getvalue() == ""


@pytest.mark.slow
def test_report_of_a_recording_of_several_imu_topics_takes_the_results_topic(tmp_path, fixture_samples, site,
                                                                            run_main):
    stamps, gyro, acc, received = fixture_samples
    messages = serialised("bag", stamps, gyro, acc)
    path = write_recording(tmp_path / "two.bag", "bag", [], received,
                           {TOPIC: (IMU, messages), "/imu2": (IMU, messages)})
    code, _, err = run_main(calibd_main, ["calibrate", path, "--latitude", site["latitude_deg"], "--g0", site["g0"],
                                          "--topic", "/imu2", "-o", tmp_path / "r.json"])
    assert code == 0, err
    code, out, err = run_main(calibd_main, ["report", tmp_path / "r.json", path, "-o", tmp_path / "r.html"])
    assert code == 0 and out.startswith(f"report: {tmp_path / 'r.html'}"), err
    page = (tmp_path / "r.html").read_text()
    assert "0 spans" in page and "None" not in page  # the stream's counts of a recording, each a number
    err = refusal(run_main, ["report", tmp_path / "r.json", path, "-o", tmp_path / "s.html", "--topic", "/imu3"])
    assert "no topic /imu3" in err

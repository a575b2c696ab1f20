"""`calibd replay` of a recording of sensor_msgs/Imu (calibd.recordingbytes): the messages become
the datagrams 0x91 they stand for, counted and read-logged by their stamps, and the daemon's
pipeline gives what it gives on the capture itself; gaps show as lost datagrams, a gap of whole
counter cycles through the read log; what cannot be a STIM300 stream is one line and exit 2."""

import json
import math

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from calibd.recordingbytes import DATAGRAM_BYTES, recording_bytes
from calibd.session import decode_sessions, power_up_session
from stim300.bulk import decode_capture
from stim300.clock import CYCLE_S, counter_times
from stim300.protocol import Status

from captures import calibd
from recording_files import (CAPTURE, EPOCH_NS, FRAME_ID, IMU, TOPIC, refusal, serialised, small_imu,
                             write_recording)
from test_serve_daemon import read_link

SITE = ["--latitude", "40.59129", "--g0", "9.79956", "--warmup-window", "10"]  # the fixture's site; no temperatures


def replay_result(path, tmp_path, *options) -> dict:
    """`calibd replay PATH` in-process: its result (result.json of its state directory)."""
    code = calibd_main(["replay", str(path), *SITE, "--state-dir", str(tmp_path / "state"), *map(str, options)])
    assert code == 0
    return json.loads((tmp_path / "state" / "result.json").read_text())


def level_imu(n: int, rate_hz: int, slots=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n messages of a level unit at rest (SI) in sample slots `slots` (default 0..n-1) at `rate_hz`."""
    slots = np.arange(n) if slots is None else slots
    stamps = EPOCH_NS + slots.astype(np.int64) * (10**9 // rate_hz)
    return stamps, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.80665], (n, 1))


@pytest.fixture(scope="module")
def raw_replay(tmp_path_factory):
    return replay_result(CAPTURE, tmp_path_factory.mktemp("raw"))


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["sqlite3", "bag", "mcap"])
def test_a_recording_replays_as_its_capture_does(kind, recordings, fixture_samples, raw_replay, tmp_path, capsys):
    stamps = fixture_samples[0]
    path = recordings[kind]
    result = replay_result(path, tmp_path)
    assert (f"calibd replay: {path}: {len(stamps)} Imu messages of topic {TOPIC} replayed as STIM300 datagrams 0x91 "
            "at 125 Hz") in capsys.readouterr().err.splitlines()
    assert set(result["estimates"]) == set(raw_replay["estimates"])
    for name, e in result["estimates"].items():
        raw = raw_replay["estimates"][name]
        assert abs(e["value"] - raw["value"]) <= 0.1 * raw["sigma"], (name, e, raw)
        assert abs(e["sigma"] - raw["sigma"]) <= 0.1 * raw["sigma"], (name, e, raw)
    for key in ("datagrams", "lost_samples", "flagged_datagrams"):
        assert result["stream"][key] == raw_replay["stream"][key], key
    assert raw_replay["stream"]["hidden_gaps"] is None  # the fixture has no read log
    assert result["stream"]["hidden_gaps"] == 0  # the stamps' read log shows no gap where there is none
    assert result["sensor"]["sample_rate_hz"] == 125 and result["sensor"]["serial_number"] is None
    words = {"sqlite3": "rosbag2 directory", "bag": "ROS 1 bag", "mcap": "rosbag2 directory"}[kind]
    assert (result["stream"]["capture"], result["stream"]["recording"], result["stream"]["topic"],
            result["stream"]["frame_id"]) == (str(path), words, TOPIC, FRAME_ID)


def test_the_datagrams_decode_to_the_messages_and_gaps_show_as_lost_datagrams(tmp_path, fixture_samples):
    """50 messages dropped at 125 Hz: the counter shows 2 lost (50 = 3 whole counter cycles + 2),
    the read log the 3 cycles; 3 dropped: 3 lost."""
    stamps, gyro, acc, received = (a[:6000] for a in fixture_samples)
    keep = np.r_[0:2000, 2050:4000, 4003:6000]
    path = write_recording(tmp_path / "gap.bag", "bag", serialised("bag", stamps[keep], gyro[keep], acc[keep]),
                           received[keep])
    replayed = recording_bytes(path)
    assert replayed.warnings == ["2 gap(s) in the header stamps: 53 sample(s) missing"]
    assert (replayed.messages, replayed.rate_hz, replayed.topic) == (len(keep), 125, TOPIC)
    assert len(replayed.data) == len(keep) * DATAGRAM_BYTES and replayed.reads["end"][-1] == len(replayed.data)
    capture = decode_capture(replayed.data, reads=replayed.reads)
    assert capture.info.rate_hz == 125 and capture.info.rate_words() == "125 Hz"  # from the counter's step alone
    assert capture.info.stats.lost_samples == 5 and capture.info.stats.crc_errors == 0
    samples = capture.samples
    assert len(samples) == len(keep) and np.all(samples["datagram_id"] == 0x91)
    lsb = capture.info.format.scales()
    assert np.abs(samples["gyro"] * (math.pi / 180) - gyro[keep]).max() <= lsb["gyro"] * math.pi / 180
    assert np.abs(samples["acc"] * 9.80665 - acc[keep]).max() <= lsb["acc"] * 9.80665
    assert np.isnan(samples["incl"]).all() and np.isnan(samples["temp_gyro"]).all()
    times = counter_times(samples["counter"], 125, samples["t_host"])
    assert times.hidden_gaps == 1 and times.hidden_s == pytest.approx(3 * CYCLE_S)
    assert np.allclose(times.time_s, (stamps[keep] - stamps[0]) * 1e-9, rtol=0, atol=1e-9)  # the stamps' times
    session = power_up_session(decode_sessions(replayed.data, str(path), replayed.reads))
    assert session.stream.lost_samples == 5 and session.stream.hidden_gaps == 1
    assert session.time_s[-1] == pytest.approx(5999 * 0.008, abs=1e-9)


@pytest.mark.slow
def test_replay_of_a_capture_with_its_read_log_finds_the_gaps_the_counter_cannot_see(tmp_path, fixture_samples,
                                                                                      raw_replay):
    """A recording's datagrams written as a capture with its read log beside it (CAPTURE.reads.npy,
    as `stim300 record` writes): replay takes the read log, as calibrate does, and finds the 16
    messages (one counter cycle at 125 Hz) dropped in a static."""
    stamps, gyro, acc, received = fixture_samples
    keep = np.r_[0:20_000, 20_016:len(stamps)]
    path = write_recording(tmp_path / "db", "sqlite3", serialised("cdr", stamps[keep], gyro[keep], acc[keep]),
                           received[keep])
    replayed = recording_bytes(path)
    capture = tmp_path / "capture.bin"
    capture.write_bytes(replayed.data)
    np.save(tmp_path / "capture.bin.reads.npy", replayed.reads)
    result = replay_result(capture, tmp_path)
    assert result["stream"]["lost_samples"] == 0  # 16 x 16 internal samples: a whole cycle, unseen by the counter
    assert result["stream"]["hidden_gaps"] == 1 and result["stream"]["hidden_gap_s"] == pytest.approx(CYCLE_S)
    for name, e in result["estimates"].items():
        raw = raw_replay["estimates"][name]
        assert abs(e["value"] - raw["value"]) <= 0.1 * raw["sigma"], (name, e, raw)


@pytest.mark.parametrize("rate_hz, lost", [(2000, 300), (200, 77)])
def test_a_gap_of_whole_counter_cycles_is_found_through_the_read_log(tmp_path, rate_hz, lost):
    """2000 Hz: 300 samples lost, of which the counter shows 44 (300 - 256); 200 Hz (a rate no
    configuration has: an external trigger's to the decoder): 77 lost, 780 internal samples of
    which the counter shows 12."""
    n = 10 * rate_hz
    stamps, gyro, acc = level_imu(n, rate_hz, np.r_[0:n // 2, n // 2 + lost:n + lost])
    path = write_recording(tmp_path / "db", "sqlite3", serialised("cdr", stamps, gyro, acc), stamps)
    replayed = recording_bytes(path)
    assert replayed.rate_hz == rate_hz and replayed.warnings == [f"1 gap(s) in the header stamps: {lost} sample(s) "
                                                                 "missing"]
    capture = decode_capture(replayed.data, reads=replayed.reads)
    assert capture.info.rate_hz == rate_hz
    times = counter_times(capture.samples["counter"], rate_hz, capture.samples["t_host"])
    assert times.hidden_gaps == 1 and times.gap_index.tolist() == [n // 2]
    assert np.allclose(times.time_s, (stamps - stamps[0]) * 1e-9, rtol=0, atol=1e-9)
    blind = counter_times(capture.samples["counter"], rate_hz)  # without the read log: whole cycles short
    assert times.time_s[-1] - blind.time_s[-1] == pytest.approx(times.hidden_s)


def test_values_beyond_a_datagram_are_saturated_flagged_and_warned(tmp_path, run_main):
    stamps, gyro, acc = level_imu(300, 125)
    gyro[10] = [10.0, 0.0, -10.0]  # rad/s: 573 deg/s
    acc[20] = [0.0, 200.0, 9.8]  # m/s^2: 20 g
    acc[21] = [0.0, 0.0, 156.0]  # 15.9 g: held
    path = write_recording(tmp_path / "db", "sqlite3", serialised("cdr", stamps, gyro, acc), stamps)
    replayed = recording_bytes(path)
    assert replayed.warnings == ["2 message(s) beyond what a datagram 0x91 holds (+-512 deg/s = 8.94 rad/s, +-16 g "
                                 "= 157 m/s^2): saturated and flagged OVERLOAD, as the sensor flags its own"]
    samples = decode_capture(replayed.data).samples
    assert samples["status_gyro"][10] == Status.OVERLOAD | Status.X | Status.Z
    assert samples["status_acc"][20] == Status.OVERLOAD | Status.Y
    assert np.count_nonzero(samples["status_gyro"]) == 1 and np.count_nonzero(samples["status_acc"]) == 1
    assert samples["gyro"][10].tolist() == pytest.approx([512, 0, -512], abs=1e-3)
    assert samples["acc"][20][1] == pytest.approx(16, abs=1e-5)
    assert samples["acc"][21][2] == pytest.approx(156 / 9.80665)
    code, out, err = run_main(calibd_main, ["replay", path, "--latitude", "40"])
    assert code == 1  # 2.4 s of data: no result
    assert err.splitlines()[1] == f"calibd replay: {path}: warning: {replayed.warnings[0]}"


def test_stamps_near_a_stim300_rate_are_replayed_at_it(tmp_path):
    """Stamps of a host clock running 0.4 % fast against the sensor's: 125.5 Hz is 125 Hz."""
    stamps = EPOCH_NS + np.arange(300, dtype=np.int64) * 7_968_127
    path = write_recording(tmp_path / "fast.bag", "bag", *small_imu("bag", stamps_ns=stamps))
    replayed = recording_bytes(path)
    assert (replayed.step, replayed.rate_hz, replayed.warnings) == (16, 125, [])
    assert replayed.description().endswith("at 125 Hz (the stamps: 125.5 Hz)")
    assert np.all(np.diff(decode_capture(replayed.data).samples["counter"]) == 16)


def test_what_cannot_be_a_stim300_stream_is_one_line_and_exit_2(tmp_path, run_main):
    stamps = EPOCH_NS + np.arange(300, dtype=np.int64) * 6_666_667  # 150 Hz: 2000 Hz / 13.3
    odd = write_recording(tmp_path / "odd.bag", "bag", *small_imu("bag", stamps_ns=stamps))
    err = refusal(run_main, ["replay", odd, "--latitude", "40"])
    assert err == (f"calibd: {odd}: the header stamps step at 150 Hz, not 2000 Hz divided by a whole number below "
                   "256 (within 1%): no STIM300 datagram counter counts so\n")
    stamps = EPOCH_NS + np.arange(300, dtype=np.int64) * 200_000_000  # 5 Hz: a step of 400 internal samples
    slow = write_recording(tmp_path / "slow.bag", "bag", *small_imu("bag", stamps_ns=stamps))
    assert "the header stamps step at 5 Hz" in refusal(run_main, ["replay", slow, "--latitude", "40"])
    err = refusal(run_main, ["replay", CAPTURE, "--latitude", "40", "--topic", TOPIC])
    assert err.startswith(f"calibd: {CAPTURE}: --topic names a topic of a recording")
    string = [b"\x05\x00\x00\x00hello"] * 3
    chatter = write_recording(tmp_path / "chatter.bag", "bag", [], stamps,
                              {"/chatter": ("std_msgs/msg/String", string)})
    err = refusal(run_main, ["replay", chatter, "--latitude", "40"])
    assert err == f"calibd: {chatter}: no sensor_msgs/msg/Imu topic (the recording has /chatter)\n"
    messages, stamps = small_imu("bag")
    two = write_recording(tmp_path / "two.bag", "bag", [], stamps, {TOPIC: (IMU, messages), "/imu2": (IMU, messages)})
    err = refusal(run_main, ["replay", two, "--latitude", "40"])
    assert err == f"calibd: {two}: 2 sensor_msgs/msg/Imu topics ({TOPIC}, /imu2): choose one with --topic\n"
    assert recording_bytes(two, "/imu2").topic == "/imu2"
    err = refusal(run_main, ["replay", two, "--latitude", "40", "--topic", "/imu3"])
    assert err == f"calibd: {two}: no topic /imu3 (its sensor_msgs/msg/Imu topics: {TOPIC}, /imu2)\n"


@pytest.mark.slow
def test_a_recording_replays_through_the_raw_pty(tmp_path):
    """`calibd replay REC --raw-pty LINK`: a driver on the link reads the recording's datagrams,
    unchanged and in order, from when it opened the link."""
    stamps, gyro, acc = level_imu(2500, 125)  # 20 s
    path = write_recording(tmp_path / "imu.mcap", "plain_mcap", serialised("cdr", stamps, gyro, acc), stamps)
    link = tmp_path / "raw"
    daemon = calibd("replay", path, "--latitude", "40", "--raw-pty", link, "--speed", "10")
    got = read_link(link, daemon)
    assert daemon.wait(timeout=30) == 1  # 20 s of data: no result
    data = recording_bytes(path).data
    assert len(got) >= DATAGRAM_BYTES and got in data and data.find(got) % DATAGRAM_BYTES == 0  # datagrams whole
    assert f"{path}: 2500 Imu messages of topic {TOPIC} replayed as STIM300 datagrams 0x91 at 125 Hz" in \
        daemon.stderr.read().decode()


@pytest.mark.slow
def test_without_a_warmup_window_a_recording_is_calibrated_from_its_first_message(recordings, raw_replay, tmp_path,
                                                                                    capsys):
    """The first message is no power-up, and no temperature tells the warm-up: as calibrate does,
    the session starts at once (with the default 600 s window this 455 s recording gave nothing)."""
    path = recordings["sqlite3"]
    code = calibd_main(["replay", str(path), *SITE[:4], "--state-dir", str(tmp_path / "state")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert f"calibd replay: {path}: warning: no temperatures: the warm-up cannot be checked" in err
    result = json.loads((tmp_path / "state" / "result.json").read_text())
    for name, e in result["estimates"].items():
        raw = raw_replay["estimates"][name]
        assert abs(e["value"] - raw["value"]) <= 0.1 * raw["sigma"], (name, e, raw)

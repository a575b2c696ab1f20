"""The MCAP a recording of the sensor is kept in (`stim300.mcaprec`): the bytes as read with
their read times, losslessly (`stim300 decode`, `info` and calibd read the capture it holds),
beside every sample as sensor_msgs/Imu that mcap-ros2-support (not ours) decodes."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from calibd.cli import main as calibd_main
from stim300.cli import main as stim300_main
from stim300.mcaprec import IMU_TOPIC, RAW_TOPIC, McapRecorder, holds_capture, read_capture
from stim300.reads import reads_path

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "heading137_lat60_125hz.bin"  # 0x93 with CR LF, a whole session
SECONDS = 75728 / 125  # its samples at 125 Hz


def record(data: bytes, path: Path, seconds: float, seed: int = 3) -> np.ndarray:
    """`data`, `seconds` of the sensor's stream, fed to a recorder in random reads at the pace the
    port gives them; its read log."""
    rng = np.random.default_rng(seed)
    cuts = np.sort(rng.choice(np.arange(1, len(data)), size=len(data) // 600, replace=False))
    pieces = np.split(np.frombuffer(data, np.uint8), cuts)
    reads = np.zeros(len(pieces), [("end", "<i8"), ("t_host_s", "<f8")])
    with open(path, "wb") as f:
        recorder = McapRecorder(f)
        end = 0
        for k, piece in enumerate(pieces):
            end += len(piece)
            t = (1_000_000_000_000 + round(end / len(data) * seconds * 1e9)) / 1e9  # whole ns, as MCAP keeps times
            reads[k] = (end, t)
            recorder.add(piece.tobytes(), t, 1_790_000_000_000_000_000 + 4_000_000 * k)
        recorder.finish()
    return reads


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The capture recorded to MCAP, and the same bytes as a raw capture with the same read log."""
    folder = tmp_path_factory.mktemp("mcaprec")
    data = CAPTURE.read_bytes()
    reads = record(data, folder / "rec.mcap", SECONDS)
    raw = folder / "raw.bin"
    raw.write_bytes(data)
    np.save(reads_path(raw), reads)
    return folder / "rec.mcap", raw, data, reads


def test_the_mcap_gives_back_the_bytes_and_the_read_log(recorded):
    mcap, _, data, reads = recorded
    assert holds_capture(mcap) and not holds_capture(CAPTURE)
    back, back_reads = read_capture(mcap)
    assert back == data and np.array_equal(back_reads["end"], reads["end"])
    assert np.allclose(back_reads["t_host_s"], reads["t_host_s"], rtol=0, atol=1e-9)


def test_decode_and_info_of_the_mcap_are_those_of_the_capture(recorded, tmp_path, run_main):
    mcap, raw, _, _ = recorded
    for source, name in ((mcap, "a"), (raw, "b")):
        assert run_main(stim300_main, ["decode", source, "-o", tmp_path / f"{name}.npz"])[0] == 0
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    infos = [json.loads(run_main(stim300_main, ["info", source, "--json"])[1]) for source in (mcap, raw)]
    assert infos[0] == infos[1]


@pytest.mark.slow  # 75,728 messages decoded by mcap-ros2-support, one by one
def test_every_sample_is_an_imu_message_in_si(recorded, tmp_path, run_main):
    mcap, raw, _, _ = recorded
    assert run_main(stim300_main, ["decode", raw, "-o", tmp_path / "b.npz"])[0] == 0
    b = np.load(tmp_path / "b.npz")
    with open(mcap, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = sorted(c.topic for c in reader.get_summary().channels.values())
        messages = [(m, ros) for _, _, m, ros in reader.iter_decoded_messages(topics=[IMU_TOPIC])]
    assert topics == sorted([RAW_TOPIC, IMU_TOPIC]) and len(messages) == len(b["counter"])
    gyro = np.array([[r.angular_velocity.x, r.angular_velocity.y, r.angular_velocity.z] for _, r in messages])
    acc = np.array([[r.linear_acceleration.x, r.linear_acceleration.y, r.linear_acceleration.z]
                    for _, r in messages])
    decoded = {c: np.column_stack([b[f"{c}_{a}"] for a in "xyz"]).astype(float) for c in ("gyro", "acc")}
    assert np.allclose(gyro, decoded["gyro"] * (math.pi / 180), rtol=1e-15, atol=0)
    assert np.allclose(acc, decoded["acc"] * 9.80665, rtol=1e-15, atol=0)
    assert [m.sequence for m, _ in messages] == list(range(len(messages)))
    stamps = np.array([r.header.stamp.sec * 10**9 + r.header.stamp.nanosec for _, r in messages])
    assert np.all(np.diff(stamps) > 0) and np.array_equal(stamps, [m.log_time for m, _ in messages])
    step = np.median(np.diff(stamps))
    assert abs(step - 8_000_000) < 1000  # 125 Hz on the sensor's own clock
    assert {r.header.frame_id for _, r in messages} == {"imu_link"}
    assert {tuple(r.angular_velocity_covariance) for _, r in messages} == {(0.0,) * 9}  # not known


@pytest.mark.slow
def test_calibd_calibrates_the_mcap_as_the_capture(recorded, tmp_path, run_main):
    mcap, raw, _, _ = recorded
    docs = []
    for source, name in ((mcap, "a"), (raw, "b")):
        code, _, err = run_main(calibd_main, ["calibrate", source, "--latitude", "60", "-o", tmp_path / f"{name}.json"])
        assert code == 0, err
        docs.append(json.loads((tmp_path / f"{name}.json").read_text()))
    assert docs[0]["estimates"] == docs[1]["estimates"] and docs[0]["session_id"] == docs[1]["session_id"]


def test_a_cut_mcap_recording_is_one_line(recorded, tmp_path, run_main):
    mcap = recorded[0]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[:len(mcap.read_bytes()) // 2])
    code, _, err = run_main(stim300_main, ["info", cut])
    assert code == 2 and err.count("\n") == 1 and "cannot read the MCAP recording" in err
    code, _, err = run_main(calibd_main, ["calibrate", cut, "--latitude", "60", "-o", tmp_path / "r.json"])
    assert code == 2 and err.count("\n") == 1 and "cannot read the MCAP recording" in err


@pytest.mark.slow
def test_replay_takes_the_mcap_as_the_capture(recorded, run_main):
    mcap, raw, _, _ = recorded
    outs = []
    for source in (mcap, raw):
        code, out, err = run_main(calibd_main, ["replay", source, "--latitude", "60", "--speed", "max"])
        assert code == 0, err
        outs.append(out.split("joint: ")[-1].split("\n", 1)[1])  # the summary after its first line (the path)
    assert outs[0] == outs[1] and "yaw" in outs[0]

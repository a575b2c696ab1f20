"""Gaps of whole counter cycles, found from host read times: live in the daemon, offline from the
read log `stim300 record` writes beside a capture."""

import json
import os
import select
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import stim300.port as port
from calibd.methods.joint import joint_real_case
from calibd.captures import load_session
from calibd.config import WarmupConfig
from calibd.daemon import Calibrator, Callbacks
from calibd.frames import Site
from calibd.results import CalibrationResult
from captures import exact_samples
from stim300.bulk import decode_capture
from stim300.cli import main as stim300_main
from stim300.clock import CYCLE_S, CounterClock
from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.port import PortReader
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, Format
from stim300.reads import READS_DTYPE, load_reads, reads_path
from stim300.ringbuffer import RingBuffer
from stim300.special import Configuration, encode_special
from test_clock import host_read_times

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "heading137_lat60_125hz.bin"  # four -90 deg index turns from 300 s, then a full turn
SITE = Site(60.0, 120.0)
RATE_HZ = 125
CUT_AT = int(368.0 * RATE_HZ)  # in the second index turn (365.5 s to 371.0 s)
CUT = 188  # 1.504 s lost: the counter sees 12 datagrams, 11 whole cycles (1.408 s) hidden


def truth() -> dict:
    return json.loads(CAPTURE.with_name(CAPTURE.name + ".truth.json").read_text())["truth"]


def cut_in_a_turn() -> tuple[np.ndarray, np.ndarray]:
    """The capture's samples with CUT datagrams lost mid-turn, stamped as a host reading in bursts
    would see them; and the true times of those kept."""
    samples = decode_capture(CAPTURE.read_bytes()).samples
    keep = np.r_[0:CUT_AT, CUT_AT + CUT:len(samples)]
    true_s = keep / RATE_HZ
    samples = samples[keep]
    samples["t_host"] = host_read_times(true_s, np.random.default_rng(7))
    return samples, true_s


def within_3_sigma(result: CalibrationResult, name: str, value: float) -> bool:
    e = result.estimates[name]
    return abs(e.value - value) < 3 * e.sigma


@pytest.mark.slow
def test_the_daemon_keeps_the_platform_angle_across_a_hidden_gap_in_a_turn():
    samples, _ = cut_in_a_turn()
    results = []
    calibrator = Calibrator(SITE, WarmupConfig(window_s=100.0), listeners=[Callbacks(result=results.append)])
    for start in range(0, len(samples), 25):  # 0.2 s batches, as the live loop drains its ring
        calibrator.feed(samples[start:start + 25], RATE_HZ)
    last = results[-1]
    statics = [s for s in last.segments if s["kind"] == "static"]
    assert [round(s["platform_angle_deg"]) for s in statics] == [0, -90, -180, -270, -360, -720]
    assert within_3_sigma(last, "yaw", truth()["yaw_deg"])
    assert last.stream.hidden_gaps == 1 and last.stream.hidden_gap_s == pytest.approx(11 * CYCLE_S)
    assert any(w.startswith("time base corrected: the host clock shows 1.408 s of data lost in 1 gap ")
               for w in last.warnings)


@pytest.fixture
def capture_with_read_log(tmp_path):
    """The cut capture as bytes, with the read log a recording host would have written."""
    data = CAPTURE.read_bytes()
    decoded = decode_capture(data)
    samples, fmt = decoded.samples, decoded.info.format
    frames = encode_samples(samples, fmt.datagram_id, fmt, fmt.crlf)
    head = data[:len(data) - frames.size]
    assert head + frames.tobytes() == data
    cut, true_s = cut_in_a_turn()
    frames = frames[np.r_[0:CUT_AT, CUT_AT + CUT:len(frames)]]
    ends = len(head) + frames.shape[1] * np.arange(1, len(frames) + 1)
    last_of_read = np.r_[np.diff(cut["t_host"]) > 0, True]  # datagrams sharing a read: its end is the last one's
    reads = np.zeros(last_of_read.sum() + 1, READS_DTYPE)
    reads[0] = (len(head), cut["t_host"][0] - 0.01)
    reads["end"][1:], reads["t_host_s"][1:] = ends[last_of_read], cut["t_host"][last_of_read]
    path = tmp_path / "cut.bin"
    path.write_bytes(head + frames.tobytes())
    np.save(reads_path(path), reads)
    return path, true_s


@pytest.mark.slow
def test_load_session_times_a_capture_from_its_read_log(capture_with_read_log, capsys):
    path, true_s = capture_with_read_log
    session = load_session(str(path))
    np.testing.assert_allclose(session.time_s, true_s, atol=1e-9)
    assert session.stream.hidden_gaps == 1 and session.stream.hidden_gap_s == pytest.approx(1.408)
    result = joint_real_case(session, SITE)
    assert within_3_sigma(result, "yaw", truth()["yaw_deg"])
    assert any(w.startswith("time base corrected") for w in result.warnings)
    assert stim300_main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["hidden_gaps"] == 1 and info["hidden_gap_s"] == pytest.approx(1.408)
    assert info["duration_s"] == pytest.approx(true_s[-1] + 1 / RATE_HZ)


def test_decode_gives_the_read_times_as_a_column(capture_with_read_log, tmp_path, capsys):
    path, _ = capture_with_read_log
    assert stim300_main(["decode", str(path), "-o", str(tmp_path / "with.npz")]) == 0
    table = np.load(tmp_path / "with.npz")
    assert json.loads(str(table["units"]))["t_host_s"] == "s"
    assert np.all(np.diff(table["t_host_s"]) >= 0) and table["t_host_s"][-1] - table["t_host_s"][0] > 600
    reads_path(path).unlink()
    assert stim300_main(["decode", str(path), "-o", str(tmp_path / "without.npz")]) == 0
    assert "t_host_s" not in np.load(tmp_path / "without.npz")


def test_without_a_read_log_the_capture_decodes_on_the_counter_alone(capture_with_read_log, capsys):
    path, true_s = capture_with_read_log
    reads_path(path).unlink()
    session = load_session(str(path))
    assert session.time_s[-1] == pytest.approx(true_s[-1] - 11 * CYCLE_S)
    assert session.stream.hidden_gaps is None  # not zero: nothing could be seen
    assert stim300_main(["info", str(path)]) == 0
    assert "hidden_gaps      - (no read log" in capsys.readouterr().out


def test_a_read_log_that_does_not_end_with_the_capture_is_not_used(capture_with_read_log):
    path, _ = capture_with_read_log
    path.write_bytes(path.read_bytes()[:-1000])  # the capture changed since it was recorded
    assert load_reads(path) is None
    assert load_session(str(path)).stream.hidden_gaps is None


def test_a_read_log_that_is_not_a_regular_file_is_not_read(capture_with_read_log):
    """A FIFO where the read log belongs would block a reader forever: it is passed over."""
    path, _ = capture_with_read_log
    reads_path(path).unlink()
    os.mkfifo(reads_path(path))
    assert load_reads(path) is None


SENT = np.r_[0:150, 166:450]  # datagrams 150..165 lost: one whole counter cycle at 125 Hz, SETTLE_S before the end


def sensor_bytes() -> tuple[bytes, np.ndarray]:
    """A configuration datagram and the frames of the datagrams SENT (a quiet 0xA7 sensor)."""
    config = Configuration.build(sample_rate_hz=RATE_HZ, bit_rate_bps=921600)
    fmt: Format = config.format
    samples = exact_samples(len(SENT), fmt, fmt.datagram_id, np.random.default_rng(3))
    samples["gyro"], samples["acc"], samples["incl"] = 0.0, 0.0, 0.0
    for name in samples.dtype.names:
        if name.startswith("status"):
            samples[name] = 0  # a healthy sensor: no start-up bit, which would read as a restart
    samples["counter"] = (SENT * (INTERNAL_RATE_HZ // RATE_HZ)) % COUNTER_MODULUS
    return encode_special(config, crlf=False), encode_samples(samples, fmt.datagram_id, fmt, crlf=False)


@pytest.fixture
def pty_sensor(pty):
    """A pty whose far end plays a 125 Hz sensor losing SENT's gap: call the returned function
    (once the reader has the port open) to send, on the sample clock, two datagrams a write."""
    master, path = pty
    head, frames = sensor_bytes()

    def send() -> None:
        os.write(master, head)
        t0 = time.monotonic()
        for k in range(0, len(frames), 2):
            time.sleep(max(0.0, t0 + SENT[k] / RATE_HZ - time.monotonic()))
            select.select([], [master], [], 1.0)
            os.write(master, frames[k:k + 2].tobytes())

    return path, send


@pytest.mark.slow
def test_port_reader_times_give_the_live_clock_the_lost_cycle(pty_sensor):
    """The read times the daemon's own port reader stamps on a real pty are evidence enough."""
    path, send = pty_sensor
    ring = RingBuffer(4096, SAMPLE_DTYPE)
    clock, kept, gaps, cursor = CounterClock(), np.zeros(0), 0, 0
    with PortReader(path, ring, request_config=False), ThreadPoolExecutor(1) as pool:
        writer = pool.submit(send)
        while cursor < len(SENT):
            time.sleep(0.2)  # as the live loop drains the ring
            samples, cursor, _ = ring.read_since(cursor)
            if len(samples):
                batch = clock.times(samples["counter"], RATE_HZ, samples["t_host"])
                for at, seconds in batch.moved:  # found SETTLE_S on: what was kept moves, as the daemon's does
                    kept[kept >= at] += seconds
                kept = np.r_[kept, batch.time_s]
                gaps += batch.hidden_gaps
        writer.result(timeout=5.0)
    assert gaps == 1
    np.testing.assert_allclose(kept, SENT / RATE_HZ, atol=1e-9)


@pytest.mark.slow
def test_record_writes_the_read_log_that_load_session_times_the_capture_with(pty_sensor, tmp_path, monkeypatch):
    """`stim300 record` on a pty fed like a sensor at 125 Hz that loses 16 datagrams (one whole
    counter cycle): the capture's read log restores the lost 0.128 s."""
    path, send = pty_sensor
    opened = threading.Event()
    real_open = port.open_serial
    monkeypatch.setattr(port, "open_serial", lambda *a, **k: (real_open(*a, **k), opened.set())[0])

    def sensor() -> None:
        assert opened.wait(5.0)
        send()

    out = tmp_path / "live.bin"
    with ThreadPoolExecutor(1) as pool:
        writer = pool.submit(sensor)
        assert stim300_main(["record", path, "-o", str(out), "--duration", "4.5"]) == 0
        writer.result(timeout=5.0)
    reads = load_reads(out)
    assert reads is not None and reads["end"][-1] == out.stat().st_size
    assert np.all(np.diff(reads["end"]) > 0) and np.all(np.diff(reads["t_host_s"]) >= 0)
    session = load_session(str(out))
    assert session.stream.hidden_gaps == 1 and session.stream.hidden_gap_s == pytest.approx(CYCLE_S)
    np.testing.assert_allclose(session.time_s, SENT / RATE_HZ, atol=1e-9)

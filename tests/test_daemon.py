"""The daemon: its state machine on replayed captures, safe result storage, and `calibd run` as a
subprocess fed through a real pty, stopped by SIGTERM."""

import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import stim300.atomic
from calibd.cli import main as calibd_main
from calibd.methods.joint import joint_real_case
from calibd.captures import load_session
from calibd.config import MethodConfig, WarmupConfig
from calibd.daemon import Calibrator, Callbacks, State
from calibd.frames import Site
from calibd.live import configure_logging, replay, stream_faults
from calibd.results import SCHEMA, CalibrationResult, Estimate
from calibd.statedir import ResultStore
from captures import calibd, plug
from stim300.bulk import decode_capture
from stim300.source import CaptureSource, PtySource

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SITE = Site(40.59129, g0=9.79956)
HEADING137 = FIXTURES / "heading137_lat60_125hz.bin"  # the thesis campaign in 607 s, 300 s level static
SITE_137 = Site(60.0)
NO_TIMER = MethodConfig(resolve_every_s=1e9)  # solves come from the campaign and the end of the data only
SETTLE_AND_MIN_STATIC_S = 1.0 + 5.0  # the segment detector's defaults


def run_replay(name: str, warmup: WarmupConfig = WarmupConfig()):
    states, results = [], []
    listener = Callbacks(state=lambda state, detail: states.append(state), result=results.append)
    calibrator = Calibrator(SITE, warmup, listeners=[listener])
    replay(CaptureSource((FIXTURES / f"{name}.bin").read_bytes()), calibrator)
    changes = [s for k, s in enumerate(states) if k == 0 or s != states[k - 1]]
    return calibrator, changes, results


@pytest.mark.slow
def test_warm_up_then_campaign_gives_a_result_near_the_truth():
    truth = json.loads((FIXTURES / "warmup_then_protocol_125hz.bin.truth.json").read_text())["truth"]
    calibrator, changes, results = run_replay("warmup_then_protocol_125hz", WarmupConfig(window_s=100.0))
    assert changes == [State.WARMING_UP, State.COLLECTING, State.SOLVED]
    last = results[-1].estimates
    assert abs(last["yaw"].value - truth["yaw_deg"]) < 3 * last["yaw"].sigma
    assert abs(last["pitch"].value - truth["pitch_deg"]) < 0.01
    # the solution improves as data arrives: the last yaw sigma is the smallest
    assert last["yaw"].sigma == min(r.estimates["yaw"].sigma for r in results)


@pytest.mark.slow
def test_the_state_progress_and_detail_are_one_record_complete_once_solved():
    """What STATE carries (`progress`) and what `calibd status` prints (the detail) come from one
    record: the same statics and the same missing step at every state, and "complete" once solved."""
    said = []
    calibrator = Calibrator(SITE, WarmupConfig(window_s=100.0), listeners=[Callbacks(
        state=lambda state, detail: said.append((state, detail, calibrator.progress_fields())))])
    replay(CaptureSource((FIXTURES / "warmup_then_protocol_125hz.bin").read_bytes()), calibrator)
    collecting = [(detail, fields) for state, detail, fields in said if "waiting for: " in detail]
    assert collecting
    for detail, fields in collecting:
        statics = int(re.search(r"(\d+) statics? at (\d)/4 index headings", detail).group(1))
        assert (statics, detail.split("waiting for: ")[1]) == (fields["statics"], fields["missing"]), detail
    solved = [(detail, fields) for state, detail, fields in said if state == State.SOLVED]
    assert solved and all(fields["missing"] is None and detail.endswith("; campaign complete")
                          for detail, fields in solved)
    assert f"{solved[-1][1]['statics']} statics at {solved[-1][1]['index_headings']}/4 index headings" in solved[-1][0]


@pytest.mark.parametrize("window_s", [100.0, 600.0])
@pytest.mark.slow
def test_no_session_starts_during_the_steep_part_of_the_warm_up(window_s):
    """The fixture's temperature rises with a 100 s time constant from power-up: whatever the
    window, the session must leave out at least the first three time constants."""
    truth = json.loads((FIXTURES / "warmup_then_protocol_125hz.bin.truth.json").read_text())
    _, _, results = run_replay("warmup_then_protocol_125hz", WarmupConfig(window_s=window_s))
    started = truth["duration_s"] - results[-1].session.duration_s
    assert started >= 3 * truth["warmup"]["time_constant_s"]


def test_sensor_restart_starts_a_new_session():
    calibrator, changes, results = run_replay("faults_125hz")
    assert State.RESTARTED in changes and changes[-1] == State.WARMING_UP and not results


@pytest.mark.slow
def test_a_data_gap_starts_a_new_session_and_keeps_the_warm_up():
    """The platform may turn while the port is gone, so the session restarts when data returns;
    the sensor stayed powered (no restart datagrams), so there is no second warm-up. While
    collecting, the status says what the session has and what it still waits for."""
    samples = decode_capture((FIXTURES / "warmup_then_protocol_125hz.bin").read_bytes()).samples
    events, results = [], []
    calibrator = Calibrator(SITE, WarmupConfig(window_s=100.0),
                            listeners=[Callbacks(state=lambda state, detail: events.append((state, detail)),
                                                 result=results.append)])
    chunks = iter(np.array_split(samples, len(samples) // 125))
    for chunk in chunks:
        calibrator.feed(chunk, 125)
        if calibrator.state == State.COLLECTING:
            break
    for _ in range(90):
        calibrator.feed(next(chunks), 125)
    before = len(events)
    calibrator.data_lost(12.0)
    for chunk in chunks:
        calibrator.feed(chunk, 125)
    after = events[before:]
    assert after[0][0] == State.FAULT and after[1][0] == State.COLLECTING and "gap" in after[1][1]
    assert State.WARMING_UP not in [state for state, _ in after]
    assert calibrator.sessions == 2 and results and results[-1].session.number == 2
    waiting = [d for state, d in events if state == State.COLLECTING and "waiting for:" in d]
    assert waiting and re.match(r"collecting: \d+ s of data, \d+ static(s)? at \d/4 index headings", waiting[0])


@pytest.mark.slow
def test_detection_settings_reach_the_session():
    """A fixed turn threshold above the platform's 20 deg/s: no turn is seen, so no result, and
    the status says so; the same data with the thresholds from the noise solves."""
    from calibd.config import DetectionConfig

    states = []
    calibrator = Calibrator(SITE, WarmupConfig(window_s=100.0), detection=DetectionConfig(turn_threshold_deg_s=25.0),
                            listeners=[Callbacks(state=lambda state, detail: states.append(detail))])
    replay(CaptureSource((FIXTURES / "warmup_then_protocol_125hz.bin").read_bytes()), calibrator)
    assert calibrator.result is None and "0 index turns" in states[-1]
    assert run_replay("warmup_then_protocol_125hz", WarmupConfig(window_s=100.0))[2]


def test_2000_hz_is_stored_block_averaged_at_125_hz():
    data = (FIXTURES / "static_turn_2000hz.bin").read_bytes()
    samples = decode_capture(data).samples
    calibrator = Calibrator(SITE)
    calibrator.feed(samples[:4003], 2000)
    calibrator.feed(samples[4003:8000], 2000)
    stored = calibrator.collector.data.arrays()
    assert calibrator.collector.stored_rate_hz == 125 and len(stored["time_s"]) == 500
    assert stored["gyro"][:, 2].mean() == pytest.approx(np.radians(samples["gyro"][:8000, 2].astype(float)).mean())
    assert np.allclose(np.diff(stored["time_s"]), 1 / 125)


def test_stream_faults_are_reported_as_they_grow():
    from stim300.stream import StreamParser
    parser = StreamParser()
    data = (FIXTURES / "faults_125hz.bin").read_bytes()
    samples = parser.feed(data)
    counts, faults = stream_faults(parser.stats, {}, samples)
    assert faults["crc_errors"] > 0 and faults["lost_samples"] > 0 and faults["skipped_bytes"] > 0
    assert "flagged_datagrams" not in faults  # only START_UP is set in this capture: not a fault
    samples["status_acc"][5] = 0x11  # overload on X
    again, more = stream_faults(parser.stats, counts, samples)
    assert more == {"flagged_datagrams": 1} and again == counts


def small_result(warning: str) -> CalibrationResult:
    return CalibrationResult("joint", {}, {"yaw": Estimate(0.0, None, "deg")}, warnings=(warning,))


def test_a_crash_while_writing_keeps_the_last_good_result(tmp_path, monkeypatch):
    store = ResultStore(tmp_path)
    store.on_result(small_result("n = 1"))

    def crash(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(stim300.atomic.os, "replace", crash)
    store.on_result(small_result("n = 2"))  # the daemon runs on, degraded
    assert "No space left on device" in store.degraded
    assert json.loads((tmp_path / "result.json").read_text())["warnings"] == ["n = 1"]
    assert not [p for p in tmp_path.rglob("*.part")]


@pytest.mark.slow
def test_kill_9_while_writing_leaves_a_readable_result(tmp_path):
    """A writer killed at random moments: result.json is always a whole result, and the
    temporary files the kills orphaned are gone once the store starts again."""
    root = str(Path(__file__).resolve().parents[1])
    script = (f"import sys; sys.path.insert(0, {root!r})\n"
              "from calibd.results import CalibrationResult, Estimate\nfrom calibd.statedir import ResultStore\n"
              "yaw = {'yaw': Estimate(0.0, None, 'deg')}\n"
              f"store = ResultStore({str(tmp_path)!r})\n"
              "n = 0\n"
              "while True:\n"
              "    n += 1\n"
              "    store.on_result(CalibrationResult('joint', {}, yaw, warnings=(str(n),) + ('x' * 1000,) * 200))\n")
    rng = np.random.default_rng(7)
    for _ in range(5):
        writer = subprocess.Popen([sys.executable, "-c", script])
        deadline = time.monotonic() + 20
        while not (tmp_path / "result.json").exists():
            assert time.monotonic() < deadline
            time.sleep(0.01)
        time.sleep(rng.uniform(0.05, 0.3))
        writer.kill()
        writer.wait()
        result = json.loads((tmp_path / "result.json").read_text())
        assert result["schema"] == SCHEMA and len(result["warnings"]) == 201
    (tmp_path / "history" / ".result-x.json.0badf00d.part").write_text("{")  # one orphan at least
    ResultStore(tmp_path)
    assert not [p for p in tmp_path.rglob("*.part")]


@pytest.mark.slow
def test_replay_command_and_status(tmp_path, capsys):
    code = calibd_main(["replay", str(FIXTURES / "warmup_then_protocol_125hz.bin"), "--latitude", "40.59129",
                        "--g0", "9.79956", "--warmup-window", "100", "--state-dir", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0 and "[SOLVED]" in out and "yaw" in out
    site = "site: latitude +40.59129 deg, height 0 m, g0 9.79956 m/s^2 (given)"
    assert site in out and "session: session 1 since the daemon started" in out
    assert len(list((tmp_path / "history").iterdir())) >= 2
    assert calibd_main(["status", "--state-dir", str(tmp_path)]) == 0
    status = capsys.readouterr().out
    assert "state: SOLVED" in status and site in status
    assert calibd_main(["status", "--state-dir", str(tmp_path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["state"]["state"] == "SOLVED"
    assert doc["result"] == json.loads((tmp_path / "result.json").read_text())
    assert calibd_main(["replay", str(FIXTURES / "faults_125hz.bin"), "--latitude", "40"]) == 1


@pytest.mark.slow
def test_replay_through_a_pty_gives_the_direct_replays_result(capsys):
    """--pty: the capture goes through a pseudo-terminal into the daemon's port reader, as fast as
    the daemon keeps up (the writer waits on the ring): no sample lost, the same final solution
    up to where the batches fall."""
    args = [str(FIXTURES / "warmup_then_protocol_125hz.bin"), "--latitude", "40.59129", "--g0", "9.79956",
            "--warmup-window", "100"]
    assert calibd_main(["replay", *args]) == 0
    direct = capsys.readouterr().out
    assert calibd_main(["replay", *args, "--pty"]) == 0
    through_pty = capsys.readouterr().out

    def pitch(out):
        return float(re.search(r"pitch +(-?[\d.]+) \+- ([\d.]+)", out).group(1))
    assert "[COLLECTING]" in through_pty and "[SOLVED]" in through_pty
    assert pitch(through_pty) == pytest.approx(pitch(direct), abs=0.002)


def _write_paced(master: int, data: bytes, bytes_per_s: float, deadline: float) -> None:
    start = time.monotonic()
    for offset in range(0, len(data), 8192):
        time.sleep(max(0.0, start + offset / bytes_per_s - time.monotonic()))
        view = memoryview(data)[offset:offset + 8192]
        while view:
            assert time.monotonic() < deadline, "the daemon stopped reading"
            if select.select([], [master], [], 1.0)[1]:
                os.set_blocking(master, False)  # a pty with less room than the chunk must not block the test
                try:
                    view = view[os.write(master, view):]
                except BlockingIOError:
                    pass
                finally:
                    os.set_blocking(master, True)


def _log_of(daemon) -> str:
    """The end of a daemon's log, for a failing assertion: stopped first, as reading the pipe of a
    running daemon would wait for it forever."""
    if daemon.poll() is None:
        daemon.kill()
    return daemon.stderr.read().decode()[-2000:]


def _wait_for_result(result_file: Path, daemon, deadline: float) -> None:
    while not result_file.exists():
        if time.monotonic() > deadline or daemon.poll() is not None:
            raise AssertionError(f"no result before the deadline, or the daemon ended: {_log_of(daemon)}")
        time.sleep(0.2)


def _calibd_run(config: Path, systemd_env: dict | None = None) -> subprocess.Popen:
    """`calibd run` as systemd starts it: a subprocess, JSON logs on stderr; `systemd_env` the
    variables systemd would set (none from the test's own environment)."""
    return calibd("run", "--config", config, env=systemd_env)


def _stop(daemon: subprocess.Popen, *fds: int) -> None:
    """After a test, pass or fail: the daemon gone, the pty closed."""
    if daemon.poll() is None:
        daemon.kill()
    for fd in fds:
        os.close(fd)


@pytest.mark.slow
def test_calibd_run_through_a_pty_until_sigterm(tmp_path):
    """The daemon as systemd runs it: a subprocess reading a pty through pyserial; the thesis
    capture is written into the pty at 100 times real time; a result appears; SIGTERM stops it."""
    link = tmp_path / "ttySTIM"
    master, slave = plug(link)
    config = tmp_path / "calibd.toml"
    state_dir = tmp_path / "state"
    config.write_text(f'[serial]\nport = "{link}"\n[site]\nlatitude_deg = 40.59129\ng0 = 9.79956\n'
                      f'[output]\nstate_dir = "{state_dir}"\n[method]\nresolve_every_s = 300\n')
    daemon = _calibd_run(config)
    try:
        data = (FIXTURES / "thesis_real_cw_125hz.bin").read_bytes()
        deadline = time.monotonic() + 120
        _write_paced(master, data, 125 * 59 * 100, deadline)  # 100 times real time
        result_file = state_dir / "result.json"
        _wait_for_result(result_file, daemon, deadline)
        time.sleep(1.0)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=20) == 0
    finally:
        _stop(daemon, master, slave)
    result = json.loads(result_file.read_text())
    assert result["method"] == "joint"
    yaw = result["estimates"]["yaw"]
    assert abs(yaw["value"] - -3.036) < 3 * yaw["sigma"]
    assert json.loads((state_dir / "state.json").read_text())["state"] in ("SOLVED", "FAULT")
    log = daemon.stderr.read().decode()
    assert '"event": "solved"' in log and '"event": "stopped"' in log  # JSON lines off a terminal


@pytest.mark.slow
def test_calibd_run_survives_unplug_and_replug(tmp_path):
    """The adapter goes away after the warm-up, in the first static, and 5 s of data are lost:
    the daemon reports the fault, reopens the port when it comes back, and, as the platform angle
    was lost, collects a second session (no second warm-up) that it solves."""
    samples = decode_capture((FIXTURES / "warmup_then_protocol_125hz.bin").read_bytes()).samples
    data = (FIXTURES / "warmup_then_protocol_125hz.bin").read_bytes()
    per_sample = len(data) // len(samples)  # 0x97 datagrams, no garbage in this capture
    link = tmp_path / "ttySTIM"
    master, slave = plug(link)
    state_dir = tmp_path / "state"
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{link}"\n[site]\nlatitude_deg = 40.59129\ng0 = 9.79956\n'
                      f'[output]\nstate_dir = "{state_dir}"\n[warmup]\nwindow_s = 100\n'
                      '[method]\nresolve_every_s = 120\n')
    daemon = _calibd_run(config)
    speed = 100 * 125 * per_sample  # bytes per second at 100 times real time
    deadline = time.monotonic() + 120
    try:
        _write_paced(master, data[:790 * 125 * per_sample], speed, deadline)
        time.sleep(1.0)  # let the daemon read what is in flight
        os.close(master)
        os.close(slave)
        time.sleep(4.0)  # silence beyond calibd's 3 s: a fault
        master, slave = plug(link)
        _write_paced(master, data[795 * 125 * per_sample:], speed, deadline)
        result_file = state_dir / "result.json"
        _wait_for_result(result_file, daemon, deadline)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=20) == 0
    finally:
        _stop(daemon, master, slave)
    events = [json.loads(line) for line in daemon.stderr.read().decode().splitlines() if line.startswith("{")]
    states = [e["state"] for e in events if e["event"] == "state"]
    assert states == ["WARMING_UP", "COLLECTING", "FAULT", "COLLECTING", "SOLVED"]
    assert any(e["event"] == "port_reopened" for e in events)
    result = json.loads(result_file.read_text())
    assert result["session"]["number"] == 2 and result["session"]["duration_s"] < 1066.9 - 795 + 1
    yaw = result["estimates"]["yaw"]
    assert abs(yaw["value"] - -3.036) < 3 * yaw["sigma"]


@pytest.mark.slow
def test_datagrams_the_sensor_flags_are_counted_and_warned_about(tmp_path):
    """An overload on the X accelerometer in ten datagrams of the session: calibrate and the
    daemon both count them, name the flags and warn; START_UP alone is no fault."""
    from stim300.codec import encode_samples

    decoded = decode_capture((FIXTURES / "thesis_real_cw_125hz.bin").read_bytes())
    samples, info = decoded.samples, decoded.info
    samples["status_acc"][20000:20010] = 0x11  # OVERLOAD on X
    samples["status_gyro"][:50] = 0x40  # START_UP only
    capture = tmp_path / "flagged.bin"
    capture.write_bytes(encode_samples(samples, 0xA7, info.format, False).tobytes())
    result = joint_real_case(load_session(str(capture)), SITE)
    assert result.stream.flagged_datagrams == 10 and result.stream.fault_flags == ("X", "OVERLOAD")
    assert any(w.startswith("10 datagrams carry fault flags (X, OVERLOAD)") for w in result.warnings)

    results = []
    calibrator = Calibrator(SITE, WarmupConfig(window_s=10.0), NO_TIMER, [Callbacks(result=results.append)])
    replay(CaptureSource(capture.read_bytes()), calibrator)
    assert results[-1].stream.flagged_datagrams == 10
    assert any("fault flags (X, OVERLOAD)" in w for w in results[-1].warnings)


@pytest.mark.slow
def test_segments_are_logged_once_each_when_final():
    from structlog.testing import capture_logs

    configure_logging()  # info level: other tests (replay) leave warnings only
    truth = json.loads((FIXTURES / "warmup_then_protocol_125hz.bin.truth.json").read_text())
    with capture_logs() as logs:
        run_replay("warmup_then_protocol_125hz", WarmupConfig(window_s=100.0))
    segments = [e for e in logs if e["event"] == "segment"]
    turns = [e for e in segments if e["kind"] == "turn"]
    assert [e["kind"] for e in segments[:4]] == ["static", "turn", "static", "turn"]
    assert len({(e["kind"], e["start_s"]) for e in segments}) == len(segments)  # no segment twice
    commanded = [p["angle_deg"] for p in truth["schedule"] if p["kind"] == "turn"]
    assert [round(e["angle_deg"]) for e in turns] == commanded[:len(turns)]


class CountingCalibrator:
    """What the pump needs of a Calibrator, counting what it is fed."""

    def __init__(self):
        self.samples, self.state, self.sensor, self.restarts = 0, State.STARTING, {}, 0

    def sensor_seen(self, identity, stream=None, trims=()):
        self.sensor = identity

    def feed(self, samples, rate_hz, first=0, restart_datagrams=()):
        self.samples += len(samples)
        self.restarts = len(restart_datagrams)

    def data_lost(self, seconds):
        self.state = State.FAULT

    def finish(self):
        self.finished = True


@pytest.mark.slow
def test_replay_through_a_pty_is_paced_and_complete():
    """--pty --speed 20: a minute of data takes about 3 s (unpaced it takes about 1 s), and every
    datagram arrives, garbage, CRC errors and the restart in this capture notwithstanding."""
    data = (FIXTURES / "faults_125hz.bin").read_bytes()
    decoded = decode_capture(data)
    samples, info = decoded.samples, decoded.info
    duration_s = (len(samples) + info.stats.lost_samples) / 125
    counting = CountingCalibrator()
    started = time.monotonic()
    replay(PtySource(data, speed=20.0), counting)
    elapsed = time.monotonic() - started
    assert counting.samples == len(samples) and counting.restarts == info.stats.restarts == 1
    assert counting.finished and counting.state != State.FAULT  # the writer stopping is no fault
    assert duration_s / 20 * 0.9 < elapsed < duration_s / 20 + 3.0


@pytest.mark.parametrize("source", [CaptureSource, PtySource])
@pytest.mark.slow
def test_a_replay_solves_at_the_end_of_the_data_as_calibrate_does(source):
    """Both replay paths end SOLVED with the whole capture's segments (the full turn and the
    final static) in the last solution, which equals calibrate's on the same data (the capture
    from where the warm-up rule started the session)."""
    calibrator = Calibrator(SITE_137, WarmupConfig(window_s=10.0), NO_TIMER)
    data = HEADING137.read_bytes()
    replay(source(data), calibrator)
    result = calibrator.result
    samples = decode_capture(data).samples
    session_start_s = (len(samples) - 1) / 125 - result.session.duration_s  # no sample lost in this capture
    reference = joint_real_case(load_session(str(HEADING137), session_start_s - 0.004), SITE_137)
    assert calibrator.state == State.SOLVED
    assert [s["kind"] for s in result.segments[-2:]] == ["turn", "static"]
    assert abs(result.segments[-2]["angle_deg"]) > 350

    def spans(r):
        return [(s["kind"], round(s["end_s"] - s["start_s"], 3)) for s in r.segments]
    assert spans(result) == spans(reference)
    for name, e in reference.estimates.items():
        assert abs(result.estimates[name].value - e.value) < 0.02 * e.sigma, name


@pytest.mark.slow
def test_the_replay_of_a_capture_that_needs_no_warm_up_gives_calibrates_result():
    """With a short warm-up window the session loses only the window's seconds: the last
    solution is calibrate's on the whole capture within 0.1 sigma."""
    calibrator = Calibrator(SITE_137, WarmupConfig(window_s=10.0), NO_TIMER)
    replay(CaptureSource(HEADING137.read_bytes()), calibrator)
    reference = joint_real_case(load_session(str(HEADING137)), SITE_137)
    for name, e in reference.estimates.items():
        assert abs(calibrator.result.estimates[name].value - e.value) < 0.1 * e.sigma, name


@pytest.mark.parametrize("method", ["joint", "thesis"])
@pytest.mark.slow
def test_a_complete_campaign_is_solved_once_the_platform_has_settled(method):
    """Fed in 0.2 s batches (as the live loop drains its ring) with no re-solve timer, the
    calibrator solves within the settle time, the minimum static and one batch (plus the
    detector's 0.2 s smoothing) of the end of each turn that completes the method's campaign:
    the joint method after every turn, the thesis method after the full turn only."""
    samples = decode_capture(HEADING137.read_bytes()).samples
    turns = [p for p in json.loads(Path(f"{HEADING137}.truth.json").read_text())["schedule"] if p["kind"] == "turn"]
    batch, now_s, solved_at_s = 25, [0.0], []
    calibrator = Calibrator(SITE_137, WarmupConfig(window_s=10.0), MethodConfig(method, resolve_every_s=1e9),
                            [Callbacks(result=lambda result: solved_at_s.append(now_s[0]))])
    for start in range(0, len(samples), batch):
        now_s[0] = min(start + batch, len(samples)) / 125
        calibrator.feed(samples[start:start + batch], 125)
    completing = turns if method == "joint" else turns[-1:]
    assert len(solved_at_s) == len(completing)  # nothing before the campaign is complete, one solve per turn after
    for turn, solved_s in zip(completing, solved_at_s):
        earliest_s = turn["end_s"] + SETTLE_AND_MIN_STATIC_S
        assert earliest_s - 0.2 <= solved_s <= earliest_s + batch / 125 + 0.2, (turn["end_s"], solved_s)


@pytest.mark.slow
def test_a_restart_marks_the_last_result_stale_before_anything_else():
    """The previous power-up's data are solved to their end, then its result is marked stale at
    once (on_stale, state RESTARTED); the new power-up's warm-up gives no result meanwhile."""
    samples = decode_capture(HEADING137.read_bytes()).samples
    events = []
    calibrator = Calibrator(SITE_137, WarmupConfig(window_s=10.0), NO_TIMER,
                            [Callbacks(result=lambda result: events.append(("result", result)),
                                       stale=lambda result: events.append(("stale", result)),
                                       state=lambda state, detail: events.append((state, detail)))])
    for chunk in np.array_split(samples, 60):
        calibrator.feed(chunk, 125)
    before = len(events)
    calibrator.feed(samples[:2000], 125, len(samples), (len(samples),))  # the stream goes on after a restart
    after = events[before:]
    kinds = [kind for kind, _ in after]
    assert kinds[:4] == [State.SOLVED, "result", "stale", State.RESTARTED]
    assert "result" not in kinds[3:]
    final, stale = after[1][1], after[2][1]
    assert final.session.duration_s > 600  # the whole power-up, the final static included
    assert final.stale is None and stale.estimates == final.estimates
    assert stale.stale.power_up == "previous" and "restarted" in stale.stale.reason
    assert stale.warnings[0].startswith("stale: the sensor restarted")
    assert calibrator.result is stale and "marked stale" in after[3][1]


@pytest.mark.slow
def test_replay_of_two_power_ups_leaves_the_first_ones_result_marked_stale(tmp_path, capsys):
    """A capture of one power-up followed by another (which restarts again): result.json says
    the result belongs to the previous power-up, `calibd status` says so, history keeps it as
    it was made, and replay reports no result for the last power-up."""
    capture = tmp_path / "two_power_ups.bin"
    capture.write_bytes(HEADING137.read_bytes() + (FIXTURES / "faults_125hz.bin").read_bytes())
    state_dir = tmp_path / "state"
    code = calibd_main(["replay", str(capture), "--latitude", "60", "--warmup-window", "10",
                        "--state-dir", str(state_dir)])
    err = capsys.readouterr().err
    assert code == 1 and "no result for the last power-up (the last result is the previous power-up's" in err
    result = json.loads((state_dir / "result.json").read_text())
    assert result["stale"]["power_up"] == "previous" and result["warnings"][0].startswith("stale:")
    history = sorted((state_dir / "history").iterdir())
    original = json.loads(history[-1].read_text())
    assert "stale" not in original and original["estimates"] == result["estimates"]
    assert not any("stale" in json.loads(p.read_text()) for p in history)
    assert calibd_main(["status", "--state-dir", str(state_dir)]) == 0
    status = capsys.readouterr().out
    assert "result: stale since" in status and "from the previous power-up" in status


@pytest.mark.slow
def test_time_spent_solving_is_not_silence(monkeypatch):
    """A feed that holds the loop longer than the no-data limit (a long solve on a loaded
    machine) is not a data fault: silence counts from the end of the last feed."""
    import calibd.live

    class Slow(CountingCalibrator):
        def feed(self, *args):
            super().feed(*args)
            time.sleep(1.2)

    monkeypatch.setattr(calibd.live, "NO_DATA_S", 1.0)
    slow = Slow()
    replay(PtySource((FIXTURES / "faults_125hz.bin").read_bytes()), slow)
    assert slow.samples and slow.finished and slow.state != State.FAULT


def test_a_batch_spanning_a_restart_is_cut_at_the_restart():
    """Every sample of the first power-up reaches its session before the restart is acted on,
    however the bytes fall into batches, so that session ends with all of its data."""
    first = HEADING137.read_bytes()
    fed, cuts_seen = [], []

    class Recorder(Calibrator):
        def _feed_power_up(self, samples, rate_hz):
            fed.append(len(samples))

        def _power_cycled(self):
            cuts_seen.append(sum(fed))

    replay(CaptureSource(first + (FIXTURES / "faults_125hz.bin").read_bytes(), chunk_bytes=1 << 20),
           Recorder(SITE, WarmupConfig(window_s=10.0), NO_TIMER))
    assert cuts_seen[0] == decode_capture(first).info.stats.datagrams


def test_a_restart_seen_only_in_the_start_up_bit_starts_a_new_power_up():
    """The power-up datagrams of a restart can be lost (CRC burst, port reopened); the start-up
    status bit of the new power-up's first samples still tells, once, at the right sample."""
    data = FIXTURES / "faults_125hz.bin"  # a sensor restart at 40 s
    decoded = decode_capture(data.read_bytes())
    samples, restart_at = decoded.samples, decoded.info.stats.restart_datagrams[0]
    states, batch = [], [0]
    calibrator = Calibrator(Site(40.59129), WarmupConfig(window_s=10.0, min_time_s=0.0),
                            listeners=[Callbacks(state=lambda state, detail: states.append((state, batch[0])))])
    for batch[0] in range(0, len(samples), 25):
        calibrator.feed(samples[batch[0]:batch[0] + 25], 125)  # no restart count: only the status bytes say it
    restarts = [start for state, start in states if state == State.RESTARTED]
    assert len(restarts) == 1 and restarts[0] <= restart_at < restarts[0] + 25


def _read_log_until(daemon: subprocess.Popen, log: list[str], event: str, count: int, deadline: float) -> None:
    """Collect the daemon's JSON log lines (stderr) until `event` has appeared `count` times."""
    os.set_blocking(daemon.stderr.fileno(), False)
    while "".join(log).count(f'"event": "{event}"') < count:
        assert time.monotonic() < deadline and daemon.poll() is None, "".join(log)[-2000:]
        if select.select([daemon.stderr], [], [], 0.2)[0]:
            log.append((daemon.stderr.read() or b"").decode())


@pytest.mark.slow
def test_a_broken_configuration_on_sighup_keeps_the_daemon_running(tmp_path):
    """Each way a configuration file can break (syntax, type, unknown key, deleted, a directory,
    not text) is one `reload_failed` line on SIGHUP, and the daemon runs on; a good file reloads."""
    link = tmp_path / "ttySTIM"
    master, slave = plug(link)
    config = tmp_path / "calibd.toml"
    good = (f'[serial]\nport = "{link}"\n[site]\nlatitude_deg = 40.59129\n'
            f'[output]\nstate_dir = "{tmp_path / "state"}"\n[method]\nresolve_every_s = 300\n')
    config.write_text(good)
    breakages = [lambda: config.write_text("[serial\n"),
                 lambda: config.write_text(good.replace("40.59129", '"forty"')),
                 lambda: config.write_text(good.replace("[method]\n", "[method]\nbogus = 1\n")),
                 lambda: config.unlink(),
                 lambda: config.mkdir(),
                 lambda: (config.rmdir(), config.write_bytes(b"\xff\xfe\x00"))]
    daemon, log = _calibd_run(config), []
    deadline = time.monotonic() + 60
    try:
        _read_log_until(daemon, log, "started", 1, deadline)
        for failures, breakage in enumerate(breakages, 1):
            breakage()
            daemon.send_signal(signal.SIGHUP)
            _read_log_until(daemon, log, "reload_failed", failures, deadline)
        config.unlink()
        config.write_text(good)
        daemon.send_signal(signal.SIGHUP)
        _read_log_until(daemon, log, "reloaded", 1, deadline)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=20) == 0
    finally:
        _stop(daemon, master, slave)
    text = "".join(log)
    for reason in ("not valid TOML", "forty", "bogus", "no such configuration file", "is a directory", "not UTF-8"):
        assert reason in text, reason


def test_a_fault_inside_the_estimator_is_an_error_not_a_wait(monkeypatch, tmp_path, capsys):
    """A programming error in the solver (here a numpy broadcasting error) is not mistaken for a
    campaign that lacks something: the daemon says the solve failed and logs the traceback, and
    the command line ends with one line and exit status 1."""
    import calibd.estimators.joint as joint

    def broken(*args, **kwargs):
        raise ValueError("operands could not be broadcast together with shapes (3,) (4,)")

    monkeypatch.setattr(joint, "solve", broken)
    configure_logging()
    samples = decode_capture(HEADING137.read_bytes()).samples
    details = []
    calibrator = Calibrator(Site(60.0), WarmupConfig(window_s=10.0, min_time_s=0.0),
                            listeners=[Callbacks(state=lambda state, detail: details.append(detail))])
    calibrator.feed(samples, 125)
    calibrator.finish()
    assert calibrator.result is None
    assert any(d.startswith("solve failed: ValueError: operands could not be broadcast") for d in details)
    assert not any("waiting for: operands" in d for d in details)
    log = capsys.readouterr().err
    assert '"event": "solve_failed"' in log and "Traceback" in log and "operands could not be broadcast" in log
    code = calibd_main(["calibrate", str(HEADING137), "--latitude", "60", "-o", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1
    assert "internal error: ValueError: operands could not be broadcast" in err and "Traceback" not in err
    assert not (tmp_path / "r.json").exists()


def test_a_replay_logs_the_stream_faults_as_the_daemon_does():
    """The one loop logs each growth of the stream's faults: over the replay they add up to the
    bulk decoder's counts."""
    from structlog.testing import capture_logs

    data = (FIXTURES / "faults_125hz.bin").read_bytes()
    stats = decode_capture(data).info.stats
    with capture_logs() as logs:
        replay(CaptureSource(data, chunk_bytes=20_000), CountingCalibrator())
    faults = [e for e in logs if e["event"] == "stream_faults"]
    assert len(faults) > 1
    for name in ("crc_errors", "lost_samples", "skipped_bytes"):
        assert sum(e.get(name, 0) for e in faults) == getattr(stats, name), name

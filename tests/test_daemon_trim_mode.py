"""The daemon's `[trim] apply = "volatile"`: after a good solve the result's biases are written
into the emulated unit as volatile trims on the port its reader lends (backup, read-back, no
flash save), said in the log, the state's detail and the result; the trim read back in the stream
marks the result stale and starts a new session, whose biases are then near zero. Off by
default; a refusal writes nothing and is logged once; a failure puts the backup back."""

from __future__ import annotations

import json
import signal
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from calibd.client import Client
from calibd.client import Result as ResultMessage
from calibd.config import MethodConfig, ServeConfig, TrimConfig, WarmupConfig, parse_config
from calibd.daemon import Calibrator, Callbacks, Trimmer
from calibd.frames import Site
from calibd.serve.hub import Hub
from calibd.serve.protocol import State as StateMessage
from calibd.results import CalibrationResult, make_result, parse_result, result_json
from calibd.trim import trim_reference
from calibd.units import DEG
from sensor_emulator import SERIAL_NUMBER, SensorEmulator, with_trims
from sensor_emulator import State as UnitState
from stim300.bulk import decode_capture
from stim300.errors import PortError
from stim300.port import PortReader
from stim300.protocol import GYRO_RATE_LSB
from stim300.records import SensorRecord, StreamRecord, TrimRecord
from stim300.ringbuffer import RingBuffer
from stim300.codec import SAMPLE_DTYPE
from stim300.source import PortSource
from stim300.stream import TrimSeen

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
HEADING137 = FIXTURES / "heading137_lat60_125hz.bin"  # the thesis campaign in 607 s: one solve in about 1.5 s
A = TrimRecord((2 ** -6, -2 ** -8, 0.0), (0.0, 2 ** -10, 0.0), (0.0, 0.0, -2 ** -13), 777, 9998)  # whole counts
UNIT = SensorRecord(serial_number=SERIAL_NUMBER, acc_range_g=10)
VOLATILE = TrimConfig(apply="volatile")
DEADLINE_S = 10.0


@pytest.fixture(scope="module")
def samples() -> np.ndarray:
    return decode_capture(HEADING137.read_bytes()).samples


def unit_state() -> UnitState:
    """125 Hz, the capture's datagram, trims A in force."""
    return UnitState(datagram_id=0xA7, sample_rate_code=0, gyro_trim_deg_s=A.gyro_deg_s, acc_trim_g=A.acc_g,
                     incl_trim_g=A.incl_g, trim_reference=A.reference)


@pytest.fixture
def unit(samples):
    emulator = SensorEmulator(unit_state(), samples=samples[5000:10000])
    emulator.start()
    try:
        with PortSource(emulator.path) as source:
            yield emulator, source
    finally:
        emulator.stop()


def result_of(sigma_deg_h: float = 0.5, session_id: str = "session-1") -> CalibrationResult:
    """A daemon's result made under trim A: gyro biases 40, -25, 10 deg/h."""
    biases = {f"gyro_bias_{axis}": (value / 3600 * DEG, sigma_deg_h / 3600 * DEG)
              for axis, value in zip("xyz", (40.0, -25.0, 10.0))}
    return make_result("joint", Site(60.0), biases, [], [], replace(UNIT, trim=A), session_id=session_id,
                       bias_reference="turn-on")


def untouched(emulator: SensorEmulator) -> bool:
    """Never in Service Mode, its trims those it started with."""
    return emulator.entries == 0 and emulator.state == emulator.flash == unit_state()


def test_off_by_default_the_sensor_is_never_written(unit, tmp_path):
    emulator, source = unit
    config = parse_config({"serial": {"port": emulator.path}, "site": {"latitude_deg": 60.0},
                           "output": {"state_dir": str(tmp_path)}}, "calibd.toml")
    assert config.trim == TrimConfig(apply="off", sensors=("gyro",))
    trimmer = Trimmer(config.trim, tmp_path, emulator.path, source.reader.lend)
    result = result_of()
    with capture_logs() as logs:
        assert trimmer(result) == (result, "")
    assert untouched(emulator) and not logs and not list(tmp_path.iterdir())


@pytest.mark.slow  # two joint solves and a trim through the emulator
def test_a_solve_is_trimmed_said_everywhere_and_the_next_session_has_no_bias(unit, samples, tmp_path):
    emulator, source = unit
    trimmer = Trimmer(VOLATILE, tmp_path, emulator.path, source.reader.lend)
    results, stale = [], []
    hub = Hub(ServeConfig(socket=tmp_path / "s.sock"), emulator.path)
    calibrator = Calibrator(Site(60.0), WarmupConfig(window_s=10.0, min_time_s=0.0), MethodConfig(resolve_every_s=1e9),
                            [Callbacks(result=results.append, stale=stale.append), hub], trim=trimmer)
    calibrator.sensor_seen(UNIT, StreamRecord(), (TrimSeen(1, 0, A),))
    try:
        with Client.connect(str(tmp_path / "s.sock")) as client:
            client.watch()
            with capture_logs() as logs:
                calibrator.feed(samples, 125, 0)
            served = _messages(client)
    finally:
        hub.close()
    first = results[0]
    assert any(isinstance(m, StateMessage) and m.state == "SOLVED" and m.detail.startswith("solved on")
               and "; trimmed (volatile): gyro x " in m.detail and m.detail.endswith(" deg/s") for m in served)
    assert [m.result.trimmed for m in served if isinstance(m, ResultMessage)] == [first.trimmed]
    written = emulator.state.gyro_trim_deg_s
    untrimmed = [first.untrimmed(f"gyro_bias_{axis}") / 3600 for axis in "xyz"]
    assert written == pytest.approx(np.negative(untrimmed), abs=GYRO_RATE_LSB)
    assert (emulator.state.acc_trim_g, emulator.state.incl_trim_g) == (A.acc_g, A.incl_g)  # [trim] sensors: gyro
    assert emulator.mode == "normal" and "s" not in emulator.lines and emulator.flash == unit_state()
    assert emulator.saves_left == 9998 and emulator.state.trim_reference == trim_reference(first.session_id)

    record = first.trimmed
    assert record.sensors == ("gyro",) and record.gyro_deg_s == written and record.remaining_saves == 9998
    assert record.reference == trim_reference(first.session_id)
    backup = json.loads(Path(record.backup).read_text())
    assert Path(record.backup).parent == tmp_path and backup["trims"]["gyro_deg_s"] == list(A.gyro_deg_s)
    assert parse_result(result_json(first), "result.json").trimmed == record
    trimmed = [entry for entry in logs if entry["event"] == "trimmed"]
    assert len(trimmed) == 1 and trimmed[0]["offsets"] == {"gyro": list(written)}
    assert trimmed[0]["units"] == {"gyro": "deg/s"}

    # The stream the daemon reads carries the trim read back (T asked at the end of the loan).
    deadline = time.monotonic() + DEADLINE_S
    while not (source.reader.parser.scanner.bias_trims
               and source.reader.parser.scanner.bias_trims[-1].trim.gyro_deg_s == written):
        assert time.monotonic() < deadline, "the new trim never came in the stream"
        source.read(0.05)
    in_stream = source.reader.parser.scanner.bias_trims[-1].trim
    sessions, end = calibrator.sessions, len(samples)
    output_now = with_trims(samples, UnitState(gyro_trim_deg_s=tuple(np.subtract(written, A.gyro_deg_s))),
                            unit_state().format)
    calibrator.sensor_seen(UNIT, StreamRecord(), (TrimSeen(1, 0, A), TrimSeen(2, end, in_stream)))
    calibrator.feed(output_now, 125, end)
    calibrator.finish()
    assert calibrator.trim == in_stream and calibrator.sessions == sessions + 1
    assert len(stale) == 1 and "bias trim offsets in force changed" in stale[0].stale.reason
    assert stale[0].trimmed == record
    second = results[-1]
    assert second is not first and second.sensor.trim == in_stream and second.trimmed is None
    for axis in "xyz":  # what is left is the trim's rounding to one count
        assert abs(second.estimates[f"gyro_bias_{axis}"].value) < GYRO_RATE_LSB * 3600
    assert emulator.entries == 1  # made on the daemon's own trim: not trimmed again


def _messages(client: Client, quiet_s: float = 0.5) -> list:
    """What the socket sends until it has been quiet for `quiet_s`."""
    messages = []
    while (message := client.read(quiet_s)) is not None:
        messages.append(message)
    return messages


def test_a_refused_result_writes_nothing_and_is_logged_once_a_session(unit, tmp_path):
    emulator, source = unit
    trimmer = Trimmer(VOLATILE, tmp_path, emulator.path, source.reader.lend)
    noisy = result_of(sigma_deg_h=6.0)
    with capture_logs() as logs:
        for _ in range(3):
            assert trimmer(noisy) == (noisy, "")
        trimmer(replace(noisy, session_id="session-2"))
    refused = [entry for entry in logs if entry["event"] == "trim_refused"]
    assert [entry["session_id"] for entry in refused] == ["session-1", "session-2"]
    assert "1-sigma 6 deg/h exceeds the datasheet's run-to-run bias 4 deg/h" in refused[0]["reason"]
    assert untouched(emulator) and not list(tmp_path.iterdir())


def test_a_result_of_another_unit_is_refused_once_the_unit_is_read(unit, tmp_path):
    emulator, source = unit
    trimmer = Trimmer(VOLATILE, tmp_path, emulator.path, source.reader.lend)
    other = replace(result_of(), sensor=replace(UNIT, serial_number="N0", trim=A))
    with capture_logs() as logs:
        assert trimmer(other) == (other, "")
    assert [entry["event"] for entry in logs] == ["trim_refused"]
    assert f"the unit on the port is {SERIAL_NUMBER}" in logs[0]["reason"]
    assert untouched(emulator) and not list(tmp_path.iterdir())


def test_a_session_is_trimmed_once_though_it_is_solved_again_before_the_trim_reaches_its_stream(unit, tmp_path):
    """A daemon behind its port solves the trimmed session's last samples after the trim (those read
    while the solve and the trim ran, before the trim read back in the stream ends the session):
    that result is of the output before the trim, which the trim already took its biases from.
    A result of another session under flash's trims (a later power-up) is trimmed again."""
    emulator, source = unit
    trimmer = Trimmer(VOLATILE, tmp_path, emulator.path, source.reader.lend)
    first, later = result_of(), result_of(sigma_deg_h=0.4)
    with capture_logs() as logs:
        trimmed, words = trimmer(first)
        written = emulator.state.gyro_trim_deg_s
        assert trimmer(later) == (later, "")
        assert emulator.entries == 1 and emulator.state.gyro_trim_deg_s == written
        next_power_up = result_of(session_id="session-2")
        emulator.state = unit_state()  # a power-up: flash's trims in force again
        assert trimmer(next_power_up)[0].trimmed is not None
    assert trimmed.trimmed is not None and words.startswith("trimmed (volatile): gyro x ")
    assert [entry["session_id"] for entry in logs if entry["event"] == "trimmed"] == ["session-1", "session-2"]
    assert emulator.entries == 2


def test_a_failure_mid_write_puts_the_backup_back_in_normal_mode(unit, tmp_path):
    emulator, source = unit
    result = result_of()
    emulator.refuse[f"b {trim_reference(result.session_id)},r"] = 3  # after the gyro offsets went in
    trimmer = Trimmer(VOLATILE, tmp_path, emulator.path, source.reader.lend)
    with capture_logs() as logs:
        assert trimmer(result) == (result, "")
    assert emulator.mode == "normal" and emulator.state == emulator.flash == unit_state()
    assert emulator.saves_left == 9998 and "s" not in emulator.lines
    assert any(line.endswith(",g,x") for line in emulator.lines)  # the new offsets had been written
    events = {entry["event"]: entry for entry in logs}
    assert "E003" in events["trim_failed"]["error"] and "no save spent" in events["trim_restored"]["detail"]
    assert "trimmed" not in events and len(list(tmp_path.glob("trim-backup-*.json"))) == 1


def test_a_lent_port_is_not_read_and_refuses_requests(samples):
    """While lent, nothing reaches the parser and `write` refuses; reading goes on after."""
    emulator = SensorEmulator(unit_state(), samples=samples[:2000])
    emulator.start()
    reader = PortReader(emulator.path, RingBuffer(4096, SAMPLE_DTYPE))
    try:
        with reader:
            deadline = time.monotonic() + DEADLINE_S
            while reader.ring.total == 0:
                assert time.monotonic() < deadline

            def use(ser):
                before = reader.ring.total
                assert not reader.write(b"N\r")
                time.sleep(0.3)  # 37 datagrams at 125 Hz
                return before, reader.ring.total, len(ser.read(ser.in_waiting))

            before, during, taken = reader.lend(use)
            assert before == during and taken > 0
            after = reader.ring.total
            while reader.ring.total == after:
                assert time.monotonic() < deadline
        with pytest.raises(PortError, match="port not open"):
            reader.lend(lambda ser: None)
    finally:
        emulator.stop()


def test_failures_are_one_log_line_per_session_with_the_count_said_after(tmp_path, monkeypatch):
    from stim300.errors import PortError

    def lend(use):
        raise PortError("port: unplugged")

    trimmer = Trimmer(TrimConfig(apply="volatile"), tmp_path, "port", lend)
    monkeypatch.setattr(trimmer, "_result_problems", lambda result: [])  # a result the daemon would trim
    first = replace(make_result("joint", Site(40.0), {}, [], [], SensorRecord()), session_id="s1")
    second = replace(first, session_id="s2")
    with capture_logs() as logs:
        for result in (first, first, first, second):
            assert trimmer(result) == (result, "")
    assert [e["event"] for e in logs] == ["trim_failed", "trim_failures_ended", "trim_failed"]
    assert logs[1]["failures"] == 3 and logs[1]["session_id"] == "s1" and logs[2]["session_id"] == "s2"


@pytest.mark.slow  # the whole session through a pty, 32 times faster than the sensor, and a joint solve
def test_calibd_run_trims_the_unit_it_reads(samples, tmp_path):
    """`calibd run` as users run it, on the emulated unit: after the first solve the result's gyro
    biases are written into the unit as volatile trims, said in result.json, backed up in the
    state directory; nothing is saved to flash, and SIGTERM ends the daemon cleanly."""
    from captures import calibd

    emulator = SensorEmulator(unit_state(), samples=samples, burst=40)  # 606 s of 125 Hz data in about 19 s
    emulator.power_cycle()  # the power-up datagrams: the serial number the trim checks
    emulator.start()
    state = tmp_path / "state"
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{emulator.path}"\n[site]\nlatitude_deg = 60.0\n'
                      f'[output]\nstate_dir = "{state}"\n[warmup]\nwindow_s = 30\nmin_time_s = 0\n'
                      f'[method]\nresolve_every_s = 86400\n[trim]\napply = "volatile"\n')
    daemon = calibd("run", "--config", config)
    try:
        deadline = time.monotonic() + 120
        while not ((state / "result.json").exists() and
                   json.loads((state / "result.json").read_text()).get("trimmed")):
            assert daemon.poll() is None, daemon.stderr.read().decode()
            assert time.monotonic() < deadline, "no trimmed result in 120 s"
            time.sleep(0.5)
        result = json.loads((state / "result.json").read_text())
        trimmed = result["trimmed"]
        assert tuple(trimmed["gyro_deg_s"]) == emulator.state.gyro_trim_deg_s != A.gyro_deg_s
        untrimmed = [result["estimates"][f"gyro_bias_{axis}"]["untrimmed"] / 3600 for axis in "xyz"]
        assert trimmed["gyro_deg_s"] == pytest.approx(np.negative(untrimmed), abs=GYRO_RATE_LSB)  # no bias left
        assert emulator.flash == unit_state() and emulator.saves_left == 9998 and emulator.mode == "normal"
        assert [p.name for p in state.glob("trim-backup-*.json")] == [Path(trimmed["backup"]).name]
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=30) == 0
        events = [json.loads(line) for line in daemon.stderr.read().decode().splitlines() if line.startswith("{")]
        said = [(e.get("event"), e.get("session_id"), e.get("timestamp", "")[11:]) for e in events]
        assert [event for event, _, _ in said].count("trimmed") == 1, [s for s in said if s[0] != "segment"]
    finally:
        if daemon.poll() is None:
            daemon.kill()
        emulator.stop()

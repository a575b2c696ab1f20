"""The daemon's state directory under faults: every fault of the directory is ridden out (one
logged error, "degraded" in the status, writes retried, recovery), symlinks are never written
through, orphaned temporary files go at start, a poorer result of the same power-up never
replaces a better one; `calibd status` refuses a bad state.json in one line; and `calibd run`
through a pty keeps systemd's watchdog fed while the sensor is silent, with journald priorities."""

import json
import os
import shutil
import signal
import socket
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
from structlog.testing import capture_logs

import calibd.statedir
from calibd.cli import main as calibd_main
from calibd.daemon import Calibrator, Callbacks, State, StateLog
from calibd.daemon.solver import stale_result
from calibd.live import Watchdog, replay
from calibd.frames import Site
from calibd.results import CalibrationResult, Estimate, ResultStream, SessionRecord, site_record, write_result
from calibd.statedir import ResultStore, StateDirError
from captures import plug
from stim300.bulk import decode_capture
from stim300.source import CaptureSource
from stim300.special import SerialNumber, encode_special
from stim300.records import SensorRecord
from test_daemon import FIXTURES, HEADING137, _calibd_run, _read_log_until, _stop, _write_paced

AS_ROOT = os.geteuid() == 0


def result(yaw_sigma_deg: float = 1.0, duration_s: float = 600.0, poor: bool = False) -> CalibrationResult:
    yaw = Estimate(10.0, yaw_sigma_deg, "deg", "poor" if poor else None)
    estimates = {"yaw": yaw, "pitch": Estimate(0.1, 0.01, "deg")}
    return CalibrationResult("joint", site_record(Site(60.0)), estimates, stream=ResultStream(capture="x"),
                             session=SessionRecord(1, duration_s, "now"))


def kept_sigma(state_dir: Path) -> float:
    return json.loads((state_dir / "result.json").read_text())["estimates"]["yaw"]["sigma"]


def break_by_file(state_dir: Path) -> None:
    shutil.rmtree(state_dir)
    state_dir.write_text("not a directory\n")


def break_result_json(state_dir: Path) -> None:
    (state_dir / "result.json").unlink(missing_ok=True)
    (state_dir / "result.json").mkdir()


def break_read_only(state_dir: Path) -> None:
    state_dir.chmod(0o555)


def break_disk_full(state_dir: Path) -> None:
    pass  # the monkeypatched writer raises ENOSPC


def repair(state_dir: Path) -> None:
    if state_dir.is_file():
        state_dir.unlink()
    elif (state_dir / "result.json").is_dir():
        (state_dir / "result.json").rmdir()
    else:
        state_dir.chmod(0o755)


@pytest.mark.parametrize("breakage, why", [
    (break_by_file, "File exists"),
    (break_result_json, "result.json: a directory"),
    pytest.param(break_read_only, "not writable",
                 marks=pytest.mark.skipif(AS_ROOT, reason="root writes into a read-only directory")),
    (break_disk_full, "No space left on device")])
def test_the_store_rides_out_a_broken_state_dir_and_recovers(tmp_path, monkeypatch, breakage, why):
    """Writes fail without raising: one logged error however many writes, "degraded: ..." in
    the status and in state.json when it can be written; the next write after the repair
    succeeds, logs the recovery and brings result.json up to date."""
    state_dir = tmp_path / "state"
    heard = []
    store = ResultStore(state_dir, on_health=heard.append)
    store.on_result(result(2.0))
    breakage(state_dir)
    real_write = calibd.statedir.write_atomic
    if breakage is break_disk_full:
        def full(path, data, durable=True, follow=True):
            raise OSError(28, "No space left on device", str(path))
        monkeypatch.setattr(calibd.statedir, "write_atomic", full)
    with capture_logs() as logs:
        for sigma in (1.5, 1.0):
            store.on_state(State.SOLVED, "solved")
            store.on_result(result(sigma, duration_s=700.0))
        assert store.degraded.startswith("cannot write results (") and why in store.degraded
        assert len(heard) == 1 and heard[0].startswith("cannot write results (") and why in heard[0]
        if breakage is break_result_json:  # state.json still says why
            assert json.loads((state_dir / "state.json").read_text())["degraded"] == store.degraded
        monkeypatch.setattr(calibd.statedir, "write_atomic", real_write)
        repair(state_dir)
        store.retry()
    events = [e["event"] for e in logs]
    assert events.count("state_dir_error") == 1 and events.count("state_dir_recovered") == 1
    assert [e["log_level"] for e in logs if e["event"] == "state_dir_error"] == ["error"]
    assert store.degraded is None and heard[-1] is None
    assert kept_sigma(state_dir) == 1.0
    assert "degraded" not in json.loads((state_dir / "state.json").read_text())
    assert len(list((state_dir / "history").iterdir())) == 3 - (breakage is break_by_file)  # the first went with it


def test_a_deleted_state_dir_is_made_again(tmp_path):
    state_dir = tmp_path / "state"
    store = ResultStore(state_dir)
    shutil.rmtree(state_dir)
    with capture_logs() as logs:
        store.on_result(result())
    assert kept_sigma(state_dir) == 1.0 and len(list((state_dir / "history").iterdir())) == 1
    assert store.degraded is None and not [e for e in logs if e["event"] == "state_dir_error"]


@pytest.mark.parametrize("name", ["history", "result.json", "state.json"])
def test_symlinks_in_the_state_dir_are_not_written_through(tmp_path, name):
    """A symlink where history/, result.json or state.json belongs: refused at start; made while
    running, a degraded store that never writes where it points."""
    outside = tmp_path / "outside"
    outside.mkdir()
    victim = outside / "victim"
    victim.write_text("keep me\n")
    target = outside if name == "history" else victim
    state_dir = tmp_path / "state"
    state_dir.mkdir()
    (state_dir / name).symlink_to(target)
    with pytest.raises(StateDirError, match=f"{name}.*symlink"):
        ResultStore(state_dir)
    (state_dir / name).unlink()
    store = ResultStore(state_dir)
    store.on_state(State.SOLVED, "solved")
    store.on_result(result())
    if name == "history":
        shutil.rmtree(state_dir / name)
    else:
        (state_dir / name).unlink()
    (state_dir / name).symlink_to(target)
    store.on_state(State.SOLVED, "solved")
    store.on_result(result(0.5))
    assert "symlink" in store.degraded and name in store.degraded
    assert victim.read_text() == "keep me\n" and sorted(p.name for p in outside.iterdir()) == ["victim"]


def test_orphaned_temporary_files_are_removed_at_start(tmp_path):
    """What a writer killed between creating and renaming its temporary file leaves
    (stim300.atomic: ".NAME.XXXXXXXX.part") goes when the store starts; nothing else does."""
    store = ResultStore(tmp_path)
    store.on_result(result())
    orphans = [tmp_path / ".result.json.0123abcd.part", tmp_path / ".state.json.89abcdef.part",
               tmp_path / "history" / ".result-20260101T000000.000000Z.json.00000000.part"]
    for orphan in orphans:
        orphan.write_text("{")
    ResultStore(tmp_path)
    assert not [p for p in tmp_path.rglob("*.part")]
    assert kept_sigma(tmp_path) == 1.0 and len(list((tmp_path / "history").iterdir())) == 1


def test_a_poorer_result_of_the_same_power_up_goes_to_history_only(tmp_path, capsys):
    """A result with a poor estimate, or a shorter session with a larger yaw sigma (the unplug
    storm's newest short session), does not replace result.json's; a longer session does, and so
    does any result of a new power-up (after the old one was marked stale)."""
    store = ResultStore(tmp_path)
    store.on_state(State.SOLVED, "solved")
    store.on_result(result(1.0, 900.0))
    store.on_result(result(0.5, 900.0, poor=True))
    assert kept_sigma(tmp_path) == 1.0
    store.on_result(result(10.8, 129.0))
    assert kept_sigma(tmp_path) == 1.0
    state = json.loads((tmp_path / "state.json").read_text())
    assert "larger than result.json's 1.00 deg" in state["held_back"] and "history/" in state["held_back"]
    assert calibd_main(["status", "--state-dir", str(tmp_path)]) == 0
    assert "held back: the new result's yaw sigma 10.80 deg on 129 s" in capsys.readouterr().out
    store.on_result(result(0.9, 1000.0))
    assert kept_sigma(tmp_path) == 0.9
    assert len(list((tmp_path / "history").iterdir())) == 4
    # a restart: result.json is the kept result marked stale, and the next power-up's replaces it
    store.on_result(result(5.0, 100.0))
    store.on_stale(stale_result(result(5.0, 100.0), "the sensor restarted"))
    stale = json.loads((tmp_path / "result.json").read_text())
    assert stale["estimates"]["yaw"]["sigma"] == 0.9 and stale["warnings"] == ["stale: the sensor restarted"]
    store.on_result(result(5.0, 100.0, poor=True))
    assert kept_sigma(tmp_path) == 5.0


def test_a_stale_result_is_marked_once_and_a_result_without_a_session_counts_as_shorter(tmp_path):
    store = ResultStore(tmp_path)
    store.on_stale(stale_result(result(), "the sensor restarted"))  # nothing kept yet: the one given
    assert json.loads((tmp_path / "result.json").read_text())["warnings"] == ["stale: the sensor restarted"]
    store.on_state(State.SOLVED, "solved")
    store.on_result(result(1.0))
    store.on_result(replace(result(2.0), session=None))  # no session: taken as 0 s long, so shorter
    held_back = json.loads((tmp_path / "state.json").read_text())["held_back"]
    assert kept_sigma(tmp_path) == 1.0 and "on 0 s is larger" in held_back


FIXTURE_UNIT = "N25582405002002"  # the serial number in the fixtures' power-up datagrams
OTHER_UNIT = "N25582405009999"
SWAPPED = f"the sensor on the port is {FIXTURE_UNIT}, the result is of sensor {OTHER_UNIT}"
REQUEST_AT = 100_032  # a datagram boundary in the capture, where a requested serial-number datagram comes


@pytest.mark.parametrize("result_serial, start_byte, requested, why", [
    (OTHER_UNIT, 0, False, SWAPPED),
    (FIXTURE_UNIT, 0, False, None),  # the same unit
    (OTHER_UNIT, 5000, False, None),  # no serial-number datagram: the daemon started after the power-up
    (OTHER_UNIT, 5000, True, SWAPPED),  # its serial number asked for (I, CR written into the raw pty)
    (None, 0, False, None)])  # the result names no sensor
def test_an_earlier_daemons_result_of_another_sensor_is_marked_stale_once(tmp_path, result_serial, start_byte,
                                                                        requested, why):
    """result.json left by an earlier daemon is served until this one solves: when the stream's
    serial-number datagram names another unit, it is marked stale at once and once (every batch
    names the sensor again); an unknown serial number on either side proves nothing."""
    write_result(tmp_path / "result.json", replace(result(), sensor=SensorRecord(serial_number=result_serial)))
    store = ResultStore(tmp_path)
    previous, heard = store.previous(), []
    calibrator = Calibrator(Site(60.0), listeners=[store, Callbacks(stale=heard.append), StateLog()],
                            previous=previous)
    data = HEADING137.read_bytes()  # its first 40 s: warming up, no result of its own
    answer = encode_special(SerialNumber(FIXTURE_UNIT), crlf=False) if requested else b""
    with capture_logs() as logs:
        replay(CaptureSource(data[start_byte:REQUEST_AT] + answer + data[REQUEST_AT:200_000]), calibrator)
    assert [e["reason"] for e in logs if e["event"] == "result_stale"] == ([] if why is None else [why])
    assert calibrator.sensor.serial_number == (FIXTURE_UNIT if start_byte == 0 or requested else None)
    assert calibrator.sessions == 0
    written = json.loads((tmp_path / "result.json").read_text())
    if why is None:
        assert heard == [] and calibrator.result is previous and written.get("stale") is None
        return
    assert [stale.stale.reason for stale in heard] == [why] and calibrator.result is heard[0]
    assert written["stale"]["reason"] == why and written["warnings"][0] == f"stale: {why}"
    assert written["estimates"]["yaw"]["value"] == 10.0  # the result as it was, marked


@pytest.mark.parametrize("content, why", [
    ("{not json", "not JSON"), ("[1, 2]", "a JSON list, not an object"), ('{"state": "SOLVED"}', "detail is missing"),
    ('{"state": "SOLVED", "detail": "x", "updated": "yesterday"}', 'updated is "yesterday", expected a number >= 0'),
    (b"\xff\xfe", "cannot read it"), (None, "cannot read it")])
def test_status_refuses_a_bad_state_file_in_one_line(tmp_path, capsys, content, why):
    state_file = tmp_path / "state.json"
    if content is None:
        state_file.mkdir()
    elif isinstance(content, bytes):
        state_file.write_bytes(content)
    else:
        state_file.write_text(content)
    assert calibd_main(["status", "--state-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert f"{state_file}: not a calibd state file: " in err and why in err


@pytest.mark.parametrize("where", ["file", "proc"])
def test_replay_into_an_unusable_state_dir_is_one_line(tmp_path, capsys, where):
    state_dir = tmp_path / "state"
    if where == "file":
        state_dir.write_text("")
    else:
        state_dir = Path("/proc/calibd-state")
    code = calibd_main(["replay", str(FIXTURES / "faults_125hz.bin"), "--latitude", "40",
                        "--state-dir", str(state_dir)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and f"state directory {state_dir}" in err


def test_the_watchdog_pings_at_half_its_timeout(monkeypatch):
    """WATCHDOG_USEC=1 s: a ping at the first kick, then none before 0.5 s, one at 0.5 s."""
    sent = []
    monkeypatch.setattr("calibd.live.sd_notify", sent.append)
    monkeypatch.setenv("WATCHDOG_USEC", "1000000")
    now = [0.0]
    watchdog = Watchdog(clock=lambda: now[0])
    for now[0] in (0.0, 0.2, 0.4, 0.5, 0.7, 1.0):
        watchdog.kick()
    assert watchdog.interval_s == 0.5 and sent == ["WATCHDOG=1"] * 3
    monkeypatch.delenv("WATCHDOG_USEC")
    Watchdog().kick()  # no watchdog configured: no ping
    assert len(sent) == 3


class Notifications:
    """systemd's notify socket, as the daemon sees it ($NOTIFY_SOCKET), read as systemd does:
    at once, by a thread (the daemon drops messages to a full socket rather than block)."""

    def __init__(self, path: Path):
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, str]] = []
        self._open = True
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while self._open:
            try:
                self.messages.append((time.monotonic(), self.sock.recv(4096).decode()))
            except TimeoutError:
                pass

    def drain(self) -> list[str]:
        """Every message so far; the socket is closed."""
        self._open = False
        self._reader.join()
        self.sock.close()
        return [m for _, m in self.messages]


def _config(tmp_path: Path, link: Path, state_dir: Path, latitude: float = 60.0) -> Path:
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{link}"\n[site]\nlatitude_deg = {latitude}\n'
                      f'[output]\nstate_dir = "{state_dir}"\n[warmup]\nwindow_s = 10\nmin_time_s = 0\n'
                      '[method]\nresolve_every_s = 86400\n')
    return config


@pytest.mark.slow
def test_a_silent_sensor_keeps_the_watchdog_fed_and_is_a_fault_at_warning(tmp_path):
    """No byte ever arrives (the adapter is plugged, the sensor quiet): WATCHDOG=1 still comes at
    half of WATCHDOG_USEC, the state goes to FAULT after 3 s, and under journald each JSON line
    carries its syslog priority: the FAULT at warning (<4>), the start at info (<6>)."""
    link = tmp_path / "ttySTIM"
    master, slave = plug(link)
    notify = Notifications(tmp_path / "notify")
    env = {"NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "1000000", "JOURNAL_STREAM": "8:12345"}
    daemon, log = _calibd_run(_config(tmp_path, link, tmp_path / "state"), env), []
    try:
        _read_log_until(daemon, log, "state", 1, time.monotonic() + 20)
        time.sleep(1.0)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=20) == 0
        log.append(daemon.stderr.read().decode())
    finally:
        _stop(daemon, master, slave)
    messages = notify.drain()
    assert messages[0] == "READY=1" and any(m.startswith("STATUS=fault: no data for") for m in messages)
    pings = [t for t, m in notify.messages if m == "WATCHDOG=1"]
    assert len(pings) >= 6 and max(b - a for a, b in zip(pings, pings[1:])) < 0.9
    lines = "".join(log).splitlines()
    assert all(line[:3] in ("<3>", "<4>", "<6>", "<7>") for line in lines), lines
    fault = [line for line in lines if '"state": "FAULT"' in line]
    assert len(fault) == 1 and fault[0].startswith('<4>{') and '"level": "warning"' in fault[0]
    assert any(line.startswith("<6>") and '"event": "started"' in line for line in lines)


@pytest.mark.parametrize("breakage", ["replaced_by_a_file", "result_json_a_directory", "removed"])
@pytest.mark.slow
def test_calibd_run_rides_out_a_broken_state_dir(tmp_path, breakage):
    """Right after READY=1 the state directory becomes a file, or result.json a directory (what
    a read-only directory does to a daemon not running as root), or the directory is deleted:
    the daemon calibrates on, logs one state_dir_error, says "degraded" in systemd's status;
    once repaired (a deleted directory: at once, made again) the recovery is logged and the
    result written."""
    samples = decode_capture(HEADING137.read_bytes()).samples
    data = HEADING137.read_bytes()
    per_sample = len(data) // len(samples)
    link = tmp_path / "ttySTIM"
    master, slave = plug(link)
    notify = Notifications(tmp_path / "notify")
    state_dir = tmp_path / "state"
    daemon, log = _calibd_run(_config(tmp_path, link, state_dir), {"NOTIFY_SOCKET": str(notify.path)}), []
    deadline = time.monotonic() + 90
    speed = 100 * 125 * per_sample  # 100 times real time
    try:
        _read_log_until(daemon, log, "started", 1, deadline)
        if breakage == "removed":
            shutil.rmtree(state_dir)
        else:
            (break_by_file if breakage == "replaced_by_a_file" else break_result_json)(state_dir)
        def repaired_after_the_error():
            _read_log_until(daemon, log, "state_dir_error", 1, deadline)
            repair(state_dir)
            _read_log_until(daemon, log, "state_dir_recovered", 1, deadline)

        _write_paced(master, data[:100 * 125 * per_sample], speed, deadline)
        if breakage == "replaced_by_a_file":  # state.json is written from the first batch on
            repaired_after_the_error()
        _write_paced(master, data[100 * 125 * per_sample:], speed, deadline)
        if breakage == "result_json_a_directory":  # result.json at the first solve
            repaired_after_the_error()
        _read_log_until(daemon, log, "solved", 1, deadline)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=20) == 0
        log.append(daemon.stderr.read().decode())
    finally:
        _stop(daemon, master, slave)
    text, statuses = "".join(log), [m for m in notify.drain() if m.startswith("STATUS=")]
    assert "Traceback" not in text
    errors = 0 if breakage == "removed" else 1
    assert text.count('"event": "state_dir_error"') == errors
    assert sum("; degraded: cannot write results (" in m for m in statuses) >= errors
    assert "degraded" not in statuses[-1]
    assert json.loads((state_dir / "result.json").read_text())["method"] == "joint"
    assert "degraded" not in json.loads((state_dir / "state.json").read_text())


@pytest.mark.parametrize("problem", ["state_dir", "port"])
def test_calibd_run_ends_before_ready_on_a_problem_found_at_start(tmp_path, problem):
    link = tmp_path / "ttySTIM"
    state_dir = tmp_path / "state"
    if problem == "state_dir":
        master, slave = plug(link)
        state_dir.write_text("")
    else:
        master = slave = None
    notify = Notifications(tmp_path / "notify")
    daemon = _calibd_run(_config(tmp_path, link, state_dir), {"NOTIFY_SOCKET": str(notify.path)})
    try:
        assert daemon.wait(timeout=20) == 1
    finally:
        _stop(daemon, *[fd for fd in (master, slave) if fd is not None])
    err = [line for line in daemon.stderr.read().decode().splitlines() if not line.startswith("{")]
    assert len(err) == 1 and err[0].startswith("calibd: ") and "Traceback" not in err[0]
    assert (str(state_dir) if problem == "state_dir" else str(link)) in err[0]
    assert "READY=1" not in notify.drain()


def test_a_long_outage_holds_only_the_newest_history_entries(tmp_path, monkeypatch):
    """While the state directory stays unusable, the history entries waiting to be written are
    bounded (memory stays bounded over a long outage): the oldest go, with a warning; the
    newest and result.json are written when it comes back."""
    monkeypatch.setattr(calibd.statedir, "MAX_PENDING_HISTORY", 3)
    state_dir = tmp_path / "state"
    store = ResultStore(state_dir)
    break_by_file(state_dir)
    with capture_logs() as logs:
        for sigma in (1.5, 1.4, 1.3, 1.2, 1.0):
            store.on_result(result(sigma, duration_s=700.0))
    assert [e["event"] for e in logs].count("history_dropped") == 2
    repair(state_dir)
    store.retry()
    assert kept_sigma(state_dir) == 1.0 and len(list((state_dir / "history").iterdir())) == 3


def test_status_shows_a_result_of_the_first_version_without_the_fields_it_lacked(tmp_path, capsys):
    """A version 1 result has no g0, height or capture: status shows it with their defaults."""
    doc = result().to_dict() | {"schema": "calibd.result/1", "stream": {}}
    doc["site"] = {"latitude_deg": 60.0}
    (tmp_path / "result.json").write_text(json.dumps(doc))
    (tmp_path / "state.json").write_text(json.dumps({"state": "SOLVED", "detail": "solved", "updated": time.time()}))
    assert calibd_main(["status", "--state-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "\njoint\n  site: latitude +60.00000 deg, height 0 m, g0 9.80665 m/s^2\n" in out

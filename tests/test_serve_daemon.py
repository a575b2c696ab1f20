"""The daemon serving its sensor, end to end: `calibd replay --serve` and `calibd run` as
subprocesses, clients on real sockets and ptys."""

import json
import os
import select
import signal
import socket
import stat
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from calibd.results import write_result
from stim300.bulk import decode_capture

from captures import calibd, command_env, plug
from test_serve_socket import OWN_GROUP, known_result

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"
CAPTURE = FIXTURES / "warmup_then_protocol_125hz.bin"


def connect(path: Path, daemon: subprocess.Popen, timeout_s: float = 60.0) -> socket.socket:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        assert daemon.poll() is None, daemon.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline, "no socket"
        time.sleep(0.02)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.connect(str(path))
    sock.settimeout(30)
    return sock


def lines(sock: socket.socket):
    """Every message until the server closes the connection."""
    buf = b""
    while True:
        chunk = sock.recv(65536)
        if not chunk:
            return
        buf += chunk
        *complete, buf = buf.split(b"\n")
        for line in complete:
            yield json.loads(line)


READERS: dict = {}  # one buffered reader per socket: a second one would lose what the first read ahead


def ask(sock: socket.socket, command: bytes, kind: str) -> dict:
    """Send `command` (may be empty) and read up to the next message of class `kind`."""
    sock.sendall(command)
    reader = READERS.setdefault(sock, sock.makefile("rb"))
    while True:
        message = json.loads(reader.readline())
        if message["class"] == kind:
            return message


@pytest.mark.slow
def test_replay_serve_gives_state_results_and_the_feeds_samples_and_ignores_garbage(tmp_path):
    """A client watching raw samples gets VERSION, the STATE stream, RESULT equal to result.json
    and SAMPLES equal to the decode of the capture; another client's garbage gets ERRORs and
    leaves the result as a replay without clients gives it."""
    sock_path, state_dir = tmp_path / "calibd.sock", tmp_path / "state"
    args = [str(CAPTURE), "--latitude", "40.59129", "--g0", "9.79956", "--warmup-window", "100"]
    daemon = calibd("replay", *args, "--state-dir", str(state_dir), "--socket", str(sock_path), "--speed", "200")
    try:
        watcher = connect(sock_path, daemon)
        watcher.sendall(b'?WATCH={"enable":true,"samples":"raw"};\n')
        rogue = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        rogue.connect(str(sock_path))
        rogue.sendall(b"\x00garbage\n?WATCH={bad json};\n" + b"z" * 200_000 + b"\n?POLL\n")
        messages = list(lines(watcher))
        answers = rogue.makefile("rb").read().decode().splitlines()
        assert daemon.wait(timeout=60) == 0, daemon.stderr.read().decode()[-2000:]
    finally:
        if daemon.poll() is None:
            daemon.kill()
    kinds = [m["class"] for m in messages]
    assert kinds[:2] == ["VERSION", "WATCH"]
    states = [m["state"] for m in messages if m["class"] == "STATE"]
    assert {"WARMING_UP", "COLLECTING", "SOLVED"} <= set(states)
    solved = next(m for m in messages if m["class"] == "STATE" and m["state"] == "SOLVED")
    assert solved["progress"]["warm"] is True and solved["progress"]["session_s"] > 100
    last = [m for m in messages if m["class"] == "STATE" and m["state"] == "SOLVED"][-1]["progress"]
    assert (last["index_headings"], last["index_turns"]) == (4, 4)  # the whole campaign, as offline detection
    results = [m["result"] for m in messages if m["class"] == "RESULT"]
    assert results and results[-1] == json.loads((state_dir / "result.json").read_text())
    truth = decode_capture(CAPTURE.read_bytes()).samples  # no sample lost: a sample's index is its time x 125 Hz
    first, following, received, overflowed = None, None, 0, 0
    for m in messages:  # each batch the capture's samples at its place, the next one after it unless OVERFLOW
        if m["class"] == "OVERFLOW":  # the watcher read too slowly (a loaded host): messages were let go
            following, overflowed = None, overflowed + m["dropped"]
        elif m["class"] == "SAMPLES":
            start = round(m["t"][0] * 125)
            first = start if first is None else first
            assert following is None or start == following
            following = start + len(m["counter"])
            assert np.array_equal(m["counter"], truth["counter"][start:following])
            assert np.array_equal(np.array(m["gyro"], np.float32), truth["gyro"][start:following])
            received += len(m["counter"])
    assert first < 1000 and following == len(truth)  # connected a moment after the data began; to the end
    assert received == len(truth) - first or overflowed
    assert [json.loads(a)["class"] for a in answers] == ["VERSION", "ERROR", "ERROR", "ERROR", "POLL"]
    plain = subprocess.run([sys.executable, "-m", "calibd.cli", "replay", *args], capture_output=True,
                           env=command_env(), text=True)
    pitch = next(line for line in plain.stdout.splitlines() if line.strip().startswith("pitch")).split()[1]
    assert results[-1]["estimates"]["pitch"]["value"] == pytest.approx(float(pitch), abs=0.002)


def _write(master: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        if select.select([], [master], [], 1.0)[1]:
            view = view[os.write(master, view):]


def _config(tmp_path: Path, serve: str) -> Path:
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{tmp_path / "tty"}"\n[site]\nlatitude_deg = 40.59129\n'
                      f'[output]\nstate_dir = "{tmp_path / "state"}"\n[serve]\n{serve}')
    return config


@pytest.mark.slow
def test_run_shows_the_previous_result_and_marks_it_once_the_sensor_restarts(tmp_path):
    """After a daemon restart ?POLL shows result.json as the last daemon left it; when the sensor
    restarts it is marked as the previous power-up's, in POLL, in the group-readable copy and in
    result.json itself;
    SIGHUP keeps the [serve] table in use; SIGTERM removes the socket."""
    (tmp_path / "state").mkdir()
    write_result(tmp_path / "state" / "result.json", known_result())
    sock_path, copy = tmp_path / "calibd.sock", tmp_path / "copy.json"
    master, slave = plug(tmp_path / "tty")
    config = _config(tmp_path, f'socket = "{sock_path}"\nresult_copy = "{copy}"\ngroup = "{OWN_GROUP}"\n')
    daemon = calibd("run", "--config", str(config))
    try:
        sock = connect(sock_path, daemon)
        poll = ask(sock, b"?POLL;\n", "POLL")
        assert poll["result"] == json.loads((tmp_path / "state" / "result.json").read_text())
        assert poll["result"].get("stale") is None
        assert stat.S_IMODE(copy.stat().st_mode) == 0o640 and copy.read_bytes() == \
            (tmp_path / "state" / "result.json").read_bytes()
        ask(sock, b'?WATCH={"enable":true};\n', "WATCH")
        start = CAPTURE.read_bytes()[:40_000]  # the power-up datagrams and a few seconds of data
        _write(master, start)
        time.sleep(0.5)
        _write(master, start)  # the sensor powers up again
        while ask(sock, b"", "STATE")["state"] != "RESTARTED":
            pass
        poll = ask(sock, b"?POLL;\n", "POLL")
        assert poll["result"]["stale"]["power_up"] == "previous"
        assert json.loads(copy.read_text())["stale"]["power_up"] == "previous"
        assert json.loads((tmp_path / "state" / "result.json").read_text())["stale"]["power_up"] == "previous"
        # a new [serve] table: not taken up
        config.write_text(config.read_text() + 'tcp = "127.0.0.1:1"\ntcp_open = true\n')
        daemon.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert ask(sock, b"?VERSION;\n", "VERSION")["proto_major"] == 1  # still served, on the same socket
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=20) == 0
        assert not sock_path.exists()
        READERS.pop(sock).close()
        log = daemon.stderr.read().decode()
        assert "changed, kept as started: [serve]" in log
    finally:
        if daemon.poll() is None:
            daemon.kill()
        os.close(master)
        os.close(slave)


def test_run_refuses_a_socket_path_taken_by_a_file_before_ready(tmp_path):
    taken = tmp_path / "calibd.sock"
    taken.write_text("mine")
    master, slave = plug(tmp_path / "tty")
    try:
        done = subprocess.run([sys.executable, "-m", "calibd.cli", "run", "--config",
                               str(_config(tmp_path, f'socket = "{taken}"\n'))], capture_output=True, text=True,
                              env=command_env(), timeout=30)
    finally:
        os.close(master)
        os.close(slave)
    printed = [line for line in done.stderr.splitlines() if line.startswith("calibd:")]
    assert done.returncode == 1 and len(printed) == 1 and "something else than a socket" in printed[0]
    assert "Traceback" not in done.stderr and '"started"' not in done.stderr and taken.read_text() == "mine"


def test_replay_serve_needs_something_to_serve(tmp_path):
    done = subprocess.run([sys.executable, "-m", "calibd.cli", "replay", str(CAPTURE), "--latitude", "40",
                           "--serve"], capture_output=True, text=True, env=command_env(), timeout=30)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "nothing to serve" in done.stderr


def read_link(link: Path, daemon: subprocess.Popen, limit_s: float = 90.0) -> bytes:
    """What a driver opening the pty at `link` (once the daemon made it) reads until the daemon
    ends; the daemon is killed if it outlives `limit_s`."""
    deadline = time.monotonic() + limit_s
    got = bytearray()
    try:
        while not link.exists():
            assert time.monotonic() < deadline and daemon.poll() is None
            time.sleep(0.01)
        fd = os.open(link, os.O_RDONLY | os.O_NOCTTY)
        tty.setraw(fd)
        while time.monotonic() < deadline:
            if not select.select([fd], [], [], 0.2)[0]:
                if daemon.poll() is not None:
                    break  # the daemon is done and the pty holds nothing more
                continue
            try:
                chunk = os.read(fd, 65536)
            except OSError:  # EIO: the daemon closed its end
                break
            if not chunk:
                break
            got += chunk
        os.close(fd)
    finally:
        if daemon.poll() is None and time.monotonic() >= deadline:
            daemon.kill()
    return bytes(got)


@pytest.mark.slow
def test_replay_serve_raw_pty_carries_the_feed_unchanged(tmp_path):
    link = tmp_path / "raw"
    data = CAPTURE.read_bytes()[:300_000]
    capture = tmp_path / "short.bin"
    capture.write_bytes(data)
    daemon = calibd("replay", str(capture), "--latitude", "40", "--raw-pty", str(link), "--speed", "20")
    got = read_link(link, daemon)
    assert daemon.wait(timeout=30) == 1  # ended: 40 s of a warm-up give no result
    assert len(got) > 0 and got in data  # from when the reader opened it: unchanged, in order


@pytest.mark.slow
def test_replay_serve_corrected_pty_holds_until_a_result_then_subtracts_its_biases(tmp_path):
    """An unchanged driver on the corrected link reads nothing while the power-up has no result,
    then the sensor's datagrams less the result's biases (every datagram: none dropped)."""
    link, state = tmp_path / "corrected", tmp_path / "state"
    daemon = calibd("replay", str(CAPTURE), "--latitude", "40.59129", "--g0", "9.79956", "--warmup-window", "10",
                    "--corrected-pty", str(link), "--speed", "100", "--state-dir", str(state))
    got = read_link(link, daemon)
    assert daemon.wait(timeout=30) == 0
    capture = decode_capture(CAPTURE.read_bytes())
    raw, scales = capture.samples, capture.info.format.scales()
    corrected = decode_capture(got).samples
    assert 0 < len(corrected) < 0.8 * len(raw)  # held through the warm-up and the campaign
    tail = raw[-len(corrected):]
    assert np.array_equal(tail["counter"], corrected["counter"])  # the stream's last datagrams, none lost
    results = [json.loads(path.read_text())["estimates"] for path in sorted((state / "history").glob("*.json"))]
    for block, per_unit, tolerance in (("gyro", 1 / 3600, 0.002), ("acc", 1e-3, 3e-4)):
        biases = np.array([[r[f"{block}_bias_{axis}"]["value"] for axis in "xyz"] for r in results]) * per_unit
        assert np.max(np.abs(biases[-1])) > 5 * tolerance  # a bias the test can tell from none
        difference = tail[block].astype(np.float64) - corrected[block]
        off = np.abs(difference[:, None, :] - biases[None, :, :]).max(axis=2)  # row x result, deg/s or g
        assert np.all(off.min(axis=1) < tolerance), block  # every datagram less the biases of one of the results
        lsb = np.max(scales[block])  # constant within a count between results (one step per new result)
        steps = np.count_nonzero(np.any(np.abs(np.diff(difference, axis=0)) > 1.5 * lsb, axis=1))
        assert steps <= 20, (block, steps)

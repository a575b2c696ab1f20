"""calibd.client, `calibd pipe` and `calibd watch` against a fake server: a real Unix (or TCP)
socket and a thread speaking the socket protocol with calibd.serve.protocol's own encode and
parse_command, as docs/protocol.md describes it."""

from __future__ import annotations

import os
import re
import signal
import socket
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import calibd.client as client_module
from calibd.cli import main as calibd_main
from calibd.client import (Client, ClientError, Device, Error, Fault, Message, Overflow, Poll, Result, Samples,
                           ServerGone, State, VersionError, Watch)
from calibd.frames import Site
from calibd.results import make_result, SessionRecord, StaleRecord
from calibd.serve import protocol
from calibd.serve.protocol import ProtocolError, decode, encode, parse_command
from calibd.units import DEG
from calibd.watchview import WatchView, progress_text, render, value_sigma
from stim300.records import SensorRecord
from captures import calibd

PROGRESS = {"warm": True, "session_s": 312.5, "statics": 3, "headings": 2, "turns": 1,
            "missing": "a turn between two statics"}
STATE = {"class": "STATE", "state": "COLLECTING", "detail": "collecting: 3 statics", "progress": PROGRESS}
RESULT_DOC = make_result("joint", Site(60.0), {"yaw": (137.2 * DEG, 0.0123 * DEG),
                                               "gyro_bias_x": (3e-6, 1e-7), "acc_bias_z": (0.01, None)},
                         [], ["a warning"], SensorRecord(serial_number="N1"), session=SessionRecord(1, 312.5)
                         ).to_dict()
SAMPLES = {"class": "SAMPLES", "corrected": False, "t": [0.0, 0.0005, 0.001], "t_host": [10.0, 10.0, 10.001],
           "counter": [7, 8, 9], "gyro": [[0.1, 0.2, 0.3]] * 3, "acc": [[0.0, 0.0, 1.0]] * 3, "incl": None}
DEVICE = {"class": "DEVICE", "path": "/dev/ttyUSB0", "part_number": "84137-0600-0000", "serial_number": "N25581",
          "datagram_id": "0x93", "rate_hz": 2000, "configuration": None,
          "units": {"gyro": "deg/s", "acc": "g", "incl": "g"}}
FAKE_TOKEN = "t0ken"
FAULT = {"class": "FAULT", "counts": {"crc_errors": 2, "lost_samples": 5}, "increase": {"crc_errors": 1}}


class FakeServer:
    """Accepts one client at a time: greets it, answers its commands, and after a WATCH sends
    `script`; then `then` says what it does: "close" the connection, "hold" it open, or "stream"
    STATE messages until the client goes."""

    def __init__(self, listener: socket.socket, script=(), then="hold", greeting=None, result=RESULT_DOC):
        self.listener, self.script, self.then, self.result = listener, list(script), then, result
        self.greeting = protocol.Version.this() if greeting is None else greeting
        self.sent: list[bytes] = []
        self.commands: list[bytes] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _send(self, conn, message) -> None:
        line = message if isinstance(message, bytes) else encode(message)
        conn.sendall(line)
        self.sent.append(line)

    def _answer(self, line: bytes) -> list:
        try:
            command = parse_command(line)
        except ProtocolError as exc:
            return [protocol.Error(str(exc))]
        if command.name == "WATCH":
            enable = bool((command.args or {}).get("enable", True))
            watch = {"class": "WATCH", "enable": enable, "samples": (command.args or {}).get("samples", "none")}
            return [watch, *(self.script if enable else [])]
        if command.name == "AUTH":
            good = (command.args or {}).get("token") == FAKE_TOKEN
            return [{"class": "AUTH", "authenticated": True} if good else protocol.Error("?AUTH: wrong token")]
        if command.name == "POLL":
            return [{"class": "POLL", "state": {k: STATE[k] for k in ("state", "detail", "progress")},
                     "result": self.result}]
        return [DEVICE if command.name == "DEVICE" else protocol.Version.this()]

    def _serve(self) -> None:
        try:
            conn, _ = self.listener.accept()
        except OSError:
            return
        with conn:
            try:
                self._send(conn, self.greeting)
                buffer = b""
                while True:
                    chunk = conn.recv(4096)
                    if not chunk:
                        return
                    buffer += chunk
                    while b"\n" in buffer:
                        line, buffer = buffer.split(b"\n", 1)
                        self.commands.append(line)
                        watching = line.startswith(b"?WATCH") and b'"enable":true' in line
                        for message in self._answer(line):
                            self._send(conn, message)
                        if watching and self.then == "close":
                            return
                        while watching and self.then == "stream":
                            self._send(conn, STATE)
                            time.sleep(0.002)
            except OSError:
                return  # the client went away

    def stop(self) -> None:
        self.listener.close()
        self.thread.join(5)


def unix_listener(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(path))
    sock.listen(1)
    return sock


@pytest.fixture
def serve(tmp_path):
    """serve(**FakeServer options) -> (socket path, server)."""
    servers = []

    def start(**options):
        path = tmp_path / f"calibd{len(servers)}.sock"
        servers.append(FakeServer(unix_listener(path), **options))
        return str(path), servers[-1]

    yield start
    for server in servers:
        server.stop()


# ---- the client ----------------------------------------------------------------------------

def test_client_reads_every_message_typed(serve):
    script = [STATE, {"class": "RESULT", "result": RESULT_DOC}, FAULT, SAMPLES, {"class": "OVERFLOW", "dropped": 4},
              {"class": "NEWTHING", "x": 1}]
    path, server = serve(script=script)
    with Client.connect(path, timeout_s=5) as client:
        assert client.version.proto_major == 1 and client.version_line == encode(protocol.Version.this())[:-1]
        assert client.watch("raw") == Watch(True, "raw")
        assert server.commands[-1] == b'?WATCH={"enable":true,"samples":"raw"};'
        state, result, fault, samples, overflow, unknown = (client.read(5) for _ in script)
    assert state == State("COLLECTING", "collecting: 3 statics", PROGRESS)
    assert isinstance(result, Result) and result.result.estimates["yaw"].value == pytest.approx(137.2)
    assert result.result.estimates["yaw"].unit == "deg" and result.result.to_dict() == RESULT_DOC
    assert fault == Fault({"crc_errors": 2, "lost_samples": 5}, {"crc_errors": 1})
    assert isinstance(samples, Samples) and not samples.corrected and samples.incl is None
    assert samples.gyro.shape == (3, 3) and samples.acc.shape == (3, 3)
    assert np.array_equal(samples.t, [0.0, 0.0005, 0.001]) and np.array_equal(samples.counter, [7, 8, 9])
    assert samples.gyro[2, 1] == 0.2 and samples.t_host.dtype == np.float64
    assert overflow == Overflow(4)
    assert unknown == Message("NEWTHING", {"class": "NEWTHING", "x": 1})


def test_answers_are_waited_for_and_what_came_before_stays_queued(serve):
    path, _ = serve(script=[STATE, FAULT])
    with Client.connect(path) as client:
        client.command("WATCH", {"enable": True, "samples": "none"})
        poll = client.poll()  # WATCH, STATE and FAULT come first: they wait in the queue
        assert isinstance(poll, Poll) and poll.state.state == "COLLECTING" and poll.state.progress == PROGRESS
        assert poll.result.estimates["gyro_bias_x"].unit == "deg/h"
        assert client.latest_result().to_dict() == RESULT_DOC
        assert client.device() == Device("/dev/ttyUSB0", "84137-0600-0000", "N25581", "0x93", 2000, None,
                                         {"gyro": "deg/s", "acc": "g", "incl": "g"})
        assert [type(client.read(1)) for _ in range(3)] == [Watch, State, Fault]
        assert client.read(0.05) is None  # nothing more: a timeout, not an error
        assert client.unwatch() == Watch(False, "none")


def test_latest_result_is_none_before_the_first(serve):
    path, _ = serve(result=None)
    with Client.connect(path) as client:
        assert client.latest_result() is None


def test_a_refused_command_is_an_error_and_error_messages_are_typed(serve):
    path, server = serve()
    with Client.connect(path) as client:
        client.command("NOPE")
        assert client.read(5) == Error("unknown command ?NOPE (known: ?WATCH, ?POLL, ?DEVICE, ?VERSION, ?AUTH)")
        with pytest.raises(ClientError, match="samples must be one of none, raw, corrected"):
            client.watch("cooked")


def test_server_gone_is_a_one_line_error_naming_the_socket(serve):
    path, _ = serve(script=[STATE], then="close")
    with Client.connect(path) as client:
        client.watch()
        assert isinstance(client.read(5), State)
        with pytest.raises(ServerGone, match=f"^{re.escape(path)}: the server closed the connection"):
            list(client)


@pytest.mark.parametrize("greeting, words", [
    ({"class": "VERSION", "release": "9.0", "proto_major": 2, "proto_minor": 0},
     r"speaks protocol 2\.0, this client 1\.x.*9\.0"),
    ({"class": "STATE", "state": "x"}, "not a calibd server"),
    (b"SSH-2.0-OpenSSH\r\n", "not a calibd server"),
])
def test_another_protocol_is_refused(serve, greeting, words):
    path, _ = serve(greeting=greeting)
    with pytest.raises(VersionError, match=words) as caught:
        Client.connect(path, timeout_s=5)
    assert str(caught.value).startswith(path) and "\n" not in str(caught.value)


def test_connection_failures_name_the_path(tmp_path):
    missing = tmp_path / "none.sock"
    with pytest.raises(ClientError, match=f"^{re.escape(str(missing))}: no such socket"):
        Client.connect(str(missing))
    not_a_socket = tmp_path / "file"
    not_a_socket.write_text("")
    with pytest.raises(ClientError, match=f"^{re.escape(str(not_a_socket))}: connection refused"):
        Client.connect(str(not_a_socket))
    with pytest.raises(ClientError, match="port 70000 is outside"):
        Client.connect("localhost:70000")


@pytest.mark.skipif(os.geteuid() == 0, reason="root connects whatever the socket's mode")
def test_permission_denied_names_the_path(serve):
    path, _ = serve()
    os.chmod(path, 0)
    with pytest.raises(ClientError, match=f"^{re.escape(path)}: permission denied"):
        Client.connect(path)


def test_permission_denied_is_said_even_where_root_would_pass(monkeypatch, tmp_path):
    def refuse(self, address):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr(socket.socket, "connect", refuse)
    with pytest.raises(ClientError, match=f"^{re.escape(str(tmp_path))}/s: permission denied .*stim300"):
        Client.connect(str(tmp_path / "s"))


def test_an_empty_samples_batch_has_empty_arrays():
    samples = client_module.message_of(dict(SAMPLES, t=[], t_host=[], counter=[], gyro=[], acc=[]))
    assert samples.t.shape == (0,) and samples.gyro.shape == (0, 3) and samples.incl is None


def test_a_correction_is_typed_with_its_units_and_watch_says_it():
    new = {"gyro_bias_x": (2.2, "deg/h"), "incl_bias_y": (-0.15, "mg")}
    doc = decode(encode(protocol.Correction.of("best", "s1", 12.0005, None, new)))
    correction = client_module.message_of(doc)
    assert correction == client_module.Correction("best", "s1", 12.0005, None, new)
    line = WatchView("x").update(correction, 0.0)
    assert line == "correction: best result s1 from t = 12.000500 s: gyro_bias_x +2.2 deg/h, incl_bias_y -0.15 mg"


def test_tcp_host_port(tmp_path):
    listener = socket.create_server(("127.0.0.1", 0))
    server = FakeServer(listener)
    try:
        with Client.connect(f"127.0.0.1:{listener.getsockname()[1]}") as client:
            assert client.poll().state.state == "COLLECTING"
    finally:
        server.stop()


def test_a_token_is_sent_first_and_a_refused_one_is_one_line(serve):
    path, server = serve()
    with Client.connect(path, token=FAKE_TOKEN) as client:
        assert client.poll().state.state == "COLLECTING"
    assert server.commands == [b'?AUTH={"token":"t0ken"};', b"?POLL;"]
    path, server = serve()
    with pytest.raises(ClientError, match=r"calibd1\.sock: the server refused the command: \?AUTH: wrong token"):
        Client.connect(path, token="other")


@pytest.mark.parametrize("content, words", [(b"", "is empty"), (b" \n", "is empty"), (b"\xff", "not UTF-8 text"),
                                            (b"x" * 4097, "longer than 4096 bytes: not a token")])
def test_a_token_file_without_a_token_is_one_line(content, words, tmp_path, capsys):
    token = tmp_path / "token"
    token.write_bytes(content)
    assert calibd_main(["pipe", str(tmp_path / "calibd.sock"), "--token-file", str(token)]) == 2
    assert capsys.readouterr().err == f"calibd: {token}: {words}\n"


def test_lines_are_bounded(serve, monkeypatch):
    monkeypatch.setattr(client_module, "MAX_MESSAGE_BYTES", 1000)
    path, _ = serve(script=[b"{" + b" " * 5000])
    with Client.connect(path) as client:
        client.command("WATCH", {"enable": True})
        assert isinstance(client.read(5), Watch)
        with pytest.raises(ProtocolError, match="a line of more than 1000 bytes"):
            client.read(5)


def test_a_garbled_known_message_is_a_one_line_error(serve):
    path, _ = serve(script=[dict(SAMPLES, gyro=[[1, 2]] * 3), {"class": "RESULT", "result": {"schema": "x/1"}}])
    with Client.connect(path) as client:
        client.watch("raw")
        with pytest.raises(ProtocolError, match=r"malformed SAMPLES message: gyro has shape \(3, 2\)"):
            client.read(5)
        with pytest.raises(ProtocolError, match="RESULT: RESULT is 'x/1', not a calibd.result file"):
            client.read(5)


# ---- calibd pipe ---------------------------------------------------------------------------

def test_pipe_prints_every_line_as_sent_then_fails_when_the_server_goes(serve):
    path, server = serve(script=[STATE, SAMPLES, {"class": "RESULT", "result": RESULT_DOC}], then="close")
    process = calibd("pipe", path, "--samples", "raw")
    out, err = process.communicate(timeout=60)
    assert out == b"".join(server.sent)  # VERSION, WATCH and the script, byte for byte
    assert len(out.splitlines()) == 5
    assert server.commands == [b'?WATCH={"enable":true,"samples":"raw"};']
    assert process.returncode == 1 and err.decode() == f"calibd: {path}: the server closed the connection\n"


def test_pipe_stops_after_count(serve):
    path, server = serve(then="stream")
    process = calibd("pipe", path, "-n", "5")
    out, err = process.communicate(timeout=60)
    assert process.returncode == 0, err
    assert out.splitlines() == [line[:-1] for line in server.sent[:5]]
    assert server.commands == [b'?WATCH={"enable":true,"samples":"none"};']


def test_pipe_exits_quietly_when_its_reader_goes_and_on_ctrl_c(serve):
    path, _ = serve(then="stream")
    process = calibd("pipe", path)
    assert process.stdout.readline().startswith(b'{"class":"VERSION"')
    process.stdout.close()  # like `calibd pipe ... | head -1`
    assert process.wait(timeout=60) == 0
    assert process.stderr.read() == b""
    path, _ = serve(then="stream")
    process = calibd("pipe", path)
    assert process.stdout.readline().startswith(b'{"class":"VERSION"')
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 0 and err == b""


def test_pipe_sends_the_token_of_its_token_file_first(serve, tmp_path):
    path, server = serve(then="close")
    token = tmp_path / "token"
    token.write_text(FAKE_TOKEN)
    process = calibd("pipe", path, "--token-file", str(token))
    out, err = process.communicate(timeout=60)
    assert server.commands[:2] == [b'?AUTH={"token":"t0ken"};', b'?WATCH={"enable":true,"samples":"none"};']
    assert b'"class":"AUTH"' not in out and out.count(b"\n") == 2  # VERSION, WATCH
    process = calibd("pipe", path, "--token-file", str(tmp_path / "absent"))
    out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and err.decode().count("\n") == 1 and "absent: no such file" in err.decode()


def test_pipe_without_a_server_is_one_line(tmp_path):
    process = calibd("pipe", str(tmp_path / "calibd.sock"))
    out, err = process.communicate(timeout=60)
    assert process.returncode == 1 and out == b""
    assert err.decode() == f"calibd: {tmp_path / 'calibd.sock'}: no such socket (is calibd serving there? see " \
                           "[serve] socket)\n"


# ---- calibd watch --------------------------------------------------------------------------

def test_value_sigma_rounds_to_the_sigmas_second_digit():
    assert value_sigma(137.23456, 0.0123, "deg") == "137.235 +- 0.012 deg"
    assert value_sigma(12.3456, 2.5, "deg/h") == "12.3 +- 2.5 deg/h"
    assert value_sigma(1234.5, 250.0, "mg") == "1234 +- 250 mg"
    assert value_sigma(0.5, None, "mg") == "0.5000 mg"


def test_progress_says_every_key_with_its_unit():
    assert progress_text(PROGRESS) == ("warm yes, session 312.5 s, statics 3, headings 2, turns 1, "
                                       "missing: a turn between two statics")
    assert progress_text({"rate_deg_s": 10.0, "new_key": "x"}) == "rate 10.0 deg/s, new key x"
    assert progress_text({}) == "-"


def test_progress_says_complete_once_nothing_is_missing():
    """After SOLVED the daemon's record has `missing` null: the words say the campaign is complete."""
    solved = {"warm": True, "statics": 6, "index_headings": 4, "missing": None}
    assert progress_text(solved) == "warm yes, statics 6, index headings 4, campaign complete"
    assert "missing" not in progress_text(solved) and "complete" not in progress_text({"warm": False})


def watched(now_s: float = 100.0, result=RESULT_DOC) -> WatchView:
    view = WatchView("/run/calibd/ttyUSB0/calibd.sock")
    for t, doc in ((0.0, decode(encode(protocol.Version.this()))), (1.0, DEVICE), (2.0, STATE),
                   (40.0, {"class": "RESULT", "result": result}), (50.0, FAULT)):
        view.update(client_module.message_of(doc), t)
    return view


def test_render_shows_state_progress_estimates_with_sigma_and_units():
    screen = "\n".join(render(watched(), 100.0))
    for text in ("calibd watch /run/calibd/ttyUSB0/calibd.sock (calibd ",
                 "device   /dev/ttyUSB0: part 84137-0600-0000, serial N25581, datagram 0x93, 2000 Hz; units gyro deg/s",
                 "state    COLLECTING (for 98 s): collecting: 3 statics",
                 "progress warm yes, session 312.5 s, statics 3, headings 2, turns 1, missing: a turn between two",
                 "result   joint, 312.5 s of data, received 60 s ago",
                 "  yaw          137.200 +- 0.012 deg\n  gyro_bias_x    0.619 +- 0.021 deg/h\n"
                 "  acc_bias_z    1.0197          mg\n",  # aligned as calibd calibrate prints them
                 "warning: a warning",
                 "faults   crc_errors 2 (+1), lost_samples 5"):
        assert text in screen, text
    assert "STALE" not in screen and "\nsamples " not in screen


def test_render_marks_a_stale_result_and_updates_estimates():
    stale = dict(RESULT_DOC, stale={"power_up": "previous", "reason": "sensor restarted", "since": "2026-01-01"})
    view = watched(result=stale)
    screen = render(view, 100.0)
    assert "         STALE: the previous power-up's result (sensor restarted)" in screen
    better = make_result("joint", Site(60.0), {"yaw": (137.25 * DEG, 0.004 * DEG)}, [], [], SensorRecord()).to_dict()
    line = view.update(client_module.message_of({"class": "RESULT", "result": better}), 101.0)
    assert line == "result joint: yaw 137.2500 +- 0.0040 deg"
    screen = render(view, 101.0)
    assert "  yaw  137.2500 +- 0.0040 deg" in screen and not any("STALE" in s for s in screen)


def test_render_measures_the_sample_rate_and_says_overflows():
    view = watched()
    view.update(Watch(True, "raw"), 60.0)
    for k in range(30):  # 0.1 s batches of 200 samples at 2000 Hz
        t = (k * 200 + np.arange(200)) / 2000.0
        view.update(Samples(False, t, t, np.arange(200) % 256, np.zeros((200, 3)), None, None), 60.0 + k / 10)
    view.update(Overflow(7), 64.0)
    screen = render(view, 64.0)
    assert "samples  raw, 2000.0 Hz measured; x, y, z: the last sample and the mean of the last 1 s" in screen
    assert "overflow 7 messages lost by this client (reading too slowly)" in screen


def test_render_shows_the_last_sample_and_the_1_s_mean_of_each_axis_with_units():
    view = watched()
    view.update(Watch(True, "corrected"), 60.0)
    for k in range(30):  # 0.1 s batches at 2000 Hz: gyro X steps from 0 to 0.03 deg/s at 1.5 s
        t = (k * 200 + np.arange(200)) / 2000.0
        gyro = np.tile([0.03 * (k >= 15), -0.5, 0.25], (200, 1))
        gyro[-1, 2] = 0.3 if k == 29 else 0.25  # the last sample stands out on Z
        acc = np.tile([0.0, 0.0, -1.0], (200, 1))
        view.update(Samples(True, t, t, np.arange(200) % 256, gyro, acc, acc * 1.0001), 60.0 + k / 10)
    screen = render(view, 64.0)
    start = screen.index(next(line for line in screen if line.startswith("samples  corrected")))
    # the mean of the last 1 s of stream time (2000 samples): X after its step, Z with 0.05 / 2000 deg/s more
    assert screen[start + 1:start + 7] == [
        "  gyro last   +0.030000   -0.500000   +0.300000 deg/s",
        "       mean   +0.030000   -0.500000   +0.250025 deg/s",
        "  acc  last   +0.000000   +0.000000   -1.000000 g",
        "       mean   +0.000000   +0.000000   -1.000000 g",
        "  incl last   +0.000000   +0.000000   -1.000100 g",
        "       mean   +0.000000   +0.000000   -1.000100 g"]
    line = view.update(Samples(True, t + 10.0, t + 10.0, np.arange(200) % 256, gyro, acc, None), 70.0)
    assert line.startswith("samples: corrected, ") and "; gyro last   +0.030000" in line and " deg/s; acc " in line
    assert "incl" not in line  # a block the datagrams lack is not shown


def test_render_fits_the_terminal_width_without_breaking_words():
    view = watched()
    view.update(client_module.message_of(dict(STATE, progress=dict(PROGRESS, missing=(
        "statics at headings 0, 270 deg after the level static and a full turn (at least 350 deg) after the level "
        "static")))), 60.0)
    whole = render(view, 100.0)
    for width in (40, 60, 80):
        screen = render(view, 100.0, width)
        assert all(len(line) <= width for line in screen), width
        words = {word for line in whole for word in line.split()}
        cut = [word for line in screen for word in line.split() if word not in words]
        assert all(word.endswith("\u2026") for word in cut), cut  # only a word wider than the screen is cut
        assert any(line.startswith("         ") for line in screen)  # wrapped under the text after its label
    assert render(view, 100.0, 200) == whole


def test_stale_result_wording_matches_the_daemon():
    result = make_result("joint", Site(60.0), {"yaw": (0.0, 0.01)}, [], [], SensorRecord())
    stale = replace(result, stale=StaleRecord("previous", "r", "s"))
    view = WatchView("x")
    assert "STALE: the previous power-up's result (r)" in view.update(Result(stale), 0.0)


def test_watch_prints_one_line_per_event_when_not_a_terminal(serve):
    stale = dict(RESULT_DOC, stale={"power_up": "previous", "reason": "sensor restarted", "since": "x"})
    path, server = serve(script=[STATE, FAULT, {"class": "RESULT", "result": stale}], then="close")
    process = calibd("watch", path)
    out, err = process.communicate(timeout=60)
    lines = out.decode().splitlines()
    assert lines[0].startswith("calibd ") and ", protocol 1.3" in lines[0]
    assert lines[1] == "watching: on, samples none"
    assert "state COLLECTING: collecting: 3 statics; progress: warm yes, session 312.5 s" in lines[2]
    assert lines[3] == "faults: crc_errors 2 (+1), lost_samples 5"
    assert lines[4].startswith("result joint, 312.5 s of data: yaw 137.200 +- 0.012 deg, gyro_bias_x ")
    assert lines[4].endswith("; STALE: the previous power-up's result (sensor restarted)")
    assert process.returncode == 1 and err.decode() == f"calibd: {path}: the server closed the connection\n"
    assert server.commands[0] == b'?WATCH={"enable":true,"samples":"none"};'


def test_watch_exits_0_on_ctrl_c(serve):
    path, server = serve(script=[STATE])
    process = calibd("watch", path, "--samples", "corrected")
    seen = [process.stdout.readline() for _ in range(3)]  # calibd ..., watching ..., the next event
    while not any(line.startswith(b"result ") for line in seen):  # the POLL answer: state, then result
        seen.append(process.stdout.readline())
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    out = b"".join(seen) + out
    assert process.returncode == 0 and err == b""
    assert server.commands == [b'?WATCH={"enable":true,"samples":"corrected"};', b"?DEVICE;", b"?POLL;"]
    assert b"device /dev/ttyUSB0: part 84137-0600-0000" in out

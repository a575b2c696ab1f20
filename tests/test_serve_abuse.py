"""Hostile local clients against the daemon's socket server (calibd.serve.sockets through
calibd.serve.hub, real sockets): deep JSON, a fault inside a client's handler, a client that
floods commands and never reads, idle and slow connections, one user taking every slot, TCP
without or with a wrong token, floods of requests. In each case ANOTHER client still gets its
answer within 0.25 s. Also the result copy, which must never be written through a link."""

import json
import os
import re
import select
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from calibd.client import Client as CalibdClient
from calibd.client import ClientError
from calibd.config import ServeConfig
from calibd.daemon import State
from calibd.serve import sockets
from calibd.serve.hub import Hub
from calibd.serve.protocol import MAX_LINE_BYTES
from calibd.serve.sockets import ServeError
from captures import command_env

from test_serve_socket import Client, known_result

ANSWER_S = 0.25  # another client's answer, whatever one client does
TOKEN = "s3cret-token-of-the-stim300-group"
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def serve(tmp_path):
    """A hub serving a socket (and what `keys` add), closed after the test."""
    hubs = []

    def make(**keys) -> Hub:
        hub = Hub(ServeConfig(socket=tmp_path / "calibd.sock", **keys), "/dev/ttySTIM")
        hubs.append(hub)
        return hub
    yield make
    for hub in hubs:
        hub.close()


def connected(path, family=socket.AF_UNIX) -> Client:
    """A client past its VERSION greeting, on the Unix socket at `path` or TCP (host, port)."""
    client = Client.__new__(Client)
    client.sock = socket.socket(family, socket.SOCK_STREAM)
    client.sock.connect(str(path) if family == socket.AF_UNIX else path)
    client.buf = b""
    assert client.message()["class"] == "VERSION"
    return client


def answer_s(client: Client) -> float:
    """How long ?POLL takes to be answered."""
    start = time.monotonic()
    client.send(b"?POLL;\n")
    assert client.until("POLL", timeout_s=5.0)["class"] == "POLL"
    return time.monotonic() - start


def worst_answer_s(client: Client, during: threading.Thread | None = None, polls: int = 10) -> float:
    """The slowest of `polls` ?POLL answers (spread while `during` runs, when given)."""
    worst = 0.0
    for _ in range(polls):
        worst = max(worst, answer_s(client))
        time.sleep(0.02)
        if during is not None and not during.is_alive():
            break
    return worst


def closed(client: Client, timeout_s: float = 5.0) -> list[dict]:
    """The messages the server sent until it closed the connection (AssertionError if it does not)."""
    client.sock.settimeout(timeout_s)
    data = client.buf
    while chunk := client.sock.recv(65536):
        data += chunk
    return [json.loads(line) for line in data.splitlines()]


def token_file(tmp_path: Path, text: str = TOKEN + "\n", mode: int = 0o640) -> Path:
    path = tmp_path / "tcp.token"
    path.write_text(text)
    path.chmod(mode)
    return path


# ---- one line must not stop serving -----------------------------------------------------------

@pytest.mark.parametrize("line", [
    b"?WATCH=" + b"[" * 1000,
    b"?WATCH=" + b"[" * 60_000,
    b'?WATCH={"a":' + b"{" * 5000 + b"}" * 5000 + b"}",
    b'?WATCH={"enable":' + b"9" * 20_000 + b"}",  # an integer json.loads spends its time on, or refuses
    b'?WATCH={"enable":1e999}',
    b'?WATCH={"enable":NaN}',
])
def test_deep_or_huge_json_is_one_error_and_everyone_is_still_served(serve, tmp_path, line):
    hub = serve()
    other, rogue = connected(tmp_path / "calibd.sock"), connected(tmp_path / "calibd.sock")
    rogue.send(line + b";\n?VERSION;\n")
    error = rogue.message()
    assert error["class"] == "ERROR" and "not JSON" in error["message"] and "\n" not in error["message"]
    assert rogue.message()["class"] == "VERSION"  # its connection goes on
    assert answer_s(other) < ANSWER_S and hub.server._thread.is_alive()


def test_a_fault_in_a_clients_handler_closes_that_client_only_logged_once(serve, tmp_path, monkeypatch):
    hub = serve()
    command = sockets.SocketServer._command

    def faulty(self, client, line):
        if b"boom" in line:
            raise RuntimeError("injected")
        command(self, client, line)
    monkeypatch.setattr(sockets.SocketServer, "_command", faulty)
    other = connected(tmp_path / "calibd.sock")
    with capture_logs() as logs:
        for _ in range(3):
            rogue = connected(tmp_path / "calibd.sock")
            rogue.send(b"?POLL;\nboom\n?VERSION;\n")
            assert [m["class"] for m in closed(rogue)] == ["POLL"]  # closed at the fault, nothing after
            assert answer_s(other) < ANSWER_S
    assert hub.server._thread.is_alive()
    assert [entry["event"] for entry in logs].count("serve_client_failed") == 1  # once per episode
    assert len(hub.server._clients) == 1


def test_a_fault_while_sending_closes_that_client_only(serve, tmp_path, monkeypatch):
    hub = serve()
    other, rogue = connected(tmp_path / "calibd.sock"), connected(tmp_path / "calibd.sock")
    rogue.send(b'?WATCH={"enable":true};\n')
    rogue.until("WATCH")
    flush = sockets.SocketServer._flush

    def faulty(self, client):
        if client.watching:
            raise ValueError("injected")
        flush(self, client)
    monkeypatch.setattr(sockets.SocketServer, "_flush", faulty)
    hub.on_state(State.WARMING_UP, "published to the watcher")
    closed(rogue)
    assert answer_s(other) < ANSWER_S and hub.server._thread.is_alive()


# ---- clients that do not read ------------------------------------------------------------------

def test_a_client_flooding_polls_without_reading_delays_nobody(serve, tmp_path):
    hub = serve()
    hub.on_result(known_result())  # POLL answers carry the result document: a few KB each
    other, rogue = connected(tmp_path / "calibd.sock"), connected(tmp_path / "calibd.sock")
    rogue.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)

    def flood():
        try:
            rogue.sock.settimeout(10)
            rogue.sock.sendall(b"?POLL;\n" * 200_000)
        except OSError:  # the server stopped reading it (its answers fill its queue), then it was closed
            pass
    flooding = threading.Thread(target=flood)
    flooding.start()
    worst = worst_answer_s(other, polls=25)
    assert worst < ANSWER_S, f"{worst * 1000:.0f} ms"
    (queued,) = [c for c in hub.server._clients.values() if c.queue]
    assert queued.queue.bytes <= sockets.QUEUE_BYTES
    rogue.sock.shutdown(socket.SHUT_RDWR)  # wakes its blocked sendall
    flooding.join(timeout=15)
    assert not flooding.is_alive()


def test_a_full_queue_of_other_messages_costs_what_it_drops(serve, tmp_path, monkeypatch):
    """The published messages to a watcher that never reads: its queue full of STATEs, each new
    one drops the oldest without going through the queue."""
    hub = serve()
    other, rogue = connected(tmp_path / "calibd.sock"), connected(tmp_path / "calibd.sock")
    rogue.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    rogue.send(b'?WATCH={"enable":true};\n')
    rogue.until("WATCH")
    detail = "x" * 200
    for k in range(30_000):  # about 9 MB: the queue holds 1 MiB of them
        hub.server.publish({"class": "STATE", "state": "COLLECTING", "detail": f"{k} {detail}", "progress": {}})
    worst = worst_answer_s(other, polls=10)
    assert worst < ANSWER_S, f"{worst * 1000:.0f} ms"
    (queued,) = [c for c in hub.server._clients.values() if c.watching]
    assert queued.queue.bytes <= sockets.QUEUE_BYTES and hub.server.overflows > 20_000
    received = []  # what the socket held, then OVERFLOW, then what the queue kept
    while not any(m["class"] == "OVERFLOW" for m in received[:-3]):
        received.append(rogue.message())
    overflow = next(m for m in received if m["class"] == "OVERFLOW")
    later = [int(m["detail"].split()[0]) for m in received[received.index(overflow) + 1:]]
    assert overflow["dropped"] > 20_000 and later == sorted(later)  # in order, the oldest lost


# ---- idle and slow connections, slots --------------------------------------------------------

def test_slow_clients_holding_every_slot_are_closed_when_idle(serve, tmp_path, monkeypatch):
    """64 clients sending 1 byte a second and never a newline: the 65th is refused (logged once
    for all its tries, with their count once they stop), after idle_timeout_s each slow client
    is told and closed and another client is served."""
    monkeypatch.setattr(sockets, "EPISODE_QUIET_S", 0.3)
    hub = serve(idle_timeout_s=1.0, max_clients_per_uid=sockets.MAX_CLIENTS)
    path = tmp_path / "calibd.sock"
    with capture_logs() as logs:
        slow = [connected(path) for _ in range(sockets.MAX_CLIENTS)]
        stop = threading.Event()

        def trickle():
            while not stop.is_set():
                for client in slow:
                    try:
                        client.sock.send(b"?")
                    except OSError:
                        pass
                stop.wait(1.0)
        trickling = threading.Thread(target=trickle)
        trickling.start()
        try:
            for _ in range(5):
                refused = Client(path)
                assert "too many clients" in refused.message()["message"]
                assert closed(refused) == []
            deadline = time.monotonic() + 10
            while hub.server._clients and time.monotonic() < deadline:  # idle_timeout_s and a cut
                time.sleep(0.05)
            start = time.monotonic()
            other = Client(path)
            assert other.message()["class"] == "VERSION" and time.monotonic() - start < ANSWER_S
            assert answer_s(other) < ANSWER_S
            for client in slow:
                told = closed(client)
                assert len(told) == 1 and "closed: idle for 1 s" in told[0]["message"]
        finally:
            stop.set()
            trickling.join()
        time.sleep(0.5)  # the refusals' episode ends
    refusals = [e for e in logs if e["event"] == "clients_refused"]
    assert len(refusals) == 1 and "too many clients" in refusals[0]["why"]
    assert {"event": "serve_episode_ended", "kind": "refused: too many clients (at most 64)", "count": 5,
            "log_level": "info"} in logs
    assert [e["event"] for e in logs].count("clients_closed") == 1


def test_a_watcher_that_reads_is_never_idle_and_one_that_polls_is_not_either(serve, tmp_path):
    hub = serve(idle_timeout_s=0.5)
    watcher, poller, idle = (connected(tmp_path / "calibd.sock") for _ in range(3))
    watcher.send(b'?WATCH={"enable":true};\n')
    watcher.until("WATCH")
    for k in range(8):
        time.sleep(0.1)
        answer_s(poller)
        if k % 4 == 0:
            hub.on_state(State.WARMING_UP, f"state {k}")
    assert watcher.until("STATE")["detail"] == "state 0"
    answer_s(watcher)
    told = closed(idle)
    assert len(told) == 1 and "closed: idle" in told[0]["message"]


def test_one_user_cannot_take_every_slot(serve, tmp_path):
    """max_clients_per_uid connections per uid on the Unix socket (SO_PEERCRED); TCP clients count
    as one more user, so they are still served."""
    hub = serve(tcp=("127.0.0.1", 0), tcp_open=True, max_clients_per_uid=3)
    path = tmp_path / "calibd.sock"
    mine = [connected(path) for _ in range(3)]
    with capture_logs() as logs:
        for _ in range(4):
            refused = Client(path)
            error = refused.message()
            assert error["class"] == "ERROR" and error["message"] == (
                f"too many connections of uid {os.getuid()} (at most 3)")
            assert closed(refused) == []
    assert [e["event"] for e in logs].count("clients_refused") == 1
    start = time.monotonic()
    other = connected(hub.server.tcp_address, socket.AF_INET)
    assert time.monotonic() - start < ANSWER_S and answer_s(other) < ANSWER_S
    mine[0].close()
    time.sleep(0.1)
    assert answer_s(connected(path)) < ANSWER_S  # a slot of the user's own again


SYSTEM_PYTHON = "/usr/bin/python3"  # one that uid 65534 may run (a virtualenv under /root may not be)


@pytest.mark.skipif(os.geteuid() != 0 or not os.access(SYSTEM_PYTHON, os.X_OK),
                    reason="another uid takes root (and a python it may run)")
def test_another_user_is_served_while_one_user_has_its_limit(tmp_path):
    """As root: the limit counts per uid, so a client of uid 65534 still gets in."""
    folder = Path(tempfile.mkdtemp())
    try:
        folder.chmod(0o755)
        hub = Hub(ServeConfig(socket=folder / "calibd.sock", max_clients_per_uid=2), "port")
        (folder / "calibd.sock").chmod(0o666)
        mine = [connected(folder / "calibd.sock") for _ in range(2)]
        assert "too many connections" in Client(folder / "calibd.sock").message()["message"]
        script = ("import socket, sys, time; s = socket.socket(socket.AF_UNIX); s.connect(sys.argv[1]); "
                  "f = s.makefile('rb'); f.readline(); t = time.monotonic(); s.sendall(b'?POLL;\\n'); "
                  "line = f.readline(); print(line[:20].decode(), time.monotonic() - t)")
        done = subprocess.run([SYSTEM_PYTHON, "-c", script, str(folder / "calibd.sock")], user=65534, cwd="/",
                              capture_output=True, text=True, timeout=30)
        assert done.stdout.startswith('{"class":"POLL"'), done.stderr
        assert float(done.stdout.split()[-1]) < ANSWER_S
        hub.close()
        assert mine
    finally:
        subprocess.run(["rm", "-rf", str(folder)], check=False)


# ---- TCP -----------------------------------------------------------------------------------------

@pytest.fixture
def tcp_hub(serve, tmp_path):
    return serve(tcp=("127.0.0.1", 0), tcp_token_file=token_file(tmp_path), idle_timeout_s=0.5)


def test_tcp_without_a_token_gets_errors_and_is_closed_after_three(tcp_hub, tmp_path):
    other = connected(tmp_path / "calibd.sock")
    rogue = connected(tcp_hub.server.tcp_address, socket.AF_INET)
    rogue.send(b'?WATCH={"enable":true};\n?POLL;\n?DEVICE;\n?POLL;\n')
    told = closed(rogue)
    assert [m["class"] for m in told] == ["ERROR"] * 3
    assert "authenticate first" in told[0]["message"] and "closed after 3 tries" in told[2]["message"]
    assert answer_s(other) < ANSWER_S


def test_tcp_with_a_wrong_token_is_closed_after_three(tcp_hub, tmp_path):
    other = connected(tmp_path / "calibd.sock")
    rogue = connected(tcp_hub.server.tcp_address, socket.AF_INET)
    with capture_logs() as logs:
        for guess in ("guess", TOKEN + "x", TOKEN[:-1]):
            rogue.send(b'?AUTH={"token":"%s"};\n' % guess.encode())
        told = closed(rogue)
    assert [m["message"] for m in told][:2] == ["?AUTH: wrong token (2 of 3 tries left)",
                                                "?AUTH: wrong token (1 of 3 tries left)"]
    assert len(told) == 3 and "closed after 3 tries" in told[2]["message"]
    assert [e["event"] for e in logs] == ["clients_closed"]
    assert answer_s(other) < ANSWER_S
    with pytest.raises(ClientError, match="wrong token"):
        CalibdClient.connect("%s:%d" % tcp_hub.server.tcp_address, token="nope")


def test_tcp_with_the_token_is_served_and_one_that_never_authenticates_is_closed(tcp_hub, tmp_path):
    where = "%s:%d" % tcp_hub.server.tcp_address
    silent = connected(tcp_hub.server.tcp_address, socket.AF_INET)
    with CalibdClient.connect(where, token=(tmp_path / "tcp.token").read_text().strip()) as client:
        assert client.poll().state.state == "STARTING"
        assert client.watch("none").enable
        time.sleep(0.7)  # beyond idle_timeout_s: a watcher that reads stays
        assert client.poll().result is None
    told = closed(silent)
    assert len(told) == 1 and told[0]["message"] == "closed: no ?AUTH within 0.5 s"
    raw = connected(tcp_hub.server.tcp_address, socket.AF_INET)
    raw.send(b'?AUTH={"token":"%s"};\n?AUTH={"token":"again"};\n' % TOKEN.encode())
    assert raw.message() == {"class": "AUTH", "authenticated": True}
    assert "needs no token" in raw.message()["message"]
    assert answer_s(raw) < ANSWER_S


@pytest.mark.parametrize("make, words", [
    (lambda p: None, "no such file"),
    (lambda p: (p.with_name("real").write_text(TOKEN), os.chmod(p.with_name("real"), 0o600),
                p.symlink_to(p.with_name("real"))), "symbolic link"),
    (lambda p: p.mkdir(), "not a regular file"),
    (lambda p: os.mkfifo(p, 0o600), "not a regular file"),
    (lambda p: (p.write_text("  \n"), p.chmod(0o600)), "is empty"),
    (lambda p: (p.write_text(TOKEN), p.chmod(0o644)), "other users may read or write it (mode 0644)"),
    (lambda p: (p.write_text("x" * 5000), p.chmod(0o600)), "longer than 4096 bytes"),
])
def test_a_token_file_that_is_no_secret_is_refused_at_start(tmp_path, make, words):
    token = tmp_path / "tcp.token"
    make(token)
    config = ServeConfig(socket=tmp_path / "calibd.sock", tcp=("127.0.0.1", 0), tcp_token_file=token)
    with pytest.raises(ServeError, match=re.escape(words)) as caught:
        Hub(config, "port")
    assert "\n" not in str(caught.value) and str(caught.value).startswith(f"tcp_token_file {token}: ")
    assert not (tmp_path / "calibd.sock").exists()


def test_tcp_is_a_decision_even_without_the_configuration_file(tmp_path):
    with pytest.raises(ServeError, match="needs tcp_token_file or tcp_open"):
        Hub(ServeConfig(tcp=("127.0.0.1", 0)), "port")


def test_serving_refuses_a_world_readable_token_file_at_start(tmp_path):
    """`calibd replay --serve`, as users run it: one line, exit status 1, before anything is served."""
    token = token_file(tmp_path, mode=0o644)
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{tmp_path / "tty"}"\n[site]\nlatitude_deg = 40\n[output]\n'
                      f'state_dir = "{tmp_path / "state"}"\n[serve]\nsocket = "{tmp_path / "s.sock"}"\n'
                      f'tcp = "127.0.0.1:29500"\ntcp_token_file = "{token}"\n')
    capture = ROOT / "fixtures" / "heading137_lat60_125hz.bin"
    done = subprocess.run([sys.executable, "-m", "calibd.cli", "replay", str(capture), "--latitude", "60",
                           "--config", str(config), "--serve"], capture_output=True, text=True,
                          env=command_env(), timeout=60)
    printed = [line for line in done.stderr.splitlines() if line.startswith("calibd:")]
    assert done.returncode == 1 and len(printed) == 1 and "other users may read or write it" in printed[0]
    assert "Traceback" not in done.stderr and not (tmp_path / "s.sock").exists()


# ---- floods ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("flood, answers", [
    (b"?VERSION;\n" * 20_000, 20_000),  # each one answered
    (b"x\n" * 30_000, 30_000),  # each one an ERROR
    (b"\r\n" * 300_000 + b"?VERSION;\n", 1),  # empty lines: no answer, but the loop's time all the same
    (b"?POLL;" + b"y" * (64 * MAX_LINE_BYTES) + b"\n", 1),  # one over-long line: one ERROR
])
def test_floods_of_requests_from_four_clients_delay_nobody(serve, tmp_path, flood, answers):
    """Four clients send their flood and read every answer; meanwhile another polls."""
    serve()
    path = tmp_path / "calibd.sock"
    other = connected(path)
    floods = [connected(path) for _ in range(4)]
    got = []

    def run(client):
        client.sock.settimeout(20)
        sender = threading.Thread(target=client.sock.sendall, args=(flood,))
        sender.start()
        lines, deadline = 0, time.monotonic() + 20
        while lines < answers and time.monotonic() < deadline:
            if select.select([client.sock], [], [], 0.05)[0]:
                chunk = client.sock.recv(1 << 20)
                if not chunk:
                    break
                lines += chunk.count(b"\n")
        sender.join()
        got.append(lines)
    threads = [threading.Thread(target=run, args=(c,)) for c in floods]
    for thread in threads:
        thread.start()
    worst = worst_answer_s(other, threads[0], polls=1000)
    for thread in threads:
        thread.join(timeout=30)
    assert worst < ANSWER_S, f"{worst * 1000:.0f} ms"
    assert got == [answers] * 4


def test_connect_floods_delay_nobody(serve, tmp_path):
    hub = serve()
    path = tmp_path / "calibd.sock"
    other = connected(path)
    stop = threading.Event()

    def churn():
        while not stop.is_set():
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.connect(str(path))
    churning = threading.Thread(target=churn)
    churning.start()
    try:
        worst = worst_answer_s(other, polls=20)
    finally:
        stop.set()
        churning.join()
    assert worst < ANSWER_S and hub.server._thread.is_alive()


# ---- the result copy -------------------------------------------------------------------------

def test_the_result_copy_is_never_written_through_a_link(serve, tmp_path):
    target = tmp_path / "precious"
    target.write_text("mine")
    target.chmod(0o600)
    copy = tmp_path / "result.json"
    copy.symlink_to(target)
    with pytest.raises(ServeError, match="is a symbolic link; never written through") as caught:
        Hub(ServeConfig(socket=tmp_path / "calibd.sock", result_copy=copy), "port", known_result())
    assert "\n" not in str(caught.value)
    assert target.read_text() == "mine" and stat.S_IMODE(target.stat().st_mode) == 0o600
    copy.unlink()
    copy.symlink_to(tmp_path / "absent")  # dangling: the daemon would create its target
    with pytest.raises(ServeError, match="symbolic link"):
        Hub(ServeConfig(socket=tmp_path / "calibd.sock", result_copy=copy), "port")
    assert not (tmp_path / "absent").exists()
    copy.unlink()
    os.mkfifo(copy)
    with pytest.raises(ServeError, match="not a regular file"):
        Hub(ServeConfig(socket=tmp_path / "calibd.sock", result_copy=copy), "port")


def test_a_link_put_there_while_running_is_skipped_and_logged_once(serve, tmp_path):
    copy, target = tmp_path / "result.json", tmp_path / "precious"
    target.write_text("mine")
    hub = serve(result_copy=copy)
    hub.on_result(known_result())
    assert stat.S_ISREG(os.lstat(copy).st_mode) and stat.S_IMODE(os.lstat(copy).st_mode) == 0o640
    copy.unlink()
    copy.symlink_to(target)
    with capture_logs() as logs:
        hub.on_result(known_result())
        hub.on_result(known_result())
        assert target.read_text() == "mine" and copy.is_symlink()
        copy.unlink()
        hub.on_result(known_result())
    assert [e["event"] for e in logs if e["event"].startswith("result_copy")] == [
        "result_copy_failed", "result_copy_recovered"]
    assert stat.S_ISREG(os.lstat(copy).st_mode) and json.loads(copy.read_text())["method"] == "joint"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]

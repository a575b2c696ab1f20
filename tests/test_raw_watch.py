"""?WATCH "raw" (protocol 1.3): the sensor's bytes as RAW messages, every byte once and in order
(offsets say where), for as many clients as watch; `calibd pipe --bytes` takes a capture from
the socket. The model is gpsd's raw watch mode."""

import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from calibd.client import Raw, message_of
from calibd.serve.protocol import ProtocolError, Watch, decode, encode
from calibd.serve.protocol import Raw as RawMessage
from calibd.serve.sockets import SocketServer
from captures import calibd

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"


def test_a_raw_message_carries_the_bytes_and_where_they_are_in_the_stream():
    data = bytes(range(256)) * 3
    assert message_of(decode(encode(RawMessage.of(1234, 5.25, data)))) == Raw(1234, 5.25, data)
    with pytest.raises(ProtocolError, match="malformed RAW message: data is not base64"):
        message_of(decode(b'{"class":"RAW","offset":0,"t_host":1.0,"data":"not base64!"}'))
    with pytest.raises(ProtocolError, match="malformed RAW message"):
        message_of(decode(b'{"class":"RAW","offset":"0","t_host":1.0,"data":""}'))


def test_watch_takes_raw_as_true_or_false_only():
    client = SimpleNamespace()
    assert SocketServer._watch(client, {"enable": True, "raw": True}) == Watch(True, "none", True)
    assert client.raw is True
    assert SocketServer._watch(client, {"enable": False, "raw": True}) == Watch(False, "none", False)
    with pytest.raises(ProtocolError, match='"raw" must be true or false, not 1'):
        SocketServer._watch(client, {"raw": 1})
    with pytest.raises(ProtocolError, match=r"unknown key\(s\) bytes \(known: enable, samples, raw\)"):
        SocketServer._watch(client, {"bytes": True})


@pytest.mark.slow
@pytest.mark.parametrize("name, speed", [("static_turn_2000hz", 4), ("faults_125hz", 12)])
def test_two_clients_each_take_every_byte_of_a_replay_from_the_socket(tmp_path, name, speed):
    """Two `calibd pipe --bytes` readers of one replayed sensor: each writes the stream's bytes
    from the moment it connected to the end, nothing lost, nothing added, neither taking any
    from the other (a pty would split them); garbage, CRC errors and a sensor restart
    (faults_125hz) pass as they came. The sensor sends the capture twice, so a reader that took
    the first copy's span to start still gets the whole second one."""
    capture = (FIXTURES / f"{name}.bin").read_bytes()
    capture_path = tmp_path / f"{name}_twice.bin"
    capture_path.write_bytes(capture * 2)
    sock = tmp_path / "calibd.sock"
    daemon = calibd("replay", capture_path, "--latitude", "60", "--socket", sock, "--speed", str(speed))
    try:
        deadline = time.monotonic() + 60
        while not sock.exists():
            assert daemon.poll() is None and time.monotonic() < deadline, daemon.stderr.read().decode()[-2000:]
            time.sleep(0.02)
        outputs = [tmp_path / f"pipe{k}.bin" for k in range(2)]
        pipes = [calibd("pipe", sock, "--bytes", stdout=path.open("wb")) for path in outputs]
        daemon.wait(timeout=120)  # to the capture's end (too short to finish a warm-up: no result, exit 1)
        for pipe in pipes:
            pipe.wait(timeout=30)
            assert "server closed the connection" in pipe.stderr.read().decode()  # the replay's end, said once
    finally:
        for process in (daemon, *locals().get("pipes", [])):
            if process.poll() is None:
                process.kill()
    stream = capture * 2
    for path in outputs:
        got = path.read_bytes()
        assert len(got) >= len(capture)  # connected within the first copy
        assert got == stream[len(stream) - len(got):]

"""The socket protocol's commands and lines (calibd.serve.protocol)."""

import pytest

from calibd.errors import CalibdError
from calibd.serve.protocol import (COMMANDS, PROTO_MAJOR, Command, ProtocolError, auth_token, decode, encode,
                                   Version, parse_command)


@pytest.mark.parametrize("line, command", [
    (b"?POLL;", Command("POLL")),
    (b"  ?DEVICE;\r", Command("DEVICE")),
    (b"?VERSION", Command("VERSION")),
    (b'?WATCH={"enable":true,"samples":"raw"};', Command("WATCH", {"enable": True, "samples": "raw"})),
    (b'?WATCH={"enable":false}', Command("WATCH", {"enable": False})),
    (b'?AUTH={"token":"abc"};', Command("AUTH", {"token": "abc"})),
])
def test_commands_parse(line, command):
    assert parse_command(line) == command


@pytest.mark.parametrize("line, words", [
    (b"hello", "not a command"),
    (b"?FOO;", r"unknown command \?FOO"),
    (b"?WATCH={enable:true};", "not JSON"),
    (b"?WATCH=[1,2];", "must be a JSON object"),
    (b"\xff\xfe", "not UTF-8"),
])
def test_bad_commands_are_one_line_protocol_errors(line, words):
    with pytest.raises(ProtocolError, match=words) as caught:
        parse_command(line)
    assert isinstance(caught.value, CalibdError) and "\n" not in str(caught.value)


@pytest.mark.parametrize("argument", [
    b"[" * 1000, b"[" * 60_000, b'{"a":' * 5000 + b"1" + b"}" * 5000,  # nested beyond any use
    b'{"a":' + b"9" * 5000 + b"}",  # an integer json.loads refuses with ValueError (Python's digit limit)
    b'{"a":NaN}', b'{"a":1e999}', b'{"a":"\\ud800"}',  # no JSON, out of range, a lone surrogate
])
def test_any_argument_that_does_not_decode_is_a_protocol_error(argument):
    """Whatever the decoder raises (RecursionError on deep nesting, ValueError on huge integers)
    becomes one ProtocolError line: the server's handler sees nothing else."""
    with pytest.raises(ProtocolError, match="argument is not JSON") as caught:
        parse_command(b"?WATCH=" + argument + b";")
    assert "\n" not in str(caught.value) and len(str(caught.value)) < 200
    with pytest.raises(ProtocolError, match="not a JSON line"):
        decode(argument)


def test_auth_takes_a_token_string_and_nothing_else():
    assert "AUTH" in COMMANDS and auth_token({"token": "x"}) == "x"
    for args in (None, {}, {"token": 5}, {"token": "x", "user": "me"}):
        with pytest.raises(ProtocolError, match=r'expected \?AUTH=\{"token":"\.\.\."\};'):
            auth_token(args)


def test_messages_are_single_json_lines_that_decode_back():
    line = encode(Version.this())
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    message = decode(line)
    assert message["class"] == "VERSION" and message["proto_major"] == PROTO_MAJOR
    for bad in (b"[1]", b"{}", b"nope"):
        with pytest.raises(ProtocolError):
            decode(bad)
    assert decode(encode({"class": "SAMPLES", "incl": [float("nan")]}))["incl"] == [None]  # JSON has no NaN


def test_a_samples_line_gives_the_float32_values_back_and_null_for_nan():
    import numpy as np

    from calibd.serve.protocol import samples_line

    rng = np.random.default_rng(1)
    gyro = (rng.normal(size=(50, 3)) * 100).astype(np.float32)
    acc = np.full((50, 3), np.nan, np.float32)  # a block the datagram lacks
    incl = rng.normal(size=(50, 3)).astype(np.float32)
    incl[7, 2] = np.nan
    t_s = np.arange(50) / 2000 + 86400.0
    message = decode(samples_line(True, t_s, t_s + 0.25, np.arange(50) % 256, gyro, acc, incl))
    assert message["class"] == "SAMPLES" and message["corrected"] is True
    assert np.array_equal(np.array(message["gyro"], np.float32), gyro) and message["acc"] is None
    assert message["incl"][7][2] is None and np.float32(message["incl"][7][1]) == incl[7, 1]
    assert np.allclose(message["t"], t_s, atol=1e-6, rtol=0) and message["counter"][-1] == 49

"""The socket protocol's commands and lines (calibd.serve.protocol)."""

import pytest

from calibd.errors import CalibdError
from calibd.serve.protocol import (PROTO_MAJOR, Command, ProtocolError, decode, encode, parse_command,
                                   version_message)


@pytest.mark.parametrize("line, command", [
    (b"?POLL;", Command("POLL")),
    (b"  ?DEVICE;\r", Command("DEVICE")),
    (b"?VERSION", Command("VERSION")),
    (b'?WATCH={"enable":true,"samples":"raw"};', Command("WATCH", {"enable": True, "samples": "raw"})),
    (b'?WATCH={"enable":false}', Command("WATCH", {"enable": False})),
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


def test_messages_are_single_json_lines_that_decode_back():
    line = encode(version_message())
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    message = decode(line)
    assert message["class"] == "VERSION" and message["proto_major"] == PROTO_MAJOR
    for bad in (b"[1]", b"{}", b"nope"):
        with pytest.raises(ProtocolError):
            decode(bad)
    with pytest.raises(ValueError):  # NaN is not JSON: a builder must say null
        encode({"class": "SAMPLES", "incl": [float("nan")]})

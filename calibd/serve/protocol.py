"""The socket protocol's one home, shared by the daemon's server and `calibd.client`.

Modelled on gpsd's: newline-delimited JSON objects, each naming its kind in "class"; commands
are single lines `?NAME;` or `?NAME={json};`. The server's messages are built here (so their
fields are spelt once) and the client reads them with `decode`; docs/protocol.md describes them.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from functools import lru_cache

import msgspec
import numpy as np

from stim300.cliutil import package_version

from ..errors import CalibdError

PROTO_MAJOR = 1
PROTO_MINOR = 2  # 1.1: ?AUTH and AUTH; 1.2: CORRECTION
MAX_LINE_BYTES = 64 * 1024  # a longer command line is refused and skipped to its newline
# A server message longer than this is not calibd's: SAMPLES of 0.1 s at 2000 Hz and result
# documents stay well below (a client's bound on what it buffers).
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
SAMPLE_KINDS = ("none", "raw", "corrected")  # what ?WATCH "samples" may ask for
SAMPLES_MAX_S = 0.1  # a SAMPLES message holds at most this much of the stream
COMMANDS = ("WATCH", "POLL", "DEVICE", "VERSION", "AUTH")
MAX_TOKEN_BYTES = 4096  # the longest token of ?AUTH ([serve] tcp_token_file)
AUTH_TRIES = 3  # refused lines before ?AUTH succeeds that close a connection which needs a token

_COMMAND = re.compile(r"\?([A-Z]+)(?:=(.*?))?;?")


class ProtocolError(CalibdError):
    """A line that is not a command or message of this protocol; the message says why in one line."""


@dataclass(frozen=True)
class Command:
    """A client's command: its NAME and the JSON object after "=" (None when absent)."""

    name: str
    args: dict | None = None


def parse_command(line: bytes) -> Command:
    """One command line (without its newline) -> Command; ProtocolError for anything else."""
    try:
        text = line.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise ProtocolError("command is not UTF-8 text") from None
    match = _COMMAND.fullmatch(text)
    if match is None:
        raise ProtocolError(f"not a command: {_excerpt(text)} (expected ?NAME; or ?NAME={{...}};)")
    name, argument = match.groups()
    if name not in COMMANDS:
        raise ProtocolError(f"unknown command ?{name} (known: {', '.join('?' + c for c in COMMANDS)})")
    if argument is None:
        return Command(name)
    try:
        args = _json(argument)
    except ValueError:
        raise ProtocolError(f"?{name}: argument is not JSON: {_excerpt(argument)}") from None
    if not isinstance(args, dict):
        raise ProtocolError(f"?{name}: argument must be a JSON object, not {_excerpt(argument)}")
    return Command(name, args)


def _json(text: bytes | str):
    """JSON text -> its value; ValueError for anything else. msgspec refuses, in microseconds,
    NaN, integers of thousands of digits (its DecodeError, a ValueError) and nesting too deep
    (RecursionError, which is none: turned into one here)."""
    try:
        return msgspec.json.decode(text)
    except RecursionError:
        raise ValueError("nested too deeply") from None


def auth_token(args: dict | None) -> str:
    """The token of an ?AUTH command's argument; ProtocolError when it has none."""
    token = (args or {}).get("token")
    if not isinstance(token, str) or set(args) != {"token"}:
        raise ProtocolError('?AUTH: expected ?AUTH={"token":"..."};')
    return token


def token_of(data: bytes) -> str:
    """The token a token file's bytes hold (its text without surrounding white space);
    ProtocolError saying why in a few words when they hold none: the daemon and the command line
    read the file alike."""
    token = data.strip()
    if len(token) > MAX_TOKEN_BYTES:
        raise ProtocolError(f"longer than {MAX_TOKEN_BYTES} bytes: not a token")
    if not token:
        raise ProtocolError("is empty")
    try:
        return token.decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolError("not UTF-8 text") from None


def _excerpt(text: str, limit: int = 60) -> str:
    return repr(text if len(text) <= limit else text[:limit] + "...")


def encode(message: dict) -> bytes:
    """A message as one line of compact JSON."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode() + b"\n"


def decode(line: bytes | str) -> dict:
    """One line from the server -> its message (a dict with "class"); ProtocolError otherwise."""
    try:
        message = _json(line)
    except ValueError:
        raise ProtocolError(f"not a JSON line: {_excerpt(str(line))}") from None
    if not isinstance(message, dict) or not isinstance(message.get("class"), str):
        raise ProtocolError(f"not a message (a JSON object with a \"class\"): {_excerpt(str(line))}")
    return message


@lru_cache(maxsize=1)
def _release() -> str:
    """calibd's version, looked up once: the lookup takes about 0.4 ms, and every connection and
    ?VERSION is answered with it."""
    return package_version()


def version_message() -> dict:
    return {"class": "VERSION", "release": _release(), "proto_major": PROTO_MAJOR, "proto_minor": PROTO_MINOR}


def error_message(text: str) -> dict:
    return {"class": "ERROR", "message": text}


def auth_message() -> dict:
    """The answer to an accepted ?AUTH."""
    return {"class": "AUTH", "authenticated": True}


def watch_message(enable: bool, samples: str) -> dict:
    return {"class": "WATCH", "enable": enable, "samples": samples}


def state_message(state: str, detail: str, progress: dict) -> dict:
    return {"class": "STATE", "state": state, "detail": detail, "progress": progress}


def poll_message(state: dict, result: dict | None) -> dict:
    """`state`: a STATE message's fields without "class"; `result`: the result document or None."""
    return {"class": "POLL", "state": state, "result": result}


def result_message(result: dict) -> dict:
    return {"class": "RESULT", "result": result}


def fault_message(counts: dict, increase: dict) -> dict:
    return {"class": "FAULT", "counts": counts, "increase": increase}


def correction_message(policy: str, session_id: str | None, from_t_s: float | None,
                       old: dict[str, tuple[float, str]] | None, new: dict[str, tuple[float, str]]) -> dict:
    """The biases the corrected outputs subtract changed: `old` (None: the power-up's first) and
    `new` map bias names to (value, unit) as the result gives them (deg/h, mg); `from_t_s` is the
    stream time (s, SAMPLES "t") of the first sample carrying `new` (None: not timed, no socket)."""
    def values(biases):
        return None if biases is None else {name: {"value": v, "unit": unit} for name, (v, unit) in biases.items()}
    return {"class": "CORRECTION", "policy": policy, "session_id": session_id,
            "from_t": None if from_t_s is None else round(from_t_s, 6), "old": values(old), "new": values(new)}


def overflow_message(dropped: int) -> dict:
    return {"class": "OVERFLOW", "dropped": dropped}


def device_message(path: str, sensor: dict, units: dict | None, configuration: dict | None) -> dict:
    """`sensor`: a StreamInfo's `sensor_record()`; `units`: of the gyro, acc and incl blocks."""
    return {"class": "DEVICE", "path": path, "part_number": sensor.get("part_number"),
            "serial_number": sensor.get("serial_number"), "datagram_id": sensor.get("datagram_id"),
            "rate_hz": sensor.get("sample_rate_hz"), "configuration": configuration, "units": units}


def samples_line(corrected: bool, t_s: np.ndarray, t_host_s: np.ndarray, counter: np.ndarray,
                 gyro: np.ndarray, acc: np.ndarray, incl: np.ndarray) -> bytes:
    """A SAMPLES message, encoded, from sample columns: times to the microsecond, values with the
    9 significant digits that give a float32 back exactly. A block the datagram lacks (all NaN)
    is null, any other NaN value null too (JSON has no NaN). Formatted in one operation per
    column rather than through json: this is the server's bulk work."""
    n = len(counter)
    return (f'{{"class":"SAMPLES","corrected":{"true" if corrected else "false"},"t":{_column(t_s, "%.6f")},'
            f'"t_host":{_column(t_host_s, "%.6f")},"counter":{_column(counter, "%d")},"gyro":{_block(gyro, n)},'
            f'"acc":{_block(acc, n)},"incl":{_block(incl, n)}}}\n').encode()


@lru_cache(maxsize=64)
def _format(item: str, n: int) -> str:
    return "[" + ",".join([item] * n) + "]"


def _column(values: np.ndarray, item: str) -> str:
    nan = np.isnan(values) if values.dtype.kind == "f" else None
    if nan is not None and nan.any():
        return json.dumps([None if missing else value for missing, value in zip(nan.tolist(), values.tolist())])
    return _format(item, len(values)) % tuple(values.tolist())


def _block(values: np.ndarray, n: int) -> str:
    """(n, 3) values as [[x,y,z],...], or null."""
    nan = np.isnan(values)
    if nan.all():
        return "null"
    if nan.any():
        return json.dumps([[None if np.isnan(v) else float(v) for v in row] for row in values])
    return _format("[%.9g,%.9g,%.9g]", n) % tuple(values.ravel().tolist())

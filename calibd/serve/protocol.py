"""The socket protocol's one home, shared by the daemon's server and `calibd.client`.

Modelled on gpsd's: newline-delimited JSON objects, each naming its kind in "class"; commands
are single lines `?NAME;` or `?NAME={json};`. The server's messages are built here (so their
fields are spelt once) and the client reads them with `decode`; docs/protocol.md describes them.
"""

from __future__ import annotations

import base64
import json
import re
from dataclasses import dataclass
from functools import lru_cache

import msgspec
import numpy as np

from stim300.cliutil import package_version
from stim300.records import SensorRecord

from ..errors import CalibdError
from ..documents import json_value

PROTO_MAJOR = 1
PROTO_MINOR = 3  # 1.1: ?AUTH and AUTH; 1.2: CORRECTION; 1.3: ?WATCH "raw" and RAW
MAX_LINE_BYTES = 64 * 1024  # a longer command line is refused and skipped to its newline
# A server message longer than this is not calibd's: SAMPLES of 0.1 s at 2000 Hz and result
# documents stay well below (a client's bound on what it buffers).
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
BYTES = "bytes"  # the kind of the RAW batches the server cuts beside the SAMPLES kinds (?WATCH "raw")
SAMPLES_MAX_S = 0.1  # a SAMPLES message holds at most this much of the stream
RAW_MAX_BYTES = 48 * 1024  # a RAW message holds at most this many of the sensor's bytes (base64: 64 kB)
COMMANDS = ("WATCH", "POLL", "DEVICE", "VERSION", "AUTH")
MAX_TOKEN_BYTES = 4096  # the longest token of ?AUTH ([serve] tcp_token_file)
AUTH_TRIES = 3  # refused lines before ?AUTH succeeds that close a connection which needs a token
MAX_CLIENTS = 64
MAX_CLIENTS_PER_UID = 16  # [serve] max_clients_per_uid's default: one user cannot take every slot
IDLE_TIMEOUT_S = 30.0  # [serve] idle_timeout_s's default

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


def decode(line: bytes | str) -> dict:
    """One line from the server -> its message (a dict with "class"); ProtocolError otherwise."""
    try:
        message = _json(line)
    except ValueError:
        raise ProtocolError(f"not a JSON line: {_excerpt(str(line))}") from None
    if not isinstance(message, dict) or not isinstance(message.get("class"), str):
        raise ProtocolError(f"not a message (a JSON object with a \"class\"): {_excerpt(str(line))}")
    return message


# ---- the server's messages: one type each, built by the server and read by the client (calibd.client)

class Message(msgspec.Struct, frozen=True, tag_field="class"):
    """A server message: a JSON object whose "class" names its type (the struct's tag)."""


class Version(Message, tag="VERSION"):
    """The greeting of every connection, and the answer to ?VERSION."""

    release: str
    proto_major: int
    proto_minor: int

    @classmethod
    def this(cls) -> Version:
        return cls(_release(), PROTO_MAJOR, PROTO_MINOR)


class Error(Message, tag="ERROR"):
    """The refusal of a command line, or why the server closes a connection."""

    message: str


class Auth(Message, tag="AUTH"):
    """The server took the token of ?AUTH."""

    authenticated: bool


class Watch(Message, tag="WATCH"):
    enable: bool
    samples: str = "none"
    raw: bool = False  # the sensor's bytes as RAW messages


class StateFields(msgspec.Struct, frozen=True):
    """The daemon's state, what it is doing (detail) and its session's progress (flat, any keys;
    docs/protocol.md): STATE's fields, and POLL's "state"."""

    state: str
    detail: str = ""
    progress: dict = {}


class State(StateFields, Message, tag="STATE"):
    """The state at each change, to watchers."""


class Poll(Message, tag="POLL"):
    state: StateFields
    result: dict | None  # the latest result document (docs/result-schema.md), None before the first


class Result(Message, tag="RESULT"):
    """A new result, or the last one marked stale (its document's `stale` says why)."""

    result: dict


class Fault(Message, tag="FAULT"):
    """Stream fault counts (crc_errors, lost_samples, ...) and their growth since the last FAULT."""

    counts: dict
    increase: dict = {}


class Overflow(Message, tag="OVERFLOW"):
    """`dropped` messages (oldest SAMPLES first) this client lost since the last OVERFLOW."""

    dropped: int


class Bias(msgspec.Struct, frozen=True):
    value: float
    unit: str


class Correction(Message, tag="CORRECTION"):
    """The biases the corrected outputs subtract changed (the [serve] `correction` policy chose
    the result of `session_id`): `old` (None: the power-up's first) and `new` by bias name, as
    the result gives them (deg/h, mg); the corrected samples carry `new` from stream time `from_t`
    (s, SAMPLES "t"; None when nothing timed the stream) on."""

    policy: str
    session_id: str | None
    from_t: float | None
    old: dict[str, Bias] | None
    new: dict[str, Bias]

    @classmethod
    def of(cls, policy: str, session_id: str | None, from_t_s: float | None,
           old: dict[str, tuple[float, str]] | None, new: dict[str, tuple[float, str]]) -> Correction:
        """From (value, unit) pairs by bias name, the stream time to the microsecond."""
        def biases(pairs):
            return None if pairs is None else {name: Bias(value, unit) for name, (value, unit) in pairs.items()}
        return cls(policy, session_id, None if from_t_s is None else round(from_t_s, 6), biases(old), biases(new))


class Device(Message, tag="DEVICE"):
    """The sensor on the port: its identity and rate (None until its datagrams said them), its
    configuration report, and the units of SAMPLES' blocks."""

    path: str
    part_number: str | None = None
    serial_number: str | None = None
    datagram_id: str | None = None
    rate_hz: float | None = None
    configuration: dict | None = None
    units: dict | None = None

    @classmethod
    def of(cls, path: str, sensor: SensorRecord, units: dict | None, configuration: dict | None) -> Device:
        """`units`: of the gyro, acc and incl blocks."""
        return cls(path, sensor.part_number, sensor.serial_number, sensor.datagram_id, sensor.sample_rate_hz,
                   configuration, units)


class Samples(Message, tag="SAMPLES"):
    """A batch of at most SAMPLES_MAX_S in the sensor's units (DEVICE's "units"); the server
    writes it with `samples_line`, its bulk work, in these fields."""

    corrected: bool
    t: list[float]
    t_host: list[float]
    counter: list[int]
    gyro: list[list[float | None]] | None
    acc: list[list[float | None]] | None = None
    incl: list[list[float | None]] | None = None


class Raw(Message, tag="RAW"):
    """The sensor's bytes as the daemon read them, every byte once and in order: `offset` is the
    number of the stream's bytes before these (a gap between two RAW messages is bytes this
    client lost, told by OVERFLOW), `t_host` the host monotonic time (s) of the first read among
    them, `data` the bytes in base64."""

    offset: int
    t_host: float
    data: str

    @classmethod
    def of(cls, offset: int, t_host_s: float, data: bytes) -> Raw:
        return cls(offset, round(t_host_s, 6), base64.b64encode(data).decode("ascii"))


MESSAGES = (Version | Error | Auth | Watch | State | Poll | Result | Fault | Overflow | Correction | Device | Samples
            | Raw)


_ENCODER = msgspec.json.Encoder(enc_hook=json_value)


def encode(message: Message | dict) -> bytes:
    """A message as one line of compact JSON."""
    return _ENCODER.encode(message) + b"\n"


def typed(doc: dict) -> Message:
    """A decoded server object (`decode`) -> its message type; KeyError for a class this side does
    not know, ProtocolError (one line) when a known class lacks or garbles a field."""
    if doc["class"] not in _CLASSES:
        raise KeyError(doc["class"])
    try:
        return msgspec.convert(doc, MESSAGES)
    except msgspec.ValidationError as exc:
        raise ProtocolError(f"malformed {doc['class']} message: {exc}") from None


_CLASSES = {kind.__struct_config__.tag for kind in MESSAGES.__args__}


@lru_cache(maxsize=1)
def _release() -> str:
    """calibd's version, looked up once: the lookup takes about 0.4 ms, and every connection and
    ?VERSION is answered with it."""
    return package_version()


_HOST_PORT = re.compile(r"(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:/\[\]\s]+)):(?P<port>\d{1,5})")


def host_port(text: str, default_host: str | None = None) -> tuple[str, int] | None:
    """"HOST:PORT" or "[V6]:PORT" (and "PORT" alone when a `default_host` is given) -> (host,
    port); None for anything else; ValueError for a port outside 1..65535. The daemon's [serve]
    tcp and the client's address are read by this one rule."""
    text = text.strip()
    match = _HOST_PORT.fullmatch(text)
    if match is not None:
        host, port = match["v6"] or match["host"], int(match["port"])
    elif default_host is not None and text.isascii() and text.isdigit() and len(text) <= 5:
        host, port = default_host, int(text)
    else:
        return None
    if not 0 < port < 65536:
        raise ValueError(f"port {port} is outside 1..65535")
    return host, port


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

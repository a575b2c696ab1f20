"""A client of calibd's socket (what gpsd's `gps` module is to gpsd): connect, watch, read
typed messages, ask for the latest result.

    with Client.connect("/run/calibd/ttyUSB0/calibd.sock") as client:
        client.watch(samples="corrected")
        for message in client:
            if isinstance(message, Samples):
                use(message.t, message.gyro)

On TCP served with a token, `Client.connect(..., token=TOKEN)` sends ?AUTH first.

The wire format is `calibd.serve.protocol`'s; this module only reads it. Every failure is a
`ClientError` of one line naming the socket: a socket that is absent or refuses, a server that
goes away or speaks another protocol major version, a malformed message of a known class. A
message of a class this client does not know is kept as a generic `Message`, never an error,
so a newer server's additions do not break older clients.
"""

from __future__ import annotations

import json
import os
import re
import socket
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from .errors import CalibdError
from .results import CalibrationResult, ResultError
from .serve.protocol import MAX_MESSAGE_BYTES, PROTO_MAJOR, SAMPLE_KINDS, ProtocolError, decode

CONNECT_TIMEOUT_S = 5.0
_HOST_PORT = re.compile(r"(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:/\[\]]+)):(?P<port>\d{1,5})")


class ClientError(CalibdError):
    """The server cannot be reached or used; one line naming where."""


class VersionError(ClientError):
    """The server speaks another protocol major version (or is not a calibd server)."""


class ServerGone(ClientError):
    """The server closed the connection."""


class NoAnswer(ClientError):
    """Nothing came from the server within the time given."""


@dataclass(frozen=True)
class Message:
    """A message of a class this client does not know: its class and the whole object."""

    cls: str
    doc: dict


@dataclass(frozen=True)
class Version:
    release: str
    proto_major: int
    proto_minor: int


@dataclass(frozen=True)
class Auth:
    """The server took the token of ?AUTH."""

    authenticated: bool


@dataclass(frozen=True)
class Watch:
    enable: bool
    samples: str


@dataclass(frozen=True)
class State:
    """The daemon's state, what it is doing (detail) and the protocol's progress (flat, any keys)."""

    state: str
    detail: str
    progress: dict


@dataclass(frozen=True)
class Result:
    """A new result, or the last one marked stale (`result.stale` then says why)."""

    result: CalibrationResult


@dataclass(frozen=True)
class Fault:
    """Stream fault counts (crc_errors, lost_samples, ...) and their growth since the last FAULT."""

    counts: dict
    increase: dict


@dataclass(frozen=True, eq=False)
class Samples:
    """A batch of at most 0.1 s in the sensor's units (DEVICE's "units"): `t` stream time (s, the
    counter clock), `t_host` host monotonic time of the read (s), `counter`, `gyro`/`acc`/`incl`
    (n, 3); a block the datagram lacks is None."""

    corrected: bool
    t: np.ndarray
    t_host: np.ndarray
    counter: np.ndarray
    gyro: np.ndarray | None
    acc: np.ndarray | None
    incl: np.ndarray | None


@dataclass(frozen=True)
class Correction:
    """The biases the corrected outputs subtract changed (the [serve] `correction` policy chose
    the result of `session_id`): `old` (None: the power-up's first) and `new` map bias names to
    (value, unit) as results give them (deg/h, mg); the corrected samples carry `new` from stream
    time `from_t` (s, as Samples `t`; None when the daemon timed no samples) on."""

    policy: str
    session_id: str | None
    from_t: float | None
    old: dict[str, tuple[float, str]] | None
    new: dict[str, tuple[float, str]]


@dataclass(frozen=True)
class Overflow:
    """`dropped` messages (oldest SAMPLES first) this client lost since the last OVERFLOW."""

    dropped: int


@dataclass(frozen=True)
class Poll:
    state: State
    result: CalibrationResult | None


@dataclass(frozen=True)
class Device:
    path: str
    part_number: str | None
    serial_number: str | None
    datagram_id: str | None
    rate_hz: float | None
    configuration: dict | None
    units: dict


@dataclass(frozen=True)
class Error:
    """The server's answer to a command it refused."""

    message: str


def _state(doc: dict) -> State:
    return State(str(doc["state"]), str(doc.get("detail", "")), dict(doc.get("progress") or {}))


def _result(doc, where: str) -> CalibrationResult | None:
    return None if doc is None else CalibrationResult.from_dict(doc, where)


def _rows(values, n: int, name: str) -> np.ndarray | None:
    if values is None:
        return None
    rows = np.asarray(values, dtype=np.float64)
    if rows.size == n == 0:
        rows = rows.reshape(0, 3)
    if rows.shape != (n, 3):
        raise ValueError(f"{name} has shape {rows.shape}, expected ({n}, 3)")
    return rows


def _samples(doc: dict) -> Samples:
    t = np.asarray(doc["t"], dtype=np.float64)
    t_host = np.asarray(doc["t_host"], dtype=np.float64)
    counter = np.asarray(doc["counter"], dtype=np.int64)
    n = len(t)
    if t.shape != (n,) or t_host.shape != (n,) or counter.shape != (n,):
        raise ValueError(f"t, t_host and counter differ in length ({len(t)}, {len(t_host)}, {len(counter)})")
    return Samples(bool(doc["corrected"]), t, t_host, counter, _rows(doc["gyro"], n, "gyro"),
                   _rows(doc.get("acc"), n, "acc"), _rows(doc.get("incl"), n, "incl"))


def _biases(doc: dict | None) -> dict[str, tuple[float, str]] | None:
    return None if doc is None else {str(name): (float(b["value"]), str(b["unit"])) for name, b in doc.items()}


def _correction(doc: dict) -> Correction:
    from_t = doc.get("from_t")
    return Correction(str(doc["policy"]), doc.get("session_id"), None if from_t is None else float(from_t),
                      _biases(doc.get("old")), _biases(doc["new"]))


_TYPES = {
    "VERSION": lambda d: Version(str(d["release"]), int(d["proto_major"]), int(d["proto_minor"])),
    "AUTH": lambda d: Auth(bool(d["authenticated"])),
    "WATCH": lambda d: Watch(bool(d["enable"]), str(d.get("samples", "none"))),
    "STATE": _state,
    "RESULT": lambda d: Result(_result(d["result"], "RESULT")),
    "FAULT": lambda d: Fault(dict(d["counts"]), dict(d.get("increase") or {})),
    "SAMPLES": _samples,
    "OVERFLOW": lambda d: Overflow(int(d["dropped"])),
    "CORRECTION": _correction,
    "POLL": lambda d: Poll(_state(d["state"]), _result(d["result"], "POLL")),
    "DEVICE": lambda d: Device(str(d["path"]), d.get("part_number"), d.get("serial_number"),
                               d.get("datagram_id"), None if d.get("rate_hz") is None else float(d["rate_hz"]),
                               d.get("configuration"),
                               dict(d.get("units") or {})),
    "ERROR": lambda d: Error(str(d["message"])),
}


def message_of(doc: dict):
    """A decoded server object -> its typed message (`Message` for a class not known here);
    ProtocolError (one line) when a known class lacks or garbles a field."""
    build = _TYPES.get(doc["class"])
    if build is None:
        return Message(doc["class"], doc)
    try:
        return build(doc)
    except ResultError as exc:
        raise ProtocolError(f"{doc['class']}: {exc}") from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"no {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ProtocolError(f"malformed {doc['class']} message: {what}") from None


def _address(where: str):
    """A Unix socket path, or ("HOST", PORT) for "HOST:PORT" / "[V6]:PORT" that is not a file."""
    match = _HOST_PORT.fullmatch(where)
    if match is None or os.path.lexists(where):
        return where
    port = int(match["port"])
    if not 0 < port < 65536:
        raise ClientError(f"{where}: port {port} is outside 1..65535")
    return (match["v6"] or match["host"], port)


def _connect_error(where: str, exc: OSError) -> ClientError:
    if isinstance(exc, FileNotFoundError):
        return ClientError(f"{where}: no such socket (is calibd serving there? see [serve] socket)")
    if isinstance(exc, PermissionError):
        return ClientError(f"{where}: permission denied (join the socket's group, e.g. stim300)")
    if isinstance(exc, ConnectionRefusedError):
        return ClientError(f"{where}: connection refused (no calibd listening there)")
    if isinstance(exc, socket.timeout):
        return ClientError(f"{where}: no answer within the timeout")
    return ClientError(f"{where}: cannot connect: {(exc.strerror or str(exc)).lower()}")


class Client:
    """One connection to calibd's socket. Lines are read as they came (`read_line`) or as typed
    messages (`read`); the answers `watch`, `poll` and `device` wait for are taken out of the
    stream and whatever arrived before them stays queued, in order, for the next read."""

    def __init__(self, sock: socket.socket, where: str, timeout_s: float, token: str | None = None):
        self._sock, self.where, self._timeout_s = sock, where, timeout_s
        self._buffer = bytearray()
        self._queued: deque[bytes] = deque()
        try:
            self.version_line = self._await_line(timeout_s)
            self.version = self._check_version(self.version_line)
            if token is not None:
                self.command("AUTH", {"token": token})
                self._answer(Auth)
        except BaseException:
            sock.close()
            raise

    def _check_version(self, line: bytes) -> Version:
        """The server's greeting, refused unless it is calibd's VERSION of this protocol major."""
        try:
            first = message_of(decode(line))
        except ProtocolError:
            first = None
        if not isinstance(first, Version):
            raise VersionError(f"{self.where}: not a calibd server (its first line is no VERSION)")
        if first.proto_major != PROTO_MAJOR:
            raise VersionError(f"{self.where}: the server speaks protocol {first.proto_major}.{first.proto_minor}, "
                               f"this client {PROTO_MAJOR}.x: use the calibd of the server's release "
                               f"({first.release})")
        return first

    @classmethod
    def connect(cls, where: str, timeout_s: float = CONNECT_TIMEOUT_S, token: str | None = None) -> Client:
        """Connect to a Unix socket path or "HOST:PORT" and read the server's VERSION; with a
        `token` (TCP served with tcp_token_file) authenticate with it first."""
        address = _address(where)
        family = socket.AF_UNIX if isinstance(address, str) else None
        try:
            if family is None:
                sock = socket.create_connection(address, timeout_s)
            else:
                sock = socket.socket(family, socket.SOCK_STREAM)
                try:
                    sock.settimeout(timeout_s)
                    sock.connect(address)
                except BaseException:
                    sock.close()
                    raise
        except OSError as exc:
            raise _connect_error(where, exc) from None
        return cls(sock, where, timeout_s, token)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._sock.close()

    # ---- commands ----------------------------------------------------------------------------

    def command(self, name: str, args: dict | None = None) -> None:
        """Send `?NAME;` or `?NAME={args};` without waiting for its answer. To a server that has
        gone the command is lost quietly: the reads that follow give what it sent before it went,
        then ServerGone."""
        line = f"?{name};" if args is None else f"?{name}={json.dumps(args, separators=(',', ':'))};"
        try:
            self._sock.sendall(line.encode() + b"\n")
        except (BrokenPipeError, ConnectionResetError):
            pass

    def watch(self, samples: str = "none") -> Watch:
        """Start the stream of STATE, RESULT and FAULT (and SAMPLES of the kind asked for)."""
        if samples not in SAMPLE_KINDS:
            raise ClientError(f"samples must be one of {', '.join(SAMPLE_KINDS)}, not {samples!r}")
        self.command("WATCH", {"enable": True, "samples": samples})
        return self._answer(Watch)

    def unwatch(self) -> Watch:
        self.command("WATCH", {"enable": False})
        return self._answer(Watch)

    def poll(self) -> Poll:
        """The daemon's state now and its latest result (None before the first)."""
        self.command("POLL")
        return self._answer(Poll)

    def latest_result(self) -> CalibrationResult | None:
        return self.poll().result

    def device(self) -> Device:
        self.command("DEVICE")
        return self._answer(Device)

    def _answer(self, kind: type):
        """The next message of `kind` (within the timeout), the lines before it queued for reading;
        an ERROR in between is the refusal of the command."""
        deadline = time.monotonic() + self._timeout_s
        passed: list[bytes] = []
        try:
            while True:
                try:
                    line = self._await_line(max(deadline - time.monotonic(), 0.0))
                except NoAnswer:
                    raise NoAnswer(f"{self.where}: no {kind.__name__.upper()} answer within "
                                   f"{self._timeout_s:g} s") from None
                message = message_of(decode(line))
                if isinstance(message, kind):
                    return message
                if isinstance(message, Error):
                    raise ClientError(f"{self.where}: the server refused the command: {message.message}")
                passed.append(line)
        finally:
            self._queued.extend(passed)

    # ---- reading -----------------------------------------------------------------------------

    def read_line(self, timeout_s: float | None = None) -> bytes | None:
        """The next line as the server sent it, without its newline; None when none came within
        `timeout_s` (None: wait for ever); ServerGone when the server closed the connection."""
        if self._queued:
            return self._queued.popleft()
        try:
            return self._await_line(timeout_s)
        except NoAnswer:
            return None

    def read(self, timeout_s: float | None = None):
        """The next typed message, or None when none came within `timeout_s`."""
        line = self.read_line(timeout_s)
        return None if line is None else message_of(decode(line))

    def __iter__(self) -> Iterator:
        """Every message until the server goes (then ServerGone)."""
        while True:
            yield self.read()

    def _await_line(self, timeout_s: float | None) -> bytes:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                line = bytes(self._buffer[:end])
                del self._buffer[:end + 1]
                return line
            if len(self._buffer) > MAX_MESSAGE_BYTES:
                raise ProtocolError(f"{self.where}: a line of more than {MAX_MESSAGE_BYTES} bytes: not calibd's")
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise NoAnswer(f"{self.where}: nothing from the server within {timeout_s:g} s")
            try:
                self._sock.settimeout(left)
                chunk = self._sock.recv(65536)
            except socket.timeout:
                continue
            except ConnectionResetError:  # it closed with commands of ours unread
                chunk = b""
            except OSError as exc:
                raise ServerGone(f"{self.where}: the server went away ({(exc.strerror or str(exc)).lower()})") \
                    from None
            if not chunk:
                raise ServerGone(f"{self.where}: the server closed the connection")
            self._buffer += chunk

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

import base64
import binascii
import json
import os
import socket
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from stim300.errors import os_reason

from .errors import CalibdError
from .results import CalibrationResult, ResultError
from .serve import SAMPLE_KINDS, protocol
from .serve.protocol import (MAX_MESSAGE_BYTES, PROTO_MAJOR, Auth, Device, Error, Fault, Overflow,
                             ProtocolError, State, StateFields, Version, Watch, decode, host_port)

# the message types: calibd.serve.protocol's, and the richer views this module reads
__all__ = ["Client", "ClientError", "VersionError", "ServerGone", "NoAnswer", "message_of",
           "Version", "Auth", "Watch", "State", "Poll", "Result", "Fault", "Samples", "Raw", "Correction", "Overflow",
           "Device", "Error", "Message"]

CONNECT_TIMEOUT_S = 5.0


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
class Result:
    """A new result, or the last one marked stale (`result.stale` then says why)."""

    result: CalibrationResult


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
class Raw:
    """protocol.Raw with its bytes decoded: `data` are the sensor's bytes from stream byte
    `offset` on, the first of them read at host monotonic time `t_host` (s)."""

    offset: int
    t_host: float
    data: bytes


@dataclass(frozen=True)
class Correction:
    """protocol.Correction with each bias as (value, unit) (deg/h, mg)."""

    policy: str
    session_id: str | None
    from_t: float | None
    old: dict[str, tuple[float, str]] | None
    new: dict[str, tuple[float, str]]


@dataclass(frozen=True)
class Poll:
    state: StateFields
    result: CalibrationResult | None


def _rows(values, n: int, name: str) -> np.ndarray | None:
    if values is None:
        return None
    rows = np.asarray(values, dtype=np.float64)
    if rows.size == n == 0:
        rows = rows.reshape(0, 3)
    if rows.shape != (n, 3):
        raise ValueError(f"{name} has shape {rows.shape}, expected ({n}, 3)")
    return rows


def _samples(m: protocol.Samples) -> Samples:
    n = len(m.t)
    if len(m.t_host) != n or len(m.counter) != n:
        raise ValueError(f"t, t_host and counter differ in length ({n}, {len(m.t_host)}, {len(m.counter)})")
    return Samples(m.corrected, np.asarray(m.t, dtype=np.float64), np.asarray(m.t_host, dtype=np.float64),
                   np.asarray(m.counter, dtype=np.int64), _rows(m.gyro, n, "gyro"), _rows(m.acc, n, "acc"),
                   _rows(m.incl, n, "incl"))


def _biases(biases: dict[str, protocol.Bias] | None) -> dict[str, tuple[float, str]] | None:
    return None if biases is None else {name: (b.value, b.unit) for name, b in biases.items()}


def _result(doc: dict | None, where: str) -> CalibrationResult | None:
    return None if doc is None else CalibrationResult.from_dict(doc, where)


_VIEWS = {  # the messages this client reads as richer types: arrays, results, (value, unit) pairs
    protocol.Samples: _samples,
    protocol.Result: lambda m: Result(_result(m.result, "RESULT")),
    protocol.Poll: lambda m: Poll(m.state, _result(m.result, "POLL")),
    protocol.Correction: lambda m: Correction(m.policy, m.session_id, m.from_t, _biases(m.old), _biases(m.new)),
    protocol.Raw: lambda m: Raw(m.offset, m.t_host, _base64(m.data)),
}


def _base64(text: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except binascii.Error as exc:
        raise ValueError(f"data is not base64 ({exc})") from None


def message_of(doc: dict):
    """A decoded server object -> its typed message: calibd.serve.protocol's type, or the richer
    view above; `Message` for a class not known here. ProtocolError (one line) when a known class
    lacks or garbles a field."""
    try:
        message = protocol.typed(doc)
    except KeyError:
        return Message(doc["class"], doc)
    view = _VIEWS.get(type(message))
    if view is None:
        return message
    try:
        return view(message)
    except ResultError as exc:
        raise ProtocolError(f"{doc['class']}: {exc}") from None
    except ValueError as exc:
        raise ProtocolError(f"malformed {doc['class']} message: {exc}") from None


def _address(where: str):
    """A Unix socket path, or (HOST, PORT) for "HOST:PORT" / "[V6]:PORT" that is not a file."""
    if os.path.lexists(where):
        return where
    try:
        address = host_port(where)
    except ValueError as exc:
        raise ClientError(f"{where}: {exc}") from None
    return where if address is None else address


def _connect_error(where: str, exc: OSError) -> ClientError:
    if isinstance(exc, FileNotFoundError):
        return ClientError(f"{where}: no such socket (is calibd serving there? see [serve] socket)")
    if isinstance(exc, PermissionError):
        return ClientError(f"{where}: permission denied (join the socket's group, e.g. stim300)")
    if isinstance(exc, ConnectionRefusedError):
        return ClientError(f"{where}: connection refused (no calibd listening there)")
    if isinstance(exc, socket.timeout):
        return ClientError(f"{where}: no answer within the timeout")
    return ClientError(f"{where}: cannot connect: {os_reason(exc)}")


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

    def watch(self, samples: str = "none", raw: bool = False) -> Watch:
        """Start the stream of STATE, RESULT and FAULT (and SAMPLES of the kind asked for, and
        with `raw` the sensor's bytes as RAW messages)."""
        if samples not in SAMPLE_KINDS:
            raise ClientError(f"samples must be one of {', '.join(SAMPLE_KINDS)}, not {samples!r}")
        self.command("WATCH", {"enable": True, "samples": samples} | ({"raw": True} if raw else {}))
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
                raise ServerGone(f"{self.where}: the server went away ({os_reason(exc)})") \
                    from None
            if not chunk:
                raise ServerGone(f"{self.where}: the server closed the connection")
            self._buffer += chunk

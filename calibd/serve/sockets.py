"""The socket server: the protocol of `calibd.serve.protocol` on a Unix stream socket and
optionally TCP, for any number of clients, in one thread.

One `selectors` loop over non-blocking sockets: a client that sends garbage, floods, vanishes
or stops reading costs the daemon a bounded queue and nothing else. Messages published from
other threads (`publish`) are encoded once there and queued to every watching client here;
sample batches are cut here, every CUT_S, by the `cut_samples` callback, once per kind.
"""

from __future__ import annotations

import collections
import os
import selectors
import socket
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path

import structlog

from ..errors import CalibdError
from .protocol import (MAX_LINE_BYTES, SAMPLE_KINDS, Command, ProtocolError, encode, error_message,
                       overflow_message, parse_command, version_message, watch_message)

log = structlog.get_logger("calibd")

CUT_S = 0.03  # how often sample batches are cut: their latency, and far within SAMPLES_MAX_S
QUEUE_BYTES = 1 << 20  # a client's queue: about 3 s of raw 2000 Hz SAMPLES
MAX_CLIENTS = 64
SOCKET_MODE = 0o660


class ServeError(CalibdError):
    """Serving cannot start (a socket path taken, a missing directory, an unknown group); one line."""


class _Client:
    """One connection: its unparsed input, its queue (oldest first; (is SAMPLES, bytes)) and what it watches."""

    def __init__(self, sock: socket.socket, name: str):
        self.sock, self.name = sock, name
        self.inbuf = bytearray()
        self.skipping = False  # inside an over-long line: input is dropped up to its newline
        self.queue: collections.deque[tuple[bool, bytes]] = collections.deque()
        self.queued_bytes = 0
        self.sending = memoryview(b"")  # the message being written (never dropped once begun)
        self.dropped = 0  # messages dropped since the last OVERFLOW
        self.watching = False
        self.samples = "none"


class SocketServer:
    """Listens at `unix_path` (mode 0660, group `gid`) and/or `tcp` (host, port); `answer(command)`
    answers ?POLL and ?DEVICE (server thread), `cut_samples(kinds)` returns the sample batches
    due, [(kind, encoded message)], for the kinds some client watches. `start()` binds (ServeError
    when it cannot) and starts the thread; `close()` stops it and removes the socket file."""

    def __init__(self, unix_path: Path | None, tcp: tuple[str, int] | None, gid: int | None,
                 answer: Callable[[Command], dict], cut_samples: Callable[[set], list[tuple[str, bytes]]]):
        self.unix_path, self.tcp, self.gid = unix_path, tcp, gid
        self._answer, self._cut_samples = answer, cut_samples
        self._selector = selectors.DefaultSelector()
        self._listeners: list[socket.socket] = []
        self._clients: dict[socket.socket, _Client] = {}
        self._published: collections.deque[bytes] = collections.deque()
        self._wake_r, self._wake_w = socket.socketpair()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.tcp_address: tuple[str, int] | None = None  # where TCP listens (the port chosen when 0 was given)
        self.overflows = 0  # messages dropped from full queues, all clients

    # ------------------------------------------------------------------ life
    def start(self) -> SocketServer:
        try:
            if self.unix_path is not None:
                self._listen(self._unix_socket(self.unix_path))
            if self.tcp is not None:
                self._listen(self._tcp_socket(*self.tcp))
        except BaseException:
            self._close_sockets()
            raise
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._loop, name="calibd socket server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._close_sockets()

    def _close_sockets(self) -> None:
        for sock in [*self._clients, *self._listeners]:
            sock.close()
        self._clients.clear()
        self._listeners.clear()
        if self.unix_path is not None and self._owns_socket_file():
            self.unix_path.unlink()
        self._selector.close()
        self._wake_r.close()
        self._wake_w.close()

    def _owns_socket_file(self) -> bool:
        return getattr(self, "_inode", None) is not None and _inode(self.unix_path) == self._inode

    def _unix_socket(self, path: Path) -> socket.socket:
        """A listening socket at `path`: a socket file left by a killed daemon (nobody answers on
        it) is replaced; anything else there is refused."""
        try:
            mode = os.lstat(path).st_mode
        except FileNotFoundError:
            mode = None
        except OSError as exc:
            raise ServeError(f"socket {path}: {(exc.strerror or str(exc)).lower()}") from None
        if mode is not None and not stat.S_ISSOCK(mode):
            raise ServeError(f"socket {path}: the path is taken by something else than a socket; not replaced")
        if mode is not None:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
                if probe.connect_ex(str(path)) == 0:
                    raise ServeError(f"socket {path}: another process is serving on it")
            path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(path))
            self._inode = _inode(path)
            os.chmod(path, SOCKET_MODE)
            if self.gid is not None:
                os.chown(path, -1, self.gid)
        except OSError as exc:
            sock.close()
            raise ServeError(f"socket {path}: {(exc.strerror or str(exc)).lower()}") from None
        return sock

    def _tcp_socket(self, host: str, port: int) -> socket.socket:
        try:
            family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
            sock = socket.socket(family, socket.SOCK_STREAM)
        except OSError as exc:
            raise ServeError(f"tcp {host}:{port}: {(exc.strerror or str(exc)).lower()}") from None
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            self.tcp_address = sock.getsockname()[:2]
        except OSError as exc:
            sock.close()
            raise ServeError(f"tcp {host}:{port}: {(exc.strerror or str(exc)).lower()}") from None
        return sock

    def _listen(self, sock: socket.socket) -> None:
        sock.listen(16)
        sock.setblocking(False)
        self._listeners.append(sock)
        self._selector.register(sock, selectors.EVENT_READ, "listen")

    # ------------------------------------------------------------------ from other threads
    def publish(self, message: dict) -> None:
        """A message to every watching client (any thread: it is queued here, sent by the loop)."""
        self._published.append(encode(message))
        self._wake()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except OSError:  # full (the loop is awake anyway) or closed
            pass

    # ------------------------------------------------------------------ the loop
    def _loop(self) -> None:
        next_cut = time.monotonic()
        while not self._stop.is_set():
            for key, mask in self._selector.select(max(0.0, next_cut - time.monotonic())):
                if key.data == "wake":
                    self._drain_wake()
                elif key.data == "listen":
                    self._accept(key.fileobj)
                else:
                    if mask & selectors.EVENT_READ:
                        self._read(key.data)
                    if mask & selectors.EVENT_WRITE and key.data.sock in self._clients:
                        self._flush(key.data)
            self._deliver_published()
            if time.monotonic() >= next_cut:
                next_cut = time.monotonic() + CUT_S
                self._deliver_samples()
        self._last_words()

    def _last_words(self, within_s: float = 1.0) -> None:
        """At stop: what was published (the last result of a replay) still reaches the clients
        that read, for at most `within_s`."""
        self._deliver_published()
        deadline = time.monotonic() + within_s
        while time.monotonic() < deadline:
            waiting = [c for c in self._clients.values() if c.sending or c.queue or c.dropped]
            if not waiting:
                return
            for key, _ in self._selector.select(max(0.0, deadline - time.monotonic())):
                if isinstance(key.data, _Client) and key.data.sock in self._clients:
                    self._flush(key.data)

    def _deliver_published(self) -> None:
        while self._published:
            data = self._published.popleft()
            for client in list(self._clients.values()):
                if client.watching:
                    self._send(client, data, samples=False)

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass

    def _deliver_samples(self) -> None:
        kinds = {c.samples for c in self._clients.values() if c.watching and c.samples != "none"}
        try:
            batches = self._cut_samples(kinds)
        except Exception:  # a fault of calibd: these samples are lost, the server and the daemon run on
            log.exception("samples_failed")
            return
        for kind, data in batches:
            for client in list(self._clients.values()):
                if client.watching and client.samples == kind:
                    self._send(client, data, samples=True)

    def _accept(self, listener: socket.socket) -> None:
        try:
            sock, address = listener.accept()
        except OSError:  # the client went before it was accepted
            return
        sock.setblocking(False)
        client = _Client(sock, str(address) or "unix")
        if len(self._clients) >= MAX_CLIENTS:
            try:
                sock.send(encode(error_message(f"too many clients (at most {MAX_CLIENTS})")))
            except OSError:  # gone already: nothing to tell
                pass
            sock.close()
            return
        self._clients[sock] = client
        self._selector.register(sock, selectors.EVENT_READ, client)
        self._send(client, encode(version_message()), samples=False)

    def _drop(self, client: _Client) -> None:
        if self._clients.pop(client.sock, None) is not None:
            self._selector.unregister(client.sock)
            client.sock.close()

    def _read(self, client: _Client) -> None:
        try:
            chunk = client.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(client)
            return
        buf = client.inbuf
        buf += chunk
        while client.sock in self._clients:
            newline = buf.find(b"\n")
            if client.skipping:
                if newline < 0:
                    buf.clear()
                    return
                del buf[:newline + 1]
                client.skipping = False
                continue
            if newline < 0:
                if len(buf) > MAX_LINE_BYTES:
                    self._refuse(client, f"command line longer than {MAX_LINE_BYTES} bytes: skipped to its newline")
                    buf.clear()
                    client.skipping = True
                return
            line = bytes(buf[:newline])
            del buf[:newline + 1]
            if len(line) > MAX_LINE_BYTES:
                self._refuse(client, f"command line longer than {MAX_LINE_BYTES} bytes: skipped")
            elif line.strip():
                self._command(client, line)

    def _refuse(self, client: _Client, why: str) -> None:
        self._send(client, encode(error_message(why)), samples=False)

    def _command(self, client: _Client, line: bytes) -> None:
        try:
            command = parse_command(line)
            if command.name == "WATCH":
                reply = self._watch(client, command.args or {})
            elif command.name == "VERSION":
                reply = version_message()
            else:
                reply = self._answer(command)
        except ProtocolError as exc:
            reply = error_message(str(exc))
        except Exception as exc:  # a fault of calibd: said to the client and logged, the server runs on
            log.exception("serve_command_failed", command=command.name)
            reply = error_message(f"internal error answering ?{command.name}: {type(exc).__name__}: {exc}")
        self._send(client, encode(reply), samples=False)

    @staticmethod
    def _watch(client: _Client, args: dict) -> dict:
        enable, samples = args.get("enable", True), args.get("samples", "none")
        if not isinstance(enable, bool):
            raise ProtocolError(f"?WATCH: \"enable\" must be true or false, not {enable!r}")
        if samples not in SAMPLE_KINDS:
            raise ProtocolError(f"?WATCH: \"samples\" must be one of {', '.join(SAMPLE_KINDS)}, not {samples!r}")
        unknown = set(args) - {"enable", "samples"}
        if unknown:
            raise ProtocolError(f"?WATCH: unknown key(s) {', '.join(sorted(unknown))} (known: enable, samples)")
        client.watching, client.samples = enable, samples if enable else "none"
        return watch_message(client.watching, client.samples)

    # ------------------------------------------------------------------ output
    def _send(self, client: _Client, data: bytes, samples: bool) -> None:
        """Queue `data` for `client`; a full queue loses its oldest SAMPLES first (then its oldest
        messages), counted for the client's next OVERFLOW."""
        client.queue.append((samples, data))
        client.queued_bytes += len(data)
        if client.queued_bytes > QUEUE_BYTES:
            self._shed(client)
        if not client.sending:  # else the socket was full: the loop writes when it can take more
            self._flush(client)

    def _shed(self, client: _Client) -> None:
        """Drop from the front of the queue, SAMPLES only, until it fits; when only other messages
        are left, the oldest of those. Costs what it drops, not the queue's length."""
        before, others = client.dropped, []
        while client.queued_bytes > QUEUE_BYTES and client.queue:
            is_samples, data = client.queue.popleft()
            if is_samples:
                client.queued_bytes -= len(data)
                client.dropped += 1
            else:
                others.append((is_samples, data))
        while client.queued_bytes > QUEUE_BYTES and len(others) > 1:
            client.queued_bytes -= len(others.pop(0)[1])
            client.dropped += 1
        client.queue.extendleft(reversed(others))
        self.overflows += client.dropped - before

    def _flush(self, client: _Client) -> None:
        """Write what the socket takes now, without blocking; wait for it to be writable otherwise."""
        while True:
            if not client.sending:
                if client.dropped:
                    client.sending = memoryview(encode(overflow_message(client.dropped)))
                    client.dropped = 0
                elif client.queue:
                    _, data = client.queue.popleft()
                    client.queued_bytes -= len(data)
                    client.sending = memoryview(data)
                else:
                    break
            try:
                sent = client.sock.send(client.sending)
            except BlockingIOError:
                break
            except OSError:
                self._drop(client)
                return
            client.sending = client.sending[sent:]
        waiting = bool(client.sending) or bool(client.queue)
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if waiting else 0)
        if self._selector.get_key(client.sock).events != events:
            self._selector.modify(client.sock, events, client)


def _inode(path: Path) -> tuple[int, int] | None:
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino

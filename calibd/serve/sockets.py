"""The socket server: the protocol of `calibd.serve.protocol` on a Unix stream socket and
optionally TCP, for any number of clients, in one thread.

One `selectors` loop over non-blocking sockets: a client that sends garbage, floods, vanishes,
stops reading or sits idle costs the daemon a bounded queue and a bounded share of the loop's
time, and nothing else: every step for a client costs the same whatever its queue holds, at
most LINES_PER_TURN of its commands are answered before the others' turn, a fault of calibd
while serving it closes that client only. Messages published from other threads (`publish`)
are encoded once there and queued to every watching client here; sample batches are cut here,
every CUT_S, by the `cut_samples` callback, once per kind.
"""

from __future__ import annotations

import collections
import contextlib
import hmac
import os
import selectors
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import structlog

from stim300.errors import os_reason

from ..errors import CalibdError
from . import SAMPLE_KINDS
from .protocol import (AUTH_TRIES, BYTES, IDLE_TIMEOUT_S, MAX_CLIENTS, MAX_CLIENTS_PER_UID, MAX_LINE_BYTES,
                       Auth, Command, Error, Message, Overflow, ProtocolError, Version, Watch, auth_token,
                       encode, parse_command)

log = structlog.get_logger("calibd")

CUT_S = 0.03  # how often sample batches are cut: their latency, and far within SAMPLES_MAX_S
QUEUE_BYTES = 1 << 20  # a client's queue: about 3 s of raw 2000 Hz SAMPLES
LINES_PER_TURN = 32  # lines of one client taken before the loop turns to the others
EPISODE_QUIET_S = 10.0  # refusals of a kind end their episode (logged with their count) after this long without one
SOCKET_MODE = 0o660


class ServeError(CalibdError):
    """Serving cannot start (a socket path taken, a missing directory, an unknown group); one line."""


class _Queue:
    """A client's messages waiting, sent in the order queued. SAMPLES and the other messages wait
    apart (each with its place in the order), so that every step, dropping the oldest SAMPLES
    of a full queue included, costs the same whatever the queue holds."""

    def __init__(self):
        self.samples: collections.deque[tuple[int, bytes]] = collections.deque()
        self.others: collections.deque[tuple[int, bytes]] = collections.deque()
        self.bytes = 0
        self._order = 0

    def __bool__(self) -> bool:
        return bool(self.samples or self.others)

    def push(self, data: bytes, samples: bool) -> None:
        self._order += 1
        (self.samples if samples else self.others).append((self._order, data))
        self.bytes += len(data)

    def pop(self) -> bytes:
        """The oldest message."""
        take_other = not self.samples or (self.others and self.others[0][0] < self.samples[0][0])
        data = (self.others if take_other else self.samples).popleft()[1]
        self.bytes -= len(data)
        return data

    def shed(self, limit: int) -> int:
        """Drop the oldest SAMPLES until at most `limit` bytes wait, then the oldest other
        messages (never the newest one); how many went."""
        dropped = 0
        while self.bytes > limit and (self.samples or len(self.others) > 1):
            self.bytes -= len((self.samples or self.others).popleft()[1])
            dropped += 1
        return dropped


class _Client:
    """One connection: its unparsed input, its queue and what it watches. `peer` is whose
    connections it counts among (a uid, or "TCP"); `active_s` when it last sent a command or
    took bytes (docs/protocol.md, Limits: idle clients are closed)."""

    def __init__(self, sock: socket.socket, name: str, peer: int | str = "", authenticated: bool = True):
        self.sock, self.name, self.peer = sock, name, peer
        self.inbuf = bytearray()
        self.skipping = False  # inside an over-long line: input is dropped up to its newline
        self.queue = _Queue()
        self.sending = memoryview(b"")  # the message being written (never dropped once begun)
        self.dropped = 0  # messages dropped since the last OVERFLOW
        self.watching = False
        self.samples = "none"
        self.raw = False  # RAW messages: the sensor's bytes
        self.authenticated = authenticated  # False on TCP with a token until ?AUTH gives it
        self.refused = 0  # lines refused before ?AUTH succeeded
        self.active_s = time.monotonic()


class _Episodes:
    """Refusals, closings and faults by kind: the first of an episode is logged by the caller,
    the count once none has come for EPISODE_QUIET_S, so a flood of them is two log lines."""

    def __init__(self):
        self._open: dict[str, list] = {}  # kind -> [count, when the last came]

    def count(self, kind: str) -> bool:
        """One more of `kind`; True when it begins an episode (log it then)."""
        episode = self._open.setdefault(kind, [0, 0.0])
        episode[0] += 1
        episode[1] = time.monotonic()
        return episode[0] == 1

    def end_quiet(self, everything: bool = False) -> None:
        now = time.monotonic()
        for kind, (count, last_s) in list(self._open.items()):
            if everything or now - last_s >= EPISODE_QUIET_S:
                del self._open[kind]
                log.info("serve_episode_ended", kind=kind, count=count)


class SocketServer:
    """Listens at `unix_path` (mode 0660, group `gid`) and/or `tcp` (host, port); `answer(command)`
    answers ?POLL and ?DEVICE (server thread), `cut_samples(kinds)` returns the sample batches
    due, [(kind, encoded message)], for the kinds some client watches. With `tcp_token` a TCP
    client must send ?AUTH with it first. `start()` binds (ServeError when it cannot) and starts
    the thread; `close()` stops it and removes the socket file."""

    def __init__(self, unix_path: Path | None, tcp: tuple[str, int] | None, gid: int | None,
                 answer: Callable[[Command], Message], cut_samples: Callable[[set], list[tuple[str, bytes]]],
                 tcp_token: bytes | None = None, idle_timeout_s: float = IDLE_TIMEOUT_S,
                 max_clients_per_uid: int = MAX_CLIENTS_PER_UID):
        self.unix_path, self.tcp, self.gid = unix_path, tcp, gid
        self._answer, self._cut_samples = answer, cut_samples
        self.tcp_token, self.idle_timeout_s, self.max_clients_per_uid = tcp_token, idle_timeout_s, max_clients_per_uid
        self._selector = selectors.DefaultSelector()
        self._listeners: list[socket.socket] = []
        self._clients: dict[socket.socket, _Client] = {}
        self._held: set[_Client] = set()  # clients with command lines read but not yet answered
        self._published: collections.deque[bytes] = collections.deque()
        self._wake_r, self._wake_w = socket.socketpair()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._episodes = _Episodes()
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
            raise ServeError(f"socket {path}: {os_reason(exc)}") from None
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
            raise ServeError(f"socket {path}: {os_reason(exc)}") from None
        return sock

    def _tcp_socket(self, host: str, port: int) -> socket.socket:
        try:
            family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
            sock = socket.socket(family, socket.SOCK_STREAM)
        except OSError as exc:
            raise ServeError(f"tcp {host}:{port}: {os_reason(exc)}") from None
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            self.tcp_address = sock.getsockname()[:2]
        except OSError as exc:
            sock.close()
            raise ServeError(f"tcp {host}:{port}: {os_reason(exc)}") from None
        return sock

    def _listen(self, sock: socket.socket) -> None:
        sock.listen(16)
        sock.setblocking(False)
        self._listeners.append(sock)
        self._selector.register(sock, selectors.EVENT_READ, "listen")

    # ------------------------------------------------------------------ from other threads
    def publish(self, message: Message) -> None:
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
            try:
                next_cut = self._turn(next_cut)
            except Exception:  # a fault of calibd outside one client's work: the loop serves on
                if self._episodes.count("fault of the server loop"):
                    log.exception("serve_loop_failed")
                next_cut = time.monotonic() + CUT_S
                self._stop.wait(CUT_S)
        self._last_words()

    def _turn(self, next_cut: float) -> float:
        """One round: what the sockets have, the commands read before, what was published, and
        every CUT_S the samples and the idle clients; when the next cut is due."""
        ready = [c for c in self._held if self._reading(c)]
        for key, mask in self._selector.select(0.0 if ready else max(0.0, next_cut - time.monotonic())):
            if key.data == "wake":
                self._drain_wake()
            elif key.data == "listen":
                self._accept(key.fileobj)
            else:
                self._guarded(key.data, self._serve_client, key.data, mask)
        for client in [c for c in self._held if self._reading(c)]:
            self._guarded(client, self._take_lines, client)
        self._deliver_published()
        if time.monotonic() >= next_cut:
            next_cut = time.monotonic() + CUT_S
            self._deliver_samples()
            self._close_idle()
            self._episodes.end_quiet()
        return next_cut

    def _guarded(self, client: _Client, work: Callable, *args) -> None:
        """`work(*args)` for one client; a fault of calibd in it closes that client (logged once
        per episode), never the server."""
        try:
            work(*args)
        except Exception:
            if self._episodes.count("fault serving a client"):
                log.exception("serve_client_failed", client=client.name)
            self._drop(client)

    def _serve_client(self, client: _Client, mask: int) -> None:
        if mask & selectors.EVENT_READ and client.sock in self._clients:
            self._read(client)
        if mask & selectors.EVENT_WRITE and client.sock in self._clients:
            self._flush(client)

    def _last_words(self, within_s: float = 1.0) -> None:
        """At stop: what was published (the last result of a replay) still reaches the clients
        that read, for at most `within_s`."""
        self._episodes.end_quiet(everything=True)
        self._deliver_published()
        deadline = time.monotonic() + within_s
        while time.monotonic() < deadline:
            waiting = [c for c in self._clients.values() if c.sending or c.queue or c.dropped]
            if not waiting:
                return
            for key, _ in self._selector.select(max(0.0, deadline - time.monotonic())):
                if isinstance(key.data, _Client) and key.data.sock in self._clients:
                    self._guarded(key.data, self._flush, key.data)

    def _deliver_published(self) -> None:
        while self._published:
            data = self._published.popleft()
            for client in list(self._clients.values()):
                if client.watching:
                    self._guarded(client, self._send, client, data, False)

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass

    def _deliver_samples(self) -> None:
        watching = [c for c in self._clients.values() if c.watching]
        kinds = {c.samples for c in watching if c.samples != "none"}
        if any(c.raw for c in watching):
            kinds.add(BYTES)
        try:
            batches = self._cut_samples(kinds)
        except Exception:  # a fault of calibd: these samples are lost, the server and the daemon run on
            if self._episodes.count("fault cutting samples"):
                log.exception("samples_failed")
            return
        for kind, data in batches:
            for client in list(self._clients.values()):
                if client.watching and (client.raw if kind == BYTES else client.samples == kind):
                    self._guarded(client, self._send, client, data, True)

    # ------------------------------------------------------------------ connections
    def _accept(self, listener: socket.socket) -> None:
        """A new client, or one ERROR and closed when all MAX_CLIENTS are taken or its user
        (its uid on the Unix socket; TCP clients together) has max_clients_per_uid."""
        try:
            sock, address = listener.accept()
        except OSError:  # the client went before it was accepted
            return
        try:
            self._admit(sock, address)
        except Exception:  # a fault of calibd: this connection is closed, the server runs on
            if self._episodes.count("fault admitting a client"):
                log.exception("serve_accept_failed")
            client = self._clients.get(sock)
            if client is not None:
                self._drop(client)
            else:
                sock.close()

    def _admit(self, sock: socket.socket, address) -> None:
        sock.setblocking(False)
        peer = _peer(sock)
        who = f"uid {peer}" if isinstance(peer, int) else "TCP"
        refusal = None
        if len(self._clients) >= MAX_CLIENTS:
            refusal = f"too many clients (at most {MAX_CLIENTS})"
        elif sum(c.peer == peer for c in self._clients.values()) >= self.max_clients_per_uid:
            refusal = f"too many connections of {who} (at most {self.max_clients_per_uid})"
        if refusal is not None:
            if self._episodes.count(f"refused: {refusal}"):
                log.warning("clients_refused", why=refusal)
            try:
                sock.send(encode(Error(refusal)))
            except OSError:  # gone already: nothing to tell
                pass
            sock.close()
            return
        client = _Client(sock, who if isinstance(peer, int) else f"TCP {address[0]}:{address[1]}", peer,
                         authenticated=isinstance(peer, int) or self.tcp_token is None)
        self._clients[sock] = client
        self._selector.register(sock, selectors.EVENT_READ, client)
        self._send(client, encode(Version.this()), samples=False)

    def _drop(self, client: _Client) -> None:
        self._held.discard(client)
        if self._clients.pop(client.sock, None) is not None:
            try:
                self._selector.unregister(client.sock)
            except (KeyError, ValueError):  # never registered, or its socket already closed
                pass
            client.sock.close()

    def _close_idle(self) -> None:
        """Close, with one ERROR, the clients idle for idle_timeout_s: no command line and no byte
        taken by their socket, unless they watch and have taken everything sent. A TCP client
        that needs a token has that long from connecting to give it."""
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.watching and not (client.sending or client.queue or client.dropped):
                client.active_s = now  # waiting for messages, as it should
            elif now - client.active_s >= self.idle_timeout_s:
                why = "idle" if client.authenticated else "no ?AUTH"
                if self._episodes.count(f"closed: {why}"):
                    log.warning("clients_closed", why=why, after_s=self.idle_timeout_s)
                told = (f"closed: idle for {self.idle_timeout_s:g} s (no command, nothing read)" if client.authenticated
                        else f"closed: no ?AUTH within {self.idle_timeout_s:g} s")
                if not client.sending:  # never inside a message begun
                    with contextlib.suppress(OSError):
                        client.sock.send(encode(Error(told)))
                self._drop(client)

    # ------------------------------------------------------------------ input
    def _reading(self, client: _Client) -> bool:
        """Whether the client's commands are read now: not while half its queue is taken, so a
        client that sends commands without reading the answers waits in its own socket."""
        return client.queue.bytes < QUEUE_BYTES // 2

    def _read(self, client: _Client) -> None:
        if client in self._held:  # lines read before are answered first
            return
        try:
            chunk = client.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(client)
            return
        client.inbuf += chunk
        self._take_lines(client)

    def _take_lines(self, client: _Client) -> None:
        """Answer at most LINES_PER_TURN command lines of the input, while the client's queue has
        room; the rest is held for the next rounds."""
        self._held.discard(client)
        buf, answered = client.inbuf, 0
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
            if answered >= LINES_PER_TURN or not self._reading(client):
                self._held.add(client)
                self._interest(client)
                return
            line = bytes(buf[:newline])
            del buf[:newline + 1]
            answered += 1
            if len(line) > MAX_LINE_BYTES:
                self._refuse(client, f"command line longer than {MAX_LINE_BYTES} bytes: skipped")
            elif line.strip():
                self._command(client, line)

    def _refuse(self, client: _Client, why: str) -> None:
        self._send(client, encode(Error(why)), samples=False)

    def _command(self, client: _Client, line: bytes) -> None:
        if not client.authenticated:
            self._authenticate(client, line)
            return
        client.active_s = time.monotonic()
        try:
            command = parse_command(line)
        except ProtocolError as exc:
            self._refuse(client, str(exc))
            return
        try:
            if command.name == "WATCH":
                reply = self._watch(client, command.args or {})
            elif command.name == "VERSION":
                reply = Version.this()
            elif command.name == "AUTH":
                raise ProtocolError("?AUTH: this connection needs no token")
            else:
                reply = self._answer(command)
        except ProtocolError as exc:
            reply = Error(str(exc))
        except Exception as exc:  # a fault of calibd: said to the client and logged, the server runs on
            if self._episodes.count("fault answering a command"):
                log.exception("serve_command_failed", command=command.name)
            reply = Error(f"internal error answering ?{command.name}: {type(exc).__name__}: {exc}")
        self._send(client, encode(reply), samples=False)

    def _authenticate(self, client: _Client, line: bytes) -> None:
        """A TCP client that needs the token: ?AUTH with it, or ERROR; the AUTH_TRIES-th refused
        line closes the connection."""
        try:
            command = parse_command(line)
            if command.name != "AUTH":
                raise ProtocolError(f"?{command.name}: authenticate first: ?AUTH={{\"token\":\"...\"}};")
            if not hmac.compare_digest(auth_token(command.args).encode("utf-8", "replace"), self.tcp_token):
                raise ProtocolError("?AUTH: wrong token")
        except ProtocolError as exc:
            client.refused += 1
            left = AUTH_TRIES - client.refused
            self._refuse(client, f"{exc} ({left} of {AUTH_TRIES} tries left)" if left else
                         f"{exc}: closed after {AUTH_TRIES} tries")
            if not left:
                if self._episodes.count("closed: authentication failed"):
                    log.warning("clients_closed", why="authentication failed", client=client.name)
                self._drop(client)
            return
        client.authenticated, client.active_s = True, time.monotonic()
        self._send(client, encode(Auth(True)), samples=False)

    @staticmethod
    def _watch(client: _Client, args: dict) -> Watch:
        enable, samples, raw = args.get("enable", True), args.get("samples", "none"), args.get("raw", False)
        for key, value in (("enable", enable), ("raw", raw)):
            if not isinstance(value, bool):
                raise ProtocolError(f"?WATCH: \"{key}\" must be true or false, not {value!r}")
        if samples not in SAMPLE_KINDS:
            raise ProtocolError(f"?WATCH: \"samples\" must be one of {', '.join(SAMPLE_KINDS)}, not {samples!r}")
        unknown = set(args) - {"enable", "samples", "raw"}
        if unknown:
            raise ProtocolError(f"?WATCH: unknown key(s) {', '.join(sorted(unknown))} (known: enable, samples, raw)")
        client.watching, client.samples, client.raw = enable, samples if enable else "none", raw and enable
        return Watch(client.watching, client.samples, client.raw)

    # ------------------------------------------------------------------ output
    def _send(self, client: _Client, data: bytes, samples: bool) -> None:
        """Queue `data` for `client`; a full queue loses its oldest SAMPLES first (then its oldest
        messages), counted for the client's next OVERFLOW."""
        client.queue.push(data, samples)
        if client.queue.bytes > QUEUE_BYTES:
            dropped = client.queue.shed(QUEUE_BYTES)
            client.dropped += dropped
            self.overflows += dropped
        if not client.sending:  # else the socket was full: the loop writes when it can take more
            self._flush(client)
        else:
            self._interest(client)

    def _flush(self, client: _Client) -> None:
        """Write what the socket takes now, without blocking; wait for it to be writable otherwise."""
        while True:
            if not client.sending:
                if client.dropped:
                    client.sending = memoryview(encode(Overflow(client.dropped)))
                    client.dropped = 0
                elif client.queue:
                    client.sending = memoryview(client.queue.pop())
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
            if sent and client.authenticated:
                client.active_s = time.monotonic()
        self._interest(client)

    def _interest(self, client: _Client) -> None:
        """Wait for the client's socket to be readable while its commands are read, writable
        while something waits for it; lines held come back to be answered once there is room."""
        if client.sock not in self._clients:
            return
        reading = self._reading(client)
        writing = bool(client.sending) or bool(client.queue) or bool(client.dropped)
        events = (selectors.EVENT_READ if reading else 0) | (selectors.EVENT_WRITE if writing else 0)
        if self._selector.get_key(client.sock).events != events:
            self._selector.modify(client.sock, events, client)


def _peer(sock: socket.socket) -> int | str:
    """Whose connection it is: the uid at the other end of a Unix socket (SO_PEERCRED), "TCP"
    for any TCP client (its user is not known)."""
    if sock.family != socket.AF_UNIX:
        return "TCP"
    _pid, uid, _gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    return uid


def _inode(path: Path) -> tuple[int, int] | None:
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino

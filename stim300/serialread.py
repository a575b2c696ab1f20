"""Reading a serial port: everything it holds now, else the bytes that arrive together within its
timeout, in one read. The port reader's live path, a recording, Service Mode and the bias trim
read a port so; apart from the reader thread (`stim300.port`), so that Service Mode costs no
parser or logging at start-up.
"""

from __future__ import annotations

import os
import select
import sys
import time

import serial


def read_available(ser: serial.Serial, limit: int | None = None) -> bytes:
    """Everything the port holds now (at most `limit` bytes), else what comes first within the
    port timeout (`read_waited`)."""
    return read_waited(ser, limit)[0]


SETTLE_S = 0.001  # after a first byte at an empty port, what came with it lands (a datagram: 0.64 ms at 921600 bit/s)
READ_MOST = 4096  # the most one read of a device takes (a tty's read buffer, the most pyserial's in_waiting
# says): a pty fed at full speed (a replay) is read a piece at a time, not gathered into one read larger than
# the ring. A full read means the port holds more: with nothing served the reader reads on without a batch
# sleep (the ring's consumer sets the pace); served, it keeps its batches, whose pace (READ_MOST per
# `stim300.port.SERVED_BATCH_S`, 1 MB/s) the served queues' threads keep up with
DISCONNECTED = "device reports readiness to read but returned no data (device disconnected?)"


def read_waited(ser: serial.Serial, limit: int | None = None) -> tuple[bytes, bool]:
    """Everything the port holds now (at most `limit` bytes, READ_MOST from a device), else wait
    (up to the port timeout) for the first byte, let what arrives with it land (SETTLE_S) and
    take it all: bytes arriving together are one read, not their first byte and then the rest.
    And whether it had to wait.

    A device port is read straight from its descriptor (pyserial opens it non-blocking, with
    VMIN = VTIME = 0: a read of an empty port returns nothing): one system call a piece, where
    pyserial's `read` costs a select, an ioctl and a timer object, several times the CPU on a
    live path that reads every few milliseconds. A pyserial URL port is read through pyserial."""
    limit = sys.maxsize if limit is None else limit
    if not (os.name == "posix" and isinstance(ser, serial.Serial)):
        waiting = ser.in_waiting
        if waiting:
            return ser.read(min(waiting, limit)), False
        first = ser.read(1)
        rest = min(ser.in_waiting, limit - 1) if first else 0
        return (first + ser.read(rest) if rest > 0 else first), True
    fd, most = ser.fileno(), min(limit, READ_MOST)
    data = _drain(fd, most)
    if data:
        return data, False
    if not select.select([fd], [], [], ser.timeout)[0]:
        return b"", True
    time.sleep(SETTLE_S)
    data = _drain(fd, most)
    if not data:  # readable, yet empty: a device that is gone reads so
        raise serial.SerialException(DISCONNECTED)
    return data, True


def _drain(fd: int, limit: int) -> bytes:
    """What the non-blocking descriptor `fd` holds now, up to `limit` bytes (b"": nothing)."""
    pieces = []
    while limit > 0:
        try:
            piece = os.read(fd, limit)
        except BlockingIOError:
            break
        if not piece:
            break
        pieces.append(piece)
        limit -= len(piece)
    return pieces[0] if len(pieces) == 1 else b"".join(pieces)

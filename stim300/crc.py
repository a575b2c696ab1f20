"""The STIM300 CRC: CRC-32/MPEG-2 over the datagram padded with zero dummy bytes.

Poly 0x04C11DB7, init 0xFFFFFFFF, no reflection, no final XOR; the covered bytes (ID up to the
last byte before the CRC, never CR LF) are padded with zeros to a multiple of 4 (DS §5.5.7).
The scalar form uses crcmod's C extension; the column form computes the CRC of many
equal-length datagrams at once with numpy, using that a CRC is affine in the message bytes:
crc(m) = crc(0...0) ^ XOR_p T_p[m_p], with one 256-entry table per byte position.
"""

from __future__ import annotations

from functools import lru_cache

import crcmod
import numpy as np

POLY = 0x04C11DB7
INIT = 0xFFFFFFFF

crc32_mpeg2 = crcmod.mkCrcFun(0x1_0000_0000 | POLY, initCrc=INIT, rev=False, xorOut=0)
"""CRC-32/MPEG-2 of raw bytes (no padding); check value of b'123456789' is 0x0376E6E7."""


def datagram_crc(covered: bytes | bytearray | memoryview) -> int:
    """CRC of one datagram: `covered` is every byte before the CRC, ID included."""
    dummy = -len(covered) % 4
    return crc32_mpeg2(bytes(covered) + b"\0" * dummy)


@lru_cache(maxsize=None)
def _byte_table() -> np.ndarray:
    """T[b] = CRC register after shifting byte b through a zero register (MSB first)."""
    reg = np.arange(256, dtype=np.uint32) << np.uint32(24)
    for _ in range(8):
        top = (reg & np.uint32(0x80000000)) != 0
        reg = (reg << np.uint32(1)) ^ np.where(top, np.uint32(POLY), np.uint32(0))
    return reg


@lru_cache(maxsize=None)
def position_tables(covered_length: int) -> tuple[np.ndarray, int]:
    """Per-position contribution tables for datagrams with `covered_length` bytes before the CRC.

    Returns (tables of shape (covered_length, 256), constant) such that
    crc = constant ^ XOR_p tables[p, byte_p]. The padding zeros add nothing but shifts, which
    are folded into the tables.
    """
    padded = covered_length + (-covered_length % 4)
    table = _byte_table()
    tables = np.empty((padded, 256), dtype=np.uint32)
    tables[padded - 1] = table
    for p in range(padded - 2, -1, -1):  # one more zero byte after position p
        prev = tables[p + 1]
        tables[p] = (prev << np.uint32(8)) ^ table[prev >> np.uint32(24)]
    constant = crc32_mpeg2(b"\0" * padded)
    return np.ascontiguousarray(tables[:covered_length]), constant


SCALAR_ROWS = 256  # up to this many rows, one crcmod call a row is faster than the tables' fixed cost


def crc_columns(frames: np.ndarray, covered_length: int) -> np.ndarray:
    """CRC of each row of `frames` (N x >= covered_length uint8, any strides) as uint32.

    A few rows (a live feed's datagrams) go row by row: the column form costs two numpy calls
    per byte position whatever the number of rows."""
    n = frames.shape[0]
    if n <= SCALAR_ROWS:
        width = covered_length + (-covered_length % 4)
        padded = np.zeros((n, width), np.uint8)
        padded[:, :covered_length] = frames[:, :covered_length]
        data = padded.tobytes()
        return np.fromiter((crc32_mpeg2(data[i:i + width]) for i in range(0, n * width, width)), np.uint32, n)
    tables, constant = position_tables(covered_length)
    result = np.full(n, constant, dtype=np.uint32)
    scratch = np.empty(n, dtype=np.uint32)
    for p in range(covered_length):
        np.take(tables[p], frames[:, p], out=scratch)
        result ^= scratch
    return result

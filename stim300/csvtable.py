"""Numeric columns written as CSV rows: the bytes `numpy.savetxt` writes with the same printf
formats ("%d", "%.Nf", "%.Pg"), about 4 times as fast (benchmarks/csv_output.py).

savetxt formats one value at a time with the `%` operator, and that is most of its time. Here
numpy arithmetic makes a block's texts a whole column at a time: a value scaled by a power of
ten is rounded to an integer as `%` rounds it (half to even, on the exact binary value: where
the scaled float lands on a half, its rounding error is found exactly), and the integer's
digits come from a table of four-digit words. Each text, with its comma, lies in a cell of 16
bytes (two uint64 words, NUL after the text); adjacent narrow cells are joined. The cells are
written in row order into one buffer through a view whose 16-byte elements start at every
byte, each where the text before ends, so the next cell overwrites a cell's NULs: numpy
assigns a 1-D index array's elements in order (tests/test_csvtable.py would show otherwise).
Values the arithmetic does not cover (NaN, infinities, magnitudes beyond its integers or its
exact powers of ten) are formatted by `%`: every text is the `%` operator's, as in savetxt (the
same digits, `nan`, `inf`, `-0`). Integers are printed from their own dtype, never through
float64, so every integer is exact.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence

import numpy as np

ROWS_PER_BLOCK = 2048  # rows made at once: 1,500 to 4,000 measured within 10 %
CELL = 16  # bytes per cell: two uint64 words
FORMAT = re.compile(rb"%(?:d|\.([0-9])f|\.([1-9])g)")  # at most 9 digits scaled: below 2^30, exact tests

_U = np.uint64
_ALL = _U(0xFFFF_FFFF_FFFF_FFFF)
_POW10 = 10 ** np.arange(19, dtype=np.int64)
_POW10_FLOAT = 10.0 ** np.arange(23)  # exact: 10^22 is the largest power of ten a float64 holds
_SPLIT = 134217729.0  # 2^27 + 1: Veltkamp's split of a float64 into two halves of 26 bits


def _digit_words() -> tuple[np.ndarray, np.ndarray]:
    """For k < 10^4: its four digits (zero-padded) as a word of ASCII bytes, the first in the
    lowest byte (as the bytes lie in memory), and how many of them are trailing zeros."""
    texts = [f"{k:04d}" for k in range(10_000)]
    words = np.frombuffer("".join(texts).encode(), "<u4").astype(_U)
    return words, np.array([4 - len(t.rstrip("0")) for t in texts], np.int64)


_DIGITS4, _ZEROS4 = _digit_words()


def _halves(x):
    """x as high + low, each of at most 26 significant bits (Veltkamp)."""
    scaled = x * _SPLIT
    high = scaled - (scaled - x)
    return high, x - high


_POW10_HALVES = _halves(_POW10_FLOAT)


def write_rows(f, columns: Sequence[np.ndarray], formats: Sequence[str], rows_per_block: int = ROWS_PER_BLOCK) -> None:
    """Write to the binary file `f` one line per row of `columns` (1-D arrays, or 2-D ones giving
    one CSV column per column), each value in its printf format of `formats` (one per CSV column:
    "%d", "%.Nf" with N <= 9, "%.Pg" with P <= 9), separated by commas."""
    flat = [part for column in columns for part in (column.T if column.ndim == 2 else [column])]
    rows = len(flat[0])
    if any(len(column) != rows for column in flat):
        raise ValueError(f"columns of different lengths: {sorted({len(column) for column in flat})} rows")
    byte_formats = [fmt.encode("ascii") for fmt in formats]
    for fmt in byte_formats:
        if not FORMAT.fullmatch(fmt):
            raise ValueError(f"format {fmt.decode()!r}: the CSV writer takes %d, %.Nf and %.Pg (N, P <= 9) only")
    runs = []  # adjacent CSV columns of one format and dtype: made as one array
    for column, fmt in zip(flat, byte_formats):
        if runs and runs[-1][0] == fmt and runs[-1][1][0].dtype == column.dtype:
            runs[-1][1].append(column)
        else:
            runs.append((fmt, [column]))
    for start in range(0, rows, rows_per_block):
        stop = min(start + rows_per_block, rows)
        cells = [cell for fmt, run in runs for cell in _cells(np.stack([c[start:stop] for c in run]), fmt)]
        f.write(_joined(*_merged(cells)))


def _cells(values: np.ndarray, fmt: bytes) -> list[tuple]:
    """The texts of a columns x rows block, each value's followed by a comma: per column, its
    cells in order, each (first words, second words, lengths) of the rows."""
    decimals, precision = FORMAT.fullmatch(fmt).groups()
    flat = values.ravel()
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # values left to `%` are computed on too
        if decimals is None and precision is None:
            cells, exact = _integers(flat)
        elif decimals is not None:
            cells, exact = _fixed(flat.astype(np.float64, copy=False), int(decimals))
        else:
            cells, exact = _general(flat.astype(np.float64, copy=False), int(precision))
    if not exact.all():
        cells = _by_operator(cells, flat, ~exact, fmt)
    shape = values.shape
    return [tuple(part.reshape(shape)[k] for part in cell) for k in range(shape[0]) for cell in cells]


def _by_operator(cells: list[tuple], values: np.ndarray, which: np.ndarray, fmt: bytes) -> list[tuple]:
    """The cells with the values `which` formatted by the `%` operator (as Python numbers: exact),
    in as many cells as the longest text needs."""
    texts = [fmt % v + b"," for v in values[which].tolist()]
    count = max(len(cells), -(-max(len(t) for t in texts) // CELL))
    cells = cells + [(np.zeros(len(values), _U), np.zeros(len(values), _U), np.zeros(len(values), np.int64))
                     for _ in range(count - len(cells))]
    words = np.frombuffer(b"".join(t.ljust(count * CELL, b"\0") for t in texts), _U).reshape(-1, count, 2)
    lengths = np.array([len(t) for t in texts])
    for k, (first, second, length) in enumerate(cells):
        first[which], second[which] = words[:, k, 0], words[:, k, 1]
        length[which] = np.clip(lengths - CELL * k, 0, CELL)
    return cells


def _merged(cells: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """The cells as rows x cells x 2 words and rows x cells lengths, adjacent ones joined while
    their longest texts fit one: a cell written costs more than a join."""
    groups = []
    for cell in cells:
        widest = int(cell[2].max())
        if groups and groups[-1][0] + widest <= CELL:
            groups[-1] = (groups[-1][0] + widest, _appended(*groups[-1][1], cell[0], cell[2], cell[1]))
        else:
            groups.append((widest, cell))
    rows = len(cells[0][0])
    words, lengths = np.empty((rows, len(groups), 2), _U), np.empty((rows, len(groups)), np.int64)
    for k, (_, (first, second, length)) in enumerate(groups):
        words[:, k, 0], words[:, k, 1], lengths[:, k] = first, second, length
    return words, lengths


def _joined(words: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The texts of `words` (rows x cells x 2) with their `lengths`, one after the other in row
    order, each row's last comma a newline, as one byte array. Each cell is written where the
    text before ends, so its NULs are overwritten by the next (in order: see the module's doc)."""
    ends = np.cumsum(lengths.ravel())
    total = int(ends[-1])
    out = np.empty(total + CELL, np.uint8)
    at_every_byte = np.ndarray((total + 1,), f"V{CELL}", out, 0, (1,))
    at_every_byte[ends - lengths.ravel()] = words.view(f"V{CELL}").ravel()
    out[ends[lengths.shape[1] - 1::lengths.shape[1]] - 1] = ord("\n")
    return out[:total]


# ---------------------------------------------------------------- the three formats

def _integers(values: np.ndarray):
    """"%d", one cell: 8- and 16-bit integers from a table of their texts, others from their
    digits when below 10^14 in magnitude."""
    if values.dtype.kind in "iu" and values.dtype.itemsize <= 2:
        table, low = _integer_texts(values.dtype.str)
        index = values.astype(np.intp) - low
        return [tuple(part[index] for part in table)], np.ones(len(values), bool)
    exact = (values < 10**14) & (values > -(10**14)) if values.dtype.kind == "i" else values < 10**14
    whole = np.where(exact, values, 0).astype(np.int64)
    return [_appended(*_signed_digits(np.abs(whole), whole < 0), _U(ord(",")), 1)], exact


@functools.cache
def _integer_texts(dtype: str) -> tuple[tuple, int]:
    """Every value of a small integer dtype as a cell ("%d,"), and the lowest value."""
    info = np.iinfo(np.dtype(dtype))
    values = np.arange(info.min, info.max + 1)
    return _appended(*_signed_digits(np.abs(values), values < 0), _U(ord(",")), 1), info.min


def _fixed(values: np.ndarray, decimals: int):
    """"%.Nf": a cell of sign and whole digits, one of point, N digits and comma (joined later
    when they fit); magnitudes below 10^14."""
    size = np.abs(values)
    exact = size < 1e14
    size = np.where(exact, size, 0.0)
    whole = np.floor(size)
    if decimals:
        fraction = _rounded(size - whole, decimals)  # the fraction is exact
    else:  # 0 or 1, from the whole value: a half rounds to its even neighbour
        fraction = _rounded(size, 0) - whole.astype(np.int64)
    carry = fraction == _POW10[decimals]
    fraction[carry] = 0
    return [_signed_digits(whole.astype(np.int64) + carry, np.signbit(values)), _fraction(fraction, decimals)], exact


def _general(values: np.ndarray, precision: int):
    """"%.Pg", one cell: P significant digits; fixed notation for decimal exponents -4 to P - 1,
    trailing zeros and a bare point dropped, else d.ddde+XX. Magnitudes of 10^(P - 23) (where
    10^22 scales them, the largest power of ten a float64 holds exactly) to 10^P, and zero."""
    layout = _general_layout(precision)
    size = np.abs(values)
    places = (precision - 1) - np.floor(np.log10(size))  # powers of ten to scale by (log10 may be off by one)
    places[size == 0] = precision - 1
    exact = (places >= 0) & (places <= 22)  # NaN and infinities fail
    digits = _rounded(size, np.where(exact, places, 0.0).astype(np.intp))
    exponent = np.where(exact, (precision - 1) - places, 0.0).astype(np.intp)
    carry = digits == _POW10[precision]  # 9.9999999996 -> 10.0000000
    digits[carry] = _POW10[precision - 1]
    exact &= ((digits >= _POW10[precision - 1]) | (size == 0)) & (digits < _POW10[precision])
    digits[~exact] = 0  # digits for `%` to replace, within the tables' reach
    row = exponent + carry - layout.lowest + np.signbit(values) * layout.exponents
    leading = digits // _POW10[precision - 1]
    rest = (digits - leading * _POW10[precision - 1]) * _POW10[9 - precision]  # 8 digits, zeros after
    high = rest // 10_000
    low = rest - high * 10_000
    eight = _DIGITS4[high] | (_DIGITS4[low] << _U(32))
    kept = np.maximum(8 - (_ZEROS4[low] + (low == 0) * _ZEROS4[high]), layout.whole[row])  # the fraction's zeros go
    eight &= ~(_ALL << (_U(8) * kept.astype(_U)))
    point = layout.point_bits[row]  # the point goes after this many of the 8 digits, times 8 bits
    dotted = kept > layout.point[row]
    after = eight >> point
    middle = (eight & ~(_ALL << point)) | ((dotted * _U(ord("."))) << point) | (after << (point + _U(8)))
    at = layout.prefix_bits[row] + _U(8)  # 1 to 7 bytes: sign, "0.000", the first digit
    first = layout.prefix[row] | ((leading.astype(_U) + _U(ord("0"))) << layout.prefix_bits[row]) | (middle << at)
    second = (middle >> (_U(64) - at)) | ((after >> (_U(56) - point)) << at)
    text = (first, second, layout.prefix_length[row] + 1 + kept + dotted)
    return [_appended(*text, layout.suffix[row], layout.suffix_length[row])], exact


class _Layout:
    """What surrounds the digits of "%.Pg", by decimal exponent (rows from the lowest the
    arithmetic reaches to P, then the same for negative values): the sign and "0.000" before the
    first digit, where the point goes among the next 8, and "e+XX," or "," after."""

    def __init__(self, precision: int):
        self.lowest = precision - 23
        self.exponents = precision - self.lowest + 1
        rows = [(negative, e) for negative in (False, True) for e in range(self.lowest, precision + 1)]
        fixed = [-4 <= e < precision for _, e in rows]
        prefixes = [b"-" * negative + (b"0." + b"0" * (-e - 1) if is_fixed and e < 0 else b"")
                    for (negative, e), is_fixed in zip(rows, fixed)]
        suffixes = [b"," if is_fixed else b"e%+03d," % e for (_, e), is_fixed in zip(rows, fixed)]
        # fixed notation: the point after e + 1 digits (the first and e of these 8, kept even when
        # zeros; none for e < 0, "0." is before); else after the first
        self.point = np.array([(e if e >= 0 else 8) if is_fixed else 0 for (_, e), is_fixed in zip(rows, fixed)])
        self.whole = np.array([e if is_fixed and e >= 0 else 0 for (_, e), is_fixed in zip(rows, fixed)])
        self.point_bits = (8 * self.point).astype(_U)
        self.prefix, self.prefix_length = _words(prefixes)
        self.prefix_bits = (8 * self.prefix_length).astype(_U)
        self.suffix, self.suffix_length = _words(suffixes)


@functools.cache
def _general_layout(precision: int) -> _Layout:
    return _Layout(precision)


def _words(texts: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Texts of up to 8 bytes as words, and their lengths."""
    return (np.frombuffer(b"".join(t.ljust(8, b"\0") for t in texts), "<u8").astype(_U),
            np.array([len(t) for t in texts], np.int64))


# ---------------------------------------------------------------- digits as words

def _rounded(size: np.ndarray, places) -> np.ndarray:
    """size * 10^places (below 2^30) rounded to an integer as `%` rounds it: half to even, on the
    exact product. The float product is within half its last place (2^-24 or less) of the exact
    one, and a multiple of it, as is 0.5: a product whose fraction is not exactly 0.5 rounds as
    the exact one; where it is, its rounding error (exact: Dekker's two-product) decides."""
    product = size * _POW10_FLOAT[places]
    below = np.floor(product)
    whole = below.astype(np.int64)
    part = product - below
    up = part > 0.5
    half = np.flatnonzero(part == 0.5)
    if len(half):
        x, p = size[half], np.broadcast_to(places, size.shape)[half]
        x_high, x_low = _halves(x)
        p_high, p_low = _POW10_HALVES[0][p], _POW10_HALVES[1][p]
        error = ((x_high * p_high - product[half]) + x_high * p_low + x_low * p_high) + x_low * p_low
        up[half] = (error > 0) | ((error == 0) & ((whole[half] & 1) == 1))
    return whole + up


def _digits8(value: np.ndarray) -> np.ndarray:
    """The 8 ASCII digits of each value < 10^8, zero-padded, as a word."""
    high = value // 10_000
    return _DIGITS4[high] | (_DIGITS4[value - high * 10_000] << _U(32))


def _signed_digits(value: np.ndarray, negative: np.ndarray):
    """'-' where `negative`, then the digits of each value < 10^15: (first word, second word, length)."""
    high = value // 10**8
    first, second = _digits8(high), _digits8(value - high * 10**8)
    count = 1 + np.searchsorted(_POW10[1:16], value, side="right")
    sign = negative.astype(_U)
    at = (_U(8) * (_U(15) - count.astype(_U)))  # the '0' before the first digit turns '-'
    first ^= (sign * _U(ord("0") ^ ord("-"))) << at
    second ^= (sign * _U(ord("0") ^ ord("-"))) << (at - _U(64))
    drop = _U(8) * (_U(16) - count.astype(_U) - sign)
    first = (first >> drop) | (second << (_U(64) - drop)) | (second >> (drop - _U(64)))
    return first, second >> drop, count + negative


def _appended(first, second, length, word, word_length, word2=None):
    """The text (first, second, length) with the text of `word` (and `word2`, its next 8 bytes)
    after it; the sum stays within 16 bytes (shifts of 64 bits or more give 0 in numpy)."""
    at = _U(8) * length.astype(_U)
    first = first | (word << at)
    second = second | (word >> (_U(64) - at)) | (word << (at - _U(64)))
    if word2 is not None:
        second = second | (word2 << at)
    return first, second, length + word_length


def _fraction(value: np.ndarray, places: int):
    """'.' and the `places` digits of each value (zero-padded; no point for none), then a comma:
    (first word, second word, length)."""
    scaled = value * _POW10[12 - places]  # 12 digits: the value's, then zeros
    high = scaled // 10**8
    eight = _digits8(scaled - high * 10**8)
    first = _U(ord(".")) | (_DIGITS4[high] << _U(8)) | (eight << _U(40))
    second = eight >> _U(24)
    length = places + 1 if places else 0
    first &= ~(_ALL << _U(8 * length))
    second &= _ALL >> _U(128 - 8 * length)
    return _appended(first, second, np.full(len(value), length), _U(ord(",")), 1)

"""Numeric columns written as CSV rows: the bytes `numpy.savetxt` writes with the same printf
formats, 1.6 to 2.2 times as fast (benchmarks/csv_output.py).

savetxt applies its row format once per row, to a row of numpy scalars of one float64 table.
Here one bytes format for a whole block of rows is applied once to the block's values as plain
Python objects, so the formatting runs in one C loop and no text is encoded afterwards; and a
float column that repeats its values (temperatures, counts within the noise) has each distinct
value formatted once per block. Every number's text is still the `%` operator's, as in
savetxt (same digits, `nan`, `inf`, `-0`), and that formatting is most of what remains.
Integers are printed from their own dtype, never through float64, so every integer is exact.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

ROWS_PER_BLOCK = 20_000  # rows formatted at once: 2,000 to 100,000 measured within 10 %


def write_rows(f, columns: Sequence[np.ndarray], formats: Sequence[str], rows_per_block: int = ROWS_PER_BLOCK) -> None:
    """Write to the binary file `f` one line per row of `columns` (1-D arrays, or 2-D ones giving
    one CSV column per column), each value in its printf format of `formats` (one per CSV column,
    e.g. "%d", "%.6f", "%.9g"), separated by commas."""
    flat = [part for column in columns for part in (column.T if column.ndim == 2 else [column])]
    rows, width = len(flat[0]), len(flat)
    if any(len(column) != rows for column in flat):
        raise ValueError(f"columns of different lengths: {sorted({len(column) for column in flat})} rows")
    byte_formats = [fmt.encode("ascii") for fmt in formats]
    for start in range(0, rows, rows_per_block):
        stop = min(start + rows_per_block, rows)
        values = [None] * ((stop - start) * width)  # row by row, column by column
        taken_as = []
        for position, (column, fmt) in enumerate(zip(flat, byte_formats)):
            values[position::width], how = _formattable(column[start:stop], fmt)
            taken_as.append(how)
        f.write(((b",".join(taken_as) + b"\n") * (stop - start)) % tuple(values))


def _formattable(values: np.ndarray, fmt: bytes) -> tuple[list, bytes]:
    """A column's block as the row format takes it, and its format there: the numbers (Python int
    or float, exact) with `fmt`, or, for floats of which at most half are distinct, each value's
    text (`fmt` applied once per distinct value) with "%b". Integers are cheap to format: finding
    their distinct values would cost more than it saves."""
    if values.dtype.kind != "f":
        return values.tolist(), fmt
    bits = values.view(f"u{values.itemsize}")  # distinct bits: -0.0 apart from 0.0
    distinct, inverse = np.unique(bits, return_inverse=True)
    if 2 * len(distinct) > len(values):
        return values.tolist(), fmt
    texts = np.array([fmt % value for value in distinct.view(values.dtype).tolist()], dtype=object)
    return texts[inverse].tolist(), b"%b"

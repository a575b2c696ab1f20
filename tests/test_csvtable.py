"""`stim300.csvtable.write_rows` writes the bytes `numpy.savetxt` writes, for every value and
format it takes (those the CSV outputs use, `stim300 decode -o OUT.csv` and `calibd apply -o
OUT.csv`, and the other "%.Nf" and "%.Pg"), in blocks of any size: exact halves rounded to
even, powers of ten and their neighbours, texts longer than a cell; and both commands' writers
give today's savetxt files byte for byte."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from calibd.apply import TIME_FORMAT, VALUE_FORMAT, CsvWriter
from captures import exact_samples
from stim300.cli import _write_csv, columns
from stim300.csvtable import ROWS_PER_BLOCK, write_rows
from stim300.protocol import Format

FLOAT_FORMATS = ("%.6f", TIME_FORMAT, VALUE_FORMAT)  # decode's times, apply's times, every other value
EVERY_FLOAT_FORMAT = tuple(f"%.{n}f" for n in range(10)) + tuple(f"%.{p}g" for p in range(1, 10))
ADVERSARIAL = [np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 1e300, -1e300, 1e-300, -1e-300, 5e-324, -5e-324,
               np.finfo(np.float64).max, -np.finfo(np.float64).max, np.finfo(np.float64).tiny,
               float(np.finfo(np.float32).max), float(np.finfo(np.float32).tiny), 1 / 3, -2 / 3, 0.5, 2.5,
               0.00005, 0.000015, -0.0000004, 1e16, 123456789.5, 9.80665, 2.0 ** 53 + 1, 1e-7]
INT_DTYPES = (np.uint8, np.uint16, np.uint32, np.uint64, np.int8, np.int16, np.int32, np.int64)
BLOCK_SIZES = (1, 3, 7, 1000, 10_000)


def savetxt_bytes(cols: list[np.ndarray], formats: list[str]) -> bytes:
    """What savetxt writes for these columns, each value from its own dtype (a structured array:
    one field per CSV column), so an int64 is printed exactly as savetxt prints it."""
    flat = [c[:, k] if c.ndim == 2 else c for c in cols for k in range(c.shape[1] if c.ndim == 2 else 1)]
    table = np.empty(len(flat[0]), [(f"c{j}", c.dtype) for j, c in enumerate(flat)])
    for j, c in enumerate(flat):
        table[f"c{j}"] = c
    out = io.BytesIO()
    np.savetxt(out, table, fmt=formats, delimiter=",")
    return out.getvalue()


def written(cols, formats, rows_per_block=ROWS_PER_BLOCK) -> bytes:
    out = io.BytesIO()
    write_rows(out, cols, formats, rows_per_block)
    return out.getvalue()


@pytest.mark.parametrize("fmt", FLOAT_FORMATS)
@pytest.mark.parametrize("dtype", (np.float64, np.float32))
def test_adversarial_floats_in_every_format(fmt, dtype):
    with np.errstate(over="ignore"):
        values = np.array(ADVERSARIAL, dtype)
    expected = savetxt_bytes([values], [fmt])
    assert b"nan" in expected and b"-inf" in expected and b"-0" in expected
    assert written([values], [fmt]) == expected


@pytest.mark.parametrize("fmt", FLOAT_FORMATS)
@pytest.mark.parametrize("dtype", (np.float64, np.float32))
@pytest.mark.parametrize("rows_per_block", (1, 7, 1000))
def test_repeated_floats_keep_each_values_text(fmt, dtype, rows_per_block):
    """A column of few distinct values: 0.0 and -0.0, NaNs of either sign and the rest each keep
    their own text."""
    rng = np.random.default_rng(7)
    with np.errstate(over="ignore"):
        values = rng.choice(np.array(ADVERSARIAL, dtype), 1000)
    assert len(np.unique(values.view(f"u{values.itemsize}"))) * 2 <= len(values)
    expected = savetxt_bytes([values], [fmt])
    assert written([values], [fmt], rows_per_block) == expected


@pytest.mark.parametrize("fmt", EVERY_FLOAT_FORMAT)
@pytest.mark.parametrize("dtype", (np.float64, np.float32))
def test_exact_halves_round_to_even(fmt, dtype):
    """Binary fractions m / 2^e end in 5: many lie exactly half-way between two texts of the
    format (the quarter-degree temperatures, the gyros' counts), and `%` takes the even one."""
    rng = np.random.default_rng(11)
    values = (rng.integers(-(1 << 24), 1 << 24, 3000) / 2.0 ** rng.integers(0, 34, 3000)).astype(dtype)
    values[:4] = [0.5, 1.5, 2.5, -0.125]
    expected = savetxt_bytes([values], [fmt])
    assert written([values], [fmt], 500) == expected
    assert fmt != "%.0f" or expected.startswith(b"0\n2\n2\n-0\n")  # halves to even, the sign kept


@pytest.mark.parametrize("fmt", EVERY_FLOAT_FORMAT)
def test_powers_of_ten_and_their_neighbours(fmt):
    """Where the decimal exponent changes (and log10 may be off by one), and where rounding
    carries into a new digit (9.9999999996)."""
    powers = 10.0 ** np.arange(-25, 26)
    nines = np.concatenate([powers * (1 - 4e-10), powers * (1 - 5e-10), powers * (1 - 6e-10)])
    values = np.concatenate([powers, np.nextafter(powers, 0), np.nextafter(powers, np.inf), nines])
    values = np.concatenate([values, -values])
    assert written([values], [fmt], 64) == savetxt_bytes([values], [fmt])


def test_texts_longer_than_a_cell_inside_a_row():
    """A value `%` formats (out of the arithmetic's range) may need many cells: its row keeps its
    order, and the rows around it theirs."""
    times = np.array([1.5, 1e300, -1e22, 2.0 ** 70, 12.25])
    values = np.array([1e-30, -np.inf, 123456.5, 5e-324, 1.0])
    counts = np.array([1, -(2**63), 2**63 - 1, 0, -1], np.int64)
    formats = ["%.6f", "%.9g", "%d"]
    expected = savetxt_bytes([times, values, counts], formats)
    assert max(len(line) for line in expected.split(b"\n")) > 300
    for rows_per_block in (1, 2, 5):
        assert written([times, values, counts], formats, rows_per_block) == expected


@pytest.mark.parametrize("fmt", ["%.10g", "%e", "%s", "%5d", "%.6f,"])
def test_formats_it_cannot_make_are_refused(fmt):
    with pytest.raises(ValueError, match="takes %d, %.Nf and %.Pg"):
        written([np.zeros(3)], [fmt])


@pytest.mark.parametrize("dtype", INT_DTYPES)
def test_integer_extremes_of_every_dtype(dtype):
    info = np.iinfo(dtype)
    values = np.array([info.min, info.max, 0, 1, info.max - 1, info.min + 1], dtype)
    expected = savetxt_bytes([values], ["%d"])
    assert str(info.max).encode() in expected  # exact, never through float64
    assert written([values], ["%d"]) == expected


def random_columns(rng, rows: int) -> tuple[list[np.ndarray], list[str]]:
    """Columns as both commands give them (float64 times, float32 and float64 values with NaN,
    repeated float32 temperatures, uint8 and uint16 integers, 2-D blocks), with adversarial values
    sprinkled in."""
    def floats(dtype, *shape):
        values = rng.normal(0, 10.0 ** rng.integers(-8, 8), (rows, *shape)).astype(dtype)
        spots = rng.random(values.shape) < 0.05
        with np.errstate(over="ignore"):
            values[spots] = rng.choice(np.array(ADVERSARIAL, dtype), spots.sum())
        return values

    temperatures = np.round(rng.normal(25, 0.1, rows), 2).astype(np.float32)  # few distinct values
    spots = rng.random(rows) < 0.05
    temperatures[spots] = rng.choice(np.array([-0.0, 0.0, np.nan, -np.nan], np.float32), spots.sum())
    cols = [np.arange(rows) / 2000 + rng.random(), floats(np.float64), floats(np.float32), temperatures,
            floats(np.float64, 3),
            rng.integers(0, 256, rows).astype(np.uint8), rng.integers(0, 256, (rows, 3)).astype(np.uint8),
            rng.integers(0, 1 << 16, rows).astype(np.uint16), rng.integers(-(1 << 62), 1 << 62, rows)]
    formats = [FLOAT_FORMATS[rng.integers(3)], *rng.choice(FLOAT_FORMATS, 6), *["%d"] * 6]
    return cols, formats


@pytest.mark.parametrize("rows", (0, 1, 5, 1001))
@pytest.mark.parametrize("rows_per_block", BLOCK_SIZES)
def test_random_columns_in_blocks_of_any_size(rows, rows_per_block):
    rng = np.random.default_rng(rows * 100 + rows_per_block)
    cols, formats = random_columns(rng, rows)
    assert written(cols, formats, rows_per_block) == savetxt_bytes(cols, formats)


@given(st.lists(st.floats(width=64), min_size=1, max_size=40), st.sampled_from(EVERY_FLOAT_FORMAT),
       st.integers(1, 50))
def test_any_float64(values, fmt, rows_per_block):
    values = np.array(values)
    assert written([values], [fmt], rows_per_block) == savetxt_bytes([values], [fmt])


@given(st.lists(st.floats(width=32), min_size=1, max_size=40), st.sampled_from(EVERY_FLOAT_FORMAT))
def test_any_float32(values, fmt):
    values = np.array(values, np.float32)
    assert written([values], [fmt]) == savetxt_bytes([values], [fmt])


@given(st.lists(st.integers(-(2**63), 2**63 - 1), min_size=1, max_size=40), st.integers(1, 50))
def test_any_int64(values, rows_per_block):
    values = np.array(values, np.int64)
    assert written([values], ["%d"], rows_per_block) == savetxt_bytes([values], ["%d"])


@pytest.mark.parametrize("lengths", ((5, 4), (4, 5)))
def test_columns_of_different_lengths_are_refused(lengths):
    with pytest.raises(ValueError, match="different lengths"):
        written([np.zeros(lengths[0]), np.zeros(lengths[1], np.uint8)], ["%.9g", "%d"])


def old_savetxt_rows(cols: list[np.ndarray], formats: list[str], chunk: int) -> bytes:
    """The rows as both commands wrote them before: float64 blocks through np.savetxt."""
    out = io.BytesIO()
    for start in range(0, len(cols[0]), chunk):
        table = np.column_stack([c[start:start + chunk].astype(np.float64) for c in cols])
        np.savetxt(out, table, fmt=formats, delimiter=",")
    return out.getvalue()


def test_decode_csv_is_todays_file():
    fmt = Format(datagram_id=0xAF, crlf=False, sample_rate_hz=2000)
    samples = exact_samples(2500, fmt, 0xAF, np.random.default_rng(3))
    samples["t_host"] = 1e5 + np.arange(len(samples)) / 2000  # a read log: the t_host_s column
    samples["temp_gyro"] = samples["temp_gyro"][np.arange(len(samples)) % 5]  # temperatures repeat
    cols = columns(samples, np.arange(len(samples)) / 2000)
    assert "t_host_s" in cols and "aux" in cols and "temp_incl_z" in cols
    out = io.BytesIO()
    _write_csv(out, cols)
    header, rows = out.getvalue().split(b"\n", 1)
    formats = ["%d" if c.dtype.kind in "ui" else "%.6f" if n in ("t_s", "t_host_s") else "%.9g"
               for n, c in cols.items()]
    assert header.decode().split(",") == list(cols)
    assert rows == old_savetxt_rows(list(cols.values()), formats, 100_000)


def test_apply_csv_is_todays_file():
    rng = np.random.default_rng(4)
    out = io.BytesIO()
    write = CsvWriter(out, {"schema": "test"})
    expected = b""
    for rows in (700, 1, 0, 65536):
        block = {"time_s": rng.integers(0, 1 << 24, rows) / 2000,
                 **{name: rng.normal(0, 10, (rows, 3)) for name in ("gyro_rad_s", "incl_m_s2")},
                 "acc_m_s2": np.round(rng.normal(0, 10, (rows, 3))) * 0.01,  # few distinct values
                 "counter": rng.integers(0, 256, rows).astype(np.uint8),
                 "status": rng.integers(0, 256, (rows, 3)).astype(np.uint8),
                 "power_up": np.full(rows, 2, np.uint16)}
        if rows:
            block["gyro_rad_s"][0] = [-0.0, np.nan, 1e-300]
        write(block)
        expected += old_savetxt_rows([block["time_s"], block["gyro_rad_s"], block["acc_m_s2"], block["incl_m_s2"],
                                      block["counter"], block["status"], block["power_up"]],
                                     [TIME_FORMAT, *[VALUE_FORMAT] * 9, *["%d"] * 5], 1 << 20)
    lines = out.getvalue().split(b"\n", 3)
    assert lines[0].startswith(b"# calibd.applied/1: ") and lines[2].startswith(b"time_s,gyro_x_rad_s,")
    assert lines[3] == expected

"""The decoder works out each (layout, format) once and reuses it: every layout in every unit,
range and PPS mode, decoded one after another, gives what the datasheet's definition gives
(big-endian counts times the LSB), computed here one value at a time."""

import itertools
import math

import numpy as np
import pytest

from stim300.codec import CHUNK, SAMPLE_DTYPE, Columns, decode_at, decode_frames
from stim300.protocol import (CLUSTERS, NORMAL_LAYOUTS, TEMP_LSB, AccUnit, Format, GyroUnit, PpsUnit, acc_lsb,
                              gyro_lsb, incl_lsb)

RANGES = (2, 5, 10, 30, 80, (10, 30, 80))  # one for all axes, or one per axis


def reference_row(frame: bytes, layout, fmt: Format) -> dict:
    """One datagram decoded from the definition, one value at a time."""
    off = layout.offsets

    def count(offset: int, size: int, signed: bool = True) -> int:
        return int.from_bytes(frame[offset:offset + size], "big", signed=signed)

    lsbs = {"gyro": [gyro_lsb(fmt.gyro_unit)] * 3, "acc": [acc_lsb(fmt.acc_unit, r) for r in fmt.acc_ranges_g],
            "incl": [incl_lsb(fmt.incl_unit)] * 3}
    row = {"datagram_id": layout.datagram_id, "counter": frame[off["counter"]],
           "latency_us": count(off["latency"], 2, signed=False)}
    for name in CLUSTERS:
        there = name in layout.clusters
        row[name] = [count(off[name] + 3 * k, 3) * lsbs[name][k] if there else math.nan for k in range(3)]
        row["status_" + name] = frame[off["status_" + name]] if there else 0
        there = name in layout.temperatures
        row["temp_" + name] = [count(off["temp_" + name] + 2 * k, 2) * TEMP_LSB if there else math.nan
                               for k in range(3)]
        row["status_temp_" + name] = frame[off["status_temp_" + name]] if there else 0
    if layout.aux == "pps":
        filtered = fmt.pps_unit in (PpsUnit.FILTERED, PpsUnit.FILTERED_DELAYED)  # unsigned, 2^-22 (DS 7.5.2.2)
        row["aux"] = count(off["aux"], 3, signed=not filtered) * (2.0**-22 if filtered else 1.0)
    elif layout.aux == "aux":
        row["aux"] = count(off["aux"], 3) * (5.0 / 2**24)
    else:
        row["aux"] = math.nan
    row["status_aux"] = frame[off["status_aux"]] if layout.aux else 0
    return row


def assert_rows_equal(decoded, frames: np.ndarray, layout, fmt: Format) -> None:
    for k, frame in enumerate(frames):
        expected = reference_row(frame.tobytes(), layout, fmt)
        for name, value in expected.items():
            got = np.asarray(decoded[name][k], SAMPLE_DTYPE[name].base)
            want = np.asarray(value, SAMPLE_DTYPE[name].base)
            assert np.array_equal(got, want, equal_nan=True), (hex(layout.datagram_id), fmt, k, name, got, want)


@pytest.mark.parametrize("ident", sorted(NORMAL_LAYOUTS))
def test_every_format_decodes_as_the_datasheet_defines_it(ident):
    """Random bytes (every sign and every bit of the unsigned PPS), the formats of one layout taken
    in turn, so a decoder that kept one format's scales for another fails."""
    layout = NORMAL_LAYOUTS[ident]
    rng = np.random.default_rng(ident)
    cases = itertools.product(GyroUnit, AccUnit, PpsUnit)
    for n, (gyro, acc, pps) in enumerate(cases):
        fmt = Format(datagram_id=ident, gyro_unit=gyro, acc_unit=acc, incl_unit=list(AccUnit)[-1 - n % 5],
                     acc_range_g=RANGES[n % len(RANGES)], pps_unit=pps)
        frames = rng.integers(0, 256, (4, layout.wire_length(False)), dtype=np.uint8)
        rows = np.empty(len(frames), SAMPLE_DTYPE)
        decode_frames(frames, layout, fmt, rows)
        assert_rows_equal(rows, frames, layout, fmt)
        gaps = [rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8) for _ in frames]  # as a read puts them
        data = np.concatenate([part for gap, frame in zip(gaps, frames) for part in (gap, frame)])
        offsets = np.cumsum([len(gap) + (k and frames.shape[1]) for k, gap in enumerate(gaps)])
        decode_at(data, offsets, layout, fmt, rows)
        assert_rows_equal(rows, frames, layout, fmt)


def test_columns_strided_frames_and_host_times():
    """The same decoding into one array per field, from every other row of a larger array, more
    rows than one chunk, with a host time per datagram."""
    layout, fmt = NORMAL_LAYOUTS[0xF7], Format(datagram_id=0xF7, acc_range_g=(2, 5, 80), pps_unit=PpsUnit.FILTERED)
    frames = np.random.default_rng(1).integers(0, 256, (2 * CHUNK + 6, layout.wire_length(True)), dtype=np.uint8)[::2]
    columns = Columns.empty(len(frames))
    t_host = np.arange(len(frames)) / 8.0
    decode_frames(frames, layout, fmt, columns, t_host)
    assert_rows_equal(columns, frames, layout, fmt)
    assert columns["t_host"].tolist() == t_host.tolist()

"""CRC and normal-datagram codec: check values, real vectors, round trips of every layout."""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from captures import capture, same_samples
from stim300.bulk import decode_capture
from stim300.codec import SAMPLE_DTYPE, decode_frames, encode_samples, seal, subtract_counts
from stim300.crc import SCALAR_ROWS, crc32_mpeg2, crc_columns, datagram_crc
from stim300.protocol import (ACC_RANGE_LSB_EXP, NORMAL_LAYOUTS, AccUnit, Format, GyroUnit, PpsUnit, normal_id,
                              status_names)

VECTORS = Path(__file__).resolve().parent / "vectors"  # real bytes from units; their sources: README there


def test_crc_check_value():
    assert crc32_mpeg2(b"123456789") == 0x0376E6E7


@given(st.lists(st.binary(min_size=13, max_size=13), min_size=1, max_size=20))
def test_crc_columns_equal_scalar(rows):
    frames = np.frombuffer(b"".join(rows), np.uint8).reshape(len(rows), 13)
    expected = [datagram_crc(r) for r in rows]
    assert crc_columns(frames, 13).tolist() == expected


def test_crc_columns_row_by_row_and_by_tables_agree():
    """A few rows go through crcmod, many through the position tables: the same CRCs."""
    frames = np.random.default_rng(0).integers(0, 256, (SCALAR_ROWS + 1, 59), dtype=np.uint8)
    expected = [datagram_crc(row[:55].tobytes()) for row in frames]
    assert crc_columns(frames, 55).tolist() == expected
    assert crc_columns(frames[:SCALAR_ROWS], 55).tolist() == expected[:SCALAR_ROWS]


def test_wire_lengths_match_datasheet_table():
    # DS Table 5-12 (+2 with CR LF), protocol doc §4.3
    wire = {0x90: 18, 0x91: 28, 0x92: 28, 0x93: 38, 0x94: 25, 0xA5: 42, 0xA6: 42, 0xA7: 59,
            0xF0: 22, 0xF3: 42, 0xF4: 29, 0xF7: 63, 0x98: 22, 0x9B: 42, 0x9C: 29, 0xAD: 46, 0xAF: 63, 0x97: 45}
    for ident, length in wire.items():
        assert NORMAL_LAYOUTS[ident].wire_length(False) == length
        assert NORMAL_LAYOUTS[ident].wire_length(True) == length + 2
    dummies = {0x90: 2, 0x91: 0, 0x93: 2, 0x94: 3, 0xA7: 1, 0xF7: 1, 0x97: 3}
    assert {i: NORMAL_LAYOUTS[i].dummy for i in dummies} == dummies


def test_normal_id_derivation():
    assert normal_id(True, True, True, None) == 0xA7
    assert normal_id(True, True, False, None) == 0x93
    assert normal_id(False, False, True, None) == 0x94
    assert normal_id(True, False, True, "pps") == 0xF5
    assert normal_id(True, True, True, "aux") == 0xAF
    assert normal_id(False, False, True, "aux") == 0x9C


def test_status_names():
    assert status_names(0x40) == ["START_UP"]
    assert status_names(0x14) == ["Z", "OVERLOAD"]
    assert status_names(0) == []


def _decode(data: bytes, fmt: Format, crlf: bool) -> np.ndarray:
    layout = NORMAL_LAYOUTS[fmt.datagram_id]
    frames = np.frombuffer(data, np.uint8).reshape(-1, layout.wire_length(crlf))
    out = np.empty(len(frames), SAMPLE_DTYPE)
    decode_frames(frames, layout, fmt, out)
    return out


@pytest.mark.parametrize("ident", sorted(NORMAL_LAYOUTS))
@pytest.mark.parametrize("crlf", [False, True])
def test_round_trip_every_id(ident, crlf):
    data, samples, fmt = capture(50, ident, crlf, seed=ident)
    assert len(data) == 50 * NORMAL_LAYOUTS[ident].wire_length(crlf)
    decoded = _decode(data, fmt, crlf)
    assert same_samples(decoded, samples)
    assert encode_samples(decoded, ident, fmt, crlf).tobytes() == data


@pytest.mark.parametrize("gyro_unit", list(GyroUnit))
@pytest.mark.parametrize("acc_unit", list(AccUnit))
def test_round_trip_every_unit(gyro_unit, acc_unit):
    data, samples, fmt = capture(20, 0xF7, False, gyro_unit=gyro_unit, acc_unit=acc_unit, incl_unit=acc_unit,
                                 pps_unit=PpsUnit.TIME_SINCE_1)
    assert same_samples(_decode(data, fmt, False), samples)


@pytest.mark.parametrize("acc_range", sorted(ACC_RANGE_LSB_EXP))
@pytest.mark.parametrize("pps_unit", list(PpsUnit))
def test_round_trip_every_range(acc_range, pps_unit):
    data, samples, fmt = capture(20, 0xF3, True, acc_range_g=acc_range, pps_unit=pps_unit)
    assert same_samples(_decode(data, fmt, True), samples)


def test_scales_are_the_datasheet_lsbs():
    fmt = Format(acc_range_g=5)
    assert fmt.scales()["gyro"] == 2.0**-14
    assert fmt.scales()["acc"] == 2.0**-20
    assert Format(acc_range_g=80, acc_unit=AccUnit.INCREMENTAL_VELOCITY).scales()["acc"] == 2.0**-19
    assert Format(gyro_unit=GyroUnit.INTEGRATED_ANGLE_DELAYED).scales()["gyro"] == 2.0**-21
    assert Format(incl_unit=AccUnit.INTEGRATED_VELOCITY_MS).scales()["incl"] == 2.0**-25


def test_encoder_saturates_out_of_range_values():
    data, samples, fmt = capture(3, 0x91)
    samples["gyro"][0] = [600.0, -600.0, 1e-9]
    decoded = _decode(encode_samples(samples, 0x91, fmt, False).tobytes(), fmt, False)
    assert decoded["gyro"][0].tolist() == [(2**23 - 1) * 2.0**-14, -(2**23) * 2.0**-14, 0.0]


def _vector(name):
    meta = json.loads((VECTORS / (name + ".json")).read_text())
    return (VECTORS / meta["file"]).read_bytes(), meta


def test_real_0x93_vector_decodes_and_reencodes():
    data, meta = _vector("geneta2580_0x93")
    raw = meta["expected"]["raw_counts"]
    fmt = Format(datagram_id=0x93, crlf=False, acc_range_g=10)
    sample = _decode(data, fmt, False)
    assert (sample["gyro"][0] / 2.0**-14).tolist() == raw["gyro"]
    assert (sample["acc"][0] / 2.0**-19).tolist() == raw["acc"]
    assert (sample["incl"][0] / 2.0**-22).tolist() == raw["incl"]
    assert sample["counter"][0] == raw["counter"]
    assert sample["latency_us"][0] == raw["latency_us"]
    assert encode_samples(sample, 0x93, fmt, False).tobytes() == data


def test_real_0xAF_vector_decodes_and_reencodes():
    data, meta = _vector("geirhovland_0xAF_crlf")
    values = meta["expected"]["source_stated_values"]
    raw = meta["expected"]["raw_counts"]
    fmt = Format(datagram_id=0xAF, crlf=True, acc_range_g=10)
    s = _decode(data, fmt, True)
    assert s["gyro"][0].tolist() == values["gyro_dps"]
    assert s["acc"][0].tolist() == values["acc_g"]
    assert s["incl"][0].tolist() == values["incl_g"]
    assert s["temp_gyro"][0].tolist() == values["temp_gyro_C"]
    assert s["temp_acc"][0].tolist() == values["temp_acc_C"]
    assert s["temp_incl"][0].tolist() == values["temp_incl_C"]
    assert round(s["aux"][0] / (5 / 2**24)) == raw["aux"]
    assert (s["counter"][0], s["latency_us"][0]) == (values["counter"], values["latency_us"])
    assert encode_samples(s, 0xAF, fmt, True).tobytes() == data


@settings(max_examples=30)
@given(st.sampled_from(sorted(NORMAL_LAYOUTS)), st.booleans(), st.integers(0, 2**32 - 1))
def test_round_trip_property(ident, crlf, seed):
    data, samples, fmt = capture(5, ident, crlf, seed=seed)
    assert same_samples(_decode(data, fmt, crlf), samples)


def test_subtracting_counts_shifts_each_axis_saturates_and_reseals():
    data, truth, fmt = capture(50, 0xA7, True, rate=2000, seed=3)
    layout = NORMAL_LAYOUTS[0xA7]
    width = layout.wire_length(True)
    frames = np.frombuffer(data, np.uint8).reshape(50, width).copy()
    frames[0, layout.offsets["gyro"]:layout.offsets["gyro"] + 3] = (0x80, 0x00, 0x01)  # the most negative + 1
    counts = np.array([5, -7, 0], np.int32)
    subtract_counts(frames, layout.offsets["gyro"], counts)
    seal(frames, layout)
    decoded = decode_capture(frames.tobytes(), fmt)
    assert decoded.info.stats.crc_errors == 0 and len(decoded.samples) == 50  # every CRC written again
    lsb = fmt.scales()["gyro"]
    shifted = truth["gyro"][1:].astype(np.float64) - counts * lsb
    assert np.array_equal(decoded.samples["gyro"][1:], shifted.astype(np.float32))
    assert decoded.samples["gyro"][0, 0] == np.float32(-(1 << 23) * lsb)  # saturated, not wrapped round
    assert np.array_equal(decoded.samples["acc"], truth["acc"])  # other clusters untouched

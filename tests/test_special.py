"""Special datagrams: round trips, wire lengths, CRC, and byte-level checks against protocol doc §8."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stim300.crc import datagram_crc
from stim300.protocol import CONFIGURATION, SPECIAL_IDS, AccUnit, Format, GyroUnit, PpsUnit
from stim300.special import (
    BiasTrimOffset,
    Configuration,
    ExtendedError,
    Parity,
    PartNumber,
    SerialNumber,
    UndefinedCode,
    decode_special,
    encode_special,
)

# ---------------------------------------------------------------- strategies

HEX = "0123456789ABCDEF"
ACC_RANGES = (2, 5, 10, 30, 80)
LPF = st.sampled_from((16, 33, 66, 131, 262))


def triple(elements):
    return st.tuples(elements, elements, elements)


def _digit_char(value: int) -> str:  # DS Table 5-14 rendering, written independently of the module
    return chr(value + (48 if value < 10 else 55))


@st.composite
def part_numbers(draw):
    nib = st.sampled_from(HEX)
    wide = st.integers(0, 255).map(_digit_char)  # digits 13 and 15 span two nibbles
    d = [draw(nib) for _ in range(12)] + [draw(wide), draw(nib), draw(wide)]
    text = "".join(d[:5]) + "-" + "".join(d[5:12]) + "-" + "".join(d[12:])
    return PartNumber(text, draw(st.characters(max_codepoint=255)))


serial_numbers = st.builds(
    lambda first, digits: SerialNumber(first + digits),
    st.characters(max_codepoint=255), st.text(alphabet=HEX, min_size=14, max_size=14))

configurations = st.builds(
    Configuration,
    revision=st.characters(max_codepoint=255),
    firmware_revision=st.integers(0, 255),
    sample_rate_code=st.integers(0, 5),
    aux_in_datagram=st.booleans(),
    temp_included=st.booleans(),
    incl_included=st.booleans(),
    acc_included=st.booleans(),
    crlf=st.booleans(),
    bit_rate_code=st.sampled_from((0, 1, 2, 3, 15)),
    stop_bits=st.sampled_from((1, 2)),
    parity=st.sampled_from(Parity),
    line_termination=st.booleans(),
    gyro_axes=triple(st.booleans()),
    gyro_unit=st.sampled_from(GyroUnit),
    gyro_lpf_hz=triple(LPF),
    gyro_g_compensation=st.integers(0, 15),
    acc_axes=triple(st.booleans()),
    acc_unit=st.sampled_from(AccUnit),
    acc_lpf_hz=triple(LPF),
    incl_axes=triple(st.booleans()),
    incl_unit=st.sampled_from(AccUnit),
    incl_lpf_hz=triple(LPF),
    pps_unit=st.sampled_from(PpsUnit),
    has_pps_input=st.booleans(),
    pps_lpf_hz=LPF,
    gyro_range_codes=triple(st.integers(0, 15)),
    acc_range_g=triple(st.sampled_from(ACC_RANGES)),
    incl_range_codes=triple(st.integers(0, 15)),
    tov_3v3=st.booleans(),
    tov_toggle_at_startup=st.booleans(),
    bto_at_startup=st.booleans(),
)

extended_errors = st.builds(ExtendedError, st.integers(0, 2**128 - 1))

COUNT24 = st.integers(-(2**23), 2**23 - 1)


@st.composite
def bias_trims(draw, acc_range_g: int = 10):
    acc_lsb = {2: 2.0**-21, 5: 2.0**-20, 10: 2.0**-19, 30: 2.0**-18, 80: 2.0**-16}[acc_range_g]
    vec = lambda lsb: tuple(draw(COUNT24) * lsb for _ in range(3))  # noqa: E731
    return BiasTrimOffset(vec(2.0**-14), vec(acc_lsb), vec(2.0**-22),
                          draw(st.integers(0, 2**32 - 1)), draw(st.integers(0, 2**16 - 1)))


any_special = st.one_of(part_numbers(), serial_numbers, configurations, extended_errors, bias_trims())

# Protocol doc §8: wire length without CR LF, and the (plain, CR LF) ids.
WIRE = {PartNumber: (20, 0xB1, 0xB3), SerialNumber: (20, 0xB5, 0xB7), Configuration: (26, 0xBC, 0xBD),
        ExtendedError: (21, 0xBE, 0xBF), BiasTrimOffset: (40, 0xD1, 0xD2)}
PRE_CRC = {PartNumber: 16, SerialNumber: 16, Configuration: 22, ExtendedError: 17, BiasTrimOffset: 36}


# ---------------------------------------------------------------- generic properties

@given(obj=any_special, crlf=st.booleans())
def test_round_trip_length_id_and_crc(obj, crlf):
    frame = encode_special(obj, crlf)
    wire, plain_id, crlf_id = WIRE[type(obj)]
    pre = PRE_CRC[type(obj)]
    assert len(frame) == wire + (2 if crlf else 0)
    assert frame[0] == (crlf_id if crlf else plain_id)
    assert SPECIAL_IDS[frame[0]] == (obj.kind, crlf)
    assert datagram_crc(frame[:pre]) == int.from_bytes(frame[pre:pre + 4], "big")
    assert frame.endswith(b"\r\n") == crlf
    assert decode_special(frame) == obj
    assert decode_special(frame[:pre]) == obj  # the CRC itself is not needed


@given(range_g=st.sampled_from(ACC_RANGES), data=st.data(), crlf=st.booleans())
def test_bias_trim_round_trip_each_acc_range(range_g, data, crlf):
    obj = data.draw(bias_trims(range_g))
    assert decode_special(encode_special(obj, crlf, acc_range_g=range_g), acc_range_g=range_g) == obj


@given(obj=any_special)
def test_decode_accepts_bytearray_and_memoryview(obj):
    frame = encode_special(obj, False)
    assert decode_special(bytearray(frame)) == obj == decode_special(memoryview(frame))


# ---------------------------------------------------------------- part number / serial number

def test_part_number_example():
    pn = PartNumber("84167-4400003-321", "K")
    frame = encode_special(pn, False)
    # digit 12 = P17, digit 13 = P12 + 16*P16, digit 14 = P13, digit 15 = P14 + 16*P15
    assert frame[1:16] == bytes.fromhex("08 41 67 2D 44 00 00 2D 32 10 03 00 00 00") + b"K"
    assert decode_special(frame) == pn
    assert str(pn) == "84167-4400003-321 REV K"
    assert str(decode_special(encode_special(PartNumber("84167-4400003-321", "-"), True))).endswith("REV -")


def test_part_number_scrambled_digits():
    # P12..P17 = 1,2,3,4,5,6 -> digit 12 = '6', 13 = 1 + 16*5 = 81 -> chr(136), 14 = '2', 15 = 3 + 16*4 = 67
    payload = bytearray(encode_special(PartNumber("00000-0000000-000", "A"), False)[:16])
    payload[9:12] = bytes([0x12, 0x34, 0x56])
    text = decode_special(bytes(payload)).text
    assert text == "00000-0000006-" + chr(81 + 55) + "2" + chr(67 + 55)


@given(nibbles=st.lists(st.integers(0, 15), min_size=20, max_size=20), rev=st.integers(0, 255))
def test_part_number_bytes_round_trip(nibbles, rev):
    """Any payload with reserved bits zero decodes and re-encodes to the same bytes."""
    n = iter(nibbles)
    pair = lambda: next(n) << 4 | next(n)  # noqa: E731
    payload = bytes([next(n), pair(), pair(), 0x2D, pair(), pair(), pair(), 0x2D, pair(), pair(), pair(),
                     0, 0, 0, rev])
    frame = bytes([0xB1]) + payload
    assert decode_special(frame).to_payload() == payload


def test_serial_number_example():
    sn = SerialNumber("N25582405002002")
    frame = encode_special(sn, True)
    assert frame[:16] == bytes.fromhex("B7 4E 25 58 24 05 00 20 02 00 00 00 00 00 00 00")
    assert decode_special(frame) == sn and str(sn) == "N25582405002002"


@pytest.mark.parametrize("make", [
    lambda: PartNumber("84167-4400003321", "K"),  # missing hyphen
    lambda: PartNumber("84167-4400003-321", "KK"),
    lambda: PartNumber("8416G-4400003-321", "K"),  # digit 5 is one nibble
    lambda: PartNumber("84167-4400003-3%1", "K"),  # not a digit character
    lambda: SerialNumber("N2558240500200"),
    lambda: SerialNumber("N2558240500200G"),
    lambda: ExtendedError(-1),
    lambda: ExtendedError(2**128),
    lambda: BiasTrimOffset(gyro=(0.0, 0.0)),
    lambda: BiasTrimOffset(remaining_saves=2**16),
])
def test_invalid_values_rejected(make):
    with pytest.raises(ValueError):
        make()


# ---------------------------------------------------------------- configuration

def test_default_configuration():
    cfg = Configuration.default()
    assert cfg == Configuration()
    assert cfg.datagram_id == 0xA7
    assert cfg.sample_rate_hz == 125 and cfg.bit_rate_bps == 921600
    assert (cfg.stop_bits, cfg.parity, cfg.crlf) == (1, Parity.NONE, False)
    assert cfg.has_pps_input and not cfg.aux_in_datagram
    assert cfg.format == Format(datagram_id=0xA7, crlf=False, sample_rate_hz=125)


def test_build_and_format():
    cfg = Configuration.build(sample_rate_hz=2000, bit_rate_bps=1843200, acc_range_g=5, crlf=True,
                              acc_included=True, incl_included=False, temp_included=False,
                              gyro_unit=GyroUnit.INCREMENTAL_ANGLE, acc_unit=AccUnit.INCREMENTAL_VELOCITY,
                              aux_in_datagram=True, pps_unit=PpsUnit.TIME_SINCE_1)
    assert cfg.acc_range_g == (5, 5, 5) and cfg.bit_rate_code == 3 and cfg.sample_rate_code == 4
    assert cfg.format == Format(datagram_id=0xF1, crlf=True, sample_rate_hz=2000,
                                gyro_unit=GyroUnit.INCREMENTAL_ANGLE, acc_unit=AccUnit.INCREMENTAL_VELOCITY,
                                acc_range_g=5, pps_unit=PpsUnit.TIME_SINCE_1)
    trig = Configuration.build(sample_rate_hz=None, bit_rate_bps=None)
    assert trig.sample_rate_hz is None and trig.external_trigger and trig.bit_rate_bps is None
    assert trig.format.sample_rate_hz is None
    with pytest.raises(ValueError):
        Configuration.build(sample_rate_hz=100)
    with pytest.raises(ValueError):
        Configuration.build(bit_rate_bps=115200)


def test_configuration_normalises_values():
    cfg = Configuration(gyro_unit=8, acc_axes=[1, 0, 1], parity=2)
    assert cfg.gyro_unit is GyroUnit.RATE_DELAYED and cfg.parity is Parity.ODD
    assert cfg.acc_axes == (True, False, True) and type(cfg.acc_axes) is tuple


# rows of protocol doc §4.2: (acc, incl, temp) -> (plain, PPS, AUX-era) ids
ID_TABLE = {
    (0, 0, 0): (0x90, 0xF0, 0x98), (1, 0, 0): (0x91, 0xF1, 0x99), (0, 1, 0): (0x92, 0xF2, 0x9A),
    (1, 1, 0): (0x93, 0xF3, 0x9B), (0, 0, 1): (0x94, 0xF4, 0x9C), (1, 0, 1): (0xA5, 0xF5, 0xAD),
    (0, 1, 1): (0xA6, 0xF6, 0xAE), (1, 1, 1): (0xA7, 0xF7, 0xAF),
}


@pytest.mark.parametrize("content", ID_TABLE)
def test_datagram_id_matches_doc_tables(content):
    acc, incl, temp = map(bool, content)
    base = Configuration(acc_included=acc, incl_included=incl, temp_included=temp)
    plain, pps, aux = ID_TABLE[content]
    assert base.datagram_id == plain  # byte 3 bit 4 clear: no PPS/AUX block, whatever the input kind
    assert dataclasses.replace(base, has_pps_input=False).datagram_id == plain
    assert dataclasses.replace(base, aux_in_datagram=True, has_pps_input=True).datagram_id == pps
    assert dataclasses.replace(base, aux_in_datagram=True, has_pps_input=False).datagram_id == aux


def _frame(**changes) -> bytes:
    return encode_special(dataclasses.replace(Configuration.default(), **changes), changes.get("crlf", False))


def _bits(frame: bytes, byte: int, high: int, low: int) -> int:
    return frame[byte] >> low & ((1 << (high - low + 1)) - 1)


# changed field -> every (byte, high bit, low bit, expected code) it must set; no other bit may change
@pytest.mark.parametrize("changes, expected", [
    (dict(revision="Q"), [(1, 7, 0, ord("Q"))]),
    (dict(firmware_revision=213), [(2, 7, 0, 213)]),
    (dict(sample_rate_code=4), [(3, 7, 5, 0b100)]),  # 2000 Hz
    (dict(sample_rate_code=5), [(3, 7, 5, 0b101)]),  # external trigger
    (dict(aux_in_datagram=True), [(3, 4, 4, 1)]),
    (dict(temp_included=False), [(3, 3, 3, 0)]),
    (dict(incl_included=False), [(3, 2, 2, 0)]),
    (dict(acc_included=False), [(3, 1, 1, 0)]),
    (dict(crlf=True), [(3, 0, 0, 1)]),
    (dict(bit_rate_code=3), [(4, 7, 4, 0b0011)]),
    (dict(bit_rate_code=15), [(4, 7, 4, 0b1111)]),
    (dict(stop_bits=2), [(4, 3, 3, 1)]),
    (dict(parity=Parity.EVEN), [(4, 2, 1, 0b01)]),
    (dict(parity=Parity.ODD), [(4, 2, 1, 0b10)]),
    (dict(line_termination=True), [(4, 0, 0, 1)]),
    (dict(gyro_axes=(True, False, True)), [(5, 6, 4, 0b101)]),
    (dict(gyro_unit=GyroUnit.RATE_DELAYED), [(5, 3, 0, 8)]),
    (dict(gyro_unit=GyroUnit.INTEGRATED_ANGLE_DELAYED), [(5, 3, 0, 11)]),
    (dict(gyro_lpf_hz=(16, 33, 131)), [(6, 6, 4, 0b000), (6, 2, 0, 0b001), (7, 6, 4, 0b011)]),
    (dict(gyro_g_compensation=15), [(7, 3, 0, 15)]),
    (dict(acc_axes=(False, True, True)), [(8, 6, 4, 0b011)]),
    (dict(acc_unit=AccUnit.INTEGRATED_VELOCITY_MS), [(8, 3, 0, 4)]),
    (dict(acc_lpf_hz=(66, 262, 33)), [(9, 6, 4, 0b010), (9, 2, 0, 0b100), (10, 6, 4, 0b001)]),
    (dict(incl_axes=(True, True, False)), [(11, 6, 4, 0b110)]),
    (dict(incl_unit=AccUnit.INCREMENTAL_VELOCITY), [(11, 3, 0, 1)]),
    (dict(incl_lpf_hz=(33, 66, 131)), [(12, 6, 4, 0b001), (12, 2, 0, 0b010), (13, 6, 4, 0b011)]),
    (dict(pps_unit=PpsUnit.TIME_SINCE_1), [(13, 3, 0, 3)]),
    (dict(has_pps_input=False), [(14, 3, 3, 0)]),
    (dict(pps_lpf_hz=262), [(14, 2, 0, 0b100)]),
    (dict(gyro_range_codes=(1, 2, 3)), [(15, 7, 4, 1), (15, 3, 0, 2), (16, 7, 4, 3)]),
    (dict(acc_range_g=(5, 10, 10)), [(17, 7, 4, 0b0011)]),  # X only
    (dict(acc_range_g=(10, 30, 80)), [(17, 7, 4, 0b0000), (17, 3, 0, 0b0100), (18, 7, 4, 0b0110)]),
    (dict(acc_range_g=(2, 2, 2)), [(17, 7, 4, 0b0010), (17, 3, 0, 0b0010), (18, 7, 4, 0b0010)]),
    (dict(incl_range_codes=(4, 5, 6)), [(19, 7, 4, 4), (19, 3, 0, 5), (20, 7, 4, 6)]),
    (dict(tov_3v3=True), [(21, 3, 3, 1)]),
    (dict(tov_toggle_at_startup=True), [(21, 2, 2, 1)]),
    (dict(bto_at_startup=True), [(21, 1, 1, 1)]),
])
def test_configuration_byte_map(changes, expected):
    frame = _frame(**changes)
    default = _frame(crlf=changes.get("crlf", False))
    allowed = bytearray(len(frame))
    for byte, high, low, code in expected:
        assert _bits(frame, byte, high, low) == code, (byte, high, low)
        allowed[byte] |= ((1 << (high - low + 1)) - 1) << low
    assert all((a ^ b) & ~m == 0 for a, b, m in zip(frame[1:22], default[1:22], allowed[1:22]))


def test_configuration_crlf_id_and_default_bytes():
    frame = _frame(crlf=True)
    assert frame[0] == 0xBD and frame[3] & 1 and frame.endswith(b"\r\n")
    # default: 125 Hz, no PPS in datagram, temp+incl+acc, no CR LF; 921600 8N1; all active, unit 0;
    # LPF 262/262/262; acc LPF 262; incl 16; has PPS input, PPS LPF 16; ranges 0; byte 21 clear
    assert encode_special(Configuration(), False)[:22] == bytes.fromhex(
        "BC 4B 00 0E 20 70 44 40 70 44 40 70 00 00 08 00 00 00 00 00 00 00")


# reserved bits of bytes 1..21 (protocol doc §8.1)
RESERVED = {5: 0x80, 6: 0x88, 7: 0x80, 8: 0x80, 9: 0x88, 10: 0x8F, 11: 0x80, 12: 0x88, 13: 0x80,
            14: 0xF0, 16: 0x0F, 18: 0x0F, 20: 0x0F, 21: 0xF1}


@given(cfg=configurations, crlf=st.booleans())
def test_configuration_reserved_bits_zero_and_ignored(cfg, crlf):
    frame = bytearray(encode_special(cfg, crlf))
    assert all(frame[b] & m == 0 for b, m in RESERVED.items())
    for b, m in RESERVED.items():
        frame[b] |= m
    assert decode_special(bytes(frame)) == cfg


@pytest.mark.parametrize("byte, mask, code", [
    (5, 0x0F, 4),  # gyro unit 4 (VX's "delayed" coding; undefined in DS rev.31)
    (5, 0x0F, 5),  # gyro unit 5: likewise
    (8, 0x0F, 5),  # acc unit 5
    (11, 0x0F, 7),  # incl unit 7
    (13, 0x0F, 4),  # PPS unit 4
    (17, 0xF0, 0b0001 << 4),  # acc range nibble 0001
    (18, 0xF0, 0b0111 << 4),  # acc range Z nibble 0111
])
def test_configuration_undefined_codes_values_depend_on_are_rejected(byte, mask, code):
    """Units and ranges decide every decoded value: an undefined one refuses the configuration."""
    frame = bytearray(encode_special(Configuration(), False))
    frame[byte] = frame[byte] & ~mask | code
    with pytest.raises(ValueError, match="not defined in the byte map.*cannot be decoded without it"):
        decode_special(bytes(frame))


@pytest.mark.parametrize("byte, mask, code, field, value", [
    (3, 0xE0, 0b110 << 5, "sample_rate_code", 6),  # the rate is then inferred from the counter
    (4, 0xF0, 0b0100 << 4, "bit_rate_code", 4),
    (4, 0x06, 0b11 << 1, "parity", 3),
    (6, 0x70, 0b101 << 4, "gyro_lpf_hz", 5),
])
def test_configuration_other_undefined_codes_are_kept_as_read_with_a_warning(byte, mask, code, field, value):
    frame = bytearray(encode_special(Configuration(), False))
    frame[byte] = frame[byte] & ~mask | code
    covered = bytes(frame[:CONFIGURATION.pre_crc])
    frame[CONFIGURATION.pre_crc:CONFIGURATION.pre_crc + 4] = datagram_crc(covered).to_bytes(4, "big")
    cfg = decode_special(bytes(frame))
    kept = getattr(cfg, field)
    assert UndefinedCode(value) in (kept if isinstance(kept, tuple) else (kept,))
    assert len(cfg.warnings) == 1 and field in cfg.warnings[0] and f"{value:#x}" in cfg.warnings[0]
    assert encode_special(cfg, False) == bytes(frame)  # kept as read: the same bytes again
    assert cfg.format.datagram_id == 0xA7 and cfg.format.gyro_unit == GyroUnit.RATE


def test_a_5g_incremental_angle_unit_with_an_undefined_bit_rate_decodes():
    """A real unit's configuration: 5 g, incremental-angle gyro output, bit-rate code 4."""
    cfg = decode_special(bytes.fromhex("bc4b1f06407144407044407044400c00003330000000a91f9809"))
    assert cfg.format == Format(datagram_id=0x93, crlf=False, sample_rate_hz=125,
                                gyro_unit=GyroUnit.INCREMENTAL_ANGLE, acc_range_g=5)
    assert cfg.bit_rate_code == UndefinedCode(4) and cfg.bit_rate_bps is None
    assert cfg.as_dict()["bit_rate_code"] == "undefined code 0x4"
    assert cfg.warnings and "bit_rate_code" in cfg.warnings[0]


def test_per_axis_accelerometer_ranges_reach_the_format():
    cfg = Configuration(acc_range_g=(5, 10, 30))
    assert cfg.format.acc_ranges_g == (5, 10, 30) and cfg.format.scales()["acc"] == (2.0**-20, 2.0**-19, 2.0**-18)
    assert Configuration(acc_range_g=(5, 5, 5)).format.acc_range_g == 5  # one range: the scalar as before


@pytest.mark.parametrize("changes", [
    dict(sample_rate_code=6), dict(bit_rate_code=4), dict(stop_bits=0), dict(gyro_unit=4),
    dict(gyro_unit=UndefinedCode(5)), dict(bit_rate_code=UndefinedCode(2)),
    dict(gyro_lpf_hz=(16, 16, 17)), dict(acc_range_g=(10, 10)), dict(acc_range_g=(10, 10, 20)),
    dict(gyro_g_compensation=16), dict(revision="KK"), dict(revision="\u20ac"), dict(firmware_revision=256),
])
def test_configuration_invalid_fields_rejected(changes):
    with pytest.raises(ValueError):
        Configuration(**changes)


# ---------------------------------------------------------------- extended error

def test_extended_error_flags_and_byte_order():
    bits = 1 << 16 | 1 << 0 | 1 << 2 | 1 << 46 | 1 << 57 | 1 << 62 | 1 << 68 | 1 << 103 | 1 << 112 | 1 << 127
    err = ExtendedError(bits)
    assert err.flags() == ["gyro_x_excitation", "gyro_z_excitation", "start_up", "acc_y_clipped",
                           "flash_check", "stack_warning_3", "uart_unable_to_transmit", "gyro_z_overload",
                           "pps_time_overflow", "E127"]
    assert ExtendedError().flags() == []
    assert ExtendedError(1 << 3).flags() == ["E3"]
    assert encode_special(ExtendedError(1 << 127), False)[1:17] == b"\x80" + bytes(15)  # byte 1 = E127..E120
    assert encode_special(ExtendedError(1), False)[1:17] == bytes(15) + b"\x01"


def test_extended_error_named_bits():
    named = {16: "start_up", 56: "ram_check", 58: "internal_dac", 59: "supply_overvoltage",
             10: "gyro_x_clipped", 53: "incl_z_clipped", 65: "gyro_x_data_missing", 104: "acc_x_overload",
             109: "incl_z_overload", 60: "stack_warning_1", 64: "stack_warning_5"}
    for bit, name in named.items():
        assert ExtendedError(1 << bit).flags() == [name]


# ---------------------------------------------------------------- bias trim offset

def test_bias_trim_scaling_and_layout():
    bto = BiasTrimOffset(gyro=(1.0, -2.0**-14, 0.0), acc=(2.0**-20, 0.0, -0.5), incl=(0.0, 0.0, 2.0**-22),
                         reference_info=0x01020304, remaining_saves=0x0506)
    frame = encode_special(bto, False, acc_range_g=5)
    assert frame[0] == 0xD1
    assert frame[1:10] == bytes.fromhex("004000 FFFFFF 000000")  # 1 deg/s = 2^14 counts
    assert frame[10:19] == bytes.fromhex("000001 000000 F80000")  # 5 g range: 2^-20 g per count
    assert frame[19:28] == bytes.fromhex("000000 000000 000001")
    assert frame[28:36] == bytes.fromhex("01020304 0506 0000")
    assert decode_special(frame, acc_range_g=5) == bto
    # the same bytes read with the 10 g LSB give twice the acc values
    assert decode_special(frame).acc == (2.0**-19, 0.0, -1.0)


def test_bias_trim_encode_rounds_and_checks_range():
    frame = encode_special(BiasTrimOffset(gyro=(1.4 * 2.0**-14, 0.0, 0.0)), False)
    assert frame[1:4] == b"\x00\x00\x01"
    for bad in [dict(gyro=(512.0, 0.0, 0.0)), dict(acc=(float("nan"), 0.0, 0.0)),
                dict(incl=(float("inf"), 0.0, 0.0))]:
        with pytest.raises(ValueError):
            encode_special(BiasTrimOffset(**bad), False)
    with pytest.raises(ValueError):
        encode_special(BiasTrimOffset(), False, acc_range_g=7)


# ---------------------------------------------------------------- decode_special errors

def test_decode_special_errors():
    with pytest.raises(ValueError, match="not a special datagram id"):
        decode_special(bytes([0x90]) + bytes(40))
    with pytest.raises(ValueError, match="empty"):
        decode_special(b"")
    frame = encode_special(Configuration(), False)
    with pytest.raises(ValueError, match="needs 22 bytes"):
        decode_special(frame[:21])
    with pytest.raises(TypeError):
        encode_special(Format(), False)


def test_bias_trim_acc_counts_are_scaled_by_each_axis_range():
    """A unit of mixed accelerometer ranges scales each axis's trim counts by its own range, as its
    normal datagrams scale each axis; the live parser decodes them with the configuration's."""
    from stim300.protocol import AccUnit, acc_lsb
    from stim300.stream import StreamParser

    ranges = (10, 30, 80)
    counts = (1000, -2000, 3000)
    acc = tuple(c * acc_lsb(AccUnit.ACCELERATION, r) for c, r in zip(counts, ranges))
    trim = BiasTrimOffset((163 * 2.0**-14, 0.0, 0.0), acc, (0.0, 0.0, 2.0**-20), 5, 9000)  # whole counts
    payload = trim.to_payload(ranges)
    assert [int.from_bytes(payload[9 + 3 * k:12 + 3 * k], "big", signed=True) for k in range(3)] == list(counts)
    assert BiasTrimOffset.from_payload(payload, ranges) == trim
    assert BiasTrimOffset.from_payload(payload, 10).acc != acc  # one range for all would misread Y and Z
    config = dataclasses.replace(Configuration.build(sample_rate_hz=125), acc_range_g=ranges)
    parser = StreamParser()
    parser.feed(encode_special(config, False) + encode_special(trim, False, ranges))
    parser.finish()
    assert parser.scanner.specials[-1] == trim

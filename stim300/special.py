"""Special (Init-Mode / on-request) datagrams <-> Python objects.

Part Number, Serial Number, Configuration, Extended Error Information and Bias Trim Offset
(protocol doc §8, §8.1). Every class turns into exactly the payload it was decoded from; reserved
bits and bytes are written as zero and ignored when read. Byte numbers below are the datasheet's
(ID = byte 0), so they can be checked against the doc table by eye.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import IntEnum
from typing import Any, ClassVar, Sequence

from .crc import datagram_crc
from .errors import FormatError
from .protocol import (
    BIAS_TRIM,
    CONFIGURATION,
    CR_LF,
    DEFAULT_BIT_RATE,
    EXTENDED_ERROR,
    GYRO_RATE_LSB,
    INCL_ACC_LSB,
    PART_NUMBER,
    SAMPLE_RATES_HZ,
    SERIAL_NUMBER,
    SPECIAL_IDS,
    STANDARD_BIT_RATES,
    AccUnit,
    Format,
    GyroUnit,
    PpsUnit,
    SpecialKind,
    acc_lsb,
    normal_id,
    special_id,
)

__all__ = [
    "BiasTrimOffset",
    "Configuration",
    "EXTENDED_ERROR_NAMES",
    "EXTERNAL_TRIGGER_CODE",
    "ExtendedError",
    "UndefinedCode",
    "Parity",
    "PartNumber",
    "SerialNumber",
    "SpecialDatagram",
    "decode_special",
    "encode_special",
]


# ---------------------------------------------------------------- small shared helpers

def _char_byte(char: str, name: str) -> int:
    """One text character as one byte; latin-1 so that every byte value decodes and re-encodes."""
    if not isinstance(char, str) or len(char) != 1 or ord(char) > 0xFF:
        raise FormatError(f"{name} must be a single character U+0000..U+00FF, got {char!r}")
    return ord(char)


def _value_char(value: int) -> str:
    """DS Table 5-14 digit rendering: +48 below 10, else +55 (10 -> 'A')."""
    return chr(value + (48 if value < 10 else 55))


def _char_value(char: str, limit: int, name: str) -> int:
    """Inverse of `_value_char`, refusing values that do not fit the nibble(s) behind them."""
    code = ord(char) if isinstance(char, str) and len(char) == 1 else -1
    value = code - 48 if 48 <= code <= 57 else code - 55 if code >= 65 else -1
    if not 0 <= value < limit:
        raise FormatError(f"{name}: character {char!r} does not encode a value 0..{limit - 1}")
    return value


def _uint(value: int, size: int, name: str) -> bytes:
    if not isinstance(value, int) or not 0 <= value < 1 << (8 * size):
        raise FormatError(f"{name} must be an integer 0..{(1 << 8 * size) - 1}, got {value!r}")
    return value.to_bytes(size, "big")


def _acc_lsb(range_g: int) -> float:
    try:
        return acc_lsb(AccUnit.ACCELERATION, range_g)
    except KeyError:
        raise FormatError(f"accelerometer range {range_g!r} g is unknown") from None


def _triple(values: Sequence[Any], name: str) -> tuple:
    values = tuple(values)
    if len(values) != 3:
        raise FormatError(f"{name} needs one value per axis (X, Y, Z), got {values!r}")
    return values


class _Special:
    """What every special datagram class provides (used by `encode_special`/`decode_special`).

    `acc_range_g` only matters to BiasTrimOffset; the others accept and ignore it so that the
    two module functions can treat all classes alike.
    """

    kind: ClassVar[SpecialKind]

    def to_payload(self, acc_range_g: int = 10) -> bytes:
        """Bytes 1 .. pre_crc-1 (between the ID and the CRC)."""
        raise NotImplementedError

    @classmethod
    def from_payload(cls, payload: bytes, acc_range_g: int = 10):
        raise NotImplementedError


# ---------------------------------------------------------------- part number / serial number

# Part-number nibbles P1..P17 per datasheet byte (high, low); index 0 means "always zero".
_PN_BYTES = {1: (0, 1), 2: (2, 3), 3: (4, 5), 5: (6, 7), 6: (8, 9), 7: (10, 11),
             9: (12, 13), 10: (14, 15), 11: (16, 17)}
_PN_FIXED = {4: 0x2D, 8: 0x2D}  # ASCII '-' in the datagram itself
# Text digit (1..15, hyphens not counted) -> (low nibble, high nibble or None): value = low + 16*high.
# Digits 12-15 are scrambled in DS Table 5-14; protocol doc §8.
_PN_DIGITS = {**{d: (d, None) for d in range(1, 12)},
              12: (17, None), 13: (12, 16), 14: (13, None), 15: (14, 15)}
_PN_HYPHENS = (5, 13)  # text positions of the 5-7-3 separators


@dataclass(frozen=True)
class PartNumber(_Special):
    """Part number in its 5-7-3 text form, e.g. "84167-4400003-321", and revision ('K', '-', ...)."""

    kind: ClassVar[SpecialKind] = PART_NUMBER
    text: str
    revision: str

    def __post_init__(self):
        self.to_payload()  # validate now rather than at the first encode

    def __str__(self) -> str:
        return f"{self.text} REV {self.revision}"

    def to_payload(self, acc_range_g: int = 10) -> bytes:
        text = self.text
        if not isinstance(text, str) or len(text) != 17 or any(text[i] != "-" for i in _PN_HYPHENS):
            raise FormatError(f"part number must look like 'DDDDD-DDDDDDD-DDD', got {text!r}")
        digits = [c for i, c in enumerate(text) if i not in _PN_HYPHENS]
        nibbles = [0] * 18
        for digit, (low, high) in _PN_DIGITS.items():
            value = _char_value(digits[digit - 1], 256 if high is not None else 16,
                                f"part number digit {digit}")
            nibbles[low] = value & 0xF
            if high is not None:
                nibbles[high] = value >> 4
        payload = bytearray(PART_NUMBER.pre_crc - 1)
        for byte, (high, low) in _PN_BYTES.items():
            payload[byte - 1] = nibbles[high] << 4 | nibbles[low]
        for byte, value in _PN_FIXED.items():
            payload[byte - 1] = value
        payload[14] = _char_byte(self.revision, "part number revision")  # byte 15
        return bytes(payload)

    @classmethod
    def from_payload(cls, payload: bytes, acc_range_g: int = 10) -> PartNumber:
        nibbles = [0] * 18
        for byte, (high, low) in _PN_BYTES.items():
            nibbles[high], nibbles[low] = payload[byte - 1] >> 4, payload[byte - 1] & 0xF
        digits = [_value_char(nibbles[low] + 16 * (nibbles[high] if high is not None else 0))
                  for low, high in _PN_DIGITS.values()]
        text = "".join(digits[:5]) + "-" + "".join(digits[5:12]) + "-" + "".join(digits[12:])
        return cls(text, chr(payload[14]))


@dataclass(frozen=True)
class SerialNumber(_Special):
    """Serial number text: byte 1 (always 'N') followed by 14 BCD digits, e.g. "N25582405002002"."""

    kind: ClassVar[SpecialKind] = SERIAL_NUMBER
    text: str

    def __post_init__(self):
        self.to_payload()

    def __str__(self) -> str:
        return self.text

    def to_payload(self, acc_range_g: int = 10) -> bytes:
        if not isinstance(self.text, str) or len(self.text) != 15:
            raise FormatError(f"serial number must be 'N' + 14 digits, got {self.text!r}")
        # Hex digits A-F are accepted so any byte pattern round-trips; real units send 0-9.
        values = [_char_value(c, 16, "serial number digit") for c in self.text[1:]]
        digits = bytes(hi << 4 | lo for hi, lo in zip(values[0::2], values[1::2]))
        payload = bytes([_char_byte(self.text[0], "serial number prefix")]) + digits
        return payload.ljust(SERIAL_NUMBER.pre_crc - 1, b"\0")  # bytes 9-15 reserved

    @classmethod
    def from_payload(cls, payload: bytes, acc_range_g: int = 10) -> SerialNumber:
        digits = "".join(_value_char(b >> 4) + _value_char(b & 0xF) for b in payload[1:8])
        return cls(chr(payload[0]) + digits)


# ---------------------------------------------------------------- configuration

class Parity(IntEnum):
    """Parity as coded in configuration byte 4 bits 2-1 (the Service-Mode `t` command uses 1=odd)."""

    NONE = 0
    EVEN = 1
    ODD = 2


@dataclass(frozen=True)
class UndefinedCode:
    """A configuration code the byte map does not define, kept as read: real units send some
    (a bit-rate code of firmware newer than the datasheet) in fields no value depends on."""

    code: int

    def __str__(self) -> str:
        return f"undefined code {self.code:#x}"


class _Table:
    """Bijection between the values of one configuration field and its bit code. `needed`: the
    normal datagrams cannot be decoded without knowing the value (content, units, ranges), so
    an undefined code refuses the configuration; elsewhere it is kept as an `UndefinedCode`."""

    def __init__(self, to_value: dict[int, Any], describe: str | None = None, needed: bool = False):
        self.to_value = to_value
        self.to_code = {value: code for code, value in to_value.items()}
        self.describe = describe or ", ".join(repr(v) for v in to_value.values())
        self.needed = needed

    def code(self, name: str, value: Any) -> int:
        if isinstance(value, UndefinedCode) and not self.needed and value.code not in self.to_value:
            return value.code
        try:
            return self.to_code[value]
        except (KeyError, TypeError):
            raise FormatError(f"configuration {name}={value!r}: expected one of {self.describe}") from None

    def value(self, name: str, code: int) -> Any:
        if code in self.to_value:
            return self.to_value[code]
        if not self.needed:
            return UndefinedCode(code)
        raise FormatError(f"configuration {name}: code {code:#x} is not defined in the byte map "
                          f"(defined: {self.describe}), and the values cannot be "
                          "decoded without it")


def _raw(width: int) -> _Table:
    return _Table({c: c for c in range(1 << width)}, f"0..{(1 << width) - 1}")


def _enum(enum: type[IntEnum], needed: bool = False) -> _Table:
    return _Table({int(m): m for m in enum}, ", ".join(f"{m.name}={int(m)}" for m in enum), needed)


_BOOL = _Table({0: False, 1: True})
_CHAR = _Table({c: chr(c) for c in range(256)}, "one character U+0000..U+00FF")
# low-pass filter code -> -3 dB frequency (Hz): the configuration datagram's and `stim300 config`'s
LPF_HZ = _Table({0b000: 16, 0b001: 33, 0b010: 66, 0b011: 131, 0b100: 262})
_ACC_RANGE_G = _Table({0b0000: 10, 0b0011: 5, 0b0100: 30, 0b0110: 80, 0b0010: 2}, needed=True)  # 2 g: VX only
EXTERNAL_TRIGGER_CODE = 5
USER_BIT_RATE_CODE = 15
_SAMPLE_RATE_HZ = dict(enumerate(SAMPLE_RATES_HZ)) | {EXTERNAL_TRIGGER_CODE: None}  # codes 0..4: 125..2000 Hz
_BIT_RATE_BPS = dict(enumerate(STANDARD_BIT_RATES)) | {USER_BIT_RATE_CODE: None}  # codes 0..3: 374400..1843200

# Field -> (value table, one (byte, lowest bit, width) per axis or a single one). DS Table 5-16.
_CONFIG_MAP: dict[str, tuple[_Table, tuple[tuple[int, int, int], ...]]] = {
    "revision": (_CHAR, ((1, 0, 8),)),
    "firmware_revision": (_raw(8), ((2, 0, 8),)),
    "sample_rate_code": (_Table({c: c for c in _SAMPLE_RATE_HZ}, "0..5"), ((3, 5, 3),)),
    "aux_in_datagram": (_BOOL, ((3, 4, 1),)),
    "temp_included": (_BOOL, ((3, 3, 1),)),
    "incl_included": (_BOOL, ((3, 2, 1),)),
    "acc_included": (_BOOL, ((3, 1, 1),)),
    "crlf": (_BOOL, ((3, 0, 1),)),
    "bit_rate_code": (_Table({c: c for c in _BIT_RATE_BPS}, "0..3 or 15"), ((4, 4, 4),)),
    "stop_bits": (_Table({0: 1, 1: 2}), ((4, 3, 1),)),
    "parity": (_enum(Parity), ((4, 1, 2),)),
    "line_termination": (_BOOL, ((4, 0, 1),)),
    "gyro_axes": (_BOOL, ((5, 6, 1), (5, 5, 1), (5, 4, 1))),
    "gyro_unit": (_enum(GyroUnit, needed=True), ((5, 0, 4),)),
    "gyro_lpf_hz": (LPF_HZ, ((6, 4, 3), (6, 0, 3), (7, 4, 3))),
    "gyro_g_compensation": (_raw(4), ((7, 0, 4),)),
    "acc_axes": (_BOOL, ((8, 6, 1), (8, 5, 1), (8, 4, 1))),
    "acc_unit": (_enum(AccUnit, needed=True), ((8, 0, 4),)),
    "acc_lpf_hz": (LPF_HZ, ((9, 4, 3), (9, 0, 3), (10, 4, 3))),
    "incl_axes": (_BOOL, ((11, 6, 1), (11, 5, 1), (11, 4, 1))),
    "incl_unit": (_enum(AccUnit, needed=True), ((11, 0, 4),)),
    "incl_lpf_hz": (LPF_HZ, ((12, 4, 3), (12, 0, 3), (13, 4, 3))),
    "pps_unit": (_enum(PpsUnit, needed=True), ((13, 0, 4),)),
    "has_pps_input": (_BOOL, ((14, 3, 1),)),
    "pps_lpf_hz": (LPF_HZ, ((14, 0, 3),)),
    "gyro_range_codes": (_raw(4), ((15, 4, 4), (15, 0, 4), (16, 4, 4))),
    "acc_range_g": (_ACC_RANGE_G, ((17, 4, 4), (17, 0, 4), (18, 4, 4))),
    "incl_range_codes": (_raw(4), ((19, 4, 4), (19, 0, 4), (20, 4, 4))),
    "tov_3v3": (_BOOL, ((21, 3, 1),)),
    "tov_toggle_at_startup": (_BOOL, ((21, 2, 1),)),
    "bto_at_startup": (_BOOL, ((21, 1, 1),)),
}


def _field_values(name: str, value: Any, positions: tuple) -> tuple:
    """A field's value as one entry per bit position (per-axis fields are tuples)."""
    return _triple(value, name) if len(positions) > 1 else (value,)


def _lookup(table: dict[int, Any], wanted: Any, what: str) -> int:
    for code, value in table.items():
        if value == wanted:
            return code
    raise FormatError(f"{what} {wanted!r} is not one of {[v for v in table.values()]}")


@dataclass(frozen=True)
class Configuration(_Special):
    """Every field of the configuration datagram (protocol doc §8.1, DS Table 5-16).

    The field defaults describe a typical unit, chosen by us (not read from a datasheet default
    table): revision 'K', firmware 0, full 0xA7 content (acc + incl + all temperatures, PPS input
    present but not in the datagram), 125 Hz, no CR LF, 921600 bit/s 8N1 without line termination,
    all axes active, rate / acceleration / acceleration / filtered-PPS units, LPF gyro 262, acc
    262, incl 16, PPS 16 Hz, g-compensation preset 0, ±400 deg/s, ±10 g, ±1.7 g (codes 0), TOV 5 V,
    no TOV toggling or bias-trim datagram at start-up. Use `build()` or `dataclasses.replace`
    to change it. Values are normalised on construction (ints -> enums, lists -> tuples).
    """

    kind: ClassVar[SpecialKind] = CONFIGURATION

    revision: str = "K"  # byte 1: part-number revision
    firmware_revision: int = 0  # byte 2
    sample_rate_code: int = 0  # byte 3 bits 7-5: 0..4 = 125..2000 Hz, 5 = external trigger
    aux_in_datagram: bool = False  # byte 3 bit 4: PPS (PPS units) / AUX (AUX-era units) in datagram
    temp_included: bool = True  # byte 3 bit 3
    incl_included: bool = True  # byte 3 bit 2
    acc_included: bool = True  # byte 3 bit 1
    crlf: bool = False  # byte 3 bit 0: Normal (and special) datagrams end with CR LF
    bit_rate_code: int = 2  # byte 4 bits 7-4: see bit_rate_bps; 15 = user-defined
    stop_bits: int = 1  # byte 4 bit 3
    parity: Parity = Parity.NONE  # byte 4 bits 2-1
    line_termination: bool = False  # byte 4 bit 0: RS422 120 ohm receiver termination
    gyro_axes: tuple[bool, bool, bool] = (True, True, True)  # X, Y, Z active
    gyro_unit: GyroUnit = GyroUnit.RATE
    gyro_lpf_hz: tuple[int, int, int] = (262, 262, 262)
    gyro_g_compensation: int = 0  # preset 0..12, 15 = user-defined
    acc_axes: tuple[bool, bool, bool] = (True, True, True)
    acc_unit: AccUnit = AccUnit.ACCELERATION
    acc_lpf_hz: tuple[int, int, int] = (262, 262, 262)
    incl_axes: tuple[bool, bool, bool] = (True, True, True)
    incl_unit: AccUnit = AccUnit.ACCELERATION
    incl_lpf_hz: tuple[int, int, int] = (16, 16, 16)
    pps_unit: PpsUnit = PpsUnit.FILTERED
    has_pps_input: bool = True  # byte 14 bit 3: False = unit has an AUX input instead
    pps_lpf_hz: int = 16
    gyro_range_codes: tuple[int, int, int] = (0, 0, 0)  # 0 = ±400 deg/s
    acc_range_g: tuple[int, int, int] = (10, 10, 10)
    incl_range_codes: tuple[int, int, int] = (0, 0, 0)  # 0 = ±1.7 g
    tov_3v3: bool = False  # byte 21 bit 3: TOV logic level 3.3 V (else 5 V)
    tov_toggle_at_startup: bool = False  # byte 21 bit 2
    bto_at_startup: bool = False  # byte 21 bit 1: bias trim offset datagram in the start-up sequence

    def __post_init__(self):
        # Round-trip every field through its code: validates and normalises in one go.
        for name, (table, positions) in _CONFIG_MAP.items():
            values = tuple(table.value(name, table.code(name, v))
                           for v in _field_values(name, getattr(self, name), positions))
            object.__setattr__(self, name, values if len(positions) > 1 else values[0])

    @classmethod
    def default(cls) -> Configuration:
        """The typical unit described in the class docstring."""
        return cls()

    @classmethod
    def build(cls, *, sample_rate_hz: int | None = 125, bit_rate_bps: int | None = DEFAULT_BIT_RATE,
              acc_range_g: int = 10, **fields_: Any) -> Configuration:
        """Default configuration with rate (None = external trigger), bit-rate (None = user-defined)
        and accelerometer range (all axes) in physical units; any other field by name."""
        return cls(sample_rate_code=_lookup(_SAMPLE_RATE_HZ, sample_rate_hz, "sample rate"),
                   bit_rate_code=_lookup(_BIT_RATE_BPS, bit_rate_bps, "bit-rate"),
                   acc_range_g=(acc_range_g,) * 3, **fields_)

    @property
    def sample_rate_hz(self) -> int | None:
        """Samples per second; None when the unit is externally triggered (or the code undefined)."""
        return _SAMPLE_RATE_HZ.get(self.sample_rate_code)

    @property
    def external_trigger(self) -> bool:
        return self.sample_rate_code == EXTERNAL_TRIGGER_CODE

    @property
    def bit_rate_bps(self) -> int | None:
        """Standard bit-rate; None for a user-defined one (its value is not in this datagram)."""
        return _BIT_RATE_BPS.get(self.bit_rate_code)

    @property
    def aux_kind(self) -> str | None:
        """What byte 3 bit 4 adds to the Normal datagram: "pps", "aux" (AUX-era unit) or None."""
        if not self.aux_in_datagram:
            return None
        return "pps" if self.has_pps_input else "aux"

    @property
    def datagram_id(self) -> int:
        """Normal datagram id this configuration produces (protocol doc §8.1 'Derivation')."""
        return normal_id(self.acc_included, self.incl_included, self.temp_included, self.aux_kind)

    @property
    def format(self) -> Format:
        """What the Normal-datagram decoder needs, the accelerometer range of each axis included."""
        return Format(datagram_id=self.datagram_id, crlf=self.crlf, sample_rate_hz=self.sample_rate_hz,
                      gyro_unit=self.gyro_unit, acc_unit=self.acc_unit, acc_range_g=self.acc_range_g,
                      incl_unit=self.incl_unit, pps_unit=self.pps_unit)

    @property
    def warnings(self) -> tuple[str, ...]:
        """One line per field holding a code the byte map does not define (kept as read)."""
        out = []
        for name in _CONFIG_MAP:
            values = getattr(self, name)
            for value in values if isinstance(values, tuple) else (values,):
                if isinstance(value, UndefinedCode):
                    out.append(f"configuration {name}: {value} (not in the byte map), kept as read: "
                               "no decoded value depends on it")
        return tuple(dict.fromkeys(out))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready view: enums by name, plus the derived rate, bit-rate and datagram id."""
        def plain(value):
            if isinstance(value, tuple):
                return [plain(v) for v in value]
            if isinstance(value, UndefinedCode):
                return str(value)
            return value.name if isinstance(value, IntEnum) else value
        out = {f.name: plain(getattr(self, f.name)) for f in fields(self)}
        out.update(sample_rate_hz=self.sample_rate_hz, bit_rate_bps=self.bit_rate_bps,
                   datagram_id=f"0x{self.datagram_id:02X}")
        return out

    def to_payload(self, acc_range_g: int = 10) -> bytes:
        payload = bytearray(CONFIGURATION.pre_crc - 1)
        for name, (table, positions) in _CONFIG_MAP.items():
            values = _field_values(name, getattr(self, name), positions)
            for (byte, shift, _), value in zip(positions, values):
                payload[byte - 1] |= table.code(name, value) << shift
        return bytes(payload)

    @classmethod
    def from_payload(cls, payload: bytes, acc_range_g: int = 10) -> Configuration:
        values = {}
        for name, (table, positions) in _CONFIG_MAP.items():
            axis = tuple(table.value(name, payload[byte - 1] >> shift & ((1 << width) - 1))
                         for byte, shift, width in positions)
            values[name] = axis if len(positions) > 1 else axis[0]
        return cls(**values)


assert set(_CONFIG_MAP) == {f.name for f in fields(Configuration)}, "byte map and fields disagree"


# ---------------------------------------------------------------- extended error information

def _per_axis(first_bit: int, pattern: str) -> dict[int, str]:
    """Three consecutive bits named X, Y, Z (axis order within each group is our assumption)."""
    return {first_bit + i: pattern.format(axis) for i, axis in enumerate("xyz")}


# The bits the protocol doc (§8) names; DS Table 5-19 has more.
EXTENDED_ERROR_NAMES: dict[int, str] = {
    **_per_axis(0, "gyro_{}_excitation"),
    **_per_axis(10, "gyro_{}_clipped"),
    16: "start_up",
    **_per_axis(45, "acc_{}_clipped"),
    **_per_axis(51, "incl_{}_clipped"),
    56: "ram_check",
    57: "flash_check",
    58: "internal_dac",
    59: "supply_overvoltage",
    **{60 + i: f"stack_warning_{i + 1}" for i in range(5)},
    **_per_axis(65, "gyro_{}_data_missing"),
    68: "uart_unable_to_transmit",
    **_per_axis(101, "gyro_{}_overload"),
    **_per_axis(104, "acc_{}_overload"),
    **_per_axis(107, "incl_{}_overload"),
    112: "pps_time_overflow",
}


@dataclass(frozen=True)
class ExtendedError(_Special):
    """The 128-bit error register E127..E0 as one int (bit n = En). Reading it clears it."""

    kind: ClassVar[SpecialKind] = EXTENDED_ERROR
    bits: int = 0

    def __post_init__(self):
        self.to_payload()

    def flags(self) -> list[str]:
        """Names of the set bits, lowest first; "E<n>" for bits without a name here."""
        return [EXTENDED_ERROR_NAMES.get(n, f"E{n}") for n in range(128) if self.bits >> n & 1]

    def to_payload(self, acc_range_g: int = 10) -> bytes:
        return _uint(self.bits, EXTENDED_ERROR.pre_crc - 1, "extended error bits")  # byte 1 = E127..E120

    @classmethod
    def from_payload(cls, payload: bytes, acc_range_g: int = 10) -> ExtendedError:
        return cls(int.from_bytes(payload[:EXTENDED_ERROR.pre_crc - 1], "big"))


# ---------------------------------------------------------------- bias trim offset

def _scaled24(values: tuple[float, ...], lsbs: tuple[float, ...], name: str) -> bytes:
    """Values as 24-bit big-endian two's complement counts of their axis's LSB, rounded to the
    nearest count."""
    out = bytearray()
    for value, lsb in zip(values, lsbs):
        try:
            count = round(value / lsb)
        except (TypeError, ValueError, OverflowError):
            raise FormatError(f"{name}: {value!r} is not a finite number") from None
        if not -(1 << 23) <= count < 1 << 23:
            raise FormatError(f"{name}: {value!r} is outside the 24-bit range of LSB {lsb!r}")
        out += count.to_bytes(3, "big", signed=True)
    return bytes(out)


def _unscaled24(chunk: bytes, lsbs: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(int.from_bytes(chunk[3 * k:3 * k + 3], "big", signed=True) * lsb for k, lsb in enumerate(lsbs))


@dataclass(frozen=True)
class BiasTrimOffset(_Special):
    """User bias trims: gyro in deg/s, acc and incl in g whatever the output units (DS §7.5.2.3).

    The acc counts are in the acceleration LSB of the fitted range, so encoding and decoding
    need that range (`acc_range_g`: one for every axis, default 10 g, or one per axis X, Y, Z, as
    a unit of mixed ranges scales each axis's output by its own).
    """

    kind: ClassVar[SpecialKind] = BIAS_TRIM
    gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc: tuple[float, float, float] = (0.0, 0.0, 0.0)
    incl: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference_info: int = 0
    remaining_saves: int = 0

    def __post_init__(self):
        for name in ("gyro", "acc", "incl"):
            object.__setattr__(self, name, _triple(getattr(self, name), name))
        _uint(self.reference_info, 4, "reference_info")
        _uint(self.remaining_saves, 2, "remaining_saves")

    @staticmethod
    def _lsbs(acc_range_g: int | tuple[int, int, int]) -> dict[str, tuple[float, float, float]]:
        ranges = _triple(acc_range_g, "acc_range_g") if isinstance(acc_range_g, (tuple, list)) else (acc_range_g,) * 3
        return {"gyro": (GYRO_RATE_LSB,) * 3, "acc": tuple(map(_acc_lsb, ranges)), "incl": (INCL_ACC_LSB,) * 3}

    def to_payload(self, acc_range_g: int | tuple[int, int, int] = 10) -> bytes:
        blocks = [_scaled24(getattr(self, name), lsb, name) for name, lsb in self._lsbs(acc_range_g).items()]
        return (b"".join(blocks) + _uint(self.reference_info, 4, "reference_info")
                + _uint(self.remaining_saves, 2, "remaining_saves") + bytes(2))  # bytes 34-35 reserved

    @classmethod
    def from_payload(cls, payload: bytes, acc_range_g: int | tuple[int, int, int] = 10) -> BiasTrimOffset:
        lsbs = cls._lsbs(acc_range_g)
        vectors = {name: _unscaled24(payload[9 * i:9 * i + 9], lsb)
                   for i, (name, lsb) in enumerate(lsbs.items())}
        return cls(**vectors, reference_info=int.from_bytes(payload[27:31], "big"),
                   remaining_saves=int.from_bytes(payload[31:33], "big"))


# ---------------------------------------------------------------- whole datagrams

SpecialDatagram = PartNumber | SerialNumber | Configuration | ExtendedError | BiasTrimOffset

_CLASSES: dict[SpecialKind, type[_Special]] = {
    cls.kind: cls for cls in (PartNumber, SerialNumber, Configuration, ExtendedError, BiasTrimOffset)
}


def encode_special(obj: SpecialDatagram, crlf: bool, acc_range_g: int | tuple[int, int, int] = 10) -> bytes:
    """The datagram as sent: ID (CR LF variant if `crlf`), payload, big-endian CRC, [CR LF]."""
    if not isinstance(obj, _Special):
        raise TypeError(f"{type(obj).__name__} is not a special datagram class")
    kind = obj.kind
    covered = bytes([special_id(kind, crlf)]) + obj.to_payload(acc_range_g)
    assert len(covered) == kind.pre_crc
    return covered + datagram_crc(covered).to_bytes(4, "big") + (CR_LF if crlf else b"")


def decode_special(frame: bytes, acc_range_g: int | tuple[int, int, int] = 10) -> SpecialDatagram:
    """Object for a special datagram starting at its ID byte; the CRC is the caller's job."""
    if not frame:
        raise FormatError("empty frame: no special datagram id")
    entry = SPECIAL_IDS.get(frame[0])
    if entry is None:
        raise FormatError(f"0x{frame[0]:02X} is not a special datagram id")
    kind = entry[0]
    if len(frame) < kind.pre_crc:
        raise FormatError(f"{kind.name} datagram 0x{frame[0]:02X} needs {kind.pre_crc} bytes before "
                         f"the CRC, got {len(frame)}")
    return _CLASSES[kind].from_payload(bytes(frame[1:kind.pre_crc]), acc_range_g)

"""STIM300 protocol tables: datagram identifiers, layouts, lengths, scale factors, status bits.

The facts are Safran's STIM300 datasheet's (TS1524 rev.31), checked against public drivers and real bytes
(tests/vectors).
This module holds tables and the little logic needed to read them; nothing here touches bytes
of a stream.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

from .errors import FormatError

CR_LF = b"\r\n"
COUNTER_MODULUS = 256
INTERNAL_RATE_HZ = 2000  # the counter counts internal 2000 Hz samples
SAMPLE_RATES_HZ = (125, 250, 500, 1000, 2000)
STANDARD_BIT_RATES = (374400, 460800, 921600, 1843200)
DEFAULT_BIT_RATE = 921600


class Status(IntFlag):
    """One status byte per cluster (DS Table 5-23). Not latched: describes that datagram only."""

    X = 0x01
    Y = 0x02
    Z = 0x04
    CHANNEL_ERROR = 0x08
    OVERLOAD = 0x10
    OUTSIDE_OPERATING_CONDITIONS = 0x20
    START_UP = 0x40
    SYSTEM_INTEGRITY_ERROR = 0x80


def status_names(byte: int) -> list[str]:
    """Names of the flags set in one status byte, e.g. ['START_UP'] or ['OVERLOAD', 'Z']."""
    return [flag.name for flag in Status if byte & flag]


class GyroUnit(IntEnum):
    """Gyro output unit codes (configuration byte 5, bits 3-0); 8-11 are the 'delayed' variants."""

    RATE = 0
    INCREMENTAL_ANGLE = 1
    AVERAGE_RATE = 2
    INTEGRATED_ANGLE = 3
    RATE_DELAYED = 8
    INCREMENTAL_ANGLE_DELAYED = 9
    AVERAGE_RATE_DELAYED = 10
    INTEGRATED_ANGLE_DELAYED = 11

    @property
    def is_angle(self) -> bool:
        return self & 0x7 in (1, 3)

    @property
    def symbol(self) -> str:
        return "deg" if self.is_angle else "deg/s"


class AccUnit(IntEnum):
    """Accelerometer / inclinometer output unit codes (configuration bytes 8 and 11)."""

    ACCELERATION = 0
    INCREMENTAL_VELOCITY = 1
    AVERAGE_ACCELERATION = 2
    INTEGRATED_VELOCITY_GS = 3
    INTEGRATED_VELOCITY_MS = 4

    @property
    def is_velocity(self) -> bool:
        return self not in (AccUnit.ACCELERATION, AccUnit.AVERAGE_ACCELERATION)

    @property
    def symbol(self) -> str:
        return {0: "g", 1: "m/s", 2: "g", 3: "g*s", 4: "m/s"}[int(self)]


class PpsUnit(IntEnum):
    """PPS output unit codes (configuration byte 13, bits 3-0)."""

    FILTERED = 0
    FILTERED_DELAYED = 1
    TIME_SINCE_0 = 2
    TIME_SINCE_1 = 3


# Accelerometer range (g) -> log2 of the acceleration LSB in g (DS Eq.3; 2 g from VX only).
ACC_RANGE_LSB_EXP = {2: -21, 5: -20, 10: -19, 30: -18, 80: -16}
GYRO_RATE_LSB = 2.0**-14  # deg/s
GYRO_ANGLE_LSB = 2.0**-21  # deg
INCL_ACC_LSB = 2.0**-22  # g
STANDARD_GRAVITY = 9.80665  # m/s^2 per g: the STIM300's g unit (k0 of the datasheet)
VELOCITY_LSB_SHIFT = -3  # incremental/integrated velocity LSB = acceleration LSB * 2^-3
TEMP_LSB = 2.0**-8  # degC
PPS_FILTERED_LSB = 2.0**-22  # unitless, unsigned
AUX_LSB = 5.0 / 2**24  # volts (AUX-era units; VX/NL, unverified)


def gyro_lsb(unit: GyroUnit) -> float:
    return GYRO_ANGLE_LSB if unit.is_angle else GYRO_RATE_LSB


def acc_lsb(unit: AccUnit, range_g: int) -> float:
    exp = ACC_RANGE_LSB_EXP[range_g]
    return 2.0 ** (exp + (VELOCITY_LSB_SHIFT if unit.is_velocity else 0))


def incl_lsb(unit: AccUnit) -> float:
    return INCL_ACC_LSB * (2.0**VELOCITY_LSB_SHIFT if unit.is_velocity else 1.0)


# ---------------------------------------------------------------- normal datagram layouts

CLUSTERS = ("gyro", "acc", "incl")


@dataclass(frozen=True)
class Layout:
    """Where each block of one normal datagram sits (offsets from the ID byte)."""

    datagram_id: int
    clusters: tuple[str, ...]  # measurement clusters present, in wire order
    temperatures: tuple[str, ...]  # clusters whose temperature triple is present
    aux: str | None  # "pps", "aux" or None
    offsets: dict[str, int] = field(compare=False)
    pre_crc: int = 0  # bytes before the CRC, ID included

    @property
    def dummy(self) -> int:
        """Zero bytes appended for the CRC only (DS Table 5-22)."""
        return -self.pre_crc % 4

    def wire_length(self, crlf: bool) -> int:
        return self.pre_crc + 4 + (2 if crlf else 0)

    @property
    def counter_offset(self) -> int:
        return self.offsets["counter"]


def _layout(datagram_id: int, clusters, temperatures, aux) -> Layout:
    offsets: dict[str, int] = {}
    pos = 1
    for name in clusters:
        offsets[name] = pos
        offsets["status_" + name] = pos + 9
        pos += 10
    for name in temperatures:
        offsets["temp_" + name] = pos
        offsets["status_temp_" + name] = pos + 6
        pos += 7
    if aux:
        offsets["aux"] = pos
        offsets["status_aux"] = pos + 3
        pos += 4
    offsets["counter"] = pos
    offsets["latency"] = pos + 1
    return Layout(datagram_id, tuple(clusters), tuple(temperatures), aux, offsets, pos + 3)


def _family() -> dict[int, Layout]:
    # content -> (clusters, temperature triples); low bits of the id: acc=1, incl=2, temp=4
    contents = {
        0x0: (("gyro",), ()),
        0x1: (("gyro", "acc"), ()),
        0x2: (("gyro", "incl"), ()),
        0x3: (("gyro", "acc", "incl"), ()),
        0x4: (("gyro",), ("gyro",)),
        0x5: (("gyro", "acc"), ("gyro", "acc")),
        0x6: (("gyro", "incl"), ("gyro", "incl")),
        0x7: (("gyro", "acc", "incl"), ("gyro", "acc", "incl")),
    }
    base = {0: 0x90, 1: 0x91, 2: 0x92, 3: 0x93, 4: 0x94, 5: 0xA5, 6: 0xA6, 7: 0xA7}
    layouts = {}
    for low, (clusters, temps) in contents.items():
        plain = base[low]
        layouts[plain] = _layout(plain, clusters, temps, None)
        layouts[0xF0 | low] = _layout(0xF0 | low, clusters, temps, "pps")
        layouts[plain + 8] = _layout(plain + 8, clusters, temps, "aux")  # AUX-era 0x98-0x9C, 0xAD-0xAF
    # Legacy (product revision <= C): all clusters, gyro temperatures only.
    layouts[0x97] = _layout(0x97, ("gyro", "acc", "incl"), ("gyro",), None)
    return layouts


NORMAL_LAYOUTS: dict[int, Layout] = _family()


def normal_id(acc: bool, incl: bool, temp: bool, aux: str | None) -> int:
    """Normal datagram id for a content selection (protocol doc §8.1, 'Derivation')."""
    low = int(acc) | int(incl) << 1 | int(temp) << 2
    if aux == "pps":
        return 0xF0 | low
    plain = (0xA0 | low) if temp and (acc or incl) else (0x90 | low)
    return plain + 8 if aux == "aux" else plain


# ---------------------------------------------------------------- special datagrams

@dataclass(frozen=True)
class SpecialKind:
    name: str
    pre_crc: int
    request: bytes  # Normal-mode command that asks for it

    @property
    def dummy(self) -> int:
        return -self.pre_crc % 4


PART_NUMBER = SpecialKind("part_number", 16, b"N\r")
SERIAL_NUMBER = SpecialKind("serial_number", 16, b"I\r")
CONFIGURATION = SpecialKind("configuration", 22, b"C\r")
EXTENDED_ERROR = SpecialKind("extended_error", 17, b"E\r")
BIAS_TRIM = SpecialKind("bias_trim", 36, b"T\r")

# id -> (kind, CR LF terminated)
SPECIAL_IDS: dict[int, tuple[SpecialKind, bool]] = {
    0xB1: (PART_NUMBER, False),
    0xB3: (PART_NUMBER, True),
    0xB5: (SERIAL_NUMBER, False),
    0xB7: (SERIAL_NUMBER, True),
    0xBC: (CONFIGURATION, False),
    0xBD: (CONFIGURATION, True),
    0xBE: (EXTENDED_ERROR, False),
    0xBF: (EXTENDED_ERROR, True),
    0xD1: (BIAS_TRIM, False),
    0xD2: (BIAS_TRIM, True),
}


def special_id(kind: SpecialKind, crlf: bool) -> int:
    return next(i for i, (k, c) in SPECIAL_IDS.items() if k is kind and c == crlf)


# ---------------------------------------------------------------- what a decoder must know

@dataclass(frozen=True)
class Format:
    """Everything needed to turn normal datagrams into physical values.

    Comes from a configuration datagram (`Configuration.format`) or from the user when a capture
    has none. `datagram_id` None means: accept whichever normal id verifies. `acc_range_g` is one
    range for all axes or one per axis (X, Y, Z); three equal ones are kept as one.
    """

    datagram_id: int | None = None
    crlf: bool | None = None  # None: detect from the first datagrams
    sample_rate_hz: int | None = None  # None: infer the counter step from the data (external trigger too)
    gyro_unit: GyroUnit = GyroUnit.RATE
    acc_unit: AccUnit = AccUnit.ACCELERATION
    acc_range_g: int | tuple[int, int, int] = 10
    incl_unit: AccUnit = AccUnit.ACCELERATION
    pps_unit: PpsUnit = PpsUnit.FILTERED

    def __post_init__(self):
        if self.datagram_id is not None and self.datagram_id not in NORMAL_LAYOUTS:
            raise FormatError(f"unknown normal datagram id 0x{self.datagram_id:02X}")
        ranges = tuple(self.acc_range_g) if isinstance(self.acc_range_g, (tuple, list)) else (self.acc_range_g,)
        if len(ranges) not in (1, 3) or any(r not in ACC_RANGE_LSB_EXP for r in ranges):
            raise FormatError(f"accelerometer range {self.acc_range_g} g is not one of "
                              f"{sorted(ACC_RANGE_LSB_EXP)} g (one, or one per axis)")
        object.__setattr__(self, "acc_range_g", ranges[0] if len(set(ranges)) == 1 else ranges)
        if self.sample_rate_hz is not None and self.sample_rate_hz not in SAMPLE_RATES_HZ:
            raise FormatError(f"sample rate {self.sample_rate_hz} Hz is not one of {SAMPLE_RATES_HZ} Hz")

    @property
    def counter_step(self) -> int | None:
        return None if self.sample_rate_hz is None else INTERNAL_RATE_HZ // self.sample_rate_hz

    @property
    def acc_ranges_g(self) -> tuple[int, int, int]:
        """The accelerometer range of each axis (X, Y, Z)."""
        return self.acc_range_g if isinstance(self.acc_range_g, tuple) else (self.acc_range_g,) * 3

    def scales(self) -> dict[str, float | tuple[float, float, float]]:
        """LSB of each value block, in the units of `units()`: one per axis for an accelerometer
        whose axes have different ranges."""
        pps_lsb = PPS_FILTERED_LSB if self.pps_unit in (PpsUnit.FILTERED, PpsUnit.FILTERED_DELAYED) else 1.0
        acc = tuple(acc_lsb(self.acc_unit, r) for r in self.acc_ranges_g)
        return {
            "gyro": gyro_lsb(self.gyro_unit),
            "acc": acc[0] if len(set(acc)) == 1 else acc,
            "incl": incl_lsb(self.incl_unit),
            "temp": TEMP_LSB,
            "pps": pps_lsb,
            "aux": AUX_LSB,
        }

    def units(self) -> dict[str, str]:
        pps = "1" if self.pps_unit in (PpsUnit.FILTERED, PpsUnit.FILTERED_DELAYED) else "us"
        return {"gyro": self.gyro_unit.symbol, "acc": self.acc_unit.symbol, "incl": self.incl_unit.symbol,
                "temp": "degC", "pps": pps, "aux": "V", "latency": "us", "counter": "1"}

    @property
    def pps_unsigned(self) -> bool:
        """Filtered PPS is a 24-bit unsigned value; time-since-PPS is signed (DS §7.5.2.2)."""
        return self.pps_unit in (PpsUnit.FILTERED, PpsUnit.FILTERED_DELAYED)

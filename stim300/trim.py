"""The unit's bias trim offsets (STIM300 datasheet TS1524 rev.31, 7.5.2.3 and 9.2): read the ones
in force, write new ones and a reference, check them, save them to flash.

The unit adds each offset after its own compensation (adjusted = compensated + offset), in deg/s
for the gyros and g for the accelerometers and inclinometers whatever the output unit. Offsets
written with Service Mode `b` are volatile until `s` saves them (9.11 rates the flash to 10,000
saves); `x N` leaves without saving, so they hold until the next power-up. What is in force is
read from the Bias Trim Offset datagram (`T` in Normal Mode), whose counts are the only exact
record: the acc counts are scaled by the accelerometers' range, which the configuration datagram
(`C`) gives, so both are asked for.

This is the driver's part: it writes what it is given and knows no calibration result
(`calibd.trim` decides what to write and when to refuse).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import serial

from .errors import ServiceError, Stim300Error
from .serialread import read_available
from .protocol import GYRO_RATE_LSB, INCL_ACC_LSB, AccUnit, GyroUnit, Status, acc_lsb
from .records import TrimOffsets
from .service import save_to_flash, service_command, service_mode
from .special import BiasTrimOffset, Configuration, SerialNumber
from .stream import StreamParser

SENSORS = ("gyro", "acc", "incl")
SENSOR_LETTERS = {"gyro": "g", "acc": "a", "incl": "i"}
UNITS = {"gyro": "deg/s", "acc": "g", "incl": "g"}
REFERENCE_LIMIT = 1 << 32  # the reference is a 32-bit number


class TrimError(Stim300Error):
    """A trim the unit refused, or that it does not hold as written."""


def trim_lsb(sensor: str, acc_range_g: int) -> float:
    """One count of the T datagram (deg/s for the gyros, g otherwise): the resolution an offset
    is held and read back at."""
    return {"gyro": GYRO_RATE_LSB, "acc": acc_lsb(AccUnit.ACCELERATION, acc_range_g), "incl": INCL_ACC_LSB}[sensor]


@dataclass(frozen=True)
class TrimReading:
    """A Bias Trim Offset datagram as read: the offsets, the 32-bit reference, the flash saves left
    and the accelerometers' range (g; the widest axis's when they differ, each axis's counts
    being scaled by its own): the trim range and the read-back tolerance are taken at it."""

    trims: TrimOffsets
    reference: int
    remaining_saves: int
    acc_range_g: int

    def differences(self, trims: TrimOffsets, reference: int) -> list[str]:
        """What differs from `trims` by more than one count, and a reference that differs; [] when none."""
        found = []
        for sensor in SENSORS:
            lsb = trim_lsb(sensor, self.acc_range_g)
            for axis, held, wanted in zip("xyz", self.trims.of(sensor), trims.of(sensor)):
                if abs(held - wanted) > lsb * 1.0001:  # one count, and float rounding
                    found.append(f"{sensor} {axis} holds {held:+.9f} {UNITS[sensor]}, not {wanted:+.9f}")
        if self.reference != reference:
            found.append(f"reference is {self.reference}, not {reference}")
        return found


@dataclass(frozen=True)
class UnitReading:
    """What Normal Mode says before a trim: the offsets in force, the serial number, the gyros'
    output unit, and whether the unit was starting up (power-up datagrams or the start-up status
    bit in what was read)."""

    trim: TrimReading
    serial_number: str
    gyro_unit: GyroUnit
    starting_up: bool


class NormalLink:
    """Requests in Normal Mode (no echo; the answer replaces the next datagrams) on one parser: the
    configuration read first scales what follows, and the data read while waiting tell whether
    the unit is starting up."""

    def __init__(self, ser: serial.Serial, timeout: float = 3.0):
        self.ser, self.timeout = ser, timeout
        self.parser = StreamParser()
        self.starting_up = False

    def ask(self, request: bytes, kind: type):
        """Send `request` CR; return the first special datagram of `kind` that arrives after it."""
        seen = self.parser.stats.special_datagrams
        self.ser.write(request + b"\r")
        deadline = time.monotonic() + self.timeout
        while True:
            self._feed()
            new = self.parser.stats.special_datagrams - seen
            found = [s for s in list(self.parser.scanner.specials)[-new:] if isinstance(s, kind)] if new else []
            if found:
                return found[0]
            if time.monotonic() >= deadline:
                raise TrimError(f"no answer to {request.decode()!r} within {self.timeout} s "
                                "(is the unit in Normal Mode, at this bit rate?)")

    def samples(self, duration_s: float) -> np.ndarray:
        """The next `duration_s` seconds of data, counted at the configured sample rate (not by the
        host's clock; C is asked first when the configuration is not known yet)."""
        if self.parser.scanner.configuration is None:
            self.ask(b"C", Configuration)
        rate_hz = self.parser.format.sample_rate_hz or 2000
        wanted = int(round(duration_s * rate_hz))
        parts, count = [], 0
        limit_s = duration_s * 4 + self.timeout
        deadline = time.monotonic() + limit_s
        while count < wanted:
            if time.monotonic() >= deadline:
                raise TrimError(f"{count} of {wanted} samples ({duration_s:g} s at {rate_hz} Hz) within {limit_s:g} s")
            part = self._feed()
            parts.append(part)
            count += len(part)
        return np.concatenate(parts)[:wanted]

    def _feed(self) -> np.ndarray:
        samples = self.parser.feed(read_available(self.ser), time.monotonic())
        flags = samples["status_gyro"] | samples["status_acc"] | samples["status_incl"]
        self.starting_up |= bool(self.parser.stats.restarts or np.any(flags & Status.START_UP))
        return samples


def read_trims(ser: serial.Serial, timeout: float = 3.0) -> UnitReading:
    """In Normal Mode: the configuration (C, for the acc range), the serial number (I) and the
    trims in force (T)."""
    link = NormalLink(ser, timeout)
    configuration = link.ask(b"C", Configuration)
    serial_number = link.ask(b"I", SerialNumber)
    bto = link.ask(b"T", BiasTrimOffset)
    reading = TrimReading(TrimOffsets(bto.gyro, bto.acc, bto.incl), bto.reference_info, bto.remaining_saves,
                          max(configuration.acc_range_g))
    return UnitReading(reading, str(serial_number), configuration.gyro_unit, link.starting_up)


def number(value: float) -> str:
    """A value as the `b` command takes it: fixed-point, nine decimals (below any count), no exponent."""
    text = f"{value:.9f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def trim_commands(trims: TrimOffsets, sensors=SENSORS, reference: int | None = None) -> list[str]:
    """The `b` commands that make `sensors`' offsets exactly `trims`, then the reference.

    The unit sets one axis only by a delta (`b delta,<g|a|i>,<x|y|z>`); its absolute forms set a
    whole triad to one value. So each triad is set to 0 first (`b 0,<g|a|i>`), then each axis
    gets its value as a delta from 0: what is written never depends on reading the old values
    right, and a command sent twice cannot add up.
    """
    commands = []
    for sensor in sensors:
        letter = SENSOR_LETTERS[sensor]
        commands.append(f"b 0,{letter}")
        commands += [f"b {number(v)},{letter},{axis}" for axis, v in zip("xyz", trims.of(sensor)) if v]
    if reference is not None:
        if not 0 <= reference < REFERENCE_LIMIT:
            raise ValueError(f"reference {reference}: a 32-bit number (0 to {REFERENCE_LIMIT - 1})")
        commands.append(f"b {reference},r")
    return commands


def write_trims(ser: serial.Serial, commands: list[str], timeout: float = 3.0, step=lambda text: None) -> None:
    """Run the `b` commands in Service Mode (the caller's `service_mode`); `step(command)` is told
    before each. E008 (the unit clamped a value) or any refusal raises TrimError naming it."""
    for command in commands:
        step(command)
        try:
            service_command(ser, command, timeout)
        except ServiceError as exc:
            clamped = " (beyond the trim range: the unit clamped it)" if exc.code == 8 else ""
            raise TrimError(f"{exc}{clamped}") from exc


def apply_trims(ser: serial.Serial, trims: TrimOffsets, sensors, reference: int, timeout: float = 3.0,
                step=lambda text: None) -> TrimReading:
    """Write the volatile trims and the reference, leave Service Mode without saving, read T back
    and check every offset within one count; TrimError when the unit holds something else."""
    step("enter Service Mode")
    with service_mode(ser, timeout):
        write_trims(ser, trim_commands(trims, sensors, reference), timeout, step)
        step("x N")
    step("read T")
    reading = read_trims(ser, timeout).trim
    differences = reading.differences(trims, reference)
    if differences:
        raise TrimError(f"the unit does not hold the trims written: {'; '.join(differences)}")
    return reading


def save_trims(ser: serial.Serial, before: TrimReading, timeout: float = 3.0, step=lambda text: None) -> TrimReading:
    """Save to flash (`s`, answered Y) what `before` read, then read T again: the same offsets and
    reference, and exactly one save fewer. Refused when no save remains."""
    if before.remaining_saves <= 0:
        raise TrimError("the unit has no flash saves left (0 remaining): nothing saved")
    step("enter Service Mode")
    with service_mode(ser, timeout):
        step("s")
        try:
            save_to_flash(ser, timeout)
        except ServiceError as exc:
            raise TrimError(str(exc)) from exc
        step("x N")
    step("read T")
    after = read_trims(ser, timeout).trim
    problems = after.differences(before.trims, before.reference)
    if after.remaining_saves != before.remaining_saves - 1:
        problems.append(f"remaining saves went from {before.remaining_saves} to {after.remaining_saves}, "
                        "not down by one")
    if problems:
        raise TrimError(f"after the save: {'; '.join(problems)}")
    return after

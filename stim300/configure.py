"""The sensor's configuration through Service Mode: the `i` report as typed fields, the change
commands, and the flow that applies them (and saves them to flash when asked).

The protocol description lists what the `i` report holds (serial and part number, firmware,
sample rate, datagram, termination, units, filters, bit rate, ...) but not its wording. The
report is read as `NAME = VALUE` lines; `_FIELDS` says which names give which typed field,
every other line is kept as the sensor printed it. A field the report does not carry stays
None and is shown as absent, never guessed.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields

import serial

from .errors import FormatError, ServiceError, Stim300Error
from .protocol import NORMAL_LAYOUTS, SAMPLE_RATES_HZ, STANDARD_BIT_RATES, AccUnit, GyroUnit, normal_id
from .service import change_bit_rate, save_to_flash, service_command, service_mode
from .special import LPF_HZ, EXTERNAL_TRIGGER_CODE

GROUPS = ("gyro", "acc", "incl")
EXTERNAL = "external"
SAMPLE_RATE_CODES: dict[int | str, int] = {hz: code for code, hz in enumerate(SAMPLE_RATES_HZ)} | {
    EXTERNAL: EXTERNAL_TRIGGER_CODE}
LPF_CODES: dict[int, int] = dict(LPF_HZ.to_code)  # -3 dB frequency (Hz) -> `f` code
# `d` type codes: 0..7 for the plain family, l..t for the PPS family (protocol doc §4.2)
DATAGRAM_CODES: dict[int, str] = ({0x90 | low: str(low) for low in range(5)}
                                  | {0xA0 | low: str(low) for low in (5, 6, 7)}
                                  | {0xF0 | low: code for low, code in enumerate("lmnpqrst")})
USER_BIT_RATE_BPS = (1500, 5184000)  # `t f,<bps>`: the unit makes the nearest rate its clock divides to


def bit_rate_command(bit_rate_bps: int) -> str:
    """`t` for a standard rate (its code) or a user-defined one; FormatError outside the range."""
    if bit_rate_bps in STANDARD_BIT_RATES:
        return f"t {STANDARD_BIT_RATES.index(bit_rate_bps)}"
    low, high = USER_BIT_RATE_BPS
    if not low <= bit_rate_bps <= high:
        raise FormatError(f"bit rate {bit_rate_bps} bit/s: expected {', '.join(map(str, STANDARD_BIT_RATES))} "
                          f"or a user-defined rate {low}..{high} bit/s")
    return f"t f,{bit_rate_bps}"


# ---------------------------------------------------------------- the `i` report

@dataclass(frozen=True)
class SensorReport:
    """The `i` report: typed fields where the report names them, every other line verbatim."""

    product: str | None = None
    part_number: str | None = None
    serial_number: str | None = None
    firmware: str | None = None
    sample_rate_hz: int | None = None
    external_trigger: bool | None = None
    datagram_id: int | None = None
    crlf: bool | None = None
    gyro_unit: GyroUnit | None = None
    acc_unit: AccUnit | None = None
    incl_unit: AccUnit | None = None
    gyro_lpf_hz: tuple[int, ...] | None = None
    acc_lpf_hz: tuple[int, ...] | None = None
    incl_lpf_hz: tuple[int, ...] | None = None
    bit_rate_bps: int | None = None
    remaining_saves: int | None = None
    other: tuple[tuple[str, str], ...] = ()  # (name, value) lines no typed field reads

    def as_dict(self) -> dict:
        out = {}
        for name, value in asdict(self).items():
            if name == "other":
                out[name] = dict(value)
            elif name == "datagram_id" and value is not None:
                out[name] = f"0x{value:02X}"
            elif name.endswith("_unit") and value is not None:
                out[name] = getattr(self, name).name.lower()
            else:
                out[name] = list(value) if isinstance(value, tuple) else value
        return out

    def rows(self) -> list[tuple[str, str]]:
        """(name, "value unit") for printing; absent fields say so."""
        rows = []
        for f in fields(self):
            if f.name == "sample_rate_hz" and self.external_trigger:
                rows.append((f.name, "- (external trigger)"))
            elif f.name != "other":
                rows.append((f.name, _shown(f.name, getattr(self, f.name))))
        return rows + list(self.other)


def _shown(name: str, value) -> str:
    if value is None:
        return "- (not in the report)"
    if name == "datagram_id":
        return f"0x{value:02X}"
    if name.endswith("_unit"):
        return f"{value.name.lower()} ({value.symbol})"
    if name.endswith("_lpf_hz"):
        return ", ".join(map(str, value)) + " Hz"
    if name == "sample_rate_hz":
        return f"{value} Hz"
    if name == "bit_rate_bps":
        return f"{value} bit/s"
    if name == "remaining_saves":
        return f"{value} saves"
    if isinstance(value, bool):
        return "yes" if value else "no"
    return str(value)


def _integer(value: str) -> int:
    found = re.search(r"\d+", value)
    if found is None:
        raise ValueError(value)
    return int(found[0])


def _yes(value: str) -> bool:
    words = set(re.findall(r"[A-Z]+", value.upper()))
    if words & {"ON", "YES", "CRLF", "CR", "ENABLED"} or value.strip() == "1":
        return True
    if words & {"OFF", "NO", "NONE", "DISABLED"} or value.strip() == "0":
        return False
    raise ValueError(value)


def _datagram(value: str) -> int:
    """A hex id in the value, else the content words (RATE, ACC, INCL, TEMP, PPS)."""
    found = re.search(r"0x([0-9A-F]{2})", value, re.I)
    if found:
        return int(found[1], 16)
    words = value.upper()
    if "RATE" not in words:
        raise ValueError(value)
    return normal_id("ACC" in words, "INCL" in words, "TEMP" in words, "pps" if "PPS" in words else None)


def _gyro_unit(value: str) -> GyroUnit:
    v = value.upper()
    kind = ("INCREMENTAL_ANGLE" if "INCREMENT" in v else "INTEGRATED_ANGLE" if "INTEGRAT" in v
            else "AVERAGE_RATE" if "AVERAGE" in v else "RATE" if "RATE" in v else None)
    if kind is None:
        raise ValueError(value)
    return GyroUnit[kind + ("_DELAYED" if "DELAY" in v else "")]


def _acc_unit(value: str) -> AccUnit:
    v = value.upper()
    if "INCREMENT" in v:
        return AccUnit.INCREMENTAL_VELOCITY
    if "INTEGRAT" in v:
        return AccUnit.INTEGRATED_VELOCITY_MS if re.search(r"M/S|\bMS\b", v) else AccUnit.INTEGRATED_VELOCITY_GS
    if "AVERAGE" in v:
        return AccUnit.AVERAGE_ACCELERATION
    if "ACCEL" in v:
        return AccUnit.ACCELERATION
    raise ValueError(value)


def _filters(value: str) -> tuple[int, ...]:
    values = tuple(int(v) for v in re.findall(r"\d+", value))
    if len(values) not in (1, 3) or any(v not in LPF_CODES for v in values):
        raise ValueError(value)
    return values * 3 if len(values) == 1 else values


# Report name (upper case, [unit] removed) -> typed field and how its value reads. First match wins.
_FIELDS: tuple[tuple[str, str | None, Callable | None], ...] = (
    (r"^SERIAL NUMBER$", "serial_number", str.strip),
    (r"^PART NUMBER$", "part_number", str.strip),
    (r"^PRODUCT$", "product", str.strip),
    (r"\bFW\b|FIRMWARE", "firmware", str.strip),
    (r"^SAMPLE RATE$", "sample_rate_hz", _integer),
    (r"^LINE TERMINATION$", None, None),  # the RS422 resistor (`r`), not the datagram's CR LF
    (r"TERMINATION", "crlf", _yes),
    (r"^DATAGRAM$|^DATAGRAM (TYPE|FORMAT|CONTENT)$", "datagram_id", _datagram),
    (r"^GYRO (OUTPUT )?UNIT$", "gyro_unit", _gyro_unit),
    (r"^ACC(ELEROMETER)? (OUTPUT )?UNIT$", "acc_unit", _acc_unit),
    (r"^INCL(INOMETER)? (OUTPUT )?UNIT$", "incl_unit", _acc_unit),
    (r"^GYRO .*(FILTER|LPF)", "gyro_lpf_hz", _filters),
    (r"^ACC(ELEROMETER)? .*(FILTER|LPF)", "acc_lpf_hz", _filters),
    (r"^INCL(INOMETER)? .*(FILTER|LPF)", "incl_lpf_hz", _filters),
    (r"^BIT ?RATE$", "bit_rate_bps", _integer),
    (r"SAVES", "remaining_saves", _integer),
)
_LINE = re.compile(r"^\s*([^=]+?)\s*=\s*(.*?)\s*$")


def parse_report(text: str) -> SensorReport:
    """Typed fields of an `i` report (Service Mode text, one line per '\\n').

    A line that is not `NAME = VALUE`, an unknown name, and a value a known name carries that
    does not read (a unit word not listed) are kept under `other` as printed: nothing the
    sensor says is lost.
    """
    typed: dict = {}
    other = []
    for line in filter(str.strip, text.splitlines()):
        match = _LINE.match(line)
        if not match:
            other.append((line.strip(), ""))
            continue
        name, value = match[1], match[2]
        key = re.sub(r"\s*\[[^\]]*\]", "", name).upper().strip()
        if key == "TRIGGER" or key == "SAMPLE RATE" and "EXT" in value.upper():
            typed["external_trigger"] = "EXT" in value.upper()
            continue
        field_name, read = next(((f, r) for pattern, f, r in _FIELDS if re.search(pattern, key)), (None, None))
        if field_name is not None and field_name not in typed:
            try:
                typed[field_name] = read(value)
                continue
            except ValueError:
                pass  # kept below, as printed
        other.append((name, value))
    if typed.get("sample_rate_hz") is not None and "external_trigger" not in typed:
        typed["external_trigger"] = False
    return SensorReport(**typed, other=tuple(other))


def read_report(ser: serial.Serial, timeout: float = 3.0) -> SensorReport:
    return parse_report(service_command(ser, "i", timeout))


# ---------------------------------------------------------------- changes

@dataclass(frozen=True)
class Changes:
    """What to set; None leaves a setting as it is. Values are checked by the command line
    against the allowed ones (SAMPLE_RATE_CODES, DATAGRAM_CODES, ...) before any is sent."""

    sample_rate: int | str | None = None  # Hz or EXTERNAL
    datagram_id: int | None = None
    crlf: bool | None = None
    gyro_unit: GyroUnit | None = None
    acc_unit: AccUnit | None = None
    incl_unit: AccUnit | None = None
    gyro_lpf_hz: int | None = None
    acc_lpf_hz: int | None = None
    incl_lpf_hz: int | None = None
    bit_rate_bps: int | None = None


@dataclass(frozen=True)
class Command:
    option: str  # the command-line option it comes from
    text: str  # the Service Mode command


class ConfigureError(Stim300Error):
    """A change the unit refused or that cannot be made; says what was applied before it."""


def plan(changes: Changes, current: SensorReport) -> list[Command]:
    """The Service Mode commands for `changes`, in an order the unit can take them.

    The unit refuses a datagram that does not fit the sample rate and bit rate (E007), judged
    at each command, so what lightens the line goes first: a higher bit rate before everything
    (the port follows it), a shorter datagram before a higher sample rate; a lower bit rate goes
    last. `d` sets the datagram type and its termination together: the one not given is the
    current one, read from the report.
    """
    commands = []
    if changes.sample_rate is not None:
        commands.append(Command("--rate", f"m {SAMPLE_RATE_CODES[changes.sample_rate]}"))
    if changes.datagram_id is not None or changes.crlf is not None:
        datagram_id = current.datagram_id if changes.datagram_id is None else changes.datagram_id
        crlf = current.crlf if changes.crlf is None else changes.crlf
        option = "--datagram" if changes.datagram_id is not None else "--crlf"
        if datagram_id not in DATAGRAM_CODES or crlf is None:
            missing = "--datagram" if datagram_id not in DATAGRAM_CODES else "--crlf"
            raise ConfigureError(f"{option}: the `d` command sets datagram and termination together, and the "
                                 f"sensor's report gives no settable current value for {missing}: give both")
        datagram = Command(option, f"d {DATAGRAM_CODES[datagram_id]},{int(crlf)}")
        shorter = (current.datagram_id in NORMAL_LAYOUTS and current.crlf is not None
                   and NORMAL_LAYOUTS[datagram_id].wire_length(crlf)
                   < NORMAL_LAYOUTS[current.datagram_id].wire_length(current.crlf))
        commands.insert(0, datagram) if shorter else commands.append(datagram)
    for group in GROUPS:
        unit = getattr(changes, group + "_unit")
        if unit is not None:
            commands.append(Command(f"--{group}-unit", f"u {group[0]},{int(unit):x}"))
    for group in GROUPS:
        lpf_hz = getattr(changes, group + "_lpf_hz")
        if lpf_hz is not None:
            commands.append(Command(f"--{group}-lpf", f"f {LPF_CODES[lpf_hz]},{group[0]}"))
    if changes.bit_rate_bps is not None:
        bit_rate = Command("--bit-rate", bit_rate_command(changes.bit_rate_bps))
        higher = current.bit_rate_bps is not None and changes.bit_rate_bps > current.bit_rate_bps
        commands.insert(0, bit_rate) if higher else commands.append(bit_rate)
    return commands


@dataclass(frozen=True)
class Outcome:
    before: SensorReport
    after: SensorReport  # the report read after the changes (and the save); `before` if none
    applied: tuple[str, ...]  # the commands the unit accepted, in order
    saved: bool
    save_declined: bool = False

    def changed(self) -> list[str]:
        """Names of the typed fields whose value differs between the two reports."""
        return [f.name for f in fields(SensorReport) if f.name not in ("other", "remaining_saves")
                and getattr(self.before, f.name) != getattr(self.after, f.name)]


def configure(ser: serial.Serial, changes: Changes, save: bool = False,
              confirm: Callable[[SensorReport], bool] = lambda report: True, timeout: float = 3.0) -> Outcome:
    """Enter Service Mode, apply `changes` one by one, re-read the report, save if asked.

    The unit is back in Normal Mode on every way out (`service_mode`). A refused command ends
    the run with a ConfigureError naming it and what was applied before it (those changes stay,
    volatile). `--save` is refused before any change when the report says no saves remain;
    `confirm(after)` is asked once the changes are in; a no leaves them volatile (`save_declined`).
    """
    applied: list[str] = []
    with service_mode(ser, timeout):
        before = read_report(ser, timeout)  # not the entry banner: datagram bytes may precede it
        commands = plan(changes, before)
        if save and before.remaining_saves == 0:
            raise ConfigureError("--save: the sensor reports 0 flash saves remaining: nothing was changed")
        after = before
        for command in commands:
            try:
                if command.option == "--bit-rate":
                    after = parse_report(change_bit_rate(ser, command.text, changes.bit_rate_bps, timeout))
                    if after.bit_rate_bps:  # a user-defined rate is the nearest the unit's clock makes
                        ser.baudrate = after.bit_rate_bps
                else:
                    service_command(ser, command.text, timeout)
            except ServiceError as exc:
                done = f"applied before it: {', '.join(applied)}" if applied else "nothing was applied"
                raise ConfigureError(f"{command.option}: {exc} ({done})") from exc
            applied.append(command.text)
        if applied and commands[-1].option != "--bit-rate":  # the bit rate's own report is the last word
            after = read_report(ser, timeout)
        if save and not confirm(after):
            return Outcome(before, after, tuple(applied), saved=False, save_declined=True)
        if save:
            try:
                save_to_flash(ser, timeout)
            except ServiceError as exc:
                raise ConfigureError(f"--save: {exc}") from exc
            after = read_report(ser, timeout)
    return Outcome(before, after, tuple(applied), saved=save)

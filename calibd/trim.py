"""A calibration result written into the sensor as its bias trim offsets (docs/trim.md): what to
write, when to refuse, and the guarded flow around the driver's `stim300.trim`.

The unit adds each offset after its compensation (adjusted = compensated + offset; STIM300
datasheet TS1524 rev.31, 7.5.2.3), so an output that carries a bias b loses it with the offset
present - b. calibd decides here because it reads results and the datasheet's figures
(`calibd.spec`); stim300 is the driver and knows no results.

Nothing is changed before the offsets in force are read and written to a backup file; what is
written is volatile and read back; any failure, Ctrl-C or SIGTERM on the way puts the backup's
offsets back (volatile: no save spent); a save comes only after the check, when asked.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from msgspec import Meta, Struct

from stim300.atomic import write_atomic
from stim300.cliutil import DOCUMENT_LIMIT_BYTES, read_input
from stim300.errors import UsageError
from stim300.records import TrimOffsets
from stim300.trim import (REFERENCE_LIMIT, SENSORS, UNITS, NormalLink, TrimReading, UnitReading,
                          apply_trims, read_trims, save_trims, trim_commands)

from . import spec
from .correction import sensor_biases
from .documents import decode_json, document_version, validate
from .errors import CalibdError
from .frames import Site, nav_to_imu
from .results import CalibrationResult
from .units import RAD_S_TO_DEG_H, SQRT_S_PER_SQRT_H, value_sigma

BACKUP_SCHEMA, BACKUP_VERSION = "calibd.trim-backup", 1
VERIFY_SCHEMA, VERIFY_VERSION = "calibd.trim-verify", 1
VERIFY_SIGMAS = 2.0  # a residual gyro bias within this many sigma of zero passes the check
# sensor -> (the result's estimate names' prefix, its display unit)
FROM_RESULT = {"gyro": ("gyro_bias", "deg/h"), "acc": ("acc_bias", "mg"), "incl": ("incl_bias", "mg")}


class TrimRefused(CalibdError):
    """A trim calibd will not write (the result, the unit or the options do not allow it)."""


def noise_figure(sensor: str, acc_range_g: int) -> tuple[float, str]:
    """The datasheet figure an estimate's 1-sigma must not exceed, in the result's unit, and its
    name: the gyros' run-to-run bias; the datasheet states none for the others, so the
    accelerometers' 1-year bias stability and the inclinometers' bias over temperature (rms),
    the smallest long-term bias figure each has."""
    triad = spec.triads(acc_range_g)[sensor]
    if sensor == "gyro":
        return triad.bias_run_to_run, "run-to-run bias"
    if sensor == "acc":
        return triad.bias_one_year, "1-year bias stability"
    return triad.bias_over_temperature, "bias over temperature (rms)"


def trim_reference(session_id: str) -> int:
    """The 32-bit reference stored with a trim: the first 4 bytes (big-endian) of the SHA-256 of
    the result's session_id, so the unit says which result its trims came from."""
    return int.from_bytes(hashlib.sha256(session_id.encode()).digest()[:4], "big")


def new_offsets(result: CalibrationResult, present: TrimOffsets, sensors) -> TrimOffsets:
    """The offsets under which the result was made less its bias, for each chosen sensor (the
    output carries the bias on top of the offsets in force then: the result's `sensor.trim`,
    taken to be the present ones when it does not say); the others as they are."""
    made_under = present if result.sensor.trim is None else result.sensor.trim
    biases = sensor_biases(result)  # deg/s and g, the trim's own units
    trims = present
    for sensor in sensors:
        trims = trims.replaced(sensor, np.subtract(made_under.of(sensor), biases[sensor]))
    return trims


def beyond_range(trims: TrimOffsets, sensors, acc_range_g: int) -> list[str]:
    """Offsets outside their triad's trim range (the unit would clamp them: E008)."""
    found = []
    for sensor in sensors:
        limit = spec.triads(acc_range_g)[sensor].bias_trim_range
        found += [f"{sensor} {axis} offset {v:+.6f} {UNITS[sensor]} is beyond the trim range "
                  f"+-{limit:g} {UNITS[sensor]} ({spec.DATASHEET}, 7.5.2.3)"
                  for axis, v in zip("xyz", trims.of(sensor)) if abs(v) > limit]
    return found


def missing(result: CalibrationResult, sensors) -> list[str]:
    """The chosen sensors' bias estimates the result does not hold (nothing to trim them by)."""
    return [f"{FROM_RESULT[sensor][0]}_{axis}" for sensor in sensors for axis in "xyz"
            if f"{FROM_RESULT[sensor][0]}_{axis}" not in result.estimates]


def refusals(result: CalibrationResult, unit: UnitReading, sensors) -> list[str]:
    """Why this result must not trim this unit (each lifted by --force); [] when none."""
    found = []
    if result.sensor.serial_number != unit.serial_number:
        found.append(f"the result is of sensor {result.sensor.serial_number or '(not named)'}, the unit on the port "
                     f"is {unit.serial_number}")
    found += result_refusals(result, sensors, unit.trim.acc_range_g)
    if result.bias_reference == "turn-on" and unit.starting_up:
        found.append("the result's biases are turn-on biases and the unit is starting up now (power-up datagrams or "
                     "its start-up status bit): it restarted after them")
    return found


def result_refusals(result: CalibrationResult, sensors, acc_range_g: int) -> list[str]:
    """What the result itself says against trimming with it, before the unit is asked (the
    daemon checks this before it takes the port): stale, an estimate without a trustworthy
    1-sigma, turn-on biases whose capture goes on into a later power-up."""
    found = []
    if result.stale is not None:
        found.append(f"the result is stale: {result.stale.reason}")
    for sensor in sensors:
        prefix, unit_text = FROM_RESULT[sensor]
        figure, figure_name = noise_figure(sensor, acc_range_g)
        for axis in "xyz":
            name = f"{prefix}_{axis}"
            estimate = result.estimates[name]
            if estimate.sigma is None:
                found.append(f"{name} has no 1-sigma")
            elif estimate.quality == "poor":
                found.append(f"{name} is flagged poor")
            elif estimate.sigma > figure:
                found.append(f"{name}: 1-sigma {estimate.sigma:.3g} {unit_text} exceeds the datasheet's {figure_name} "
                             f"{figure:g} {unit_text}: the trim would write noise")
    power_up = result.stream.power_up
    if result.bias_reference == "turn-on" and power_up is not None and power_up.number < power_up.count:
        found.append(f"the result's biases are turn-on biases and its capture shows the sensor restarted after them "
                     f"(power-up {power_up.number} of {power_up.count})")
    return found


# ---------------------------------------------------------------- backup and check files

class TrimsDoc(Struct):
    gyro_deg_s: tuple[float, float, float]
    acc_g: tuple[float, float, float]
    incl_g: tuple[float, float, float]


class BackupDoc(Struct):
    schema: str
    serial_number: str | None
    port: str
    taken_at: str
    acc_range_g: Literal[spec.ACC_RANGES_G]
    trims: TrimsDoc
    reference: Annotated[int, Meta(ge=0, lt=REFERENCE_LIMIT)]
    remaining_saves: Annotated[int, Meta(ge=0, lt=1 << 16)]


@dataclass(frozen=True)
class Backup:
    """A backup file read: the unit it was taken of and what it held."""

    serial_number: str | None
    reading: TrimReading


def write_backup(directory: Path, unit: UnitReading, port: str, now: datetime) -> Path:
    """trim-backup-<serial>-<UTC time>.json in `directory`, atomic, never through a link, and
    never over another backup (a second one within the same second gets -2, -3, ...)."""
    t = unit.trim
    doc = {"schema": f"{BACKUP_SCHEMA}/{BACKUP_VERSION}", "serial_number": unit.serial_number, "port": port,
           "taken_at": now.isoformat(timespec="seconds"), "acc_range_g": t.acc_range_g, "trims": t.trims.to_dict(),
           "reference": t.reference, "remaining_saves": t.remaining_saves}
    stem = f"trim-backup-{unit.serial_number}-{now.strftime('%Y%m%dT%H%M%SZ')}"
    path = directory / f"{stem}.json"
    for n in itertools.count(2):
        if not os.path.lexists(path):
            break
        path = directory / f"{stem}-{n}.json"
    write_atomic(path, (json.dumps(doc, indent=1) + "\n").encode(), follow=False)
    return path


def prune_backups(directory: Path, serial_number: str, keep: int) -> list[Path]:
    """Remove all but the `keep` newest backups of one sensor in `directory` (names as
    `write_backup` makes them, oldest first by their time and number); returns those removed."""
    prefix = f"trim-backup-{serial_number}-"

    def when(path: Path) -> tuple[str, int]:
        stamp, _, number = path.stem[len(prefix):].partition("-")
        return stamp, int(number) if number.isdigit() else 1
    backups = sorted((p for p in directory.glob(f"{prefix}*.json") if p.is_file() and not p.is_symlink()), key=when)
    removed = backups[:max(0, len(backups) - keep)]
    for path in removed:
        path.unlink(missing_ok=True)
    return removed


def load_backup(path) -> Backup:
    where = str(path)
    doc = decode_json(read_input(path, "trim backup", DOCUMENT_LIMIT_BYTES), where, BackupDoc, TrimRefused)
    document_version(doc, BACKUP_SCHEMA, BACKUP_VERSION, where, TrimRefused)
    backup = validate(doc, BackupDoc, where, TrimRefused)
    try:
        trims = TrimOffsets(backup.trims.gyro_deg_s, backup.trims.acc_g, backup.trims.incl_g)
    except ValueError as exc:
        raise TrimRefused(f"{where}: trims: {exc}") from None
    return Backup(backup.serial_number, TrimReading(trims, backup.reference, backup.remaining_saves,
                                                    backup.acc_range_g))


def verify_check(result: CalibrationResult, gyro_mean_deg_s, duration_s: float) -> dict:
    """The residual gyro biases of a static read after the trim: the mean less the Earth rate in
    the sensor's axes (the result's attitude at the platform's home position, its site's
    latitude), each against VERIFY_SIGMAS x sigma, where sigma joins the white noise's over
    `duration_s` (the datasheet's angular random walk) and that of what the result expects
    (`expected_static_sigma`)."""
    rotation = result.rotation_matrix("nav_to_imu")
    earth_deg_h = rotation @ Site(result.site["latitude_deg"]).earth_rate_nav * RAD_S_TO_DEG_H
    white_deg_h = spec.GYRO.random_walk * SQRT_S_PER_SQRT_H / math.sqrt(duration_s)
    expected_sigma_deg_h = expected_static_sigma(result)
    axes = {}
    for i, axis in enumerate("xyz"):
        residual = float(gyro_mean_deg_s[i] * 3600 - earth_deg_h[i])
        sigma = math.hypot(white_deg_h, expected_sigma_deg_h[i])
        axes[axis] = {"residual_deg_h": residual, "expected_earth_rate_deg_h": float(earth_deg_h[i]),
                      "sigma_deg_h": sigma, "passed": bool(abs(residual) <= VERIFY_SIGMAS * sigma)}
    return {"schema": f"{VERIFY_SCHEMA}/{VERIFY_VERSION}", "duration_s": duration_s, "sigmas": VERIFY_SIGMAS,
            "session_id": result.session_id, "axes": axes, "passed": all(a["passed"] for a in axes.values())}


ATTITUDE = ("yaw", "pitch", "roll")


def expected_static_sigma(result: CalibrationResult) -> np.ndarray:
    """1-sigma (deg/h, per gyro axis) of what the result expects a static gyro to read once its
    bias is trimmed off: its bias estimate's error plus the Earth rate its attitude's error puts
    on the axis (a yaw off by 2 deg moves 11 deg/h of horizontal Earth rate by 0.4 deg/h). The
    joint method's covariance correlates them (both come from the same statics) and is used
    when the result has it; otherwise they are taken as independent."""
    site = Site(result.site["latitude_deg"])
    angles = np.array([result.estimates[name].value_si for name in ATTITUDE])

    def earth(values):
        return nav_to_imu(*values) @ site.earth_rate_nav * RAD_S_TO_DEG_H

    steps = np.eye(3) * 1e-6
    turned = np.column_stack([(earth(angles + h) - earth(angles - h)) / 2e-6 for h in steps])  # deg/h per rad
    names = [*ATTITUDE, *(f"gyro_bias_{axis}" for axis in "xyz")]
    covariance = result.covariance_matrix(si=True)
    if covariance is not None and all(name in result.covariance["names"] for name in names):
        index = [result.covariance["names"].index(name) for name in names]
        jacobian = np.hstack([turned, np.eye(3) * RAD_S_TO_DEG_H])  # the biases' SI is rad/s
        return np.sqrt(np.diag(jacobian @ covariance[np.ix_(index, index)] @ jacobian.T))
    attitude = np.array([result.estimates[name].sigma_si or 0.0 for name in ATTITUDE])
    bias = np.array([result.estimates[f"gyro_bias_{axis}"].sigma or 0.0 for axis in "xyz"])
    return np.sqrt(bias**2 + (turned**2) @ attitude**2)


def verify_lines(check: dict) -> list[str]:
    return [f"gyro {axis}: residual {value_sigma(a['residual_deg_h'], a['sigma_deg_h'], 'deg/h')} "
            f"(Earth rate {a['expected_earth_rate_deg_h']:+.3f} deg/h taken off): "
            f"{'within' if a['passed'] else 'beyond'} {check['sigmas']:g} sigma"
            for axis, a in check["axes"].items()]


# ---------------------------------------------------------------- the flow

@dataclass(frozen=True)
class TrimOptions:
    sensors: tuple[str, ...] = SENSORS
    force: bool = False
    dry_run: bool = False
    save: bool = False
    verify_s: float | None = None
    backup_dir: Path = Path(".")
    timeout: float = 3.0


class VerifyFailed(CalibdError):
    """The static check after the trim found residual gyro biases beyond VERIFY_SIGMAS sigma."""


class RestoreFailed(CalibdError):
    """The backup could not be put back: the message says which file to restore from."""


def trim_rows(reading: TrimReading) -> list[str]:
    """The trims in force, the reference and the saves left, one line each, with units."""
    rows = [f"{sensor + ' trim':<16} "
            + "  ".join(f"{axis} {v:+.9f}" for axis, v in zip("xyz", reading.trims.of(sensor))) + f" {UNITS[sensor]}"
            for sensor in SENSORS]
    return rows + [f"{'reference':<16} {reading.reference} (0x{reading.reference:08X})",
                   f"{'remaining saves':<16} {reading.remaining_saves} saves"]


def plan_rows(result: CalibrationResult, present: TrimOffsets, target: TrimOffsets, sensors) -> list[str]:
    """Each changed axis: the offset in force, the new one, the bias it takes off."""
    rows = []
    for sensor in sensors:
        prefix, unit_text = FROM_RESULT[sensor]
        for axis, old, new in zip("xyz", present.of(sensor), target.of(sensor)):
            e = result.estimates[f"{prefix}_{axis}"]
            rows.append(f"{sensor} {axis}: {old:+.9f} -> {new:+.9f} {UNITS[sensor]} "
                        f"(bias {value_sigma(e.value, e.sigma, unit_text)})")
    return rows


def show(ser, options: TrimOptions) -> list[str]:
    unit = read_trims(ser, options.timeout)
    return [f"{'serial number':<16} {unit.serial_number}"] + trim_rows(unit.trim)


def trim_from_result(ser, result: CalibrationResult, options: TrimOptions, say, confirm,
                     step=lambda text: None) -> list[str]:
    """The whole flow for `calibd trim --from`: read, refuse or warn, back up, write volatile,
    check (and --verify), save when asked. Returns the lines to print: the trims then in force."""
    sensors = options.sensors
    step("read the trims in force (C, I, T)")
    unit = read_trims(ser, options.timeout)
    _can_save(unit, options)
    if options.verify_s is not None and unit.gyro_unit.is_angle:
        raise TrimRefused(f"--verify needs the gyros' output as a rate, the unit outputs {unit.gyro_unit.name.lower()}")
    problems = refusals(result, unit, sensors)
    if problems and not options.force:
        raise TrimRefused("; ".join(problems) + " (--force writes it anyway)")
    for problem in problems:
        say(f"warning: {problem} (--force: trimming anyway)")
    target = new_offsets(result, unit.trim.trims, sensors)
    beyond = beyond_range(target, sensors, unit.trim.acc_range_g)
    if beyond:
        raise TrimRefused("; ".join(beyond) + ": the unit would clamp it, nothing was written")
    reference = trim_reference(result.session_id)
    for row in plan_rows(result, unit.trim.trims, target, sensors):
        say(row)

    def verify(backup_path: Path) -> None:
        step(f"verify: {options.verify_s:g} s of static data")
        mean = collect_gyro_mean(ser, options.verify_s, options.timeout)
        check = verify_check(result, mean, options.verify_s)
        path = backup_path.with_name(backup_path.name.replace("trim-backup-", "trim-verify-"))
        write_atomic(path, (json.dumps(check, indent=1) + "\n").encode(), follow=False)
        for line in verify_lines(check):
            say(line)
        if not check["passed"]:
            raise VerifyFailed(f"--verify: residual gyro biases beyond {VERIFY_SIGMAS:g} sigma ({path}): "
                               "the trim was taken back")
        say(f"verify passed ({path})")

    return _write(ser, unit, target, sensors, reference, options, step, say, confirm,
                  verify if options.verify_s else None)


def restore_backup(ser, backup: Backup, where: str, options: TrimOptions, say, confirm,
                   step=lambda text: None) -> list[str]:
    """`calibd trim --restore`: exactly the backup's offsets and reference, guarded as a trim."""
    step("read the trims in force (C, I, T)")
    unit = read_trims(ser, options.timeout)
    _can_save(unit, options)
    if backup.serial_number != unit.serial_number:
        problem = f"{where} is of sensor {backup.serial_number}, the unit on the port is {unit.serial_number}"
        if not options.force:
            raise TrimRefused(problem + " (--force restores it anyway)")
        say(f"warning: {problem} (--force: restoring anyway)")
    return _write(ser, unit, backup.reading.trims, SENSORS, backup.reading.reference, options, step, say, confirm)


def _can_save(unit: UnitReading, options: TrimOptions) -> None:
    """--save is refused before anything is written when the unit has no flash saves left."""
    if options.save and unit.trim.remaining_saves <= 0:
        raise TrimRefused("--save: the unit has no flash saves left (0 remaining): nothing was written")


def _write(ser, unit: UnitReading, target: TrimOffsets, sensors, reference: int, options: TrimOptions, step, say,
           confirm, verify=None) -> list[str]:
    """What a trim and a restore share once decided: the dry run's commands; or the backup, then,
    guarded, the write, `verify(backup_path)` and the save when asked; the rows then in force."""
    if options.dry_run:
        return ["dry run: nothing written; the commands would be:"] + trim_commands(target, sensors, reference)
    backup_path = write_backup(options.backup_dir, unit, ser.port, datetime.now(timezone.utc))
    say(f"backup of the trims in force: {backup_path}")

    def written(reading: TrimReading) -> TrimReading:
        say(f"trims written and read back within one count, reference {reference} (volatile: lost at power-off)")
        if verify is not None:
            verify(backup_path)
        if not options.save:
            return reading
        if not confirm(reading.remaining_saves):
            say("not saved: the trims stay volatile until power-off")
            return reading
        saved = save_trims(ser, reading, options.timeout, step)
        say(f"saved to flash: {saved.remaining_saves} saves remain")
        return saved

    return trim_rows(guarded(ser, unit, backup_path, options, say,
                             lambda: written(apply_trims(ser, target, sensors, reference, options.timeout, step))))


def guarded(ser, unit: UnitReading, backup_path: Path, options: TrimOptions, say, flow) -> TrimReading:
    """`flow()`, the unit's offsets changed; on any failure, Ctrl-C or SIGTERM before it returns,
    the backup's offsets and reference are put back (volatile) and the failure goes on its way.
    A save already made stays in flash: the message says so."""
    saves = unit.trim.remaining_saves
    try:
        return flow()
    except BaseException as failure:
        with _shielded():
            try:
                restored = apply_trims(ser, unit.trim.trims, SENSORS, unit.trim.reference, options.timeout)
            except Exception as restore_failure:
                raise RestoreFailed(f"{ser.port}: could not put back the offsets of {backup_path} "
                                    f"({restore_failure}) after: {_described(failure)}; "
                                    f"run calibd trim --restore {backup_path}") from failure
        spent = ("no save spent" if restored.remaining_saves == saves else
                 f"but the flash holds the new trims: --restore {backup_path} --save puts the old ones back there")
        say(f"restored the offsets of {backup_path} after: {_described(failure)} (volatile; {spent})")
        raise


def _described(failure: BaseException) -> str:
    return str(failure) or type(failure).__name__


@contextmanager
def _shielded():
    """Ctrl-C ignored while the backup is put back: a second one must not stop it half-way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def collect_gyro_mean(ser, duration_s: float, timeout: float) -> np.ndarray:
    """Mean gyro output (deg/s: the unit outputs a rate) over the next `duration_s` s of data."""
    return NormalLink(ser, timeout).samples(duration_s)["gyro"].astype(float).mean(axis=0)


def usage_checks(result: CalibrationResult, sensors, verify_s: float | None) -> None:
    """What the options ask of the result, checked before the port is opened."""
    absent = missing(result, sensors)
    if absent:
        raise TrimRefused(f"the result has no {', '.join(absent)}: leave that sensor out with --sensors")
    if verify_s is not None and "gyro" not in sensors:
        raise UsageError("trim: --verify checks the gyros' residual biases: give --sensors with gyro")
    if verify_s is not None and result.rotation_matrix("nav_to_imu") is None:
        raise UsageError("trim: --verify needs the result's attitude (yaw, pitch, roll) for the Earth rate; "
                         "this result has none")
    if result.session_id is None:
        raise TrimRefused("the result has no session_id to make the trim's reference from")


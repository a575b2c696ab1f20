"""The daemon's `[trim] apply = "volatile"` (docs/trim.md): a good result's biases written into
the sensor as volatile bias trims, between two batches, on the port the reader lends.

The rules are `calibd.trim`'s, as for `calibd trim`, without --force: any refusal means no trim
(logged once a session, with the reason). What the result alone says is checked before the port
is taken, so a refused result costs no data; the rest (the unit's serial number, its trims in
force, the trim range) once the unit has been read. Offsets in force go to a backup file in the
state directory first (the KEPT_BACKUPS newest of a sensor are kept), what is written is read
back within one count, and any failure puts the backup back and leaves the unit in Normal Mode.
No flash save is ever spent. A result made on the output this daemon trimmed (its `sensor.trim`
carries the reference written) is not trimmed again, nor a later result of the session a trim was
made from (samples read while the solve and the trim ran, solved after them: output before the
trim): once per power-up, as a power-up starts again from flash's trims.
"""

from __future__ import annotations

from contextlib import suppress
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import serial
import structlog

from stim300.errors import Stim300Error
from stim300.protocol import BIAS_TRIM
from stim300.trim import UNITS, TrimReading, apply_trims, read_trims

from ..config import TrimConfig
from ..errors import CalibdError
from ..results import CalibrationResult, TrimmedRecord
from ..trim import (TrimOptions, TrimRefused, beyond_range, guarded, missing, new_offsets, prune_backups, refusals,
                    result_refusals, trim_reference, write_backup)

log = structlog.get_logger("calibd")
KEPT_BACKUPS = 16  # the daemon's backups of a sensor kept in the state directory: one is written every power-up


class Trimmer:
    """Called with each new result (the Calibrator's `trim`): returns the result as it is to be
    published (with its `trimmed` record when written) and words for the state's detail ("" when
    nothing was written). `lend(use)` is the port reader's (`stim300.port.PortReader.lend`)."""

    def __init__(self, config: TrimConfig, backup_dir: Path, port: str, lend, timeout: float = 3.0):
        self.config, self.backup_dir, self.port, self.lend, self.timeout = config, backup_dir, port, lend, timeout
        self._written: TrimReading | None = None  # the trims this daemon wrote last, as read back
        self._refused_session: str | None = None  # the session whose refusal was logged
        self._failed: tuple[str | None, int] = (None, 0)  # the session whose failure was logged, and its failures

    def __call__(self, result: CalibrationResult) -> tuple[CalibrationResult, str]:
        if self.config.apply == "off" or self._trimmed_already(result):
            return result, ""
        try:
            problems = self._result_problems(result)
            if problems:
                raise TrimRefused("; ".join(problems))
            reading, backup = self.lend(lambda ser: self._trim(ser, result))
        except TrimRefused as refused:
            self._refused(result, str(refused))
            return result, ""
        except (Stim300Error, CalibdError, serial.SerialException, OSError) as exc:
            self._failure(result, str(exc) or type(exc).__name__)
            return result, ""
        self._written = reading
        sensors = self.config.sensors
        offsets = {sensor: list(reading.trims.of(sensor)) for sensor in sensors}
        log.info("trimmed", offsets=offsets, units={sensor: UNITS[sensor] for sensor in sensors},
                 reference=reading.reference, remaining_saves=reading.remaining_saves, backup=str(backup),
                 session_id=result.session_id)
        record = TrimmedRecord(datetime.now(timezone.utc).isoformat(timespec="seconds"), sensors,
                               reading.trims.gyro_deg_s, reading.trims.acc_g, reading.trims.incl_g,
                               reading.reference, reading.remaining_saves, str(backup))
        words = "; ".join(f"{sensor} " + " ".join(f"{axis} {v:+.6f}" for axis, v in zip("xyz", values))
                          + f" {UNITS[sensor]}" for sensor, values in offsets.items())
        return replace(result, trimmed=record), f"trimmed (volatile): {words}"

    def _trimmed_already(self, result: CalibrationResult) -> bool:
        """Whether the result was made on the output this daemon trimmed (its trim's reference is
        the one written, which names the result it came from: its biases are what the trim left),
        or is a later one of the session the trim was made from (its output is from before the
        trim, whose stream ends that session once the trim read back reaches it)."""
        if self._written is None:
            return False
        written = self._written.reference  # trim_reference of the session it was made from
        return trim_reference(result.session_id) == written or (
            result.sensor.trim is not None and result.sensor.trim.reference == written)

    def _result_problems(self, result: CalibrationResult) -> list[str]:
        """What the result alone says against it: its estimates, staleness, its power-up."""
        absent = missing(result, self.config.sensors)
        if absent:
            return [f"the result has no {', '.join(absent)}"]
        if result.sensor.acc_range_g is None:
            return ["the stream has not given the accelerometers' range (no configuration datagram)"]
        return result_refusals(result, self.config.sensors, result.sensor.acc_range_g)

    def _refused(self, result: CalibrationResult, reason: str) -> None:
        if result.session_id != self._refused_session:
            self._refused_session = result.session_id
            log.info("trim_refused", reason=reason, session_id=result.session_id,
                     detail="not trimmed; later results of this session are checked again without a log line")

    def _failure(self, result: CalibrationResult, error: str) -> None:
        """A failed trim: logged once per session, the session's count said when another begins."""
        session, count = self._failed
        if result.session_id == session:
            self._failed = (session, count + 1)
            return
        if count > 1:
            log.warning("trim_failures_ended", session_id=session, failures=count)
        self._failed = (result.session_id, 1)
        log.error("trim_failed", error=error, session_id=result.session_id,
                  detail="the backup is back in force; later failures of this session are counted, not logged")

    def _trim(self, ser, result: CalibrationResult) -> tuple[TrimReading, Path]:
        """On the lent port: read the unit, refuse (TrimRefused) or back up, write, read back
        (the backup put back on any failure), and ask for T, so the stream the daemon reads
        carries the new trims (a new session, the result marked stale)."""
        sensors = self.config.sensors
        unit = read_trims(ser, self.timeout)
        target = new_offsets(result, unit.trim.trims, sensors)
        problems = refusals(result, unit, sensors) + beyond_range(target, sensors, unit.trim.acc_range_g)
        if problems:
            raise TrimRefused("; ".join(problems))
        backup = write_backup(self.backup_dir, unit, self.port, datetime.now(timezone.utc))
        prune_backups(self.backup_dir, unit.serial_number, KEPT_BACKUPS)
        try:
            reading = guarded(ser, unit, backup, TrimOptions(timeout=self.timeout),
                              lambda text: log.warning("trim_restored", detail=text),
                              lambda: apply_trims(ser, target, sensors, trim_reference(result.session_id),
                                                  self.timeout))
        finally:
            with suppress(serial.SerialException, OSError):  # a port gone: the reader finds out
                ser.write(BIAS_TRIM.request)
        return reading, backup

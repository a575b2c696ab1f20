"""`calibd batch`: every power-up of many captures calibrated on the batch engine (calibd.engine)
into one fleet table (calibd.fleettable), resumable, one row per power-up.

The driver hashes each input (SHA-256: a capture already in the table with this calibd version
and these settings is skipped; a second input with the same bytes is a duplicate row), hands the
rest to the cluster one capture a task, and writes each finished task's rows at once into the
journal beside the table (FLEET.parquet.journal/, one Parquet file a task, each written
atomically): a batch killed at any moment loses no finished capture. At the end, and on SIGTERM
or Ctrl-C, the journal is folded into the table, written atomically and sorted, so the table is
the same whatever order the tasks finished in and however many workers ran them.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from stim300.cliutil import package_version
from stim300.errors import UsageError

from . import fleettable
from .captures import file_identity
from .errors import CalibdError, CalibrationError
from .frames import Site

SIDECARS = (".reads.npy", ".truth.json")  # files beside a capture that are not captures


@dataclass(frozen=True)
class BatchSettings:
    """What `calibd calibrate` would be told for each capture: the method and its options, the
    site, where to start in each power-up (None: where the warm-up ends), a recording's topic."""

    method: str
    site: Site
    options: dict = field(default_factory=dict)
    start_s: float | None = None
    topic: str | None = None

    def text(self) -> str:
        """The settings as the table's `settings` column holds them (canonical JSON)."""
        return fleettable.settings_text({"method": self.method, "latitude_deg": self.site.latitude_deg,
                                         "height_m": self.site.height_m, "g0_m_s2": self.site.g0,
                                         "options": self.options, "start_s": self.start_s, "topic": self.topic})


@dataclass(frozen=True)
class CaptureJob:
    """One capture for a worker: its path, what the driver found of the file, the settings."""

    path: str
    sha256: str
    size: int
    mtime_s: float
    settings: BatchSettings
    version: str

    def base_row(self) -> dict:
        return fleettable.file_row(self.path, self.settings.text(), self.version, self.sha256, self.size,
                                   self.mtime_s) | {"method": self.settings.method}


def calibrate_file(job: CaptureJob) -> list[dict]:
    """Every power-up of one capture as rows of the fleet table (runs on a worker): the
    calibration `calibd calibrate --power-up N` gives, or the one line saying why not."""
    from .calibrate import calibrate_capture
    from .captures import open_capture
    from .methods import estimator
    from .results import result_json

    base = job.base_row()
    try:
        capture = open_capture(job.path, topic=job.settings.topic)
    except (CalibdError, UsageError, OSError) as exc:
        return [base | {"status": "failed", "error": _line(exc)}]
    method = estimator(job.settings.method)
    options = method.options(job.settings.options)
    count = len(capture.power_ups)
    sensor = {"serial_number": capture.sensor.serial_number, "part_number": capture.sensor.part_number}
    rows = []
    for number in range(1, count + 1):
        try:
            result = calibrate_capture(capture, lambda s: method.solve(s, job.settings.site, None, options), number,
                                       job.settings.start_s)
        except CalibrationError as exc:
            rows.append(base | sensor | {"power_up": number, "power_ups": count, "status": "refused",
                                         "error": str(exc)})
            continue
        text = result_json(result).decode()
        rows.append(fleettable.result_row(base, json.loads(text), text))
    return rows


def _line(exc: BaseException) -> str:
    if isinstance(exc, OSError):
        return f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": ")
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def capture_paths(inputs: list[str]) -> list[str]:
    """The captures named: files as given, directories walked (sorted; hidden files and the
    sidecars calibd writes beside a capture left out)."""
    paths = []
    for given in inputs:
        if not os.path.isdir(given):
            paths.append(given)
            continue
        for root, dirs, files in os.walk(given):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            paths += [os.path.join(root, name) for name in sorted(files)
                      if not name.startswith(".") and not name.endswith(SIDECARS)]
    return paths


@dataclass
class Tally:
    """What a batch did, for its progress line and its last line."""

    total: int = 0
    done: int = 0
    skipped: int = 0
    duplicates: int = 0
    failed: int = 0
    refused: int = 0
    power_ups: int = 0
    started: float = field(default_factory=time.monotonic)

    def count(self, rows: list[dict]) -> None:
        self.done += 1
        self.failed += any(r["status"] == "failed" for r in rows)
        self.refused += sum(r["status"] == "refused" for r in rows)
        self.power_ups += sum(r["status"] == "ok" for r in rows)

    def line(self) -> str:
        elapsed = time.monotonic() - self.started
        left = self.total - self.done
        eta = f", about {_duration(elapsed / self.done * left)} left" if self.done and left else ""
        return (f"batch: {self.done}/{self.total} captures done, {self.failed} failed, {self.refused} power-ups "
                f"refused, {_duration(elapsed)}{eta}")


def _duration(seconds: float) -> str:
    minutes, s = divmod(round(seconds), 60)
    return f"{minutes} min {s:02d} s" if minutes else f"{s} s"


class Progress:
    """The tally on stderr: redrawn in place on a terminal, else a line at most every 10 s."""

    EVERY_S = 10.0

    def __init__(self, stream=sys.stderr) -> None:
        self.stream = stream
        self.tty = stream.isatty()
        self.last, self.shown = -float("inf"), None

    def show(self, tally: Tally, final: bool = False) -> None:
        now, line = time.monotonic(), tally.line()
        if self.tty:
            self.stream.write("\r\033[K" + line + ("\n" if final else ""))
        elif (final and (tally.done, tally.failed) != self.shown) or now - self.last >= self.EVERY_S:
            self.stream.write(line + "\n")
            self.last, self.shown = now, (tally.done, tally.failed)
        self.stream.flush()


class Journal:
    """The rows of finished tasks beside the table, one Parquet file a task, until folded in."""

    def __init__(self, table: Path) -> None:
        self.directory = table.with_name(table.name + ".journal")
        self.written = len(self.parts())

    def parts(self) -> list[Path]:
        return sorted(self.directory.glob("part-*.parquet")) if self.directory.is_dir() else []

    def add(self, rows: list[dict]) -> None:
        self.directory.mkdir(exist_ok=True)
        self.written += 1
        fleettable.write_table(self.directory / f"part-{self.written:06d}.parquet", rows)

    def rows(self) -> list[dict]:
        return [row for part in self.parts() for row in fleettable.read_rows(part)]

    def clear(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)


def merged(old: list[dict], new: list[dict]) -> list[dict]:
    """The table's rows after a run: a new row of a capture path replaces that path's older rows
    of the same calibd version and settings (the same bytes, or a failure before)."""
    replaced = {(r["capture"], r["calibd_version"], r["settings"]) for r in new}
    new_bytes = {(r["capture"], r["capture_sha256"]) for r in new}

    def stays(row: dict) -> bool:
        if (row["capture"], row["calibd_version"], row["settings"]) not in replaced:
            return True
        return row["status"] != "failed" and row["capture_sha256"] is not None and \
            (row["capture"], row["capture_sha256"]) not in new_bytes
    return [r for r in old if stays(r)] + new


@dataclass
class Plan:
    """What a run will do: the jobs for the cluster and the rows already settled by the driver."""

    jobs: list[CaptureJob]
    rows: list[dict]
    skipped: int
    duplicates: int


def plan(paths: list[str], settings: BatchSettings, known: list[dict], redo: bool) -> Plan:
    """Each input hashed: unreadable -> a failed row; the bytes of an earlier input -> a duplicate
    row; already in the table (this version, these settings, not failed) -> skipped unless `redo`."""
    version, text = package_version(), settings.text()
    done = {r["capture_sha256"] for r in known
            if r["status"] != "failed" and r["calibd_version"] == version and r["settings"] == text}
    first: dict[str, str] = {}
    jobs, rows, skipped, duplicates = [], [], 0, 0
    for path in paths:
        try:
            sha256, size, mtime_s = file_identity(path)
        except OSError as exc:
            rows.append(fleettable.file_row(path, text, version) | {"method": settings.method, "status": "failed",
                                                                     "error": _line(exc)})
            continue
        if sha256 in first:
            duplicates += 1
            rows.append(fleettable.file_row(path, text, version, sha256, size, mtime_s) | {
                "method": settings.method, "status": "duplicate",
                "error": f"the same bytes as {first[sha256]} (SHA-256 {sha256[:16]})"})
            continue
        first[sha256] = path
        if sha256 in done and not redo:
            skipped += 1
            continue
        jobs.append(CaptureJob(path, sha256, size, mtime_s, settings, version))
    return Plan(jobs, rows, skipped, duplicates)


def run_batch(inputs: list[str], settings: BatchSettings, output: str, client, redo: bool = False,
              progress: Progress | None = None) -> Tally:
    """Calibrate `inputs` on the Dask `client` into the fleet table `output` (docs/fleet.md)."""
    from .engine import TaskFailed, run_tasks

    table = Path(output)
    journal = Journal(table)
    old = fleettable.read_rows(table) if table.exists() else []
    pending = journal.rows()  # a run that was killed: its finished tasks count as done
    work = plan(capture_paths(inputs), settings, old + pending, redo)
    tally = Tally(total=len(work.jobs) + len(work.rows), skipped=work.skipped, duplicates=work.duplicates)
    progress = progress or Progress()
    try:
        if work.rows:
            journal.add(work.rows)
            for row in work.rows:
                tally.count([row])
        results = run_tasks(client, calibrate_file, work.jobs, names=[job.sha256[:16] for job in work.jobs])
        for index, rows in results:
            if isinstance(rows, TaskFailed):
                job = work.jobs[index]
                rows = [job.base_row() | {"status": "failed", "error": f"calibd failed on it: {rows.reason}"}]
            journal.add(rows)
            tally.count(rows)
            progress.show(tally)
    finally:
        fleettable.write_table(table, merged(old, journal.rows()))
        journal.clear()
    progress.show(tally, final=True)
    return tally

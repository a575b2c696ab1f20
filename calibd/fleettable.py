"""The fleet table (schema calibd.fleet/1): one row per power-up of every capture a batch
calibrated, in a Parquet file (docs/fleet.md describes every column).

A row says which file and which sensor (path, SHA-256, serial and part number, when the capture
was written), which calibd and settings made it, whether it was calibrated (`status`: "ok";
"refused" when the power-up lacks what the method needs; "failed" when the capture could not be
read; "duplicate" when another input has the same bytes) with the one-line reason, the stream's
health, and each estimate as three columns: its value and 1-sigma in the unit of the result
document (deg, deg/h, mg; each column's Parquet metadata names it) and its quality. `result`
holds the whole result document, byte for byte what `calibd calibrate` writes.

The file's key-value metadata carries the schema ("calibd.schema"); the version policy is the
result's (docs/result-schema.md): a reader reads its version and older ones, refuses newer ones.
"""

from __future__ import annotations

import datetime
import json

from stim300.atomic import atomic_file

from .documents import ESTIMATE_BOUNDS, SchemaError, schema_version
from .errors import CalibdError

FLEET_SCHEMA = "calibd.fleet"
FLEET_VERSION = 1
SCHEMA = f"{FLEET_SCHEMA}/{FLEET_VERSION}"
SCHEMA_KEY = b"calibd.schema"
NEEDS_EXTRA = "the fleet table needs the fleet extra: pip install 'stim300-calib[fleet]'"
STATUSES = ("ok", "refused", "failed", "duplicate")
ESTIMATE_NAMES = tuple(ESTIMATE_BOUNDS)
# the stream's health in a row: the power-up's counts, taken from the result's stream record
HEALTH = ("datagrams", "lost_samples", "inferred_missing", "crc_errors", "restarts", "flagged_datagrams")
# column -> (type name, unit or None, what it holds); the estimates' columns follow these
_FIXED = {
    "capture": ("string", None, "the capture's path as the batch was given it"),
    "capture_sha256": ("string", None, "SHA-256 of the capture's bytes (null when unreadable)"),
    "capture_bytes": ("int64", "B", "the capture's size"),
    "capture_time": ("timestamp", None, "when the capture file was last written (its modification time), UTC"),
    "power_up": ("int32", None, "the power-up of the capture the row is of, from 1 (null: the capture failed)"),
    "power_ups": ("int32", None, "power-ups in the capture"),
    "session_id": ("string", None, "the result's session_id: SHA256[:16]/pN/tSTART"),
    "serial_number": ("string", None, "the sensor's serial number, as its stream names it"),
    "part_number": ("string", None, "the sensor's part number"),
    "calibd_version": ("string", None, "the stim300-calib version that made the row"),
    "settings": ("string", None, "the batch's options (method, site, start) as canonical JSON"),
    "method": ("string", None, "the calibration method"),
    "status": ("string", None, "ok, refused, failed or duplicate"),
    "error": ("string", None, "why the row has no result, in one line (null when ok)"),
    "warnings": ("list<string>", None, "the result's warnings"),
    **{name: ("int64", None, f"the power-up's {name.replace('_', ' ')}") for name in HEALTH},
    "duration_s": ("float64", "s", "the power-up's length"),
    "start_s": ("float64", "s", "where in the power-up the calibration started"),
}
_ESTIMATE_COLUMNS = {
    column: spec for name, (unit, _) in ESTIMATE_BOUNDS.items() for column, spec in (
        (name, ("float64", unit, f"the {name} estimate")),
        (f"{name}_sigma", ("float64", unit, f"1-sigma of {name}")),
        (f"{name}_quality", ("string", None, f"{name}'s quality: poor when not to be used as it is, else null")))}
COLUMNS = {**_FIXED, **_ESTIMATE_COLUMNS,
           "result": ("string", None, "the result document (JSON), as calibd calibrate writes it")}


class FleetError(CalibdError):
    """A fleet table that cannot be read or written; one line naming the file."""


def pyarrow():
    """pyarrow, or one line saying which extra brings it."""
    try:
        import pyarrow
        import pyarrow.parquet  # noqa: F401 (the submodule the table's I/O uses)
    except ImportError:
        raise FleetError(NEEDS_EXTRA) from None
    return pyarrow


def arrow_schema():
    """The table's Arrow schema: each column's type, its unit and description as field metadata."""
    pa = pyarrow()
    types = {"string": pa.string(), "int64": pa.int64(), "int32": pa.int32(), "float64": pa.float64(),
             "list<string>": pa.list_(pa.string()), "timestamp": pa.timestamp("us", tz="UTC")}
    fields = [pa.field(name, types[kind], metadata={"description": what, **({"unit": unit} if unit else {})})
              for name, (kind, unit, what) in COLUMNS.items()]
    return pa.schema(fields, metadata={SCHEMA_KEY: SCHEMA.encode()})


def empty_row() -> dict:
    return dict.fromkeys(COLUMNS)


def file_row(path: str, settings: str, version: str, sha256: str | None = None, size: int | None = None,
             mtime_s: float | None = None) -> dict:
    """A row's identity part: which file (when it was written: seconds since the epoch) and which batch."""
    when = None if mtime_s is None else datetime.datetime.fromtimestamp(mtime_s, datetime.timezone.utc)
    return empty_row() | {"capture": path, "capture_sha256": sha256, "capture_bytes": size, "capture_time": when,
                          "calibd_version": version, "settings": settings, "warnings": []}


def result_row(base: dict, doc: dict, text: str) -> dict:
    """`base` (file_row) filled from a result document `doc` and its JSON `text`."""
    stream, sensor = doc["stream"], doc["sensor"]
    power_up = stream.get("power_up") or {}
    row = base | {"power_up": power_up.get("number"), "power_ups": power_up.get("count"),
                  "session_id": doc.get("session_id"), "serial_number": sensor.get("serial_number"),
                  "part_number": sensor.get("part_number"), "method": doc["method"], "status": "ok",
                  "warnings": list(doc["warnings"]), "duration_s": power_up.get("duration_s"),
                  "start_s": stream.get("start_s"), "result": text}
    row |= {name: stream.get(name) for name in HEALTH}
    if power_up:
        row["datagrams"] = power_up.get("datagrams", row["datagrams"])
    for name, estimate in doc["estimates"].items():
        row |= {name: estimate["value"], f"{name}_sigma": estimate["sigma"], f"{name}_quality": estimate.get("quality")}
    return row


def table(rows: list[dict]):
    """The rows as an Arrow table of this schema, sorted by capture, then power-up (failed rows of
    a whole capture first): the same table whatever order its rows came in."""
    pa = pyarrow()
    ordered = sorted(rows, key=lambda r: (r["capture"], r["power_up"] is not None, r["power_up"] or 0))
    return pa.Table.from_pylist([{name: row.get(name) for name in COLUMNS} for row in ordered],
                                schema=arrow_schema())


def write_table(path, rows: list[dict], durable: bool = True) -> None:
    """The rows written to `path` as one Parquet file, atomically (never half a table)."""
    pq = pyarrow().parquet
    data = table(rows)
    try:
        with atomic_file(path, durable) as f:
            pq.write_table(data, f, compression="zstd")
    except OSError as exc:
        raise FleetError(f"{path}: cannot write: {exc.strerror or exc}") from None


def read_rows(path) -> list[dict]:
    """The rows of a fleet table, or one line naming the file and what is wrong with it."""
    pa = pyarrow()
    try:
        data = pa.parquet.read_table(path)
    except FileNotFoundError:
        raise FleetError(f"{path}: no such file") from None
    except (OSError, pa.ArrowException) as exc:
        raise FleetError(f"{path}: not a fleet table: {str(exc).splitlines()[0][:120]}") from None
    meta = data.schema.metadata or {}
    try:
        version = schema_version(meta.get(SCHEMA_KEY, b"").decode(errors="replace") or None, FLEET_SCHEMA,
                                 FLEET_VERSION, f"{path}: the table's schema")
    except SchemaError as exc:
        raise FleetError(str(exc)) from None
    missing = [name for name in COLUMNS if name not in data.column_names]
    if missing and version == FLEET_VERSION:
        raise FleetError(f"{path}: {SCHEMA} table without column {missing[0]!r}")
    try:
        data = data.select(list(COLUMNS)).cast(arrow_schema())
    except (pa.ArrowException, KeyError) as exc:
        raise FleetError(f"{path}: a column of the wrong type: {str(exc).splitlines()[0][:120]}") from None
    return data.to_pylist()


def settings_text(settings: dict) -> str:
    """A batch's options as canonical JSON: the same options give the same text."""
    return json.dumps(settings, sort_keys=True, separators=(",", ":"))

"""Reading the documents calibd is given: JSON and TOML text decoded safely, and each kind of
JSON document checked against its one schema.

msgspec decodes JSON in C and converts it into typed structs whose fields carry their ranges
(msgspec.Meta), so a reader gets either a document it can compute with or one line naming the
file and the field ("r.json: estimates.pitch.value is 1e+308, expected a number in [-360, 360]").
NaN and Infinity are not JSON and never pass; a number beyond the float or 64-bit range is
refused; free-form parts (a check's figures, the error budget) nest at most FREE_DEPTH deep.
Hostile text fails in one line as well: nesting deeper than the interpreter's recursion
(RecursionError, from msgspec and tomllib alike), integers of thousands of digits, bytes that are
not UTF-8.

Each schema is what calibd itself writes: keys a schema does not know are ignored (a later version
may add some, docs/result-schema.md), fields an older version lacks take their defaults, and the
version policy is `schema_version`. The scenario's keys and ranges are its parser's
(`calibd.scenario`); its text comes through `parse_toml`, as the configuration's does.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import sys
import tomllib
from pathlib import Path
from typing import Annotated, Literal, Union

import msgspec
import numpy as np
from msgspec import Meta, Struct

from stim300.cliutil import DOCUMENT_LIMIT_BYTES, read_input
from stim300.errors import UsageError

from . import spec
from .errors import CalibdError
from .frames import SITE_RANGES, Site, SiteError

FLOAT_MAX = sys.float_info.max
FREE_DEPTH = 6  # lists and objects inside a free-form field (the error budget's factory terms need 3)
NOISE_MAX = 1000.0  # each noise figure in its unit (scenarios, noise files, `calibd plan`'s options)
# estimate name -> (display unit, largest magnitude): an angle within a turn, a bias within its
# sensor's input range (calibd.spec; the accelerometers' widest). The truth file's angles and biases
# are bounded alike.
ESTIMATE_BOUNDS = {
    **{angle: ("deg", 360.0) for angle in ("pitch", "roll", "yaw", "alpha", "beta")},
    **{f"gyro_bias_{a}": ("deg/h", spec.GYRO_RANGE_DEG_S * 3600.0) for a in "xyz"},
    **{f"acc_bias_{a}": ("mg", max(spec.ACC_RANGES_G) * 1000.0) for a in "xyz"},
    **{f"incl_bias_{a}": ("mg", spec.INCL_RANGE_G * 1000.0) for a in "xyz"},
}


class DocumentError(CalibdError):
    """A document that cannot be read as its kind; one line naming the file and the field."""


class SchemaError(CalibdError):
    """A document of another schema, or of a newer version than this calibd reads; one line."""


def schema_version(schema, name: str, newest: int, what: str, aliases: tuple[str, ...] = ()) -> int:
    """The version N of a document whose schema is "NAME/N" (or "ALIAS/N": a former name), by
    the version policy: newer than `newest` or another schema is a SchemaError naming `what`."""
    base, _, number = str(schema).rpartition("/")
    if base not in (name, *aliases) or not number.isascii() or not number.isdigit() or int(number) < 1:
        shown = repr(schema) if isinstance(schema, str) or schema is None else _shown(schema)
        raise SchemaError(f"{what} is {shown[:60]}, not a {name} file")
    if int(number) > newest:
        raise SchemaError(f"{what} is {name}/{number}, newer than this calibd reads (up to {newest}): "
                          "upgrade calibd")
    return int(number)


def document_version(doc, name: str, newest: int, where: str, error: type[CalibdError] = DocumentError) -> int:
    """The version of a decoded document that must be a JSON object of schema NAME/N (by the
    version policy), or `error` in one line naming `where`."""
    if not isinstance(doc, dict):
        raise error(f"{where}: a JSON {type(doc).__name__}, not an object: not a {name} file")
    try:
        return schema_version(doc.get("schema"), name, newest, where)
    except SchemaError as exc:
        raise error(str(exc)) from None


# ---------------------------------------------------------------- field types

def number(low: float = -FLOAT_MAX, high: float = FLOAT_MAX):
    """A finite number (an integer is taken too) in [low, high]."""
    return Annotated[float, Meta(ge=low, le=high)]


Number = number()
NonNegative = number(0.0)
Count = Annotated[int, Meta(ge=0)]
Ordinal = Annotated[int, Meta(ge=1)]
Vector = Annotated[list[Number], Meta(min_length=3, max_length=3)]
_Scalar = Union[str, bool, int, Number, None]


def _free(depth: int):
    """Any JSON value with at most `depth` levels of lists and objects inside, finite numbers."""
    value = _Scalar
    for _ in range(depth):
        value = Union[_Scalar, list[value], dict[str, value]]
    return value


Free = _free(FREE_DEPTH)


def _site_range(key: str):
    (low, high), _, _ = SITE_RANGES[key]
    return number(low, high)


# ---------------------------------------------------------------- calibd.result

def _estimate(kind: str, unit: str, bound: float) -> type:
    """An estimate as written: value within +-bound, its unit, a finite sigma >= 0 or null. The
    SI values and a bias's untrimmed value beside them are made again from these, never read."""
    return msgspec.defstruct(f"Estimate_{kind}", [
        ("value", number(-bound, bound)), ("unit", Literal[unit]),
        ("sigma", Union[NonNegative, None], None), ("quality", Union[str, None], None),
        ("value_si", Number, 0.0), ("sigma_si", Union[NonNegative, None], None), ("unit_si", str, ""),
        ("untrimmed", Union[number(-bound, bound), None], None)])


_KINDS = {name: "angle" if unit == "deg" else name[:-2] for name, (unit, _) in ESTIMATE_BOUNDS.items()}
_ESTIMATE_TYPES = {kind: _estimate(kind, *ESTIMATE_BOUNDS[name]) for name, kind in _KINDS.items()}  # one per kind
Estimates = msgspec.defstruct("Estimates", [(name, Union[_ESTIMATE_TYPES[kind], None], None)
                                            for name, kind in _KINDS.items()])


class Software(Struct):
    name: str
    version: str


class SiteDoc(Struct):
    latitude_deg: _site_range("latitude_deg")
    height_m: _site_range("height_m") = 0.0
    g0_m_s2: _site_range("g0") = 9.80665
    g0_given: bool = False
    g0_sigma_m_s2: NonNegative = 0.0
    earth_rate_deg_h: Number = 0.0
    earth_rate_rad_s: Number = 0.0


class RotationRecord(Struct):
    matrix: Annotated[list[Vector], Meta(min_length=3, max_length=3)]
    quaternion: Annotated[list[number(-1.0, 1.0)], Meta(min_length=4, max_length=4)]
    angles: list[str]
    poor: list[str] = []


class RotationDoc(Struct):
    convention: str
    nav_to_imu: Union[RotationRecord, None] = None
    int_to_imu: Union[RotationRecord, None] = None


class Covariance(Struct):
    names: list[Literal[tuple(ESTIMATE_BOUNDS)]]
    units: list[Literal["deg", "deg/h", "mg"]]
    matrix: list[list[Number]]

    def __post_init__(self):
        n = len(self.names)
        if len(self.units) != n or len(self.matrix) != n or any(len(row) != n for row in self.matrix):
            raise ValueError(f"names, units and matrix must be of one size n and n x n ({n} names)")


class SegmentDoc(Struct):
    kind: str = "static"
    role: Union[str, None] = None
    start_s: NonNegative = 0.0
    end_s: NonNegative = 0.0
    platform_angle_deg: Number = 0.0
    angle_deg: Number = 0.0
    rate_deg_s: Number = 0.0
    up: str = "+Z"


def _trims(bound: float):
    """Three bias trim offsets within +-bound (the triad's trim range, calibd.spec)."""
    return Annotated[list[number(-bound, bound)], Meta(min_length=3, max_length=3)]


class TrimDoc(Struct):
    """The bias trim offsets in force (stim300.records.TrimRecord); the accelerometers' within the
    widest range's trim range here, within their unit's in SensorDoc."""

    gyro_deg_s: _trims(spec.GYRO.bias_trim_range)
    acc_g: _trims(max(triad.bias_trim_range for triad in spec.ACC.values()))
    incl_g: _trims(spec.INCL.bias_trim_range)
    reference: Annotated[int, Meta(ge=0, le=(1 << 32) - 1)]
    remaining_saves: Annotated[int, Meta(ge=0, le=(1 << 16) - 1)]


class SensorDoc(Struct):
    serial_number: Union[str, None] = None
    part_number: Union[str, None] = None
    datagram_id: Union[str, None] = None
    sample_rate_hz: Union[number(1e-9), None] = None
    sample_rate: Union[str, None] = None
    acc_range_g: Union[Literal[spec.ACC_RANGES_G], None] = None
    trim: Union[TrimDoc, None] = None

    def __post_init__(self):
        """The accelerometer trims within the trim range of the unit's range, when it is known."""
        if self.trim is None or self.acc_range_g is None:
            return
        limit = spec.ACC[self.acc_range_g].bias_trim_range
        if any(abs(v) > limit for v in self.trim.acc_g):
            raise ValueError(f"trim.acc_g is {self.trim.acc_g}, beyond the +-{limit:g} g trim range of a "
                             f"{self.acc_range_g} g unit")


class PowerUp(Struct):
    number: Ordinal
    count: Ordinal
    first_datagram: Count
    datagrams: Count
    duration_s: NonNegative


class StreamDoc(Struct):
    capture: Union[str, None] = None
    datagrams: Union[Count, None] = None
    lost_samples: Count = 0
    inferred_missing: Count = 0
    crc_errors: Count = 0
    restarts: Count = 0
    warnings: list[str] = []
    start_s: Union[NonNegative, None] = None
    start_by: Union[str, None] = None
    power_up: Union[PowerUp, None] = None
    session: Union[Ordinal, None] = None
    flagged_datagrams: Count = 0
    fault_flags: list[Free] = []
    hidden_gaps: Union[Count, None] = None
    hidden_gap_s: Union[NonNegative, None] = None
    recording: Union[str, None] = None  # a recording of Imu messages (docs/recordings.md): what it is, in words
    topic: Union[str, None] = None
    frame_id: Union[str, None] = None
    messages: Union[Count, None] = None
    gaps: Union[Count, None] = None

    def __post_init__(self):
        if self.power_up is not None and self.start_s is None:
            raise ValueError("a power_up record comes with start_s, where calibration started in it (a number)")


class EarthRateCheck(Struct):
    fitted: Number
    sigma: NonNegative
    expected: Number


class Chi2(Struct):
    chi2: NonNegative
    dof: Count
    p_value: number(0.0, 1.0)


class TurnAngle(Struct):
    start_s: NonNegative
    end_s: NonNegative
    gyro_deg: Number
    tilt_minus_gyro_deg: Number
    sigma_deg: NonNegative
    corrected: bool


class IndexedTurnsCheck(Struct):
    step_deg: Number
    sigma_deg: NonNegative
    static_angles_deg: list[Number]
    gyro_minus_stop_deg: list[Number]
    scale_along_axis_ppm: Number
    scale_sigma_ppm: NonNegative
    turns_left_out: list[Ordinal] = []


Pair = Annotated[list[Number], Meta(min_length=2, max_length=2)]


class SecondMountingCheck(Struct):
    """The unit's second mounting (calibd.methods.joint.SecondMounting): its capture, its tilt, and
    the two tilts' sum against what the factory residuals allow."""

    size_bytes: Count
    sha256: Annotated[str, Meta(pattern="^[0-9a-f]{64}$")]
    power_up: Ordinal
    remount_sigma_deg: NonNegative
    alpha_deg: Number
    beta_deg: Number
    tilt_sum_mrad: Pair
    predicted_mrad: Pair
    sigma_mrad: Annotated[list[NonNegative], Meta(min_length=2, max_length=2)]
    chi2: NonNegative
    p_value: number(0.0, 1.0)
    path: Union[str, None] = None


class Checks(Struct):
    earth_rate_horizontal_deg_h: Union[EarthRateCheck, None] = None
    static_chi2: Union[Chi2, None] = None
    force_static_chi2: Union[Chi2, None] = None
    gyro_residual_rms_deg_s: Union[Vector, None] = None
    platform_axis_in_gyro_axes: Union[Vector, None] = None
    noise_excess_over_white: dict[str, NonNegative] = {}
    turn_angles: list[TurnAngle] = []
    indexed_turns: Union[IndexedTurnsCheck, None] = None
    second_mounting: Union[SecondMountingCheck, None] = None


class IntrinsicsDoc(Struct):
    """The factory terms an earlier result of the unit estimated, taken as known (`--intrinsics`)."""

    terms: list[str]
    path: Union[str, None] = None


class Options(Struct):
    fixed_amplitude: bool = False
    drift: bool = False
    index_step_deg: Union[Number, None] = None
    index_sigma_deg: Union[NonNegative, None] = None
    intrinsics: Union[IntrinsicsDoc, None] = None


class CaptureDoc(Struct):
    size_bytes: Count
    sha256: Annotated[str, Meta(pattern="^[0-9a-f]{64}$")]
    path: Union[str, None] = None
    serial_number: Union[str, None] = None


class SessionDoc(Struct):
    number: Ordinal
    duration_s: NonNegative
    solved_at: Union[str, None] = None


class Stale(Struct):
    power_up: str
    reason: str
    since: str


class Trimmed(TrimDoc):
    """The daemon's volatile trim made from the result (calibd.results.TrimmedRecord): the offsets
    and reference read back, and when, which triads, the backup."""

    at: str
    sensors: Annotated[list[Literal["gyro", "acc", "incl"]], Meta(min_length=1, max_length=3)]
    backup: str


class ResultDoc(Struct):
    """calibd.result/1 to /7 (docs/result-schema.md); the rotation is made from the estimates."""

    schema: str
    method: str
    site: SiteDoc
    estimates: Estimates
    software: Union[Software, None] = None
    session_id: Union[str, None] = None
    rotation: Union[RotationDoc, None] = None  # checked, never read: it is made from the estimates
    covariance: Union[Covariance, None] = None
    segments: list[SegmentDoc] = []
    warnings: list[str] = []
    sensor: SensorDoc = msgspec.field(default_factory=SensorDoc)
    stream: StreamDoc = msgspec.field(default_factory=StreamDoc)
    options: Union[Options, None] = None
    checks: Union[Checks, None] = None
    bias_reference: Union[str, None] = None
    error_budget: Union[dict[str, Free], None] = None
    platform_rate_deg_s: Union[number(-spec.GYRO_RANGE_DEG_S, spec.GYRO_RANGE_DEG_S), None] = None
    earth_rate_diagnostic: Union[dict[str, Free], None] = None
    turns_alpha_beta_deg: Union[list[Free], None] = None
    capture: Union[CaptureDoc, None] = None
    session: Union[SessionDoc, None] = None
    stale: Union[Stale, None] = None
    trimmed: Union[Trimmed, None] = None


# ---------------------------------------------------------------- calibd.noise

class Figure(Struct):
    """A figure read off an Allan curve: its value and 68 % interval in `unit`, at tau_s."""

    value: number(0.0, NOISE_MAX)
    unit: str
    low: NonNegative = 0.0
    high: NonNegative = 0.0
    tau_s: NonNegative = 0.0


class NoiseChannel(Struct):
    random_walk: Figure
    bias_instability: Figure
    rate_random_walk: Union[Figure, None] = None
    adev_unit: Union[str, None] = None
    taus_s: list[NonNegative] = []
    adev: list[NonNegative] = []
    adev_low: list[NonNegative] = []
    adev_high: list[NonNegative] = []


# gyro and accelerometers always; the inclinometers' three channels when the unit has them
NoiseChannels = msgspec.defstruct("NoiseChannels", [
    *((f"{s}_{a}", NoiseChannel) for s in ("gyro", "acc") for a in "xyz"),
    *((f"incl_{a}", Union[NoiseChannel, None], None) for a in "xyz")])


class NoiseDoc(Struct):
    """calibd.noise/1 (docs/noise.md)."""

    schema: str
    channels: NoiseChannels
    capture: Union[str, None] = None
    sample_rate_hz: Union[number(1e-9), None] = None
    static_s: NonNegative = 0.0
    segments: Count = 0


# ---------------------------------------------------------------- calibd.truth

def _truth_fields() -> list:
    """The truth's numbers: angles and biases bounded as the estimates they are compared with,
    the factory residuals finite (three scale factors, six misalignments)."""
    fields = [(f"{name}_deg", number(-bound, bound), 0.0) for name, (unit, bound) in ESTIMATE_BOUNDS.items()
              if unit == "deg"]
    for sensor in ("gyro", "acc", "incl"):
        unit, bound = ESTIMATE_BOUNDS[f"{sensor}_bias_x"]
        triple = Annotated[list[number(-bound, bound)], Meta(min_length=3, max_length=3)]
        zeros = msgspec.field(default_factory=lambda: [0.0] * 3)
        fields += [(f"{sensor}_bias_{'deg_h' if unit == 'deg/h' else 'mg'}", triple, zeros),
                   (f"{sensor}_scale_ppm", Vector, zeros),
                   (f"{sensor}_misalignment_mrad", Annotated[list[Number], Meta(min_length=6, max_length=6)],
                    msgspec.field(default_factory=lambda: [0.0] * 6))]
    return fields


TruthValues = msgspec.defstruct("TruthValues", _truth_fields())


class DuringCapture(Struct):
    session: Vector


class TruthDoc(Struct):
    """calibd.truth/1 and /2 (calibd.sim.truth_record); what the report compares with."""

    schema: str
    truth: TruthValues
    bias_during_capture: dict[str, DuringCapture] = {}


# ---------------------------------------------------------------- the daemon's state.json

class StateDoc(Struct):
    """What `calibd status` reads of state.json (calibd.results.ResultStore writes it)."""

    state: str
    detail: str
    updated: NonNegative  # s since the epoch
    degraded: Union[str, None] = None
    held_back: Union[str, None] = None


# ---------------------------------------------------------------- decoding

DEEP = 64  # where a document nested deeper than the decoders recurse (some 1000 levels) is said to be
DEEP_TOML = r"(\[\s*){%d}" % DEEP
_JSON_TOKENS = re.compile(rb'"(?:[^"\\]|\\.)*"|[\[\]{}:,]')
_NOT_NUMBERS = re.compile(rb"-?(NaN|Infinity)")  # what Python's json writes and JSON does not have


# ---------------------------------------------------------------- TOML tables

class Table:
    """Typed access to one TOML table (a scenario's, a daemon configuration's), with errors of
    type `error` that say file, table and key."""

    def __init__(self, data: dict, where: str, error: type[CalibdError] = DocumentError):
        self.data, self.where, self.used, self.error = data, where, set(), error

    def fail(self, key: str, message: str):
        raise self.error(f"{self.where} {key}: {message}")

    def get(self, key: str, default, kind=float, check=None, expect: str = ""):
        self.used.add(key)
        length = len(default) if isinstance(default, tuple) else 3  # of a list (kind tuple)
        if key not in self.data:
            return default
        value = self.data[key]
        try:
            if kind is float:
                if not finite(value):
                    raise TypeError
                value = float(value)
            elif kind is tuple:
                if not isinstance(value, list) or len(value) != length or not all(map(finite, value)):
                    raise TypeError
                value = tuple(map(float, value))
            elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise TypeError
        except TypeError:
            names = {float: "a number", int: "an integer", bool: "true or false", str: "a string",
                     tuple: f"a list of {length} numbers", dict: "a table", list: "a list"}
            self.fail(key, f"{_table_value(value)} is not {names[kind]}")
        if check is not None and not check(value):
            self.fail(key, f"{_table_value(value)} is not {expect}")
        return value

    def missing(self, key: str, words: str):
        """Fail: `key` is missing; an unknown key of the table close to it is named (a typo)."""
        typo = difflib.get_close_matches(key, [k for k in self.data if k not in self.used], 1, 0.75)
        self.fail(key, f"missing: {words}" + (f" (the table has {typo[0]!r}, an unknown key: a typo?)" if typo else ""))

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            self.fail(unknown[0], f"unknown key (known: {', '.join(sorted(self.used))})")


def _table_value(value) -> str:
    """A TOML value as a table's message shows it (Python's spelling, at most 60 characters: a list
    nested deep, a long string)."""
    text = repr(value) if not isinstance(value, int) or value.bit_length() < 200 else "an integer too large"
    return text if len(text) <= 60 else f"{text[:57]}..."


def site_from_table(t: Table) -> Site:
    """The [site] table of a scenario or a daemon configuration; the Site checks the ranges, the
    table says where."""
    lat = t.get("latitude_deg", None, float)
    if lat is None:
        t.missing("latitude_deg", "the site's latitude is needed for the Earth rate")
    try:
        site = Site(lat, t.get("height_m", 0.0, float), t.get("g0", None, float))
    except SiteError as exc:
        t.fail(exc.field, exc.reason)
    t.finish()
    return site


def json_value(value):
    """A numpy number or array that reached a document (a check's flag, a figure) as the JSON
    value it holds: the hook of every encoder of results (result files, socket messages)."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def decode_json(data: str | bytes, where, schema: type, error: type[CalibdError] = DocumentError,
                noun: str = "JSON"):
    """The JSON value of `data` (dicts, lists, ...) or `error` in one line: not JSON (said as
    "not {noun}"), nested too deep, a number out of range (`schema` finds its field)."""
    try:
        return msgspec.json.decode(data)
    except msgspec.ValidationError as exc:  # a number out of any range: the schema names its field
        try:
            msgspec.json.decode(data, type=schema)
        except msgspec.ValidationError as located:
            raise error(f"{where}: {_message(located, schema)}") from None
        except msgspec.DecodeError as broken:  # the number was in a field the schema skips; broken beyond it
            raise error(f"{where}: not {noun} ({str(broken).removeprefix('JSON is malformed: ')})") from None
        except (RecursionError, UnicodeDecodeError):
            pass
        raise error(f"{where}: {str(exc).partition(' - at')[0].lower()} in a field calibd does not read") from None
    except msgspec.DecodeError as exc:
        at = re.search(r"\(byte (\d+)\)", str(exc))
        raw = data.encode() if isinstance(data, str) else bytes(data)
        token = at and _NOT_NUMBERS.match(raw, max(int(at.group(1)) - 1, 0))  # the minus sign is read first
        token = token or at and _NOT_NUMBERS.match(raw, int(at.group(1)))
        if token:
            raise error(f"{where}: {_json_path(raw, token.start())} is {token.group().decode()}, not a number "
                        "JSON has") from None
        raise error(f"{where}: not {noun} ({str(exc).removeprefix('JSON is malformed: ')})") from None
    except RecursionError:
        path = _json_path(data.encode() if isinstance(data, str) else bytes(data))
        raise error(f"{where}: {path} is nested too deep to read") from None
    except UnicodeDecodeError as exc:  # a string of bytes that are not UTF-8
        raise error(f"{where}: not UTF-8 text (byte {exc.start})") from None


def validate(doc, schema: type, where, error: type[CalibdError] = DocumentError):
    """`doc` (decoded JSON) converted to `schema`, or `error` in one line naming the field, what
    it is and what was expected."""
    try:
        return msgspec.convert(doc, schema)
    except msgspec.ValidationError as exc:
        raise error(f"{where}: {_message(exc, schema, doc)}") from None


def _message(exc: msgspec.ValidationError, schema: type, doc=None) -> str:
    """msgspec's words in calibd's: "estimates.yaw.sigma is [], expected a number >= 0 or null"."""
    text, _, path = str(exc).partition(" - at `")
    path = path.rstrip("`") or "$"
    missing = re.fullmatch(r"Object missing required field `(.*)`", text)
    if missing:
        return f"{_name(path + '.' + missing.group(1))} is missing"
    steps = re.findall(r"\.([^.\[]+)|\[(\d+|\.\.\.)\]", path[1:])
    expected = _expected(msgspec.inspect.type_info(schema), steps)
    if not text.startswith(("Expected", "Invalid enum", "Integer value", "Number out")) or expected is None:
        return f"{_name(path)}: {text}"  # a struct's own check (__post_init__)
    value = doc
    for key, index in steps:
        try:
            value = value[key] if key else value[int(index)]
        except (KeyError, IndexError, TypeError, ValueError):  # "[...]": a key msgspec does not name
            out_of_range = text.startswith(("Integer value", "Number out"))
            return f"{_name(path)} is {'out of range, expected' if out_of_range else 'not'} {expected}"
    return f"{_name(path)} is {_shown(value)}, expected {expected}"


def _name(path: str) -> str:
    return "the document" if path == "$" else path.removeprefix("$.")


def _shown(value) -> str:
    """A value as JSON, at most 40 characters (an integer of thousands of digits is not printed)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        return "an integer too large"
    try:
        return json.dumps(value)[:40]
    except (TypeError, ValueError):
        return repr(value)[:40]


def _expected(info, steps) -> str | None:
    """What the schema wants at the path `steps`, in words; None when the path leaves it."""
    for key, index in steps:
        info = _container(info, index != "" and index != "..." and not key)
        if isinstance(info, msgspec.inspect.StructType):
            info = next((f.type for f in info.fields if f.encode_name == key), None)
        elif isinstance(info, msgspec.inspect.ListType):
            info = info.item_type
        elif isinstance(info, msgspec.inspect.DictType):
            info = info.value_type
        else:
            return None
    return _words(info)


def _container(info, indexed: bool):
    """The list (`indexed`) or object member of a union, where the path goes into it."""
    if isinstance(info, msgspec.inspect.UnionType):
        kinds = (msgspec.inspect.ListType,) if indexed else (msgspec.inspect.StructType, msgspec.inspect.DictType)
        return next((t for t in info.types if isinstance(t, kinds)), info)
    return info


def _words(info) -> str:
    mi = msgspec.inspect
    if isinstance(info, mi.UnionType):
        parts = [_words(t) for t in info.types]
        return " or ".join(parts) if len(parts) < 3 else f"{', '.join(parts[:-1])} or {parts[-1]}"
    if isinstance(info, (mi.FloatType, mi.IntType)):
        low = info.ge if info.ge is not None and info.ge > -FLOAT_MAX else None
        high = info.le if info.le is not None and info.le < FLOAT_MAX else None
        what = "a number" if isinstance(info, mi.FloatType) else "a whole number"
        if low is not None and high is not None:
            return f"{what} in [{low:g}, {high:g}]"
        return what + (f" >= {low:g}" if low is not None else "") + (f" <= {high:g}" if high is not None else "")
    if isinstance(info, mi.LiteralType):
        return " or ".join(json.dumps(v) for v in info.values) if len(info.values) < 4 else \
            f"one of {', '.join(json.dumps(v) for v in info.values)}"
    if isinstance(info, mi.ListType):
        size = f" of {info.min_length}" if info.min_length and info.min_length == info.max_length else ""
        return f"a list{size}"
    if isinstance(info, mi.StrType) and info.pattern:
        return f"a string matching {info.pattern}"
    words = {mi.StrType: "a string", mi.BoolType: "true or false", mi.NoneType: "null", mi.StructType: "an object",
             mi.DictType: "an object"}
    return words.get(type(info), "a value")


def _json_path(data: bytes, offset: int | None = None) -> str:
    """The path, as msgspec writes paths, of the value at `offset` of JSON bytes, or (None) of
    the first container DEEP levels down; only read when decoding failed, so speed does not matter."""
    stack: list[list] = []  # per open container: [is an object, the current key or index]
    last = b""
    for token in _JSON_TOKENS.finditer(data):
        t = token.group()
        if offset is not None and token.start() >= offset:
            break
        if t in (b"[", b"{"):
            if len(stack) >= DEEP:
                break
            stack.append([t == b"{", None if t == b"{" else 0])
        elif t in (b"]", b"}"):
            if stack:
                stack.pop()
        elif t == b",":
            if stack and not stack[-1][0]:
                stack[-1][1] += 1
        elif t == b":":
            if stack and stack[-1][0]:
                stack[-1][1] = last[1:-1].decode("utf-8", "replace")
        else:
            last = t
    steps = [f".{key}" if is_object else f"[{key}]" for is_object, key in stack[:6]]
    return _name("$" + "".join(steps) + ("..." if len(stack) > 6 else ""))


# ---------------------------------------------------------------- TOML

def parse_toml(text: str, where, error: type[CalibdError] = DocumentError) -> dict:
    """TOML text as its tables, or `error` in one line naming `where` (and the key and line of
    arrays nested too deep, or of an integer too long to convert). tomllib takes nan and inf as
    floats: the tables' own readers refuse non-finite numbers."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{where}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{where}: {_toml_line(text, DEEP_TOML)}: arrays nested too deep to read") from None
    except ValueError:  # int() of more digits than Python converts
        limit = sys.get_int_max_str_digits()
        where_in = _toml_line(text, r"\d{%d}" % limit)
        raise error(f"{where}: {where_in}: an integer of more than {limit} digits") from None


def _toml_line(text: str, pattern: str) -> str:
    """"key (line N)" of the first line where `pattern` is found."""
    for number, line in enumerate(text.splitlines(), 1):
        if re.search(pattern, line):
            key = line.split("=", 1)[0].strip() if "=" in line else ""
            return f"{key} (line {number})" if key else f"line {number}"
    return "a value"


def finite(value) -> bool:
    """A JSON or TOML number that is finite (not a bool, not too large an integer for a float)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def load_state(state_file: Path) -> dict:
    """The daemon's state.json, as `calibd status` reads it: an object with its state (text),
    detail (text) and time of update (s since the epoch); UsageError (one line) for anything
    else."""
    def refuse(why: str):
        return UsageError(f"{state_file}: not a calibd state file: {why}")
    try:
        text = read_input(state_file, "state file", DOCUMENT_LIMIT_BYTES, follow=False).decode()
    except UsageError as exc:  # a directory, FIFO, device, symbolic link or a huge file
        raise refuse(f"cannot read it ({str(exc).removeprefix(f'{state_file}: ')})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise refuse(f"cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    where = f"{state_file}: not a calibd state file"
    try:  # its schema: calibd.documents.StateDoc
        state = decode_json(text, where, StateDoc)
        if not isinstance(state, dict):
            raise refuse(f"a JSON {type(state).__name__}, not an object")
        validate(state, StateDoc, where)
    except DocumentError as exc:
        raise UsageError(str(exc)) from None
    return state

"""The calibration result every method writes (schema calibd.result/7), typed, and its safe storage.

Estimates are kept in SI inside the code; here they become the units people read: degrees,
deg/h for gyro biases, mg (1e-3 of the sensor's g, 9.80665 m/s^2) for accelerometer and
inclinometer biases, each written with its SI value beside it. A result file is replaced
atomically and synced, so a crash never leaves a half-written or empty result where the last
good one was (the daemon's state directory: calibd.statedir). docs/result-schema.md describes
every field.

Version policy (for every file calibd writes, "NAME/N"): a reader reads its own version and
older ones (fields they lack take their defaults), refuses a newer one with a message that
says to upgrade calibd, and refuses other schemas. The version goes up when the content changes.
A result is always written as the current version, whatever version it was read from.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from stim300.atomic import write_atomic
from stim300.records import SensorRecord, StreamRecord
from stim300.cliutil import DOCUMENT_LIMIT_BYTES, package_version, read_input
from stim300.errors import UsageError

from .documents import ESTIMATE_BOUNDS, ResultDoc, decode_json, document_version, json_value, validate
from .errors import CalibdError
from .frames import EARTH_RATE, Site, int_to_imu, nav_to_imu
from .units import DEG, M_S2_TO_MG, RAD_S_TO_DEG_H

RESULT_SCHEMA = "calibd.result"
# 2: the same content as 1, written from the typed CalibrationResult; 3: SI values, the rotation
# as matrix and quaternion, the estimates' covariance, software, session_id, the site's g0 sigma;
# 4: the joint method's error_budget (each sigma by its terms; the factory residuals' prior), its
# sigmas and covariance now carrying the factory residuals; 5: sensor.trim, the bias trim offsets in
# force, and each bias estimate's untrimmed value beside it, and trimmed, the daemon's volatile trim
# made from the result
RESULT_VERSION = 7
SCHEMA = f"{RESULT_SCHEMA}/{RESULT_VERSION}"
# display unit -> (display units per SI unit, SI unit): the one conversion of estimates
DISPLAY_UNITS = {"deg": (1 / DEG, "rad"), "deg/h": (RAD_S_TO_DEG_H, "rad/s"), "mg": (M_S2_TO_MG, "m/s^2")}
# estimate name -> (factor from SI, display unit); the names, units and ranges are the schema's
ESTIMATES = {name: (DISPLAY_UNITS[unit][0], unit) for name, (unit, _) in ESTIMATE_BOUNDS.items()}
ROTATION_CONVENTION = ("passive: M takes a vector's components in the frame it is from (NAV: North-West-Up; int: "
                       "the mounting interface) to its IMU components, v_IMU = M v; matrix row-major; quaternion "
                       "[w, x, y, z], Hamilton, unit, w >= 0, v_IMU = q v q* (the same map as the matrix)")
# rotation -> (the function of frames that makes it, its angles in the order it takes them)
ROTATIONS = {"nav_to_imu": (nav_to_imu, ("yaw", "pitch", "roll")), "int_to_imu": (int_to_imu, ("alpha", "beta"))}
SOFTWARE = "stim300-calib"
TRIM_TO_DISPLAY = {"deg/h": 3600.0, "mg": 1000.0}  # a bias's display units per trim unit (deg/s, g)


class ResultError(CalibdError):
    """A result file that is missing, unreadable or not of this schema."""


@dataclass(frozen=True)
class Estimate:
    """One estimate in the units people read; quality "poor" when it is not to be used as it is.
    Its SI value follows from its unit (DISPLAY_UNITS)."""

    value: float
    sigma: float | None
    unit: str
    quality: str | None = None

    @classmethod
    def from_si(cls, name: str, value_si: float, sigma_si: float | None = None) -> Estimate:
        factor, unit = ESTIMATES[name]
        return cls(float(value_si) * factor, None if sigma_si is None else float(sigma_si) * factor, unit)

    @property
    def unit_si(self) -> str:
        return DISPLAY_UNITS[self.unit][1]

    @property
    def value_si(self) -> float:
        return self.value / DISPLAY_UNITS[self.unit][0]

    @property
    def sigma_si(self) -> float | None:
        return None if self.sigma is None else self.sigma / DISPLAY_UNITS[self.unit][0]

    def to_dict(self) -> dict:
        return {"value": self.value, "sigma": self.sigma, "unit": self.unit, "value_si": self.value_si,
                "sigma_si": self.sigma_si, "unit_si": self.unit_si,
                **({"quality": self.quality} if self.quality else {})}


# optional fields, written only when set: the method's own (joint: options, checks, bias_reference,
# error_budget; thesis: platform_rate_deg_s, earth_rate_diagnostic; thesis bench:
# turns_alpha_beta_deg), then the capture's identity (offline), then the daemon's (session, stale,
# trimmed)
_OPTIONAL = ("options", "checks", "bias_reference", "error_budget", "platform_rate_deg_s", "earth_rate_diagnostic",
             "turns_alpha_beta_deg", "capture", "session", "stale", "trimmed")


@dataclass(frozen=True)
class PowerUpRecord:
    """Which power-up of a capture a result rests on: its number of `count`, where its datagrams
    are in the capture, and its length (s)."""

    number: int
    count: int
    first_datagram: int
    datagrams: int
    duration_s: float


@dataclass(frozen=True)
class ResultStream:
    """The data a result rests on and their stream's health, typed from where a session is made
    (a capture's power-up, a recording, the daemon's session) to the result's "stream" object.
    The statistics are the driver's (`stim300.records.StreamRecord`) with the session's faults
    and hidden gaps; the rest says where the data came from. None is "not known" (a result of an
    older version says less): `to_dict` leaves it out, but for the hidden gaps of a session's
    fault record, null where there were no host read times to look with."""

    capture: str | None = None  # the file or port read
    recording: str | None = None  # a recording of Imu messages: its format in words
    topic: str | None = None
    frame_id: str | None = None
    messages: int | None = None
    datagrams: int | None = None
    lost_samples: int | None = None
    gaps: int | None = None  # a recording: gaps in its header stamps
    inferred_missing: int | None = None
    crc_errors: int | None = None
    restarts: int | None = None
    warnings: tuple[str, ...] | None = None  # what the decoder refused or kept as read, one line each
    start_s: float | None = None  # calibrate: where calibration started in the power-up (s)
    start_by: str | None = None  # and why there
    power_up: PowerUpRecord | None = None
    session: int | None = None  # the daemon: its session's number
    flagged_datagrams: int | None = None  # datagrams whose status bytes flagged a fault
    fault_flags: tuple[str, ...] | None = None
    hidden_gaps: int | None = None  # gaps of whole counter cycles the host's read times showed
    hidden_gap_s: float | None = None

    def __post_init__(self):
        for name in ("warnings", "fault_flags"):  # tuples, as read from a file's lists too
            if getattr(self, name) is not None:
                object.__setattr__(self, name, tuple(getattr(self, name)))
        if isinstance(self.power_up, dict):
            object.__setattr__(self, "power_up", PowerUpRecord(**self.power_up))

    @classmethod
    def of(cls, stats: StreamRecord, **where) -> ResultStream:
        """The driver's statistics of a stream, with where it came from (fields of this record)."""
        return cls(**{f.name: getattr(stats, f.name) for f in fields(StreamRecord)}, **where)

    def to_dict(self) -> dict:
        looked = {"hidden_gaps", "hidden_gap_s"} if self.flagged_datagrams is not None else set()
        return {f.name: _json_ready(getattr(self, f.name)) for f in fields(self)
                if getattr(self, f.name) is not None or f.name in looked}

    @classmethod
    def from_dict(cls, doc: dict) -> ResultStream:
        """The record of a (validated) document's "stream" object; keys it does not know are left out."""
        return cls(**{f.name: doc[f.name] for f in fields(cls) if f.name in doc})


def _json_ready(value):
    return list(value) if isinstance(value, tuple) else asdict(value) if isinstance(value, PowerUpRecord) else value


@dataclass(frozen=True)
class SessionRecord:
    """The daemon's session a result was solved on: its number since the daemon started, its
    length (s) and when it was solved (ISO 8601, UTC)."""

    number: int
    duration_s: float
    solved_at: str | None = None


@dataclass(frozen=True)
class StaleRecord:
    """Why a result no longer applies: the power-up it belongs to ("previous": the sensor
    restarted after it; "current": the bias trim changed under it; "unknown": an earlier daemon's
    result whose trim is not the one in force), the reason in words, since when (ISO 8601, UTC)."""

    power_up: str
    reason: str
    since: str


@dataclass(frozen=True)
class TrimmedRecord:
    """The daemon wrote the result into the sensor as volatile bias trims ([trim] apply =
    "volatile", docs/trim.md): when (ISO 8601, UTC), which triads, the nine offsets then in force
    as read back (deg/s, g), the reference naming the result, the flash saves left (none spent)
    and the backup file of the offsets before."""

    at: str
    sensors: tuple[str, ...]
    gyro_deg_s: tuple[float, float, float]
    acc_g: tuple[float, float, float]
    incl_g: tuple[float, float, float]
    reference: int
    remaining_saves: int
    backup: str

    def __post_init__(self):
        for name in ("sensors", "gyro_deg_s", "acc_g", "incl_g"):  # tuples, as read from a file's lists too
            object.__setattr__(self, name, tuple(getattr(self, name)))


# optional fields written as records
_RECORDS = {"session": SessionRecord, "stale": StaleRecord, "trimmed": TrimmedRecord}


@dataclass(frozen=True)
class CalibrationResult:
    """What a method found on a session: estimates by name, the segments and data they rest on,
    and what the reader must know (warnings). Changed by copies (`flag_poor`, `with_warning`,
    `dataclasses.replace`), never in place. The rotation record is made from the estimates each
    time it is written, so it always agrees with them (their quality too)."""

    method: str
    site: dict  # site_record
    estimates: dict[str, Estimate]
    segments: tuple[dict, ...] = ()
    warnings: tuple[str, ...] = ()
    sensor: SensorRecord = SensorRecord()
    stream: ResultStream = ResultStream()
    covariance: dict | None = None  # covariance_record: the joint method's; None: the method has none
    software: dict | None = None  # name and version of what made it; None: read from a version 1 or 2 file
    session_id: str | None = None  # the data it rests on (offline: capture, power-up, start; daemon: its session)
    options: dict | None = None  # joint: the options it was solved with
    checks: dict | None = None  # joint: model checks (Earth rate seen, chi-squares, turn angles)
    bias_reference: str | None = None  # joint: "turn-on"
    error_budget: dict | None = None  # joint: each sigma by its terms, and the factory residuals' prior
    platform_rate_deg_s: float | None = None  # thesis real case
    earth_rate_diagnostic: dict | None = None  # thesis real case
    turns_alpha_beta_deg: list | None = None  # thesis bench: alpha and beta from each full turn
    capture: dict | None = None  # offline: the file it was made from (path, size_bytes, sha256, serial_number)
    session: SessionRecord | None = None  # daemon: which session, how long, when solved
    stale: StaleRecord | None = None  # daemon: why the result no longer applies
    trimmed: TrimmedRecord | None = None  # daemon: the volatile trim written from it
    schema: str = SCHEMA  # the version it was read as (it is written as the current one)

    def flag_poor(self, names, why: str | None = None) -> CalibrationResult:
        """The result with the estimates `names` flagged poor, and `why` among the warnings."""
        estimates = {name: replace(e, quality="poor") if name in names else e for name, e in self.estimates.items()}
        flagged = replace(self, estimates=estimates)
        return flagged if why is None else flagged.with_warning(why)

    def with_warning(self, text: str, first: bool = False) -> CalibrationResult:
        return replace(self, warnings=(text, *self.warnings) if first else (*self.warnings, text))

    def rotation_matrix(self, name: str = "nav_to_imu") -> np.ndarray | None:
        """The 3 x 3 matrix of ROTATIONS[name] (v_IMU = M v) from the estimated angles; None when
        one of them is not estimated."""
        make, angles = ROTATIONS[name]
        if not all(a in self.estimates for a in angles):
            return None
        return make(*(self.estimates[a].value_si for a in angles))

    def covariance_matrix(self, si: bool = False) -> np.ndarray | None:
        """The estimates' covariance in the order of covariance["names"], in display units
        (entry i, j in units[i] x units[j]) or SI; None when the method gives none."""
        if self.covariance is None:
            return None
        matrix = np.array(self.covariance["matrix"], dtype=float)
        if not si:
            return matrix
        to_si = np.array([1 / DISPLAY_UNITS[unit][0] for unit in self.covariance["units"]])
        return matrix * np.outer(to_si, to_si)

    def rotation_record(self) -> dict | None:
        """Each rotation whose angles are all estimated: matrix, quaternion, and which of its
        angles are flagged poor (a poor yaw is kept, and said); None when there is none."""
        records = {}
        for name, (_, angles) in ROTATIONS.items():
            matrix = self.rotation_matrix(name)
            if matrix is not None:
                records[name] = {"matrix": matrix.tolist(), "quaternion": quaternion(matrix), "angles": list(angles),
                                 "poor": [a for a in angles if self.estimates[a].quality == "poor"]}
        return {"convention": ROTATION_CONVENTION, **records} if records else None

    def untrimmed(self, name: str) -> float | None:
        """A bias estimate less the trim offset in force on its axis (in the estimate's unit): the
        bias the output would carry without the trim, comparable across trims. None for an
        estimate that is no bias, or when the trim in force is not known (`sensor.trim`)."""
        triad, _, axis = name.partition("_bias_")
        trim, estimate = self.sensor.trim, self.estimates[name]
        if trim is None or not axis:
            return None
        return estimate.value - trim.of(triad)["xyz".index(axis)] * TRIM_TO_DISPLAY[estimate.unit]

    def to_dict(self) -> dict:
        estimates = {name: e.to_dict() | ({} if (u := self.untrimmed(name)) is None else {"untrimmed": u})
                     for name, e in self.estimates.items()}
        doc = {"schema": SCHEMA, "method": self.method, "software": self.software, "session_id": self.session_id,
               "site": self.site, "estimates": estimates,
               "rotation": self.rotation_record(), "covariance": self.covariance,
               "segments": list(self.segments), "warnings": list(self.warnings), "sensor": self.sensor.to_dict(),
               "stream": self.stream.to_dict()}
        optional = {name: getattr(self, name) for name in _OPTIONAL if getattr(self, name) is not None}
        return doc | optional | {name: asdict(optional[name]) for name in _RECORDS if name in optional}

    @classmethod
    def from_dict(cls, doc, where: str = "result") -> CalibrationResult:
        """A result document of this or an older version, checked against its schema
        (calibd.documents.ResultDoc); ResultError (one line naming the field) otherwise. What
        follows from the estimates (SI values, the rotation record) is made again, not read, and
        keys the schema does not know are left out."""
        document_version(doc, RESULT_SCHEMA, RESULT_VERSION, where, ResultError)
        estimates = doc.get("estimates")
        if not isinstance(estimates, dict) or not any(estimates.get(name) is not None for name in ESTIMATES):
            raise ResultError(f"{where}: the result has no estimates (value and unit each)")
        validate(doc, ResultDoc, where, ResultError)
        known = {"method", "site", "covariance", "software", "session_id", *_OPTIONAL} - set(_RECORDS)
        return cls(**{key: value for key, value in doc.items() if key in known},
                   **{name: record(**doc[name]) for name, record in _RECORDS.items() if doc.get(name) is not None},
                   sensor=SensorRecord.from_dict(doc.get("sensor") or {}),
                   stream=ResultStream.from_dict(doc.get("stream") or {}),
                   estimates={name: Estimate(e["value"], e.get("sigma"), e["unit"], e.get("quality"))
                              for name, e in estimates.items() if name in ESTIMATES and e is not None},
                   segments=tuple(doc.get("segments", ())), warnings=tuple(doc.get("warnings", ())),
                   schema=doc["schema"])



def quaternion(matrix: np.ndarray) -> list[float]:
    """The unit quaternion [w, x, y, z] (Hamilton, w >= 0) with q v q* = matrix v."""
    from scipy.spatial.transform import Rotation  # here: reading a result (`calibd status`) needs no scipy

    return Rotation.from_matrix(matrix).as_quat(canonical=True, scalar_first=True).tolist()


def covariance_record(names, covariance_si: np.ndarray) -> dict:
    """The estimates' covariance in display units: entry i, j in units[i] x units[j]."""
    factors = np.array([ESTIMATES[name][0] for name in names])
    return {"names": list(names), "units": [ESTIMATES[name][1] for name in names],
            "matrix": (np.asarray(covariance_si) * np.outer(factors, factors)).tolist()}


def software_record() -> dict:
    return {"name": SOFTWARE, "version": package_version()}


def site_record(site: Site) -> dict:
    """The site the estimates rest on: what was given and what follows from it (g0 and its
    1-sigma: 0 when given, a typical local anomaly for normal gravity; the Earth rate)."""
    return {"latitude_deg": site.latitude_deg, "height_m": site.height_m, "g0_m_s2": site.gravity,
            "g0_given": site.g0 is not None, "g0_sigma_m_s2": site.gravity_sigma,
            "earth_rate_deg_h": EARTH_RATE * 3600 / DEG, "earth_rate_rad_s": EARTH_RATE}


def make_result(method: str, site: Site, estimates: dict[str, tuple[float, float | None]], segments: list[dict],
                warnings: list[str], sensor: SensorRecord, covariance: np.ndarray | None = None,
                **extra) -> CalibrationResult:
    """The result of a method; `estimates` maps names of ESTIMATES to (value, sigma) in SI, and
    `covariance` (SI), when the method has one, is theirs in the same order."""
    unknown = set(estimates) - set(ESTIMATES)
    if unknown:
        raise ValueError(f"unknown estimate names: {sorted(unknown)}")
    return CalibrationResult(method, site_record(site),
                             {name: Estimate.from_si(name, *pair) for name, pair in estimates.items()},
                             tuple(segments), tuple(warnings), sensor,
                             covariance=None if covariance is None else covariance_record(estimates, covariance),
                             software=software_record(), **extra)


def result_json(result: CalibrationResult) -> bytes:
    """The result file's bytes: JSON, one key a line, no NaN (a result with one is a bug)."""
    return (json.dumps(result.to_dict(), indent=1, allow_nan=False, default=json_value) + "\n").encode()


def write_result(path, result: CalibrationResult) -> None:
    write_atomic(path, result_json(result))


def load_result(path) -> CalibrationResult:
    try:
        data = read_input(path, "result file", DOCUMENT_LIMIT_BYTES)
    except UsageError as exc:
        raise ResultError(str(exc)) from None
    return parse_result(data, path)


def parse_result(data: str | bytes, where) -> CalibrationResult:
    """A result file's text or bytes (read once, e.g. to hash them too) as a result; `where` names
    it. Decoded by msgspec (calibd.documents): deep nesting, NaN and numbers out of range are
    refused in one line like every other fault of the document."""
    return CalibrationResult.from_dict(decode_json(data, where, ResultDoc, ResultError), str(where))

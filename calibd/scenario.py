"""Simulation scenarios: a TOML file (or a ready-made one by name) -> a validated `Scenario`.

A scenario says what the sensor is and sends (datagram, rate, units), where it is (site), the
truth the estimators must find (biases at thermal equilibrium, attitude at the home position,
interface tilt), the noise and warm-up models, the motion (segments) and optional faults.
Errors name the file, the table and the key, and say what was expected: this parser is the
scenario's schema (its keys, kinds and RANGES); the text is decoded by `calibd.documents.parse_toml`.
The truth file written beside a simulated capture is read back by `truth_from_json`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

from stim300.cliutil import TEXT_LIMIT_BYTES, read_text
from stim300.errors import FormatError, UsageError
from stim300.protocol import ACC_RANGE_LSB_EXP, NORMAL_LAYOUTS, SAMPLE_RATES_HZ
from stim300.special import PartNumber, SerialNumber

from . import scenarios, spec
from .scenarios import READY_MADE
from .documents import (NOISE_MAX, SchemaError, Table, TruthDoc, decode_json, parse_toml, schema_version,
                        site_from_table, validate)
from .errors import CalibdError
from .frames import Site

GYRO_UNITS = ("rate", "average", "incremental")
ACC_UNITS = ("acceleration", "average", "incremental")
UP_AXES = ("+Z", "-Z", "+Y", "-Y", "+X", "-X")
MAX_RATE_DEG_S = spec.GYRO_RANGE_DEG_S
MAX_ACCEL_DEG_S2 = 10_000.0
# A segment's duration and a turn's angle are bounded so that the schedule's arithmetic stays
# finite and exact to a sample; how long a session may be is the simulator's rule (sim.MAX_SAMPLES)
MAX_SEGMENT_S = 1e9
MAX_TURN_DEG = 1e10
RANGES = {  # table: {key: (low, high, unit)} for every number of the truth, noise and warm-up; beyond,
    # the model means nothing, or exp() and the sensor's counts overflow
    "truth": {"yaw_deg": (-360.0, 360.0, "deg"), "pitch_deg": (-90.0, 90.0, "deg"), "roll_deg": (-180.0, 180.0, "deg"),
              "alpha_deg": (-10.0, 10.0, "deg"), "beta_deg": (-10.0, 10.0, "deg"),
              "gyro_bias_deg_h": (-36000.0, 36000.0, "deg/h"), "acc_bias_mg": (-1000.0, 1000.0, "mg"),
              "incl_bias_mg": (-1000.0, 1000.0, "mg"),
              # a first-order model of the factory residuals: beyond, it means nothing
              **{f"{s}_scale_ppm": (-10_000.0, 10_000.0, "ppm") for s in ("gyro", "acc", "incl")},
              **{f"{s}_misalignment_mrad": (-50.0, 50.0, "mrad") for s in ("gyro", "acc", "incl")}},
    "noise": {key: (0.0, 10.0 if key == "temperature_noise_c" else NOISE_MAX, "")
              for key in ("gyro_arw_deg_sqrt_h", "gyro_bias_instability_deg_h", "acc_vrw_m_s_sqrt_h",
                          "acc_bias_instability_mg", "incl_vrw_m_s_sqrt_h", "incl_bias_instability_mg",
                          "temperature_noise_c")},
    "warmup": {"power_on_s": (0.0, 1e9, "s"), "time_constant_s": (1.0, 1e7, "s"),
               "ambient_c": (-60.0, 100.0, "degC"), "settled_c": (-60.0, 100.0, "degC"),
               "ramp_c_per_h": (-60.0, 60.0, "degC/h"),
               "gyro_tempco_deg_h_per_c": (-100.0, 100.0, "deg/h/degC"),
               "acc_tempco_mg_per_c": (-100.0, 100.0, "mg/degC"), "incl_tempco_mg_per_c": (-100.0, 100.0, "mg/degC")},
}
MAX_GARBAGE_BYTES = 1_000_000
MAX_VIBRATION = 10_000.0  # times the sensor's white noise: beyond, the counts overflow


class ScenarioError(CalibdError):
    """A scenario that cannot be simulated; the message says where and why in one line."""


@dataclass(frozen=True)
class Sensor:
    datagram_id: int = 0xA7
    sample_rate_hz: int = 125
    crlf: bool = False
    acc_range_g: int = 10
    gyro_unit: str = "rate"
    acc_unit: str = "acceleration"
    part_number: str = "84167-4400003-321"
    revision: str = "K"
    serial_number: str = "N25582405002002"
    latency_us: int = 516


TRUTH_SCHEMA = "calibd.truth"  # the truth file beside a simulated capture (calibd.sim.truth_record)
TRUTH_VERSION = 2  # 2: the triads' factory residuals (scale factors, misalignment) in the truth
TRUTH_FORMER_NAMES = ("stim300-calib/truth",)  # its name before calibd.truth: read as the same version


@dataclass(frozen=True)
class Truth:
    """Biases at thermal equilibrium; attitude of the IMU at the home position (platform angle 0)."""

    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    alpha_deg: float = 0.0
    beta_deg: float = 0.0
    gyro_bias_deg_h: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc_bias_mg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    incl_bias_mg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Factory residuals of each triad (`spec.triad_error`): the sensor outputs (I + E) times the
    # input in housing axes, E from scale-factor errors (ppm, X Y Z) and the off-diagonal
    # elements (mrad, in the order of spec.OFF_DIAGONAL: xy xz yx yz zx zy). The angles
    # above describe the housing.
    gyro_scale_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc_scale_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    incl_scale_ppm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro_misalignment_mrad: tuple[float, ...] = (0.0,) * 6
    acc_misalignment_mrad: tuple[float, ...] = (0.0,) * 6
    incl_misalignment_mrad: tuple[float, ...] = (0.0,) * 6

    def triad_error(self, sensor: str):
        """E of one triad ("gyro", "acc", "incl"): its output is (I + E) times the housing-axes input."""
        return spec.triad_error(getattr(self, f"{sensor}_scale_ppm"), getattr(self, f"{sensor}_misalignment_mrad"))

    def estimates(self) -> dict[str, float]:
        """The truth under the result schema's estimate names and units (deg, deg/h, mg)."""
        out = {"pitch": self.pitch_deg, "roll": self.roll_deg, "yaw": self.yaw_deg, "alpha": self.alpha_deg,
               "beta": self.beta_deg}
        for name, values in (("gyro_bias", self.gyro_bias_deg_h), ("acc_bias", self.acc_bias_mg),
                             ("incl_bias", self.incl_bias_mg)):
            out |= {f"{name}_{axis}": value for axis, value in zip("xyz", values)}
        return out


@dataclass(frozen=True)
class Noise(spec.NoiseFigures):
    """The simulated sensor's noise: its figures (`spec.NoiseFigures`, by default the
    datasheet's for a 10 g unit; the scenario parser takes the sensor's own range,
    `Noise.datasheet`), whether it is on, and the temperature sensor's. The inclinometers are
    made 35 % noisier along gravity (`spec.incl_noise_factor`)."""

    enabled: bool = True
    temperature_noise_c: float = 0.01


@dataclass(frozen=True)
class Warmup:
    """Temperature T(t) = settled + ramp t - (settled - ambient) exp(-(t + power_on_s) / time_constant_s).

    30 min makes 1 h 30 min three time constants (5% of the rise left), matching the thesis's
    warm-up of at least 1 h 30 min (section 5.1). Biases move with temperature by the
    coefficients, so data taken early gives visibly wrong biases. `ramp_c_per_h`: the room
    warming or cooling during the capture, which the sensor follows."""

    power_on_s: float = 5400.0  # time since power-on when the capture starts
    time_constant_s: float = 1800.0
    ambient_c: float = 22.0
    settled_c: float = 38.0
    ramp_c_per_h: float = 0.0
    gyro_tempco_deg_h_per_c: tuple[float, float, float] = (1.5, -2.0, 1.0)
    acc_tempco_mg_per_c: tuple[float, float, float] = (0.05, -0.04, 0.03)
    incl_tempco_mg_per_c: tuple[float, float, float] = (0.02, 0.03, -0.01)


@dataclass(frozen=True)
class Segment:
    """static, turn (about the platform axis; positive angle = counter-clockwise about Up), or
    position (bench: the IMU re-mounted with the named axis up, then static)."""

    kind: str
    duration_s: float = 0.0
    angle_deg: float = 0.0
    peak_rate_deg_s: float = 0.0
    accel_deg_s2: float = 0.0
    up: str = "+Z"
    ripple: float = 0.0  # turn: relative once-per-revolution rate ripple (0.01 = 1 %)
    # static, position: white noise added on every sensor, this multiple of its own white noise
    # (the noise figures' random walk at the sample rate): a vehicle standing with its engine on
    vibration: float = 0.0


@dataclass(frozen=True)
class Faults:
    drop: int = 0  # normal datagrams removed
    garbage_bursts: int = 0  # bursts of random bytes inserted between datagrams
    garbage_max_bytes: int = 100
    bit_flips: int = 0  # single-bit errors in random datagrams
    restart_at_s: float | None = None  # the sensor restarts here: power-up datagrams, counter from 0


@dataclass(frozen=True)
class Scenario:
    name: str
    seed: int
    sensor: Sensor
    site: Site
    truth: Truth
    noise: Noise
    warmup: Warmup
    segments: tuple[Segment, ...]
    faults: Faults = field(default_factory=Faults)


# ---------------------------------------------------------------- reading

def _datagram(text: str) -> int:
    try:
        value = int(text, 16)
    except ValueError:
        return -1
    return value


def _sensor(t: Table) -> Sensor:
    d = Sensor()
    ident = _datagram(t.get("datagram", f"0x{d.datagram_id:02X}", str, lambda s: _datagram(s) in NORMAL_LAYOUTS,
                            "a normal datagram id such as \"0xA7\""))
    layout = NORMAL_LAYOUTS[ident]
    if layout.clusters != ("gyro", "acc", "incl") and layout.clusters != ("gyro", "acc"):
        t.fail("datagram", f"0x{ident:02X} carries no accelerometers: nothing to calibrate with")
    sensor = Sensor(
        datagram_id=ident,
        sample_rate_hz=t.get("sample_rate_hz", d.sample_rate_hz, int, lambda r: r in SAMPLE_RATES_HZ,
                             f"one of {', '.join(map(str, SAMPLE_RATES_HZ))} Hz"),
        crlf=t.get("crlf", d.crlf, bool),
        acc_range_g=t.get("acc_range_g", d.acc_range_g, int, lambda r: r in ACC_RANGE_LSB_EXP,
                          f"one of {', '.join(map(str, ACC_RANGE_LSB_EXP))} g"),
        gyro_unit=t.get("gyro_unit", d.gyro_unit, str, lambda u: u in GYRO_UNITS, f"one of {', '.join(GYRO_UNITS)}"),
        acc_unit=t.get("acc_unit", d.acc_unit, str, lambda u: u in ACC_UNITS, f"one of {', '.join(ACC_UNITS)}"),
        part_number=t.get("part_number", d.part_number, str),
        revision=t.get("revision", d.revision, str, lambda r: len(r) == 1 and ord(r) <= 0xFF,
                       "one character U+0000..U+00FF"),
        serial_number=t.get("serial_number", d.serial_number, str),
        latency_us=t.get("latency_us", d.latency_us, int, lambda v: 0 <= v < 65536, "0 to 65535 us"),
    )
    t.finish()
    for key, special in (("part_number", lambda: PartNumber(sensor.part_number, sensor.revision)),
                         ("serial_number", lambda: SerialNumber(sensor.serial_number))):
        try:
            special()  # the identity datagrams' own rules (stim300.special), not a copy of them
        except FormatError as exc:
            t.fail(key, str(exc))
    return sensor


def _fields(cls, t: Table, defaults=None):
    """The table's keys as a `cls`, each missing one taken from `defaults` (default: cls())."""
    values = {}
    for name, default in vars(cls() if defaults is None else defaults).items():
        kind = tuple if isinstance(default, tuple) else type(default) if default is not None else float
        values[name] = t.get(name, default, kind)
    t.finish()
    return cls(**values)


def _segment(t: Table) -> Segment:
    kind = t.get("type", None, str, lambda k: k in ("static", "turn", "position"), "static, turn or position")
    if kind is None:
        t.fail("type", "missing (static, turn or position)")
    if kind == "turn":
        seg = Segment(kind, angle_deg=t.get("angle_deg", None, float, lambda a: 0 < abs(a) <= MAX_TURN_DEG,
                                            f"a non-zero angle within +-{MAX_TURN_DEG:g} deg"),
                      peak_rate_deg_s=t.get("peak_rate_deg_s", None, float, lambda r: 0 < r <= MAX_RATE_DEG_S,
                                            f"a rate in (0, {MAX_RATE_DEG_S:g}] deg/s (the gyros' range)"),
                      accel_deg_s2=t.get("accel_deg_s2", None, float, lambda a: 0 < a <= MAX_ACCEL_DEG_S2,
                                         f"an acceleration in (0, {MAX_ACCEL_DEG_S2:g}] deg/s^2"),
                      ripple=t.get("ripple", 0.0, float, lambda r: 0 <= r < 0.5, "a relative ripple in [0, 0.5)"))
        for key in ("angle_deg", "peak_rate_deg_s", "accel_deg_s2"):
            if getattr(seg, key) is None:
                t.fail(key, "missing for a turn")
    else:
        duration = t.get("duration_s", None, float, lambda d: 0 < d <= MAX_SEGMENT_S,
                         f"a duration in (0, {MAX_SEGMENT_S:g}] s")
        if duration is None:
            t.fail("duration_s", f"missing for a {kind} segment")
        up = t.get("up", "+Z", str, lambda u: u in UP_AXES, f"one of {', '.join(UP_AXES)}") if kind == "position" \
            else "+Z"
        vibration = t.get("vibration", 0.0, float, lambda v: 0 <= v <= MAX_VIBRATION,
                          f"a multiple of the sensor's white noise in [0, {MAX_VIBRATION:g}]")
        seg = Segment(kind, duration_s=duration, up=up, vibration=vibration)
    t.finish()
    return seg


def parse_scenario(data: dict, where: str) -> Scenario:
    """Build a Scenario from TOML data; `where` names the source in error messages."""
    top = Table(data, where, ScenarioError)

    def table(key):
        value = top.get(key, {}, dict)
        return Table(value, f"{where} [{key}]", ScenarioError)

    name = top.get("name", Path(where).stem, str)
    seed = top.get("seed", 0, int, lambda s: s >= 0, "a non-negative integer")
    segments_data = top.get("segments", None, list)
    if not segments_data:
        top.fail("segments", "missing: a scenario needs at least one [[segments]] entry")
    segments = tuple(_segment(Table(s if isinstance(s, dict) else {}, f"{where} [[segments]] #{i + 1}",
                                    ScenarioError)) for i, s in enumerate(segments_data))
    faults_t = table("faults")
    faults = Faults(drop=faults_t.get("drop", 0, int, lambda v: v >= 0, "a count >= 0"),
                    garbage_bursts=faults_t.get("garbage_bursts", 0, int, lambda v: v >= 0, "a count >= 0"),
                    garbage_max_bytes=faults_t.get("garbage_max_bytes", 100, int, lambda v: 0 < v <= MAX_GARBAGE_BYTES,
                                                   f"a size in [1, {MAX_GARBAGE_BYTES}] B"),
                    bit_flips=faults_t.get("bit_flips", 0, int, lambda v: v >= 0, "a count >= 0"),
                    restart_at_s=faults_t.get("restart_at_s", None, float, lambda t: 0 < t <= MAX_SEGMENT_S,
                                              f"a time in (0, {MAX_SEGMENT_S:g}] s"))
    faults_t.finish()
    sensor = _sensor(table("sensor"))
    scenario = Scenario(name=name, seed=seed, sensor=sensor, site=site_from_table(table("site")),
                        truth=_fields(Truth, table("truth")),
                        noise=_fields(Noise, table("noise"), Noise.datasheet(sensor.acc_range_g)),
                        warmup=_fields(Warmup, table("warmup")), segments=segments, faults=faults)
    top.finish()
    for table, ranges in RANGES.items():
        for key, (low, high, unit) in ranges.items():
            value = getattr(getattr(scenario, table), key)
            if not all(low <= v <= high for v in (value if isinstance(value, tuple) else (value,))):
                raise ScenarioError(f"{where} [{table}] {key}: {value!r} is not in [{low:g}, {high:g}]"
                                    + (f" {unit}" if unit else ""))
    return scenario


def load_scenario(source: str) -> Scenario:
    """A scenario from a TOML file path, or one of READY_MADE by name."""
    if source in READY_MADE:
        text = resources.files(scenarios).joinpath(f"{source}.toml").read_text()
        where = f"{source} (ready-made)"
    else:
        ready_made = f"ready-made ones: {', '.join(READY_MADE)}"
        if not Path(source).exists():
            raise ScenarioError(f"{source}: no such scenario file ({ready_made})")
        try:  # a directory or a device (/dev/zero) is not a scenario either, and said so
            text = read_text(source, "scenario file", TEXT_LIMIT_BYTES)
        except UsageError as exc:
            raise ScenarioError(f"{exc} ({ready_made})") from None
        where = source
    return parse_scenario(parse_toml(text, where, ScenarioError), where)


def truth_from_json(data: str | bytes, where) -> tuple[Truth, Truth]:
    """A truth file's truth (calibd.truth/1 or /2, or its former name), and the truth the data
    carry: the biases moved by temperature and by the session mean of their wander. A version 1
    truth has no factory residuals: they were none. ScenarioError (one line) for anything else."""
    doc = decode_json(data, where, TruthDoc, ScenarioError)
    try:
        schema_version(doc.get("schema") if isinstance(doc, dict) else None, TRUTH_SCHEMA, TRUTH_VERSION, str(where),
                       TRUTH_FORMER_NAMES)
    except SchemaError as exc:
        raise ScenarioError(str(exc)) from None
    record = validate(doc, TruthDoc, where, ScenarioError)
    truth = Truth(**{name: getattr(record.truth, name) if name.endswith("_deg") else tuple(getattr(record.truth, name))
                     for name in vars(Truth())})
    carried = replace(truth, **{name: tuple(during.session) for name, during in record.bias_during_capture.items()
                                if name in vars(truth)})
    return truth, carried

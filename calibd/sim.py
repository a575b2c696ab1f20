"""Scenario simulator: truth -> sensor samples -> the bytes a STIM300 would send.

Physics as docs/method.md (Rotation conventions):
R_NAV^IMU(t) = M · R_int^IMU · R3(chi(t)) · R_NAV^int, with chi the platform angle about the
interface Z axis (counter-clockwise positive) and M the bench re-mounting (identity unless a
`position` segment says otherwise);
gyro = (I + E_g)·(R(t)·Omega_E + M·R_int^IMU·[0, 0, chi']) + b_g + noise,
accelerometer and inclinometer = (I + E)·R(t)·[0, 0, g0] + b + noise, in the sensor's units (g
of 9.80665 m/s^2), with E each triad's factory residuals (scale factor and misalignment,
`Truth.triad_error`): R(t) and the truth's angles describe the housing. The inclinometers'
noise is larger along gravity (`spec.incl_noise_factor`). Rates are averages over each sample
interval, so they integrate exactly to the angle turned. Everything is vectorised over
samples; the bytes come from `stim300.codec`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.signal import lfilter

from stim300.atomic import atomic_file
from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.protocol import (COUNTER_MODULUS, INTERNAL_RATE_HZ, NORMAL_LAYOUTS, SAMPLE_RATES_HZ, AccUnit, Format,
                              GyroUnit, Status)
from stim300.special import BiasTrimOffset, Configuration, PartNumber, SerialNumber, encode_special

from . import spec
from .allan import FLICKER_TAUS_S, flicker_sigma
from .frames import EARTH_RATE, MOUNTS, STANDARD_GRAVITY, euler_321, int_to_imu, nav_to_imu, r3
from .scenario import TRUTH_SCHEMA, TRUTH_VERSION, Scenario, ScenarioError, Truth
from .units import DEG

MAX_SAMPLES = 10_000_000  # about 1.4 h at 2000 Hz, 22 h at 125 Hz: the simulator holds some 1 kB a sample
START_UP_S = 0.7  # gyro start-up period after power-on: status bit 6 set (DS §7.5.2.1)
TEMP_OFFSETS_C = {"gyro": 0.6, "acc": 0.0, "incl": 0.3}  # clusters sit at slightly different temperatures


# ---------------------------------------------------------------- motion

@dataclass(frozen=True)
class Phase:
    """One segment placed in time (s from the first sample); turns carry their profile."""

    kind: str
    start_s: float
    end_s: float
    up: str = "+Z"
    angle_deg: float = 0.0
    peak_rate_deg_s: float = 0.0
    accel_deg_s2: float = 0.0
    chi_start_deg: float = 0.0
    cruise_start_s: float | None = None
    cruise_end_s: float | None = None
    ripple: float = 0.0
    vibration: float = 0.0  # extra white noise, times the sensor's (scenario.Segment.vibration)

    @property
    def turned_deg(self) -> float:
        """The whole angle of a turn, ripple included (0 for statics)."""
        return 0.0 if self.kind != "turn" else np.sign(self.angle_deg) * _rippled(abs(self.angle_deg), self.ripple)


def _rippled(theta_deg, ripple: float):
    """Angle turned when the rate is the profile's times (1 + ripple sin(angle)): the profile's
    angle plus ripple (1 - cos(angle)), in closed form (d/dt of it is the rippled rate)."""
    return theta_deg + np.degrees(ripple * (1 - np.cos(np.radians(theta_deg))))


def schedule(scenario: Scenario) -> list[Phase]:
    """Segments laid end to end; a turn's duration follows from its trapezoidal rate profile.
    Every phase carries the mount of the last `position` segment (+Z up before any)."""
    phases, t, chi, mount = [], 0.0, 0.0, "+Z"
    for seg in scenario.segments:
        if seg.kind == "position":
            mount = seg.up  # the IMU stays mounted so until the next position segment
        if seg.kind == "turn":
            angle, rate, accel = abs(seg.angle_deg), seg.peak_rate_deg_s, seg.accel_deg_s2
            if angle < rate**2 / accel:  # never reaches the peak rate: triangular profile
                rate = np.sqrt(angle * accel)
            t_acc = rate / accel
            t_cruise = (angle - rate * t_acc) / rate
            end = t + 2 * t_acc + t_cruise
            phase = Phase("turn", t, end, up=mount, angle_deg=seg.angle_deg, peak_rate_deg_s=float(rate),
                          accel_deg_s2=accel, chi_start_deg=chi, cruise_start_s=t + t_acc,
                          cruise_end_s=t + t_acc + t_cruise, ripple=seg.ripple)
            phases.append(phase)
            chi += phase.turned_deg
        else:
            end = t + seg.duration_s
            phases.append(Phase(seg.kind, t, end, up=mount, chi_start_deg=chi, vibration=seg.vibration))
        t = end
    return phases


def platform_angle(phases: list[Phase], t: np.ndarray) -> np.ndarray:
    """chi(t) in degrees (exact trapezoidal profile, with its ripple), for any times t."""
    chi = np.full(t.shape, phases[-1].chi_start_deg + phases[-1].turned_deg)
    for p in reversed(phases):
        inside = (t >= p.start_s) & (t < p.end_s) if p is not phases[-1] else t >= p.start_s
        if p.kind != "turn":
            chi[inside] = p.chi_start_deg
            continue
        tau = np.clip(t[inside] - p.start_s, 0.0, p.end_s - p.start_s)
        a, w = p.accel_deg_s2, p.peak_rate_deg_s
        t_acc, t_cruise = p.cruise_start_s - p.start_s, p.cruise_end_s - p.cruise_start_s
        rise = 0.5 * a * np.minimum(tau, t_acc) ** 2
        cruise = w * np.clip(tau - t_acc, 0.0, t_cruise)
        down = np.clip(tau - t_acc - t_cruise, 0.0, t_acc)
        fall = w * down - 0.5 * a * down**2
        chi[inside] = p.chi_start_deg + np.sign(p.angle_deg) * _rippled(rise + cruise + fall, p.ripple)
    return chi


# ---------------------------------------------------------------- noise

def gauss_markov(rng: np.random.Generator, n: int, dt: float, sigma: float, tau_s: float, axes: int = 3):
    """First-order Gauss-Markov process, stationary from the first sample."""
    a = np.exp(-dt / tau_s)
    white = rng.standard_normal((axes, n)) * sigma * np.sqrt(1 - a * a)
    start = rng.standard_normal((axes, 1)) * sigma
    out, _ = lfilter([1.0], [1.0, -a], white, axis=1, zi=a * start)
    return out.T


def sensor_noise(rng: np.random.Generator, n: int, rate_hz: float, density: float, instability: float):
    """White noise of `density` (unit·sqrt(s)) as seen by averages over 1/rate, plus flicker-like
    bias instability (minimum of the Allan deviation), for 3 axes: (total, coloured part)."""
    dt = 1.0 / rate_hz
    white = rng.standard_normal((n, 3)) * density * np.sqrt(rate_hz)
    coloured = np.zeros((n, 3))
    sigma = flicker_sigma(density, instability) if instability > 0 else 0.0
    if sigma:
        for corr in FLICKER_TAUS_S:
            coloured += gauss_markov(rng, n, dt, sigma, corr)
    return white + coloured, coloured


# ---------------------------------------------------------------- the session

@dataclass
class Simulation:
    """Samples (SAMPLE_DTYPE, physical units), their times, and the truth behind them."""

    scenario: Scenario
    samples: np.ndarray
    time_s: np.ndarray
    phases: list[Phase]
    temperature_c: np.ndarray
    exact: dict[str, np.ndarray]  # gyro (deg/s), acc, incl (g) in float64 before quantisation: for model tests
    wander: dict[str, np.ndarray]  # session mean of the bias-instability noise (deg/s, g): part of the bias now


def _attitude_truth(t: Truth) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    """(R_int^IMU, R_NAV^int, gammas in deg) from the home attitude and the interface tilt."""
    r_int_imu = int_to_imu(t.alpha_deg * DEG, t.beta_deg * DEG)
    r_nav_imu = nav_to_imu(t.yaw_deg * DEG, t.pitch_deg * DEG, t.roll_deg * DEG)
    r_nav_int = r_int_imu.T @ r_nav_imu
    g1, g2, g3 = euler_321(r_nav_int)
    return r_int_imu, r_nav_int, (float(g1) / DEG, float(g2) / DEG, float(g3) / DEG)


def remounted(truth: Truth, turn_error_rad: float = 0.0) -> Truth:
    """The same unit with its housing turned 180 deg (plus `turn_error_rad`, the fixture's own
    error) about its own Z axis on the interface: a second mounting (calibd.estimators.remount),
    the platform where it was. R_int^IMU becomes R3(pi) R1(alpha) R2(beta) = R1(-alpha) R2(-beta)
    R3(pi): alpha and beta change sign (exactly, with no turn error), the home attitude follows
    from R_NAV^IMU = R_int^IMU R_NAV^int. The factory residuals are the sensor's and stay."""
    r_int_imu, r_nav_int, _ = _attitude_truth(truth)
    turned = r3(np.pi + turn_error_rad) @ r_int_imu
    axis = turned[:, 2]  # the platform axis in the turned housing's axes
    yaw, pitch, roll = euler_321(turned @ r_nav_int)
    return replace(truth, yaw_deg=float(yaw) / DEG, pitch_deg=float(pitch) / DEG, roll_deg=float(roll) / DEG,
                   alpha_deg=float(np.arctan2(axis[1], axis[2])) / DEG, beta_deg=float(-np.arcsin(axis[0])) / DEG)


def simulated_samples(scenario: Scenario, phases: list[Phase]) -> int:
    """Samples the scenario's schedule needs; ScenarioError past MAX_SAMPLES (a day-long turn at
    2000 Hz would ask for hundreds of GiB) or when the faults drop every sample."""
    rate = scenario.sensor.sample_rate_hz
    duration_s = phases[-1].end_s
    if not duration_s * rate <= MAX_SAMPLES:
        hours = MAX_SAMPLES / rate / 3600
        raise ScenarioError(f"{duration_s:.6g} s at {rate} Hz is more than the simulator's "
                            f"{MAX_SAMPLES:,} samples ({hours:.1f} h at {rate} Hz): shorten the segments")
    n = int(round(duration_s * rate))
    if scenario.faults.drop >= n:
        raise ScenarioError(f"[faults] drop: {scenario.faults.drop} is not fewer than the "
                            f"{n} samples simulated")
    return n


def simulate(scenario: Scenario) -> Simulation:
    sensor, site, truth = scenario.sensor, scenario.site, scenario.truth
    rate = sensor.sample_rate_hz
    dt = 1.0 / rate
    phases = schedule(scenario)
    n = simulated_samples(scenario, phases)
    rng = np.random.default_rng(scenario.seed)
    t_end = np.arange(1, n + 1) * dt  # sample k averages over [k dt, (k + 1) dt) and is sent at its end
    t_mid = t_end - dt / 2

    chi_edges = platform_angle(phases, np.arange(n + 1) * dt) * DEG
    chi_rate = np.diff(chi_edges) / dt  # average rate over each interval: integrates exactly
    chi_mid = platform_angle(phases, t_mid) * DEG
    phase_index = np.searchsorted([p.end_s for p in phases], t_mid, side="right").clip(0, len(phases) - 1)
    mounts = np.stack([MOUNTS[p.up] for p in phases])[phase_index]

    r_int_imu, r_nav_int, _ = _attitude_truth(truth)
    body = mounts @ r_int_imu  # (n, 3, 3)
    r_nav_imu = body @ r3(chi_mid) @ r_nav_int
    omega = r_nav_imu @ site.earth_rate_nav + body[:, :, 2] * chi_rate[:, None]  # rad/s
    force = r_nav_imu @ site.gravity_nav / STANDARD_GRAVITY  # g

    w = scenario.warmup
    since_power_on = t_mid + w.power_on_s
    temperature = w.settled_c + w.ramp_c_per_h * t_mid / 3600 \
        - (w.settled_c - w.ambient_c) * np.exp(-since_power_on / w.time_constant_s)
    excess = (temperature - w.settled_c)[:, None]
    sensed = {name: np.eye(3) + truth.triad_error(name) for name in ("gyro", "acc", "incl")}  # factory residuals
    gyro = omega @ sensed["gyro"].T / DEG \
        + (np.asarray(truth.gyro_bias_deg_h) + excess * w.gyro_tempco_deg_h_per_c) / 3600
    acc = force @ sensed["acc"].T + (np.asarray(truth.acc_bias_mg) + excess * w.acc_tempco_mg_per_c) / 1000
    incl = force @ sensed["incl"].T + (np.asarray(truth.incl_bias_mg) + excess * w.incl_tempco_mg_per_c) / 1000

    noise = scenario.noise
    wander = {"gyro": np.zeros(3), "acc": np.zeros(3), "incl": np.zeros(3)}  # coloured noise, session mean
    if noise.enabled:
        mg = STANDARD_GRAVITY / 1000
        vibration = np.array([p.vibration for p in phases])[phase_index]
        shaker = np.random.default_rng(scenario.seed + 2) if vibration.any() else None  # others' draws unchanged
        for name, values, density, instability in (
                ("gyro", gyro, noise.gyro_arw_deg_sqrt_h * 60 / 3600, noise.gyro_bias_instability_deg_h / 3600),
                ("acc", acc, noise.acc_vrw_m_s_sqrt_h / 60 / STANDARD_GRAVITY,
                 noise.acc_bias_instability_mg * mg / STANDARD_GRAVITY),
                ("incl", incl, noise.incl_vrw_m_s_sqrt_h / 60 / STANDARD_GRAVITY,
                 noise.incl_bias_instability_mg * mg / STANDARD_GRAVITY)):
            total, coloured = sensor_noise(rng, n, rate, density, instability)
            if name == "incl":  # noisier along gravity (spec.INCL_NOISE_AT_1G)
                factor = spec.incl_noise_factor(force)
                total, coloured = total * factor, coloured * factor
            values += total
            wander[name] = coloured.mean(axis=0)
            if shaker is not None:
                values += shaker.standard_normal((n, 3)) * (density * np.sqrt(rate) * vibration)[:, None]

    lsb = sensor_format(scenario).scales()

    def counts(values, block):  # round to the sensor's counts in float64, before float32 storage
        return np.rint(values / lsb[block]) * lsb[block]

    samples = np.zeros(n, SAMPLE_DTYPE)
    samples["t_host"] = np.nan
    samples["datagram_id"] = sensor.datagram_id
    samples["gyro"] = counts(gyro * (dt if sensor.gyro_unit == "incremental" else 1.0), "gyro")
    samples["acc"] = counts(acc * (dt * STANDARD_GRAVITY if sensor.acc_unit == "incremental" else 1.0), "acc")
    samples["incl"] = counts(incl, "incl")
    for cluster, offset in TEMP_OFFSETS_C.items():
        jitter = rng.standard_normal((n, 3)) * noise.temperature_noise_c if noise.enabled else 0.0
        samples["temp_" + cluster] = counts((temperature + offset)[:, None] + jitter, "temp")
    starting = np.where(since_power_on < START_UP_S, Status.START_UP, 0)
    for cluster in ("gyro", "acc", "incl"):
        samples["status_" + cluster] = starting
    samples["aux"] = np.nan
    samples["counter"] = counter_values(n, rate)
    samples["latency_us"] = sensor.latency_us
    return Simulation(scenario, samples, t_end, phases, temperature, {"gyro": gyro, "acc": acc, "incl": incl},
                      wander)


def counter_values(n: int, rate_hz: int) -> np.ndarray:
    """The datagram counter of n datagrams from power-up: it counts the internal samples, so it
    steps by INTERNAL_RATE_HZ / rate_hz (a periodic external trigger's too) and wraps at
    COUNTER_MODULUS."""
    return np.arange(n) * (INTERNAL_RATE_HZ // rate_hz) % COUNTER_MODULUS


def external_trigger(scenario: Scenario) -> bool:
    """A rate no configuration code has (200 Hz) is simulated as a periodic external trigger at
    that rate: the counter steps by 2000 / rate, the configuration says "external trigger"."""
    return scenario.sensor.sample_rate_hz not in SAMPLE_RATES_HZ


def sensor_format(scenario: Scenario) -> Format:
    s = scenario.sensor
    return Format(datagram_id=s.datagram_id, crlf=s.crlf,
                  sample_rate_hz=None if external_trigger(scenario) else s.sample_rate_hz,
                  gyro_unit={"rate": GyroUnit.RATE, "average": GyroUnit.AVERAGE_RATE,
                             "incremental": GyroUnit.INCREMENTAL_ANGLE}[s.gyro_unit],
                  acc_unit={"acceleration": AccUnit.ACCELERATION, "average": AccUnit.AVERAGE_ACCELERATION,
                            "incremental": AccUnit.INCREMENTAL_VELOCITY}[s.acc_unit],
                  acc_range_g=s.acc_range_g)


def configuration(scenario: Scenario) -> Configuration:
    """The configuration datagram that describes what the simulated sensor sends."""
    s = scenario.sensor
    fmt = sensor_format(scenario)
    layout = NORMAL_LAYOUTS[s.datagram_id]
    return Configuration.build(sample_rate_hz=fmt.sample_rate_hz, acc_range_g=s.acc_range_g, revision=s.revision,
                               crlf=s.crlf, acc_included="acc" in layout.clusters,
                               incl_included="incl" in layout.clusters, temp_included=bool(layout.temperatures),
                               aux_in_datagram=layout.aux is not None, has_pps_input=layout.aux != "aux",
                               gyro_unit=fmt.gyro_unit, acc_unit=fmt.acc_unit)


def power_up_datagrams(scenario: Scenario, trim: BiasTrimOffset | None = None) -> bytes:
    """The sensor's start-up sequence: part number, serial number, configuration and, with `trim`
    (the offsets in force), the Bias Trim Offset datagram its configuration then says it sends."""
    s = scenario.sensor
    told = configuration(scenario) if trim is None else replace(configuration(scenario), bto_at_startup=True)
    return (encode_special(PartNumber(s.part_number, s.revision), s.crlf)
            + encode_special(SerialNumber(s.serial_number), s.crlf)
            + encode_special(told, s.crlf)
            + (b"" if trim is None else encode_special(trim, s.crlf, s.acc_range_g)))


def capture_bytes(sim: Simulation) -> tuple[bytes, dict]:
    """The byte stream (power-up datagrams, then normal datagrams, with the scenario's faults)
    and a record of the faults applied."""
    scenario = sim.scenario
    fmt = sensor_format(scenario)
    samples = sim.samples.copy()
    faults = scenario.faults
    rng = np.random.default_rng(scenario.seed + 1)
    restart = None
    if faults.restart_at_s is not None and faults.restart_at_s < sim.time_s[-1]:
        restart = int(np.searchsorted(sim.time_s, faults.restart_at_s))
        after = np.arange(len(samples) - restart)
        samples["counter"][restart:] = counter_values(len(after), scenario.sensor.sample_rate_hz)
        up = after * (1.0 / scenario.sensor.sample_rate_hz) < START_UP_S
        for cluster in ("gyro", "acc", "incl"):
            samples["status_" + cluster][restart:][up] = Status.START_UP
    frames = encode_samples(samples, scenario.sensor.datagram_id, fmt, scenario.sensor.crlf)
    n, length = frames.shape
    flipped = rng.choice(n, size=min(faults.bit_flips, n), replace=False)
    for row in flipped:
        frames[row, rng.integers(length)] ^= np.uint8(1 << rng.integers(8))
    dropped = np.sort(rng.choice(n, size=min(faults.drop, n), replace=False))
    bursts = sorted(rng.choice(np.arange(1, n), size=min(faults.garbage_bursts, n - 1), replace=False).tolist())
    cuts = sorted({0, n, *bursts, *([restart] if restart else [])})
    keep = np.ones(n, bool)
    keep[dropped] = False
    chunks = [power_up_datagrams(scenario)]
    garbage_bytes = 0
    for a, b in zip(cuts, cuts[1:]):
        if a == restart:
            chunks.append(power_up_datagrams(scenario))
        if a in bursts:
            size = int(rng.integers(1, faults.garbage_max_bytes + 1))
            chunks.append(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
            garbage_bytes += size
        chunks.append(frames[a:b][keep[a:b]].tobytes())
    record = {"dropped_samples": dropped.tolist(), "bit_flipped_samples": sorted(flipped.tolist()),
              "garbage_bursts_before_samples": bursts, "garbage_bytes": garbage_bytes,
              "restart_at_sample": restart}
    return b"".join(chunks), record


def _bias_drift(sim: Simulation) -> dict:
    """Biases the data actually carry: warm-up moves them (first sample, last sample, mean), and
    bias instability adds a slow wander whose session mean no estimator can tell from the bias
    (`session` = mean + that wander: the bias a calibration of this capture should find)."""
    scenario, temperature = sim.scenario, sim.temperature_c
    w, t = scenario.warmup, scenario.truth
    out = {}
    for name, key, settled, tempco, unit in (
            ("gyro_bias_deg_h", "gyro", t.gyro_bias_deg_h, w.gyro_tempco_deg_h_per_c, 3600.0),
            ("acc_bias_mg", "acc", t.acc_bias_mg, w.acc_tempco_mg_per_c, 1000.0),
            ("incl_bias_mg", "incl", t.incl_bias_mg, w.incl_tempco_mg_per_c, 1000.0)):
        excess = np.array([temperature[0], temperature[-1], temperature.mean()]) - w.settled_c
        values = np.asarray(settled) + excess[:, None] * np.asarray(tempco)
        wander = sim.wander[key] * unit
        out[name] = {"first": values[0].tolist(), "last": values[1].tolist(), "mean": values[2].tolist(),
                     "wander_mean": wander.tolist(), "session": (values[2] + wander).tolist()}
    return out


def _phase_record(phase: Phase) -> dict:
    """A phase as the truth file lists it; `vibration` only where there is some, so the truth of
    a scenario without vibration reads as before the option existed."""
    record = asdict(phase)
    if not phase.vibration:
        del record["vibration"]
    return record


def truth_record(sim: Simulation, faults: dict) -> dict:
    """Every parameter of the truth, for the truth file beside a capture."""
    scenario = sim.scenario
    _, _, gammas = _attitude_truth(scenario.truth)
    site = scenario.site
    lat = np.radians(site.latitude_deg)
    earth = EARTH_RATE / DEG * 3600 * np.array([np.cos(lat), np.sin(lat)])  # deg/h, horizontal and vertical
    mid_s = sim.time_s - 0.5 / scenario.sensor.sample_rate_hz
    return {
        "schema": f"{TRUTH_SCHEMA}/{TRUTH_VERSION}",
        "scenario": scenario.name,
        "seed": scenario.seed,
        "units": {"angles": "deg", "gyro_bias": "deg/h", "acc_bias": "mg", "incl_bias": "mg", "time": "s",
                  "g0": "m/s^2", "rates": "deg/s"},
        "sensor": asdict(scenario.sensor) | {"datagram_id": f"0x{scenario.sensor.datagram_id:02X}"},
        "site": {"latitude_deg": site.latitude_deg, "height_m": site.height_m, "g0": site.gravity,
                 "g0_given": site.g0 is not None, "earth_rate_horizontal_deg_h": float(earth[0]),
                 "earth_rate_vertical_deg_h": float(earth[1])},
        "truth": asdict(scenario.truth) | {"gamma1_deg": gammas[0], "gamma2_deg": gammas[1], "gamma3_deg": gammas[2]},
        "bias_during_capture": _bias_drift(sim),
        "noise": asdict(scenario.noise),
        "warmup": asdict(scenario.warmup),
        "samples": len(sim.samples),
        "duration_s": float(sim.time_s[-1]),
        "schedule": [_phase_record(p) | {"first_sample": int(np.searchsorted(mid_s, p.start_s)),
                                         "end_sample": int(np.searchsorted(mid_s, p.end_s))}
                     for p in sim.phases],
        "faults": faults,
    }


def write_capture(scenario: Scenario, path) -> dict:
    """Simulate, write CAPTURE and CAPTURE.truth.json (each renamed into place when complete)."""
    sim = simulate(scenario)
    data, faults = capture_bytes(sim)
    record = truth_record(sim, faults)
    try:
        truth = json.dumps(record, indent=1, allow_nan=False) + "\n"  # strict JSON: no NaN or Infinity
    except ValueError:
        raise ScenarioError("the truth is not finite (a value out of range): "
                            "nothing written") from None
    # the truth is written first and renamed last, once the capture (the write that can fill a
    # disk) is in place: a failed write leaves neither file
    with atomic_file(f"{path}.truth.json") as truth_file, atomic_file(path) as capture_file:
        truth_file.write(truth.encode())
        capture_file.write(data)
    return record

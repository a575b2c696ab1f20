"""Noise of a session's static data: the Allan deviation (calibd.allan) with confidence
intervals, and the noise figures read off it; the `calibd.noise/1` file.

`characterise` gives every channel's Allan deviation from the statics of a session, pooled (the
squared second differences of every static are summed and divided by their total count, so each
static's offset cancels), with 68 % intervals from the chi-square distribution, and reads off:
- random walk N: the -1/2 line fitted where that slope dominates, read at 1 s;
- bias instability B: the minimum of the deviation (the manufacturer's definition, which the
  simulator uses; IEEE 952's flicker coefficient would be B / 0.664);
- rate random walk K: the +1/2 line fitted where the curve rises again, read at 3 s (IEEE 952),
  or None when the data does not reach a rising part.
`kalibr_yaml` writes the same figures in SI per sqrt(Hz) as Kalibr's imu.yaml takes them.
docs/noise.md has the details and the reasons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .allan import WHITE_RATE, RANDOM_WALK_RATE, confidence_interval, noise_alpha, pooled_allan_deviation
from .detect import Segment
from .errors import CalibdError
from .segments import session_segments
from .session import Session
from .units import M_S2_TO_MG, RAD_S_TO_DEG_H, SQRT_S_PER_SQRT_H

NOISE_SCHEMA, NOISE_VERSION = "calibd.noise", 1  # the noise file's schema name and newest version
SCHEMA = f"{NOISE_SCHEMA}/{NOISE_VERSION}"
DETECTION_CONFIDENCE = 0.9  # a rise past the minimum counts when these intervals do not overlap (docs/noise.md)
MIN_STATIC_S = 30.0  # taus to 7.5 s: the random walk is read at 1 s inside the data, not extrapolated
RANDOM_WALK_TAU_S, RATE_RANDOM_WALK_TAU_S = 1.0, 3.0  # where IEEE 952 reads the -1/2 and +1/2 lines

CHANNELS = tuple(f"{sensor}_{axis}" for sensor in ("gyro", "acc", "incl") for axis in "xyz")


class NoiseError(CalibdError):
    """The data cannot give an Allan deviation (no static long enough); one line."""


# ---------------------------------------------------------------- reading the curve

@dataclass(frozen=True)
class Reading:
    """One value read off an Allan curve, with its interval, unit and the tau it is read at."""

    value: float
    low: float
    high: float
    unit: str
    tau_s: float

    def as_dict(self) -> dict:
        return {"value": self.value, "low": self.low, "high": self.high, "unit": self.unit, "tau_s": self.tau_s}


@dataclass(frozen=True)
class ChannelNoise:
    """One channel's Allan deviation (in adev_unit) with its 68 % interval, the figures read off
    it, and the static data it comes from (static_s seconds in `segments` statics)."""

    name: str
    adev_unit: str
    taus_s: np.ndarray
    adev: np.ndarray
    adev_low: np.ndarray
    adev_high: np.ndarray
    random_walk: Reading
    bias_instability: Reading
    rate_random_walk: Reading | None
    static_s: float = 0.0
    segments: int = 0

    def as_dict(self) -> dict:
        return {"adev_unit": self.adev_unit, "taus_s": self.taus_s.tolist(), "adev": self.adev.tolist(),
                "adev_low": self.adev_low.tolist(), "adev_high": self.adev_high.tolist(),
                "random_walk": self.random_walk.as_dict(), "bias_instability": self.bias_instability.as_dict(),
                "rate_random_walk": None if self.rate_random_walk is None else self.rate_random_walk.as_dict()}


@dataclass(frozen=True)
class _Units:
    """Display units of a sensor: the deviation's, per SI unit; the random walk's, per deviation
    at 1 s; the rate random walk's (per deviation at 3 s: SQRT_S_PER_SQRT_H)."""

    adev: str
    per_si: float
    random_walk: str
    random_walk_per_adev: float
    rate_random_walk: str


UNITS = {"gyro": _Units("deg/h", RAD_S_TO_DEG_H, "deg/sqrt(h)", 1 / SQRT_S_PER_SQRT_H, "deg/h/sqrt(h)"),
         "acc": _Units("mg", M_S2_TO_MG, "m/s/sqrt(h)", SQRT_S_PER_SQRT_H / M_S2_TO_MG, "mg/sqrt(h)"),
         "incl": _Units("mg", M_S2_TO_MG, "m/s/sqrt(h)", SQRT_S_PER_SQRT_H / M_S2_TO_MG, "mg/sqrt(h)")}


def _longest_run(mask: np.ndarray) -> np.ndarray | None:
    """Indices of the longest run of True, or None."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if not len(starts):
        return None
    k = int(np.argmax(stops - starts))
    return np.arange(starts[k], stops[k])


def _line_reading(taus, values, rel_low, rel_high, edf, run, slope, tau_s, scale, unit) -> Reading:
    """The line of log-log `slope` fitted to `values` at the points `run` (weights: their edf),
    read at tau_s. The points share their samples, so they are strongly correlated: the reading's
    relative interval is the weighted mean of theirs (in log), as for fully correlated points,
    not the narrower one independent points would give."""
    w = edf[run]
    value = np.exp(np.average(np.log(values[run]) - slope * np.log(taus[run]), weights=w)) * tau_s**slope
    low, high = (value * np.exp(np.average(np.log(rel[run]), weights=w)) for rel in (rel_low, rel_high))
    return Reading(float(value * scale), float(low * scale), float(high * scale), unit, tau_s)


def _read_channel(name, units: _Units, taus, adev, edf, static_s, segments) -> ChannelNoise:
    rel_low, rel_high = confidence_interval(1.0, edf)
    low, high = adev * rel_low, adev * rel_high
    values = np.maximum(adev, np.finfo(float).tiny)  # noise-free data: zeros, kept out of the logs
    alpha = noise_alpha(taus, adev)
    white = _longest_run(alpha == WHITE_RATE)
    if white is None:  # no -1/2 slope: the deviation at the tau nearest 1 s
        white = np.array([np.argmin(np.abs(np.log(taus / RANDOM_WALK_TAU_S)))])
    random_walk = _line_reading(taus, values, rel_low, rel_high, edf, white, -0.5, RANDOM_WALK_TAU_S,
                                units.random_walk_per_adev, units.random_walk)
    k = int(np.argmin(adev))
    bias = Reading(float(adev[k]), float(low[k]), float(high[k]), units.adev, float(taus[k]))
    # a rise: the +1/2 slope after the minimum, clear of it at DETECTION_CONFIDENCE. The line is
    # fitted with the random walk's share of the variance removed: near the minimum it would bias K up
    low_d, high_d = confidence_interval(adev, edf, DETECTION_CONFIDENCE)
    rising = _longest_run((np.arange(len(taus)) > k) & (alpha == RANDOM_WALK_RATE) & (low_d > high_d[k]))
    walk_at_1s = random_walk.value / units.random_walk_per_adev
    rate_walk_part = np.sqrt(np.maximum(adev**2 - walk_at_1s**2 / taus, np.finfo(float).tiny))
    rate_random_walk = None if rising is None else _line_reading(
        taus, rate_walk_part, rel_low, rel_high, edf, rising, 0.5, RATE_RANDOM_WALK_TAU_S, SQRT_S_PER_SQRT_H,
        units.rate_random_walk)
    return ChannelNoise(name, units.adev, taus, adev, low, high, random_walk, bias, rate_random_walk,
                        static_s, segments)


def _static_records(session: Session, statics: list[Segment]) -> list[tuple[int, int]]:
    """(start, stop) of the statics, split where samples were lost (the deviation needs a
    contiguous record); pieces shorter than a second add nothing."""
    pieces = []
    for s in statics:
        gaps = np.flatnonzero(np.diff(session.time_s[s.start:s.stop]) > 1.5 / session.rate_hz) + 1
        bounds = np.concatenate(([0], gaps, [s.stop - s.start])) + s.start
        pieces += [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= session.rate_hz]
    return pieces


def characterise(session: Session, segments: list[Segment] | None = None) -> dict[str, ChannelNoise]:
    """Allan deviation of the nine channels (gyro_x ... incl_z; six on a unit without
    inclinometers) from the session's statics, pooled, with the noise figures read off it.
    `segments`: the session's, when already found.
    Raises NoiseError when no static (without lost samples) lasts MIN_STATIC_S."""
    if segments is None:
        segments = session_segments(session)
    statics = [s for s in segments if s.kind == "static"]
    pieces = _static_records(session, statics)
    longest = max((b - a for a, b in pieces), default=0) / session.rate_hz
    if longest < MIN_STATIC_S:
        found = f"the longest of {len(statics)} lasts {longest:.1f} s" if statics else "none found"
        raise NoiseError(f"no static segment of at least {MIN_STATIC_S:g} s without lost samples ({found}): the "
                         f"Allan deviation reads the random walk at 1 s on taus up to a quarter of a static")
    sensors = {"gyro": session.gyro, "acc": session.acc, "incl": session.incl}
    present = [name for name, values in sensors.items() if values is not None]
    data = np.hstack([np.asarray(sensors[name], dtype=np.float64) * UNITS[name].per_si for name in present])
    names = [c for c in CHANNELS if c.split("_")[0] in present]
    taus, adev, edf = pooled_allan_deviation([data[a:b] for a, b in pieces], session.rate_hz)
    static_s = sum(b - a for a, b in pieces) / session.rate_hz
    return {name: _read_channel(name, UNITS[name.split("_")[0]], taus, adev[:, k], edf[:, k], static_s, len(statics))
            for k, name in enumerate(names)}


def noise_record(session: Session, channels: dict[str, ChannelNoise], capture: str) -> dict:
    """The `calibd.noise/1` document of a characterisation."""
    first = next(iter(channels.values()))
    return {"schema": SCHEMA, "capture": str(capture), "sample_rate_hz": session.rate_hz,
            "static_s": first.static_s, "segments": first.segments,
            "channels": {name: c.as_dict() for name, c in channels.items()}}


def _reading_text(r: Reading) -> str:
    return f"{r.value:.4g} [{r.low:.4g}, {r.high:.4g}] {r.unit}"


def noise_table(channels: dict[str, ChannelNoise]) -> str:
    """One line per channel: random walk, bias instability (at tau), rate random walk, each with
    its 68 % interval and unit."""
    first = next(iter(channels.values()))
    plural = "" if first.segments == 1 else "s"
    lines = [f"{first.static_s:.1f} s of static data in {first.segments} segment{plural}, Allan deviation to "
             f"tau {first.taus_s[-1]:.4g} s; [68 % interval]",
             f"{'channel':8s} {'random walk (at 1 s)':38s} {'bias instability (minimum, at tau)':46s} "
             f"rate random walk (at 3 s)"]
    falling = False
    for name, c in channels.items():
        b = c.bias_instability
        end = b.tau_s >= c.taus_s[-1]
        falling |= end
        bias = f"{_reading_text(b)} at {b.tau_s:.4g} s" + (" *" if end else "")
        rrw = (f"not reached in {c.static_s:.0f} s of data" if c.rate_random_walk is None
               else _reading_text(c.rate_random_walk))
        lines.append(f"{name:8s} {_reading_text(c.random_walk):38s} {bias:46s} {rrw}")
    if falling:
        lines.append("* the minimum is at the longest tau: the floor may lie lower (longer statics would show it)")
    return "\n".join(lines)


# ---------------------------------------------------------------- Kalibr's imu.yaml

KALIBR_SENSORS = {"gyroscope": "gyro", "accelerometer": "acc"}  # Kalibr's name: ours (no inclinometers)
KALIBR_SI_UNITS = {"gyro": ("rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)"), "acc": ("m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)")}


def _si_per_sqrt_s(channel: ChannelNoise) -> tuple[float, float, bool]:
    """A channel's white noise density N and rate random walk K in SI per sqrt(s), and whether K
    was read on a +1/2 slope. N is the deviation at 1 s of the -1/2 line (sigma^2 = N^2 / tau);
    K the deviation at 3 s of the +1/2 line (sigma^2 = K^2 tau / 3). Not reached: the largest K
    the curve allows, the +1/2 line through its minimum, K = B sqrt(3 / tau_B) (an upper bound)."""
    units = UNITS[channel.name.split("_")[0]]
    density = channel.random_walk.value / units.random_walk_per_adev / units.per_si
    if channel.rate_random_walk is not None:
        return density, channel.rate_random_walk.value / SQRT_S_PER_SQRT_H / units.per_si, True
    b = channel.bias_instability
    return density, b.value * np.sqrt(RATE_RANDOM_WALK_TAU_S / b.tau_s) / units.per_si, False


def kalibr_yaml(session: Session, channels: dict[str, ChannelNoise], rostopic: str = "/imu0") -> str:
    """Kalibr's imu.yaml: per sensor the largest of its three axes' figures (Kalibr takes one
    value per sensor; the largest keeps its filter from trusting any axis more than it should),
    update_rate the sensor's sample rate: the rate of the messages Kalibr's filter gets, which turns
    each density into a per-sample noise (the densities do not change with calibd's block
    averaging, the rate they are used at does). docs/noise.md gives the formulas."""
    first = next(iter(channels.values()))
    lines = [f"# Kalibr IMU noise model from {first.static_s:.1f} s of static data (calibd noise)"]
    rate_hz = float(session.sensor.sample_rate_hz or session.rate_hz)  # made without the sensor's rate: its own
    discrete_lines = [f"# The same figures discrete, per sample at {rate_hz:g} Hz (imu_utils-style tools, a "
                      "filter's per-step noise):"]
    for kalibr, ours in KALIBR_SENSORS.items():
        figures = [_si_per_sqrt_s(c) for name, c in channels.items() if name.split("_")[0] == ours]
        density_unit, walk_unit = KALIBR_SI_UNITS[ours]
        walk_how = ("rate random walk, Allan +1/2 slope at 3 s" if all(read for _, _, read in figures) else
                    "upper bound B*sqrt(3 s/tau_B) from the bias instability B at tau_B (no +1/2 slope reached)")
        density, walk = (float(max(column)) for column in list(zip(*figures))[:2])
        lines += [f"{kalibr}_noise_density: {density!r}  # {density_unit}, white noise: Allan deviation at 1 s, "
                  f"largest axis",
                  f"{kalibr}_random_walk: {walk!r}  # {walk_unit}, {walk_how}, largest axis"]
        sample, step = discrete(density, walk, rate_hz)
        unit = density_unit.split("/sqrt")[0]
        discrete_lines += [f"#   {kalibr}_noise_discrete: {sample!r}  # {unit}, one sample's white noise = density "
                           "* sqrt(update_rate)",
                           f"#   {kalibr}_random_walk_discrete: {step!r}  # {unit}, the bias's step per sample = "
                           "random walk / sqrt(update_rate)"]
    lines += [f"rostopic: {rostopic}", f"update_rate: {rate_hz!r}  # Hz, the sensor's sample rate", *discrete_lines]
    return "\n".join(lines) + "\n"


def discrete(density: float, random_walk: float, rate_hz: float) -> tuple[float, float]:
    """Continuous densities (per sqrt(Hz)) -> per-sample figures at `rate_hz`: one sample's white
    noise sigma_w sqrt(rate) and the bias's random-walk step sigma_b / sqrt(rate), in the
    signal's own unit (rad/s, m/s^2)."""
    return density * math.sqrt(rate_hz), random_walk / math.sqrt(rate_hz)

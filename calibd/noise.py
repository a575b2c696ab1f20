"""Noise of static data: overlapping Allan deviation (IEEE 952) with confidence intervals, the
noise figures read off it, and a white + flicker model of it.

Flicker (bias instability) is approximated by a sum of first-order Gauss-Markov processes with
decade-spaced time constants, as in the simulator; the same family gives the correlated-noise
covariance the estimators need.

`characterise` gives every channel's Allan deviation from the statics of a session, pooled (the
squared second differences of every static are summed and divided by their total count, so each
static's offset cancels), with 68 % intervals from the chi-square distribution, and reads off:
- random walk N: the -1/2 line fitted where that slope dominates, read at 1 s;
- bias instability B: the minimum of the deviation (the manufacturer's definition, which the
  simulator uses; IEEE 952's flicker coefficient would be B / 0.664);
- rate random walk K: the +1/2 line fitted where the curve rises again, read at 3 s (IEEE 952),
  or None when the data does not reach a rising part.
docs/noise.md has the details and the reasons.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import nnls
from scipy.special import chdtri

from .frames import STANDARD_GRAVITY

if TYPE_CHECKING:
    from .calibrate import Session
    from .detect import Segment

FLICKER_TAUS_S = (3.0, 30.0, 300.0, 3000.0, 30000.0)  # Gauss-Markov time constants approximating flicker
SCHEMA = "calibd.noise/1"
ONE_SIGMA = 0.6826894921370859  # two-sided confidence of +-1 sigma
DETECTION_CONFIDENCE = 0.9  # a rise past the minimum counts when these intervals do not overlap (docs/noise.md)
TAUS_PER_DECADE = 10
MIN_STATIC_S = 30.0  # taus to 7.5 s: the random walk is read at 1 s inside the data, not extrapolated
SLOPE_WINDOW_DECADES = 0.3  # local slopes are fitted over +-0.3 decades of tau (a factor of 2 each way)
RANDOM_WALK_TAU_S, RATE_RANDOM_WALK_TAU_S = 1.0, 3.0  # where IEEE 952 reads the -1/2 and +1/2 lines
SQRT_S_PER_SQRT_H = 60.0

# noise types by the exponent alpha of their rate power spectrum (f^alpha), as the edf tables name them
WHITE_RATE, FLICKER_RATE, RANDOM_WALK_RATE = 0, -1, -2
# Greenhall & Riley (2003), overlapping Allan variance (d = 2): (a0, a1) of 1/edf = (a0 - a1/r) / r
GREENHALL_A = {WHITE_RATE: (2 / 3, 1 / 3), FLICKER_RATE: (0.852, 0.375), RANDOM_WALK_RATE: (1.079, 0.368)}

RAD_S_TO_DEG_H = 180 / np.pi * 3600
M_S2_TO_MG = 1000 / STANDARD_GRAVITY
CHANNELS = tuple(f"{sensor}_{axis}" for sensor in ("gyro", "acc", "incl") for axis in "xyz")


class NoiseError(ValueError):
    """The data cannot give an Allan deviation (no static long enough); one line."""


# ---------------------------------------------------------------- Allan deviation

def allan_gm(tau: np.ndarray, sigma: float, corr: float) -> np.ndarray:
    """Allan variance of a Gauss-Markov process of stationary sigma, correlation time corr."""
    x = np.asarray(tau, float) / corr
    return sigma**2 / x**2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x))


FLOOR_TAUS_S = np.logspace(0, 4, 400)  # where the instability floor is read: 1 s to about 3 h


def flicker_sigma(white_density: float, instability: float) -> float:
    """Sigma of each flicker component so that the minimum of the Allan deviation of white noise
    (density `white_density`, unit·sqrt(s)) plus the components is `instability`, read over
    1 s to 3 h (the datasheet's figure comes from a 20-hour record; beyond the longest time
    constant the sum of Gauss-Markov processes would fall off, where flicker noise stays flat)."""
    taus = FLOOR_TAUS_S
    white = white_density**2 / taus

    def minimum(sigma):
        coloured = sum(allan_gm(taus, sigma, c) for c in FLICKER_TAUS_S)
        return np.sqrt(white + coloured).min()

    lo, hi = 0.0, 10 * instability
    if minimum(lo) >= instability:
        return 0.0  # white noise alone already reaches the instability floor in range
    for _ in range(60):  # bisection: the minimum grows with sigma
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if minimum(mid) < instability else (lo, mid)
    return 0.5 * (lo + hi)


def _second_difference_sums(x: np.ndarray, m: np.ndarray, rate_hz: float) -> np.ndarray:
    """Sum over the record of the squared second differences of its integral at lags m (samples),
    per channel."""
    angle = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)]) / rate_hz

    def sum_of_squares(k):
        d = angle[2 * k:] - angle[k:-k]  # in place from here: a third of the time of the plain expression
        d -= angle[k:-k]
        d += angle[:-2 * k]
        return np.einsum("i...,i...->...", d, d)

    return np.array([sum_of_squares(k) for k in m])


def _variance(sums: np.ndarray, counts: np.ndarray, m: np.ndarray, rate_hz: float) -> np.ndarray:
    """Allan variance from the sums of squared second differences and their counts, per tau."""
    tau = m / rate_hz
    return sums / (counts * 2 * tau**2).reshape((-1,) + (1,) * (sums.ndim - 1))


def allan_deviation(rate: np.ndarray, rate_hz: float, taus_s=None) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of a rate signal (samples along axis 0; extra axes are
    channels), at averaging times `taus_s` (default: 1, 2, 4 ... samples up to a ninth of the
    record). Returns (taus actually used, in s; deviations in the signal's unit)."""
    x = np.asarray(rate, dtype=np.float64)
    n = len(x)
    if taus_s is None:
        m = 2 ** np.arange(int(np.log2(max(n // 9, 1))) + 1)
    else:
        m = np.unique(np.round(np.asarray(taus_s, float) * rate_hz).astype(int))
    m = m[(m >= 1) & (m <= (n - 1) // 2)]
    return m / rate_hz, np.sqrt(_variance(_second_difference_sums(x, m, rate_hz), n + 1 - 2 * m, m, rate_hz))


def pooled_allan_deviation(records: list[np.ndarray], rate_hz: float,
                           taus_s=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of several records of the same noise (e.g. the statics of a
    session, samples x channels each): the squared second differences of every record are summed
    per tau and divided by their total count, so each record's offset cancels. A record takes part
    at the taus up to a quarter of its length (where the edf formula holds). Default taus:
    TAUS_PER_DECADE per decade from one sample to a quarter of the longest record.
    Returns (taus in s, deviations (taus x channels), equivalent degrees of freedom, same shape)."""
    records = [np.asarray(r, dtype=np.float64).reshape(len(r), -1) for r in records]
    longest = max(len(r) for r in records)
    if taus_s is None:
        decades = np.log10(max(longest // 4, 1))
        m = np.unique(np.round(np.logspace(0, decades, int(TAUS_PER_DECADE * decades) + 1)).astype(int))
    else:
        m = np.unique(np.round(np.asarray(taus_s, float) * rate_hz).astype(int))
    m = m[(m >= 1) & (4 * m <= longest)]
    sums = np.zeros((len(m), records[0].shape[1]))
    counts = np.zeros((len(records), len(m)))
    for k, record in enumerate(records):
        used = 4 * m <= len(record)
        centred = record - record.mean(axis=0)  # it cancels; a small integral keeps rounding small
        sums[used] += _second_difference_sums(centred, m[used], rate_hz).reshape(-1, sums.shape[1])
        counts[k, used] = len(record) + 1 - 2 * m[used]
    total = counts.sum(axis=0)
    adev = np.sqrt(_variance(sums, total, m, rate_hz))
    alpha = noise_alpha(m / rate_hz, adev)
    # records are independent: Satterthwaite's edf of the count-weighted mean of their variances
    share = (counts / total)[:, :, None]
    edf = allan_edf(alpha[None], np.maximum(counts, 1)[:, :, None], m[None, :, None])
    inverse = np.divide(share**2, edf, out=np.zeros_like(edf), where=share > 0).sum(axis=0)
    return m / rate_hz, adev, 1.0 / inverse


def local_slope(taus_s: np.ndarray, adev: np.ndarray) -> np.ndarray:
    """Log-log slope of the deviation at each tau (per channel), fitted over +-SLOPE_WINDOW_DECADES:
    -1 white angle noise, -1/2 white rate noise, 0 flicker, +1/2 rate random walk."""
    x = np.log10(taus_s)
    y = np.log10(np.maximum(adev, np.finfo(float).tiny)).reshape(len(x), -1)
    w = (np.abs(x[:, None] - x[None, :]) <= SLOPE_WINDOW_DECADES).astype(float)
    w /= w.sum(axis=1, keepdims=True)
    dx = x[None, :] - (w @ x)[:, None]  # deviation of each tau from each window's mean
    spread = (w * dx**2).sum(axis=1)
    slope = ((w * dx) @ y) / np.where(spread > 0, spread, 1.0)[:, None]
    return np.where(spread[:, None] > 0, slope, -0.5).reshape(adev.shape)


def noise_alpha(taus_s: np.ndarray, adev: np.ndarray) -> np.ndarray:
    """The noise type dominating at each tau, from the local slope rounded to the nearest type.
    Slopes steeper than -1/2 count as white rate noise too: white angle noise (slope -1) would
    have m times its edf, and a noisy slope at long taus taken for it would give intervals
    orders of magnitude too narrow; where it is real (quantisation at a few samples) the
    intervals are far below 1 % either way."""
    slope = local_slope(taus_s, adev)
    return np.select([slope < -0.25, slope < 0.25], [WHITE_RATE, FLICKER_RATE], RANDOM_WALK_RATE)


def allan_edf(alpha, count, m):
    """Equivalent degrees of freedom of an overlapping Allan variance made of `count` second
    differences at lag `m` samples, for the noise type `alpha` (WHITE_RATE, FLICKER_RATE or
    RANDOM_WALK_RATE): the closed form of Greenhall and Riley (2003, table 2) in r = count/m.
    It matches their full algorithm (allantools.edf_greenhall) to 1 % for m >= 40 and r >= 2;
    at a few samples it overestimates the edf (up to twice at m = 1, white noise), where the
    intervals are far below 1 %."""
    alpha, count, m = np.broadcast_arrays(np.asarray(alpha), np.asarray(count, float), np.asarray(m, float))
    a0 = np.select([alpha == a for a in GREENHALL_A], [c[0] for c in GREENHALL_A.values()])
    a1 = np.select([alpha == a for a in GREENHALL_A], [c[1] for c in GREENHALL_A.values()])
    r = count / m
    return r / (a0 - a1 / r)


def confidence_interval(adev: np.ndarray, edf: np.ndarray, confidence: float = ONE_SIGMA):
    """(low, high) of a deviation whose variance is chi-square distributed with `edf` degrees
    of freedom (scipy.special, not the slow-to-import scipy.stats)."""
    tail = (1 - confidence) / 2
    return adev * np.sqrt(edf / chdtri(edf, tail)), adev * np.sqrt(edf / chdtri(edf, 1 - tail))


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
    """Allan deviation of the nine channels (gyro_x ... incl_z) from the session's statics,
    pooled, with the noise figures read off it. `segments`: the session's, when already found.
    Raises NoiseError when no static (without lost samples) lasts MIN_STATIC_S."""
    if segments is None:
        from .calibrate import session_segments  # calibrate imports the estimators, which import this module

        segments = session_segments(session)
    statics = [s for s in segments if s.kind == "static"]
    pieces = _static_records(session, statics)
    longest = max((b - a for a, b in pieces), default=0) / session.rate_hz
    if longest < MIN_STATIC_S:
        found = f"the longest of {len(statics)} lasts {longest:.1f} s" if statics else "none found"
        raise NoiseError(f"no static segment of at least {MIN_STATIC_S:g} s without lost samples ({found}): the "
                         f"Allan deviation reads the random walk at 1 s on taus up to a quarter of a static")
    data = np.hstack([session.gyro * UNITS["gyro"].per_si, session.acc * UNITS["acc"].per_si,
                      session.incl * UNITS["incl"].per_si])
    taus, adev, edf = pooled_allan_deviation([data[a:b] for a, b in pieces], session.rate_hz)
    static_s = sum(b - a for a, b in pieces) / session.rate_hz
    return {name: _read_channel(name, UNITS[name.split("_")[0]], taus, adev[:, k], edf[:, k], static_s, len(statics))
            for k, name in enumerate(CHANNELS)}


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


# ---------------------------------------------------------------- noise model of the estimators

def fit_noise_model(residuals: np.ndarray, rate_hz: float, corr_taus=FLICKER_TAUS_S[:4]) -> tuple[float, float]:
    """(white variance per sample, variance of each flicker component) whose Allan deviation best
    matches that of `residuals` (static, samples x channels, pooled), in relative terms."""
    n = len(residuals)
    taus, adev = allan_deviation(residuals, rate_hz, 2.0 ** np.arange(int(np.log2(max(n // 4, 1))) + 1) / rate_hz)
    if not len(taus):
        return float(np.var(residuals)), 0.0
    target = (adev**2).mean(axis=1)
    rows = np.column_stack([1.0 / (taus * rate_hz), sum(allan_gm(taus, 1.0, c) for c in corr_taus)])
    coef, _ = nnls(rows / target[:, None], np.ones(len(taus)))
    return float(coef[0]), float(coef[1])


def correlate(columns: np.ndarray, rate_hz: float, corrs) -> list[np.ndarray]:
    """K @ columns for each unit Gauss-Markov correlation K_ij = exp(-|i - j| / (corr rate_hz)),
    one per time constant in `corrs`: convolutions with the two-sided exponential, by FFT
    (no N x N matrix; the columns are transformed once for all time constants)."""
    n = len(columns)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    lags = np.arange(size)
    lags = np.minimum(lags, size - lags)  # circular distance: wraps only beyond n, which is cut off
    spectrum = np.fft.rfft(columns, size, axis=0)
    out = []
    for corr in corrs:
        kernel = np.exp(-lags / (corr * rate_hz))
        kernel[n:size - n + 1] = 0.0
        out.append(np.fft.irfft(np.fft.rfft(kernel)[:, None] * spectrum, size, axis=0)[:n])
    return out

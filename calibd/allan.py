"""Allan-deviation maths: the overlapping Allan deviation (IEEE 952), pooled over records, with
equivalent degrees of freedom and chi-square intervals; flicker noise as a sum of first-order
Gauss-Markov processes with decade-spaced time constants (the simulator's model), and the
correlated-noise products the estimators need from the same family.

Pure functions of arrays: the simulator, the estimators and the noise characterisation
(calibd.noise) all build on it, and it imports nothing of theirs.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np


FLICKER_TAUS_S = (3.0, 30.0, 300.0, 3000.0, 30000.0)  # Gauss-Markov time constants approximating flicker
ONE_SIGMA = 0.6826894921370859  # two-sided confidence of +-1 sigma
TAUS_PER_DECADE = 10
SLOPE_WINDOW_DECADES = 0.3  # local slopes are fitted over +-0.3 decades of tau (a factor of 2 each way)

# noise types by the exponent alpha of their rate power spectrum (f^alpha), as the edf tables name them
WHITE_RATE, FLICKER_RATE, RANDOM_WALK_RATE = 0, -1, -2
# Greenhall & Riley (2003), overlapping Allan variance (d = 2): (a0, a1) of 1/edf = (a0 - a1/r) / r
GREENHALL_A = {WHITE_RATE: (2 / 3, 1 / 3), FLICKER_RATE: (0.852, 0.375), RANDOM_WALK_RATE: (1.079, 0.368)}


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
    from scipy.special import chdtri  # when used: start-up (docs/architecture.md)
    tail = (1 - confidence) / 2
    return adev * np.sqrt(edf / chdtri(edf, tail)), adev * np.sqrt(edf / chdtri(edf, 1 - tail))


# ---------------------------------------------------------------- noise model of the estimators

def fit_noise_model(residuals: np.ndarray, rate_hz: float, corr_taus=FLICKER_TAUS_S[:4]) -> tuple[float, float]:
    """(white variance per sample, variance of each flicker component) whose Allan deviation best
    matches that of `residuals` (static, samples x channels, pooled), in relative terms."""
    from scipy.optimize import nnls  # when used: start-up (docs/architecture.md)
    n = len(residuals)
    taus, adev = allan_deviation(residuals, rate_hz, 2.0 ** np.arange(int(np.log2(max(n // 4, 1))) + 1) / rate_hz)
    target = (adev**2).mean(axis=1)
    if not len(taus) or not np.all(target > 0):  # too short, or noise-free: nothing to fit a model to
        return float(np.var(residuals)), 0.0
    rows = np.column_stack([1.0 / (taus * rate_hz), sum(allan_gm(taus, 1.0, c) for c in corr_taus)])
    coef, _ = nnls(rows / target[:, None], np.ones(len(taus)))
    return float(coef[0]), float(coef[1])


def gauss_markov_forms(columns: np.ndarray, rate_hz: float, corrs) -> Iterator[np.ndarray]:
    """columns' K columns for each unit Gauss-Markov correlation K_ij = exp(-|i - j| / (corr
    rate_hz)), one per time constant in `corrs`, in turn: convolutions with the two-sided
    exponential, by FFT (no N x N matrix), one column at a time, so what is held is one column's
    padded transform, not every column's."""
    n = len(columns)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    lags = np.arange(size)
    lags = np.minimum(lags, size - lags)  # circular distance: wraps only beyond n, which is cut off
    for corr in corrs:
        kernel = np.exp(-lags / (corr * rate_hz))
        kernel[n:size - n + 1] = 0.0
        spectrum = np.fft.rfft(kernel)
        form = np.empty((columns.shape[1], columns.shape[1]))
        for j, column in enumerate(columns.T):
            form[:, j] = columns.T @ np.fft.irfft(spectrum * np.fft.rfft(column, size), size)[:n]
        yield form

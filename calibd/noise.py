"""Noise of static data: overlapping Allan deviation (IEEE 952) and a white + flicker model of it.

Flicker (bias instability) is approximated by a sum of first-order Gauss-Markov processes with
decade-spaced time constants, as in the simulator; the same family gives the correlated-noise
covariance the estimators need.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

FLICKER_TAUS_S = (3.0, 30.0, 300.0, 3000.0, 30000.0)  # Gauss-Markov time constants approximating flicker


def allan_gm(tau: np.ndarray, sigma: float, corr: float) -> np.ndarray:
    """Allan variance of a Gauss-Markov process of stationary sigma, correlation time corr."""
    x = np.asarray(tau, float) / corr
    return sigma**2 / x**2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x))


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
    angle = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)]) / rate_hz
    devs = []
    for k in m:
        tau = k / rate_hz
        d = angle[2 * k:] - 2 * angle[k:-k] + angle[:-2 * k]
        devs.append(np.sqrt(np.mean(d**2, axis=0) / (2 * tau**2)))
    return m / rate_hz, np.array(devs)


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

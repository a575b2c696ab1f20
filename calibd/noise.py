"""Noise levels of static data: overlapping Allan deviation (IEEE 952)."""

from __future__ import annotations

import numpy as np


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

"""Small synthetic captures for driver tests: exact values (integer counts times the LSB)."""

from __future__ import annotations

import numpy as np

from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, NORMAL_LAYOUTS, Format, Status


def exact_samples(n: int, fmt: Format, datagram_id: int, rng: np.random.Generator, counter0: int = 0) -> np.ndarray:
    """n samples whose every value the sensor can represent, counters stepping at the sample rate."""
    layout = NORMAL_LAYOUTS[datagram_id]
    scales = fmt.scales()
    s = np.zeros(n, SAMPLE_DTYPE)
    s["t_host"] = np.nan
    s["datagram_id"] = datagram_id
    for name in ("gyro", "acc", "incl"):
        if name in layout.clusters:
            s[name] = rng.integers(-(1 << 23), 1 << 23, (n, 3)) * scales[name]
            s["status_" + name] = rng.choice([0, 0, 0, Status.START_UP, Status.OVERLOAD | Status.X], n)
        else:
            s[name] = np.nan
    for name in ("gyro", "acc", "incl"):
        if name in layout.temperatures:
            s["temp_" + name] = rng.integers(-(1 << 15), 1 << 15, (n, 3)) * scales["temp"]
            s["status_temp_" + name] = rng.integers(0, 256, n)
        else:
            s["temp_" + name] = np.nan
    if layout.aux:
        lo, hi = (0, 1 << 24) if layout.aux == "pps" and fmt.pps_unsigned else (-(1 << 23), 1 << 23)
        s["aux"] = rng.integers(lo, hi, n) * scales[layout.aux]
        s["status_aux"] = rng.integers(0, 256, n)
    else:
        s["aux"] = np.nan
    step = INTERNAL_RATE_HZ // (fmt.sample_rate_hz or INTERNAL_RATE_HZ)
    s["counter"] = (counter0 + step * np.arange(n)) % COUNTER_MODULUS
    s["latency_us"] = rng.integers(0, 1 << 16, n)
    return s


def capture(n: int, datagram_id: int = 0xA7, crlf: bool = False, rate: int = 2000, seed: int = 0,
            **units) -> tuple[bytes, np.ndarray, Format]:
    """Bytes of n normal datagrams, the samples they carry, and their format."""
    fmt = Format(datagram_id=datagram_id, crlf=crlf, sample_rate_hz=rate, **units)
    samples = exact_samples(n, fmt, datagram_id, np.random.default_rng(seed))
    return encode_samples(samples, datagram_id, fmt, crlf).tobytes(), samples, fmt


def same_samples(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal in every field but the host timestamp; NaN equals NaN."""
    if len(a) != len(b):
        return False
    for name in SAMPLE_DTYPE.names:
        if name != "t_host" and not np.array_equal(a[name], b[name], equal_nan=a[name].dtype.kind == "f"):
            return False
    return True

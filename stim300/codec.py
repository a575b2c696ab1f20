"""Normal datagrams <-> samples, vectorised over many datagrams of one layout.

A sample is one row of SAMPLE_DTYPE in physical units (see `Format.units()`). Every STIM300
value is a 24-bit (or 16-bit) count times a power of two, so float32 holds it exactly; the AUX
voltage (5 V / 2^24 per count) is the exception and is kept in float64. Blocks a datagram does
not carry are NaN (values) and 0 (status).
"""

from __future__ import annotations

import numpy as np

from .crc import crc_columns
from .protocol import CLUSTERS, CR_LF, NORMAL_LAYOUTS, Format, Layout

SAMPLE_DTYPE = np.dtype([
    ("t_host", "f8"),  # host monotonic clock when the read that completed it returned (s); NaN offline
    ("datagram_id", "u1"),
    ("counter", "u1"),
    ("latency_us", "u2"),
    ("gyro", "f4", (3,)),
    ("acc", "f4", (3,)),
    ("incl", "f4", (3,)),
    ("status_gyro", "u1"),
    ("status_acc", "u1"),
    ("status_incl", "u1"),
    ("temp_gyro", "f4", (3,)),
    ("temp_acc", "f4", (3,)),
    ("temp_incl", "f4", (3,)),
    ("status_temp_gyro", "u1"),
    ("status_temp_acc", "u1"),
    ("status_temp_incl", "u1"),
    ("aux", "f8"),  # PPS (filtered, unitless, or time since PPS edge in us) or AUX volts
    ("status_aux", "u1"),
])


def _clear(out: np.ndarray, names) -> None:
    """Mark the blocks `names` (and their status bytes) absent: NaN values, status 0."""
    for name in names:
        out[name] = np.nan
        out["status_" + name] = 0


def _int24(frames: np.ndarray, offset: int, signed: bool = True) -> np.ndarray:
    """Big-endian 24-bit integers at `offset` of every row, as int32."""
    word = frames[:, offset].astype(np.int32) << 24
    word |= frames[:, offset + 1].astype(np.int32) << 16
    word |= frames[:, offset + 2].astype(np.int32) << 8
    if signed:
        return word >> 8
    return (word >> 8) & 0xFFFFFF


def _int16(frames: np.ndarray, offset: int) -> np.ndarray:
    word = frames[:, offset].astype(np.int16) << 8
    word |= frames[:, offset + 1]
    return word


def decode_frames(frames: np.ndarray, layout: Layout, fmt: Format, out: np.ndarray,
                  t_host: float = np.nan) -> None:
    """Decode normal datagrams (rows of `frames`, N x >= pre_crc uint8) into `out` (N samples).

    Every field of `out` is written, so it may come from np.empty. The CRC is not checked here:
    callers only pass frames they have verified.
    """
    scales = fmt.scales()
    off = layout.offsets
    out["t_host"] = t_host
    out["datagram_id"] = layout.datagram_id
    _clear(out, [c for c in CLUSTERS if c not in layout.clusters])
    _clear(out, ["temp_" + c for c in CLUSTERS if c not in layout.temperatures])
    if not layout.aux:
        _clear(out, ["aux"])
    for name in layout.clusters:
        block = out[name]
        for axis in range(3):
            np.multiply(_int24(frames, off[name] + 3 * axis), scales[name], out=block[:, axis], casting="unsafe")
        out["status_" + name] = frames[:, off["status_" + name]]
    for name in layout.temperatures:
        block = out["temp_" + name]
        for axis in range(3):
            np.multiply(_int16(frames, off["temp_" + name] + 2 * axis), scales["temp"], out=block[:, axis],
                        casting="unsafe")
        out["status_temp_" + name] = frames[:, off["status_temp_" + name]]
    if layout.aux:
        unsigned = layout.aux == "pps" and fmt.pps_unsigned
        out["aux"] = _int24(frames, off["aux"], signed=not unsigned) * scales[layout.aux]
        out["status_aux"] = frames[:, off["status_aux"]]
    out["counter"] = frames[:, off["counter"]]
    latency = frames[:, off["latency"]].astype(np.uint16) << 8
    latency |= frames[:, off["latency"] + 1]
    out["latency_us"] = latency


def _put_int(frames: np.ndarray, offset: int, counts: np.ndarray, nbytes: int) -> None:
    counts = counts.astype(np.int64)
    for k in range(nbytes):
        frames[:, offset + k] = (counts >> (8 * (nbytes - 1 - k))) & 0xFF


def _counts(values: np.ndarray, lsb: float, bits: int, signed: bool = True) -> np.ndarray:
    """Nearest counts, saturated like the sensor's output at the ends of the range."""
    counts = np.rint(np.nan_to_num(np.asarray(values, np.float64)) / lsb)
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    return np.clip(counts, lo, hi).astype(np.int64)


def encode_samples(samples: np.ndarray, datagram_id: int, fmt: Format, crlf: bool) -> np.ndarray:
    """Datagrams for `samples`, as an N x wire_length uint8 array (`.tobytes()` is the stream).

    Exact inverse of `decode_frames` for values the sensor can represent; others are rounded
    to the nearest count and saturated.
    """
    layout = NORMAL_LAYOUTS[datagram_id]
    scales = fmt.scales()
    off = layout.offsets
    n = len(samples)
    frames = np.zeros((n, layout.wire_length(crlf)), np.uint8)
    frames[:, 0] = datagram_id
    for name in layout.clusters:
        for axis in range(3):
            _put_int(frames, off[name] + 3 * axis, _counts(samples[name][:, axis], scales[name], 24), 3)
        frames[:, off["status_" + name]] = samples["status_" + name]
    for name in layout.temperatures:
        for axis in range(3):
            counts = _counts(samples["temp_" + name][:, axis], scales["temp"], 16)
            _put_int(frames, off["temp_" + name] + 2 * axis, counts, 2)
        frames[:, off["status_temp_" + name]] = samples["status_temp_" + name]
    if layout.aux:
        unsigned = layout.aux == "pps" and fmt.pps_unsigned
        _put_int(frames, off["aux"], _counts(samples["aux"], scales[layout.aux], 24, signed=not unsigned), 3)
        frames[:, off["status_aux"]] = samples["status_aux"]
    frames[:, off["counter"]] = samples["counter"]
    _put_int(frames, off["latency"], samples["latency_us"], 2)
    crc = crc_columns(frames, layout.pre_crc)
    _put_int(frames, layout.pre_crc, crc, 4)
    if crlf:
        frames[:, -2:] = np.frombuffer(CR_LF, np.uint8)
    return frames

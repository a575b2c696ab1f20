"""Normal datagrams <-> samples, vectorised over many datagrams of one layout.

A sample is one row of SAMPLE_DTYPE in physical units (see `Format.units()`). Every STIM300
value is a 24-bit (or 16-bit) count times a power of two, so float32 holds it exactly; the AUX
voltage (5 V / 2^24 per count) is the exception and is kept in float64. Blocks a datagram does
not carry are NaN (values) and 0 (status).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .crc import crc_columns
from .protocol import CLUSTERS, CR_LF, NORMAL_LAYOUTS, Format, Layout, Status

AXES = "xyz"

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


START_UP = int(Status.START_UP)  # the gyros' start-up period after power-on
FAULT_BITS = 0xFF & ~START_UP  # every status bit but START_UP: the sensor's own report of a bad measurement


def fault_bits(samples: np.ndarray) -> np.ndarray:
    """Per sample, the fault bits set in any of its gyro, accelerometer or inclinometer status
    bytes (0: a clean measurement)."""
    return (samples["status_gyro"] | samples["status_acc"] | samples["status_incl"]) & FAULT_BITS


def start_up_flags(samples: np.ndarray) -> np.ndarray:
    """Per sample, whether its gyro, accelerometer or inclinometer status has the start-up bit."""
    return ((samples["status_gyro"] | samples["status_acc"] | samples["status_incl"]) & START_UP) != 0


def start_up_rises(samples: np.ndarray, start_up_before: bool = True) -> np.ndarray:
    """Indices of the samples where the start-up status bit comes on after data without it: a
    sensor restart, seen even when its power-up datagrams were lost. `start_up_before`: whether
    the sample before these had the bit (True at a stream's start: nothing came before)."""
    up = start_up_flags(samples)
    return np.flatnonzero(up & ~np.concatenate(([start_up_before], up[:-1])))


def empty_columns(n: int) -> dict[str, np.ndarray]:
    """Column-major storage for n samples: SAMPLE_DTYPE's fields as separate arrays, every axis of
    a vector field contiguous (field[:, k] is a contiguous view). Bulk output to files wants this."""
    columns = {}
    for name in SAMPLE_DTYPE.names:
        dtype, shape = SAMPLE_DTYPE[name].base, SAMPLE_DTYPE[name].shape
        columns[name] = np.empty(shape + (n,), dtype).T
    return columns


def _clear(out, names) -> None:
    """Mark the blocks `names` (and their status bytes) absent: NaN values, status 0."""
    for name in names:
        out[name][...] = np.nan
        out["status_" + name][...] = 0


@lru_cache(maxsize=None)
def _record(layout: Layout, width: int) -> np.dtype:
    """Overlapping big-endian fields over one datagram row, so each value is a strided view.

    A 24-bit value at offset o is read as the 32-bit word at o - 1 (the byte before it is
    shifted out); o >= 1 always, as byte 0 is the id.
    """
    off = layout.offsets
    fields: dict[str, tuple[str, int]] = {}
    for name in layout.clusters:
        for k, axis in enumerate(AXES):
            fields[f"{name}_{axis}"] = (">i4", off[name] + 3 * k - 1)
        fields["status_" + name] = ("u1", off["status_" + name])
    for name in layout.temperatures:
        for k, axis in enumerate(AXES):
            fields[f"temp_{name}_{axis}"] = (">i2", off["temp_" + name] + 2 * k)
        fields["status_temp_" + name] = ("u1", off["status_temp_" + name])
    if layout.aux:
        fields["aux"] = (">i4", off["aux"] - 1)
        fields["status_aux"] = ("u1", off["status_aux"])
    fields["counter"] = ("u1", off["counter"])
    fields["latency_us"] = (">u2", off["latency"])
    return np.dtype({"names": list(fields), "formats": [f for f, _ in fields.values()],
                     "offsets": [o for _, o in fields.values()], "itemsize": width})


def _int24(word: np.ndarray, signed: bool = True) -> np.ndarray:
    """The low 24 bits of big-endian words, sign-extended or not, as native int32."""
    value = word.astype(np.int32)
    if signed:
        value <<= 8
        value >>= 8
    else:
        value &= 0xFFFFFF
    return value


def decode_frames(frames: np.ndarray, layout: Layout, fmt: Format, out: np.ndarray,
                  t_host: float | np.ndarray = np.nan) -> None:
    """Decode normal datagrams (rows of `frames`, N x width uint8 with width >= pre_crc) into
    `out`: N samples of SAMPLE_DTYPE, or a dict of columns like `empty_columns` gives;
    `t_host` is one read time for all, or one per datagram.

    Every field of `out` is written, so it may come from np.empty. The CRC is not checked here:
    callers only pass frames they have verified.
    """
    if not frames.flags.c_contiguous:
        frames = np.ascontiguousarray(frames)
    rec = frames.view(_record(layout, frames.shape[1]))[:, 0]
    scales = {name: np.broadcast_to(np.asarray(value, np.float32), 3) for name, value in fmt.scales().items()}
    out["t_host"][...] = t_host
    out["datagram_id"][...] = layout.datagram_id
    _clear(out, [c for c in CLUSTERS if c not in layout.clusters])
    _clear(out, ["temp_" + c for c in CLUSTERS if c not in layout.temperatures])
    for name in layout.clusters:
        block = out[name]
        for k, axis in enumerate(AXES):
            np.multiply(_int24(rec[f"{name}_{axis}"]), scales[name][k], out=block[:, k], dtype=np.float32,
                        casting="unsafe")
        out["status_" + name][...] = rec["status_" + name]
    for name in layout.temperatures:
        block = out["temp_" + name]
        for k, axis in enumerate(AXES):
            np.multiply(rec[f"temp_{name}_{axis}"], scales["temp"][k], out=block[:, k], dtype=np.float32,
                        casting="unsafe")
        out["status_temp_" + name][...] = rec["status_temp_" + name]
    if layout.aux:
        unsigned = layout.aux == "pps" and fmt.pps_unsigned
        out["aux"][...] = _int24(rec["aux"], signed=not unsigned) * fmt.scales()[layout.aux]
        out["status_aux"][...] = rec["status_aux"]
    else:
        _clear(out, ["aux"])
    out["counter"][...] = rec["counter"]
    out["latency_us"][...] = rec["latency_us"]


def _put_ints(frames: np.ndarray, offset: int, counts: np.ndarray, nbytes: int) -> None:
    """Big-endian `nbytes`-byte integers, counts[:, k] at offset + k * nbytes (counts: N x K)."""
    n, k = counts.shape
    octets = counts.astype(">i8").view(np.uint8).reshape(n, k, 8)[:, :, 8 - nbytes:]
    frames[:, offset:offset + k * nbytes] = octets.reshape(n, k * nbytes)


def _counts(values: np.ndarray, lsb: float, bits: int, signed: bool = True) -> np.ndarray:
    """Nearest counts, saturated like the sensor's output at the ends of the range (NaN: 0)."""
    counts = np.array(values, np.float64)
    counts /= lsb
    np.rint(counts, out=counts)
    counts[np.isnan(counts)] = 0
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    np.maximum(counts, lo, out=counts)
    return np.minimum(counts, hi, out=counts).astype(np.int64)


def subtract_counts(frames: np.ndarray, offset: int, counts: np.ndarray) -> None:
    """Take `counts` (one per axis) off the three 24-bit values at `offset` of every datagram row
    of `frames` (N x >= pre_crc + 4 uint8), saturating as the sensor does; `seal` then writes
    the CRC. A constant offset in counts is a bias taken out without decoding the datagram."""
    octets = frames[:, offset:offset + 9].reshape(len(frames), 3, 3).astype(np.int32)
    value = _int24((octets[:, :, 0] << 16) | (octets[:, :, 1] << 8) | octets[:, :, 2]) - counts
    np.maximum(value, -(1 << 23), out=value)  # not np.clip: its checks cost more than the work here
    np.minimum(value, (1 << 23) - 1, out=value)
    _put_ints(frames, offset, value, 3)


def seal(frames: np.ndarray, layout: Layout) -> None:
    """Each datagram row's CRC, computed again after its content changed."""
    _put_ints(frames, layout.pre_crc, crc_columns(frames, layout.pre_crc)[:, None], 4)


def encode_samples(samples: np.ndarray, datagram_id: int, fmt: Format, crlf: bool) -> np.ndarray:
    """Datagrams for `samples`, as an N x wire_length uint8 array (`.tobytes()` is the stream).

    Exact inverse of `decode_frames` for values the sensor can represent; others are rounded
    to the nearest count and saturated. One step per block, not per axis: a live feed encodes
    a few datagrams at a time, where numpy's cost per call dominates.
    """
    layout = NORMAL_LAYOUTS[datagram_id]
    scales = {name: np.broadcast_to(value, 3) for name, value in fmt.scales().items()}
    off = layout.offsets
    n = len(samples)
    frames = np.zeros((n, layout.wire_length(crlf)), np.uint8)
    frames[:, 0] = datagram_id
    for name in layout.clusters:
        _put_ints(frames, off[name], _counts(samples[name], scales[name], 24), 3)
        frames[:, off["status_" + name]] = samples["status_" + name]
    for name in layout.temperatures:
        _put_ints(frames, off["temp_" + name], _counts(samples["temp_" + name], scales["temp"], 16), 2)
        frames[:, off["status_temp_" + name]] = samples["status_temp_" + name]
    if layout.aux:
        unsigned = layout.aux == "pps" and fmt.pps_unsigned
        counts = _counts(samples["aux"][:, None], scales[layout.aux][0], 24, signed=not unsigned)
        _put_ints(frames, off["aux"], counts, 3)
        frames[:, off["status_aux"]] = samples["status_aux"]
    frames[:, off["counter"]] = samples["counter"]
    _put_ints(frames, off["latency"], samples["latency_us"][:, None], 2)
    seal(frames, layout)
    if crlf:
        frames[:, -2:] = np.frombuffer(CR_LF, np.uint8)
    return frames

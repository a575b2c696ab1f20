"""Normal datagrams <-> samples, vectorised over many datagrams of one layout.

A sample is one row of SAMPLE_DTYPE in physical units (see `Format.units()`). Every STIM300
value is a 24-bit (or 16-bit) count times a power of two, so float32 holds it exactly; the AUX
voltage (5 V / 2^24 per count) is the exception and is kept in float64. Blocks a datagram does
not carry are NaN (values) and 0 (status).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .crc import crc_columns
from .protocol import CR_LF, NORMAL_LAYOUTS, Format, Layout, Status

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


def join_samples(pieces: list[np.ndarray]) -> np.ndarray:
    """Rows of one structured dtype (SAMPLE_DTYPE) end to end, as a writable array. The live
    path joins a tick's reads: np.concatenate promotes a structured dtype piece by piece (about
    13 us a piece), joining their bytes costs about 1 us in all."""
    if len(pieces) == 1:
        return pieces[0]
    return np.frombuffer(bytearray(b"".join([piece.tobytes() for piece in pieces])), pieces[0].dtype)


VECTORS = ("gyro", "acc", "incl", "temp_gyro", "temp_acc", "temp_incl")  # SAMPLE_DTYPE's three-axis values
INTEGERS = ("status_gyro", "status_acc", "status_incl", "status_temp_gyro", "status_temp_acc", "status_temp_incl",
            "status_aux", "counter", "latency_us")  # SAMPLE_DTYPE's fields copied as sent
_ABSENT = (0, 1, 0)  # (offset, bytes, mask) of a value the datagram lacks: 0 (NaN once scaled)
CHUNK = 4096  # datagrams decode_frames decodes together: their words stay in the cache


_GROUPS = {"values": VECTORS[:3], "temperatures": VECTORS[3:], "aux": ("aux",), "statuses": INTEGERS[:3],
           "temperature_statuses": INTEGERS[3:6], **{name: (name,) for name in INTEGERS[6:]},
           "t_host": ("t_host",), "datagram_id": ("datagram_id",)}  # SAMPLE_DTYPE's fields by block


def _blocks() -> np.dtype:
    """SAMPLE_DTYPE seen as blocks: runs of fields of one type that lie end to end in a row
    (`_GROUPS`), each one field, so decoding writes a block of columns in one step, not a field
    at a time (a live feed's cost is per numpy call, not per value)."""
    names, formats, offsets = [], [], []
    for name, fields in _GROUPS.items():
        base, first = SAMPLE_DTYPE[fields[0]].base, SAMPLE_DTYPE.fields[fields[0]][1]
        count = sum(SAMPLE_DTYPE[f].itemsize for f in fields) // base.itemsize
        last = SAMPLE_DTYPE.fields[fields[-1]][1] + SAMPLE_DTYPE[fields[-1]].itemsize
        if any(SAMPLE_DTYPE[f].base != base for f in fields) or last != first + count * base.itemsize:
            raise TypeError(f"SAMPLE_DTYPE's {', '.join(fields)} are not one run of one type")
        names.append(name)
        formats.append(base if count == 1 else (base, count))
        offsets.append(first)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": SAMPLE_DTYPE.itemsize})


_BLOCKS = _blocks()
_PLAN_FIELDS = tuple(name for name in VECTORS for _ in range(3)) + ("aux", *INTEGERS)  # each plan column's field


def _plan_columns(fields: tuple[str, ...]) -> slice | int:
    """A block's columns of a plan: a run of them, or the one column of a single value."""
    at = [k for k, field in enumerate(_PLAN_FIELDS) if field in fields]
    return at[0] if len(at) == 1 else slice(at[0], at[-1] + 1)


_COLUMNS = {block: _plan_columns(fields) for block, fields in _GROUPS.items() if fields[0] in _PLAN_FIELDS}


class Columns(dict):
    """Column-major storage for samples: SAMPLE_DTYPE's fields by name, each a separate array,
    every axis of a vector field contiguous (field[:, k] is a contiguous view). Bulk output to
    files wants this. The fields are views of `blocks` (as `_BLOCKS` groups them), which decoding
    writes."""

    def __init__(self, blocks: dict[str, np.ndarray]):
        super().__init__()
        self.blocks = blocks
        for name, fields in _GROUPS.items():
            block = blocks[name]
            if block.ndim == 1:
                self[fields[0]] = block
                continue
            for k, field in enumerate(fields):  # three scalars, or three vectors of three
                self[field] = block[:, k] if SAMPLE_DTYPE[field].shape == () else block[:, 3 * k:3 * k + 3]
        for name in SAMPLE_DTYPE.names:  # in SAMPLE_DTYPE's order, as the rows have them
            self[name] = self.pop(name)

    @classmethod
    def empty(cls, n: int) -> Columns:
        """Storage for n samples, uninitialised."""
        return cls({name: np.empty(_BLOCKS[name].shape + (n,), _BLOCKS[name].base).T for name in _BLOCKS.names})

    def rows(self, start: int, stop: int) -> Columns:
        """Samples start to stop, a view."""
        return Columns({name: block[start:stop] for name, block in self.blocks.items()})


@dataclass(frozen=True)
class _Plan:
    """How to decode one layout in one format, worked out once: a live feed decodes a few
    datagrams at a time, where numpy's cost per call, not per value, is what counts.

    Every value of a datagram is one column: the big-endian 32-bit word that ends with its last
    byte, shifted left and back right (which drops the bytes before a 24-, 16- or 8-bit value
    and sign-extends it) and masked (keeping an unsigned value's bits; 0 for a block the
    datagram lacks). Columns: VECTORS' 18 values, the AUX or PPS value, INTEGERS' (`_PLAN_FIELDS`)."""

    starts: np.ndarray  # per column, the offset of its word in a datagram
    shifts: np.ndarray  # int32 per column
    masks: np.ndarray  # int32 per column
    scales: np.ndarray  # float32 per value of VECTORS; NaN for a block the datagram lacks
    aux_scale: float  # the AUX or PPS value's LSB (float64 products); NaN without one


@lru_cache(maxsize=None)
def _plan(layout: Layout, fmt: Format) -> _Plan:
    off, lsb = layout.offsets, fmt.scales()
    columns, scales = [], []  # (offset, bytes, mask) per column; LSB per value of VECTORS
    for name in VECTORS:
        cluster = name.removeprefix("temp_")
        present = cluster in (layout.temperatures if name.startswith("temp_") else layout.clusters)
        size = 2 if name.startswith("temp_") else 3
        columns += [(off[name] + size * k, size, -1) if present else _ABSENT for k in range(3)]
        scales += np.broadcast_to(lsb["temp" if size == 2 else name] if present else np.nan, 3).tolist()
    unsigned = layout.aux == "pps" and fmt.pps_unsigned
    columns.append((off["aux"], 3, 0xFFFFFF if unsigned else -1) if layout.aux else _ABSENT)
    for name in INTEGERS:
        size = 2 if name == "latency_us" else 1
        offset = off.get("latency" if name == "latency_us" else name)
        columns.append(_ABSENT if offset is None else (offset, size, (1 << 8 * size) - 1))
    return _Plan(starts=np.array([max(o + size - 4, 0) for o, size, _ in columns], np.intp),
                 shifts=np.array([[8 * (4 - size)] for _, size, _ in columns], np.int32),
                 masks=np.array([[mask] for _, _, mask in columns], np.int32),
                 scales=np.array(scales, np.float32)[:, None],
                 aux_scale=lsb[layout.aux] if layout.aux else np.nan)


def _words(data: np.ndarray, rows: int, row_bytes: int) -> np.ndarray:
    """The big-endian 32-bit word starting at each byte of `rows` rows of `row_bytes` bytes
    (C-contiguous uint8 `data`): a view, rows x (row_bytes - 3)."""
    return np.ndarray((rows, row_bytes - 3), ">i4", buffer=data, strides=(row_bytes, 1))


def decode_frames(frames: np.ndarray, layout: Layout, fmt: Format, out: np.ndarray,
                  t_host: float | np.ndarray = np.nan) -> None:
    """Decode normal datagrams (rows of `frames`, N x width uint8 with width >= pre_crc) into
    `out`: N samples of SAMPLE_DTYPE, or `Columns`; `t_host` is one read time for all, or one per
    datagram.

    Every field of `out` is written, so it may come from np.empty. The CRC is not checked here:
    callers only pass frames they have verified. Many datagrams are decoded CHUNK at a time, one
    strided copy per column each (`decode_at` gathers a few in one step)."""
    plan = _plan(layout, fmt)
    frames = np.ascontiguousarray(frames)
    words = _words(frames, *frames.shape)
    blocks = out.blocks if isinstance(out, Columns) else out.view(_BLOCKS)
    for start in range(0, len(frames), CHUNK):
        rows = slice(start, start + CHUNK)
        columns = np.empty((len(plan.starts), len(words[rows])), np.int32)
        for column, word in zip(columns, plan.starts.tolist()):
            column[...] = words[rows, word]
        part = {name: block[rows] for name, block in blocks.items()} if isinstance(out, Columns) else blocks[rows]
        _finish(columns, layout, plan, part, t_host[rows] if np.ndim(t_host) else t_host)


def decode_at(data: np.ndarray, offsets: np.ndarray, layout: Layout, fmt: Format, out: np.ndarray,
              t_host: float | np.ndarray = np.nan) -> None:
    """`decode_frames` of the datagrams starting at `offsets` of `data` (C-contiguous uint8) into
    SAMPLE_DTYPE rows, every value gathered in one step: a live feed's few datagrams, wherever
    the read put them."""
    plan = _plan(layout, fmt)
    words = _words(data, 1, len(data))[0]
    _finish(words[plan.starts[:, None] + offsets].astype(np.int32), layout, plan, out.view(_BLOCKS), t_host)


def _finish(columns: np.ndarray, layout: Layout, plan: _Plan, blocks, t_host) -> None:
    """Decode from each datagram's words (`columns`: one row per plan column, one column per
    datagram, native int32, changed in place) into `blocks` (rows of `_BLOCKS`, or its blocks by
    name), a block of fields at a time."""
    columns <<= plan.shifts
    columns >>= plan.shifts
    columns &= plan.masks
    for name, at in _COLUMNS.items():
        if name == "aux":
            np.multiply(columns[at], plan.aux_scale, out=blocks[name])
        elif _BLOCKS[name].base == np.float32:
            np.multiply(columns[at], plan.scales[at], out=blocks[name].T, dtype=np.float32, casting="unsafe")
        else:
            blocks[name][...] = columns[at].T
    blocks["t_host"][...] = t_host
    blocks["datagram_id"][...] = layout.datagram_id


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


def subtract_counts(frames: np.ndarray, offset: int, counts: np.ndarray, matrix: np.ndarray | None = None) -> None:
    """Take `counts` (one per axis) off the three 24-bit values at `offset` of every datagram row
    of `frames` (N x >= pre_crc + 4 uint8), then, with `matrix` (3 x 3, in counts), take them
    through it to the nearest count; saturating as the sensor does; `seal` then writes the CRC.
    A constant offset in counts is a bias taken out without decoding the datagram."""
    octets = frames[:, offset:offset + 9].reshape(len(frames), 3, 3).astype(np.int32)
    value = ((octets[:, :, 0] << 24) | (octets[:, :, 1] << 16) | (octets[:, :, 2] << 8)) >> 8  # sign-extended
    value -= counts
    if matrix is not None:
        value = np.rint(value @ matrix.T).astype(np.int32)
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

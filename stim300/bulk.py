"""Whole-capture decoding at numpy speed, with exactly the stream parser's results.

The stream parser's `Scanner` decides everything it would decide; this module only adds a fast
path: from an offset where a datagram of the current format starts, it checks a block of
consecutive datagrams at once (id byte, CRC by column tables, CR LF) and decodes the valid
prefix in one go. The first datagram that does not verify goes back to the scanner, which
re-synchronises byte by byte exactly as it does on a live stream.

`decode_capture` gives rows (SAMPLE_DTYPE), `decode_columns` one array per field: what writing
tables wants (no strided passes over whole records); `decode_blocks` hands the rows over block by
block, for captures larger than their samples should take in memory.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from numpy.lib.stride_tricks import as_strided

from .capture import Capture, StreamInfo, stream_info
from .codec import SAMPLE_DTYPE, decode_frames, empty_columns
from .crc import crc_columns
from .protocol import CR_LF, NORMAL_LAYOUTS, SPECIAL_IDS, Format
from .reads import read_times
from .stream import WAIT, Scanner

BLOCK = 65536  # datagrams checked and decoded together: keeps the columns in cache
FIRST_BLOCK = 64  # a block after a re-synchronisation starts small, in case the stream is noisy
_IS_ID = np.zeros(1 << 8, bool)  # per byte value: can a datagram start with it
_IS_ID[list(NORMAL_LAYOUTS) + list(SPECIAL_IDS)] = True
_SHORTEST = min(layout.wire_length(False) for layout in NORMAL_LAYOUTS.values())


class BulkDecoder:
    """Decode one capture held in memory (bytes, bytearray, mmap) into the storage `allocate(n)`
    gives: SAMPLE_DTYPE rows or `codec.empty_columns`; with `on_block`, into a scratch block
    handed to `on_block(samples, scanner, offset)` as each is decoded, so memory stays one block
    whatever the capture's size (`offset`: the bytes before it are done with)."""

    def __init__(self, data, fmt: Format | None, reads: np.ndarray | None, allocate, on_block=None):
        self._reads = reads
        self._raw = memoryview(data).cast("B")
        self._bytes = np.frombuffer(self._raw, np.uint8)
        self._found: list[tuple[int, int]] = []
        self.scanner = Scanner(fmt, lambda offset, ident: self._found.append((offset, ident)))
        self.scanner.stats.bytes_in = len(self._raw)
        most = len(self._raw) // _SHORTEST + 1  # untouched rows cost address space only
        self._allocate, self._on_block = allocate, on_block
        self._out = allocate(0 if on_block else most)
        self._n = 0

    def run(self) -> np.ndarray | dict[str, np.ndarray]:
        """All normal samples in stream order (scanner statistics in `self.scanner.stats`)."""
        pos, end = 0, len(self._raw)
        block = FIRST_BLOCK
        while pos < end:
            taken = self._fast_run(pos, block)
            if taken:
                pos = taken
                block = min(block * 4, BLOCK)
                continue
            pos = self._scalar_step(pos)
            block = FIRST_BLOCK
        return self._rows(0, self._n)

    def _rows(self, start: int, stop: int):
        if isinstance(self._out, dict):
            return {name: column[start:stop] for name, column in self._out.items()}
        return self._out[start:stop]

    def release(self) -> None:
        """Let go of the capture's buffer (an mmap can only close once nothing points into it)."""
        self._bytes = None
        self._raw.release()

    def _scalar_step(self, pos: int) -> int:
        """One scanner decision at `pos`, after jumping over bytes that cannot start a datagram."""
        candidates = np.flatnonzero(_IS_ID[self._bytes[pos:pos + 4096]])
        jump = int(candidates[0]) if len(candidates) else min(4096, len(self._raw) - pos)
        self.scanner.stats.skipped_bytes += jump
        pos += jump
        if pos >= len(self._raw):
            return pos
        nxt = self.scanner.step(self._raw, pos, final=True)
        assert nxt != WAIT  # final=True always decides
        for offset, ident in self._found:
            layout = NORMAL_LAYOUTS[ident]
            frames = self._bytes[offset:offset + layout.pre_crc][None, :]
            self._decode(frames, layout, offset, layout.wire_length(self.scanner.format.crlf is True))
        self._found.clear()
        return nxt

    def _fast_run(self, pos: int, block: int) -> int:
        """Accept consecutive datagrams of the current format from `pos`; return the new offset
        (0 when not even the first one verifies, or the format is not settled)."""
        fmt = self.scanner.format
        if fmt.datagram_id is None or fmt.crlf is None:
            return 0
        layout = NORMAL_LAYOUTS[fmt.datagram_id]
        length = layout.wire_length(fmt.crlf)
        start = pos
        while True:
            count = min(block, (len(self._raw) - pos) // length)
            if count <= 0:
                break
            frames = as_strided(self._bytes[pos:], shape=(count, length), strides=(length, 1), writeable=False)
            valid = self._verify(frames, layout, fmt.crlf)
            good = count if valid.all() else int(np.argmin(valid))
            if good:
                self.scanner.count_counters(frames[:good, layout.counter_offset])
                self._decode(frames[:good], layout, pos, length)
                pos += good * length
            if good < count:
                break
            block = min(block * 4, BLOCK)
        return pos if pos > start else 0

    @staticmethod
    def _verify(frames: np.ndarray, layout, crlf: bool) -> np.ndarray:
        pre = layout.pre_crc
        sent = frames[:, pre].astype(np.uint32) << 24
        sent |= frames[:, pre + 1].astype(np.uint32) << 16
        sent |= frames[:, pre + 2].astype(np.uint32) << 8
        sent |= frames[:, pre + 3]
        valid = crc_columns(frames, pre) == sent
        valid &= frames[:, 0] == layout.datagram_id
        if crlf:
            valid &= (frames[:, -2] == CR_LF[0]) & (frames[:, -1] == CR_LF[1])
        return valid

    def _decode(self, frames: np.ndarray, layout, start: int, length: int) -> None:
        """Decode datagrams laid `length` bytes apart from byte `start`; with a read log, stamp
        each with the host time of the read that completed it."""
        n = len(frames)
        if self._on_block is not None:
            if len(self._out) < n:
                self._out = self._allocate(n)
            self._n = 0
        t_host = np.nan if self._reads is None else read_times(self._reads, start + length * np.arange(1, n + 1))
        decode_frames(frames, layout, self.scanner.format, self._rows(self._n, self._n + n), t_host)
        self._n += n
        if self._on_block is not None:
            self._on_block(self._rows(0, n), self.scanner, start)


def decode_capture(data, fmt: Format | None = None, reads: np.ndarray | None = None) -> Capture:
    """A whole capture's samples (SAMPLE_DTYPE rows) and its StreamInfo. `fmt` describes a capture
    without a configuration datagram; `reads`, its read log (`stim300.reads`), gives each sample
    its `t_host`."""
    samples, info = _decode(data, fmt, reads, partial(np.empty, dtype=SAMPLE_DTYPE))
    return Capture(samples, info)


def decode_columns(data, fmt: Format | None = None, reads: np.ndarray | None = None) \
        -> tuple[dict[str, np.ndarray], StreamInfo]:
    """`decode_capture` as one array per SAMPLE_DTYPE field (like `codec.empty_columns`)."""
    return _decode(data, fmt, reads, empty_columns)


def decode_blocks(data, on_block, fmt: Format | None = None, reads: np.ndarray | None = None) -> StreamInfo:
    """Decode a capture of any size in one block's memory: `on_block(samples, scanner, offset)` gets
    each block of SAMPLE_DTYPE rows in stream order (a scratch buffer the next block overwrites:
    copy what is kept), the scanner as of that block (format, running statistics), and the byte
    offset before which the capture is done with (an mmap may let those pages go)."""
    decoder = BulkDecoder(data, fmt, reads, partial(np.empty, dtype=SAMPLE_DTYPE), on_block)
    try:
        decoder.run()
    finally:
        decoder.release()
    return stream_info(decoder.scanner)


def _decode(data, fmt, reads, allocate):
    decoder = BulkDecoder(data, fmt, reads, allocate)
    samples = decoder.run()
    decoder.release()
    return samples, stream_info(decoder.scanner)

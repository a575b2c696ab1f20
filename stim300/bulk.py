"""Whole-capture decoding at numpy speed, with exactly the stream parser's results.

The stream parser's `Scanner` decides everything it would decide; this module only adds a fast
path. Once the scanner has accepted `SYNC_RUN` datagrams back to back, the stream is taken to be
in step: from there a block of consecutive datagrams of the current format is checked at once
(id byte, CR LF, CRC by column tables) and its valid prefix decoded in one go. The first datagram
that does not verify goes back to the scanner, which re-synchronises exactly as it does on a live
stream; over bytes that cannot start a datagram it jumps with a vectorised search.

What the scanner accepts is decoded in batches, so garbage costs what it costs the stream parser
and the vectorised path only runs where a run of good datagrams pays for it.

`decode_capture` gives rows (SAMPLE_DTYPE), `decode_columns` one array per field: what writing
tables wants (no strided passes over whole records); `decode_blocks` hands the rows over block by
block, for captures larger than their samples should take in memory.
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.lib.stride_tricks import as_strided

from .capture import Capture, StreamInfo, stream_info
from .codec import SAMPLE_DTYPE, Columns, decode_frames
from .crc import crc_columns
from .protocol import CR_LF, NORMAL_LAYOUTS, SPECIAL_IDS, Format
from .reads import read_times
from .stream import FOLLOW_BLOCK, Accepted, Scanner, verified

BLOCK = 65536  # datagrams checked and decoded together: keeps the columns in cache
SYNC_RUN = 128  # datagrams the scanner accepts back to back before the vectorised path is tried: an
# attempt that fails at once costs about as much as 30-60 scanner decisions, so a run this long pays for it
SEARCH = 4096  # bytes searched at once for the next byte that can start a datagram
_IS_ID = np.zeros(1 << 8, bool)  # per byte value: can a datagram start with it
_IS_ID[list(NORMAL_LAYOUTS) + list(SPECIAL_IDS)] = True
_CAN_START = tuple(_IS_ID.tolist())  # the same for one byte at a time, at Python speed
_SHORTEST = min(layout.wire_length(False) for layout in NORMAL_LAYOUTS.values())


@dataclass
class Work:
    """What a decode cost, counted in steps rather than seconds, so that a test can bound the
    work per byte on any input and a decoder gone quadratic fails it on any machine."""

    steps: int = 0  # scanner decisions
    searched: int = 0  # bytes looked at for the next possible datagram start
    fast_runs: int = 0  # vectorised attempts
    checked: int = 0  # datagrams whose CRC the vectorised path computed
    followed: int = 0  # datagrams the scanner took back to back after one it accepted (`Scanner.follow`)


class BulkDecoder:
    """Decode one capture held in memory (bytes, bytearray, mmap) into the storage `allocate(n)`
    gives: SAMPLE_DTYPE rows or `codec.Columns`; with `on_block`, into a scratch block
    handed to `on_block(samples, scanner, offset)` as each is decoded, so memory stays one block
    whatever the capture's size (`offset`: the bytes before it are done with)."""

    def __init__(self, data, fmt: Format | None, reads: np.ndarray | None, allocate, on_block=None):
        self._reads = reads
        self._raw = memoryview(data).cast("B")
        self._bytes = np.frombuffer(self._raw, np.uint8)
        self._accepted = Accepted()  # by the scanner, not yet decoded
        self.scanner = Scanner(fmt, self._found_normal)
        self.scanner.stats.bytes_in = len(self._raw)
        self.work = Work()
        self._starts: list[int] = []  # offsets that can start a datagram, in the searched window
        self._next = 0  # index into _starts
        self._searched_to = 0  # end of the searched window
        most = len(self._raw) // _SHORTEST + 1  # untouched rows cost address space only
        self._allocate, self._on_block = allocate, on_block
        self._out = allocate(0 if on_block else most)
        self._n = 0

    def _found_normal(self, offset: int, ident: int) -> None:
        self._accepted.add((offset,), self.scanner.format)

    def run(self) -> np.ndarray | dict[str, np.ndarray]:
        """All normal samples in stream order (scanner statistics in `self.scanner.stats`)."""
        pos, end = 0, len(self._raw)
        while pos < end:
            pos = self._scan(pos)
            if pos < end:
                pos = self._fast_run(pos)
        self._flush()
        return self._rows(0, self._n)

    def _rows(self, start: int, stop: int):
        return self._out.rows(start, stop) if isinstance(self._out, Columns) else self._out[start:stop]

    def release(self) -> None:
        """Let go of the capture's buffer (an mmap can only close once nothing points into it)."""
        self._bytes = None
        self._raw.release()

    def _scan(self, pos: int) -> int:
        """Scanner decisions from `pos` until it has accepted SYNC_RUN normal datagrams back to back
        (return the offset after them) or the capture ends; after each datagram it accepts, those
        that follow it back to back are taken as the live parser takes them (`Scanner.follow`)."""
        raw, end, scanner, accepted, work = self._raw, len(self._raw), self.scanner, self._accepted, self.work
        run = 0
        while pos < end:
            if not _CAN_START[raw[pos]]:
                start = self._next_start(pos)
                scanner.stats.skipped_bytes += start - pos
                pos, run = start, 0
                if pos == self._searched_to:  # no start in the searched window: search on
                    continue
            before = len(accepted)
            pos = scanner.step(raw, pos, final=True)  # final=True always decides
            work.steps += 1
            if len(accepted) == before:
                run = 0
                continue
            run += 1
            followed = scanner.follow(raw, pos, SYNC_RUN - run)  # checked FOLLOW_BLOCK at a time
            if followed:
                accepted.add(followed, scanner.format)
                run, pos = run + len(followed), followed.stop
                work.followed += len(followed)
            if run >= SYNC_RUN:
                break
            if len(accepted) >= BLOCK:
                self._flush()
        return pos

    def _next_start(self, pos: int) -> int:
        """The first offset from `pos` whose byte can start a datagram (the end of the searched
        window when it has none); each byte is searched once."""
        if pos >= self._searched_to:
            stop = min(pos + SEARCH, len(self._raw))
            self._starts = (np.flatnonzero(_IS_ID[self._bytes[pos:stop]]) + pos).tolist()
            self._next, self._searched_to = 0, stop
            self.work.searched += stop - pos
        starts = self._starts
        self._next = k = bisect_left(starts, pos, self._next)
        return starts[k] if k < len(starts) else self._searched_to

    def _fast_run(self, pos: int) -> int:
        """Accept consecutive datagrams of the current format from `pos` in blocks growing from
        SYNC_RUN (a block wastes at most what was accepted before it, plus one SYNC_RUN); return the
        offset after the last one that verifies."""
        fmt = self.scanner.format
        layout = NORMAL_LAYOUTS[fmt.datagram_id]
        length = layout.wire_length(fmt.crlf)
        block = SYNC_RUN
        self.work.fast_runs += 1
        while True:
            count = min(block, (len(self._raw) - pos) // length)
            if count <= 0:
                break
            frames = as_strided(self._bytes[pos:], shape=(count, length), strides=(length, 1), writeable=False)
            good = self._verified(frames, layout, fmt.crlf)
            if good:
                self._flush()
                self.scanner.count_counters(frames[:good, layout.counter_offset])
                self._emit(frames[:good], layout, fmt, pos + length * np.arange(1, good + 1), pos,
                           self.scanner.stats.datagrams - good)
                pos += good * length
            if good < count:
                break
            block = min(block * 4, BLOCK)
        return pos

    def _verified(self, frames: np.ndarray, layout, crlf: bool) -> int:
        """How many leading frames are valid datagrams. Up to FOLLOW_BLOCK of them (a run's first
        block) are checked as `Scanner.follow` checks, in one gather; a larger block by columns,
        the CRC only up to the first wrong id or CR LF, so a block that runs into garbage costs
        little more than its good part."""
        if len(frames) <= FOLLOW_BLOCK:
            self.work.checked += len(frames)
            return verified(frames, layout, crlf)
        framed = frames[:, 0] == layout.datagram_id
        if crlf:
            framed &= (frames[:, -2] == CR_LF[0]) & (frames[:, -1] == CR_LF[1])
        count = len(frames) if framed.all() else int(np.argmin(framed))
        if not count:
            return 0
        self.work.checked += count
        frames, pre = frames[:count], layout.pre_crc
        sent = frames[:, pre].astype(np.uint32) << 24
        sent |= frames[:, pre + 1].astype(np.uint32) << 16
        sent |= frames[:, pre + 2].astype(np.uint32) << 8
        sent |= frames[:, pre + 3]
        valid = crc_columns(frames, pre) == sent
        return count if valid.all() else int(np.argmin(valid))

    def _flush(self) -> None:
        """Decode what the scanner accepted since the last flush, a run of one format at a time."""
        first = self.scanner.stats.datagrams - len(self._accepted)  # the stream number of the first
        for layout, fmt, offsets, start, _ in self._accepted.take():
            frames = self._bytes[offsets[:, None] + np.arange(layout.pre_crc)]
            self._emit(frames, layout, fmt, offsets + layout.wire_length(fmt.crlf), int(offsets[0]), first + start)

    def _emit(self, frames: np.ndarray, layout, fmt: Format, ends: np.ndarray, start: int, number: int) -> None:
        """Decode datagrams (rows of `frames`, the first starting at byte `start` with stream
        number `number`, each ending at `ends`) into the output; with a read log, stamp each with
        the host time of the read that completed it (`Scanner.decided`, as the live reader does)."""
        n = len(frames)
        if self._on_block is not None:
            if len(self._out) < n:
                self._out = self._allocate(n)
            self._n = 0
        self.scanner.forget(number)
        t_host = np.nan if self._reads is None else read_times(self._reads, self.scanner.decided(number, ends))
        decode_frames(frames, layout, fmt, self._rows(self._n, self._n + n), t_host)
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
    """`decode_capture` as one array per SAMPLE_DTYPE field (like `codec.Columns`)."""
    return _decode(data, fmt, reads, Columns.empty)


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

"""Incremental STIM300 parser: bytes in any chunking -> samples, with stream statistics.

There is no start-of-frame marker, so a frame is any known id byte followed by enough bytes
whose CRC (and CR LF when the format has it) verifies; after a failed candidate the scan
advances one byte. The same `Scanner` state machine drives the bulk decoder, which only adds a
vectorised fast path over runs of well-formed datagrams, so both give identical results.
"""

from __future__ import annotations

import collections
import math
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache

import numpy as np

from .codec import SAMPLE_DTYPE, START_UP, decode_at
from .crc import datagram_crc, position_tables
from .protocol import (BIAS_TRIM, CONFIGURATION, COUNTER_MODULUS, CR_LF, INTERNAL_RATE_HZ, NORMAL_LAYOUTS,
                       PART_NUMBER, SAMPLE_RATES_HZ, SERIAL_NUMBER, SPECIAL_IDS, Format, Layout)
from .reads import read_times
from .records import TrimRecord
from .special import decode_special

SPECIAL_HISTORY = 64  # special datagrams remembered (they are rare: power-up and on request)
MAX_WARNINGS = 16  # distinct stream warnings kept (each says what was refused or kept, and why)
STANDARD_STEPS = frozenset(INTERNAL_RATE_HZ // rate for rate in SAMPLE_RATES_HZ)  # counter steps of the fixed rates
ODD_STEPS_SHARE = 0.01  # counter steps off the usual step's multiples a fixed step tolerates (restarts, glitches)


@dataclass(frozen=True)
class StreamStats:
    """`Stats` at one moment, with the counter-derived figures worked out: what a result carries."""

    bytes_in: int
    datagrams: int
    crc_errors: int
    lost_samples: int
    skipped_bytes: int
    restarts: int
    restart_datagrams: tuple[int, ...]
    config_changes: int
    special_datagrams: int
    undecodable_specials: int
    counter_step: int | None
    external_trigger: bool
    inferred_missing: int
    mean_step: float | None


@dataclass
class Stats:
    """What the stream looked like. `lost_samples` derives from a histogram of counter steps."""

    bytes_in: int = 0
    datagrams: int = 0  # CRC-valid normal datagrams
    crc_errors: int = 0  # candidates of a known id and full length that failed, one per failed span
    skipped_bytes: int = 0  # bytes that belonged to no valid datagram
    restarts: int = 0  # power-up sequences seen after normal data
    restart_datagrams: list[int] = field(default_factory=list)  # per restart: normal datagrams before it,
    # i.e. the index of the restarted sensor's first sample in the decoded output (bulk and stream alike)
    config_changes: int = 0  # the normal format changed (new configuration or new datagram id)
    special_datagrams: int = 0
    undecodable_specials: int = 0  # CRC-valid special datagrams with codes the byte map lacks
    counter_steps: np.ndarray = field(default_factory=lambda: np.zeros(COUNTER_MODULUS, np.int64))
    configured_step: int | None = None  # from the sample rate when known
    triggered: bool = False  # the configuration says the sensor samples at an external trigger

    @property
    def counter_step(self) -> int | None:
        """Counter increment per datagram: INTERNAL_RATE_HZ / sample rate when configured, else the
        most common step when nearly every step is a whole multiple of it (a fixed rate, or a
        periodic trigger: 10 at 200 Hz); None with no steps yet or steps of no fixed size (an
        irregular external trigger)."""
        if self.configured_step:
            return self.configured_step
        counts = self.counter_steps.copy()
        counts[0] = 0  # a whole cycle (or a stuck counter) says nothing of the step
        total = int(counts.sum())
        if not total:
            return None
        step = int(np.argmax(counts))
        odd = int(counts[np.arange(COUNTER_MODULUS) % step != 0].sum())
        return step if odd <= ODD_STEPS_SHARE * total else None

    @property
    def external_trigger(self) -> bool:
        """Sampled at an external trigger: the configuration says so, or (without a configured
        rate) the counter steps by no fixed rate's step."""
        if self.configured_step:
            return False
        if self.triggered:
            return True
        step = self.counter_step
        return step not in STANDARD_STEPS and bool(self.counter_steps[1:].any())

    @property
    def mean_step(self) -> float | None:
        """Internal samples per datagram on average, missing datagrams included (a step of 0 counts
        as a whole counter cycle): the trigger's measured period, in ticks."""
        steps = int(self.counter_steps.sum())
        if not steps:
            return None
        ticks = int(np.arange(COUNTER_MODULUS) @ self.counter_steps) + COUNTER_MODULUS * int(self.counter_steps[0])
        return ticks / steps

    def _missing(self) -> int:
        step = self.counter_step
        if step is None:
            return 0
        deltas = np.arange(COUNTER_MODULUS)
        deltas[0] = COUNTER_MODULUS
        missing = np.maximum(-(-deltas // step) - 1, 0)
        return int(missing @ self.counter_steps)

    @property
    def lost_samples(self) -> int:
        """Datagrams missing by the counter at a fixed rate (losses of a whole counter cycle alias
        to fewer). Externally triggered, a step is whatever time passed between triggers: no loss
        is certain (see `inferred_missing`)."""
        return 0 if self.external_trigger else self._missing()

    @property
    def inferred_missing(self) -> int:
        """Externally triggered at a fixed step: datagrams missing by that usual step (a missed
        trigger reads the same), counted apart from `lost_samples`."""
        return self._missing() if self.external_trigger else 0

    def snapshot(self) -> StreamStats:
        """A frozen copy: these counters go on changing while the stream is read."""
        return StreamStats(
            bytes_in=self.bytes_in, datagrams=self.datagrams, crc_errors=self.crc_errors,
            lost_samples=self.lost_samples, skipped_bytes=self.skipped_bytes, restarts=self.restarts,
            restart_datagrams=tuple(self.restart_datagrams), config_changes=self.config_changes,
            special_datagrams=self.special_datagrams, undecodable_specials=self.undecodable_specials,
            counter_step=self.counter_step, external_trigger=self.external_trigger,
            inferred_missing=self.inferred_missing, mean_step=self.mean_step)

    def as_dict(self) -> dict:
        return asdict(self.snapshot())


WAIT = -1  # scan result: not enough bytes yet to decide
FOLLOW_BLOCK = 128  # datagrams `Scanner.follow` checks at once: more than a live read holds, and the most it
# checks in vain before a datagram that fails (about what `step` then costs to re-synchronise)


@lru_cache(maxsize=None)
def _check_table(layout: Layout, crlf: bool) -> tuple[np.ndarray, np.ndarray]:
    """One 256-entry table per byte of a datagram on the wire, such that the XOR of every byte's
    entry is 0 exactly when it verifies: the low 32 bits add up to its CRC (`position_tables`)
    XOR the CRC it carries, bit 32 is set by an id other than the layout's, bits 33 and 34 by
    a CR or LF that is not one. Returns the tables end to end and each byte's first index."""
    pre = layout.pre_crc
    tables, constant = position_tables(pre)
    check = np.zeros((layout.wire_length(crlf), 256), np.uint64)
    check[:pre] = tables
    check[0] ^= np.uint64(constant)
    for k in range(4):  # the CRC sent, most significant byte first
        check[pre + k] = np.arange(256, dtype=np.uint64) << np.uint64(24 - 8 * k)
    expected = [(0, layout.datagram_id)] + ([(pre + 4, CR_LF[0]), (pre + 5, CR_LF[1])] if crlf else [])
    for bit, (position, byte) in enumerate(expected, 32):
        check[position, np.arange(256) != byte] ^= np.uint64(1 << bit)
    return check.ravel(), np.arange(len(check), dtype=np.intp) * 256


def verified(frames: np.ndarray, layout: Layout, crlf: bool) -> int:
    """How many leading rows of `frames` (N x wire length uint8) are datagrams of `layout` that
    verify as `Scanner.step` checks them: id byte, CRC, CR LF when `crlf`. One table entry per
    byte, all gathered at once (a word per byte: a few rows at a time, FOLLOW_BLOCK at most)."""
    check, first = _check_table(layout, crlf)
    valid = np.bitwise_xor.reduce(check[frames + first], axis=1) == 0
    return len(valid) if valid.all() else int(np.argmin(valid))


@dataclass(frozen=True)
class TrimSeen:
    """A Bias Trim Offset datagram where the stream carried it: `sequence` numbers those seen
    (from 1), `datagram` is the stream number of the first normal datagram after it, so it tells
    the trim in force in the power-up holding that datagram (after a restart, the restarted
    sensor's first: a start-up BTO datagram belongs to the new power-up)."""

    sequence: int
    datagram: int
    trim: TrimRecord


class Scanner:
    """The framing state machine shared by the stream and bulk decoders.

    `step(buf, i, final)` decides what starts at offset i and returns the next offset (or WAIT).
    Accepted normal datagrams are reported to `on_normal(offset, layout_id)`; special datagrams
    are decoded and kept, and their bytes given to `on_special(frame)` when set. `final` means
    no more bytes will come, so a short tail is skipped.
    """

    def __init__(self, fmt: Format | None, on_normal, on_special=None):
        self.format = fmt or Format()
        self.stats = Stats(configured_step=self.format.counter_step)
        self.specials: collections.deque = collections.deque(maxlen=SPECIAL_HISTORY)
        self.configuration = None
        self.part_number = None
        self.serial_number = None
        self.bias_trims: tuple[TrimSeen, ...] = ()  # the last SPECIAL_HISTORY, replaced whole: a reader in
        # another thread always gets a consistent tuple
        self._trims_seen = 0
        self.last_counter: int | None = None
        self.warnings: list[str] = []  # what was refused or kept as read, and why (distinct, oldest first)
        self._on_normal, self._on_special = on_normal, on_special
        self._power_up = 0  # how far a power-up sequence has come: 1 part number, 2 then serial number
        self._quiet_until = 0  # no further CRC error is counted inside a failed candidate's span
        self._consumed = 0  # absolute offset of buf[0], to keep _quiet_until valid across buffers
        self._reach: list[tuple[int, int]] = [(0, 0)]  # (datagram number, absolute offset): that datagram and
        # those after it are decided only once the bytes up to that offset are read (`decided`)

    # ------------------------------------------------------------------ decisions
    def step(self, buf, i: int, final: bool) -> int:
        ident = buf[i]
        layout = NORMAL_LAYOUTS.get(ident)
        if layout is not None:
            crlf = self.format.crlf
            return self._candidate(buf, i, final, layout.pre_crc, crlf, normal=True)
        special = SPECIAL_IDS.get(ident)
        if special is not None:
            kind, crlf = special
            return self._candidate(buf, i, final, kind.pre_crc, crlf, normal=False)
        return self._skip(i)

    def _candidate(self, buf, i, final, pre, crlf, normal) -> int:
        end = i + pre + 4
        self._look(end)
        if len(buf) < end:
            return WAIT if not final else self._skip(i)
        if datagram_crc(buf[i:i + pre]) != int.from_bytes(buf[i + pre:end], "big"):
            return self._fail(i, end)
        if crlf is not False:
            self._look(end + 2)
            if len(buf) < end + 2 and not final:
                return WAIT
            has_crlf = buf[end:end + 2] == CR_LF
            if crlf and not has_crlf:
                return self._fail(i, end)
            if normal and crlf is None:
                self.format = replace(self.format, crlf=has_crlf)
            if has_crlf:
                end += 2
        if normal:
            self._accept_normal(buf, i)
        else:
            self._accept_special(bytes(buf[i:end]))
        return end

    def _look(self, end: int) -> None:
        """A decision reads the buffer up to `end`: no datagram from the next one on is accepted
        before that byte has come."""
        end += self._consumed
        number, reach = self._reach[-1]
        if end > reach:
            if number == self.stats.datagrams:
                self._reach[-1] = (number, end)
            else:
                self._reach.append((self.stats.datagrams, end))

    def decided(self, first: int, ends: np.ndarray) -> np.ndarray:
        """Where the bytes end that decide the datagrams numbered first, first + 1, ... (stream
        numbers; `ends`: each one's end, absolute offsets): its own last byte, or a later one where
        a decision before it (a candidate that needed more bytes, its CR LF being told) read
        further. Fed in pieces, a datagram is accepted with the piece holding that byte, so a read
        log stamps each datagram alike whatever the chunking (`StreamParser.feed_reads`, the bulk
        decoder). Not for datagrams before the last `forget`."""
        numbers, reach = np.array(self._reach).T
        return np.maximum(ends, reach[np.searchsorted(numbers, np.arange(first, first + len(ends)), "right") - 1])

    def forget(self, first: int) -> None:
        """`decided` will not be asked of datagrams before `first`: keep what later ones need."""
        while len(self._reach) > 1 and self._reach[1][0] <= first:
            del self._reach[0]

    @property
    def buffer_start(self) -> int:
        """The absolute offset of the first byte of the buffer `step` is given."""
        return self._consumed

    def _skip(self, i: int) -> int:
        self.stats.skipped_bytes += 1
        return i + 1

    def _fail(self, i: int, end: int) -> int:
        absolute = self._consumed + i
        if absolute >= self._quiet_until:
            self.stats.crc_errors += 1
            self._quiet_until = self._consumed + end
        return self._skip(i)

    # ------------------------------------------------------------------ accepted datagrams
    def _accept_normal(self, buf, i: int) -> None:
        ident = buf[i]
        if self.format.datagram_id is None:
            self.format = replace(self.format, datagram_id=ident)
        elif ident != self.format.datagram_id:
            self.format = replace(self.format, datagram_id=ident)
            self.stats.config_changes += 1
        layout = NORMAL_LAYOUTS[ident]
        if self._power_up == 2 and buf[i + layout.offsets["status_gyro"]] & START_UP:
            self._restart()  # a power-up whose configuration datagram was lost: the start-up bit says it
        self._power_up = 0
        self._count(buf[i + layout.counter_offset])
        self._on_normal(i, ident)

    def _count(self, counter: int) -> None:
        """One more normal datagram, with this counter."""
        if self.last_counter is not None:
            self.stats.counter_steps[(counter - self.last_counter) % COUNTER_MODULUS] += 1
        self.stats.datagrams += 1
        self.last_counter = counter

    def follow(self, buf, i: int, most: int | None = None) -> range:
        """Accept the datagrams of the current format that lie whole and back to back from offset
        i (at most `most` of them), each exactly as `step` would, and return their offsets (a
        range: its stop is the offset after them). A stream in step is made of little else: they
        are checked FOLLOW_BLOCK at a time (`verified`); whatever else comes (another id, a CRC
        or CR LF that fails, a tail still short) is left to `step`. Only once the format is known
        (its id and CR LF) and no power-up sequence is under way."""
        fmt = self.format
        if fmt.datagram_id is None or fmt.crlf is None or self._power_up:
            return range(i, i)
        layout = NORMAL_LAYOUTS[fmt.datagram_id]
        length = layout.wire_length(fmt.crlf)
        start = i
        stop = len(buf) if most is None else min(len(buf), i + most * length)
        while count := min(FOLLOW_BLOCK, (stop - i) // length):
            frames = np.frombuffer(buf, np.uint8, count * length, i).reshape(count, length)
            good = verified(frames, layout, fmt.crlf)
            self.count_counters(frames[:good, layout.counter_offset])
            i += good * length
            if good < count:
                break
        return range(start, i, length)

    def count_counters(self, counters: np.ndarray) -> None:
        """`_accept_normal`'s counter accounting for a run of datagrams at once (uint8 array, whose
        differences wrap modulo COUNTER_MODULUS as the counter does)."""
        if not len(counters):
            return
        if self.last_counter is not None:
            self.stats.counter_steps[(int(counters[0]) - self.last_counter) % COUNTER_MODULUS] += 1
        self.stats.counter_steps += np.bincount(counters[1:] - counters[:-1], minlength=COUNTER_MODULUS)
        self.stats.datagrams += len(counters)
        self.last_counter = int(counters[-1])
        self._power_up = 0

    def _accept_special(self, frame: bytes) -> None:
        """A power-up sequence is part number, serial number, configuration (DS §7.2); a part
        number and a serial number requested while data flow are followed by data without the
        start-up status bit, and are no restart."""
        self.stats.special_datagrams += 1
        if self._on_special is not None:
            self._on_special(frame)
        kind = SPECIAL_IDS[frame[0]][0]
        sequence = {PART_NUMBER: 1 if self.stats.datagrams else 0, SERIAL_NUMBER: 2 if self._power_up == 1 else 0}
        if kind is CONFIGURATION and self._power_up == 2:
            self._restart()
        self._power_up = sequence.get(kind, 0)
        try:
            item = decode_special(frame, acc_range_g=self.format.acc_ranges_g)  # each axis by its own range
        except ValueError as exc:  # e.g. unit codes of firmware the datasheet does not describe
            self.stats.undecodable_specials += 1
            self.warn(f"{kind.name.replace('_', ' ')} datagram refused: {exc}"
                      + ("; decoding goes on as before" if kind is CONFIGURATION else ""))
            return
        self.specials.append(item)
        if kind is SERIAL_NUMBER:
            self.serial_number = item
        elif kind is PART_NUMBER:
            self.part_number = item
        elif kind is CONFIGURATION:
            self._adopt(item)
        elif kind is BIAS_TRIM:
            self._bias_trim(item)

    def _bias_trim(self, item) -> None:
        """Keep a BTO datagram with where it came. Its accelerometer counts are scaled by the
        range the configuration datagram gives: without one yet their scale is unknown, so it is
        not kept."""
        if self.configuration is None:
            self.warn("bias trim offset datagram before any configuration datagram: the scale of its "
                      "accelerometer offsets is unknown, not recorded")
            return
        self._trims_seen += 1
        seen = TrimSeen(self._trims_seen, self.stats.datagrams, TrimRecord.of_datagram(item))
        self.bias_trims = (*self.bias_trims[1 - SPECIAL_HISTORY:], seen)

    def _restart(self) -> None:
        self.stats.restarts += 1
        self.stats.restart_datagrams.append(self.stats.datagrams)
        self.last_counter = None  # the counter restarts with the sensor

    def warn(self, text: str) -> None:
        """Keep a stream warning once (at most MAX_WARNINGS distinct ones)."""
        if text not in self.warnings and len(self.warnings) < MAX_WARNINGS:
            self.warnings.append(text)

    def _adopt(self, configuration) -> None:
        new = configuration.format
        if self.configuration is not None and new != self.format:
            self.stats.config_changes += 1
        elif self.configuration is None and self.format.datagram_id not in (None, new.datagram_id):
            self.stats.config_changes += 1
        self.configuration = configuration
        self.format = new
        self.stats.configured_step = new.counter_step
        self.stats.triggered = configuration.external_trigger
        for text in configuration.warnings:
            self.warn(text)

    def advance(self, consumed: int) -> None:
        """The owner dropped `consumed` bytes from the front of its buffer."""
        self._consumed += consumed


class Accepted:
    """Normal datagrams the scanner accepted and nobody decoded yet: their offsets in stream order,
    and where each run of one format starts (a datagram has its format's id). The stream parser
    and the bulk decoder both decode them as runs of one format (`take`)."""

    def __init__(self) -> None:
        self._offsets: list[int] = []
        self._formats: list[tuple[int, Format]] = []  # (index into _offsets, format) where a run starts

    def __len__(self) -> int:
        return len(self._offsets)

    def add(self, offsets, fmt: Format) -> None:
        """Datagrams at `offsets` (any iterable of ints, a range at C speed), all in `fmt`."""
        if not self._formats or self._formats[-1][1] is not fmt:
            self._formats.append((len(self._offsets), fmt))
        self._offsets.extend(offsets)

    def take(self) -> tuple:
        """Empty the list into its runs: (layout, format, offsets array, start, stop) each, with
        the run's datagrams at [start:stop] of those taken."""
        offsets = np.array(self._offsets, np.int64)
        stops = [start for start, _ in self._formats[1:]] + [len(offsets)]
        runs = tuple((NORMAL_LAYOUTS[fmt.datagram_id], fmt, offsets[start:stop], start, stop)
                     for (start, fmt), stop in zip(self._formats, stops))
        self._offsets.clear()
        self._formats.clear()
        return runs


@dataclass(frozen=True)
class Settled:
    """The bytes one feed settled, for a tap (`StreamParser.tap`): every byte fed is in exactly
    one Settled, in stream order, datagrams whole; `samples` were decoded from `data`, and
    `runs` says where: (layout, format, offsets into `data`, start, stop) with
    samples[start:stop] decoded from the datagrams at those offsets (`Accepted.take`). `first` is
    the stream number of samples[0], `restart_datagrams` the parser's restarts from `first` on
    (each restarted sensor's first stream number, `Stats.restart_datagrams`): what a tap needs to
    cut at power-ups by the same rule as the daemon (`calibd.session.PowerUpCuts`). `specials`:
    the special datagrams among `data`, as sent, in stream order."""

    data: bytes
    samples: np.ndarray
    runs: tuple
    first: int = 0
    restart_datagrams: tuple[int, ...] = ()
    specials: tuple[bytes, ...] = ()
    trims: tuple[TrimRecord, ...] = ()  # the Bias Trim Offset datagrams among them, as the scanner decoded them


class StreamParser:
    """`feed(bytes) -> samples`: identical output for any chunking of the same bytes.

    Memory stays bounded: only an undecided tail shorter than the longest datagram is kept.
    Never raises on any input. `tap`, when set, is called with each feed's `Settled` bytes
    (those it has decided on), so one parse serves whoever wants the bytes as well as the
    samples (a daemon passing the sensor's stream on); a tap must not raise.
    """

    def __init__(self, fmt: Format | None = None, tap=None):
        self._buf = bytearray()
        self._accepted = Accepted()  # the normal datagrams accepted in the buffer, not yet decoded
        self._specials: list[bytes] = []  # the special datagrams of the feed being settled, for the tap
        self.scanner = Scanner(fmt, self._found_normal, self._specials.append if tap is not None else None)
        self.tap = tap
        self._trims_tapped = 0  # the scanner's BTO datagrams (by sequence) a tap has been given

    def _found_normal(self, offset: int, ident: int) -> None:
        self._accepted.add((offset,), self.scanner.format)

    def _follow(self, i: int) -> int:
        """`Scanner.follow` from offset i; the offset after what it accepted."""
        run = self.scanner.follow(self._buf, i)
        if run:
            self._accepted.add(run, self.scanner.format)
        return run.stop

    @property
    def stats(self) -> Stats:
        return self.scanner.stats

    @property
    def format(self) -> Format:
        return self.scanner.format

    def feed(self, data: bytes, t_host: float = math.nan) -> np.ndarray:
        """Add bytes; return the samples they complete, stamped with `t_host` (s)."""
        self.stats.bytes_in += len(data)
        self._buf += data
        return self._scan(final=False, t_host=t_host)

    def feed_reads(self, data: bytes, reads: np.ndarray) -> np.ndarray:
        """`feed` of several reads at once: `data` is their bytes end to end, `reads` (READS_DTYPE
        rows, `stim300.reads`) where each ended in `data` and when it returned. Each datagram is
        stamped with the time of the read that completed it (`Scanner.decided`), as the bulk
        decoder stamps a capture by its read log: the samples feeding the reads one by one gives,
        at one parse's cost (a live reader that reads often and parses seldom)."""
        stamps = reads.copy()
        stamps["end"] += self.scanner.buffer_start + len(self._buf)  # absolute offsets, as the scanner counts
        self.stats.bytes_in += len(data)
        self._buf += data
        return self._scan(final=False, t_host=stamps)

    def finish(self, t_host: float = math.nan) -> np.ndarray:
        """End of stream: decide the tail (incomplete datagrams are skipped bytes)."""
        return self._scan(final=True, t_host=t_host)

    def _scan(self, final: bool, t_host: float | np.ndarray) -> np.ndarray:
        buf, scanner = self._buf, self.scanner
        i = self._follow(0)  # a stream in step: the datagram the last feed left short, and the rest
        while i < len(buf):
            datagrams = scanner.stats.datagrams
            nxt = scanner.step(buf, i, final)
            if nxt == WAIT:
                break
            i = nxt if scanner.stats.datagrams == datagrams else self._follow(nxt)
        samples, runs = self._decode(buf, t_host)
        if self.tap is not None and i:
            first = self.stats.datagrams - len(samples)
            restarts = tuple(k for k in self.stats.restart_datagrams if k >= first)
            latest = scanner.bias_trims[-1].sequence if scanner.bias_trims else 0
            trims = () if latest == self._trims_tapped else \
                tuple(t.trim for t in scanner.bias_trims if t.sequence > self._trims_tapped)
            self._trims_tapped = latest
            self.tap(Settled(bytes(buf[:i]), samples, runs, first, restarts, tuple(self._specials), trims))
            self._specials.clear()
        del buf[:i]
        scanner.advance(i)
        return samples

    def _decode(self, buf: bytearray, t_host: float | np.ndarray) -> tuple[np.ndarray, tuple]:
        """The accepted datagrams' samples, and their runs of one format (as `Settled.runs`);
        `t_host`: one time for all, or the reads `buf` holds (`feed_reads`)."""
        out = np.empty(len(self._accepted), SAMPLE_DTYPE)
        if not len(out):
            return out, ()
        first = self.stats.datagrams - len(out)  # the stream number of the first
        runs = self._accepted.take()
        view = np.frombuffer(buf, np.uint8)
        for layout, fmt, run, start, stop in runs:
            stamps = t_host if not isinstance(t_host, np.ndarray) else read_times(t_host, self.scanner.decided(
                first + start, self.scanner.buffer_start + run + layout.wire_length(fmt.crlf)))
            decode_at(view, run, layout, fmt, out[start:stop], stamps)
        del view
        self.scanner.forget(self.stats.datagrams)
        return out, runs

"""Fuzzing: the bulk decoder and the stream parser agree on every input, and garbage stays cheap.

The cases are built from a seed (numpy), so `benchmarks/fuzz.py` runs the same cases by the
million; here hypothesis draws the seeds, the kind of damage and the chunking. The speed guard
counts the bulk decoder's work (scanner decisions, bytes searched, vectorised attempts and CRCs)
instead of timing it, so a decoder gone quadratic on garbage fails on any machine.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from captures import capture, power_up, same_samples, stream_decode
from stim300 import bulk
from stim300.bulk import SYNC_RUN, BulkDecoder, decode_blocks, decode_capture
from stim300.capture import stream_info
from stim300.codec import SAMPLE_DTYPE
from stim300.protocol import NORMAL_LAYOUTS, Format
from stim300.reads import READS_DTYPE
from stim300.special import Configuration, PartNumber, SerialNumber, encode_special
from stim300.stream import Stats

FORMATS = ((0xA7, False), (0x93, True), (0x90, False), (0xF7, True), (0xAF, False))


def valid_capture(rng: np.random.Generator, n: int) -> tuple[bytes, int, bool]:
    """n datagrams of a random format, with power-up datagrams in front half the time."""
    ident, crlf = FORMATS[rng.integers(len(FORMATS))]
    data, _, _ = capture(n, ident, crlf, rate=2000 if ident == 0xA7 else 125, seed=int(rng.integers(1 << 30)))
    if rng.random() < 0.5 and ident == 0xA7:
        data = power_up(Configuration.build(sample_rate_hz=2000, crlf=crlf)) + data
    return data, ident, crlf


def random_bytes(rng: np.random.Generator) -> bytes:
    return rng.integers(0, 256, int(rng.integers(0, 3000)), dtype=np.uint8).tobytes()


def mutated(rng: np.random.Generator) -> bytes:
    """A valid capture damaged a few times: bit flips, inserted and deleted bytes, truncation,
    special datagrams repeated or sent on request (part number, serial number) between datagrams."""
    data, ident, crlf = valid_capture(rng, int(rng.integers(1, 200)))
    buf = bytearray(data)
    length = NORMAL_LAYOUTS[ident].wire_length(crlf)
    specials = [encode_special(PartNumber("84167-4400003-321", "K"), crlf),
                encode_special(SerialNumber("N25582405002002"), crlf),
                encode_special(Configuration.build(sample_rate_hz=125, crlf=crlf), crlf)]
    for _ in range(int(rng.integers(0, 6))):
        kind = rng.integers(5)
        pos = int(rng.integers(0, len(buf) + 1))
        if kind == 0 and buf:
            buf[min(pos, len(buf) - 1)] ^= 1 << int(rng.integers(8))
        elif kind == 1:
            buf[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 80)), dtype=np.uint8).tobytes()
        elif kind == 2:
            del buf[pos:pos + int(rng.integers(1, 80))]
        elif kind == 3:
            del buf[pos:]
        else:  # on a datagram boundary, as a sensor answers a request
            pos = pos // length * length
            picked = rng.integers(len(specials), size=int(rng.integers(1, 3)))
            buf[pos:pos] = b"".join(specials[k] for k in picked)
    return bytes(buf)


def after_header(rng: np.random.Generator, garbage: bytes) -> bytes:
    """Valid datagrams, garbage, and sometimes valid datagrams again."""
    head, _, _ = valid_capture(rng, int(rng.integers(1, 100)))
    tail = valid_capture(rng, int(rng.integers(1, 100)))[0] if rng.random() < 0.5 else b""
    return head + garbage + tail


def garbage_runs(rng: np.random.Generator) -> bytes:
    """Random bytes or a run of 0xA7 after a valid header."""
    size = int(rng.integers(1, 3000))
    if rng.random() < 0.5:
        return after_header(rng, b"\xa7" * size)
    return after_header(rng, rng.integers(0, 256, size, dtype=np.uint8).tobytes())


CASES = {"random": random_bytes, "mutated": mutated, "garbage": garbage_runs}
GIVEN_FORMATS = (None, Format(crlf=True), Format(datagram_id=0xA7, crlf=False, sample_rate_hz=2000),
                 Format(sample_rate_hz=125))  # what a user may say of a capture without configuration


def chunking(rng: np.random.Generator, size: int) -> list[int]:
    """Random cut points, sometimes byte by byte for a stretch."""
    cuts = rng.integers(0, size + 1, int(rng.integers(0, 12))).tolist()
    if size and rng.random() < 0.2:
        start = int(rng.integers(size))
        cuts += range(start, min(size, start + 200))
    return sorted(set(cuts))


def grouping(rng: np.random.Generator, cuts: list[int]) -> list[int]:
    """Random groups of the reads that `cuts` make, by the index of each group's first read: what a
    live reader parses at once."""
    return sorted(set(rng.integers(0, len(cuts) + 1, int(rng.integers(1, 6))).tolist()))


def different_stats(mine: Stats, theirs: Stats) -> str | None:
    for field in fields(Stats):
        if not np.array_equal(getattr(mine, field.name), getattr(theirs, field.name)):
            return f"stats.{field.name}: {getattr(mine, field.name)} against {getattr(theirs, field.name)}"
    return None


def read_log(data: bytes, cuts: list[int]) -> np.ndarray:
    """The read log of `data` read in pieces cut at `cuts`, read k returned at time k s (as
    `captures.stream_decode` stamps them)."""
    ends = np.array(sorted({*cuts, len(data)} - {0}), np.int64)
    log = np.empty(len(ends), READS_DTYPE)
    log["end"] = ends
    log["t_host_s"] = np.searchsorted(np.array([0, *sorted(set(cuts)), len(data)]), ends, "left") - 1
    return log


def disagreement(data: bytes, cuts: list[int], fmt: Format | None = None, together: list[int] = (0,)) -> str | None:
    """What differs between the stream parser (fed reads cut at `cuts`, one at a time) and the bulk
    decoder (whole with the reads' log, and block by block), both told `fmt`: rows with their
    host times, any Stats field, or the stream's description; or between those reads fed one at a
    time and in groups (starting at the reads `together`): rows with their host times, or any
    Stats field. None when all agree."""
    samples, parser = stream_decode(data, cuts, fmt)
    grouped, grouped_parser = stream_decode(data, cuts, fmt, together)
    if not (same_samples(samples, grouped) and np.array_equal(samples["t_host"], grouped["t_host"], equal_nan=True)):
        return f"rows or host times: read by read {len(samples)}, reads together {len(grouped)}"
    if (differs := different_stats(grouped_parser.stats, parser.stats)) is not None:
        return f"reads together: {differs}"
    decoder = BulkDecoder(data, fmt, read_log(data, cuts), lambda n: np.empty(n, SAMPLE_DTYPE))
    rows = decoder.run()
    if not same_samples(samples, rows):
        return f"rows: stream {len(samples)}, bulk {len(rows)}"
    if not np.array_equal(samples["t_host"], rows["t_host"], equal_nan=True):
        return "host times: stream read by read, bulk by the read log"
    if (differs := different_stats(parser.stats, decoder.scanner.stats)) is not None:
        return f"stream against bulk: {differs}"
    if stream_info(parser) != stream_info(decoder.scanner):
        return "stream info"
    blocks = []
    info = decode_blocks(data, lambda samples, scanner, offset: blocks.append(samples.copy()), fmt)
    if not same_samples(samples, np.concatenate([np.empty(0, SAMPLE_DTYPE), *blocks])):
        return f"rows by blocks: stream {len(samples)}, bulk {sum(map(len, blocks))}"
    if info != stream_info(parser):
        return "stream info by blocks"
    return None


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(CASES)), st.sampled_from(GIVEN_FORMATS), st.integers(0, 2**63 - 1))
def test_stream_and_bulk_agree_on_any_input_and_chunking(kind, fmt, seed):
    rng = np.random.default_rng(seed)
    data = CASES[kind](rng)
    cuts = chunking(rng, len(data))
    assert disagreement(data, cuts, fmt, grouping(rng, cuts)) is None


def test_a_requested_part_number_then_data_then_a_serial_number_is_no_restart():
    """The vectorised path, like the scanner, forgets a part number once normal data follows."""
    data, _, _ = capture(4 * SYNC_RUN, 0xA7, False)
    half = 2 * SYNC_RUN * 59
    stream = (data[:half] + encode_special(PartNumber("84167-4400003-321", "K"), False) + data[half:]
              + encode_special(SerialNumber("N25582405002002"), False))
    assert disagreement(stream, [1000]) is None
    assert decode_capture(stream).info.stats.restarts == 0


def bursts(count: int, per_burst: int = 16, seed: int = 0) -> bytes:
    """A clean 0xA7 capture with `count` bursts of random bytes (10-190 each), one every
    `per_burst` datagrams."""
    rng = np.random.default_rng(seed)
    data, _, _ = capture(per_burst * count, 0xA7, False, seed=seed)
    frames = np.frombuffer(data, np.uint8).reshape(-1, 59)
    parts = []
    for piece in np.array_split(frames, count):
        parts += [piece.tobytes(), rng.integers(0, 256, int(rng.integers(10, 190)), dtype=np.uint8).tobytes()]
    return b"".join(parts)


GARBAGE = {
    "random after a header": lambda: capture(20)[0] + np.random.default_rng(1).integers(
        0, 256, 200_000, dtype=np.uint8).tobytes(),
    "0xA7 run after a header": lambda: capture(20)[0] + b"\xa7" * 50_000,
    "bursts in a clean capture": lambda: bursts(300),
    "bursts between long runs": lambda: bursts(30, per_burst=500),
}


def test_garbage_costs_work_linear_in_its_size():
    """Each byte is searched once and decided at most once; the vectorised path is tried only
    after SYNC_RUN datagrams accepted one after another, and checks a bounded multiple of what it
    accepts; so the work per byte is bounded whatever the input."""
    for name, make in GARBAGE.items():
        data = make()
        decoder = BulkDecoder(data, None, None, lambda n: np.empty(n, SAMPLE_DTYPE))
        decoder.run()
        work, datagrams = decoder.work, decoder.scanner.stats.datagrams
        assert work.searched <= len(data), name
        assert work.steps <= len(data), name
        assert work.fast_runs <= datagrams // SYNC_RUN, name
        assert work.checked <= 9 * datagrams, name
        if "after a header" in name:
            assert (work.fast_runs, work.checked) == (0, 0), name  # 20 datagrams never pay for it
            assert work.steps < 0.2 * len(data) or name.startswith("0xA7"), name


def test_a_clean_capture_goes_the_vectorised_way():
    data, _, _ = capture(20_000, 0xA7, False)
    decoder = BulkDecoder(data, None, None, lambda n: np.empty(n, SAMPLE_DTYPE))
    decoder.run()
    assert decoder.work.steps == 1  # the scanner only finds the stream's step, and takes what follows
    assert decoder.work.followed == SYNC_RUN - 1
    assert decoder.work.fast_runs == 1
    assert decoder.work.checked == 20_000 - SYNC_RUN


def test_scattered_datagrams_are_handed_over_in_bounded_blocks(monkeypatch):
    """Datagrams the scanner accepts one by one (a stray byte after each) are decoded in batches,
    but never more than BLOCK at once: decode_blocks keeps its memory bound."""
    monkeypatch.setattr(bulk, "BLOCK", 50)
    data, truth, _ = capture(400, 0x90, False)
    frames = np.frombuffer(data, np.uint8).reshape(400, -1)
    scattered = np.hstack([frames, np.zeros((400, 1), np.uint8)]).tobytes()
    blocks = []
    info = decode_blocks(scattered, lambda samples, scanner, offset: blocks.append(samples.copy()))
    assert same_samples(np.concatenate(blocks), truth)
    assert max(map(len, blocks)) <= 50 and len(blocks) >= 8
    assert info.stats.skipped_bytes == 400

"""Fuzzing the decoders at length, and what garbage costs the bulk decoder against the stream parser.

Runs --count of the cases of tests/test_fuzz.py (random bytes, mutated captures, garbage runs after a
valid header, each under a random chunking, with each format a user may give) and counts exceptions
and disagreements between the stream parser and the bulk decoder (rows and every Stats field), and
between reads parsed one by one and in groups (rows with their host times, every Stats field). Then
decodes garbage both ways and prints the CPU time per MB, the stream parser fed 4096-byte chunks as
a serial read would deliver them, both measured in this run (target: bulk <= 2x stream):

- random bytes after a valid header;
- a run of 0xA7 bytes after a valid header (every byte starts a candidate datagram);
- a clean 0xA7 capture with 10,000 garbage bursts, one every 16 datagrams;
- a clean 0xA7 capture with a bit flip every SYNC_RUN + 1 datagrams (each run just long enough to
  try the vectorised path, which then fails at once: its worst case).

    python benchmarks/fuzz.py [--count 20000] [--seed 0] [--workers 1] [--documents 0]

1e6 inputs take a few CPU-hours (about 10 ms each on one core). `--documents N` also runs N inputs
of benchmarks/fuzz_documents.py: the socket command parser, the client's message reader and the
result, state, noise, configuration and scenario readers, on mutated real documents (about 2 ms
each).
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

import fuzz_documents

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from captures import capture  # noqa: E402
from stim300.bulk import SYNC_RUN, decode_capture  # noqa: E402
from stim300.stream import StreamParser  # noqa: E402
from test_fuzz import CASES, GIVEN_FORMATS, bursts, chunking, disagreement, grouping  # noqa: E402


def fuzz_range(seed: int, start: int, stop: int) -> tuple[int, int, int, str | None]:
    """Inputs start..stop-1: (bytes, exceptions, disagreements, the first failure)."""
    kinds = sorted(CASES)
    total, exceptions, disagreements, first = 0, 0, 0, None
    for k in range(start, stop):
        rng = np.random.default_rng([seed, k])
        kind, fmt = kinds[k % len(kinds)], GIVEN_FORMATS[k // len(kinds) % len(GIVEN_FORMATS)]
        data = CASES[kind](rng)
        total += len(data)
        try:
            cuts = chunking(rng, len(data))
            what = disagreement(data, cuts, fmt, grouping(rng, cuts))
        except Exception as exc:  # noqa: BLE001 - counting is the point
            exceptions += 1
            what = f"{type(exc).__name__}: {exc}"
        else:
            disagreements += what is not None
        if what and first is None:
            first = f"input {k} ({kind}, format {fmt}, seed [{seed}, {k}]): {what}"
    return total, exceptions, disagreements, first


def fuzz(count: int, seed: int, workers: int) -> None:
    t = time.perf_counter()
    edges = np.linspace(0, count, 8 * workers + 1).astype(int).tolist()
    with ProcessPoolExecutor(workers) as pool:
        results = list(pool.map(fuzz_range, [seed] * (len(edges) - 1), edges[:-1], edges[1:]))
    total, exceptions, disagreements = (sum(r[i] for r in results) for i in range(3))
    print(f"fuzz: {count} inputs ({total / 1e6:.1f} MB) in {time.perf_counter() - t:.0f} s: "
          f"{exceptions} exceptions, {disagreements} disagreements")
    first = next((r[3] for r in results if r[3]), None)
    if first:
        print(f"  first: {first}")


def flipped_runs(runs: int) -> bytes:
    """0xA7 datagrams with one bit flipped in every (SYNC_RUN + 1)-th."""
    data, _, _ = capture(runs * (SYNC_RUN + 1), 0xA7, False)
    buf = np.frombuffer(data, np.uint8).reshape(-1, 59).copy()
    buf[SYNC_RUN::SYNC_RUN + 1, 20] ^= 0x04
    return buf.tobytes()


def cpu_s(decode, data: bytes, repeats: int = 5) -> float:
    """The median CPU time of `repeats` decodes: one takes tens of milliseconds, noise for a ratio."""
    times = []
    for _ in range(repeats):
        t = time.process_time()
        decode(data)
        times.append(time.process_time() - t)
    return float(np.median(times))


def stream(data: bytes, chunk: int = 4096) -> None:
    parser = StreamParser()
    for start in range(0, len(data), chunk):
        parser.feed(data[start:start + chunk])
    parser.finish()


def garbage_speed() -> None:
    rng = np.random.default_rng(1)
    header = capture(20)[0]
    cases = {
        "random bytes after a header": header + rng.integers(0, 256, 1_000_000, dtype=np.uint8).tobytes(),
        "0xA7 run after a header": header + b"\xa7" * 300_000,
        "10,000 garbage bursts in a capture": bursts(10_000),
        f"a bit flip every {SYNC_RUN + 1} datagrams": flipped_runs(2000),
    }
    print("CPU time per MB (bulk decoder vs stream parser in 4096 B chunks; target: bulk <= 2x stream):")
    for name, data in cases.items():
        mb = len(data) / 1e6
        bulk_s, stream_s = cpu_s(decode_capture, data) / mb, cpu_s(stream, data) / mb
        print(f"  {name} ({mb:.2f} MB): bulk {bulk_s:.3f} CPU-s/MB, stream {stream_s:.3f} CPU-s/MB, "
              f"ratio {bulk_s / stream_s:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=20_000, help="fuzz inputs (default 20000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fuzz inputs (default 0)")
    ap.add_argument("--workers", type=int, default=1, help="processes for the fuzz inputs (default 1)")
    ap.add_argument("--documents", type=int, default=0,
                    help="also fuzz the document and line readers with this many inputs (default 0)")
    args = ap.parse_args()
    fuzz(args.count, args.seed, args.workers)
    garbage_speed()
    if args.documents:
        return fuzz_documents.run(args.documents, args.seed, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Decoding throughput: bulk decoder vs streaming parser, a live feed's cost, and `stim300 decode` as a whole process.

Targets (driver issue): bulk >= 200 MB/s on one core for 0xA7 captures and >= 50x the streaming
parser; `stim300 decode` of a 1-hour 2000 Hz 0xA7 capture (425 MB) to .npz in <= 5 s. The ratio
was set when the streaming parser took one datagram at a time; it now takes runs of them
vectorised as well (`Scanner.follow`), so the ratio fell while both got faster: it is printed, not
pursued (slowing the live parser to meet it is no goal).

Live feeds first: a serving port reader hands the parser what one read returned, 8 datagrams at
2000 Hz (a read every 4 ms, `stim300.port.SERVED_BATCH_S`), cut anywhere in a datagram (unserved,
it parses 0.2 s of reads at once: benchmarks/live.py). Printed: us per feed and per
datagram (best of --repeat), the share of one core that parsing takes at 2000 Hz (the port reader
thread's target, its reads included, is <= 1 %: benchmarks/live.py measures it), and two baselines
of the same run: copying each read into numpy (what any reader pays) and the bulk decoder's cost
per datagram on the same bytes.

The streaming parser is fed 4096-byte chunks, as a serial read would deliver them. Every figure is
measured in this run. The bulk figure is the best of --repeat runs: on a virtual machine the first
touch of memory the guest has never used is slow (host page faults), which says nothing about the
decoder; the first run is printed too.

    python benchmarks/decode.py [--seconds 3600] [--repeat 3] [--feeds-only]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stim300.bulk import decode_capture
from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, NORMAL_LAYOUTS, Format
from stim300.stream import StreamParser

RATE = INTERNAL_RATE_HZ  # the fastest rate: one datagram per internal sample
FMT = Format(datagram_id=0xA7, crlf=False, sample_rate_hz=RATE)
LENGTH = NORMAL_LAYOUTS[0xA7].wire_length(False)
FEED_DATAGRAMS = 8  # what one port read holds at 2000 Hz (PortReader.batch_s = 4 ms)


def static_bytes(start: int, n: int, rng: np.random.Generator) -> bytes:
    """n 0xA7 datagrams of static-looking data (noisy counts around gravity), counters from `start`."""
    scales = FMT.scales()
    s = np.zeros(n, SAMPLE_DTYPE)
    s["gyro"] = np.rint(rng.normal(0, 0.05, (n, 3)) / scales["gyro"]) * scales["gyro"]
    s["acc"] = np.rint((rng.normal(0, 1e-3, (n, 3)) + [0, 0, 1]) / scales["acc"]) * scales["acc"]
    s["incl"] = np.rint((rng.normal(0, 1e-4, (n, 3)) + [0, 0, 1]) / scales["incl"]) * scales["incl"]
    for block in ("temp_gyro", "temp_acc", "temp_incl"):
        s[block] = 35.5
    s["counter"] = (start + np.arange(n)) % COUNTER_MODULUS
    s["latency_us"] = 516
    return encode_samples(s, 0xA7, FMT, False).tobytes()


def make_capture(path: Path, seconds: float) -> None:
    """A 0xA7 capture of static-looking data at 2000 Hz."""
    rng = np.random.default_rng(1)
    total = int(seconds * RATE)
    with open(path, "wb") as f:
        for start in range(0, total, 500_000):
            f.write(static_bytes(start, min(500_000, total - start), rng))


def best_us(run, repeat: int) -> float:
    """The fastest of `repeat` calls of `run()`, in us."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        run()
        times.append(time.perf_counter() - t)
    return min(times) * 1e6


def live_feeds(seconds: float, repeat: int) -> None:
    """Print what a live feed of FEED_DATAGRAMS datagrams costs the stream parser, against copying
    the same reads into numpy and against the bulk decoder per datagram."""
    data = static_bytes(0, int(seconds * RATE), np.random.default_rng(2))
    size = FEED_DATAGRAMS * LENGTH
    edges = [0, *range(LENGTH // 2, len(data), size), len(data)]  # every read ends inside a datagram
    reads = [data[a:b] for a, b in zip(edges, edges[1:])]
    datagrams = len(data) // LENGTH

    def stream():
        parser = StreamParser()
        for t_host, chunk in enumerate(reads):
            parser.feed(chunk, float(t_host))
        assert parser.stats.datagrams == datagrams

    def copy():
        for chunk in reads:
            np.frombuffer(bytes(chunk), np.uint8)

    feed_us = best_us(stream, repeat)
    copy_us = best_us(copy, repeat)
    bulk_us = best_us(lambda: decode_capture(data), repeat)
    feeds_per_s = RATE / FEED_DATAGRAMS
    print(f"live feeds of {FEED_DATAGRAMS} datagrams (0xA7, {len(reads)} reads of {size} B cut inside a datagram, "
          f"best of {repeat}):")
    print(f"  stream parser: {feed_us / len(reads):.1f} us per feed, {feed_us / datagrams:.2f} us per datagram; "
          f"at {RATE} Hz ({feeds_per_s:.0f} feeds/s) {feed_us / len(reads) * feeds_per_s / 1e4:.2f} % of one core "
          f"parsing (target: the port reader thread, reads and all, <= 1 %: benchmarks/live.py)")
    print(f"  baseline, each read copied into numpy: {copy_us / len(reads):.2f} us per feed; "
          f"parser / copy {feed_us / copy_us:.0f}x")
    print(f"  baseline, bulk decoder on the same bytes: {bulk_us / datagrams:.3f} us per datagram; "
          f"parser / bulk {feed_us / bulk_us:.0f}x")


def bulk_rate(data: bytes) -> tuple[float, float, int]:
    t = time.perf_counter()
    samples = decode_capture(data).samples
    elapsed = time.perf_counter() - t
    return len(data) / elapsed / 1e6, elapsed, len(samples)


def stream_rate(data: bytes, chunk: int = 4096) -> float:
    parser = StreamParser()
    t = time.perf_counter()
    for start in range(0, len(data), chunk):
        parser.feed(data[start:start + chunk])
    parser.finish()
    return len(data) / (time.perf_counter() - t) / 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3600.0, help="capture length in s (default 3600)")
    ap.add_argument("--repeat", type=int, default=3, help="bulk runs; the best is reported (default 3)")
    ap.add_argument("--stream-seconds", type=float, default=30.0,
                    help="seconds of the capture given to the (slow) streaming parser (default 30)")
    ap.add_argument("--feed-seconds", type=float, default=10.0,
                    help="seconds of 2000 Hz data fed as live reads of 8 datagrams (default 10)")
    ap.add_argument("--feeds-only", action="store_true", help="measure the live feeds only")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} cores")
    live_feeds(args.feed_seconds, args.repeat)
    if args.feeds_only:
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(tmp) / "capture.bin"
        t = time.perf_counter()
        make_capture(capture, args.seconds)
        size = capture.stat().st_size
        print(f"capture: 0xA7 at {RATE} Hz, {args.seconds:.0f} s, {size / 1e6:.1f} MB "
              f"(made in {time.perf_counter() - t:.1f} s)")
        data = capture.read_bytes()

        runs = [bulk_rate(data) for _ in range(args.repeat)]
        best = max(r[0] for r in runs)
        print(f"bulk decoder: first run {runs[0][0]:.0f} MB/s ({runs[0][1]:.2f} s), best of {args.repeat} "
              f"{best:.0f} MB/s = {best / 59:.2f} M datagrams/s  (target >= 200 MB/s)")

        part = data[:int(args.stream_seconds * RATE) * 59]
        stream = stream_rate(part)
        print(f"streaming parser, 4096 B chunks: {stream:.1f} MB/s on {len(part) / 1e6:.1f} MB")
        print(f"ratio bulk / streaming: {best / stream:.0f}x  (driver issue's target >= 50x, not pursued: see above)")
        del data

        out = Path(tmp) / "out.npz"
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "stim300.cli", "decode", str(capture), "-o", str(out)],
                       check=True, stderr=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(Path.cwd())})
        whole = time.perf_counter() - t
        print(f"stim300 decode -> .npz as a process: {whole:.2f} s for {size / 1e6:.0f} MB "
              f"({out.stat().st_size / 1e6:.0f} MB written)  (target <= 5 s for 425 MB: "
              f"{whole * 425e6 / size:.2f} s scaled)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Decoding throughput: bulk decoder vs streaming parser, and `stim300 decode` as a whole process.

Targets (driver issue): bulk >= 200 MB/s on one core for 0xA7 captures and >= 50x the streaming
parser; `stim300 decode` of a 1-hour 2000 Hz 0xA7 capture (425 MB) to .npz in <= 5 s.

The streaming parser is fed 4096-byte chunks, as a serial read would deliver them. Every figure is
measured in this run. The bulk figure is the best of --repeat runs: on a virtual machine the first
touch of memory the guest has never used is slow (host page faults), which says nothing about the
decoder; the first run is printed too.

    python benchmarks/decode.py [--seconds 3600] [--repeat 3]
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
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, Format
from stim300.stream import StreamParser

RATE = INTERNAL_RATE_HZ  # the fastest rate: one datagram per internal sample
FMT = Format(datagram_id=0xA7, crlf=False, sample_rate_hz=RATE)


def make_capture(path: Path, seconds: float) -> None:
    """A 0xA7 capture of static-looking data: noisy counts around gravity, 2000 Hz counters."""
    rng = np.random.default_rng(1)
    total = int(seconds * RATE)
    scales = FMT.scales()
    with open(path, "wb") as f:
        for start in range(0, total, 500_000):
            n = min(500_000, total - start)
            s = np.zeros(n, SAMPLE_DTYPE)
            s["gyro"] = np.rint(rng.normal(0, 0.05, (n, 3)) / scales["gyro"]) * scales["gyro"]
            s["acc"] = np.rint((rng.normal(0, 1e-3, (n, 3)) + [0, 0, 1]) / scales["acc"]) * scales["acc"]
            s["incl"] = np.rint((rng.normal(0, 1e-4, (n, 3)) + [0, 0, 1]) / scales["incl"]) * scales["incl"]
            for block in ("temp_gyro", "temp_acc", "temp_incl"):
                s[block] = 35.5
            s["counter"] = (start + np.arange(n)) % COUNTER_MODULUS
            s["latency_us"] = 516
            f.write(encode_samples(s, 0xA7, FMT, False).tobytes())


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
    args = ap.parse_args()
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
        print(f"ratio bulk / streaming: {best / stream:.0f}x  (target >= 50x)")
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

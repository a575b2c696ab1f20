"""Cost of the ptys' taps in the port reader thread, per second of 2000 Hz data.

The reader thread feeds its parser about every 4 ms (`PortReader.batch_s`), so at 2000 Hz each
feed settles about 8 datagrams. This feeds 10 s of 0xA7 datagrams (rate, acceleration,
inclination, temperatures; 59 bytes each) that way through a parser alone, with the raw pty's
tap, and with the corrected pty's tap holding a result, while a reader drains both links, at 4
times real time; it prints the thread's CPU time per second of data for each (the best of
--repeats runs) and the bytes the links dropped (0: the readers kept up).

    python benchmarks/pty_tap.py [--seconds 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import select
import sys
import tempfile
import threading
import time
import tty
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from calibd.results import CalibrationResult, Estimate  # noqa: E402
from calibd.serve.ptys import CorrectedPty, RawPty  # noqa: E402
from captures import exact_samples  # noqa: E402
from stim300.codec import encode_samples  # noqa: E402
from stim300.records import SensorRecord  # noqa: E402
from stim300.special import Configuration, encode_special  # noqa: E402
from stim300.stream import StreamParser  # noqa: E402

RATE_HZ = 2000
PER_FEED = 8  # datagrams settled per feed at 2000 Hz with the reader's 4 ms pause
PACE = 4  # times real time


def stream(seconds: float) -> tuple[bytes, list[bytes]]:
    config = Configuration.build(sample_rate_hz=RATE_HZ)
    fmt = config.format
    samples = exact_samples(int(seconds * RATE_HZ), fmt, fmt.datagram_id, np.random.default_rng(0))
    for cluster in ("gyro", "acc", "incl"):
        samples["status_" + cluster] = 0
    frames = encode_samples(samples, fmt.datagram_id, fmt, crlf=False)
    return encode_special(config, crlf=False), [frames[i:i + PER_FEED].tobytes()
                                                for i in range(0, len(frames), PER_FEED)]


def drain(path: Path, stop: threading.Event) -> None:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    while not stop.is_set():
        if select.select([fd], [], [], 0.05)[0]:
            os.read(fd, 1 << 16)
    os.close(fd)


def timed(tap, head: bytes, feeds: list[bytes]) -> float:
    """Thread CPU seconds to parse (and tap) the feeds, at PACE times real time so the links'
    readers keep up (a pty that drops is cheaper to write)."""
    parser = StreamParser(tap=tap)
    parser.feed(head)
    cpu_s = 0.0
    for data in feeds:
        start = time.thread_time()
        parser.feed(data)
        cpu_s += time.thread_time() - start
        time.sleep(PER_FEED / RATE_HZ / PACE)
    return cpu_s


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    head, feeds = stream(args.seconds)
    estimates = {f"{c}_bias_{a}": Estimate(0.5, 0.1, u) for c, u in
                 (("gyro", "deg/h"), ("acc", "mg"), ("incl", "mg")) for a in "xyz"}
    result = CalibrationResult("joint", {}, estimates, sensor=SensorRecord(sample_rate_hz=RATE_HZ))
    with tempfile.TemporaryDirectory() as tmp:
        raw = RawPty(Path(tmp) / "raw", forward=lambda request: None)
        corrected = CorrectedPty(Path(tmp) / "corrected")
        corrected.set_result(result)
        stop = threading.Event()
        drains = [threading.Thread(target=drain, args=(Path(tmp) / name, stop)) for name in ("raw", "corrected")]
        for thread in drains:
            thread.start()
        try:
            costs = {name: min(timed(tap, head, feeds) for _ in range(args.repeats)) / args.seconds
                     for name, tap in (("parser alone", None), ("parser + raw tap", raw.tap),
                                       ("parser + corrected tap", corrected.tap))}
        finally:
            stop.set()
            for thread in drains:
                thread.join()
            raw.close()
            corrected.close()
    for name, cost in costs.items():
        print(f"{name:24s} {1000 * cost:6.1f} ms per s of {RATE_HZ} Hz data ({100 * cost:.1f} % of a core)")
    base = costs["parser alone"]
    print(f"raw tap {1000 * (costs['parser + raw tap'] - base):.1f} ms/s, corrected tap "
          f"{1000 * (costs['parser + corrected tap'] - base):.1f} ms/s; dropped: raw {raw.dropped_bytes} B, "
          f"corrected {corrected.dropped_bytes} B")
    return 0


if __name__ == "__main__":
    sys.exit(main())

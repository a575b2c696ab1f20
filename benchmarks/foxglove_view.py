"""Cost of the Foxglove view per second of 2000 Hz data, against the port reader's parsing of
the same data measured in the same run.

The reader thread feeds its parser about every 4 ms, so at 2000 Hz each read settles about 8
datagrams. This parses 10 s of 0xA7 datagrams (rate, acceleration, inclination) that way (the
baseline), then hands the samples to a view as the feeds thread does (the reads of each TICK_S
together, with a correction, so raw and corrected), first with no client connected, then with a
client subscribed to both IMU channels and reading everything, at 4 times real time. It prints
the calling thread's CPU time per second of data for each (the best of --repeats runs), their
ratios to the parser's, a no-client call's cost alone, the messages the client got and the
machine's load.

    python benchmarks/foxglove_view.py [--seconds 10] [--repeats 3] [--rate-hz 100]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
import timeit
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from websockets.sync.client import connect  # noqa: E402

from calibd.correction import ServedCorrection  # noqa: E402
from calibd.results import CalibrationResult, Estimate  # noqa: E402
from calibd.serve.feeds import TICK_S, FeedBatch  # noqa: E402
from calibd.serve.foxglove import IMU_TOPICS, FoxgloveView  # noqa: E402
from pty_tap import PACE, PER_FEED, RATE_HZ, stream  # noqa: E402  (the same stream and reads)
from stim300.capture import StreamInfo, stream_info  # noqa: E402
from stim300.stream import StreamParser  # noqa: E402

T0_NS = 1_800_000_000_000_000_000


def parsed(head: bytes, feeds: list[bytes]) -> tuple[float, list[np.ndarray], StreamInfo]:
    """Thread CPU seconds to parse the feeds, each feed's samples and the stream's record."""
    parser = StreamParser()
    parser.feed(head)
    cpu_s, reads = 0.0, []
    for data in feeds:
        start = time.thread_time()
        reads.append(parser.feed(data))
        cpu_s += time.thread_time() - start
    return cpu_s, reads, stream_info(parser)


def batches(reads: list[np.ndarray], info: StreamInfo) -> list[FeedBatch]:
    """The reads as the feeds thread hands them over: those of each TICK_S together, stamped, with
    a correction."""
    estimates = {f"{c}_bias_{a}": Estimate(0.5, 0.1, u) for c, u in
                 (("gyro", "deg/h"), ("acc", "mg"), ("incl", "mg")) for a in "xyz"}
    bias = {cluster: np.full(3, 1e-4, np.float32) for cluster in ("gyro", "acc", "incl")}
    correction = ServedCorrection(CalibrationResult("joint", {}, estimates), bias)
    per_tick = max(1, round(TICK_S * RATE_HZ / PER_FEED))
    ticks = [np.concatenate(reads[i:i + per_tick]) for i in range(0, len(reads), per_tick)]
    ends = np.cumsum([len(samples) for samples in ticks])
    return [FeedBatch(samples, T0_NS + np.arange(end - len(samples), end) * (1_000_000_000 // RATE_HZ), correction,
                      info) for samples, end in zip(ticks, ends)]


def viewed(view: FoxgloveView, fed: list[FeedBatch]) -> float:
    """Thread CPU seconds to hand the batches to the view, paced."""
    cpu_s = 0.0
    for batch in fed:
        start = time.thread_time()
        view.samples(batch)
        cpu_s += time.thread_time() - start
        time.sleep(len(batch.samples) / RATE_HZ / PACE)
    return cpu_s


def watch(port: int, ready: threading.Event, stop: threading.Event, got: list[int]) -> None:
    """A client subscribed to both IMU channels, reading every message until `stop`."""
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
        channels = {}
        while len(channels) < len(IMU_TOPICS):
            message = json.loads(ws.recv())
            channels |= {c["topic"]: c["id"] for c in message.get("channels", ()) if c["topic"] in IMU_TOPICS.values()}
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": channel_id}
                                                                 for i, channel_id in enumerate(channels.values())]}))
        ready.set()
        while not stop.is_set():
            try:
                frame = ws.recv(timeout=0.1)
            except TimeoutError:
                continue
            got[0] += isinstance(frame, bytes)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    args = parser.parse_args()
    head, feeds = stream(args.seconds)
    base = min(parsed(head, feeds)[0] for _ in range(args.repeats)) / args.seconds
    fed = batches(*parsed(head, feeds)[1:])
    view = FoxgloveView(port=0, rate_hz=args.rate_hz)
    try:
        idle = min(viewed(view, fed) for _ in range(args.repeats)) / args.seconds
        call_s = min(timeit.repeat(lambda: view.samples(fed[0]), number=10000, repeat=args.repeats)) / 10000
        ready, stop, got = threading.Event(), threading.Event(), [0]
        client = threading.Thread(target=watch, args=(view.port, ready, stop, got))
        client.start()
        ready.wait(10)
        while not all(view.watching(topic) for topic in IMU_TOPICS.values()):
            time.sleep(0.01)
        watched = min(viewed(view, fed) for _ in range(args.repeats)) / args.seconds
        time.sleep(0.5)
        stop.set()
        client.join()
    finally:
        view.close()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"load average {load} on {os.cpu_count()} cores; {args.seconds:g} s of {RATE_HZ} Hz data in reads of "
          f"{PER_FEED}, best of {args.repeats}, display rate {args.rate_hz:g} Hz")
    for name, cost in (("parser alone (baseline)", base), ("view, no client", idle),
                       ("view, one client watching raw and corrected", watched)):
        print(f"{name:45s} {1000 * cost:7.2f} ms per s of data ({100 * cost:.2f} % of a core, "
              f"{cost / base:.3f}x the parser)")
    print(f"one call with no client, back to back: {1e6 * call_s:.2f} us")
    expected = 2 * args.repeats * args.seconds * min(args.rate_hz, RATE_HZ)
    print(f"messages the client got: {got[0]} of about {expected:.0f} sent")
    return 0


if __name__ == "__main__":
    sys.exit(main())

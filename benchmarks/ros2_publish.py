"""What publishing sensor_msgs/Imu costs: calibd.ros2's batch encoding (one numpy step per batch,
each sample written as prepared bytes) against building each message as a cyclonedds struct and
writing it (the struct's own serialize), side by side in one run, to a subscriber in another
process (so every sample goes out over UDP on loopback).

Printed: for each way, the publishing thread's CPU time per message (µs) and the messages per
second of CPU that gives, for the encoding alone and for encoding and writing; the ratio of the
two ways; what the subscriber received; the load average. At 2000 Hz on two topics (raw and
corrected), a cost of C µs per message is 0.4 * C % of a core.
Target: publishing both topics at most 3 % of a core (C <= 7.5 µs).

    python benchmarks/ros2_publish.py [--messages 40000] [--batch 20]
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import time

import numpy as np

# DDS on loopback only, unicast discovery: the benchmark never sends to another host.
LOOPBACK = ("<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/></Interfaces>"
            "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
            "<Peers><Peer address='127.0.0.1'/></Peers></Discovery></Domain></CycloneDDS>")
os.environ["CYCLONEDDS_URI"] = LOOPBACK

from cyclonedds.core import Qos  # noqa: E402  (after the configuration above)
from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.pub import DataWriter  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

from calibd.ros2 import wire  # noqa: E402
from stim300.rosimu import ImuEncoder  # noqa: E402

FRAME_ID = "stim300_link"
TARGET_US = 7.5
SUBSCRIBER = """
import sys, time
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.core import Policy, Qos
from calibd.ros2 import wire
participant = DomainParticipant(int(sys.argv[1]))
qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(100000))  # keeps a burst to count it
readers = [DataReader(participant, Topic(participant, name, wire.Imu), qos) for name in sys.argv[2:]]
print("ready", flush=True)
counts = [0] * len(readers)
import select
while not select.select([sys.stdin], [], [], 0.005)[0]:
    for i, reader in enumerate(readers):
        counts[i] += len(reader.take(N=1000))
for i, reader in enumerate(readers):
    counts[i] += len(reader.take(N=100000))
print(" ".join(map(str, counts)), flush=True)
"""


def batches(messages: int, batch: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(stamps ns, gyro rad/s, acc m/s^2) of a 2000 Hz stream, `batch` samples at a time."""
    rng = np.random.default_rng(0)
    return [(1_750_000_000_000_000_000 + (start + np.arange(batch)) * 500_000,
             rng.normal(0, 0.01, (batch, 3)), rng.normal((0, 0, 9.8), 0.01, (batch, 3)))
            for start in range(0, messages, batch)]


COV = list(np.diag([1e-8] * 3).ravel())


def structs(stamps, gyro, acc) -> list:
    """The messages as cyclonedds structs, one object tree each."""
    return [wire.Imu(wire.header(int(t), FRAME_ID), wire.Quaternion(0.0, 0.0, 0.0, 1.0), [-1.0] + [0.0] * 8,
                     wire.Vector3(*g), COV, wire.Vector3(*a), COV)
            for t, g, a in zip(stamps.tolist(), gyro.tolist(), acc.tolist())]


def per_message_us(stream: list, step) -> float:
    """CPU time of this thread per message (µs) for `step` run over every batch of `stream`."""
    start = time.thread_time()
    for stamps, gyro, acc in stream:
        step(stamps, gyro, acc)
    return (time.thread_time() - start) / sum(len(stamps) for stamps, _, _ in stream) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=40000)
    parser.add_argument("--batch", type=int, default=20, help="samples per call (20: 10 ms at 2000 Hz)")
    args = parser.parse_args()
    domain = random.randint(1, 200)
    names = ["rt/bench/imu_batch", "rt/bench/imu_struct"]
    child = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(domain), *names], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline() == "ready\n"
    publisher = wire.Publisher(domain, {"imu": names[0].removeprefix("rt/")}, FRAME_ID)
    participant = DomainParticipant(domain)
    struct_writer = DataWriter(participant, Topic(participant, names[1], wire.Imu), Qos(*wire.SENSOR_QOS))
    time.sleep(1.0)  # discovery: both writers matched with the subscriber before the first sample

    encoder = ImuEncoder(FRAME_ID)
    stream = batches(args.messages, args.batch)
    ways = {
        "encode, numpy batch": lambda s, g, a: encoder.encode(s, g, a, COV, COV),
        "encode, struct serialize": lambda s, g, a: [m.serialize() for m in structs(s, g, a)],
        "encode + write, Publisher.imu": lambda s, g, a: publisher.imu("imu", s, g, a, COV, COV),
        "encode + write, struct": lambda s, g, a: [struct_writer.write(m) for m in structs(s, g, a)],
    }
    rows = {name: per_message_us(stream, step) for name, step in ways.items()}
    time.sleep(0.5)
    received, _ = child.communicate("done\n", timeout=60)
    publisher.close()

    print(f"{args.messages} Imu messages ({len(encoder.encode(*stream[0], COV, COV)[0])} bytes each), "
          f"batches of {args.batch}, publishing thread CPU time:")
    for name, us in rows.items():
        print(f"  {name:32s} {us:7.2f} µs/message  {1e6 / us:10.0f} messages/s of CPU")
    print(f"ratio struct / batch: encode {rows['encode, struct serialize'] / rows['encode, numpy batch']:.1f}x, "
          f"encode + write {rows['encode + write, struct'] / rows['encode + write, Publisher.imu']:.1f}x")
    cost = rows["encode + write, Publisher.imu"]
    print(f"2000 Hz on two topics: {0.4 * cost:.2f} % of a core (target {0.4 * TARGET_US:.0f} %: "
          f"{'met' if cost <= TARGET_US else 'NOT met'})")
    print(f"subscriber received (batch, struct): {received.strip()} of {len(stream) * args.batch} messages each "
          "(best effort, written as fast as the CPU goes: a burst far above 2000 Hz)")
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"load average (1, 5, 15 min): {load} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()

"""A ROS 2 subscriber of calibd's Imu topics for benchmarks/serve.py, in a process of its own so
its work never counts as the daemon's: it takes every sample of imu/data_raw and imu/data it
gets (best effort, as a ROS 2 sensor-data subscriber) and every result document of
imu/calibration (reliable, transient local, as a late ROS 2 subscriber of a latched topic), and
when its stdin closes writes the samples' stamps (ns), angular velocities and linear
accelerations, and the documents, to an NPZ file.

    python benchmarks/ros2_listen.py DOMAIN OUT.npz      (CYCLONEDDS_URI as the daemon's)
"""

from __future__ import annotations

import select
import sys

import numpy as np
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.internal import InvalidSample
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from calibd.ros2 import wire

TOPICS = {"raw": "rt/imu/data_raw", "corrected": "rt/imu/data"}
CALIBRATION = "rt/imu/calibration"


def main() -> int:
    participant = DomainParticipant(int(sys.argv[1]))
    qos = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(100_000))
    readers = {kind: DataReader(participant, Topic(participant, name, wire.Imu), qos) for kind, name in TOPICS.items()}
    latched = Qos(Policy.Reliability.Reliable(0), Policy.Durability.TransientLocal, Policy.History.KeepAll)
    results = DataReader(participant, Topic(participant, CALIBRATION, wire.String), latched)
    rows: dict[str, list] = {kind: [] for kind in TOPICS}
    documents: list[str] = []
    print("ready", flush=True)
    while True:
        done = bool(select.select([sys.stdin], [], [], 0.01)[0])
        for kind, reader in readers.items():
            for s in reader.take(N=100_000):
                if not isinstance(s, InvalidSample):
                    w, a = s.angular_velocity, s.linear_acceleration
                    rows[kind].append((s.header.stamp.sec * 10**9 + s.header.stamp.nanosec, w.x, w.y, w.z,
                                       a.x, a.y, a.z))
        documents += [s.data for s in results.take(N=100) if not isinstance(s, InvalidSample)]
        if done:
            break
    arrays = {kind: np.array(found, dtype=np.float64).reshape(-1, 7) for kind, found in rows.items()}
    np.savez(sys.argv[2], **{f"{kind}_stamp_ns": np.array([r[0] for r in rows[kind]], dtype=np.int64)
                             for kind in TOPICS}, **{f"{kind}_values": a[:, 1:] for kind, a in arrays.items()},
             documents=np.array(documents, dtype=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())

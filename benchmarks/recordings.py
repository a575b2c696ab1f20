"""What reading a recording costs: `calibd noise` on a 2000 Hz STIM300 capture against the same
samples recorded as sensor_msgs/Imu in a rosbag2 with SQLite3 storage, one with MCAP storage
(both read by rosbags), that one's MCAP file alone (read by the mcap package) and a ROS 1 bag
(read by calibd.bag1), each in a process of its own; beside them, the same samples loaded whole
from an NPZ file (numpy.load): reading into memory with nothing computed.

Printed for each: the wall time, the peak memory (the process's maximum RSS) and the time per
message, and the ratio to the raw capture's; and whether the noise table's gyro and accelerometer
figures are the raw capture's (a recording has no inclinometers). Targets (the recordings issue):
26.4 M messages (13,210 s) in <= 2 minutes and <= 1 GB; run with --seconds 13210 for that
(about 12 GB of disk for the recordings). The default, 600 s, is 1.2 M messages. A stream longer
than PIECE_S is one simulated piece repeated, its counter running on (the simulator holds at most
10 M samples): what is measured is the cost of reading, which does not care.

    python benchmarks/recordings.py [--seconds 600]
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

from live import ENV, capture_2000hz  # benchmarks/live.py: a simulated 2000 Hz stream

from calibd.frames import STANDARD_GRAVITY
from stim300.rosimu import ImuEncoder
from calibd.units import DEG
from stim300.bulk import decode_capture
from stim300.protocol import NORMAL_LAYOUTS

TOPIC = "/stim300/imu"
PIECE_S = 3600  # the longest stretch simulated at once
COUNTER_CYCLE = 256  # datagrams per counter cycle: a piece repeats whole cycles, so the counter runs on
BATCH = 100_000  # messages encoded and written at once


def long_capture(seconds: float) -> bytes:
    """A 2000 Hz capture `seconds` long: simulated (benchmarks/live.py), or for more than PIECE_S one
    piece's datagrams, cut to whole counter cycles, repeated after its power-up datagrams."""
    if seconds <= PIECE_S:
        return capture_2000hz(seconds)[0]
    piece = capture_2000hz(PIECE_S)[0]
    decoded = decode_capture(piece)
    fmt = decoded.info.format
    length = NORMAL_LAYOUTS[fmt.datagram_id].wire_length(fmt.crlf)
    start = len(piece) - len(decoded.samples) * length  # after the power-up datagrams (a fault-free piece)
    cycles = len(decoded.samples) // COUNTER_CYCLE * COUNTER_CYCLE
    wanted = round(seconds * fmt.sample_rate_hz)
    body = piece[start:start + cycles * length]
    return piece[:start] + (body * -(-wanted // cycles))[:wanted * length]


def write_rosbag2(path: Path, storage: str, stamps: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
    """The samples as sensor_msgs/Imu CDR (calibd's own encoder, the bytes rosbags' serialiser
    gives: tests/test_ros2_wire.py) in a rosbag2 directory, received 1 ms after their stamps."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    encoder = ImuEncoder("imu_link")
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        connection = writer.add_connection(TOPIC, "sensor_msgs/msg/Imu",
                                           typestore=get_typestore(Stores.ROS2_JAZZY))
        for lo in range(0, len(stamps), BATCH):
            part = slice(lo, lo + BATCH)
            messages = encoder.encode(stamps[part], gyro[part], acc[part], [0.0] * 9, [0.0] * 9)
            for when, message in zip((stamps[part] + 1_000_000).tolist(), messages):
                writer.write(connection, when, message)


def ros1_messages(stamps: np.ndarray, gyro: np.ndarray, acc: np.ndarray, frame_id: bytes = b"imu_link") -> np.ndarray:
    """The samples as ROS 1 sensor_msgs/Imu, one row of bytes each, built with numpy: seq 0, the
    stamp, the frame id, then 37 float64 (orientation, angular velocity, linear acceleration, each
    with its covariance), packed."""
    n, head = len(stamps), 16 + len(frame_id)
    out = np.zeros((n, head + 37 * 8), np.uint8)
    out[:, 4:8] = (stamps // 10**9).astype("<u4").view(np.uint8).reshape(n, 4)
    out[:, 8:12] = (stamps % 10**9).astype("<u4").view(np.uint8).reshape(n, 4)
    out[:, 12:16] = np.frombuffer(np.uint32(len(frame_id)).astype("<u4").tobytes(), np.uint8)
    out[:, 16:head] = np.frombuffer(frame_id, np.uint8)
    values = out[:, head:].view("<f8")
    values[:, 3], values[:, 4] = 1.0, -1.0  # w of the orientation; no orientation (REP 145)
    values[:, 13:16], values[:, 25:28] = gyro, acc
    return out


def write_bag(path: Path, stamps: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
    """The samples as a ROS 1 bag (rosbags' writer), received 1 ms after their stamps."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    with Writer(path) as writer:
        connection = writer.add_connection(TOPIC, "sensor_msgs/msg/Imu", typestore=get_typestore(Stores.ROS1_NOETIC))
        for lo in range(0, len(stamps), BATCH):
            part = slice(lo, lo + BATCH)
            for when, message in zip((stamps[part] + 1_000_000).tolist(), ros1_messages(stamps[part], gyro[part],
                                                                                        acc[part])):
                writer.write(connection, when, message.tobytes())


WRAPPER = ("import resource, subprocess, sys\n"
           "done = subprocess.run([sys.executable, *sys.argv[1:]], capture_output=True, text=True)\n"
           "sys.stdout.write(f'{resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}\\n' + done.stdout)\n"
           "sys.stderr.write(done.stderr)\n"
           "sys.exit(done.returncode)\n")
NPZ_READER = ("import numpy, sys\n"
              "with numpy.load(sys.argv[1]) as arrays:\n"
              "    print(sum(float(arrays[name].sum()) for name in arrays.files))\n")


def measured(argv: list[str]) -> tuple[float, float, str]:
    """`python ARGV` started by a small process that reports its maximum RSS (a child forked from
    this process would count this process's pages too): (wall s, peak RSS MB, its stdout)."""
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-c", WRAPPER, *argv], env=ENV, capture_output=True, text=True)
    wall = time.monotonic() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)}: {done.stderr.strip()}")
    peak_kb, out = done.stdout.split("\n", 1)
    return wall, int(peak_kb) / 1024, out


def noise(path: Path) -> tuple[float, float, str]:
    """`calibd noise PATH` in a process of its own: (wall s, peak RSS MB, its table)."""
    return measured(["-m", "calibd.cli", "noise", str(path)])


def figures(table: str) -> list[str]:
    """The noise table's gyro and accelerometer lines (a recording carries no inclinometers)."""
    return [line for line in table.splitlines() if line.startswith(("gyro", "acc"))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="length of the 2000 Hz stream (default 600 s)")
    args = ap.parse_args()
    print(f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} on {os.cpu_count()} cores")
    data = long_capture(args.seconds)
    samples = decode_capture(data).samples
    stamps = 1_790_000_000 * 10**9 + np.arange(len(samples), dtype=np.int64) * 500_000
    gyro, acc = samples["gyro"].astype(np.float64) * DEG, samples["acc"].astype(np.float64) * STANDARD_GRAVITY
    del samples
    print(f"{len(stamps):,} samples ({len(stamps) / 2000:.0f} s at 2000 Hz)")
    with tempfile.TemporaryDirectory() as tmp:
        inputs = {"raw capture": Path(tmp) / "capture.bin"}
        inputs["raw capture"].write_bytes(data)
        del data
        for storage in ("sqlite3", "mcap"):
            inputs[f"rosbag2 {storage}"] = Path(tmp) / f"imu_{storage}"
            started = time.monotonic()
            write_rosbag2(inputs[f"rosbag2 {storage}"], storage, stamps, gyro, acc)
            print(f"rosbag2 {storage} written in {time.monotonic() - started:.0f} s")
        inputs["plain MCAP"] = next(inputs["rosbag2 mcap"].glob("*.mcap"))  # its storage file alone: the mcap package
        inputs["ROS 1 bag"] = Path(tmp) / "imu.bag"
        started = time.monotonic()
        write_bag(inputs["ROS 1 bag"], stamps, gyro, acc)
        print(f"ROS 1 bag written in {time.monotonic() - started:.0f} s")
        runs = {name: noise(path) for name, path in inputs.items()}
        npz = Path(tmp) / "samples.npz"  # the floor: the same samples loaded whole from NPZ, nothing computed
        np.savez(npz, stamp_ns=stamps, gyro_rad_s=gyro, acc_m_s2=acc)
        npz_wall, npz_rss, _ = measured(["-c", NPZ_READER, str(npz)])
    raw_wall, raw_rss, raw_table = runs["raw capture"]
    for name, (wall, rss, table) in runs.items():
        same = figures(table) == figures(raw_table)
        print(f"{name:18s} {wall:7.1f} s ({wall / len(stamps) * 1e6:.2f} us a message, {wall / raw_wall:.2f}x the raw "
              f"capture), peak RSS {rss:.0f} MB ({rss / raw_rss:.2f}x); noise table "
              f"{'the same as the raw capture' if same else 'DIFFERENT'}")
    print(f"{'NPZ, loaded whole':18s} {npz_wall:7.1f} s ({npz_wall / len(stamps) * 1e6:.2f} us a message, "
          f"{npz_wall / raw_wall:.2f}x the raw capture), peak RSS {npz_rss:.0f} MB ({npz_rss / raw_rss:.2f}x): "
          "the same samples read into memory, no noise computed")
    at_target = 26.4e6 / len(stamps)
    for name, (wall, rss, _) in runs.items():
        print(f"{name}: at 26.4 M messages about {wall * at_target:.0f} s (target <= 120 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`calibd batch` on 100 captures: one worker process against two, on this machine.

Target (fleet issue): `--workers 2` at least 1.7x faster than `--workers 1` (the serial run:
the same code, one capture after another) on this 2-core machine, the two tables identical row
for row, and the peak memory of any one process of the batch (the driver or a worker: the
largest resident set of the command's process tree, from wait4) at most 500 MB for these 125 Hz
captures. The captures (the continuous-rotation scenario, 9 minutes at 125 Hz, each with its
own seed, three serial numbers) are simulated once and cached. The machine's load average is
printed before and after: other work on the two cores lowers the ratio.

    python benchmarks/batch.py [--captures 100] [--cache DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from calibd.fleettable import read_rows
from calibd.scenario import load_scenario
from calibd.sim import write_capture

from long_capture import run  # one child's wall time and peak RSS (its process tree's largest)

SPEED_TARGET = 1.7
PEAK_TARGET_MB = 500
SITE = ["--latitude", "40.59129", "--g0", "9.79956"]  # the continuous scenario's site
SERIALS = ("N25582405009001", "N25582405009002", "N25582405009003")


def captures(cache: Path, count: int) -> Path:
    """`count` simulated captures in a folder of the cache (made the first time)."""
    folder = cache / f"batch-{count}"
    folder.mkdir(parents=True, exist_ok=True)
    base = load_scenario("continuous")
    for k in range(count):
        path = folder / f"capture-{k:03d}.bin"
        if not path.exists():
            serial = SERIALS[k % len(SERIALS)]
            write_capture(replace(base, name=path.stem, seed=5000 + k,
                                  sensor=replace(base.sensor, serial_number=serial)), path)
    return folder


def batch(folder: Path, table: Path, workers: int) -> tuple[float, float]:
    """Wall time (s) and peak RSS (MB) of one `calibd batch` into a new table."""
    table.unlink(missing_ok=True)
    wall, peak_mb, code, _ = run([sys.executable, "-m", "calibd.cli", "batch", str(folder), "-o", str(table),
                                  "--workers", str(workers), *SITE])
    if code:
        raise SystemExit(f"calibd batch --workers {workers} failed with exit status {code}")
    return wall, peak_mb


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=int, default=100)
    parser.add_argument("--cache", default=Path(tempfile.gettempdir()) / "calibd-benchmarks", type=Path)
    args = parser.parse_args()
    folder = captures(args.cache, args.captures)
    print(f"{args.captures} captures in {folder}; load average {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as out:
        serial_s, serial_mb = batch(folder, Path(out) / "one.parquet", 1)
        print(f"--workers 1: {serial_s:.1f} s, peak {serial_mb:.0f} MB")
        parallel_s, parallel_mb = batch(folder, Path(out) / "two.parquet", 2)
        print(f"--workers 2: {parallel_s:.1f} s, peak {parallel_mb:.0f} MB")
        one, two = read_rows(Path(out) / "one.parquet"), read_rows(Path(out) / "two.parquet")
    same = one == two and len(one) == args.captures and all(r["status"] == "ok" for r in one)
    ratio = serial_s / parallel_s
    peak = max(serial_mb, parallel_mb)
    print(f"load average after {os.getloadavg()[0]:.2f}")
    print(f"speed-up {ratio:.2f}x (target >= {SPEED_TARGET}x): {'met' if ratio >= SPEED_TARGET else 'NOT met'}")
    print(f"peak memory of a process {peak:.0f} MB (target <= {PEAK_TARGET_MB} MB): "
          f"{'met' if peak <= PEAK_TARGET_MB else 'NOT met'}")
    print(f"tables identical, {len(one)} rows, every capture calibrated: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())

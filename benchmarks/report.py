"""`calibd report` against `calibd calibrate` in CPU time, on the same capture in the same run.

Target: the report (PNG figures, the default) costs at most 2x the CPU of the calibration it
reports on; `report --svg` (each figure's vector copy as well) is shown for information. The
capture is README's quick start's (the shipped thesis session); the result the reports read is
made by the first `calibd calibrate` of the run. CPU is user + system time of each child process
(from wait4), the median of ROUNDS rounds that run the commands in turn, so a change of the
machine's load reaches all of them alike. OpenBLAS's worker threads spin while they wait, and more
so on a loaded machine: that inflates calibrate's CPU (its joint fit is most of it) more than the
report's (matplotlib is single-threaded) and flatters the ratio. `OPENBLAS_NUM_THREADS=1` gives a
ratio that does not depend on the load; the run prints the setting it had.

    [OPENBLAS_NUM_THREADS=1] python benchmarks/report.py [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

from startup import cpu_s  # benchmarks/startup.py: one child's user + system CPU

ROOT = Path(__file__).resolve().parent.parent
CAPTURE = ROOT / "fixtures" / "thesis_real_cw_125hz.bin"
SITE = ["--latitude", "40.59129", "--g0", "9.79956"]  # the thesis's, as in README's quick start
TARGET_RATIO = 2.0


def load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg()) + " (1, 5, 15 min)"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    calibd = [sys.executable, "-m", "calibd.cli"]
    print(f"capture: {CAPTURE.relative_to(ROOT)} ({CAPTURE.stat().st_size / 1e6:.1f} MB); OPENBLAS_NUM_THREADS "
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; {load()} before")
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        commands = {"calibd calibrate": calibd + ["calibrate", str(CAPTURE), *SITE, "-o", str(result)],
                    "calibd report": calibd + ["report", str(result), str(CAPTURE), "-o", f"{tmp}/png.html"],
                    "calibd report --svg": calibd + ["report", str(result), str(CAPTURE), "-o", f"{tmp}/svg.html",
                                                     "--svg"]}
        times = {name: [] for name in commands}
        for _ in range(args.rounds):
            for name, argv in commands.items():  # calibrate first: the reports read its result
                times[name].append(cpu_s(argv))
    median = {name: statistics.median(t) for name, t in times.items()}
    for name, t in times.items():
        print(f"{name:20s} median {median[name]:6.2f} s CPU  (runs: {', '.join(f'{x:.2f} s' for x in t)})")
    ratio = median["calibd report"] / median["calibd calibrate"]
    print(f"report / calibrate: {ratio:.2f}x CPU (target <= {TARGET_RATIO:g}x: "
          f"{'met' if ratio <= TARGET_RATIO else 'NOT met'}); report --svg / calibrate: "
          f"{median['calibd report --svg'] / median['calibd calibrate']:.2f}x (for information)")
    print(f"{load()} after")
    return 0 if ratio <= TARGET_RATIO else 1


if __name__ == "__main__":
    sys.exit(main())

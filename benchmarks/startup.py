"""Start-up cost of the command lines: the CPU time (user + sys) of `calibd --version`, `calibd
status` and `stim300 --version` against `python -c "import numpy"`, measured in the same run.

Targets: `calibd --version` and `calibd status --state-dir DIR` each at most 2x the baseline's
CPU time (a command that does no calibration should cost about what numpy's import costs).
Printed for information: `stim300 --version`, the driver's command line, which never loads scipy,
and `calibd calibrate` on the shipped fixture (README's quick start), which pays for the methods
and scipy it uses.

Each round runs every command once, in turn, so a change of the machine's load touches all of
them alike; the medians of the rounds are compared. The CPU time is the child's own, from wait4.

    python benchmarks/startup.py [--runs 9]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from calibd.daemon import State
from calibd.results import load_result
from calibd.statedir import ResultStore

ROOT = Path(__file__).resolve().parent.parent
FIXTURE = ROOT / "fixtures" / "thesis_real_cw_125hz.bin"
SITE = ["--latitude", "40.59129", "--g0", "9.79956"]
TARGET_RATIO = 2.0
BASELINE = "python -c 'import numpy'"


def program(name: str) -> list[str]:
    """The installed console script beside this interpreter, else the package run as a module."""
    script = Path(sys.executable).parent / name
    return [str(script)] if script.exists() else [sys.executable, "-m", name]


def cpu_s(argv: list[str]) -> float:
    """User + system CPU time of one run of `argv`, in s; a failed run stops the benchmark."""
    child = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT,
                             env=os.environ | {"PYTHONPATH": str(ROOT)})
    err = child.stderr.read()
    _, status, usage = os.wait4(child.pid, 0)
    if os.waitstatus_to_exitcode(status):
        sys.exit(f"{' '.join(argv)} failed: {err.decode().strip()}")
    return usage.ru_utime + usage.ru_stime


def state_dir(directory: Path, result_file: Path) -> Path:
    """A daemon's state directory holding a solved state and the fixture's result."""
    store = ResultStore(directory)
    store.on_result(load_result(result_file))
    store.on_state(State.SOLVED, "solved: the fixture's result")
    return directory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=9, help="rounds of every command (default 9)")
    args = parser.parse_args()
    calibd, stim300 = program("calibd"), program("stim300")
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        calibrate = [*calibd, "calibrate", str(FIXTURE), *SITE, "-o", str(result)]
        cpu_s(calibrate)  # warms the caches, and writes the result the state directory holds
        commands = {  # name -> (argv, target ratio or None)
            BASELINE: ([sys.executable, "-c", "import numpy"], None),
            "calibd --version": ([*calibd, "--version"], TARGET_RATIO),
            "calibd status --state-dir DIR": ([*calibd, "status", "--state-dir",
                                               str(state_dir(Path(tmp) / "state", result))], TARGET_RATIO),
            "stim300 --version": ([*stim300, "--version"], None),
            "calibd calibrate (fixture)": (calibrate, None),
        }
        load_before = os.getloadavg()
        times = {name: [] for name in commands}
        for _ in range(args.runs):
            for name, (argv, _) in commands.items():
                times[name].append(cpu_s(argv))
        load_after = os.getloadavg()
    medians = {name: statistics.median(runs) for name, runs in times.items()}
    baseline = medians[BASELINE]
    print(f"CPU time (user + sys), median of {args.runs} interleaved runs; load average (1, 5, 15 min) "
          f"{' '.join(f'{x:.2f}' for x in load_before)} before, {' '.join(f'{x:.2f}' for x in load_after)} after, "
          f"{os.cpu_count()} CPUs")
    print(f"{'command':32} {'CPU s':>7} {'x numpy':>8}  target")
    failed = False
    for name, (_, target) in commands.items():
        ratio = medians[name] / baseline
        verdict = ("baseline" if name == BASELINE else "for information" if target is None
                   else f"<= {target:g}x: {'met' if ratio <= target else 'MISSED'}")
        failed |= target is not None and ratio > target
        print(f"{name:32} {medians[name]:7.3f} {ratio:7.2f}x  {verdict}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()

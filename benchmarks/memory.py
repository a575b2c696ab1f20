"""Peak memory of `calibd calibrate` against session length, at 125 Hz.

The thesis real-case campaign with every static stretched by the same factor, so the session
lasts 19 minutes (the thesis's own), 75 minutes and 2 hours; each capture is calibrated in a
child process whose peak RSS is read from its own rusage. Baseline, measured in the same run:
`calibd --version` (the interpreter and the imports). Printed: the peak of each, the growth per
hour of session beyond the shortest, and the target (flat in session length: <= 300 MB for a
2-hour 125 Hz session). The captures are simulated once and cached.

    python benchmarks/memory.py [--cache DIR] [--minutes 19 75 120]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from calibd.scenario import load_scenario
from calibd.sim import schedule, write_capture

from long_capture import run  # one child's wall time and peak RSS

PEAK_TARGET_MB = 300
LATITUDE = "40.59129"


def scenario(minutes: float):
    """thesis-real at 125 Hz with its statics stretched evenly to last `minutes` in all."""
    base = load_scenario("thesis-real")
    total_s = schedule(base)[-1].end_s
    statics_s = sum(s.duration_s for s in base.segments if s.kind == "static")
    factor = (minutes * 60 - (total_s - statics_s)) / statics_s
    segments = tuple(replace(s, duration_s=s.duration_s * factor) if s.kind == "static" else s
                     for s in base.segments)
    return replace(base, name=f"memory-{minutes:g}min", segments=segments)


def capture_path(cache: Path, minutes: float) -> Path:
    path = cache / f"memory_{minutes:g}min_125hz.bin"
    if not path.exists():
        started = time.perf_counter()
        write_capture(scenario(minutes), path)
        print(f"simulated {path} ({path.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - started:.0f} s")
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default=Path(tempfile.gettempdir()) / "calibd-benchmarks", type=Path)
    parser.add_argument("--minutes", type=float, nargs="+", default=[19, 75, 120])
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    _, floor_mb, _, _ = run([sys.executable, "-m", "calibd.cli", "--version"])
    print(f"load average {os.getloadavg()[0]:.2f}; baseline `calibd --version`: {floor_mb:.0f} MB peak")
    peaks = []
    for minutes in sorted(args.minutes):
        path = capture_path(args.cache, minutes)
        out = Path(tempfile.mkdtemp()) / "result.json"
        wall_s, peak_mb, code, _ = run([sys.executable, "-m", "calibd.cli", "calibrate", str(path), "--latitude",
                                        LATITUDE, "-o", str(out)])
        if code != 0:
            print(f"calibrate failed on {path} (exit {code})")
            return 1
        peaks.append((minutes, peak_mb))
        print(f"{minutes:6.0f} min session: calibrate peak {peak_mb:6.0f} MB ({peak_mb / floor_mb:.1f}x the "
              f"baseline), {wall_s:.1f} s wall")
    (m0, p0), (m1, p1) = peaks[0], peaks[-1]
    if m1 > m0:
        per_sample_kb = (p1 - p0) * 1024 / ((m1 - m0) * 60 * 125)
        print(f"growth: {(p1 - p0) / ((m1 - m0) / 60):.0f} MB per hour of session ({per_sample_kb:.2f} kB per 125 Hz "
              "sample)")
    print(f"{m1:.0f} min: {p1:.0f} MB (target <= {PEAK_TARGET_MB} MB at 120 min: "
          f"{'met' if p1 <= PEAK_TARGET_MB or m1 < 120 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

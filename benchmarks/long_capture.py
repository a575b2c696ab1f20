"""A one-hour 2000 Hz capture: `calibd calibrate` against `stim300 info` in wall time and peak memory,
and the block-averaged session's estimates against a full-rate session's.

Targets: calibrate's peak RSS <= 500 MB and wall time <= 3x `stim300 info` on the same file; the
estimates from the 125 Hz block means (what calibrate keeps) within 0.1 sigma of those from every
2000 Hz sample. The capture (the thesis real-case campaign with its level static stretched to make
an hour, 0xA7 at 2000 Hz) is simulated once and cached under the temporary directory.

    python benchmarks/long_capture.py [--cache DIR] [--skip-full-rate]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibd.methods.joint import joint_real_case
from calibd.frames import STANDARD_GRAVITY
from calibd.scenario import load_scenario
from calibd.session import Session
from calibd.sim import schedule, write_capture
from calibd.units import DEG
from stim300.bulk import decode_capture
from stim300.clock import counter_times
from stim300.records import SensorRecord
from calibd.results import ResultStream

RATE_HZ = 2000
DURATION_S = 3600.0
PEAK_TARGET_MB = 500
WALL_TARGET_RATIO = 3.0
AGREE_TARGET_SIGMA = 0.1
ROOT = Path(__file__).resolve().parent.parent
GNU_TIME = "/usr/bin/time"


def scenario():
    """thesis-real at 2000 Hz, its level static long enough for the whole to last an hour."""
    base = load_scenario("thesis-real")
    base = replace(base, name="long-capture-2000hz", sensor=replace(base.sensor, sample_rate_hz=RATE_HZ))
    rest_s = schedule(base)[-1].end_s - base.segments[0].duration_s
    level = replace(base.segments[0], duration_s=round(DURATION_S - rest_s))
    return replace(base, segments=(level,) + base.segments[1:])


def capture_path(cache: Path) -> Path:
    path = cache / "long_capture_2000hz.bin"
    if not path.exists():
        started = time.perf_counter()
        write_capture(scenario(), path)
        print(f"simulated {path} ({path.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - started:.0f} s")
    return path


def run(argv: list[str]) -> tuple[float, float, int, bytes]:
    """(wall time in s, peak RSS in MB, exit code, stdout) of one child process, its peak as GNU
    time reports it (`/usr/bin/time -f %M`, from its own wait4). Not this process's wait4: Python
    starts children with vfork, and a vforked child's peak RSS starts at the parent's peak (the
    kernel keeps the larger across exec), so a benchmark holding 100 MB would read 100 MB for any
    child; GNU time is a small process that forks the command itself."""
    if not os.access(GNU_TIME, os.X_OK):
        raise SystemExit(f"{GNU_TIME} (GNU time) is needed to read a child's peak memory: apt install time")
    started = time.perf_counter()
    with tempfile.NamedTemporaryFile("r") as peak:
        child = subprocess.run([GNU_TIME, "-f", "%M", "-o", peak.name, *argv], stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, cwd=ROOT, env=os.environ | {"PYTHONPATH": str(ROOT)})
        kb = float(peak.read().strip().splitlines()[-1])
    return time.perf_counter() - started, kb / 1024, child.returncode, child.stdout


def full_rate_session(path: Path) -> Session:
    """The last power-up at every sample, float64, without block averaging."""
    capture = decode_capture(path.read_bytes())  # a capture of one power-up
    s, rate_hz = capture.samples, capture.info.rate_hz
    times = counter_times(s["counter"], rate_hz, s["t_host"])
    return Session(time_s=times.time_s, gyro=s["gyro"].astype(np.float64) * DEG,
                   acc=s["acc"].astype(np.float64) * STANDARD_GRAVITY,
                   incl=s["incl"].astype(np.float64) * STANDARD_GRAVITY, temperature_c=None,
                   rate_hz=rate_hz, sensor=SensorRecord(), stream=ResultStream(capture=str(path)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default=Path(tempfile.gettempdir()) / "calibd-benchmarks", type=Path)
    parser.add_argument("--skip-full-rate", action="store_true", help="no in-process full-rate comparison")
    args = parser.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    path = capture_path(args.cache)
    sc = scenario()
    result_path = args.cache / "long_capture_result.json"
    info_s, info_mb, info_code, _ = run([sys.executable, "-m", "stim300.cli", "info", str(path)])
    cal_s, cal_mb, cal_code, _ = run([sys.executable, "-m", "calibd.cli", "calibrate", str(path), "--start", "0",
                                       "--latitude", str(sc.site.latitude_deg), "--g0", str(sc.site.g0),
                                       "-o", str(result_path)])
    if info_code or cal_code:
        print(f"failed: stim300 info exit {info_code}, calibd calibrate exit {cal_code}")
        return 1
    ratio = cal_s / info_s
    print(f"capture: {path.stat().st_size / 1e6:.0f} MB, {DURATION_S:.0f} s at {RATE_HZ} Hz")
    print(f"stim300 info      {info_s:7.1f} s  peak {info_mb:6.0f} MB")
    print(f"calibd calibrate  {cal_s:7.1f} s  peak {cal_mb:6.0f} MB  (target {PEAK_TARGET_MB} MB: "
          f"{'met' if cal_mb <= PEAK_TARGET_MB else 'NOT met'})")
    print(f"wall ratio calibrate/info {ratio:.2f} (target <= {WALL_TARGET_RATIO:g}: "
          f"{'met' if ratio <= WALL_TARGET_RATIO else 'NOT met'})")
    if args.skip_full_rate:
        return 0
    averaged = json.loads(result_path.read_text())["estimates"]
    started = time.perf_counter()
    full = joint_real_case(full_rate_session(path), sc.site).estimates
    print(f"full-rate joint fit in-process: {time.perf_counter() - started:.0f} s")
    worst = 0.0
    for name, e in full.items():
        z = (averaged[name]["value"] - e.value) / e.sigma
        worst = max(worst, abs(z))
        print(f"  {name:12s} 125 Hz {averaged[name]['value']:12.5f}  2000 Hz {e.value:12.5f} +- "
              f"{e.sigma:.3g} {e.unit}  difference {z:+.3f} sigma")
    print(f"largest difference {worst:.3f} sigma (target <= {AGREE_TARGET_SIGMA:g}: "
          f"{'met' if worst <= AGREE_TARGET_SIGMA else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Simulator speed: a 25-minute 125 Hz thesis-like session, against real time.

Target (simulator issue): a few seconds. Prints the time to simulate the samples and to encode
them to bytes, and the ratio to the session's own duration, all measured in this run.

    python benchmarks/simulate.py [--minutes 25] [--rate 125]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

from calibd.scenario import Segment, load_scenario
from calibd.sim import capture_bytes, schedule, simulate


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=25.0)
    ap.add_argument("--rate", type=int, default=125, choices=(125, 250, 500, 1000, 2000))
    args = ap.parse_args()
    base = load_scenario("thesis-real")
    extra = args.minutes * 60 - schedule(base)[-1].end_s  # a longer level static fills the session
    segments = (Segment("static", duration_s=max(extra, 1.0)),) + base.segments
    scenario = replace(base, segments=segments, sensor=replace(base.sensor, sample_rate_hz=args.rate))
    t = time.perf_counter()
    sim = simulate(scenario)
    t_sim = time.perf_counter() - t
    t = time.perf_counter()
    data, _ = capture_bytes(sim)
    t_bytes = time.perf_counter() - t
    session = float(sim.time_s[-1])
    total = t_sim + t_bytes
    print(f"session {session / 60:.1f} min at {args.rate} Hz: {len(sim.samples)} samples, {len(data) / 1e6:.1f} MB")
    print(f"simulate {t_sim:.2f} s + encode {t_bytes:.2f} s = {total:.2f} s  (target: a few seconds)")
    print(f"ratio session time / simulation time: {session / total:.0f}x real time")
    return 0


if __name__ == "__main__":
    sys.exit(main())

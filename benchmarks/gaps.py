"""Datagram losses the counter cannot see, on random thesis sessions (those of accuracy.py).

Per session three captures through bytes: clean, 16 datagrams (one counter cycle) cut from the
constant-rate part of a random index turn, and 188 (1.5 s, read as 12) from the full turn's.
Prints how often a turn is corrected or the force chi-square flags the estimates, and how many
estimates left unflagged land more than 3 reported sigma from the truth (biases against the bias
the data carry).

    python benchmarks/gaps.py [--sessions 30] [--workers 2]
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from accuracy import random_scenario
from calibd.calibrate import joint_real_case
from calibd.cli import load_session
from calibd.sim import capture_bytes, simulate, truth_record

CASES = ("clean", "index turn, 16 lost", "full turn, 188 lost")


def one_session(seed: int) -> list[dict]:
    scenario = random_scenario(seed)
    sim = simulate(scenario)
    truth = scenario.truth.estimates()
    carried = truth_record(sim, {})["bias_during_capture"]
    for name, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg"), ("incl_bias", "incl_bias_mg")):
        truth |= {f"{name}_{a}": v for a, v in zip("xyz", carried[key]["session"])}
    rng = np.random.default_rng(seed)
    turns = [p for p in sim.phases if p.kind == "turn"]
    index_turn = int(rng.integers(4))
    cuts = [(0, 0, None),
            (turns[index_turn].cruise_start_s + rng.uniform(0, 2), 16, index_turn),
            (turns[4].cruise_start_s + rng.uniform(0, 10), 188, 4)]
    out = []
    for at_s, count, turn in cuts:
        first = int(at_s * scenario.sensor.sample_rate_hz)
        cut = replace(sim, samples=np.delete(sim.samples, np.arange(first, first + count)))
        result = joint_real_case(load_session(f"seed {seed}", data=capture_bytes(cut)[0]), scenario.site)
        z = []
        for name, e in result.estimates.items():
            if e.quality != "poor":
                error = e.value - truth[name]
                z.append(abs((error + 180) % 360 - 180 if name == "yaw" else error) / e.sigma)
        checked = result.checks.get("turn_angles", [])
        out.append({"corrected": [k for k, t in enumerate(checked) if t["corrected"]], "expected": turn,
                    "flagged": any(e.quality == "poor" and n != "yaw" for n, e in result.estimates.items()),
                    "worst_z": max(z, default=0.0), "unchecked": not checked or any(t["sigma_deg"] is None
                                                                                     for t in checked)})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with ProcessPoolExecutor(args.workers) as pool:
        sessions = list(pool.map(one_session, range(args.sessions)))
    print(f"{args.sessions} random thesis sessions, 125 Hz, STIM300 noise")
    print("| capture | the lossy turn corrected | another turn corrected | flagged poor | turns unchecked | "
          "unflagged beyond 3 sigma | worst unflagged |")
    print("|---|---|---|---|---|---|---|")
    for k, case in enumerate(CASES):
        rows = [s[k] for s in sessions]
        right = sum(r["expected"] in r["corrected"] for r in rows)
        wrong = sum(any(c != r["expected"] for c in r["corrected"]) for r in rows)
        print(f"| {case} | {'-' if k == 0 else right} | {wrong} | {sum(r['flagged'] for r in rows)} | "
              f"{sum(r['unchecked'] for r in rows)} | {sum(r['worst_z'] > 3 for r in rows)} | "
              f"{max(r['worst_z'] for r in rows):.1f} sigma |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

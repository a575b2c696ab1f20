"""Datagram losses the counter cannot see, on random thesis sessions (those of accuracy.py).

Per session three captures through bytes: clean, 16 datagrams (one counter cycle) cut from the
constant-rate part of a random index turn, and 188 (1.5 s, read as 12) from the full turn's.
Prints how often a turn is corrected or the force chi-square flags the estimates, and how many
estimates left unflagged land more than 3 reported sigma from the truth (biases against the bias
the data carry).

With --stalls, host stalls instead, which are no loss: a 2000 Hz stream (benchmarks/live.py's)
through `calibd replay --pty` in real time, the daemon stopped with SIGSTOP for 0.3 to 2 s every
1.5 to 4 s, optionally with `--load` busy processes starving it; printed per run: the hidden gaps
found (target: none) and how far each estimate lies from the counter-only replay's, in sigma
(target: 0.2). The short version is tests/test_stalls.py.

    python benchmarks/gaps.py [--sessions 30] [--workers 2]
    python benchmarks/gaps.py --stalls [--seconds 300] [--runs 2] [--load 0]
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from accuracy import random_scenario
from calibd.methods.joint import joint_real_case
from calibd.captures import load_session
from calibd.sim import capture_bytes, simulate, truth_record
from live import ENV, capture_2000hz

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


def replay(capture: Path, state_dir: Path, *args: str, stalls: random.Random | None = None) -> tuple[dict, int, int]:
    """result.json, the hidden_gap lines logged and the stalls of one `calibd replay`."""
    daemon = subprocess.Popen([sys.executable, "-m", "calibd.cli", "replay", str(capture), "--latitude", "40.59129",
                               "--g0", "9.79956", "--warmup-window", "60", "--state-dir", str(state_dir), *args],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    stopped = 0
    if stalls is not None:
        time.sleep(3.0)
        while daemon.poll() is None:
            time.sleep(stalls.uniform(1.5, 4.0))
            daemon.send_signal(signal.SIGSTOP)
            time.sleep(stalls.uniform(0.3, 2.0))
            daemon.send_signal(signal.SIGCONT)
            stopped += 1
    stderr = daemon.communicate()[1].decode()
    return json.loads((state_dir / "result.json").read_text()), stderr.count('"hidden_gap"'), stopped


def stalls(seconds: float, runs: int, load: int) -> int:
    data, _ = capture_2000hz(seconds)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(load)]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            capture = Path(tmp) / "capture.bin"
            capture.write_bytes(data)
            reference, _, _ = replay(capture, Path(tmp) / "counter")
            print(f"2000 Hz stream, {seconds:.0f} s in real time through a pty, {load} busy processes")
            print("| run | stalls | hidden gaps | hidden_gaps in the result | largest estimate difference |")
            print("|---|---|---|---|---|")
            for run in range(runs):
                for kind, rng in (("unstalled", None), ("stalled", random.Random(run))):
                    result, gaps, stopped = replay(capture, Path(tmp) / f"{kind}{run}", "--pty", "--speed", "1",
                                                   stalls=rng)
                    shifts = {k: abs(result["estimates"][k]["value"] - e["value"]) / e["sigma"]
                              for k, e in reference["estimates"].items() if e.get("sigma")}
                    worst = max(shifts, key=shifts.get)
                    print(f"| {run} {kind} | {stopped} | {gaps} | {result['stream'].get('hidden_gaps')} | "
                          f"{shifts[worst]:.3f} sigma ({worst}) |", flush=True)
    finally:
        for process in busy:
            process.kill()
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--stalls", action="store_true", help="host stalls on a live replay instead of losses")
    ap.add_argument("--seconds", type=float, default=300.0, help="--stalls: the stream's length, real time")
    ap.add_argument("--runs", type=int, default=2, help="--stalls: stalled and unstalled runs of each")
    ap.add_argument("--load", type=int, default=0, help="--stalls: busy processes alongside")
    args = ap.parse_args()
    if args.stalls:
        return stalls(args.seconds, args.runs, args.load)
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

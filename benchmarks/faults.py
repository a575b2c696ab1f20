"""Fault cases: what `calibd calibrate` makes of captures that break the protocol's assumptions.

The rule a calibration must keep is "never a confident wrong answer": each estimate is right
within its sigma, or flagged ("quality": "poor", with a warning naming the cause), or the run
refuses in one line. Per case and seed this runs calibrate's own code path (load_session on a
capture file, with its read log when the case has one, then the method) on a simulated capture
and prints the largest |error| / sigma among the estimates not flagged poor, how many were
flagged, and the refusal if any. Numbers are whatever the code does today: nothing is tuned here.

The session is an index protocol (300 s level static, four 90 deg index turns with 60 s statics,
a 390 deg full turn, 30 s static; 125 Hz, warmed up) unless the case changes it. Cases:
- no fault: the session as it should be (what the others compare with);
- hidden gap N: N datagrams lost in the middle of the second index turn (16 and 64 are whole
  counter cycles, 188 is 1.5 s: the counter sees 12), with the read log `stim300 record` keeps
  (host times of reads every few ms, with jitter) or without it;
- restart: the sensor power-cycles during the second index static (two power-ups in one file);
- warm-up: 600 s of static data from a cold power-up before the protocol;
- one index position: a level static, one 90 deg turn, one static;
- full turn 360 (thesis): the thesis method on a 360 deg full turn, whose ramps leave its
  constant-rate part short of a whole revolution.
Biases are compared with the bias the sensor has at the end of the capture (plus the session
mean of its bias-instability wander): the bias the calibration will be used for.

    python benchmarks/faults.py [--seeds 3] [--markdown]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibd.calibrate import CalibrationError, joint_real_case, load_session, thesis_real_case
from calibd.scenario import Faults, Scenario, Segment, load_scenario
from calibd.sim import capture_bytes, power_up_datagrams, schedule, sensor_format, simulate, truth_record
from stim300.codec import encode_samples
from stim300.reads import READS_DTYPE, reads_path

RATE_HZ = 125
CUT_IN_TURN = 2  # the index turn a hidden gap falls in
BIAS_KEYS = {"gyro_bias": "gyro_bias_deg_h", "acc_bias": "acc_bias_mg", "incl_bias": "incl_bias_mg"}


def index_protocol(level_s: float = 300, index_s: float = 60, turns: int = 4, full_deg: float | None = 390
                   ) -> tuple[Segment, ...]:
    turn = Segment("turn", angle_deg=-90, peak_rate_deg_s=20, accel_deg_s2=20)
    body = [Segment("static", duration_s=level_s)]
    for _ in range(turns):
        body += [turn, Segment("static", duration_s=index_s)]
    if full_deg:
        body += [Segment("turn", angle_deg=-full_deg, peak_rate_deg_s=27.93, accel_deg_s2=30),
                 Segment("static", duration_s=30)]
    return tuple(body)


def scenario(seed: int, **changes) -> Scenario:
    base = load_scenario("thesis-real")
    return replace(base, name="faults", seed=seed, **({"segments": index_protocol()} | changes))


def host_read_log(ends: np.ndarray, true_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The read log a recording host keeps: reads every 2-6 ms, each taking the datagrams that
    arrived before it (on a host clock 50 ppm off the sensor's)."""
    reads = np.cumsum(rng.uniform(0.002, 0.006, int(true_s[-1] / 0.002) + 10))
    t_read = reads[np.searchsorted(reads, true_s + 0.0002)]
    last = np.r_[np.diff(t_read) > 0, True]
    log = np.zeros(last.sum(), READS_DTYPE)
    log["end"], log["t_host_s"] = ends[last], 500.0 + t_read[last] * (1 + 50e-6)
    return log


def hidden_gap_capture(seed: int, lost: int, with_reads: bool, folder: Path) -> tuple[Path, dict]:
    sc = scenario(seed)
    sim = simulate(sc)
    turn = [p for p in sim.phases if p.kind == "turn"][CUT_IN_TURN - 1]
    at = int((turn.start_s + turn.end_s) / 2 * RATE_HZ)
    keep = np.r_[0:at, at + lost:len(sim.samples)]
    head = power_up_datagrams(sc)
    frames = encode_samples(sim.samples[keep], sc.sensor.datagram_id, sensor_format(sc), sc.sensor.crlf)
    path = folder / f"gap{lost}-{'reads' if with_reads else 'counter'}-{seed}.bin"
    path.write_bytes(head + frames.tobytes())
    if with_reads:
        ends = len(head) + frames.shape[1] * np.arange(1, len(frames) + 1)
        np.save(reads_path(path), host_read_log(ends, keep / RATE_HZ, np.random.default_rng(seed)))
    return path, truth_record(sim, {})


def simulated_capture(sc: Scenario, folder: Path, name: str) -> tuple[Path, dict]:
    sim = simulate(sc)
    data, faults = capture_bytes(sim)
    path = folder / f"{name}-{sc.seed}.bin"
    path.write_bytes(data)
    return path, truth_record(sim, faults)


def restart_capture(seed: int, folder: Path):
    sc = scenario(seed)
    second_index = [p for p in schedule(sc) if p.kind == "static"][2]
    restart_s = (second_index.start_s + second_index.end_s) / 2
    return simulated_capture(replace(sc, faults=Faults(restart_at_s=restart_s)), folder, "restart")


def warmup_capture(seed: int, folder: Path):
    sc = scenario(seed)
    cold = replace(sc, warmup=replace(sc.warmup, power_on_s=0.0),
                   segments=(Segment("static", duration_s=600),) + sc.segments)
    return simulated_capture(cold, folder, "warmup")


def one_index_capture(seed: int, folder: Path):
    return simulated_capture(scenario(seed, segments=index_protocol(turns=1, full_deg=None)), folder, "one-index")


def full_360_capture(seed: int, folder: Path):
    return simulated_capture(scenario(seed, segments=index_protocol(full_deg=360)), folder, "full360")


CASES = {
    "no fault": (lambda seed, folder: simulated_capture(scenario(seed), folder, "clean"), "joint"),
    **{f"hidden gap {n}, read log": (lambda seed, folder, n=n: hidden_gap_capture(seed, n, True, folder), "joint")
       for n in (16, 64, 188)},
    **{f"hidden gap {n}, no read log": (lambda seed, folder, n=n: hidden_gap_capture(seed, n, False, folder), "joint")
       for n in (16, 64, 188)},
    "restart": (restart_capture, "joint"),
    "600 s warm-up": (warmup_capture, "joint"),
    "one index position": (one_index_capture, "joint"),
    "full turn 360 (thesis)": (full_360_capture, "thesis"),
}


def truth_values(record: dict) -> dict[str, float]:
    truth = {name: record["truth"][f"{name}_deg"] for name in ("pitch", "roll", "yaw", "alpha", "beta")}
    carried = record["bias_during_capture"]
    for name, key in BIAS_KEYS.items():
        values = np.add(carried[key]["last"], carried[key]["wander_mean"])
        truth |= {f"{name}_{a}": float(v) for a, v in zip("xyz", values)}
    return truth


def run_case(name: str, seed: int, folder: Path) -> dict:
    make, method = CASES[name]
    path, record = make(seed, folder)
    site = load_scenario("thesis-real").site
    try:
        session = load_session(str(path))
        result = joint_real_case(session, site) if method == "joint" else thesis_real_case(session, site)
    except CalibrationError as exc:
        return {"case": name, "seed": seed, "refused": str(exc).splitlines()[0]}
    truth = truth_values(record)
    worst, worst_name, flagged = 0.0, "-", 0
    for est_name, e in result["estimates"].items():
        if e.get("quality") == "poor":
            flagged += 1
            continue
        if e["sigma"] is None or est_name not in truth:
            continue
        error = e["value"] - truth[est_name]
        if est_name == "yaw":
            error = (error + 180) % 360 - 180
        ratio = abs(error) / e["sigma"] if e["sigma"] > 0 else np.inf
        if ratio > worst:
            worst, worst_name = ratio, est_name
    return {"case": name, "seed": seed, "refused": None, "worst": worst, "worst_name": worst_name,
            "flagged": flagged, "hidden_gaps": result.get("stream", {}).get("hidden_gaps")}


def report(rows: list[dict], markdown: bool) -> str:
    head = ["case", "seed", "largest abs(error) / sigma, not flagged", "flagged poor", "refused"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] if markdown else \
        [f"{head[0]:<28} {head[1]:>4}  {head[2]:<40} {head[3]:<14} {head[4]}"]
    for r in rows:
        if r["refused"]:
            cells = [r["case"], str(r["seed"]), "-", "-", r["refused"]]
        else:
            cells = [r["case"], str(r["seed"]), f"{r['worst']:.1f} sigma ({r['worst_name']})",
                     f"{r['flagged']} estimates", "no"]
        lines.append("| " + " | ".join(cells) + " |" if markdown else
                     f"{cells[0]:<28} {cells[1]:>4}  {cells[2]:<40} {cells[3]:<14} {cells[4]}")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds per case (default 3)")
    ap.add_argument("--markdown", action="store_true", help="print a markdown table (for the docs)")
    ap.add_argument("--case", action="append", choices=list(CASES), help="only this case (repeatable)")
    args = ap.parse_args()
    started = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="calibd-faults-") as folder:
        for name in args.case or CASES:
            for seed in range(1, args.seeds + 1):
                rows.append(run_case(name, seed, Path(folder)))
                print(f"{name}, seed {seed}: {time.perf_counter() - started:.0f} s", file=sys.stderr)
    print(report(rows, args.markdown))
    print(f"\n{len(rows)} runs in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

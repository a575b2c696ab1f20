"""Fault cases: what `calibd calibrate` makes of captures that break the campaign's assumptions.

The rule a calibration must keep is "never a confident wrong answer": each estimate is right
within its sigma, or flagged ("quality": "poor", with a warning naming the cause), or the run
refuses in one line. Per case and seed this runs calibrate's own code path (load_session on a
capture file, with its read log when the case has one: the `calibd calibrate` command itself,
which picks the power-up and skips the warm-up) on a simulated capture and prints the largest
|error| / sigma among the estimates not flagged poor, how many were flagged, and the refusal if
any. Numbers are whatever the code does today: nothing is tuned here.

The session is an index campaign (300 s level static, four 90 deg index turns with 60 s statics,
a 360 deg full turn with ramps, 30 s static; 125 Hz, warmed up) unless the case changes it. Cases:
- no fault: the session as it should be (what the others compare with);
- hidden gap N: N datagrams lost in the middle of the second index turn (16 and 64 are whole
  counter cycles, 188 is 1.5 s: the counter sees 12), with the read log `stim300 record` keeps
  (host times of reads every few ms, with jitter) or without it;
- restart: the sensor power-cycles during the second index static (two power-ups in one file;
  the last has the rest of the campaign, and its home position is that static's platform angle);
- warm-up: 600 s of static data from a cold power-up before the campaign, with a thermal time
  constant of 100 s (settled before the campaign) or 1800 s (never settles in the capture);
- one index position: a level static, one 90 deg turn, one static;
- thesis method: the thesis's estimators on the 360 deg full turn, whose ramps leave its
  constant-rate part short of a whole revolution (they carry no sigma: only refusals and flags
  are shown).
Biases are compared with the sensor's turn-on bias, the bias the result reports.

The runs are tasks of calibd's batch engine (calibd.engine, Dask): a local cluster of --workers
processes, or a running cluster with --scheduler (docs/fleet.md).

    python benchmarks/faults.py [--seeds 3] [--workers 2 | --scheduler ADDRESS] [--write docs/accuracy.md]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibd.cli import main as calibd_main
from calibd.engine import TaskFailed, cluster, run_tasks
from calibd.frames import euler_321, int_to_imu, nav_to_int, r3
from calibd.scenario import Faults, Scenario, Segment, load_scenario
from calibd.sim import capture_bytes, power_up_datagrams, schedule, sensor_format, simulate, truth_record
from stim300.codec import encode_samples
from stim300.reads import READS_DTYPE, reads_path

RATE_HZ = 125
CUT_IN_TURN = 2  # the index turn a hidden gap falls in
BIAS_KEYS = {"gyro_bias": "gyro_bias_deg_h", "acc_bias": "acc_bias_mg", "incl_bias": "incl_bias_mg"}


def index_campaign(level_s: float = 300, index_s: float = 60, turns: int = 4, full_deg: float | None = 360
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
    return replace(base, name="faults", seed=seed, **({"segments": index_campaign()} | changes))


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
    """The last power-up has the whole campaign but the level static: its home position is the
    platform angle of the static it starts in, where its attitude truth is taken."""
    sc = scenario(seed)
    second_index = [p for p in schedule(sc) if p.kind == "static"][2]
    restart_s = (second_index.start_s + second_index.end_s) / 2
    path, record = simulated_capture(replace(sc, faults=Faults(restart_at_s=restart_s)), folder, "restart")
    return path, record | {"home_chi_deg": second_index.chi_start_deg}


def warmup_capture(seed: int, folder: Path, time_constant_s: float):
    """600 s of static data from a cold power-up, then the campaign: with a thermal time constant
    of 100 s the temperature settles before the campaign starts, with 1800 s it never does."""
    sc = scenario(seed)
    cold = replace(sc, warmup=replace(sc.warmup, power_on_s=0.0, time_constant_s=time_constant_s),
                   segments=(Segment("static", duration_s=600),) + sc.segments)
    return simulated_capture(cold, folder, f"warmup{time_constant_s:.0f}")


def one_index_capture(seed: int, folder: Path):
    return simulated_capture(scenario(seed, segments=index_campaign(turns=1, full_deg=None)), folder, "one-index")




CASES = {
    "no fault": (lambda seed, folder: simulated_capture(scenario(seed), folder, "clean"), "joint"),
    **{f"hidden gap {n}, read log": (lambda seed, folder, n=n: hidden_gap_capture(seed, n, True, folder), "joint")
       for n in (16, 64, 188)},
    **{f"hidden gap {n}, no read log": (lambda seed, folder, n=n: hidden_gap_capture(seed, n, False, folder), "joint")
       for n in (16, 64, 188)},
    "restart": (restart_capture, "joint"),
    "600 s warm-up, settles": (lambda seed, folder: warmup_capture(seed, folder, 100.0), "joint"),
    "600 s warm-up, never settles": (lambda seed, folder: warmup_capture(seed, folder, 1800.0), "joint"),
    "one index position": (one_index_capture, "joint"),
    "thesis method": (lambda seed, folder: simulated_capture(scenario(seed), folder, "thesis"), "thesis"),
}


def attitude_at(record: dict) -> dict[str, float]:
    """Pitch, roll and yaw (deg) of the truth at the home position of the calibrated power-up
    (the platform angle `home_chi_deg`, 0 unless a restart moved it)."""
    t = record["truth"]
    r_nav_int = nav_to_int(*np.radians([t["gamma1_deg"], t["gamma2_deg"], t["gamma3_deg"]]))
    r_nav_imu = int_to_imu(np.radians(t["alpha_deg"]), np.radians(t["beta_deg"])) @ \
        r3(np.radians(record.get("home_chi_deg", 0.0))) @ r_nav_int
    yaw, pitch, roll = np.degrees(euler_321(r_nav_imu))
    return {"pitch": float(pitch), "roll": float(roll), "yaw": float(yaw)}


def truth_values(record: dict) -> dict[str, float]:
    truth = {name: record["truth"][f"{name}_deg"] for name in ("alpha", "beta")} | attitude_at(record)
    for name, key in BIAS_KEYS.items():
        truth |= {f"{name}_{a}": float(v) for a, v in zip("xyz", record["truth"][key])}
    return truth


def run_case(name: str, seed: int, folder: Path) -> dict:
    make, method = CASES[name]
    path, record = make(seed, folder)
    site = load_scenario("thesis-real").site
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = calibd_main(["calibrate", str(path), "--latitude", str(site.latitude_deg), "--g0", str(site.gravity),
                            "--method", method, "-o", str(path.with_suffix(".json"))])
    if code != 0:
        return {"case": name, "seed": seed, "refused": err.getvalue().strip().split(": ", 2)[-1]}
    result = json.loads(path.with_suffix(".json").read_text())
    truth = truth_values(record)
    worst, worst_name, flagged = None, "-", 0
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
        if worst is None or ratio > worst:
            worst, worst_name = ratio, est_name
    return {"case": name, "seed": seed, "refused": None, "worst": worst, "worst_name": worst_name,
            "flagged": flagged, "hidden_gaps": result.get("stream", {}).get("hidden_gaps")}


def run_in_own_folder(run: tuple[str, int]) -> dict:
    """One case and seed in a temporary folder of the worker that runs it."""
    with tempfile.TemporaryDirectory(prefix="calibd-faults-") as folder:
        return run_case(*run, Path(folder))


def report(rows: list[dict]) -> str:
    """One markdown row per case over its seeds: the worst unflagged ratio, the estimates flagged
    per seed, the refusals."""
    lines = ["| case | runs | largest abs(error) / sigma, not flagged | estimates flagged poor, per run | refused |",
             "|---|---|---|---|---|"]
    for case in dict.fromkeys(r["case"] for r in rows):
        runs = [r for r in rows if r["case"] == case]
        solved = [r for r in runs if not r["refused"]]
        rated = [r for r in solved if r["worst"] is not None]
        worst = max(rated, key=lambda r: r["worst"]) if rated else None
        worst_text = f"{worst['worst']:.1f} ({worst['worst_name']})" if worst else "-"
        flagged = ", ".join(str(r["flagged"]) for r in solved) or "-"
        refused = "; ".join(sorted({r["refused"] for r in runs if r["refused"]})) or "no"
        lines.append(f"| {case} | {len(runs)} | {worst_text} | {flagged} | {refused} |")
    return "\n".join(lines)


MARKERS = ("<!-- fault table: benchmarks/faults.py -->", "<!-- end of fault table -->")


def write_table(path: Path, table: str) -> None:
    """Put the table between the markers of the document (docs/accuracy.md)."""
    text = path.read_text()
    head, rest = text.split(MARKERS[0])
    tail = rest.split(MARKERS[1])[1]
    path.write_text(f"{head}{MARKERS[0]}\n{table}\n{MARKERS[1]}{tail}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds per case (default 3)")
    ap.add_argument("--write", type=Path, help="also put the table into this document (docs/accuracy.md)")
    ap.add_argument("--case", action="append", choices=list(CASES), help="only this case (repeatable)")
    ap.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    ap.add_argument("--scheduler", help="a running Dask cluster: tcp://HOST:PORT or a scheduler file")
    args = ap.parse_args()
    started = time.perf_counter()
    runs = [(name, seed) for name in args.case or CASES for seed in range(1, args.seeds + 1)]
    rows = [None] * len(runs)
    with cluster(args.scheduler, None if args.scheduler else args.workers) as client:
        for index, row in run_tasks(client, run_in_own_folder, runs, names=[f"{n}-{s}" for n, s in runs]):
            name, seed = runs[index]
            if isinstance(row, TaskFailed):
                raise SystemExit(f"{name}, seed {seed}: {row.reason}")
            rows[index] = row
            print(f"{name}, seed {seed}: {time.perf_counter() - started:.0f} s", file=sys.stderr)
    table = report(rows)
    print(table)
    if args.write:
        write_table(args.write, table)
    print(f"\n{len(rows)} runs in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

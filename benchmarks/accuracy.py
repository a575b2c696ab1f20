"""Monte Carlo accuracy of the thesis's methods and the joint estimator on random thesis sessions.

Each session: the thesis real-case protocol (10 min level static, four 90 deg index turns with
120 s statics, a full turn at 27.93 deg/s) in a random sense, with a random truth (any heading,
pitch/roll within 1 deg, alpha/beta within 1 deg, biases within the STIM300's range), STIM300
noise (white plus bias instability), 125 Hz. Per estimate it prints the RMS error of the thesis
nominal run (a-priori alpha/beta off by the thesis's 0.0030/0.0071 deg), the thesis linear run,
the joint estimator, the white-noise Cramer-Rao bound for the same data, and the share of
sessions where the joint estimate is within 2 reported sigma. Biases are compared with the bias
the data carry (the settled value plus the session mean of the bias-instability wander).

    python benchmarks/accuracy.py [--sessions 200] [--write docs/accuracy.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibd import detect
from calibd.calibrate import Session, joint_real_case, thesis_real_case
from calibd.estimators.joint import JointInput, solve, white_noise_bound
from calibd.frames import STANDARD_GRAVITY
from calibd.scenario import Truth, load_scenario
from calibd.sim import simulate, truth_record

DEG = np.pi / 180
NAMES = ["pitch", "roll", "yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "acc_bias_x",
         "acc_bias_y", "acc_bias_z", "incl_bias_x", "incl_bias_y", "incl_bias_z"]
UNITS = {**{n: "deg" for n in NAMES[:5]}, **{n: "deg/h" for n in NAMES[5:8]}, **{n: "mg" for n in NAMES[8:]}}
ARW = 0.15 / 60 * DEG  # rad/sqrt(s): the datasheet angle random walk the bound assumes
GYRO_DRIVEN = ("yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z")  # what the gyro bound covers


def random_scenario(seed: int):
    rng = np.random.default_rng(10_000 + seed)
    base = load_scenario("thesis-real")
    truth = Truth(yaw_deg=rng.uniform(-180, 180), pitch_deg=rng.uniform(-1, 1), roll_deg=rng.uniform(-1, 1),
                  alpha_deg=rng.uniform(-1, 1), beta_deg=rng.uniform(-1, 1),
                  gyro_bias_deg_h=tuple(rng.uniform(-250, 250, 3)), acc_bias_mg=tuple(rng.uniform(-5, 5, 3)),
                  incl_bias_mg=tuple(rng.uniform(-2, 2, 3)))
    sense = rng.choice([-1, 1])
    segments = tuple(replace(s, angle_deg=abs(s.angle_deg) * sense) if s.kind == "turn" else s
                     for s in base.segments)
    return replace(base, seed=seed, truth=truth, segments=segments)


def one_session(seed: int) -> dict:
    scenario = random_scenario(seed)
    sim = simulate(scenario)
    s = sim.samples
    rate = scenario.sensor.sample_rate_hz
    session = Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                      acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                      temperature_c=None, rate_hz=rate, sensor={}, stream={"capture": f"seed {seed}"})
    truth = scenario.truth.estimates()
    carried = truth_record(sim, {})["bias_during_capture"]
    for name, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg"), ("incl_bias", "incl_bias_mg")):
        truth |= {f"{name}_{a}": v for a, v in zip("xyz", carried[key]["session"])}
    tilt = (truth["alpha"] + 0.0030, truth["beta"] - 0.0071)
    out = {}
    for run, result in (("nominal", thesis_real_case(session, scenario.site, tilt)),
                        ("linear", thesis_real_case(session, scenario.site)),
                        ("joint", joint_real_case(session, scenario.site))):
        e = {n: result["estimates"][n]["value"] - truth[n] for n in NAMES}
        e["yaw"] = (e["yaw"] + 180) % 360 - 180
        out[run] = [e[n] for n in NAMES]
        if run == "joint":
            out["sigma"] = [result["estimates"][n]["sigma"] for n in NAMES]
    out["bound"] = _bound(session, scenario)
    return out


def _bound(session: Session, scenario) -> list[float]:
    segments = detect.find_segments(session.gyro / DEG, session.acc / STANDARD_GRAVITY, session.rate_hz)
    statics = [(s.start, s.stop) for s in segments if s.kind == "static"]
    first = statics[0][0]
    inp = JointInput(session.time_s[first:] - session.time_s[first], session.gyro[first:], session.acc[first:],
                     session.incl[first:], tuple((a - first, b - first) for a, b in statics), session.rate_hz)
    bound = white_noise_bound(inp, solve(inp, scenario.site), scenario.site, ARW)
    scale = {"deg": 1 / DEG, "deg/h": 3600 / DEG}
    return [bound[n] * scale[UNITS[n]] if n in GYRO_DRIVEN else float("nan") for n in NAMES]


def table(results: list[dict]) -> str:
    arr = {k: np.array([r[k] for r in results]) for k in ("nominal", "linear", "joint", "sigma", "bound")}

    def rms(x):
        return np.sqrt(np.mean(x**2, axis=0))

    lines = ["| estimate | unit | thesis nominal RMS | thesis linear RMS | joint RMS | white-noise bound | "
             "joint / bound | joint within 2 sigma |", "|---|---|---|---|---|---|---|---|"]
    for i, name in enumerate(NAMES):
        bound = np.mean(arr["bound"][:, i])
        joint = rms(arr["joint"][:, i])
        ratio = f"{joint / bound:.2f}" if np.isfinite(bound) else "-"
        bound_text = f"{bound:.4g}" if np.isfinite(bound) else "-"
        covered = np.mean(np.abs(arr["joint"][:, i]) <= 2 * arr["sigma"][:, i])
        lines.append(f"| {name} | {UNITS[name]} | {rms(arr['nominal'][:, i]):.4g} | {rms(arr['linear'][:, i]):.4g} | "
                     f"{joint:.4g} | {bound_text} | {ratio} | {100 * covered:.0f}% |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--write", help="also write the report to this markdown file (docs/accuracy.md)")
    args = ap.parse_args()
    started = time.perf_counter()
    results = []
    with ProcessPoolExecutor(args.workers) as pool:
        for k, result in enumerate(pool.map(one_session, range(1, args.sessions + 1)), 1):
            results.append(result)
            if k % 20 == 0:
                print(f"{k}/{args.sessions} sessions, {time.perf_counter() - started:.0f} s", file=sys.stderr)
    report = (f"{args.sessions} random thesis sessions (any heading, either sense, alpha/beta within 1 deg, "
              f"STIM300 noise, 125 Hz); errors against the truth, biases against the bias the data carry.\n\n"
              + table(results) + "\n")
    print(report)
    if args.write:
        path = Path(args.write)
        text = path.read_text() if path.exists() else ""
        marker = "<!-- accuracy table: benchmarks/accuracy.py -->"
        head = text.split(marker)[0] if marker in text else text
        path.write_text(head + marker + "\n" + report)
    return 0


if __name__ == "__main__":
    sys.exit(main())

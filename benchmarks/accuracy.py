"""Monte Carlo accuracy of the joint estimator's estimates and 1-sigma (and of the thesis's methods).

Run sets of random sessions, each with a random truth (any heading, pitch/roll within
1 deg, alpha/beta within 1 deg, biases within the STIM300's range), STIM300 noise (white plus
bias instability), 125 Hz, turns in a random sense:
- `g0 given`: the thesis real-case campaign (10 min level static, four 90 deg index turns with
  120 s statics, a full turn at 27.93 deg/s) with the site's measured g0 given;
- `normal gravity`: the same campaign without g0: the calibration takes normal gravity, while the
  simulated true g0 differs from it by a random local anomaly of the documented spread
  (frames.NORMAL_GRAVITY_SIGMA);
- `one index`: statics at two platform angles only (10 min level static, one 90 deg index turn
  with a 120 s static, a full turn, 30 s static), through `calibd calibrate`'s path (refusals and
  "poor" flags counted);
- `no inclinometers`: the thesis campaign with g0 given on a unit without inclinometers (pitch,
  roll and the accelerometer biases from the accelerometers);
- `vibrating static`: the thesis campaign with g0 given, its second index static 21 s long with
  VIBRATION times the sensor's white noise on every sensor (0.35 deg/s per gyro sample: an
  engine running), through `calibd calibrate`'s path (the static is weighed by its own noise);
- `field`: the thesis campaign with g0 given on a sensor with the datasheet's factory residuals
  (each triad's misalignment elements drawn N(0, 0.5 mrad), scale factors N(0, half their
  limit)), turns with a 2 % once-per-revolution rate ripple, through `calibd calibrate`'s path;
- `limit`: the same on units at the datasheet's limits, random signs: each scale factor at its
  limit; each triad turned so that every sensing axis is its misalignment limit (1 mrad) from its
  housing reference, and each pair of its axes off orthogonal by the orthogonality limit
  (0.2 mrad) (`calibd.spec.limit_misalignment`: independent elements at +-1 mrad would put each
  axis 1.4 mrad off and two axes up to 2 mrad off orthogonal, a unit the datasheet does not
  admit);
- `beyond limit`: those units, each element at +-1 mrad on its own, on the same sessions as the
  limit set: what the estimator does with a unit outside the datasheet;
- `tilted axis`: the field set on a platform axis tilted about 5.8 deg from Up (pitch 5, roll
  3 deg), where the statics' forces see some residuals: which terms the data estimated, and how
  well, is tabled too;
- `indexed`: the field set's sessions, without the rate ripple (the simulator's ripple adds to a
  turn's angle: a platform driven by time, not one that stops at its detents), calibrated with
  their statics at an indexing table's 90 deg stops (`--index-step 90`, the stops' 1-sigma
  0.01 deg: the simulated stops are exact): the
  gyro Z scale factor from the turns, on the field set's axes (within about 2 deg of Up, where the
  statics' forces see it only in part);
- `two mountings`: the field set's sessions, each with a second session of the same unit with its
  housing turned 180 deg about its Z axis (the fixture's turn off 180 deg by N(0, 0.1 deg), the
  default `--remount-sigma`), calibrated together (`--remounted`): the gyro misalignment that
  tilts the platform axis from the two tilts, and pitch, roll, alpha and beta without it;
- `known intrinsics`: the field set's sessions calibrated with the unit's factory terms known from
  earlier, independent data (`--intrinsics`): a bench campaign of the unit (its force triads'
  terms) and a second-mounting pair (its gyro triad's that tilt the axis);
- `temperature ramp`: the field set in a room warming or cooling at 2 degC/h (random sign) after
  the warm-up, each bias channel's slope with temperature drawn from the datasheet's figure
  (calibd.spec, `bias_temperature_sigma`), the temperatures in the session, through `calibd
  calibrate`'s path with its temperature judgement (the ramp never meets the warm-up rule's
  1 degC/h: a sigma that carries the ramp leaves the estimates unflagged).
Biases against the housing-frame truth throughout; no lever arm or g-sensitivity is simulated.
Per estimate it prints the RMS error, RMS(error / reported sigma) and the share of sessions
within 1, 2 and 3 reported sigma (a Gaussian error: 68, 95, 99.7 %); for the first set also
the RMS error of the thesis nominal run (a-priori alpha/beta off by the thesis's 0.0030/0.0071
deg) and linear run and the white-noise Cramer-Rao bound. Biases are compared with the turn-on
bias: the bias the sensor has at this power-up (the settled bias moved by the warm-up's mean
temperature excess), which the bias-instability wander moves during the session.

The sessions are tasks of calibd's batch engine (calibd.engine, Dask): a local cluster of
--workers processes, or a running cluster with --scheduler (docs/fleet.md).

    python benchmarks/accuracy.py [--sessions 200] [--workers 2 | --scheduler ADDRESS] [--write docs/accuracy.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from calibd.methods.base import DEFAULT_REMOUNT_SIGMA_DEG
from calibd.methods.bench import thesis_bench
from calibd.methods.joint import SecondMounting, joint_fit, joint_real_case, measured_terms
from calibd.methods.thesis import thesis_real_case
from calibd import spec
from calibd.calibrate import judged_by_temperature
from calibd.engine import TaskFailed, cluster, run_tasks
from calibd.errors import CalibrationError
from calibd.estimators.joint import JointOptions, white_noise_bound
from calibd.frames import NORMAL_GRAVITY_SIGMA, STANDARD_GRAVITY, Site, normal_gravity
from calibd.results import ResultStream
from calibd.scenario import Truth, load_scenario
from calibd.session import Session
from calibd.sim import remounted, simulate, truth_record
from calibd.units import DEG
from calibd.warmup import record_settling
from stim300.records import SensorRecord

NAMES = ["pitch", "roll", "yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "acc_bias_x",
         "acc_bias_y", "acc_bias_z", "incl_bias_x", "incl_bias_y", "incl_bias_z"]
UNITS = {**{n: "deg" for n in NAMES[:5]}, **{n: "deg/h" for n in NAMES[5:8]}, **{n: "mg" for n in NAMES[8:]}}
ARW = 0.15 / 60 * DEG  # rad/sqrt(s): the datasheet angle random walk the bound assumes
GYRO_DRIVEN = ("yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z")  # what the gyro bound covers
RUN_SETS = ("g0 given", "normal gravity", "one index", "no inclinometers", "vibrating static", "field", "limit",
            "beyond limit", "tilted axis", "indexed", "two mountings", "known intrinsics", "temperature ramp")
SEED_OFFSET = {"g0 given": 0, "normal gravity": 100_000, "one index": 200_000, "no inclinometers": 300_000,
               "vibrating static": 400_000, "field": 500_000, "limit": 600_000,
               "beyond limit": 600_000, "tilted axis": 700_000, "indexed": 500_000, "two mountings": 500_000,
               "known intrinsics": 500_000, "temperature ramp": 800_000}
SECOND_SEED = 50_000  # the second mounting's noise: another session's
EARLIER_SEED = 60_000  # the known intrinsics' earlier sessions (bench, two mountings): other data
# with the datasheet's factory residuals
FACTORY_SETS = ("field", "limit", "beyond limit", "tilted axis", "indexed", "two mountings", "known intrinsics",
                "temperature ramp")
CALIBRATE_PATH = ("one index", "vibrating static", *FACTORY_SETS)  # through calibd calibrate: flags count
TILTED_DEG = (5.0, 3.0)  # the tilted-axis set's pitch and roll: its platform axis about 5.8 deg from Up
VIBRATION = 12.5  # times the sensor's white noise (scenario.Segment.vibration)
FIELD_RIPPLE = 0.02  # once-per-revolution rate ripple of the field and limit sets' turns
RAMP_C_PER_H = 2.0  # the temperature ramp set's room drift, either sign
INDEXED = JointOptions(index_step=90 * DEG, index_sigma=0.01 * DEG)  # the indexed set's stops


def names(run_set: str) -> list[str]:
    """The estimates of a run set: a unit without inclinometers has no inclinometer biases."""
    return [n for n in NAMES if not (run_set == "no inclinometers" and n.startswith("incl_"))]


def random_scenario(seed: int, run_set: str = "g0 given"):
    rng = np.random.default_rng(10_000 + seed)
    base = load_scenario("thesis-real")
    truth = Truth(yaw_deg=rng.uniform(-180, 180), pitch_deg=rng.uniform(-1, 1), roll_deg=rng.uniform(-1, 1),
                  alpha_deg=rng.uniform(-1, 1), beta_deg=rng.uniform(-1, 1),
                  gyro_bias_deg_h=tuple(rng.uniform(-250, 250, 3)), acc_bias_mg=tuple(rng.uniform(-5, 5, 3)),
                  incl_bias_mg=tuple(rng.uniform(-2, 2, 3)))
    sense = rng.choice([-1, 1])
    segments = base.segments
    if run_set == "one index":  # the level static, the first index turn and static, the full turn and its static
        segments = segments[:3] + segments[-2:]
    if run_set == "vibrating static":
        segments = segments[:4] + (replace(segments[4], duration_s=21.0, vibration=VIBRATION),) + segments[5:]
    segments = tuple(replace(s, angle_deg=abs(s.angle_deg) * sense) if s.kind == "turn" else s for s in segments)
    site = base.site
    if run_set == "normal gravity":
        lat = site.latitude_deg
        site = Site(lat, site.height_m, normal_gravity(lat, site.height_m) + rng.normal(0, NORMAL_GRAVITY_SIGMA))
    if run_set in FACTORY_SETS:
        truth = replace(truth, **factory_residuals(rng, run_set))
        ripple = 0.0 if run_set == "indexed" else FIELD_RIPPLE  # the simulated ripple moves where a turn ends
        segments = tuple(replace(s, ripple=ripple) if s.kind == "turn" else s for s in segments)
    if run_set == "tilted axis":
        truth = replace(truth, pitch_deg=TILTED_DEG[0], roll_deg=TILTED_DEG[1])
    warmup = base.warmup
    if run_set == "temperature ramp":
        slopes = {name: tuple(rng.normal(0, triad.bias_temperature_sigma, 3))
                  for name, triad in spec.triads(spec.DEFAULT_ACC_RANGE_G).items()}
        warmup = replace(warmup, power_on_s=1e7, ramp_c_per_h=rng.choice([-1, 1]) * RAMP_C_PER_H,
                         gyro_tempco_deg_h_per_c=slopes["gyro"], acc_tempco_mg_per_c=slopes["acc"],
                         incl_tempco_mg_per_c=slopes["incl"])
    return replace(base, seed=seed, truth=truth, segments=segments, site=site, warmup=warmup)


def factory_residuals(rng: np.random.Generator, run_set: str) -> dict:
    """Each triad's scale factors and misalignment elements (Truth's fields): drawn with the
    datasheet's limits as 2 sigma (field), at the limits with random signs (limit), or every
    element at its limit on its own (beyond limit)."""
    out = {}
    for sensor, triad in spec.triads(spec.DEFAULT_ACC_RANGE_G).items():
        if run_set not in ("limit", "beyond limit"):
            scale = rng.normal(0, triad.scale_factor_sigma_ppm, 3)
            misalignment = rng.normal(0, triad.misalignment_sigma_mrad, 6)
        else:
            scale = rng.choice([-1, 1], 3) * triad.scale_factor_ppm
            misalignment = spec.limit_misalignment(rng, triad) if run_set == "limit" \
                else rng.choice([-1, 1], 6) * triad.misalignment_mrad
        out[f"{sensor}_scale_ppm"] = tuple(scale)
        out[f"{sensor}_misalignment_mrad"] = tuple(misalignment)
    return out


def _session(sim, run_set: str, seed: int) -> Session:
    s = sim.samples
    rate = sim.scenario.sensor.sample_rate_hz
    return Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                   acc=s["acc"].astype(float) * STANDARD_GRAVITY,
                   incl=None if run_set == "no inclinometers" else s["incl"].astype(float) * STANDARD_GRAVITY,
                   temperature_c=sim.temperature_c if run_set == "temperature ramp" else None,
                   rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture=f"seed {seed}"))


def second_mounting(scenario, seed: int) -> SecondMounting:
    """The same unit turned 180 deg about its Z axis (off by N(0, the default --remount-sigma)),
    simulated with noise of its own and fitted as `calibd calibrate --remounted` fits it."""
    error = np.random.default_rng(seed).normal(0, DEFAULT_REMOUNT_SIGMA_DEG) * DEG
    turned = replace(scenario, truth=remounted(scenario.truth, error), seed=scenario.seed + SECOND_SEED)
    fit = joint_fit(_session(simulate(turned), "two mountings", seed), turned.site).fit
    return SecondMounting(fit, {"path": f"seed {seed}, turned", "power_up": 1}, DEFAULT_REMOUNT_SIGMA_DEG * DEG)


def known_intrinsics(scenario, seed: int) -> JointOptions:
    """The unit's factory terms as `--intrinsics` takes them from two earlier results on data of
    their own: a bench campaign (the force triads' terms from six positions) and a pair of
    mountings (the gyro triad's that tilt the axis)."""
    residuals = {name: getattr(scenario.truth, name) for name in scenario.truth.__dataclass_fields__
                 if name.endswith(("_scale_ppm", "_misalignment_mrad"))}
    bench = load_scenario("thesis-bench")
    bench = replace(bench, truth=replace(bench.truth, **residuals), seed=scenario.seed + EARLIER_SEED)
    earlier = replace(scenario, seed=scenario.seed + EARLIER_SEED + 1)
    first = _session(simulate(earlier), "known intrinsics", seed)
    pair = joint_real_case(first, earlier.site, JointOptions(), None, second_mounting(earlier, seed + EARLIER_SEED))
    terms = measured_terms(thesis_bench(_session(simulate(bench), "known intrinsics", seed), bench.site))
    return JointOptions(known_terms=terms + measured_terms(pair))


def one_session(seed: int, run_set: str) -> dict:
    scenario = random_scenario(seed + SEED_OFFSET[run_set], run_set)
    sim = simulate(scenario)
    session = _session(sim, run_set, seed)
    given = scenario.site
    site = Site(given.latitude_deg, given.height_m) if run_set == "normal gravity" else given
    truth = scenario.truth.estimates()
    carried = truth_record(sim, {})["bias_during_capture"]
    for name, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg"), ("incl_bias", "incl_bias_mg")):
        truth |= {f"{name}_{a}": v for a, v in zip("xyz", carried[key]["mean"])}  # turn-on: without the wander

    estimated = names(run_set)

    def error(values: dict[str, float]):
        e = {n: values[n] - truth[n] for n in estimated}
        e["yaw"] = (e["yaw"] + 180) % 360 - 180
        return [e[n] for n in estimated]

    def values(result):
        return {n: e.value for n, e in result.estimates.items()}

    out = {"refused": None, "poor": False, "poor_names": []}
    if run_set in CALIBRATE_PATH:
        try:
            options = INDEXED if run_set == "indexed" else \
                known_intrinsics(scenario, seed) if run_set == "known intrinsics" else JointOptions()
            second = second_mounting(scenario, seed) if run_set == "two mountings" else None
            result = judged_by_temperature(joint_real_case(session, site, options, None, second),
                                           record_settling(session.time_s, session.temperature_c))
        except CalibrationError as exc:
            return out | {"refused": str(exc)}
        out["poor_names"] = [n for n, e in result.estimates.items() if e.quality == "poor"]
        out["poor"] = bool(out["poor_names"])
        if run_set in FACTORY_SETS:  # each factory term's estimate against the simulated residual
            terms = result.error_budget["factory_residuals"]["terms"]
            out["terms"] = {name: (t["value"] - _residual(scenario.truth, name), t["sigma"], t["prior_sigma"],
                                   t["source"]) for name, t in terms.items()}
        estimates, sigmas = values(result), {n: e.sigma for n, e in result.estimates.items()}
    else:
        fitted = joint_fit(session, site)
        estimates = {n: fitted.fit.estimates[n] * _display(n) for n in estimated}
        sigmas = {n: fitted.fit.sigmas[n] * _display(n) for n in estimated}
        bound = white_noise_bound(fitted.inp, fitted.fit, site, ARW)
        out["bound"] = [bound[n] * _display(n) if n in GYRO_DRIVEN else float("nan") for n in estimated]
    out["joint"] = error(estimates)
    out["sigma"] = [sigmas[n] for n in estimated]
    if run_set == "g0 given":
        tilt = (truth["alpha"] + 0.0030, truth["beta"] - 0.0071)
        out["nominal"] = error(values(thesis_real_case(session, site, tilt)))
        out["linear"] = error(values(thesis_real_case(session, site)))
    return out


def _residual(truth: Truth, term: str) -> float:
    """A factory term's simulated value, in its result unit (ppm, mrad), by the term's name."""
    element = spec.FactoryTerm.named(term)
    return float(truth.triad_error(element.sensor)[element.row, element.col] * element.to_unit)


def term_table(results: list[dict]) -> str:
    """The factory terms the data estimated in some session (their sigma at most half the
    prior's): how often, the RMS of error / sigma and the share within 2 sigma, and the mean
    sigma against the prior's."""
    solved = [r for r in results if "terms" in r]
    rows = ["| term | estimated in | RMS(error / sigma) | within 2 sigma | mean sigma / prior sigma |",
            "|---|---|---|---|---|"]
    for name in solved[0]["terms"] if solved else ():
        picked = [r["terms"][name] for r in solved if r["terms"][name][3] == "estimated"]
        if not picked:
            continue
        z = np.array([e / s for e, s, _, _ in picked])
        rows.append(f"| {name} | {len(picked)} of {len(solved)} | {np.sqrt(np.mean(z**2)):.2f} | "
                    f"{100 * np.mean(np.abs(z) <= 2):.0f}% | {np.mean([s / p for _, s, p, _ in picked]):.2f} |")
    return "\n".join(rows) if len(rows) > 2 else "no term estimated in any session"


def _display(name: str) -> float:
    return {"deg": 1 / DEG, "deg/h": 3600 / DEG, "mg": 1000 / STANDARD_GRAVITY}[UNITS[name]]


def table(results: list[dict], estimated: list[str]) -> str:
    solved = [r for r in results if r["refused"] is None]
    arr = {k: np.array([r[k] for r in solved]) for k in ("nominal", "linear", "joint", "sigma", "bound")
           if solved and k in solved[0]}

    def rms(x):
        return np.sqrt(np.mean(np.square(x), axis=0))

    def column(key, i):
        return f"{rms(arr[key][:, i]):.4g}" if key in arr else "-"

    lines = ["| estimate | unit | joint RMS error | RMS(error / sigma) | within 1 / 2 / 3 sigma | beyond 3 sigma, "
             "not flagged | white-noise bound | thesis nominal RMS | thesis linear RMS |",
             "|---|---|---|---|---|---|---|---|---|"]
    for i, name in enumerate(estimated):
        err, sigma = arr["joint"][:, i], arr["sigma"][:, i]
        bound = np.mean(arr["bound"][:, i]) if "bound" in arr else float("nan")
        within = " / ".join(f"{100 * np.mean(np.abs(err) <= k * sigma):.0f}%" for k in (1, 2, 3))
        unflagged = sum(abs(r["joint"][i]) > 3 * r["sigma"][i] and name not in r["poor_names"] for r in solved)
        lines.append(f"| {name} | {UNITS[name]} | {rms(err):.4g} | {rms(err / sigma):.2f} | {within} | {unflagged} | "
                     f"{f'{bound:.4g}' if np.isfinite(bound) else '-'} | {column('nominal', i)} | "
                     f"{column('linear', i)} |")
    return "\n".join(lines)


def summary(run_set: str, results: list[dict]) -> str:
    refused = [r["refused"] for r in results if r["refused"] is not None]
    poor = sum(r["poor"] for r in results)
    head = f"### {run_set}: {len(results)} sessions"
    notes = []
    if refused:
        notes.append(f"{len(refused)} refused (\"{refused[0]}\")")
    if poor:
        notes.append(f"{poor} with an estimate of quality poor")
    head += (" (" + "; ".join(notes) + ")") if notes else ""
    body = table(results, names(run_set)) if len(refused) < len(results) else "every session refused"
    if run_set in FACTORY_SETS and len(refused) < len(results):
        body += "\n\nFactory terms the data estimated:\n\n" + term_table(results)
    return head + "\n\n" + body + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    ap.add_argument("--scheduler", help="a running Dask cluster: tcp://HOST:PORT or a scheduler file")
    ap.add_argument("--sets", nargs="+", choices=RUN_SETS, default=list(RUN_SETS), help="run sets (default: all)")
    ap.add_argument("--write", help="also write the report to this markdown file (docs/accuracy.md)")
    args = ap.parse_args()
    started = time.perf_counter()
    parts = []
    with cluster(args.scheduler, None if args.scheduler else args.workers) as client:
        for run_set in args.sets:
            results = [None] * args.sessions
            seeds = range(1, args.sessions + 1)
            for k, (index, result) in enumerate(run_tasks(client, partial(one_session, run_set=run_set), seeds,
                                                          names=[f"{run_set}-{seed}" for seed in seeds]), 1):
                if isinstance(result, TaskFailed):
                    raise SystemExit(f"{run_set}, seed {index + 1}: {result.reason}")
                results[index] = result
                if k % 20 == 0:
                    print(f"{run_set}: {k}/{args.sessions} sessions, {time.perf_counter() - started:.0f} s",
                          file=sys.stderr)
            parts.append(summary(run_set, results))
    report = ("Random sessions (any heading, either sense, alpha/beta within 1 deg, STIM300 noise, 125 Hz); "
              "errors against the truth, biases against the turn-on bias.\n\n" + "\n".join(parts))
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

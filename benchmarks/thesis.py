"""Monte Carlo of the thesis's estimators on simulated thesis sessions (noise only changes).

For each seed: simulate the thesis real-case session (truth of the thesis-real scenario, clockwise), decode
it, find the segments, and run the nominal chain (lab alpha/beta 0.5964/-0.1125, off the truth
by the thesis's 0.0030/0.0071 deg) and the linear same-dataset chain. Prints, per estimate, the
RMS and mean absolute error of each, next to the thesis's own errors (Tables 7.5-7.8 and
7.15-7.18), as a markdown table for docs/thesis-estimators.md.

    python benchmarks/thesis.py [--seeds 50]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibd.methods.thesis import thesis_real_case
from calibd.captures import load_session
from calibd.frames import Site
from calibd.scenario import load_scenario
from calibd.sim import write_capture

SITE = Site(40.59129, g0=9.79956)
NAMES = ["pitch", "roll", "yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "acc_bias_x",
         "acc_bias_y", "acc_bias_z", "incl_bias_x", "incl_bias_y"]
THESIS_NOMINAL = {"pitch": 0.0186, "roll": 0.0076, "yaw": 27.9465, "gyro_bias_x": 1.0408, "gyro_bias_y": 5.4036,
                  "gyro_bias_z": 0.7638, "acc_bias_x": 0.2836, "acc_bias_y": 0.1653, "acc_bias_z": 0.0581,
                  "incl_bias_x": 0.3212, "incl_bias_y": 0.1361}
THESIS_LINEAR = {"pitch": 0.0128, "roll": 0.0105, "yaw": 2.6527, "alpha": 0.0029, "beta": 0.0058,
                 "gyro_bias_x": 2.1012, "gyro_bias_y": 0.5308, "gyro_bias_z": 0.6880, "acc_bias_x": 0.1832,
                 "acc_bias_y": 0.2153, "acc_bias_z": 0.0579, "incl_bias_x": 0.2208, "incl_bias_y": 0.1861}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    args = ap.parse_args()
    base = load_scenario("thesis-real")
    truth = base.truth.estimates()
    errors = {"nominal": [], "linear": []}
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "session.bin"
        for k, seed in enumerate(range(1, args.seeds + 1)):
            write_capture(replace(base, seed=seed), path)
            session = load_session(str(path))
            for run, tilt in (("nominal", (0.5964, -0.1125)), ("linear", None)):
                result = thesis_real_case(session, SITE, tilt)
                errors[run].append([result.estimates[n].value - truth[n] for n in NAMES])
            if (k + 1) % 10 == 0:
                print(f"{k + 1}/{args.seeds} sessions, {time.perf_counter() - started:.0f} s", file=sys.stderr)
    units = {"pitch": "deg", "roll": "deg", "yaw": "deg", "alpha": "deg", "beta": "deg"}
    print(f"{args.seeds} simulated thesis sessions (clockwise, 125 Hz, STIM300 noise), absolute errors vs truth\n")
    print("| estimate | unit | nominal RMS | nominal mean abs | thesis nominal | linear RMS | linear mean abs "
          "| thesis linear |")
    print("|---|---|---|---|---|---|---|---|")
    for i, name in enumerate(NAMES):
        unit = units.get(name, "deg/h" if name.startswith("gyro") else "mg")
        row = [name, unit]
        for run, reference in (("nominal", THESIS_NOMINAL), ("linear", THESIS_LINEAR)):
            e = np.array(errors[run])[:, i]
            row += [f"{np.sqrt(np.mean(e**2)):.4f}", f"{np.mean(np.abs(e)):.4f}",
                    f"{reference[name]:.4f}" if name in reference else "a priori"]
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A simulated fleet for the batch and fleet tests: three STIM300s, eight captures each, one a
day, each unit on its own mount with its own biases; from one power-up to the next the gyro
biases move by the datasheet's run-to-run figure (4 deg/h, TS1524 rev.31 Table 5-3) and nothing
else moves. The last capture of the stepped unit has its X gyro bias stepped by STEP_DEG_H."""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calibd import spec
from calibd.scenario import load_scenario
from calibd.sim import write_capture

SERIALS = ("N25582405001001", "N25582405001002", "N25582405001003")
STEPPED = SERIALS[2]
STEP_ESTIMATE = "gyro_bias_x"
STEP_DEG_H = 40.0
CAPTURES_PER_UNIT = 8
FIRST_DAY = datetime.datetime(2026, 3, 2, 8, 0, tzinfo=datetime.timezone.utc)
LATITUDE = "40.59129"  # the continuous scenario's site
G0 = "9.79956"


@dataclass(frozen=True)
class FleetCapture:
    path: Path
    serial: str
    day: int
    truth: dict  # the scenario's truth in the result's names and units


def simulate_fleet(directory: Path, captures_per_unit: int = CAPTURES_PER_UNIT) -> list[FleetCapture]:
    """Write the fleet's captures into `directory` (each with its truth beside it), their
    modification times one day apart, and return them in the order written."""
    base = load_scenario("continuous")
    rng = np.random.default_rng(29)
    made = []
    for unit, serial in enumerate(SERIALS):
        mount = replace(base.truth, yaw_deg=float(rng.uniform(-180, 180)), pitch_deg=float(rng.normal(0, 0.5)),
                        roll_deg=float(rng.normal(0, 0.5)))
        biases = np.asarray(base.truth.gyro_bias_deg_h) + rng.normal(0, 20, 3)
        for day in range(captures_per_unit):
            gyro = biases + rng.normal(0, spec.GYRO.bias_run_to_run, 3)
            if serial == STEPPED and day == captures_per_unit - 1:
                gyro[0] += STEP_DEG_H
            scenario = replace(base, name=f"{serial}-{day}", seed=1000 * unit + day,
                               sensor=replace(base.sensor, serial_number=serial),
                               truth=replace(mount, gyro_bias_deg_h=tuple(float(g) for g in gyro)))
            path = directory / f"{serial}-day{day:02d}.bin"
            write_capture(scenario, path)
            when = (FIRST_DAY + datetime.timedelta(days=day, minutes=10 * unit)).timestamp()
            os.utime(path, (when, when))
            made.append(FleetCapture(path, serial, day, scenario.truth.estimates()))
    return made

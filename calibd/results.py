"""The calibration result every method writes (schema calibd.result/1), and its safe storage.

Estimates are kept in SI inside the code; here they become the units people read: degrees,
deg/h for gyro biases, mg (1e-3 of the sensor's g, 9.80665 m/s^2) for accelerometer and
inclinometer biases. A result file is replaced atomically and synced, so a crash never leaves
a half-written or empty result where the last good one was.
"""

from __future__ import annotations

import json
from pathlib import Path

from stim300.atomic import write_atomic

from .errors import CalibdError
from .frames import EARTH_RATE, STANDARD_GRAVITY, Site
from .units import DEG

SCHEMA = "calibd.result/1"
_ANGLE = (1 / DEG, "deg")
_GYRO = (3600 / DEG, "deg/h")
_FORCE = (1000 / STANDARD_GRAVITY, "mg")
# estimate name -> (factor from SI, unit)
ESTIMATES = {"pitch": _ANGLE, "roll": _ANGLE, "yaw": _ANGLE, "alpha": _ANGLE, "beta": _ANGLE,
             **{f"gyro_bias_{a}": _GYRO for a in "xyz"},
             **{f"acc_bias_{a}": _FORCE for a in "xyz"},
             **{f"incl_bias_{a}": _FORCE for a in "xyz"}}


class ResultError(CalibdError):
    """A result file that is missing, unreadable or not of this schema."""


def estimate(name: str, value_si: float, sigma_si: float | None = None) -> dict:
    factor, unit = ESTIMATES[name]
    return {"value": float(value_si) * factor, "sigma": None if sigma_si is None else float(sigma_si) * factor,
            "unit": unit}


def site_record(site: Site) -> dict:
    return {"latitude_deg": site.latitude_deg, "height_m": site.height_m, "g0_m_s2": site.gravity,
            "g0_given": site.g0 is not None, "earth_rate_deg_h": EARTH_RATE * 3600 / DEG}


def make_result(method: str, site: Site, estimates: dict[str, tuple[float, float | None]], segments: list[dict],
                warnings: list[str], sensor: dict, **extra) -> dict:
    """The result document; `estimates` maps names of ESTIMATES to (value, sigma) in SI."""
    unknown = set(estimates) - set(ESTIMATES)
    if unknown:
        raise ValueError(f"unknown estimate names: {sorted(unknown)}")
    return {"schema": SCHEMA, "method": method, "site": site_record(site),
            "estimates": {name: estimate(name, *pair) for name, pair in estimates.items()},
            "segments": segments, "warnings": list(warnings), "sensor": sensor, **extra}


def result_json(result: dict) -> bytes:
    """The result file's bytes: JSON, one key a line, no NaN (a result with one is a bug)."""
    return (json.dumps(result, indent=1, allow_nan=False) + "\n").encode()


def write_result(path, result: dict) -> None:
    write_atomic(path, result_json(result))


def load_result(path) -> dict:
    try:
        result = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise ResultError(f"{path}: cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise ResultError(f"{path}: not JSON: {exc}") from None
    if not isinstance(result, dict) or result.get("schema") != SCHEMA:
        raise ResultError(f"{path}: not a {SCHEMA} result")
    return result

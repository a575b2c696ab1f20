"""`calibd fleet`: a fleet table (calibd.fleettable) read back as each sensor's history: every
estimate over time, its run-to-run spread beside the datasheet's figure, and the units whose
latest result is out of family.

Rows: only "ok" rows count. A session (session_id) calibrated more than once (other calibd
versions or settings) counts once: the row of the highest calibd_version (by packaging.version
when it is installed, else as text; ties: the table's last row). A unit's results are ordered by
capture time; an estimate whose quality is "poor" is shown but left out of every statistic.

The out-of-family test of an estimate of a unit compares its latest value x with the mean m of
the n usable earlier values (the unit's history; yaw taken modulo 360 deg around the first). The
history's sample standard deviation s is the observed run-to-run scatter: it carries the true
run-to-run change and each result's own noise, so the latest's own sigma adds only what it has
beyond the history's (a shorter or noisier session). The spread of x - m is

    spread^2 = s^2 (1 + 1/n) + max(0, sigma_latest^2 - mean(sigma_history^2))

and t = (x - m) / spread follows Student's t with n - 1 degrees of freedom for a unit that has
not changed (a prediction interval: s is itself estimated from n values, which t accounts for).
The latest is out of family when |t| lies beyond the two-sided probability of 3 sigma of a normal
(99.73 %): t beyond 9.2 with 3 degrees of freedom, 4.9 with 6, 3.4 with 20. Its "sigma" is the
normal deviate with the same tail probability, so 3.3 sigma means as unlikely as 3.3 sigma of a
normal, whatever n. With fewer than MIN_OWN_HISTORY usable earlier values the unit's own s says
too little: s, its degrees of freedom and the mean sigma^2 are then the fleet's, pooled over every
unit's history (each value about its own unit's mean; the run-to-run scatter is the sensor
type's, as the datasheet states it; `--serial` hides the other units but they are still pooled).
A unit's first result has nothing to be compared with (units
differ by their own turn-on biases and mounts) and is not tested. Sigmas shared by all of a unit's
results (the factory residuals in every 1-sigma) cancel in x - m, and the test never uses them.
At 3 sigma a clean unit with its 14 estimates raises a false flag about once in 26 reports.
"""

from __future__ import annotations

import datetime
import json
import warnings
from dataclasses import dataclass

import numpy as np

from . import fleettable, spec
from .errors import CalibdError
from .units import fixed, value_sigma, value_sigma_texts

OUT_OF_FAMILY_SIGMAS = 3.0
MIN_OWN_HISTORY = 5  # usable earlier values before a unit's own scatter is used (4 degrees of freedom)
NAMES = fleettable.ESTIMATE_NAMES
UNITS = {name: fleettable.COLUMNS[name][1] for name in NAMES}
GROUPS = {"mounting": ("pitch", "roll", "yaw"), "platform axis": ("alpha", "beta"),
          "gyro biases": ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z"),
          "accelerometer biases": ("acc_bias_x", "acc_bias_y", "acc_bias_z"),
          "inclinometer biases": ("incl_bias_x", "incl_bias_y", "incl_bias_z")}
WRAPPED = NAMES.index("yaw")  # an angle of the full circle: compared modulo 360 deg
EARLIEST = datetime.datetime.min.replace(tzinfo=datetime.timezone.utc)


class FleetReportError(CalibdError):
    """The report cannot be made (matplotlib missing); one line."""


@dataclass
class Unit:
    """One sensor's calibrated power-ups in time order: (results x estimates) arrays, NaN where a
    result has no value or sigma; yaw unwrapped around the first."""

    serial: str
    times: list[datetime.datetime]
    values: np.ndarray
    sigmas: np.ndarray
    poor: np.ndarray
    acc_range_g: int | None

    @property
    def usable(self) -> np.ndarray:
        return ~self.poor & np.isfinite(self.values)


@dataclass
class Pooled:
    """The fleet's run-to-run scatter of each estimate: pooled over the units' histories."""

    scatter: np.ndarray
    dof: np.ndarray
    sigma2: np.ndarray  # mean sigma^2 of the values pooled


@dataclass
class Verdict:
    """Each estimate's latest value against the unit's history (arrays over NAMES)."""

    count: np.ndarray  # usable earlier values
    mean: np.ndarray  # their mean
    scatter: np.ndarray  # their standard deviation: the observed run-to-run spread (NaN below 2)
    own: np.ndarray  # the test used the unit's own scatter (else the fleet's)
    spread: np.ndarray  # of latest - mean (NaN: not tested)
    t: np.ndarray
    dof: np.ndarray
    sigmas: np.ndarray  # the normal deviate of t's two-sided tail probability
    untested: list[str | None]  # why an estimate was not tested, else None

    @property
    def flagged(self) -> np.ndarray:
        return np.nan_to_num(self.sigmas, nan=0.0) > OUT_OF_FAMILY_SIGMAS

    def limit(self) -> np.ndarray:
        """Half the width of the latest's 3-sigma prediction interval, in the estimate's unit."""
        from scipy.special import ndtr, stdtrit

        with np.errstate(invalid="ignore"):
            return self.spread * stdtrit(np.maximum(self.dof, 1), ndtr(OUT_OF_FAMILY_SIGMAS))


@dataclass
class Fleet:
    table: str
    units: list[Unit]
    verdicts: list[Verdict]
    pooled: Pooled
    rows: int  # in the table
    not_ok: int  # rows whose status is not "ok"
    repeats: int  # "ok" rows of a session another row stands for


def analyse(table: str, rows: list[dict], serial: str | None = None) -> Fleet:
    """The units of `rows` (of the fleet table `table`; only `serial` when given) with their
    verdicts; FleetError when there is nothing to report."""
    if not rows:
        raise fleettable.FleetError(f"{table}: an empty fleet table (no rows)")
    kept = calibrated(rows)
    if not kept:
        statuses = ", ".join(f"{sum(r['status'] == s for r in rows)} {s}" for s in fleettable.STATUSES)
        raise fleettable.FleetError(f"{table}: no calibrated power-up in the table ({statuses})")
    units = build_units(kept)
    pooled = pool(units)
    if serial is not None:
        units = [u for u in units if u.serial == serial]
        if not units:
            known = sorted({r["serial_number"] or "?" for r in kept})
            raise fleettable.FleetError(f"{table}: no calibrated power-up of serial number {serial!r} (the table "
                                        f"has {', '.join(known[:10])}{', ...' if len(known) > 10 else ''})")
    ok = sum(r["status"] == "ok" for r in rows)
    return Fleet(table, units, [verdict(u, pooled) for u in units], pooled, len(rows), len(rows) - ok, ok - len(kept))


def calibrated(rows: list[dict]) -> list[dict]:
    """The "ok" rows, one per session: the highest calibd version's, the last of equals."""
    best: dict[str, tuple] = {}
    for index, row in enumerate(rows):
        if row["status"] != "ok":
            continue
        key = row["session_id"] or f"row {index}"
        rank = (version_key(row["calibd_version"]), index)
        if key not in best or rank > best[key][0]:
            best[key] = (rank, row)
    return [row for _, row in best.values()]


def version_key(text: str | None) -> tuple:
    """A calibd version for comparison: a PEP 440 version above any text it cannot parse."""
    try:
        from packaging.version import InvalidVersion, Version
    except ImportError:
        return (0, text or "")
    try:
        return (1, Version(text or ""))
    except InvalidVersion:
        return (0, text or "")


def build_units(rows: list[dict]) -> list[Unit]:
    """The rows by serial number (sorted), each unit's in time order."""
    by_serial: dict[str, list[dict]] = {}
    for row in rows:
        by_serial.setdefault(row["serial_number"] or "?", []).append(row)
    units = []
    for serial in sorted(by_serial):
        rows = sorted(by_serial[serial], key=lambda r: (r["capture_time"] or EARLIEST, r["power_up"] or 0,
                                                         r["capture"] or ""))
        values = np.array([[np.nan if r[n] is None else r[n] for n in NAMES] for r in rows], dtype=float)
        sigmas = np.array([[np.nan if r[f"{n}_sigma"] is None else r[f"{n}_sigma"] for n in NAMES] for r in rows],
                          dtype=float)
        poor = np.array([[r[f"{n}_quality"] == "poor" for n in NAMES] for r in rows], dtype=bool)
        yaw = values[:, WRAPPED]
        first = yaw[np.isfinite(yaw)][:1]
        if first.size:
            values[:, WRAPPED] = first[0] + wrap_deg(yaw - first[0])
        units.append(Unit(serial, [r["capture_time"] for r in rows], values, sigmas, poor,
                          acc_range(rows[-1]["result"])))
    return units


def wrap_deg(angle):
    """An angle (deg) into [-180, 180)."""
    return (np.asarray(angle) + 180.0) % 360.0 - 180.0


def acc_range(result: str | None) -> int | None:
    """The accelerometers' range (g) the result document names, None when it does not."""
    try:
        found = json.loads(result or "{}").get("sensor", {}).get("acc_range_g")
    except (ValueError, AttributeError):
        return None
    return found if found in spec.ACC else None


def history(unit: Unit) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The earlier results' usable values: (count, mean, standard deviation (NaN below 2), the
    mean sigma^2 (NaN where no sigma)), each over NAMES."""
    use = unit.usable[:-1]
    values = np.where(use, unit.values[:-1], np.nan)
    count = use.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN column (no inclinometers) is expected
        mean = np.nanmean(values, axis=0)
        scatter = np.where(count >= 2, np.nanstd(values, axis=0, ddof=1), np.nan)
        sigma2 = np.nanmean(np.where(use, unit.sigmas[:-1] ** 2, np.nan), axis=0)
    return count, mean, scatter, sigma2


def pool(units: list[Unit]) -> Pooled:
    """Every unit's earlier usable values about its own mean, pooled: the sum of squares over
    the sum of (n - 1); units with fewer than two such values add nothing."""
    squares = np.zeros(len(NAMES))
    dof = np.zeros(len(NAMES))
    sigma2_sum = np.zeros(len(NAMES))
    sigma2_count = np.zeros(len(NAMES))
    for unit in units:
        count, mean, scatter, sigma2 = history(unit)
        counted = count >= 2
        squares += np.where(counted, np.nan_to_num(scatter) ** 2 * (count - 1), 0.0)
        dof += np.where(counted, count - 1, 0)
        has_sigma = counted & np.isfinite(sigma2)
        sigma2_sum += np.where(has_sigma, np.nan_to_num(sigma2) * count, 0.0)
        sigma2_count += np.where(has_sigma, count, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return Pooled(np.sqrt(squares / dof), dof, sigma2_sum / sigma2_count)


def verdict(unit: Unit, pooled: Pooled) -> Verdict:
    """The latest result of each estimate against the unit's history (the module's rule)."""
    count, mean, scatter, sigma2 = history(unit)
    own = count >= MIN_OWN_HISTORY
    used_scatter = np.where(own, scatter, pooled.scatter)
    dof = np.where(own, count - 1, pooled.dof)
    reference = np.nan_to_num(np.where(own, sigma2, pooled.sigma2))
    latest, sigma = unit.values[-1], np.nan_to_num(unit.sigmas[-1])
    untested = [untested_reason(latest[k], unit.poor[-1, k], count[k], dof[k], used_scatter[k])
                for k in range(len(NAMES))]
    tested = np.array([why is None for why in untested])
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.sqrt(used_scatter ** 2 * (1.0 + 1.0 / count) + np.maximum(sigma ** 2 - reference, 0.0))
        spread = np.where(tested, spread, np.nan)
        t = (latest - mean) / spread
    return Verdict(count, mean, scatter, own, spread, t, dof, normal_sigmas(t, dof), untested)


def untested_reason(latest: float, poor: bool, count: int, dof: float, scatter: float) -> str | None:
    if not np.isfinite(latest):
        return "no latest value"
    if poor:
        return "the latest is poor"
    if count == 0:
        return "no usable earlier result"
    if not dof >= 1 or not scatter > 0:
        return "no run-to-run scatter to compare with"
    return None


def normal_sigmas(t: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """The normal deviate whose two-sided tail probability is t's with `dof` degrees of freedom."""
    from scipy.special import ndtri, stdtr

    with np.errstate(invalid="ignore", divide="ignore"):
        return -ndtri(stdtr(np.maximum(dof, 1), -np.abs(t)))


def datasheet(name: str, unit: Unit) -> tuple[float | None, str]:
    """The datasheet figure an estimate's run-to-run spread compares with (in its unit, None
    where there is none) and what it is, citing the table (STIM300 datasheet TS1524 rev.31)."""
    if name.startswith("gyro_bias"):
        return spec.GYRO.bias_run_to_run, f"run-to-run, {spec.GYRO.table}"
    if name.startswith("acc_bias"):
        if unit.acc_range_g is None:
            return None, "accelerometer range unknown"
        triad = spec.ACC[unit.acc_range_g]
        return triad.bias_one_year, f"one-year stability, {triad.table}"
    if name.startswith("incl_bias"):
        return spec.INCL.bias_run_to_run, f"none stated, {spec.INCL.table}"
    return None, "the mount's, not the sensor's"


def datasheet_text(name: str, unit: Unit) -> str:
    figure, what = datasheet(name, unit)
    return what if figure is None else f"{figure:g} {UNITS[name]} ({what})"


# ---------------------------------------------------------------- text

def display(name: str, value: float) -> float:
    return float(wrap_deg(value)) if name == "yaw" else float(value)


def unit_rows(unit: Unit, v: Verdict) -> list[dict[str, str]]:
    """The unit's table, one dict a shown estimate: the cells as text (units.value_sigma_texts
    rounding), shared by the text and the HTML report."""
    rows = []
    for k, name in enumerate(NAMES):
        if not np.isfinite(unit.values[:, k]).any():
            continue  # no result has it (a unit without inclinometers)
        value, sigma = unit.values[-1, k], unit.sigmas[-1, k]
        if np.isfinite(value):
            value_text, sigma_text = value_sigma_texts(display(name, value), sigma if np.isfinite(sigma) else None)
            latest = f"{value_text} +- {sigma_text}" if sigma_text else value_text
            latest += " (poor)" if unit.poor[-1, k] else ""
        else:
            latest = "none"
        mean_text, scatter_text = (value_sigma_texts(display(name, v.mean[k]), v.scatter[k])
                                   if np.isfinite(v.mean[k]) else ("n/a", None))
        spread = (f"{scatter_text} {UNITS[name]} ({counted(v.count[k], 'result')})" if scatter_text
                  else f"n/a ({counted(v.count[k], 'earlier result')})")
        rows.append({"estimate": name, "unit": UNITS[name], "latest": latest, "mean": mean_text,
                     "spread": spread, "datasheet": datasheet_text(name, unit), "flag": flag_text(v, k)})
    return rows


def flag_text(v: Verdict, k: int) -> str:
    if v.untested[k]:
        return f"not tested: {v.untested[k]}"
    basis = "" if v.own[k] else ", fleet scatter"
    verdict_text = "OUT OF FAMILY" if v.flagged[k] else "ok"
    return f"{verdict_text} {fixed(v.sigmas[k], 1)} sigma{basis}"


HEADINGS = {"estimate": "estimate", "unit": "unit", "latest": "latest +- 1-sigma", "mean": "history mean",
            "spread": "run-to-run spread", "datasheet": "datasheet", "flag": "latest vs history"}


def text_table(rows: list[dict[str, str]], indent: str = "  ") -> list[str]:
    widths = {key: max(len(HEADINGS[key]), *(len(r[key]) for r in rows)) for key in HEADINGS}
    right = {"latest", "mean"}

    def line(cells):
        return indent + "  ".join(cells[k].rjust(widths[k]) if k in right else cells[k].ljust(widths[k])
                                  for k in HEADINGS).rstrip()
    return [line(HEADINGS)] + [line(r) for r in rows]


def counted(number: float, noun: str) -> str:
    """`3 results`, `1 result`."""
    return f"{number:.0f} {noun}{'' if number == 1 else 's'}"


def when(time: datetime.datetime | None) -> str:
    return "unknown time" if time is None else time.astimezone(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def flags(fleet: Fleet) -> list[tuple[Unit, str, str]]:
    """Each out-of-family estimate: (unit, estimate, the one-line account)."""
    found = []
    for unit, v in zip(fleet.units, fleet.verdicts):
        limits = v.limit()
        for k in np.flatnonzero(v.flagged):
            name = NAMES[k]
            u = UNITS[name]
            earlier = counted(v.count[k], "earlier result")
            basis = "its history's" if v.own[k] else f"the fleet's (the unit has {earlier})"
            mean_text, _ = value_sigma_texts(display(name, v.mean[k]), v.spread[k])
            off_text, limit_text = value_sigma_texts(unit.values[-1, k] - v.mean[k], limits[k])
            latest = value_sigma(display(name, unit.values[-1, k]), unit.sigmas[-1, k], u)
            found.append((unit, name, f"{unit.serial} {name}: {latest} on {when(unit.times[-1])} is "
                                      f"{fixed(v.sigmas[k], 1)} sigma out of family: {off_text} {u} from the mean "
                                      f"{mean_text} {u} of {earlier}, beyond its limit of {limit_text} {u} (Student "
                                      f"t = {fixed(v.t[k], 1)}, {counted(v.dof[k], 'degree')} of freedom, on {basis} "
                                      "run-to-run scatter)"))
    return found


def summary(fleet: Fleet) -> str:
    results = sum(len(u.times) for u in fleet.units)
    times = [t for u in fleet.units for t in u.times if t is not None]
    span = f", {when(min(times))} to {when(max(times))}" if times else ""
    return (f"{fleet.table}: {counted(len(fleet.units), 'unit')}, {counted(results, 'calibrated power-up')}{span} "
            f"({counted(fleet.rows, 'row')}; "
            f"{fleet.not_ok} not ok, {fleet.repeats} repeated sessions left out)")


def pooled_rows(fleet: Fleet) -> list[str]:
    """The fleet's pooled run-to-run spread per estimate beside the datasheet."""
    lines = []
    for k, name in enumerate(NAMES):
        if not fleet.pooled.dof[k] >= 1:
            continue
        _, text = value_sigma_texts(0.0, fleet.pooled.scatter[k])
        lines.append(f"  {name:<12} {text:>8} {UNITS[name]:<5} ({counted(fleet.pooled.dof[k], 'degree')} of freedom)  "
                     f"datasheet: {datasheet_text(name, fleet.units[0])}")
    return lines


def text_report(fleet: Fleet) -> str:
    lines = [summary(fleet), ""]
    for unit, v in zip(fleet.units, fleet.verdicts):
        lines.append(f"{unit.serial}: {counted(len(unit.times), 'result')}, latest {when(unit.times[-1])}")
        lines += text_table(unit_rows(unit, v)) + [""]
    lines.append("run-to-run spread of the fleet (every unit's earlier results about its own mean, pooled):")
    lines += pooled_rows(fleet) + [""]
    found = flags(fleet)
    tested = sum(int(np.sum(~np.isnan(v.spread))) for v in fleet.verdicts)
    lines.append(f"out of family (latest beyond {OUT_OF_FAMILY_SIGMAS:g} sigma of the history; "
                 f"{counted(tested, 'latest estimate')} tested): {len(found) or 'none'}")
    lines += [f"  {text}" for _, _, text in found]
    return "\n".join(lines) + "\n"

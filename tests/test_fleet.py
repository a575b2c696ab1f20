"""`calibd fleet`: the out-of-family rule's numbers and false-flag rate on hand-made histories,
which rows count, and on a simulated fleet (tests/fleet_captures.py) the stepped unit flagged on
its stepped estimate and nothing else, in the text and in a self-contained HTML page; bad
inputs as one line and exit status 2."""

import datetime
import json
import math
import re
import sys

import numpy as np
import pytest
from scipy import stats

from calibd import fleettable
from calibd.cli import main as calibd_main
from calibd.fleet import (MIN_OWN_HISTORY, NAMES, Pooled, Unit, analyse, calibrated, datasheet, flags,
                          text_report, unit_rows, verdict)
from fleet_captures import CAPTURES_PER_UNIT, SERIALS, STEP_ESTIMATE, STEPPED

T0 = datetime.datetime(2026, 1, 5, 9, 0, tzinfo=datetime.timezone.utc)
GYRO_X = NAMES.index("gyro_bias_x")
THREE_SIGMA = math.erf(3 / math.sqrt(2))  # two-sided


def make_row(serial: str, day: int, estimates: dict, session: str | None = None, version: str = "0.1.0",
             status: str = "ok") -> dict:
    """A fleet-table row of a result: `estimates` maps a name to (value, sigma) or (value, sigma, quality)."""
    row = fleettable.empty_row() | {
        "capture": f"/captures/{serial}-{day}.bin", "capture_time": T0 + datetime.timedelta(days=day), "power_up": 1,
        "power_ups": 1, "session_id": session or f"{serial}/{day}", "serial_number": serial, "calibd_version": version,
        "settings": "{}", "method": "joint", "status": status, "warnings": [],
        "result": json.dumps({"sensor": {"serial_number": serial, "acc_range_g": 10}})}
    if status == "ok":
        for name, (value, sigma, *quality) in estimates.items():
            row |= {name: value, f"{name}_sigma": sigma, f"{name}_quality": quality[0] if quality else None}
    return row


def history_rows(serial: str, values, sigma: float = 1.0, name: str = "gyro_bias_x") -> list[dict]:
    return [make_row(serial, day, {name: (float(v), sigma)}) for day, v in enumerate(values)]


def one_unit(values, sigmas, poor=None) -> Unit:
    values = np.asarray(values, dtype=float).reshape(len(values), -1)
    return Unit("SN", [T0] * len(values), values, np.asarray(sigmas, dtype=float).reshape(values.shape),
                np.zeros(values.shape, bool) if poor is None else np.asarray(poor).reshape(values.shape), 10)


NO_FLEET = Pooled(np.full(len(NAMES), np.nan), np.zeros(len(NAMES)), np.full(len(NAMES), np.nan))


# ---------------------------------------------------------------- the rule's numbers

def test_the_latest_is_tested_with_a_student_t_prediction_interval():
    history = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    fleet = analyse("t.parquet", history_rows("A", history + [10.0]))
    v = fleet.verdicts[0]
    s = np.std(history, ddof=1)
    t = 7.5 / (s * math.sqrt(1 + 1 / 6))
    assert v.t[GYRO_X] == pytest.approx(t)
    assert v.dof[GYRO_X] == 5 and v.own[GYRO_X]
    assert v.sigmas[GYRO_X] == pytest.approx(stats.norm.isf(stats.t.sf(t, 5)))  # the same tail probability
    assert v.limit()[GYRO_X] == pytest.approx(s * math.sqrt(1 + 1 / 6) * stats.t.ppf(1 - (1 - THREE_SIGMA) / 2, 5))
    assert v.sigmas[GYRO_X] == pytest.approx(2.46, abs=0.01) and not v.flagged[GYRO_X]  # t = 3.7, 5 dof
    v = analyse("t.parquet", history_rows("A", history + [14.0])).verdicts[0]
    assert v.sigmas[GYRO_X] == pytest.approx(3.04, abs=0.01) and v.flagged[GYRO_X]  # t = 5.7, beyond 5.5


def test_a_noisier_latest_widens_the_interval_by_its_excess_sigma_only():
    rows = history_rows("A", [0.0, 1.0, 2.0, 3.0, 4.0, 5.0], sigma=1.0) + [
        make_row("A", 6, {"gyro_bias_x": (10.0, 3.0)})]
    v = analyse("t.parquet", rows).verdicts[0]
    s2 = np.var([0.0, 1.0, 2.0, 3.0, 4.0, 5.0], ddof=1)
    assert v.spread[GYRO_X] == pytest.approx(math.sqrt(s2 * (1 + 1 / 6) + 3.0 ** 2 - 1.0 ** 2))


def test_a_clean_unit_is_flagged_at_the_rate_of_3_sigma():
    """20000 clean histories of eight results (seven earlier): the t interval keeps the false-flag
    rate at 0.27 %, where a normal 3-sigma limit on the sample scatter would flag 2.3 %."""
    rng = np.random.default_rng(5)
    units = 2000
    values = rng.normal(0.0, 4.0, (units, CAPTURES_PER_UNIT, len(NAMES)))
    sigmas = np.ones_like(values)
    flagged = sum(int(verdict(one_unit(values[u], sigmas[u]), NO_FLEET).flagged.sum()) for u in range(units))
    tests = units * len(NAMES)
    expected = tests * (1 - THREE_SIGMA)
    assert abs(flagged - expected) < 4 * math.sqrt(expected), (flagged, expected)


def test_a_short_history_is_tested_on_the_fleets_pooled_scatter():
    rng = np.random.default_rng(3)
    long_units = [history_rows(serial, 50.0 + rng.normal(0, 4.0, 8)) for serial in ("A", "B")]
    short = history_rows("C", [50.0, 52.0, 85.0])  # two earlier results: too few for its own scatter
    fleet = analyse("t.parquet", long_units[0] + long_units[1] + short)
    v = fleet.verdicts[2]
    assert v.count[GYRO_X] == 2 < MIN_OWN_HISTORY and not v.own[GYRO_X]
    assert v.dof[GYRO_X] == fleet.pooled.dof[GYRO_X] == 6 + 6 + 1  # the seven earlier results of A and B, its pair
    pooled = fleet.pooled.scatter[GYRO_X]
    assert v.spread[GYRO_X] == pytest.approx(pooled * math.sqrt(1 + 1 / 2))
    assert v.flagged[GYRO_X]  # 34 deg/h off on 5.8 deg/h of scatter
    assert ", fleet scatter" in {r["estimate"]: r for r in unit_rows(fleet.units[2], v)}["gyro_bias_x"]["flag"]


def test_a_first_result_is_not_tested():
    fleet = analyse("t.parquet", history_rows("A", [1.0, 2.0, 3.0, 1.5, 2.5, 3.0]) + history_rows("B", [99.0]))
    v = fleet.verdicts[1]
    assert v.untested[GYRO_X] == "no usable earlier result" and not v.flagged.any()


def test_poor_estimates_are_shown_but_left_out_of_the_statistics():
    rows = history_rows("A", [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    rows.insert(3, make_row("A", 3, {"gyro_bias_x": (500.0, 1.0, "poor")}, session="A/poor"))
    rows.append(make_row("A", 9, {"gyro_bias_x": (2.0, 1.0)}))
    v = analyse("t.parquet", rows).verdicts[0]
    assert v.count[GYRO_X] == 6 and v.mean[GYRO_X] == pytest.approx(2.5)
    rows[-1] = make_row("A", 9, {"gyro_bias_x": (900.0, 1.0, "poor")})
    fleet = analyse("t.parquet", rows)
    v = fleet.verdicts[0]
    assert v.untested[GYRO_X] == "the latest is poor" and not v.flagged.any()
    shown = {r["estimate"]: r for r in unit_rows(fleet.units[0], v)}["gyro_bias_x"]
    assert shown["latest"] == "900.0 +- 1.0 (poor)"


def test_yaw_is_compared_modulo_360_degrees():
    yaws = [179.0, -179.5, 179.5, -179.0, 178.8, -179.2, 179.9, -179.8]
    fleet = analyse("t.parquet", [make_row("A", day, {"yaw": (y, 0.5)}) for day, y in enumerate(yaws)])
    v = fleet.verdicts[0]
    k = NAMES.index("yaw")
    assert v.scatter[k] < 1.0 and not v.flagged[k]
    assert {r["estimate"]: r for r in unit_rows(fleet.units[0], v)}["yaw"]["mean"].startswith(("179.", "-179."))


def test_one_row_per_session_the_highest_version_the_last_of_equals():
    rows = [make_row("A", 0, {"gyro_bias_x": (1.0, 1.0)}, session="s1", version="0.10.0"),
            make_row("A", 0, {"gyro_bias_x": (2.0, 1.0)}, session="s1", version="0.9.0"),  # "0.9" > "0.10" as text
            make_row("A", 1, {"gyro_bias_x": (3.0, 1.0)}, session="s2"),
            make_row("A", 1, {"gyro_bias_x": (4.0, 1.0)}, session="s2"),  # the same version: the last row
            make_row("A", 2, {}, session="s3", status="refused")]
    kept = calibrated(rows)
    assert sorted(r["gyro_bias_x"] for r in kept) == [1.0, 4.0]
    fleet = analyse("t.parquet", rows)
    assert (fleet.rows, fleet.not_ok, fleet.repeats) == (5, 1, 2)
    assert "5 rows; 1 not ok, 2 repeated sessions left out" in text_report(fleet)


def test_the_datasheet_figures_beside_the_spread():
    fleet = analyse("t.parquet", history_rows("A", [1.0, 2.0]))
    unit = fleet.units[0]
    assert datasheet("gyro_bias_y", unit) == (4.0, "run-to-run, Table 5-3")
    assert datasheet("acc_bias_z", unit) == (1.9, "one-year stability, Table 5-5")
    assert datasheet("incl_bias_x", unit) == (None, "none stated, Table 5-8")
    assert datasheet("yaw", unit)[0] is None


# ---------------------------------------------------------------- bad inputs

@pytest.fixture
def small_table(tmp_path):
    path = tmp_path / "small.parquet"
    fleettable.write_table(path, history_rows("A", [1.0, 2.0, 3.0]) + history_rows("B", [5.0, 6.0]), durable=False)
    return path


def test_bad_inputs_are_one_line_and_exit_2(run_main, tmp_path, small_table):
    text = tmp_path / "notes.txt"
    text.write_text("not parquet\n")
    empty = tmp_path / "empty.parquet"
    fleettable.write_table(empty, [], durable=False)
    newer = tmp_path / "newer.parquet"
    data = fleettable.table(history_rows("A", [1.0]))
    fleettable.pyarrow().parquet.write_table(data.replace_schema_metadata({fleettable.SCHEMA_KEY: b"calibd.fleet/2"}),
                                             newer)
    refused = tmp_path / "refused.parquet"
    fleettable.write_table(refused, [make_row("A", 0, {}, status="refused")], durable=False)
    cases = {(text,): "not a fleet table", (empty,): "empty fleet table", (newer,): "newer than this calibd reads",
             (refused,): "no calibrated power-up in the table (0 ok, 1 refused",
             (tmp_path / "missing.parquet",): "no such file",
             (small_table, "--serial", "N000"): "no calibrated power-up of serial number 'N000' (the table has A, B)",
             (small_table, "--html", tmp_path): "is a directory"}
    for args, said in cases.items():
        code, out, err = run_main(calibd_main, ["fleet", *args])
        assert code == 2 and out == "", args
        assert err.count("\n") == 1 and said in err and str(args[0] if len(args) == 1 else args[-1]) in err, err


def test_html_without_matplotlib_is_one_line(run_main, monkeypatch, small_table, tmp_path):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    code, out, err = run_main(calibd_main, ["fleet", small_table, "--html", tmp_path / "r.html"])
    assert code == 2 and err == "calibd fleet --html needs matplotlib: pip install 'stim300-calib[plot]'\n"
    assert not (tmp_path / "r.html").exists()


# ---------------------------------------------------------------- a simulated fleet

@pytest.fixture(scope="module")
def fleet_table(fleet_batch):
    """The simulated fleet's table as `calibd batch` made it (tests/conftest.py)."""
    return fleet_batch[2]


@pytest.mark.slow
def test_the_stepped_unit_is_flagged_on_the_stepped_estimate_only(fleet_table):
    fleet = analyse(str(fleet_table), fleettable.read_rows(fleet_table))
    assert [u.serial for u in fleet.units] == sorted(SERIALS)
    assert all(len(u.times) == CAPTURES_PER_UNIT for u in fleet.units)
    flagged = {(u.serial, NAMES[k]) for u, v in zip(fleet.units, fleet.verdicts) for k in np.flatnonzero(v.flagged)}
    assert flagged == {(STEPPED, STEP_ESTIMATE)}
    unit = next(u for u in fleet.units if u.serial == STEPPED)
    v = fleet.verdicts[fleet.units.index(unit)]
    k = NAMES.index(STEP_ESTIMATE)
    assert v.own[k] and v.dof[k] == CAPTURES_PER_UNIT - 2
    assert 2.0 < v.scatter[k] < 8.0  # the datasheet's 4 deg/h run-to-run and each result's noise
    # the fleet's pooled gyro run-to-run spread lies near the datasheet's 4 deg/h
    gyro = [NAMES.index(f"gyro_bias_{a}") for a in "xyz"]
    assert np.all((fleet.pooled.scatter[gyro] > 2.5) & (fleet.pooled.scatter[gyro] < 7.0))


@pytest.mark.slow
def test_the_text_names_the_flag_and_each_unit(fleet_table, run_main):
    code, out, err = run_main(calibd_main, ["fleet", fleet_table])
    assert code == 0 and err == ""
    assert "latest estimates tested): 1\n" in out
    flag_lines = [line for line in out.splitlines() if line.startswith(f"  {STEPPED} {STEP_ESTIMATE}: ")]
    assert len(flag_lines) == 1 and "sigma out of family" in flag_lines[0] and "2026-03-09" in flag_lines[0]
    for serial in SERIALS:
        assert f"\n{serial}: {CAPTURES_PER_UNIT} results" in out
    table_line = next(line for line in out.splitlines() if line.startswith(f"  {STEP_ESTIMATE} "))
    assert "deg/h" in table_line and "4 deg/h (run-to-run, Table 5-3)" in table_line


@pytest.mark.slow
def test_serial_filters_the_report(fleet_table, run_main):
    other = SERIALS[0]
    code, out, _ = run_main(calibd_main, ["fleet", fleet_table, "--serial", other])
    assert code == 0 and f"\n{other}: " in out and STEPPED not in out
    assert "1 unit, 8 calibrated power-ups" in out and "latest estimates tested): none" in out
    code, out, _ = run_main(calibd_main, ["fleet", fleet_table, "--serial", STEPPED])
    assert code == 0 and other not in out and f"  {STEPPED} {STEP_ESTIMATE}: " in out


@pytest.mark.slow
def test_the_html_is_self_contained_with_a_figure_per_unit_and_group(fleet_table, run_main, tmp_path):
    page = tmp_path / "fleet.html"
    code, out, err = run_main(calibd_main, ["fleet", fleet_table, "--html", page])
    assert code == 0 and err == "" and STEPPED in out
    html = page.read_text()
    figures = re.findall(r'<figure class="group" data-serial="([^"]+)" data-group="([^"]+)"><img src="([^"]+)"', html)
    groups = ("mounting", "platform axis", "gyro biases", "accelerometer biases", "inclinometer biases")
    assert sorted((s, g) for s, g, _ in figures) == sorted((s, g) for s in SERIALS for g in groups)
    assert all(src.startswith("data:image/png;base64,iVBOR") for _, _, src in figures)
    assert all(src.startswith("data:") for src in re.findall(r'\ssrc="([^"]*)"', html))
    assert all(href.startswith("#") for href in re.findall(r'\shref="([^"]*)"', html))
    assert "<link" not in html and "<script" not in html and "url(" not in html
    assert f'<tr data-estimate="{STEP_ESTIMATE}" class="out">' in html
    assert html.count('class="out"') == 1
    assert re.search(rf'<li data-serial="{STEPPED}" data-estimate="{STEP_ESTIMATE}">', html)


def test_flags_lists_each_flag_with_its_numbers():
    rows = history_rows("A", [10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 40.0])
    fleet = analyse("t.parquet", rows)
    ((unit, name, text),) = flags(fleet)
    assert (unit.serial, name) == ("A", "gyro_bias_x")
    assert text.startswith("A gyro_bias_x: 40.0 +- 1.0 deg/h on 2026-01-11 09:00 UTC is ")
    assert "from the mean 12.5 deg/h of 6 earlier results" in text and "5 degrees of freedom" in text

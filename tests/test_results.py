"""The typed calibration result: its JSON round-trips, its version policy (older read, newer and
other schemas refused in one line), copies instead of in-place changes; the truth file's schema."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibd.frames import Site
from calibd.report import read_truth
from calibd.documents import SchemaError, schema_version
from calibd.results import (SCHEMA, CalibrationResult, Estimate, ResultError, ResultStream, load_result, make_result,
                            result_json, write_result)
from calibd.units import DEG
from stim300.records import SensorRecord

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def joint_like() -> CalibrationResult:
    return make_result("joint", Site(60.0), {"yaw": (0.5 * DEG, 0.1 * DEG), "gyro_bias_x": (1e-6, None)},
                       [{"kind": "static", "role": "static", "start_s": 0.0, "end_s": 60.0}], ["a warning"],
                       SensorRecord(serial_number="N1"), stream=ResultStream(capture="c.bin"),
                       options={"fixed_amplitude": False},
                       checks={"static_chi2": {"chi2": 3.0, "dof": 4, "p_value": 0.5}}, bias_reference="turn-on")


def test_estimates_are_in_the_units_people_read():
    result = joint_like()
    assert result.estimates["yaw"] == Estimate(pytest.approx(0.5), pytest.approx(0.1), "deg")
    assert result.estimates["gyro_bias_x"].value == pytest.approx(1e-6 * 3600 / DEG)
    assert result.estimates["gyro_bias_x"].unit == "deg/h" and result.estimates["gyro_bias_x"].sigma is None


def test_a_result_round_trips_through_its_file(tmp_path):
    result = joint_like().flag_poor(["yaw"], "yaw is poor")
    write_result(tmp_path / "r.json", result)
    assert load_result(tmp_path / "r.json") == result
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["schema"] == SCHEMA == "calibd.result/7"
    assert list(doc) == ["schema", "method", "software", "session_id", "site", "estimates", "rotation", "covariance",
                         "segments", "warnings", "sensor", "stream",
                         "options", "checks", "bias_reference"]  # unset optional fields are not written
    assert doc["rotation"] is None and doc["covariance"] is None  # no pitch and roll; no covariance given
    assert doc["estimates"]["yaw"]["quality"] == "poor" and "quality" not in doc["estimates"]["gyro_bias_x"]


def test_changes_are_copies():
    result = joint_like()
    flagged = result.flag_poor(["yaw"], "why")
    assert result.estimates["yaw"].quality is None and result.warnings == ("a warning",)
    assert flagged.estimates["yaw"].quality == "poor" and flagged.estimates["gyro_bias_x"].quality is None
    assert flagged.warnings == ("a warning", "why")
    assert result.with_warning("first", first=True).warnings == ("first", "a warning")


def test_a_version_1_file_is_read(tmp_path):
    """A result as calibd wrote it before the typed result: schema 1, no optional fields. What
    version 3 adds takes its default (None: not known), or follows from the estimates (SI), and
    it is written back as the current version (its sensor record with every field)."""
    doc = {"schema": "calibd.result/1", "method": "thesis-linear", "site": {"latitude_deg": 40.0},
           "estimates": {"yaw": {"value": 0.0, "sigma": None, "unit": "deg"}}, "warnings": ["w"]}
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    result = load_result(path)
    assert result.schema == "calibd.result/1" and result.method == "thesis-linear"
    assert result.estimates["yaw"] == Estimate(0.0, None, "deg") and result.warnings == ("w",)
    assert result.stream == ResultStream() and result.segments == () and result.checks is None and result.stale is None
    assert result.software is None and result.session_id is None and result.covariance is None
    assert result.estimates["yaw"].value_si == 0.0 and result.estimates["yaw"].unit_si == "rad"
    assert json.loads(result_json(result)) == doc | {
        "schema": SCHEMA, "software": None, "session_id": None, "rotation": None, "covariance": None,
        "estimates": {"yaw": {"value": 0.0, "sigma": None, "unit": "deg", "value_si": 0.0, "sigma_si": None,
                              "unit_si": "rad"}},
        "segments": [], "stream": {}, "sensor": SensorRecord().to_dict()}  # every field, null: not known


@pytest.mark.parametrize("schema, message", [
    ("calibd.result/8", "r.json is calibd.result/8, newer than this calibd reads (up to 7): upgrade calibd"),
    ("calibd.noise/1", "r.json is 'calibd.noise/1', not a calibd.result file"),
    ("calibd.result/x", "r.json is 'calibd.result/x', not a calibd.result file"),
    (None, "r.json is None, not a calibd.result file"),
])
def test_newer_versions_and_other_schemas_are_refused_in_one_line(tmp_path, schema, message):
    path = tmp_path / "r.json"
    path.write_text(json.dumps(joint_like().to_dict() | {"schema": schema}))
    with pytest.raises(ResultError) as refusal:
        load_result(path)
    assert str(refusal.value) == f"{path.parent}/{message}"


def test_the_version_policy_reads_former_names():
    assert schema_version("stim300-calib/truth/1", "calibd.truth", 1, "t", ("stim300-calib/truth",)) == 1
    with pytest.raises(SchemaError, match="newer than this calibd reads"):
        schema_version("calibd.truth/2", "calibd.truth", 1, "t")


def test_the_truth_file_is_read_under_its_new_and_its_former_name(tmp_path):
    source = FIXTURES / "heading137_lat60_125hz.bin.truth.json"
    record = json.loads(source.read_text())
    assert record["schema"] == "calibd.truth/2"
    expected = read_truth(str(source).removesuffix(".truth.json"))
    assert expected is not None
    for schema, readable in (("stim300-calib/truth/1", True), ("calibd.truth/1", True), ("calibd.truth/3", False)):
        capture = tmp_path / f"{schema.replace('/', '_')}.bin"
        Path(f"{capture}.truth.json").write_text(json.dumps(record | {"schema": schema}))
        assert read_truth(str(capture)) == (expected if readable else None), schema


def test_a_version_1_truth_has_no_factory_residuals_and_reads_as_before(tmp_path):
    """Version 1 truths came from a perfect sensor: the factory residuals they lack are zero."""
    record = json.loads((FIXTURES / "heading137_lat60_125hz.bin.truth.json").read_text())
    residuals = [key for key in record["truth"] if key.endswith(("_scale_ppm", "_misalignment_mrad"))]
    assert len(residuals) == 6 and all(not any(record["truth"][key]) for key in residuals)
    truth = {k: v for k, v in record["truth"].items() if k not in residuals}
    old = record | {"schema": "calibd.truth/1", "truth": truth}
    capture = tmp_path / "old.bin"
    Path(f"{capture}.truth.json").write_text(json.dumps(old))
    assert read_truth(str(capture)) == read_truth(str(FIXTURES / "heading137_lat60_125hz.bin"))


def test_status_refuses_a_newer_result_in_one_line(tmp_path, capsys):
    from calibd.cli import main as calibd_main

    (tmp_path / "state.json").write_text(json.dumps({"state": "SOLVED", "detail": "solved", "updated": 0}))
    (tmp_path / "result.json").write_text(json.dumps(joint_like().to_dict() | {"schema": "calibd.result/8"}))
    assert calibd_main(["status", "--state-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "calibd.result/8, newer than this calibd reads (up to 7): upgrade calibd" in err


def test_numpy_scalars_in_a_result_are_written_as_plain_json():
    """A check's flag computed with numpy is a numpy bool: the file holds true/false, not a crash."""
    result = replace(joint_like(), checks={"turn_angles": [{"corrected": np.bool_(True), "gyro_deg": np.float64(90.5),
                                                            "n": np.int64(3)}]})
    doc = json.loads(result_json(result))
    assert doc["checks"]["turn_angles"] == [{"corrected": True, "gyro_deg": 90.5, "n": 3}]
    with pytest.raises(TypeError):
        result_json(replace(result, checks={"bad": object()}))


@pytest.mark.slow
def test_a_calibrated_capture_names_the_file_it_came_from(tmp_path):
    """The result says which bytes it rests on: size, SHA-256 and the sensor's serial number."""
    import hashlib

    from calibd.calibrate import calibrate_capture
    from calibd.captures import open_capture
    from calibd.methods import estimator

    path = "fixtures/thesis_real_cw_125hz.bin"
    data = open(path, "rb").read()
    method = estimator("joint")
    site = Site(40.59129)
    result = calibrate_capture(open_capture(path), lambda s: method.solve(s, site, None, method.options({})))
    assert result.capture == {"path": path, "size_bytes": len(data), "sha256": hashlib.sha256(data).hexdigest(),
                              "serial_number": "N25582405002002"}
    write_result(tmp_path / "r.json", result)
    assert load_result(tmp_path / "r.json").capture == result.capture

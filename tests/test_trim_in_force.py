"""The bias trim offsets in force, from the stream to the result: a power-up's Bias Trim Offset
datagram becomes `sensor.trim`, each bias estimate states its untrimmed value (estimate - trim),
a result without one says null, and a document whose trim is not a unit's is refused in one line."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from calibd.cli import main as calibd_main
from calibd.frames import Site
from calibd.results import ResultError, load_result, make_result, parse_result, result_json
from calibd.scenario import load_scenario
from calibd.session import decode_sessions, power_up_session
from calibd.sim import power_up_datagrams
from calibd.units import DEG
from stim300.records import SensorRecord, TrimRecord
from stim300.special import BiasTrimOffset, encode_special

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
FULL = FIXTURES / "thesis_real_cw_125hz.bin"  # simulated from the thesis-real scenario, one power-up
REAL = load_scenario("thesis-real")
HEAD = power_up_datagrams(REAL)  # FULL's power-up datagrams
# offsets of whole counts (gyro 2^-14 deg/s, 10 g acc 2^-19 g, incl 2^-22 g), so they read back exactly
TRIM = BiasTrimOffset(gyro=(164 * 2 ** -14, -328 * 2 ** -14, 49 * 2 ** -14),
                      acc=(524 * 2 ** -19, 0.0, -26214 * 2 ** -19),
                      incl=(0.0, 41943 * 2 ** -22, -4194 * 2 ** -22), reference_info=1234, remaining_saves=9000)
RECORD = TrimRecord(TRIM.gyro, TRIM.acc, TRIM.incl, 1234, 9000)
SCALE = {"gyro": 3600.0, "acc": 1000.0, "incl": 1000.0}  # deg/h per deg/s, mg per g


def trimmed_capture(trim: BiasTrimOffset = TRIM) -> bytes:
    """FULL as a unit whose configuration sends the BTO datagram at start-up would send it."""
    return power_up_datagrams(REAL, trim) + FULL.read_bytes()[len(HEAD):]


def test_the_power_up_datagrams_carry_the_trim_when_given():
    with_trim = power_up_datagrams(REAL, TRIM)
    assert with_trim.startswith(HEAD[:-36]) and with_trim.endswith(encode_special(TRIM, False, 10))
    session = power_up_session(decode_sessions(trimmed_capture(), "c.bin"))
    assert session.sensor.trim == RECORD and session.sensor.serial_number == REAL.sensor.serial_number
    assert power_up_session(decode_sessions(FULL.read_bytes(), "c.bin")).sensor.trim is None


@pytest.mark.slow
def test_a_result_on_trimmed_output_records_the_trim_and_the_untrimmed_biases(tmp_path, capsys):
    capture, out = tmp_path / "trimmed.bin", tmp_path / "r.json"
    capture.write_bytes(trimmed_capture())
    assert calibd_main(["calibrate", str(capture), "--latitude", "40.59129", "-o", str(out)]) == 0, \
        capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert doc["sensor"]["trim"] == RECORD.to_dict()
    biases = {name: e for name, e in doc["estimates"].items() if "_bias_" in name}
    assert len(biases) == 9
    for name, e in biases.items():
        triad, _, axis = name.partition("_bias_")
        assert e["untrimmed"] == pytest.approx(e["value"] - RECORD.of(triad)["xyz".index(axis)] * SCALE[triad],
                                               abs=1e-9)
    assert "untrimmed" not in doc["estimates"]["yaw"]
    assert load_result(out).sensor.trim == RECORD


def test_untrimmed_is_the_estimate_less_the_trim_in_its_unit():
    result = make_result("joint", Site(60.0), {"gyro_bias_x": (10 / 3600 * DEG, None),
                                               "acc_bias_z": (0.002 * 9.80665, None), "yaw": (0.1, None)},
                         [], [], SensorRecord(acc_range_g=10, trim=RECORD))
    assert result.untrimmed("gyro_bias_x") == pytest.approx(10 - RECORD.gyro_deg_s[0] * 3600)
    assert result.untrimmed("acc_bias_z") == pytest.approx(2 - RECORD.acc_g[2] * 1000)
    assert result.untrimmed("yaw") is None
    read = parse_result(result_json(result), "r.json")
    assert read == result and read.to_dict()["estimates"]["gyro_bias_x"]["untrimmed"] == result.untrimmed("gyro_bias_x")
    untrimmed = replace(result, sensor=SensorRecord(acc_range_g=10))
    assert untrimmed.untrimmed("gyro_bias_x") is None
    doc = json.loads(result_json(untrimmed))
    assert doc["sensor"]["trim"] is None and "untrimmed" not in doc["estimates"]["gyro_bias_x"]


def test_a_version_4_result_reads_with_the_trim_unknown():
    doc = json.loads(result_json(make_result("joint", Site(60.0), {"yaw": (0.1, None)}, [], [], SensorRecord())))
    doc["schema"] = "calibd.result/4"
    del doc["sensor"]["trim"]
    assert parse_result(json.dumps(doc), "r.json").sensor.trim is None


def test_a_trim_changed_within_a_power_up_is_the_last_and_said():
    """A T answered mid-stream (a raw pty's reader asked) after the trim changed: the power-up's
    record is the last, the stream's warnings say the data mix two trims; a later power-up's BTO
    datagram is its own."""
    data = FULL.read_bytes()
    middle = len(HEAD) + 59 * 50_000  # a datagram boundary (59-byte datagrams)
    other = replace(TRIM, gyro=(0.0, 0.0, 0.0))
    capture = trimmed_capture() + data[len(HEAD):middle] + encode_special(other, False, 10) + data[middle:]
    session = power_up_session(decode_sessions(capture, "c.bin"))
    assert session.sensor.trim == replace(RECORD, gyro_deg_s=(0.0, 0.0, 0.0))
    assert any("changed 1 time(s) during power-up 1" in w for w in session.stream.warnings)
    two = decode_sessions(FULL.read_bytes() + trimmed_capture(), "two.bin")
    assert [p.trim for p in two.power_ups] == [None, RECORD]


def test_a_trim_before_any_configuration_is_not_recorded():
    """Its accelerometer counts' scale is the configured range's: without a configuration it is unknown."""
    headless = FULL.read_bytes()[len(HEAD):]
    capture = encode_special(TRIM, False, 10) + headless
    session = power_up_session(decode_sessions(capture, "c.bin"))
    assert session.sensor.trim is None
    assert any("bias trim offset datagram before any configuration" in w for w in session.stream.warnings)


def _result_doc() -> dict:
    result = make_result("joint", Site(60.0), {"gyro_bias_x": (1e-6, None)}, [], [],
                         SensorRecord(acc_range_g=10, trim=RECORD))
    return json.loads(result_json(result))


@pytest.mark.parametrize("path, value, words", [
    ("gyro_deg_s", [1.5, 0, 0], "sensor.trim.gyro_deg_s[0] is 1.5, expected a number in [-1, 1]"),
    ("incl_g", [0, 0, -0.03], "sensor.trim.incl_g[2] is -0.03, expected a number in [-0.02, 0.02]"),
    ("acc_g", [0, 0.2, 0], "sensor: trim.acc_g is [0.0, 0.2, 0.0], beyond the +-0.1 g trim range of a 10 g unit"),
    ("acc_g", [0, 0], "sensor.trim.acc_g is [0, 0], expected a list of 3"),
    ("reference", 1 << 32, "sensor.trim.reference is 4294967296, expected a whole number in [0, 4.29497e+09]"),
    ("remaining_saves", -1, "sensor.trim.remaining_saves is -1, expected a whole number in [0, 65535]"),
    ("gyro_deg_s", None, "sensor.trim.gyro_deg_s is null, expected a list of 3"),
])
def test_a_trim_that_is_no_units_is_refused_in_one_line(path, value, words):
    doc = _result_doc()
    doc["sensor"]["trim"][path] = value
    with pytest.raises(ResultError) as caught:
        parse_result(json.dumps(doc), "r.json")
    message = str(caught.value)
    assert message.startswith("r.json: ") and "\n" not in message
    assert words in message, message


def test_an_80_g_units_accelerometer_trim_may_reach_its_wider_range():
    doc = _result_doc()
    doc["sensor"] |= {"acc_range_g": 80, "trim": doc["sensor"]["trim"] | {"acc_g": [0.7, 0, 0]}}
    assert parse_result(json.dumps(doc), "r.json").sensor.trim.acc_g == (0.7, 0.0, 0.0)


def test_an_untrimmed_value_beyond_the_estimates_range_is_refused():
    doc = _result_doc()
    doc["estimates"]["gyro_bias_x"]["untrimmed"] = 1e300
    with pytest.raises(ResultError, match=r"estimates.gyro_bias_x.untrimmed is 1e\+300, expected a number in"):
        parse_result(json.dumps(doc), "r.json")

"""Every document calibd reads (result, state, noise, truth, scenario) against its one schema
(calibd.documents): a hostile or malformed one is exit 2 with one stderr line naming the file and
the field, never a traceback, an internal error or a silent accept, and leaves no output; every
document calibd itself writes, and every fixture, passes its schema and reads back the same."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from calibd import documents
from calibd.cli import main as calibd_main
from calibd.results import load_result, parse_result, result_json
from calibd.scenario import READY_MADE, ScenarioError, load_scenario, truth_from_json

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
GOOD = FIXTURES / "heading137_lat60_125hz.bin"  # calibrates, has statics long enough for `noise`
SMALL = FIXTURES / "faults_125hz.bin"  # a capture quick to decode: the document fails before it matters
SCENARIO = (Path(documents.__file__).parent / "scenarios" / "thesis-real.toml").read_text()
DEEP = "[" * 5000 + "]" * 5000
HUGE = "9" * 5000


class Raw(str):
    """JSON text put in place of a value as it is (NaN, a deep nesting, a huge integer)."""


def _put(doc: dict, path: str, value) -> None:
    *keys, last = [int(k) if k.isdigit() else k for k in path.split(".")]
    for key in keys:
        doc = doc[key]
    if value is KeyError:
        del doc[last]
    else:
        doc[last] = value


def edited(text: str, path: str, value) -> str:
    """A JSON document's text with the value at `path` (dotted, list indices as numbers) replaced."""
    doc = json.loads(text)
    if not path:
        return value if isinstance(value, Raw) else json.dumps(value)
    _put(doc, path, "@@raw@@" if isinstance(value, Raw) else value)
    return json.dumps(doc).replace('"@@raw@@"', value) if isinstance(value, Raw) else json.dumps(doc)


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict[str, Path]:
    """Documents made by calibd's own commands: results of the joint method (with and without
    inclinometers) and of the thesis's real case and bench campaign, a noise file, the daemon's
    state directory."""
    d = tmp_path_factory.mktemp("made")
    runs = (["calibrate", str(GOOD), "--latitude", "60", "-o", str(d / "result.json")],
            ["calibrate", str(FIXTURES / "thesis_bench_125hz.bin"), "--latitude", "40.59129", "--method", "thesis",
             "--bench", "-o", str(d / "bench.json")],
            ["calibrate", str(FIXTURES / "thesis_real_ccw_125hz.bin"), "--latitude", "40.59129", "--method", "thesis",
             "-o", str(d / "thesis.json")],
            ["calibrate", str(FIXTURES / "gyro_acc_125hz.bin"), "--latitude", "40.59129", "-o",
             str(d / "gyro_acc.json")],
            ["noise", str(GOOD), "-o", str(d / "noise.json")])
    for argv in runs:
        assert calibd_main(argv) == 0, argv
    # the daemon's pipeline in a process of its own: it sets up the log for the whole process
    subprocess.run([sys.executable, "-m", "calibd", "replay", str(GOOD), "--latitude", "60", "--state-dir",
                    str(d / "state")], check=True, capture_output=True)
    return {"result": d / "result.json", "bench": d / "bench.json", "thesis": d / "thesis.json",
            "gyro_acc": d / "gyro_acc.json", "noise": d / "noise.json",
            "state": d / "state" / "state.json", "daemon result": d / "state" / "result.json"}


# ---------------------------------------------------------------- the table

RESULT_DEFECTS = {  # name: (path, value, what the message names)
    "deep nesting": ("estimates.pitch.value", Raw(DEEP), "estimates.pitch.value[0]"),
    "deep nesting in an unknown key": ("x", Raw(DEEP), "x[0][0]"),
    "NaN latitude": ("site.latitude_deg", Raw("NaN"), "site.latitude_deg is NaN"),
    "Infinity gyro bias": ("estimates.gyro_bias_x.value", Raw("Infinity"), "estimates.gyro_bias_x.value is Infinity"),
    "-Infinity sigma": ("estimates.yaw.sigma", Raw("-Infinity"), "estimates.yaw.sigma is -Infinity"),
    "huge integer": ("estimates.acc_bias_x.value", Raw(HUGE), "estimates.acc_bias_x.value is out of range"),
    "1e308 gyro bias": ("estimates.gyro_bias_x.value", 1e308, "estimates.gyro_bias_x.value is 1e+308"),
    "yaw 400 deg": ("estimates.yaw.value", 400.0, "estimates.yaw.value is 400.0, expected a number in [-360, 360]"),
    "incl bias beyond 1.7 g": ("estimates.incl_bias_x.value", 2000.0, "estimates.incl_bias_x.value is 2000.0"),
    "negative sigma": ("estimates.pitch.sigma", -1.0, "estimates.pitch.sigma is -1.0, expected a number >= 0"),
    "estimate unit": ("estimates.pitch.unit", "rad", 'estimates.pitch.unit is "rad", expected "deg"'),
    "estimate value text": ("estimates.pitch.value", "x", 'estimates.pitch.value is "x", expected a number'),
    "estimate value missing": ("estimates.roll.value", KeyError, "estimates.roll.value is missing"),
    "rotation a string": ("rotation", "x", 'rotation is "x", expected an object or null'),
    "latitude text": ("site.latitude_deg", "north", 'site.latitude_deg is "north", expected a number in [-90, 90]'),
    "g0 zero": ("site.g0_m_s2", 0, "site.g0_m_s2 is 0"),
    "capture a number": ("capture", 5, "capture is 5"),
    "capture sha256": ("capture.sha256", "zz", 'capture.sha256 is "zz"'),
    "stream a string": ("stream", "x", 'stream is "x", expected an object'),
    "covariance a string": ("covariance", "x", 'covariance is "x"'),
    "covariance of two sizes": ("covariance.matrix.0", [1.0], "covariance: names, units and matrix"),
    "session_id a number": ("session_id", 5, "session_id is 5, expected a string or null"),
    "sensor a number": ("sensor", 5, "sensor is 5, expected an object"),
    "acc range 7 g": ("sensor.acc_range_g", 7, "sensor.acc_range_g is 7"),
    "stale a number": ("stale", 5, "stale is 5, expected an object or null"),
    "segment start text": ("segments.0.start_s", "x", 'segments[0].start_s is "x", expected a number'),
    "p-value 2": ("checks.static_chi2.p_value", 2.0, "checks.static_chi2.p_value is 2.0, expected a number in [0, 1]"),
    "power-up number 0": ("stream.power_up.number", 0, "stream.power_up.number is 0"),
    "warning a number": ("warnings.0", 1, "warnings[0] is 1, expected a string"),
    "free part too deep": ("error_budget.x", [[[[[[[1]]]]]]], "error_budget[...]"),
    "newer version": ("schema", "calibd.result/9", "is calibd.result/9, newer than this calibd reads"),
    "another schema": ("schema", "calibd.noise/1", "is 'calibd.noise/1', not a calibd.result file"),
    "not an object": ("", Raw("[]"), "a JSON list, not an object: not a calibd.result file"),
    "power-up without its start": ("stream.start_s", KeyError, "stream: a power_up record comes with start_s"),
    "power-up without its duration": ("stream.power_up.duration_s", KeyError, "stream.power_up.duration_s is missing"),
}
REPORT = ("deep nesting", "NaN latitude", "huge integer", "1e308 gyro bias", "rotation a string", "capture a number",
          "segment start text", "p-value 2")
STATUS = ("deep nesting", "Infinity gyro bias", "huge integer", "yaw 400 deg", "stale a number", "session_id a number",
          "newer version")
STATE_DEFECTS = {
    "deep nesting": ("detail", Raw(DEEP), "detail[0]"),
    "NaN updated": ("updated", Raw("NaN"), "updated is NaN"),
    "Infinity updated": ("updated", Raw("Infinity"), "updated is Infinity"),
    "huge integer": ("updated", Raw(HUGE), "updated is out of range"),
    "updated text": ("updated", "yesterday", 'updated is "yesterday", expected a number >= 0'),
    "updated negative": ("updated", -1, "updated is -1, expected a number >= 0"),
    "state a number": ("state", 5, "state is 5, expected a string"),
    "detail missing": ("detail", KeyError, "detail is missing"),
    "degraded a list": ("degraded", [], "degraded is [], expected a string or null"),
}
NOISE_DEFECTS = {
    "deep nesting": ("channels.gyro_x.adev", Raw(DEEP), "channels.gyro_x.adev[0]"),
    "NaN": ("channels.gyro_x.random_walk.value", Raw("NaN"), "channels.gyro_x.random_walk.value is NaN"),
    "Infinity": ("channels.acc_y.bias_instability.value", Raw("Infinity"),
                 "channels.acc_y.bias_instability.value is Infinity"),
    "huge integer": ("channels.gyro_z.random_walk.value", Raw(HUGE), "channels.gyro_z.random_walk.value is out of"),
    "1e308 figure": ("channels.gyro_x.random_walk.value", 1e308,
                     "channels.gyro_x.random_walk.value is 1e+308, expected a number in [0, 1000]"),
    "negative figure": ("channels.incl_x.bias_instability.value", -1, "channels.incl_x.bias_instability.value is -1"),
    "unit a number": ("channels.acc_x.random_walk.unit", 5, "channels.acc_x.random_walk.unit is 5"),
    "wrong unit": ("channels.acc_x.random_walk.unit", "m/s", "channels.acc_x.random_walk.unit is 'm/s'"),
    "channel missing": ("channels.gyro_y", KeyError, "channels.gyro_y is missing"),
    "channels a string": ("channels", "x", 'channels is "x", expected an object'),
    "newer version": ("schema", "calibd.noise/2", "schema is calibd.noise/2, newer than this calibd reads"),
}
SCENARIO_DEFECTS = {  # name: (text replaced, by, what the message names)
    "deep nesting": ("[truth]\n", "[truth]\nx = " + DEEP + "\n", "x (line"),
    "huge integer": ("seed = 2026", "seed = " + HUGE, "seed (line"),
    "NaN angle": ("angle_deg = -90", "angle_deg = nan", "angle_deg: nan is not a number"),
    "inf duration": ("duration_s = 600", "duration_s = inf", "duration_s: inf is not a number"),
    "1e308 angle": ("angle_deg = -90", "angle_deg = 1e308", "angle_deg: 1e+308 is not a non-zero angle within"),
    "integer angle beyond float": ("angle_deg = -90", "angle_deg = 1" + "0" * 400, "angle_deg: an integer too large"),
    "1e308 truth": ("yaw_deg = -3.0360", "yaw_deg = 1e308", "[truth] yaw_deg: 1e+308 is not in [-360, 360] deg"),
    "noise figure 1e308": ("[warmup]", "[noise]\ngyro_arw_deg_sqrt_h = 1e308\n[warmup]",
                           "[noise] gyro_arw_deg_sqrt_h: 1e+308 is not in [0, 1000]"),
    "wrong type": ("duration_s = 600", 'duration_s = "long"', "duration_s: 'long' is not a number"),
    "latitude text": ("latitude_deg = 40.59129", 'latitude_deg = "north"', "latitude_deg: 'north' is not a number"),
    "not TOML": ("[site]", "[site", "not valid TOML"),
}


def _rows():
    rows = [("apply", name) for name in RESULT_DEFECTS] + [("report", name) for name in REPORT]
    rows += [("status result.json", name) for name in STATUS] + [("status state.json", name) for name in STATE_DEFECTS]
    rows += [("plan --noise", name) for name in NOISE_DEFECTS]
    rows += [(command, name) for command in ("plan --scenario", "simulate") for name in SCENARIO_DEFECTS]
    return rows


@pytest.mark.parametrize("command, defect", _rows(), ids=[" / ".join(row) for row in _rows()])
def test_a_bad_document_is_exit_2_and_one_line_naming_file_and_field(command, defect, made, tmp_path, capsys):
    ins, out = tmp_path / "in", tmp_path / "out"
    ins.mkdir()
    out.mkdir()
    if command == "status state.json":
        path, value, names = STATE_DEFECTS[defect]
        bad = ins / "state.json"
    elif command == "plan --noise":
        path, value, names = NOISE_DEFECTS[defect]
        bad = ins / "noise.json"
    elif command in ("plan --scenario", "simulate"):
        old, new, names = SCENARIO_DEFECTS[defect]
        bad = ins / "mine.toml"
        assert old in SCENARIO
        bad.write_text(SCENARIO.replace(old, new, 1))
    else:
        path, value, names = RESULT_DEFECTS[defect]
        bad = ins / "result.json"
    if bad.suffix == ".json":
        source = made["noise"] if command == "plan --noise" else made["state"] if "state.json" in command \
            else made["result"]
        bad.write_text(edited(source.read_text(), path, value))
    if command.startswith("status"):
        other = made["daemon result"] if command == "status state.json" else made["state"]
        (ins / other.name).write_bytes(other.read_bytes())
    argv = {"apply": ["apply", bad, SMALL, "-o", out / "a.csv"],
            "report": ["report", bad, SMALL, "-o", out / "r.html"],
            "status result.json": ["status", "--state-dir", ins],
            "status state.json": ["status", "--state-dir", ins, "--json"],
            "plan --noise": ["plan", "--campaign", "thesis", "--latitude", "40", "--noise", bad],
            "plan --scenario": ["plan", "--scenario", bad],
            "simulate": ["simulate", bad, "-o", out / "c.bin"]}[command]
    code = calibd_main([str(a) for a in argv])
    stdout, err = capsys.readouterr()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and err.endswith("\n"), err
    assert err.startswith(f"calibd: {bad}") and names in err, err
    assert "Traceback" not in err and "internal error" not in err and stdout == ""
    assert list(out.iterdir()) == [] and not [p for p in ins.iterdir() if p.name.startswith(".")]


TRUTH_DEFECTS = {
    "deep nesting": ("truth.yaw_deg", Raw(DEEP), "truth.yaw_deg[0]"),
    "NaN": ("truth.pitch_deg", Raw("NaN"), "truth.pitch_deg is NaN"),
    "huge integer": ("truth.roll_deg", Raw(HUGE), "truth.roll_deg is out of range"),
    "yaw 1e308": ("truth.yaw_deg", 1e308, "truth.yaw_deg is 1e+308, expected a number in [-360, 360]"),
    "bias of two axes": ("truth.gyro_bias_deg_h", [1.0, 2.0],
                         "truth.gyro_bias_deg_h is [1.0, 2.0], expected a list of 3"),
    "carried bias text": ("bias_during_capture.acc_bias_mg.session", "x", "bias_during_capture[...].session is not"),
    "newer version": ("schema", "calibd.truth/3", "is calibd.truth/3, newer than this calibd reads"),
}


@pytest.mark.parametrize("defect", list(TRUTH_DEFECTS))
def test_a_bad_truth_file_is_one_line_naming_the_field(defect, tmp_path):
    """The report reads a truth file only to compare with it: one it cannot read is left out
    (calibd.report.read_truth), but what is wrong is still one line naming the field."""
    path, value, names = TRUTH_DEFECTS[defect]
    bad = tmp_path / "c.bin.truth.json"
    bad.write_text(edited((FIXTURES / "heading137_lat60_125hz.bin.truth.json").read_text(), path, value))
    with pytest.raises(ScenarioError) as refusal:
        truth_from_json(bad.read_bytes(), bad)
    message = str(refusal.value)
    assert message.startswith(f"{bad}") and names in message and "\n" not in message, message


# ---------------------------------------------------------------- what calibd writes passes

def test_every_result_calibd_writes_passes_its_schema_and_reads_back_the_same(made):
    for name in ("result", "bench", "thesis", "gyro_acc", "daemon result"):
        text = made[name].read_text()
        documents.validate(json.loads(text), documents.ResultDoc, name)
        result = load_result(made[name])
        assert json.loads(result_json(result)) == json.loads(text), name
        assert parse_result(result_json(result), name) == result


def test_the_state_and_noise_files_calibd_writes_pass_their_schemas(made):
    state = documents.validate(json.loads(made["state"].read_text()), documents.StateDoc, "state.json")
    assert state.state == "SOLVED" and state.updated > 0
    noise = documents.validate(json.loads(made["noise"].read_text()), documents.NoiseDoc, "noise.json")
    assert noise.channels.incl_z is not None and noise.channels.gyro_x.random_walk.unit == "deg/sqrt(h)"


@pytest.mark.parametrize("truth", sorted(FIXTURES.glob("*.truth.json")), ids=lambda p: p.name)
def test_every_fixtures_truth_passes_its_schema(truth):
    record = json.loads(truth.read_text())
    values, carried = truth_from_json(truth.read_text(), truth)
    assert values.yaw_deg == record["truth"]["yaw_deg"]
    assert list(carried.gyro_bias_deg_h) == record["bias_during_capture"]["gyro_bias_deg_h"]["session"]


@pytest.mark.parametrize("name", READY_MADE)
def test_every_ready_made_scenario_reads(name):
    assert load_scenario(name).segments


def test_the_estimates_bounds_are_the_datasheets_ranges():
    """Angles within a turn; biases within the sensor's input range (400 deg/s, 80 g, 1.7 g)."""
    assert documents.ESTIMATE_BOUNDS["yaw"] == ("deg", 360.0)
    assert documents.ESTIMATE_BOUNDS["gyro_bias_z"] == ("deg/h", 1_440_000.0)
    assert documents.ESTIMATE_BOUNDS["acc_bias_x"] == ("mg", 80_000.0)
    assert documents.ESTIMATE_BOUNDS["incl_bias_y"] == ("mg", 1_700.0)


@pytest.mark.parametrize("text, says", [
    ("x = " + DEEP, "x (line 1): arrays nested too deep to read"),
    ("a = 1\nb = " + HUGE, "b (line 2): an integer of more than"),
    ("a = [1,", "not valid TOML"),
])
def test_parse_toml_refuses_in_one_line(text, says):
    with pytest.raises(documents.DocumentError) as refusal:
        documents.parse_toml(text, "c.toml")
    assert str(refusal.value).startswith("c.toml: ") and says in str(refusal.value)


@pytest.mark.parametrize("rate, ok", [("0", False), ("1e-300", False), ("-500", False), ("nan", False),
                                      ("-27.93", True), ("0.1", True), ("400", True)])
def test_the_platform_rate_has_a_range(rate, ok, tmp_path, capsys):
    """0 divided by, 1e-300 taken: a rate whose magnitude is 0.1 to 400 deg/s (the gyros' range)."""
    code = calibd_main(["calibrate", str(tmp_path / "absent.bin"), "--method", "thesis", "--latitude", "40",
                        "--platform-rate", rate, "-o", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1
    assert ("outside +-[0.1, 400] deg/s" in err) != ok and ("no such file" in err) == ok, err


@pytest.mark.parametrize("command", ["apply", "plan"])
def test_a_fresh_process_refuses_a_deep_document_in_one_line(command, made, tmp_path):
    """Outside the test runner's stack too, at the interpreter's own recursion limit."""
    if command == "apply":
        bad = tmp_path / "result.json"
        bad.write_text(edited(made["result"].read_text(), "estimates.pitch.value", Raw(DEEP)))
        argv, names = ["apply", bad, SMALL, "-o", tmp_path / "a.csv"], "estimates.pitch.value[0]"
    else:
        bad = tmp_path / "mine.toml"
        bad.write_text(SCENARIO.replace("[truth]\n", "[truth]\nx = " + DEEP + "\n"))
        argv, names = ["plan", "--scenario", bad], "x (line"
    run = subprocess.run([sys.executable, "-m", "calibd", *map(str, argv)], capture_output=True, text=True)
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and names in run.stderr, run.stderr
    assert run.stderr.startswith(f"calibd: {bad}") and run.stdout == "" and sorted(tmp_path.iterdir()) == [bad]


@pytest.mark.parametrize("data", [b'{"schema": "calibd.result/4", "method": "j\xa6"}', b'{"\xff": 1}'])
def test_bytes_that_are_not_utf8_inside_a_string_are_one_line(data):
    with pytest.raises(documents.CalibdError, match=r"^r\.json: not UTF-8 text \(byte \d+\)$"):
        parse_result(data, "r.json")


def test_a_null_estimate_is_no_estimate(made):
    doc = json.loads(made["result"].read_text())
    doc["estimates"]["yaw"] = None
    assert "yaw" not in parse_result(json.dumps(doc), "r.json").estimates
    doc["estimates"] = {name: None for name in doc["estimates"]}
    with pytest.raises(documents.CalibdError, match="r.json: the result has no estimates"):
        parse_result(json.dumps(doc), "r.json")

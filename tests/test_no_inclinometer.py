"""Units without inclinometers (gyro + accelerometer datagrams such as 0x91): the joint method
takes pitch, roll and the accelerometer biases from the accelerometers; inclinometer estimates
are absent, never zeros; the thesis's methods and gyro-only units are refused in one line."""

import json
from dataclasses import replace
from pathlib import Path

import pytest

from calibd.cli import main as calibd_main
from calibd.noise import characterise
from calibd.estimators.joint import JointOptions
from calibd.planner import noise_from_json, plan
from calibd.scenario import Noise
from calibd.frames import Site
from calibd.methods.common import NO_INCLINOMETERS
from calibd.captures import open_capture
from calibd.live import configure_logging
from calibd.session import power_up_session

from captures import capture

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "gyro_acc_125hz.bin"
K_SIGMA = 3.5  # 14 estimates: a 3.5-sigma miss happens once in some 150 fixtures


@pytest.fixture(scope="module")
def truth():
    return json.loads((FIXTURES / "gyro_acc_125hz.bin.truth.json").read_text())


@pytest.fixture(scope="module")
def result(tmp_path_factory, truth):
    out = tmp_path_factory.mktemp("r") / "result.json"
    code = calibd_main(["calibrate", str(CAPTURE), "--latitude", str(truth["site"]["latitude_deg"]), "-o", str(out)])
    assert code == 0
    return json.loads(out.read_text())


def test_the_capture_is_a_gyro_accelerometer_unit(truth):
    assert truth["sensor"]["datagram_id"] == "0x91"


def test_calibrate_recovers_attitude_and_biases_within_sigma(result, truth):
    expected = {"pitch": truth["truth"]["pitch_deg"], "roll": truth["truth"]["roll_deg"],
                "yaw": truth["truth"]["yaw_deg"], "alpha": truth["truth"]["alpha_deg"],
                "beta": truth["truth"]["beta_deg"]}
    biases = truth["bias_during_capture"]
    for name, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg")):
        expected |= {f"{name}_{a}": v for a, v in zip("xyz", biases[key]["mean"])}
    estimates = result["estimates"]
    for name, value in expected.items():
        e = estimates[name]
        error = (e["value"] - value + 180) % 360 - 180 if name == "yaw" else e["value"] - value
        assert abs(error) <= K_SIGMA * e["sigma"], (name, e, value)


def test_inclinometer_estimates_are_absent_and_the_result_says_why(result):
    assert not [name for name in result["estimates"] if name.startswith("incl_")]
    assert NO_INCLINOMETERS in result["warnings"]
    assert "incl" not in result["checks"]["noise_excess_over_white"]


def test_the_thesis_method_refuses_in_one_line(tmp_path, capsys):
    out = tmp_path / "r.json"
    code = calibd_main(["calibrate", str(CAPTURE), "--latitude", "40", "--method", "thesis", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "needs inclinometers" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_a_gyro_only_unit_is_refused_naming_the_accelerometers(tmp_path, capsys):
    data, _, _ = capture(3000, 0x90, rate=125)
    path = tmp_path / "gyro_only.bin"
    path.write_bytes(data)
    code = calibd_main(["calibrate", str(path), "--latitude", "40", "-o", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 2 and "gyros only" in err and "accelerometers" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_noise_has_six_channels_and_plan_reads_the_file_as_a_unit_without_inclinometers(tmp_path, capsys):
    path = tmp_path / "noise.json"
    assert calibd_main(["noise", str(CAPTURE), "-o", str(path)]) == 0
    doc = json.loads(path.read_text())
    assert list(doc["channels"]) == [f"{s}_{a}" for s in ("gyro", "acc") for a in "xyz"]
    figures = noise_from_json(path.read_bytes(), str(path))
    assert figures.incl_vrw_m_s_sqrt_h is None and figures.acc_vrw_m_s_sqrt_h == pytest.approx(0.024, rel=0.05)
    planned = plan("thesis", Site(45.0), figures)
    assert planned.session.incl is None and not [n for n in planned.sigmas if n.startswith("incl_")]
    perfect = JointOptions(factory_residuals=False)
    # the quieter force sensor gives the tilt: a 10 g unit's accelerometers (0.024 m/s/sqrt(h),
    # 0.005 mg) are quieter than the inclinometers, so a unit without them loses nothing; with
    # accelerometers much noisier than the inclinometers, the inclinometers' tilt is the one
    for acc, lost in (((0.024, 0.005), 1.0), ((0.5, 0.2), 2.0)):
        figures = replace(Noise(), acc_vrw_m_s_sqrt_h=acc[0], acc_bias_instability_mg=acc[1])
        without, with_incl = (plan("thesis", Site(45.0), f, options=perfect) for f in
                              (replace(figures, incl_vrw_m_s_sqrt_h=None, incl_bias_instability_mg=None), figures))
        assert without.sigmas["pitch"] == pytest.approx(with_incl.sigmas["pitch"], rel=1e-6) if lost == 1.0 else \
            without.sigmas["pitch"] > lost * with_incl.sigmas["pitch"]
    capsys.readouterr()
    assert calibd_main(["plan", "--latitude", "45", "--campaign", "index", "--noise", str(path)]) == 0
    printed = capsys.readouterr().out
    assert "no inclinometers" in printed and "incl_bias" not in printed


def test_characterise_skips_the_missing_sensor():
    session = power_up_session(open_capture(str(CAPTURE)), None, 0.0)
    assert session.incl is None
    assert list(characterise(session)) == [f"{s}_{a}" for s in ("gyro", "acc") for a in "xyz"]


@pytest.mark.slow
def test_the_daemon_solves_a_unit_without_inclinometers(tmp_path, capsys):
    try:
        code = calibd_main(["replay", str(CAPTURE), "--latitude", "40.59129", "--warmup-window", "10"])
    finally:
        configure_logging()  # replay logs warnings only; later tests read info events
    out = capsys.readouterr().out
    assert code == 0, out
    assert "[SOLVED]" in out and "acc_bias_z" in out and "incl_bias" not in out and "no inclinometers" in out

"""`calibd apply`: a result's biases off a capture's samples, in SI, in IMU axes or the home frame;
another sensor, poor estimates and summed outputs refused in one line; CSV and NPZ alike."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibd import spec
from calibd.apply import ApplyError, NpzWriter, apply_capture, correction
from calibd.cli import main
from calibd.frames import Site, nav_to_imu
from calibd.results import make_result, write_result
from calibd.scenario import Segment, load_scenario
from calibd.sim import capture_bytes, simulate
from calibd.units import DEG
from captures import capture
from stim300.codec import encode_samples
from stim300.protocol import GyroUnit
from stim300.special import Configuration, encode_special
from stim300.records import SensorRecord

FIXTURE = Path(__file__).parent.parent / "fixtures" / "heading137_lat60_125hz.bin"
TRUTH = json.loads(Path(f"{FIXTURE}.truth.json").read_text())
SERIAL = TRUTH["sensor"]["serial_number"]
HOME_STATIC_S = (5.0, 295.0)  # inside the first static (0 to 300 s), at the home position
K = 4.0


def truth_result(serial: str | None = SERIAL, poor: tuple[str, ...] = (), **changes):
    """A result holding the fixture's true biases over the session and its true attitude."""
    t, bias = TRUTH["truth"], TRUTH["bias_during_capture"]
    site = Site(TRUTH["site"]["latitude_deg"], TRUTH["site"]["height_m"])
    estimates = {name: (t[f"{name}_deg"] * DEG, 1e-4) for name in ("yaw", "pitch", "roll", "alpha", "beta")}
    for cluster, unit in (("gyro", DEG / 3600), ("acc", 9.80665e-3), ("incl", 9.80665e-3)):
        session = bias[f"{cluster}_bias_{'deg_h' if cluster == 'gyro' else 'mg'}"]["session"]
        for axis, value in zip("xyz", session):
            estimates[f"{cluster}_bias_{axis}"] = (value * unit, 1e-3 * unit)
    for name in changes.pop("drop", ()):
        del estimates[name]
    result = make_result("joint", site, estimates, [], [], SensorRecord(serial_number=serial))
    return result.flag_poor(poor) if poor else result


def applied_columns(result, frame: bool = False, data: bytes | None = None, force: bool = False):
    data = FIXTURE.read_bytes() if data is None else data
    gather = NpzWriter(NpzWriter.capacity_for(len(data)), None, {})
    applied = apply_capture(data, "c.bin", correction(result, frame, force), result.sensor.serial_number,
                            force, gather)
    return {name: values[:gather.n] for name, values in gather.columns.items()}, applied


def home_static_mean(columns, name):
    t = columns["time_s"]
    keep = (t > HOME_STATIC_S[0]) & (t < HOME_STATIC_S[1])
    return columns[name][keep].mean(axis=0)


def sigmas():
    """1-sigma of a home-static mean of corrected gyro (rad/s), accelerometer and inclinometer
    (m/s^2) data: white noise over the static, and the bias instability's wander, by which the
    static's bias differs from the session's mean the result holds (the inclinometers' taken at
    1 g, where they are noisiest)."""
    noise, span = TRUTH["noise"], HOME_STATIC_S[1] - HOME_STATIC_S[0]
    gyro = np.hypot(noise["gyro_arw_deg_sqrt_h"] / 60 / np.sqrt(span) * DEG,
                    noise["gyro_bias_instability_deg_h"] * DEG / 3600)
    acc = np.hypot(noise["acc_vrw_m_s_sqrt_h"] / 60 / np.sqrt(span), noise["acc_bias_instability_mg"] * 9.80665e-3)
    incl = spec.INCL_NOISE_AT_1G * np.hypot(noise["incl_vrw_m_s_sqrt_h"] / 60 / np.sqrt(span),
                                            noise["incl_bias_instability_mg"] * 9.80665e-3)
    return gyro, acc, incl


@pytest.fixture(scope="module")
def imu_axes():
    return applied_columns(truth_result())


def test_a_home_static_corrected_is_the_earth_rate_and_gravity_in_imu_axes(imu_axes):
    columns, applied = imu_axes
    site = Site(TRUTH["site"]["latitude_deg"], TRUTH["site"]["height_m"])
    t = TRUTH["truth"]
    r_nav_imu = nav_to_imu(t["yaw_deg"] * DEG, t["pitch_deg"] * DEG, t["roll_deg"] * DEG)
    gyro_sigma, acc_sigma, _ = sigmas()
    assert applied.samples == TRUTH["samples"] and applied.power_ups == 1 and applied.serial_number == SERIAL
    assert not applied.warnings
    np.testing.assert_allclose(home_static_mean(columns, "gyro_rad_s"), r_nav_imu @ site.earth_rate_nav,
                               atol=K * gyro_sigma)
    np.testing.assert_allclose(home_static_mean(columns, "acc_m_s2"), r_nav_imu @ site.gravity_nav, atol=K * acc_sigma)
    # uncorrected, the gyro bias (about 77 deg/h) is many sigma away: the test sees the correction
    raw = columns["gyro_rad_s"] + correction(truth_result(), False, False).biases["gyro"]
    assert np.abs(home_static_mean({"time_s": columns["time_s"], "g": raw}, "g")
                  - r_nav_imu @ site.earth_rate_nav).max() > 10 * K * gyro_sigma


def test_the_home_frame_turns_a_home_static_into_nwu():
    columns, applied = applied_columns(truth_result(), frame=True)
    lat = TRUTH["site"]["latitude_deg"] * DEG
    omega = 7.2921150e-5
    g0 = TRUTH["site"]["g0"]
    gyro_sigma, acc_sigma, incl_sigma = sigmas()
    np.testing.assert_allclose(home_static_mean(columns, "gyro_rad_s"), [omega * np.cos(lat), 0, omega * np.sin(lat)],
                               atol=K * gyro_sigma)
    np.testing.assert_allclose(home_static_mean(columns, "acc_m_s2"), [0, 0, g0], atol=K * acc_sigma)
    np.testing.assert_allclose(home_static_mean(columns, "incl_m_s2"), [0, 0, g0], atol=K * incl_sigma)


def test_biases_come_off_exactly_and_times_follow_the_counter():
    """Analytic: exact sensor values minus the result's biases; times are counter ticks / 2000."""
    _, samples, fmt = capture(500, 0xA7, False, rate=250)
    for cluster in ("gyro", "acc", "incl"):
        samples[f"status_{cluster}"] = 0  # a start-up bit coming on would be a restart
    data = encode_samples(samples, 0xA7, fmt, False).tobytes()
    result = truth_result(serial=None)
    columns, applied = applied_columns(result, data=data)
    fix = correction(result, False, False)
    for cluster, factor in (("gyro", DEG), ("acc", 9.80665), ("incl", 9.80665)):
        unit = "rad_s" if cluster == "gyro" else "m_s2"
        np.testing.assert_array_equal(columns[f"{cluster}_{unit}"],
                                      samples[cluster].astype(np.float64) * factor - fix.biases[cluster])
    np.testing.assert_allclose(columns["time_s"], np.arange(500) / 250, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(columns["counter"], samples["counter"])
    np.testing.assert_array_equal(columns["status"][:, 0], samples["status_gyro"])
    assert any("no serial-number datagram" in w for w in applied.warnings)


def test_a_gap_and_garbage_keep_the_time_base_and_lose_only_what_is_lost():
    """Datagrams lost mid-stream and a garbage burst: the rest is corrected, the times jump by
    the lost datagrams' duration (the counter says it), and the garbage gives no row."""
    _, samples, fmt = capture(600, 0xA7, False, rate=250)
    for cluster in ("gyro", "acc", "incl"):
        samples[f"status_{cluster}"] = 0
    encoded = encode_samples(samples, 0xA7, fmt, False)
    kept = np.r_[0:200, 220:600]  # 20 datagrams (0.08 s at 250 Hz, within one 0.128 s counter cycle) lost
    data = b"".join([encoded[:200].tobytes(), bytes(range(7, 250, 3)) * 3, encoded[220:].tobytes()])
    columns, applied = applied_columns(truth_result(serial=None), data=data)
    assert applied.samples == len(kept)
    np.testing.assert_array_equal(columns["counter"], samples["counter"][kept])
    np.testing.assert_allclose(columns["time_s"], kept / 250, rtol=0, atol=1e-12)
    assert any("20 samples lost" in w for w in applied.warnings)


def test_a_restart_is_warned_and_numbered_and_restarts_the_times():
    scenario = replace(load_scenario("thesis-real"), seed=5, segments=(Segment("static", duration_s=4),))
    one = capture_bytes(simulate(scenario))[0]
    columns, applied = applied_columns(truth_result(), data=one + one)
    assert applied.power_ups == 2
    assert any("restarted 1 time(s)" in w and "power_up" in w for w in applied.warnings)
    up = columns["power_up"]
    assert set(up.tolist()) == {1, 2} and np.all(np.diff(up) >= 0)
    assert columns["time_s"][up == 2][0] == 0.0


@pytest.mark.parametrize("poor, frame, says", [
    (("gyro_bias_x",), False, "gyro_bias_x is flagged poor"),
    (("yaw",), True, "has yaw flagged poor"),
])
def test_poor_estimates_are_refused(poor, frame, says):
    with pytest.raises(ApplyError, match=says):
        correction(truth_result(poor=poor), frame, False)


def test_poor_estimates_apply_with_force_and_a_warning_but_yaw_poor_never_gives_the_frame():
    fix = correction(truth_result(poor=("acc_bias_z",)), False, True)
    assert fix.warnings == ("the result's acc_bias_z is flagged poor: applied anyway (--force)",)
    assert correction(truth_result(poor=("yaw", "alpha")), False, False).rotation is None  # not used: no refusal
    with pytest.raises(ApplyError, match="has yaw flagged poor"):
        correction(truth_result(poor=("yaw",)), True, True)
    with pytest.raises(ApplyError, match="has no yaw"):
        correction(truth_result(drop=("yaw",)), True, True)


def test_summed_outputs_are_refused():
    data, _, _ = capture(300, 0xA7, False, rate=125, gyro_unit=GyroUnit.INCREMENTAL_ANGLE)
    config = encode_special(Configuration.build(sample_rate_hz=125, gyro_unit=GyroUnit.INCREMENTAL_ANGLE), False)
    with pytest.raises(ApplyError, match="gyro incremental_angle outputs are not rates"):
        applied_columns(truth_result(), data=config + data)


@pytest.fixture(scope="module")
def result_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("results")
    write_result(folder / "r.json", truth_result())
    write_result(folder / "other.json", truth_result(serial="N00000000000001"))
    write_result(folder / "poor.json", truth_result(poor=("gyro_bias_z", "roll")))
    return folder


def test_csv_and_npz_agree(result_files, tmp_path, run_main):
    for name in ("o.csv", "o.npz"):
        code, out, err = run_main(main, ["apply", result_files / "r.json", FIXTURE, "-o", tmp_path / name, "--frame"])
        assert code == 0 and err == "" and "75728 samples" in out, err
    npz = np.load(tmp_path / "o.npz")
    lines = (tmp_path / "o.csv").read_text().splitlines()
    assert lines[0].startswith("# calibd.applied/1: ") and json.loads(lines[0].split(": ", 1)[1]) == \
        json.loads(str(npz["meta"]))
    header = lines[2].split(",")
    assert header[:4] == ["time_s", "gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"] and header[-1] == "power_up"
    table = np.loadtxt(lines[3:], delimiter=",")
    assert len(table) == len(npz["time_s"])
    np.testing.assert_array_equal(np.rint(table[:, 0] * 2000), np.rint(npz["time_s"] * 2000))  # 0.5 ms ticks
    np.testing.assert_allclose(table[:, 0], npz["time_s"], rtol=0, atol=1e-9)
    for first, name in ((1, "gyro_rad_s"), (4, "acc_m_s2"), (7, "incl_m_s2")):
        np.testing.assert_allclose(table[:, first:first + 3], npz[name], rtol=1e-8, atol=1e-15)
    np.testing.assert_array_equal(table[:, 10:].astype(int),
                                  np.column_stack([npz["counter"], npz["status"], npz["power_up"]]))
    meta = json.loads(str(npz["meta"]))
    assert meta["frame"] == "home" and meta["result"]["serial_number"] == SERIAL
    assert len(meta["result"]["sha256"]) == 64 and meta["biases_subtracted"]["gyro_rad_s"][0] == pytest.approx(
        TRUTH["bias_during_capture"]["gyro_bias_deg_h"]["session"][0] * DEG / 3600)


def test_another_sensor_is_refused_and_applied_with_force(result_files, tmp_path):
    argv = [sys.executable, "-m", "calibd", "apply", str(result_files / "other.json"), str(FIXTURE),
            "-o", str(tmp_path / "o.npz")]
    refused = subprocess.run(argv, capture_output=True, text=True)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert f"sensor {SERIAL}" in refused.stderr and "sensor N00000000000001" in refused.stderr
    assert not (tmp_path / "o.npz").exists() and not list(tmp_path.glob(".*.part"))
    forced = subprocess.run(argv + ["--force"], capture_output=True, text=True)
    assert forced.returncode == 0, forced.stderr
    assert "warning: the capture is of sensor" in forced.stderr and "applied anyway (--force)" in forced.stderr
    assert len(np.load(tmp_path / "o.npz")["time_s"]) == TRUTH["samples"]


def test_poor_estimates_refused_on_the_command_line_and_applied_with_force(result_files, tmp_path):
    argv = [sys.executable, "-m", "calibd", "apply", str(result_files / "poor.json"), str(FIXTURE),
            "-o", str(tmp_path / "o.csv"), "--frame"]
    refused = subprocess.run(argv, capture_output=True, text=True)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "gyro_bias_z, roll are flagged poor: not applied (--force applies it anyway)" in refused.stderr
    assert not (tmp_path / "o.csv").exists()
    forced = subprocess.run(argv + ["--force"], capture_output=True, text=True)
    assert forced.returncode == 0 and "warning: the result's gyro_bias_z, roll are flagged poor" in forced.stderr
    assert "in the home frame" in forced.stdout


@pytest.mark.parametrize("output, says", [
    ("o.txt", "unknown output type '.txt': name it .npz, .csv or .mcap"),
    ("o", "unknown output type '(no extension)'"),
])
def test_an_output_that_is_not_npz_csv_or_mcap_is_refused(result_files, tmp_path, run_main, output, says):
    code, _, err = run_main(main, ["apply", result_files / "r.json", FIXTURE, "-o", tmp_path / output])
    assert code == 2 and says in err and err.count("\n") == 1, err


def test_the_output_cannot_be_an_input(result_files, tmp_path, run_main):
    capture_copy = tmp_path / "c.csv"
    capture_copy.write_bytes(FIXTURE.read_bytes())
    code, _, err = run_main(main, ["apply", result_files / "r.json", capture_copy, "-o", capture_copy])
    assert code == 2 and "is the input" in err and err.count("\n") == 1
    assert capture_copy.read_bytes() == FIXTURE.read_bytes()


def test_a_file_that_is_not_a_result_is_refused(tmp_path, run_main):
    bad = tmp_path / "r.json"
    bad.write_text('{"schema": "calibd.noise/1"}')
    code, _, err = run_main(main, ["apply", bad, FIXTURE, "-o", tmp_path / "o.npz"])
    assert code == 2 and "not a calibd.result file" in err and err.count("\n") == 1, err
    code, _, err = run_main(main, ["apply", tmp_path / "missing.json", FIXTURE, "-o", tmp_path / "o.npz"])
    assert code == 2 and "no such file" in err, err


def test_a_cluster_the_result_has_no_biases_for_is_refused_unless_forced(imu_axes):
    no_incl = truth_result(drop=[f"incl_bias_{axis}" for axis in "xyz"])
    with pytest.raises(ApplyError, match="the result has no inclinometer biases: those columns would stay uncorrected"):
        applied_columns(no_incl)
    columns, applied = applied_columns(no_incl, force=True)
    assert any("no inclinometer biases: those columns are as measured" in w for w in applied.warnings)
    corrected, _ = imu_axes
    incl_bias = correction(truth_result(), False, False).biases["incl"]
    np.testing.assert_allclose(columns["incl_m_s2"], corrected["incl_m_s2"] + incl_bias, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(columns["gyro_rad_s"], corrected["gyro_rad_s"])


def test_a_result_that_names_no_sensor_is_applied_with_a_warning():
    columns, applied = applied_columns(truth_result(serial=None))
    assert applied.samples == TRUTH["samples"]
    assert applied.warnings == ["the result names no sensor serial number: cannot check it is of this capture's "
                                "sensor"]

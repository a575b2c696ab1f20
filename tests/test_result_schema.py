"""The result document's version 3 content: the rotation as matrix and quaternion (one map, the
frames' R1(roll) R2(pitch) R3(yaw)), the joint estimates' covariance (its diagonal the sigmas),
SI values beside display units, software, the session id; older versions read, newer refused;
`calibd calibrate` and the daemon write it all."""

import hashlib
import json
import math
import re
import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibd.calibrate import calibrate_capture
from calibd.methods.joint import joint_real_case
from calibd.captures import load_session, open_capture
from calibd.cli import main as calibd_main
from calibd.config import WarmupConfig
from calibd.daemon import Calibrator, Callbacks
from calibd.frames import STANDARD_GRAVITY, Site, int_to_imu, nav_to_imu
from calibd.live import replay
from calibd.methods import estimator
from calibd.results import (ESTIMATES, ROTATION_CONVENTION, SCHEMA, ResultError, load_result, make_result,
                            result_json)
from calibd.scenario import load_scenario
from calibd.sim import capture_bytes, simulate
from calibd.units import DEG
from stim300.cliutil import package_version
from stim300.source import CaptureSource
from stim300.records import SensorRecord

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CW = FIXTURES / "thesis_real_cw_125hz.bin"
SITE = Site(40.59129)
ANGLES_DEG = {"yaw": 137.0, "pitch": -2.5, "roll": 1.25, "alpha": 0.6, "beta": -0.12}


def angles_result(**angles_deg):
    return make_result("joint", SITE, {name: (value * DEG, 0.1 * DEG) for name, value in angles_deg.items()}, [], [],
                       SensorRecord())


def hamilton(p, q):
    """The Hamilton product of [w, x, y, z] quaternions."""
    (a, b, c, d), (e, f, g, h) = p, q
    return np.array([a * e - b * f - c * g - d * h, a * f + b * e + c * h - d * g,
                     a * g - b * h + c * e + d * f, a * h + b * g - c * f + d * e])


@pytest.fixture(scope="module")
def cw_result():
    method = estimator("joint")
    return calibrate_capture(open_capture(str(CW)), lambda s: method.solve(s, SITE, None, method.options({})))


def test_the_rotation_is_the_frames_matrix_and_the_quaternion_is_the_same_map():
    rad = {name: value * DEG for name, value in ANGLES_DEG.items()}
    record = json.loads(result_json(angles_result(**ANGLES_DEG)))["rotation"]
    assert record["convention"] == ROTATION_CONVENTION and "[w, x, y, z], Hamilton" in record["convention"]
    expected = {"nav_to_imu": nav_to_imu(rad["yaw"], rad["pitch"], rad["roll"]),
                "int_to_imu": int_to_imu(rad["alpha"], rad["beta"])}
    vectors = np.random.default_rng(3).normal(size=(5, 3))
    for name, matrix in expected.items():
        m, q = np.array(record[name]["matrix"]), np.array(record[name]["quaternion"])
        assert m == pytest.approx(matrix, abs=1e-15) and record[name]["poor"] == []
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15) and q[0] >= 0
        conjugate = q * [1, -1, -1, -1]
        for v in vectors:  # q v q* takes NAV components to IMU components, as the matrix does
            assert hamilton(hamilton(q, np.r_[0.0, v]), conjugate) == pytest.approx(np.r_[0.0, m @ v], abs=1e-14)
        # scipy's quaternions are scalar-last and its rotations active: apply(v) = m v
        assert Rotation.from_quat(np.roll(q, -1)).apply(vectors) == pytest.approx(vectors @ m.T, abs=1e-14)
    # passive: NWU's North seen from an IMU turned 90 deg left (yaw +90 deg, towards West) lies along -y
    turned = np.array(json.loads(result_json(angles_result(yaw=90.0, pitch=0.0, roll=0.0)))
                      ["rotation"]["nav_to_imu"]["matrix"])
    assert turned @ [1.0, 0.0, 0.0] == pytest.approx([0.0, -1.0, 0.0], abs=1e-15)


def test_a_poor_yaw_keeps_the_rotation_and_says_so():
    result = angles_result(**ANGLES_DEG).flag_poor(["yaw"], "yaw is too poor to use")
    record = result.rotation_record()
    assert record["nav_to_imu"]["poor"] == ["yaw"] and record["int_to_imu"]["poor"] == []
    assert result.rotation_matrix() == pytest.approx(angles_result(**ANGLES_DEG).rotation_matrix())


def test_without_all_three_angles_there_is_no_nav_to_imu_rotation():
    alpha_beta = angles_result(alpha=0.6, beta=-0.12)  # the bench campaign's
    assert alpha_beta.rotation_matrix() is None and list(alpha_beta.rotation_record()) == ["convention", "int_to_imu"]
    assert angles_result(yaw=1.0).rotation_record() is None


def test_si_values_are_the_display_values_over_one_factor(cw_result):
    assert ESTIMATES["yaw"][0] == pytest.approx(180 / math.pi)
    assert ESTIMATES["gyro_bias_y"][0] == pytest.approx(3600 * 180 / math.pi)
    assert ESTIMATES["acc_bias_x"][0] == pytest.approx(1000 / STANDARD_GRAVITY)
    doc = json.loads(result_json(cw_result))
    units_si = {"deg": "rad", "deg/h": "rad/s", "mg": "m/s^2"}
    for name, e in doc["estimates"].items():
        factor, unit = ESTIMATES[name]
        assert e["unit"] == unit and e["unit_si"] == units_si[unit]
        assert e["value_si"] == pytest.approx(e["value"] / factor, rel=1e-15)
        assert e["sigma_si"] == pytest.approx(e["sigma"] / factor, rel=1e-15)


def test_the_covariance_is_the_joint_fits_and_its_diagonal_the_sigmas(cw_result):
    """Written in display units with the names and units of its rows; yaw and the gyro Y bias
    come from the same Earth-rate terms, so they are correlated."""
    record = cw_result.covariance
    assert record["names"] == list(cw_result.estimates) and len(record["names"]) == 14
    assert record["units"] == [cw_result.estimates[name].unit for name in record["names"]]
    cov, cov_si = cw_result.covariance_matrix(), cw_result.covariance_matrix(si=True)
    sigma = np.array([cw_result.estimates[name].sigma for name in record["names"]])
    sigma_si = np.array([cw_result.estimates[name].sigma_si for name in record["names"]])
    assert np.diag(cov) == pytest.approx(sigma**2, rel=1e-12)
    assert np.diag(cov_si) == pytest.approx(sigma_si**2, rel=1e-12)
    assert cov == pytest.approx(cov.T, rel=1e-12)
    assert np.linalg.eigvalsh(cov_si / np.outer(sigma_si, sigma_si)).min() > 0  # a correlation matrix
    yaw, bias_y = record["names"].index("yaw"), record["names"].index("gyro_bias_y")
    assert cov[yaw, bias_y] / (sigma[yaw] * sigma[bias_y]) > 0.2


@pytest.mark.slow
def test_a_turn_angle_correction_keeps_the_diagonal_the_sigmas():
    """A turn corrected for datagrams lost unseen adds its correction's effect to the whole
    covariance: the sigmas still are its diagonal."""
    sim = simulate(replace(load_scenario("thesis-real"), seed=1))
    turn = [p for p in sim.phases if p.kind == "turn"][2]
    first = int((turn.cruise_start_s + 0.5) * 125)
    cut = replace(sim, samples=np.delete(sim.samples, np.arange(first, first + 188)))
    result = joint_real_case(load_session("cut.bin", data=capture_bytes(cut)[0]), sim.scenario.site)
    assert any(t["corrected"] for t in result.checks["turn_angles"])
    sigma = np.array([result.estimates[name].sigma for name in result.covariance["names"]])
    assert np.diag(result.covariance_matrix()) == pytest.approx(sigma**2, rel=1e-12)


def test_the_thesis_methods_have_no_covariance_and_the_linear_yaw_is_poor():
    """The linear run's yaw is not an estimate (eq. 7.3 folds the Earth-rate term into alpha):
    flagged, so its rotation says yaw is poor; the nominal run's is not flagged here."""
    session = load_session(str(CW))
    method = estimator("thesis")
    for given, poor in (({"alpha_deg": 0.5934, "beta_deg": -0.1196}, []), ({}, ["yaw"])):
        result = method.solve(session, SITE, None, method.options(given))
        assert result.covariance is None and result.covariance_matrix() is None
        doc = json.loads(result_json(result))
        assert doc["covariance"] is None and doc["rotation"]["nav_to_imu"]["poor"] == poor, given


@pytest.mark.slow
def test_calibrate_writes_every_version_3_field(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert calibd_main(["calibrate", str(CW), "--latitude", "40.59129", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    sha256 = hashlib.sha256(CW.read_bytes()).hexdigest()
    assert doc["schema"] == SCHEMA == "calibd.result/7"
    assert doc["software"] == {"name": "stim300-calib", "version": package_version()}
    assert doc["session_id"] == f"{sha256[:16]}/p1/t{doc['stream']['start_s']:.3f}"
    assert doc["capture"] == {"path": str(CW), "size_bytes": CW.stat().st_size, "sha256": sha256,
                              "serial_number": "N25582405002002"}
    assert set(doc["site"]) == {"latitude_deg", "height_m", "g0_m_s2", "g0_given", "g0_sigma_m_s2",
                                "earth_rate_deg_h", "earth_rate_rad_s"}
    assert doc["site"]["g0_sigma_m_s2"] == pytest.approx(4.2e-4) and not doc["site"]["g0_given"]
    assert all({"value_si", "sigma_si", "unit_si"} <= set(e) for e in doc["estimates"].values())
    assert set(doc["rotation"]) == {"convention", "nav_to_imu", "int_to_imu"}
    assert np.array(doc["covariance"]["matrix"]).shape == (14, 14)
    result = load_result(out)
    assert json.loads(result_json(result)) == doc
    assert result.rotation_matrix() == pytest.approx(np.array(doc["rotation"]["nav_to_imu"]["matrix"]), abs=1e-15)


def test_the_same_capture_and_start_give_the_same_session_id(tmp_path, capsys):
    ids = []
    for start in ("0", "0", "10"):
        out = tmp_path / f"r{len(ids)}.json"
        assert calibd_main(["calibrate", str(FIXTURES / "gyro_acc_125hz.bin"), "--latitude", "40.59129", "--start",
                            start, "-o", str(out)]) == 0
        ids.append(json.loads(out.read_text())["session_id"])
    assert ids[0] == ids[1] != ids[2] and ids[2].endswith("/p1/t10.000")


@pytest.mark.slow
def test_a_daemon_session_gives_every_result_its_id():
    results = []
    calibrator = Calibrator(Site(60.0), WarmupConfig(window_s=100.0), listeners=[Callbacks(result=results.append)])
    replay(CaptureSource((FIXTURES / "heading137_lat60_125hz.bin").read_bytes()), calibrator)
    assert results and {r.session_id for r in results} == {calibrator.session_id}
    assert uuid.UUID(calibrator.session_id).version == 4
    assert results[-1].software["version"] == package_version() and results[-1].covariance is not None


def test_a_version_2_document_still_loads(tmp_path, cw_result):
    """As calibd wrote it before version 3: no SI values, rotation, covariance, software or session id."""
    doc = json.loads(result_json(cw_result))
    for key in ("software", "session_id", "rotation", "covariance"):
        del doc[key]
    doc["schema"] = "calibd.result/2"
    doc["estimates"] = {name: {key: value for key, value in e.items() if not key.endswith("_si")}
                        for name, e in doc["estimates"].items()}
    path = tmp_path / "v2.json"
    path.write_text(json.dumps(doc))
    result = load_result(path)
    assert result.schema == "calibd.result/2" and result.session_id is None and result.software is None
    assert result.covariance is None and result.estimates == cw_result.estimates
    assert result.rotation_matrix() == pytest.approx(cw_result.rotation_matrix(), abs=1e-15)


@pytest.mark.parametrize("change, message", [
    ({"schema": "calibd.result/8"},
     "r.json is calibd.result/8, newer than this calibd reads (up to 7): upgrade calibd"),
    ({"estimates": {"yaw": {"value": 1.0, "unit": "grad"}}},
     'r.json: estimates.yaw.unit is "grad", expected "deg"'),
])
def test_a_newer_version_or_an_unknown_unit_is_refused_in_one_line(tmp_path, change, message):
    path = tmp_path / "r.json"
    path.write_text(json.dumps(json.loads(result_json(angles_result(**ANGLES_DEG))) | change))
    with pytest.raises(ResultError) as refusal:
        load_result(path)
    assert str(refusal.value) == f"{path.parent}/{message}"
    assert re.fullmatch(r"[^\n]+", str(refusal.value))

"""`calibd trim` and `stim300.trim` against the pty emulation of the sensor (tests/sensor_emulator.py)
serving a short simulated session: calibrate -> trim -> calibrate again leaves biases within
2 sigma of zero; the backup, --restore, the refusals, --save and its counter, --verify, and the
unit back in Normal Mode with its previous offsets after an interrupt at any step."""

import json
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from captures import command_env
from sensor_emulator import SensorEmulator, State, with_trims
from calibd.calibrate import calibrate_capture
from calibd import spec
from calibd.cli import main
from calibd.frames import Site
from calibd.methods import estimator
from calibd.results import StaleRecord, write_result
from calibd.scenario import Segment, load_scenario
from calibd.session import decode_sessions
from calibd.sim import capture_bytes, simulate
from calibd.trim import TrimOptions, trim_from_result, trim_reference
from stim300.port import open_serial
from stim300.protocol import GyroUnit
from stim300.records import TrimOffsets
from stim300.trim import SENSORS, TrimError, read_trims, trim_commands, trim_lsb, write_trims
from stim300.service import service_mode

ROOT = Path(__file__).resolve().parents[1]
STATIC_S = 60.0
SENSOR_STATE = State(datagram_id=0xA7, sample_rate_code=0)  # the simulated sensor's 0xA7 at 125 Hz
TRIMMED_BEFORE = replace(SENSOR_STATE, gyro_trim_deg_s=(2**-6, -2**-8, 0.0), acc_trim_g=(0.0, 2**-10, 0.0),
                         incl_trim_g=(0.0, 0.0, -2**-13), trim_reference=777)  # whole counts of the T datagram


# ---------------------------------------------------------------- a short session and its result

@pytest.fixture(scope="module")
def session():
    """A level static, then three quarter turns each with a static after: the joint method's
    campaign, in 3 simulated minutes (a fraction of a second to solve)."""
    scenario = load_scenario("thesis-real")
    turn = Segment("turn", angle_deg=-90, peak_rate_deg_s=20, accel_deg_s2=20)
    scenario = replace(scenario, segments=(Segment("static", STATIC_S), *(turn, Segment("static", 30.0)) * 3))
    return simulate(scenario)


def calibrated(sim):
    """The joint method's result on a simulation's capture (what `calibd calibrate` writes)."""
    capture = decode_sessions(capture_bytes(sim)[0], "session.bin")
    method = estimator("joint")
    site = Site(sim.scenario.site.latitude_deg, g0=sim.scenario.site.g0)
    return calibrate_capture(capture, lambda s: method.solve(s, site, None, method.options({})), None, 0.0)


@pytest.fixture(scope="module")
def result(session):
    return calibrated(session)


@pytest.fixture
def result_file(result, tmp_path):
    def write(changed=None):
        path = tmp_path / "result.json"
        write_result(path, changed or result)
        return str(path)
    return write


@pytest.fixture
def unit(session):
    """The emulated sensor serving the session's level static over and over."""
    emulators = []

    def start(state: State = SENSOR_STATE, measured_with=SENSOR_STATE, **kwargs):
        """`measured_with`: the trims in force when the session was recorded (the emulator's
        output with `state`'s trims is the session's data with the difference added)."""
        static = session.samples[:int(STATIC_S * session.scenario.sensor.sample_rate_hz)]
        difference = replace(state, **{name: tuple(-np.asarray(value)) for name, value in (
            ("gyro_trim_deg_s", measured_with.gyro_trim_deg_s), ("acc_trim_g", measured_with.acc_trim_g),
            ("incl_trim_g", measured_with.incl_trim_g))})
        emulator = SensorEmulator(state, samples=with_trims(static, difference, state.format), **kwargs)
        emulator.start()
        emulators.append(emulator)
        return emulator
    yield start
    for emulator in emulators:
        if emulator.is_alive():  # not stopped by the test
            emulator.stop()


def trim(emulator, *options, backup_dir):
    return main(["trim", emulator.path, *options, "--backup-dir", str(backup_dir)])


def one_line(err: str) -> str:
    """The error: one line after the progress lines, no traceback."""
    *progress, error = err.splitlines()
    assert all(line.startswith("calibd trim: ") for line in progress) and "Traceback" not in err, err
    return error


def biases(result, sensor):
    prefix = {"gyro": "gyro_bias", "acc": "acc_bias", "incl": "incl_bias"}[sensor]
    return [result.estimates[f"{prefix}_{axis}"] for axis in "xyz"]


# ---------------------------------------------------------------- the cycle

def test_calibrate_trim_calibrate_again_leaves_biases_within_two_sigma(session, result, result_file, unit,
                                                                      tmp_path, capsys):
    emulator = unit()
    assert trim(emulator, "--from", result_file(), backup_dir=tmp_path) == 0
    out = capsys.readouterr().out
    assert "gyro trim" in out and "deg/s" in out and f"reference        {trim_reference(result.session_id)}" in out
    gyro_x = biases(result, "gyro")[0].value
    assert abs(emulator.state.gyro_trim_deg_s[0] + gyro_x / 3600) <= trim_lsb("gyro", 10)  # the bias taken off
    assert emulator.mode == "normal" and emulator.saves_left == 9998 and emulator.flash == SENSOR_STATE

    trimmed = replace(session, samples=with_trims(session.samples, emulator.state, emulator.state.format))
    again = calibrated(trimmed)
    for sensor in SENSORS:
        for before, after in zip(biases(result, sensor), biases(again, sensor)):
            assert abs(before.value) > 0.2 and abs(after.value) <= 2 * after.sigma, (sensor, before, after)


def test_the_backup_holds_what_was_in_force_and_restore_puts_it_back_exactly(result_file, unit, tmp_path, capsys):
    emulator = unit(TRIMMED_BEFORE)
    assert trim(emulator, "--from", result_file(), backup_dir=tmp_path) == 0
    assert emulator.state.trims() != TRIMMED_BEFORE.trims()
    [backup] = tmp_path.glob("trim-backup-N25582405002002-*Z.json")
    doc = json.loads(backup.read_text())
    assert doc["trims"] == {"gyro_deg_s": [2**-6, -2**-8, 0.0], "acc_g": [0.0, 2**-10, 0.0],
                            "incl_g": [0.0, 0.0, -2**-13]}
    assert (doc["reference"], doc["remaining_saves"], doc["acc_range_g"]) == (777, 9998, 10)
    trimmed = emulator.state
    assert trim(emulator, "--restore", str(backup), backup_dir=tmp_path) == 0
    assert emulator.state == TRIMMED_BEFORE and emulator.saves_left == 9998 and emulator.mode == "normal"
    backups = sorted(tmp_path.glob("trim-backup-*.json"), key=lambda p: p.stat().st_mtime_ns)
    assert backups[0] == backup and json.loads(backup.read_text()) == doc  # never written over, same second or not
    assert json.loads(backups[1].read_text())["trims"]["gyro_deg_s"] == list(trimmed.gyro_trim_deg_s)


@pytest.mark.parametrize("change, words", [
    ({"reference": 1 << 32}, "reference"),
    ({"schema": "calibd.trim-backup/2"}, "newer than this calibd reads"),
    ({"acc_range_g": 7}, "acc_range_g"),
])
def test_a_bad_backup_is_one_line_and_the_unit_is_not_touched(result_file, unit, tmp_path, capsys, change, words):
    emulator = unit(TRIMMED_BEFORE)
    assert trim(emulator, "--from", result_file(), backup_dir=tmp_path) == 0
    [backup] = tmp_path.glob("trim-backup-*.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(json.loads(backup.read_text()) | change))
    trimmed = emulator.state
    capsys.readouterr()
    assert trim(emulator, "--restore", str(bad), backup_dir=tmp_path) == 2
    error = one_line(capsys.readouterr().err)
    assert str(bad) in error and words in error
    assert emulator.state == trimmed


def test_a_trim_is_volatile_until_saved_and_save_drops_the_counter_by_one(result_file, unit, tmp_path, capsys):
    emulator = unit()
    assert trim(emulator, "--from", result_file(), backup_dir=tmp_path) == 0
    volatile = emulator.state
    emulator.power_cycle()
    assert emulator.state == SENSOR_STATE  # lost at power-off
    time.sleep(0.3)  # past the start-up datagrams
    assert trim(emulator, "--from", result_file(), "--save", "--yes", "--force", backup_dir=tmp_path) == 0
    assert emulator.saves_left == 9997 and emulator.flash == volatile == emulator.state
    err = capsys.readouterr().err
    assert "remaining flash saves: 9998 saves" in err and "9997 saves remain" in err
    emulator.power_cycle()
    assert emulator.state == volatile


def test_save_is_refused_before_anything_is_written_when_no_saves_remain(result_file, unit, tmp_path, capsys):
    emulator = unit(saves_left=0)
    assert trim(emulator, "--from", result_file(), "--save", "--yes", backup_dir=tmp_path) == 2
    assert "no flash saves left" in one_line(capsys.readouterr().err)
    assert emulator.lines == [] and emulator.state == SENSOR_STATE and not list(tmp_path.glob("trim-backup-*"))


def test_show_prints_the_trims_in_force_with_units(unit, tmp_path, capsys):
    emulator = unit(TRIMMED_BEFORE)
    assert main(["trim", emulator.path, "--show"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "serial number    N25582405002002"
    assert out[1] == "gyro trim        x +0.015625000  y -0.003906250  z +0.000000000 deg/s"
    assert out[4:] == ["reference        777 (0x00000309)", "remaining saves  9998 saves"]
    assert emulator.lines == []  # Normal Mode requests only


def test_dry_run_writes_nothing(result, result_file, unit, tmp_path, capsys):
    emulator = unit()
    assert trim(emulator, "--from", result_file(), "--dry-run", backup_dir=tmp_path) == 0
    out = capsys.readouterr().out
    assert "b 0,g" in out and f"b {trim_reference(result.session_id)},r" in out
    assert emulator.lines == [] and not list(tmp_path.glob("trim-backup-*"))


# ---------------------------------------------------------------- refusals

def _poor(r):
    return r.flag_poor(["acc_bias_y"])


def _missing(r):
    return replace(r, estimates={k: e for k, e in r.estimates.items() if not k.startswith("incl_")})


def _noisy(r):
    return replace(r, estimates=r.estimates | {"gyro_bias_z": replace(r.estimates["gyro_bias_z"], sigma=4.5)})


def _other_sensor(r):
    return replace(r, sensor=replace(r.sensor, serial_number="N25582405009999"))


def _stale(r):
    return replace(r, stale=StaleRecord("previous", "the sensor restarted", "2026-01-01T00:00:00+00:00"))


def _later_power_up(r):
    return replace(r, stream=replace(r.stream, power_up=replace(r.stream.power_up, number=1, count=2)))


@pytest.mark.parametrize("change, words", [
    (_other_sensor, "the result is of sensor N25582405009999, the unit on the port is N25582405002002"),
    (_poor, "acc_bias_y is flagged poor"),
    (_noisy, "gyro_bias_z: 1-sigma 4.5 deg/h exceeds the datasheet's run-to-run bias 4 deg/h"),
    (_stale, "the result is stale: the sensor restarted"),
    (_later_power_up, "turn-on biases and its capture shows the sensor restarted after them (power-up 1 of 2)"),
])
def test_each_refusal_changes_nothing_and_force_overrides_it(result, result_file, unit, tmp_path, capsys,
                                                              change, words):
    emulator = unit()
    path = result_file(change(result))
    assert trim(emulator, "--from", path, backup_dir=tmp_path) == 2
    err = one_line(capsys.readouterr().err)
    assert words in err and "--force" in err
    assert emulator.lines == [] and emulator.state == SENSOR_STATE and not list(tmp_path.glob("trim-backup-*"))
    assert trim(emulator, "--from", path, "--force", backup_dir=tmp_path) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if line.startswith("calibd trim: warning: ")]
    assert len(warned) == 1 and words in warned[0]
    assert emulator.state != SENSOR_STATE


def test_a_result_without_a_sensors_estimates_is_refused_and_trims_the_others(result, result_file, unit, tmp_path,
                                                                            capsys):
    emulator = unit()
    path = result_file(_missing(result))
    assert trim(emulator, "--from", path, "--force", backup_dir=tmp_path) == 2
    assert "the result has no incl_bias_x, incl_bias_y, incl_bias_z: leave that sensor out with --sensors" in \
        one_line(capsys.readouterr().err)
    assert emulator.lines == []
    assert trim(emulator, "--from", path, "--sensors", "gyro,acc", backup_dir=tmp_path) == 0
    assert emulator.state.incl_trim_g == (0.0, 0.0, 0.0) and emulator.state.acc_trim_g != (0.0, 0.0, 0.0)


def test_a_unit_starting_up_refuses_a_turn_on_result(result_file, unit, tmp_path, capsys):
    emulator = unit()
    emulator.power_cycle()  # its power-up datagrams and start-up data are read before anything is changed
    assert trim(emulator, "--from", result_file(), backup_dir=tmp_path) == 2
    assert "the unit is starting up now" in one_line(capsys.readouterr().err)
    assert emulator.lines == []


def test_an_offset_beyond_the_trim_range_is_refused_even_with_force(result_file, unit, tmp_path, capsys):
    emulator = unit(replace(SENSOR_STATE, gyro_trim_deg_s=(-0.99, 0.0, 0.0)))  # less a +97 deg/h bias: < -1 deg/s
    assert trim(emulator, "--from", result_file(), "--force", backup_dir=tmp_path) == 2
    err = one_line(capsys.readouterr().err)
    assert "gyro x offset -1.01" in err and "beyond the trim range +-1 deg/s" in err and "7.5.2.3" in err
    assert emulator.lines == []


@pytest.mark.parametrize("argv, words", [
    (["--show", "--save"], "--show only reads"),
    (["--from", "r.json", "--yes"], "--yes answers the question --save asks"),
    (["--restore", "b.json", "--verify", "5"], "--restore puts back every offset"),
    (["--sensors", "gyro,mag", "--show"], "'gyro,mag': a comma-separated list of gyro, acc, incl"),
    ([], "give one of --from RESULT.json, --restore BACKUP.json, --show"),
])
def test_bad_options_are_one_line_and_exit_2(argv, words, capsys):
    assert main(["trim", "/dev/null", *argv]) == 2
    assert words in one_line(capsys.readouterr().err)


# ---------------------------------------------------------------- verify

@pytest.mark.slow  # seconds of static data read from the emulator in real time
def test_verify_passes_on_the_static_and_is_written_beside_the_backup(result_file, unit, tmp_path, capsys):
    emulator = unit()
    assert trim(emulator, "--from", result_file(), "--verify", "4", backup_dir=tmp_path) == 0
    [check] = tmp_path.glob("trim-verify-N25582405002002-*Z.json")
    doc = json.loads(check.read_text())
    assert doc["passed"] and doc["duration_s"] == 4 and set(doc["axes"]) == {"x", "y", "z"}
    assert all(abs(a["residual_deg_h"]) <= 2 * a["sigma_deg_h"] for a in doc["axes"].values())
    assert "verify passed" in capsys.readouterr().err


@pytest.mark.slow  # seconds of static data read from the emulator in real time
def test_a_failed_verify_takes_the_trim_back(result, result_file, unit, tmp_path, capsys):
    wrong = replace(result.estimates["gyro_bias_y"], value=result.estimates["gyro_bias_y"].value + 40)
    emulator = unit(TRIMMED_BEFORE, measured_with=TRIMMED_BEFORE)
    assert trim(emulator, "--from", result_file(replace(result, estimates=result.estimates | {"gyro_bias_y": wrong})),
                "--verify", "4", "--save", "--yes", backup_dir=tmp_path) == 1
    err = capsys.readouterr().err
    assert "gyro y: residual" in err and "beyond 2 sigma" in err and "the trim was taken back" in err
    assert emulator.state == TRIMMED_BEFORE and emulator.saves_left == 9998
    [check] = tmp_path.glob("trim-verify-*.json")
    assert json.loads(check.read_text())["passed"] is False


def test_verify_needs_a_rate_output_and_says_so_before_anything_is_written(result_file, unit, tmp_path, capsys):
    emulator = unit(replace(SENSOR_STATE, gyro_unit=GyroUnit.INCREMENTAL_ANGLE))
    assert trim(emulator, "--from", result_file(), "--verify", "4", backup_dir=tmp_path) == 2
    assert "--verify needs the gyros' output as a rate, the unit outputs incremental_angle" in \
        one_line(capsys.readouterr().err)
    assert emulator.lines == []


# ---------------------------------------------------------------- interrupted at every step

@pytest.mark.slow  # a whole trim with --verify and --save, interrupted at each of its steps
def test_an_interrupt_at_any_step_puts_the_backup_back_in_normal_mode(result, unit, tmp_path):
    """Every step of a trim with --verify and --save, Ctrl-C there: the unit is back in Normal Mode
    with the offsets and reference it had, and no save is spent unless the save went through."""
    options = TrimOptions(backup_dir=tmp_path, verify_s=2.0, save=True)
    steps = []
    emulator = unit(TRIMMED_BEFORE, measured_with=TRIMMED_BEFORE)
    with open_serial(emulator.path) as ser:
        trim_from_result(ser, result, options, lambda text: None, lambda saves: True, steps.append)
    assert emulator.saves_left == 9997 and steps[1] == "enter Service Mode" and "s" in steps
    for k, at in enumerate(steps):
        emulator = unit(TRIMMED_BEFORE, measured_with=TRIMMED_BEFORE)

        def step(text, count=iter(range(len(steps)))):
            if next(count) == k:
                raise KeyboardInterrupt
        with open_serial(emulator.path) as ser, pytest.raises(KeyboardInterrupt):
            trim_from_result(ser, result, options, lambda text: None, lambda saves: True, step)
        assert emulator.mode == "normal" and emulator.state == TRIMMED_BEFORE, at
        assert emulator.saves_left == (9998 if k <= steps.index("s") else 9997), at
        emulator.stop()


def test_sigterm_mid_trim_puts_the_backup_back(result, result_file, unit, tmp_path):
    emulator = unit(TRIMMED_BEFORE, silent=(f"b {trim_reference(result.session_id)},r",))  # the program waits there
    program = subprocess.Popen([sys.executable, "-m", "calibd", "trim", emulator.path, "--from", result_file(),
                                "--backup-dir", str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=command_env(), cwd=ROOT)
    deadline = time.monotonic() + 20
    while emulator.silent[0] not in emulator.lines and time.monotonic() < deadline:
        time.sleep(0.02)
    program.send_signal(signal.SIGTERM)
    _, err = program.communicate(timeout=30)
    assert program.returncode == 130 and "Traceback" not in err
    assert "restored the offsets of" in err
    assert emulator.mode == "normal" and emulator.state == TRIMMED_BEFORE and emulator.saves_left == 9998


# ---------------------------------------------------------------- the driver

def test_each_axis_is_set_from_zero_by_a_delta():
    trims = TrimOffsets((0.5, 0.0, -0.25), (0.0, 0.0, 0.0), (1.5e-5, 0.0, 0.0))
    assert trim_commands(trims, ("gyro", "incl"), 42) == ["b 0,g", "b 0.5,g,x", "b -0.25,g,z", "b 0,i",
                                                          "b 0.000015,i,x", "b 42,r"]


def test_a_clamped_trim_is_the_units_e008_and_the_clamped_value_stays(unit):
    emulator = unit()
    with open_serial(emulator.path) as ser:
        with pytest.raises(TrimError, match="E008 BIAS TRIM CLIPPED .*clamped"), service_mode(ser):
            write_trims(ser, ["b 1.5,g,x"])
        reading = read_trims(ser)
    assert reading.trim.trims.gyro_deg_s == (1.0, 0.0, 0.0) and emulator.mode == "normal"


# ---------------------------------------------------------------- the documented rules

def test_the_reference_is_the_session_ids_sha256_first_four_bytes():
    assert trim_reference("abc") == 0xBA7816BF  # SHA-256("abc") begins ba7816bf
    assert trim_reference("3d86dee0e7552854/p1/t0.000") != trim_reference("3d86dee0e7552854/p1/t1.000")


def test_docs_trim_gives_the_datasheet_figures_calibd_uses():
    text = " ".join((ROOT / "docs" / "trim.md").read_text(encoding="utf-8").split())
    gyro, incl, acc = spec.GYRO, spec.INCL, spec.ACC
    assert f"run-to-run bias, {gyro.bias_run_to_run:g} deg/h" in text
    assert f"({gyro.bias_over_temperature:g} deg/h rms for the gyros" in text
    assert f"+-{gyro.bias_trim_range:g} deg/s for the gyros" in text and f"+-{incl.bias_trim_range:g} g" in text
    assert f"({acc[5].bias_one_year:g} mg for 5 and 10 g" in text and f"{acc[80].bias_one_year:g} mg for 80 g" in text
    assert f"bias error over temperature ({incl.bias_over_temperature:g} mg rms)" in text
    assert f"angular random walk, {gyro.random_walk:g} deg/sqrt(h)" in text


def test_the_verify_sigma_carries_the_attitude_and_its_correlation_with_the_biases():
    from calibd.frames import nav_to_imu
    from calibd.results import make_result
    from calibd.trim import expected_static_sigma
    from calibd.units import DEG, RAD_S_TO_DEG_H
    from stim300.records import SensorRecord
    site = Site(40.0)
    names = ["yaw", "pitch", "roll", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z"]
    sigmas = np.array([2 * DEG, 0.01 * DEG, 0.01 * DEG, *(np.full(3, 0.5 / RAD_S_TO_DEG_H))])
    values = {"yaw": 0.3, "pitch": 0.0, "roll": 0.0, "gyro_bias_x": 0.0, "gyro_bias_y": 0.0, "gyro_bias_z": 0.0}
    independent = make_result("joint", site, {n: (values[n], s) for n, s in zip(names, sigmas)}, [], [],
                              SensorRecord())
    # without a covariance: the bias's 0.5 deg/h and the yaw's 2 deg of 11.2 deg/h of horizontal Earth rate
    horizontal = np.cos(np.radians(40.0)) * 15.041
    turned = np.abs((nav_to_imu(0.3 + 1e-6, 0, 0) - nav_to_imu(0.3 - 1e-6, 0, 0)) / 2e-6
                    @ site.earth_rate_nav * RAD_S_TO_DEG_H)
    expected = np.hypot(0.5, turned * 2 * DEG)
    np.testing.assert_allclose(expected_static_sigma(independent), expected, rtol=1e-4)  # and pitch, roll: 1e-5
    # yaw turns the whole horizontal Earth rate between X and Y
    assert np.sqrt(np.sum(expected[:2] ** 2 - 0.25)) == pytest.approx(horizontal * 2 * DEG, rel=0.01)
    # the joint method's yaw and horizontal biases move together: the gyro reading they expect is the statics'
    jacobian = (nav_to_imu(0.3 + 1e-6, 0, 0) - nav_to_imu(0.3 - 1e-6, 0, 0)) / 2e-6 @ site.earth_rate_nav
    covariance = np.diag(sigmas**2)
    covariance[3:, 0] = covariance[0, 3:] = -jacobian * sigmas[0] ** 2  # bias errors that undo the yaw's
    covariance[3:, 3:] += np.outer(jacobian, jacobian) * sigmas[0] ** 2
    correlated = make_result("joint", site, {n: (values[n], s) for n, s in zip(names, np.sqrt(np.diag(covariance)))},
                             [], [], SensorRecord(), covariance)
    np.testing.assert_allclose(expected_static_sigma(correlated), np.full(3, 0.5), rtol=1e-4)


def test_the_new_offsets_start_from_those_the_result_was_made_under():
    from calibd.results import make_result
    from calibd.trim import new_offsets
    from calibd.units import RAD_S_TO_DEG_H
    from stim300.records import SensorRecord, TrimRecord
    bias_deg_h = (36.0, -18.0, 7.2)
    estimates = {f"gyro_bias_{a}": (b / RAD_S_TO_DEG_H, 0.5 / RAD_S_TO_DEG_H) for a, b in zip("xyz", bias_deg_h)}
    made_under = TrimRecord((0.01, 0.0, -0.02), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 7, 100)
    present = TrimOffsets((0.5, 0.5, 0.5), (0.0,) * 3, (0.0,) * 3)  # trimmed again since: not what the output carried
    result = make_result("joint", Site(40.0), estimates, [], [], SensorRecord(trim=made_under))
    expected = np.subtract(made_under.gyro_deg_s, np.array(bias_deg_h) / 3600)
    np.testing.assert_allclose(new_offsets(result, present, ("gyro",)).gyro_deg_s, expected, atol=1e-12)
    unknown = make_result("joint", Site(40.0), estimates, [], [], SensorRecord())  # says nothing: the present ones
    np.testing.assert_allclose(new_offsets(unknown, present, ("gyro",)).gyro_deg_s,
                               np.subtract(present.gyro_deg_s, np.array(bias_deg_h) / 3600), atol=1e-12)


def test_the_daemon_keeps_only_the_newest_backups_of_each_sensor(tmp_path):
    from datetime import datetime, timedelta, timezone

    from calibd.trim import prune_backups, write_backup
    from stim300.trim import TrimReading, UnitReading

    start = datetime(2026, 5, 1, tzinfo=timezone.utc)
    reading = TrimReading(TrimOffsets((0.0,) * 3, (0.0,) * 3, (0.0,) * 3), 1, 9998, 10)
    made = [write_backup(tmp_path, UnitReading(reading, serial, GyroUnit.RATE, False), "/dev/x",
                         start + timedelta(seconds=k // 2)) for k in range(8) for serial in ("A1", "B2")]
    other = tmp_path / "notes.json"
    other.write_text("{}")
    removed = prune_backups(tmp_path, "A1", keep=3)
    kept = {p.name for p in tmp_path.glob("trim-backup-A1-*")}
    assert kept == {"trim-backup-A1-20260501T000002Z-2.json", "trim-backup-A1-20260501T000003Z.json",
                    "trim-backup-A1-20260501T000003Z-2.json"}  # the second of a second is newer than the first
    assert len(removed) == 5 and all(not p.exists() for p in removed)
    assert len(list(tmp_path.glob("trim-backup-B2-*"))) == 8 and other.exists()  # another sensor's; not a backup
    assert len(made) == 16

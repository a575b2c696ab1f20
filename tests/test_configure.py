"""`stim300 config PORT` against a pty emulation of the sensor (tests/sensor_emulator.py): the `i`
report read and printed, each change reaching the unit, bad values refused before the unit is
touched, the unit's refusals reported, the flash save and its refusals, a port held by another
process, and the unit back in Normal Mode on every way out."""

import io
import json
import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest

from captures import Terminal, command_env
from sensor_emulator import SensorEmulator, State, report
import stim300.configure as configure_module
from stim300.cli import main
from stim300.configure import (Changes, ConfigureError, bit_rate_command, configure, parse_report,
                               plan)
from stim300.errors import FormatError, ServiceError, ServiceTimeout
from stim300.port import open_serial
from stim300.service import service_mode
from stim300.protocol import AccUnit, Format, GyroUnit
from stim300.stream import StreamParser

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def sensor():
    emulator = SensorEmulator()
    emulator.start()
    yield emulator
    emulator.stop()


def emulated(**kwargs):
    emulator = SensorEmulator(**kwargs)
    emulator.start()
    return emulator


def report_of(state: State, saves_left: int = 9998):
    return parse_report(report(state, saves_left).decode("latin-1").replace("\r", "\n"))


def stderr_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


# ---------------------------------------------------------------- the report, the commands

def test_report_fields_are_typed_and_other_lines_kept_as_printed():
    state = State(sample_rate_code=1, datagram_id=0xF5, crlf=True, gyro_unit=GyroUnit.INTEGRATED_ANGLE_DELAYED,
                  acc_unit=AccUnit.INTEGRATED_VELOCITY_MS, incl_unit=AccUnit.INTEGRATED_VELOCITY_GS,
                  gyro_lpf_hz=(16, 33, 66), bit_rate_bps=1843200)
    report = report_of(state, saves_left=17)
    assert (report.serial_number, report.part_number, report.firmware) == (
        "N25582405002002", "84167-4400003-321 REV K", "SWD12345 REV 2")
    assert (report.sample_rate_hz, report.external_trigger, report.datagram_id, report.crlf) == (250, False, 0xF5, True)
    assert (report.gyro_unit, report.acc_unit, report.incl_unit) == (
        GyroUnit.INTEGRATED_ANGLE_DELAYED, AccUnit.INTEGRATED_VELOCITY_MS, AccUnit.INTEGRATED_VELOCITY_GS)
    assert (report.gyro_lpf_hz, report.acc_lpf_hz, report.incl_lpf_hz) == ((16, 33, 66), (262,) * 3, (16,) * 3)
    assert (report.bit_rate_bps, report.remaining_saves) == (1843200, 17)
    assert dict(report.other)["LINE TERMINATION"] == "ON"  # the RS422 resistor, not the datagram's CR LF
    assert report_of(State(sample_rate_code=5)).external_trigger is True


def test_report_values_that_do_not_read_are_kept_not_guessed():
    report = parse_report("DATAGRAM = RATE, ACC, INCL, TEMP\nGYRO OUTPUT UNIT = FURLONGS\nSAMPLE RATE [Hz] = fast\n"
                          "TRIGGER = EXTERNAL\nnot a field line")
    assert report.datagram_id == 0xA7  # content words give the id as the configuration datagram would
    assert report.gyro_unit is None and report.sample_rate_hz is None and report.external_trigger is True
    assert report.other == (("GYRO OUTPUT UNIT", "FURLONGS"), ("SAMPLE RATE [Hz]", "fast"), ("not a field line", ""))
    assert dict(report.rows())["bit_rate_bps"] == "- (not in the report)"


def test_each_change_is_one_service_mode_command_bit_rate_last():
    current = report_of(State())
    commands = plan(Changes(bit_rate_bps=460800, sample_rate="external", datagram_id=0xF7, gyro_unit=GyroUnit(9),
                            acc_unit=AccUnit(4), incl_unit=AccUnit(2), gyro_lpf_hz=16, acc_lpf_hz=131, incl_lpf_hz=66),
                    current)
    assert [(c.option, c.text) for c in commands] == [
        ("--rate", "m 5"), ("--datagram", "d t,0"), ("--gyro-unit", "u g,9"), ("--acc-unit", "u a,4"),
        ("--incl-unit", "u i,2"), ("--gyro-lpf", "f 0,g"), ("--acc-lpf", "f 3,a"), ("--incl-lpf", "f 2,i"),
        ("--bit-rate", "t 1")]
    assert [c.text for c in plan(Changes(bit_rate_bps=1843200, gyro_lpf_hz=16), current)] == ["t 3", "f 0,g"]
    assert [c.text for c in plan(Changes(sample_rate=2000, datagram_id=0x90), current)] == ["d 0,0", "m 4"]
    assert [c.text for c in plan(Changes(crlf=True), current)] == ["d 3,1"]  # the current datagram, 0x93
    assert [c.text for c in plan(Changes(datagram_id=0x94), current)] == ["d 4,0"]  # the current termination
    with pytest.raises(ConfigureError, match="--crlf.*give both"):
        plan(Changes(crlf=True), parse_report("SAMPLE RATE [Hz] = 125"))


def test_bit_rate_commands():
    assert bit_rate_command(500000) == "t f,500000" and bit_rate_command(1843200) == "t 3"
    with pytest.raises(FormatError, match="1500..5184000"):
        bit_rate_command(5184001)


# ---------------------------------------------------------------- reading

# Ends of the datagram in progress at SERVICEMODE: bytes a report holds (0xB0, 0xB1, CR, '>',
# digits, letters) among bytes it does not (controls, other Latin-1), and right before the
# report bytes that could be its text but for a letter to begin it
DATAGRAM_TAILS = (bytes([0x93, 0xB0, 0x3E, 0x0D, 0xB1, 0x81, 0xB0, 0x41, 0x7F, 0xB1, 0x02]),
                  bytes([0x93, 0x41, 0xA5, 0x0D, 0x3E, 0x35, 0xB0, 0xB1, 0x20]),
                  bytes([0x12, 0x0D, 0x3E, 0x93, 0x7F, 0xA5]))


@pytest.mark.parametrize("tail", DATAGRAM_TAILS)
def test_the_servicemode_report_keeps_its_latin1_signs_and_drops_the_datagram_tail(tail):
    """A real unit prints deg and +- as the single bytes 0xB0 and 0xB1: the whole report is kept
    (the text after the last of them is not all there is), the datagram's tail is not."""
    sensor = emulated(datagram_tail=tail)
    try:
        with open_serial(sensor.path) as ser:
            with service_mode(ser) as banner:
                pass
    finally:
        sensor.stop()
    expected = report(State(), 9998).decode("latin-1").replace("\r", "\n")
    assert banner == expected
    assert banner.startswith("PRODUCT = STIM300\n") and "GYRO RANGE [deg/s] = \u00b1400" in banner
    assert "GYRO TRIM [\u00b0/s] = +0.000000000" in banner

def test_config_reads_prints_and_leaves_the_sensor_sending_datagrams(sensor, capsys):
    assert main(["config", sensor.path]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "sample_rate_hz:     2000 Hz" in out and "datagram_id:        0x93" in out
    assert "bit_rate_bps:       921600 bit/s" in out and "remaining_saves:    9998 saves" in out
    assert len({len(line) - len(line[line.index(":") + 1:].lstrip()) for line in out}) == 1  # one value column
    assert sensor.mode == "normal" and sensor.lines == ["i", "x N"] and sensor.state == State()
    sent = sensor.datagrams_sent
    with open_serial(sensor.path) as ser:
        time.sleep(0.1)
        samples = StreamParser(Format(datagram_id=0x93, crlf=False, sample_rate_hz=2000)).feed(ser.read(4096))
    assert sensor.datagrams_sent > sent and len(samples) > 0


def test_config_json_names_every_field(sensor, capsys):
    assert main(["config", sensor.path, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["configuration"]["sample_rate_hz"] == 2000 and doc["configuration"]["gyro_unit"] == "rate"
    assert doc["changed"] == [] and doc["applied"] == [] and doc["saved"] is False
    assert sensor.mode == "normal"


# ---------------------------------------------------------------- changing

@pytest.mark.parametrize("option, value, field, expected, shown", [
    ("--rate", "250", "sample_rate_code", 1, "sample_rate_hz:     250 Hz"),
    ("--rate", "external", "sample_rate_code", 5, "external_trigger:   yes"),
    ("--datagram", "0x91", "datagram_id", 0x91, "datagram_id:        0x91"),
    ("--datagram", "0xF3", "datagram_id", 0xF3, "datagram_id:        0xF3"),
    ("--crlf", "yes", "crlf", True, "crlf:               yes"),
    ("--gyro-unit", "integrated-delayed", "gyro_unit", GyroUnit.INTEGRATED_ANGLE_DELAYED,
     "gyro_unit:          integrated_angle_delayed (deg)"),
    ("--acc-unit", "integrated-ms", "acc_unit", AccUnit.INTEGRATED_VELOCITY_MS,
     "acc_unit:           integrated_velocity_ms (m/s)"),
    ("--incl-unit", "incremental", "incl_unit", AccUnit.INCREMENTAL_VELOCITY,
     "incl_unit:          incremental_velocity (m/s)"),
    ("--gyro-lpf", "16", "gyro_lpf_hz", (16, 16, 16), "gyro_lpf_hz:        16, 16, 16 Hz"),
    ("--acc-lpf", "66", "acc_lpf_hz", (66, 66, 66), "acc_lpf_hz:         66, 66, 66 Hz"),
    ("--incl-lpf", "131", "incl_lpf_hz", (131, 131, 131), "incl_lpf_hz:        131, 131, 131 Hz"),
    ("--bit-rate", "1843200", "bit_rate_bps", 1843200, "bit_rate_bps:       1843200 bit/s"),
    ("--bit-rate", "1000000", "bit_rate_bps", 999325, "bit_rate_bps:       999325 bit/s"),  # 82944000 / 83
])
def test_each_setting_reaches_the_sensor_and_the_report_shows_it(sensor, capsys, option, value, field, expected,
                                                                  shown):
    assert main(["config", sensor.path, option, value]) == 0
    assert getattr(sensor.state, field) == expected
    assert sensor.flash == State() and sensor.mode == "normal"  # volatile
    out, err = capsys.readouterr()
    assert [line for line in out.splitlines() if line.startswith(shown)][0].split("   (was ")[1]
    assert "volatile" in err


def test_the_port_ends_at_the_rate_the_unit_made_of_a_user_defined_one(sensor):
    with open_serial(sensor.path) as ser:
        outcome = configure(ser, Changes(bit_rate_bps=1000000))
        assert ser.baudrate == outcome.after.bit_rate_bps == sensor.state.bit_rate_bps == 999325
    assert sensor.mode == "normal" and sensor.lines == ["i", "t f,1000000", "i", "x N"]


@pytest.mark.slow
def test_changes_go_one_by_one_and_the_port_follows_the_bit_rate(sensor, capsys):
    assert main(["config", sensor.path, "--rate", "500", "--gyro-lpf", "33", "--bit-rate", "460800"]) == 0
    assert sensor.lines == ["i", "m 2", "f 1,g", "t 1", "i", "x N"]
    assert sensor.state == replace(State(), sample_rate_code=2, gyro_lpf_hz=(33, 33, 33), bit_rate_bps=460800)
    assert "bit_rate_bps:       460800 bit/s   (was 921600 bit/s)" in capsys.readouterr().out
    assert main(["config", sensor.path]) == 1  # the sensor now runs at 460800 bit/s
    assert "at 921600 bit/s? --baud" in stderr_line(capsys)
    assert main(["config", sensor.path, "--baud", "460800"]) == 0
    assert sensor.mode == "normal"


@pytest.mark.parametrize("argv, allowed", [
    (["--rate", "300"], "125, 250, 500, 1000, 2000, external"),
    (["--datagram", "0xAF"], "0x90, 0x91"),
    (["--datagram", "zz"], "0xF7"),
    (["--crlf", "maybe"], "yes, no"),
    (["--gyro-unit", "rad/s"], "rate, incremental, average, integrated, rate-delayed"),
    (["--acc-unit", "integrated"], "integrated-gs, integrated-ms"),
    (["--incl-lpf", "100"], "16, 33, 66, 131, 262"),
    (["--bit-rate", "115"], "374400, 460800, 921600, 1843200 or a user-defined rate 1500..5184000"),
    (["--bit-rate", "fast"], "not a number of bit/s"),
    (["--yes"], "with --save"),
])
def test_invalid_values_are_refused_before_the_sensor_is_touched(sensor, capsys, argv, allowed):
    assert main(["config", sensor.path, "--rate", "125", *argv]) == 2
    err = stderr_line(capsys)
    assert err.startswith("stim300 config: ") and allowed in err
    assert argv[0] in err
    assert sensor.entries == 0 and sensor.lines == [] and sensor.state == State()


def test_what_lightens_the_line_goes_first(sensor, capsys):
    """0xA7 (59 bytes) at 2000 Hz needs more than 921600 bit/s: the bit rate is raised first."""
    assert main(["config", sensor.path, "--datagram", "0xA7", "--bit-rate", "1843200"]) == 0
    assert sensor.lines == ["i", "t 3", "i", "d 7,0", "i", "x N"]
    assert (sensor.state.datagram_id, sensor.state.bit_rate_bps, sensor.mode) == (0xA7, 1843200, "normal")
    sensor.lines.clear()
    # back down: the shorter datagram first, the lower bit rate last (first, 0xA7 would not fit)
    assert main(["config", sensor.path, "--baud", "1843200", "--bit-rate", "374400", "--rate", "1000",
                 "--datagram", "0x90"]) == 0
    assert sensor.lines == ["i", "d 0,0", "m 3", "t 0", "i", "x N"]
    assert sensor.state == replace(State(), datagram_id=0x90, sample_rate_code=3, bit_rate_bps=374400)


def test_a_sensor_error_reply_names_the_command_and_what_was_applied(capsys):
    sensor = emulated(refuse={"f 1,g": 3})
    try:
        assert main(["config", sensor.path, "--rate", "500", "--gyro-lpf", "33", "--acc-lpf", "16"]) == 1
        err = stderr_line(capsys)
        assert "--gyro-lpf: service command 'f 1,g': E003 INVALID PARAMETER (applied before it: m 2)" in err
        assert "back in Normal Mode" in err
        assert sensor.mode == "normal" and sensor.lines == ["i", "m 2", "f 1,g", "x N"]
        assert sensor.state == replace(State(), sample_rate_code=2)  # the refused one and those after it: not sent
    finally:
        sensor.stop()


def test_a_datagram_too_long_for_the_bit_rate_is_the_sensors_e007(sensor, capsys):
    # 0xA7 is 59 bytes: 2000 Hz needs 1.18 Mbit/s, the unit runs at 921600 bit/s
    assert main(["config", sensor.path, "--datagram", "0xA7"]) == 1
    assert "--datagram: service command 'd 7,0': E007" in stderr_line(capsys)
    # a bit rate too low for the datagram is refused at the old rate: the port stays there
    assert main(["config", sensor.path, "--bit-rate", "374400"]) == 1
    assert "--bit-rate: service command 't 0': E007" in stderr_line(capsys)
    assert sensor.state == State() and sensor.mode == "normal"
    assert main(["config", sensor.path]) == 0


# ---------------------------------------------------------------- saving

def test_save_with_yes_writes_flash_and_shows_the_remaining_saves(sensor, capsys):
    assert main(["config", sensor.path, "--rate", "1000", "--save", "--yes"]) == 0
    assert sensor.flash == sensor.state == replace(State(), sample_rate_code=3) and sensor.saves_left == 9997
    out, err = capsys.readouterr()
    assert "remaining flash saves: 9998 saves" in err and "saved to flash" in err
    assert "remaining_saves:    9997 saves" in out
    assert sensor.lines == ["i", "m 3", "i", "s", "i", "x N"] and sensor.mode == "normal"


def test_a_declined_save_keeps_the_changes_volatile(sensor, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", Terminal("n\n"))
    assert main(["config", sensor.path, "--incl-lpf", "33", "--save"]) == 1
    out, err = capsys.readouterr()
    assert "write this configuration to the sensor's flash? [y/N]" in err
    assert err.rstrip().endswith("not saved: the save was declined; the changes stay until the sensor is reset")
    assert "(was 16, 16, 16 Hz)" in out
    assert sensor.state.incl_lpf_hz == (33, 33, 33) and sensor.flash == State() and sensor.saves_left == 9998
    assert "s" not in sensor.lines and sensor.mode == "normal"


def test_save_is_refused_when_no_flash_saves_remain(capsys):
    sensor = emulated(saves_left=0)
    try:
        assert main(["config", sensor.path, "--rate", "125", "--save", "--yes"]) == 1
        assert "0 flash saves remaining: nothing was changed" in stderr_line(capsys)
        assert sensor.lines == ["i", "x N"] and sensor.state == State() and sensor.mode == "normal"
    finally:
        sensor.stop()


def test_save_without_a_terminal_needs_yes(sensor, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", io.StringIO("y\n"))
    assert main(["config", sensor.path, "--save"]) == 2
    assert "give --yes" in stderr_line(capsys)
    assert sensor.entries == 0


def test_ctrl_c_at_the_question_leaves_the_sensor_in_normal_mode(sensor, monkeypatch):
    class Interrupted(Terminal):
        def readline(self, *args):
            raise KeyboardInterrupt
    monkeypatch.setattr(sys, "stdin", Interrupted())
    assert main(["config", sensor.path, "--rate", "250", "--save"]) == 130
    assert sensor.mode == "normal" and sensor.lines[-1] == "x N" and sensor.flash == State()


# ---------------------------------------------------------------- the port and silence

def test_a_port_held_by_another_process_is_refused(sensor, capsys):
    with open_serial(sensor.path):
        assert main(["config", sensor.path, "--rate", "125"]) == 1
    assert stderr_line(capsys) == f"stim300 config: {sensor.path}: in use by another process\n"
    assert sensor.entries == 0 and sensor.state == State()


def test_a_silent_sensor_mid_session_is_still_sent_back_to_normal_mode():
    sensor = emulated(silent=("m 1",))
    try:
        with open_serial(sensor.path) as ser, pytest.raises(ConfigureError, match="--rate.*no prompt after 'm 1'"):
            configure(ser, Changes(sample_rate=250), timeout=0.3)
        assert sensor.mode == "normal" and sensor.lines == ["i", "m 1", "x N"]
    finally:
        sensor.stop()


def test_a_failed_exit_names_both_failures(monkeypatch):
    sensor = emulated(silent=("x N",), refuse={"m 1": 3})
    try:
        with open_serial(sensor.path) as ser, pytest.raises(ServiceError) as failed:
            configure(ser, Changes(sample_rate=250), timeout=0.3)
        assert "could not leave Service Mode" in str(failed.value) and "E003" in str(failed.value)
    finally:
        sensor.stop()


# ---------------------------------------------------------------- as a program

def run_cli(*argv):
    return subprocess.run([sys.executable, "-m", "stim300.cli", "config", *argv], capture_output=True, text=True,
                          env=command_env(), cwd=ROOT, timeout=60)


def test_the_program_reads_the_configuration_and_refuses_a_held_port(sensor):
    done = run_cli(sensor.path)
    assert done.returncode == 0 and done.stderr == ""
    assert "serial_number:      N25582405002002" in done.stdout.splitlines()
    with open_serial(sensor.path):
        held = run_cli(sensor.path, "--gyro-lpf", "33")
    assert held.returncode == 1 and held.stdout == ""
    assert held.stderr == f"stim300 config: {sensor.path}: in use by another process\n"
    bad = run_cli(sensor.path, "--rate", "3000")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--rate" in bad.stderr
    assert sensor.mode == "normal" and sensor.state == State() and sensor.lines == ["i", "x N"]


def test_a_unit_that_keeps_its_bit_rate_is_found_at_the_old_one():
    sensor = emulated(silent=("t 1",))  # takes the command, says nothing, keeps 921600 bit/s
    try:
        with open_serial(sensor.path) as ser, pytest.raises(ConfigureError) as kept:
            configure(ser, Changes(bit_rate_bps=460800), timeout=0.3)
        assert "still answers at 921600 bit/s, not at 460800 bit/s" in str(kept.value)
        assert ser.baudrate == 921600
        assert sensor.mode == "normal" and sensor.lines == ["i", "t 1", "\ufffd\ufffd", "i", "x N"]  # i CR at 460800
    finally:
        sensor.stop()


def test_no_prompt_after_servicemode_still_sends_the_exit(pty):
    """SERVICEMODE may have arrived and only the prompt been lost: `x N` goes out anyway."""
    master, path = pty
    with open_serial(path) as ser, pytest.raises(ServiceTimeout, match="SERVICEMODE|Service Mode"):
        configure(ser, Changes(), timeout=0.2)
    written = b""
    while select.select([master], [], [], 0.5)[0]:
        written += os.read(master, 100)
    assert written == b"SERVICEMODE\rx N\r"


def test_ctrl_c_while_a_command_is_answered_still_leaves_cleanly(sensor, monkeypatch, capsys):
    """The answer to the interrupted command arrives after Ctrl-C: it is not taken for the exit's."""
    def interrupted(ser, command, timeout=3.0):
        if command == "i":
            return real(ser, command, timeout)
        ser.write(command.encode() + b"\r")
        raise KeyboardInterrupt
    real = configure_module.service_command
    monkeypatch.setattr(configure_module, "service_command", interrupted)
    assert main(["config", sensor.path, "--rate", "250"]) == 130
    assert capsys.readouterr().err == ""
    assert sensor.lines == ["i", "m 1", "x N"] and sensor.mode == "normal"


def test_sigterm_mid_session_leaves_the_sensor_in_normal_mode():
    """`kill` (or systemd stopping a script's unit) ends a session as Ctrl-C does: back to Normal Mode."""
    sensor = emulated(silent=("m 1",))  # the unit takes the command and says nothing: the program waits
    try:
        program = subprocess.Popen([sys.executable, "-m", "stim300.cli", "config", sensor.path, "--rate", "250"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=command_env(),
                                   cwd=ROOT)
        deadline = time.monotonic() + 20
        while "m 1" not in sensor.lines and time.monotonic() < deadline:
            time.sleep(0.02)
        program.send_signal(signal.SIGTERM)
        _, err = program.communicate(timeout=20)
        assert program.returncode == 130 and "Traceback" not in err
        assert sensor.mode == "normal" and sensor.lines[-1] == "x N"
    finally:
        sensor.stop()

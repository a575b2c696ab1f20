"""Every command, on every bad input: exit 2 (input) or 1 (run), one line on stderr naming the
thing, no traceback, no file left behind, no device or FIFO replaced."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from captures import capture, exact_samples
from stim300.cli import main as stim300_main
from stim300.codec import encode_samples
from stim300.protocol import Format
from stim300.special import Configuration, encode_special

FIXTURES = Path(__file__).parent.parent / "fixtures"
GOOD = FIXTURES / "heading137_lat60_125hz.bin"  # calibrates, and has statics long enough for `noise`


def _scenario(tables: str) -> bytes:
    return ('seed = 1\n[site]\nlatitude_deg = 60\n' + tables).encode()


def _quiet_capture(n: int) -> bytes:
    """n datagrams at 125 Hz with no status bit set (no start-up bit: one power-up)."""
    fmt = Format(datagram_id=0xA7, crlf=True, sample_rate_hz=125)
    samples = exact_samples(n, fmt, 0xA7, np.random.default_rng(3))
    for cluster in ("gyro", "acc", "incl"):
        samples["status_" + cluster] = 0
    return encode_samples(samples, 0xA7, fmt, True).tobytes()


def _inputs(d: Path) -> dict[str, Path]:
    """Bad (and good) inputs by name, built in `d`."""
    config = encode_special(Configuration.build(sample_rate_hz=125, crlf=True), True)
    data, samples, fmt = capture(300, 0x93, True, rate=125)
    datagram = len(data) // 300
    stuck = samples.copy()
    stuck["counter"] = 7
    external = encode_special(Configuration.build(sample_rate_hz=None, crlf=True), True)
    files = {
        "one.bin": data[:datagram],
        "one_cfg.bin": config + data[:datagram],
        "stuck.bin": encode_samples(stuck, 0x93, fmt, True).tobytes(),
        "external.bin": external + data[:datagram],
        "short_cfg.bin": config + _quiet_capture(100),
        "text.bin": b"not a STIM300 capture\n" * 100,
        "rate125.bin": data,
        "empty.bin": b"",
        "huge.toml": _scenario('[[segments]]\ntype = "turn"\nangle_deg = 1e9\npeak_rate_deg_s = 1\n'
                               'accel_deg_s2 = 1\n'),
        "serial.toml": _scenario('[sensor]\nserial_number = "X1"\n[[segments]]\ntype = "static"\n'
                                 'duration_s = 1\n'),
        "drop.toml": _scenario('[faults]\ndrop = 125\n[[segments]]\ntype = "static"\nduration_s = 1\n'),
    }
    for name, content in files.items():
        (d / name).write_bytes(content)
    os.mkfifo(d / "fifo")
    os.mkfifo(d / "fifo.csv")
    (d / "dir").mkdir()
    return {name.split(".")[0]: d / name for name in files} | {
        "fifo": d / "fifo", "fifo_csv": d / "fifo.csv", "dir": d / "dir"}


def _run(main, argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


CALIBRATE = ["calibrate", "{capture}", "-o", "{out}/r.json", "--latitude", "60"]

CASES = {  # name: (program, argv with {placeholders}, exit status, text in the one stderr line)
    # inputs that are not regular files are refused, never read until memory runs out
    "calibrate /dev/zero": ("calibd", ["calibrate", "/dev/zero", "-o", "{out}/r.json", "--latitude", "60"], 2,
                            "/dev/zero: not a regular file"),
    "calibrate fifo": ("calibd", ["calibrate", "{fifo}", "-o", "{out}/r.json", "--latitude", "60"], 2,
                       "not a regular file"),
    "replay /dev/zero": ("calibd", ["replay", "/dev/zero", "--latitude", "60"], 2, "/dev/zero: not a regular file"),
    "noise /dev/zero": ("calibd", ["noise", "/dev/zero"], 2, "/dev/zero: not a regular file"),
    "report /dev/zero result": ("calibd", ["report", "/dev/zero", GOOD, "-o", "{out}/r.html"], 2,
                                "/dev/zero: not a regular file"),
    "report /dev/zero capture": ("calibd", ["report", "{result}", "/dev/zero", "-o", "{out}/r.html"], 2,
                                 "/dev/zero: not a regular file"),
    "run config /dev/zero": ("calibd", ["run", "--config", "/dev/zero"], 2, "/dev/zero: not a regular file"),
    "simulate scenario /dev/zero": ("calibd", ["simulate", "/dev/zero", "-o", "{out}/c.bin"], 2,
                                    "/dev/zero: not a regular file (a device or FIFO), expected a scenario file"),
    "plan noise /dev/zero": ("calibd", ["plan", "--latitude", "60", "--protocol", "thesis", "--noise", "/dev/zero"],
                             2, "/dev/zero: not a regular file"),
    "info /dev/zero": ("stim300", ["info", "/dev/zero"], 2, "/dev/zero: not a regular file"),
    "decode fifo": ("stim300", ["decode", "{fifo}", "-o", "{out}/t.npz"], 2, "not a regular file"),
    "calibrate directory": ("calibd", ["calibrate", "{dir}", "-o", "{out}/r.json", "--latitude", "60"], 2,
                            "is a directory"),
    # option values out of range
    "replay --speed 1e-300": ("calibd", ["replay", GOOD, "--latitude", "60", "--speed", "1e-300"], 2,
                              "'1e-300' is not 'max' or a factor of real time in [0.001, 1e+06]"),
    "replay --speed nan": ("calibd", ["replay", GOOD, "--latitude", "60", "--speed", "nan"], 2, "'nan' is not"),
    # captures the calibration cannot use
    "calibrate one datagram": ("calibd", CALIBRATE, 2, "too few to infer it"),
    "noise one datagram": ("calibd", ["noise", "{one}"], 2, "too few to infer it"),
    "calibrate one datagram + configuration": ("calibd", [*CALIBRATE[:1], "{one_cfg}", *CALIBRATE[2:]], 2,
                                               "no static segment"),
    "calibrate stuck counter": ("calibd", [*CALIBRATE[:1], "{stuck}", *CALIBRATE[2:]], 2,
                                "does not step (stuck)"),
    "noise stuck counter": ("calibd", ["noise", "{stuck}"], 2, "does not step (stuck)"),
    "calibrate 0.8 s of data": ("calibd", [*CALIBRATE[:1], "{short_cfg}", *CALIBRATE[2:]], 2, "no static segment"),
    "noise start past the end": ("calibd", ["noise", "{short_cfg}", "--start", "5"], 2,
                                 "short_cfg.bin: start 5 s is past the end of power-up 1 of 1"),
    "calibrate external trigger": ("calibd", [*CALIBRATE[:1], "{external}", *CALIBRATE[2:]], 2,
                                   "sample rate unknown: its configuration datagram says the sensor is externally "
                                   "triggered"),
    "noise external trigger": ("calibd", ["noise", "{external}"], 2, "sample rate unknown"),
    "replay not STIM300": ("calibd", ["replay", "{text}", "--latitude", "60"], 1, "no result for the last power-up"),
    # a result.json of the wrong kinds of values
    "report estimate value a string": ("calibd", ["report", "{result_value_text}", GOOD, "-o", "{out}/r.html"], 2,
                                       'estimates.pitch.value is "x", expected a number'),
    "report sigma a list": ("calibd", ["report", "{result_sigma_list}", GOOD, "-o", "{out}/r.html"], 2,
                            "estimates.yaw.sigma is [], expected a number >= 0 or null"),
    "apply estimate value a string": ("calibd", ["apply", "{result_value_text}", GOOD, "-o", "{out}/a.npz"], 2,
                                      'estimates.pitch.value is "x", expected a number'),
    "status --json sigma a list": ("calibd", ["status", "--state-dir", "{state_dir_sigma_list}", "--json"], 2,
                                   "estimates.yaw.sigma is [], expected a number >= 0 or null"),
    "report latitude null": ("calibd", ["report", "{result_latitude_null}", GOOD, "-o", "{out}/r.html"], 2,
                             "site.latitude_deg is null, expected a number"),
    "report power-up a string": ("calibd", ["report", "{result_power_up_text}", GOOD, "-o", "{out}/r.html"], 2,
                                 "stream.power_up is"),
    "report segments a number": ("calibd", ["report", "{result_segments_number}", GOOD, "-o", "{out}/r.html"], 2,
                                 "segments is 1, expected a list"),
    "report segment start null": ("calibd", ["report", "{result_segment_start_null}", GOOD, "-o", "{out}/r.html"],
                                  2, "segments[0].start_s is null, expected a number"),
    # stim300 record
    "record --duration nan": ("stim300", ["record", "/dev/null", "-o", "{out}/c.bin", "--duration", "nan"], 2,
                              "'nan' must be a positive finite number"),
    "record -o /dev/null": ("stim300", ["record", "/dev/null", "-o", "/dev/null"], 2,
                            "/dev/null: not a regular file"),
    "record -o fifo": ("stim300", ["record", "/dev/null", "-o", "{fifo}"], 2, "not a regular file"),
    # a format option the data contradict
    "info --rate 2000 on 125 Hz data": ("stim300", ["info", "{rate125}", "--rate", "2000"], 2,
                                        "--rate 2000 disagrees with the datagram counter, which mostly steps by 16 "
                                        "(125 Hz)"),
    "decode --rate 250 on 125 Hz data": ("stim300", ["decode", "{rate125}", "--rate", "250", "-o", "{out}/t.npz"],
                                         2, "--rate 250 disagrees"),
    # scenarios the simulator cannot make
    "simulate 1e9 deg turn": ("calibd", ["simulate", "{huge}", "-o", "{out}/c.bin"], 2,
                              "more than the simulator's 10,000,000 samples"),
    "simulate bad serial number": ("calibd", ["simulate", "{serial}", "-o", "{out}/c.bin"], 2,
                                   "[sensor] serial_number: serial number must be"),
    "simulate drop every sample": ("calibd", ["simulate", "{drop}", "-o", "{out}/c.bin"], 2,
                                   "[faults] drop: 125 is not fewer than the 125 samples"),
    # outputs: a device or FIFO is written in place, never replaced; a directory is refused
    "calibrate -o /dev/full": ("calibd", ["calibrate", GOOD, "-o", "/dev/full", "--latitude", "60"], 1,
                               "/dev/full: cannot write: no space left on device"),
    "calibrate -o fifo": ("calibd", ["calibrate", GOOD, "-o", "{fifo}", "--latitude", "60"], 1,
                          "a FIFO that no process reads"),
    "calibrate -o directory": ("calibd", ["calibrate", GOOD, "-o", "{dir}", "--latitude", "60"], 2,
                               "cannot write: is a directory"),
    "noise -o /dev/full": ("calibd", ["noise", GOOD, "-o", "/dev/full"], 1, "no space left on device"),
    "decode -o fifo": ("stim300", ["decode", GOOD, "-o", "{fifo_csv}"], 1, "a FIFO that no process reads"),
}


def _results(good: Path, d: Path) -> dict[str, str]:
    """The good result, and copies of it with one field of the wrong kind."""
    places = {"result": str(good)}
    for name, edit in {"value_text": lambda r: r["estimates"]["pitch"].update(value="x"),
                       "sigma_list": lambda r: r["estimates"]["yaw"].update(sigma=[]),
                       "latitude_null": lambda r: r["site"].update(latitude_deg=None),
                       "power_up_text": lambda r: r["stream"].update(power_up="first"),
                       "segments_number": lambda r: r.update(segments=1),
                       "segment_start_null": lambda r: r["segments"][0].update(start_s=None)}.items():
        record = json.loads(good.read_text())
        edit(record)
        (d / f"{name}.json").write_text(json.dumps(record))
        places[f"result_{name}"] = str(d / f"{name}.json")
    state = d / "state_sigma_list"  # a daemon's state directory whose result.json is of the wrong kinds
    state.mkdir()
    (state / "state.json").write_text(json.dumps({"state": "SOLVED", "detail": "solved", "updated": 0.0}))
    (state / "result.json").write_text((d / "sigma_list.json").read_text())
    places["state_dir_sigma_list"] = str(state)
    return places


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    """A real result of GOOD, for the report cases."""
    path = tmp_path_factory.mktemp("result") / "result.json"
    assert calibd_main(["calibrate", str(GOOD), "-o", str(path), "--latitude", "60"]) == 0
    return path


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_one_line_and_leaves_nothing(name, tmp_path, capsys, request):
    program, argv, status, text = CASES[name]
    ins = tmp_path / "in"
    ins.mkdir()
    places = {k: str(v) for k, v in _inputs(ins).items()}
    out = tmp_path / "out"
    out.mkdir()
    places |= {"out": str(out), "capture": places["one"]}
    if any("{result" in str(a) or "{state_dir" in str(a) for a in argv):
        places |= _results(request.getfixturevalue("result_file"), ins)
    kinds = {p: stat.S_IFMT(os.lstat(p).st_mode) for p in ("/dev/null", "/dev/full", places["fifo"])}
    main = calibd_main if program == "calibd" else stim300_main
    code, stdout, err = _run(main, [str(a).format(**places) for a in argv], capsys)
    lines = err.strip().splitlines()
    assert code == status, err
    assert len(lines) == 1, err
    assert text in lines[0] and "Traceback" not in err and "internal error" not in err
    assert list(out.iterdir()) == []  # no partial output, no .part
    assert not [p for p in ins.iterdir() if p.name.endswith(".part") or p.name.startswith(".")]
    assert {p: stat.S_IFMT(os.lstat(p).st_mode) for p in kinds} == kinds  # devices and FIFOs stay what they were


def test_record_killed_by_sigterm_keeps_the_bytes(tmp_path):
    """SIGTERM (kill, systemd) ends a recording as Ctrl-C does: the bytes read so far are in OUT,
    its read log beside it, no .part left; it once left a 0-byte .part."""
    master, slave = os.openpty()
    tty.setraw(slave)
    out = tmp_path / "imu.bin"
    data = bytes(range(256)) * 20
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    recorder = subprocess.Popen([sys.executable, "-m", "stim300.cli", "record", os.ttyname(slave), "-o", str(out)],
                                stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert recorder.stderr.readline().startswith("recorded 0 B")  # the port is open: what follows is read
        os.write(master, data)
        deadline = time.monotonic() + 10
        part = tmp_path / "imu.bin.part"
        while time.monotonic() < deadline and not (part.exists() and recorder.stderr.readline().startswith(
                f"recorded {len(data)} B")):
            pass
        recorder.send_signal(signal.SIGTERM)
        assert recorder.wait(10) == 0
    finally:
        recorder.kill()
        os.close(master)
        os.close(slave)
    assert out.read_bytes() == data
    assert (tmp_path / "imu.bin.reads.npy").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imu.bin", "imu.bin.reads.npy"]


@pytest.mark.parametrize("command", [
    ["calibrate", "{capture}", "-o", "{capture}", "--latitude", "60"],
    ["calibrate", "{capture}", "-o", "{link}", "--latitude", "60"],
    ["noise", "{capture}", "-o", "{capture}"],
    ["report", "{capture}.json", "{capture}", "-o", "{capture}"],
    ["simulate", "{scenario}", "-o", "{scenario}"],
])
def test_an_output_that_is_an_input_is_refused(command, tmp_path, capsys):
    """`-o` naming the command's own input (or a link to it) would replace the capture with what
    was made from it: refused before anything is read, and the input is as it was."""
    capture, scenario, link = tmp_path / "c.bin", tmp_path / "s.toml", tmp_path / "link.bin"
    capture.write_bytes(GOOD.read_bytes()[:200_000])
    (tmp_path / "c.bin.json").write_text("{}")
    scenario.write_bytes(_scenario('[[segments]]\ntype = "static"\nduration_s = 1\n'))
    link.symlink_to(capture)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    argv = [a.format(capture=capture, scenario=scenario, link=link) for a in command]
    code, _, err = _run(calibd_main, argv, capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "writing it would destroy the input" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_decode_onto_its_input_is_refused(tmp_path, capsys):
    capture = tmp_path / "c.csv"
    capture.write_bytes(GOOD.read_bytes()[:100_000])
    code, _, err = _run(stim300_main, ["decode", capture, "-o", capture], capsys)
    assert code == 2 and "writing it would destroy the input" in err
    assert capture.read_bytes() == GOOD.read_bytes()[:100_000]


def test_output_to_dev_stdout_and_through_a_link(tmp_path):
    """`-o /dev/stdout` into a pipe writes the pipe (its /proc link names no file to rename onto);
    an output that is a symbolic link keeps the link and replaces its target."""
    from stim300.atomic import write_atomic

    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    piped = subprocess.run([sys.executable, "-m", "calibd.cli", "noise", str(GOOD), "-o", "/dev/stdout"],
                           capture_output=True, text=True, env=env)
    assert piped.returncode == 0, piped.stderr
    assert json.loads(piped.stdout[:piped.stdout.rindex("}") + 1])["schema"] == "calibd.noise/1"
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old")
    link.symlink_to(target)
    write_atomic(link, b"new")
    assert link.is_symlink() and target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "target.json"]

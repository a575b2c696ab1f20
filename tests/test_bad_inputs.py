"""Every command, on every bad input: exit 2 (input) or 1 (run), one line on stderr naming the
thing, no traceback, no file left behind, no device or FIFO replaced, never a hang on a FIFO or
a read of /dev/zero through a link."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from captures import capture, command_env, exact_samples
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
        "tiny.toml": _scenario('[[segments]]\ntype = "static"\nduration_s = 1\n'),
        "random.bin": np.random.default_rng(5).bytes(100_000),
        "run.toml": f'[serial]\nport = "{d}/no_tty"\n[site]\nlatitude_deg = 60\n[output]\n'
                    f'state_dir = "{d}/run_state"\n'.encode(),
    }
    for name, content in files.items():
        (d / name).write_bytes(content)
    os.mkfifo(d / "fifo")
    os.mkfifo(d / "fifo.csv")
    (d / "dir").mkdir()
    (d / "sim.bin.truth.json").mkdir()  # where `simulate -o sim.bin` would put the truth
    for name, size in (("zeros.bin", 20 << 20), ("huge.json", 17 << 20)):  # sparse: no disk used
        with open(d / name, "wb") as f:
            f.truncate(size)
    links = {"zero_link": "/dev/zero", "fifo_link": d / "fifo", "sock_link": d / "nowhere"}
    for name, target in links.items():
        (d / name).symlink_to(target)
    return ({name.split(".")[0]: d / name for name in files} | {name: d / name for name in links} | {
        "fifo": d / "fifo", "fifo_csv": d / "fifo.csv", "dir": d / "dir", "zeros": d / "zeros.bin",
        "huge_json": d / "huge.json", "sim": d / "sim.bin", "state_new": d / "state"} | _state_dirs(d))


def _state_dirs(d: Path) -> dict[str, Path]:
    """Daemon state directories with a FIFO, a device link, a link, a directory or a huge file
    where state.json or result.json belongs: `calibd status` must refuse each, never hang or
    read /dev/zero."""
    good_state = json.dumps({"state": "SOLVED", "detail": "solved", "updated": 0.0})
    (d / "good_state.json").write_text(good_state)
    dirs = {}
    for name, file in (("state", "state.json"), ("result", "result.json")):
        for kind in ("fifo", "zero", "link", "big", "directory"):
            state_dir = dirs[f"{name}_{kind}"] = d / f"{name}_{kind}"
            state_dir.mkdir()
            if name == "result":
                (state_dir / "state.json").write_text(good_state)
            path = state_dir / file
            if kind == "fifo":
                os.mkfifo(path)
            elif kind == "zero":
                path.symlink_to("/dev/zero")
            elif kind == "link":
                path.symlink_to(d / "good_state.json")
            elif kind == "directory":
                path.mkdir()
            else:
                with open(path, "wb") as f:
                    f.truncate(17 << 20)
    return dirs


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
    "plan noise /dev/zero": ("calibd", ["plan", "--latitude", "60", "--campaign", "thesis", "--noise", "/dev/zero"],
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
                                               "it lacks a level static"),
    "calibrate stuck counter": ("calibd", [*CALIBRATE[:1], "{stuck}", *CALIBRATE[2:]], 2,
                                "does not step (stuck)"),
    "noise stuck counter": ("calibd", ["noise", "{stuck}"], 2, "does not step (stuck)"),
    "calibrate 0.8 s of data": ("calibd", [*CALIBRATE[:1], "{short_cfg}", *CALIBRATE[2:]], 2,
                                "it lacks a level static"),
    "noise start past the end": ("calibd", ["noise", "{short_cfg}", "--start", "5"], 2,
                                 "short_cfg.bin: start 5 s is past the end of power-up 1 of 1"),
    "calibrate external trigger": ("calibd", [*CALIBRATE[:1], "{external}", *CALIBRATE[2:]], 2,
                                   "sample rate unknown: its configuration datagram says the sensor is externally "
                                   "triggered"),
    "noise external trigger": ("calibd", ["noise", "{external}"], 2, "sample rate unknown"),
    "replay not STIM300": ("calibd", ["replay", "{text}", "--latitude", "60"], 2, "no STIM300 datagram found"),
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
    # the daemon's state directory: a FIFO, a device, a link, a directory or a huge file where its
    # files belong is refused at once (it hung, or read /dev/zero until the OOM killer came)
    "status state.json fifo": ("calibd", ["status", "--state-dir", "{state_fifo}"], 2,
                               "state.json: not a calibd state file: cannot read it (not a regular file"),
    "status --json state.json fifo": ("calibd", ["status", "--state-dir", "{state_fifo}", "--json"], 2,
                                      "not a regular file"),
    "status --follow state.json fifo": ("calibd", ["status", "--state-dir", "{state_fifo}", "--follow"], 2,
                                        "not a regular file"),
    "status state.json link to /dev/zero": ("calibd", ["status", "--state-dir", "{state_zero}"], 2,
                                            "state.json: not a calibd state file: cannot read it (a symbolic link"),
    "status --follow --json state.json link to /dev/zero": (
        "calibd", ["status", "--state-dir", "{state_zero}", "--follow", "--json"], 2, "a symbolic link"),
    "status state.json link to a regular file": ("calibd", ["status", "--state-dir", "{state_link}"], 2,
                                                 "a symbolic link (not followed)"),
    "status state.json 17 MiB": ("calibd", ["status", "--state-dir", "{state_big}"], 2,
                                 "cannot read it (17825792 bytes, too large for a state file"),
    "status state.json a directory": ("calibd", ["status", "--state-dir", "{state_directory}"], 2,
                                      "state.json: not a calibd state file: cannot read it (is a directory"),
    "status result.json fifo": ("calibd", ["status", "--state-dir", "{result_fifo}"], 2,
                                "result.json: not a regular file (a device or FIFO), expected a result file"),
    "status --follow result.json fifo": ("calibd", ["status", "--state-dir", "{result_fifo}", "--follow"], 2,
                                         "result.json: not a regular file"),
    "status --json result.json link to /dev/zero": ("calibd", ["status", "--state-dir", "{result_zero}", "--json"],
                                                    2, "result.json: a symbolic link (not followed)"),
    "status result.json link to a regular file": ("calibd", ["status", "--state-dir", "{result_link}"], 2,
                                                  "result.json: a symbolic link"),
    "status result.json 17 MiB": ("calibd", ["status", "--state-dir", "{result_big}"], 2, "too large"),
    "status --state-dir ''": ("calibd", ["status", "--state-dir", ""], 2, "an empty path names no file"),
    # calibd report: the figures directory and the page, whole or not at all
    "report -o /dev/full": ("calibd", ["report", "{result}", GOOD, "-o", "/dev/full"], 1,
                            "/dev/full: cannot write: no space left on device"),
    "report on a full disk": ("calibd", ["report", "{result}", GOOD, "-o", "{out}/r.html"], 1,
                              "r.html: cannot write: no space left on device"),
    "report -o fifo": ("calibd", ["report", "{result}", GOOD, "-o", "{fifo}"], 1, "a FIFO that no process reads"),
    "report figures directory a link": ("calibd", ["report", "{result}", GOOD, "-o", "{in}/dir_link.html"], 2,
                                        "dir_link_files: not a directory (a symbolic link is not followed)"),
    "report result fifo": ("calibd", ["report", "{fifo}", GOOD, "-o", "{out}/r.html"], 2, "not a regular file"),
    "report result link to /dev/zero": ("calibd", ["report", "{zero_link}", GOOD, "-o", "{out}/r.html"], 2,
                                        "zero_link: not a regular file"),
    "report result 17 MiB": ("calibd", ["report", "{huge_json}", GOOD, "-o", "{out}/r.html"], 2,
                             "too large for a result file"),
    "report capture link to a fifo": ("calibd", ["report", "{result}", "{fifo_link}", "-o", "{out}/r.html"], 2,
                                      "fifo_link: not a regular file"),
    # stim300 record: a failed write leaves no OUT.part
    "record on a full disk": ("stim300", ["record", "loop://", "-o", "{out}/c.bin", "--duration", "0.2"], 1,
                              "c.bin: cannot write: no space left on device"),
    "record -o directory": ("stim300", ["record", "loop://", "-o", "{dir}"], 2, "a directory"),
    "record -o ''": ("stim300", ["record", "loop://", "-o", ""], 2, "an empty path names no file"),
    "record -o link to /dev/null": ("stim300", ["record", "loop://", "-o", "{in}/null_link"], 2,
                                    "not a regular file"),
    # calibd simulate: both outputs checked before anything is written
    "simulate truth path a directory": ("calibd", ["simulate", "{tiny}", "-o", "{sim}"], 2,
                                        "sim.bin.truth.json: cannot write: is a directory"),
    "simulate on a full disk": ("calibd", ["simulate", "{tiny}", "-o", "{out}/c.bin"], 1, "no space left on device"),
    "simulate -o /dev/full": ("calibd", ["simulate", "{tiny}", "-o", "/dev/full"], 1, "no space left on device"),
    "simulate -o directory": ("calibd", ["simulate", "{tiny}", "-o", "{dir}"], 2, "is a directory"),
    # calibd replay: no STIM300 data is bad input, found fast; a failed state directory fails the run
    "replay empty": ("calibd", ["replay", "{empty}", "--latitude", "60"], 2, "empty.bin: no STIM300 datagram found"),
    "replay random bytes": ("calibd", ["replay", "{random}", "--latitude", "60"], 2, "no STIM300 datagram found"),
    "replay 20 MB of zeros": ("calibd", ["replay", "{zeros}", "--latitude", "60"], 2, "no STIM300 datagram found"),
    "replay fifo": ("calibd", ["replay", "{fifo}", "--latitude", "60"], 2, "not a regular file"),
    "replay link to /dev/zero": ("calibd", ["replay", "{zero_link}", "--latitude", "60"], 2, "not a regular file"),
    "replay --config fifo": ("calibd", ["replay", GOOD, "--config", "{fifo}"], 2, "not a regular file"),
    "replay --state-dir on a full disk": ("calibd", ["replay", GOOD, "--latitude", "60", "--state-dir", "{state_new}"],
                                          1, "cannot write results"),
    "replay --state-dir ''": ("calibd", ["replay", GOOD, "--latitude", "60", "--state-dir", ""], 2,
                              "an empty path names no file"),
    "replay --socket taken by a link": ("calibd", ["replay", GOOD, "--latitude", "60", "--socket", "{sock_link}"],
                                        1, "the path is taken by something else than a socket"),
    # calibd noise, calibrate, apply, plan; stim300 decode and info
    "noise -o ''": ("calibd", ["noise", GOOD, "-o", ""], 2, "an empty path names no file"),
    "noise --kalibr ''": ("calibd", ["noise", GOOD, "--kalibr", ""], 2, "an empty path names no file"),
    "noise --kalibr /dev/full": ("calibd", ["noise", GOOD, "--kalibr", "/dev/full"], 1, "no space left on device"),
    "noise on a full disk": ("calibd", ["noise", GOOD, "-o", "{out}/n.json"], 1, "no space left on device"),
    "calibrate on a full disk": ("calibd", ["calibrate", GOOD, "-o", "{out}/r.json", "--latitude", "60"], 1,
                                 "r.json: cannot write: no space left on device"),
    "calibrate capture link to a fifo": ("calibd", [*CALIBRATE[:1], "{fifo_link}", *CALIBRATE[2:]], 2,
                                         "not a regular file"),
    "apply result fifo": ("calibd", ["apply", "{fifo}", GOOD, "-o", "{out}/a.npz"], 2, "not a regular file"),
    "apply result 17 MiB": ("calibd", ["apply", "{huge_json}", GOOD, "-o", "{out}/a.npz"], 2, "too large"),
    "apply -o fifo": ("calibd", ["apply", "{result}", GOOD, "-o", "{fifo_csv}"], 1, "a FIFO that no process reads"),
    "apply on a full disk": ("calibd", ["apply", "{result}", GOOD, "-o", "{out}/a.npz"], 1,
                             "no space left on device"),
    "plan --noise fifo": ("calibd", ["plan", "--latitude", "60", "--campaign", "thesis", "--noise", "{fifo}"], 2,
                          "not a regular file"),
    "plan --noise ''": ("calibd", ["plan", "--latitude", "60", "--campaign", "thesis", "--noise", ""], 2,
                        "an empty path names no file"),
    "run --config ''": ("calibd", ["run", "--config", ""], 2, "an empty path names no file"),
    "run without its port": ("calibd", ["run", "--config", "{run}"], 1, "no_tty: no such device"),  # no log line too
    "decode on a full disk": ("stim300", ["decode", GOOD, "-o", "{out}/t.npz"], 1, "no space left on device"),
    "decode capture link to /dev/zero": ("stim300", ["decode", "{zero_link}", "-o", "{out}/t.npz"], 2,
                                         "zero_link: not a regular file"),
    "info fifo": ("stim300", ["info", "{fifo}"], 2, "not a regular file"),
    "info link to a fifo": ("stim300", ["info", "{fifo_link}"], 2, "not a regular file"),
}
FULL_DISK = {name for name in CASES if name.endswith("on a full disk")}
# the cases that calibrate, report or replay the whole capture before the output fails: end-to-end runs
WHOLE_RUNS = {"calibrate -o /dev/full", "calibrate -o fifo", "calibrate -o directory", "calibrate on a full disk",
              "report -o /dev/full", "report -o fifo", "report on a full disk", "replay --state-dir on a full disk"}


@pytest.fixture
def full_disk(monkeypatch):
    """Every file opened for writing through os.fdopen (stim300.atomic, the recorder) is a full
    disk: its descriptor is made /dev/full's, so the file exists and each write fails with ENOSPC
    as on a full device."""
    real = os.fdopen

    def fdopen(fd, mode="r", *args, **kwargs):
        if "w" in mode or "a" in mode:
            full = os.open("/dev/full", os.O_WRONLY)
            os.dup2(full, fd)
            os.close(full)
        return real(fd, mode, *args, **kwargs)

    monkeypatch.setattr(os, "fdopen", fdopen)


def _files(root: Path) -> set[str]:
    """Every path under `root` that is not a directory (links not followed)."""
    return {os.path.join(where, name) for where, dirs, files in os.walk(root) for name in files}


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


@pytest.mark.parametrize("name", [pytest.param(name, marks=pytest.mark.slow) if name in WHOLE_RUNS else name
                                  for name in CASES])
def test_bad_input_is_one_line_and_leaves_nothing(name, tmp_path, run_main, request):
    program, argv, status, text = CASES[name]
    ins = tmp_path / "in"
    ins.mkdir()
    places = {k: str(v) for k, v in _inputs(ins).items()}
    out = tmp_path / "out"
    out.mkdir()
    places |= {"out": str(out), "in": str(ins), "capture": places["one"]}
    if any("{result" in str(a) or "{state_dir" in str(a) for a in argv):
        places |= _results(request.getfixturevalue("result_file"), ins)
    (ins / "dir_link_files").symlink_to(ins / "dir")  # a report's figures directory that is a link
    (ins / "null_link").symlink_to("/dev/null")
    if name in FULL_DISK:
        request.getfixturevalue("full_disk")
    before = _files(tmp_path)
    kinds = {p: stat.S_IFMT(os.lstat(p).st_mode) for p in ("/dev/null", "/dev/full", "/dev/zero", places["fifo"])}
    main = calibd_main if program == "calibd" else stim300_main
    code, stdout, err = run_main(main, [str(a).format(**places) for a in argv])
    lines = err.strip().splitlines()
    assert code == status, err
    assert len(lines) == 1, err
    assert text in lines[0] and "Traceback" not in err and "internal error" not in err
    assert _files(tmp_path) == before  # no partial output, no .part, no half of a pair of outputs
    assert not list(Path("/dev").glob("*_files"))  # no figures directory beside a device
    assert {p: stat.S_IFMT(os.lstat(p).st_mode) for p in kinds} == kinds  # devices and FIFOs stay what they were


@pytest.mark.slow
def test_record_killed_by_sigterm_keeps_the_bytes(tmp_path, pty):
    """SIGTERM (kill, systemd) ends a recording as Ctrl-C does: the bytes read so far are in OUT,
    its read log beside it, no .part left; it once left a 0-byte .part."""
    master, path = pty
    out = tmp_path / "imu.bin"
    data = bytes(range(256)) * 20
    recorder = subprocess.Popen([sys.executable, "-m", "stim300.cli", "record", path, "-o", str(out)],
                                stderr=subprocess.PIPE, text=True, env=command_env())
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
def test_an_output_that_is_an_input_is_refused(command, tmp_path, run_main):
    """`-o` naming the command's own input (or a link to it) would replace the capture with what
    was made from it: refused before anything is read, and the input is as it was."""
    capture, scenario, link = tmp_path / "c.bin", tmp_path / "s.toml", tmp_path / "link.bin"
    capture.write_bytes(GOOD.read_bytes()[:200_000])
    (tmp_path / "c.bin.json").write_text("{}")
    scenario.write_bytes(_scenario('[[segments]]\ntype = "static"\nduration_s = 1\n'))
    link.symlink_to(capture)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    argv = [a.format(capture=capture, scenario=scenario, link=link) for a in command]
    code, _, err = run_main(calibd_main, argv)
    assert code == 2 and len(err.splitlines()) == 1 and "writing it would destroy the input" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_decode_onto_its_input_is_refused(tmp_path, run_main):
    capture = tmp_path / "c.csv"
    capture.write_bytes(GOOD.read_bytes()[:100_000])
    code, _, err = run_main(stim300_main, ["decode", capture, "-o", capture])
    assert code == 2 and "writing it would destroy the input" in err
    assert capture.read_bytes() == GOOD.read_bytes()[:100_000]


def test_output_to_dev_stdout_and_through_a_link(tmp_path):
    """`-o /dev/stdout` into a pipe writes the pipe (its /proc link names no file to rename onto);
    an output that is a symbolic link keeps the link and replaces its target."""
    from stim300.atomic import write_atomic

    piped = subprocess.run([sys.executable, "-m", "calibd.cli", "noise", str(GOOD), "-o", "/dev/stdout"],
                           capture_output=True, text=True, env=command_env())
    assert piped.returncode == 0, piped.stderr
    assert json.loads(piped.stdout[:piped.stdout.rindex("}") + 1])["schema"] == "calibd.noise/1"
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old")
    link.symlink_to(target)
    write_atomic(link, b"new")
    assert link.is_symlink() and target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "target.json"]


def test_a_file_the_program_owns_is_never_written_through_a_link(tmp_path):
    """`follow=False` (a state directory's files): a link at the name is replaced by the file, and
    what it pointed at, a device included, is untouched; a device itself is still written in place."""
    from stim300.atomic import write_atomic

    target, link, device_link = tmp_path / "target.json", tmp_path / "state.json", tmp_path / "result.json"
    target.write_text("old")
    link.symlink_to(target)
    device_link.symlink_to("/dev/full")
    write_atomic(link, b"new", follow=False)
    write_atomic(device_link, b"new", follow=False)  # through the link this would fail: ENOSPC
    assert not link.is_symlink() and link.read_text() == "new" and target.read_text() == "old"
    assert not device_link.is_symlink() and device_link.read_text() == "new"
    assert stat.S_ISCHR(os.lstat("/dev/full").st_mode)
    write_atomic("/dev/null", b"x", follow=False)
    assert stat.S_ISCHR(os.lstat("/dev/null").st_mode)


def test_record_never_writes_through_a_left_part_file(tmp_path):
    """OUT.part is the recorder's own: a link of that name (or a file a killed recording left) is
    removed, never written through."""
    elsewhere, out = tmp_path / "elsewhere.bin", tmp_path / "c.bin"
    elsewhere.write_bytes(b"keep")
    (tmp_path / "c.bin.part").symlink_to(elsewhere)
    assert stim300_main(["record", "loop://", "-o", str(out), "--duration", "0.1"]) == 0
    assert elsewhere.read_bytes() == b"keep" and out.read_bytes() == b""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.bin", "c.bin.reads.npy", "elsewhere.bin"]

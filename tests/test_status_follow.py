"""`calibd status --follow`: the status, then again at every change of state.json or result.json
(JSON Lines with --json), a state directory that goes away said once and waited for, and Ctrl-C
or a reader that went away ending it quietly."""

import json
import os
import select
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from calibd.daemon import State
from calibd.frames import Site
from calibd.results import CalibrationResult, Estimate, ResultStream, SessionRecord, site_record
from calibd.statedir import ResultStore
from captures import calibd, command_env

ENV = command_env()


def result(yaw_deg: float) -> CalibrationResult:
    estimates = {"yaw": Estimate(yaw_deg, 1.75, "deg"), "pitch": Estimate(-0.321412, 0.00123, "deg")}
    return CalibrationResult("joint", site_record(Site(60.0)), estimates, stream=ResultStream(capture="x"),
                             session=SessionRecord(1, 600.0, "now"))


class Child:
    """`calibd status --follow` as a subprocess, its output read a line at a time with a timeout."""

    def __init__(self, state_dir: Path, *options: str):
        self.process = calibd("status", "--state-dir", state_dir, "--follow", *options)
        self.pending = {self.process.stdout: b"", self.process.stderr: b""}

    def line(self, stream=None, timeout_s: float = 20.0) -> str:
        """The next line the child writes on stdout (or `stream`); fails rather than hangs."""
        stream = self.process.stdout if stream is None else stream
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self.pending[stream]:
            ready, _, _ = select.select([stream], [], [], max(deadline - time.monotonic(), 0))
            assert ready, f"no line within {timeout_s} s"
            chunk = os.read(stream.fileno(), 65536)
            assert chunk, "the child ended"
            self.pending[stream] += chunk
        line, self.pending[stream] = self.pending[stream].split(b"\n", 1)
        return line.decode() + "\n"

    def interrupt(self) -> tuple[int, str]:
        """Ctrl-C: its exit status and whatever else it said on stderr."""
        self.process.send_signal(signal.SIGINT)
        _, err = self.process.communicate(timeout=20)
        return self.process.returncode, (self.pending[self.process.stderr] + err).decode()


def test_json_lines_at_each_change_then_ctrl_c_ends_quietly(tmp_path):
    store = ResultStore(tmp_path)
    store.on_state(State.COLLECTING, "collecting: 300 s of data")
    child = Child(tmp_path, "--json")
    try:
        first = json.loads(child.line())
        assert first == {"state": json.loads((tmp_path / "state.json").read_text()), "result": None}
        store.on_result(result(-3.3303))
        store.on_state(State.SOLVED, "solved on 662 s: yaw -3.3 +- 1.8 deg")
        documents = [json.loads(child.line())]
        while documents[-1]["state"]["state"] != "SOLVED":  # the result and the state may come as one change or two
            documents.append(json.loads(child.line()))
        assert documents[-1]["result"]["estimates"]["yaw"]["value"] == -3.3303
        assert documents[-1]["state"]["detail"].startswith("solved on 662 s")
    finally:
        code, err = child.interrupt()
    assert code == 0 and err == ""


@pytest.mark.slow
def test_text_blocks_a_vanished_state_dir_said_once_and_waited_for(tmp_path):
    state_dir = tmp_path / "state"
    store = ResultStore(state_dir)
    store.on_state(State.WARMING_UP, "waiting for the temperature to settle")
    child = Child(state_dir)
    try:
        assert child.line().startswith("state: WARMING_UP (waiting for the temperature to settle)")
        assert child.line() == "no result yet\n"
        shutil.rmtree(state_dir)
        said = child.line(child.process.stderr)
        assert said == (f"calibd: {state_dir}: no state.json (is calibd running with this state directory?); "
                        "waiting for it to change\n")
        time.sleep(1.2)  # two looks more at the missing directory: said once only
        store = ResultStore(state_dir)
        store.on_result(result(-3.3303))
        store.on_state(State.SOLVED, "solved on 662 s")
        lines = [child.line() for _ in range(2)]
        while not any(line.startswith("  yaw") for line in lines):
            lines.append(child.line())
        assert "\n" in lines and any(line.startswith("state: SOLVED (solved on 662 s)") for line in lines)
        assert [line.split() for line in lines if line.startswith("  yaw")] == [["yaw", "-3.3", "+-", "1.8", "deg"]]
    finally:
        code, err = child.interrupt()
    assert code == 0 and err == ""  # nothing more on stderr: the vanished directory was said once


def test_a_reader_that_goes_away_ends_it_quietly(tmp_path):
    """`| head -n 1`: the next change finds stdout closed, and the follower ends without a word."""
    store = ResultStore(tmp_path)
    store.on_state(State.COLLECTING, "collecting")
    command = f"{sys.executable} -m calibd status --state-dir {tmp_path} --follow --json | head -n 1"
    pipeline = subprocess.Popen(["bash", "-c", command + '; exit "${PIPESTATUS[0]}"'], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, env=ENV)  # calibd's exit status, not head's
    first = pipeline.stdout.readline()
    assert json.loads(first)["state"]["state"] == "COLLECTING"
    time.sleep(0.2)  # head has gone
    store.on_state(State.SOLVED, "solved")
    out, err = pipeline.communicate(timeout=20)
    assert pipeline.returncode == 0 and out == b"" and err == b""


def test_the_first_look_still_refuses_a_directory_without_state(tmp_path):
    done = subprocess.run([sys.executable, "-m", "calibd", "status", "--state-dir", str(tmp_path), "--follow"],
                          capture_output=True, text=True, env=ENV, timeout=30)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == f"calibd: {tmp_path}: no state.json (is calibd running with this state directory?)\n"


def test_a_reader_that_goes_away_ends_it_on_an_unchanging_directory(tmp_path):
    """`| head -n 1` with nothing new to print: the follower sees its reader gone while it waits
    (it once waited forever, writing nothing that could fail)."""
    store = ResultStore(tmp_path)
    store.on_state(State.COLLECTING, "collecting")
    command = f"{sys.executable} -m calibd status --state-dir {tmp_path} --follow --json | head -n 1"
    started = time.monotonic()
    done = subprocess.run(["bash", "-c", command + '; exit "${PIPESTATUS[0]}"'], capture_output=True, env=ENV,
                          timeout=20)
    assert done.returncode == 0 and done.stderr == b""
    assert json.loads(done.stdout)["state"]["state"] == "COLLECTING"
    assert time.monotonic() - started < 10


def test_special_files_in_the_state_directory_are_refused_at_once(tmp_path):
    """A FIFO as state.json hung `status --follow`; a link to /dev/zero read it until memory ran out."""
    os.mkfifo(tmp_path / "state.json")
    done = subprocess.run([sys.executable, "-m", "calibd", "status", "--state-dir", str(tmp_path), "--follow"],
                          capture_output=True, text=True, env=ENV, timeout=30)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == (f"calibd: {tmp_path / 'state.json'}: not a calibd state file: cannot read it (not a "
                           "regular file (a device or FIFO), expected a state file)\n")
    (tmp_path / "state.json").unlink()
    (tmp_path / "state.json").symlink_to("/dev/zero")
    done = subprocess.run([sys.executable, "-m", "calibd", "status", "--state-dir", str(tmp_path)],
                          capture_output=True, text=True, env=ENV, timeout=30)
    assert done.returncode == 2
    assert done.stderr.endswith("state.json: not a calibd state file: cannot read it (a symbolic link (not "
                                "followed), expected a state file)\n")

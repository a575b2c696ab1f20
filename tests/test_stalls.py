"""A stalled daemon is no loss: `calibd replay --pty` (the daemon's own port reader, fed in real
time) stopped with SIGSTOP for 0.3 to 2 s at random reads the bytes late, in bursts, and must
find no hidden gap and give the result of a run that was never stopped."""

import json
import random
import signal
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import pytest

from calibd.scenario import Segment, load_scenario
from calibd.sim import capture_bytes, simulate
from captures import calibd

SITE = ["--latitude", "40.59129", "--g0", "9.79956", "--warmup-window", "2"]
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """44 s at 2000 Hz (120 kB/s, so a 2 s stall leaves 240 kB to read late): statics and two
    90 deg turns, the joint method's campaign."""
    base = load_scenario("thesis-real")
    turn = Segment("turn", angle_deg=90, peak_rate_deg_s=20, accel_deg_s2=20)
    segments = (Segment("static", duration_s=12), turn, Segment("static", duration_s=10), turn,
                Segment("static", duration_s=10))
    scenario = replace(base, sensor=replace(base.sensor, sample_rate_hz=2000), segments=segments)
    path = tmp_path_factory.mktemp("stalls") / "capture.bin"
    path.write_bytes(capture_bytes(simulate(scenario))[0])
    return path


def replay(capture: Path, state_dir: Path, *args: str, stalls: random.Random | None = None) -> tuple[dict, str, list]:
    """result.json, stderr and the stalls (s) of a replay; with `stalls`, SIGSTOP it for 0.3 to 2 s
    every 1.5 to 4 s from 3 s after its start to its end."""
    daemon = calibd("replay", capture, *SITE, "--state-dir", state_dir, *args, stdout=subprocess.DEVNULL)
    stopped = []
    try:
        if stalls is not None:
            time.sleep(3.0)
            while daemon.poll() is None:
                time.sleep(stalls.uniform(1.5, 4.0))
                seconds = stalls.uniform(0.3, 2.0)
                daemon.send_signal(signal.SIGSTOP)
                time.sleep(seconds)
                daemon.send_signal(signal.SIGCONT)
                stopped.append(seconds)
        stderr = daemon.communicate(timeout=120)[1].decode()
    finally:
        if daemon.poll() is None:
            daemon.send_signal(signal.SIGCONT)
            daemon.kill()
    assert daemon.returncode == 0, stderr[-2000:]
    return json.loads((state_dir / "result.json").read_text()), stderr, stopped


def test_host_stalls_find_no_hidden_gap_and_leave_the_result_as_it_was(capture, tmp_path):
    stalled, stderr, stopped = replay(capture, tmp_path / "stalled", "--pty", "--speed", "1",
                                      stalls=random.Random(3))
    unstalled, _, _ = replay(capture, tmp_path / "counter")  # as fast as possible: the counter's times alone
    assert len(stopped) >= 6
    assert "hidden_gap" not in stderr
    assert stalled["stream"]["hidden_gaps"] == 0  # looked for (the host clock was evidence), none found
    for name, estimate in unstalled["estimates"].items():
        if estimate.get("sigma"):
            assert abs(stalled["estimates"][name]["value"] - estimate["value"]) <= 0.2 * estimate["sigma"], name

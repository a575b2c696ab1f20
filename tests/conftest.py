"""What every test starts from, and the fixtures several test files share."""

import os
import signal
import tty

import pytest
import structlog


def pytest_configure(config):
    """Ctrl-C heard again: a run started in the background by a non-interactive shell (`pytest &`
    in a script) ignores SIGINT and SIGQUIT, and so would every program the tests start, which
    then never sees the Ctrl-C the tests send it (Python keeps an ignored SIGINT ignored)."""
    for number in (signal.SIGINT, signal.SIGQUIT):
        if signal.getsignal(number) == signal.SIG_IGN:
            signal.signal(number, signal.default_int_handler if number == signal.SIGINT else signal.SIG_DFL)


@pytest.fixture(autouse=True)
def default_logging():
    """structlog's defaults again after each test: a command run in-process configures logging
    for the whole process (a level filter included), which would hide the info events that
    `capture_logs` looks for in the tests after it."""
    yield
    structlog.reset_defaults()


@pytest.fixture
def run_main(capsys):
    """Runs a command line in-process: `run_main(main, argv)` gives its exit status, stdout and
    stderr."""
    def run(main, argv):
        code = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return code, out, err
    return run


@pytest.fixture
def pty():
    """A raw pseudo-terminal pair, closed after the test: (the master fd, where the test plays the
    sensor; the path the code under test opens)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


@pytest.fixture(scope="session")
def fleet_batch(tmp_path_factory):
    """The simulated fleet (tests/fleet_captures.py: 24 captures of three units) and the fleet
    table `calibd batch` makes of it on a local cluster of two workers, run as users run it:
    (folder, captures, table, the command's stdout and stderr)."""
    import subprocess
    import sys

    from captures import ROOT, command_env
    from fleet_captures import G0, LATITUDE, simulate_fleet

    directory = tmp_path_factory.mktemp("fleet")
    captures = simulate_fleet(directory)
    table = tmp_path_factory.mktemp("fleet-table") / "fleet.parquet"
    done = subprocess.run([sys.executable, "-m", "calibd.cli", "batch", str(directory), "-o", str(table),
                           "--workers", "2", "--latitude", LATITUDE, "--g0", G0], cwd=ROOT, env=command_env(),
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return directory, captures, table, done.stdout, done.stderr


@pytest.fixture(scope="session")
def fixture_samples():
    """The recordings' capture's samples in SI with header stamps at 125 Hz, and the recorder's
    jittered times (tests/recording_files.py)."""
    import math

    import numpy as np

    from recording_files import CAPTURE, EPOCH_NS
    from stim300.bulk import decode_capture

    samples = decode_capture(CAPTURE.read_bytes()).samples
    stamps = EPOCH_NS + np.arange(len(samples), dtype=np.int64) * 8_000_000
    received = stamps + np.random.default_rng(5).integers(200_000, 3_000_000, len(samples))  # 0.2-3 ms late
    return stamps, samples["gyro"] * (math.pi / 180), samples["acc"] * 9.80665, received


@pytest.fixture(scope="session")
def recordings(tmp_path_factory, fixture_samples):
    """The capture's samples as a recording of each format: kind -> path."""
    from recording_files import FORMATS, recording_name, serialised, write_recording

    tmp = tmp_path_factory.mktemp("recordings")
    stamps, gyro, acc, received = fixture_samples
    ros1, cdr = serialised("bag", stamps, gyro, acc), serialised("cdr", stamps, gyro, acc)
    return {kind: write_recording(recording_name(tmp, kind), kind, ros1 if kind in ("bag", "ros1_mcap") else cdr,
                                  received) for kind in FORMATS}


@pytest.fixture(scope="session")
def site():
    """The site of the recordings' capture (its truth file's)."""
    import json

    from recording_files import FIXTURES

    return json.loads((FIXTURES / "gyro_acc_125hz.bin.truth.json").read_text())["site"]


@pytest.fixture(scope="session")
def raw_result(tmp_path_factory, site):
    """`calibd calibrate` of the recordings' capture itself."""
    from recording_files import CAPTURE, calibrate

    return calibrate(CAPTURE, site, tmp_path_factory.mktemp("raw") / "result.json")

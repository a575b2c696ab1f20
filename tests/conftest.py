"""What every test starts from, and the fixtures several test files share."""

import os
import tty

import pytest
import structlog


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

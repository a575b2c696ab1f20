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

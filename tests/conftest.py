"""What every test starts from."""

import pytest
import structlog


@pytest.fixture(autouse=True)
def default_logging():
    """structlog's defaults again after each test: a command run in-process configures logging
    for the whole process (a level filter included), which would hide the info events that
    `capture_logs` looks for in the tests after it."""
    yield
    structlog.reset_defaults()

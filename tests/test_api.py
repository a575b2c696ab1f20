"""The stim300 package's seams: one error root, and the public names of `import stim300`."""

import inspect
import subprocess
import sys
from pathlib import Path

import pytest

import stim300.errors as errors
from captures import command_env
from stim300.errors import FormatError, PortError, ServiceError, ServiceTimeout, Stim300Error, UsageError
from stim300.port import open_serial
from stim300.protocol import Format
from stim300.special import SerialNumber, decode_special

ROOT = Path(__file__).resolve().parents[1]


def test_every_public_error_class_is_a_stim300_error():
    classes = [c for name, c in inspect.getmembers(errors, inspect.isclass)
               if c.__module__ == errors.__name__ and not name.startswith("_")]
    assert {c.__name__ for c in classes} >= {"FormatError", "PortError", "ServiceError", "ServiceTimeout",
                                             "UsageError"}
    assert all(issubclass(c, Stim300Error) for c in classes)


def test_errors_keep_the_builtin_a_caller_caught_before():
    assert issubclass(PortError, OSError)
    assert issubclass(FormatError, ValueError)
    assert issubclass(ServiceTimeout, TimeoutError) and issubclass(ServiceTimeout, ServiceError)
    assert not issubclass(UsageError, (OSError, ValueError))


def test_the_driver_raises_its_own_errors_for_bad_input(tmp_path):
    with pytest.raises(FormatError, match="sample rate 7 Hz"):
        Format(sample_rate_hz=7)
    with pytest.raises(FormatError, match="not a special datagram id"):
        decode_special(b"\x93" + bytes(30))
    with pytest.raises(FormatError, match="serial number"):
        SerialNumber("X1").to_payload()
    with pytest.raises(PortError, match="no such device"):
        open_serial(str(tmp_path / "ttyNONE"))


def test_every_public_name_resolves():
    import stim300
    assert len(stim300.__all__) == len(set(stim300.__all__))
    missing = [name for name in stim300.__all__ if getattr(stim300, name, None) is None]
    assert not missing
    assert {"decode_capture", "Capture", "StreamInfo", "StreamParser", "PortReader", "Stim300Error",
            "service_command", "CounterClock", "SAMPLE_DTYPE"} <= set(stim300.__all__)


def test_import_stim300_loads_neither_calibd_nor_scipy():
    code = ("import sys, stim300; from stim300 import *; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'calibd', 'scipy', 'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=command_env(), cwd=ROOT).stdout
    assert out.strip() == "[]"

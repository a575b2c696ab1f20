"""calibd's public names: `import calibd` gives what a library user needs, without matplotlib."""

import subprocess
import sys
from pathlib import Path

import pytest

import calibd
from captures import command_env

ROOT = Path(__file__).resolve().parents[1]


def test_every_public_name_resolves_and_is_listed_once():
    assert len(calibd.__all__) == len(set(calibd.__all__))
    for name in calibd.__all__:
        assert getattr(calibd, name) is not None, name
    assert {"calibrate_capture", "power_up_session", "Session", "estimator", "CalibrationResult", "Estimate",
            "load_result", "Site", "CalibdError"} <= set(calibd.__all__)


def test_the_public_errors_share_calibds_root():
    names = [name for name in calibd.__all__ if name.endswith("Error") or name == "CampaignIncomplete"]
    errors = [getattr(calibd, name) for name in names]
    assert len(errors) >= 8
    assert all(issubclass(e, calibd.CalibdError) for e in errors)


@pytest.mark.slow
def test_the_library_calibrates_a_capture_through_its_public_names():
    path = ROOT / "fixtures" / "thesis_real_cw_125hz.bin"
    capture = calibd.decode_sessions(path.read_bytes(), path.name)
    site = calibd.Site(40.59129, g0=9.79956)
    method = calibd.estimator("joint")
    result = calibd.calibrate_capture(capture, lambda s: method.solve(s, site, None, method.options({})), None, 0.0)
    assert isinstance(result, calibd.CalibrationResult) and result.method == "joint"
    assert isinstance(result.estimates["yaw"], calibd.Estimate) and result.estimates["yaw"].unit == "deg"


@pytest.mark.parametrize("module", ["calibd", "calibd.frames", "calibd.session", "calibd.estimators.joint"])
def test_import_calibd_loads_no_matplotlib(module):
    code = f"import sys, {module}; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=command_env(), cwd=ROOT).stdout
    assert out.strip() == "False"

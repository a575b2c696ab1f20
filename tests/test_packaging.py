"""A non-editable install must carry every package: pyproject lists them explicitly."""

import subprocess
import sys
import tomllib
from importlib.metadata import version
from pathlib import Path

from captures import command_env

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for top in ("stim300", "calibd")
             for p in (ROOT / top).rglob("__init__.py")}
    assert listed == found


def test_both_commands_say_their_version():
    expected = version("stim300-calib")
    for command in ("stim300", "calibd"):
        for module in (command, f"{command}.cli"):  # `python -m calibd` as well as the module itself
            done = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True,
                                  env=command_env(), cwd=ROOT, timeout=60)
            assert (done.returncode, done.stdout, done.stderr) == (0, f"{command} {expected}\n", "")

"""A non-editable install must carry every package: pyproject lists them explicitly."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for top in ("stim300", "calibd")
             for p in (ROOT / top).rglob("__init__.py")}
    assert listed == found

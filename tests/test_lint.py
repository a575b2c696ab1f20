"""The code passes the project's lint (pyproject.toml [tool.ruff]): unused imports and names,
undefined names, syntax and style errors fail the suite, so they never land."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


STANDALONE_PATHS = ("README.md", "docs", "calibd", "stim300", "benchmarks")


def test_project_files_do_not_point_outside_the_repository():
    """A clone has no shared/ folder beside it: docs and code must say things in their own words."""
    tracked = subprocess.run(["git", "ls-files", "-z", *STANDALONE_PATHS], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.split("\0")
    files = [ROOT / name for name in tracked if name]
    assert len(files) > 20
    offenders = [str(f.relative_to(ROOT)) for f in files
                 if "shared/" in f.read_text(encoding="utf-8", errors="ignore")]
    assert offenders == []

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


def test_project_files_do_not_point_outside_the_repository():
    """A clone has no shared/ folder beside it: docs, code, tests and their data must say things in
    their own words. Every tracked text file is read (this one, which names the folder, aside)."""
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split("\0")
    files = [ROOT / name for name in tracked if name and ROOT / name != Path(__file__).resolve()]
    texts = {f: f.read_bytes() for f in files if f.is_file()}
    texts = {f: data for f, data in texts.items() if b"\0" not in data[:8192]}  # binary captures aside
    assert len(texts) > 50 and ROOT / "tests" / "vectors" / "README.md" in texts
    offenders = [str(f.relative_to(ROOT)) for f, data in texts.items() if b"shared/" in data]
    assert offenders == []

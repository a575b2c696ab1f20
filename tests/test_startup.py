"""calibd starts without scipy: `import calibd`, `import calibd.cli`, `calibd --version` and
`calibd status` load none of it; each command imports what it needs itself, and a method's
module is imported when the method is asked for. `stim300 --version` loads no decoder, port
reader or logging (the speed: benchmarks/startup.py). Each check runs in a fresh interpreter,
where nothing is loaded yet."""

import json
import os
import subprocess
import sys
from pathlib import Path

from calibd.daemon import State
from calibd.statedir import ResultStore

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))
SCIPY_LOADED = "[m for m in sys.modules if m.split('.')[0] == 'scipy']"


def scipy_after(code: str) -> tuple[list[str], str]:
    """The scipy modules a fresh interpreter holds after running `code`, and what `code` printed."""
    program = f"import sys\n{code}\nprint(__import__('json').dumps({SCIPY_LOADED}))"
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, env=ENV, cwd=ROOT,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    *printed, loaded = done.stdout.splitlines()
    return json.loads(loaded), "\n".join(printed)


def calibd_main(argv: list[str]) -> str:
    """`calibd ARGV` in the interpreter, its exit status (argparse's --version exits) printed."""
    return (f"import calibd.cli\ntry:\n    code = calibd.cli.main({argv!r})\nexcept SystemExit as exc:\n"
            f"    code = exc.code\nprint('exit', code)")


def test_the_check_sees_scipy_when_it_is_loaded():
    loaded, _ = scipy_after("import scipy.optimize")
    assert "scipy.optimize" in loaded


def test_import_calibd_and_its_cli_load_no_scipy():
    assert scipy_after("import calibd") == ([], "")
    assert scipy_after("import calibd.cli") == ([], "")


def test_calibd_names_are_imported_when_first_used():
    _, printed = scipy_after("import calibd\nprint(sorted(m for m in sys.modules if m.startswith('calibd.')))\n"
                             "from calibd import Site\nprint(Site is sys.modules['calibd.frames'].Site)")
    assert printed == "[]\nTrue"


def test_version_loads_no_scipy():
    loaded, printed = scipy_after(calibd_main(["--version"]))
    assert printed.startswith("calibd ") and printed.endswith("\nexit 0")
    assert loaded == []


def test_status_loads_no_scipy(tmp_path):
    store = ResultStore(tmp_path)
    store.on_state(State.COLLECTING, "collecting: 300 s of data")
    loaded, printed = scipy_after(calibd_main(["status", "--state-dir", str(tmp_path)]))
    assert printed.splitlines()[0].startswith("state: COLLECTING (collecting: 300 s of data)")
    assert printed.endswith("no result yet\nexit 0")
    assert loaded == []


def test_status_help_works():
    done = subprocess.run([sys.executable, "-m", "calibd", "status", "--help"], capture_output=True, text=True,
                          env=ENV, cwd=ROOT, timeout=60)
    assert done.returncode == 0 and done.stderr == ""
    assert done.stdout.startswith("usage: calibd status") and "--state-dir" in done.stdout


def test_stim300_version_and_its_parser_load_no_decoder_reader_or_logging():
    heavy = ("stim300.stream", "stim300.bulk", "stim300.port", "stim300.csvtable", "structlog")
    program = (f"import sys, stim300.cli\ntry:\n    stim300.cli.main(['--version'])\nexcept SystemExit:\n    pass\n"
               f"print(sorted(m for m in sys.modules if m in {heavy!r}))")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, env=ENV, cwd=ROOT,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    version, loaded = done.stdout.splitlines()
    assert version.startswith("stim300 ") and loaded == "[]"

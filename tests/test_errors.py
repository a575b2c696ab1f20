"""One error root for calibd, one line from the CLI for each error, and no import cycle."""

import ast
import importlib
import json
import inspect
import pkgutil
from pathlib import Path

import pytest

import calibd
from captures import capture
from calibd.cli import main as calibd_main
from calibd.errors import CalibdError
from calibd.results import SCHEMA as RESULT_SCHEMA
from stim300.protocol import GyroUnit
from stim300.special import Configuration, encode_special

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("calibd", "stim300")
CAPTURE = str(ROOT / "fixtures" / "thesis_real_cw_125hz.bin")


def _modules() -> list[str]:
    return [name for _, name, _ in pkgutil.walk_packages(calibd.__path__, "calibd.")]


def test_every_calibd_error_is_a_calibd_error_and_none_is_a_value_error():
    errors = set()
    for name in _modules():
        module = importlib.import_module(name)
        errors |= {cls for _, cls in inspect.getmembers(module, inspect.isclass)
                   if issubclass(cls, Exception) and cls.__module__.startswith("calibd.")}
    names = {cls.__name__ for cls in errors}
    assert {"CalibrationError", "CampaignIncomplete", "ConfigError", "ResultError", "ScenarioError", "NoiseError",
            "PlanError", "ReportError", "Underdetermined"} <= names
    for cls in errors:
        assert issubclass(cls, CalibdError), cls
        assert not issubclass(cls, ValueError), cls


@pytest.mark.parametrize("error, argv, says", [
    ("CalibrationError", ["calibrate", "{garbage}", "--latitude", "40", "-o", "{tmp}/r.json"], "no STIM300 datagram"),
    ("ConfigError", ["replay", "{garbage}", "--config", "{tmp}/missing.toml"], "no such configuration file"),
    ("ScenarioError", ["simulate", "{tmp}/missing.toml", "-o", "{tmp}/s.bin"], "no such scenario file"),
    ("ResultError", ["report", "{garbage}", CAPTURE, "-o", "{tmp}/report.html"], "not JSON"),
    ("PlanError", ["plan", "--campaign", "thesis", "--noise", "{garbage}", "--latitude", "40"], "not a JSON noise"),
    ("ReportError", ["report", "{empty_result}", CAPTURE, "-o", "{tmp}/report.html"], "has no estimates"),
])
def test_each_error_is_one_line_from_the_cli(error, argv, says, tmp_path, capsys):
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(b"not a capture, not JSON\n" * 10)
    empty_result = tmp_path / "empty.json"
    empty_result.write_text(json.dumps({"schema": RESULT_SCHEMA, "site": {"latitude_deg": 40.0}}))
    code = calibd_main([a.format(garbage=garbage, tmp=tmp_path, empty_result=empty_result) for a in argv])
    _, err = capsys.readouterr()
    assert code == 2 and says in err, (error, err)
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err


def _imports(path: Path, module: str, modules) -> set[str]:
    """The project modules `module` (at `path`) imports at any depth of its body, lazy ones included.
    `from package import submodule` needs the submodule, not the package's other names: Python
    binds it even while the package's __init__ is still running, so it is no edge to the package."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            submodules = {f"{base}.{alias.name}" for alias in node.names}
            found |= submodules if submodules <= set(modules) else {base} | submodules
    return found


def _graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (under TYPE_CHECKING too: a circle there is one still)."""
    modules = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return {name: {m for m in _imports(path, name, modules) if m in modules and m != name}
            for name, path in modules.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of `graph` (depth-first search), or None."""
    state: dict[str, str] = {}

    def visit(node, path):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt, path + [nxt])):
                return found
        state[node] = "done"
        return None

    return next((found for node in sorted(graph) if node not in state and (found := visit(node, [node]))), None)


def test_project_imports_have_no_cycle():
    graph = _graph()
    assert "calibd.allan" in graph["calibd.estimators.joint"]  # the walk sees the imports it should
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_the_cycle_check_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycle(graph) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


@pytest.mark.parametrize("datagram_id, units, says", [
    (0x90, {}, "carries gyros only: calibration needs accelerometers too"),
    (0xA7, {"gyro_unit": GyroUnit.INCREMENTAL_ANGLE}, "calibration needs rate and acceleration outputs"),
])
def test_a_capture_calibd_cannot_use_is_one_line(datagram_id, units, says, tmp_path, capsys):
    """Refused while the mapped capture is being decoded: the decoder lets go of the file first."""
    data, _, fmt = capture(300, datagram_id, False, rate=125, **units)
    config = encode_special(Configuration.build(sample_rate_hz=125, **units), False) if units else b""
    path = tmp_path / "c.bin"
    path.write_bytes(config + data)
    code = calibd_main(["calibrate", str(path), "--latitude", "40", "-o", str(tmp_path / "r.json")])
    _, err = capsys.readouterr()
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err


BYTE_READERS = {"read_bytes", "mmap", "load_reads", "decode_capture", "decode_columns", "BulkDecoder"}


def _reads_bytes(tree: ast.AST) -> list[str]:
    """The ways a module gets at a file's bytes: the names above, or open(..., "rb"...)."""
    found = []
    for node in ast.walk(tree):
        name = node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else None
        if name in BYTE_READERS:
            found.append(f"{name} (line {node.lineno})")
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "open":
            modes = [a.value for a in node.args[1:2] + [k.value for k in node.keywords if k.arg == "mode"]
                     if isinstance(a, ast.Constant)]
            if any("b" in str(m) for m in modes):
                found.append(f"open(..., {modes[0]!r}) (line {node.lineno})")
    return found


def test_only_calibd_captures_opens_capture_files():
    """Calibration code takes decoded captures, sessions and batches; only calibd/captures.py reads a
    capture's bytes (the check can fail: it finds captures.py's own)."""
    sources = {p.relative_to(ROOT).as_posix(): ast.parse(p.read_text()) for p in (ROOT / "calibd").rglob("*.py")}
    assert _reads_bytes(sources.pop("calibd/captures.py"))
    assert {path: found for path, tree in sources.items() if (found := _reads_bytes(tree))} == {}

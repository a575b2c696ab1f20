"""systemd/: the example config has the loader's keys; the unit passes `systemd-analyze verify`
and `systemd-analyze security --offline=yes` rates it at most 2.0 (skipped without systemd-analyze)."""

import os
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parent.parent / "systemd"
UNIT = SYSTEMD / "calibd@.service"
EXAMPLE = SYSTEMD / "calibd.example.toml"
RULES = SYSTEMD / "99-stim300.rules"
DEVICE = "ttyUSB0"
MAX_EXPOSURE = 2.0

ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze not on PATH")

# What `systemd-analyze verify` says about a unit file that systemd would partly ignore.
SYNTAX_ERRORS = re.compile(r"Unknown key|Unknown section|Unknown lvalue|Failed to parse|Invalid|"
                           r"Missing '='|Assignment outside of section|is not executable|Ignoring",
                           re.IGNORECASE)


def directives(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) for every assignment of a unit file, in order."""
    section, out = "", []
    for line in text.splitlines():
        line = line.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
        else:
            key, _, value = line.partition("=")
            out.append((section, key.strip(), value.strip()))
    return out


# ---- the example configuration --------------------------------------------------------------

def test_example_config_has_the_loaders_keys():
    config = tomllib.loads(EXAMPLE.read_text())
    expected = {
        "serial": {"port": str, "baudrate": int},
        "site": {"latitude_deg": float, "height_m": float},
        "output": {"state_dir": str},
        "warmup": {"max_slope_c_per_h": float, "window_s": int, "min_time_s": int},
        "detection": {"min_static_s": float, "settle_s": float},
        "method": {"name": str, "fixed_amplitude": bool, "drift": bool, "resolve_every_s": int},
    }
    assert set(config) == set(expected)
    for table, keys in expected.items():
        assert set(config[table]) == set(keys), table
        for key, kind in keys.items():
            assert isinstance(config[table][key], kind), f"[{table}] {key}"
    assert config["serial"] == {"port": "/dev/ttyUSB0", "baudrate": 921600}
    assert config["method"]["name"] in ("joint", "thesis")
    assert config["output"]["state_dir"] == f"/var/lib/calibd/{DEVICE}"  # the unit's StateDirectory=


def test_example_config_shows_the_optional_keys_commented_out():
    text = EXAMPLE.read_text()
    for key in ("g0", "alpha_deg", "beta_deg"):
        assert re.search(rf"^# {key} = ", text, re.MULTILINE), key


# ---- the unit and the udev rule, as text ----------------------------------------------------

def test_unit_has_the_required_settings():
    found = directives(UNIT.read_text())
    settings = {(s, k): v for s, k, v in found}
    assert settings[("Service", "Type")] == "notify"
    assert settings[("Service", "NotifyAccess")] == "main"
    assert settings[("Service", "WatchdogSec")] == "30"
    assert settings[("Service", "Restart")] == "on-failure"
    assert settings[("Service", "SyslogLevelPrefix")] == "yes"  # the daemon's "<N>" priorities
    assert settings[("Service", "ExecStart")] == \
        "/usr/local/bin/calibd run --config /etc/calibd/%i.toml --port /dev/%i"
    assert settings[("Unit", "BindsTo")] == settings[("Unit", "After")] == "dev-%i.device"
    assert settings[("Service", "DynamicUser")] == "yes"
    assert settings[("Service", "SupplementaryGroups")] == "dialout"
    assert settings[("Service", "DevicePolicy")] == "closed"
    assert settings[("Service", "DeviceAllow")] == "/dev/%i rw"
    assert settings[("Service", "StateDirectory")] == "calibd/%i"
    assert settings[("Service", "RestrictAddressFamilies")] == "AF_UNIX"
    assert [v for s, k, v in found if k == "SystemCallFilter"] == ["@system-service", "~@privileged @resources"]
    # PrivateUsers= would map dialout to nobody and lock the daemon out of its port.
    assert ("Service", "PrivateUsers") not in settings
    keys = [k for _, k, _ in found]
    assert {k for k in keys if keys.count(k) > 1} == {"SystemCallFilter"}, "a setting given twice"


def test_udev_rule_starts_the_unit():
    rule = RULES.read_text().replace("\\\n", " ")
    lines = [line for line in rule.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert len(lines) == 1
    for part in ('SUBSYSTEM=="tty"', 'TAG+="systemd"', 'ENV{SYSTEMD_WANTS}+="calibd@%k.service"',
                 'GROUP="dialout"', 'MODE="0660"', 'SYMLINK+="stim300-%n"'):
        assert part in lines[0], part


# ---- systemd-analyze ------------------------------------------------------------------------

def analyze(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, SYSTEMD_COLORS="0", SYSTEMD_PAGER="", SYSTEMD_LOG_COLOR="0", LC_ALL="C.UTF-8")
    return subprocess.run([ANALYZE, *args], capture_output=True, env=env, timeout=30,
                          encoding="utf-8", errors="replace")


def unit_copy(directory: Path, text: str | None = None) -> Path:
    """The unit in `directory` with every Exec*= program replaced by an executable that exists
    here (verify rejects a missing /usr/local/bin/calibd); returns the path of its instance
    calibd@ttyUSB0.service, which systemd-analyze loads from the template beside it."""
    true = shutil.which("true") or "/bin/true"
    text = UNIT.read_text() if text is None else text
    text = re.sub(r"^(Exec\w+=)[-@:+!]*\S+", rf"\g<1>{true}", text, flags=re.MULTILINE)
    (directory / UNIT.name).write_text(text)
    return directory / f"calibd@{DEVICE}.service"


def verify_complaints(unit: Path) -> tuple[int, list[str]]:
    result = analyze("verify", "--man=no", str(unit))
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    # The device unit exists only while the adapter is plugged in; verify may say so.
    return result.returncode, [line for line in lines if f"dev-{DEVICE}.device" not in line]


@needs_analyze
def test_verify_catches_syntax_errors(tmp_path):
    """The check below means something: on this systemd, verify reports a bad key and value."""
    broken = UNIT.read_text().replace("LockPersonality=yes", "LockPersonality=yes\nLockPersonalty=yes") \
                             .replace("WatchdogSec=30", "WatchdogSec=thirty")
    _, complaints = verify_complaints(unit_copy(tmp_path, broken))
    assert any("LockPersonalty" in line and SYNTAX_ERRORS.search(line) for line in complaints), complaints
    assert any("thirty" in line and SYNTAX_ERRORS.search(line) for line in complaints), complaints


@needs_analyze
def test_unit_verifies_cleanly(tmp_path):
    code, complaints = verify_complaints(unit_copy(tmp_path))
    assert not [line for line in complaints if SYNTAX_ERRORS.search(line)], "\n".join(complaints)
    assert code == 0 or not complaints, "\n".join(complaints)


@needs_analyze
def test_unit_exposure_is_low(tmp_path):
    result = analyze("security", "--offline=yes", str(unit_copy(tmp_path)))
    output = result.stdout + result.stderr
    if result.returncode != 0 and re.search(r"unrecognized option|unknown option|--offline", output, re.I):
        pytest.skip(f"this systemd-analyze has no --offline: {output.strip().splitlines()[0]}")
    match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", output)
    assert match, output
    exposure = float(match.group(1))
    assert exposure <= MAX_EXPOSURE, output

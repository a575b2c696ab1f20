"""systemd/: the example config has the loader's keys; the unit passes `systemd-analyze verify`
and `systemd-analyze security --offline=yes` rates it at most 2.0, also with the drop-in its
comments give for serving on TCP (skipped without systemd-analyze); it serves what it serves to
the stim300 group under /run/calibd/<device>."""

import os
import re
from dataclasses import fields
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


def test_example_configs_ros2_and_foxglove_tables_uncommented_are_the_defaults():
    """The commented [ros2] and [foxglove] tables say what an empty table gives."""
    from calibd.config import FoxgloveConfig, Ros2Config, parse_config

    text = EXAMPLE.read_text()
    for table, default in (("ros2", Ros2Config()), ("foxglove", FoxgloveConfig())):
        block = text.split(f"# [{table}]\n", 1)[1].split("\n\n", 1)[0]
        keys = [line[2:].split("#")[0] for line in block.splitlines() if re.match(r"# \w+ = ", line)]
        assert len(keys) == len(fields(default)), table  # every key shown
        config = parse_config(tomllib.loads(text + f"\n[{table}]\n" + "\n".join(keys)), "example")
        assert getattr(config, table) == default


def test_example_configs_record_table_uncommented_is_its_defaults():
    from calibd.config import RecordConfig, parse_config

    text = EXAMPLE.read_text()
    block = text.split("# [record]\n", 1)[1].split("\n\n", 1)[0]
    keys = [line[2:].split("#")[0] for line in block.splitlines() if re.match(r"# \w+ = ", line)]
    assert len(keys) == len(fields(RecordConfig))
    config = parse_config(tomllib.loads(text + "\n[record]\n" + "\n".join(keys)), "example")
    assert config.record == RecordConfig(Path(f"/var/lib/calibd/{DEVICE}/recordings"))


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
    # the port through dialout; what is served (socket, ptys, result copy) handed to stim300
    assert settings[("Service", "SupplementaryGroups")] == "dialout stim300"
    assert settings[("Service", "DevicePolicy")] == "closed"
    # the port, and the ptys the raw and corrected streams are served on
    assert [v for s, k, v in found if k == "DeviceAllow"] == ["/dev/%i rw", "/dev/ptmx rw", "char-pts rw"]
    assert settings[("Service", "StateDirectory")] == "calibd/%i"
    # /run/calibd/%i: searchable by the stim300 clients, the files' own group and mode guard them
    assert settings[("Service", "RuntimeDirectory")] == "calibd/%i"
    assert settings[("Service", "RuntimeDirectoryMode")] == "0711"
    assert settings[("Service", "RestrictAddressFamilies")] == "AF_UNIX"
    # chown (in @privileged) given back: the daemon hands the socket, ptys and result copy to stim300
    assert [v for s, k, v in found if k == "SystemCallFilter"] == \
        ["@system-service", "~@privileged @resources", "@chown"]
    # PrivateUsers= would map dialout to nobody and lock the daemon out of its port.
    assert ("Service", "PrivateUsers") not in settings
    keys = [k for _, k, _ in found]
    assert {k for k in keys if keys.count(k) > 1} == {"SystemCallFilter", "DeviceAllow"}, "a setting given twice"


def test_unit_and_readme_say_where_clients_find_what_is_served():
    for text in (UNIT.read_text(), (SYSTEMD / "README.md").read_text()):
        for words in ("/run/calibd/", "calibd.sock", "raw", "corrected", "result.json",
                      "groupadd --system stim300", "usermod -aG stim300 USER"):
            assert words in text, words


def tcp_drop_in() -> str:
    """The drop-in the unit's comments give for [serve] tcp: the commented block after "[Service]"."""
    lines = UNIT.read_text().splitlines()
    start = lines.index("#   [Service]")
    block = []
    for line in lines[start:]:
        if not line.startswith("#   "):
            break
        block.append(line[4:])
    return "\n".join(block) + "\n"


def test_the_tcp_drop_in_opens_the_network():
    settings = directives(tcp_drop_in())
    assert ("Service", "PrivateNetwork", "no") in settings
    assert ("Service", "IPAddressAllow", "localhost") in settings
    assert any(k == "RestrictAddressFamilies" and "AF_INET" in v for _, k, v in settings)


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
@pytest.mark.parametrize("drop_in", [None, "tcp"])
def test_unit_exposure_is_low(tmp_path, drop_in):
    unit = unit_copy(tmp_path)
    if drop_in:  # systemd-analyze reads drop-ins from NAME.d/ beside the unit
        (tmp_path / f"{UNIT.name}.d").mkdir()
        (tmp_path / f"{UNIT.name}.d" / "tcp.conf").write_text(tcp_drop_in())
        code, complaints = verify_complaints(unit)
        assert not [line for line in complaints if SYNTAX_ERRORS.search(line)], "\n".join(complaints)
    result = analyze("security", "--offline=yes", str(unit))
    output = result.stdout + result.stderr
    if result.returncode != 0 and re.search(r"unrecognized option|unknown option|--offline", output, re.I):
        pytest.skip(f"this systemd-analyze has no --offline: {output.strip().splitlines()[0]}")
    match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", output)
    assert match, output
    exposure = float(match.group(1))
    assert exposure <= MAX_EXPOSURE, output
    if drop_in:  # the drop-in was read: the score counts the network it opens
        assert "host's network" in output, output

"""calibd.config: the daemon's TOML configuration and its one-line errors."""

import os
import tomllib
from pathlib import Path

import pytest

from calibd.config import (ConfigError, DaemonConfig, DetectionConfig, MethodConfig, SerialConfig, ServeConfig,
                           WarmupConfig, load_config, parse_config)
from calibd.frames import Site

EXAMPLE = Path(__file__).resolve().parent.parent / "systemd" / "calibd.example.toml"

FULL = """
[serial]
port = "/dev/ttyUSB0"
baudrate = 460800

[site]
latitude_deg = 40.59129
height_m = 12.5
g0 = 9.79956

[output]
state_dir = "/var/lib/calibd/ttyUSB0"

[warmup]
max_slope_c_per_h = 0.5
window_s = 900
min_time_s = 3600

[detection]
turn_threshold_deg_s = 2.0
min_static_s = 8
settle_s = 0

[method]
name = "thesis"
alpha_deg = 0.5964
beta_deg = -0.1125
resolve_every_s = 30
"""

MINIMAL = """
[serial]
port = "/dev/ttyUSB1"
[site]
latitude_deg = -33.9
[output]
state_dir = "state"
"""


def write(tmp_path, text: str) -> Path:
    path = tmp_path / "calibd.toml"
    path.write_text(text)
    return path


def error(path) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "\n" not in message and "calibd.toml" in message
    return message


def test_full_config_round_trips(tmp_path):
    config = load_config(write(tmp_path, FULL))
    assert config == DaemonConfig(
        serial=SerialConfig("/dev/ttyUSB0", 460800),
        site=Site(40.59129, 12.5, 9.79956),
        state_dir=Path("/var/lib/calibd/ttyUSB0"),
        warmup=WarmupConfig(0.5, 900.0, 3600.0),
        method=MethodConfig("thesis", alpha_deg=0.5964, beta_deg=-0.1125, resolve_every_s=30.0),
        detection=DetectionConfig(turn_threshold_deg_s=2.0, min_static_s=8.0, settle_s=0.0))
    assert isinstance(config.warmup.window_s, float)
    assert config.detection.options() == {"turn_threshold_deg_s": 2.0, "min_static_s": 8.0, "settle_s": 0.0}


def test_joint_options(tmp_path):
    path = write(tmp_path, MINIMAL + '[method]\nname = "joint"\nfixed_amplitude = true\ndrift = true\n')
    assert load_config(path).method == MethodConfig("joint", fixed_amplitude=True, drift=True)
    path = write(tmp_path, MINIMAL + '[method]\nindex_step_deg = 90\nindex_sigma_deg = 0.005\n')
    method = load_config(path).method
    assert (method.index_step_deg, method.index_sigma_deg) == (90.0, 0.005)
    message = error(write(tmp_path, MINIMAL + '[method]\nindex_sigma_deg = 0.005\n'))
    assert message.endswith("[method] index_sigma_deg: is the index's 1-sigma: give index_step_deg too"), message


def test_defaults_apply(tmp_path):
    config = load_config(str(write(tmp_path, MINIMAL)))
    assert config.serial == SerialConfig("/dev/ttyUSB1", 921600)
    assert config.site == Site(-33.9) and config.site.g0 is None
    assert config.state_dir == Path("state")
    assert config.warmup == WarmupConfig(1.0, 600.0, 0.0)
    assert config.method == MethodConfig("joint", False, False, None, None, 60.0)
    assert config.detection.options() == {}  # find_segments' defaults, thresholds from the noise


SERVE = """
[serve]
raw_pty = "/run/calibd/ttyUSB0/raw"
corrected_pty = "/run/calibd/ttyUSB0/corrected"
corrected_before_result = "raw"
allow_service_mode = true
socket = "/run/calibd/ttyUSB0/calibd.sock"
tcp = "0.0.0.0:2950"
tcp_token_file = "/etc/calibd/tcp.token"
group = "stim300"
result_copy = "/run/calibd/ttyUSB0/result.json"
idle_timeout_s = 60
max_clients_per_uid = 4
"""


def test_serve_table(tmp_path):
    run = Path("/run/calibd/ttyUSB0")
    assert load_config(write(tmp_path, MINIMAL + SERVE)).serve == ServeConfig(
        raw_pty=run / "raw", corrected_pty=run / "corrected", corrected_before_result="raw", allow_service_mode=True,
        socket=run / "calibd.sock", tcp=("0.0.0.0", 2950), tcp_token_file=Path("/etc/calibd/tcp.token"),
        group="stim300", result_copy=run / "result.json", idle_timeout_s=60.0, max_clients_per_uid=4)
    default = load_config(write(tmp_path, MINIMAL)).serve
    assert default == ServeConfig() and not ServeConfig().serving
    assert default.idle_timeout_s == 30.0 and default.max_clients_per_uid == 16 and not default.tcp_open
    only_port = load_config(write(tmp_path, MINIMAL + '[serve]\ntcp = "2950"\ntcp_open = true\n')).serve
    assert only_port.tcp == ("127.0.0.1", 2950) and only_port.serving  # loopback unless told otherwise
    assert only_port.tcp_open and only_port.tcp_token_file is None
    assert load_config(write(tmp_path, MINIMAL + '[serve]\ntcp = "[::1]:2950"\ntcp_open = true\n')).serve.tcp == (
        "::1", 2950)


def test_raw_pty_is_one_path_or_a_list_of_them(tmp_path):
    """One pty serves one reader (a second reader of a pty splits its bytes), so several readers
    get several raw ptys."""
    one = load_config(write(tmp_path, MINIMAL + '[serve]\nraw_pty = "/run/a"\n')).serve
    assert one.raw_ptys == (Path("/run/a"),) and one.serving
    two = load_config(write(tmp_path, MINIMAL + '[serve]\nraw_pty = ["/run/a", "/run/b"]\n')).serve
    assert two.raw_ptys == (Path("/run/a"), Path("/run/b")) and two.serving
    assert ServeConfig().raw_ptys == ()


@pytest.mark.parametrize("value, words", [
    ("[]", ["[] is not a path, or a list of paths"]),
    ('["/run/a", 3]', ["['/run/a', 3] is not a path, or a list of paths"]),
    ('["/run/a", ""]', ["is not a path, or a list of paths"]),
    ("5", ["5 is not a path, or a list of paths"]),
    ('["/run/a", "/run/a"]', ["'/run/a' is also raw_pty"]),
    ('["/run/a", "/run/calibd/ttyUSB0/corrected"]', ["is also raw_pty"]),
])
def test_a_bad_raw_pty_is_one_line_naming_it(tmp_path, value, words):
    message = error(write(tmp_path, MINIMAL + replace_line(SERVE, 'raw_pty = "/run/calibd/ttyUSB0/raw"',
                                                            f"raw_pty = {value}")))
    assert "[serve] raw_pty" in message or "[serve] corrected_pty" in message
    assert "\n" not in message
    for word in words:
        assert word in message


@pytest.mark.parametrize("old, new, key, words", [
    ('tcp = "0.0.0.0:2950"', 'tcp = "localhost"', "tcp", ["'localhost'", "HOST:PORT"]),
    ('tcp = "0.0.0.0:2950"', 'tcp = "127.0.0.1:70000"', "tcp", ["70000", "[1, 65535]"]),
    ('tcp = "0.0.0.0:2950"', 'tcp = ":2950"', "tcp", ["':2950'"]),
    ('tcp = "0.0.0.0:2950"', "tcp = 2950", "tcp", ["2950 is not a string"]),
    ('corrected_before_result = "raw"', 'corrected_before_result = "zero"', "corrected_before_result",
     ["'zero'", '"hold" or "raw"']),
    ("allow_service_mode = true", 'allow_service_mode = "yes"', "allow_service_mode", ["true or false"]),
    ('group = "stim300"', 'group = ""', "group", ["''", "group name"]),
    ('socket = "/run/calibd/ttyUSB0/calibd.sock"', 'socket = ""', "socket", ["''", "a path"]),
    ('result_copy = "/run/calibd/ttyUSB0/result.json"', 'result_copy = "/run/calibd/ttyUSB0/raw"', "result_copy",
     ["also raw_pty"]),
    ('group = "stim300"', 'owner = "stim300"', "owner", ["unknown key", "socket"]),
    ('tcp_token_file = "/etc/calibd/tcp.token"', "", "tcp", ["needs tcp_token_file = PATH", "tcp_open = true"]),
    ('tcp_token_file = "/etc/calibd/tcp.token"', "tcp_open = false", "tcp", ["needs tcp_token_file"]),
    ('group = "stim300"', "tcp_open = true", "tcp_open", ["choose one"]),
    ('tcp = "0.0.0.0:2950"', "", "tcp_token_file", ["without tcp"]),
    ('tcp_token_file = "/etc/calibd/tcp.token"', 'tcp_open = "yes"', "tcp_open", ["true or false"]),
    ("idle_timeout_s = 60", "idle_timeout_s = 0", "idle_timeout_s", ["a timeout in (0, 86400] s"]),
    ("idle_timeout_s = 60", "idle_timeout_s = -5", "idle_timeout_s", ["(0, 86400] s"]),
    ("max_clients_per_uid = 4", "max_clients_per_uid = 65", "max_clients_per_uid", ["[1, 64]"]),
    ("max_clients_per_uid = 4", "max_clients_per_uid = 2.5", "max_clients_per_uid", ["not an integer"]),
])
def test_serve_errors_name_the_key(tmp_path, old, new, key, words):
    message = error(write(tmp_path, MINIMAL + replace_line(SERVE, old, new)))
    assert "[serve]" in message and key in message
    for word in words:
        assert word in message


def test_empty_optional_tables_give_defaults(tmp_path):
    config = load_config(write(tmp_path, MINIMAL + "[warmup]\n[method]\n"))
    assert config.warmup == WarmupConfig() and config.method == MethodConfig()


def test_with_port_changes_only_the_port(tmp_path):
    config = load_config(write(tmp_path, FULL))
    other = config.with_port("/dev/ttyUSB3")
    assert other.serial == SerialConfig("/dev/ttyUSB3", 460800)
    assert other.site == config.site and other.method == config.method and other.state_dir == config.state_dir
    assert config.serial.port == "/dev/ttyUSB0"


def replace_line(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new)


@pytest.mark.parametrize("old, new, table, key, words", [
    # missing required keys (and a missing required table)
    ('port = "/dev/ttyUSB0"\n', "", "[serial]", "port", ["missing"]),
    ("latitude_deg = 40.59129\n", "", "[site]", "latitude_deg", ["missing"]),
    ('[output]\nstate_dir = "/var/lib/calibd/ttyUSB0"\n', "", "[output]", "state_dir", ["missing"]),
    # wrong types
    ("baudrate = 460800", 'baudrate = "fast"', "[serial]", "baudrate", ["'fast'", "integer"]),
    ("baudrate = 460800", "baudrate = 460800.0", "[serial]", "baudrate", ["460800.0", "integer"]),
    ('port = "/dev/ttyUSB0"', "port = 3", "[serial]", "port", ["3", "string"]),
    ("height_m = 12.5", "height_m = true", "[site]", "height_m", ["True", "number"]),
    ("latitude_deg = 40.59129", 'latitude_deg = "40N"', "[site]", "latitude_deg", ["'40N'", "number"]),
    ('state_dir = "/var/lib/calibd/ttyUSB0"', "state_dir = []", "[output]", "state_dir", ["[]", "string"]),
    ('name = "thesis"', "name = 1", "[method]", "name", ["1", "string"]),
    ("min_static_s = 8", 'min_static_s = "long"', "[detection]", "min_static_s", ["'long'", "number"]),
    # out of range
    ("turn_threshold_deg_s = 2.0", "turn_threshold_deg_s = 0", "[detection]", "turn_threshold_deg_s",
     ["0 is not a positive rate in (0, 1000] deg/s"]),
    ("settle_s = 0", "settle_s = -1", "[detection]", "settle_s",
     ["-1.0 is not a non-negative duration in [0, 3600] s"]),
    ("min_static_s = 8", "min_static_s = 1e308", "[detection]", "min_static_s", ["1e+308", "(0, 86400] s"]),
    ("turn_threshold_deg_s = 2.0", "turn_threshold_deg_s = 2.0\nremount_g = 1e9", "[detection]", "remount_g",
     ["1000000000.0 is not a positive acceleration step in (0, 10] g"]),
    ("latitude_deg = 40.59129", "latitude_deg = 95.0", "[site]", "latitude_deg",
     ["95.0 is not a latitude in [-90, 90] deg"]),
    ("height_m = 12.5", "height_m = 9500", "[site]", "height_m", ["9500", "[-500, 9000]"]),
    ("g0 = 9.79956", "g0 = 9.5", "[site]", "g0", ["9.5", "9.7"]),
    ("baudrate = 460800", "baudrate = 0", "[serial]", "baudrate", ["0", "positive"]),
    ("baudrate = 460800", "baudrate = 4611686018427387904", "[serial]", "baudrate", ["(0, 1e+07] bit/s"]),
    ('port = "/dev/ttyUSB0"', 'port = " "', "[serial]", "port", ["' '", "device path"]),
    ('state_dir = "/var/lib/calibd/ttyUSB0"', 'state_dir = ""', "[output]", "state_dir", ["''", "directory"]),
    ("max_slope_c_per_h = 0.5", "max_slope_c_per_h = 0", "[warmup]", "max_slope_c_per_h", ["0", "positive"]),
    ("max_slope_c_per_h = 0.5", "max_slope_c_per_h = 1e9", "[warmup]", "max_slope_c_per_h", ["(0, 100] degC/h"]),
    ("window_s = 900", "window_s = -1", "[warmup]", "window_s", ["-1", "a duration in [1, 86400] s"]),
    ("window_s = 900", "window_s = 1e308", "[warmup]", "window_s", ["1e+308", "a duration in [1, 86400] s"]),
    ("min_time_s = 3600", "min_time_s = -5", "[warmup]", "min_time_s", ["-5", "[0, 604800] s"]),
    ("resolve_every_s = 30", "resolve_every_s = 0", "[method]", "resolve_every_s", ["0", "[1, 86400] s"]),
    ("resolve_every_s = 30", "resolve_every_s = 1e-300", "[method]", "resolve_every_s",
     ["1e-300 is not an interval in [1, 86400] s"]),
    ('name = "thesis"', 'name = "kalman"', "[method]", "name", ["'kalman'", '"joint" or "thesis"']),
    ("alpha_deg = 0.5964", "alpha_deg = 12", "[method]", "alpha_deg", ["12", "[-10, 10]"]),
    # unknown keys and tables
    ("baudrate = 460800", "baud = 460800", "[serial]", "baud", ["unknown key", "baudrate", "port"]),
    ("g0 = 9.79956", "latitude = 40.6", "[site]", "latitude", ["unknown key", "latitude_deg"]),
    ("[output]", "[outputs]", "[outputs]", "outputs", ["unknown table", "[output]", "[warmup]"]),
    ("[serial]\n", "", "port", "port", ["'/dev/ttyUSB0'", "[serial]"]),  # keys outside any table
    # method-option mixups
    ("beta_deg = -0.1125\n", "", "[method]", "alpha_deg", ["0.5964", "without beta_deg"]),
    ("alpha_deg = 0.5964\n", "", "[method]", "beta_deg", ["-0.1125", "without alpha_deg"]),
    ('name = "thesis"', 'name = "joint"', "[method]", "alpha_deg", ["0.5964", '"joint"', "thesis method"]),
    ('name = "thesis"', 'name = "thesis"\ndrift = false', "[method]", "drift", ["False", '"thesis"', "joint"]),
    ('name = "thesis"', 'name = "thesis"\nfixed_amplitude = true', "[method]", "fixed_amplitude",
     ["True", '"thesis"']),
    ('name = "thesis"', 'name = "joint"\nindex_step_deg = 0.5', "[method]", "index_step_deg",
     ["0.5", "an indexing table's step in [1, 360] deg"]),
])
def test_errors_name_file_table_and_key(tmp_path, old, new, table, key, words):
    message = error(write(tmp_path, replace_line(FULL, old, new)))
    assert table in message and key in message
    for word in words:
        assert word in message


def test_table_given_as_a_value(tmp_path):
    message = error(write(tmp_path, 'method = "joint"\n' + MINIMAL))
    assert "[method]" in message and "'joint' is not a table" in message


def test_missing_file(tmp_path):
    assert "no such" in error(tmp_path / "calibd.toml")


def test_directory(tmp_path):
    (tmp_path / "calibd.toml").mkdir()
    assert "is a directory" in error(tmp_path / "calibd.toml")


def test_bad_toml(tmp_path):
    assert "not valid TOML" in error(write(tmp_path, "[serial]\nport = /dev/ttyUSB0\n"))


def test_not_utf8(tmp_path):
    path = tmp_path / "calibd.toml"
    path.write_bytes(b'[serial]\nport = "\xff"\n')
    assert "cannot read" in error(path)


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root reads any file")
def test_unreadable(tmp_path):
    path = write(tmp_path, FULL)
    path.chmod(0)
    try:
        assert "cannot read: permission denied" in error(path)
    finally:
        path.chmod(0o600)


@pytest.mark.parametrize("text, words", [
    ("a = " + "[" * 5000 + "]" * 5000, "a (line 1): arrays nested too deep to read"),
    ("[site]\nlatitude_deg = " + "9" * 5000, "latitude_deg (line 2): an integer of more than 4300 digits"),
    ("x = 1\n" * 200_000, "too large for a TOML configuration file"),
])
def test_hostile_toml_is_one_line(tmp_path, text, words):
    assert words in error(write(tmp_path, text))


def test_example_config_loads():
    config = load_config(EXAMPLE)
    assert config.with_port("/dev/ttyUSB9").serial.port == "/dev/ttyUSB9"


def test_example_serve_section_loads_once_uncommented():
    text = EXAMPLE.read_text()
    section = text[text.index("# [serve]"):].split("\n\n", 1)[0]  # the [serve] block, up to the next table's
    keys = [line[2:] for line in section.splitlines() if line.startswith("# ") and (" = " in line or "[" in line)]
    config = parse_config(tomllib.loads(text + "\n" + "\n".join(keys) + "\n"), "example")
    assert config.serve.socket == Path("/run/calibd/ttyUSB0/calibd.sock") and config.serve.tcp == ("127.0.0.1", 2950)
    assert config.serve.corrected_before_result == "hold" and config.serve.group == "stim300"
    assert config.serve.tcp_token_file == Path("/etc/calibd/tcp.token") and not config.serve.tcp_open
    assert config.serve.idle_timeout_s == 30 and config.serve.max_clients_per_uid == 16


@pytest.mark.parametrize("text, says", [
    ('[serial]\nport = "/dev/x"\n[site]\nlatitud_deg = 60\n[output]\nstate_dir = "s"\n',
     "[site] latitude_deg: missing: the site's latitude is needed for the Earth rate (the table has 'latitud_deg', "
     "an unknown key: a typo?)"),
    ('[serial]\nprot = "/dev/x"\n[site]\nlatitude_deg = 60\n[output]\nstate_dir = "s"\n',
     "[serial] port: missing: expected a device path such as \"/dev/ttyUSB0\" or a pyserial URL (the table has "
     "'prot', an unknown key: a typo?)"),
    ('[serial]\nport = "/dev/x"\n[site]\nheight_m = 3\n[output]\nstate_dir = "s"\n',
     "[site] latitude_deg: missing: the site's latitude is needed for the Earth rate"),
])
def test_a_missing_key_names_the_unknown_key_it_was_probably_typed_as(tmp_path, text, says):
    message = error(write(tmp_path, text))
    assert message.endswith(says), message


def test_a_correction_policy_outside_the_choices_is_one_line(tmp_path):
    text = '[serial]\nport = "/dev/x"\n[site]\nlatitude_deg = 60\n[output]\nstate_dir = "s"\n[serve]\n' \
           'corrected_pty = "/tmp/c"\ncorrection = "median"\n'
    says = """[serve] correction: 'median' is not "latest" or "first" or "best\""""
    assert error(write(tmp_path, text)).endswith(says)

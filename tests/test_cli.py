"""`stim300 decode | info`: tables in physical units, capture health, one-line errors; calibd's
printed estimates: value and sigma rounded alike, columns aligned."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from calibd.units import value_sigma, value_sigma_texts
from captures import capture
from stim300.cli import main
from stim300.protocol import Status
from stim300.special import Configuration, encode_special


@pytest.fixture
def capture_file(tmp_path):
    config = Configuration.build(sample_rate_hz=125, crlf=True)
    data, truth, _ = capture(300, 0xA7, True, rate=125)
    path = tmp_path / "session.bin"
    path.write_bytes(encode_special(config, True) + data[:100 * 61] + b"\x00garbage" + data[101 * 61:])
    return path, np.delete(truth, 100)


def test_decode_to_npz_gives_physical_columns(capture_file, tmp_path, run_main):
    path, truth = capture_file
    out = tmp_path / "table.npz"
    code, _, err = run_main(main, ["decode", path, "-o", out])
    assert code == 0, err
    table = np.load(out)
    expected = ["t_s", "counter", "latency_us", "gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z",
                "incl_x", "incl_y", "incl_z", "temp_gyro_x", "temp_gyro_y", "temp_gyro_z", "temp_acc_x",
                "temp_acc_y", "temp_acc_z", "temp_incl_x", "temp_incl_y", "temp_incl_z", "status_gyro",
                "status_acc", "status_incl", "status_temp_gyro", "status_temp_acc", "status_temp_incl", "units"]
    assert table.files == expected
    assert np.array_equal(table["gyro_y"], truth["gyro"][:, 1])
    assert np.array_equal(table["temp_incl_z"], truth["temp_incl"][:, 2])
    assert np.array_equal(table["counter"], truth["counter"])
    assert table["gyro_x"].dtype == np.float32 and table["counter"].dtype == np.uint8
    assert np.array_equal(table["t_s"], np.delete(np.arange(300), 100) / 125)  # the lost datagram's time skipped
    units = json.loads(str(table["units"]))
    assert units["gyro_x"] == "deg/s" and units["acc_z"] == "g" and units["temp_acc_x"] == "degC"
    assert units["t_s"] == "s"
    assert "299 datagrams" in err and "lost_samples 1" in err


def test_decode_to_csv_matches_npz(capture_file, tmp_path, run_main):
    path, truth = capture_file
    code, _, err = run_main(main, ["decode", path, "-o", tmp_path / "t.csv"])
    assert code == 0, err
    lines = (tmp_path / "t.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header[:6] == ["t_s", "counter", "latency_us", "gyro_x", "gyro_y", "gyro_z"]
    table = np.loadtxt(tmp_path / "t.csv", delimiter=",", skiprows=1)
    assert table.shape == (299, len(header))
    assert np.array_equal(table[:, 0], np.delete(np.arange(300), 100) / 125)
    assert np.array_equal(table[:, header.index("acc_y")].astype(np.float32), truth["acc"][:, 1])


def test_decode_without_configuration_takes_options(tmp_path, run_main):
    data, truth, _ = capture(50, 0x93, False, rate=500, acc_range_g=30)
    path = tmp_path / "c.bin"
    path.write_bytes(data)
    code, _, err = run_main(main, ["decode", path, "-o", tmp_path / "t.npz", "--acc-range", "30"])
    assert code == 0, err
    table = np.load(tmp_path / "t.npz")
    assert np.array_equal(table["acc_x"], truth["acc"][:, 0])
    assert "temp_gyro_x" not in table.files


def test_info_json(capture_file, run_main):
    path, truth = capture_file
    code, out, err = run_main(main, ["info", path, "--json"])
    assert code == 0, err
    info = json.loads(out)
    assert info["datagrams"] == 299
    assert info["lost_samples"] == 1
    assert info["crc_errors"] == 0
    assert info["skipped_bytes"] == len(b"\x00garbage")
    assert info["datagram_id"] == "0xA7"
    assert info["sample_rate_hz"] == 125
    assert info["duration_s"] == pytest.approx(300 / 125)
    assert info["configuration"]["sample_rate_hz"] == 125
    flags = info["status_flags"]
    assert flags["gyro"]["START_UP"] == np.count_nonzero(truth["status_gyro"] == Status.START_UP)
    assert flags["acc"]["OVERLOAD"] == flags["acc"]["X"] == np.count_nonzero(truth["status_acc"] == 0x11)
    assert set(flags) == {"gyro", "acc", "incl", "temp_gyro", "temp_acc", "temp_incl"}


def test_info_text_has_units(capture_file, run_main):
    path, _ = capture_file
    code, out, _ = run_main(main, ["info", path])
    assert code == 0
    assert "125 Hz" in out and "2.400 s" in out and "datagrams        299" in out


def test_info_shows_the_configuration_as_grouped_lines_with_units(tmp_path, run_main):
    config = Configuration.build(sample_rate_hz=500, crlf=True, gyro_lpf_hz=(262, 131, 66),
                                 incl_axes=(True, True, False), parity=2, stop_bits=2)
    data, _, _ = capture(50, 0xA7, True, rate=500)
    path = tmp_path / "c.bin"
    path.write_bytes(encode_special(config, True) + data)
    code, out, _ = run_main(main, ["info", path])
    assert code == 0 and "{" not in out
    shown = out[out.index("configuration    "):].splitlines()
    groups = [line.strip() for line in shown if line.startswith("  ") and not line.startswith("    ")]
    assert groups == ["gyro", "acc", "incl", "serial line", "outputs"]
    for row in ("    low-pass        262 Hz / 131 Hz / 66 Hz (X / Y / Z)", "    range           +-400 deg/s",
                "    unit            rate (deg/s)", "    range           +-10 g", "    axes            X, Y",
                "    range           +-1.7 g", "    bit rate        921600 bit/s", "    framing         2 stop bits, "
                "parity odd", "    CR LF           yes", "    datagram        0xA7 (gyro, acc, incl, temperatures)",
                "    sample rate     500 Hz"):
        assert row in shown, row
    code, out, _ = run_main(main, ["info", path, "--json"])
    assert json.loads(out)["configuration"]["gyro_lpf_hz"] == [262, 131, 66]  # the machine form keeps the fields


def test_info_shows_an_undefined_configuration_code_as_read(tmp_path, run_main):
    """A real unit's configuration with bit-rate code 4, which the byte map does not define: shown
    as what it is, not as a user-defined bit rate."""
    config = bytes.fromhex("bc4b1f06407144407044407044400c00003330000000a91f9809")
    data, _, _ = capture(50, 0x93, False, rate=125)
    path = tmp_path / "c.bin"
    path.write_bytes(config + data)
    code, out, _ = run_main(main, ["info", path])
    assert code == 0 and "    bit rate        undefined code 0x4" in out.splitlines()
    assert "user-defined" not in out and "warning" in out


@pytest.mark.parametrize("case", ["missing", "directory", "empty", "not_stim300", "bad_datagram", "bad_range",
                                  "bad_unit", "bad_suffix", "no_output_dir", "output_is_dir"])
def test_bad_input_is_one_line_and_nonzero(case, capture_file, tmp_path, run_main):
    path, _ = capture_file
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    noise = tmp_path / "noise.bin"
    noise.write_bytes(bytes(range(256)) * 40)
    argv = {
        "missing": ["info", tmp_path / "nope.bin"],
        "directory": ["info", tmp_path],
        "empty": ["info", empty],
        "not_stim300": ["decode", noise, "-o", tmp_path / "x.npz"],
        "bad_datagram": ["info", path, "--datagram", "0x42"],
        "bad_range": ["info", path, "--acc-range", "7"],
        "bad_unit": ["decode", path, "-o", tmp_path / "x.npz", "--gyro-unit", "furlongs"],
        "bad_suffix": ["decode", path, "-o", tmp_path / "x.txt"],
        "no_output_dir": ["decode", path, "-o", tmp_path / "missing" / "x.npz"],
        "output_is_dir": ["decode", path, "-o", tmp_path / "d.npz"],
    }[case]
    (tmp_path / "d.npz").mkdir()
    code, out, err = run_main(main, argv)
    assert code != 0
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]


def test_console_script_reports_errors_without_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "stim300.cli", "info", str(tmp_path / "nope.bin")],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.strip() == f"stim300: {tmp_path / 'nope.bin'}: no such file"


@pytest.mark.parametrize("option, note", [
    (["--datagram", "0x93"], "--datagram 0x93 not used: its configuration datagram says 0xA7"),
    (["--rate", "2000"], "--rate 2000 not used: its configuration datagram says 125 Hz"),
])
def test_format_options_the_data_override_are_said(option, note, capture_file, run_main):
    """The options describe captures without a configuration datagram; one that has one wins,
    and the user is told in one line rather than left to believe the option applied."""
    path, _ = capture_file
    code, out, err = run_main(main, ["info", path, "--json", *option])
    assert code == 0 and json.loads(out)["sample_rate_hz"] == 125
    assert err.strip().splitlines() == [f"stim300: {path}: {note}"]


def test_a_rate_the_counter_confirms_is_taken(tmp_path, run_main):
    data, _, _ = capture(40, 0x93, True, rate=250)
    path = tmp_path / "c.bin"
    path.write_bytes(data)
    code, out, err = run_main(main, ["info", path, "--json", "--rate", "250"])
    assert code == 0 and err == ""
    info = json.loads(out)
    assert info["sample_rate_hz"] == 250 and info["lost_samples"] == 0


@pytest.mark.parametrize("value, sigma, texts", [
    (-3.33030, 1.75, ("-3.3", "1.8")), (-0.321412, 0.00123, ("-0.3214", "0.0012")),
    (98.63005, 0.667, ("98.63", "0.67")),
    (1234.5, 250.0, ("1234", "250")), (-3.33030, None, ("-3.3303", None)), (-4e-9, None, ("0.0000", None)),
    (0.5, float("nan"), ("0.5000", None)), (0.5, 0.0, ("0.5000", None)),
])
def test_a_value_is_rounded_at_its_sigmas_second_digit(value, sigma, texts):
    assert value_sigma_texts(value, sigma) == texts
    unit = "deg"
    assert value_sigma(value, sigma, unit) == (f"{texts[0]} +- {texts[1]} {unit}" if texts[1] else f"{texts[0]} {unit}")


@pytest.mark.slow
def test_calibrate_prints_estimates_rounded_and_aligned(tmp_path, capsys):
    code = calibd_main(["calibrate", "fixtures/thesis_real_cw_125hz.bin", "--latitude", "40.59129",
                        "-o", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    assert code == 0
    result = json.loads((tmp_path / "r.json").read_text())
    rows = [line for line in out.splitlines() if " +- " in line]
    assert len(rows) == len(result["estimates"])
    for line in rows:
        name, value, _, sigma, unit = line.split()
        estimate = result["estimates"][name]
        assert (value, sigma) == value_sigma_texts(estimate["value"], estimate["sigma"]) and unit == estimate["unit"]
        assert len(sigma.replace(".", "").lstrip("0")) == 2  # two significant digits, no more
    assert len({line.index(" +- ") for line in rows}) == 1 and len({len(line.split(" +- ")[0]) for line in rows}) == 1
    assert len({line.rindex(" ") for line in rows if line.endswith(" deg")}) == 1


@pytest.mark.parametrize("method", ["joint", "thesis"])
def test_a_bench_capture_refused_by_a_single_mounting_method_points_to_the_bench(method, tmp_path, capsys):
    code = calibd_main(["calibrate", "fixtures/thesis_bench_125hz.bin", "--latitude", "40.59129", "--method", method,
                        "-o", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and not (tmp_path / "r.json").exists()
    assert err.rstrip().endswith("; this looks like the bench campaign: use --method thesis --bench")
    code = calibd_main(["calibrate", "fixtures/thesis_bench_125hz.bin", "--latitude", "40.59129", "--method", "thesis",
                        "--bench", "-o", str(tmp_path / "r.json")])
    assert code == 0 and json.loads((tmp_path / "r.json").read_text())["method"] == "thesis-bench"


def test_a_refusal_of_what_is_not_the_bench_campaign_has_no_bench_hint():
    from calibd.methods import CampaignIncomplete
    from calibd.methods.joint import joint_real_case
    from calibd.captures import load_session
    from calibd.frames import Site

    session = load_session("fixtures/thesis_real_cw_125hz.bin")
    first_10_s = {name: getattr(session, name)[:1250] for name in ("time_s", "gyro", "acc", "incl", "temperature_c")}
    with pytest.raises(CampaignIncomplete) as refused:  # the level static alone: no turn after it
        joint_real_case(replace(session, **first_10_s), Site(40.59129))
    assert "it lacks a turn and a static after it on the level static's mounting" in str(refused.value)
    assert "bench" not in str(refused.value)


def test_replay_with_a_config_that_serves_says_it_serves_only_with_serve(capture_file, tmp_path, capsys):
    """A run's configuration given to replay: its [serve] table is not served without --serve,
    and one stderr line says so; the exit status is the replay's own."""
    path, _ = capture_file
    site = (f'[serial]\nport = "{tmp_path / "tty"}"\n[site]\nlatitude_deg = 40\n'
            f'[output]\nstate_dir = "{tmp_path / "state"}"\n')
    plain, served = tmp_path / "plain.toml", tmp_path / "served.toml"
    plain.write_text(site)
    served.write_text(site + f'[serve]\nsocket = "{tmp_path / "calibd.sock"}"\n')
    code = calibd_main(["replay", str(path), "--config", str(plain)])
    assert code == 1 and "[serve]" not in capsys.readouterr().err  # too short to solve: replayed, no result
    assert calibd_main(["replay", str(path), "--config", str(served)]) == code
    notes = [line for line in capsys.readouterr().err.splitlines() if "[serve]" in line]
    assert notes == [f"calibd replay: {served} serves the sensor ([serve]): a replay serves only with --serve"]
    assert not (tmp_path / "calibd.sock").exists()


def test_power_up_is_also_taken_by_its_former_name_session():
    from calibd.cli import build_parser

    for option in ("--power-up", "--session"):
        args = build_parser().parse_args(["calibrate", "c.bin", "-o", "r.json", "--latitude", "1", option, "2"])
        assert args.power_up == 2
    assert "--session" not in build_parser()._subparsers._group_actions[0].choices["calibrate"].format_help()

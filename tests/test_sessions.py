"""`calibd calibrate` on captures with sensor restarts and warm-ups: one power-up at a time, from
where the warm-up ends, and the site it used in every printout."""

import json
import re
from dataclasses import replace
from pathlib import Path

import pytest

from calibd.cli import main as calibd_main
from calibd.captures import open_capture
from calibd.frames import normal_gravity
from calibd.report import read_truth
from calibd.scenario import Segment, load_scenario
from calibd.sim import capture_bytes, power_up_datagrams, simulate

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
FULL = FIXTURES / "thesis_real_cw_125hz.bin"  # the whole thesis campaign, warm
SITE_ARGS = ["--latitude", "40.59129", "--g0", "9.79956"]


def calibrate(capsys, capture, *argv, tmp_path):
    out = tmp_path / "r.json"
    code = calibd_main(["calibrate", str(capture), *SITE_ARGS, "-o", str(out), *argv])
    printed = capsys.readouterr()
    return code, (json.loads(out.read_text()) if code == 0 else None), printed.out, printed.err


def assert_near_truth(result, truth, k=3.0):
    for name, e in result["estimates"].items():
        if e["sigma"]:
            assert abs(e["value"] - truth[name]) < k * e["sigma"], (name, e, truth[name])


@pytest.fixture(scope="module")
def level_only_bytes():
    """A later power-up: other turn-on biases, another heading, and only a 2 min level static."""
    real = load_scenario("thesis-real")
    scenario = replace(real, name="level-only", seed=77, segments=(Segment("static", duration_s=120),),
                       truth=replace(real.truth, yaw_deg=51.0, gyro_bias_deg_h=(80.0, -10.0, 5.0)))
    return capture_bytes(simulate(scenario))[0]


@pytest.mark.slow
def test_a_restart_followed_by_a_level_static_uses_the_power_up_with_the_campaign(level_only_bytes, tmp_path,
                                                                                  capsys):
    capture = tmp_path / "two.bin"
    capture.write_bytes(FULL.read_bytes() + level_only_bytes)
    code, result, out, err = calibrate(capsys, capture, tmp_path=tmp_path)
    assert code == 0, err
    power_up = result["stream"]["power_up"]
    assert (power_up["number"], power_up["count"]) == (1, 2)
    assert power_up["duration_s"] == pytest.approx(json.loads(Path(f"{FULL}.truth.json").read_text())["duration_s"],
                                                   abs=0.1)
    assert_near_truth(result, read_truth(str(FULL))[1])
    assert any("restarted after this power-up (1 of 2)" in w and "it lacks a turn and a static after it" in w
               for w in result["warnings"])
    assert "session: power-up 1 of 2" in out


@pytest.mark.slow
def test_the_last_power_up_with_the_campaign_wins_and_session_picks_another(level_only_bytes, tmp_path, capsys):
    capture = tmp_path / "two.bin"
    capture.write_bytes(level_only_bytes + FULL.read_bytes())
    code, result, out, err = calibrate(capsys, capture, tmp_path=tmp_path)
    assert code == 0, err
    assert result["stream"]["power_up"]["number"] == 2 and "session: power-up 2 of 2" in out
    assert_near_truth(result, read_truth(str(FULL))[1])
    assert not any("restarted" in w for w in result["warnings"])

    code, _, _, err = calibrate(capsys, capture, "--power-up", "1", tmp_path=tmp_path)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "power-up 1 of 2" in err and "it lacks a turn and a static after it" in err
    code, _, _, err = calibrate(capsys, capture, "--power-up", "3", tmp_path=tmp_path)
    assert code == 2 and "no power-up 3: the capture has 2" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_session_option_picks_the_first_power_up(tmp_path, capsys):
    """Two whole campaigns (0xA7 with temperatures, then 0x93 without): --session 1 is the first."""
    capture = tmp_path / "two.bin"
    capture.write_bytes(FULL.read_bytes() + (FIXTURES / "thesis_real_ccw_125hz.bin").read_bytes())
    code, last, _, err = calibrate(capsys, capture, tmp_path=tmp_path)
    assert code == 0, err
    assert last["stream"]["power_up"]["number"] == 2
    assert any("no temperatures" in w for w in last["warnings"])
    code, first, out, err = calibrate(capsys, capture, "--power-up", "1", tmp_path=tmp_path)
    assert code == 0, err
    assert first["stream"]["power_up"]["number"] == 1 and "session: power-up 1 of 2" in out
    assert not any("no temperatures" in w for w in first["warnings"])
    assert any("restarted after this power-up (1 of 2):" in w for w in first["warnings"])
    assert_near_truth(first, read_truth(str(FULL))[1])


@pytest.mark.slow
def test_a_restart_whose_power_up_datagrams_were_lost_is_seen_by_the_start_up_bit(tmp_path, capsys):
    real = load_scenario("thesis-real")
    restarted = replace(real, name="restarted", seed=79, segments=(Segment("static", duration_s=60),),
                        warmup=replace(real.warmup, power_on_s=0.0))  # the start-up bit in the first 0.7 s
    stream = capture_bytes(simulate(restarted))[0]
    headless = stream[len(power_up_datagrams(restarted)):]
    capture = tmp_path / "two.bin"
    capture.write_bytes(FULL.read_bytes() + headless)
    code, result, out, err = calibrate(capsys, capture, tmp_path=tmp_path)
    assert code == 0, err
    assert result["stream"]["restarts"] == 0  # the scanner saw no power-up sequence
    assert result["stream"]["power_up"]["count"] == 2 and result["stream"]["power_up"]["number"] == 1
    assert_near_truth(result, read_truth(str(FULL))[1])


def test_start_past_the_end_is_one_line(tmp_path, capsys):
    code, _, _, err = calibrate(capsys, FULL, "--start", "5000", tmp_path=tmp_path)
    assert code == 2 and len(err.strip().splitlines()) == 1
    duration_s = json.loads(FULL.with_name(FULL.name + ".truth.json").read_text())["duration_s"]
    assert f"start 5000 s is past the end of power-up 1 of 1 ({duration_s:.1f} s)" in err


def test_a_capture_whose_power_ups_all_lack_the_campaign_is_refused_naming_each(tmp_path, capsys):
    code, _, _, err = calibrate(capsys, FIXTURES / "faults_125hz.bin", tmp_path=tmp_path)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "power-up 2 of 2: not the joint" in err and "power-up 1 of 2: not the joint" in err


WARMING = FIXTURES / "warmup_then_protocol_125hz.bin"  # from power-on, 100 s time constant


def settled_truth():
    """The biases once warm (the rule's session starts where 0.25 degC of the rise is left)."""
    record = json.loads(Path(f"{WARMING}.truth.json").read_text())
    truth = read_truth(str(WARMING))[0]
    for name in ("gyro_bias", "acc_bias", "incl_bias"):
        last = record["bias_during_capture"][f"{name}_{'deg_h' if name == 'gyro_bias' else 'mg'}"]["last"]
        truth |= {f"{name}_{axis}": value for axis, value in zip("xyz", last)}
    return truth


@pytest.mark.slow
def test_calibrate_starts_where_the_warm_up_ends(tmp_path, capsys):
    code, result, out, err = calibrate(capsys, WARMING, tmp_path=tmp_path)
    assert code == 0, err
    start = result["stream"]["start_s"]
    assert 300 < start < 600 and "warm-up rule: the temperature settled" in result["stream"]["start_by"]
    assert f"power-up 1 of 1, {start:.1f} s to" in out and "warm-up rule" in out
    assert_near_truth(result, settled_truth())
    assert not any("warm-up" in w for w in result["warnings"])
    assert result["segments"][0]["start_s"] >= start


@pytest.mark.slow
def test_start_overrides_the_warm_up_rule(tmp_path, capsys):
    code, result, out, err = calibrate(capsys, WARMING, "--start", "0", tmp_path=tmp_path)
    assert code == 0, err
    assert result["stream"]["start_s"] == 0.0 and "from the given start" in out
    warning = next(w for w in result["warnings"] if "are warm-up" in w)
    assert "the first 417 s" in warning
    code, result, _, err = calibrate(capsys, WARMING, "--start", "600", tmp_path=tmp_path)
    assert code == 0, err
    assert result["stream"]["start_s"] == 600.0 and not any("warm-up" in w for w in result["warnings"])


@pytest.mark.slow
def test_a_power_up_that_never_settles_is_calibrated_and_flagged(tmp_path, capsys):
    real = load_scenario("thesis-real")
    scenario = replace(real, name="cold", seed=78, warmup=replace(real.warmup, power_on_s=0.0, time_constant_s=1000.0))
    capture = tmp_path / "cold.bin"
    capture.write_bytes(capture_bytes(simulate(scenario))[0])
    code, result, out, err = calibrate(capsys, capture, tmp_path=tmp_path)
    assert code == 0, err
    assert "never settles" in result["stream"]["start_by"]
    assert all(e.get("quality") == "poor" for e in result["estimates"].values())
    assert any("never settles" in w for w in result["warnings"])
    assert any("flagged poor" in w and "warmed up" in w for w in result["warnings"])
    assert "(poor)" in out


@pytest.mark.parametrize("argv,shown", [
    (["--latitude", "-40.59129"],
     f"site: latitude -40.59129 deg, height 0 m, g0 {normal_gravity(-40.59129, 0.0):.5f} m/s^2 (normal gravity)"),
    (["--latitude", "40.59129", "--g0", "9.79956", "--height", "120"],
     "site: latitude +40.59129 deg, height 120 m, g0 9.79956 m/s^2 (given)"),
])
@pytest.mark.slow
def test_calibrate_echoes_the_site(argv, shown, tmp_path, capsys):
    code = calibd_main(["calibrate", str(FULL), *argv, "-o", str(tmp_path / "r.json")])
    assert code == 0
    assert shown in capsys.readouterr().out
    assert json.loads((tmp_path / "r.json").read_text())["site"]["g0_given"] == ("--g0" in argv)


@pytest.mark.slow
def test_the_report_reads_the_power_up_the_result_used(level_only_bytes, tmp_path, capsys):
    from calibd.report import write_report

    capture = tmp_path / "two.bin"
    capture.write_bytes(FULL.read_bytes() + level_only_bytes)
    code, result, _, err = calibrate(capsys, capture, tmp_path=tmp_path)
    assert code == 0 and result["stream"]["power_up"]["number"] == 1, err
    write_report(tmp_path / "r.json", open_capture(str(capture)), tmp_path / "report.html")
    page = (tmp_path / "report.html").read_text()
    assert "The fit redone here gives a yaw" not in page  # the same data as the result's
    roles = re.findall(r"<tr><td>\d+</td><td>([a-z ]+)</td>", page.split('id="segments"')[1])
    assert roles == ["static", "index turn"] * 4 + ["static", "full turn", "static"]

"""The warm-up rule (calibd.warmup): one implementation for the daemon, calibrate and the report."""

from pathlib import Path

import numpy as np
import pytest

from calibd.captures import load_session
from calibd.config import WarmupConfig
from calibd.warmup import (WARM_UP_RULE, record_settling, settling, start_words, warm_up_end_s, warm_up_label,
                           warm_up_warnings)

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.fixture(scope="module")
def warming():
    """Recorded from power-on: 22 -> 38 degC with a 100 s time constant, then flat."""
    session = load_session(str(FIXTURES / "warmup_then_protocol_125hz.bin"))
    return session.time_s, session.temperature_c


def trend(t, temp, start, window_s=600.0):
    """Oracle: a least-squares line through the raw samples of the window."""
    keep = (t >= start) & (t < start + window_s)
    return np.polyfit(t[keep], temp[keep], 1)[0] * 3600


def test_settled_part_starts_at_the_first_window_within_the_limit(warming):
    t, temp = warming
    verdict = settling(t, temp)
    assert verdict.settled
    assert abs(trend(t, temp, verdict.start_s)) <= 1.0 < abs(trend(t, temp, verdict.start_s - 2))
    assert verdict.trend_c_per_h == pytest.approx(trend(t, temp, verdict.start_s), abs=0.02)
    assert 300 < verdict.start_s < 600
    shorter = settling(t, temp, WarmupConfig(window_s=100.0))  # a shorter window settles later: steeper part
    assert shorter.settled and shorter.start_s > verdict.start_s
    assert abs(trend(t, temp, shorter.start_s, 100.0)) <= 1.0


def test_a_settled_record_starts_at_once_even_shorter_than_the_window(warming):
    t, temp = warming
    late = t > 700  # 366 s: the whole record is the window
    assert settling(t[late], temp[late]).start_s == pytest.approx(t[late][0], abs=1e-9)


def test_a_record_that_never_settles_gives_its_calmest_window(warming):
    t, temp = warming
    early = t < 400
    verdict = settling(t[early], temp[early], WarmupConfig(window_s=100.0))
    assert not verdict.settled
    assert verdict.start_s == pytest.approx(t[early][-1] - 100, abs=1.5)  # the warm-up slows: the last window
    assert verdict.trend_c_per_h > 1.0


def test_min_time_since_power_up(warming):
    t, temp = warming
    verdict = settling(t, temp, WarmupConfig(window_s=100.0, min_time_s=900.0))
    assert verdict.settled and verdict.start_s == pytest.approx(800.0, abs=1.5)  # the first window ending at 900 s


def test_without_temperatures_only_time_since_power_up_counts(warming):
    t, _ = warming
    assert settling(t, None) == settling(t, None, WarmupConfig(window_s=100.0))
    assert settling(t, None).start_s == 0.0 and settling(t, None).trend_c_per_h is None
    assert settling(t, None, WarmupConfig(min_time_s=700.0)).start_s == pytest.approx(100.0, abs=1.5)
    assert not settling(t[t < 500], None, WarmupConfig(min_time_s=700.0)).settled


def test_the_verdict_in_words(warming):
    """The session's start, its warnings and the report's label all come from calibd.warmup."""
    t, temp = warming
    verdict = record_settling(t, temp)
    assert verdict == settling(t, temp, WARM_UP_RULE)
    assert start_words(verdict).startswith("warm-up rule: the temperature settled (+")
    assert warm_up_end_s(t, temp) == verdict.start_s
    [early] = warm_up_warnings(t, temp)
    assert f"the first {verdict.start_s - t[0]:.0f} s of the data are warm-up" in early
    assert "1 degC/h over 600 s" in early
    late = t >= verdict.start_s
    assert warm_up_warnings(t[late], temp[late]) == []
    never = t < 400
    [unsettled] = warm_up_warnings(t[never], temp[never])
    assert "never settles" in unsettled and "not warmed up" in unsettled
    assert "never settles" in start_words(record_settling(t[never], temp[never]))
    assert warm_up_end_s(t[never], temp[never]) == t[never][-1]
    assert "above 1 degC/h" in warm_up_label()


def test_without_temperatures_the_rule_has_no_verdict(warming):
    t, _ = warming
    assert record_settling(t, None) is None and record_settling(t[:1], np.ones(1)) is None
    assert warm_up_warnings(t, None) == ["no temperatures in the data (its datagrams or messages carry none): "
                                         "warm-up cannot be checked"]
    assert "no temperatures" in start_words(None)
    assert warm_up_end_s(t, None) == t[0]


def test_the_warm_up_warning_says_the_start_that_leaves_it_out_where_a_user_can_give_one(warming):
    """A capture's power-up can be restarted later (`calibd calibrate --start`): its warning says the
    value; the daemon has no such option, and its warning does not mention one."""
    t, temp = warming
    verdict = record_settling(t, temp)
    start = int(np.ceil(verdict.start_s))
    [hinted] = warm_up_warnings(t, temp, start_hint=True)
    assert hinted.endswith(f"(calibrate with --start {start} to leave it out)")
    assert hinted.startswith(warm_up_warnings(t, temp)[0]) and "--start" not in warm_up_warnings(t, temp)[0]
    late = t >= start
    assert warm_up_warnings(t[late], temp[late], start_hint=True) == []  # the hinted start has no warm-up left


@pytest.mark.slow
def test_calibrate_from_power_on_names_the_start_and_the_daemons_session_does_not(tmp_path, capsys):
    from dataclasses import replace

    from calibd.methods.common import session_warnings
    from calibd.cli import main

    capture = str(FIXTURES / "warmup_then_protocol_125hz.bin")
    assert main(["calibrate", capture, "--latitude", "40.59129", "--start", "0", "-o", str(tmp_path / "r.json")]) == 0
    [warning] = [line for line in capsys.readouterr().out.splitlines() if "warm-up" in line]
    start = warning.rsplit("--start ", 1)[1].split()[0]
    assert main(["calibrate", capture, "--latitude", "40.59129", "--start", start, "-o", str(tmp_path / "r.json")]) == 0
    assert "warm-up" not in capsys.readouterr().out
    session = load_session(capture, 0.0)
    daemons = replace(session, stream=replace(session.stream, power_up=None))
    assert any("--start" in w for w in session_warnings(session))
    assert not any("--start" in w for w in session_warnings(daemons)) and any("warm-up" in w for w in
                                                                                session_warnings(daemons))


def test_the_words_never_name_a_window_longer_than_the_data(warming, tmp_path):
    """A record shorter than the rule's 600 s window is judged as a whole, and said so."""
    t, temp = warming
    flat = t >= t[-1] - 445  # settled: the last 445 s
    assert start_words(record_settling(t[flat], temp[flat])).endswith("degC/h over the whole 445 s of data)")
    never = t < 400  # still warming
    words = start_words(record_settling(t[never], temp[never])) + warm_up_warnings(t[never], temp[never])[0]
    assert words.count("over the whole 400 s of data") == 2 and "600" not in words
    assert "over 600 s" in start_words(record_settling(t, temp))  # a longer record: the rule's window
    data = (FIXTURES / "warmup_then_protocol_125hz.bin").read_bytes()
    path = tmp_path / "c.bin"
    path.write_bytes(data[:66] + data[-445 * 125 * 45:])  # its configuration datagram and the last 445 s
    assert load_session(str(path), None).stream.start_by.endswith("over the whole 445 s of data)")

"""The warm-up rule (calibd.warmup): one implementation for the daemon, calibrate and the report."""

from pathlib import Path

import numpy as np
import pytest

from calibd.cli import load_session
from calibd.config import WarmupConfig
from calibd.warmup import settling

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

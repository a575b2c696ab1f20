"""The warm-up rule: where a temperature record has settled enough to calibrate on.

Biases follow temperature, so data from a sensor still warming up carry biases that are wrong
by the time they are used. The rule (`WarmupConfig`): the settled part starts at the first
window of `window_s` (the whole record when shorter) whose least-squares temperature trend is
within `max_slope_c_per_h` and which ends at least `min_time_s` after power-up. The daemon
applies it to the data so far, `calibd calibrate` and the report to a whole power-up. The
verdict's words (a session's start, its warnings, the report's label) are said here too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class WarmupConfig:
    """When the IMU counts as warmed up: biases follow temperature, so calibrating on a thermal
    ramp gives biases that are wrong by the time they are used."""

    max_slope_c_per_h: float = 1.0  # temperature trend over the window below which it is warm
    window_s: float = 600.0  # the window the trend is fitted over
    min_time_s: float = 0.0  # and at least this long since power-up


WINDOW_RANGE_S = (1.0, 86400.0)  # a window_s that makes sense: [warmup] window_s and `calibd replay --warmup-window`
WARM_UP_RULE = WarmupConfig()  # the daemon's default: calibrate starts a power-up where it is met
NOT_WARMED_UP = ("every estimate is flagged poor: the data were taken while the IMU warmed up, and biases move "
                 "with temperature (record after the warm-up)")
# A trend this slow (degC/h) is the room, not the warm-up: the joint method's error budget carries
# the biases' slope with temperature at the datasheet's figure (calibd.spec), so the estimates
# keep their sigma and only those the ramp moves by TEMPERATURE_POOR_SHARE of it are flagged
RAMP_MODELLED_C_PER_H = 2.0
TEMPERATURE_POOR_SHARE = 0.5  # of an estimate's sigma: its temperature part beyond this flags it poor


@dataclass(frozen=True)
class Settling:
    """The rule's verdict on a record. `settled`: a window passed, and `start_s` is the first such
    window's start; otherwise `start_s` is the start of the calmest window (the best part of a
    record that never settles). `trend_c_per_h` is that window's trend (None without temperatures).
    `window_s`: the seconds that trend was fitted over (0 without one), the rule's window or, when
    the record is shorter, the whole record, so the words never name more data than there are."""

    settled: bool
    start_s: float
    trend_c_per_h: float | None
    window_s: float


def settling(time_s: np.ndarray, temperature_c: np.ndarray | None, rule: WarmupConfig = WarmupConfig()) -> Settling:
    """The warm-up rule on a record (time since power-up, s; temperatures, degC, or None when the
    datagram has none: then time since power-up alone decides)."""
    if len(time_s) < 2:
        return Settling(False, float(time_s[0]) if len(time_s) else 0.0, None, 0.0)
    seconds = np.floor(time_s - time_s[0]).astype(np.int64)  # 1-s means: the trend needs no more
    count = np.bincount(seconds)
    have = np.flatnonzero(count)
    first_sample = np.searchsorted(seconds, have)  # each second's first sample
    t = (np.bincount(seconds, time_s)[have] / count[have])
    width = int(min(rule.window_s, len(t)))
    end_s = t[width - 1:]  # each window's last second
    if temperature_c is None or width < 2:
        trend = None
        calm = np.ones(len(end_s), bool)
    else:
        temp = np.bincount(seconds, temperature_c)[have] / count[have]
        trend = _window_slopes_c_per_h(t - t[0], temp, width)
        calm = np.abs(trend) <= rule.max_slope_c_per_h
    eligible = end_s >= rule.min_time_s
    passed = np.flatnonzero(calm & eligible)
    if len(passed):
        k, settled = int(passed[0]), True
    else:
        pool = np.flatnonzero(eligible) if eligible.any() else np.arange(len(end_s))
        k = int(pool[np.argmin(np.abs(trend[pool]))]) if trend is not None else int(pool[-1])
        settled = False
    if trend is None:
        window_s = 0.0
    elif width < len(t):  # windows slide: each is the rule's
        window_s = rule.window_s
    else:  # one window: the whole record
        window_s = min(rule.window_s, float(time_s[-1] - time_s[0]))
    return Settling(settled, float(time_s[first_sample[k]]), None if trend is None else float(trend[k]), window_s)


def _window_slopes_c_per_h(t: np.ndarray, temp: np.ndarray, width: int) -> np.ndarray:
    """Least-squares slope of every run of `width` consecutive points, by running sums."""
    def sums(x):
        c = np.concatenate(([0.0], np.cumsum(x)))
        return c[width:] - c[:-width]

    st, sy, stt, sty = sums(t), sums(temp), sums(t * t), sums(t * temp)
    return (width * sty - st * sy) / (width * stt - st * st) * 3600


def rule_words(rule: WarmupConfig = WARM_UP_RULE, verdict: Settling | None = None) -> str:
    """The rule as applied: over the verdict's window, the whole record when it is the shorter."""
    return f"{rule.max_slope_c_per_h:g} degC/h {_over(verdict, rule)}"


def _over(verdict: Settling | None, rule: WarmupConfig) -> str:
    if verdict is not None and verdict.window_s < rule.window_s:
        return f"over the whole {verdict.window_s:.0f} s of data"
    return f"over {rule.window_s:g} s"


def record_settling(time_s: np.ndarray, temperature_c: np.ndarray | None,
                    rule: WarmupConfig = WARM_UP_RULE) -> Settling | None:
    """The rule on a record's own temperatures; None when it has none to judge by (no
    temperatures in the datagram, or fewer than two samples)."""
    if temperature_c is None or len(time_s) < 2:
        return None
    return settling(time_s, temperature_c, rule)


def ramp_carried(verdict: Settling) -> bool:
    """Whether a power-up that never settled ramps slowly enough (RAMP_MODELLED_C_PER_H) for the
    joint method's sigma to carry it (its budget's temperature part)."""
    return verdict.trend_c_per_h is not None and abs(verdict.trend_c_per_h) <= RAMP_MODELLED_C_PER_H


def ramp_words(verdict: Settling, moved: list[str]) -> str:
    """Why a slow ramp's estimates keep their sigma, and which are flagged."""
    flagged = (f"{', '.join(moved)} flagged poor: the ramp moves them by {TEMPERATURE_POOR_SHARE:g} of their "
               "sigma or more" if moved else f"none moves by {TEMPERATURE_POOR_SHARE:g} of its sigma")
    return (f"the temperature ramps at {verdict.trend_c_per_h:+.1f} degC/h, within the {RAMP_MODELLED_C_PER_H:g} "
            "degC/h a sigma can carry: each sigma carries the biases' slope with temperature at the STIM300 "
            f"datasheet's figure (error_budget part 'temperature'); {flagged}")


def start_words(verdict: Settling | None, rule: WarmupConfig = WARM_UP_RULE) -> str:
    """Why a power-up's session starts where the rule put it (its `start_by`)."""
    if verdict is None:
        return "the first sample (no temperatures: the warm-up rule cannot be applied)"
    if verdict.trend_c_per_h is None:  # under 2 s of data: no trend to judge, time alone decided
        return "warm-up rule: too little data for a temperature trend (under 2 s), from the first sample"
    if verdict.settled:
        return f"warm-up rule: the temperature settled ({verdict.trend_c_per_h:+.2f} degC/h {_over(verdict, rule)})"
    return (f"warm-up rule: the temperature never settles, the calmest window ({verdict.trend_c_per_h:+.2f} "
            f"degC/h {_over(verdict, rule)})")


def warm_up_warnings(time_s: np.ndarray, temperature_c: np.ndarray | None,
                     rule: WarmupConfig = WARM_UP_RULE, start_hint: bool = False) -> list[str]:
    """What a record's temperatures say about its biases: not checkable, never settled, or
    settled only after its start. `start_hint`: the record is a capture's power-up (its times
    count from the power-up's first sample, as `calibd calibrate --start` does), so the warning
    says the --start that leaves the warm-up out; the daemon has no such option, and its
    sessions count from their own start, so its results do not say it."""
    verdict = record_settling(time_s, temperature_c, rule)
    if verdict is None:
        return ["no temperatures in the data (its datagrams or messages carry none): warm-up cannot be checked"]
    if not verdict.settled:
        return [f"the temperature never settles in this power-up (calmest trend {verdict.trend_c_per_h:+.1f} degC/h "
                f"from {verdict.start_s:.0f} s; warmed up means within {rule_words(rule, verdict)}): the IMU is not "
                "warmed up, biases drift with temperature"]
    early_s = verdict.start_s - time_s[0]
    if early_s > 1.0:
        hint = f" (calibrate with --start {math.ceil(verdict.start_s)} to leave it out)" if start_hint else ""
        return [f"the first {early_s:.0f} s of the data are warm-up (the temperature settles within "
                f"{rule_words(rule, verdict)} only from {verdict.start_s:.0f} s of the power-up): biases drift{hint}"]
    return []


def warm_up_end_s(time_s: np.ndarray, temperature_c: np.ndarray | None,
                  rule: WarmupConfig = WARM_UP_RULE) -> float:
    """Where the rule ends a record's warm-up: its start without temperatures, its end if it never settles."""
    if temperature_c is None:
        return float(time_s[0])
    verdict = settling(time_s, temperature_c, rule)
    return verdict.start_s if verdict.settled else float(time_s[-1])


def warm_up_label(rule: WarmupConfig = WARM_UP_RULE) -> str:
    """The report's name for the data before warm_up_end_s."""
    return f"warm-up (temperature trend above {rule.max_slope_c_per_h:g} degC/h)"

"""When a power-up has warmed up: the warm-up rule (calibd.warmup) on live data, looked at every
WARM_CHECK_EVERY_S of data time on the data since the last look's window, which is all the
daemon keeps while the sensor warms up."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..session import SessionBuilder
from ..warmup import WarmupConfig, settling

WARM_CHECK_EVERY_S = 10.0  # how often (data time) the warm-up rule is evaluated


@dataclass(frozen=True)
class Warmth:
    """A look's verdict: `start_s`, where the session starts (s since power-up; None: still
    warming up), and what to tell."""

    start_s: float | None
    detail: str


class WarmWatch:
    """The warm-up rule, applied as a power-up's data arrive."""

    def __init__(self) -> None:
        self._next_look_s = 0.0

    def look(self, data: SessionBuilder, rule: WarmupConfig) -> Warmth | None:
        """The rule's verdict on the data so far, or None between looks; data older than the
        next look's window are forgotten."""
        elapsed = data.end_s
        if elapsed < self._next_look_s:
            return None
        self._next_look_s = elapsed + WARM_CHECK_EVERY_S
        data.trim(elapsed - rule.window_s - WARM_CHECK_EVERY_S - 1.0)
        if elapsed < max(rule.window_s, rule.min_time_s):
            return Warmth(None, f"warming up: {elapsed:.0f} s since power-up")
        recent = data.arrays()
        no_temperature = np.isnan(recent["temp"]).all()
        verdict = settling(recent["time_s"], None if no_temperature else recent["temp"], rule)
        if not verdict.settled:
            return Warmth(None, f"warming up: temperature moving {verdict.trend_c_per_h:+.2f} degC/h")
        how = (f"{rule.window_s:.0f} s since power-up (no temperatures in the datagram: time since power-up only)"
               if no_temperature else f"{verdict.trend_c_per_h:+.2f} degC/h over {rule.window_s:.0f} s")
        return Warmth(verdict.start_s, f"warmed up ({how})")

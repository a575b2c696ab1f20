"""When the daemon solves a session it is collecting: as soon as the platform has stopped after
moving and the segments end on a static that completes the method's campaign, and again every
`resolve_every_s` of new data. Between solves only the gyros of each batch are looked at: the
segments are found again only once the platform has been quiet long enough to show a new static.
"""

from __future__ import annotations

import numpy as np

from .. import detect
from ..methods import Estimator


class SolveTrigger:
    """The platform's motion since the segments were last looked at, and the re-solve timer."""

    def __init__(self) -> None:
        self.next_solve_s = 0.0  # data time of the next timed solve
        self.solved_until_s = -np.inf  # data time of the last solve attempt
        self._moved = False  # the platform moved since the last look at the segments
        self._last_motion_s = -np.inf  # data time of the end of the last motion seen

    def session_started(self, now_s: float, resolve_every_s: float) -> None:
        self.next_solve_s = now_s + resolve_every_s
        self._moved = False

    def solved(self, now_s: float, resolve_every_s: float) -> None:
        """A solve was attempted on the data up to `now_s`: the timer starts again from there."""
        self.solved_until_s = now_s
        self.next_solve_s = now_s + resolve_every_s

    def timer_due(self, now_s: float) -> bool:
        return now_s >= self.next_solve_s

    def unsolved(self, now_s: float) -> bool:
        """Whether data came after the last solve attempt."""
        return now_s > self.solved_until_s

    def stopped_moving(self, t: np.ndarray, gyro_deg_s: np.ndarray, now_s: float, settings: dict,
                       rate_hz: float) -> bool:
        """Whether the platform moved since the segments were last looked at and has been quiet
        since for the settle time plus the minimum static, the least after which the detector
        shows a new static. Moving: a gyro average over the detector's smoothing window above
        its turn threshold (its floor before the tracker's first update). `t`, `gyro_deg_s`: the
        batch just stored (s, deg/s); `settings`: the segment tracker's."""
        if len(t):
            threshold = settings["turn_threshold_deg_s"] or detect.MIN_TURN_THRESHOLD_DEG_S
            k = min(len(t), max(1, round(settings["smooth_s"] * rate_hz)))
            edges = np.arange(0, len(t) - k + 1, k)  # a short remainder joins the last window
            sizes = np.diff(np.append(edges, len(t)))
            means = np.add.reduceat(gyro_deg_s, edges, axis=0) / sizes[:, None]
            moving = np.flatnonzero(np.linalg.norm(means, axis=1) > threshold)
            if len(moving):
                self._moved = True
                self._last_motion_s = float(t[edges[moving[-1]] + sizes[moving[-1]] - 1])
        quiet_s = now_s - self._last_motion_s
        return self._moved and quiet_s >= settings["settle_s"] + settings["min_static_s"]

    def campaign_done(self, segments: list[detect.Segment], method: Estimator) -> bool:
        """Once the platform has stopped: whether the segments now end on a static (it lasted the
        settle time and the minimum static; else look again next batch) and hold what the method
        needs."""
        if not segments or segments[-1].kind != "static":
            return False
        self._moved = False
        return method.missing(segments) is None

"""Find the segments of a calibration session (statics, turns) in decoded data.

Pure numpy functions: no state, no per-sample Python loops, so the same code serves a capture
file and a growing live buffer. Units at the interface: gyro in deg/s, acc in g, times in s,
angles in degrees, counter-clockwise about Up positive (docs/method.md, Rotation conventions).

How a session is cut (each step exists because the campaigns of docs/method.md need it):
- moving = |gyro vector, moving average over `smooth_s`| > threshold. The norm, not one axis,
  so a hand re-mounting the IMU is motion too. The threshold adapts to the sensor: ten times the
  noise of that average, estimated from the data (`motion_thresholds`), and never below
  0.5 deg/s, which stays far above any gyro bias plus the Earth rate (STIM300: ~0.03 deg/s). For
  the STIM300 the floor rules (its white noise averages to ~0.006 deg/s); a noisier sensor
  raises it, and so does the noise around each sample (`_local_variance`): a static on a
  vehicle with its engine running is not motion for its vibration.
- quiet stretches are split where the mean acc vector jumps (a bench re-mount, instantaneous in
  the simulator: gravity moves to another axis while the gyros see nothing; the jump threshold
  adapts to the accelerometer noise the same way, and to the local noise around each sample,
  so a static on a vibrating vehicle is not cut into pieces), trimmed by
  `settle_s` next to any motion or re-mount, and kept when at least `min_static_s` long.
- the motion between two statics is one turn when it is mostly about the vertical (the unit mean
  acc of the static before); otherwise it is handling and gives no segment.
- a turn's angle integrates the gyro, with the neighbouring statics' mean removed (bias and Earth
  rate), over everything between those statics (so the ramps' tails below the threshold count),
  projected on the turn's own axis (the direction of the integrated vector: the platform axis in
  IMU axes, which the interface tilt sets apart from gravity by ~0.5 deg).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


TURN_AXIS_SHARE = 0.9  # share of a motion's rotation about the vertical that makes it a turn (~25 deg cone)
AXES = "XYZ"
NOISE_MULTIPLE = 10.0  # thresholds sit this many noise sigmas above a quiet sensor's averaged output
MIN_TURN_THRESHOLD_DEG_S = 0.5  # above gyro bias + Earth rate of any navigation-grade gyro
MIN_REMOUNT_G = 0.05  # a re-mount moves gravity by ~1 g between axes
LOCAL_NOISE_WIDTHS = 8  # the accelerometers' local noise is measured over this many step widths
BLOCK = 1 << 16  # samples taken at once where a session-long temporary is not needed


@dataclass(frozen=True)
class Segment:
    """A static or a turn: samples [start, stop), times [start_s, end_s).

    platform_angle_deg is chi (the platform angle about the vertical, relative to the first
    static) during a static, or at the start of a turn. Turn-only fields (None for statics):
    angle_deg (signed), rate_deg_s (signed mean over the constant-rate part), cruise_start /
    cruise_stop (samples of the constant-rate part, ramps removed) and cruise_angle_deg
    (rate x duration of that part). Static-only: up, the IMU axis the gravity reaction points
    along ("+Z", "-X", ...)."""

    kind: str
    start: int
    stop: int
    start_s: float
    end_s: float
    platform_angle_deg: float
    angle_deg: float | None = None
    rate_deg_s: float | None = None
    cruise_start: int | None = None
    cruise_stop: int | None = None
    cruise_angle_deg: float | None = None
    up: str | None = None


# ---------------------------------------------------------------- helpers

def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starts and stops (exclusive) of the runs of True."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def _cumsum0(x: np.ndarray) -> np.ndarray:
    c = np.empty((len(x) + 1,) + x.shape[1:])
    c[0] = 0.0
    np.cumsum(x, axis=0, out=c[1:])
    return c


def _window_means(c: np.ndarray, start: int, stop: int, lo_offset: int, hi_offset: int) -> np.ndarray:
    """For each sample i in [start, stop), the mean over [i + lo_offset, i + hi_offset), cut to
    the data, from the cumulative sum c (0 where the window is empty): a block at a time, so
    that only the cumulative sum is as long as the session."""
    n, i = len(c) - 1, np.arange(start, stop)
    lo, hi = np.clip(i + lo_offset, 0, n), np.clip(i + hi_offset, 0, n)
    count = (hi - lo).astype(float)[:, None]
    return np.divide(c[hi] - c[lo], count, out=np.zeros((len(lo),) + c.shape[1:]), where=count > 0)


def _blocks(n: int):
    return ((lo, min(lo + BLOCK, n)) for lo in range(0, n, BLOCK))


def _moving_average(x: np.ndarray, half: int) -> np.ndarray:
    """Centred moving average over 2*half+1 samples, shrinking at the ends."""
    c, mean = _cumsum0(x), np.empty(x.shape)
    for lo, hi in _blocks(len(x)):
        mean[lo:hi] = _window_means(c, lo, hi, -half, half + 1)
    return mean


def _step_size(x: np.ndarray, width: int) -> np.ndarray:
    """|mean of the next `width` samples - mean of the previous `width`| at each sample."""
    c, size = _cumsum0(x), np.empty(len(x))
    for lo, hi in _blocks(len(x)):
        size[lo:hi] = np.linalg.norm(_window_means(c, lo, hi, 0, width) - _window_means(c, lo, hi, -width, 0), axis=1)
    size[:1] = 0.0  # nothing before the first sample: no step to see
    return size


def _weights(t: np.ndarray, dt: float) -> np.ndarray:
    """Seconds each sample stands for (midpoint rule): a lost datagram's interval is shared
    by its neighbours, so angles integrate across losses."""
    ext = np.concatenate(([t[0] - dt], t, [t[-1] + dt]))
    return (ext[2:] - ext[:-2]) / 2


def _up_name(acc_mean: np.ndarray) -> str:
    k = int(np.argmax(np.abs(acc_mean)))
    return ("+" if acc_mean[k] >= 0 else "-") + AXES[k]


def _static_pieces(moving, acc, half, settle_n, min_n, remount_g):
    """(start, stop) of the statics: quiet runs split at re-mounts, trimmed, long enough."""
    n = len(acc)
    step = _step_size(acc, 2 * half)
    local = np.sqrt(_local_variance(acc, 2 * half) * 2 / (2 * half))  # the noise of a step of two means
    jump = (step > np.maximum(remount_g, NOISE_MULTIPLE * local)) & ~moving
    cuts = []  # (a, b): [a, b) is in no static; a == b is a split point
    for a, b in zip(*_runs(jump)):
        a2, b2 = a + 2 * half, b - 2 * half  # an instantaneous step shows over +-width: undo that blur
        if a2 < b2:
            cuts.append((a2, b2))
        else:
            j = a + int(np.argmax(step[a:b]))
            cuts.append((j, j))
    cut_starts = np.array([c[0] for c in cuts], dtype=int)
    pieces = []
    for qa, qb in zip(*_runs(~moving)):
        inside = [cuts[k] for k in np.flatnonzero((cut_starts >= qa) & (cut_starts < qb))]
        bounds = [qa] + [x for c in inside for x in c] + [qb]
        for a, b in zip(bounds[::2], bounds[1::2]):
            a2 = a + settle_n if a > 0 else a
            b2 = b - settle_n if b < n else b
            if b2 - a2 >= max(min_n, 1):
                pieces.append((int(a2), int(b2)))
    return pieces


def _local_variance(x: np.ndarray, width: int) -> np.ndarray:
    """Per sample, the white noise variance of the samples around it, summed over the axes (the
    mean square of their first differences over LOCAL_NOISE_WIDTHS windows of `width`): a static
    on a vibrating vehicle averages and steps by its own noise, far above the session's quiet
    noise, and is neither motion nor a re-mount for that. A turn (its rate changes slowly from
    sample to sample) and a re-mount (gravity moving ~1 g) stand well above it."""
    variance = np.empty(len(x))
    for lo, hi in _blocks(len(x)):
        before = x[lo - 1:hi - 1] if lo else np.concatenate((x[:1], x[:hi - 1]))  # the first has no step
        variance[lo:hi] = np.sum((x[lo:hi] - before) ** 2, axis=1) / 2
    return _moving_average(variance[:, None], LOCAL_NOISE_WIDTHS * width // 2)[:, 0]


# ---------------------------------------------------------------- segments

def _white_sigma(x: np.ndarray) -> np.ndarray:
    """Per-column white-noise sigma per sample, robustly: the median absolute deviation of the
    first differences, which turns at constant rate, slow drifts and biases do not inflate."""
    d = np.diff(x, axis=0)
    if len(d) < 2:
        return np.zeros(x.shape[1:])
    d -= np.median(d, axis=0, overwrite_input=True)  # a median reorders, which the next one ignores
    mad = np.median(np.abs(d, out=d), axis=0, overwrite_input=True)
    return 1.4826 * mad / np.sqrt(2.0)


def motion_thresholds(gyro: np.ndarray, acc: np.ndarray, rate_hz: float, smooth_s: float = 0.2) -> tuple[float, float]:
    """(turn threshold in deg/s, re-mount threshold in g) for this sensor and this data: NOISE_MULTIPLE
    times the noise of the averages they are compared with, at least the floors."""
    half = max(int(round(smooth_s * rate_hz / 2)), 1)
    gyro_noise = np.linalg.norm(_white_sigma(np.asarray(gyro, float))) / np.sqrt(2 * half + 1)
    acc_noise = np.linalg.norm(_white_sigma(np.asarray(acc, float))) * np.sqrt(2.0 / (2 * half))  # step of two means
    return (max(MIN_TURN_THRESHOLD_DEG_S, NOISE_MULTIPLE * float(gyro_noise)),
            max(MIN_REMOUNT_G, NOISE_MULTIPLE * float(acc_noise)))


def find_segments(gyro: np.ndarray, acc: np.ndarray, rate_hz: float, time_s: np.ndarray | None = None, *,
                  turn_threshold_deg_s: float | None = None, min_static_s: float = 5.0, settle_s: float = 1.0,
                  cruise_tolerance: float = 0.01, smooth_s: float = 0.2,
                  remount_g: float | None = None) -> list[Segment]:
    """Statics and turns of a session, in time order.

    gyro (N,3) deg/s and acc (N,3) g, finite; time_s as from `stim300.clock.counter_times` (default: no losses).
    A turn is motion above `turn_threshold_deg_s` (gyro averaged over `smooth_s`) mostly about
    the vertical; statics lose `settle_s` at each end next to motion or a re-mount (an acc step
    larger than `remount_g` between quiet stretches) and must keep `min_static_s`. A turn's
    constant-rate part is the longest run of samples whose smoothed rate is within
    `cruise_tolerance` (relative) of the median rate of the turn's central half. Thresholds left
    None come from the data's own noise (`motion_thresholds`).
    """
    gyro = np.asarray(gyro, dtype=np.float64)
    acc = np.asarray(acc, dtype=np.float64)
    n = len(gyro)
    if n == 0:
        return []
    if not (np.isfinite(gyro).all() and np.isfinite(acc).all()):
        raise ValueError("find_segments needs finite gyro and acc samples (a datagram without accelerometers "
                         "cannot show gravity)")
    if turn_threshold_deg_s is None or remount_g is None:
        turn, remount = motion_thresholds(gyro, acc, rate_hz, smooth_s)
        turn_threshold_deg_s = turn if turn_threshold_deg_s is None else turn_threshold_deg_s
        remount_g = remount if remount_g is None else remount_g
    dt = 1.0 / rate_hz
    t = np.arange(n) * dt if time_s is None else np.asarray(time_s, dtype=np.float64)
    w = _weights(t, dt)
    half = max(int(round(smooth_s * rate_hz / 2)), 1)
    gyro_s = _moving_average(gyro, half)
    local = np.sqrt(_local_variance(gyro, 2 * half + 1) / (2 * half + 1))  # the noise of the average
    moving = np.linalg.norm(gyro_s, axis=1) > np.maximum(turn_threshold_deg_s, NOISE_MULTIPLE * local)
    settle_n, min_n = int(round(settle_s * rate_hz)), int(round(min_static_s * rate_hz))
    pieces = _static_pieces(moving, acc, half, settle_n, min_n, remount_g)

    def span(a, b):
        return float(t[a]), float(t[b - 1] + dt)

    statics = [{"start": a, "stop": b, "gyro": gyro[a:b].mean(0), "acc": acc[a:b].mean(0)} for a, b in pieces]
    gaps = zip([0] + [s["stop"] for s in statics], [s["start"] for s in statics] + [n])
    out, chi = [], 0.0  # chi: platform angle, from the start of the data
    for k, (a, b) in enumerate(gaps):
        prev = statics[k - 1] if k > 0 else None
        nxt = statics[k] if k < len(statics) else None
        turn = _turn(gyro, gyro_s, acc, moving, w, a, b, prev, nxt, cruise_tolerance)
        if turn is not None:
            start, stop, angle, rate, cs, ce = turn
            cruise_s = span(cs, ce)
            out.append(Segment("turn", start, stop, *span(start, stop), chi, angle_deg=angle, rate_deg_s=rate,
                               cruise_start=cs, cruise_stop=ce,
                               cruise_angle_deg=rate * (cruise_s[1] - cruise_s[0])))
            chi += angle
        if nxt is not None:
            out.append(Segment("static", nxt["start"], nxt["stop"], *span(nxt["start"], nxt["stop"]), chi,
                               up=_up_name(nxt["acc"])))
    origin = next((s.platform_angle_deg for s in out if s.kind == "static"), 0.0)  # relative to the first static
    return [replace(s, platform_angle_deg=s.platform_angle_deg - origin) for s in out]


class SegmentTracker:
    """The segments of a growing session without re-scanning all of it at every update.

    Everything before the second-to-last static is final: a static ends where motion starts, and
    a turn depends only on the statics on either side of it. So each update runs `find_segments`
    from that static on, and shifts what it finds into the session's samples and platform angle.
    The thresholds are set from the data of the first update (the sensor's noise does not change
    within a session), so every pass cuts alike.
    """

    def __init__(self, rate_hz: float, turn_threshold_deg_s: float | None = None, remount_g: float | None = None,
                 **options):
        """`options` as find_segments'; thresholds left None follow the first update's noise."""
        self.rate_hz, self.options = rate_hz, options
        self.final: list[Segment] = []
        self._tail_start = 0  # first sample of the part still re-scanned
        self._tail_chi = 0.0  # platform angle there, relative to the session's first static
        self._given = {key: value for key, value in (("turn_threshold_deg_s", turn_threshold_deg_s),
                                                     ("remount_g", remount_g)) if value is not None}
        self._thresholds: dict | None = None

    @property
    def settings(self) -> dict:
        """The find_segments options the tracker cuts with: the defaults, those given, and the
        thresholds once set (None before the first update when they follow the noise), for a
        caller that watches for motion between updates."""
        return find_segments.__kwdefaults__ | self.options | self._given | (self._thresholds or {})

    def update(self, gyro: np.ndarray, acc: np.ndarray, time_s: np.ndarray | None = None) -> list[Segment]:
        """All segments so far. gyro (N,3) deg/s, acc (N,3) g, time_s: the whole session, which
        only grows (earlier samples never change)."""
        n = len(gyro)
        if n == 0:
            return list(self.final)
        t = np.arange(n) / self.rate_hz if time_s is None else np.asarray(time_s, dtype=np.float64)
        if self._thresholds is None:
            turn, remount = motion_thresholds(gyro, acc, self.rate_hz, self.options.get("smooth_s", 0.2))
            self._thresholds = {"turn_threshold_deg_s": turn, "remount_g": remount} | self._given
        a = self._tail_start
        tail = find_segments(gyro[a:], acc[a:], self.rate_hz, t[a:], **self._thresholds, **self.options)
        shifted = [_shifted(s, a, self._tail_chi) for s in tail]
        segments = self.final + shifted
        statics = [s for s in segments if s.kind == "static"]
        if len(statics) >= 2 and statics[-2].start > self._tail_start:
            keep = statics[-2]
            self.final = [s for s in segments if s.start < keep.start]
            self._tail_start, self._tail_chi = keep.start, keep.platform_angle_deg
        return segments


def _shifted(s: Segment, samples: int, chi_deg: float) -> Segment:
    def move(i):
        return None if i is None else i + samples
    return replace(s, start=s.start + samples, stop=s.stop + samples, cruise_start=move(s.cruise_start),
                   cruise_stop=move(s.cruise_stop), platform_angle_deg=s.platform_angle_deg + chi_deg)


def _turn(gyro, gyro_s, acc, moving, w, a, b, prev, nxt, tolerance):
    """The turn between two statics (samples [a, b) between them; either may be None at the
    session's ends) as (start, stop, angle, rate, cruise_start, cruise_stop), or None when
    nothing moved there (a re-mount, a dropped short static) or the motion was handling."""
    moved = np.flatnonzero(moving[a:b])
    if not len(moved):
        return None
    start, stop = a + int(moved[0]), a + int(moved[-1]) + 1
    ref = prev or nxt  # the vertical from the static before (after, at the session's start)
    gravity = ref["acc"] if ref else acc.mean(0)
    up = gravity / np.linalg.norm(gravity)
    near = [s for s in (prev, nxt) if s is not None and _up_name(s["acc"]) == _up_name(gravity)]
    level = np.mean([s["gyro"] for s in near], axis=0) if near else np.zeros(3)  # no static: bias kept
    rel_s = gyro_s[start:stop] - level
    if np.abs(rel_s @ up).sum() < TURN_AXIS_SHARE * np.linalg.norm(rel_s, axis=1).sum():
        return None  # handling: not a rotation about the vertical
    rel = gyro[a:b] - level  # everything between the statics: the ramps' tails below the threshold count
    vector = (rel * w[a:b, None]).sum(0)
    axis = vector / np.linalg.norm(vector) if np.linalg.norm(vector) > 1.0 else up
    axis = axis if axis @ up >= 0 else -axis  # counter-clockwise about Up positive
    rate = rel @ axis
    angle = float((rate * w[a:b]).sum())
    cs, ce = _cruise(rel_s @ axis, tolerance)
    cs, ce = start + cs, start + ce
    mean_rate = float((rate[cs - a:ce - a] * w[cs:ce]).sum() / w[cs:ce].sum())
    return start, stop, angle, mean_rate, cs, ce


def _cruise(rate_s: np.ndarray, tolerance: float) -> tuple[int, int]:
    """Longest run within `tolerance` (relative) of the median of the central half."""
    m = len(rate_s)
    centre = rate_s[m // 4: m - m // 4] if m >= 4 else rate_s
    peak = float(np.median(centre))
    starts, stops = _runs(np.abs(rate_s - peak) <= tolerance * abs(peak))
    if not len(starts):
        return m // 4, max(m - m // 4, m // 4 + 1)
    k = int(np.argmax(stops - starts))
    return int(starts[k]), int(stops[k])


# ---------------------------------------------------------------- the campaign's segments

def level_static(segments: list[Segment]) -> Segment:
    """The first static: the home position (platform angle 0) of the real-case campaign."""
    for s in segments:
        if s.kind == "static":
            return s
    raise ValueError("no static segment: the session needs a level static first")


def heading_deg(platform_angle_deg: float) -> float:
    """The platform's heading: its angle modulo 360 deg, in [0, 360) deg to 0.1 deg (so -0.02 deg
    is 0, not 360). The one place headings are compared or printed: 990 deg after turns is the
    270 deg heading."""
    return round(platform_angle_deg % 360.0, 1) % 360.0


def index_heading(platform_angle_deg: float, tolerance_deg: float = 5.0) -> int | None:
    """The index heading (0..3: quarter turns, 0 deg, 90 deg, ...) within `tolerance_deg` of the
    platform's heading (`heading_deg`), or None between them."""
    heading = heading_deg(platform_angle_deg)
    quarter = round(heading / 90.0)
    return quarter % 4 if abs(heading - 90.0 * quarter) <= tolerance_deg else None


def index_positions(segments: list[Segment], tolerance_deg: float = 5.0) -> list[Segment]:
    """The four index positions (thesis eqs. 6.8-6.11): after the level static, the first static
    at each of the four index headings (`index_heading`), in time order. Averaging over the four
    cancels the tilt terms."""
    level = level_static(segments)
    chosen: dict[int, Segment] = {}
    for s in segments:
        if s.kind != "static" or s.start <= level.start:
            continue
        quarter = index_heading(s.platform_angle_deg, tolerance_deg)
        if quarter is not None:
            chosen.setdefault(quarter, s)
        if len(chosen) == 4:
            break
    if len(chosen) < 4:
        missing = [f"{90 * q}" for q in range(4) if q not in chosen]
        seen = ", ".join(f"{heading_deg(s.platform_angle_deg):g}" for s in segments
                         if s.kind == "static" and s.start > level.start)
        raise ValueError(f"need statics at four platform headings 90 deg apart after the level static; "
                         f"none at {', '.join(missing)} deg (mod 360); statics after it seen at headings "
                         f"[{seen}] deg")
    return sorted(chosen.values(), key=lambda s: s.start)


FULL_TURN_MIN_DEG = 350.0  # a turn of at least this total angle, ramps included, is a full turn


def full_turns(segments: list[Segment], min_angle_deg: float = FULL_TURN_MIN_DEG) -> list[Segment]:
    """Turns of at least `min_angle_deg` in total (ramps included), in time order.

    Judged on the whole angle, as a platform is commanded: a 360 deg turn at 27.93 deg/s with
    30 deg/s^2 ramps keeps its constant rate for only ~334 deg, and the thesis used exactly that
    part of exactly such a turn. The gyro gives the angle within a fraction of a degree, so the
    10 deg below 360 only admit a platform stopping short of its mark; longer turns (390, 720
    deg) are full turns too. Whether the constant-rate part covers a whole period is the
    consumer's question (calibd.methods.common.one_period)."""
    return [s for s in segments if s.kind == "turn" and abs(s.angle_deg) >= min_angle_deg]


INDEX_TOLERANCE_DEG = 5.0  # an index turn is this close to +-90 deg, an index heading to a multiple of 90 deg


def segment_roles(segments: list[Segment]) -> list[str]:
    """The campaign role of each segment: static, index turn (about 90 deg), full turn (at least
    350 deg, see `full_turns`), other turn."""
    full = {id(s) for s in full_turns(segments)}
    roles = []
    for s in segments:
        if s.kind == "static":
            roles.append("static")
        elif id(s) in full:
            roles.append("full turn")
        elif abs(abs(s.angle_deg) - 90.0) <= INDEX_TOLERANCE_DEG:
            roles.append("index turn")
        else:
            roles.append("other turn")
    return roles


def index_headings(segments: list[Segment]) -> set[int]:
    """The index headings (0..3, quarter turns of the platform) the statics after the level static
    cover: the headings `index_positions` finds statics at."""
    statics = [s for s in segments if s.kind == "static"]
    return {q for s in statics[1:] if (q := index_heading(s.platform_angle_deg, INDEX_TOLERANCE_DEG)) is not None}


@dataclass(frozen=True)
class Progress:
    """How far a session is through a method's campaign, counted once from one list of segments.
    The daemon's STATE `progress` and its status detail, `calibd watch`, `calibd status`, and the
    refusals of `calibd calibrate` and `calibd report` all show this record, so its counts, its
    headings and what it says is missing cannot disagree."""

    statics: int
    index_headings: int  # of the four index headings, how many the statics after the level static cover
    index_turns: int  # turns of about 90 deg
    full_turns: int  # turns of at least FULL_TURN_MIN_DEG, ramps included
    other_turns: int
    missing: str | None  # what the method still lacks; None: its campaign is complete

    @classmethod
    def of(cls, segments: list[Segment], missing: str | None) -> Progress:
        """The record of `segments`, with what the method says it lacks in them."""
        roles = segment_roles(segments)
        return cls(roles.count("static"), len(index_headings(segments)), roles.count("index turn"),
                   roles.count("full turn"), roles.count("other turn"), missing)

    @property
    def complete(self) -> bool:
        return self.missing is None

    def found(self) -> str:
        """The segments in the campaign's words: "3 statics at 2/4 index headings, 2 index turns, ..."."""
        def count(n: int, role: str) -> str:
            return f"{n} {role}" + ("" if n == 1 else "s")
        return (f"{count(self.statics, 'static')} at {self.index_headings}/4 index headings, "
                f"{count(self.index_turns, 'index turn')}, {count(self.full_turns, 'full turn')}, "
                f"{count(self.other_turns, 'other turn')}")

    def words(self) -> str:
        """What was found and what the campaign waits for, or that it is complete."""
        return f"{self.found()}; " + ("campaign complete" if self.complete else f"waiting for: {self.missing}")

    def fields(self) -> dict:
        """The flat fields of STATE's `progress` (docs/protocol.md): the counts and `missing`
        (null once complete)."""
        return {"statics": self.statics, "index_headings": self.index_headings, "index_turns": self.index_turns,
                "full_turns": self.full_turns, "other_turns": self.other_turns, "missing": self.missing}


def campaign_progress(segments: list[Segment]) -> str:
    """What a session has so far, in the campaign's words (`Progress.found`), for a refusal that
    says itself what is lacking."""
    return Progress.of(segments, None).found()

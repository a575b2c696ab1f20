"""A session's segments, and the one record of a segment that results and logs carry."""

from __future__ import annotations

import numpy as np

from . import detect
from .frames import STANDARD_GRAVITY
from .session import Session
from .units import DEG


def session_segments(session: Session) -> list[detect.Segment]:
    """The statics and turns of a whole session (the daemon tracks them incrementally instead)."""
    return detect.find_segments(_in_unit(session.gyro, DEG), _in_unit(session.acc, STANDARD_GRAVITY), session.rate_hz,
                                session.time_s)


def _in_unit(values, unit: float) -> np.ndarray:
    """`values` / `unit` in float64 (stored float32 taken to float64 first), one array made."""
    out = np.array(values, dtype=np.float64)
    out /= unit
    return out


def segment_record(seg: detect.Segment, role: str | None = None) -> dict:
    """A segment in the session's time (s) and platform angle (deg): a turn's angle and rate, a
    static's up axis; `role`, what a method used it for."""
    record = {"kind": seg.kind} | ({} if role is None else {"role": role}) | {
        "start_s": round(seg.start_s, 3), "end_s": round(seg.end_s, 3),
        "platform_angle_deg": round(seg.platform_angle_deg, 3)}
    if seg.kind == "turn":
        record |= {"angle_deg": round(seg.angle_deg, 3), "rate_deg_s": round(seg.rate_deg_s, 4)}
    elif seg.up:
        record["up"] = seg.up
    return record

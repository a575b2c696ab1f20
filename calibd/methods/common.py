"""What the methods' solves share: the session's own warnings (faults, hidden gaps, warm-up, no
inclinometers), the inclinometers the thesis's chains need, a static's mean, the window of a full
turn that averages the Earth rate out, and the rule that judges a campaign once the platform stops."""

from __future__ import annotations

import numpy as np

from stim300.clock import CYCLE_S

from .. import detect
from ..errors import CalibrationError
from ..estimators import thesis
from ..frames import Site
from ..session import Session
from ..units import DEG
from ..warmup import warm_up_warnings

YAW_SIGMA_POOR_DEG = 5.0  # a yaw with a larger 1-sigma is flagged, not presented as usable


def judged_once_stopped(segments: list[detect.Segment], lacking) -> str | None:
    """What `lacking(segments) -> str` ("" when nothing) says a campaign lacks, None once complete.
    Complete is judged on the segments up to the last static (a turn under way after a complete
    campaign leaves it complete); what is lacking on all of them, so a turn under way is the turn
    the campaign waits for."""
    last = max((k for k, s in enumerate(segments) if s.kind == "static"), default=-1)
    if not lacking(segments[:last + 1]):
        return None
    return lacking(segments) or None


def session_warnings(session: Session) -> list[str]:
    """What is wrong with the data itself: faults the sensor flagged, gaps the time base had to
    be corrected for, a warm-up not over."""
    flagged = session.stream.flagged_datagrams
    faults = [f"{flagged} datagrams carry fault flags ({', '.join(session.stream.fault_flags)}): their samples "
              "are in the fit; an overload or channel error biases the statics they fall in"] if flagged else []
    hidden = session.stream.hidden_gaps
    if hidden:
        faults.append(f"time base corrected: the host clock shows {session.stream.hidden_gap_s:.3f} s of data "
                      f"lost in {hidden} gap{'s' if hidden > 1 else ''} the datagram counter could not see (whole "
                      f"{CYCLE_S:.3f} s counter cycles); that time was added")
    if session.incl is None:
        faults.append(NO_INCLINOMETERS)
    from_capture = session.stream.power_up is not None  # calibrate --start can move it; the daemon cannot
    return faults + warm_up_warnings(session.time_s, session.temperature_c, start_hint=from_capture)



THESIS_DOC = "docs/thesis-estimators.md"  # where a user reads what the thesis method's warnings mean
NO_INCLINOMETERS = ("the unit has no inclinometers: pitch, roll and the accelerometer biases come from the "
                    "accelerometers alone, and no inclinometer bias is estimated")


def needs_inclinometers(session: Session, method: str) -> None:
    """The thesis's chains take pitch and roll, and their own biases, from the inclinometers."""
    if session.incl is None:
        raise CalibrationError(f"method {method} needs inclinometers, and the unit has none (its datagrams carry "
                               "gyros and accelerometers only): use the joint method")



def one_period(session: Session, turn: detect.Segment) -> tuple[slice, float]:
    """The samples eq. 6.31 averages over and the platform angle they cover (deg): the first whole
    revolution of the turn's constant-rate part, timed by the sample clock (a lost datagram
    does not lengthen it); the whole constant-rate part when it is shorter, as for a 360 deg turn
    with ramps (the thesis's own case)."""
    covered_deg = abs(turn.cruise_angle_deg)
    if covered_deg < 360.0:
        return slice(turn.cruise_start, turn.cruise_stop), covered_deg
    t = session.time_s
    end_s = t[turn.cruise_start] + 360.0 / abs(turn.rate_deg_s) - 0.5 / session.rate_hz
    return slice(turn.cruise_start, int(np.searchsorted(t, end_s))), 360.0


def partial_period(covered_deg: float, site: Site) -> tuple[float, str]:
    """(bound on the unaveraged horizontal Earth rate, rad/s; the start of the warning that says
    so) for a window covering `covered_deg` of platform angle; (0, "") for a whole revolution."""
    if covered_deg >= 360.0:
        return 0.0, ""
    bound = thesis.unaveraged_earth_rate(covered_deg * DEG, site)
    return bound, (f"the full turn's constant-rate part covers {covered_deg:.0f} deg, not a whole revolution: the "
                   f"horizontal Earth rate does not average out of the turn's mean gyro; at "
                   f"{site.latitude_deg:.2f} deg latitude the rest is up to {bound / DEG * 3600:.2f} deg/h")


def static_mean(values: np.ndarray, seg: detect.Segment) -> np.ndarray:
    return values[seg.start:seg.stop].mean(axis=0, dtype=np.float64)  # a capture's session stores float32

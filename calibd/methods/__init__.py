"""The calibration methods, one module each: what its campaign needs (`missing`, in the words the
daemon's progress shows; the method's solve refuses exactly then), its options, and its solve
(the maths beside it in calibd.estimators). `calibd calibrate`, `calibd report`, the
configuration and the daemon find methods here by name. Adding a method is one module with a
`METHOD` and one line in ESTIMATORS (docs/architecture.md, How to add a method)."""

from __future__ import annotations

from .. import detect
from ..estimators.joint import JointOptions
from . import bench, joint, thesis
from .base import Estimator, OptionError, ProtocolIncomplete, Setting
from .thesis import ThesisOptions

ESTIMATORS: dict[str, Estimator] = {m.name: m for m in (joint.METHOD, thesis.METHOD, bench.METHOD)}
DAEMON_METHODS = ("joint", "thesis")  # one mounting, a campaign the daemon sees complete as it happens

__all__ = ["ESTIMATORS", "DAEMON_METHODS", "Estimator", "OptionError", "ProtocolIncomplete", "Setting",
           "JointOptions", "ThesisOptions", "estimator", "progress"]


def estimator(name: str) -> Estimator:
    """The method called `name`; KeyError naming the known ones otherwise."""
    try:
        return ESTIMATORS[name]
    except KeyError:
        raise KeyError(f"no method {name!r} (known: {', '.join(ESTIMATORS)})") from None


def progress(method: str, segments: list[detect.Segment]) -> detect.Progress:
    """The one progress record of a session's segments through method `method`'s campaign: what
    the daemon's state and `calibd watch` show, and what `calibd report` says of the thesis method."""
    return detect.Progress.of(segments, estimator(method).missing(segments))

"""The calibration methods, one module each: what its campaign needs (`missing`, in the words the
daemon's progress shows; the method's solve refuses exactly then), its options, and its solve
(the maths beside it in calibd.estimators). `calibd calibrate`, `calibd report`, the
configuration and the daemon find methods here by name. Adding a method is one module with a
`METHOD` and one line in MODULES (docs/architecture.md, How to add a method).

A method's module is imported when the method is first asked for (`estimator`, ESTIMATORS):
the command line builds its choices from the names without them (docs/architecture.md, Start-up)."""

from __future__ import annotations

import importlib
from functools import cache
from typing import TYPE_CHECKING

from .base import CampaignIncomplete, Estimator, OptionError, Setting

if TYPE_CHECKING:
    from .. import detect

MODULES = {"joint": "joint", "thesis": "thesis", "thesis-bench": "bench"}  # method name -> its module here
DAEMON_METHODS = ("joint", "thesis")  # one mounting, a campaign the daemon sees complete as it happens
_OPTIONS = {"JointOptions": "..estimators.joint", "ThesisOptions": ".thesis"}  # the option types' homes

__all__ = ["MODULES", "ESTIMATORS", "DAEMON_METHODS", "Estimator", "OptionError", "CampaignIncomplete", "Setting",
           "JointOptions", "ThesisOptions", "estimator", "progress"]


@cache
def _registry() -> dict[str, Estimator]:
    """Every method by name (`ESTIMATORS`), its module imported."""
    return {name: importlib.import_module(f".{module}", __name__).METHOD for name, module in MODULES.items()}


def __getattr__(name: str):
    if name == "ESTIMATORS":
        return _registry()
    if name in _OPTIONS:
        return getattr(importlib.import_module(_OPTIONS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def estimator(name: str) -> Estimator:
    """The method called `name`; KeyError naming the known ones otherwise."""
    try:
        return _registry()[name]
    except KeyError:
        raise KeyError(f"no method {name!r} (known: {', '.join(MODULES)})") from None


def progress(method: str, segments: list[detect.Segment]) -> detect.Progress:
    """The one progress record of a session's segments through method `method`'s campaign: what
    the daemon's state and `calibd watch` show, and what `calibd report` says of the thesis method."""
    from .. import detect  # here: the command line builds its choices from this package without it

    return detect.Progress.of(segments, estimator(method).missing(segments))

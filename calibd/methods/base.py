"""What a calibration method is at the seam: the `Estimator` every method module provides, the
`Setting`s it takes from a configuration file, and its two refusals (`OptionError` for options
that do not go together, `CampaignIncomplete` for data its campaign does not hold)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from ..errors import CalibdError, CalibrationError

if TYPE_CHECKING:
    from .. import detect


# the joint method's index settings (an indexing table's step, how exactly a static sits at its
# stop: deg), here so that the command line offers them without loading the method
INDEX_STEP_DEG = (1.0, 360.0)
INDEX_SIGMA_DEG = (0.0, 1.0)
DEFAULT_INDEX_SIGMA_DEG = 0.01
REMOUNT_SIGMA_DEG = (0.0, 5.0)  # a second mounting's turn about 180 deg, 1-sigma
DEFAULT_REMOUNT_SIGMA_DEG = 0.1  # a fixture with locating pins


class OptionError(CalibdError):
    """Settings a method cannot take together: `key` names the one at fault, `reason` says why."""

    def __init__(self, key: str, reason: str):
        super().__init__(f"{key}: {reason}")
        self.key, self.reason = key, reason


class CampaignIncomplete(CalibrationError):
    """The session lacks segments a method needs: why (`reason`) and what it has (`found`)."""

    def __init__(self, reason: str, found: str):
        super().__init__(f"{reason}; found {found}")
        self.reason, self.found = reason, found


def refusal(campaign: str, lacking: str, segments: list[detect.Segment], hint: str = "") -> CampaignIncomplete:
    """The refusal of a method whose campaign (`campaign`, in words) the segments do not hold:
    what it lacks, in the words its `missing` gives the daemon's progress, and what was found."""
    from .. import detect  # here: the command line imports this package for the methods' names

    found = detect.campaign_progress(segments)
    return CampaignIncomplete(f"not the {campaign}: it lacks {lacking}", f"{found}; {hint}" if hint else found)


@dataclass(frozen=True)
class Setting:
    """One option a method takes from a configuration file: its kind, and the range it must lie in
    (`check`) said in words (`expect`)."""

    kind: type
    check: Callable[[Any], bool] | None = None
    expect: str = ""


class Estimator(Protocol):
    name: str
    settings: Mapping[str, Setting]  # the options a configuration file may set for this method

    def options(self, settings: Mapping[str, Any]) -> Any:
        """This method's options from named settings (a MethodConfig's fields, the command line's);
        settings of other methods are ignored. OptionError when its own do not go together."""

    def missing(self, segments: list[detect.Segment]) -> str | None:
        """What the campaign still lacks in these segments, in words; None when they hold all it
        needs. The one judge: the method's solve refuses exactly when this is not None."""

    def solve(self, session, site, segments: list[detect.Segment] | None, options):
        """The CalibrationResult of a session (`segments`: its segments, None: found here);
        CalibrationError when the data cannot give it."""

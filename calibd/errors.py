"""The root of calibd's own errors.

Every error calibd raises about its input (a capture, a configuration, a result, a scenario, a
campaign the data lack) derives from `CalibdError`, so the CLI and the daemon tell them apart
from faults of the code: a ValueError from numpy or a bug is not one of them.
"""


class CalibdError(Exception):
    """Something wrong with what calibd was given, said in one line."""


class SiteError(CalibdError):
    """A site value out of its range (calibd.frames.SITE_RANGES): `field` names it, `reason`
    says why in words every way in (option, configuration, scenario) repeats."""

    def __init__(self, field: str, reason: str):
        super().__init__(f"site {field}: {reason}")
        self.field, self.reason = field, reason


class CalibrationError(CalibdError):
    """The data cannot give this calibration (missing segments, wrong campaign); one line."""

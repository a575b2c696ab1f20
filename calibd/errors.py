"""The root of calibd's own errors.

Every error calibd raises about its input (a capture, a configuration, a result, a scenario, a
protocol the data lack) derives from `CalibdError`, so the CLI and the daemon tell them apart
from faults of the code: a ValueError from numpy or a bug is not one of them.
"""


class CalibdError(Exception):
    """Something wrong with what calibd was given, said in one line."""


class CalibrationError(CalibdError):
    """The data cannot give this calibration (missing segments, wrong protocol); one line."""

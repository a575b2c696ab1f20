"""calibd: calibrate a STIM300 IMU on a rotary platform, from a capture or live.

A capture's bytes `decode_sessions` to `CaptureSessions`; `power_up_session` makes a `Session` of one power-up
(from where its warm-up ends); `estimator(name)` is a method of the registry, whose `solve`
gives a `CalibrationResult` of `Estimate`s (`calibrate_capture` picks the power-up). The site
is a `Site`; results are written and read with `write_result` / `load_result`. Every error
raised about the input is a `CalibdError`. Plotting (calibd.report) is not imported here.
"""

from .calibrate import calibrate_capture
from .config import ConfigError, DaemonConfig, load_config
from .errors import CalibdError, CalibrationError, SiteError
from .frames import Site, normal_gravity
from .methods import ESTIMATORS, Estimator, JointOptions, OptionError, ProtocolIncomplete, ThesisOptions, estimator
from .results import CalibrationResult, Estimate, ResultError, SchemaError, load_result, write_result
from .scenario import Scenario, ScenarioError, load_scenario
from .session import CaptureSessions, Session, SessionBuilder, decode_sessions, power_up_session
from .warmup import WarmupConfig

__all__ = [
    "decode_sessions", "CaptureSessions", "Session", "SessionBuilder", "power_up_session", "WarmupConfig",
    "estimator", "ESTIMATORS", "Estimator", "JointOptions", "ThesisOptions", "calibrate_capture",
    "CalibrationResult", "Estimate", "load_result", "write_result",
    "Site", "normal_gravity", "DaemonConfig", "load_config", "Scenario", "load_scenario",
    "CalibdError", "CalibrationError", "ProtocolIncomplete", "SiteError", "OptionError", "ConfigError",
    "ScenarioError", "ResultError", "SchemaError",
]

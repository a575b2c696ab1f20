"""calibd: calibrate a STIM300 IMU on a rotary platform, from a capture or live.

A capture's bytes `decode_sessions` to `CaptureSessions`; `power_up_session` makes a `Session` of one power-up
(from where its warm-up ends); `estimator(name)` is a method of the registry, whose `solve`
gives a `CalibrationResult` of `Estimate`s (`calibrate_capture` picks the power-up). The site
is a `Site`; results are written and read with `write_result` / `load_result`. Every error
raised about the input is a `CalibdError`. Plotting (calibd.report) is not imported here.

The names are imported when first used (PEP 562), not with the package: `import calibd` loads
none of calibd's modules, so neither the methods nor scipy (docs/architecture.md, Start-up).
"""

from stim300.lazy import lazy_exports

_HOMES = {  # public name -> the module of calibd that defines it
    "decode_sessions": "session", "CaptureSessions": "session", "Session": "session", "SessionBuilder": "session",
    "power_up_session": "session", "WarmupConfig": "warmup",
    "estimator": "methods", "ESTIMATORS": "methods", "Estimator": "methods", "JointOptions": "methods",
    "ThesisOptions": "methods", "calibrate_capture": "calibrate",
    "CalibrationResult": "results", "Estimate": "results", "load_result": "results", "write_result": "results",
    "Site": "frames", "normal_gravity": "frames", "DaemonConfig": "config", "load_config": "config",
    "Scenario": "scenario", "load_scenario": "scenario",
    "CalibdError": "errors", "CalibrationError": "errors", "CampaignIncomplete": "methods", "SiteError": "errors",
    "OptionError": "methods", "ConfigError": "config", "ScenarioError": "scenario", "ResultError": "results",
    "SchemaError": "documents",
}

__all__ = list(_HOMES)

__getattr__ = lazy_exports(__name__, _HOMES)

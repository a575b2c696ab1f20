"""The calibration methods behind one seam: an `Estimator` says what a session's segments still
lack for its protocol and solves a session into a CalibrationResult. `calibd calibrate`, `calibd
report` and the daemon find methods here by name; adding a method is one module and one line in
ESTIMATORS.

The entries wrap the method functions of calibd.calibrate (which build on the pure estimator
mathematics of calibd.estimators)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from . import detect
from .errors import CalibdError
from .calibrate import bench_lacking, joint_real_case, thesis_bench, thesis_real_case
from .estimators.joint import JointOptions


class OptionError(CalibdError):
    """Settings a method cannot take together: `key` names the one at fault, `reason` says why."""

    def __init__(self, key: str, reason: str):
        super().__init__(f"{key}: {reason}")
        self.key, self.reason = key, reason


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
        """What the protocol still lacks in these segments; None when they hold all it needs."""

    def solve(self, session, site, segments: list[detect.Segment] | None, options):
        """The CalibrationResult of a session (`segments`: its segments, None: found here);
        CalibrationError when the data cannot give it."""


@dataclass(frozen=True)
class ThesisOptions:
    """The thesis real case: nominal with the interface tilt given, else linear."""

    alpha_beta_deg: tuple[float, float] | None = None  # a-priori interface tilt alpha, beta (deg)
    platform_rate_deg_s: float | None = None  # the full turn's rate from telemetry (default: from the gyros)


class _SingleAxis:
    """A method of a session on one mounting whose protocol the segment detector knows
    (`detect.protocol_lacking`)."""

    name: str

    def missing(self, segments):
        return detect.protocol_lacking(segments, self.name)


class Joint(_SingleAxis):
    """Every static and turning sample in one fit, with 1-sigma (the default method)."""

    name = "joint"
    settings = {"fixed_amplitude": Setting(bool), "drift": Setting(bool)}

    def options(self, settings: Mapping[str, Any]) -> JointOptions:
        return JointOptions(bool(settings.get("fixed_amplitude")), bool(settings.get("drift")))


    def solve(self, session, site, segments, options: JointOptions):
        return joint_real_case(session, site, options, segments)


class Thesis(_SingleAxis):
    """The thesis's real-case chain: level static, four index positions, a full turn."""

    name = "thesis"
    settings = {key: Setting(float, lambda a: -10 <= a <= 10, "an interface tilt in [-10, 10] deg")
                for key in ("alpha_deg", "beta_deg")}

    def options(self, settings: Mapping[str, Any]) -> ThesisOptions:
        alpha, beta = settings.get("alpha_deg"), settings.get("beta_deg")
        if (alpha is None) != (beta is None):
            given, other, value = ("alpha_deg", "beta_deg", alpha) if beta is None else ("beta_deg", "alpha_deg", beta)
            raise OptionError(given, f"{value!r} given without {other}: give both (a-priori tilt) or neither "
                                     "(tilt estimated from the data)")
        return ThesisOptions(None if alpha is None or beta is None else (alpha, beta),
                             settings.get("platform_rate_deg_s"))


    def solve(self, session, site, segments, options: ThesisOptions):
        return thesis_real_case(session, site, options.alpha_beta_deg, options.platform_rate_deg_s, segments)


class ThesisBench:
    """The thesis's bench campaign: six-position biases and alpha/beta from full turns."""

    name = "thesis-bench"
    settings: Mapping[str, Setting] = {}

    def options(self, settings: Mapping[str, Any]) -> None:
        return None

    def missing(self, segments):
        return ", ".join(bench_lacking(segments)) or None

    def solve(self, session, site, segments, options: None):
        return thesis_bench(session, site, segments)


ESTIMATORS: dict[str, Estimator] = {e.name: e for e in (Joint(), Thesis(), ThesisBench())}
DAEMON_METHODS = ("joint", "thesis")  # one mounting, a protocol the segment detector knows complete


def estimator(name: str) -> Estimator:
    """The method called `name`; KeyError naming the known ones otherwise."""
    try:
        return ESTIMATORS[name]
    except KeyError:
        raise KeyError(f"no method {name!r} (known: {', '.join(ESTIMATORS)})") from None


def progress(method: str, segments: list[detect.Segment]) -> detect.Progress:
    """The one progress record of a session's segments through method `method`'s protocol: what
    the daemon's state and `calibd watch` show, and what `calibd report` says of the thesis method."""
    return detect.Progress.of(segments, estimator(method).missing(segments))

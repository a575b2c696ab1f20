"""The thesis's bench campaign (`thesis-bench`): the IMU re-mounted with each of its six axes up
for six-position biases of every channel (thesis eq. 5.3), and alpha/beta from every full turn
(eqs. 5.6-5.8), averaged. The six positions also show the accelerometers' and inclinometers'
scale factors and misalignments to the housing (calibd.estimators.sixpos), which the result
gives as estimated factory terms. Offline only: a re-mounting is not something the daemon waits
for."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .. import detect, spec
from ..estimators import thesis
from ..estimators.joint import ESTIMATED_BELOW, NoiseModel, datasheet_noise, mean_variance, sample_variance
from ..estimators.sixpos import fit_six_positions
from ..frames import STANDARD_GRAVITY, Site
from ..results import CalibrationResult, make_result
from ..segments import segment_record, session_segments
from ..session import Session
from ..units import DEG
from .base import Setting, refusal
from .common import needs_inclinometers, one_period, partial_period, session_warnings, static_mean

CAMPAIGN = "bench campaign"
SIX_POSITIONS = "six positions"  # the error budget's "from": its factory terms were fitted without a prior


def positions(segments: list[detect.Segment]) -> dict[str, detect.Segment]:
    """The bench campaign's six positions: the first static with each axis up, by axis ("+Z")."""
    first: dict[str, detect.Segment] = {}
    for s in segments:
        if s.kind == "static":
            first.setdefault(s.up, s)
    return first


def lacking(segments: list[detect.Segment]) -> str | None:
    """What the bench campaign lacks in these segments (a static with each axis up, a full turn),
    in words; None when it holds them all."""
    found = positions(segments)
    parts = [f"a static with {axis} up" for axis in thesis.UP_AXES if axis not in found]
    if not detect.full_turns(segments):
        parts.append(f"a full turn (at least {detect.FULL_TURN_MIN_DEG:.0f} deg)")
    return ", ".join(parts) or None


def hint(segments: list[detect.Segment]) -> str:
    """What a single-mounting method's refusal adds when the segments hold the whole bench
    campaign instead: which method fits them."""
    return "" if lacking(segments) else "this looks like the bench campaign: use --method thesis --bench"


def thesis_bench(session: Session, site: Site, segments: list[detect.Segment] | None = None) -> CalibrationResult:
    """The bench campaign: six-position biases of every channel (eq. 5.3) and alpha/beta from
    every full turn (eqs. 5.6-5.8), averaged. `segments`: the session's, when already found."""
    needs_inclinometers(session, "thesis-bench")
    segments = session_segments(session) if segments is None else segments
    if missing := lacking(segments):
        raise refusal(CAMPAIGN, missing, segments)
    statics = [s for s in segments if s.kind == "static"]
    at = positions(segments)
    biases = {name: thesis.six_position_biases({axis: static_mean(values, seg) for axis, seg in at.items()})
              for name, values in (("gyro", session.gyro), ("acc", session.acc), ("incl", session.incl))}
    turns = detect.full_turns(segments)
    warnings, tilts = session_warnings(session), []
    for turn in turns:
        before = [s for s in statics if s.stop <= turn.start and s.up == "+Z"]
        level = before[-1] if before else at["+Z"]
        pitch, roll = thesis.pitch_roll(static_mean(session.incl, level) - biases["incl"])
        window, covered_deg = one_period(session, turn)
        earth_bound, partial = partial_period(covered_deg, site)
        if partial:  # eq. 5.7 assumes the yaw term averaged out; its rest tilts the platform-rate vector
            warnings.append(f"{partial} in the turn at {turn.start_s:.0f} s, up to "
                            f"{earth_bound / abs(turn.rate_deg_s * DEG) / DEG:.4f} deg on its alpha and beta")
        turning = session.gyro[window].mean(axis=0, dtype=np.float64)
        rate = thesis.bench_platform_rate(turning, biases["gyro"], pitch, roll, site)
        tilts.append(thesis.interface_tilt(rate))
    alpha, beta = np.mean(tilts, axis=0)
    estimates = {"alpha": (alpha, None), "beta": (beta, None)}
    for name, values in biases.items():
        estimates |= {f"{name}_bias_{a}": (values[k], None) for k, a in enumerate("xyz")}
    records = ([segment_record(at[axis], f"{axis} up") for axis in thesis.UP_AXES]
               + [segment_record(t, "full turn") for t in turns])
    acc_range_g = session.sensor.acc_range_g if session.sensor.acc_range_g in spec.ACC else spec.DEFAULT_ACC_RANGE_G
    warnings.append(INTRINSIC_WARNING)
    return make_result("thesis-bench", site, estimates, records, warnings, session.sensor, stream=session.stream,
                       turns_alpha_beta_deg=[[a / DEG, b / DEG] for a, b in tilts],
                       error_budget={"frame": "housing", "factory_residuals": {
                           "reference": spec.SPECIFICATIONS, "acc_range_g": acc_range_g, "from": SIX_POSITIONS,
                           "terms": intrinsic_terms(session, at, site, acc_range_g)}})


INTRINSIC_WARNING = ("the accelerometers' and inclinometers' scale factors and misalignments to the housing come "
                     "from the six positions, the fixture's faces taken as exact (its own error enters the "
                     "misalignments one for one): error_budget.factory_residuals; calibd apply and the corrected "
                     "outputs take them out")


def intrinsic_terms(session: Session, at: dict[str, detect.Segment], site: Site, acc_range_g: int) -> dict:
    """Each force triad's factory terms fitted to the six positions' means (value, sigma, the
    datasheet's prior sigma, in ppm or mrad; `estimated` by the joint method's rule, a sigma at
    most half the prior's): the noise of a mean from the static's own white noise and the
    datasheet's flicker (a vibrating position counts as it is)."""
    terms = {}
    for sensor, values in (("acc", session.acc), ("incl", session.incl)):
        means, variances = {}, {}
        for up, segment in at.items():
            means[up] = values[segment.start:segment.stop].mean(axis=0, dtype=np.float64)
            along = means[up] / STANDARD_GRAVITY  # an inclinometer axis along gravity is noisier
            figures = datasheet_noise(spec.NoiseFigures.datasheet(acc_range_g), session.rate_hz, along)
            noise = NoiseModel(sample_variance(values, [(segment.start, segment.stop)])[0],
                               getattr(figures, sensor).flicker)
            variances[up] = mean_variance(noise, segment.stop - segment.start, session.rate_hz)
        fit = fit_six_positions(means, variances, site.gravity)
        for term in spec.factory_terms(acc_range_g, (sensor,)):
            sigma = fit.term_sigma(term)
            terms[term.name] = {"value": float(fit.error[term.row, term.col]) * term.to_unit,
                                "sigma": sigma * term.to_unit, "prior_sigma": term.sigma_in_unit, "unit": term.unit,
                                "source": "estimated" if sigma <= ESTIMATED_BELOW * term.sigma else "prior"}
    return terms


class ThesisBench:
    """The thesis's bench campaign: six-position biases and alpha/beta from full turns."""

    name = "thesis-bench"
    settings: Mapping[str, Setting] = {}

    def options(self, settings: Mapping[str, Any]) -> None:
        return None

    def missing(self, segments: list[detect.Segment]) -> str | None:
        return lacking(segments)

    def solve(self, session, site, segments, options: None):
        return thesis_bench(session, site, segments)


METHOD = ThesisBench()

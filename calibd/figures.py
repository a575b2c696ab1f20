"""The report's figures: the session timeline, the Earth-rate fit against the platform angle, and
the Allan deviation of the static data, each drawn into PNG bytes, and into SVG on request.

matplotlib is imported inside the functions only (the optional extra `[plot]`); `calibd.report`
checks it is there before any of these run. Every figure is FIGURE_WIDTH_IN wide at 100 dpi, the
page's width in pixels, so the page shows it at its own size and STYLE's point sizes hold there.
"""

from __future__ import annotations

import functools
import io
from dataclasses import dataclass

import numpy as np

from . import detect, spec
from .methods.joint import joint_fit, joint_input
from .errors import CalibrationError
from .methods import estimator
from .estimators.joint import (AXIS_PARAMS, DRIFT_PARAMS, EARTH_RATE_PARAMS, OFFSET_PARAMS, GyroFit, JointInput,
                               JointOptions, alpha_beta, datasheet_noise, fit_gyros, has_drift)
from .frames import Site, int_to_imu
from .noise import UNITS as NOISE_UNITS
from .results import CalibrationResult
from .noise import NoiseError, characterise
from .session import Session
from .units import DEG, M_S2_TO_MG, RAD_S_TO_DEG_H, SQRT_S_PER_SQRT_H

FIGURE_WIDTH_IN = 12.0  # at DPI: 1200 px, the report page's width (report.CSS), shown unscaled
DPI = 100
STYLE = {"font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "xtick.labelsize": 9.5,
         "ytick.labelsize": 9.5, "legend.fontsize": 9, "figure.titlesize": 11,
         "svg.fonttype": "none", "svg.hashsalt": "calibd.report"}  # SVG text as text: small, searchable
TIMELINE_BINS = 1500  # plotted points per trace: min/max envelopes keep turns and spikes visible
ROBUST_PERCENTILES = (1.0, 99.0)  # small-signal panels' y range: spikes (turn ramps) run off it
TURN_BIN_DEG = 30.0  # turn samples are averaged in bins of platform angle this wide
ROLE_COLOURS = {"static": "#2ca02c", "index turn": "#1f77b4", "full turn": "#ff7f0e", "other turn": "#7f7f7f"}
AXIS_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")  # X, Y, Z
SENSOR_NAMES = {"gyro": "gyros", "acc": "accelerometers", "incl": "inclinometers"}
YAW_MARKER = "yaw-marker"  # gid of the Earth-rate figure's phase line (an id in the SVG)


def need_matplotlib(missing: str, error: type[Exception]) -> None:
    """matplotlib with its Agg back end (compiled; the SVG one is Python of the same package), or
    `error(missing)`: the one line that names the command and the extra that brings it."""
    try:
        import matplotlib  # noqa: F401  (the package first: a missing one must say so, not a submodule)
        import matplotlib.backends.backend_agg  # noqa: F401
    except ImportError:
        raise error(missing) from None


@dataclass
class Figure:
    """One figure of the report: its PNG and the matplotlib figure drawn, or why there is none."""

    name: str  # file stem: report_files/<name>.png (and .svg)
    title: str
    caption: str
    png: bytes | None = None
    drawing: object = None  # the matplotlib Figure: its SVG when asked for, and what tests read
    missing: str = ""

    def svg(self) -> bytes:
        """The vector copy (`calibd report --svg`), rendered only when asked for: a second drawing,
        half the PNG's CPU again. Laid out as the PNG, with no date: the same report gives the same
        file."""
        from matplotlib import rc_context

        svg = io.BytesIO()
        with rc_context(STYLE):  # read while saving: text as text, ids salted alike
            self.drawing.savefig(svg, format="svg", metadata={"Date": None})
        return svg.getvalue()


def _styled(draw):
    """Run a figure function under STYLE (sizes readable at the page's width, SVG text as text)."""
    @functools.wraps(draw)
    def styled(*args, **kwargs):
        from matplotlib import rc_context

        with rc_context(STYLE):
            return draw(*args, **kwargs)
    return styled


def _figure(name: str, title: str, caption: str, fig) -> Figure:
    """The figure with its PNG."""
    png = io.BytesIO()
    fig.savefig(png, format="png")
    fig.set_layout_engine("none")  # laid out by this drawing: an SVG drawn later keeps it
    return Figure(name, title, caption, png.getvalue(), fig)


def _new_figure(height_in: float):
    from matplotlib.figure import Figure as MplFigure

    return MplFigure(figsize=(FIGURE_WIDTH_IN, height_in), dpi=DPI, layout="constrained")


def envelope(time_s: np.ndarray, values: np.ndarray, bins: int = TIMELINE_BINS):
    """(bin time, min, max, mean) of each column over `bins` equal sample bins: a 1-h session at
    125 Hz (450k samples) plots as a few thousand points without losing a turn or a spike."""
    n = len(time_s)
    if n <= 2 * bins:
        return time_s, values, values, values
    starts = np.linspace(0, n, bins + 1).astype(np.int64)[:-1]
    count = np.diff(np.append(starts, n))[:, None]
    return (np.add.reduceat(time_s, starts) / count[:, 0], np.minimum.reduceat(values, starts),
            np.maximum.reduceat(values, starts), np.add.reduceat(values, starts) / count)


def platform_axis(result: CalibrationResult) -> np.ndarray | None:
    """The platform's turning axis in the gyros' axes: as the joint fit saw it (its checks), else
    R_int^IMU [0, 0, 1] from the result's alpha and beta, which describe the housing and differ
    from the gyro triad's by its factory misalignment (None when it has neither)."""
    seen = (result.checks or {}).get("platform_axis_in_gyro_axes")
    if seen is not None:
        return np.asarray(seen, dtype=float)
    tilt = result.rotation_matrix("int_to_imu")
    return None if tilt is None else tilt[:, 2]


def without_platform_rate(gyro: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The gyros less the rate about the platform axis, N x 3 (same unit): a turn's tens of deg/s
    gone, the Earth rate and the biases left in the horizontal channels (the vertical Earth rate and
    the Z bias along the axis go too, but they reach X and Y only through the axis's tilt)."""
    return gyro - np.outer(gyro @ axis, axis)


def robust_limits(values: np.ndarray) -> tuple[float, float]:
    """A y range holding ROBUST_PERCENTILES of `values` with a margin: turn ramps and spikes run off
    it instead of flattening the trace."""
    low, high = np.percentile(values, ROBUST_PERCENTILES)
    margin = max(0.15 * (high - low), 1e-3 * max(abs(low), abs(high)), 1e-6)
    return float(low - margin), float(high + margin)


def _band_panel(ax, t, low, high, mean, names) -> None:
    """Large signals: each bin's mean as a line, its minimum to maximum as a band."""
    for k, name in enumerate(names):
        ax.fill_between(t, low[:, k], high[:, k], color=AXIS_COLOURS[k], alpha=0.25, lw=0)
        ax.plot(t, mean[:, k], color=AXIS_COLOURS[k], lw=0.8, label=name)


def _small_signal_panel(ax, time_s, values, statics, names) -> None:
    """Small signals under sample noise: the bin means only (the min-max band would be the
    noise), a y range from robust percentiles, and each static's mean as a thick bar."""
    t, _, _, mean = envelope(time_s, values)
    for k, name in enumerate(names):
        ax.plot(t, mean[:, k], color=AXIS_COLOURS[k], lw=0.7, alpha=0.6, label=name)
    for start, stop in statics:
        a, b = np.searchsorted(time_s, (start, stop))
        if b > a:
            level = values[a:b].mean(axis=0)
            for k in range(values.shape[1]):
                ax.plot((start, stop), (level[k], level[k]), color=AXIS_COLOURS[k], lw=2.5, solid_capstyle="butt")
    ax.set_ylim(*robust_limits(mean))


@_styled
def timeline_figure(whole: Session, segments, roles, warm_up: tuple[float, str], axis: np.ndarray | None) -> Figure:
    """`axis`: the platform axis in IMU axes (`platform_axis`), None to take the IMU's Z."""
    from matplotlib.patches import Patch

    statics = [(s.start_s, s.end_s) for s in segments if s.kind == "static"]
    axis_known = axis is not None
    axis = np.array([0.0, 0.0, 1.0]) if axis is None else axis
    time_s = whole.time_s
    panels = [("gyro [deg/s]", whole.gyro / DEG, "gyro {}", False),
              ("horizontal gyros less\nplatform rate [deg/h]",
               without_platform_rate(whole.gyro, axis)[:, :2] * RAD_S_TO_DEG_H, "gyro {}", True),
              ("accelerometer [m/s$^2$]", whole.acc, "acc {}", False),
              ("horizontal\naccelerometers [mg]", whole.acc[:, :2] * M_S2_TO_MG, "acc {}", True),
              ("horizontal\ninclinometers [mg]", None if whole.incl is None else whole.incl[:, :2] * M_S2_TO_MG,
               "incl {}", True)]
    heights = [1.2, 1, 0.8, 1, 1 if whole.incl is not None else 0.3, 0.8 if whole.temperature_c is not None else 0.3]
    fig = _new_figure(16.0 - 6 * (6 - sum(heights)) / 5)  # a panel saying "none" takes little room
    axes = fig.subplots(len(panels) + 1, 1, sharex=True, height_ratios=heights)
    for ax, (label, values, name, small) in zip(axes, panels):
        if values is None:  # the text names it: no label, which would not fit the short panel
            ax.text(0.5, 0.5, "no inclinometers in this datagram", transform=ax.transAxes, ha="center", va="center")
            ax.set_yticks([])
            continue
        ax.set_ylabel(label)
        names = [name.format(a) for a in "XYZ"[:values.shape[1]]]
        if small:
            _small_signal_panel(ax, time_s, values, statics, names)
        else:
            _band_panel(ax, *envelope(time_s, values), names)
        ax.legend(loc="center left", bbox_to_anchor=(1.0, 0.5))  # outside: the traces keep the panel
    temp_ax = axes[-1]
    if whole.temperature_c is None:
        temp_ax.text(0.5, 0.5, "no temperatures in this datagram", transform=temp_ax.transAxes, ha="center",
                     va="center")
        temp_ax.set_yticks([])
    else:
        t, low, high, mean = envelope(time_s, whole.temperature_c[:, None])
        temp_ax.fill_between(t, low[:, 0], high[:, 0], color="k", alpha=0.2, lw=0)
        temp_ax.plot(t, mean[:, 0], color="k", lw=0.8)
        temp_ax.set_ylabel("gyro temperature\n[degC]")
    temp_ax.set_xlabel("time from the first datagram [s]")
    span = float(time_s[-1] - time_s[0]) or 1.0
    for seg, role in zip(segments, roles):
        for ax in axes:
            ax.axvspan(seg.start_s, seg.end_s, color=ROLE_COLOURS[role], alpha=0.12 if role == "static" else 0.3, lw=0)
        width = (seg.end_s - seg.start_s) / span
        if seg.kind == "static" and width > 0.012:  # narrower ones get no room for a label
            axes[0].text((seg.start_s + seg.end_s) / 2, 0.5, f"{seg.up} up\nchi {seg.platform_angle_deg:.0f}°",
                         transform=axes[0].get_xaxis_transform(), ha="center", va="center", fontsize=9,
                         rotation=0 if width > 0.07 else 90, bbox={"facecolor": "white", "alpha": 0.7, "lw": 0})
    warm_end, warm_label = warm_up
    handles = [Patch(color=ROLE_COLOURS[r], alpha=0.35, label=r) for r in ROLE_COLOURS if r in roles]
    if warm_end > time_s[0]:
        for ax in axes:
            ax.axvspan(float(time_s[0]), warm_end, facecolor="none", edgecolor="#d62728", hatch="//", lw=0)
        handles.append(Patch(facecolor="none", edgecolor="#d62728", hatch="//", label=warm_label))
    if handles:
        fig.legend(handles=handles, loc="outside upper center", ncols=len(handles), fontsize=10)
    axes[-1].set_xlim(float(time_s[0]), float(time_s[-1]))
    n_static = sum(r == "static" for r in roles)
    about = ("the platform axis R_int^IMU [0, 0, 1] of the result's alpha and beta" if axis_known else
             "the IMU's Z axis (the result has no alpha and beta)")
    return _figure("timeline", "Session timeline",
                   f"Gyro, accelerometer and gyro temperature (the mean of the three gyros') against time "
                   f"(lines: means over {TIMELINE_BINS} bins, "
                   f"bands: each bin's min to max). The small signals get panels of their own, with the bin means "
                   f"only and a y range from percentile {ROBUST_PERCENTILES[0]:g} to percentile "
                   f"{ROBUST_PERCENTILES[1]:g} of those (turn ramps run off it): the horizontal gyros in deg/h "
                   f"less the rate about {about}, "
                   f"which leaves the Earth rate and the bias (each static's mean: thick bar; it steps with the "
                   f"platform angle by the horizontal Earth rate), and the horizontal accelerometers and "
                   f"inclinometers in mg (the tilt and the bias). Shaded: the {len(segments)} segments found "
                   f"({n_static} statics, labelled with the IMU axis up and the platform angle chi); hatched: "
                   f"{f'{warm_label} up to {warm_end:.0f} s' if warm_end > time_s[0] else 'no warm-up'}.",
                   fig)


def north_chi_deg(yaw_deg: float) -> float:
    """The platform angle (deg, mod 360) at which the IMU's X axis points North: yaw is positive
    from North towards West, counter-clockwise about Up as chi is, so turning by chi = -yaw takes X
    to North. There the X gyro's Earth-rate term peaks and Y's crosses zero going down (to within
    the platform axis's tilt, through which the vertical Earth rate adds a sinusoid of its own)."""
    return float(-yaw_deg % 360.0)


def earth_term(params: np.ndarray, chi: np.ndarray) -> np.ndarray:
    """The joint model's Earth-rate term (estimators/joint.py), N x 3 in rad/s, at platform angles
    chi (rad): v1 (A0 cos chi - A1 sin chi) + v2 (A0 sin chi + A1 cos chi), A = R_int^IMU of the
    fitted axis."""
    a = int_to_imu(*alpha_beta(params[AXIS_PARAMS]))
    cos, sin = np.cos(chi)[:, None], np.sin(chi)[:, None]
    v1, v2 = params[EARTH_RATE_PARAMS]
    return v1 * (a[:, 0] * cos - a[:, 1] * sin) + v2 * (a[:, 0] * sin + a[:, 1] * cos)


@dataclass(frozen=True)
class EarthRateFit:
    """What the Earth-rate figure draws of the joint fit: the segments it used, the session sample
    its input starts at (the level static's first), the input, the gyro fit, and yaw with its
    1-sigma (rad)."""

    segments: list[detect.Segment]
    first: int
    inp: JointInput
    gyro: GyroFit
    yaw: tuple[float, float]


def earth_rate_fit(session: Session, site: Site, options: JointOptions, segments,
                   result: CalibrationResult | None = None) -> EarthRateFit:
    """The joint fit on the session. With `result`, a joint result of this session, the gyro fit
    alone is redone (a seventh of the whole fit's CPU: the force fits and the error budget's
    refits draw nothing here) and yaw is the result's, once that gyro fit is shown to be the
    result's own: its Earth rate, 1-sigma and platform axis as the result's checks record them,
    and no turn's angle corrected by the tilt (which the whole fit alone finds). Otherwise
    (another method's result; other data, options or software) the whole fit, whose yaw the
    caption compares with the result's. CalibrationError when the session gives no joint fit."""
    checks = (result.checks or {}) if result is not None else {}
    if "earth_rate_horizontal_deg_h" in checks and not any(t["corrected"] for t in checks.get("turn_angles", [])):
        gyro_only = _gyro_fit(session, site, options, segments)
        if gyro_only is not None and _as_recorded(gyro_only[-1], checks):
            yaw = result.estimates["yaw"]
            return EarthRateFit(*gyro_only, (yaw.value_si, yaw.sigma_si))
    fitted = joint_fit(session, site, options, segments)
    return EarthRateFit(fitted.segments, fitted.first, fitted.inp, fitted.fit.gyro,
                        (fitted.fit.estimates["yaw"], fitted.fit.sigmas["yaw"]))


def _gyro_fit(session: Session, site: Site, options: JointOptions, segments):
    """(segments used, first sample, input, gyro fit): the joint estimator's gyro fit on the input
    `joint_fit` gives it; None when the segments give no joint fit (the whole fit then says why)."""
    if estimator("joint").missing(segments):
        return None
    used, first, inp = joint_input(session, segments)
    least = datasheet_noise(spec.NoiseFigures.datasheet(), inp.rate_hz).gyro.flicker  # the same for every range
    try:
        return used, first, inp, fit_gyros(inp, site, options, least_flicker=least)
    except np.linalg.LinAlgError:
        return None


def _as_recorded(gyro: GyroFit, checks: dict) -> bool:
    """Whether a gyro fit is the one whose checks a joint result records (to 1e-9: JSON keeps a
    float's every digit, but its units are converted)."""
    recorded = checks["earth_rate_horizontal_deg_h"]
    axis = gyro.params[AXIS_PARAMS] / np.linalg.norm(gyro.params[AXIS_PARAMS])
    return bool(np.allclose(np.array(gyro.amplitude_check) * RAD_S_TO_DEG_H, [recorded["fitted"], recorded["sigma"]],
                            rtol=1e-9, atol=0.0)
                and np.allclose(axis, checks.get("platform_axis_in_gyro_axes", np.nan), rtol=0.0, atol=1e-12))


def earth_rate_seen(fitted: EarthRateFit) -> np.ndarray:
    """The gyros less every fitted term but the Earth rate's (the platform rate k chi', the
    offsets c, a drift when fitted), N x 3 rad/s: what the model says is Earth rate plus noise."""
    g, inp = fitted.gyro, fitted.inp
    p = g.params
    rest = np.outer(g.chi_rate, p[AXIS_PARAMS]) + p[OFFSET_PARAMS]
    if has_drift(p):
        rest += np.outer(inp.time_s - inp.time_s.mean(), p[DRIFT_PARAMS])
    return inp.gyro - rest


def _binned(chi_deg: np.ndarray, values: np.ndarray, width: float):
    """Means and standard errors of `values` (N x k) in bins of chi mod 360 (deg); empty bins dropped."""
    index = np.floor((chi_deg % 360.0) / width).astype(np.int64)
    count = np.bincount(index, minlength=int(360 / width))
    have = count > 1
    centres = (np.arange(len(count)) + 0.5) * width
    means, errors = [], []
    for column in values.T:
        total, square = np.bincount(index, column, len(count)), np.bincount(index, column**2, len(count))
        mean = total[have] / count[have]
        var = np.maximum(square[have] / count[have] - mean**2, 0.0)
        means.append(mean)
        errors.append(np.sqrt(var / count[have]))
    return centres[have], np.column_stack(means), np.column_stack(errors)


@_styled
def earth_rate_figure(session: Session, site: Site, segments, result: CalibrationResult) -> Figure:
    joint = estimator("joint")
    joint_result = result.method == joint.name
    options = joint.options((result.options or {}) if joint_result else {})
    title = "Earth rate against the platform angle"
    try:
        fitted = earth_rate_fit(session, site, options, segments, result if joint_result else None)
    except CalibrationError as exc:
        return Figure("earth_rate", title, "", missing=f"no joint fit on this capture: {exc}")
    g = fitted.gyro
    seen = earth_rate_seen(fitted) * RAD_S_TO_DEG_H
    model = earth_term(g.params, g.chi) * RAD_S_TO_DEG_H
    residual = seen - model
    chi_deg = g.chi / DEG
    statics = fitted.inp.statics
    static_chi = np.array([chi_deg[a:b].mean() for a, b in statics]) % 360.0
    static_seen = np.array([seen[a:b].mean(axis=0) for a, b in statics])
    static_res = np.array([residual[a:b].mean(axis=0) for a, b in statics])
    static_err = np.array([residual[a:b].std(axis=0) / np.sqrt(b - a) for a, b in statics]) * g.noise_scale
    turning = np.zeros(len(chi_deg), bool)
    for s in fitted.segments:
        if s.kind == "turn":
            turning[s.start - fitted.first:s.stop - fitted.first] = True
    bin_chi, bin_seen, bin_err = _binned(chi_deg[turning], seen[turning], TURN_BIN_DEG)
    _, bin_res, _ = _binned(chi_deg[turning], residual[turning], TURN_BIN_DEG)
    grid = np.linspace(0.0, 360.0, 361)
    curve = earth_term(g.params, grid * DEG) * RAD_S_TO_DEG_H

    fig = _new_figure(8.0)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    for k, axis in enumerate("XY"):
        colour = AXIS_COLOURS[k]
        top.plot(grid, curve[:, k], color=colour, lw=1.5, label=f"gyro {axis}: fitted Earth-rate term")
        top.errorbar(static_chi, static_seen[:, k], static_err[:, k], fmt="o", color=colour, ms=6, capsize=3,
                     label=f"gyro {axis}: static means")
        top.errorbar(bin_chi, bin_seen[:, k], bin_err[:, k], fmt="x", color=colour, ms=5, alpha=0.5, lw=0.8,
                     label=f"gyro {axis}: turn samples, {TURN_BIN_DEG:.0f}° bins")
        bottom.errorbar(static_chi, static_res[:, k], static_err[:, k], fmt="o", color=colour, ms=6, capsize=3)
        bottom.errorbar(bin_chi, bin_res[:, k], bin_err[:, k], fmt="x", color=colour, ms=5, alpha=0.5, lw=0.8)
    bottom.axhline(0.0, color="k", lw=0.8)
    amplitude, sigma = (x * RAD_S_TO_DEG_H for x in g.amplitude_check)
    expected = float(np.hypot(*site.earth_rate_nav[:2])) * RAD_S_TO_DEG_H
    yaw, yaw_sigma = (x / DEG for x in fitted.yaw)
    seen_amplitude = (f"horizontal Earth rate fixed to Ω_E cos(lat) = {expected:.2f} deg/h"
                      if options.fixed_amplitude else
                      f"fitted horizontal Earth rate {amplitude:.2f} ± {sigma:.2f} deg/h (Ω_E cos(lat) = "
                      f"{expected:.2f} deg/h)")
    fig.suptitle(f"{seen_amplitude}; yaw {yaw:.2f} ± {yaw_sigma:.2f} deg")
    north = north_chi_deg(yaw)
    for ax in (top, bottom):
        ax.axvline(north, color="k", ls="--", lw=1.2, gid=YAW_MARKER if ax is top else None)
    top.text(north + (-1.5 if north > 270 else 1.5), 0.97, f"yaw = {yaw:.2f} ± {yaw_sigma:.2f} deg\n"
             f"chi = -yaw = {north:.1f}°: X towards North", transform=top.get_xaxis_transform(), va="top",
             ha="right" if north > 270 else "left", bbox={"facecolor": "white", "alpha": 0.8, "lw": 0})
    top.set_ylabel("gyro less fitted offsets and\nplatform-rate terms [deg/h]")
    bottom.set_ylabel("residual [deg/h]")
    bottom.set_xlabel("platform angle chi mod 360 [deg] (counter-clockwise about Up, 0 at the level static)")
    bottom.set_xlim(0, 360)
    bottom.set_xticks(np.arange(0, 361, 45))
    # statics dominate: keep the scale on them, the noisier turn bins may run off it
    span = np.abs(np.concatenate([static_seen.ravel(), curve[:, :2].ravel()])).max()
    top.set_ylim(-1.6 * span, 1.6 * span)
    res_span = max(np.abs(static_res).max() + static_err.max(), 1e-3)
    bottom.set_ylim(-4 * res_span, 4 * res_span)
    fig.legend(*top.get_legend_handles_labels(), loc="outside lower center", ncols=3)
    note = "" if joint_result else (f" The result's method ({result.method}) fits no sinusoid: this is "
                                    "the joint estimator's fit on the same segments.")
    stated = result.estimates["yaw"].value if "yaw" in result.estimates else None
    if joint_result and stated is not None and abs(stated - yaw) > 1e-6 + 1e-3 * yaw_sigma:
        note += (f" The fit redone here gives a yaw of {yaw:.4f} deg where the result has {stated:.4f} deg: the "
                 "result was made with other data, options or software.")
    caption = (f"The horizontal gyros less the fitted offsets and platform-rate terms, against the platform "
               f"angle: the Earth rate's horizontal component, a sinusoid whose phase is the yaw. Circles: the "
               f"mean of each of the {len(statics)} statics (error bars 1-sigma, white noise scaled by the "
               f"measured excess {g.noise_scale:.2f}); crosses: turn samples averaged in {TURN_BIN_DEG:.0f}° "
               f"bins of chi. Dashed vertical line: chi = -yaw, the platform angle at which the IMU's X axis "
               f"points North (yaw is positive from North towards West, counter-clockwise about Up as chi is), "
               f"the sinusoid's phase: X's term peaks there. Below: the residuals after the fitted "
               f"sinusoid.{note}")
    return _figure("earth_rate", title, caption, fig)


def guide_points(noise) -> list[tuple[float, float] | None]:
    """(tau s, deviation in the curve's unit) where the random-walk, bias-instability and rate
    random-walk guides pass through the values read (None: not read). The readings are in their own
    units (deg/sqrt(h), m/s/sqrt(h), ...): back to the deviation they were read from."""
    rw, bi, rrw = noise.random_walk, noise.bias_instability, noise.rate_random_walk
    per_adev = NOISE_UNITS[noise.name.split("_")[0]].random_walk_per_adev
    return [(rw.tau_s, rw.value / per_adev), (bi.tau_s, bi.value),
            None if rrw is None else (rrw.tau_s, rrw.value / SQRT_S_PER_SQRT_H)]


def _allan_panel(ax, members) -> None:
    """One sensor's channels: curves with their bands, the guides through the values read, and
    the values in the legend."""
    for k, noise in enumerate(members):
        colour, taus = AXIS_COLOURS[k % 3], np.asarray(noise.taus_s)
        rw, bi, rrw = noise.random_walk, noise.bias_instability, noise.rate_random_walk
        falling = bi.tau_s >= taus[-1]  # no minimum inside the data: an upper bound
        label = (f"{noise.name.split('_')[-1].upper()}: RW {rw.value:.3g} {rw.unit}\n"
                 f"BI {'< ' if falling else ''}{bi.value:.3g} {bi.unit}"
                 + (f", RRW {rrw.value:.3g} {rrw.unit}" if rrw is not None else ""))
        ax.fill_between(taus, noise.adev_low, noise.adev_high, color=colour, alpha=0.2, lw=0)
        ax.loglog(taus, noise.adev, color=colour, lw=1.3, label=label)
        (tau_rw, at_rw), (tau_bi, at_bi), rising = guide_points(noise)
        ax.loglog(taus, at_rw * np.sqrt(tau_rw / taus), color=colour, ls=":", lw=1.2)
        ax.axhline(at_bi, color=colour, ls="--", lw=0.9)
        points = [(tau_rw, at_rw), (tau_bi, at_bi)]
        if rising is not None:
            ax.loglog(taus, rising[1] * np.sqrt(taus / rising[0]), color=colour, ls="-.", lw=1.2)
            points.append(rising)
        ax.plot(*zip(*points), "o", color=colour, ms=5, mec="k", mew=0.5)
    unit = members[0].adev_unit
    ax.set_xlabel("averaging time tau [s]")
    ax.set_ylabel(f"Allan deviation [{unit}]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), frameon=False)  # below: the curves keep the panel


@_styled
def allan_figure(session: Session, segments) -> Figure:
    title = "Allan deviation of the static data"
    try:
        channels = characterise(session, segments)
    except NoiseError as exc:
        return Figure("allan", title, "", missing=f"no Allan deviation: {exc}")
    groups = {}
    for name, noise in channels.items():
        groups.setdefault(name.split("_")[0], []).append(noise)
    fig = _new_figure(6.5)
    for ax, (sensor, members) in zip(fig.subplots(1, len(groups)), groups.items()):
        ax.set_title(SENSOR_NAMES.get(sensor, sensor))
        _allan_panel(ax, members)
    first = next(iter(channels.values()))
    caption = (f"Overlapping Allan deviation of each channel over the {first.static_s:.0f} s of static data in "
               f"{first.segments} statics, pooled (bands: 68 % interval). Guides in the channel's colour: "
               "dotted, slope -1/2 through the random walk (RW) read at 1 s (dot); dashed, the bias instability "
               "(BI, the "
               "curve's minimum, dot; '<' when the curve is still falling at its last tau); dash-dot, slope +1/2 "
               "through the rate random walk (RRW) when the curve rises again.")
    return _figure("allan", title, caption, fig)


# ---------------------------------------------------------------- page

"""The calibration report: one self-contained HTML page, and its figures as PNG files beside it.

A result file holds numbers; the report shows what they rest on. It re-reads the capture the
result was made from, finds the segments again and draws the session's timeline, the Earth-rate
sinusoid the horizontal gyros see against the platform angle, and the Allan deviation of the
static data; it tables every estimate with its 1-sigma beside the thesis method's value on the
same capture and, for a simulated capture, the truth. `report.html` embeds the figures (data
URIs, inline CSS: it can be mailed or archived alone); `report_files/*.png` are the same figures.

matplotlib (the optional extra `[plot]`) is imported here only, inside the functions, and draws
on an Agg canvas: the other commands never load it, and no display is needed.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from stim300.atomic import write_atomic
from stim300.progress import Progress

from . import detect
from .calibrate import (CalibrationError, JointFit, Session, joint_fit, load_session, session_segments,
                        thesis_real_case)
from .config import WarmupConfig
from .estimators.joint import JointOptions, alpha_beta
from .frames import Site, int_to_imu
from .noise import SQRT_S_PER_SQRT_H, NoiseError, characterise
from .noise import UNITS as NOISE_UNITS
from .results import load_result
from .scenario import Truth

MATPLOTLIB_MISSING = "calibd report needs matplotlib: pip install 'stim300-calib[plot]'"
DEG = np.pi / 180
DEG_H = 3600 / DEG  # rad/s -> deg/h
TIMELINE_BINS = 1500  # plotted points per trace: min/max envelopes keep turns and spikes visible
INDEX_TURN_TOLERANCE_DEG = 5.0  # a turn within this of +-90 deg is an index turn (as detect.protocol_progress)
TURN_BIN_DEG = 30.0  # turn samples are averaged in bins of platform angle this wide
STEPS = ("capture", "segments", "timeline", "Earth-rate fit", "Allan deviation", "thesis method", "files")
ROLE_COLOURS = {"static": "#2ca02c", "index turn": "#1f77b4", "full turn": "#ff7f0e", "other turn": "#7f7f7f"}
AXIS_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")  # X, Y, Z
SENSOR_NAMES = {"gyro": "gyros", "acc": "accelerometers", "incl": "inclinometers"}


class ReportError(ValueError):
    """The report cannot be made from these inputs (matplotlib missing, wrong capture, unwritable output)."""


@dataclass
class Figure:
    """One figure of the report: its PNG, or why there is none."""

    name: str  # file stem: report_files/<name>.png
    title: str
    caption: str
    png: bytes | None = None
    missing: str = ""


def figures_dir(output) -> Path:
    """Where the PNGs go: `report.html` -> `report_files/`."""
    output = Path(output)
    return output.with_name(f"{output.stem}_files")


def write_report(result_path, capture: str, output, data: bytes | None = None, stream=None) -> list[Path]:
    """Render the report of the result at `result_path` on `capture` (its bytes in `data` when
    already read) to `output` and its figures directory; returns the files written, the HTML
    first. A progress bar goes to `stream` (stderr) when it is a terminal."""
    canvas = _agg_canvas()
    result = load_result(result_path)
    site = _site(result, result_path)
    estimates = result.get("estimates")
    if not (isinstance(estimates, dict) and all(isinstance(e, dict) and {"value", "unit"} <= set(e)
                                                for e in estimates.values())):
        raise ReportError(f"{result_path}: the result has no estimates (value and unit each)")
    output = Path(output)
    _check_writable(output)
    with Progress("report", len(STEPS), "steps", stream) as bar:
        bar.update(0, STEPS[0])
        skipped_s = float(result.get("stream", {}).get("start_s") or 0.0)
        start_s = analysis_start_s(result)
        whole = load_session(capture, 0.0, data)
        _check_same_capture(result, whole, capture)
        session = load_session(capture, start_s, data) if start_s > 0 else whole
        bar.update(1, STEPS[1])
        segments = session_segments(session)
        roles = segment_roles(segments)
        warm_up = (skipped_s, "warm-up skipped by the result (--start)") if skipped_s > 0 else (
            warm_up_end_s(whole.time_s, whole.temperature_c),
            f"warm-up (temperature trend above {WarmupConfig().max_slope_c_per_h:g} degC/h)")
        bar.update(2, STEPS[2])
        figures = [timeline_figure(canvas, whole, segments, roles, warm_up)]
        bar.update(3, STEPS[3])
        figures.append(earth_rate_figure(canvas, session, site, segments, result))
        bar.update(4, STEPS[4])
        figures.append(allan_figure(canvas, session, segments))
        bar.update(5, STEPS[5])
        try:
            thesis = thesis_real_case(session, site, segments=segments)
        except CalibrationError as exc:
            thesis = {"error": str(exc)}
        bar.update(6, STEPS[6])
        page = render_html(result, str(result_path), capture, whole, segments, roles, warm_up, figures, thesis,
                           read_truth(capture), figures_dir(output).name)
        written = _write(output, figures, page)
        bar.update(len(STEPS))
    return written


# ---------------------------------------------------------------- inputs

def _agg_canvas():
    """The Agg canvas class, or the one-line reason why there is none."""
    try:
        import matplotlib  # noqa: F401  (the package first: a missing one must say so, not a submodule)
        from matplotlib.backends.backend_agg import FigureCanvasAgg
    except ImportError:
        raise ReportError(MATPLOTLIB_MISSING) from None
    return FigureCanvasAgg


def _site(result: dict, path) -> Site:
    try:
        site = result["site"]
        return Site(site["latitude_deg"], site.get("height_m", 0.0), site.get("g0_m_s2"))
    except (KeyError, TypeError, ValueError) as exc:
        raise ReportError(f"{path}: no usable site in the result ({exc})") from None


def _check_writable(output: Path) -> None:
    """Refuse before the work rather than after it."""
    parent = output.parent
    if output.is_dir():
        raise ReportError(f"{output}: is a directory, expected an HTML file name")
    if not parent.is_dir():
        raise ReportError(f"{output}: cannot write: no such directory {parent}")
    if not os.access(parent, os.W_OK):
        raise ReportError(f"{output}: cannot write: permission denied")


def analysis_start_s(result: dict) -> float:
    """Where the result's data began in its capture: the start offset it records (stream.start_s,
    `calibd calibrate --start`), else its first segment's start (results of older versions do not
    record the offset, but their segments begin after it). The segments found from there are the
    result's."""
    recorded = result.get("stream", {}).get("start_s")
    if recorded:
        return float(recorded)
    first = min((float(s["start_s"]) for s in result.get("segments", []) if "start_s" in s), default=0.0)
    return max(first - 1e-6, 0.0)  # the record is rounded to 1 ms: keep the first sample


def _check_same_capture(result: dict, whole: Session, capture: str) -> None:
    """A report on other data than the result's would put its numbers under figures of something
    else: refused. The datagram count (recorded by `calibd calibrate`) identifies the capture;
    a result without it (the daemon's) must at least have its segments inside the capture."""
    recorded = result.get("stream", {}).get("datagrams")
    have = whole.stream["datagrams"]
    if recorded is not None and recorded != have:
        raise ReportError(f"{capture}: {have} datagrams, but the result was made from a capture of {recorded} "
                          f"datagrams ({result['stream'].get('capture')}): not the result's capture")
    duration = float(whole.time_s[-1]) + 1.0 / whole.rate_hz
    end = max((float(s.get("end_s", 0.0)) for s in result.get("segments", [])), default=0.0)
    if end > duration + 1.0:
        raise ReportError(f"{capture}: {duration:.1f} s long, but the result's segments run to {end:.1f} s: "
                          "not the result's capture")


def read_truth(capture: str) -> tuple[dict[str, float], dict[str, float]] | None:
    """The truth of a simulated capture (`CAPTURE.truth.json`, written by `calibd simulate`) under
    the result's estimate names and units: (the scenario's truth, the truth the data carry), or
    None when there is none or it cannot be read. The data carry the settled biases moved by
    temperature and by the session mean of the bias wander, which no calibration of this capture
    can tell from the bias: that is what an estimate is to be compared with (docs/accuracy.md)."""
    path = Path(f"{capture}.truth.json")
    try:
        record = json.loads(path.read_text())
        truth = Truth(**{f.name: record["truth"][f.name] for f in fields(Truth)})
        carried = Truth(**{f.name: getattr(truth, f.name) if f.name not in record.get("bias_during_capture", {})
                           else record["bias_during_capture"][f.name]["session"] for f in fields(Truth)})
        return truth.estimates(), carried.estimates()
    except (OSError, ValueError, KeyError, TypeError):
        return None


def segment_roles(segments: list[detect.Segment]) -> list[str]:
    """The protocol role of each segment: static, index turn (about 90 deg), full turn (a
    constant-rate part of a whole revolution), other turn."""
    full = {id(s) for s in detect.full_turns(segments)}
    roles = []
    for s in segments:
        if s.kind == "static":
            roles.append("static")
        elif id(s) in full:
            roles.append("full turn")
        elif abs(abs(s.angle_deg) - 90.0) <= INDEX_TURN_TOLERANCE_DEG:
            roles.append("index turn")
        else:
            roles.append("other turn")
    return roles


def warm_up_end_s(time_s: np.ndarray, temperature_c: np.ndarray | None, rule: WarmupConfig = WarmupConfig()) -> float:
    """The first time from which the temperature trend over the next `rule.window_s` (the whole
    rest when shorter) is within `rule.max_slope_c_per_h`: the daemon's warm-up criterion, read
    forwards over a whole capture. 0 without temperatures; the capture's end if it never settles."""
    if temperature_c is None or len(time_s) < 2:
        return 0.0
    seconds = np.floor(time_s - time_s[0]).astype(np.int64)  # 1-s means: the trend needs no more
    count = np.bincount(seconds)
    have = count > 0
    t = (np.bincount(seconds, time_s) / np.maximum(count, 1))[have]
    temp = (np.bincount(seconds, temperature_c) / np.maximum(count, 1))[have]
    width = int(min(rule.window_s, len(t)))
    if width < 2:
        return 0.0
    t0 = t - t[0]  # fewer digits lost in the sums

    def window_sums(x):
        c = np.concatenate(([0.0], np.cumsum(x)))
        return c[width:] - c[:-width]

    st, sy, stt, sty = window_sums(t0), window_sums(temp), window_sums(t0 * t0), window_sums(t0 * temp)
    slope = (width * sty - st * sy) / (width * stt - st * st) * 3600
    settled = np.flatnonzero(np.abs(slope) <= rule.max_slope_c_per_h)
    if not len(settled):
        return float(time_s[-1])
    return float(time_s[0] + np.flatnonzero(have)[settled[0]])  # the start of that second


# ---------------------------------------------------------------- figures

def _png(canvas, fig) -> bytes:
    buffer = io.BytesIO()
    canvas(fig).print_png(buffer)
    return buffer.getvalue()


def _new_figure(width_in: float, height_in: float):
    from matplotlib.figure import Figure as MplFigure

    return MplFigure(figsize=(width_in, height_in), dpi=100, layout="constrained")


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


def timeline_figure(canvas, whole: Session, segments, roles, warm_up: tuple[float, str]) -> Figure:
    from matplotlib.patches import Patch

    fig = _new_figure(11, 8.5)
    axes = fig.subplots(3, 1, sharex=True)
    traces = [("gyro [deg/s]", whole.gyro / DEG, "gyro {}"), ("accelerometer [m/s$^2$]", whole.acc, "acc {}")]
    for ax, (label, values, name) in zip(axes, traces):
        t, low, high, mean = envelope(whole.time_s, values)
        for k, axis in enumerate("XYZ"):
            ax.fill_between(t, low[:, k], high[:, k], color=AXIS_COLOURS[k], alpha=0.25, lw=0)
            ax.plot(t, mean[:, k], color=AXIS_COLOURS[k], lw=0.8, label=name.format(axis))
        ax.set_ylabel(label)
        ax.legend(loc="best", fontsize=8, ncols=3)
    temp_ax = axes[2]
    if whole.temperature_c is None:
        temp_ax.text(0.5, 0.5, "no temperatures in this datagram", transform=temp_ax.transAxes, ha="center")
        temp_ax.set_yticks([])
    else:
        t, low, high, mean = envelope(whole.time_s, whole.temperature_c[:, None])
        temp_ax.fill_between(t, low[:, 0], high[:, 0], color="k", alpha=0.2, lw=0)
        temp_ax.plot(t, mean[:, 0], color="k", lw=0.8, label="gyro temperature (mean of X, Y, Z)")
        temp_ax.legend(loc="lower right", fontsize=8)
    temp_ax.set_ylabel("temperature [degC]")
    temp_ax.set_xlabel("time from the first datagram [s]")
    span = float(whole.time_s[-1] - whole.time_s[0]) or 1.0
    for seg, role in zip(segments, roles):
        for ax in axes:
            ax.axvspan(seg.start_s, seg.end_s, color=ROLE_COLOURS[role], alpha=0.12 if role == "static" else 0.3, lw=0)
        width = (seg.end_s - seg.start_s) / span
        if seg.kind == "static" and width > 0.012:  # narrower ones get no room for a label
            axes[0].text((seg.start_s + seg.end_s) / 2, 0.5, f"{seg.up} up\nchi {seg.platform_angle_deg:.0f}°",
                         transform=axes[0].get_xaxis_transform(), ha="center", va="center", fontsize=8,
                         rotation=0 if width > 0.07 else 90, bbox={"facecolor": "white", "alpha": 0.7, "lw": 0})
    warm_end, warm_label = warm_up
    handles = [Patch(color=ROLE_COLOURS[r], alpha=0.35, label=r) for r in ROLE_COLOURS if r in roles]
    if warm_end > whole.time_s[0]:
        for ax in axes:
            ax.axvspan(float(whole.time_s[0]), warm_end, facecolor="none", edgecolor="#d62728", hatch="//", lw=0)
        handles.append(Patch(facecolor="none", edgecolor="#d62728", hatch="//", label=warm_label))
    if handles:
        fig.legend(handles=handles, loc="outside upper center", ncols=len(handles), fontsize=9)
    axes[2].set_xlim(float(whole.time_s[0]), float(whole.time_s[-1]))
    n_static = sum(r == "static" for r in roles)
    return Figure("timeline", "Session timeline",
                  f"Gyro, accelerometer and temperature against time (lines: means over "
                  f"{TIMELINE_BINS} bins, bands: each bin's min to max). Shaded: the {len(segments)} segments "
                  f"found ({n_static} statics, labelled with the IMU axis up and the platform angle chi); hatched: "
                  f"{f'{warm_label} up to {warm_end:.0f} s' if warm_end > whole.time_s[0] else 'no warm-up'}.",
                  _png(canvas, fig))


def earth_term(params: np.ndarray, chi: np.ndarray) -> np.ndarray:
    """The joint model's Earth-rate term (estimators/joint.py), N x 3 in rad/s, at platform angles
    chi (rad): v1 (A0 cos chi - A1 sin chi) + v2 (A0 sin chi + A1 cos chi), A = R_int^IMU of the
    fitted axis."""
    a = int_to_imu(*alpha_beta(params[2:5]))
    cos, sin = np.cos(chi)[:, None], np.sin(chi)[:, None]
    return params[0] * (a[:, 0] * cos - a[:, 1] * sin) + params[1] * (a[:, 0] * sin + a[:, 1] * cos)


def earth_rate_seen(fitted: JointFit) -> np.ndarray:
    """The gyros less every fitted term but the Earth rate's (the platform rate k chi', the
    offsets c, a drift when fitted), N x 3 rad/s: what the model says is Earth rate plus noise."""
    g, inp = fitted.fit.gyro, fitted.inp
    p = g.params
    rest = np.outer(g.chi_rate, p[2:5]) + p[5:8]
    if len(p) > 8:
        rest += np.outer(inp.time_s - inp.time_s.mean(), p[8:11])
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


def earth_rate_figure(canvas, session: Session, site: Site, segments, result: dict) -> Figure:
    joint_result = result.get("method") == "joint"
    options = result.get("options", {}) if joint_result else {}
    title = "Earth rate against the platform angle"
    try:
        fitted = joint_fit(session, site, JointOptions(bool(options.get("fixed_amplitude")),
                                                       bool(options.get("drift"))), segments)
    except CalibrationError as exc:
        return Figure("earth_rate", title, "", missing=f"no joint fit on this capture: {exc}")
    g = fitted.fit.gyro
    seen = earth_rate_seen(fitted) * DEG_H
    model = earth_term(g.params, g.chi) * DEG_H
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
    curve = earth_term(g.params, grid * DEG) * DEG_H

    fig = _new_figure(10, 7.5)
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
    amplitude, sigma = (x * DEG_H for x in g.amplitude_check)
    expected = float(np.hypot(*site.earth_rate_nav[:2])) * DEG_H
    yaw, yaw_sigma = fitted.fit.estimates["yaw"] / DEG, fitted.fit.sigmas["yaw"] / DEG
    seen_amplitude = (f"horizontal Earth rate fixed to Ω_E cos(lat) = {expected:.2f} deg/h"
                      if options.get("fixed_amplitude") else
                      f"fitted horizontal Earth rate {amplitude:.2f} ± {sigma:.2f} deg/h (Ω_E cos(lat) = "
                      f"{expected:.2f} deg/h)")
    fig.suptitle(f"{seen_amplitude}; yaw {yaw:.2f} ± {yaw_sigma:.2f} deg", fontsize=10)
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
    fig.legend(*top.get_legend_handles_labels(), loc="outside lower center", ncols=3, fontsize=8)
    note = "" if joint_result else (f" The result's method ({result.get('method')}) fits no sinusoid: this is "
                                    "the joint estimator's fit on the same segments.")
    stated = result["estimates"].get("yaw", {}).get("value")
    if joint_result and stated is not None and abs(stated - yaw) > 1e-6 + 1e-3 * yaw_sigma:
        note += (f" The fit redone here gives a yaw of {yaw:.4f} deg where the result has {stated:.4f} deg: the "
                 "result was made with other data, options or software.")
    caption = (f"The horizontal gyros less the fitted offsets and platform-rate terms, against the platform "
               f"angle: the Earth rate's horizontal component, a sinusoid whose phase is the yaw. Circles: the "
               f"mean of each of the {len(statics)} statics (error bars 1-sigma, white noise scaled by the "
               f"measured excess {g.noise_scale:.2f}); crosses: turn samples averaged in {TURN_BIN_DEG:.0f}° "
               f"bins of chi. Below: the residuals after the fitted sinusoid.{note}")
    return Figure("earth_rate", title, caption, _png(canvas, fig))


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
        label = (f"{noise.name}: RW {rw.value:.3g} {rw.unit}, BI {'< ' if falling else ''}{bi.value:.3g} {bi.unit}"
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
    ax.legend(fontsize=7, loc="upper right")


def allan_figure(canvas, session: Session, segments) -> Figure:
    title = "Allan deviation of the static data"
    try:
        channels = characterise(session, segments)
    except NoiseError as exc:
        return Figure("allan", title, "", missing=f"no Allan deviation: {exc}")
    groups = {}
    for name, noise in channels.items():
        groups.setdefault(name.split("_")[0], []).append(noise)
    fig = _new_figure(16, 5.5)
    for ax, (sensor, members) in zip(fig.subplots(1, len(groups)), groups.items()):
        ax.set_title(SENSOR_NAMES.get(sensor, sensor), fontsize=10)
        _allan_panel(ax, members)
    first = next(iter(channels.values()))
    caption = (f"Overlapping Allan deviation of each channel over the {first.static_s:.0f} s of static data in "
               f"{first.segments} statics, pooled (bands: 68 % interval). Guides in the channel's colour: "
               "dotted, slope -1/2 through the random walk (RW) read at 1 s (dot); dashed, the bias instability (BI, the "
               "curve's minimum, dot; '<' when the curve is still falling at its last tau); dash-dot, slope +1/2 "
               "through the rate random walk (RRW) when the curve rises again.")
    return Figure("allan", title, caption, _png(canvas, fig))


# ---------------------------------------------------------------- page

CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.8em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; }
td.num { text-align: right; font-family: monospace; }
tr.poor td { background: #fde8e8; }
.warning { color: #8a4b00; } .missing { color: #a00; font-style: italic; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; }
"""


def _e(text) -> str:
    return html.escape(str(text))


def _num(value: float | None, name: str, form: str = ".5f") -> str:
    """A table cell with a number shown as `form` (five decimals, as `calibd calibrate` prints) and
    kept whole in data-value."""
    if value is None:
        return f'<td class="num" data-name="{name}">n/a</td>'
    return f'<td class="num" data-name="{name}" data-value="{float(value)!r}">{float(value):{form}}</td>'


def _estimates_table(result: dict, thesis: dict, truth: tuple[dict, dict] | None) -> str:
    thesis_estimates = thesis.get("estimates", {})
    thesis_note = (f"thesis method ({_e(thesis['method'])})" if "method" in thesis
                   else f"thesis method: n/a ({_e(thesis['error'])})")
    scenario, carried = truth if truth else ({}, {})
    head = ["estimate", "value", "1-sigma", "unit", "quality", "thesis method", "truth", "truth in the data",
            "value - truth in the data"]
    rows = [f"<tr>{''.join(f'<th>{h}</th>' for h in head)}</tr>"]
    for name, e in result["estimates"].items():
        other = thesis_estimates.get(name)
        true = carried.get(name)
        error = None if true is None else e["value"] - true
        if name == "yaw" and error is not None:
            error = (error + 180.0) % 360.0 - 180.0
        quality = e.get("quality", "")
        rows.append(f'<tr class="{_e(quality)}" data-estimate="{_e(name)}"><td>{_e(name)}</td>'
                    f'{_num(e["value"], "value")}{_num(e.get("sigma"), "sigma", ".3g")}<td>{_e(e["unit"])}</td>'
                    f'<td>{_e(quality)}</td>{_num(None if other is None else other["value"], "thesis")}'
                    f'{_num(scenario.get(name), "truth")}{_num(true, "carried")}{_num(error, "error")}</tr>')
    notes = [f"<p>Beside the result: the {thesis_note} on the same capture"
             + (", and the truth of the simulation (CAPTURE.truth.json): the scenario's, and the one the data "
                "carry (biases moved by temperature and by the session mean of the bias wander, which no "
                "calibration of this capture can tell from the bias: what the estimate should find)."
                if truth else "; no truth file beside the capture.") + "</p>"]
    if thesis.get("warnings"):
        notes.append("<p>Thesis method notes:</p><ul>" + "".join(f"<li>{_e(w)}</li>" for w in thesis["warnings"])
                     + "</ul>")
    return f'<table id="estimates">{"".join(rows)}</table>' + "".join(notes)


def _checks(result: dict) -> str:
    checks = result.get("checks", {})
    lines = []
    earth = checks.get("earth_rate_horizontal_deg_h")
    if earth:
        lines.append(f"horizontal Earth rate seen by the gyros {earth['fitted']:.3f} ± {earth['sigma']:.3f} deg/h, "
                     f"expected {earth['expected']:.3f} deg/h")
    chi2 = checks.get("static_chi2")
    if chi2:
        lines.append(f"statics' mean residuals: chi-square {chi2['chi2']:.1f} for {chi2['dof']} degrees of freedom "
                     f"(p = {chi2['p_value']:.3g})")
    return "".join(f"<li>{_e(line)}</li>" for line in lines)


def _stream(result: dict, whole: Session) -> str:
    s = whole.stream
    duration = float(whole.time_s[-1]) + 1.0 / whole.rate_hz
    rows = [("datagrams", f"{s['datagrams']} datagrams"), ("CRC errors", f"{s['crc_errors']} spans"),
            ("lost samples", f"{s['lost_samples']} samples"), ("sensor restarts", f"{s['restarts']} restarts"),
            *([("datagrams with fault flags", f"{s['flagged_datagrams']} datagrams")] if "flagged_datagrams" in s else []),
            ("duration", f"{duration:.3f} s at {whole.rate_hz} Hz")]
    sensor = result.get("sensor", {})
    rows += [(label, sensor[key]) for key, label in (("serial_number", "serial number"),
                                                     ("part_number", "part number"), ("datagram_id", "datagram"))
             if sensor.get(key)]
    return '<table id="stream">' + "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in rows) + "</table>"


def _segments_table(segments, roles) -> str:
    head = "<tr><th>#</th><th>role</th><th>start [s]</th><th>end [s]</th><th>platform angle chi [deg]</th>" \
           "<th>turn angle [deg]</th><th>rate [deg/s]</th><th>up</th></tr>"
    rows = [head]
    for k, (s, role) in enumerate(zip(segments, roles), 1):
        turn = s.kind == "turn"
        rows.append(f"<tr><td>{k}</td><td>{_e(role)}</td><td class='num'>{s.start_s:.3f}</td>"
                    f"<td class='num'>{s.end_s:.3f}</td><td class='num'>{s.platform_angle_deg:.3f}</td>"
                    f"<td class='num'>{f'{s.angle_deg:.3f}' if turn else ''}</td>"
                    f"<td class='num'>{f'{s.rate_deg_s:.4f}' if turn else ''}</td><td>{_e(s.up or '')}</td></tr>")
    return '<table id="segments">' + "".join(rows) + "</table>"


def _figure_html(figure: Figure, directory: str) -> str:
    if figure.png is None:
        return f'<h2>{_e(figure.title)}</h2><p class="missing">{_e(figure.missing)}</p>'
    file = f"{directory}/{figure.name}.png"
    data = base64.b64encode(figure.png).decode("ascii")
    return (f'<h2>{_e(figure.title)}</h2><figure id="{figure.name}"><img src="data:image/png;base64,{data}" '
            f'alt="{_e(file)}" title="{_e(file)}"><figcaption>{_e(figure.caption)} '
            f'File: <a href="{_e(file)}">{_e(file)}</a></figcaption></figure>')


def render_html(result: dict, result_name: str, capture: str, whole: Session, segments, roles,
                warm_up: tuple[float, str], figures: list[Figure], thesis: dict, truth: dict | None,
                directory: str) -> str:
    site = result["site"]
    warnings = "".join(f'<li class="warning">{_e(w)}</li>' for w in result.get("warnings", [])) or "<li>none</li>"
    warm_end, warm_label = warm_up
    summary = (f"method {result.get('method')}; site latitude {site['latitude_deg']:.5f} deg, height "
               f"{site.get('height_m', 0.0):g} m, g0 {site.get('g0_m_s2', float('nan')):.5f} m/s^2; "
               f"{len(segments)} segments found; "
               + (f"{warm_label} up to {warm_end:.0f} s" if warm_end > whole.time_s[0] else "no warm-up in the capture"))
    body = [f"<h1>Calibration report</h1><p>Result <code>{_e(result_name)}</code> on capture "
            f"<code>{_e(capture)}</code>: {_e(summary)}.</p>",
            "<h2>Estimates</h2>", _estimates_table(result, thesis, truth),
            "<h2>Warnings</h2><ul>", warnings, "</ul>"]
    checks = _checks(result)
    if checks:
        body += ["<h2>Checks</h2><ul>", checks, "</ul>"]
    body += ["<h2>Stream</h2>", _stream(result, whole)]
    body += [_figure_html(f, directory) for f in figures]
    body += ["<h2>Segments found</h2>", _segments_table(segments, roles)]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>Calibration report: {_e(Path(capture).name)}</title><style>{CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")


def _write(output: Path, figures: list[Figure], page: str) -> list[Path]:
    """The PNGs, then the page: each file appears whole or not at all."""
    directory = figures_dir(output)
    written = [output]
    try:
        directory.mkdir(exist_ok=True)
        for f in figures:
            if f.png is not None:
                path = directory / f"{f.name}.png"
                write_atomic(path, f.png, durable=False)  # figures can be made again: no sync
                written.append(path)
        write_atomic(output, page.encode(), durable=False)
    except OSError as exc:
        raise ReportError(f"{output}: cannot write: {(exc.strerror or str(exc)).lower()}") from None
    return written

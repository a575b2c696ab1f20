"""The calibration report: one self-contained HTML page, and its figures as PNG files beside it
(and as SVG on request).

A result file holds numbers; the report shows what they rest on. On the capture the result was
made from (decoded by the caller), it finds the segments again and draws the session's timeline, the Earth-rate
sinusoid the horizontal gyros see against the platform angle, and the Allan deviation of the
static data; it tables every estimate with its 1-sigma beside the thesis method's value on the
same capture and, for a simulated capture, the truth and the error in sigma. `report.html` embeds
the figures (data URIs, inline CSS: it can be mailed or archived alone); `report_files/*.png` are
the same figures, and `*.svg` their vector copies when asked for (`svg=True`: a second drawing
of each figure).

matplotlib (the optional extra `[plot]`) is imported only inside the functions here and in
`calibd.figures`, and draws with its Agg back end (SVG's for the vector copies): the other
commands never load it, and no display is needed.
"""

from __future__ import annotations

import base64
import html
import math
import os
import secrets
import shutil
from pathlib import Path

from stim300.atomic import atomic_file, in_place, write_atomic
from stim300.cliutil import DOCUMENT_LIMIT_BYTES, read_input
from stim300.errors import UsageError
from stim300.progress import Progress

from . import detect
from .warmup import warm_up_end_s, warm_up_label
from .errors import CalibdError, CalibrationError, SiteError
from .methods import estimator, progress
from .figures import (DPI, FIGURE_WIDTH_IN, Figure, allan_figure, earth_rate_figure, need_matplotlib, platform_axis,
                      timeline_figure)
from .frames import Site
from .results import CalibrationResult, parse_result
from .scenario import ScenarioError, truth_from_json
from .segments import segment_record, session_segments
from .session import CaptureSessions, Session, power_up_session
from .units import fixed, value_sigma_texts

MATPLOTLIB_MISSING = "calibd report needs matplotlib: pip install 'stim300-calib[plot]'"
STEPS = ("capture", "segments", "timeline", "Earth-rate fit", "Allan deviation", "thesis method", "files")


class ReportError(CalibdError):
    """The report cannot be made from these inputs (matplotlib missing, wrong capture, unwritable output)."""


def figures_dir(output) -> Path:
    """Where the PNGs go: `report.html` -> `report_files/`."""
    output = Path(output)
    return output.with_name(f"{output.stem}_files")


def write_report(result_path, capture: CaptureSessions, output, stream=None, svg: bool = False) -> list[Path]:
    """Render the report of the result at `result_path` on the decoded `capture` to `output` and
    its figures directory (with each figure's SVG beside its PNG when `svg`); returns the files
    written, the HTML first. A progress bar goes to `stream` (stderr) when it is a terminal.
    ReportError (or UsageError, for a result file that is not a regular file) for inputs it cannot
    use, OSError when the files cannot be written."""
    need_matplotlib(MATPLOTLIB_MISSING, ReportError)
    # a regular file of bounded size; parse_result checks the schema, the estimates and the site
    result = parse_result(read_input(result_path, "result file", DOCUMENT_LIMIT_BYTES), result_path)
    site = _site(result, result_path)
    output = Path(output)
    _check_writable(output)
    with Progress("report", len(STEPS), "steps", stream) as bar:
        bar.update(0, STEPS[0])
        skipped_s = float(result.stream.start_s or 0.0)
        start_s = analysis_start_s(result)
        power_up = None if result.stream.power_up is None else result.stream.power_up.number
        _check_identity(result, result_path, capture)
        whole = power_up_session(capture, power_up, 0.0)
        _check_same_capture(result, whole, capture.path)
        session = power_up_session(capture, power_up, start_s) if start_s > 0 else whole
        bar.update(1, STEPS[1])
        segments = session_segments(session)
        roles = detect.segment_roles(segments)
        warm_up = (skipped_s, "warm-up skipped by the result") if skipped_s > 0 else (
            warm_up_end_s(whole.time_s, whole.temperature_c), warm_up_label())
        bar.update(2, STEPS[2])
        figures = [timeline_figure(whole, segments, roles, warm_up, platform_axis(result))]
        bar.update(3, STEPS[3])
        figures.append(earth_rate_figure(session, site, segments, result))
        bar.update(4, STEPS[4])
        figures.append(allan_figure(session, segments))
        bar.update(5, STEPS[5])
        thesis = thesis_comparison(session, site, segments)
        bar.update(6, STEPS[6])
        page = render_html(result, str(result_path), capture.path, whole, segments, roles, warm_up, figures, thesis,
                           read_truth(capture.path), figures_dir(output).name, svg)
        written = _write(output, figures, page, svg)
        bar.update(len(STEPS))
    return written


def thesis_comparison(session: Session, site: Site, segments: list[detect.Segment]) -> CalibrationResult | str:
    """The thesis method's result on the same segments, or why there is none: what its campaign
    lacks, in the words of the session's progress record (the daemon's, so the two never
    disagree), else what the data cannot give."""
    record = progress("thesis", segments)
    if not record.complete:
        return f"its campaign lacks {record.missing}; found {record.found()}"
    method = estimator("thesis")
    try:
        return method.solve(session, site, segments, method.options({}))
    except CalibrationError as exc:
        return str(exc)


# ---------------------------------------------------------------- inputs

def _site(result: CalibrationResult, path) -> Site:
    try:
        site = result.site
        return Site(site["latitude_deg"], site.get("height_m", 0.0), site.get("g0_m_s2"))
    except (KeyError, TypeError, SiteError) as exc:
        raise ReportError(f"{path}: no usable site in the result ({exc})") from None


def _check_writable(output: Path) -> None:
    """Refuse before the work rather than after it."""
    parent, figures = output.parent, figures_dir(output)
    if output.is_dir():
        raise ReportError(f"{output}: is a directory, expected an HTML file name")
    if in_place(output):  # a device or FIFO: nothing goes beside it
        return
    if not parent.is_dir():
        raise ReportError(f"{output}: cannot write: no such directory {parent}")
    if not os.access(parent, os.W_OK):
        raise ReportError(f"{output}: cannot write: permission denied")
    if os.path.lexists(figures) and (figures.is_symlink() or not figures.is_dir()):
        raise ReportError(f"{figures}: not a directory (a symbolic link is not followed): the report's figures "
                          "go there; move it away")


def analysis_start_s(result: CalibrationResult) -> float:
    """Where the result's data began in its capture: the start offset it records (stream.start_s,
    `calibd calibrate --start`), else its first segment's start (results of older versions do not
    record the offset, but their segments begin after it). The segments found from there are the
    result's."""
    recorded = result.stream.start_s
    if recorded:
        return float(recorded)
    first = min((float(s["start_s"]) for s in result.segments if "start_s" in s), default=0.0)
    return max(first - 1e-6, 0.0)  # the record is rounded to 1 ms: keep the first sample


def _check_identity(result: CalibrationResult, result_path, capture: CaptureSessions) -> None:
    """A report on other data than the result's would put its numbers under figures of something
    else: refused. A result of `calibd calibrate` names its capture by size and SHA-256; another
    capture of the same length and datagram count (the other turning sense, say) differs there."""
    recorded = result.capture
    if recorded is None:
        return
    made_from = f"{result_path} was made from {recorded.get('path')}"
    if recorded["size_bytes"] != capture.identity["size_bytes"]:
        raise ReportError(f"{capture.path}: {capture.identity['size_bytes']} bytes, but {made_from} of "
                          f"{recorded['size_bytes']} bytes: not the result's capture")
    if recorded["sha256"] != capture.identity["sha256"]:
        raise ReportError(f"{capture.path}: SHA-256 {capture.identity['sha256'][:16]}..., but {made_from} of the "
                          f"same size with SHA-256 {recorded['sha256'][:16]}...: not the result's capture")


def _check_same_capture(result: CalibrationResult, whole: Session, capture: str) -> None:
    """For a result that does not name its capture's bytes (the daemon's, older versions): the
    datagram count (recorded by `calibd calibrate`) must match, and the segments lie inside the
    capture."""
    recorded = result.stream.datagrams
    have = whole.stream.datagrams
    if recorded is not None and recorded != have:
        raise ReportError(f"{capture}: {have} datagrams, but the result was made from a capture of {recorded} "
                          f"datagrams ({result.stream.capture}): not the result's capture")
    duration = float(whole.time_s[-1]) + 1.0 / whole.rate_hz
    end = max((float(s.get("end_s", 0.0)) for s in result.segments), default=0.0)
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
    try:  # the truth file's schema: calibd.documents.TruthDoc
        truth, carried = truth_from_json(read_input(path, "truth file", DOCUMENT_LIMIT_BYTES), path)
        return truth.estimates(), carried.estimates()
    except (UsageError, ScenarioError):  # a FIFO or device of that name too
        return None


FAR_SIGMAS = 3.0  # an error beyond this many sigma is highlighted: the sigma or the estimate is wrong
CSS = (  # the page is as wide as the figures' pixels: they show at their own size, text as sized
    f"\nbody {{ font-family: sans-serif; margin: 2em auto; padding: 0 1em; max-width: {FIGURE_WIDTH_IN * DPI:.0f}px; "
    "color: #222; }" + """
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.8em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; }
td.num { text-align: right; font-family: monospace; }
tr.poor td { background: #fde8e8; }
.warning { color: #8a4b00; } .missing { color: #a00; font-style: italic; }
figure { margin: 1em 0; } figure img { max-width: 100%; height: auto; box-sizing: border-box; border: 1px solid #ddd; }
td.far { background: #fbd3d3; font-weight: bold; }
figcaption { font-size: 0.9em; color: #444; }
""")


def _e(text) -> str:
    return html.escape(str(text))


def _num(value: float | None, name: str, decimals: int = 5, far: float = math.inf, text: str | None = None) -> str:
    """A table cell with a number shown as `text`, else to `decimals` decimals, and kept whole in
    data-value; highlighted beyond +-`far`."""
    if value is None:
        return f'<td class="num" data-name="{name}">n/a</td>'
    kind = "num far" if abs(value) > far else "num"
    text = fixed(float(value), decimals) if text is None else text
    return f'<td class="{kind}" data-name="{name}" data-value="{float(value)!r}">{text}</td>'


def _estimates_table(result: CalibrationResult, thesis: CalibrationResult | str,
                     truth: tuple[dict, dict] | None) -> str:
    """`thesis`: the thesis method's result on the same data, or why there is none."""
    solved = isinstance(thesis, CalibrationResult)
    thesis_estimates = thesis.estimates if solved else {}
    thesis_note = f"thesis method ({_e(thesis.method)})" if solved else f"thesis method: n/a ({_e(thesis)})"
    scenario, carried = truth if truth else ({}, {})
    head = ["estimate", "value", "1-sigma", "unit", "quality", "thesis method", "truth", "truth in the data",
            "value - truth in the data"] + (["error / sigma"] if truth else [])
    rows = [f"<tr>{''.join(f'<th>{h}</th>' for h in head)}</tr>"]
    for name, e in result.estimates.items():
        other = thesis_estimates.get(name)
        true = carried.get(name)
        error = None if true is None else e.value - true
        if name == "yaw" and error is not None:
            error = (error + 180.0) % 360.0 - 180.0
        quality = e.quality or ""
        in_sigmas = "" if not truth else _num(None if error is None or not e.sigma else error / e.sigma,
                                               "error_sigmas", 1, FAR_SIGMAS)
        value_text, sigma_text = value_sigma_texts(e.value, e.sigma)  # rounded where the sigma says
        rows.append(f'<tr class="{_e(quality)}" data-estimate="{_e(name)}"><td>{_e(name)}</td>'
                    f'{_num(e.value, "value", text=value_text)}{_num(e.sigma, "sigma", text=sigma_text)}'
                    f'<td>{_e(e.unit)}</td>'
                    f'<td>{_e(quality)}</td>{_num(None if other is None else other.value, "thesis")}'
                    f'{_num(scenario.get(name), "truth")}{_num(true, "carried")}{_num(error, "error")}'
                    f'{in_sigmas}</tr>')
    notes = [f"<p>Beside the result: the {thesis_note} on the same capture"
             + (", and the truth of the simulation (CAPTURE.truth.json): the scenario's, and the one the data "
                "carry (biases moved by temperature and by the session mean of the bias wander, which no "
                "calibration of this capture can tell from the bias: what the estimate should find); the error "
                f"in units of the result's 1-sigma, highlighted beyond {FAR_SIGMAS:g} sigma."
                if truth else "; no truth file beside the capture.") + "</p>"]
    if solved and thesis.warnings:
        notes.append("<p>Thesis method notes:</p><ul>" + "".join(f"<li>{_e(w)}</li>" for w in thesis.warnings)
                     + "</ul>")
    return f'<table id="estimates">{"".join(rows)}</table>' + "".join(notes)


def _checks(result: CalibrationResult) -> str:
    checks = result.checks or {}
    lines = []
    earth = checks.get("earth_rate_horizontal_deg_h")
    if earth:
        lines.append(f"horizontal Earth rate seen by the gyros {earth['fitted']:.3f} ± {earth['sigma']:.3f} deg/h, "
                     f"expected {earth['expected']:.3f} deg/h")
    chi2 = checks.get("static_chi2")
    if chi2:
        lines.append(f"statics' mean residuals: chi-square {chi2['chi2']:.1f} for {chi2['dof']} degrees of freedom "
                     f"(p = {chi2['p_value']:.3g})")
    second = checks.get("second_mounting")
    if second:
        total, predicted, sigma = (second[k] for k in ("tilt_sum_mrad", "predicted_mrad", "sigma_mrad"))
        lines.append(f"second mounting {second.get('path') or second['sha256'][:16]} (power-up {second['power_up']}), "
                     f"the housing turned 180 deg: its alpha {second['alpha_deg']:.5f} deg, beta "
                     f"{second['beta_deg']:.5f} deg; the two tilts sum to ({total[0]:.4f}, {total[1]:.4f}) mrad "
                     f"against ({predicted[0]:.4f} ± {sigma[0]:.4f}, {predicted[1]:.4f} ± {sigma[1]:.4f}) mrad "
                     f"the factory residuals allow (p = {second['p_value']:.3g})")
    return "".join(f"<li>{_e(line)}</li>" for line in lines)


def _stream(result: CalibrationResult, whole: Session) -> str:
    s = whole.stream
    duration = float(whole.time_s[-1]) + 1.0 / whole.rate_hz
    rows = [("datagrams", f"{s.datagrams} datagrams"), ("CRC errors", f"{s.crc_errors} spans"),
            ("lost samples", f"{s.lost_samples} samples"), ("sensor restarts", f"{s.restarts} restarts"),
            ("datagrams with fault flags", f"{s.flagged_datagrams} datagrams"),
            ("duration", f"{duration:.3f} s at {whole.rate_hz} Hz")]
    sensor = result.sensor
    rows += [(label, value) for value, label in ((sensor.serial_number, "serial number"),
                                                 (sensor.part_number, "part number"), (sensor.datagram_id, "datagram"))
             if value]
    return '<table id="stream">' + "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in rows) + "</table>"


def _segments_table(segments, roles) -> str:
    head = "<tr><th>#</th><th>role</th><th>start [s]</th><th>end [s]</th><th>platform angle chi [deg]</th>" \
           "<th>heading [deg]</th><th>turn angle [deg]</th><th>rate [deg/s]</th><th>up</th></tr>"
    rows = [head]
    for k, (s, role) in enumerate(zip(segments, roles), 1):
        r = segment_record(s, role)
        turn = r["kind"] == "turn"
        cells = [f"{r['start_s']:.3f}", f"{r['end_s']:.3f}", f"{r['platform_angle_deg']:.3f}",
                 f"{detect.heading_deg(s.platform_angle_deg):.1f}",
                 f"{r['angle_deg']:.3f}" if turn else "", f"{r['rate_deg_s']:.4f}" if turn else ""]
        rows.append(f"<tr><td>{k}</td><td>{_e(role)}</td>" + "".join(f"<td class='num'>{c}</td>" for c in cells)
                    + f"<td>{_e(r.get('up', ''))}</td></tr>")
    return '<table id="segments">' + "".join(rows) + "</table>"


def _figure_html(figure: Figure, directory: str, svg: bool) -> str:
    """The figure embedded, its PNG named and linked, and its SVG linked only when written."""
    if figure.png is None:
        return f'<h2>{_e(figure.title)}</h2><p class="missing">{_e(figure.missing)}</p>'
    file, vector = (f"{directory}/{figure.name}.{suffix}" for suffix in ("png", "svg"))
    data = base64.b64encode(figure.png).decode("ascii")
    files = (f'Files: <a href="{_e(file)}">{_e(file)}</a>, <a href="{_e(vector)}">{_e(vector)}</a> (vector)' if svg
             else f'File: <a href="{_e(file)}">{_e(file)}</a>')
    return (f'<h2>{_e(figure.title)}</h2><figure id="{figure.name}"><img src="data:image/png;base64,{data}" '
            f'alt="{_e(file)}" title="{_e(file)}"><figcaption>{_e(figure.caption)} {files}</figcaption></figure>')


def render_html(result: CalibrationResult, result_name: str, capture: str, whole: Session, segments, roles,
                warm_up: tuple[float, str], figures: list[Figure], thesis: CalibrationResult | str,
                truth: dict | None, directory: str, svg: bool) -> str:
    site = result.site
    warnings = "".join(f'<li class="warning">{_e(w)}</li>' for w in result.warnings) or "<li>none</li>"
    warm_end, warm_label = warm_up
    summary = (f"method {result.method}; site latitude {site['latitude_deg']:.5f} deg, height "
               f"{site.get('height_m', 0.0):g} m, g0 {site.get('g0_m_s2', float('nan')):.5f} m/s^2; "
               f"{len(segments)} segments found; "
               + (f"{warm_label} up to {warm_end:.0f} s" if warm_end > whole.time_s[0]
                  else "no warm-up in the capture"))
    body = [f"<h1>Calibration report</h1><p>Result <code>{_e(result_name)}</code> on capture "
            f"<code>{_e(capture)}</code>: {_e(summary)}.</p>",
            "<h2>Estimates</h2>", _estimates_table(result, thesis, truth),
            "<h2>Warnings</h2><ul>", warnings, "</ul>"]
    checks = _checks(result)
    if checks:
        body += ["<h2>Checks</h2><ul>", checks, "</ul>"]
    body += ["<h2>Stream</h2>", _stream(result, whole)]
    body += [_figure_html(f, directory, svg) for f in figures]
    body += ["<h2>Segments found</h2>", _segments_table(segments, roles)]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>Calibration report: {_e(Path(capture).name)}</title><style>{CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")


def _write(output: Path, figures: list[Figure], page: str, svg: bool) -> list[Path]:
    """The page and its figures directory (the PNGs, and the SVGs when `svg`), each whole or not at
    all; OSError (a full disk) leaves nothing of this run behind. The figures go into a new
    directory beside the output, which replaces `report_files/` only once the page is written too;
    the page is renamed into place last. Nothing is written through a symbolic link: the directory
    is made by this run and its files are new. A page that is a device or FIFO (`-o /dev/stdout`)
    has no beside: the page only, which embeds the figures."""
    if in_place(output):
        write_atomic(output, page.encode(), durable=False)
        return [output]
    directory = figures_dir(output)
    fresh = directory.with_name(f".{directory.name}.{secrets.token_hex(4)}.part")
    written = [output]
    os.mkdir(fresh)
    try:
        with atomic_file(output, durable=False) as f:
            for figure in (f for f in figures if f.png is not None):
                for suffix, data in [("png", figure.png)] + ([("svg", figure.svg())] if svg else []):
                    name = f"{figure.name}.{suffix}"
                    write_atomic(fresh / name, data, durable=False, follow=False)  # can be made again: no sync
                    written.append(directory / name)
            f.write(page.encode())
            f.flush()  # a full disk fails here, before the old figures go
            _replace_directory(fresh, directory)
    finally:
        shutil.rmtree(fresh, ignore_errors=True)  # gone already when it took the figures' place
    return written


def _replace_directory(fresh: Path, directory: Path) -> None:
    """`fresh` renamed to `directory`; an old one there (a real directory, `_check_writable`) is
    moved aside first and removed after, or put back when the rename fails."""
    old = fresh.with_suffix(".old")
    try:
        os.rename(directory, old)
    except FileNotFoundError:
        old = None
    try:
        os.rename(fresh, directory)
    except OSError:
        if old is not None:
            os.rename(old, directory)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)

"""The fleet report's HTML page (`calibd fleet --html`): one self-contained file, each unit's table
and one figure per estimate group (mounting, platform axis, gyro, accelerometer and inclinometer
biases) embedded as base64 PNG, so it can be mailed or archived alone.

Each panel is one estimate's history: every result with its 1-sigma, poor ones hollow and grey,
the history's mean, the band within which the latest is in family (the 3-sigma prediction
interval of calibd.fleet) and, for a bias with a datasheet figure, the mean +- that figure. A
mount that moved shows as a step in the mounting figure. matplotlib (the extra `[plot]`) is
imported inside the functions only and draws with its Agg back end.
"""

from __future__ import annotations

import base64
import datetime
import html
import io

import numpy as np

from .fleet import (GROUPS, HEADINGS, NAMES, OUT_OF_FAMILY_SIGMAS, UNITS, Fleet, FleetReportError, Unit, Verdict,
                    datasheet, display, flags, pooled_rows, summary, unit_rows, when)
from .figures import DPI, FIGURE_WIDTH_IN, STYLE, need_matplotlib
from .report import CSS

MATPLOTLIB_MISSING = "calibd fleet --html needs matplotlib: pip install 'stim300-calib[plot]'"
PANEL_HEIGHT_IN = 3.2
COLOURS = {"history": "#1f77b4", "poor": "#999999", "latest": "#222222", "out": "#d62728"}
FLEET_CSS = "tr.out td { background: #fbd3d3; font-weight: bold; } ul.flags li { margin: 0.3em 0; }\n"


def _e(text) -> str:
    return html.escape(str(text))


def _pm(text: str) -> str:
    """The text report's ASCII +- as the page's ±."""
    return text.replace(" +- ", " ± ")


def group_figure(unit: Unit, v: Verdict, names: tuple[str, ...]) -> bytes:
    """One PNG: a panel per estimate of `names` that some result of the unit has."""
    from matplotlib import rc_context
    from matplotlib.dates import AutoDateLocator, ConciseDateFormatter
    from matplotlib.figure import Figure

    shown = [NAMES.index(n) for n in names if np.isfinite(unit.values[:, NAMES.index(n)]).any()]
    with rc_context(STYLE):
        fig = Figure(figsize=(FIGURE_WIDTH_IN, PANEL_HEIGHT_IN), dpi=DPI, layout="constrained")
        axes = fig.subplots(1, len(shown), squeeze=False)[0]
        limits = v.limit()
        for ax, k in zip(axes, shown):
            _panel(ax, unit, v, k, limits[k])
            locator = AutoDateLocator(minticks=3, maxticks=6)
            ax.xaxis.set_major_locator(locator)
            ax.xaxis.set_major_formatter(ConciseDateFormatter(locator))
        handles = {label: h for ax in axes for h, label in zip(*ax.get_legend_handles_labels())}
        fig.legend(handles.values(), handles.keys(), loc="outside lower center", ncols=min(len(handles), 4))
        png = io.BytesIO()
        fig.savefig(png, format="png")
    return png.getvalue()


def _panel(ax, unit: Unit, v: Verdict, k: int, limit: float) -> None:
    name = NAMES[k]
    times = np.array([None if t is None else t.astimezone(datetime.timezone.utc).replace(tzinfo=None)
                      for t in unit.times], dtype="datetime64[us]")  # UTC: the axis's dates have no zone
    values, sigmas = unit.values[:, k], np.nan_to_num(unit.sigmas[:, k])
    if name == "yaw":  # drawn around the history's mean in [-180, 180)
        values = values - v.mean[k] + display(name, v.mean[k]) if np.isfinite(v.mean[k]) else values
    mean = display(name, v.mean[k]) if np.isfinite(v.mean[k]) else np.nan
    earlier = np.arange(len(values)) < len(values) - 1
    for mask, colour, label, face in ((earlier & ~unit.poor[:, k], COLOURS["history"], "earlier results", None),
                                      (unit.poor[:, k], COLOURS["poor"], "poor (not used)", "none")):
        if mask.any():
            ax.errorbar(times[mask], values[mask], sigmas[mask], fmt="o", color=colour, mfc=face, ms=5, capsize=3,
                        label=label)
    out = bool(v.flagged[k])
    if not unit.poor[-1, k] and np.isfinite(values[-1]):
        ax.errorbar(times[-1:], values[-1:], sigmas[-1:], fmt="D", ms=7, capsize=3,
                    color=COLOURS["out" if out else "latest"],
                    label=f"latest, out of family (> {OUT_OF_FAMILY_SIGMAS:g} sigma)" if out else "latest")
    if np.isfinite(mean):
        ax.axhline(mean, color=COLOURS["history"], lw=0.9, ls="-", label="history mean")
        if np.isfinite(limit):
            ax.axhspan(mean - limit, mean + limit, color=COLOURS["history"], alpha=0.12, lw=0,
                       label=f"in family ({OUT_OF_FAMILY_SIGMAS:g}-sigma prediction interval)")
        figure, _ = datasheet(name, unit)
        if figure is not None:
            for sign in (-1, 1):
                ax.axhline(mean + sign * figure, color="#8a4b00", lw=0.9, ls=":",
                           label="history mean ± datasheet figure")
    ax.set_title(f"{name}: {_verdict_text(v, k)}", color=COLOURS["out"] if out else "black")
    ax.set_ylabel(f"{name} [{UNITS[name]}]")
    ax.grid(alpha=0.3)


def _verdict_text(v: Verdict, k: int) -> str:
    if v.untested[k]:
        return "not tested"
    return f"latest {v.sigmas[k]:.1f} sigma" + (", OUT OF FAMILY" if v.flagged[k] else "")


def _table(rows: list[dict[str, str]], flagged: set[str]) -> str:
    rows = [r | {"latest": _pm(r["latest"])} for r in rows]
    head = "".join(f"<th>{_e(_pm(h))}</th>" for h in HEADINGS.values())
    out = ' class="out"'
    body = "".join(f'<tr data-estimate="{_e(r["estimate"])}"{out if r["estimate"] in flagged else ""}>'
                   + "".join(f'<td class="num">{_e(r[key])}</td>' if key in ("latest", "mean")
                             else f"<td>{_e(r[key])}</td>" for key in HEADINGS) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _unit_section(unit: Unit, v: Verdict) -> str:
    flagged = {NAMES[k] for k in np.flatnonzero(v.flagged)}
    parts = [f'<h2 id="unit-{_e(unit.serial)}">{_e(unit.serial)}</h2>',
             f"<p>{len(unit.times)} results, latest {_e(when(unit.times[-1]))}.</p>",
             _table(unit_rows(unit, v), flagged)]
    for group, names in GROUPS.items():
        if not any(np.isfinite(unit.values[:, NAMES.index(n)]).any() for n in names):
            continue
        data = base64.b64encode(group_figure(unit, v, names)).decode("ascii")
        alt = f"{unit.serial}: {group} over time"
        parts.append(f'<figure class="group" data-serial="{_e(unit.serial)}" data-group="{_e(group)}">'
                     f'<img src="data:image/png;base64,{data}" alt="{_e(alt)}"><figcaption>{_e(alt)}: each '
                     "result with its 1-sigma.</figcaption></figure>")
    return "\n".join(parts)


def render_html(fleet: Fleet) -> str:
    """The whole page (no file or network reference: figures and style inline)."""
    need_matplotlib(MATPLOTLIB_MISSING, FleetReportError)
    found = flags(fleet)
    flag_items = "".join(f'<li data-serial="{_e(u.serial)}" data-estimate="{_e(name)}">{_e(_pm(text))}</li>'
                         for u, name, text in found) or "<li>none</li>"
    index = " ".join(f'<a href="#unit-{_e(u.serial)}">{_e(u.serial)}</a>' for u in fleet.units)
    body = [f"<h1>Fleet report</h1><p>{_e(summary(fleet))}</p><p>Units: {index}</p>",
            f"<h2>Out of family</h2><p>Latest results beyond {OUT_OF_FAMILY_SIGMAS:g} sigma of the unit's history "
            "(a Student-t prediction interval on the history's run-to-run scatter and the results' 1-sigma; "
            "the fleet's pooled scatter where a unit has fewer earlier results than the rule needs).</p>"
            f'<ul class="flags" id="flags">{flag_items}</ul>',
            "<h2>Run-to-run spread of the fleet</h2><p>Every unit's earlier results about its own mean, pooled, "
            "beside the STIM300 datasheet TS1524 rev.31 figure.</p><pre>"
            + _e("\n".join(line.strip() for line in pooled_rows(fleet))) + "</pre>"]
    body += [_unit_section(u, v) for u, v in zip(fleet.units, fleet.verdicts)]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>Fleet report: {_e(fleet.table)}</title><style>{CSS}{FLEET_CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")

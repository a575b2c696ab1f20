"""What `calibd watch` shows (as gpsmon/cgps show a receiver): the daemon's state and campaign
progress, every estimate with its sigma and unit, the result's staleness, stream health, the
device and, when samples are watched, their rate and live values. `WatchView` gathers the
messages; `render` (view -> lines, fitted to a terminal's width) and `WatchView.update`'s event
line are the text, kept free of the terminal so tests read them directly.
"""

from __future__ import annotations

import re
import textwrap
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .client import (Correction, Device, Error, Fault, Message, Overflow, Poll, Result, Samples, State, Version,
                     Watch)
from .results import CalibrationResult
from .units import estimate_rows, value_sigma

RATE_WINDOW_S = 2.0  # stream time the measured sample rate is averaged over
MEAN_WINDOW_S = 1.0  # stream time each axis's live mean is taken over
BLOCKS = (("gyro", "deg/s"), ("acc", "g"), ("incl", "g"))  # blocks and their usual units (DEVICE may say others)
LABEL_WIDTH = 9  # "progress " : a wrapped line goes on under the text after its label
_NUMBER_UNIT = re.compile(r"(\d) (?=(deg/s|deg/h|deg|Hz|mg|g|s)\b)")  # kept on one line when wrapping
SAMPLES_LINE_EVERY_S = 10.0  # plain lines: the sample rate and live values are said this often (stream time)
# progress keys end in their unit; longest first, so "_deg_s" is not read as "_s"
_SUFFIX_UNITS = (("_deg_s", "deg/s"), ("_deg_h", "deg/h"), ("_deg", "deg"), ("_hz", "Hz"), ("_mg", "mg"),
                 ("_s", "s"))


def progress_text(progress: dict) -> str:
    """A flat progress object in words: whatever keys it has, units taken from their names;
    `missing` last, and "campaign complete" where it is null."""
    parts = []
    for key, value in progress.items():
        if key == "missing":
            continue
        name, unit = key, ""
        for suffix, suffix_unit in _SUFFIX_UNITS:
            if key.endswith(suffix):
                name, unit = key[:-len(suffix)], f" {suffix_unit}"
                break
        if isinstance(value, bool):
            text = "yes" if value else "no"
        elif isinstance(value, float):
            text = f"{value:.1f}{unit}"
        else:
            text = f"{value}{unit}"
        parts.append(f"{name.replace('_', ' ')} {text}")
    if "missing" in progress:
        parts.append(f"missing: {progress['missing']}" if progress["missing"] else "campaign complete")
    return ", ".join(parts) if parts else "-"


def stale_text(result: CalibrationResult) -> str | None:
    """Why the result no longer applies, or None while it does."""
    if result.stale is None:
        return None
    return f"STALE: the {result.stale.power_up} power-up's result ({result.stale.reason})"


def _result_head(result: CalibrationResult) -> str:
    span = "" if result.session is None else f", {result.session.duration_s:.1f} s of data"
    return f"{result.method}{span}"


def _counts(counts: dict, increase: dict) -> str:
    return ", ".join(f"{name} {count}" + (f" (+{increase[name]})" if increase.get(name) else "")
                     for name, count in counts.items()) or "none"


def correction_text(correction: Correction) -> str:
    """The biases the corrected outputs now subtract, and since when."""
    since = "" if correction.from_t is None else f" from t = {correction.from_t:.6f} s"
    biases = ", ".join(f"{name} {value:+.4g} {unit}" for name, (value, unit) in correction.new.items())
    return f"{correction.policy} result {correction.session_id}{since}: {biases}"


def _device_text(device: Device) -> str:
    rate = "" if device.rate_hz is None else f", {device.rate_hz:g} Hz"
    units = ", ".join(f"{block} {unit}" for block, unit in device.units.items())
    return (f"{device.path}: part {device.part_number or '?'}, serial {device.serial_number or '?'}, "
            f"datagram {device.datagram_id or '?'}{rate}" + (f"; units {units}" if units else ""))


@dataclass
class WatchView:
    """What the messages so far say, with the host time (s, monotonic) each part was last heard."""

    where: str
    version: Version | None = None
    device: Device | None = None
    state: State | None = None
    state_since_s: float | None = None
    result: CalibrationResult | None = None
    result_at_s: float | None = None
    faults: Fault | None = None
    correction: Correction | None = None
    overflow_dropped: int = 0
    samples_kind: str = "none"
    recent: deque = field(default_factory=deque)  # the SAMPLES of the last RATE_WINDOW_S of stream time
    samples_said_t: float | None = None
    last_error: str | None = None

    def sample_rate_hz(self) -> float | None:
        """Samples per second of stream time over the last RATE_WINDOW_S."""
        count = sum(len(s.t) for s in self.recent)
        if count < 2:
            return None
        span = float(self.recent[-1].t[-1] - self.recent[0].t[0])
        return (count - 1) / span if span > 0 else None

    def sample_values(self) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
        """(block, unit, last sample, mean of the last MEAN_WINDOW_S of stream time) of each block
        the samples carry, per axis x, y, z, in the units DEVICE gives (else the sensor's usual)."""
        if not self.recent:
            return []
        since_s = float(self.recent[-1].t[-1]) - MEAN_WINDOW_S
        units = self.device.units if self.device else {}
        values = []
        for block, unit in BLOCKS:
            last = getattr(self.recent[-1], block)
            if last is None or not len(last):
                continue
            window = np.concatenate([getattr(s, block)[s.t > since_s] for s in self.recent
                                     if getattr(s, block) is not None])
            values.append((block, units.get(block) or unit, np.asarray(last[-1], float), window.mean(axis=0)))
        return values

    def update(self, message, now_s: float) -> str | None:
        """Take one message; the line it is worth on its own (None: nothing worth a line)."""
        if isinstance(message, Version):
            self.version = message
            return f"calibd {message.release}, protocol {message.proto_major}.{message.proto_minor}"
        if isinstance(message, Device):
            self.device = message
            return f"device {_device_text(message)}"
        if isinstance(message, (State, Poll)):
            state = message if isinstance(message, State) else message.state
            if self.state is None or state.state != self.state.state:
                self.state_since_s = now_s
            self.state = state
            line = f"state {state.state}: {state.detail}; progress: {progress_text(state.progress)}"
            if isinstance(message, Poll) and message.result is not None:
                self.result, self.result_at_s = message.result, now_s
                return f"{line}\n{self.result_line()}"
            return line
        if isinstance(message, Result):
            self.result, self.result_at_s = message.result, now_s
            return self.result_line()
        if isinstance(message, Fault):
            self.faults = message
            return f"faults: {_counts(message.counts, message.increase)}"
        if isinstance(message, Correction):
            self.correction = message
            return f"correction: {correction_text(message)}"
        if isinstance(message, Overflow):
            self.overflow_dropped += message.dropped
            return f"overflow: this client lost {message.dropped} messages (reading too slowly)"
        if isinstance(message, Samples):
            return self._take_samples(message)
        if isinstance(message, Watch):
            self.samples_kind = message.samples if message.enable else "none"
            return f"watching: {'on' if message.enable else 'off'}, samples {self.samples_kind}"
        if isinstance(message, Error):
            self.last_error = message.message
            return f"server error: {message.message}"
        if isinstance(message, Message):
            return f"{message.cls} (not known to this calibd watch)"
        return None

    def _take_samples(self, samples: Samples) -> str | None:
        if not len(samples.t):
            return None
        self.recent.append(samples)
        while len(self.recent) > 1 and samples.t[-1] - self.recent[0].t[0] > RATE_WINDOW_S:
            self.recent.popleft()
        t = float(samples.t[-1])
        if self.samples_said_t is not None and t - self.samples_said_t < SAMPLES_LINE_EVERY_S:
            return None
        self.samples_said_t = t
        rate = self.sample_rate_hz()
        values = "".join(f"; {block} last {_axes(last)}, {MEAN_WINDOW_S:g}-s mean {_axes(mean)} {unit}"
                         for block, unit, last, mean in self.sample_values())
        return f"samples: {'corrected' if samples.corrected else 'raw'}, " + \
            ("rate not yet measured" if rate is None else f"{rate:.1f} Hz") + values

    def result_line(self) -> str:
        result = self.result
        estimates = ", ".join(f"{name} {value_sigma(e.value, e.sigma, e.unit)}"
                              + (f" ({e.quality})" if e.quality else "") for name, e in result.estimates.items())
        stale = stale_text(result)
        return f"result {_result_head(result)}: {estimates}" + (f"; {stale}" if stale else "")


def _axes(values: np.ndarray) -> str:
    """x, y, z of one block, signed, aligned in columns."""
    return " ".join(f"{v:+11.6f}" for v in values)


def fit(lines: list[str], width: int | None) -> list[str]:
    """`lines` within `width` columns (None: as they are): a longer line wraps at spaces (never
    between a number and its unit) and goes on under the text after its label; a single word wider
    than that is cut with an ellipsis, so the terminal never breaks a word."""
    if width is None:
        return lines
    indent = " " * min(LABEL_WIDTH, width // 2)
    out = []
    for line in lines:
        parts = [line] if len(line) <= width else [part.replace("\xa0", " ") for part in textwrap.wrap(
            _NUMBER_UNIT.sub("\\1\xa0", line), width, subsequent_indent=indent, break_long_words=False,
            break_on_hyphens=False)]
        out += [part if len(part) <= width else part[:width - 1] + "\u2026" for part in parts]
    return out


def render(view: WatchView, now_s: float, width: int | None = None) -> list[str]:
    """The whole screen for `view` at host time `now_s` (s, monotonic), one string per line,
    within `width` columns (a terminal's; None: lines as long as they are)."""
    release = "" if view.version is None else \
        f" (calibd {view.version.release}, protocol {view.version.proto_major}.{view.version.proto_minor})"
    lines = [f"calibd watch {view.where}{release}"]
    lines.append(f"device   {_device_text(view.device) if view.device else 'not yet known'}")
    if view.state is None:
        lines.append("state    not yet known")
    else:
        since = "" if view.state_since_s is None else f" (for {now_s - view.state_since_s:.0f} s)"
        lines.append(f"state    {view.state.state}{since}: {view.state.detail}")
        lines.append(f"progress {progress_text(view.state.progress)}")
    if view.result is None:
        lines.append("result   none yet")
    else:
        lines.append(f"result   {_result_head(view.result)}, received {now_s - view.result_at_s:.0f} s ago")
        stale = stale_text(view.result)
        if stale:
            lines.append(f"         {stale}")
        lines += [f"  {row}" for row in estimate_rows(view.result.estimates)]
        lines += [f"  warning: {w}" for w in view.result.warnings]
    faults = "none reported" if view.faults is None else _counts(view.faults.counts, view.faults.increase)
    lines.append(f"faults   {faults}")
    if view.correction is not None:
        lines.append(f"correction {correction_text(view.correction)}")
    if view.samples_kind != "none":
        rate = view.sample_rate_hz()
        values = view.sample_values()
        lines.append(f"samples  {view.samples_kind}, " + ("rate not yet measured" if rate is None else
                                                           f"{rate:.1f} Hz measured")
                     + (f"; x, y, z: the last sample and the mean of the last {MEAN_WINDOW_S:g} s" if values else ""))
        for block, unit, last, mean in values:
            lines.append(f"  {block:<5}last {_axes(last)} {unit}")
            lines.append(f"  {'':<5}mean {_axes(mean)} {unit}")
    if view.overflow_dropped:
        lines.append(f"overflow {view.overflow_dropped} messages lost by this client (reading too slowly)")
    if view.last_error:
        lines.append(f"error    {view.last_error}")
    return fit(lines, width)

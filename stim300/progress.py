"""A progress bar for long command-line work: one rewritten line on a terminal, nothing otherwise.

Logs, pipes and tests see no bar at all (no carriage returns in files), so commands can report
progress unconditionally. Lines printed while the bar is drawn go through `above(stream)`: the
bar is cleared before them and redrawn after, so a line never ends glued to the bar's text when
both reach the same terminal (the bar on stderr, the lines on stdout).
"""

from __future__ import annotations

import sys
import time

WIDTH = 30  # characters of bar
CLEAR_LINE = "\r\x1b[K"  # to the line's start, erase to its end


class Progress:
    """`update(done)` with `done` in [0, total] of `unit`; redrawn at most every `interval_s`."""

    def __init__(self, label: str, total: float, unit: str = "", stream=None, interval_s: float = 0.2):
        self.label, self.total, self.unit = label, max(float(total), 1e-12), unit
        self.stream = sys.stderr if stream is None else stream
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = interval_s
        self.started = time.monotonic()
        self._shown = -float("inf")
        self._text = ""  # the bar as last drawn
        self._open = False  # the bar is on the terminal's current line

    def update(self, done: float, note: str = "") -> None:
        now = time.monotonic()
        if not self.enabled or (now - self._shown < self.interval_s and done < self.total):
            return
        self._shown = now
        fraction = min(max(done / self.total, 0.0), 1.0)
        filled = int(round(fraction * WIDTH))
        elapsed = now - self.started
        eta = f", {elapsed * (1 - fraction) / fraction:.0f} s left" if 0 < fraction < 1 and elapsed > 1 else ""
        unit = f" {self.unit}" if self.unit else ""
        self._text = (f"{self.label} [{'#' * filled}{'.' * (WIDTH - filled)}] {fraction:6.1%} "
                      f"({done:.0f}/{self.total:.0f}{unit}, {elapsed:.0f} s{eta}){' ' + note if note else ''}")
        self._draw()

    def _draw(self) -> None:
        self.stream.write(f"\r{self._text}\x1b[K")
        self.stream.flush()
        self._open = True

    def clear(self) -> None:
        """Takes the bar off the terminal's line (a line printed next starts at its left edge)."""
        if self._open:
            self.stream.write(CLEAR_LINE)
            self.stream.flush()
            self._open = False

    def redraw(self) -> None:
        """Draws the bar again as it was (after a line printed above it)."""
        if self._text and not self._open:
            self._draw()

    def above(self, stream) -> "Above":
        """`stream` with the bar cleared before what is written to it and redrawn after each line."""
        return Above(self, stream)

    def close(self) -> None:
        """Ends the bar's line (only if one was drawn); later lines printed above it leave it alone."""
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False
        self._text = ""

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Above:
    """A text stream whose lines go above a progress bar (`Progress.above`)."""

    def __init__(self, bar: Progress, stream):
        self.bar, self.stream = bar, stream

    def write(self, text: str) -> int:
        if not text:
            return 0
        self.bar.clear()
        written = self.stream.write(text)
        self.stream.flush()
        if text.endswith("\n"):  # the line is complete: the bar goes back under it
            self.bar.redraw()
        return written

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return self.stream.isatty()

"""A progress bar for long command-line work: one rewritten line on a terminal, nothing otherwise.

Logs, pipes and tests see no bar at all (no carriage returns in files), so commands can report
progress unconditionally.
"""

from __future__ import annotations

import sys
import time

WIDTH = 30  # characters of bar


class Progress:
    """`update(done)` with `done` in [0, total] of `unit`; redrawn at most every `interval_s`."""

    def __init__(self, label: str, total: float, unit: str = "", stream=None, interval_s: float = 0.2):
        self.label, self.total, self.unit = label, max(float(total), 1e-12), unit
        self.stream = sys.stderr if stream is None else stream
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = interval_s
        self.started = time.monotonic()
        self._shown = -float("inf")
        self._open = False

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
        line = (f"\r{self.label} [{'#' * filled}{'.' * (WIDTH - filled)}] {fraction:6.1%} "
                f"({done:.0f}/{self.total:.0f}{unit}, {elapsed:.0f} s{eta}){' ' + note if note else ''}")
        self.stream.write(line + "\x1b[K")
        self.stream.flush()
        self._open = True

    def close(self) -> None:
        """Ends the bar's line (only if one was drawn)."""
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

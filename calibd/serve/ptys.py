"""Pseudo-terminals that pass the sensor's datagram stream on: raw, and bias-corrected.

(Interface only; the implementation follows.)
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from stim300.stream import Settled

from ..results import CalibrationResult


class RawPty:
    """A pty whose slave is linked at `link`: every settled byte of the sensor's stream, unchanged
    and in order; single-letter requests written by a client go to `forward`."""

    def __init__(self, link: Path, forward: Callable[[bytes], None], allow_service_mode: bool = False,
                 group: str | None = None):
        raise NotImplementedError

    def tap(self, settled: Settled) -> None:
        """The parser's tap (reader thread): never blocks, never raises."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class CorrectedPty:
    """A pty whose slave is linked at `link`: the stream with each normal datagram re-encoded
    after subtracting the current power-up's result's biases."""

    def __init__(self, link: Path, before_result: str = "hold", group: str | None = None):
        raise NotImplementedError

    def tap(self, settled: Settled) -> None:
        raise NotImplementedError

    def set_result(self, result: CalibrationResult | None) -> None:
        """The result whose biases to subtract (None: none of this power-up yet)."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

"""What a decoded stream is: its samples, and what is known of the sensor and the stream.

A module of its own, apart from the bulk decoder, because live readers need `stream_info` too:
the daemon describes its `StreamParser` after each batch exactly as `decode_capture` describes a
whole capture, so offline and live agree on the sample rate and on the sensor's identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .protocol import INTERNAL_RATE_HZ, Format
from .records import SensorRecord, StreamRecord
from .special import Configuration
from .stream import Scanner, StreamParser, StreamStats


@dataclass(frozen=True)
class StreamInfo:
    """The stream's format, sample rate, statistics and the sensor's identity, at one moment.

    `rate_hz` is the configured sample rate, else the one the counter steps imply (externally
    triggered: measured, 2000 / the usual step, or / the mean step when steps have no fixed
    size), else None (too few datagrams to tell). The identity comes from the part and serial
    number datagrams of the sensor's power-up (None when the stream has none). `warnings`: what
    the decoder refused or kept as read (an undefined configuration code), one line each."""

    format: Format
    rate_hz: int | float | None
    stats: StreamStats
    serial_number: str | None
    part_number: str | None
    configuration: Configuration | None
    warnings: tuple[str, ...] = ()

    @property
    def datagram_id(self) -> int | None:
        return self.format.datagram_id

    @property
    def external_trigger(self) -> bool:
        return self.stats.external_trigger

    @property
    def fixed_step(self) -> bool:
        """The counter steps by one size (a fixed rate or a periodic trigger): a step beyond it is
        a loss. Else each datagram's step is the time since the one before."""
        return self.stats.counter_step is not None

    def rate_words(self) -> str:
        """The sample rate as people read it: "125 Hz", "external trigger, 200.0 Hz",
        "external trigger, irregular steps, 392.1 Hz on average", "unknown"."""
        rate = self.rate_hz
        if rate is None:
            return "external trigger, rate unknown" if self.external_trigger else "unknown"
        if not self.external_trigger:
            return f"{rate} Hz"
        if not self.fixed_step:
            return f"external trigger, irregular steps, {rate:.1f} Hz on average"
        return f"external trigger, {rate:.1f} Hz"

    def sensor_record(self) -> SensorRecord:
        """The sensor's identity as the stream names it so far."""
        ident = self.datagram_id
        ranges = None if self.configuration is None else self.configuration.acc_range_g
        return SensorRecord(self.serial_number, self.part_number, None if ident is None else f"0x{ident:02X}",
                            self.rate_hz, self.rate_words(), None if ranges is None else max(ranges))

    def stream_record(self) -> StreamRecord:
        """The stream's statistics as a result records them: what came, what was lost or refused."""
        s = self.stats
        return StreamRecord(s.datagrams, s.lost_samples, s.inferred_missing, s.crc_errors, s.restarts, self.warnings)


@dataclass(frozen=True, eq=False)
class Capture:
    """A whole capture decoded: every CRC-valid normal datagram in stream order, and the stream."""

    samples: np.ndarray  # SAMPLE_DTYPE rows
    info: StreamInfo


def stream_info(source: Scanner | StreamParser) -> StreamInfo:
    """The StreamInfo of a scanner (bulk decoding) or of a live parser, as of now: cheap enough to
    ask after every batch (tens of microseconds)."""
    scanner = source.scanner if isinstance(source, StreamParser) else source
    stats = scanner.stats.snapshot()
    fmt = scanner.format
    return StreamInfo(
        format=fmt, rate_hz=fmt.sample_rate_hz or _counter_rate_hz(stats), stats=stats,
        serial_number=scanner.serial_number.text if scanner.serial_number else None,
        part_number=str(scanner.part_number) if scanner.part_number else None,
        configuration=scanner.configuration, warnings=tuple(scanner.warnings))


def _counter_rate_hz(stats: StreamStats) -> int | float | None:
    """The rate the counter steps imply: a fixed rate's (int), a periodic trigger's (2000 / its
    step), or an irregular trigger's mean."""
    step = stats.counter_step
    if step is not None and not stats.external_trigger:
        return INTERNAL_RATE_HZ // step
    if step is not None:
        return INTERNAL_RATE_HZ / step
    return INTERNAL_RATE_HZ / stats.mean_step if stats.external_trigger and stats.mean_step else None

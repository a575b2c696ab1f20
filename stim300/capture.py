"""What a decoded stream is: its samples, and what is known of the sensor and the stream.

A module of its own, apart from the bulk decoder, because live readers need `stream_info` too:
the daemon describes its `StreamParser` after each batch exactly as `decode_capture` describes a
whole capture, so offline and live agree on the sample rate and on the sensor's identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .protocol import INTERNAL_RATE_HZ, Format
from .special import Configuration
from .stream import Scanner, StreamParser, StreamStats


@dataclass(frozen=True)
class StreamInfo:
    """The stream's format, sample rate, statistics and the sensor's identity, at one moment.

    `rate_hz` is the configured sample rate, else the one the counter steps imply, else None
    (too few datagrams to tell). The identity comes from the part and serial number datagrams
    of the sensor's power-up (None when the stream has none)."""

    format: Format
    rate_hz: int | None
    stats: StreamStats
    serial_number: str | None
    part_number: str | None
    configuration: Configuration | None

    @property
    def datagram_id(self) -> int | None:
        return self.format.datagram_id

    def sensor_record(self) -> dict:
        """The sensor's identity as a result or status document records it (JSON-ready)."""
        ident = self.datagram_id
        return {"serial_number": self.serial_number, "part_number": self.part_number,
                "datagram_id": None if ident is None else f"0x{ident:02X}", "sample_rate_hz": self.rate_hz}


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
    step = stats.counter_step
    return StreamInfo(
        format=fmt, rate_hz=fmt.sample_rate_hz or (INTERNAL_RATE_HZ // step if step else None), stats=stats,
        serial_number=scanner.serial_number.text if scanner.serial_number else None,
        part_number=str(scanner.part_number) if scanner.part_number else None,
        configuration=scanner.configuration)

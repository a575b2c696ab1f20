"""The driver's records of a stream, typed across the seam to calibd (its sessions, results and
messages), each written as a document's object by `to_dict` and read back by `from_dict`. A
module of their own, with nothing heavy to import: reading a result needs them."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields


@dataclass(frozen=True)
class SensorRecord:
    """The sensor's identity as its stream names it, typed across the seam from the driver to
    calibd's sessions, results and messages; `to_dict` is the record a result or a status writes
    (JSON-ready, every field, null where the stream did not say). `acc_range_g`: the
    accelerometers' range from the configuration datagram (the widest axis's)."""

    serial_number: str | None = None
    part_number: str | None = None
    datagram_id: str | None = None  # "0xA7"
    sample_rate_hz: int | float | None = None
    sample_rate: str | None = None  # in words (`StreamInfo.rate_words`)
    acc_range_g: int | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: Mapping) -> SensorRecord:
        """The record of a document's "sensor" object (a field it lacks is null)."""
        return cls(**{f.name: doc.get(f.name) for f in fields(cls)})

"""The driver's records of a stream, typed across the seam to calibd (its sessions, results and
messages), each written as a document's object by `to_dict` and read back by `from_dict`. A
module of their own, with nothing heavy to import: reading a result needs them."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace

TRIAD_TRIMS = {"gyro": "gyro_deg_s", "acc": "acc_g", "incl": "incl_g"}  # triad -> its TrimOffsets field


@dataclass(frozen=True)
class TrimOffsets:
    """Nine bias trim offsets, each triad's X, Y, Z in the unit's own terms: the unit adds each
    after its own compensation (deg/s for the gyros, g for the accelerometers and inclinometers,
    whatever the output unit), so the output's biases include them."""

    gyro_deg_s: tuple[float, float, float]
    acc_g: tuple[float, float, float]
    incl_g: tuple[float, float, float]

    def __post_init__(self):
        for name in TRIAD_TRIMS.values():
            values = tuple(float(v) for v in getattr(self, name))
            if len(values) != 3 or not all(map(math.isfinite, values)):
                raise ValueError(f"{name}: three finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, values)

    def of(self, triad: str) -> tuple[float, float, float]:
        """One triad's offsets ("gyro": deg/s; "acc", "incl": g)."""
        return getattr(self, TRIAD_TRIMS[triad])

    def replaced(self, triad: str, values) -> TrimOffsets:
        """These offsets with one triad's replaced by `values`."""
        return TrimOffsets(**{name: tuple(values) if key == triad else self.of(key)
                              for key, name in TRIAD_TRIMS.items()})

    def same_offsets(self, other: TrimOffsets) -> bool:
        """Whether both add the same offsets to the output (a record's reference and saves left aside)."""
        return all(self.of(triad) == other.of(triad) for triad in TRIAD_TRIMS)

    def to_dict(self) -> dict:
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v for f in fields(self)}


@dataclass(frozen=True)
class TrimRecord(TrimOffsets):
    """The bias trim offsets in force, as the unit's Bias Trim Offset datagram carries them, with
    the 32-bit reference stored beside them and the flash saves left."""

    reference: int
    remaining_saves: int

    @classmethod
    def of_datagram(cls, bto) -> TrimRecord:
        """The record of a decoded Bias Trim Offset datagram (`stim300.special.BiasTrimOffset`)."""
        return cls(bto.gyro, bto.acc, bto.incl, bto.reference_info, bto.remaining_saves)

    @classmethod
    def from_dict(cls, doc: Mapping) -> TrimRecord:
        return cls(**{f.name: doc[f.name] for f in fields(cls)})


@dataclass(frozen=True)
class SensorRecord:
    """The sensor's identity as its stream names it, typed across the seam from the driver to
    calibd's sessions, results and messages; `to_dict` is the record a result or a status writes
    (JSON-ready, every field, null where the stream did not say). `acc_range_g`: the
    accelerometers' range from the configuration datagram (the widest axis's). `trim`: the bias
    trim offsets in force in the power-up the data are of (None: its stream carried no Bias Trim
    Offset datagram)."""

    serial_number: str | None = None
    part_number: str | None = None
    datagram_id: str | None = None  # "0xA7"
    sample_rate_hz: int | float | None = None
    sample_rate: str | None = None  # in words (`StreamInfo.rate_words`)
    acc_range_g: int | None = None
    trim: TrimRecord | None = None

    def to_dict(self) -> dict:
        return asdict(replace(self, trim=None)) | {"trim": None if self.trim is None else self.trim.to_dict()}

    @classmethod
    def from_dict(cls, doc: Mapping) -> SensorRecord:
        """The record of a document's "sensor" object (a field it lacks is null)."""
        record = cls(**{f.name: doc.get(f.name) for f in fields(cls) if f.name != "trim"})
        trim = doc.get("trim")
        return record if trim is None else replace(record, trim=TrimRecord.from_dict(trim))


@dataclass(frozen=True)
class StreamRecord:
    """The stream's statistics as a result records them, typed across the seam from the driver to
    calibd's sessions and the daemon (`StreamInfo.stream_record`): what came, what was lost or
    refused, so offline and daemon results say the same. `to_dict` gives the fields a result's
    "stream" object starts its statistics with."""

    datagrams: int = 0
    lost_samples: int = 0
    inferred_missing: int = 0
    crc_errors: int = 0
    restarts: int = 0
    warnings: tuple[str, ...] = ()  # what the decoder refused or kept as read, one line each

    def to_dict(self) -> dict:
        return asdict(self) | {"warnings": list(self.warnings)}

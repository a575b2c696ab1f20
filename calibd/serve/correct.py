"""A result's biases (calibd.correction) taken out of the sensor's own datagrams, in place, CRCs
written again.

The corrected pty carries the stream a driver already reads, so the correction is done in each
datagram's own units: a rate or an acceleration loses the bias itself, an incremental angle or
velocity the bias times the sample interval. Each is rounded to whole counts once per result
and taken off the datagrams' values without decoding them (within one count of raw - bias).
A triad with factory terms the data estimated (`correction.estimated_maps`) then goes through
its map, in counts, to the nearest count.
An integrated angle or velocity has summed the bias since power-up, which no constant offset
undoes: those blocks pass unchanged (said once in the log).
"""

from __future__ import annotations

import numpy as np
import structlog

from stim300.codec import seal, subtract_counts
from stim300.protocol import AccUnit, Format, GyroUnit, Layout
from stim300.stream import Settled

from ..correction import estimated_maps, sensor_biases
from ..frames import STANDARD_GRAVITY
from ..results import CalibrationResult

log = structlog.get_logger("calibd")

# a block's unit in the sensor's base unit (deg/s, g) per sample interval's worth of it
_GYRO_PER_BASE = {GyroUnit.RATE: "base", GyroUnit.AVERAGE_RATE: "base", GyroUnit.INCREMENTAL_ANGLE: "interval"}
_FORCE_PER_BASE = {AccUnit.ACCELERATION: "base", AccUnit.AVERAGE_ACCELERATION: "base",
                   AccUnit.INCREMENTAL_VELOCITY: "interval_m_s"}


def _gyro_unit(unit) -> GyroUnit:
    """The gyro output unit without its delayed flag."""
    return GyroUnit(unit & 0x7)


class Corrector:
    """One result's biases, subtracted from the normal datagrams of settled bytes.

    `rate_hz` (the result's sample rate) gives the sample interval of incremental units when
    the stream's format does not say it (no configuration datagram seen)."""

    def __init__(self, result: CalibrationResult):
        self.biases = sensor_biases(result)
        self.maps = estimated_maps(result)
        self.rate_hz = result.sensor.sample_rate_hz
        self._counts: dict[tuple[int, Format], list[tuple[int, np.ndarray, np.ndarray | None]]] = {}
        self._said: set[tuple[str, str]] = set()

    def apply(self, settled: Settled) -> bytes | bytearray:
        """The settled bytes with every normal datagram's biases subtracted, CRC recomputed;
        counter, status, latency, temperatures and special datagrams as they were."""
        if not settled.runs:
            return settled.data
        out = bytearray(settled.data)
        view = np.frombuffer(out, np.uint8)
        for layout, fmt, offsets, _, _ in settled.runs:
            subtract = self._counts_for(layout, fmt)
            if not subtract:
                continue
            rows = offsets[:, None] + np.arange(layout.pre_crc + 4)  # CR LF, when there, stays as it is
            frames = view[rows]
            for first, counts, matrix in subtract:
                subtract_counts(frames, first, counts, matrix)
            seal(frames, layout)
            view[rows] = frames
        return out

    def _counts_for(self, layout: Layout, fmt: Format) -> list[tuple[int, np.ndarray, np.ndarray | None]]:
        """What to subtract from the datagrams of this layout and format: per corrected cluster,
        its byte offset, the bias in counts of its axes (the nearest: raw - bias within one
        count) and its estimated map in counts (axes of another count size scale it), or None;
        worked out once per format."""
        key = (layout.datagram_id, fmt)
        if key not in self._counts:
            rate_hz = fmt.sample_rate_hz or self.rate_hz
            units = {"gyro": (fmt.gyro_unit, _GYRO_PER_BASE), "acc": (fmt.acc_unit, _FORCE_PER_BASE),
                     "incl": (fmt.incl_unit, _FORCE_PER_BASE)}
            counts = []
            scales = fmt.scales()
            for cluster in layout.clusters:
                if cluster not in self.biases:
                    continue
                unit, kinds = units[cluster]
                scale = self._scale(cluster, _gyro_unit(unit) if cluster == "gyro" else unit, kinds, rate_hz)
                if scale is not None:
                    lsb = np.broadcast_to(scales[cluster], 3)
                    matrix = self.maps.get(cluster)
                    counts.append((layout.offsets[cluster],
                                   np.rint(self.biases[cluster] * scale / scales[cluster]).astype(np.int32),
                                   None if matrix is None else matrix * lsb[None, :] / lsb[:, None]))
            self._counts[key] = counts
        return self._counts[key]

    def _scale(self, cluster: str, unit, kinds: dict, rate_hz: int | None) -> float | None:
        """Bias in the sensor's base unit -> bias in `unit` (None: this unit cannot be corrected)."""
        kind = kinds.get(unit)
        if kind == "base":
            return 1.0
        if kind is not None and rate_hz:
            return (STANDARD_GRAVITY if kind == "interval_m_s" else 1.0) / rate_hz
        why = ("the sample rate is unknown (externally triggered?)" if kind is not None else
               f"{unit.name.lower()} sums the bias since power-up")
        if (cluster, why) not in self._said:
            self._said.add((cluster, why))
            log.warning("corrected_pty_uncorrected", cluster=cluster, why=why)
        return None

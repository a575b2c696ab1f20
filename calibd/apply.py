"""A result applied to a capture: the capture's samples in SI, the result's biases subtracted,
optionally turned into the platform's home frame (`calibd apply`, docs/apply.md).

One job: a result and decoded samples -> corrected arrays, block by block as the bulk decoder
hands them over, so a capture of any length streams to a CSV file in one block's memory. The
command line opens the files; `Correction` says what is subtracted and how vectors turn,
`apply_capture` runs the decoder and gives each corrected block to a writer (`CsvWriter`,
`NpzWriter`, `calibd.mcapout`); `apply_recording` does the same for a recording of Imu messages,
batch by batch. Which biases a result has, which outputs can take them and whether the result is
of the capture's sensor have one home, `calibd.correction`, shared with the daemon's corrected
outputs.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from stim300.bulk import decode_blocks
from stim300.capture import stream_info
from stim300.clock import CounterClock
from stim300.csvtable import write_rows
from stim300.protocol import CLUSTERS, INTERNAL_RATE_HZ, NORMAL_LAYOUTS

from .errors import CalibdError
from .recordings import StampTimes
from .results import ROTATIONS, CalibrationResult
from .correction import SI_PER_SENSOR_UNIT, WORDS, estimated_maps, other_sensor, si_biases, through, uncorrectable
from .session import PowerUpCuts

APPLIED_SCHEMA = "calibd.applied/1"
RECORDING_CLUSTERS = ("gyro", "acc")  # what a sensor_msgs/Imu carries
UNITS = {"gyro": "rad_s", "acc": "m_s2", "incl": "m_s2"}  # in column and array names
ATTITUDE = ROTATIONS["nav_to_imu"][1]  # yaw, pitch, roll
# 9 significant digits: every STIM300 value is a 24-bit count (exact in float32, which 9 digits
# round-trip); a corrected value printed so is within 0.02 LSB at full scale, far below one
# sample's noise (17 digits would add half the size for digits the sensor never had). Times are
# whole 0.5 ms counter ticks: 4 decimals are exact.
VALUE_FORMAT = "%.9g"
TIME_FORMAT = "%.4f"
CAPTURE_UNITS = (b"# units: time_s s since the power-up's first sample (datagram counter); gyro rad/s; "
                 b"acc and incl m/s^2; status bytes as the sensor sent them\n")
RECORDING_UNITS = (b"# units: time_s s since the first message's header stamp (to 0.1 ms); gyro rad/s; acc m/s^2; "
                   b"stamp_ns the message's header stamp, ns since the epoch\n")


class ApplyError(CalibdError):
    """A result that cannot be applied to this capture as asked; one line."""


@dataclass(frozen=True)
class Correction:
    """What apply does to every sample: subtract `biases` (SI per cluster: rad/s, m/s^2), take
    the triad through its `maps` (the factory terms the data estimated, `estimated_maps`), then,
    with `rotation` (R_NAV^IMU at the home position), express the vectors in the home frame.
    `warnings`: what --force let pass, one line each."""

    biases: dict[str, np.ndarray]
    rotation: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    maps: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def frame(self) -> str:
        return "imu" if self.rotation is None else "home"

    def corrected(self, cluster: str, values: np.ndarray) -> np.ndarray:
        """A cluster's vectors (N x 3, SI, float64) as apply writes them: bias off, through the
        estimated map, in the asked frame."""
        if cluster in self.biases:
            values = through(values - self.biases[cluster], self.maps.get(cluster))
        if self.rotation is not None:
            values = values @ self.rotation  # v_home = R_NAV^IMU.T v_imu, row by row
        return values


def correction(result: CalibrationResult, frame: bool, force: bool) -> Correction:
    """The correction a result gives. Estimates it would use that are flagged poor refuse it
    (ApplyError naming them) unless `force`, then each is a warning: corrected data are trusted
    without looking back at the result, so a poor bias must not pass silently. A result
    without yaw, or with yaw poor, cannot give the home frame: refused even with `force`."""
    biases = si_biases(result)
    if "gyro" not in biases and "acc" not in biases:
        raise ApplyError("the result has neither gyro nor accelerometer biases: nothing to apply")
    used = [f"{cluster}_bias_{axis}" for cluster in biases for axis in "xyz"]
    rotation = None
    if frame:
        rotation = result.rotation_matrix("nav_to_imu")
        missing = [name for name in ATTITUDE if name not in result.estimates]
        if rotation is None or result.estimates["yaw"].quality == "poor":
            why = f"has no {', '.join(missing)}" if missing else "has yaw flagged poor"
            raise ApplyError(f"--frame: the result {why}: the home frame needs yaw, pitch and roll")
        used += list(ATTITUDE)
    poor = [name for name in used if result.estimates[name].quality == "poor"]
    warnings = ()
    if poor:
        text = f"the result's {', '.join(poor)} {'is' if len(poor) == 1 else 'are'} flagged poor"
        if not force:
            raise ApplyError(f"{text}: not applied (--force applies it anyway)")
        warnings = (f"{text}: applied anyway (--force)",)
    return Correction(biases, rotation, warnings, estimated_maps(result))


@dataclass
class Applied:
    """What apply found in the capture: samples written, power-ups, the sensor's serial number
    (None: no serial-number datagram), a recording's Imu topic and the warnings to show."""

    samples: int = 0
    power_ups: int = 0
    serial_number: str | None = None
    clusters: tuple[str, ...] = ()
    warnings: list[str] = field(default_factory=list)
    topic: str | None = None

    @property
    def words(self) -> str:
        if self.topic is not None:
            return f"{self.samples} messages of topic {self.topic}"
        return f"{self.samples} samples, {self.power_ups} power-up(s)"


def _without_biases(clusters, correction: Correction, force: bool) -> tuple[str | None, str | None]:
    """(warning, refusal) for data carrying a cluster the result has no biases for: its columns
    would pass as measured under a file that says corrected, so it is refused unless forced."""
    missing = [WORDS[c] for c in clusters if c not in correction.biases]
    if not missing:
        return None, None
    text = f"the result has no {' or '.join(missing)} biases"
    if force:
        return f"{text}: those columns are as measured, in SI (--force)", None
    return None, f"{text}: those columns would stay uncorrected (--force writes them as measured)"


class _Applier:
    """Decoded blocks in stream order -> corrected column blocks handed to `write(columns)`.

    A refusal found while decoding (another sensor, outputs that are not rates and
    accelerations) stops the writing and is raised once the decoder is done, so a mapped
    capture is never left held."""

    def __init__(self, correction: Correction, result_serial: str | None, force: bool, write):
        self.correction, self.result_serial, self.force, self.write = correction, result_serial, force, write
        self.applied = Applied()
        self.refusal: str | None = None
        self._cuts = PowerUpCuts()
        self._clock = CounterClock()
        self._checked_serial = False

    def consume(self, samples: np.ndarray, scanner) -> None:
        if self.refusal:
            return
        self._check(scanner)
        if self.refusal:
            return
        info = stream_info(scanner)
        rate_hz = info.rate_hz or INTERNAL_RATE_HZ  # sizes the read log's window only, until the rate is known
        applied = self.applied
        for restarted, piece in self._cuts.pieces(samples, applied.samples, info.stats.restart_datagrams):
            if applied.power_ups == 0 or (restarted and applied.samples):
                applied.power_ups += 1
                self._clock = CounterClock()  # times are seconds since the power-up's first sample
            time_s = self._clock.times(piece["counter"], rate_hz, piece["t_host"]).time_s
            self.write(self._columns(piece, time_s))
            applied.samples += len(piece)

    def _check(self, scanner) -> None:
        """Refuse outputs apply cannot turn into rates and accelerations, and another sensor."""
        fmt = scanner.format
        clusters = NORMAL_LAYOUTS[fmt.datagram_id].clusters
        if not self.applied.clusters:
            self.applied.clusters = tuple(c for c in CLUSTERS if c in clusters)
            self._uncorrected()
        summed = uncorrectable(fmt)
        if summed:
            self.refusal = (f"the capture's {', '.join(summed)} outputs are not rates and accelerations: "
                            "apply writes rad/s and m/s^2 and corrects those only (configure rate and "
                            "acceleration outputs, as calibration needs)")
        if self._checked_serial or scanner.serial_number is None:
            return
        self._checked_serial = True
        serial = self.applied.serial_number = scanner.serial_number.text
        if other_sensor(self.result_serial, serial):
            text = (f"the capture is of sensor {serial}, the result of sensor {self.result_serial}: "
                    "its biases are another sensor's")
            if self.force:
                self.applied.warnings.append(f"{text}: applied anyway (--force)")
            else:
                self.refusal = f"{text} (--force applies it anyway)"

    def _uncorrected(self) -> None:
        warning, self.refusal = _without_biases(self.applied.clusters, self.correction, self.force)
        self.applied.warnings += [warning] if warning else []

    def _columns(self, samples: np.ndarray, time_s: np.ndarray) -> dict[str, np.ndarray]:
        """One block's output columns: SI vectors, biases off, in the asked frame."""
        columns = {"time_s": time_s}
        for cluster in self.applied.clusters:  # float64: float32 would round
            columns[f"{cluster}_{UNITS[cluster]}"] = self.correction.corrected(
                cluster, samples[cluster].astype(np.float64) * SI_PER_SENSOR_UNIT[cluster])
        columns["counter"] = samples["counter"]
        columns["status"] = np.column_stack([samples[f"status_{c}"] for c in CLUSTERS])
        columns["power_up"] = np.full(len(samples), self.applied.power_ups, np.uint16)
        return columns


def apply_capture(data, name: str, correction: Correction, result_serial: str | None, force: bool,
                  write, reads: np.ndarray | None = None, drop_before=lambda offset: None) -> Applied:
    """Decode the capture's bytes block by block and hand each corrected block to `write`
    (`reads`: its read log; `drop_before(offset)`: the bytes before `offset` are done with).
    ApplyError (one line naming `name`) for a capture that cannot take this result; the
    writer may then have been given some blocks, so it must write to a file replaced only on
    success (`stim300.atomic`)."""
    applier = _Applier(correction, result_serial, force, write)

    def on_block(samples, scanner, offset) -> None:
        applier.consume(samples, scanner)
        drop_before(offset)

    info = decode_blocks(data, on_block, reads=reads)
    if applier.refusal:
        raise ApplyError(f"{name}: {applier.refusal}")
    applied = applier.applied
    if not applied.samples:
        raise ApplyError(f"{name}: no STIM300 datagram found")
    applied.warnings = [*correction.warnings, *applied.warnings, *_identity_warnings(applied, result_serial, name)]
    if applied.power_ups > 1:
        applied.warnings.append(
            f"{name}: the sensor restarted {applied.power_ups - 1} time(s): the result's biases are one "
            "power-up's turn-on biases, samples of the other power-ups carry their own (column power_up)")
    lost = info.stats.lost_samples
    if lost:
        applied.warnings.append(f"{name}: {lost} samples lost in the capture (the datagram counter shows the gaps): "
                                "no row stands for them, and time_s jumps across each gap")
    for text in info.warnings:
        applied.warnings.append(f"{name}: {text}")
    return applied


def apply_recording(recording, correction: Correction, result: CalibrationResult, force: bool,
                    open_writer) -> Applied:
    """A recording of Imu messages (`calibd.recordings.ImuRecording`) corrected batch by batch:
    each batch's columns (time_s since the first message, the header stamps, gyro and
    accelerometer in SI) go to the writer `open_writer(rate_hz, frame_id)` gives at the first
    batch, once the stamps have told the rate. ApplyError (one line naming the recording) for a
    recording that cannot take this result; as for a capture, the writer must write to a file
    replaced only on success."""
    name = str(recording.path)
    applied = Applied(power_ups=1, clusters=RECORDING_CLUSTERS)
    warning, refusal = _without_biases(RECORDING_CLUSTERS, correction, force)
    if refusal:
        raise ApplyError(f"{name}: {refusal}")
    applied.warnings += [warning] if warning else []
    stamps, write = StampTimes(name), None
    for stamps_ns, gyro, acc, frame_id in recording.batches():
        time_s = stamps.times(stamps_ns, frame_id)
        if write is None:
            applied.warnings += _frame_warnings(result, frame_id, name, force)
            write = open_writer(stamps.rate_hz, frame_id)
        write({"time_s": time_s, "gyro_rad_s": correction.corrected("gyro", gyro),
               "acc_m_s2": correction.corrected("acc", acc), "stamp_ns": stamps_ns})
        applied.samples += len(stamps_ns)
    applied.topic = recording.topic
    applied.warnings = [*correction.warnings, *applied.warnings,
                        *(f"{name}: {text}: no row stands for them" for text in stamps.warnings)]
    return applied


def _frame_warnings(result: CalibrationResult, frame_id: str, name: str, force: bool) -> list[str]:
    """Whether a result is of the sensor a recording holds, as far as a recording can tell: it
    names no serial number, only the frame its driver stamped. A result of a recording with another
    frame id is another sensor's, or the same under another name: refused unless forced."""
    if result.sensor.serial_number is not None:
        return [f"{name}: a recording names no serial number: cannot check the result (of sensor "
                f"{result.sensor.serial_number}) is of this sensor"]
    result_frame = result.stream.frame_id
    if result_frame is None or result_frame == frame_id:
        return []
    text = (f"the recording's frame id is {frame_id!r}, the result's {result_frame!r}: its biases may be another "
            "sensor's")
    if not force:
        raise ApplyError(f"{name}: {text} (--force applies it anyway)")
    return [f"{name}: {text}: applied anyway (--force)"]


def _identity_warnings(applied: Applied, result_serial: str | None, name: str) -> list[str]:
    """Where the identity check could not be made: a serial-number datagram comes only at a
    power-up, so many captures lack it, and refusing them would refuse most real captures."""
    if applied.serial_number is None:
        return [f"{name}: no serial-number datagram (recorded after the sensor's power-up): "
                "cannot check the result is of this sensor"]
    if result_serial is None:
        return ["the result names no sensor serial number: cannot check it is of this capture's sensor"]
    return []


def meta_record(correction: Correction, result_path: str, result_sha256: str, result: CalibrationResult,
                capture_path: str, version: str) -> dict:
    """What an output says of itself: the result applied (path, SHA-256, sensor), the frame,
    the biases subtracted (SI), the estimated factory maps applied, and the software."""
    record = {"schema": APPLIED_SCHEMA, "software": f"calibd {version}",
              "result": {"path": result_path, "sha256": result_sha256,
                         "serial_number": result.sensor.serial_number},
              "capture": capture_path, "frame": correction.frame,
              "biases_subtracted": {f"{c}_{UNITS[c]}": correction.biases[c].tolist() for c in correction.biases}}
    if correction.maps:
        record["estimated_maps"] = {c: m.tolist() for c, m in correction.maps.items()}
    if correction.rotation is not None:
        record["rotation_home_from_imu"] = correction.rotation.T.tolist()
    return record


class CsvWriter:
    """Corrected blocks as CSV: `#` comment lines (what the file is, in JSON; the units), a
    header of column names carrying their units, one row per sample. The columns are known
    with the first block (which clusters the datagram carries; a capture's counter and status
    bytes or a recording's header stamps), so the header waits for it."""

    def __init__(self, f, meta: dict):
        self.f, self.meta = f, meta
        self.order: list[str] | None = None
        self.formats: list[str] = []

    def _header(self, columns: dict[str, np.ndarray]) -> None:
        vectors = {f"{c}_{UNITS[c]}": c for c in CLUSTERS if f"{c}_{UNITS[c]}" in columns}  # in CLUSTERS' order
        self.order = ["time_s", *vectors, *(name for name in columns if name not in vectors and name != "time_s")]
        names = []
        for name in self.order:
            if name in vectors:
                names += [f"{vectors[name]}_{a}_{UNITS[vectors[name]]}" for a in "xyz"]
                self.formats += [VALUE_FORMAT] * 3
            elif name == "status":
                names += [f"status_{c}" for c in CLUSTERS]
                self.formats += ["%d"] * len(CLUSTERS)
            else:
                names.append(name)
                self.formats.append(TIME_FORMAT if name == "time_s" else "%d")
        self.f.write(f"# {APPLIED_SCHEMA}: {json.dumps(self.meta)}\n".encode())
        self.f.write(RECORDING_UNITS if "stamp_ns" in columns else CAPTURE_UNITS)
        self.f.write((",".join(names) + "\n").encode())

    def __call__(self, columns: dict[str, np.ndarray]) -> None:
        if self.order is None:
            self._header(columns)
        write_rows(self.f, [columns[name] for name in self.order], self.formats)

    def finish(self) -> None:
        """Nothing is held back: each block was written as it came."""


class NpzWriter:
    """Corrected blocks gathered into one array per column, written as an NPZ to `f` at
    `finish`. Each column is allocated once for the most samples the input can hold (the bytes
    of a capture, the index's count of a recording; pages never written cost address space
    only), so the samples are held once, not as blocks plus their concatenation."""

    def __init__(self, capacity: int, f, meta: dict):
        self.capacity, self.n, self.f, self.meta = capacity, 0, f, meta
        self.columns: dict[str, np.ndarray] = {}

    @staticmethod
    def capacity_for(size_bytes: int) -> int:
        """The most samples `size_bytes` of capture can hold: one per shortest datagram."""
        return size_bytes // min(layout.wire_length(False) for layout in NORMAL_LAYOUTS.values()) + 1

    def __call__(self, columns: dict[str, np.ndarray]) -> None:
        n = len(columns["time_s"])
        if self.n + n > self.capacity:  # more messages than a recording's index counted
            self.capacity = 2 * (self.n + n)
            self.columns = {name: np.resize(values, (self.capacity, *values.shape[1:]))
                            for name, values in self.columns.items()}
        for name, values in columns.items():
            if name not in self.columns:
                self.columns[name] = np.empty((self.capacity, *values.shape[1:]), values.dtype)
            self.columns[name][self.n:self.n + n] = values
        self.n += n

    def finish(self) -> None:
        np.savez(self.f, **{name: values[:self.n] for name, values in self.columns.items()},
                 meta=np.array(json.dumps(self.meta)))

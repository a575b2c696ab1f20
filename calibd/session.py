"""Sessions: decoded samples in SI units, block-averaged to at most STORE_RATE_HZ.

One rule keeps a session, for the daemon on live data and for the one-shot commands on a
capture: `SessionBuilder` takes batches of decoded samples with their times and keeps them
block-averaged (averages of averages keep the estimators' models exact, and their work and
memory follow the stored samples) in float32. A capture is cut at every sensor restart and
one power-up makes a session, from where its warm-up ends or a given start.
"""

from __future__ import annotations

import bisect
import hashlib
from dataclasses import dataclass, replace

import numpy as np

from stim300.bulk import decode_blocks
from stim300.capture import StreamInfo, stream_info
from stim300.records import SensorRecord, TrimRecord
from stim300.clock import counter_times
from stim300.codec import fault_bits, start_up_flags, start_up_rises
from stim300.protocol import status_names

from .documents import DocumentError, SensorDoc, validate
from .errors import CalibrationError
from .frames import STANDARD_GRAVITY
from .results import PowerUpRecord, ResultStream
from .units import DEG
from .warmup import WARM_UP_RULE, record_settling, start_words

STORE_RATE_HZ = 125  # faster data is block-averaged to this (the thesis's rate)


@dataclass
class Session:
    """Decoded data in SI, with what is known of the sensor and the stream. A capture's session
    holds its samples as stored (`SessionBuilder`: float32 views, no copy; the daemon's, float64):
    whatever sums them takes them to float64 first, as the stored values are."""

    time_s: np.ndarray  # float64
    gyro: np.ndarray  # rad/s
    acc: np.ndarray  # m/s^2
    incl: np.ndarray | None  # m/s^2; None: the unit has no inclinometers (its datagram carries none)
    temperature_c: np.ndarray | None  # float64, mean of the gyro temperatures, when the datagram has them
    rate_hz: int | float  # stored samples per second (an externally triggered sensor's: measured)
    sensor: SensorRecord
    stream: ResultStream


@dataclass
class PowerUp:
    """One power-up of a capture as a session keeps it: its block means (timed by the counter over
    the whole power-up), where its datagrams are in the capture, and the gaps its host read times
    proved the counter could not see."""

    data: SessionBuilder
    first_datagram: int
    datagrams: int
    duration_s: float
    gap_time_s: np.ndarray  # where each hidden gap was found (s since the power-up's first sample)
    gap_s: np.ndarray  # the time each added
    checked: bool  # host times were there to look for hidden gaps
    trim: TrimRecord | None = None  # the last bias trim offsets its stream carried (None: none)
    trim_changes: int = 0  # how often the offsets carried changed within it


@dataclass
class CaptureSessions:
    """A capture as calibration keeps it (not `stim300.Capture`, which holds every sample): cut
    at every sensor restart, each power-up block-averaged. Each power-up has its own turn-on
    biases, counter and platform angle, so a calibration uses one of them, never a mix."""

    path: str
    power_ups: list[PowerUp]
    rate_hz: int | float  # the sensor's samples per second (externally triggered: measured)
    sensor: SensorRecord
    stream: ResultStream  # the whole capture's stream statistics
    identity: dict  # which file this is: its size_bytes and sha256 (results record it, a report checks it)


def block_factor(rate_hz: int | float) -> int:
    """Samples averaged into one stored sample."""
    return max(1, int(rate_hz // STORE_RATE_HZ))


def stored_rate_hz(rate_hz: int | float) -> int | float:
    """Stored samples per second: a whole number at the fixed rates, measured (a float) when the
    sensor is externally triggered."""
    k = block_factor(rate_hz)
    return rate_hz // k if rate_hz % k == 0 else rate_hz / k


class SessionBuilder:
    """A growing session, block-averaged to at most STORE_RATE_HZ and stored in float32 (1e-4 mg
    and 1e-5 deg/h: half the memory). A block's time is its first sample's; samples short of a
    whole block wait for the next batch. Fault flags are kept per flagged sample, so a session
    cut at any time counts exactly its own."""

    COLUMNS = ("time_s", "gyro", "acc", "incl", "temp")

    def __init__(self) -> None:
        self._time: list[np.ndarray] = []
        self._values: list[np.ndarray] = []  # float32 (n, 10): gyro, acc, incl (SI), temperature
        self._pending = np.zeros((0, 11))
        self._flagged: list[tuple[np.ndarray, np.ndarray]] = []  # (times, fault bits) of flagged samples

    def add(self, samples: np.ndarray, time_s: np.ndarray, rate_hz: int | float) -> tuple[np.ndarray, np.ndarray]:
        """Store a batch (stim300.codec.SAMPLE_DTYPE, times in s); returns the times (s) and gyro
        samples (deg/s) stored from it."""
        k = block_factor(rate_hz)
        bits = fault_bits(samples)
        flagged = np.flatnonzero(bits)
        if len(flagged):
            self._flagged.append((time_s[flagged], bits[flagged]))
        temp = _mean_temperature(samples["temp_gyro"])
        block = np.column_stack([time_s, samples["gyro"] * DEG, samples["acc"] * STANDARD_GRAVITY,
                                 samples["incl"] * STANDARD_GRAVITY, temp])
        block = np.concatenate([self._pending, block])
        whole = len(block) // k * k
        self._pending = block[whole:]
        mean = block[:whole].reshape(-1, k, block.shape[1]).mean(axis=1)
        mean[:, 0] = block[:whole:k, 0]  # a block's time is its first sample's
        if len(mean):
            self._time.append(mean[:, 0].copy())  # a column of `mean` would keep all of its 11
            self._values.append(mean[:, 1:].astype(np.float32))
        return mean[:, 0], mean[:, 1:4] / DEG

    def arrays(self, since_s: float = -np.inf) -> dict[str, np.ndarray]:
        """The stored samples from `since_s` on, float64: time_s, gyro, acc, incl, temp."""
        time_s = np.concatenate(self._time) if self._time else np.zeros(0)
        keep = time_s >= since_s
        values = np.concatenate(self._values)[keep].astype(np.float64) if self._values else np.zeros((0, 10))
        return {"time_s": time_s[keep], "gyro": values[:, 0:3], "acc": values[:, 3:6], "incl": values[:, 6:9],
                "temp": values[:, 9]}

    def stored(self) -> tuple[np.ndarray, np.ndarray]:
        """(times, float32 values: gyro, acc, incl, temperature) as stored, not copied: the batches
        are joined once and kept joined, so a session of a whole capture costs no second copy."""
        if len(self._time) > 1:
            self._time, self._values = [_joined(self._time)], [_joined(self._values)]
        return (self._time[0], self._values[0]) if self._time else (np.zeros(0), np.zeros((0, 10), np.float32))

    @property
    def end_s(self) -> float:
        return float(self._time[-1][-1]) if self._time else 0.0

    def trim(self, before_s: float) -> None:
        """Forget whole batches that end before `before_s` (warm-up data nobody will use)."""
        while self._time and self._time[0][-1] < before_s:
            self._time.pop(0)
            self._values.pop(0)
        self._flagged = [(t[t >= before_s], b[t >= before_s]) for t, b in self._flagged if t[-1] >= before_s]

    def shift(self, from_s: float, seconds: float) -> None:
        """Move the samples stored from `from_s` on `seconds` later: datagrams lost before them,
        found only after they were stored (`stim300.clock.CounterClock`)."""
        def moved(t: np.ndarray) -> np.ndarray:
            return np.where(t >= from_s, t + seconds, t)
        for k in range(len(self._time) - 1, -1, -1):  # newest first: a gap is found within seconds
            if self._time[k][-1] < from_s:
                break
            self._time[k] = moved(self._time[k])
        self._pending[:, 0] = moved(self._pending[:, 0])
        self._flagged = [(moved(t), b) for t, b in self._flagged]

    def retime(self, time_s: np.ndarray) -> None:
        """Replace times fed as sample numbers by those samples' times `time_s` (s)."""
        self._time = [time_s[t.astype(np.int64)] for t in self._time]
        self._flagged = [(time_s[t.astype(np.int64)], b) for t, b in self._flagged]

    def fault_summary(self, since_s: float = -np.inf) -> tuple[int, int]:
        """(samples the sensor flagged from `since_s` on, the union of their fault bits)."""
        bits = [b[t >= since_s] for t, b in self._flagged]
        count = sum(len(b) for b in bits)
        return count, int(np.bitwise_or.reduce(np.concatenate(bits))) if count else 0


def _joined(chunks: list[np.ndarray]) -> np.ndarray:
    """The chunks as one array, each let go once copied (from the list given): the joined array
    and one chunk at a time, not the chunks and their copy."""
    joined = np.empty((sum(len(c) for c in chunks),) + chunks[0].shape[1:], chunks[0].dtype)
    end = len(joined)
    while chunks:  # from the last
        chunk = chunks.pop()
        joined[end - len(chunk):end] = chunk
        end -= len(chunk)
    return joined


def _mean_temperature(temp_gyro: np.ndarray) -> np.ndarray:
    """Per sample, the mean of its gyro temperatures that are there (NaN: none in the datagram).
    A plain mean where all are there: nanmean's masking costs more than the rest of a batch."""
    if np.isnan(temp_gyro[0, 0]):
        return np.full(len(temp_gyro), np.nan)
    mean = temp_gyro.mean(axis=1)
    partial = np.isnan(mean)
    if partial.any():
        mean[partial] = np.nanmean(temp_gyro[partial], axis=1)
    return mean


def missing_sensors(samples: np.ndarray, where: str) -> str | None:
    """Why samples cannot be calibrated for what their datagram carries, or None. Gyros and
    accelerometers are needed (the accelerometers find the statics and the direction of gravity
    that pitch, roll and yaw rest on); inclinometers are not: without them the accelerometers
    give the tilt."""
    if len(samples) and np.isnan(samples["acc"][0, 0]):
        return (f"{where}: datagram 0x{samples['datagram_id'][0]:02X} carries gyros only: calibration needs "
                "accelerometers too (to find the statics and the direction of gravity for pitch, roll and yaw)")
    return None


def inclinometers(values: np.ndarray) -> np.ndarray | None:
    """A session's inclinometer samples, or None where the datagram has none (stored as NaN)."""
    return None if len(values) and np.isnan(values[0, 0]) else values


def fault_record(count: int, bits: int) -> dict:
    return {"flagged_datagrams": count, "fault_flags": status_names(bits)}


def hidden_gap_record(gap_s: list[float] | np.ndarray | None) -> dict:
    """Gaps the datagram counter could not see (whole counter cycles), found from host read times
    (`gap_s`: the time each added), or None where there were no host times to look with."""
    if gap_s is None:
        return {"hidden_gaps": None, "hidden_gap_s": None}
    return {"hidden_gaps": len(gap_s), "hidden_gap_s": round(float(np.sum(gap_s)), 3)}


def checked_trim(trim: TrimRecord | None, acc_range_g: int | None) -> tuple[TrimRecord | None, list[str]]:
    """The trim offsets a result can record (a unit clamps its offsets to their triad's trim range,
    calibd.spec, so one beyond it is no trim of a unit's), and what is wrong with them: (the trim
    or None, [] or the one-line reason it is not recorded)."""
    if trim is None:
        return None, []
    try:
        validate({"acc_range_g": acc_range_g, "trim": trim.to_dict()}, SensorDoc, "sensor")
    except DocumentError as exc:
        return None, [f"bias trim offset datagram not recorded: {exc}"]
    return trim, []


class PowerUpCuts:
    """Where the sensor restarted in a stream of sample batches: turn-on biases change at every
    power-up, so the data of two power-ups never share a session. A restart is where the stream
    parser saw the power-up datagrams (`restart_datagrams`: each restarted sensor's first sample
    number in the stream) or, when those were lost, where the start-up status bit comes on after
    samples without it. The one rule for captures and for the daemon's live batches."""

    def __init__(self) -> None:
        self._start_up_before = True  # whether the last sample had the start-up bit (none yet: as if)

    def pieces(self, samples: np.ndarray, first: int, restart_datagrams) -> list[tuple[bool, np.ndarray]]:
        """The batch (stream sample numbers from `first`) cut at each restart: (whether a new
        power-up starts with the piece, the piece), in stream order."""
        count = len(samples)
        starts = {i - first for i in restart_datagrams if first <= i < first + count}
        starts |= set(start_up_rises(samples, self._start_up_before).tolist())
        if count:
            self._start_up_before = bool(start_up_flags(samples[-1:])[0])
        bounds = sorted(starts | {0, count})
        return [(lo in starts, samples[lo:hi]) for lo, hi in zip(bounds, bounds[1:])]


class _PowerUpReader:
    """Decoded blocks of a capture in stream order -> one SessionBuilder per power-up, cut at every
    sensor restart (a power-up datagram sequence, or the start-up bit coming on). The builders are
    fed sample numbers as times: a power-up's times come from its counter as a whole (stim300.clock),
    known at its end, when the block means are retimed. Only the counter (and the host read time,
    with a read log) of every sample is kept until then: 1 (9) bytes a sample instead of 99."""

    DECIDE_RATE_AFTER = 256  # datagrams: enough counter steps to tell the sample rate without a configuration

    def __init__(self, name: str, with_host_times: bool):
        self.name, self.with_host_times = name, with_host_times
        self.rate_hz: int | float | None = None
        self.power_ups: list[PowerUp] = []
        self._seen = 0  # samples consumed
        self._cuts = PowerUpCuts()
        self._waiting: list[np.ndarray] = []  # samples before the rate is known
        self._open: tuple[SessionBuilder, int, list, list] | None = None  # builder, first, counters, host times
        self.refusal: str | None = None  # why the capture cannot be calibrated (raised once the decoder is done)
        self._bias_trims: tuple = ()  # the scanner's BTO datagrams (stim300.stream.TrimSeen) as of the last block
        self._trims_placed = 0  # the sequence number of the last one placed in its power-up
        self._trims: dict[int, tuple[TrimRecord, int]] = {}  # power-up's first datagram -> (last trim, changes)

    def consume(self, samples: np.ndarray, scanner) -> None:
        if self.refusal:
            return
        if self.rate_hz is None:
            self.refusal = self._refusal(samples, scanner)
            if self.refusal:
                return
            fmt, stats = scanner.format, scanner.stats
            if not (fmt.sample_rate_hz or stats.datagrams >= self.DECIDE_RATE_AFTER):
                self._waiting.append(samples.copy())
                return
            info = stream_info(scanner)
            if info.rate_hz is None:  # refused once decoding ends: raising here would leave a mapped capture held
                self.refusal = self._unknown_rate(info)
                return
            self._rate_known(info)
        self._cut_and_add(samples, scanner.stats.restart_datagrams)
        self._bias_trims = scanner.bias_trims
        self._place_trims()

    def finish(self, info: StreamInfo) -> None:
        """The capture is decoded (`info`: the whole stream)."""
        if self.rate_hz is None and self._waiting:
            self._rate_known(info)
        self._close()
        self._place_trims()
        for power_up in self.power_ups:
            power_up.trim, power_up.trim_changes = self._trims.get(power_up.first_datagram, (None, 0))

    def _place_trims(self) -> None:
        """Each BTO datagram to the power-up holding the datagram after it; one no sample follows
        yet waits (a restart may come first), one no sample ever follows is nobody's."""
        firsts = [p.first_datagram for p in self.power_ups] + ([self._open[1]] if self._open else [])
        for seen in self._bias_trims:
            if seen.sequence <= self._trims_placed:
                continue
            if seen.datagram >= self._seen or not firsts:
                return
            first = firsts[bisect.bisect_right(firsts, seen.datagram) - 1]
            last, changes = self._trims.get(first, (seen.trim, 0))
            self._trims[first] = (seen.trim, changes + (not last.same_offsets(seen.trim)))
            self._trims_placed = seen.sequence

    def _rate_known(self, info: StreamInfo) -> None:
        """The stream's rate is known: the blocks that waited for it go in."""
        self.rate_hz = info.rate_hz
        if self.rate_hz is None:
            raise CalibrationError(self._unknown_rate(info))
        waiting, self._waiting = self._waiting, []
        for block in waiting:
            self._cut_and_add(block, info.stats.restart_datagrams)

    def _unknown_rate(self, info: StreamInfo) -> str:
        n = info.stats.datagrams
        why = (f"{n} datagram(s) are too few to infer it from the counter" if n < self.DECIDE_RATE_AFTER else
               f"the counter of its {n} datagrams does not step (stuck)")
        said = ("no configuration datagram" if info.configuration is None else
                "its configuration datagram says the sensor is externally triggered" if info.external_trigger
                else "its configuration datagram gives none")
        return f"{self.name}: sample rate unknown: {said}, and {why}"

    def _refusal(self, samples: np.ndarray, scanner) -> str | None:
        fmt = scanner.format
        if fmt.gyro_unit.is_angle or fmt.acc_unit.is_velocity:
            return (f"{self.name}: calibration needs rate and acceleration outputs, "
                    f"not {fmt.gyro_unit.name} / {fmt.acc_unit.name}")
        return missing_sensors(samples, self.name)

    def _cut_and_add(self, samples: np.ndarray, restarts) -> None:
        """Add a block, cut at the sensor's restarts (`restarts`: each restarted sensor's first
        sample number, as the decoder knows them so far)."""
        for restarted, piece in self._cuts.pieces(samples, self._seen, restarts):
            if restarted:
                self._close()
            self._add(piece)
        self._seen += len(samples)

    def _add(self, samples: np.ndarray) -> None:
        if self._open is None:
            self._open = (SessionBuilder(), self._seen, [], [])
        builder, first, counters, host = self._open
        start = sum(len(c) for c in counters)
        builder.add(samples, np.arange(start, start + len(samples), dtype=np.float64), self.rate_hz)
        counters.append(samples["counter"].copy())
        if self.with_host_times:
            host.append(samples["t_host"].copy())

    def _close(self) -> None:
        """The open power-up is complete: time it by its counter and retime its block means."""
        if self._open is None:
            return
        builder, first, counters, host = self._open
        self._open = None
        counter = np.concatenate(counters)
        times = counter_times(counter, self.rate_hz, np.concatenate(host) if host else None)
        builder.retime(times.time_s)
        self.power_ups.append(PowerUp(
            builder, first, len(counter), float(times.time_s[-1]) + 1 / self.rate_hz,
            times.time_s[times.gap_index], times.gap_s, times.checked))


def decode_sessions(data, name: str, reads: np.ndarray | None = None,
                    drop_before=lambda offset: None) -> CaptureSessions:
    """Decode a capture's bytes (`name` says which capture in messages) into its power-ups, each
    kept block-averaged as it is decoded. `reads`, the capture's read log, stamps each datagram
    with its host read time, so the time base can include datagrams lost for whole counter
    cycles. `drop_before(offset)`: the bytes before `offset` are done with (an mmap can let them go)."""
    reader = _PowerUpReader(name, reads is not None)
    digest, hashed = hashlib.sha256(), 0  # hashed as decoded: the bytes are read once

    def on_block(samples, scanner, offset):
        nonlocal hashed
        reader.consume(samples, scanner)
        if offset > hashed:
            digest.update(memoryview(data)[hashed:offset])
            hashed = offset
        drop_before(offset)

    info = decode_blocks(data, on_block, reads=reads)
    digest.update(memoryview(data)[hashed:])
    if reader.refusal:
        raise CalibrationError(reader.refusal)
    if not info.stats.datagrams:
        raise CalibrationError(f"{name}: no STIM300 datagram found")
    reader.finish(info)
    return CaptureSessions(
        path=str(name), power_ups=reader.power_ups, rate_hz=reader.rate_hz,
        sensor=replace(info.sensor_record(), sample_rate_hz=reader.rate_hz),
        stream=ResultStream.of(info.stream_record(), capture=str(name)),
        identity={"size_bytes": len(data), "sha256": digest.hexdigest()})


def power_up_session(capture: CaptureSessions, number: int | None = None, start_s: float | None = 0.0) -> Session:
    """Power-up `number` (1-based; None: the last) from `start_s` (s since its first sample), or,
    with `start_s` None, from where the warm-up rule says its temperature has settled."""
    count = len(capture.power_ups)
    number = count if number is None else number
    if not 1 <= number <= count:
        raise CalibrationError(f"no power-up {number}: the capture has {count} (the sensor restarted "
                               f"{count - 1} times)")
    power_up = capture.power_ups[number - 1]
    time_s, values = power_up.data.stored()
    temps = None if np.isnan(values[:, 9]).all() else values[:, 9].astype(np.float64)
    if start_s is not None:
        start_by = "the given start"
    else:
        verdict = record_settling(time_s, temps, WARM_UP_RULE)
        start_s, start_by = (0.0 if verdict is None else verdict.start_s), start_words(verdict, WARM_UP_RULE)
    first = int(np.searchsorted(time_s, start_s))  # the times only grow
    if first == len(time_s):
        raise CalibrationError(f"start {start_s:g} s is past the end of power-up {number} of {count} "
                               f"({power_up.duration_s - 1 / capture.rate_hz:.1f} s)")
    hidden = power_up.gap_s[power_up.gap_time_s > start_s] if power_up.checked else None
    trim, trim_warnings = checked_trim(power_up.trim, capture.sensor.acc_range_g)
    if power_up.trim_changes:
        trim_warnings.append(f"the bias trim offsets changed {power_up.trim_changes} time(s) during power-up "
                             f"{number}: its data mix outputs of different trims; sensor.trim is the last")
    return Session(
        time_s=time_s[first:], gyro=values[first:, 0:3], acc=values[first:, 3:6],
        incl=inclinometers(values[first:, 6:9]),
        temperature_c=None if temps is None else temps[first:], rate_hz=stored_rate_hz(capture.rate_hz),
        sensor=replace(capture.sensor, trim=trim),
        stream=replace(capture.stream, warnings=(*capture.stream.warnings, *trim_warnings), start_s=float(start_s),
                       start_by=start_by, power_up=PowerUpRecord(number, count, power_up.first_datagram,
                                                                 power_up.datagrams, power_up.duration_s),
                       **fault_record(*power_up.data.fault_summary(start_s)), **hidden_gap_record(hidden)))

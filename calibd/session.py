"""Sessions: decoded samples in SI units, block-averaged to at most STORE_RATE_HZ.

One rule keeps a session, for the daemon on live data and for the one-shot commands on a
capture: `SessionBuilder` takes batches of decoded samples with their times and keeps them
block-averaged (averages of averages keep the estimators' models exact, and their work and
memory follow the stored samples) in float32. A capture is cut at every sensor restart and
one power-up makes a session, from where its warm-up ends or a given start.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stim300.bulk import decode_capture
from stim300.clock import counter_times
from stim300.codec import fault_bits, start_up_rises
from stim300.protocol import status_names

from .config import WarmupConfig
from .errors import CalibrationError
from .frames import STANDARD_GRAVITY
from .units import DEG
from .warmup import settling

STORE_RATE_HZ = 125  # faster data is block-averaged to this (the thesis's rate)
CHUNK_S = 60.0  # a capture is fed to the builder this much at a time: float64 temporaries stay small
WARM_UP_RULE = WarmupConfig()  # the daemon's default: calibrate starts a power-up where it is met


@dataclass
class Session:
    """Decoded data in SI, with what is known of the sensor and the stream."""

    time_s: np.ndarray
    gyro: np.ndarray  # rad/s
    acc: np.ndarray  # m/s^2
    incl: np.ndarray  # m/s^2
    temperature_c: np.ndarray | None  # mean of the gyro temperatures, when the datagram has them
    rate_hz: int
    sensor: dict
    stream: dict


@dataclass
class Capture:
    """A decoded capture cut at every sensor restart: each power-up has its own turn-on biases,
    counter and platform angle, so a calibration uses one of them, never a mix."""

    path: str
    samples: np.ndarray  # stim300.codec.SAMPLE_DTYPE, every power-up in stream order
    power_ups: list[tuple[int, int]]  # each power-up's samples [start, stop)
    rate_hz: int
    sensor: dict
    stream: dict  # the whole capture's stream statistics


def block_factor(rate_hz: int) -> int:
    """Samples averaged into one stored sample."""
    return max(1, rate_hz // STORE_RATE_HZ)


def stored_rate_hz(rate_hz: int) -> int:
    return rate_hz // block_factor(rate_hz)


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

    def add(self, samples: np.ndarray, time_s: np.ndarray, rate_hz: int) -> tuple[np.ndarray, np.ndarray]:
        """Store a batch (stim300.codec.SAMPLE_DTYPE, times in s); returns the times (s) and gyro
        samples (deg/s) stored from it."""
        k = block_factor(rate_hz)
        bits = fault_bits(samples)
        flagged = np.flatnonzero(bits)
        if len(flagged):
            self._flagged.append((time_s[flagged], bits[flagged]))
        temp = np.nanmean(samples["temp_gyro"], axis=1) if not np.isnan(samples["temp_gyro"][0, 0]) \
            else np.full(len(samples), np.nan)
        block = np.column_stack([time_s, samples["gyro"] * DEG, samples["acc"] * STANDARD_GRAVITY,
                                 samples["incl"] * STANDARD_GRAVITY, temp])
        block = np.concatenate([self._pending, block])
        whole = len(block) // k * k
        self._pending = block[whole:]
        mean = block[:whole].reshape(-1, k, block.shape[1]).mean(axis=1)
        mean[:, 0] = block[:whole:k, 0]  # a block's time is its first sample's
        if len(mean):
            self._time.append(mean[:, 0])
            self._values.append(mean[:, 1:].astype(np.float32))
        return mean[:, 0], mean[:, 1:4] / DEG

    def arrays(self, since_s: float = -np.inf) -> dict[str, np.ndarray]:
        """The stored samples from `since_s` on, float64: time_s, gyro, acc, incl, temp."""
        time_s = np.concatenate(self._time) if self._time else np.zeros(0)
        keep = time_s >= since_s
        values = np.concatenate(self._values)[keep].astype(np.float64) if self._values else np.zeros((0, 10))
        return {"time_s": time_s[keep], "gyro": values[:, 0:3], "acc": values[:, 3:6], "incl": values[:, 6:9],
                "temp": values[:, 9]}

    @property
    def end_s(self) -> float:
        return float(self._time[-1][-1]) if self._time else 0.0

    def trim(self, before_s: float) -> None:
        """Forget whole batches that end before `before_s` (warm-up data nobody will use)."""
        while self._time and self._time[0][-1] < before_s:
            self._time.pop(0)
            self._values.pop(0)
        self._flagged = [(t[t >= before_s], b[t >= before_s]) for t, b in self._flagged if t[-1] >= before_s]

    def fault_summary(self, since_s: float = -np.inf) -> tuple[int, int]:
        """(samples the sensor flagged from `since_s` on, the union of their fault bits)."""
        bits = [b[t >= since_s] for t, b in self._flagged]
        count = sum(len(b) for b in bits)
        return count, int(np.bitwise_or.reduce(np.concatenate(bits))) if count else 0


def fault_record(count: int, bits: int) -> dict:
    return {"flagged_datagrams": count, "fault_flags": status_names(bits)}


def hidden_gap_record(gap_s: list[float] | np.ndarray | None) -> dict:
    """Gaps the datagram counter could not see (whole counter cycles), found from host read times
    (`gap_s`: the time each added), or None where there were no host times to look with."""
    if gap_s is None:
        return {"hidden_gaps": None, "hidden_gap_s": None}
    return {"hidden_gaps": len(gap_s), "hidden_gap_s": round(float(np.sum(gap_s)), 3)}


def decode(data, name: str, reads: np.ndarray | None = None) -> Capture:
    """Decode a capture's bytes (`name` says which capture in messages) and find its power-ups.
    `reads`, the capture's read log, stamps each datagram with its host read time, so the time
    base can include datagrams lost for whole counter cycles."""
    samples, scanner = decode_capture(data, reads=reads)
    if not len(samples):
        raise CalibrationError(f"{name}: no STIM300 datagram found")
    fmt = scanner.format
    if fmt.gyro_unit.is_angle or fmt.acc_unit.is_velocity:
        raise CalibrationError(f"{name}: calibration needs rate and acceleration outputs, "
                               f"not {fmt.gyro_unit.name} / {fmt.acc_unit.name}")
    if np.isnan(samples["acc"][0, 0]) or np.isnan(samples["incl"][0, 0]):
        raise CalibrationError(f"{name}: datagram 0x{fmt.datagram_id:02X} lacks accelerometers or inclinometers")
    stats = scanner.stats
    rate = fmt.sample_rate_hz or 2000 // stats.counter_step
    cuts = sorted({0, len(samples), *stats.restart_datagrams, *start_up_rises(samples).tolist()})
    return Capture(
        path=str(name), samples=samples, power_ups=list(zip(cuts, cuts[1:])), rate_hz=rate,
        sensor={"serial_number": scanner.serial_number.text if scanner.serial_number else None,
                "part_number": str(scanner.part_number) if scanner.part_number else None,
                "datagram_id": f"0x{fmt.datagram_id:02X}", "sample_rate_hz": rate},
        stream={"capture": str(name), "datagrams": stats.datagrams, "lost_samples": stats.lost_samples,
                "crc_errors": stats.crc_errors, "restarts": stats.restarts})


def power_up_session(capture: Capture, number: int | None = None, start_s: float | None = 0.0) -> Session:
    """Power-up `number` (1-based; None: the last) from `start_s` (s since its first sample), or,
    with `start_s` None, from where the warm-up rule says its temperature has settled. The samples
    go through the SessionBuilder CHUNK_S at a time, as the daemon's batches do."""
    count = len(capture.power_ups)
    number = count if number is None else number
    if not 1 <= number <= count:
        raise CalibrationError(f"no power-up {number}: the capture has {count} (the sensor restarted "
                               f"{count - 1} times)")
    first, stop = capture.power_ups[number - 1]
    samples = capture.samples[first:stop]
    times = counter_times(samples["counter"], capture.rate_hz, samples["t_host"])
    builder = SessionBuilder()
    chunk = max(1, int(CHUNK_S * capture.rate_hz))
    for a in range(0, len(samples), chunk):
        builder.add(samples[a:a + chunk], times.time_s[a:a + chunk], capture.rate_hz)
    data = builder.arrays()
    time_s = data["time_s"]
    temps = None if np.isnan(data["temp"]).all() else data["temp"]
    if start_s is not None:
        start_by = "the given start"
    elif temps is None:
        start_s, start_by = 0.0, "the first sample (no temperatures: the warm-up rule cannot be applied)"
    else:
        verdict = settling(time_s, temps, WARM_UP_RULE)
        start_s = verdict.start_s
        start_by = (f"warm-up rule: the temperature settled ({verdict.trend_c_per_h:+.2f} degC/h over "
                    f"{WARM_UP_RULE.window_s:g} s)" if verdict.settled else
                    f"warm-up rule: the temperature never settles, the calmest window ({verdict.trend_c_per_h:+.2f} "
                    f"degC/h over {WARM_UP_RULE.window_s:g} s)")
    keep = time_s >= start_s
    if not keep.any():
        raise CalibrationError(f"start {start_s:g} s is past the end of power-up {number} of {count} "
                               f"({times.time_s[-1]:.1f} s)")
    hidden = times.gap_s[times.time_s[times.gap_index] > start_s] if times.checked else None
    return Session(
        time_s=time_s[keep], gyro=data["gyro"][keep], acc=data["acc"][keep], incl=data["incl"][keep],
        temperature_c=None if temps is None else temps[keep], rate_hz=stored_rate_hz(capture.rate_hz),
        sensor=capture.sensor,
        stream=capture.stream | {
            "start_s": float(start_s), "start_by": start_by,
            "power_up": {"number": number, "count": count, "first_datagram": first, "datagrams": stop - first,
                         "duration_s": float(times.time_s[-1]) + 1 / capture.rate_hz},
            **fault_record(*builder.fault_summary(start_s)), **hidden_gap_record(hidden)})

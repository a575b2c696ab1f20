"""A recording of Imu messages as the STIM300 byte stream it stands for, so that `calibd replay`
feeds it through the daemon's own path (its parser, a pty, what it serves) unchanged.

Each message becomes one normal datagram 0x91 (rates and accelerations: a recording has no
inclinometers and no temperatures) in the format a decoder takes when no configuration datagram
says otherwise (accelerometer range 10 g, no CR LF). The stream has no power-up datagrams (the
serial number and the configuration are not known): the decoder takes the rate from the
counter's step, a rate that is not one of the configured ones as an external trigger's. The
counter counts internal 2000 Hz samples by the header stamps, so a gap in the stamps is a gap
the counter shows, as a lost datagram is; the read log (`stim300.reads`), its times the stamps,
lets the counter clock find the gaps of whole counter cycles, as in a recorded capture. Values
beyond what the datagram holds are saturated and flagged OVERLOAD, as the sensor flags its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stim300.clock import STEADY_S
from stim300.codec import encode_samples
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, NORMAL_LAYOUTS, Format, Status
from stim300.reads import READS_DTYPE

from .errors import CalibrationError
from .frames import STANDARD_GRAVITY
from .recordings import ImuRecording, StampTimes, imu_samples
from .units import DEG

DATAGRAM_ID = 0x91
FORMAT = Format(datagram_id=DATAGRAM_ID, crlf=False)  # the scales a decoder takes without a configuration datagram
DATAGRAM_BYTES = NORMAL_LAYOUTS[DATAGRAM_ID].wire_length(crlf=False)
RATE_TOLERANCE = 0.01  # how far the stamps' rate may be from 2000 Hz / a whole counter step
READ_MESSAGES = 64  # a read ends after this many messages at most, and after STEADY_S of them: the messages
# of a read share its time, and the counter clock takes a read spanning more for a backlog read late
COUNT_LIMITS = (-(1 << 23), (1 << 23) - 1)  # a 24-bit value's counts
LSB = {name: FORMAT.scales()[name] for name in ("gyro", "acc")}  # deg/s, g
AXIS_BITS = np.array([Status.X, Status.Y, Status.Z], np.uint8)


@dataclass(frozen=True)
class RecordingBytes:
    """A recording's messages as datagrams (`data`) with their read log (READS_DTYPE rows), and
    what they are: the recording (its format in words), topic and frame id, how many messages, the
    counter's step (internal samples per message), the stamps' measured rate, and warnings (gaps,
    values saturated), one line each."""

    data: bytearray
    reads: np.ndarray
    recording: str
    topic: str
    frame_id: str
    messages: int
    step: int
    stamps_rate_hz: int | float
    warnings: list[str]

    @property
    def rate_hz(self) -> int | float:
        """The stream's rate: 2000 Hz / the counter's step (a whole number when it divides)."""
        return INTERNAL_RATE_HZ // self.step if INTERNAL_RATE_HZ % self.step == 0 else INTERNAL_RATE_HZ / self.step

    @property
    def origin(self) -> dict:
        """What the daemon's results say of the recording beside the datagrams' statistics, as
        `calibd calibrate` says it of a recording."""
        return {"recording": self.recording, "topic": self.topic, "frame_id": self.frame_id}

    def description(self) -> str:
        measured = "" if self.stamps_rate_hz == self.rate_hz else f" (the stamps: {self.stamps_rate_hz:.6g} Hz)"
        return (f"{self.messages} Imu messages of topic {self.topic} replayed as STIM300 datagrams "
                f"0x{DATAGRAM_ID:02X} at {self.rate_hz:g} Hz{measured}")


def counter_step(where, rate_hz: float) -> int:
    """The counter's step (internal samples per message) of a rate within RATE_TOLERANCE of
    2000 Hz / a whole step smaller than a counter cycle; CalibrationError otherwise."""
    step = max(1, round(INTERNAL_RATE_HZ / rate_hz))
    if step >= COUNTER_MODULUS or abs(INTERNAL_RATE_HZ / step / rate_hz - 1) > RATE_TOLERANCE:
        raise CalibrationError(f"{where}: the header stamps step at {rate_hz:.6g} Hz, not {INTERNAL_RATE_HZ} Hz "
                               f"divided by a whole number below {COUNTER_MODULUS} (within {RATE_TOLERANCE:.0%}): "
                               "no STIM300 datagram counter counts so")
    return step


def _saturate(samples: np.ndarray) -> int:
    """Flag OVERLOAD (with the axes) in the status of each gyro and accelerometer triad beyond
    what a datagram holds (the encoder saturates the values); how many samples have one."""
    beyond_any = np.zeros(len(samples), bool)
    for name, lsb in LSB.items():
        counts = np.rint(samples[name] / lsb)
        beyond = (counts < COUNT_LIMITS[0]) | (counts > COUNT_LIMITS[1])
        axes = beyond @ AXIS_BITS
        samples["status_" + name] = np.where(axes, axes | Status.OVERLOAD, 0)
        beyond_any |= axes != 0
    return int(np.count_nonzero(beyond_any))


def _read_ends(index: np.ndarray, slots: np.ndarray, per_read: int) -> np.ndarray:
    """Which messages of a batch end a read: every `per_read`-th, each one a gap follows, the
    batch's last."""
    ends = (index + 1) % per_read == 0
    ends[:-1] |= np.diff(slots) > 1
    ends[-1] = True
    return ends


def recording_bytes(path, topic: str | None = None) -> RecordingBytes:
    """The Imu messages of `topic` (None: the recording's only Imu topic) as datagrams 0x91, one
    each, with a read log timed by their stamps; CalibrationError (one line naming the file) for
    a recording that cannot be read or whose stamps no STIM300 counter could count."""
    recording, stamps = ImuRecording(path, topic), StampTimes(str(path))
    data, reads, saturated = bytearray(), [], 0  # extended in place: a large bytearray grows without a copy
    step = per_read = None
    for stamps_ns, gyro, acc, frame_id in recording.batches():
        time_s = stamps.times(stamps_ns, frame_id)
        if step is None:
            step = counter_step(path, stamps.rate_hz)
            per_read = max(1, min(READ_MESSAGES, int(STEADY_S * INTERNAL_RATE_HZ / step)))
        first = stamps.messages - len(stamps_ns)
        samples = imu_samples(gyro, acc)
        slot = stamps.slots
        samples["counter"] = slot * step % COUNTER_MODULUS
        saturated += _saturate(samples)
        data += encode_samples(samples, DATAGRAM_ID, FORMAT, crlf=False).tobytes()
        index = first + np.arange(len(stamps_ns))
        ends = _read_ends(index, slot, per_read)
        log = np.empty(np.count_nonzero(ends), READS_DTYPE)
        log["end"], log["t_host_s"] = (index[ends] + 1) * DATAGRAM_BYTES, time_s[ends]
        reads.append(log)
    if not stamps.messages:
        raise CalibrationError(f"{path}: topic {recording.topic}: no message could be read")
    gyro_limit, acc_limit = (COUNT_LIMITS[1] * lsb for lsb in LSB.values())
    warnings = stamps.warnings + ([f"{saturated} message(s) beyond what a datagram 0x{DATAGRAM_ID:02X} holds "
                                   f"(+-{gyro_limit:.0f} deg/s = {gyro_limit * DEG:.2f} rad/s, "
                                   f"+-{acc_limit:.0f} g = {acc_limit * STANDARD_GRAVITY:.0f} m/s^2): "
                                   "saturated and flagged OVERLOAD, as the sensor flags its own"]
                                 if saturated else [])
    return RecordingBytes(data, np.concatenate(reads), recording.words, recording.topic, stamps.frame_id,
                          stamps.messages, step, stamps.rate_hz, warnings)

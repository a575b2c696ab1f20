"""A STIM300 recording as one MCAP file (`stim300 record PORT -o OUT.mcap`): the sensor's bytes
exactly as read, with their read times, beside the samples as ROS 2 sensor_msgs/Imu, so one file
serves the STIM300 tools (lossless), Foxglove and ROS 2 tools (`ros2 bag play`, any MCAP reader).

The file has the ROS 2 profile and two channels, both ROS 2 messages in CDR:
- RAW_TOPIC, std_msgs/msg/UInt8MultiArray: one message per read of the port, its `data` the
  bytes read, in order (sequence numbers from 0); log_time the host's realtime clock at the read,
  publish_time its monotonic clock, which the read log keeps (`stim300.reads`: the datagram
  counter's hidden gaps are found from it). Concatenated, the messages are the capture.
- IMU_TOPIC, sensor_msgs/msg/Imu: every sample of a rate and acceleration output in SI, stamped
  on the host's realtime clock from the sensor's counter (`stim300.wallclock`); the covariances
  are left unknown (zeros: the driver states no noise figures), no orientation (REP 145).
`read_capture` gives the bytes and the read log back, so `stim300 decode`, `stim300 info` and
calibd read such a file as the raw capture it holds. The `mcap` package writes and reads it (the
`recordings` extra); the message definitions' text is rosbags' generation.
"""

from __future__ import annotations

import math
import os
import stat
import struct
import time

import numpy as np

from .capture import stream_info
from .clock import CounterClock
from .codec import join_samples
from .errors import FormatError, UsageError
from .protocol import NORMAL_LAYOUTS, STANDARD_GRAVITY
from .reads import READS_DTYPE
from .rosimu import ABSENT, CDR_LE, IMU, NS_PER_S, ImuEncoder
from .stream import StreamParser
from .wallclock import WallClock

NEEDS_EXTRA = "an MCAP recording needs the recordings extra: pip install 'stim300-calib[recordings]'"
RAW = "std_msgs/msg/UInt8MultiArray"
RAW_TOPIC = "/stim300/raw"
IMU_TOPIC = "/imu/data_raw"
MAGIC = b"\x89MCAP0\r\n"
_RAW_HEADER = CDR_LE + struct.pack("<II", 0, 0)  # no layout dimensions, data_offset 0; then the length
UNKNOWN = np.zeros(9)  # sensor_msgs/Imu: a covariance of zeros is not known
PENDING_READS = 4096  # reads whose samples wait until the stream's rate is known (seconds at most)
IMU_BATCH = 256  # samples turned into Imu messages at once (0.13 s at 2000 Hz, 2 s at 125 Hz)


def mcap_modules():
    """The mcap package's modules and rosbags' ROS 2 type store, or a UsageError naming the extra."""
    try:
        import mcap.reader
        import mcap.records
        import mcap.stream_reader
        import mcap.writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise UsageError(NEEDS_EXTRA) from None
    return mcap, get_typestore(Stores.ROS2_HUMBLE)


def holds_capture(path) -> bool:
    """Whether `path` is an MCAP file (by its magic) with a channel of a STIM300's bytes
    (RAW_TOPIC): in its summary, or for a file whose summary cannot be read (cut short, damaged),
    among the records before the damage (`read_capture` then says what is wrong)."""
    try:
        with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as f:  # a FIFO: no wait for a writer
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode) or f.read(len(MAGIC)) != MAGIC:
                return False
            mcap, _ = mcap_modules()
            f.seek(0)
            try:
                summary = mcap.reader.make_reader(f).get_summary()
            except Exception:  # noqa: BLE001 (mcap's errors, struct's on a cut record: look at what is there)
                summary = None
            if summary is not None:
                return any(c.topic == RAW_TOPIC for c in summary.channels.values())
            f.seek(0)
            return _raw_channel_before_damage(mcap, f)
    except OSError:
        return False


def _raw_channel_before_damage(mcap, f) -> bool:
    found = False
    try:
        for record in mcap.stream_reader.StreamReader(f, skip_magic=False).records:
            if isinstance(record, mcap.records.Channel) and record.topic == RAW_TOPIC:
                found = True
                break
    except Exception:  # noqa: BLE001 (the damage itself)
        pass
    return found


class McapRecorder:
    """Reads of the port in, an MCAP written to the binary file `f`; `finish()` ends it."""

    def __init__(self, f, frame_id: str = "imu_link", library: str = "stim300"):
        mcap, types = mcap_modules()
        self.writer = mcap.writer.Writer(f)
        self.writer.start(profile="ros2", library=library)
        schemas = {name: self.writer.register_schema(name, "ros2msg", types.generate_msgdef(name, ros_version=2)[0]
                                                     .encode()) for name in (RAW, IMU)}
        self.raw = self.writer.register_channel(RAW_TOPIC, "cdr", schemas[RAW])
        self.imu = self.writer.register_channel(IMU_TOPIC, "cdr", schemas[IMU])
        self.encoder = ImuEncoder(frame_id)
        self.parser = StreamParser()
        self.clock, self.wall = CounterClock(), WallClock()
        self.reads = self.samples = 0
        self.pending: list[np.ndarray] = []
        self.pending_samples = 0
        self.unpublished: str | None = None  # why the samples are not Imu messages (outputs not rates)

    def add(self, data: bytes, t_host_s: float, realtime_ns: int | None = None) -> None:
        """One read: its bytes and the host's monotonic time when it returned (s)."""
        realtime_ns = time.time_ns() if realtime_ns is None else realtime_ns
        self.writer.add_message(self.raw, realtime_ns, _RAW_HEADER + struct.pack("<I", len(data)) + data,
                                round(t_host_s * NS_PER_S), self.reads)
        self.reads += 1
        samples = self.parser.feed(data, t_host_s)
        if len(samples) and not self.unpublished:
            self.pending.append(samples)
            self.pending_samples += len(samples)
            if len(self.pending) > PENDING_READS:  # the rate is still not known: the oldest go
                self.pending_samples -= len(self.pending.pop(0))
        if self.pending_samples >= IMU_BATCH:
            self._imu()

    def _imu(self) -> None:
        """The pending samples as Imu messages, once the stream's rate is known: in batches, as
        the counter clock and the encoder cost per call more than per sample."""
        info = stream_info(self.parser)
        if not info.rate_hz or not self.pending or self.unpublished:
            return
        fmt = info.format
        clusters = NORMAL_LAYOUTS[fmt.datagram_id].clusters
        if fmt.gyro_unit.is_angle or ("acc" in clusters and fmt.acc_unit.is_velocity):
            self.unpublished = (f"the outputs are {fmt.gyro_unit.name.lower()} and {fmt.acc_unit.name.lower()}: "
                                "sensor_msgs/Imu carries rates and accelerations")
            return
        samples = join_samples(self.pending)
        self.pending, self.pending_samples = [], 0
        times = self.clock.times(samples["counter"], info.rate_hz, samples["t_host"])
        stamps, _ = self.wall.stamps(times.time_s, samples["t_host"])
        gyro = samples["gyro"].astype(np.float64) * (math.pi / 180)
        acc = samples["acc"].astype(np.float64) * STANDARD_GRAVITY
        acc_cov = UNKNOWN if "acc" in clusters else ABSENT
        for stamp, message in zip(stamps.tolist(), self.encoder.encode(stamps, gyro, acc, UNKNOWN, acc_cov)):
            self.writer.add_message(self.imu, stamp, message, stamp, self.samples)
            self.samples += 1

    def finish(self) -> None:
        self._imu()
        self.writer.finish()


def read_capture(path) -> tuple[bytes, np.ndarray]:
    """The bytes of the raw channel of a recording `McapRecorder` wrote, in order, and its read log
    (`stim300.reads.READS_DTYPE`); UsageError (one line naming the file) for an MCAP without it."""
    mcap, _ = mcap_modules()
    chunks = []
    try:
        with open(path, "rb") as f:
            reader = mcap.reader.make_reader(f)
            for _, channel, message in reader.iter_messages(topics=[RAW_TOPIC]):
                body = message.data
                (length,) = struct.unpack_from("<I", body, len(_RAW_HEADER))
                start = len(_RAW_HEADER) + 4
                if body[:len(_RAW_HEADER)] != _RAW_HEADER or len(body) != start + length:
                    raise FormatError(f"message {message.sequence} of {RAW_TOPIC} is not a {RAW} of raw bytes")
                chunks.append((message.sequence, body[start:], message.publish_time / NS_PER_S))
    except (OSError, FormatError, struct.error, mcap.exceptions.McapError) as exc:
        raise UsageError(f"{path}: cannot read the MCAP recording: {str(exc).splitlines()[0][:160]}") from None
    if not chunks:
        raise UsageError(f"{path}: an MCAP file without the channel {RAW_TOPIC} of a STIM300's bytes "
                         "(stim300 record -o OUT.mcap writes it)")
    chunks.sort(key=lambda chunk: chunk[0])
    reads = np.empty(len(chunks), READS_DTYPE)
    reads["end"] = np.cumsum([len(data) for _, data, _ in chunks])
    reads["t_host_s"] = [t for _, _, t in chunks]
    return b"".join(data for _, data, _ in chunks), reads

"""Recordings of sensor_msgs/Imu as captures: rosbag2 directories (SQLite3 or MCAP storage) and
SQLite3 files alone, read through rosbags; plain MCAP files of any profile, with ROS 2 (CDR) or
ROS 1 messages, through the mcap package; ROS 1 bags through calibd.bag1, chunk by chunk.

What the robotics world shares of a STIM300 is its driver's Imu topic, not the sensor's bytes: the
angular velocity (rad/s) and linear acceleration (m/s^2), stamped. No inclinometers, no
temperatures, no counter and no status bytes come with it: a recording is calibrated as a unit
without inclinometers whose warm-up cannot be checked. Its times are the header stamps (when the
driver says the sample was taken, not when the recorder got it), its rate the stamps' median step,
its gaps the steps of more than GAP_STEPS sample intervals. Messages are read in batches of
BATCH_MESSAGES and decoded with numpy from their serialised bytes (an Imu is fixed-size after its
frame id), and used as they come (block-averaged into a power-up, or corrected by apply): a long
recording is never held whole.
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
import struct
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from stim300.cliutil import open_regular
from stim300.codec import SAMPLE_DTYPE
from stim300.protocol import INTERNAL_RATE_HZ
from stim300.records import SensorRecord

from .errors import CalibrationError
from .frames import STANDARD_GRAVITY
from .results import ResultStream
from .session import CaptureSessions, PowerUp, SessionBuilder
from .units import DEG

IMU_TYPE = "sensor_msgs/msg/Imu"
NEEDS_EXTRA = "reading a recording needs the recordings extra: pip install 'stim300-calib[recordings]'"
KINDS = {  # how a file starts -> the name ending rosbags reads it by, and what it is in words
    b"#ROSBAG V": (".bag", "ROS 1 bag"),
    b"\x89MCAP0\r\n": (".mcap", "MCAP file"),
    b"SQLite format 3\x00": (".db3", "rosbag2 SQLite3 file"),
}
ROSBAG2_DIRECTORY = "rosbag2 directory"
MCAP_FILE = KINDS[b"\x89MCAP0\r\n"][1]  # read by the mcap package: every profile and ROS 1 messages too
ROS1_BAG = KINDS[b"#ROSBAG V"][1]  # read by calibd.bag1 in bounded memory
BATCH_MESSAGES = 16384  # messages decoded at once; the first batch's stamps also give the rate
GAP_STEPS = 1.5  # a stamp step longer than this many sample intervals is a gap
FASTEST_RATE_HZ = 1.05 * INTERNAL_RATE_HZ  # a faster median step is not the sensor's (host stamps of bursts of reads)
HASH_BLOCK_BYTES = 1 << 20

# An Imu after its header: orientation, angular velocity and linear acceleration (float64 x 4, 3, 3),
# each followed by its 3x3 covariance: 296 bytes, packed in ROS 1, 8-aligned in CDR. The header
# starts alike in both (ROS 1: seq; CDR: the encapsulation, then): stamp seconds at byte 4,
# nanoseconds at 8, the frame id's length at 12 and its characters from 16 (CDR: with a NUL).
IMU_BODY_BYTES = 296
GYRO_FROM_END = 192  # angular velocity: the body's bytes 104-128
ACC_FROM_END = 96  # linear acceleration: 200-224
ACC_COVARIANCE_FROM_END = 72  # its covariance's first element: -1 when the message carries none (REP 145)
CDR_LITTLE_ENDIAN = b"\x00\x01"


def _kind(path) -> tuple[str, str] | None:
    """(the name ending rosbags reads it by, what it is in words) of a recording, by its content;
    None for anything else. UsageError (one line) for an input that is no file or directory."""
    if os.path.isdir(path):
        return ("", ROSBAG2_DIRECTORY) if os.path.isfile(os.path.join(path, "metadata.yaml")) else None
    with open_regular(path) as f:
        head = f.read(16)
    return next((kind for magic, kind in KINDS.items() if head.startswith(magic)), None)


def is_recording(path) -> bool:
    """Whether `path` is a recording (by its content, whatever its name) rather than a STIM300 capture."""
    return _kind(path) is not None


def _unreadable(exc: Exception) -> bool:
    """Whether rosbags or mcap raised `exc` for a file it cannot read (a truncated bag, a corrupt
    chunk, a bad metadata.yaml, a damaged database, a cut record), not for a fault of the program.
    lz4 says a corrupt chunk with a RuntimeError of its own words; bz2 (ROS 1 chunks) with an
    OSError; mcap's zstd (the zstandard package) with its own ZstdError."""
    from mcap.exceptions import McapError
    from rosbags.highlevel import AnyReaderError

    from .bag1 import BagError
    from zstandard import ZstdError as McapZstdError
    from rosbags.rosbag1 import ReaderError as Bag1Error
    from rosbags.rosbag2 import ReaderError as Bag2Error
    try:
        from compression.zstd import ZstdError  # the zstd rosbags decompresses with: the standard library's
    except ImportError:  # before Python 3.14
        from backports.zstd import ZstdError

    return (isinstance(exc, (AnyReaderError, Bag1Error, Bag2Error, McapError, BagError, ZstdError, McapZstdError,
                             sqlite3.DatabaseError, EOFError, OSError, struct.error))
            or isinstance(exc, RuntimeError) and str(exc).startswith("LZ4"))


class ImuRecording:
    """The Imu messages of one topic of a recording, read in decoded batches (`batches`): `topic`
    (None: `preferred` when the recording has that Imu topic, else its only one; its name once
    read), `words` what the file is, `messages` how many the recording's index counts (0 until
    read)."""

    def __init__(self, path, topic: str | None = None, preferred: str | None = None):
        try:
            from rosbags.highlevel import AnyReader  # noqa: F401 (the extra is there)
        except ImportError:
            raise CalibrationError(f"{path}: {NEEDS_EXTRA}") from None
        self.path, self.topic, self.preferred, self.messages = path, topic, preferred, 0
        ending, self.words = _kind(path)
        if ending == ".db3" and Path(path).suffix != ending:  # rosbags reads a storage file by its name
            raise CalibrationError(f"{path}: a {self.words} by its content, but recordings are read by the name "
                                   f"ending {ending}: rename it")

    def batches(self):
        """(header stamps in ns, angular velocity in rad/s, linear acceleration in m/s^2, the first
        message's frame id) of up to BATCH_MESSAGES messages at a time, in the recording's order;
        CalibrationError (one line naming the file) for a recording that cannot be read."""
        path, read, batch = self.path, 0, []
        try:
            with ExitStack() as opened:
                backend = {MCAP_FILE: self._mcap_messages, ROS1_BAG: self._bag1_messages}.get(self.words,
                                                                                             self._rosbags_messages)
                messages, encoding = backend(opened)
                for data in messages:
                    batch.append(data)
                    if len(batch) == BATCH_MESSAGES:
                        yield decode_imu(batch, encoding, path, read)
                        read, batch = read + len(batch), []
                if batch:
                    yield decode_imu(batch, encoding, path, read)
        except Exception as exc:
            if not _unreadable(exc):
                raise
            raise CalibrationError(f"{path}: cannot read the {self.words}: {' '.join(str(exc).split())}") from None

    def _bag1_messages(self, opened: ExitStack):
        """A ROS 1 bag's serialised messages of the topic in the file's order (calibd.bag1: rosbags'
        reader would index every message first), and their encoding (kept open in `opened`)."""
        from .bag1 import Bag1

        bag = Bag1(opened.enter_context(open_regular(self.path)))
        topics = {name: (_ros2_type(msgtype) if msgtype else "", count)
                  for name, (msgtype, count) in bag.topics.items()}
        self.topic = _imu_topic(topics, self.path, self.topic, self.preferred)
        self.messages = topics[self.topic][1]
        return bag.messages(self.topic), "ros1"

    def _rosbags_messages(self, opened: ExitStack):
        """A bag's or a rosbag2's serialised messages of the topic, and their encoding, read by rosbags
        (kept open in `opened`)."""
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        # a bag of ROS 2 Humble or older names no message definitions: the standard ones are taken
        reader = opened.enter_context(AnyReader([Path(self.path)], default_typestore=get_typestore(Stores.LATEST)))
        topics = reader.topics
        self.topic = _imu_topic({name: (info.msgtype, info.msgcount) for name, info in topics.items()},
                                self.path, self.topic, self.preferred)
        self.messages, connections = topics[self.topic].msgcount, topics[self.topic].connections
        encodings = {"ros1"} if not reader.is2 else {getattr(c.ext, "serialization_format", "cdr") for c in connections}
        return (data for _, _, data in reader.messages(connections)), _one_encoding(encodings, self.path, self.topic)

    def _mcap_messages(self, opened: ExitStack):
        """A plain MCAP file's serialised messages of the topic in the file's order, and their
        encoding, read by the mcap package: any profile, ROS 2 (CDR) or ROS 1 messages (kept open
        in `opened`)."""
        from mcap.reader import make_reader
        from mcap.records import Message
        from mcap.stream_reader import StreamReader

        f = opened.enter_context(open_regular(self.path))
        summary = make_reader(f).get_summary()
        if summary is None or summary.statistics is None:
            raise CalibrationError(f"{self.path}: the MCAP file has no summary (cut short? `mcap recover` rebuilds "
                                   "one)")
        topics: dict[str, list] = {}
        for channel in summary.channels.values():
            topics.setdefault(channel.topic, []).append(channel)
        counts = summary.statistics.channel_message_counts
        schemas = {name: {_ros2_type(summary.schemas[c.schema_id].name) if c.schema_id in summary.schemas else ""
                          for c in channels} for name, channels in topics.items()}
        self.topic = _imu_topic({name: (next(iter(types)) if len(types) == 1 else "", sum(
            counts.get(c.id, 0) for c in topics[name])) for name, types in schemas.items()}, self.path, self.topic,
            self.preferred)
        self.messages = sum(counts.get(c.id, 0) for c in topics[self.topic])
        encodings = {c.message_encoding for c in topics[self.topic]}
        ids = {c.id for c in topics[self.topic]}
        f.seek(0)  # the records in the file's order, as recorded (twice as fast as the reader's log-time merge)
        return ((record.data for record in StreamReader(f).records
                 if isinstance(record, Message) and record.channel_id in ids),
                _one_encoding(encodings, self.path, self.topic))


def open_recording(path, topic: str | None = None, progress=lambda done, total: None) -> CaptureSessions:
    """The Imu messages of `topic` (None: the recording's only Imu topic) as a capture of one
    power-up, block-averaged as they come (`progress(messages read, messages in all)` after each
    batch); CalibrationError (one line naming the file) for a recording that cannot be read or
    has no such messages."""
    recording, stamps, builder = ImuRecording(path, topic), StampTimes(str(path)), SessionBuilder()
    for stamps_ns, gyro, acc, frame_id in recording.batches():
        builder.add(imu_samples(gyro, acc), stamps.times(stamps_ns, frame_id), stamps.rate_hz)
        progress(stamps.messages, recording.messages)
    if not stamps.messages:
        raise CalibrationError(f"{path}: topic {recording.topic}: no message could be read")
    return stamps.capture(builder, recording.topic, recording.words, identity(path))


def _imu_topic(topics: dict[str, tuple[str, int]], path, topic: str | None, preferred: str | None = None) -> str:
    """The Imu topic asked for (else `preferred` when it is one, else the only one) of `topics`
    (name -> (message type, "" when of several; message count)), with messages."""
    imu = sorted(name for name, (msgtype, _) in topics.items() if msgtype == IMU_TYPE)
    if topic is None and preferred in imu:
        topic = preferred
    if topic is None:
        if not imu:
            raise CalibrationError(f"{path}: no {IMU_TYPE} topic (the recording has "
                                   f"{', '.join(sorted(topics)) or 'no topics'})")
        if len(imu) > 1:
            raise CalibrationError(f"{path}: {len(imu)} {IMU_TYPE} topics ({', '.join(imu)}): choose one with --topic")
        topic = imu[0]
    elif topic not in topics:
        raise CalibrationError(f"{path}: no topic {topic} (its {IMU_TYPE} topics: {', '.join(imu) or 'none'})")
    elif topics[topic][0] != IMU_TYPE:
        raise CalibrationError(f"{path}: topic {topic} is {topics[topic][0] or 'of several types'}, not {IMU_TYPE}")
    if not topics[topic][1]:
        raise CalibrationError(f"{path}: topic {topic} has no messages")
    return topic


def _ros2_type(name: str) -> str:
    """A message type by its ROS 2 name (a ROS 1 schema says sensor_msgs/Imu), as rosbags names them."""
    package, _, message = name.rpartition("/")
    return name if not package or "/" in package else f"{package}/msg/{message}"


def _one_encoding(encodings: set[str], path, topic: str) -> str:
    """The topic's one message encoding that decode_imu reads (ros1 or cdr)."""
    if len(encodings) != 1 or not encodings <= {"ros1", "cdr"}:
        raise CalibrationError(f"{path}: topic {topic} is encoded as {', '.join(sorted(encodings))}: "
                               "only cdr or ros1 is read")
    return next(iter(encodings))


def _gather(buf: np.ndarray, offsets: np.ndarray, dtype: str, count: int = 1) -> np.ndarray:
    """`count` values of `dtype` at each offset of `buf` (bytes), one row per offset."""
    size = np.dtype(dtype).itemsize * count
    return buf[offsets[:, None] + np.arange(size)].view(dtype).reshape(len(offsets), count)


def decode_imu(messages: list, encoding: str, where, first: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Serialised sensor_msgs/Imu messages (`encoding`: "ros1" or "cdr", little-endian) -> (header stamps
    in ns, angular velocity in rad/s, linear acceleration in m/s^2, the first message's frame id),
    decoded together: a message's values lie at fixed places from its end. `first`: the first
    message's number in the topic, for messages that are not Imu as serialised."""
    lengths = np.fromiter(map(len, messages), np.int64, len(messages))
    buf = np.frombuffer(b"".join(messages), np.uint8)
    ends = np.cumsum(lengths)
    starts = ends - lengths
    short = np.flatnonzero(lengths < 16 + IMU_BODY_BYTES)
    if len(short):
        raise CalibrationError(f"{where}: message {first + short[0] + 1} is {lengths[short[0]]} bytes: too short for "
                               f"a {IMU_TYPE}")
    name_bytes = _gather(buf, starts + 12, "<u4")[:, 0].astype(np.int64)
    if encoding == "cdr":
        expected = 4 + (12 + name_bytes + 7) // 8 * 8 + IMU_BODY_BYTES
        foreign = np.flatnonzero((buf[starts] != 0) | (buf[starts + 1] != 1))
        if len(foreign):
            k = foreign[0]
            raise CalibrationError(f"{where}: message {first + k + 1} has CDR encapsulation "
                                   f"0x{bytes(buf[starts[k]:starts[k] + 2]).hex()}: only little-endian CDR "
                                   f"(0x{CDR_LITTLE_ENDIAN.hex()}) is read")
    else:
        expected = 16 + name_bytes + IMU_BODY_BYTES
    wrong = np.flatnonzero(lengths != expected)
    if len(wrong):
        k = wrong[0]
        raise CalibrationError(f"{where}: message {first + k + 1} is {lengths[k]} bytes, not the {expected[k]} of a "
                               f"{IMU_TYPE} with its frame id: not an Imu as serialised")
    seconds = _gather(buf, starts + 4, "<i4" if encoding == "cdr" else "<u4")[:, 0].astype(np.int64)
    stamps_ns = seconds * 1_000_000_000 + _gather(buf, starts + 8, "<u4")[:, 0]
    if np.any(_gather(buf, ends - ACC_COVARIANCE_FROM_END, "<f8")[:, 0] == -1):
        raise CalibrationError(f"{where}: the messages carry no linear acceleration (its covariance is -1): "
                               "calibration needs accelerometers")
    gyro, acc = _gather(buf, ends - GYRO_FROM_END, "<f8", 3), _gather(buf, ends - ACC_FROM_END, "<f8", 3)
    unfinite = np.flatnonzero(~np.isfinite(gyro).all(axis=1) | ~np.isfinite(acc).all(axis=1))
    if len(unfinite):
        k = unfinite[0]
        raise CalibrationError(f"{where}: message {first + k + 1} has angular velocity {gyro[k].tolist()} rad/s and "
                               f"linear acceleration {acc[k].tolist()} m/s^2: not numbers")
    name = bytes(buf[starts[0] + 16:starts[0] + 16 + name_bytes[0]]).rstrip(b"\0").decode(errors="replace")
    return stamps_ns, gyro, acc, name


def imu_samples(gyro_rad_s: np.ndarray, acc_m_s2: np.ndarray) -> np.ndarray:
    """SAMPLE_DTYPE rows in the sensor's units (deg/s, g): no inclinometers, no temperatures (NaN)."""
    samples = np.zeros(len(gyro_rad_s), SAMPLE_DTYPE)
    for name in ("t_host", "incl", "temp_gyro", "temp_acc", "temp_incl", "aux"):
        samples[name] = np.nan
    samples["gyro"] = gyro_rad_s / DEG
    samples["acc"] = acc_m_s2 / STANDARD_GRAVITY
    return samples


def measured_rate_hz(stamps_ns: np.ndarray) -> int | float:
    """Samples per second from the stamps' median step: a whole number when the step divides a second."""
    rate = 1e9 / float(np.median(np.diff(stamps_ns)))
    return int(rate) if rate.is_integer() else rate


class StampTimes:
    """The header stamps of one topic's batches, in order -> each message's time (s since the
    first message), the rate (the first batch's median step) and the gaps the stamps show, and
    the last batch's sample slots (`slots`: samples since the first message, a gap's missing
    samples counted). Stamps that do not increase, or step faster than a STIM300 samples, are
    refused."""

    def __init__(self, where: str):
        self.where = where
        self.rate_hz: int | float | None = None
        self.first_ns = self.last_ns = None
        self.messages = self.gaps = self.lost_samples = 0
        self.frame_id = ""
        self.slots, self._last_slot = np.zeros(0, np.int64), -1

    def times(self, stamps_ns: np.ndarray, frame_id: str) -> np.ndarray:
        if self.rate_hz is None:  # the first batch: all the messages when there are fewer than a batch
            if len(stamps_ns) < 2:
                raise CalibrationError(f"{self.where}: {len(stamps_ns)} message: too few to tell the sample rate")
            self.rate_hz, self.first_ns, self.frame_id = measured_rate_hz(stamps_ns), stamps_ns[0], frame_id
            if self.rate_hz > FASTEST_RATE_HZ:
                raise CalibrationError(f"{self.where}: the header stamps step by {1e3 / self.rate_hz:.3g} ms (median), "
                                       f"{self.rate_hz:.0f} Hz, faster than a STIM300 samples ({INTERNAL_RATE_HZ} Hz): "
                                       "they do not time the samples (a driver stamping its reads?)")
        if self.last_ns is None:
            steps, later = np.diff(stamps_ns), 2  # step k ends at message k + 2 (counted from 1)
        else:
            steps, later = np.diff(stamps_ns, prepend=self.last_ns), 1
        back = np.flatnonzero(steps <= 0)
        if len(back):
            k = self.messages + back[0] + later
            raise CalibrationError(f"{self.where}: message {k}'s header stamp is {steps[back[0]] / 1e6:g} ms after "
                                   "the one before: stamps must increase")
        interval_ns = 1e9 / self.rate_hz
        counts = np.ones(len(stamps_ns), np.int64)  # slots after the message before (the very first: slot 0)
        gap = steps > GAP_STEPS * interval_ns
        counts[len(stamps_ns) - len(steps):][gap] = np.rint(steps[gap] / interval_ns)
        self.gaps += int(np.count_nonzero(gap))
        self.lost_samples += int(counts.sum()) - len(counts)
        self.slots = self._last_slot + np.cumsum(counts)
        self._last_slot = int(self.slots[-1])
        self.messages += len(stamps_ns)
        self.last_ns = stamps_ns[-1]
        return (stamps_ns - self.first_ns) * 1e-9

    @property
    def warnings(self) -> list[str]:
        return [f"{self.gaps} gap(s) in the header stamps: {self.lost_samples} sample(s) missing"] if self.gaps else []

    def capture(self, builder: SessionBuilder, topic: str, words: str, identity_record: dict) -> CaptureSessions:
        """The power-up `builder` holds, with what the stamps showed."""
        duration_s = float(self.last_ns - self.first_ns) * 1e-9 + 1 / self.rate_hz
        return CaptureSessions(
            path=self.where,
            power_ups=[PowerUp(builder, 0, self.messages, duration_s, np.zeros(0), np.zeros(0), True)],
            rate_hz=self.rate_hz,
            sensor=SensorRecord(sample_rate_hz=self.rate_hz,
                                sample_rate=f"{self.rate_hz:g} Hz, measured from the header stamps"),
            stream=ResultStream(capture=self.where, recording=words, topic=topic, frame_id=self.frame_id,
                                messages=self.messages, datagrams=self.messages, lost_samples=self.lost_samples,
                                gaps=self.gaps, inferred_missing=0, crc_errors=0, restarts=0,
                                warnings=tuple(self.warnings)),
            identity=identity_record)


def recording_files(path) -> list[Path]:
    """The files a recording is: itself, or a rosbag2 directory's metadata.yaml then its storage files
    in the order metadata.yaml lists them."""
    path = Path(path)
    if not path.is_dir():
        return [path]
    from ruamel.yaml import YAML  # rosbags' own YAML reader: it read the same file

    metadata = YAML(typ="safe").load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return [path / "metadata.yaml", *(path / Path(name).name for name in metadata["relative_file_paths"])]


def identity(path) -> dict:
    """Which recording this is (a result records it, a report checks it): the size and SHA-256 of its
    files' bytes one after the other (`recording_files`)."""
    digest, size = hashlib.sha256(), 0
    for name in recording_files(path):
        with open_regular(name) as f:
            while block := f.read(HASH_BLOCK_BYTES):
                digest.update(block)
                size += len(block)
    return {"size_bytes": size, "sha256": digest.hexdigest()}

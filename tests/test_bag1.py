"""calibd.bag1, the ROS 1 bag reader that needs no per-message index: the messages rosbags' own
reader gives, in the same order, from uncompressed, bz2 and lz4 chunks, several topics and
connections; a bag it cannot read is a BagError with the reason."""

import io

import numpy as np
import pytest
from rosbags.rosbag1 import Reader, Writer

from calibd.bag1 import Bag1, BagError
from recording_files import EPOCH_NS, IMU, ROS1, serialised, small_imu


def write_bag(path, topics: dict, compression=None, chunk_bytes: int | None = None):
    """`topics`: name -> (type, messages); messages of the topics interleaved, 1 ms apart."""
    writer = Writer(path)
    if compression:
        writer.set_compression(compression)
    if chunk_bytes:
        writer.chunk_threshold = chunk_bytes
    with writer:
        connections = {name: writer.add_connection(name, msgtype, typestore=ROS1)
                       for name, (msgtype, _) in topics.items()}
        longest = max(len(messages) for _, messages in topics.values())
        for k in range(longest):
            for name, (_, messages) in topics.items():
                if k < len(messages):
                    writer.write(connections[name], EPOCH_NS + k * 1_000_000, messages[k])
    return path


def rosbags_messages(path, topic):
    with Reader(path) as reader:
        return [data for c, _, data in reader.messages() if c.topic == topic]


@pytest.mark.parametrize("compression", [None, Writer.CompressionFormat.BZ2, Writer.CompressionFormat.LZ4])
def test_the_messages_are_those_rosbags_reads(tmp_path, compression):
    imu, _ = small_imu("bag", n=2000)
    strings = [bytes(ROS1.serialize_ros1(ROS1.types["std_msgs/msg/String"](f"m{k}"), "std_msgs/msg/String"))
               for k in range(700)]
    path = write_bag(tmp_path / "b.bag", {"/imu": (IMU, imu), "/chatter": ("std_msgs/msg/String", strings)},
                     compression, chunk_bytes=64 * 1024)  # many chunks
    with open(path, "rb") as f:
        bag = Bag1(f)
        assert bag.topics == {"/imu": ("sensor_msgs/Imu", 2000), "/chatter": ("std_msgs/String", 700)}
        assert len(bag.chunks) > 5
        assert list(bag.messages("/imu")) == rosbags_messages(path, "/imu") == imu
        assert list(bag.messages("/chatter")) == strings
        assert list(bag.messages("/nothing")) == []


def test_a_topic_of_several_connections_of_one_type_is_one_topic(tmp_path):
    first, _ = small_imu("bag", n=50)
    path = tmp_path / "two.bag"
    with Writer(path) as writer:
        a = writer.add_connection("/imu", IMU, typestore=ROS1, callerid="/a")
        b = writer.add_connection("/imu", IMU, typestore=ROS1, callerid="/b")
        for k, data in enumerate(first):
            writer.write(a if k % 2 else b, EPOCH_NS + k, data)
    with open(path, "rb") as f:
        bag = Bag1(f)
        assert bag.topics == {"/imu": ("sensor_msgs/Imu", 50)}
        assert list(bag.messages("/imu")) == first


def test_bags_it_cannot_read_say_why(tmp_path):
    imu, _ = small_imu("bag", n=300)
    whole = write_bag(tmp_path / "w.bag", {"/imu": (IMU, imu)}).read_bytes()
    index_pos = whole.index(b"index_pos=") + len(b"index_pos=")
    unindexed = whole[:index_pos] + bytes(8) + whole[index_pos + 8:]
    damaged = bytearray(whole)
    first_message = whole.index(b"op=\x02")
    damaged[first_message - 8:first_message - 4] = (1 << 30).to_bytes(4, "little")  # a header longer than the chunk
    cases = {"cut short": (whole[:len(whole) // 2], "the bag is cut short"),
             "another version": (whole.replace(b"V2.0", b"V1.2", 1), "not a ROS bag of format 2.0"),
             "not indexed": (unindexed, "the bag has no index"),
             "damaged chunk": (bytes(damaged), "runs past the chunk's end")}
    for what, (data, words) in cases.items():
        with pytest.raises(BagError, match=words):
            list(Bag1(io.BytesIO(data)).messages("/imu"))


def test_samples_decode_alike_through_either_reader(tmp_path):
    stamps = EPOCH_NS + np.arange(100, dtype=np.int64) * 8_000_000
    rng = np.random.default_rng(3)
    messages = serialised("bag", stamps, rng.normal(size=(100, 3)), rng.normal(size=(100, 3)))
    path = write_bag(tmp_path / "s.bag", {"/imu": (IMU, messages)}, Writer.CompressionFormat.LZ4)
    with open(path, "rb") as f:
        assert list(Bag1(f).messages("/imu")) == messages

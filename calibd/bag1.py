"""A ROS 1 bag (format 2.0) read chunk by chunk in the file's order, in bounded memory.

rosbags' ROS 1 reader indexes every message of every topic when it opens a bag (about 170 B a
message: 4.4 GB for the 26 million messages of a 3.6-hour recording at 2000 Hz), so a long bag
could not be read in bounded memory. The format is small: the bag header points at the index at
the file's end, whose connection records name each connection's topic and type and whose
chunk-info records say where each chunk is and how many messages of each connection it holds;
a chunk (uncompressed, bz2 or lz4) is a run of records, each a header of name=value fields and
its data, a message record's header holding its connection. Read here: the index's connections
and chunk infos (the topics, their types and message counts, without a per-message index), then
each chunk once, its records walked in order, the messages of the connections asked for handed
out as they are found. The file's order is the order the recorder wrote.
"""

from __future__ import annotations

import bz2
import struct

from .errors import CalibdError

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 0x02, 0x03, 0x05, 0x06, 0x07
U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")


class BagError(CalibdError):
    """A bag that cannot be read (cut short, damaged, of another format); one line (calibd.recordings
    says which file)."""


def _fields(header: bytes) -> dict[bytes, bytes]:
    """A record header's name=value fields."""
    fields, pos = {}, 0
    while pos < len(header):
        if pos + 4 > len(header):
            raise BagError("a record header is cut short")
        (size,) = U32.unpack_from(header, pos)
        name, sep, value = header[pos + 4:pos + 4 + size].partition(b"=")
        if not sep or pos + 4 + size > len(header):
            raise BagError("a record header field cannot be parsed")
        fields[name] = value
        pos += 4 + size
    return fields


def _number(fields: dict[bytes, bytes], name: bytes, unpacker: struct.Struct) -> int:
    value = fields.get(name)
    if value is None or len(value) != unpacker.size:
        raise BagError(f"a record lacks its {name.decode()} field")
    return unpacker.unpack(value)[0]


def _read(f, size: int) -> bytes:
    data = f.read(size)
    if len(data) != size:
        raise BagError("the bag is cut short")
    return data


def _record(f, op: int) -> tuple[dict[bytes, bytes], bytes]:
    """The record at the file's position, which must be of `op`: its header fields and data."""
    fields = _fields(_read(f, U32.unpack(_read(f, 4))[0]))
    if fields.get(b"op") != bytes([op]):
        raise BagError(f"a record of op {fields.get(b'op', b'?').hex()} where op {op:02x} belongs")
    return fields, _read(f, U32.unpack(_read(f, 4))[0])


def _decompress(compression: bytes, data: bytes) -> bytes:
    if compression == b"none":
        return data
    if compression == b"bz2":
        return bz2.decompress(data)
    if compression == b"lz4":
        from lz4.frame import decompress  # the roslz4 chunks are LZ4 frames; lz4 comes with rosbags

        return decompress(data)
    raise BagError(f"chunks compressed as {compression.decode(errors='replace')!r}: only none, bz2 and lz4 are read")


class Bag1:
    """The index of a ROS 1 bag open as the binary file `f`: `topics` (name -> (message type as
    the bag names it, message count)) and the messages of a topic (`messages`)."""

    def __init__(self, f):
        self.f = f
        if f.read(len(MAGIC)) != MAGIC:
            raise BagError("not a ROS bag of format 2.0")
        fields, _ = _record(f, OP_BAG_HEADER)
        index_pos = _number(fields, b"index_pos", U64)
        if not index_pos:
            raise BagError("the bag has no index (a recording cut short: `rosbag reindex` writes one)")
        f.seek(index_pos)
        self.connections: dict[int, tuple[str, str]] = {}  # id -> (topic, type)
        for _ in range(_number(fields, b"conn_count", U32)):
            header, data = _record(f, OP_CONNECTION)
            self.connections[_number(header, b"conn", U32)] = (
                header.get(b"topic", b"").decode(errors="replace"),
                _fields(data).get(b"type", b"").decode(errors="replace"))
        self.counts = dict.fromkeys(self.connections, 0)
        self.chunks: list[int] = []
        for _ in range(_number(fields, b"chunk_count", U32)):
            header, data = _record(f, OP_CHUNK_INFO)
            self.chunks.append(_number(header, b"chunk_pos", U64))
            for k in range(0, len(data) // 8 * 8, 8):
                conn, count = struct.unpack_from("<II", data, k)
                self.counts[conn] = self.counts.get(conn, 0) + count
        self.chunks.sort()

    @property
    def topics(self) -> dict[str, tuple[str, int]]:
        """name -> (type, "" when its connections differ; messages)."""
        topics: dict[str, tuple[str, int]] = {}
        for conn, (topic, msgtype) in self.connections.items():
            known, count = topics.get(topic, (msgtype, 0))
            topics[topic] = (known if known == msgtype else "", count + self.counts[conn])
        return topics

    def messages(self, topic: str):
        """The serialised messages of `topic`, chunk by chunk in the file's order."""
        ids = {conn for conn, (name, _) in self.connections.items() if name == topic}
        for position in self.chunks:
            self.f.seek(position)
            fields, data = _record(self.f, OP_CHUNK)
            chunk = _decompress(fields.get(b"compression", b"none"), data)
            pos, end = 0, len(chunk)
            while pos < end:  # a record: header length, header, data length, data
                start = pos + 8 + (U32.unpack_from(chunk, pos)[0] if pos + 4 <= end else end)
                stop = start + U32.unpack_from(chunk, start - 4)[0] if start <= end else end + 1
                if stop > end:
                    raise BagError(f"a record in the chunk at byte {position} runs past the chunk's end")
                fields = _fields(chunk[pos + 4:start - 4])
                if fields.get(b"op") == b"\x02" and _number(fields, b"conn", U32) in ids:
                    yield chunk[start:stop]
                pos = stop

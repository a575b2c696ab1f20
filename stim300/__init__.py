"""Safran STIM300 IMU driver: decode its serial protocol, read a port, talk Service Mode.

A whole capture decodes with `decode_capture` (samples and a `StreamInfo`), a live stream with
`StreamParser` (any chunking, the same samples) described by `stream_info`; `PortReader` reads a
port into a `RingBuffer`. Samples are SAMPLE_DTYPE rows in the sensor's units, timed by
`counter_times` / `CounterClock`. Every error raised on purpose is a `Stim300Error`.
"""

from .bulk import decode_capture, decode_columns
from .capture import Capture, StreamInfo, stream_info
from .clock import CounterClock, CounterTimes, counter_times
from .codec import SAMPLE_DTYPE
from .errors import FormatError, PortError, ServiceError, ServiceTimeout, Stim300Error, UsageError
from .port import PortReader, open_serial, record
from .protocol import AccUnit, Format, GyroUnit, PpsUnit, Status
from .reads import load_reads
from .ringbuffer import RingBuffer
from .service import enter_service_mode, exit_service_mode, service_command
from .stream import StreamParser, StreamStats

__all__ = [
    "decode_capture", "decode_columns", "Capture", "StreamInfo", "StreamStats", "stream_info", "StreamParser",
    "load_reads", "SAMPLE_DTYPE", "Format", "GyroUnit", "AccUnit", "PpsUnit", "Status",
    "counter_times", "CounterClock", "CounterTimes",
    "open_serial", "PortReader", "RingBuffer", "record",
    "enter_service_mode", "service_command", "exit_service_mode",
    "Stim300Error", "FormatError", "PortError", "ServiceError", "ServiceTimeout", "UsageError",
]

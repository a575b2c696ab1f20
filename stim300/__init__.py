"""Safran STIM300 IMU driver: decode its serial protocol, read a port, talk Service Mode.

A whole capture decodes with `decode_capture` (samples and a `StreamInfo`), a live stream with
`StreamParser` (any chunking, the same samples) described by `stream_info`; `PortReader` reads a
port into a `RingBuffer`. Samples are SAMPLE_DTYPE rows in the sensor's units, timed by
`counter_times` / `CounterClock`. Every error raised on purpose is a `Stim300Error`.

The names are imported when first used (PEP 562), not with the package: a program that needs
one module of the driver (`stim300.cliutil` for calibd's command line) does not load the port,
pyserial and the logging with it.
"""

from .lazy import lazy_exports

_HOMES = {  # public name -> the module of stim300 that defines it
    "decode_capture": "bulk", "decode_columns": "bulk", "Capture": "capture", "StreamInfo": "capture",
    "SensorRecord": "records",
    "StreamStats": "stream", "stream_info": "capture", "StreamParser": "stream",
    "load_reads": "reads", "SAMPLE_DTYPE": "codec", "Format": "protocol", "GyroUnit": "protocol",
    "AccUnit": "protocol", "PpsUnit": "protocol", "Status": "protocol",
    "counter_times": "clock", "CounterClock": "clock", "CounterTimes": "clock",
    "open_serial": "port", "PortReader": "port", "RingBuffer": "ringbuffer", "record": "port",
    "enter_service_mode": "service", "service_command": "service", "exit_service_mode": "service",
    "Stim300Error": "errors", "FormatError": "errors", "PortError": "errors", "ServiceError": "errors",
    "ServiceTimeout": "errors", "UsageError": "errors",
}

__all__ = list(_HOMES)

__getattr__ = lazy_exports(__name__, _HOMES)

"""Serial side on a real pty: the reader thread, reopen after unplug, custom bit-rates, raw
recording and Service Mode, all through `open_serial` as on a real port."""

import json
import os
import re
import select
import threading
import time
import tty
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import stim300.port as port
import stim300.serialread as serialread
from captures import exact_samples, same_samples, wait_until
from stim300.bulk import decode_capture
from stim300.cli import main as stim300_main
from stim300.clock import CYCLE_S
from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.errors import FormatError, PortError, ServiceError, ServiceTimeout
from stim300.port import PortReader, open_serial, record
from stim300.protocol import Format
from stim300.reads import load_reads
from stim300.ringbuffer import RingBuffer
from stim300.service import enter_service_mode, exit_service_mode, service_command
from stim300.special import Configuration, encode_special
from stim300.stream import StreamParser

DEADLINE_S = 5.0


class Pty:
    """A raw pty pair: the test plays the sensor on `master`, the code under test opens `path`."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)  # a writer must not hang on a full pty if the reader died
        self.path = os.ttyname(self.slave)
        self.received = bytearray()

    def write(self, data: bytes, timeout: float = DEADLINE_S) -> None:
        deadline = time.monotonic() + timeout
        view = memoryview(data)
        while view:
            left = deadline - time.monotonic()
            assert left > 0, f"nobody reads {self.path}: {len(view)} bytes left to write"
            if select.select([], [self.master], [], left)[1]:
                view = view[os.write(self.master, view):]

    def expect(self, wanted: bytes, timeout: float = DEADLINE_S) -> None:
        """Wait until the code under test has written `wanted` (e.g. the configuration request)."""
        deadline = time.monotonic() + timeout
        while wanted not in self.received:
            left = deadline - time.monotonic()
            assert left > 0, f"{wanted!r} never written to {self.path}; got {bytes(self.received)!r}"
            if select.select([self.master], [], [], left)[0]:
                self.received += os.read(self.master, 4096)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass  # already closed by the test


@pytest.fixture
def pty():
    pair = Pty()
    yield pair
    pair.close()


def sensor_stream(n: int, rate: int = 2000, seed: int = 0):
    """A configuration datagram (as after `C<CR>`), then the 0xA7 frames of n exact samples."""
    config = Configuration.build(sample_rate_hz=rate, bit_rate_bps=1843200)
    fmt = config.format
    samples = exact_samples(n, fmt, fmt.datagram_id, np.random.default_rng(seed))
    return encode_special(config, crlf=False), encode_samples(samples, fmt.datagram_id, fmt, crlf=False), samples


def write_paced(pty: Pty, head: bytes, frames: np.ndarray, rate: int, per_write: int = 20) -> None:
    """Write like the sensor: `per_write` datagrams at a time, on the sample clock."""
    pty.write(head)
    t0 = time.monotonic()
    for start in range(0, len(frames), per_write):
        time.sleep(max(0.0, t0 + start / rate - time.monotonic()))
        pty.write(frames[start:start + per_write].tobytes())


@pytest.mark.slow
def test_reader_fills_the_ring_with_exactly_the_bulk_decoded_samples(pty):
    """Live path == offline path: the same bytes give the same samples, stamped in order."""
    head, frames, samples = sensor_stream(3000)
    ring = RingBuffer(4096, SAMPLE_DTYPE)
    raw = []
    t_start = time.monotonic()
    with PortReader(pty.path, ring, baudrate=1843200, on_raw=raw.append) as reader, ThreadPoolExecutor(1) as pool:
        pty.expect(b"C\r")  # the reader asks for the configuration: the parser learns the format
        writer = pool.submit(write_paced, pty, head, frames, 2000)
        wait_until(lambda: ring.total == len(samples), "all samples in the ring")
        writer.result(timeout=DEADLINE_S)
    assert not reader.is_alive() and reader.error is None
    truth = decode_capture(head + frames.tobytes()).samples
    got = ring.latest_copy(ring.total)
    assert same_samples(got, truth) and same_samples(truth, samples)
    t = got["t_host"]
    assert np.isfinite(t).all() and (np.diff(t) >= 0).all()
    assert t_start <= t[0] and t[-1] <= time.monotonic()
    stats = reader.parser.stats
    assert (stats.datagrams, stats.crc_errors, stats.lost_samples, stats.special_datagrams) == (3000, 0, 0, 1)
    assert reader.parser.format.sample_rate_hz == 2000
    assert b"".join(raw) == head + frames.tobytes()  # what a recorder attached to on_raw gets
    assert reader.bytes_read == len(head) + frames.nbytes
    assert (reader.reopens, reader.read_errors) == (0, 0)


def test_reader_reopens_after_unplug_and_asks_for_the_configuration_again(tmp_path):
    """A vanished device (EIO) is reopened by path with backoff; data after replug arrives."""
    head, frames, samples = sensor_stream(400)
    link = tmp_path / "imu"
    first, second = Pty(), None
    link.symlink_to(first.path)
    ring = RingBuffer(1024, SAMPLE_DTYPE)
    reader = PortReader(str(link), ring, reopen_backoff=(0.02, 0.2))
    try:
        reader.start()
        first.expect(b"C\r")
        first.write(head + frames[:200].tobytes())
        wait_until(lambda: ring.total == 200, "samples before the unplug")
        first.close()  # unplug: the reader's next read fails with EIO
        wait_until(lambda: reader.read_errors >= 1, "the read error")
        assert not reader.connected
        second = Pty()  # replug: a new device node, reached through the repointed link
        (tmp_path / "imu.new").symlink_to(second.path)
        os.replace(tmp_path / "imu.new", link)
        second.expect(b"C\r")
        second.write(head + frames[200:].tobytes())
        wait_until(lambda: ring.total == 400, "samples after the replug")
        assert reader.connected
    finally:
        reader.stop()
        for pair in (first, second):
            if pair is not None:
                pair.close()
    assert reader.reopens >= 1 and reader.error is None
    assert same_samples(ring.latest_copy(400), samples)
    stats = reader.parser.stats
    assert (stats.datagrams, stats.crc_errors, stats.lost_samples, stats.special_datagrams) == (400, 0, 0, 2)


def test_a_failing_callback_ends_the_reader_and_is_kept(pty):
    """A bug in on_raw must not leave a silently dead thread: the daemon can see `error`."""
    def broken(data):
        raise RuntimeError("disk full")

    reader = PortReader(pty.path, RingBuffer(16, SAMPLE_DTYPE), on_raw=broken).start()
    try:
        pty.write(b"\x93")
        wait_until(lambda: not reader.is_alive(), "the reader to end")
    finally:
        reader.stop()
    assert isinstance(reader.error, RuntimeError) and not reader.connected


@pytest.mark.parametrize("baudrate", [1843200, 374400])
def test_non_termios_bit_rates_open_and_read(pty, baudrate):
    """374400 and 1843200 have no Bxxx constant: pyserial must set them (a pty accepts any)."""
    with open_serial(pty.path, baudrate) as ser:
        assert ser.baudrate == baudrate
        pty.write(b"\x93\r\nraw")
        got = bytearray()
        wait_until(lambda: got.extend(ser.read(16)) or len(got) == 6, "bytes through the port")
        assert got == b"\x93\r\nraw"  # 8 bit clean, no CR/LF translation


def test_a_read_takes_bytes_that_came_together_at_once_and_says_whether_it_waited(pty):
    """Bytes already waiting are one read; bytes arriving at an empty port are one read too (not
    their first byte and then the rest), and that read says it waited for them."""
    with open_serial(pty.path, timeout=DEADLINE_S) as ser, ThreadPoolExecutor(1) as pool:
        pty.write(bytes(range(200)))
        wait_until(lambda: ser.in_waiting == 200, "bytes in the port")
        assert serialread.read_waited(ser) == (bytes(range(200)), False)
        later = pool.submit(serialread.read_waited, ser)
        time.sleep(0.2)  # the read waits at an empty port
        pty.write(bytes(range(100, 0, -1)))
        assert later.result(timeout=DEADLINE_S) == (bytes(range(100, 0, -1)), True)
        pty.write(bytes(range(50)))
        wait_until(lambda: ser.in_waiting == 50, "bytes in the port")
        assert serialread.read_available(ser, limit=20) == bytes(range(20))  # a recording's last read



def test_a_pyserial_url_port_reads_the_same_way():
    """A port opened by URL (here loop://, what is written comes back) has no descriptor of its
    own: it is read through pyserial, with the same answers."""
    with open_serial("loop://", timeout=0.05) as ser:
        assert serialread.read_waited(ser) == (b"", True)  # nothing within the port timeout
        ser.write(bytes(range(30)))
        wait_until(lambda: ser.in_waiting == 30, "bytes in the port")
        assert serialread.read_waited(ser) == (bytes(range(30)), False)
        ser.write(bytes(range(10)))
        wait_until(lambda: ser.in_waiting == 10, "bytes in the port")
        assert serialread.read_available(ser, limit=4) == bytes(range(4))

def test_served_datagrams_after_quiet_spells_are_served_at_once_without_a_batch_wait(pty):
    """Served, the reader sleeps `batch_s` only after bytes that were waiting: a datagram it
    waited for (a low rate, or a port that delivers in bursts) is parsed at once and leaves it
    waiting for the next."""
    fmt = Format(datagram_id=0xA7, crlf=False, sample_rate_hz=125)
    frames = encode_samples(exact_samples(3, fmt, 0xA7, np.random.default_rng(0)), 0xA7, fmt, crlf=False)
    ring = RingBuffer(16, SAMPLE_DTYPE)
    with PortReader(pty.path, ring, fmt=fmt, request_config=False, batch_s=10.0, tap=lambda settled: None):
        for k, frame in enumerate(frames, 1):
            time.sleep(0.2)
            pty.write(frame.tobytes())
            wait_until(lambda: ring.total == k, f"datagram {k} in the ring", timeout=DEADLINE_S)


def test_an_unserved_reader_parses_its_reads_together_each_datagram_stamped_by_its_read(pty):
    """Unserved, reads wait for one parse (`parse_s`), each datagram stamped with the time its own
    read returned; a loan, a stop or PARSE_MOST bytes parse them whatever their age."""
    fmt = Format(datagram_id=0xA7, crlf=False, sample_rate_hz=2000)
    frames = encode_samples(exact_samples(1200, fmt, 0xA7, np.random.default_rng(0)), 0xA7, fmt, crlf=False)
    ring = RingBuffer(2048, SAMPLE_DTYPE)
    reader = PortReader(pty.path, ring, fmt=fmt, request_config=False, batch_s=0.01, parse_s=60.0)
    written = []
    with reader:
        for k, frame in enumerate(frames[:3], 1):
            written.append(time.monotonic())
            pty.write(frame.tobytes())
            wait_until(lambda: reader.bytes_read == k * frames.shape[1], f"datagram {k} read", timeout=DEADLINE_S)
        assert ring.total == 0  # read, not parsed yet
        reader.lend(lambda port: None)
        assert ring.total == 3
        stamps = ring.read_since(0)[0]["t_host"]
        assert written[0] <= stamps[0] < written[1] <= stamps[1] < written[2] <= stamps[2]
        pty.write(frames[3:5].tobytes())
        wait_until(lambda: reader.bytes_read == 5 * frames.shape[1], "datagrams 4 and 5 read", timeout=DEADLINE_S)
    assert ring.total == 5  # parsed at the stop
    with PortReader(pty.path, ring, fmt=fmt, request_config=False, batch_s=0.01, parse_s=60.0):
        pty.write(frames[5:].tobytes())  # 70 kB: more than PARSE_MOST
        wait_until(lambda: ring.total >= 5 + port.PARSE_MOST // frames.shape[1], "a parse of PARSE_MOST bytes",
                   timeout=DEADLINE_S)


def test_a_reader_reads_and_parses_less_often_when_nothing_is_served(pty):
    """With a tap, reads are served as they come: at most SERVED_BATCH_S of added latency. Without
    one the samples wait in the ring for a consumer that polls: the reader reads every 50 ms, each
    datagram's host time still late by less than half a counter cycle (so the host clock proves a
    lost cycle, `stim300.clock`), and parses a quarter as often. What is given is kept."""
    ring = RingBuffer(16, SAMPLE_DTYPE)
    unserved = PortReader(pty.path, ring, request_config=False)
    assert (unserved.batch_s, unserved.parse_s) == (port.UNSERVED_BATCH_S, port.UNSERVED_PARSE_S) == (0.05, 0.2)
    assert port.UNSERVED_BATCH_S < CYCLE_S / 2
    served = PortReader(pty.path, ring, request_config=False, tap=lambda settled: None)
    assert (served.batch_s, served.parse_s) == (port.SERVED_BATCH_S, 0.0) == (0.004, 0.0)
    given = PortReader(pty.path, ring, request_config=False, batch_s=0.0, parse_s=1.0)
    assert (given.batch_s, given.parse_s) == (0.0, 1.0)


def test_open_errors_are_one_line_naming_the_port(pty, tmp_path):
    missing = str(tmp_path / "ttyUSB7")
    with pytest.raises(PortError, match=f"^{re.escape(missing)}: no such device$"):
        open_serial(missing)
    with open_serial(pty.path), pytest.raises(PortError, match=f"^{re.escape(pty.path)}: in use by another"):
        open_serial(pty.path)  # two readers would each get half of the bytes


@pytest.fixture
def opened(monkeypatch):
    """Set when record() has opened its port: only bytes written after that can be recorded."""
    event = threading.Event()
    real_open = port.open_serial

    def open_and_tell(*args, **kwargs):
        ser = real_open(*args, **kwargs)
        event.set()
        return ser

    monkeypatch.setattr(port, "open_serial", open_and_tell)
    return event


def write_when_open(pty: Pty, opened: threading.Event, data: bytes) -> None:
    assert opened.wait(DEADLINE_S)
    pty.write(data)


def test_record_stops_at_max_bytes_exactly(pty, opened, tmp_path):
    data = np.random.default_rng(1).integers(0, 256, 30_500, np.uint8).tobytes()
    out = tmp_path / "imu.bin"
    with ThreadPoolExecutor(1) as pool:
        writer = pool.submit(write_when_open, pty, opened, data)
        assert record(pty.path, out, max_bytes=30_000) == 0
        writer.result(timeout=DEADLINE_S)
    assert out.read_bytes() == data[:30_000]
    assert not (tmp_path / "imu.bin.part").exists()


def test_record_stops_after_the_duration(pty, opened, tmp_path, capsys):
    data = np.random.default_rng(2).integers(0, 256, 10_000, np.uint8).tobytes()
    out = tmp_path / "imu.bin"
    with ThreadPoolExecutor(1) as pool:
        writer = pool.submit(write_when_open, pty, opened, data)
        t0 = time.monotonic()
        assert record(pty.path, out, duration_s=0.4) == 0
        elapsed = time.monotonic() - t0
        writer.result(timeout=DEADLINE_S)
    assert 0.4 <= elapsed < 2.0
    assert out.read_bytes() == data
    assert re.search(r"recorded 10000 B in 0\.\d s", capsys.readouterr().err)


def test_record_keeps_the_bytes_on_ctrl_c(pty, monkeypatch, tmp_path):
    """Ctrl-C ends an open-ended recording; the file is renamed from .part and complete."""
    data = b"\xa7" * 5000
    real_open, real_read, seen = port.open_serial, port.read_available, [0]

    def open_then_write(*args, **kwargs):
        ser = real_open(*args, **kwargs)
        pty.write(data)
        return ser

    def read_then_interrupt(ser, limit=None):
        if seen[0] == len(data):
            raise KeyboardInterrupt  # as Ctrl-C lands in a read
        chunk = real_read(ser, limit)
        seen[0] += len(chunk)
        return chunk

    monkeypatch.setattr(port, "read_available", read_then_interrupt)
    monkeypatch.setattr(port, "open_serial", open_then_write)
    out = tmp_path / "imu.bin"
    assert record(pty.path, out) == 0
    assert out.read_bytes() == data and not (tmp_path / "imu.bin.part").exists()


def record_fed(pty: Pty, opened: threading.Event, out: Path, n: int, paced: bool) -> int:
    """Record what a sensor writes, on its sample clock or all at once (a capture fed to a
    pty as fast as it goes); the number of reads the read log keeps."""
    head, frames, _ = sensor_stream(n)

    def feed():
        assert opened.wait(DEADLINE_S)
        write_paced(pty, head, frames, 2000) if paced else pty.write(head + frames.tobytes())

    with ThreadPoolExecutor(1) as pool:
        writer = pool.submit(feed)
        assert record(pty.path, out, max_bytes=len(head) + frames.nbytes) == 0
        writer.result(timeout=DEADLINE_S)
    reads = load_reads(out)
    assert reads is not None and reads["end"][-1] == out.stat().st_size
    return len(reads)


def test_info_uses_the_read_log_of_a_recording(pty, opened, tmp_path, capsys):
    out = tmp_path / "imu.bin"
    reads = record_fed(pty, opened, out, 600, paced=True)
    capsys.readouterr()
    assert stim300_main(["info", str(out)]) == 0
    assert f"hidden_gaps      0 (0.000 s, found from the read log of {reads} reads)" in capsys.readouterr().out


def test_info_tells_a_read_log_too_fast_to_show_gaps_from_none(pty, opened, tmp_path, capsys):
    """A capture fed faster than real time is read so: its read log is there, and cannot show
    gaps (the host clock outran the data), which is not having none."""
    out = tmp_path / "imu.bin"
    reads = record_fed(pty, opened, out, 4000, paced=False)  # 2 s of data
    capsys.readouterr()
    assert stim300_main(["info", str(out)]) == 0
    assert f"hidden_gaps      - (read log of {reads} reads, which came faster than real time" in capsys.readouterr().out
    assert stim300_main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["read_log_reads"] == reads and info["hidden_gaps"] is None


def test_record_to_mcap_keeps_the_bytes_their_read_times_and_every_sample_as_imu(pty, opened, tmp_path, capsys):
    """`stim300 record PORT -o OUT.mcap` on a paced 2000 Hz stream: decode of the MCAP is decode
    of the bytes fed, its read log is in it, and an MCAP reader that is not ours decodes one
    sensor_msgs/Imu per sample."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    head, frames, _ = sensor_stream(1200)
    out = tmp_path / "imu.mcap"
    with ThreadPoolExecutor(1) as pool:
        writer = pool.submit(lambda: (opened.wait(DEADLINE_S), write_paced(pty, head, frames, 2000)))
        assert record(pty.path, out, max_bytes=len(head) + frames.nbytes) == 0
        writer.result(timeout=DEADLINE_S)
    assert not (tmp_path / "imu.mcap.part").exists() and not (tmp_path / "imu.mcap.reads.npy").exists()
    capsys.readouterr()
    assert stim300_main(["decode", str(out), "-o", str(tmp_path / "a.npz")]) == 0
    fed = tmp_path / "fed.bin"
    fed.write_bytes(head + frames.tobytes())
    assert stim300_main(["decode", str(fed), "-o", str(tmp_path / "b.npz")]) == 0
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert set(a.files) == set(b.files) | {"t_host_s"}
    assert all(np.array_equal(a[k], b[k]) for k in b.files if k != "units")
    with open(out, "rb") as f:
        imu = [ros for _, _, _, ros in make_reader(f, decoder_factories=[DecoderFactory()])
               .iter_decoded_messages(topics=["/imu/data_raw"])]
    assert len(imu) == len(b["counter"]) == 1200
    assert imu[0].angular_velocity.x == pytest.approx(float(b["gyro_x"][0]) * np.pi / 180, rel=1e-12)


def test_record_to_mcap_without_the_extra_is_one_line(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mcap", None)
    for module in [m for m in sys.modules if m.startswith("mcap.")]:
        monkeypatch.delitem(sys.modules, module)
    assert record(str(tmp_path / "ttyUSB7"), tmp_path / "imu.mcap") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'stim300-calib[recordings]'" in err


def test_record_reports_a_missing_port_in_one_line(tmp_path, capsys):
    missing = str(tmp_path / "ttyUSB7")
    assert record(missing, tmp_path / "imu.bin") == 1
    assert capsys.readouterr().err == f"stim300 record: {missing}: no such device\n"
    assert not list(tmp_path.glob("imu.bin*"))


# Echo, exit line and the first bytes of a 0x93 datagram, as a real unit sent them (a fixture of
# pystim300's tests, taken from a TS1524 rev. 31 unit; tests/vectors/README.md).
EXIT_FRAGMENT = b"x N\rSYSTEM RETURNING TO NORMAL MODE\r" + bytes.fromhex("93000180")
REPORT = b"SERIAL NUMBER = N25580000001\rPRODUCT = STIM300\rSAMPLE RATE [Hz] = 2000"
# End of the datagram in progress when SERVICEMODE arrived; "\r>" inside is not a prompt.
DATAGRAM_END = bytes([0x12, 0x0D, 0x3E, 0x93, 0x7F, 0xA5])


def datagrams_after_exit():
    """0x93 samples whose first datagram starts with the 4 bytes of the exit fragment."""
    fmt = Format(datagram_id=0x93, crlf=False, sample_rate_hz=2000)
    samples = exact_samples(5, fmt, 0x93, np.random.default_rng(3))
    samples["gyro"][0, 0] = 0x000180 * fmt.scales()["gyro"]
    stream = encode_samples(samples, 0x93, fmt, crlf=False).tobytes()
    assert stream.startswith(EXIT_FRAGMENT[-4:])
    return fmt, samples, stream


class FakeSensor(threading.Thread):
    """Answers each CR-terminated line on the master from a table, as the unit would."""

    def __init__(self, pty: Pty, replies: dict[bytes, bytes]):
        super().__init__(daemon=True)
        self.pty, self.replies, self.done = pty, replies, threading.Event()

    def run(self):
        buf = b""
        while not self.done.is_set():
            if select.select([self.pty.master], [], [], 0.02)[0]:
                buf += os.read(self.pty.master, 4096)
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                self.pty.write(self.replies.get(line, line + b"\rE001 UNKNOWN COMMAND\r>"))


def test_service_mode_enter_command_error_and_exit_back_to_datagrams(pty):
    fmt, samples, stream = datagrams_after_exit()
    sensor = FakeSensor(pty, {
        b"SERVICEMODE": DATAGRAM_END + REPORT + b"\r>",  # Normal Mode commands are not echoed
        b"i m": b"i m\rSAMPLE RATE [Hz] = 2000\r\nTRIGGER = INTERNAL\r>",
        b"x I": b"x I\rE003 INVALID PARAMETER\r>",  # as if the unit refused: it stays in Service Mode
        b"x N": EXIT_FRAGMENT + stream[4:],
    })
    sensor.start()
    try:
        with open_serial(pty.path) as ser:
            assert enter_service_mode(ser, timeout=DEADLINE_S) == REPORT.decode().replace("\r", "\n")
            assert service_command(ser, "i m", timeout=DEADLINE_S) == "SAMPLE RATE [Hz] = 2000\nTRIGGER = INTERNAL"
            with pytest.raises(ServiceError) as refused:
                service_command(ser, "q", timeout=DEADLINE_S)
            assert (refused.value.code, refused.value.text) == (1, "UNKNOWN COMMAND")
            with pytest.raises(FormatError):
                exit_service_mode(ser, "n")  # lower case would wait for a confirmation
            with pytest.raises(FormatError):
                service_command(ser, "i m\rs")  # two commands: the second would go unanswered
            with pytest.raises(ServiceError, match="E003 INVALID PARAMETER"):
                exit_service_mode(ser, "I", timeout=DEADLINE_S)
            data = bytearray(exit_service_mode(ser, timeout=DEADLINE_S))
            assert data.startswith(EXIT_FRAGMENT[-4:])  # binary after the exit line goes to the parser
            wait_until(lambda: data.extend(ser.read(max(1, ser.in_waiting))) or len(data) >= len(stream),
                     "the datagrams after the exit")
    finally:
        sensor.done.set()
        sensor.join(DEADLINE_S)
    assert bytes(data) == stream
    assert same_samples(StreamParser(fmt).feed(bytes(data)), samples)


def test_service_mode_timeout_names_what_was_awaited(pty):
    with open_serial(pty.path) as ser, pytest.raises(ServiceTimeout, match="prompt after 'i m'") as silent:
        service_command(ser, "i m", timeout=0.1)
    assert silent.value.command == "i m"
    assert isinstance(silent.value, TimeoutError) and isinstance(silent.value, ServiceError)


FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.mark.parametrize("name", ["faults_125hz", "static_turn_2000hz"])
def test_shipped_captures_replayed_through_a_pty_equal_the_bulk_decoder(pty, name):
    """The end-to-end path the daemon uses: fixture bytes -> pty -> pyserial -> parser -> ring."""
    data = (FIXTURES / f"{name}.bin").read_bytes()
    decoded = decode_capture(data)
    truth = decoded.samples
    ring = RingBuffer(len(truth) + 1, SAMPLE_DTYPE)
    with PortReader(pty.path, ring, request_config=False, batch_s=0.0) as reader:
        for start in range(0, len(data), 4096):
            pty.write(data[start:start + 4096])
        wait_until(lambda: ring.total == len(truth), f"{len(truth)} samples of {name}")
    assert reader.error is None
    assert same_samples(ring.latest_copy(ring.total), truth)
    live, offline = reader.parser.stats.snapshot(), decoded.info.stats
    assert replace(live, bytes_in=0) == replace(offline, bytes_in=0)

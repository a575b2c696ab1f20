"""Drivers as they are, on the served ptys: a driver of the vortexntnu/stim300-driver family on
the corrected pty long after the sensor's power-up, a driver that only waits, a flood of bad
requests, and two readers each on its own raw pty. A sensor streams through a parser into the
hub in real time at 2000 Hz."""

import os
import select
import termios
import threading
import time
import tty

import numpy as np
import pytest
from structlog.testing import capture_logs

from pathlib import Path

from captures import calibd, exact_samples, power_up, wait_until
from calibd.config import ServeConfig
from calibd.serve import ptys
from calibd.serve.hub import Hub
from stim300.codec import encode_samples
from stim300.protocol import Status
from stim300.special import Configuration
from stim300.stream import StreamParser

from test_serve_pty import ACC_BIAS_MG, GYRO_BIAS_DEG_H, INCL_BIAS_MG, result

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 2000
pytestmark = pytest.mark.slow  # every test feeds a sensor in real time
FEED_DATAGRAMS = 8  # a port reader's read at 2000 Hz: 4 ms of datagrams


class Sensor:
    """A STIM300 past its start-up, streaming through the daemon's parser into `tap` in real
    time: the power-up datagrams, then `seconds` of normal datagrams whose latency field is the
    sample's index (so a reader's samples are found among the sent ones)."""

    def __init__(self, tap, seconds: float, crlf: bool = False, seed: int = 0):
        self.fmt = Configuration.build(sample_rate_hz=RATE_HZ, crlf=crlf).format
        self.samples = exact_samples(int(seconds * RATE_HZ), self.fmt, self.fmt.datagram_id,
                                     np.random.default_rng(seed))
        for cluster in ("gyro", "acc", "incl"):
            self.samples["status_" + cluster] &= np.uint8(0xFF & ~Status.START_UP)
        self.samples["latency_us"] = np.arange(len(self.samples))
        self.head = power_up(Configuration.build(sample_rate_hz=RATE_HZ, crlf=crlf))
        frames = encode_samples(self.samples, self.fmt.datagram_id, self.fmt, crlf)
        self.datagrams = frames.tobytes()
        self.data = self.head + self.datagrams
        self._frames = frames
        self._parser = StreamParser(tap=tap)
        self.sent = 0  # normal datagrams through the parser so far
        self._thread = threading.Thread(target=self._stream, daemon=True)

    def start(self) -> "Sensor":
        self._thread.start()
        return self

    def _stream(self) -> None:
        self._parser.feed(self.head)
        started = time.monotonic()
        for lo in range(0, len(self._frames), FEED_DATAGRAMS):
            due = started + lo / RATE_HZ
            time.sleep(max(0.0, due - time.monotonic()))
            self._parser.feed(self._frames[lo:lo + FEED_DATAGRAMS].tobytes())
            self.sent = lo + FEED_DATAGRAMS
        self._parser.finish()

    def join(self) -> None:
        self._thread.join()


def open_link(link) -> int:
    """The pty opened as a reader that waits: raw modes set at once, never flushing what the
    daemon may already have written (setraw's default, TCSAFLUSH, would drop the greeting)."""
    fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd, termios.TCSANOW)
    return fd


def read_until(fd: int, done, timeout_s: float = 5.0) -> bytes:
    """What the link gives until `done(bytes so far)`, within `timeout_s` (a loaded machine is slow)."""
    got, deadline = bytearray(), time.monotonic() + timeout_s
    while not done(bytes(got)) and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.02)[0]:
            got += os.read(fd, 65536)
    return bytes(got)


def specials_in(data: bytes) -> int:
    parser = StreamParser()
    parser.feed(data)
    return len(parser.scanner.specials)


def read_for(fd: int, seconds: float) -> bytes:
    got, deadline = bytearray(), time.monotonic() + seconds
    while time.monotonic() < deadline:
        if select.select([fd], [], [], 0.02)[0]:
            got += os.read(fd, 65536)
    return bytes(got)


class VortexLikeDriver:
    """What a driver of the vortexntnu/stim300-driver family does with its port: open it, flush
    its input, ask for the configuration with `C<CR>` (again while none comes), and decode
    nothing until a configuration datagram has told it the format (here with stim300's decoder)."""

    ASK_AGAIN_S = 0.5

    def __init__(self, link, flush_after_s: float = 0.0):
        self.opened = time.monotonic()
        self.fd = open_link(link)
        time.sleep(flush_after_s)  # a slow start: the greeting has come, and is flushed away
        termios.tcflush(self.fd, termios.TCIFLUSH)
        self.parser = StreamParser()
        self.samples: list[np.ndarray] = []
        self.first_sample_s: float | None = None  # after opening

    def run(self, seconds: float) -> None:
        asked = -self.ASK_AGAIN_S
        deadline = self.opened + seconds
        while time.monotonic() < deadline:
            configured = self.parser.scanner.configuration is not None
            if not configured and time.monotonic() - asked >= self.ASK_AGAIN_S:
                os.write(self.fd, b"C\r")
                asked = time.monotonic()
            if not select.select([self.fd], [], [], 0.01)[0]:
                continue
            samples = self.parser.feed(os.read(self.fd, 65536))
            if configured and len(samples):  # decoded under a configuration seen before
                self.samples.append(samples)
                if self.first_sample_s is None:
                    self.first_sample_s = time.monotonic() - self.opened

    def close(self) -> None:
        os.close(self.fd)


def corrected_within_one_lsb(got: np.ndarray, sensor: Sensor) -> None:
    """Each sample the reader decoded is the sent one (found by its latency field, its index) less
    the result's biases, within 1 LSB."""
    sent = sensor.samples[got["latency_us"].astype(int)]
    assert np.array_equal(got["counter"], sent["counter"])
    lsb = sensor.fmt.scales()
    biases = {"gyro": np.array(GYRO_BIAS_DEG_H) / 3600, "acc": np.array(ACC_BIAS_MG) / 1000,
              "incl": np.array(INCL_BIAS_MG) / 1000}
    for cluster, bias in biases.items():
        wanted = np.clip(sent[cluster] / lsb[cluster] - bias / lsb[cluster], -2**23, 2**23 - 1)
        assert np.abs(got[cluster] / lsb[cluster] - wanted).max() <= 1.0, cluster


@pytest.mark.parametrize("flush_after_s", [0.0, 0.05])
def test_a_vortex_like_driver_gets_corrected_samples_within_2_s_long_after_the_power_up(tmp_path, flush_after_s):
    """Its `C` is answered by the corrected pty (or the greeting's configuration, when it comes
    after the flush): the sensor's own power-up datagrams went by long before."""
    link = tmp_path / "imu-corrected"
    hub = Hub(ServeConfig(corrected_pty=link), "port")
    hub.on_result(result())
    sensor = Sensor(hub.tap, seconds=5.0).start()
    try:
        time.sleep(1.5)  # the power-up datagrams went by long ago
        driver = VortexLikeDriver(link, flush_after_s)
        try:
            driver.run(seconds=2.5)
        finally:
            driver.close()
        sensor.join()
    finally:
        hub.close()
    assert driver.first_sample_s is not None and driver.first_sample_s < 2.0, driver.first_sample_s
    got = np.concatenate(driver.samples)
    assert len(got) > 0.8 * 2.0 * RATE_HZ
    corrected_within_one_lsb(got, sensor)
    assert hub.corrected_pty.requests_refused == 0
    if flush_after_s:
        assert hub.corrected_pty.requests_answered >= 1
    print(f"open -> first corrected sample: {driver.first_sample_s * 1000:.0f} ms (flushed after {flush_after_s} s)")


def test_a_reader_that_only_waits_gets_the_power_up_datagrams_first(tmp_path):
    link = tmp_path / "imu-corrected"
    hub = Hub(ServeConfig(corrected_pty=link), "port")
    hub.on_result(result())
    sensor = Sensor(hub.tap, seconds=2.0, crlf=True).start()
    try:
        time.sleep(0.5)  # nobody reads meanwhile: nothing waits in the pty for the reader to come
        fd = open_link(link)
        try:
            got = read_for(fd, 0.5)
        finally:
            os.close(fd)
        sensor.join()
    finally:
        hub.close()
    assert got.startswith(sensor.head)  # part number, serial number, configuration: as at power-up
    parser = StreamParser()
    samples = parser.feed(got)
    assert parser.scanner.configuration is not None and parser.stats.crc_errors == 0
    assert 0.3 * RATE_HZ < len(samples) and samples["latency_us"][0] > 0.4 * RATE_HZ  # the present, not old bytes
    corrected_within_one_lsb(samples, sensor)


def test_queries_are_answered_in_place_of_one_datagram_each_and_never_reach_the_sensor(tmp_path):
    link = tmp_path / "imu-corrected"
    forwarded = []
    hub = Hub(ServeConfig(corrected_pty=link), "port")
    hub.port_writer = forwarded.append
    hub.on_result(result())
    sensor = Sensor(hub.tap, seconds=3.0).start()
    try:
        time.sleep(0.3)
        fd = open_link(link)
        try:
            before = read_until(fd, lambda data: specials_in(data) >= 3)  # the greeting and some data
            with capture_logs() as logs:
                os.write(fd, b"N\r\nI\rT\r")  # the stream carried no bias trim datagram: refused
                got = read_until(fd, lambda data: specials_in(before + data) >= 5)
                got += read_for(fd, 0.05)  # and datagrams after the answers
        finally:
            os.close(fd)
        sensor.join()
    finally:
        hub.close()
    parser = StreamParser()
    samples = parser.feed(before + got)
    kinds = [type(item).__name__ for item in parser.scanner.specials]
    assert kinds == ["PartNumber", "SerialNumber", "Configuration", "PartNumber", "SerialNumber"]
    assert forwarded == [] and parser.stats.crc_errors == 0
    index = samples["latency_us"].astype(int)
    assert np.all(np.diff(index) >= 1) and np.sum(np.diff(index) - 1) == 2  # two datagrams replaced, no more
    assert [e["event"] for e in logs] == ["pty_request_refused"] and "bias trim" in logs[0]["why"]


def test_a_flood_of_bad_requests_to_the_corrected_pty_is_two_log_lines(tmp_path, monkeypatch):
    monkeypatch.setattr(ptys, "QUIET_S", 0.3)
    link = tmp_path / "imu-corrected"
    hub = Hub(ServeConfig(corrected_pty=link), "port")
    hub.on_result(result())
    sensor = Sensor(hub.tap, seconds=1.5).start()
    try:
        fd = open_link(link)
        try:
            with capture_logs() as logs:
                for _ in range(20):
                    os.write(fd, b"X\rSERVICEMODE\rc\r" * 100)
                    read_for(fd, 0.02)
                wait_until(lambda: hub.corrected_pty.requests_refused == 6000)
                wait_until(lambda: any(e["event"] == "pty_refusals_ended" for e in logs))
        finally:
            os.close(fd)
        sensor.join()
    finally:
        hub.close()
    said = [(e["event"], e.get("refused")) for e in logs if e["event"] not in ("pty_dropping", "pty_drops_ended")]
    assert said == [("pty_request_refused", None), ("pty_refusals_ended", 6000)]  # (the test stops reading)


def test_two_raw_ptys_each_carry_every_byte_and_share_one_request_rate(tmp_path):
    links = (tmp_path / "raw-a", tmp_path / "raw-b")
    forwarded = []
    hub = Hub(ServeConfig(raw_pty=links), "port")
    hub.port_writer = forwarded.append
    sensor = Sensor(hub.tap, seconds=5.0, crlf=True)
    readers = [open_link(link) for link in links]
    got = [bytearray(), bytearray()]

    def read(k: int) -> None:
        while len(got[k]) < len(sensor.data):
            if select.select([readers[k]], [], [], 1.0)[0]:
                got[k] += os.read(readers[k], 65536)
            elif not sensor._thread.is_alive():
                return
    threads = [threading.Thread(target=read, args=(k,), daemon=True) for k in (0, 1)]
    try:
        for thread in threads:
            thread.start()
        sensor.start()
        os.write(readers[0], b"C\r")
        wait_until(lambda: len(forwarded) == 1)
        os.write(readers[1], b"C\r")  # the same sensor: within the second, not forwarded
        wait_until(lambda: hub.raw_ptys[1].requests_throttled == 1)
        sensor.join()
        for thread in threads:
            thread.join(timeout=5)
    finally:
        for fd in readers:
            os.close(fd)
        hub.close()
    assert forwarded == [b"C\r"]
    assert [len(g) for g in got] == [len(sensor.data)] * 2
    assert bytes(got[0]) == sensor.data and bytes(got[1]) == sensor.data
    assert [pty.dropped_bytes for pty in hub.raw_ptys] == [0, 0]
    print(f"each raw reader got {len(got[0])} and {len(got[1])} bytes of {len(sensor.data)}")


def test_replay_serve_feeds_two_raw_ptys_of_a_config_list_every_byte(tmp_path):
    """`calibd replay --serve` with `raw_pty = [A, B]`: 5 s of a 2000 Hz capture in real time, a
    reader on each link; each gets the capture unchanged from when it opened its link."""
    data = (ROOT / "fixtures" / "static_turn_2000hz.bin").read_bytes()[:10_000 * 61]  # 5 s of 0xA7 + CR LF
    capture = tmp_path / "short.bin"
    capture.write_bytes(data)
    links = (tmp_path / "raw-a", tmp_path / "raw-b")
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{tmp_path / "tty"}"\n[site]\nlatitude_deg = 44.5\n'
                      f'[output]\nstate_dir = "{tmp_path / "state"}"\n'
                      f'[serve]\nraw_pty = ["{links[0]}", "{links[1]}"]\n')
    daemon = calibd("replay", capture, "--config", config, "--serve", "--speed", "1")
    got = [bytearray(), bytearray()]
    try:
        deadline = time.monotonic() + 30
        while not all(link.exists() for link in links):
            assert daemon.poll() is None and time.monotonic() < deadline, daemon.stderr.read().decode()[-2000:]
            time.sleep(0.01)
        readers = [open_link(link) for link in links]
        open_fds = list(readers)
        while open_fds and time.monotonic() < deadline:
            for fd in select.select(open_fds, [], [], 0.2)[0]:
                try:
                    chunk = os.read(fd, 65536)
                except OSError:  # EIO: the daemon closed the pty
                    chunk = b""
                if not chunk:
                    open_fds.remove(fd)
                got[readers.index(fd)] += chunk
        for fd in readers:
            os.close(fd)
    finally:
        if daemon.poll() is None:
            daemon.kill()
        daemon.wait()
    for k in (0, 1):
        print(k, len(got[k]), data.startswith(bytes(got[k])), data.endswith(bytes(got[k])), bytes(got[k]) in data)
    for k in (0, 1):
        assert len(got[k]) > 0.9 * len(data) and bytes(got[k]) in data, k
    print(f"raw readers got {len(got[0])} and {len(got[1])} bytes of the capture's {len(data)}")

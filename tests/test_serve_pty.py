"""The raw and corrected ptys on real pseudo-terminals: bytes out of the link, requests in,
biases out of the corrected datagrams, links made and removed."""

import os
import select
import stat
import threading
import time
import tty

import numpy as np
import pytest
from structlog.testing import capture_logs

from captures import exact_samples, wait_until
from calibd.config import ServeConfig
from calibd.frames import STANDARD_GRAVITY
from calibd.results import CalibrationResult, Estimate
from calibd.serve import ptys
from calibd.serve.hub import Hub
from calibd.serve.ptys import CorrectedPty, PtyError, RawPty
from calibd.serve.sockets import ServeError
from stim300.bulk import decode_capture
from stim300.codec import encode_samples
from stim300.protocol import AccUnit, GyroUnit, Status
from stim300.source import PortSource
from stim300.special import Configuration, encode_special
from stim300.stream import StreamParser
from stim300.records import SensorRecord

DEADLINE_S = 5.0
GYRO_BIAS_DEG_H = (98.6, -34.7, -27.4)
ACC_BIAS_MG = (-1.28, 7.03, 0.51)
INCL_BIAS_MG = (-0.90, -0.66, -0.24)


def sensor_bytes(n=600, datagram_id=0x93, rate=2000, crlf=False, seed=0, gyro_unit=GyroUnit.RATE,
                 acc_unit=AccUnit.ACCELERATION, incl_unit=AccUnit.ACCELERATION):
    """A configuration datagram (as after `C<CR>`) describing the datagrams that follow: the
    bytes, the configuration datagram's length and the samples."""
    config = Configuration.build(sample_rate_hz=rate, crlf=crlf, acc_included=datagram_id & 1 == 1,
                                 incl_included=datagram_id & 2 == 2, temp_included=datagram_id & 4 == 4,
                                 gyro_unit=gyro_unit, acc_unit=acc_unit, incl_unit=incl_unit)
    fmt = config.format
    assert fmt.datagram_id == datagram_id
    samples = exact_samples(n, fmt, datagram_id, np.random.default_rng(seed))
    for cluster in ("gyro", "acc", "incl"):  # a sensor past its start-up (the bit ends a result)
        samples["status_" + cluster] &= np.uint8(0xFF & ~Status.START_UP)
    head = encode_special(config, crlf)
    return head + encode_samples(samples, datagram_id, fmt, crlf).tobytes(), len(head), samples


def result(incl=True, rate_hz=2000):
    estimates = {f"gyro_bias_{a}": Estimate(v, 0.1, "deg/h") for a, v in zip("xyz", GYRO_BIAS_DEG_H)}
    estimates |= {f"acc_bias_{a}": Estimate(v, 0.01, "mg") for a, v in zip("xyz", ACC_BIAS_MG)}
    if incl:
        estimates |= {f"incl_bias_{a}": Estimate(v, 0.01, "mg") for a, v in zip("xyz", INCL_BIAS_MG)}
    return CalibrationResult("joint", {}, estimates, sensor=SensorRecord(sample_rate_hz=rate_hz))


def feed(tap, data: bytes, seed: int = 1, pause_s: float = 0.0002) -> StreamParser:
    """Through a parser in random chunks, as reads of a port come, `pause_s` apart (a port's
    pace, which a reader keeps up with)."""
    parser = StreamParser(tap=tap)
    rng = np.random.default_rng(seed)
    i = 0
    while i < len(data):
        n = int(rng.integers(1, 400))
        parser.feed(data[i:i + n])
        i += n
        time.sleep(pause_s)
    parser.finish()
    return parser


class LinkReader:
    """A client of the link: opens it as a driver opens a port and reads everything."""

    def __init__(self, link, read=True):
        self.fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.got = bytearray()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        if read:
            self._thread.start()

    def _read(self):
        while not self._stop.is_set():
            if select.select([self.fd], [], [], 0.02)[0]:
                self.got += os.read(self.fd, 65536)

    def wait_for(self, size: int, timeout: float = DEADLINE_S) -> bytes:
        deadline = time.monotonic() + timeout
        while len(self.got) < size and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(0.05)  # anything more that should not be there
        return bytes(self.got)

    def close(self):
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        os.close(self.fd)


@pytest.fixture
def link(tmp_path):
    return tmp_path / "imu-raw"


def collect():
    sent = []
    return sent, sent.append


@pytest.fixture
def quick_episodes(monkeypatch):
    """Episodes end after 0.3 s of quiet instead of QUIET_S, so a test sees their ends."""
    monkeypatch.setattr(ptys, "QUIET_S", 0.3)


# ---------------------------------------------------------------- raw pty

def test_the_raw_link_carries_every_byte_unchanged_and_in_order(link):
    data, _, _ = sensor_bytes(n=2000)
    data = b"\x00\x93junk" + data + b"\x93\x01"  # bytes of no datagram pass as well
    raw = RawPty(link, forward=lambda request: None)
    reader = LinkReader(link)
    try:
        feed(raw.tap, data)
        assert reader.wait_for(len(data)) == data
        assert raw.dropped_bytes == 0
    finally:
        reader.close()
        raw.close()


def test_a_reader_that_never_reads_does_not_hold_the_tap_up(link):
    data, _, _ = sensor_bytes(n=20000)  # 800 kB, far beyond what a pty holds
    raw = RawPty(link, forward=lambda request: None)
    idle = LinkReader(link, read=False)
    try:
        with capture_logs() as logs:
            started = time.monotonic()
            parser = feed(raw.tap, data, pause_s=0)
            elapsed_s = time.monotonic() - started
        assert parser.stats.datagrams == 20000
        assert elapsed_s < 5.0
        assert 700_000 < raw.dropped_bytes < len(data)  # what the pty held is all that went in
        assert [e["event"] for e in logs if e["log_level"] == "warning"] == ["pty_dropping"]  # once, not per write
    finally:
        idle.close()
        raw.close()


def test_nothing_waits_in_the_pty_for_a_reader_that_opens_it_later(link):
    """Nobody has the link open: nothing is written. A reader that leaves bytes unread and closes:
    they are flushed, the next reader starts with what comes after it opened."""
    first, second = sensor_bytes(n=200, seed=1)[0], sensor_bytes(n=200, seed=2)[0]
    raw = RawPty(link, forward=lambda request: None)
    try:
        feed(raw.tap, first)  # nobody there
        leaving = LinkReader(link, read=False)
        feed(raw.tap, first)
        leaving.close()  # without reading
        feed(raw.tap, first[:100])  # the tap sees it gone
        reader = LinkReader(link)
        feed(raw.tap, second)
        assert reader.wait_for(len(second)) == second
        reader.close()
        assert raw.dropped_bytes == 0
    finally:
        raw.close()


def test_allowed_requests_reach_forward_and_refused_ones_do_not(link, quick_episodes):
    sent, forward = collect()
    raw = RawPty(link, forward=forward)
    client = LinkReader(link, read=False)
    try:
        with capture_logs() as logs:
            os.write(client.fd, b"C\rN\r\nSERVICEMODE\rR\rc\rUTILITYMODE\r\nXYZ\r" + b"C" * 80 + b"\rI")
            time.sleep(0.05)
            os.write(client.fd, b"\rT\rE\r")
            wait_until(lambda: len(sent) == 5)
            wait_until(lambda: any(e["event"] == "pty_refusals_ended" for e in logs))
        assert sent == [b"C\r", b"N\r", b"I\r", b"T\r", b"E\r"]
        refused = [(e["event"], e["log_level"], e.get("request"), e.get("refused")) for e in logs
                   if e["event"].startswith("pty_refus") or e["event"] == "pty_request_refused"]
        assert refused == [("pty_request_refused", "warning", "SERVICEMODE", None),  # once, with the first
                           ("pty_refusals_ended", "info", None, 5)]  # and the count
        assert [e["event"] for e in logs].count("pty_request_too_long") == 1
        assert (raw.requests_forwarded, raw.requests_refused, raw.requests_throttled) == (5, 5, 0)
    finally:
        client.close()
        raw.close()


@pytest.mark.slow
def test_a_flood_of_one_request_is_forwarded_once_a_second_and_logged_per_episode(link, quick_episodes):
    """10,000 `N` over about 2 s: each answer would replace a normal datagram, so at most one a
    second reaches the sensor; the rest are counted, and said in two lines."""
    sent, forward = collect()
    raw = RawPty(link, forward=forward)
    client = LinkReader(link, read=False)
    try:
        with capture_logs() as logs:
            started = time.monotonic()
            for _ in range(10):
                os.write(client.fd, b"N\r" * 1000)
                time.sleep(0.22)
            wait_until(lambda: raw.requests_forwarded + raw.requests_throttled == 10_000)
            elapsed_s = time.monotonic() - started
            wait_until(lambda: any(e["event"] == "pty_throttling_ended" for e in logs))
        assert 2 <= len(sent) <= elapsed_s + 1 and set(sent) == {b"N\r"}
        assert raw.requests_throttled == 10_000 - len(sent)
        events = [e["event"] for e in logs]
        assert events.count("pty_request") == len(sent)  # one line per request that went
        assert [e for e in events if e != "pty_request"] == ["pty_request_throttled", "pty_throttling_ended"]
        ended = next(e for e in logs if e["event"] == "pty_throttling_ended")
        assert ended["throttled"] == raw.requests_throttled
    finally:
        client.close()
        raw.close()


@pytest.mark.slow
def test_each_kind_of_request_has_its_own_second(link):
    sent, forward = collect()
    raw = RawPty(link, forward=forward, allow_service_mode=True)
    client = LinkReader(link, read=False)
    try:
        os.write(client.fd, b"C\rN\rC\rSERVICEMODE\rR\rSERVICEMODE\rR\rN\r")
        wait_until(lambda: raw.requests_forwarded + raw.requests_throttled == 8)
        assert sent == [b"C\r", b"N\r", b"SERVICEMODE\r", b"R\r"]
        assert raw.requests_throttled == 4
        time.sleep(1.05)
        os.write(client.fd, b"C\r")
        wait_until(lambda: len(sent) == 5)
        assert sent[-1] == b"C\r"
    finally:
        client.close()
        raw.close()


def test_a_flood_of_refused_requests_and_long_lines_is_two_lines_each(tmp_path, quick_episodes):
    """50,000 unknown requests into the raw pty, 50,000 requests into the corrected one, 1000 lines
    too long: each flood is counted, and said when it begins and, with its count, when it ends."""
    raw = RawPty(tmp_path / "raw", forward=lambda request: None)
    corrected = CorrectedPty(tmp_path / "corrected")
    to_raw, to_corrected = LinkReader(tmp_path / "raw", read=False), LinkReader(tmp_path / "corrected", read=False)
    try:
        with capture_logs() as logs:
            os.write(to_raw.fd, b"X\r" * 50_000)
            os.write(to_raw.fd, (b"L" * 100 + b"\r") * 1000)
            os.write(to_corrected.fd, b"C\r" * 50_000)
            wait_until(lambda: (raw.requests_refused, corrected.requests_refused) == (50_000, 50_000))
            wait_until(lambda: [e["event"] for e in logs].count("pty_refusals_ended") == 2
                       and any(e["event"] == "pty_long_lines_ended" for e in logs))
        by_link = {}
        for e in logs:
            by_link.setdefault(e["link"], []).append((e["event"], e.get("refused", e.get("lines"))))
        assert sorted(by_link[str(tmp_path / "raw")]) == [  # the two floods' episodes overlap
            ("pty_long_lines_ended", 1000), ("pty_refusals_ended", 50_000), ("pty_request_refused", None),
            ("pty_request_too_long", None)]
        assert by_link[str(tmp_path / "corrected")] == [("pty_request_refused", None), ("pty_refusals_ended", 50_000)]
        assert raw.requests_forwarded == 0 and raw.long_lines == 1000
    finally:
        to_raw.close()
        to_corrected.close()
        raw.close()
        corrected.close()


def test_service_mode_requests_go_when_allowed_and_long_lines_are_bounded(link):
    sent, forward = collect()
    raw = RawPty(link, forward=forward, allow_service_mode=True)
    client = LinkReader(link, read=False)
    try:
        with capture_logs() as logs:
            for _ in range(10):  # a line without end, in pieces: discarded, said once, up to its CR
                os.write(client.fd, b"x" * 30)
                time.sleep(0.005)
            os.write(client.fd, b"SERVICEMODE\rUTILITYMODE\rR\r")
            deadline = time.monotonic() + DEADLINE_S
            while len(sent) < 2 and time.monotonic() < deadline:
                time.sleep(0.005)
            time.sleep(0.05)
        assert sent == [b"UTILITYMODE\r", b"R\r"]  # SERVICEMODE was the end of the 300-byte line
        assert [e["event"] for e in logs] == ["pty_request_too_long", "pty_request", "pty_request"]
    finally:
        client.close()
        raw.close()


def test_the_daemon_read_path_forwards_a_request_written_to_the_raw_link(link, pty):
    """PortSource on a pty (the sensor's side is the other master): a request written into the
    raw link reaches the sensor, and the sensor's bytes come out of the link unchanged."""
    sensor_master, sensor_path = pty
    raw = None
    source = PortSource(sensor_path, request_config=False, tap=lambda settled: raw.tap(settled))
    raw = RawPty(link, forward=source.reader.write)
    client = LinkReader(link)
    try:
        os.write(client.fd, b"C\r")
        heard, deadline = b"", time.monotonic() + DEADLINE_S
        while b"C\r" not in heard and time.monotonic() < deadline:
            if select.select([sensor_master], [], [], 0.05)[0]:
                heard += os.read(sensor_master, 64)
        assert heard == b"C\r"
        data, _, _ = sensor_bytes(n=200)
        os.write(sensor_master, data)
        assert client.wait_for(len(data)) == data
    finally:
        client.close()
        raw.close()
        source.close()
    assert source.reader.write(b"C\r") is False  # the port is closed: said, not raised


def test_a_request_to_a_sensor_that_is_gone_is_false_not_an_exception():
    """Forwarding runs in the ptys' request thread: a port that fails under it (unplugged: the
    other side of the pty closed) makes `write` say False while the reader thread reopens."""
    sensor_master, sensor_slave = os.openpty()
    tty.setraw(sensor_master)
    tty.setraw(sensor_slave)
    source = PortSource(os.ttyname(sensor_slave), request_config=False)
    try:
        assert source.reader.write(b"C\r") is True
        assert os.read(sensor_master, 16) == b"C\r"
        os.close(sensor_master)
        said = []
        for _ in range(40):
            said.append(source.reader.write(b"N\r"))
            time.sleep(0.005)
        assert said.count(False) > 30
    finally:
        source.close()
        os.close(sensor_slave)


# ---------------------------------------------------------------- corrected pty

@pytest.mark.parametrize("datagram_id, gyro_unit, acc_unit, rate, incl_result, crlf", [
    (0x93, GyroUnit.RATE, AccUnit.ACCELERATION, 2000, True, False),
    (0x93, GyroUnit.INCREMENTAL_ANGLE, AccUnit.INCREMENTAL_VELOCITY, 500, True, True),
    (0xA7, GyroUnit.INCREMENTAL_ANGLE_DELAYED, AccUnit.AVERAGE_ACCELERATION, 125, False, False),
    (0x91, GyroUnit.AVERAGE_RATE, AccUnit.ACCELERATION, 1000, False, True),  # a unit without inclinometers
])
def test_corrected_datagrams_are_raw_minus_bias_within_one_lsb(link, datagram_id, gyro_unit, acc_unit, rate,
                                                             incl_result, crlf):
    data, head_len, samples = sensor_bytes(n=1500, datagram_id=datagram_id, rate=rate, crlf=crlf,
                                           gyro_unit=gyro_unit, acc_unit=acc_unit, incl_unit=acc_unit)
    corrected = CorrectedPty(link, before_result="hold")
    corrected.set_result(result(incl=incl_result, rate_hz=rate))
    reader = LinkReader(link)
    try:
        feed(corrected.tap, data)
        out = reader.wait_for(len(data))
    finally:
        reader.close()
        corrected.close()
    assert len(out) == len(data) and out[:head_len] == data[:head_len]  # the configuration passes unchanged
    capture = decode_capture(out)
    got, fmt = capture.samples, capture.info.format
    assert capture.info.stats.datagrams == len(samples) and capture.info.stats.crc_errors == 0
    dt_s = 1 / rate
    per_sample = {"gyro": dt_s if gyro_unit.is_angle else 1.0,
                  "acc": dt_s * STANDARD_GRAVITY if acc_unit.is_velocity else 1.0}
    per_sample["incl"] = per_sample["acc"]
    biases = {"gyro": np.array(GYRO_BIAS_DEG_H) / 3600, "acc": np.array(ACC_BIAS_MG) / 1000,
              "incl": np.array(INCL_BIAS_MG) / 1000 if incl_result else np.zeros(3)}
    lsb = fmt.scales()
    for cluster in ("gyro", "acc", "incl"):
        if np.isnan(samples[cluster][0, 0]):
            assert np.isnan(got[cluster]).all()
            continue
        raw_counts = samples[cluster] / lsb[cluster]
        wanted = np.clip(raw_counts - biases[cluster] * per_sample[cluster] / lsb[cluster], -2**23, 2**23 - 1)
        error = np.abs(got[cluster] / lsb[cluster] - wanted)
        assert error.max() <= 1.0, cluster
        shift = np.median(raw_counts - got[cluster] / lsb[cluster], axis=0)
        assert np.all(np.abs(shift) >= 1) == (cluster != "incl" or incl_result), cluster  # the bias is taken out
    for name in ("counter", "latency_us", "status_gyro", "status_acc", "status_incl", "temp_gyro", "temp_acc"):
        assert np.array_equal(got[name], samples[name], equal_nan=got[name].dtype.kind == "f"), name


def test_integrated_units_pass_unchanged_and_say_why(link):
    data, _, _ = sensor_bytes(n=300, gyro_unit=GyroUnit.INTEGRATED_ANGLE, acc_unit=AccUnit.ACCELERATION,
                              incl_unit=AccUnit.INTEGRATED_VELOCITY_MS)
    corrected = CorrectedPty(link)
    corrected.set_result(result())
    reader = LinkReader(link)
    try:
        with capture_logs() as logs:
            feed(corrected.tap, data)
        out = reader.wait_for(len(data))
    finally:
        reader.close()
        corrected.close()
    raw, got = decode_capture(data).samples, decode_capture(out).samples
    assert np.array_equal(got["gyro"], raw["gyro"]) and np.array_equal(got["incl"], raw["incl"])
    assert not np.array_equal(got["acc"], raw["acc"])
    said = [(e["cluster"], e["why"]) for e in logs if e["event"] == "corrected_pty_uncorrected"]
    assert said == [("gyro", "integrated_angle sums the bias since power-up"),
                    ("incl", "integrated_velocity_ms sums the bias since power-up")]


def test_before_a_result_hold_carries_only_special_datagrams_and_raw_the_raw_bytes(tmp_path):
    data, head_len, _ = sensor_bytes(n=300)
    hold = CorrectedPty(tmp_path / "hold", before_result="hold")
    raw = CorrectedPty(tmp_path / "raw", before_result="raw")
    held, passed = LinkReader(tmp_path / "hold"), LinkReader(tmp_path / "raw")
    try:
        feed(lambda settled: (hold.tap(settled), raw.tap(settled)), data)
        assert passed.wait_for(len(data)) == data
        assert held.wait_for(head_len + 1, timeout=0.2) == data[:head_len]  # the configuration, no data
        hold.set_result(result())
        feed(hold.tap, data)
        corrected = held.wait_for(head_len + len(data))[head_len:]
        assert len(corrected) == len(data) and corrected != data
        hold.set_result(None)  # the sensor restarted: its biases are no longer these
        feed(hold.tap, data)
        assert held.wait_for(2 * head_len + len(data) + 1, timeout=0.2)[head_len:] == corrected + data[:head_len]
    finally:
        held.close()
        passed.close()
        hold.close()
        raw.close()


def test_the_start_up_bit_coming_on_ends_the_result_before_the_daemon_says_so(link):
    """The hub's tap cuts at a restart (here the start-up bit rising, its power-up datagrams
    lost) and the corrected pty passes the new power-up's datagrams unchanged at once."""
    fmt = Configuration.build(sample_rate_hz=2000).format
    samples = exact_samples(120, fmt, fmt.datagram_id, np.random.default_rng(3))
    for cluster in ("gyro", "acc", "incl"):
        samples["status_" + cluster] = np.where(np.arange(120) < 80, 0, Status.START_UP)  # restarted at 80
    frames = encode_samples(samples, fmt.datagram_id, fmt, crlf=False)
    before, after = frames[:80].tobytes(), frames[80:].tobytes()
    hub = Hub(ServeConfig(corrected_pty=link, corrected_before_result="raw"), "port")
    hub.on_result(result())
    reader = LinkReader(link)
    try:
        parser = StreamParser(fmt, tap=hub.tap)
        parser.feed(before)
        parser.feed(after)
        out = reader.wait_for(len(frames.tobytes()))
        hub.on_result(result())  # the old power-up's finishing solve, before the daemon says RESTARTED
        parser.feed(after)
        again = reader.wait_for(len(out) + len(after))[len(out):]
    finally:
        reader.close()
        hub.close()
    assert len(out) == len(before) + len(after)
    assert out[:len(before)] != before and out[len(before):] == after  # corrected, then raw after the restart
    assert again == after  # that result is published, not subtracted from the new power-up's datagrams


def test_a_bad_before_result_is_one_line():
    with pytest.raises(PtyError, match="corrected_before_result = 'keep': expected one of hold, raw"):
        CorrectedPty("/tmp/never", before_result="keep")


# ---------------------------------------------------------------- the link

def test_an_old_link_is_replaced_and_ours_removed_at_close(link):
    link.symlink_to("/dev/null")
    raw = RawPty(link, forward=lambda request: None)
    slave = os.readlink(link)
    assert slave.startswith("/dev/pts/") and os.path.samefile(link, slave)
    assert stat.S_IMODE(os.stat(slave).st_mode) == 0o660
    assert sorted(p.name for p in link.parent.iterdir()) == [link.name]  # no temporary link left
    raw.close()
    assert not os.path.lexists(link)
    raw.close()  # again: nothing left to do


def test_a_link_someone_else_replaced_is_left_at_close(link):
    raw = RawPty(link, forward=lambda request: None)
    link.unlink()
    link.symlink_to("/dev/null")
    raw.close()
    assert os.readlink(link) == "/dev/null"


def test_a_regular_file_or_a_missing_directory_is_refused(link):
    link.write_text("keep me")
    with pytest.raises(PtyError, match="exists and is not a symlink"):
        RawPty(link, forward=lambda request: None)
    assert link.read_text() == "keep me"
    with pytest.raises(PtyError, match="does not exist"):
        CorrectedPty(link.parent / "missing" / "imu")


def test_the_slave_gets_the_group_and_an_unknown_group_is_one_line(link):
    raw = RawPty(link, forward=lambda request: None, gid=os.getgid())
    try:
        assert os.stat(link).st_gid == os.getgid()
    finally:
        raw.close()
    with pytest.raises(ServeError, match="^group 'no-such-group-here': no such group"):
        Hub(ServeConfig(raw_pty=link, group="no-such-group-here"), "port")
    assert not os.path.lexists(link)
    with pytest.raises(ServeError, match=f"^corrected_pty {link.parent}/missing/imu: directory "
                                         f"{link.parent}/missing does not exist$"):
        Hub(ServeConfig(corrected_pty=link.parent / "missing" / "imu"), "port")

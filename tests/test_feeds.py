"""The feeds thread (ROS 2, Foxglove): every sample once, in order, stamped on the sensor's
clock, with the correction its read took; the calibrator's events and the stream's health
handed over; a feed that fails logged once per episode with a count, and retried."""

import threading
import time
from pathlib import Path

import numpy as np
from structlog.testing import capture_logs

from calibd.config import ServeConfig
from calibd.correction import sensor_biases
from calibd.daemon import State
from calibd.serve import feeds as feeds_module
from calibd.serve import queue as queue_module
from calibd.serve.hub import Hub
from stim300.capture import stream_info
from stim300.stream import StreamParser
from test_serve_socket import DATA_2000, known_result


class Recorder:
    """A feed that keeps what it is given; its first `failures` sample calls raise."""

    def __init__(self, failures: int = 0):
        self.batches, self.states, self.results, self.healths = [], [], [], []
        self.failures, self.closed = failures, False
        self.thread = set()

    def samples(self, batch):
        self.thread.add(threading.current_thread().name)
        if self.failures:
            self.failures -= 1
            raise OSError("no route to host")
        self.batches.append(batch)

    def state(self, state, detail, progress):
        self.states.append((state, detail))

    def result(self, result):
        self.results.append(result)

    def health(self, health):
        self.healths.append(health)

    def close(self):
        self.closed = True


def run_hub(monkeypatch, feeds: dict, chunk: int = 4096):
    """DATA_2000 through a hub serving only `feeds`, a result given halfway; the parser."""
    monkeypatch.setattr(queue_module, "PENDING_SAMPLES", 10**7)
    monkeypatch.setattr(feeds_module, "HEALTH_S", 0.05)
    hub = Hub(ServeConfig(), "port", feeds=feeds)
    parser = StreamParser(tap=hub.tap)
    half = len(DATA_2000) // 2
    hub.on_state(State.COLLECTING, "collecting", {"statics": 1})
    for offset in range(0, len(DATA_2000), chunk):
        if offset <= half < offset + chunk:
            hub.on_result(known_result())
        parser.feed(DATA_2000[offset:offset + chunk])
        hub.stream_seen(stream_info(parser), {"crc_errors": parser.stats.crc_errors}, {})
        time.sleep(0.001)
    time.sleep(0.2)
    hub.close()
    return parser


def test_every_sample_once_in_order_stamped_and_corrected_from_the_result_on(monkeypatch):
    feed = Recorder()
    parser = run_hub(monkeypatch, {"recorder": feed})
    samples = np.concatenate([b.samples for b in feed.batches])
    assert len(samples) == parser.stats.datagrams
    assert np.all(np.diff(samples["counter"].astype(int)) % 256 == 1)  # 2000 Hz: every step one count
    stamps = np.concatenate([b.stamp_ns for b in feed.batches])
    assert np.all(np.diff(stamps) > 0) and abs(np.median(np.diff(stamps)) - 500_000) < 1  # ns, 2000 Hz
    corrected = [b.correction is not None for b in feed.batches]
    first = corrected.index(True)
    assert first > 0 and all(corrected[first:])  # none before the result, every batch from it on
    expected = sensor_biases(known_result())
    assert all(np.array_equal(feed.batches[-1].correction.bias[k], expected[k].astype(np.float32)) for k in expected)
    assert feed.states[0] == ("COLLECTING", "collecting") and len(feed.results) == 1
    assert feed.healths and feed.healths[-1].counts["crc_errors"] == parser.stats.crc_errors
    assert feed.healths[-1].state == "COLLECTING" and feed.closed
    assert feed.thread == {"calibd-feeds"}  # never the reader's thread


def test_a_failing_feed_is_logged_once_with_a_count_and_retried(monkeypatch):
    failing, healthy = Recorder(failures=5), Recorder()
    with capture_logs() as logs:
        parser = run_hub(monkeypatch, {"ros2": failing, "foxglove": healthy})
    events = [e for e in logs if e["event"].startswith("feed_")]
    assert [(e["event"], e["feed"]) for e in events] == [("feed_failing", "ros2"), ("feed_recovered", "ros2")]
    assert "no route to host" in events[0]["error"] and events[1]["failed_calls"] == 5
    assert sum(len(b.samples) for b in healthy.batches) == parser.stats.datagrams  # the other feed lost nothing
    assert failing.batches  # retried: it publishes again once it works


def test_stamps_reset_again_and_again_are_one_log_line(monkeypatch):
    """A stream whose reads all carry one host time (the host clock seems stopped): the mapping
    resets at tick after tick, and the log says so once."""
    monkeypatch.setattr(queue_module, "PENDING_SAMPLES", 10**7)
    feed = Recorder()
    hub = Hub(ServeConfig(), "port", feeds={"recorder": feed})
    parser = StreamParser(tap=hub.tap)
    with capture_logs() as logs:
        for offset in range(0, len(DATA_2000), 4096):
            parser.feed(DATA_2000[offset:offset + 4096], 1000.0)
            hub.stream_seen(stream_info(parser), {}, {})
            time.sleep(0.002)
        time.sleep(0.1)
        hub.close()
    assert [e["event"] for e in logs if e["event"].startswith("stamps_")] == ["stamps_reset"]
    assert sum(len(b.samples) for b in feed.batches) == parser.stats.datagrams


def test_every_state_change_in_order_even_two_in_one_tick(monkeypatch):
    feed = Recorder()
    hub = Hub(ServeConfig(), "port", feeds={"recorder": feed})
    for k in range(3):  # within one tick
        hub.on_state(State.COLLECTING, f"collecting {k}", {})
    hub.on_state(State.SOLVED, "solved", {})
    time.sleep(0.1)
    hub.close()
    assert feed.states == [("COLLECTING", f"collecting {k}") for k in range(3)] + [("SOLVED", "solved")]


def test_after_a_sensor_restart_no_batch_carries_the_old_power_ups_correction(monkeypatch):
    """Two power-ups of one capture back to back, a result during the first: its correction goes
    with the first power-up's samples only; the stamps go on increasing across the restart."""
    monkeypatch.setattr(queue_module, "PENDING_SAMPLES", 10**7)
    capture = (Path(__file__).resolve().parents[1] / "fixtures" / "heading137_lat60_125hz.bin").read_bytes()
    feed = Recorder()
    hub = Hub(ServeConfig(), "port", feeds={"recorder": feed})
    parser = StreamParser(tap=hub.tap)
    first_power_up = 0
    for power_up in range(2):
        for offset in range(0, len(capture), 16384):
            if power_up == 0 and offset == 16384 * 10:
                hub.on_result(known_result())
            parser.feed(capture[offset:offset + 16384])
            hub.stream_seen(stream_info(parser), {}, {})
        if power_up == 0:
            first_power_up = parser.stats.datagrams  # the samples before the restart
        time.sleep(0.1)
    hub.close()
    assert parser.stats.restarts == 1
    counted, corrected_after = 0, 0
    for batch in feed.batches:
        corrected_after += (batch.correction is not None) * max(0, counted + len(batch.samples) - first_power_up)
        counted += len(batch.samples)
    assert counted == parser.stats.datagrams and corrected_after == 0
    assert any(b.correction is not None for b in feed.batches)  # the first power-up's samples took it
    stamps = np.concatenate([b.stamp_ns for b in feed.batches])
    assert np.all(np.diff(stamps) > 0)

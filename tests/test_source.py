"""The sample-source seam: every backend gives the bulk decoder's samples with their stream
index, restarts and fault counts; pacing takes the data's time divided by the speed; silence
grows only while nothing arrives; a capture is decoded in bounded memory."""

import gc
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from captures import capture, same_samples
from stim300.bulk import decode_capture
from stim300.codec import SAMPLE_DTYPE
from stim300.errors import PortError
from stim300.protocol import INTERNAL_RATE_HZ
from stim300.reads import READS_DTYPE
import stim300.source as source_module
from stim300.source import CaptureSource, PortSource, PtySource

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
FAULTS = FIXTURES / "faults_125hz.bin"  # garbage, CRC errors, lost datagrams and a sensor restart
DEADLINE_S = 20.0


def read_all(source, timeout_s: float = 0.05, expected: int | None = None) -> list:
    """Every batch with samples until the source ends (or has given `expected` samples)."""
    batches, count = [], 0
    deadline = time.monotonic() + DEADLINE_S
    while not source.ended and count != expected:
        assert time.monotonic() < deadline, f"{count} samples after {DEADLINE_S} s"
        batch = source.read(timeout_s)
        if batch is not None and len(batch.samples):
            batches.append(batch)
            count += len(batch.samples)
    return batches


def check_batches(batches: list, data: bytes) -> None:
    """The batches hold the bulk decoder's samples in order, each numbered where it starts, and
    the last one the stream's restarts and fault counts."""
    capture = decode_capture(data)
    assert same_samples(np.concatenate([b.samples for b in batches]), capture.samples)
    assert [b.first for b in batches] == np.cumsum([0] + [len(b.samples) for b in batches[:-1]]).tolist()
    last, stats = batches[-1].info, capture.info.stats
    assert last.stats.restart_datagrams == stats.restart_datagrams and last.stats.restarts == stats.restarts == 1
    assert (last.stats.crc_errors, last.stats.lost_samples, last.stats.skipped_bytes) == \
        (stats.crc_errors, stats.lost_samples, stats.skipped_bytes)
    assert last.rate_hz == 125 and last.sensor_record() == capture.info.sensor_record()


def test_a_capture_source_gives_the_bulk_decoders_samples_then_ends():
    data = FAULTS.read_bytes()
    with CaptureSource(data, chunk_bytes=10_000) as source:
        batches = read_all(source)
        assert source.ended and source.read(0.05) is None and source.error is None
        assert source.done_bytes == source.total_bytes == len(data)
    check_batches(batches, data)


def test_a_capture_source_stamps_samples_with_the_read_log_as_the_bulk_decoder_does():
    data = FAULTS.read_bytes()
    ends = np.unique(np.random.default_rng(3).integers(1, len(data) - 5000, 300))  # the log stops short
    reads = np.empty(len(ends), READS_DTYPE)
    reads["end"], reads["t_host_s"] = ends, 100.0 + np.arange(len(ends)) * 0.004
    with CaptureSource(data, reads=reads, chunk_bytes=7_000) as source:
        stamped = np.concatenate([b.samples["t_host"] for b in read_all(source)])
    truth = decode_capture(data, reads=reads).samples
    assert np.isnan(stamped[-10:]).all()  # bytes the log does not cover
    np.testing.assert_array_equal(stamped, truth["t_host"])


def test_a_pty_source_gives_the_bulk_decoders_samples_then_ends():
    data = FAULTS.read_bytes()
    with PtySource(data) as source:
        batches = read_all(source)
        assert source.ended and source.error is None and source.done_bytes == len(data)
    check_batches(batches, data)
    assert all(np.isfinite(b.samples["t_host"]).all() for b in batches)  # stamped by the port reader


def test_a_port_source_gives_the_bulk_decoders_samples(pty):
    master, path = pty
    data = FAULTS.read_bytes()
    truth = decode_capture(data).samples
    with PortSource(path, request_config=False) as source:
        for offset in range(0, len(data), 4096):
            os.write(master, data[offset:offset + 4096])
        batches = read_all(source, expected=len(truth))
        assert not source.ended  # a port does not end
    check_batches(batches, data)


@pytest.mark.slow
def test_silence_grows_while_nothing_arrives_and_not_while_the_consumer_works(pty):
    master, path = pty
    data, _, _ = capture(500, rate=2000)
    opened = time.monotonic()
    with PortSource(path, request_config=False) as source:
        for _ in range(4):
            assert source.read(0.1) is None
        assert 0.4 <= source.silent_s <= time.monotonic() - opened
        os.write(master, data)
        assert len(read_all(source, expected=500)[-1].samples)
        assert source.silent_s == 0.0
        time.sleep(0.5)  # the consumer works on the batch: not silence
        assert source.read(0.1) is None and 0.1 <= source.silent_s < 0.3


def test_a_port_that_does_not_open_is_a_port_error(tmp_path):
    with pytest.raises(PortError, match="no such device"):
        PortSource(str(tmp_path / "ttyNONE"))


@pytest.mark.slow
def test_a_paced_capture_takes_its_data_time_over_the_speed():
    """The fault capture's minute of data (its lost datagrams included) at 60 times real time
    takes about a second; unpaced, a small fraction of that."""
    data = FAULTS.read_bytes()
    capture = decode_capture(data)
    truth = capture.samples
    duration_s = (len(truth) + capture.info.stats.lost_samples) / 125
    speed = duration_s / 1.0
    for pace, low_s, high_s in ((speed, 0.9, 1.3), (None, 0.0, 0.3)):
        started = time.monotonic()
        with CaptureSource(data, speed=pace, chunk_bytes=4096) as source:
            count = sum(len(b.samples) for b in read_all(source))
        elapsed = time.monotonic() - started
        assert count == len(truth) and low_s <= elapsed <= high_s, (pace, elapsed)


def test_a_pty_writer_takes_its_pace_from_the_capture_not_from_the_reader():
    """The byte rate a paced pty is written at is the capture's own, known before the first write:
    the fault capture's exactly (its lost datagrams and garbage included), a 2000 Hz capture's from
    its first megabyte. It once came from what the reader had parsed, and a reader starved of CPU
    gave it from a partial first read: a replay 2.4 times too fast."""
    data = FAULTS.read_bytes()
    faults = decode_capture(data)
    duration_s = (len(faults.samples) + faults.info.stats.lost_samples) / 125
    assert source_module._bytes_per_second(data) == pytest.approx(len(data) / duration_s, rel=1e-12)
    data = (FIXTURES / "static_turn_2000hz.bin").read_bytes()
    assert len(data) > source_module.PACE_BYTES
    fast = decode_capture(data)
    duration_s = (len(fast.samples) + fast.info.stats.lost_samples) / 2000
    assert source_module._bytes_per_second(data) == pytest.approx(len(data) / duration_s, rel=0.005)
    assert source_module._bytes_per_second(bytes(range(256)) * 8) is None  # nothing tells it: unpaced


def test_a_capture_source_holds_one_chunk_of_samples_not_the_capture():
    """A 2000 Hz capture of 3 MB: the bulk decoder holds every sample at once, the source one
    chunk's worth, whatever the capture's length."""
    data, samples, _ = capture(50_000, rate=2000)
    tracemalloc.start()
    try:
        decode_capture(data)
        _, whole_peak = tracemalloc.get_traced_memory()
        gc.collect()  # the bulk decoder and its scanner form a cycle
        tracemalloc.reset_peak()
        count = 0
        with CaptureSource(data) as source:
            while (batch := source.read(0.0)) is not None:
                count += len(batch.samples)
        _, source_peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == len(samples)
    assert whole_peak >= len(samples) * SAMPLE_DTYPE.itemsize
    assert source_peak < whole_peak / 10, (source_peak, whole_peak)


def test_a_port_source_reports_the_samples_an_overrun_cost(pty):
    """A ring of 50 samples read only after 500 arrived: the batch holds the newest 50 and says
    450 were lost, so nothing vanishes unreported."""
    master, path = pty
    data, samples, _ = capture(500, rate=2000)
    with PortSource(path, request_config=False, ring_s=50 / INTERNAL_RATE_HZ) as source:
        os.write(master, data)
        deadline = time.monotonic() + DEADLINE_S
        while source.reader.parser.stats.datagrams < 500:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        batch = source.read(0.0)
    assert batch.overrun_samples == 450 and batch.first == 450
    assert same_samples(batch.samples, samples[450:])


def test_a_port_whose_reader_fails_ends_with_the_readers_error(pty):
    master, path = pty
    data, _, _ = capture(100, rate=2000)
    with PortSource(path, request_config=False) as source:
        def broken(*args):
            raise RuntimeError("parser fault")
        source.reader.parser.feed = source.reader.parser.feed_reads = broken
        os.write(master, data)
        read_all(source)
        assert source.ended and isinstance(source.error, RuntimeError) and source.read(0.0) is None


def test_a_pty_whose_writer_fails_ends_with_the_write_error(monkeypatch):
    """The pty refusing bytes (EIO) ends the replay with that error, not with a silently short
    capture."""
    import stim300.source

    def refuse(fd, data):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(stim300.source.os, "write", refuse)
    with PtySource(FAULTS.read_bytes()) as source:
        assert read_all(source) == []
        assert source.ended and isinstance(source.error, OSError) and source.error.errno == 5

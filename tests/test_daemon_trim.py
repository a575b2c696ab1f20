"""The daemon knows the bias trim in force: a port asks the sensor (T) once per power-up whose
datagrams carried none, the Calibrator records the trim in its results (sensor.trim, untrimmed
biases), a trim other than a held result's marks that result stale, a trim that changes during a
session starts a new one, and the corrected outputs stop subtracting a result made under
another trim."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibd.client import Client, Samples
from calibd.config import MethodConfig, ServeConfig, WarmupConfig
from calibd.daemon import Calibrator, Callbacks, State
from calibd.frames import Site
from calibd.results import make_result
from calibd.serve.hub import Hub
from calibd.units import DEG
from sensor_emulator import SensorEmulator
from sensor_emulator import State as UnitState
from stim300.bulk import decode_capture
from stim300.capture import stream_info
from stim300.records import SensorRecord, StreamRecord, TrimRecord
from stim300.source import PortSource
from stim300.stream import StreamParser, TrimSeen

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
HEADING137 = FIXTURES / "heading137_lat60_125hz.bin"  # the thesis campaign in 607 s
SHORT = FIXTURES / "faults_125hz.bin"  # a sensor restart at 40 s
A = TrimRecord((2 ** -6, -2 ** -8, 0.0), (0.0, 2 ** -10, 0.0), (0.0, 0.0, -2 ** -13), 777, 9998)  # whole counts
B = replace(A, gyro_deg_s=(0.0, 0.0, 0.0))
UNIT = SensorRecord(acc_range_g=10)


def held(trim: TrimRecord | None):
    """An earlier daemon's result, made under `trim`."""
    biases = {f"gyro_bias_{axis}": (10 / 3600 * DEG, 0.1 / 3600 * DEG) for axis in "xyz"}
    return make_result("joint", Site(60.0), biases, [], [], replace(UNIT, trim=trim))


def fed(calibrator: Calibrator, samples: np.ndarray, first: int, trims=(), restarts=()) -> None:
    """One batch as the daemon's loop gives it."""
    calibrator.sensor_seen(UNIT, StreamRecord(), trims)
    calibrator.feed(samples, 125, first, restarts)


def test_a_held_result_made_under_another_trim_is_stale_at_once():
    samples = decode_capture(SHORT.read_bytes()).samples[:500]
    stale = []
    calibrator = Calibrator(Site(60.0), previous=held(A), listeners=[Callbacks(stale=stale.append)])
    fed(calibrator, samples[:100], 0)
    assert calibrator.trim is None and not stale  # not said yet: nothing known
    fed(calibrator, samples[100:200], 100, (TrimSeen(1, 150, B),))
    assert calibrator.trim == B and len(stale) == 1 and calibrator.result is stale[0]
    record = stale[0].stale
    assert record.power_up == "unknown" and "bias trim offsets in force changed since this result" in record.reason
    assert stale[0].warnings[0].startswith("stale: the bias trim offsets")


@pytest.mark.parametrize("result_trim", [A, None])
def test_a_held_result_of_the_same_trim_or_of_none_known_stands(result_trim):
    samples = decode_capture(SHORT.read_bytes()).samples[:200]
    calibrator = Calibrator(Site(60.0), previous=held(result_trim))
    fed(calibrator, samples, 0, (TrimSeen(1, 0, A),))
    assert calibrator.trim == A and calibrator.result.stale is None


def test_the_trim_is_the_power_ups_own():
    """A BTO datagram before a restart says nothing of the power-up after it; one after the restart
    does; a trim beyond its triad's range is no unit's, and is not taken."""
    samples = decode_capture(SHORT.read_bytes()).samples[:300]
    calibrator = Calibrator(Site(60.0))
    fed(calibrator, samples[:200], 0, (TrimSeen(1, 50, A),), restarts=(100,))
    assert calibrator.trim is None
    fed(calibrator, samples[200:], 200, (TrimSeen(1, 50, A), TrimSeen(2, 250, B)), restarts=(100,))
    assert calibrator.trim == B
    beyond = replace(A, incl_g=(0.0, 0.0, 0.5))
    fed(calibrator, samples[:10], 300, (TrimSeen(3, 300, beyond),), restarts=(100,))
    assert calibrator.trim == B


@pytest.mark.slow
def test_results_carry_the_trim_and_a_trim_changed_mid_session_marks_the_result_stale():
    samples = decode_capture(HEADING137.read_bytes()).samples
    events = []
    calibrator = Calibrator(Site(60.0), WarmupConfig(window_s=10.0), MethodConfig(resolve_every_s=1e9),
                            [Callbacks(result=lambda r: events.append(("result", r)),
                                       stale=lambda r: events.append(("stale", r)),
                                       state=lambda state, detail: events.append((state, detail)))])
    first = 0
    for chunk in np.array_split(samples, 60):
        fed(calibrator, chunk, first, (TrimSeen(1, 0, A),))
        first += len(chunk)
    results = [r for kind, r in events if kind == "result"]
    assert results and all(r.sensor.trim == A for r in results)
    last = results[-1]
    assert last.untrimmed("gyro_bias_x") == pytest.approx(last.estimates["gyro_bias_x"].value - A.gyro_deg_s[0] * 3600)
    before, sessions = len(events), calibrator.sessions
    fed(calibrator, samples[:500], first, (TrimSeen(1, 0, A), TrimSeen(2, first + 100, B)))
    after = events[before:]
    stale = [r for kind, r in after if kind == "stale"]
    assert len(stale) == 1 and stale[0].stale.power_up == "current" and stale[0].estimates == last.estimates
    assert "bias trim offsets in force changed" in stale[0].stale.reason
    assert calibrator.trim == B and calibrator.sessions == sessions + 1
    assert (State.COLLECTING, "the bias trim offsets changed: the output moved by the difference, collecting a new "
                              "session (warm-up stands)") in after


def _until(condition, calibrator: Calibrator, source: PortSource, timeout_s: float = 10.0) -> None:
    """The daemon's loop (calibd.live.pump) on a port, until `condition()`."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        batch = source.read(0.05)
        if batch is not None and len(batch.samples) and batch.info.rate_hz:
            calibrator.sensor_seen(batch.info.sensor_record(), batch.info.stream_record(), batch.trims)
            calibrator.feed(batch.samples, batch.info.rate_hz, batch.first, batch.info.stats.restart_datagrams)


@pytest.mark.slow
def test_a_port_asks_for_the_trim_once_per_power_up_and_the_daemon_follows_the_unit():
    unit = UnitState(datagram_id=0xA7, sample_rate_code=0, gyro_trim_deg_s=A.gyro_deg_s, acc_trim_g=A.acc_g,
                     incl_trim_g=A.incl_g, trim_reference=777)  # 125 Hz, as the capture whose samples it sends
    emulator = SensorEmulator(unit, samples=decode_capture(HEADING137.read_bytes()).samples[5000:10000])
    asked = []
    answer = emulator._request
    emulator._request = lambda line: (asked.append(line), answer(line))
    emulator.start()
    stale = []
    calibrator = Calibrator(Site(60.0), previous=held(A), listeners=[Callbacks(stale=stale.append)])
    try:
        with PortSource(emulator.path) as source:
            _until(lambda: calibrator.trim is not None, calibrator, source)
            assert calibrator.trim == A and not stale and asked == [b"C", b"T"]
            time.sleep(0.5)
            _until(lambda: True, calibrator, source)
            assert asked == [b"C", b"T"]  # once
            emulator.state = replace(emulator.state, gyro_trim_deg_s=B.gyro_deg_s)  # changed, then a reader asks T
            emulator._request(b"T")
            _until(lambda: stale, calibrator, source)
            assert calibrator.trim == B and "bias trim offsets in force changed" in stale[0].stale.reason
            emulator.power_cycle()  # back to flash's trim (A); the power-up datagrams carry none: T is asked again
            _until(lambda: calibrator.trim == A, calibrator, source)
            assert asked[-1] == b"T" and asked.count(b"T") == 3  # the test's own one, and one per power-up
    finally:
        emulator.stop()


def _read_samples(client: Client, timeout_s: float) -> int:
    count, deadline = 0, time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        message = client.read(0.2)
        if isinstance(message, Samples):
            count += len(message.t)
    return count


@pytest.mark.slow
def test_a_result_made_under_another_trim_is_no_longer_subtracted(tmp_path):
    """The corrected outputs subtract a result's biases, which include the trim then in force:
    once the daemon hears the trim changed, the result is stale and the corrected SAMPLES stop
    (held until a new result), the raw ones go on. The read that carried the new trim was passed
    on corrected: the tap serves it before the daemon's loop hears of it."""
    data = (FIXTURES / "static_turn_2000hz.bin").read_bytes()
    hub = Hub(ServeConfig(socket=tmp_path / "s.sock"), "/dev/ttySTIM")
    result = held(A)
    calibrator = Calibrator(Site(60.0), previous=result, listeners=[hub])
    clients = {kind: Client.connect(str(tmp_path / "s.sock")) for kind in ("raw", "corrected")}
    try:
        for kind, client in clients.items():
            client.watch(samples=kind)
        hub.on_result(result)  # as after the daemon's own solve: subtracted
        parser = StreamParser(tap=hub.tap)
        step = 61 * 400  # 0.2 s at 2000 Hz

        def read(k: int, trims=()) -> int:
            samples = parser.feed(data[k * step:(k + 1) * step], time.monotonic())
            hub.stream_seen(stream_info(parser), {}, {})
            calibrator.sensor_seen(UNIT, StreamRecord(), trims)
            calibrator.feed(samples, 2000, parser.stats.datagrams - len(samples))
            return len(samples)

        first = read(0, (TrimSeen(1, 0, A),))
        assert _read_samples(clients["corrected"], 1.0) == first > 0
        during = read(1, (TrimSeen(1, 0, A), TrimSeen(2, first, B)))  # the tap passed it on before the pump heard
        assert calibrator.result.stale is not None
        later = read(2) + read(3)
        assert _read_samples(clients["corrected"], 1.0) == during
        assert _read_samples(clients["raw"], 1.0) == first + during + later
    finally:
        for client in clients.values():
            client.close()
        hub.close()


@pytest.mark.parametrize("offsets, dropped", [(A, False), (B, True)], ids=["the same trim", "another trim"])
def test_the_served_correction_ends_at_the_read_that_carries_another_trim(offsets, dropped):
    """The hub stops subtracting at the read whose Bias Trim Offset datagram differs from the
    result's sensor.trim, before the calibrator marks the result stale."""
    from stim300.codec import SAMPLE_DTYPE
    from stim300.special import BiasTrimOffset, encode_special
    from stim300.stream import Settled
    estimates = {f"gyro_bias_{a}": (1e-5, 1e-6) for a in "xyz"}
    result = make_result("joint", Site(60.0), estimates, [], [], SensorRecord(acc_range_g=10, trim=A))
    hub = Hub(ServeConfig(), "port")
    try:
        hub.on_result(result)
        assert hub._kept is not None
        item = BiasTrimOffset(offsets.gyro_deg_s, offsets.acc_g, offsets.incl_g, offsets.reference,
                              offsets.remaining_saves)
        bto = encode_special(item, crlf=False, acc_range_g=10)
        hub.tap(Settled(bto, np.empty(0, SAMPLE_DTYPE), (), 0, (), (bto,), (TrimRecord.of_datagram(item),)))
        assert (hub._kept is None) == dropped
    finally:
        hub.close()

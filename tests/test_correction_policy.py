"""[serve] correction: which result of the power-up the corrected outputs subtract, and the
CORRECTION message announcing each change. The hub is driven as the daemon drives it (results
from the pump thread, bytes through a real parser into its tap) and read by real socket clients."""

import time
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from calibd.client import Client, Correction, Samples
from calibd.config import ServeConfig
from calibd.daemon import State
from calibd.frames import Site
from calibd.results import make_result
from calibd.correction import replaces
from calibd.serve.hub import Hub
from calibd.units import DEG
from stim300.bulk import decode_capture
from stim300.capture import stream_info
from stim300.stream import StreamParser
from stim300.records import SensorRecord

DATA = (Path(__file__).resolve().parents[1] / "fixtures" / "static_turn_2000hz.bin").read_bytes()
LSB = decode_capture(DATA[:20_000]).info.format.scales()  # one count of each block (deg/s, g)
STEP_BYTES = 61 * 400  # 400 datagrams of 0xA7 (0.2 s at 2000 Hz) after each event
G = 9.80665
NAMES = [f"{block}_bias_{axis}" for block in ("gyro", "acc", "incl") for axis in "xyz"]


def result(session: str, k: float, sigma: float, poor: bool = False):
    """A result of session `session` with biases k times (1, -2, 3) deg/h and k times
    (0.1, -0.2, 0.3) mg, each with `sigma` times 0.1 deg/h or 0.01 mg."""
    si = {f"gyro_bias_{a}": (k * v / 3600 * DEG, sigma * 0.1 / 3600 * DEG) for a, v in zip("xyz", (1, -2, 3))}
    for block in ("acc", "incl"):
        si |= {f"{block}_bias_{a}": (k * v * 1e-3 * G, sigma * 1e-5 * G) for a, v in zip("xyz", (0.1, -0.2, 0.3))}
    made = make_result("joint", Site(40.0), si, [], [], SensorRecord(serial_number="N1"), session_id=session)
    return made.flag_poor(NAMES, "bias poorly observed") if poor else made


A, B, C = result("A", 1.0, 1.0), result("B", 2.0, 0.5), result("C", 3.0, 2.0)  # first, better, poorer
D = result("D", 4.0, 0.1, poor=True)  # the smallest sigmas, but flagged poor
E = result("E", 4.0, 0.6)  # D's biases again, not poor, sigmas larger than B's
F, H = result("F", 5.0, 3.0), result("H", 6.0, 1.0)  # after a sensor restart: poorer than all before, better
EVENTS = [A, B, C, D, E, "restart", F, H]
KEPT = {  # what each policy subtracts after each event (None: nothing, the new power-up has no result yet)
    "latest": [A, B, C, D, D, None, F, H],
    "first": [A, A, A, A, A, None, F, F],
    "best": [A, B, B, B, B, None, F, H],
}


def expected_corrections(kept: list) -> list[tuple]:
    """(old, new, index of the event after which it is first carried) of each change."""
    changes, before = [], None
    for i, now in enumerate(kept):
        if now is not None and now is not before:
            changes.append((before, now, i))
        before = now
    return changes


def biases(result) -> dict:
    return {name: (result.estimates[name].value, result.estimates[name].unit) for name in NAMES}


def base_units(result) -> dict[str, np.ndarray]:
    """The result's biases as the samples carry them: gyro deg/s, acc and incl g."""
    return {"gyro": np.array([result.estimates[f"gyro_bias_{a}"].value for a in "xyz"]) / 3600,
            **{block: np.array([result.estimates[f"{block}_bias_{a}"].value for a in "xyz"]) * 1e-3
               for block in ("acc", "incl")}}


def read_all(client: Client, samples: int, timeout_s: float = 10.0) -> tuple[list, list]:
    """Every CORRECTION and SAMPLES until `samples` samples have come and nothing more comes
    for 0.3 s."""
    corrections, batches, seen = [], [], 0
    deadline = time.monotonic() + timeout_s
    while (message := client.read(0.3 if seen >= samples else 0.5)) is not None or seen < samples:
        assert time.monotonic() < deadline, f"{seen} of {samples} samples"
        if isinstance(message, Correction):
            corrections.append(message)
        elif isinstance(message, Samples):
            batches.append(message)
            seen += len(message.t)
    return corrections, batches


@pytest.mark.slow  # a whole session calibrated and served
@pytest.mark.parametrize("policy", ["latest", "first", "best"])
def test_each_policy_keeps_its_biases_and_says_every_change_once(tmp_path, policy):
    hub = Hub(ServeConfig(socket=tmp_path / "s.sock", correction=policy), "/dev/ttySTIM")
    clients = {kind: Client.connect(str(tmp_path / "s.sock")) for kind in ("raw", "corrected", "none")}
    try:
        for kind, client in clients.items():
            client.watch(samples=kind)
        parser = StreamParser(tap=hub.tap)
        steps = []  # the stream times (s) of each event's samples, from the raw SAMPLES below
        counts = []
        with capture_logs() as logs:
            for i, event in enumerate(EVENTS):
                if event == "restart":
                    hub.on_state(State.RESTARTED, "sensor restarted")
                else:
                    hub.on_result(event)
                counts.append(len(parser.feed(DATA[i * STEP_BYTES:(i + 1) * STEP_BYTES], time.monotonic())))
                hub.stream_seen(stream_info(parser), {}, {})
            raw_said, raw = read_all(clients["raw"], sum(counts))
            held = counts[EVENTS.index("restart")]  # "hold": nothing corrected before the new power-up's result
            said, corrected = read_all(clients["corrected"], sum(counts) - held)
            none_said, _ = read_all(clients["none"], 0)
        logged = [entry for entry in logs if entry["event"] == "correction_changed"]
    finally:
        for client in clients.values():
            client.close()
        hub.close()

    t_raw = np.concatenate([b.t for b in raw])
    bounds = np.cumsum([0] + counts)
    steps = [t_raw[lo] for lo in bounds[:-1]]  # the stream time of each event's first sample
    expected = expected_corrections(KEPT[policy])
    assert said == raw_said == none_said  # every watcher, whatever samples it watches
    assert len(said) == len(logged) == len(expected)
    for message, line, (old, new, i) in zip(said, logged, expected, strict=True):
        assert message.policy == policy and message.session_id == new.session_id
        assert message.old == (None if old is None else biases(old)) and message.new == biases(new)
        assert message.from_t == pytest.approx(steps[i], abs=1e-6)
        assert line["from_t"] == message.from_t and line["session_id"] == new.session_id
        assert line["new"]["gyro_bias_x"] == {"value": new.estimates["gyro_bias_x"].value, "unit": "deg/h"}

    raw_by_t = {round(float(t), 6): j for j, t in enumerate(t_raw)}
    event_of = np.searchsorted(bounds, np.arange(len(t_raw)), side="right") - 1
    for block in ("gyro", "acc", "incl"):
        raw_values = np.concatenate([getattr(b, block) for b in raw])
        for batch in corrected:
            assert batch.corrected
            rows = [raw_by_t[round(float(t), 6)] for t in batch.t]
            kept = {id(KEPT[policy][event_of[j]]): KEPT[policy][event_of[j]] for j in rows}
            assert len(kept) == 1 and None not in kept.values()  # one result's biases a batch, no held samples
            bias = base_units(*kept.values())[block]
            assert np.allclose(raw_values[rows] - getattr(batch, block), bias, rtol=0, atol=LSB[block]), block


def test_best_compares_sigmas_and_never_takes_a_poor_result():
    assert replaces("best", None, D)  # a first result is kept whatever it is
    assert replaces("best", A, B) and not replaces("best", B, C) and not replaces("best", B, D)
    assert replaces("best", D, C)  # a kept poor one gives way to any that is not
    assert not replaces("best", B, E)  # one sigma larger is enough to stay
    assert replaces("best", B, result("B2", 9.0, 0.5))  # none larger: equal sigmas replace
    assert replaces("latest", B, C) and not replaces("first", A, B)

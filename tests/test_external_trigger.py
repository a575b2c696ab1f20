"""An externally triggered sensor: the counter counts the internal 2000 Hz samples between
triggers, so time is the running sum of its steps / 2000, no step is a loss, and the rate is
measured. The shipped 200 Hz capture (step 10) calibrates; irregular steps decode."""

import json
from pathlib import Path

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from calibd.daemon import Calibrator
from calibd.frames import Site
from calibd.live import replay
from calibd.warmup import WarmupConfig
from captures import capture
from stim300.bulk import decode_capture
from stim300.capture import stream_info
from stim300.cli import main as stim300_main
from stim300.clock import counter_times
from stim300.codec import encode_samples
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, Format
from stim300.source import CaptureSource
from stim300.special import Configuration, encode_special
from stim300.stream import StreamParser

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "external_trigger_200hz.bin"
TRUTH = json.loads(Path(f"{FIXTURE}.truth.json").read_text())
SITE = ["--latitude", str(TRUTH["site"]["latitude_deg"]), "--g0", str(TRUTH["site"]["g0"])]


def triggered(steps: np.ndarray, datagram_id: int = 0x93) -> tuple[bytes, np.ndarray]:
    """Datagrams whose counters step by `steps` (internal samples between triggers), and the
    true time of each (s since the first)."""
    ticks = np.concatenate(([0], np.cumsum(steps)))
    data, samples, fmt = capture(len(ticks), datagram_id, False, rate=2000)
    samples["counter"] = (ticks + 3) % COUNTER_MODULUS
    return encode_samples(samples, datagram_id, fmt, False).tobytes(), ticks / INTERNAL_RATE_HZ


def per_estimate_z(result: dict) -> dict[str, float]:
    """(estimate - truth) / sigma for every estimate, against the biases the capture carries."""
    truth, biases = TRUTH["truth"], TRUTH["bias_during_capture"]
    keys = {"gyro_bias": "gyro_bias_deg_h", "acc_bias": "acc_bias_mg", "incl_bias": "incl_bias_mg"}
    z = {}
    for name, e in result["estimates"].items():
        if name in ("pitch", "roll", "yaw", "alpha", "beta"):
            true = truth[f"{name}_deg"]
        else:
            kind, axis = name.rsplit("_", 1)
            true = biases[keys[kind]]["session"]["xyz".index(axis)]
        z[name] = (e["value"] - true) / e["sigma"]
    return z


def test_the_200hz_capture_is_an_external_trigger_at_its_measured_rate(capsys):
    assert stim300_main(["info", str(FIXTURE)]) == 0
    text = capsys.readouterr().out
    assert "sample rate      external trigger, 200.0 Hz" in text
    assert "lost_samples     0 (externally triggered: 0 missing by the usual step, inferred)" in text
    assert stim300_main(["info", "--json", str(FIXTURE)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["sample_rate_hz"], info["external_trigger"], info["lost_samples"]) == (200.0, True, 0)
    assert info["configuration"]["sample_rate_hz"] is None  # the configuration says: external trigger
    assert info["duration_s"] == pytest.approx(TRUTH["duration_s"])
    assert info["datagrams"] == TRUTH["samples"]


def test_calibrate_recovers_the_truth_of_the_200hz_capture(tmp_path, capsys):
    out = tmp_path / "result.json"
    assert calibd_main(["calibrate", str(FIXTURE), *SITE, "-o", str(out)]) == 0, capsys.readouterr().err
    result = json.loads(out.read_text())
    assert result["sensor"]["sample_rate_hz"] == 200.0
    assert result["sensor"]["sample_rate"] == "external trigger, 200.0 Hz"
    assert result["stream"]["lost_samples"] == 0 and result["stream"]["power_up"]["duration_s"] == pytest.approx(
        TRUTH["duration_s"])
    z = per_estimate_z(result)
    assert max(abs(v) for v in z.values()) < 3.0, z


@pytest.mark.slow
def test_the_daemon_times_the_200hz_capture_in_seconds():
    """A replay through the daemon's loop: the session spans the capture's seconds (not five
    times as many, as at the 1000 Hz a step of 10 once implied) and solves near the truth."""
    site = Site(TRUTH["site"]["latitude_deg"], g0=TRUTH["site"]["g0"])
    calibrator = Calibrator(site, WarmupConfig(window_s=10.0))
    replay(CaptureSource(FIXTURE.read_bytes()), calibrator)
    result = calibrator.result
    assert result is not None
    assert result.session.duration_s == pytest.approx(TRUTH["duration_s"], abs=0.01)  # no temperatures: no wait
    turns = [p for p in TRUTH["schedule"] if p["kind"] == "turn"]
    found = [s for s in result.segments if s["kind"] == "turn"]
    assert len(found) == len(turns)
    for seg, true in zip(found, turns):
        assert seg["end_s"] - seg["start_s"] == pytest.approx(true["end_s"] - true["start_s"], abs=0.5)
    z = per_estimate_z(result.to_dict())
    assert max(abs(v) for v in z.values()) < 3.5, z


def test_noise_reads_the_200hz_capture(tmp_path, capsys):
    out = tmp_path / "noise.json"
    assert calibd_main(["noise", str(FIXTURE), "-o", str(out)]) == 0, capsys.readouterr().err
    assert json.loads(out.read_text())["sample_rate_hz"] == 200.0


@pytest.mark.parametrize("configured", [True, False])
def test_a_periodic_trigger_keeps_its_step_and_infers_its_missing_datagrams(configured):
    """Steps of 10 (200 Hz), some datagrams missing: the step stays 10 (not 2, the largest power
    of two dividing it), no loss is certain, the missing ones are inferred by the usual step."""
    steps = np.full(999, 10)
    steps[[100, 500]] = [20, 40]  # 1 and 3 datagrams missing
    data, true_s = triggered(steps)
    if configured:
        data = encode_special(Configuration.build(sample_rate_hz=None, temp_included=False), False) + data
    info = decode_capture(data).info
    assert info.stats.counter_step == 10 and info.external_trigger
    assert (info.stats.lost_samples, info.stats.inferred_missing) == (0, 4)
    assert info.rate_hz == 200.0 and info.rate_words() == "external trigger, 200.0 Hz"
    samples = decode_capture(data).samples
    assert np.allclose(counter_times(samples["counter"], info.rate_hz).time_s, true_s)


def test_irregular_trigger_steps_decode_with_no_loss_and_their_times(tmp_path, capsys):
    """Steps of 3, 5 and 7 internal samples: no fixed step, nothing lost, each sample's time is
    its counter's running sum / 2000, and `stim300 decode` writes those times."""
    steps = np.random.default_rng(7).choice([3, 5, 7], 1500)
    data, true_s = triggered(steps)
    info = decode_capture(data).info
    assert info.stats.counter_step is None and info.external_trigger
    assert (info.stats.lost_samples, info.stats.inferred_missing) == (0, 0)
    assert info.rate_hz == pytest.approx(INTERNAL_RATE_HZ / steps.mean())
    assert info.rate_words().startswith("external trigger, irregular steps, ")
    path, out = tmp_path / "irregular.bin", tmp_path / "irregular.npz"
    path.write_bytes(data)
    assert stim300_main(["decode", str(path), "-o", str(out)]) == 0
    assert "lost_samples 0" in capsys.readouterr().err
    np.testing.assert_allclose(np.load(out)["t_s"], true_s, atol=1e-12)
    parser = StreamParser()  # the live parser says the same
    parser.feed(data)
    assert stream_info(parser).stats == info.stats


@pytest.mark.parametrize("rate", [125, 500, 2000])
def test_the_fixed_rates_are_no_trigger(rate):
    """A step of 16, 4 or 1 without a configuration is the fixed rate it always was."""
    data, _, fmt = capture(300, 0x93, False, rate=rate)
    info = decode_capture(data, Format(datagram_id=0x93)).info
    assert not info.external_trigger and info.rate_hz == rate and info.rate_words() == f"{rate} Hz"

"""What the field's recordings are made of together: a unit without inclinometers (0x91) on a
200 Hz external trigger (counter step 10). Each part has its own tests; this one checks they
compose: the capture decodes with no losses, calibrates within sigma with no inclinometer
estimates, and the daemon's replay solves it."""

from dataclasses import replace

import pytest

from calibd.cli import main as calibd_main
from calibd.live import configure_logging
from calibd.results import load_result
from calibd.scenario import Segment, load_scenario
from calibd.sim import capture_bytes, simulate, truth_record
from stim300.bulk import decode_capture


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    real = load_scenario("thesis-real")
    turn = Segment("turn", angle_deg=90, peak_rate_deg_s=20, accel_deg_s2=20)
    segments = [Segment("static", duration_s=60)]
    for _ in range(3):
        segments += [turn, Segment("static", duration_s=30)]
    scenario = replace(real, name="triggered-gyro-acc", seed=4242,
                       sensor=replace(real.sensor, datagram_id=0x91, sample_rate_hz=200),
                       warmup=replace(real.warmup, power_on_s=1e7), segments=tuple(segments))
    sim = simulate(scenario)
    data, faults = capture_bytes(sim)
    path = tmp_path_factory.mktemp("triggered") / "triggered.bin"
    path.write_bytes(data)
    return path, truth_record(sim, faults)


def test_it_decodes_as_a_200hz_trigger_with_no_losses(recording):
    path, truth = recording
    info = decode_capture(path.read_bytes()).info
    assert info.rate_hz == pytest.approx(200.0) and info.stats.lost_samples == 0
    assert info.format.datagram_id == 0x91


def test_it_calibrates_within_sigma_without_inclinometer_estimates(recording, tmp_path, capsys):
    path, truth = recording
    out = tmp_path / "result.json"
    site = ["--latitude", str(truth["site"]["latitude_deg"]), "--g0", str(truth["site"]["g0"])]
    assert calibd_main(["calibrate", str(path), *site, "-o", str(out)]) == 0, capsys.readouterr().err
    result = load_result(out)
    assert not any(name.startswith("incl_") for name in result.estimates)
    for name in ("pitch", "roll", "yaw"):
        e = result.estimates[name]
        assert abs(e.value - truth["truth"][f"{name}_deg"]) < 3.5 * e.sigma, (name, e)
    biases = truth["bias_during_capture"]
    for kind, key in (("gyro_bias", "gyro_bias_deg_h"), ("acc_bias", "acc_bias_mg")):
        for k, axis in enumerate("xyz"):
            e = result.estimates[f"{kind}_{axis}"]
            assert abs(e.value - biases[key]["session"][k]) < 3.5 * e.sigma, (kind, axis, e)


@pytest.mark.slow
def test_the_daemon_solves_it(recording, capsys):
    path, truth = recording
    try:
        code = calibd_main(["replay", str(path), "--latitude", str(truth["site"]["latitude_deg"]),
                            "--warmup-window", "10"])
    finally:
        configure_logging()
    out = capsys.readouterr().out
    assert code == 0 and "[SOLVED]" in out and "incl_bias" not in out, out

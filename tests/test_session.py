"""The one block-averaging rule: SessionBuilder, as the daemon and the one-shot path use it."""

from pathlib import Path

import numpy as np

from calibd.captures import open_capture
from calibd.frames import STANDARD_GRAVITY
from calibd.session import STORE_RATE_HZ, PowerUpCuts, SessionBuilder, power_up_session
from calibd.units import DEG
from stim300.bulk import decode_capture
from stim300.codec import SAMPLE_DTYPE
from stim300.protocol import Status

FIXTURE_2000HZ = Path(__file__).resolve().parent.parent / "fixtures" / "static_turn_2000hz.bin"


def samples_2000hz(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    s = np.zeros(n, SAMPLE_DTYPE)
    s["gyro"] = rng.normal(0, 0.1, (n, 3))
    s["acc"] = rng.normal([0, 0, 1], 1e-3, (n, 3))
    s["incl"] = rng.normal([0, 0, 1], 1e-3, (n, 3))
    s["temp_gyro"] = 25 + rng.normal(0, 0.01, (n, 3))
    return s, np.arange(n) / 2000.0


def test_block_means_at_125_hz_whatever_the_batches():
    """16 samples at 2000 Hz make one stored sample, timed at the first; batches that split blocks
    give the same session as one batch; the rest short of a block waits."""
    samples, t = samples_2000hz(16 * 100 + 5)
    whole = SessionBuilder()
    stored_t, stored_gyro = whole.add(samples, t, 2000)
    assert len(stored_t) == 100 and np.array_equal(stored_t, t[:1600:16])
    expected = samples["gyro"][:1600].astype(np.float64).reshape(100, 16, 3).mean(axis=1)
    assert np.allclose(stored_gyro, expected, rtol=1e-12)
    batched = SessionBuilder()
    for a, b in zip([0, 7, 30, 1000, 1601], [7, 30, 1000, 1601, 1605]):
        batched.add(samples[a:b], t[a:b], 2000)
    for name, values in whole.arrays().items():
        assert np.array_equal(values, batched.arrays()[name]), name
    d = whole.arrays()
    assert np.allclose(d["gyro"], expected * DEG, rtol=1e-6)  # float32 storage: 1e-7 relative
    assert np.allclose(d["acc"][:, 2], samples["acc"][:1600, 2].reshape(100, 16).mean(axis=1) * STANDARD_GRAVITY,
                       rtol=1e-6)
    assert np.allclose(d["temp"], samples["temp_gyro"][:1600].mean(axis=1).reshape(100, 16).mean(axis=1))
    assert whole._values[0].dtype == np.float32


def test_faults_are_counted_per_sample_from_a_start():
    samples, t = samples_2000hz(3200)
    samples["status_acc"][[10, 2000, 2001]] = 0x01
    samples["status_gyro"][3000] = 0x02
    builder = SessionBuilder()
    builder.add(samples, t, 2000)
    assert builder.fault_summary() == (4, 0x03)
    assert builder.fault_summary(t[2000]) == (3, 0x03)
    builder.trim(t[2500])  # trimming forgets the flags before, not after
    assert builder.fault_summary() == (1, 0x02)


def test_a_2000_hz_capture_makes_a_125_hz_session():
    """Decoded block by block into 16-sample means, the same as averaging every decoded sample."""
    samples = decode_capture(FIXTURE_2000HZ.read_bytes()).samples
    capture = open_capture(str(FIXTURE_2000HZ))
    assert capture.rate_hz == 2000
    session = power_up_session(capture)
    assert session.rate_hz == STORE_RATE_HZ
    assert np.allclose(np.diff(session.time_s), 1 / STORE_RATE_HZ)
    assert len(session.time_s) == len(samples) // 16
    means = samples["gyro"][:len(samples) // 16 * 16].astype(np.float64).reshape(-1, 16, 3).mean(axis=1) * DEG
    assert np.allclose(session.gyro, means, rtol=1e-6, atol=1e-9)  # float32: 1e-10 rad/s at 1e-3 rad/s
    assert session.stream.power_up.duration_s == len(samples) / 2000


def _lengths(pieces):
    return [(new, len(piece)) for new, piece in pieces]


def test_power_ups_are_cut_where_the_parser_saw_a_restart_or_the_start_up_bit_comes_on():
    """One rule for captures and live batches: a restart position inside a batch or at its first
    sample cuts it; so does the start-up bit coming on after samples without it (power-up
    datagrams lost); both at one sample are one cut; the new power-up's own bit is no second."""
    samples = np.zeros(100, SAMPLE_DTYPE)
    samples["status_gyro"][:10] = Status.START_UP  # the first power-up's start-up: no cut
    samples["status_gyro"][40:50] = Status.START_UP  # a restart the parser saw at 40
    samples["status_gyro"][70:80] = Status.START_UP  # one only the status bit tells
    cuts = PowerUpCuts()
    assert _lengths(cuts.pieces(samples[:60], 0, (40,))) == [(False, 40), (True, 20)]
    assert _lengths(cuts.pieces(samples[60:], 60, (40,))) == [(False, 10), (True, 30)]
    at_batch_start = PowerUpCuts()
    at_batch_start.pieces(samples[20:40], 20, ())
    assert _lengths(at_batch_start.pieces(samples[40:60], 40, (40,))) == [(True, 20)]
    assert _lengths(at_batch_start.pieces(samples[:0], 60, (40,))) == []


def test_a_stored_temperature_is_the_mean_of_the_gyro_temperatures_there():
    """All three gyro temperatures: their mean; some missing: the mean of the rest; none: NaN."""
    samples, t = samples_2000hz(48)
    samples["temp_gyro"][16:32, 1] = np.nan
    builder = SessionBuilder()
    builder.add(samples, t, 2000)
    temp = samples["temp_gyro"].astype(np.float64)
    expected = [temp[:16].mean(), temp[16:32][:, [0, 2]].mean(), temp[32:].mean()]
    assert np.allclose(builder.arrays()["temp"], expected, rtol=1e-6)
    samples["temp_gyro"] = np.nan
    none = SessionBuilder()
    none.add(samples, t, 2000)
    assert np.isnan(none.arrays()["temp"]).all()


def test_a_decoded_capture_knows_its_size_and_sha256(tmp_path):
    """The identity a report or apply checks a capture against is the file's, hashed as decoded."""
    import hashlib

    from calibd.captures import open_capture

    path = "fixtures/thesis_real_cw_125hz.bin"
    data = open(path, "rb").read()
    decoded = open_capture(path)
    assert decoded.identity == {"size_bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    copy = tmp_path / "one_byte_less.bin"
    copy.write_bytes(data[:-1])
    assert open_capture(str(copy)).identity["sha256"] != decoded.identity["sha256"]

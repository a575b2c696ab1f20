"""A capture's session without copies, and the segmentation and the joint fit block by block: the
same results as whole float64 arrays in one pass (docs/architecture.md, Long captures in bounded
memory)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from calibd import detect
from calibd.captures import open_capture
from calibd.estimators import joint
from calibd.frames import Site
from calibd.methods.joint import joint_fit
from calibd.segments import session_segments
from calibd.session import SessionBuilder, power_up_session
from stim300.codec import SAMPLE_DTYPE

FIXTURE = Path(__file__).resolve().parent.parent / "fixtures" / "thesis_real_cw_125hz.bin"
SITE = Site(40.59129, g0=9.79956)


@pytest.fixture(scope="module")
def session():
    return power_up_session(open_capture(str(FIXTURE)))


def float64_copy(session):
    """The session as float64 arrays of its own, as the daemon's sessions are."""
    return replace(session, gyro=session.gyro.astype(np.float64), acc=session.acc.astype(np.float64),
                   incl=session.incl.astype(np.float64))


def test_a_builders_times_are_not_views_of_its_batch_means():
    """A batch's times kept as a column of its 11-column means would keep all of them (88 B a
    sample more); the stored values are float32 and the times their own arrays."""
    samples = np.zeros(1000, SAMPLE_DTYPE)
    samples["acc"][:, 2] = 1.0
    builder = SessionBuilder()
    builder.add(samples, np.arange(1000) / 125.0, 125)
    time_s, values = builder.stored()
    assert time_s.base is None and values.dtype == np.float32 and values.shape == (1000, 10)


def test_a_capture_session_is_the_stored_means_not_a_copy(session):
    capture = open_capture(str(FIXTURE))
    whole = power_up_session(capture)
    _, values = capture.power_ups[-1].data.stored()
    assert np.shares_memory(whole.gyro, values) and np.shares_memory(whole.acc, values)
    assert whole.gyro.dtype == np.float32 and whole.time_s.dtype == np.float64
    assert np.array_equal(whole.gyro, session.gyro) and len(whole.gyro) > 100_000


@pytest.mark.slow
def test_float32_views_fit_as_float64_copies(session):
    """Every sum over the samples takes them to float64 first: the fit of the float32 views is
    that of their float64 copies."""
    views, copies = (joint_fit(s, SITE).fit for s in (session, float64_copy(session)))
    for name, value in views.estimates.items():
        sigma = views.sigmas[name]
        assert abs(value - copies.estimates[name]) < 1e-9 * sigma, name
        assert abs(sigma - copies.sigmas[name]) < 1e-9 * sigma, name


@pytest.mark.slow
def test_blocks_of_any_length_give_the_same_fit(session, monkeypatch):
    """Blocks that split statics, flicker bins and turns at odd places: the sums and the
    covariance add up to the same fit (to rounding)."""
    whole = joint_fit(session, SITE).fit
    monkeypatch.setattr(joint, "BLOCK", 7919)
    blocks = joint_fit(session, SITE).fit
    assert len(session.time_s) > 10 * 7919
    for name, value in whole.estimates.items():
        sigma = whole.sigmas[name]
        assert abs(value - blocks.estimates[name]) < 1e-8 * sigma, name
        assert abs(sigma - blocks.sigmas[name]) < 1e-8 * sigma, name


def test_segments_do_not_depend_on_the_block_length(session, monkeypatch):
    whole = session_segments(session)
    monkeypatch.setattr(detect, "BLOCK", 1009)
    assert session_segments(session) == whole and len(whole) > 5

"""The bench campaign's six positions see the accelerometers' and inclinometers' factory error:
scale factors and the misalignment of each axis to the housing (the faces it is mounted on),
recovered exactly from exact data and within their sigma from a simulated capture, and taken
out by every corrected output (calibd.correction.estimated_maps)."""

from dataclasses import replace

import numpy as np
import pytest

from calibd import spec
from calibd.correction import estimated_maps
from calibd.estimators.sixpos import fit_six_positions
from calibd.frames import MOUNTS, STANDARD_GRAVITY
from calibd.methods.bench import thesis_bench
from calibd.scenario import load_scenario
from calibd.session import Session
from calibd.sim import simulate
from calibd.units import DEG
from stim300.records import SensorRecord
from calibd.results import ResultStream

BENCH = load_scenario("thesis-bench")
RESIDUALS = dict(acc_scale_ppm=(120.0, -80.0, 150.0), acc_misalignment_mrad=(0.4, -0.3, 0.2, 0.6, -0.5, 0.1),
                 incl_scale_ppm=(300.0, -200.0, 100.0), incl_misalignment_mrad=(0.3, 0.2, -0.4, 0.1, 0.5, -0.6))


def test_exact_means_give_the_error_exactly():
    error = spec.triad_error(RESIDUALS["acc_scale_ppm"], RESIDUALS["acc_misalignment_mrad"])
    v = 9.8 * np.array([0.01, -0.02, np.sqrt(1 - 0.01**2 - 0.02**2)])  # a degree-ish off Z
    bias = np.array([1e-3, -2e-3, 5e-4])
    means = {up: (np.eye(3) + error) @ m @ v + bias for up, m in MOUNTS.items()}
    fit = fit_six_positions(means, {up: np.full(3, 1e-10) for up in MOUNTS}, 9.8)
    np.testing.assert_allclose(fit.error, error, atol=1e-10)
    np.testing.assert_allclose(fit.bias, bias, atol=1e-9)
    np.testing.assert_allclose(fit.force, v, atol=1e-9)


@pytest.mark.slow
def test_a_simulated_bench_recovers_the_force_triads_terms_within_their_sigma():
    truth = replace(BENCH.truth, **RESIDUALS)
    sim = simulate(replace(BENCH, truth=truth))
    s, rate = sim.samples, BENCH.sensor.sample_rate_hz
    session = Session(time_s=np.arange(len(s)) / rate, gyro=s["gyro"].astype(float) * DEG,
                      acc=s["acc"].astype(float) * STANDARD_GRAVITY, incl=s["incl"].astype(float) * STANDARD_GRAVITY,
                      temperature_c=None, rate_hz=rate, sensor=SensorRecord(), stream=ResultStream(capture="simulated"))
    result = thesis_bench(session, BENCH.site)
    terms = result.error_budget["factory_residuals"]["terms"]
    z = []
    for name, term in terms.items():
        element = spec.FactoryTerm.named(name)
        true = truth.triad_error(element.sensor)[element.row, element.col] * element.to_unit
        z.append((term["value"] - true) / term["sigma"])
        assert term["sigma"] < term["prior_sigma"], name  # the data, not the datasheet, set it
    z = np.array(z)
    assert len(z) == 18 and np.all(np.abs(z) < 3) and np.sqrt(np.mean(z**2)) < 1.5
    acc = {n: t for n, t in terms.items() if n.startswith("acc")}
    assert all(t["source"] == "estimated" and t["sigma"] < 0.1 * t["prior_sigma"] for t in acc.values())
    # the corrected outputs take the accelerometers' error out: (I + E)^-1 within its sigma
    residual = estimated_maps(result)["acc"] @ (np.eye(3) + truth.triad_error("acc")) - np.eye(3)
    worst_sigma = max(t["sigma"] / spec.FactoryTerm.named(n).to_unit for n, t in acc.items())
    assert np.abs(residual).max() < 3 * worst_sigma

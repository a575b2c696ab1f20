"""A slow temperature ramp (the room warming during the campaign): the joint fit's budget carries
the biases' slope with temperature at the datasheet's figure, a ramp moves the estimates as the
budget predicts, and a power-up that never settles is flagged only where the ramp matters (a
ramp within RAMP_MODELLED_C_PER_H) or everywhere (a faster one: still warming up)."""

from dataclasses import replace

import numpy as np
import pytest

from calibd import spec
from calibd.calibrate import judged_by_temperature
from calibd.estimators import joint
from calibd.frames import STANDARD_GRAVITY
from calibd.methods.joint import joint_real_case
from calibd.scenario import load_scenario
from calibd.sim import simulate
from calibd.units import DEG
from calibd.warmup import NOT_WARMED_UP, RAMP_MODELLED_C_PER_H, record_settling
from test_factory import session_of
from test_joint import exact_input

THESIS = load_scenario("thesis-real")
SETTLED = replace(THESIS.warmup, power_on_s=1e7)  # the warm-up long over: only the ramp moves the temperature
TEMPCO = {"gyro": spec.GYRO.bias_temperature_sigma, "acc": spec.ACC[10].bias_temperature_sigma,
          "incl": spec.INCL.bias_temperature_sigma}  # deg/h/degC, mg/degC: the prior's 1-sigma


def ramped(ramp_c_per_h: float, gyro=(0.0, 0.0, 0.0), acc=(0.0, 0.0, 0.0), incl=(0.0, 0.0, 0.0), noise=False,
           seed=THESIS.seed):
    warmup = replace(SETTLED, ramp_c_per_h=ramp_c_per_h, gyro_tempco_deg_h_per_c=gyro, acc_tempco_mg_per_c=acc,
                     incl_tempco_mg_per_c=incl)
    return simulate(replace(THESIS, seed=seed, warmup=warmup, noise=replace(THESIS.noise, enabled=noise)))


def with_temperature(sim) -> joint.JointInput:
    inp = exact_input(sim)
    return replace(inp, temperature_c=sim.temperature_c[len(sim.temperature_c) - len(inp.time_s):])


def test_the_temperature_prior_is_the_datasheet_figure_over_the_operating_range():
    # 10 deg/h rms over -40..+85 degC as a straight line: slope x 125 / sqrt(12) = 10 deg/h
    assert spec.GYRO.bias_temperature_sigma * 125 / np.sqrt(12) == pytest.approx(10.0)
    assert spec.ACC[30].bias_temperature_sigma * 125 / np.sqrt(12) == pytest.approx(1.5)


@pytest.mark.slow  # four noisy 19-minute sessions simulated and solved
def test_a_ramp_moves_the_estimates_as_the_temperature_budget_predicts():
    ramp = 2.0  # with noise, the same draws in both: the fit's weights come from the statics' noise, as on a unit
    flat = ramped(ramp, noise=True)
    base = joint.solve(with_temperature(flat), THESIS.site)
    names = list(base.estimates)
    assert "temperature" in base.budget
    # each channel's column: its slope at 1 sigma; the gyro Y and accelerometer X at that slope
    tilted = ramped(ramp, gyro=(0.0, TEMPCO["gyro"], 0.0), acc=(TEMPCO["acc"], 0.0, 0.0), noise=True)
    fit = joint.solve(with_temperature(tilted), THESIS.site)
    effects = joint.temperature_effects(with_temperature(flat), THESIS.site, joint.JointOptions(), base.gyro,
                                        base.incl, base.acc, base.tilt_from_incl).estimates
    predicted = effects[:, 1] + effects[:, 6 + 0]  # gyro Y; acc X (after gyro XYZ and incl XYZ)
    excursion_mean = (flat.temperature_c[-len(with_temperature(flat).time_s):] - SETTLED.settled_c).mean()
    moved = np.array([fit.estimates[n] - base.estimates[n] for n in names])
    # the biases also move by their slope times the mean excursion: the bias at the mean temperature
    moved[names.index("gyro_bias_y")] -= TEMPCO["gyro"] * excursion_mean / 3600 * DEG
    moved[names.index("acc_bias_x")] -= TEMPCO["acc"] * excursion_mean * STANDARD_GRAVITY / 1000
    for name in ("yaw", "gyro_bias_y", "acc_bias_x"):
        k = names.index(name)
        assert abs(predicted[k]) > 0, name
        assert moved[k] == pytest.approx(predicted[k], rel=0.05), name
    # the budget's part is the sum of the columns' squares
    assert np.allclose(base.budget["temperature"], effects @ effects.T)


def test_without_temperatures_the_budget_has_no_temperature_part():
    fit = joint.solve(exact_input(ramped(2.0)), THESIS.site)
    assert "temperature" not in fit.budget


@pytest.mark.slow
@pytest.mark.parametrize("ramp, all_poor", [(1.6, False), (-1.6, False), (3.0, True)])
def test_a_ramp_within_the_modelled_rate_keeps_its_estimates_a_faster_one_flags_them(ramp, all_poor):
    sim = ramped(ramp, gyro=tuple(TEMPCO["gyro"] * s for s in (1, -1, 1)),
                 acc=tuple(TEMPCO["acc"] * s for s in (-1, 1, 1)), incl=tuple(TEMPCO["incl"] * s for s in (1, 1, -1)),
                 noise=True, seed=31)
    session = replace(session_of(sim), temperature_c=sim.temperature_c)
    verdict = record_settling(session.time_s, session.temperature_c)
    assert not verdict.settled and abs(verdict.trend_c_per_h) == pytest.approx(abs(ramp), rel=0.05)
    result = judged_by_temperature(joint_real_case(session, THESIS.site), verdict)
    poor = [n for n, e in result.estimates.items() if e.quality == "poor"]
    if all_poor:
        assert len(poor) == len(result.estimates) and NOT_WARMED_UP in result.warnings
        return
    assert abs(ramp) <= RAMP_MODELLED_C_PER_H
    assert poor == [] and NOT_WARMED_UP not in result.warnings
    assert any(f"ramps at {ramp:+.1f} degC/h" in w for w in result.warnings)
    # the turn-on bias: the settled one moved by its slope times the session's mean excursion
    excess = (sim.temperature_c - SETTLED.settled_c).mean()
    warmup = sim.scenario.warmup
    truth = THESIS.truth.estimates()
    for sensor, settled, tempco in (("gyro", THESIS.truth.gyro_bias_deg_h, warmup.gyro_tempco_deg_h_per_c),
                                    ("acc", THESIS.truth.acc_bias_mg, warmup.acc_tempco_mg_per_c),
                                    ("incl", THESIS.truth.incl_bias_mg, warmup.incl_tempco_mg_per_c)):
        truth |= {f"{sensor}_bias_{a}": b + c * excess for a, b, c in zip("xyz", settled, tempco)}
    for name, e in result.estimates.items():
        error = (e.value - truth[name] + 180) % 360 - 180 if name == "yaw" else e.value - truth[name]
        assert abs(error) < 3 * e.sigma, (name, error, e.sigma)
        parts = result.error_budget["sigma"][name]
        assert parts["temperature"] > 0
        assert sum(v**2 for v in parts.values()) == pytest.approx(e.sigma**2, rel=1e-4)  # the parts add up

"""Datagram losses the counter cannot see, found and corrected from the data itself.

The datagram counter repeats every 256 internal samples (0.128 s): a loss of a whole number of
cycles during a turn shortens the time base unseen, and the gyro-integrated platform angle chi
of every later static is short by the angle turned in the lost time (2.6 deg for one cycle at
20 deg/s). The accelerometers and inclinometers see the platform angle independently: in a
static at angle chi they read f = g0 A R3(chi) u + b, and the platform axis's tilt u turns with
chi. Fitting the statics' mean forces with one free angle correction per turn (the motion
between two statics) tells, for each turn, the angle the tilt saw it add beyond what the gyros
integrated. A correction many sigma from zero is a loss; the joint fit is then redone with the
corrected angles. The precision is the static means' noise over the tilt g0 |u_h|: a tenth of
a degree for a tilt of 0.5 deg; a platform axis within a few hundredths of a degree of Up
leaves the angles unchecked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .estimators.joint import (FactoryEffects, FactoryPosterior, JointInput, NoiseModel, TemperatureEffects, turn_ramps,
                               Underdetermined, alpha_beta, mean_variance, static_inflation)
from .allan import FLICKER_TAUS_S
from .frames import int_to_imu, r3

FOUND_SIGMAS = 4.0  # a correction this many sigma from zero is a loss (5 turns: 3e-4 false alarms a session)
CHECKABLE_SIGMA_RAD = np.radians(1.0)  # a turn pinned less well than this is not checked
MIN_HEADINGS = 3  # statics at fewer distinct headings cannot tell a turn's angle from the tilt
HEADING_SEPARATION_RAD = np.radians(30.0)  # statics closer in heading (mod 360 deg) share one


def distinct_headings(static_chi: np.ndarray) -> int:
    """How many headings (platform angles mod 360 deg, HEADING_SEPARATION_RAD apart) the statics
    cover. Each heading adds one tilt direction; the tilt (2 unknowns) and one angle per turn are
    determined only from three on: at two headings one difference vector fits any angle."""
    headings = np.sort(np.mod(static_chi, 2 * np.pi))
    steps = np.diff(np.concatenate((headings, [headings[0] + 2 * np.pi])))
    return max(1, int(np.count_nonzero(steps > HEADING_SEPARATION_RAD)))


@dataclass(frozen=True)
class TurnAngle:
    """The motion between two statics [stop of the one before, start of the one after) in
    fit-input samples, and the angle the tilt saw it turn beyond the gyros' integral."""

    start: int
    stop: int
    gyro_rad: float  # chi after minus chi before, from the gyros
    correction_rad: float  # tilt minus gyros
    sigma_rad: float

    @property
    def checkable(self) -> bool:
        return bool(self.sigma_rad <= CHECKABLE_SIGMA_RAD)

    @property
    def found(self) -> bool:
        return self.checkable and bool(abs(self.correction_rad) > FOUND_SIGMAS * self.sigma_rad)


@dataclass(frozen=True)
class TiltCheck:
    """Every turn's angle against the tilt, and the chi-square of the statics' mean forces with
    the gyros' angles (no correction): large when a platform angle or a static is wrong."""

    turns: tuple[TurnAngle, ...]
    chi2: float
    dof: int
    # what the statics' forces say of the factory residuals (`factory_posterior`): each term's
    # value and their covariance, in units of its prior sigma; None without a factory prior
    factory: FactoryPosterior | None = None

    @property
    def p_value(self) -> float:
        from scipy.special import gammaincc  # when used: start-up (docs/architecture.md)
        return float(gammaincc(self.dof / 2, self.chi2 / 2))


# the check's parameter vector: the platform axis's tilt, each force sensor's biases (the
# accelerometers', then the inclinometers' where the unit has them), then one angle correction
# per turn (rad)
TILT = slice(0, 2)


def _corrections_from(sensors: int) -> int:
    return TILT.stop + 3 * sensors


def _model(params: np.ndarray, static_chi: np.ndarray, a: np.ndarray, g0: float, sensors: int) -> np.ndarray:
    """Static mean forces of each sensor, (sensors, S, 3): g0 A R3(chi + corrections so far) u + b."""
    u1, u2 = params[TILT]
    u = np.array([u1, u2, np.sqrt(1.0 - u1**2 - u2**2)])
    chi = static_chi + np.concatenate(([0.0], np.cumsum(params[_corrections_from(sensors):])))
    tilt = g0 * (a @ r3(chi) @ u)  # (S, 3)
    return np.stack([tilt + params[TILT.stop + 3 * k:TILT.stop + 3 * k + 3] for k in range(sensors)])


def check_turn_angles(inp: JointInput, chi: np.ndarray, a: np.ndarray, g0: float,
                      acc_noise: NoiseModel, incl_noise: NoiseModel, u0: np.ndarray,
                      factory: FactoryEffects | None = None, gyro_noise: NoiseModel | None = None,
                      temperature: TemperatureEffects | None = None) -> TiltCheck:
    """Fit (u, b_acc[, b_incl], one angle correction per turn) to the statics' mean forces,
    weighted by the covariance the sensors' noise models give those means (`incl_noise` is
    unused for a unit without inclinometers: `inp.incl` None) and the factory residuals'
    prior (`factory`: how each moves the modelled means; a quiet accelerometer sees a gyro
    scale factor's angle error and the triads' misalignment acting on the turning tilt). `chi`:
    the joint fit's platform angle; `a`: R_int^IMU; `u0`: the joint fit's (u1, u2) to start from.
    `gyro_noise`: the gyros' noise model, whose white noise integrated through the turns puts
    the statics' angles off by a random walk (0.007 deg a 7 s turn): on a platform axis tilted by
    degrees the quiet accelerometers see it. `temperature`: the biases' slope with temperature,
    which moves each static's mean force by the slope times its mean temperature (a 10 g
    accelerometer's 0.03 mg/degC over a 2 degC/h ramp: five times a 120 s static's noise).
    Raises Underdetermined when the statics do not determine the corrections."""
    from scipy.linalg import block_diag  # when used: start-up (docs/architecture.md)
    from scipy.optimize import least_squares
    statics = inp.statics
    static_chi = np.array([chi[s:e].mean() for s, e in statics])
    if distinct_headings(static_chi) < MIN_HEADINGS:
        raise Underdetermined(f"statics at fewer than {MIN_HEADINGS} headings")
    forces = [(inp.acc, acc_noise)] + ([] if inp.incl is None else [(inp.incl, incl_noise)])
    first = _corrections_from(len(forces))
    means = np.stack([[values[s:e].mean(axis=0, dtype=np.float64) for s, e in statics] for values, _ in forces])
    # covariance of the misfit (sensors, statics, channels) flattened: each channel's means as the
    # noise model gives them, and every factory residual's move of them
    noise_cov = block_diag(*[_by_channel(static_means_covariance(noise, inp, static_inflation(values, statics)))
                             for values, noise in forces])
    u = np.array([*u0, np.sqrt(1.0 - u0[0] ** 2 - u0[1] ** 2)])
    if gyro_noise is not None:
        noise_cov = noise_cov + _angle_walk_covariance(inp, static_chi, a, g0, u, len(forces), gyro_noise)
    if temperature is not None:
        moved = temperature_moves(temperature, statics, ("acc", "incl")[:len(forces)])
        noise_cov = noise_cov + moved @ moved.T
    cov, moves = noise_cov, None
    if factory is not None:
        moves = factory_moves(factory, static_chi, a, g0, u, ("acc", "incl")[:len(forces)])
        moves = moves.reshape(len(factory.terms), -1).T  # (means, terms)
        cov = noise_cov + moves @ moves.T
    whiten = np.linalg.inv(np.linalg.cholesky(cov))

    def residuals(params):
        return whiten @ (means - _model(params, static_chi, a, g0, len(forces))).ravel()

    start = np.concatenate([u0, *(m[0] - g0 * a[:, 2] for m in means), np.zeros(len(statics) - 1)])
    null = least_squares(lambda p: residuals(np.concatenate([p, start[first:]])), start[:first],
                         method="lm")  # no corrections: where the free fit starts
    free = least_squares(residuals, np.concatenate([null.x, start[first:]]), method="lm")
    cov = np.linalg.pinv(free.jac.T @ free.jac)
    sigmas = np.sqrt(np.clip(np.diag(cov)[first:], 0.0, None))
    if not np.all(np.isfinite(sigmas)) or np.linalg.matrix_rank(free.jac) < len(free.x):
        sigmas = np.full(len(statics) - 1, np.inf)
    turns = tuple(TurnAngle(statics[k][1], statics[k + 1][0], float(static_chi[k + 1] - static_chi[k]),
                            float(free.x[first:][k]), float(sigmas[k])) for k in range(len(statics) - 1))
    dof = means.size - first
    posterior = None if moves is None else factory_posterior(
        lambda p: _model(np.concatenate([p, start[first:]]), static_chi, a, g0, len(forces)).ravel(),
        null.x, means.ravel(), noise_cov, moves)
    return TiltCheck(turns, float(2 * null.cost), dof, posterior)


def _angle_walk_covariance(inp: JointInput, static_chi: np.ndarray, a: np.ndarray, g0: float, u: np.ndarray,
                           sensors: int, gyro_noise: NoiseModel) -> np.ndarray:
    """Covariance of the statics' modelled mean forces (flattened as the misfit) from the random
    walk of their platform angles: each turn adds its samples' white gyro noise about the axis,
    integrated (chi' is 0 in a static, so only the motion between statics counts), and an angle
    error moves the modelled tilt vector by its derivative."""
    dt = 1.0 / inp.rate_hz
    axis = a[:, 2]
    per_sample = float(axis**2 @ gyro_noise.white) * dt**2  # rad^2 of chi a sample of motion adds
    steps = [per_sample * (inp.statics[k][0] - inp.statics[k - 1][1]) for k in range(1, len(inp.statics))]
    walk = np.cumsum([0.0, *steps])
    angles = np.minimum.outer(walk, walk)  # cov(chi_j, chi_k): the turns they share
    turning = g0 * (a @ r3(static_chi + np.pi / 2) @ np.diag([1.0, 1.0, 0.0]) @ u)  # d/dchi of g0 A R3(chi) u
    derivative = np.zeros((sensors, len(static_chi), 3, len(static_chi)))
    for k in range(len(static_chi)):
        derivative[:, k, :, k] = turning[k]
    flat = derivative.reshape(-1, len(static_chi))
    return flat @ angles @ flat.T


def temperature_moves(temperature: TemperatureEffects, statics: tuple[tuple[int, int], ...],
                      sensors: tuple[str, ...]) -> np.ndarray:
    """(means, channels): each force channel's bias slope at its 1-sigma moves its statics' mean
    forces (laid out as the misfit: sensor, static, channel) by the slope times each static's
    mean temperature excursion. The channels' slopes are independent; the gyros' move the
    statics' angles by micro-radians (they integrate only while turning) and are left out."""
    excursion = np.array([temperature.excursion_c[s:e].mean() for s, e in statics])
    moves = np.zeros((len(sensors), len(statics), 3, 3 * len(sensors)))
    for k, sensor in enumerate(sensors):
        for c in range(3):
            moves[k, :, c, 3 * k + c] = excursion * temperature.per_degree[sensor]
    return moves.reshape(-1, 3 * len(sensors))


def factory_posterior(model, theta: np.ndarray, means: np.ndarray, noise_cov: np.ndarray,
                      moves: np.ndarray) -> FactoryPosterior:
    """The statics' mean forces fitted with the tilt and biases (`theta`, linearised about the
    check's fit) and every factory term (`moves`: the means' move at 1 sigma), the terms' prior
    N(0, I) taken as data: what the forces see of them. On a platform axis near vertical the
    moves scale with the small tilt and the posterior stays near the prior; a tilted axis lets
    the quiet accelerometers see the scale factors and the triads' relative misalignment."""
    steps = 1e-7 * np.maximum(np.abs(theta), 1.0)
    jac = np.column_stack([(model(theta + h * e) - model(theta - h * e)) / (2 * h)
                           for h, e in zip(steps, np.eye(len(theta)))])
    whiten = np.linalg.inv(np.linalg.cholesky(noise_cov))
    design = whiten @ np.hstack([jac, moves])
    info = design.T @ design
    p = len(theta)
    info[p:, p:] += np.eye(moves.shape[1])
    cov = np.linalg.inv(info)
    solution = cov @ (design.T @ (whiten @ (means - model(theta))))
    return FactoryPosterior(solution[p:], cov[p:, p:])


def _by_channel(per_channel: np.ndarray) -> np.ndarray:
    """(3, S, S) covariances of each channel's means -> the covariance of the means laid out
    static by static, channel by channel (independent channels)."""
    s = per_channel.shape[1]
    out = np.zeros((s, 3, s, 3))
    for c in range(3):
        out[:, c, :, c] = per_channel[c]
    return out.reshape(3 * s, 3 * s)


def factory_moves(factory: FactoryEffects, static_chi: np.ndarray, a: np.ndarray, g0: float, u: np.ndarray,
                  sensors: tuple[str, ...]) -> np.ndarray:
    """(terms, sensors, statics, 3): how each factory residual at its 1-sigma moves the statics'
    mean forces away from their model g0 A R3(chi) u: a force triad's error acts on its own
    sensor's tilt vector (the data move); a gyro's moves the platform axis (A) and the statics'
    angles the model takes (the model moves, the data stay: the opposite sign)."""
    tilt = g0 * (a @ r3(static_chi) @ u)  # (S, 3)
    moves = np.zeros((len(factory.terms), len(sensors), len(static_chi), 3))
    for index, term in enumerate(factory.terms):
        if term.sensor == "gyro":
            k, chi = factory.gyro_refits[index]
            moves[index] = tilt - g0 * (int_to_imu(*alpha_beta(k)) @ r3(chi) @ u)
        elif term.sensor in sensors:
            error = np.zeros((3, 3))
            error[term.row, term.col] = term.sigma
            moves[index, sensors.index(term.sensor)] = tilt @ error.T
    return moves


def static_means_covariance(noise: NoiseModel, inp: JointInput, inflation: np.ndarray | None = None) -> np.ndarray:
    """(3, S, S): covariance of each channel's means over the statics: white noise and the flicker's fast
    components as in each mean's own variance, and between statics the part of each flicker
    component that the time between them has not decorrelated (the slow ones are nearly common to
    all statics, and taken as independent they would make every angle look twice as uncertain).
    `inflation`: each static's white noise over the model's (a vibrating static's,
    `joint.static_inflation`; default 1)."""
    start_s = np.array([inp.time_s[s] for s, _ in inp.statics])
    end_s = np.array([inp.time_s[e - 1] for _, e in inp.statics]) + 1.0 / inp.rate_hz
    length_s = end_s - start_s
    gap_s = np.maximum(start_s[None, :] - end_s[:, None], start_s[:, None] - end_s[None, :])
    common = np.zeros((len(inp.statics), len(inp.statics)))
    for corr_s in FLICKER_TAUS_S[:4]:
        decay = corr_s / length_s * (1 - np.exp(-length_s / corr_s))
        common += np.outer(decay, decay) * np.exp(-np.clip(gap_s, 0.0, None) / corr_s)
    inflation = np.ones(len(inp.statics)) if inflation is None else inflation
    own = np.array([mean_variance(noise, e - s, inp.rate_hz, f) for (s, e), f in zip(inp.statics, inflation)])
    cov = noise.flicker[:, None, None] * common
    for c in range(3):
        np.fill_diagonal(cov[c], own[:, c])
    return cov


def chi_correction(inp: JointInput, chi: np.ndarray, turns: list[TurnAngle]) -> np.ndarray:
    """Per sample, the platform angle the `turns` add beyond the gyros' integral: nothing before
    a turn, all of it after, and in proportion to the angle turned in between (where in the turn
    the datagrams went is not known)."""
    added = np.zeros(len(inp.statics) - 1)
    for turn in turns:
        added[next(k for k in range(len(added)) if inp.statics[k][1] == turn.start)] += turn.correction_rad
    return turn_ramps(inp, chi, added)

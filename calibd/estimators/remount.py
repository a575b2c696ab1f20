"""Two mountings of one unit: the campaign run once, the housing turned 180 deg about its own Z
axis on the platform's interface, and the campaign run again (docs/method.md, A second mounting).

The platform axis in the housing's axes, written as the tilt tau = (k_x, k_y) / k_z, turns with
the housing: the second mounting's is exactly minus the first's. The gyro triad's misalignment to
the housing does not turn (it is the sensor's), so it adds the same to both: the sum of the two
tilts the gyros show is the factory residuals' doing alone, twice. That sum measures the terms
that tilt the gyro-derived axis (gyro_misalignment_xz and _yz) to the noise of two fits, and
alpha, beta, pitch and roll, which they moved, lose their share of the prior.

The estimate is linear and Gaussian (the residuals are a part in a thousand): the first
mounting's estimates x_A = theta + F_A z + n_A (F the factory effects, z the terms over their prior
sigma, n the noise of every other budget part), the sum s = G_A x_A + G_B x_B = H z + G_A n_A +
G_B n_B (G the tilt's Jacobian; H = G_A F_A + G_B F_B) with the prior of z what both mountings'
statics saw of it. Taking F_A z_hat off x_A takes part of n_A with it, so each budget part of the
answer is that part carried through the whole estimate, not the old part plus the new term's:
their sum is the answer's covariance exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..frames import int_to_imu
from .joint import FactoryPosterior, JointResult

REMOUNT_PART = "remounting"  # the budget part of the re-mounting's own error (its turn's distance from 180 deg)


@dataclass(frozen=True)
class Remounting:
    """What the two mountings' tilts said: their sum against what the factory residuals predict."""

    tilt_sum: np.ndarray  # (2,) rad: tau_A + tau_B as the gyros show them
    predicted: np.ndarray  # (2,) rad: what the residuals' prior (both mountings' statics) expects of it
    cov: np.ndarray  # (2, 2) rad^2: of the sum about the prediction (prior and noise)
    chi2: float  # of the sum against the prediction, 2 degrees of freedom
    second: dict[str, float]  # the second mounting's alpha and beta as its own fit gave them, rad

    @property
    def p_value(self) -> float:
        """P(chi-square of 2 degrees of freedom >= chi2): exp(-chi2 / 2)."""
        return float(np.exp(-self.chi2 / 2))


def tilt(alpha: float, beta: float) -> np.ndarray:
    """tau = (k_x, k_y) / k_z of the platform axis k = R_int^IMU [0, 0, 1]."""
    k = int_to_imu(alpha, beta)[:, 2]
    return k[:2] / k[2]


def tilt_jacobian(alpha: float, beta: float) -> np.ndarray:
    """d tau / d (alpha, beta)."""
    return np.array([[-np.tan(beta) * np.sin(alpha) / np.cos(alpha) ** 2, -1 / (np.cos(beta) ** 2 * np.cos(alpha))],
                     [1 / np.cos(alpha) ** 2, 0.0]])


@dataclass(frozen=True)
class _Mounting:
    """One mounting's fit, undone from its statics' posterior: the estimates as the model with
    E = 0 gave them, the factory effects, and the covariance of every other budget part."""

    names: list[str]
    raw: np.ndarray  # (n,) SI
    effects: np.ndarray  # (n, terms) SI per 1-sigma of each term
    noise: dict[str, np.ndarray]  # budget part -> (n, n), every part but the factory residuals
    posterior: FactoryPosterior  # what its statics (and stops) saw of the terms
    tilt: np.ndarray  # (2,) tau of the raw alpha, beta
    jacobian: np.ndarray  # (2, n) d tau / d estimates

    @classmethod
    def of(cls, fit: JointResult) -> _Mounting:
        if fit.factory is None:
            raise ValueError("two mountings need the factory residuals' prior in the fits")
        names = list(fit.estimates)
        terms = len(fit.factory.terms)
        posterior = fit.factory.posterior or FactoryPosterior(np.zeros(terms), np.eye(terms))
        raw = np.array(list(fit.estimates.values())) + fit.factory.estimates @ posterior.z
        i, j = names.index("alpha"), names.index("beta")
        jacobian = np.zeros((2, len(names)))
        jacobian[:, [i, j]] = tilt_jacobian(raw[i], raw[j])
        return cls(names, raw, fit.factory.estimates, {p: c for p, c in fit.budget.items() if p != "factory_residuals"},
                   posterior, tilt(raw[i], raw[j]), jacobian)


def _both(a: FactoryPosterior, b: FactoryPosterior) -> FactoryPosterior:
    """What two independent sets of data said of the terms, each from the prior N(0, I): their
    information added, the prior's counted once."""
    info_a, info_b = np.linalg.inv(a.cov), np.linalg.inv(b.cov)
    cov = np.linalg.inv(info_a + info_b - np.eye(len(a.z)))
    cov = (cov + cov.T) / 2
    return FactoryPosterior(cov @ (info_a @ a.z + info_b @ b.z), cov)


def two_mountings(first: JointResult, second: JointResult, remount_sigma: float) -> tuple[JointResult, Remounting]:
    """The first mounting's fit with the factory terms the two mountings' tilts show taken out,
    and the budget carried through (module docstring). `remount_sigma`: rad, the 1-sigma of the
    re-mounting's turn about 180 deg (it turns the tilt, so it enters as |tau| times it)."""
    a, b = _Mounting.of(first), _Mounting.of(second)
    if a.names != b.names or first.factory.terms != second.factory.terms:
        raise ValueError("the two mountings' fits estimate different things")
    prior = _both(a.posterior, b.posterior)
    h = a.jacobian @ a.effects + b.jacobian @ b.effects
    turned = np.array([-a.tilt[1], a.tilt[0]])  # d tau_B / d (the turn about 180 deg)
    parts = sorted(set(a.noise) | set(b.noise))
    zero = np.zeros((len(a.names), len(a.names)))
    noise = sum(a.jacobian @ a.noise.get(p, zero) @ a.jacobian.T + b.jacobian @ b.noise.get(p, zero) @ b.jacobian.T
                for p in parts) + remount_sigma**2 * np.outer(turned, turned)
    predicted = h @ prior.z
    spread = h @ prior.cov @ h.T + noise
    gain = prior.cov @ h.T @ np.linalg.inv(spread)
    total = a.tilt + b.tilt
    z = prior.z + gain @ (total - predicted)
    kept = np.eye(len(z)) - gain @ h
    left = kept @ prior.cov @ kept.T  # the prior's share of the terms' covariance after the sum
    after = left + gain @ noise @ gain.T
    posterior = FactoryPosterior(z, (after + after.T) / 2)
    carried = np.eye(len(a.names)) - a.effects @ gain @ a.jacobian  # how the first mounting's noise reaches the answer
    through = a.effects @ gain  # how the sum's noise reaches it
    budget = {p: carried @ a.noise.get(p, zero) @ carried.T + through @ b.jacobian @ b.noise.get(p, zero)
              @ b.jacobian.T @ through.T for p in parts}
    budget[REMOUNT_PART] = remount_sigma**2 * np.outer(through @ turned, through @ turned)
    budget["factory_residuals"] = a.effects @ left @ a.effects.T
    estimates = dict(zip(a.names, (a.raw - a.effects @ z).tolist()))
    residual = total - predicted
    check = Remounting(total, predicted, spread, float(residual @ np.linalg.solve(spread, residual)),
                       {"alpha": second.estimates["alpha"], "beta": second.estimates["beta"]})
    return replace(first, estimates=estimates, budget=budget,
                   factory=replace(first.factory, posterior=posterior)), check

"""A force triad's factory error from six static positions (the bench campaign: the IMU re-mounted
with each of its axes up in turn): f_k = (I + E) M_k v + b.

M_k is the k-th mounting (the housing turned so that the named axis is up), v the specific
force in the housing's axes as first mounted (gravity, a little off its Z axis by the platform's
tilt and the mounting's), E the triad's scale factors (diagonal) and its axes' misalignment to
the housing (off-diagonal), b its bias. The mountings turn the same v onto every axis, so
eighteen means pin E's nine elements, b and v's direction; v's length is g0 (a common scale of E
would trade with it otherwise). The faces of the housing define the housing's axes, so the
misalignment to them is seen here, which no turn about one axis shows. The fixture is taken as
exact: its own error enters the misalignments one for one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import spec
from ..frames import MOUNTS
ITERATIONS = 5  # Gauss-Newton from E = 0: the products E M v are a part in a thousand of the means


@dataclass(frozen=True)
class SixPosition:
    """The fit: E (3 x 3, dimensionless), b (SI), v (the specific force as first mounted, SI), and
    the covariance of E's nine elements (row-major), each of b, v's two free components."""

    error: np.ndarray
    bias: np.ndarray
    force: np.ndarray
    covariance: np.ndarray  # (14, 14): E (9, row-major), b (3), v's tilt (2)

    def term_sigma(self, term: spec.FactoryTerm) -> float:
        """A factory term's 1-sigma from the fit (dimensionless)."""
        k = 3 * term.row + term.col
        return float(np.sqrt(self.covariance[k, k]))


def _tilted(g0: float, tilt: np.ndarray) -> np.ndarray:
    """v of length g0 with X and Y components `tilt` (SI)."""
    return np.array([tilt[0], tilt[1], np.sqrt(g0**2 - tilt[0] ** 2 - tilt[1] ** 2)])


def _model(params: np.ndarray, g0: float, ups: list[str]) -> np.ndarray:
    error, bias, tilt = params[:9].reshape(3, 3), params[9:12], params[12:14]
    v = _tilted(g0, tilt)
    return np.concatenate([(np.eye(3) + error) @ MOUNTS[up] @ v + bias for up in ups])


def fit_six_positions(means: dict[str, np.ndarray], variances: dict[str, np.ndarray], g0: float) -> SixPosition:
    """E, b and v from each position's mean force (SI, by "+X" .. "-Z") and the variance of each
    channel's mean (SI^2): weighted least squares, linearised at the fixed point."""
    ups = list(MOUNTS)
    data = np.concatenate([means[up] for up in ups])
    weights = 1.0 / np.sqrt(np.concatenate([variances[up] for up in ups]))
    params = np.zeros(14)
    params[12:14] = means["+Z"][:2]  # v's tilt as the first mounting reads it
    for _ in range(ITERATIONS):
        jac = _jacobian(params, g0, ups)
        step = np.linalg.lstsq(jac * weights[:, None], (data - _model(params, g0, ups)) * weights, rcond=None)[0]
        params = params + step
    jac = _jacobian(params, g0, ups) * weights[:, None]
    covariance = np.linalg.inv(jac.T @ jac)
    return SixPosition(params[:9].reshape(3, 3), params[9:12], _tilted(g0, params[12:14]), covariance)


def _jacobian(params: np.ndarray, g0: float, ups: list[str]) -> np.ndarray:
    columns = []
    for i in range(len(params)):
        h = 1e-9 if i < 9 else 1e-6
        up, down = params.copy(), params.copy()
        up[i] += h
        down[i] -= h
        columns.append((_model(up, g0, ups) - _model(down, g0, ups)) / (2 * h))
    return np.column_stack(columns)

"""The STIM300's specification: every datasheet figure calibd uses, in one place.

Source: Safran Sensing Technologies, STIM300 datasheet TS1524 rev.31 (February 2024), section
5.2 (functional specifications): Table 5-3 (gyros), Tables 5-4 to 5-7 (accelerometers of the
5, 10, 30 and 80 g ranges), Table 5-8 (inclinometers); section 7.5.2.3 (bias trim). The noise
defaults of a simulated or planned sensor, the floors of the fitted noise, the vibration check,
the simulator's factory residuals and the joint estimator's error budget all read these figures;
no other module holds a copy. Figures marked as limits (+-) are taken as about 2 sigma of a
unit drawn from production (`Triad.scale_factor_sigma_ppm`, `misalignment_sigma_mrad`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DATASHEET = "STIM300 datasheet TS1524 rev.31"
SPECIFICATIONS = f"{DATASHEET}, section 5.2"  # the functional specifications' tables
LIMIT_SIGMAS = 2.0  # a datasheet limit (+-) taken as this many sigma of the production spread
ACC_RANGES_G = (5, 10, 30, 80)
GYRO_RANGE_DEG_S = 400.0  # the gyros' input range, +- (Table 5-3)
INCL_RANGE_G = 1.7  # the inclinometers' input range, +- (Table 5-8)
DEFAULT_ACC_RANGE_G = 10
OPERATING_TEMPERATURE_C = (-40.0, 85.0)  # Table 5-1
# At +-1 g the inclinometers' bias instability and velocity random walk are typically 35 % higher
# than at 0 g (Table 5-8, notes): an axis along gravity is noisier than a horizontal one.
INCL_NOISE_AT_1G = 1.35


@dataclass(frozen=True)
class Triad:
    """One sensor triad's datasheet figures (SI-free: the units the datasheet states)."""

    table: str  # where in the datasheet
    random_walk: float  # gyro: deg/sqrt(h) (ARW); accelerometer, inclinometer: m/s/sqrt(h) (VRW)
    bias_instability: float  # minimum of the Allan deviation: gyro deg/h, others mg
    scale_factor_ppm: float  # scale-factor accuracy, +- limit
    misalignment_mrad: float  # each sensing axis to the housing's reference, +- limit
    orthogonality_mrad: float  # between the triad's own axes, +- limit
    bias_trim_range: float  # +- range of the bias trim offset: gyro deg/s, others g (section 7.5.2.3)
    bias_over_temperature: float  # bias error over the temperature range, rms: gyro deg/h, others mg
    bias_run_to_run: float | None  # from one power-up to the next (gyro deg/h); None: not stated
    bias_one_year: float | None  # bias stability over a year (accelerometer mg); None: not stated

    @property
    def scale_factor_sigma_ppm(self) -> float:
        return self.scale_factor_ppm / LIMIT_SIGMAS

    @property
    def bias_temperature_sigma(self) -> float:
        """1-sigma of the bias's slope with temperature (gyro deg/h/degC, others mg/degC): the
        bias error over temperature, an rms over the operating range, taken as a straight line
        across it (a line over a span L has an rms of its slope times L/sqrt(12))."""
        low, high = OPERATING_TEMPERATURE_C
        return self.bias_over_temperature / ((high - low) / np.sqrt(12.0))

    @property
    def misalignment_sigma_mrad(self) -> float:
        """1-sigma of each off-diagonal element of the triad's map from the housing axes: the
        misalignment limit covers the orthogonality error too (an element is the sensitivity
        of one sensing axis to another housing axis)."""
        return self.misalignment_mrad / LIMIT_SIGMAS


GYRO = Triad(table="Table 5-3", random_walk=0.15, bias_instability=0.3, scale_factor_ppm=500.0,
             misalignment_mrad=1.0, orthogonality_mrad=0.2, bias_trim_range=1.0,
             bias_over_temperature=10.0, bias_run_to_run=4.0, bias_one_year=None)
ACC = {  # by the accelerometers' range, g
    5: Triad("Table 5-4", 0.024, 0.005, 200.0, 1.0, 0.2, 0.1, 1.1, None, 1.9),
    10: Triad("Table 5-5", 0.024, 0.005, 200.0, 1.0, 0.2, 0.1, 1.1, None, 1.9),
    30: Triad("Table 5-6", 0.04, 0.01, 300.0, 1.0, 0.2, 0.3, 1.5, None, 4.0),
    80: Triad("Table 5-7", 0.15, 0.03, 1000.0, 1.5, 0.6, 0.8, 5.0, None, 12.0),
}
INCL = Triad(table="Table 5-8", random_walk=0.08, bias_instability=0.06, scale_factor_ppm=500.0,
             misalignment_mrad=1.0, orthogonality_mrad=0.2, bias_trim_range=0.02,
             bias_over_temperature=2.0, bias_run_to_run=None, bias_one_year=None)
# Linear-acceleration effect on the gyro bias with g-compensation, deg/h/g (Table 5-3): with Z
# along gravity at every static it is part of the bias calibd estimates, so no term models it
GYRO_G_SENSITIVITY_DEG_H_PER_G = 1.0


def incl_noise_factor(force_g: np.ndarray) -> np.ndarray:
    """How many times its 0 g figure an inclinometer axis's noise is, for the specific force
    along it (g): INCL_NOISE_AT_1G at 1 g, in proportion between."""
    return 1.0 + (INCL_NOISE_AT_1G - 1.0) * np.minimum(np.abs(force_g), 1.0)


def triads(acc_range_g: int = DEFAULT_ACC_RANGE_G) -> dict[str, Triad]:
    """The three triads of a unit whose accelerometers have the range `acc_range_g` (g)."""
    if acc_range_g not in ACC:
        raise ValueError(f"no STIM300 accelerometer range of {acc_range_g} g (known: "
                         f"{', '.join(map(str, ACC_RANGES_G))} g)")
    return {"gyro": GYRO, "acc": ACC[acc_range_g], "incl": INCL}


@dataclass(frozen=True)
class NoiseFigures:
    """A unit's noise figures in the datasheet's terms, by default the datasheet's for a 10 g
    unit (`NoiseFigures.datasheet` for another range): random walk and bias instability (the
    minimum of the Allan deviation, as the manufacturer defines it) of each triad. The
    inclinometer figures are those at 0 g (an axis along gravity is noisier:
    `incl_noise_factor`), None for a unit without inclinometers. The estimator's noise floors
    and the simulator's noise both start from these."""

    gyro_arw_deg_sqrt_h: float = GYRO.random_walk
    gyro_bias_instability_deg_h: float = GYRO.bias_instability
    acc_vrw_m_s_sqrt_h: float = ACC[DEFAULT_ACC_RANGE_G].random_walk
    acc_bias_instability_mg: float = ACC[DEFAULT_ACC_RANGE_G].bias_instability
    incl_vrw_m_s_sqrt_h: float | None = INCL.random_walk
    incl_bias_instability_mg: float | None = INCL.bias_instability

    @classmethod
    def datasheet(cls, acc_range_g: int = DEFAULT_ACC_RANGE_G):
        """The datasheet's figures for a unit whose accelerometers have this range (g)."""
        acc = triads(acc_range_g)["acc"]
        return cls(acc_vrw_m_s_sqrt_h=acc.random_walk, acc_bias_instability_mg=acc.bias_instability)


# ---------------------------------------------------------------- factory residuals

# The off-diagonal elements of a triad's map from the housing axes, in the order scenarios and
# results list them: (i, j) is the sensitivity of sensing axis i to housing axis j.
OFF_DIAGONAL = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))  # xy xz yx yz zx zy


def limit_misalignment(rng: np.random.Generator, triad: Triad) -> np.ndarray:
    """A triad's misalignment elements (mrad, OFF_DIAGONAL order) at the datasheet's limits,
    random signs. The datasheet bounds each sensing axis's angle to its housing reference (the
    two off-diagonal elements of its row together) and the angle between two axes' deviation from
    90 deg (E_ij + E_ji): a rotation of the whole triad with each component limit / sqrt(2) puts
    every axis at its limit, and a symmetric part of half the orthogonality limit puts every pair
    at that limit (which moves each axis a little off its limit: 0.86 to 1.14 mrad for 1 mrad
    and 0.2 mrad)."""
    phi = rng.choice([-1, 1], 3) * triad.misalignment_mrad / np.sqrt(2)
    half = rng.choice([-1, 1], 3) * triad.orthogonality_mrad / 2  # pairs xy, xz, yz
    error = np.array([[0.0, phi[2] + half[0], -phi[1] + half[1]],
                      [-phi[2] + half[0], 0.0, phi[0] + half[2]],
                      [phi[1] + half[1], -phi[0] + half[2], 0.0]])
    return np.array([error[i, j] for i, j in OFF_DIAGONAL])


def triad_error(scale_ppm, misalignment_mrad) -> np.ndarray:
    """The 3 x 3 error E of a triad whose output is (I + E) times the input in housing axes:
    scale-factor errors (ppm) on the diagonal, the OFF_DIAGONAL elements (mrad) off it."""
    error = np.diag(np.asarray(scale_ppm, dtype=float) * 1e-6)
    for (i, j), value in zip(OFF_DIAGONAL, misalignment_mrad):
        error[i, j] = value * 1e-3
    return error


@dataclass(frozen=True)
class FactoryTerm:
    """One element of a triad's factory error E (`triad_error`) as a prior: its 1-sigma, dimensionless."""

    sensor: str  # gyro, acc, incl
    row: int
    col: int
    sigma: float

    @property
    def unit(self) -> str:
        return "ppm" if self.row == self.col else "mrad"

    @property
    def sigma_in_unit(self) -> float:
        return self.sigma * self.to_unit

    @property
    def name(self) -> str:
        """e.g. gyro_scale_z, acc_misalignment_xy."""
        if self.row == self.col:
            return f"{self.sensor}_scale_{'xyz'[self.row]}"
        return f"{self.sensor}_misalignment_{'xyz'[self.row]}{'xyz'[self.col]}"

    @property
    def to_unit(self) -> float:
        """`unit`s per unit of the element (ppm: 1e6, mrad: 1e3)."""
        return 1e6 if self.row == self.col else 1e3

    @classmethod
    def named(cls, name: str) -> FactoryTerm:
        """The element a term's `name` names (its sigma 0: where it sits, not its prior)."""
        sensor, _, axes = name.split("_")
        return cls(sensor, "xyz".index(axes[0]), "xyz".index(axes[-1]), 0.0)


def factory_terms(acc_range_g: int = DEFAULT_ACC_RANGE_G,
                  sensors: tuple[str, ...] = ("gyro", "acc", "incl")) -> tuple[FactoryTerm, ...]:
    """Every factory residual of the named triads with its datasheet prior: three scale factors
    and the six OFF_DIAGONAL elements per triad."""
    figures = triads(acc_range_g)
    terms = []
    for sensor in sensors:
        triad = figures[sensor]
        terms += [FactoryTerm(sensor, i, i, triad.scale_factor_sigma_ppm * 1e-6) for i in range(3)]
        terms += [FactoryTerm(sensor, i, j, triad.misalignment_sigma_mrad * 1e-3) for i, j in OFF_DIAGONAL]
    return tuple(terms)

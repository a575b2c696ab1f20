"""A result's correction, one home for every output that subtracts it: `calibd apply`, the
corrected pty, corrected SAMPLES (and whatever publishes corrected data next). What a result's
biases are in SI and in the sensor's base units, the factory terms the data estimated and how
they are taken out (`estimated_maps`, `through`), which output units can take them, which of a
power-up's results is subtracted ([serve] correction), whether a result is of the sensor
at hand, and the covariances a corrected sample carries (noise and the biases taken out)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stim300.protocol import CLUSTERS, NORMAL_LAYOUTS, Format

from . import spec
from .frames import STANDARD_GRAVITY
from .results import CalibrationResult, Estimate
from .units import DEG

SI_PER_SENSOR_UNIT = {"gyro": DEG, "acc": STANDARD_GRAVITY, "incl": STANDARD_GRAVITY}  # deg/s, g -> rad/s, m/s^2
WORDS = {"gyro": "gyro", "acc": "accelerometer", "incl": "inclinometer"}


@dataclass(frozen=True, eq=False)
class ServedCorrection:
    """The result of this power-up whose biases the corrected outputs subtract, and those biases
    in the sensor's base units (deg/s, g; float32 as the samples). Compared by identity: each
    change of the biases is a new one."""

    result: CalibrationResult
    bias: dict[str, np.ndarray]
    maps: dict[str, np.ndarray] = field(default_factory=dict)  # `estimated_maps`, float32

    @classmethod
    def of(cls, result: CalibrationResult) -> ServedCorrection | None:
        """The correction a result gives the served outputs; None when it has no biases."""
        bias = {block: b.astype(np.float32) for block, b in sensor_biases(result).items()}
        if not bias:
            return None
        return cls(result, bias, {block: m.astype(np.float32) for block, m in estimated_maps(result).items()})

    def biases(self) -> dict[str, tuple[float, str]]:
        """(value, unit) of each bias subtracted, as the result gives them (deg/h, mg)."""
        return {name: (e.value, e.unit) for name, e in bias_estimates(self.result).items()}

    def take_out(self, block: str, values: np.ndarray) -> np.ndarray:
        """A block's values (N x 3, the sensor's base units) less its bias, through its estimated map."""
        if block not in self.bias:
            return values
        return through(values - self.bias[block], self.maps.get(block))

    def same_as(self, other: ServedCorrection) -> bool:
        """Whether two corrections take out the same (biases and maps)."""
        return all(a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
                   for a, b in ((self.bias, other.bias), (self.maps, other.maps)))


def estimated_maps(result: CalibrationResult) -> dict[str, np.ndarray]:
    """Per triad, (I + E)^-1 of the factory terms the data estimated (the joint method's
    error_budget terms whose source is "estimated": a scale factor in ppm on the diagonal, a
    misalignment in mrad off it): what takes the triad's output, its bias off, back to the housing
    axes. A term its prior set is never applied (a prior is no measurement), so a triad without
    an estimated term is absent and its output passes as it is."""
    errors: dict[str, np.ndarray] = {}
    for name, (value, _) in estimated_terms(result).items():
        element = spec.FactoryTerm.named(name)
        errors.setdefault(element.sensor, np.zeros((3, 3)))[element.row, element.col] = value
    return {sensor: np.linalg.inv(np.eye(3) + error) for sensor, error in errors.items()}


def estimated_terms(result: CalibrationResult) -> dict[str, tuple[float, float]]:
    """The factory terms the result's data estimated (error_budget terms whose source is
    "estimated"), by name: (value, 1-sigma), dimensionless. A term its prior set is not one."""
    factory = (result.error_budget or {}).get("factory_residuals") or {}
    out = {}
    for name, term in (factory.get("terms") or {}).items():
        if term.get("source") == "estimated":
            to_unit = spec.FactoryTerm.named(name).to_unit
            out[name] = (term["value"] / to_unit, term["sigma"] / to_unit)
    return out


def through(values: np.ndarray, matrix: np.ndarray | None) -> np.ndarray:
    """Vectors (N x 3, one per row) through a 3 x 3 map; as they are without one."""
    return values if matrix is None else values @ matrix.T


def bias_estimates(result: CalibrationResult) -> dict[str, Estimate]:
    """The bias estimates a correction subtracts, by name, as the result gives them (deg/h, mg):
    those of each cluster whose three estimates the result has."""
    names = {cluster: [f"{cluster}_bias_{axis}" for axis in "xyz"] for cluster in CLUSTERS}
    return {name: result.estimates[name] for axes in names.values()
            if all(name in result.estimates for name in axes) for name in axes}


def si_biases(result: CalibrationResult) -> dict[str, np.ndarray]:
    """The biases subtracted, by cluster, in SI (gyro rad/s, accelerometer and inclinometer m/s^2)."""
    estimates = bias_estimates(result)
    return {cluster: np.array([estimates[f"{cluster}_bias_{axis}"].value_si for axis in "xyz"])
            for cluster in CLUSTERS if f"{cluster}_bias_x" in estimates}


def sensor_biases(result: CalibrationResult) -> dict[str, np.ndarray]:
    """The biases subtracted, by cluster, in the sensor's base units (deg/s, g), as the sensor's
    own datagrams carry rates and accelerations."""
    return {cluster: bias / SI_PER_SENSOR_UNIT[cluster] for cluster, bias in si_biases(result).items()}


def uncorrectable(fmt: Format) -> list[str]:
    """The outputs of this format a constant bias cannot be taken from as they are, in words
    ("gyro incremental_angle"): an incremental angle or velocity holds the bias times the sample
    interval, an integrated one has summed it since power-up. Empty: every block of the
    format's datagram is a rate or an acceleration."""
    units = {"gyro": fmt.gyro_unit, "acc": fmt.acc_unit, "incl": fmt.incl_unit}
    return [f"{WORDS[c]} {units[c].name.lower()}" for c in NORMAL_LAYOUTS[fmt.datagram_id].clusters
            if c in units and (units[c].is_angle if c == "gyro" else units[c].is_velocity)]


def sample_units(fmt: Format) -> dict[str, str]:
    """The units of the sensor blocks a bias is taken from (the SAMPLES and DEVICE units)."""
    return {block: unit for block, unit in fmt.units().items() if block in CLUSTERS}


def replaces(policy: str, kept: CalibrationResult | None, new: CalibrationResult) -> bool:
    """Whether `new`, a result of the power-up that carries biases, takes the place of `kept`,
    the one subtracted now (None: none yet), under [serve] `correction` (docs/serving.md):
    "latest" always; "first" never; "best" when none of its bias estimates is "poor" and either
    one of the kept ones is, or none of its bias sigmas is larger than the kept one's (an
    estimate without a sigma counts as infinitely uncertain). So a poorer result never replaces
    the kept one, and the kept biases only change for better-known ones."""
    if kept is None or policy == "latest":
        return True
    if policy == "first":
        return False
    new_biases, kept_biases = bias_estimates(new), bias_estimates(kept)
    if any(e.quality == "poor" for e in new_biases.values()):
        return False
    if any(e.quality == "poor" for e in kept_biases.values()):
        return True
    return all(_sigma_si(e) <= _sigma_si(kept_biases.get(name)) for name, e in new_biases.items())


def _sigma_si(estimate: Estimate | None) -> float:
    """An estimate's sigma in SI (comparable whatever unit a result wrote it in); infinite when
    it has none."""
    sigma = None if estimate is None else estimate.sigma_si
    return float("inf") if sigma is None else sigma


def other_sensor(result_serial: str | None, serial: str | None) -> bool:
    """Whether a result (of the sensor with serial number `result_serial`) is of another unit
    than the stream's (`serial`): only when both are known and differ. A serial number comes
    only in the sensor's power-up datagrams, so a stream joined later cannot tell."""
    return serial is not None and result_serial is not None and serial != result_serial


def white_noise_variance(random_walk_per_sqrt_h: float, rate_hz: float) -> float:
    """A random walk's white noise over one sample interval, as a variance: (rad/sqrt(h) or
    m/s/sqrt(h)) -> per second per sqrt(s), squared, times the rate."""
    return (random_walk_per_sqrt_h / 60.0) ** 2 * rate_hz


def noise_covariances(rate_hz: float, acc_range_g: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The datasheet's white noise of one sample at `rate_hz` (a unit of `acc_range_g`; None:
    not known, a 10 g unit's), as the 3 x 3 covariances (SI^2) of the gyros and the
    accelerometers: what every published sensor_msgs/Imu carries."""
    figures = spec.NoiseFigures.datasheet() if acc_range_g is None else spec.NoiseFigures.datasheet(acc_range_g)
    gyro = white_noise_variance(figures.gyro_arw_deg_sqrt_h * DEG, rate_hz)
    acc = white_noise_variance(figures.acc_vrw_m_s_sqrt_h, rate_hz)
    return np.eye(3) * gyro, np.eye(3) * acc


def bias_covariance(result: CalibrationResult, cluster: str) -> np.ndarray:
    """The 3 x 3 covariance (SI^2) of a cluster's biases as `si_biases` gives them: the result's
    covariance block when it has one (axes correlate through the alignment), else each sigma
    squared (an estimate without a sigma counts as zero)."""
    names = [f"{cluster}_bias_{axis}" for axis in "xyz"]
    covariance = result.covariance_matrix(si=True)
    if covariance is not None and all(name in result.covariance["names"] for name in names):
        index = [result.covariance["names"].index(name) for name in names]
        return covariance[np.ix_(index, index)]
    return np.diag([(result.estimates[name].sigma_si or 0.0) ** 2 for name in names])

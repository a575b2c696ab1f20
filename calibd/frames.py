"""Frames, rotations and the site: NWU navigation frame, passive 3-2-1 rotations (docs/method.md, Rotation conventions).

All angles here are radians; degrees appear only at the edges (configuration, results).
Rotation functions accept scalars or arrays of angles and return (..., 3, 3) matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stim300.protocol import STANDARD_GRAVITY  # noqa: F401 (the sensor's g unit is the driver's)

from .errors import SiteError

EARTH_RATE = 7.2921150e-5  # rad/s (WGS84), = 15.0411 deg/h
# How far true gravity may lie from normal gravity at a site (1-sigma): the local free-air
# anomaly, whose worldwide RMS is about 42 mGal (point anomaly variance 1795 mGal^2 in Tscherning
# and Rapp's 1974 degree-variance model); mountains and trenches reach 100 mGal and more.
NORMAL_GRAVITY_SIGMA = 4.2e-4  # m/s^2 (42 mGal, 0.043 mg)
# The values a Site accepts; every way in (command-line options, configuration and scenario
# files) refuses others with site_value_error's words.
LATITUDE_RANGE_DEG = (-90.0, 90.0)
HEIGHT_RANGE_M = (-500.0, 9000.0)  # below the Dead Sea shore to above any observatory
G0_RANGE_M_S2 = (9.7, 9.9)  # Earth gravity anywhere near the surface
SITE_RANGES = {  # Site field -> (range, unit, what the value is)
    "latitude_deg": (LATITUDE_RANGE_DEG, "deg", "a latitude"),
    "height_m": (HEIGHT_RANGE_M, "m", "a height"),
    "g0": (G0_RANGE_M_S2, "m/s^2", "an Earth gravity"),
}


def _stack(rows) -> np.ndarray:
    return np.moveaxis(np.array(rows, dtype=np.float64), (0, 1), (-2, -1))


def r1(angle) -> np.ndarray:
    """Passive rotation about X: re-expresses a vector in a frame turned by `angle`."""
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return _stack([[one, zero, zero], [zero, c, s], [zero, -s, c]])


def r2(angle) -> np.ndarray:
    """Passive rotation about Y."""
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return _stack([[c, zero, -s], [zero, one, zero], [s, zero, c]])


def r3(angle) -> np.ndarray:
    """Passive rotation about Z."""
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return _stack([[c, s, zero], [-s, c, zero], [zero, zero, one]])


# The bench's mountings: M with M [0, 0, 1] = the named IMU axis, so M v is the housing's input v
# (as first mounted, +Z up) in the sensor's axes once that axis is up
MOUNTS = {"+Z": np.eye(3), "-Z": r1(np.pi), "+Y": r1(np.pi / 2), "-Y": r1(-np.pi / 2),
          "+X": r2(-np.pi / 2), "-X": r2(np.pi / 2)}


def nav_to_imu(yaw, pitch, roll) -> np.ndarray:
    """R_NAV^IMU = R1(roll) R2(pitch) R3(yaw) (eq. 3.1)."""
    return r1(roll) @ r2(pitch) @ r3(yaw)


def int_to_imu(alpha, beta) -> np.ndarray:
    """R_int^IMU = R1(alpha) R2(beta): the IMU's tilt on its mechanical interface (eq. 5.4/5.5)."""
    return r1(alpha) @ r2(beta)


def nav_to_int(gamma1, gamma2, gamma3) -> np.ndarray:
    """R_NAV^int = R1(gamma3) R2(gamma2) R3(gamma1) (eq. 6.3)."""
    return r1(gamma3) @ r2(gamma2) @ r3(gamma1)


def euler_321(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(yaw, pitch, roll) of R = R1(roll) R2(pitch) R3(yaw); pitch in [-pi/2, pi/2]."""
    m = np.asarray(matrix)
    yaw = np.arctan2(m[..., 0, 1], m[..., 0, 0])
    pitch = -np.arcsin(np.clip(m[..., 0, 2], -1.0, 1.0))
    roll = np.arctan2(m[..., 1, 2], m[..., 2, 2])
    return yaw, pitch, roll


def normal_gravity(latitude_deg: float, height_m: float = 0.0) -> float:
    """WGS84 normal gravity (Somigliana) with the second-order free-air correction, m/s^2."""
    s2 = np.sin(np.radians(latitude_deg)) ** 2
    g_equator, k, e2 = 9.7803253359, 0.00193185265241, 0.00669437999013
    surface = g_equator * (1 + k * s2) / np.sqrt(1 - e2 * s2)
    return float(surface - (3.087691e-6 - 4.3977e-9 * s2) * height_m + 0.72125e-12 * height_m**2)


def site_value_error(field: str, value: float) -> str | None:
    """Why `value` cannot be the Site's `field` (a key of SITE_RANGES), in one phrase; None when it can."""
    (low, high), unit, what = SITE_RANGES[field]
    if low <= value <= high:
        return None
    return f"{value!r} is not {what} in [{low:g}, {high:g}] {unit}"


@dataclass(frozen=True)
class Site:
    """Where the IMU is: latitude (and height) give gravity unless g0 is measured and given."""

    latitude_deg: float
    height_m: float = 0.0
    g0: float | None = None  # m/s^2; None: normal gravity

    def __post_init__(self):
        for name in SITE_RANGES:
            value = getattr(self, name)
            reason = None if value is None else site_value_error(name, value)
            if reason is not None:
                raise SiteError(name, reason)

    @property
    def gravity(self) -> float:
        return self.g0 if self.g0 is not None else normal_gravity(self.latitude_deg, self.height_m)

    @property
    def gravity_sigma(self) -> float:
        """1-sigma of `gravity`, m/s^2: 0 for a measured g0, the local anomaly for normal gravity."""
        return 0.0 if self.g0 is not None else NORMAL_GRAVITY_SIGMA

    @property
    def earth_rate_nav(self) -> np.ndarray:
        """Earth rate in NWU, rad/s: [Omega cos(lat), 0, Omega sin(lat)] (eq. 4.2)."""
        lat = np.radians(self.latitude_deg)
        return EARTH_RATE * np.array([np.cos(lat), 0.0, np.sin(lat)])

    @property
    def gravity_nav(self) -> np.ndarray:
        """Specific force of the gravity reaction in NWU, m/s^2 (eq. 4.1)."""
        return np.array([0.0, 0.0, self.gravity])

"""The thesis's estimators, exactly as written (docs/method.md, Estimators; thesis chapters 5 to 7).

Pure functions on segment means (and, for the full turn, samples). Units inside: rad, rad/s,
m/s^2; the caller converts at the edges. Each function names its equations. Where the thesis
linearises, so do we: these are the reference the project is judged against, including their
model errors (e.g. eq. 7.3 treats the Earth rate during a turn as if it were the static one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..frames import EARTH_RATE, Site

UP_AXES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


# ---------------------------------------------------------------- bench (chapter 5)

def six_position_biases(means: dict[str, np.ndarray]) -> np.ndarray:
    """Bias of every channel of one sensor from the six static positions (eq. 5.3):
    b_i = (mean_i with axis i up + mean_i with axis i down) / 2. `means` maps "+X".."-Z" to the
    sensor's mean vector in that position. For gyros the reference is the vertical Earth rate,
    which also changes sign, so the same formula holds."""
    missing = [axis for axis in UP_AXES if axis not in means]
    if missing:
        raise ValueError(f"six-position biases need all six positions; missing {', '.join(missing)} up")
    return np.array([(means[f"+{a}"][i] + means[f"-{a}"][i]) / 2 for i, a in enumerate("XYZ")])


def interface_tilt(rate: np.ndarray) -> tuple[float, float]:
    """alpha, beta from the platform-rate vector in IMU axes (eq. 5.8), in the ratio form
    alpha = atan(w_Y / w_Z), beta = -atan(w_X / w_Z): the same for either turn sense."""
    return float(np.arctan(rate[1] / rate[2])), float(-np.arctan(rate[0] / rate[2]))


def bench_platform_rate(turn_gyro_mean: np.ndarray, gyro_bias: np.ndarray, pitch: float, roll: float,
                        site: Site) -> np.ndarray:
    """omega_Rot^NB: the full-turn mean gyro with the bench biases and the static Earth rate
    (pitch and roll terms) removed (eq. 5.7); the yaw term averages out over a whole turn."""
    lat = np.radians(site.latitude_deg)
    h, v = EARTH_RATE * np.cos(lat), EARTH_RATE * np.sin(lat)
    earth = np.array([h - pitch * v, roll * v, pitch * h + v])
    return turn_gyro_mean - earth - gyro_bias


# ---------------------------------------------------------------- real case (chapter 6)

def incl_bias_xy(index_means: np.ndarray, alpha: float, beta: float, g0: float) -> tuple[float, float]:
    """Inclinometer X and Y biases from the four index positions (eq. 6.13a/b): the gamma terms
    cancel in the sum over positions 90 deg apart. `index_means` is 4 x 3 (m/s^2)."""
    mean = np.asarray(index_means).mean(axis=0)
    return (float(mean[0] + np.sin(beta) * g0),
            float(mean[1] - np.sin(alpha) * np.cos(beta) * g0))


def pitch_roll(force: np.ndarray) -> tuple[float, float]:
    """Pitch and roll from a bias-corrected static specific force (eq. 6.16):
    roll = atan(f_Y / f_Z), pitch = -atan(f_X cos(roll) / f_Z)."""
    roll = float(np.arctan(force[1] / force[2]))
    pitch = float(-np.arctan(force[0] * np.cos(roll) / force[2]))
    return pitch, roll


def acc_biases(acc_mean: np.ndarray, pitch: float, roll: float, g0: float) -> np.ndarray:
    """Accelerometer biases from the level static (eq. 6.18): the mean minus gravity's projection."""
    gravity = g0 * np.array([-np.sin(pitch), np.sin(roll) * np.cos(pitch), np.cos(roll) * np.cos(pitch)])
    return np.asarray(acc_mean) - gravity


def gyro_y_bias_from_turn(gyro_y: np.ndarray, roll: float, alpha: float, beta: float, platform_rate: float,
                          site: Site) -> float:
    """Gyro Y bias from one whole period of the constant-rate part of a full turn (eqs. 6.29 to
    6.31): remove the roll-Earth term and the platform-rate projection, then average; the
    Earth-rate sinusoid of amplitude Omega cos(lat) integrates to zero over the period (over a
    shorter constant-rate part, up to `unaveraged_earth_rate` of it stays)."""
    lat = np.radians(site.latitude_deg)
    no_mis = np.asarray(gyro_y) - roll * EARTH_RATE * np.sin(lat) - np.sin(alpha) * np.cos(beta) * platform_rate
    return float(no_mis.mean())


def unaveraged_earth_rate(covered: float, site: Site) -> float:
    """Largest mean horizontal Earth rate on a horizontal IMU axis over a constant-rate stretch
    that covers `covered` rad of platform angle (rad/s). Eq. 6.31 assumes a whole period, where it
    is 0. Over [chi0, chi0 + covered] the mean of Omega cos(lat) sin(chi) is
    Omega cos(lat) sin(chi0 + covered/2) sin(covered/2) / (covered/2): at the worst heading chi0,
    Omega cos(lat) |sin(covered/2) / (covered/2)|, which is 0 for whole revolutions."""
    return float(EARTH_RATE * np.cos(np.radians(site.latitude_deg)) * abs(np.sinc(covered / (2 * np.pi))))


def yaw_from_static(gyro_y_static: float, roll: float, gyro_y_bias: float, site: Site) -> float:
    """Yaw from the level-static Y gyro (eq. 6.32), linearised in yaw."""
    lat = np.radians(site.latitude_deg)
    return float((gyro_y_static - roll * EARTH_RATE * np.sin(lat) - gyro_y_bias) / (-EARTH_RATE * np.cos(lat)))


def gyro_biases(gyro_static: np.ndarray, yaw: float, pitch: float, roll: float, site: Site) -> np.ndarray:
    """Gyro biases without linearisation (eq. 6.33a-c): the static mean minus the full
    R_NAV^IMU projection of the Earth rate (eq. 6.21)."""
    lat = np.radians(site.latitude_deg)
    h, v = EARTH_RATE * np.cos(lat), EARTH_RATE * np.sin(lat)
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    earth = np.array([cy * cp * h - sp * v,
                      -sy * cr * h + cy * sp * sr * h + cp * sr * v,
                      sy * sr * h + cy * sp * cr * h + cp * cr * v])
    return np.asarray(gyro_static) - earth


def interface_tilt_linear(turn_gyro_mean: np.ndarray, static_gyro_mean: np.ndarray) -> tuple[float, float]:
    """alpha, beta from the same dataset, linear method (eqs. 7.1 to 7.3): full-turn mean minus
    level-static mean leaves the platform-rate projection. It neglects that the horizontal
    Earth rate averages out during the turn but not in the static: an error of about
    Omega cos(lat) cos(yaw) / platform rate in beta."""
    return interface_tilt(np.asarray(turn_gyro_mean) - np.asarray(static_gyro_mean))


# ---------------------------------------------------------------- the real-case chain

@dataclass(frozen=True)
class RealCaseData:
    """What the chain needs from a session (means over segments; SI units)."""

    level_gyro: np.ndarray  # mean gyro over the level static, rad/s
    level_acc: np.ndarray  # m/s^2
    level_incl: np.ndarray  # m/s^2
    index_incl: np.ndarray  # 4 x 3 inclinometer means at the four index positions, m/s^2
    turn_gyro: np.ndarray  # rad/s, over one period of the full turn's constant-rate part (all of it if shorter)


def real_case(data: RealCaseData, site: Site, alpha_beta: tuple[float, float] | None = None,
              platform_rate: float | None = None) -> dict:
    """The thesis's real-case chain R1..R7 (docs/method.md, Estimators). With `alpha_beta` (rad) it is the
    nominal run (a-priori interface tilt); without, alpha and beta come from the same dataset by
    the linear method (7.1-7.3) first. `platform_rate` (rad/s, signed) stands for the robot
    telemetry; by default it is the turn's vertical rate over the static one, projected
    (cos alpha cos beta), which is what the linear method measures."""
    g0 = site.gravity
    turn_mean = data.turn_gyro.mean(axis=0)
    if alpha_beta is None:
        alpha, beta = interface_tilt_linear(turn_mean, data.level_gyro)
        method = "thesis-linear"
    else:
        alpha, beta = alpha_beta
        method = "thesis-nominal"
    if platform_rate is None:
        platform_rate = float((turn_mean[2] - data.level_gyro[2]) / (np.cos(alpha) * np.cos(beta)))
    incl_x, incl_y = incl_bias_xy(data.index_incl, alpha, beta, g0)
    incl_bias = np.array([incl_x, incl_y, 0.0])  # b_Z^i = 0 is assumed (section 6.1)
    pitch, roll = pitch_roll(data.level_incl - incl_bias)
    acc_bias = acc_biases(data.level_acc, pitch, roll, g0)
    gyro_y_bias = gyro_y_bias_from_turn(data.turn_gyro[:, 1], roll, alpha, beta, platform_rate, site)
    yaw = yaw_from_static(float(data.level_gyro[1]), roll, gyro_y_bias, site)
    gyro_bias = gyro_biases(data.level_gyro, yaw, pitch, roll, site)
    return {"method": method, "pitch": pitch, "roll": roll, "yaw": yaw, "alpha": alpha, "beta": beta,
            "gyro_bias": gyro_bias, "acc_bias": acc_bias, "incl_bias": incl_bias, "platform_rate": platform_rate,
            "gyro_y_bias_turn": gyro_y_bias}


# ---------------------------------------------------------------- analyses (section 7.1, 6.3)

def sensitivity(d_alpha: float, d_beta: float, platform_rate: float, site: Site) -> dict:
    """What interface-tilt errors do (section 7.1): d_beta -> inclinometer X bias error
    g0 sin(d_beta); d_alpha -> gyro Y bias error platform_rate * d_alpha; that gyro error ->
    yaw error d_b_Y / (Omega cos(lat)) (eq. 6.32). SI in, SI out (m/s^2, rad/s, rad)."""
    d_incl_x = site.gravity * np.sin(d_beta)
    d_gyro_y = abs(platform_rate) * d_alpha
    d_yaw = d_gyro_y / (EARTH_RATE * np.cos(np.radians(site.latitude_deg)))
    return {"incl_bias_x": float(d_incl_x), "gyro_bias_y": float(d_gyro_y), "yaw": float(d_yaw)}


def earth_rate_diagnostic(gyro: np.ndarray, rate_hz: float, site: Site, sigma_s: float = 1.0) -> dict:
    """The thesis's check that the Earth rate is observable (section 6.3, fig. 6.4): Gaussian-
    filter the gyro (sigma_s), take each channel's amplitude spectrum, and say whether the
    largest non-DC component of a horizontal channel is of the order of Omega cos(lat) (within
    a factor of 10). On static data this cannot tell the Earth rate from bias drift; during a
    turn the Earth rate is a real line at the turn frequency. A diagnostic only, as in the thesis."""
    from scipy.ndimage import gaussian_filter1d  # when used: start-up (docs/architecture.md)
    filtered = gaussian_filter1d(np.asarray(gyro, float), sigma_s * rate_hz, axis=0, mode="nearest")
    n = len(filtered)
    spectrum = np.abs(np.fft.rfft(filtered - filtered.mean(axis=0), axis=0)) * 2 / n
    freqs = np.fft.rfftfreq(n, 1.0 / rate_hz)
    peak = 1 + np.argmax(spectrum[1:], axis=0)
    amplitude = spectrum[peak, np.arange(spectrum.shape[1])]
    expected = EARTH_RATE * np.cos(np.radians(site.latitude_deg))
    ratio = amplitude[:2] / expected
    return {"expected_amplitude": float(expected), "peak_frequency_hz": freqs[peak].tolist(),
            "peak_amplitude": amplitude.tolist(), "frequencies_hz": freqs, "spectrum": spectrum,
            "visible": bool(np.any((ratio >= 0.1) & (ratio <= 10)))}

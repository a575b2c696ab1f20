"""The joint estimator (docs/method.md, Estimators): every static and turning sample in one fit, with 1-sigma.

With R_NAV^IMU(t) = A · R3(chi(t)) · R_NAV^int (A = R_int^IMU), the gyros read, exactly,

    w(t) = A R3(chi) v + A[:, 2] chi' + b,      v = R_NAV^int Omega_NAV (the Earth rate in the
                                                interface frame, |v| = Omega_E)
         = v1 (A0 cos chi - A1 sin chi) + v2 (A0 sin chi + A1 cos chi) + k chi' + c

with A0, A1 the first columns of A, k = A[:, 2] the platform axis in IMU axes and
c = v3 k + b. Given the platform angle chi(t) (the integral of the gyro about the platform axis,
its static level removed) this is linear in (v1, v2, k, c): one least-squares fit over all
three channels and all samples, static and turning, any heading, sense, rate profile or number
of turns. alpha and beta come from k, yaw from (v1, v2) with the gravity direction, the biases
from c. The accelerometers and inclinometers see f = g0 A R3(chi) u + b at every static, with
u = R_NAV^int Up the platform axis's tilt: linear in (u1, u2, b) for the gyro-derived A.
No small-angle approximation is made anywhere.

Uncertainty: each fit's covariance is that of its least squares under a white + flicker noise
model per sensor (bias instability correlates the errors over minutes; every flicker component
counts, so a bias's sigma is that of the turn-on bias, the wander over the session included).
The force fits' sensitivity to the gyro-derived axis and to g0 carries the gyro covariance and
g0's (Site.gravity_sigma) into the accelerometer and inclinometer parameters, with their
cross-covariances; the numerical Jacobian of the chain takes it all to every estimate. The
model is fitted to the Allan deviation of the residuals of the longest static that does not
vibrate, its flicker at least the STIM300 datasheet's, or given (`SensorNoise`: the campaign
planner gives a datasheet's figures to a noise-free session of the campaign). Samples noisier
than that static (vibration) weigh less in every fit by their measured noise
(`static_inflation`, `_row_weights`), so the covariance stays that of the data. A unit without
inclinometers has no inclinometer fit: the accelerometers give the tilt.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from ..errors import CalibdError
from ..frames import EARTH_RATE, STANDARD_GRAVITY, Site, euler_321, int_to_imu
from ..allan import FLICKER_TAUS_S, allan_deviation, fit_noise_model, flicker_sigma, gauss_markov_forms
from .. import spec
from ..units import DEG

INCL_ESTIMATES = ("incl_bias_x", "incl_bias_y", "incl_bias_z")  # absent for a unit without inclinometers
ESTIMATE_NAMES = ("pitch", "roll", "yaw", "alpha", "beta", "gyro_bias_x", "gyro_bias_y", "gyro_bias_z",
                  "acc_bias_x", "acc_bias_y", "acc_bias_z", *INCL_ESTIMATES)
MAX_ITERATIONS = 20  # chi depends on the fitted axis and Earth terms: iterate to a fixed point
CHI_TOLERANCE = 1e-13  # rad: the largest change of chi between passes that counts as converged
# rad: the same for the error budget's refits, whose changes of chi are 1e-4 rad and more (a
# Z scale factor's 1-sigma over a turn): a millionth of them is exact enough
REFIT_TOLERANCE = 1e-10
BLOCK = 1 << 16  # samples a pass over the session takes at once: its temporaries are this long, not the session
FLICKER_BIN_S = 0.1  # flicker's fastest component (3 s) barely changes within a bin (3 % at most)
NOISIER_FROM = 2.0  # a static whose white variance is this many times the reference static's is weighted down
LOCAL_NOISE_S = 1.0  # outside the statics, the noise around a sample is measured over this window

# The fits' parameter vectors, named once for every reader (the fits, the chain, the figures).
# Gyro fit: (v1, v2, k, c[, d]).
EARTH_RATE_PARAMS = slice(0, 2)  # v1, v2: the horizontal Earth rate in the interface frame, rad/s
AXIS_PARAMS = slice(2, 5)  # k: the platform axis in IMU axes (the gyros' rate coefficient)
OFFSET_PARAMS = slice(5, 8)  # c = v3 k + b, rad/s
DRIFT_PARAMS = slice(8, 11)  # d: a linear drift per channel, rad/s per s (JointOptions.drift only)
GYRO_PARAM_COUNT = {False: OFFSET_PARAMS.stop, True: DRIFT_PARAMS.stop}  # by JointOptions.drift
# Force fits (accelerometers, inclinometers): (u1, u2, b).
TILT_PARAMS = slice(0, 2)  # u1, u2: the platform axis's tilt in the interface frame
BIAS_PARAMS = slice(2, 5)  # b, m/s^2


class Underdetermined(CalibdError):
    """The session's segments do not determine the fit (statics at too few platform angles):
    something the campaign lacks, told apart from a fault of the code."""


@dataclass(frozen=True)
class JointInput:
    """A session in SI: samples from the level static (chi = 0 there) to the end of the campaign."""

    time_s: np.ndarray  # (N,) s, gaps where datagrams were lost
    # the samples as stored (float32 from a capture's session): every pass takes them to float64 block by block
    gyro: np.ndarray  # (N, 3) rad/s
    acc: np.ndarray  # (N, 3) m/s^2
    incl: np.ndarray | None  # (N, 3) m/s^2; None: the unit has no inclinometers
    statics: tuple[tuple[int, int], ...]  # [start, stop) sample ranges of the static segments
    rate_hz: float
    # (N,) rad added to the gyro-integrated platform angle: turns whose angle lost datagrams shortened
    chi_correction: np.ndarray | None = None
    # (statics,) rad: each static's platform angle when the platform's stops give it (an indexing
    # table), the level static's 0; None: the gyros' integral gives them
    static_angles: np.ndarray | None = None
    # (N,) degC, the sensor's temperature at each sample; None: the datagrams carry none
    temperature_c: np.ndarray | None = None


@dataclass(frozen=True)
class NoiseModel:
    """One sensor's noise as the covariance sees it, per channel (X, Y, Z): an inclinometer
    axis along gravity is noisier than a horizontal one (`spec.incl_noise_factor`). A number
    given for either stands for all three channels."""

    white: np.ndarray  # (3,) white-noise variance per sample at the session's rate, SI unit^2
    flicker: np.ndarray  # (3,) variance of each Gauss-Markov component of FLICKER_TAUS_S, SI unit^2

    def __post_init__(self):
        for name in ("white", "flicker"):
            object.__setattr__(self, name, np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (3,)).copy())


@dataclass(frozen=True)
class SensorNoise:
    """A noise model for every sensor: used instead of fitting it to the residuals."""

    gyro: NoiseModel  # rad/s
    acc: NoiseModel  # m/s^2
    incl: NoiseModel | None  # m/s^2; None: the unit has no inclinometers


def datasheet_noise(figures: spec.NoiseFigures, rate_hz: float, incl_force_g: np.ndarray | None = None) -> SensorNoise:
    """The noise models of datasheet figures, at `rate_hz`: white variance per sample from the
    random walk, and the flicker components the simulator uses for the bias instability (Allan
    deviation minimum = the figure). `incl_force_g`: the specific force along the inclinometer
    axes (g), which makes an axis along gravity noisier (`spec.incl_noise_factor`); None: the
    figures at 0 g."""
    def model(density: float, instability: float, factor=1.0) -> NoiseModel:
        flicker = flicker_sigma(density, instability) ** 2 if instability > 0 else 0.0
        return NoiseModel(density**2 * rate_hz * factor**2, flicker * factor**2)

    mg = STANDARD_GRAVITY / 1000
    gyro = model(figures.gyro_arw_deg_sqrt_h / 60 * DEG, figures.gyro_bias_instability_deg_h / 3600 * DEG)
    incl = None if figures.incl_vrw_m_s_sqrt_h is None else \
        model(figures.incl_vrw_m_s_sqrt_h / 60, figures.incl_bias_instability_mg * mg,
              1.0 if incl_force_g is None else spec.incl_noise_factor(incl_force_g))
    return SensorNoise(gyro=gyro, acc=model(figures.acc_vrw_m_s_sqrt_h / 60, figures.acc_bias_instability_mg * mg),
                       incl=incl)


@dataclass(frozen=True)
class JointOptions:
    fixed_amplitude: bool = False  # horizontal Earth rate amplitude fixed to its known value
    drift: bool = False  # a linear gyro drift per channel (thermal ramps); costs precision
    # the unit's accelerometer range, g: whose datasheet figures (noise floors, factory residuals) apply
    acc_range_g: int = spec.DEFAULT_ACC_RANGE_G
    # the factory residuals' prior (spec.factory_terms) in every sigma; False: a perfect sensor is
    # assumed (the noise-limit checks of the fit itself)
    factory_residuals: bool = True
    # rad: the platform's turns are whole multiples of this angle (an indexing table's step), so
    # each static's angle is known to index_sigma (rad, 1-sigma); None: the gyros' integral gives it
    index_step: float | None = None
    index_sigma: float = 0.0
    # factory terms an earlier calibration of the unit estimated (a bench's six positions, a second
    # mounting): (term name, value, 1-sigma), dimensionless, each taken as one more measurement of it
    known_terms: tuple[tuple[str, float, float], ...] = ()
    known_from: str | None = None  # where they come from: the earlier results' paths
    known_serial: str | None = None  # whose they are: a sensor of another serial number is refused

    def for_second_mounting(self) -> JointOptions:
        """The options a second mounting's fit takes (calibd.estimators.remount): the known terms
        enter the pair once, through the first mounting's posterior."""
        return replace(self, known_terms=(), known_from=None, known_serial=None)


# The parts a covariance is made of, in the order results list them (`JointResult.budget`)
BUDGET_PARTS = ("white_noise", "bias_instability", "temperature", "gravity", "turn_angles", "remounting",
                "factory_residuals")


@dataclass
class GyroFit:
    params: np.ndarray  # v1, v2, k (3), c (3), [drift (3)]
    cov_parts: dict[str, np.ndarray]  # white_noise, bias_instability
    chi: np.ndarray  # platform angle at each sample's mid-interval, rad
    chi_rate: np.ndarray
    residual_rms: np.ndarray  # per channel, rad/s
    noise_scale: float
    noise: NoiseModel  # the model the covariance assumes: fitted to the residuals, or given
    amplitude_check: tuple[float, float]  # fitted horizontal Earth rate and its 1-sigma, rad/s
    static_chi2: tuple[float, int]  # chi-square of the statics' mean residuals and its degrees of freedom
    model: _GyroModel  # the fit's regressors and parameters: its non-rotational part, where a refit starts
    root: np.ndarray  # (N,) each row's root weight (`_row_weights`): the same weights for every refit

    @property
    def cov(self) -> np.ndarray:
        return sum(self.cov_parts.values())


# ---------------------------------------------------------------- session-long arrays, block by block

def _spans(n: int) -> list[tuple[int, int]]:
    """[lo, hi) blocks of BLOCK samples that cover n."""
    return [(lo, min(lo + BLOCK, n)) for lo in range(0, n, BLOCK)]


def _f64(values: np.ndarray, lo: int | None = None, hi: int | None = None) -> np.ndarray:
    """Samples [lo, hi) in float64: stored float32 values taken over exactly."""
    return np.asarray(values[lo:hi], dtype=np.float64)


def _static_blocks(statics, root: np.ndarray) -> list[tuple[int, int, float]]:
    """The statics' samples as [lo, hi) blocks of at most BLOCK, each with its static's root weight."""
    return [(lo, min(lo + BLOCK, b), r) for (a, b), r in zip(statics, root) for lo in range(a, b, BLOCK)]


def _static_mean(values: np.ndarray, statics) -> np.ndarray:
    """The mean of every static sample, summed static by static (no copy of them all)."""
    total = sum(values[a:b].sum(axis=0, dtype=np.float64) for a, b in statics)
    return total / sum(b - a for a, b in statics)


# ---------------------------------------------------------------- statics' own noise

def sample_variance(values: np.ndarray, statics) -> np.ndarray:
    """Each static's white noise variance per sample (SI^2, the mean of its channels), from its
    Allan variance at one sample (half the mean squared step between samples): the static's
    constant value and slow wander drop out. Vibration that is not white (an engine's few
    frequencies) counts as white noise of the same power: more than it moves a static's mean,
    so sigmas built on it stay on the safe side."""
    return np.array([np.mean(np.diff(_f64(values, a, b), axis=0) ** 2) / 2 for a, b in statics])


def reference_static(variance: np.ndarray, statics) -> int:
    """The static the noise model is fitted to: the longest of those not NOISIER_FROM times
    noisier than the quietest (a vibrating static would make every other one look quiet)."""
    quiet = [k for k, v in enumerate(variance) if v <= NOISIER_FROM * variance.min()]
    return max(quiet, key=lambda k: statics[k][1] - statics[k][0])


def static_inflation(values: np.ndarray, statics) -> np.ndarray:
    """Per static, how many times the reference static's white variance its own is (1 unless
    NOISIER_FROM times or more: estimates of the same noise scatter by a few per cent). A static
    taken with an engine running weighs that much less in the fits, and its means' variance is
    that much larger."""
    variance = sample_variance(values, statics)
    ref = variance[reference_static(variance, statics)]
    if ref <= 0:  # noise-free data (planning): nothing to weigh by
        return np.ones(len(statics))
    ratio = variance / ref
    return np.where(ratio >= NOISIER_FROM, ratio, 1.0)


def _row_weights(values: np.ndarray, inp: JointInput) -> np.ndarray:
    """Per sample, the square root of its weight, 1 / sqrt(inflation): in a static, the static's
    (`static_inflation`); elsewhere (turns, and the settling next to a static that vibrates),
    that of the noise around the sample, from the mean square of its second differences over
    LOCAL_NOISE_S (a turn's constant or steadily changing rate has none), against the
    reference static's. Vibrating samples weighed as quiet ones would put their noise into the
    fit while its covariance took them for quiet."""
    variance = sample_variance(values, inp.statics)
    ref = variance[reference_static(variance, inp.statics)]
    inflation = np.ones(len(values))
    if ref > 0:  # noise-free data (planning): nothing to weigh by
        second = np.empty(max(len(values) - 2, 0))  # white noise: 6 sigma^2
        for lo, hi in _spans(len(second)):
            second[lo:hi] = np.mean(np.diff(_f64(values, lo, hi + 2), n=2, axis=0) ** 2, axis=1) / 6
        half = max(1, int(LOCAL_NOISE_S * inp.rate_hz / 2))
        window = np.ones(2 * half + 1) / (2 * half + 1)
        local = np.convolve(np.pad(second, half + 1, mode="edge"), window, mode="valid")  # centred, n samples
        inflation = np.where(local >= NOISIER_FROM * ref, local / ref, 1.0)
    for (a, b), factor in zip(inp.statics, static_inflation(values, inp.statics)):
        inflation[a:b] = factor
    return 1.0 / np.sqrt(inflation)


def _scaled(designs: list[ChannelDesign], root: np.ndarray) -> list[ChannelDesign]:
    """Designs with each row multiplied by its root weight: their least squares is the weighted
    one. Channels that share a basis share its scaled copy."""
    scaled: dict[int, np.ndarray] = {}
    for d in designs:
        if id(d.basis) not in scaled:
            scaled[id(d.basis)] = d.basis * root[:, None]
    return [ChannelDesign(d.params, scaled[id(d.basis)], d.mix) for d in designs]


# ---------------------------------------------------------------- gyro fit

def _platform_angle(inp: JointInput, axis: np.ndarray, offset, data) -> tuple[np.ndarray, np.ndarray]:
    """chi at each sample's mid-interval and chi' (the sample's average rate): the gyro (`data(lo,
    hi)`, samples [lo, hi)) minus its non-rotational part (`offset(lo, hi)`), projected on the
    platform axis, integrated over time (lost datagrams leave gaps in time_s). The platform does
    not turn in a static: chi' = 0 there, which also anchors the vertical offset (else it trades
    with a drift of chi)."""
    rate = np.empty(len(inp.time_s))
    for lo, hi in _spans(len(rate)):
        rate[lo:hi] = (data(lo, hi) - offset(lo, hi)) @ axis
    for a, b in inp.statics:
        rate[a:b] = 0.0
    dt = 1.0 / inp.rate_hz
    chi = np.diff(inp.time_s, append=inp.time_s[-1] + dt)  # each sample's interval, then the angle at its start
    chi *= rate
    np.cumsum(chi, out=chi)
    chi[1:], chi[0] = chi[:-1], 0.0
    # half an interval at a linearly changing rate: r dt/2 less slope dt^2/8 (matters in ramps)
    chi += rate * dt / 2
    chi -= np.gradient(rate) * dt / 8
    if inp.chi_correction is not None:
        chi += inp.chi_correction
    if inp.static_angles is not None:  # each turn stretched to end at its stop, the statics pinned there
        integrated = np.array([chi[a:b].mean() for a, b in inp.statics])
        chi += turn_ramps(inp, chi, np.diff(inp.static_angles) - np.diff(integrated - integrated[0]))
    return chi, rate


def turn_ramps(inp: JointInput, chi: np.ndarray, added: np.ndarray) -> np.ndarray:
    """Per sample, the angle (rad) each turn between two statics adds beyond `chi` (`added`, one
    per turn): nothing before the turn, all of it after, and in proportion to the angle `chi`
    turned in between (where in the turn datagrams went missing, or a scale factor acted, is
    spread as the turning was)."""
    total = np.zeros(len(inp.time_s))
    for k, angle in enumerate(added):
        start, stop = inp.statics[k][1], inp.statics[k + 1][0]
        progress = (chi - chi[start - 1]) / (chi[stop] - chi[start - 1])
        ramp = np.clip(progress, 0.0, 1.0)
        ramp[:start] = 0.0
        ramp[stop:] = 1.0
        total += angle * ramp
    return total


@dataclass(frozen=True)
class ChannelDesign:
    """One channel's regressors, kept as the non-zero columns of its N x P design (each channel
    has its own offsets, rate and drift terms, so most of the P columns are zero), and those as
    a few N-long columns all channels of a fit share (`basis`: cos chi, sin chi, ...) mixed by
    the channel's own small matrix (`mix`): the channels differ only in how they mix the same
    columns, so a session's columns are held once, not once per channel. A session of two hours
    at 125 Hz would otherwise spend most of the solver's memory on them."""

    params: np.ndarray  # which of the P parameters the columns belong to
    basis: np.ndarray  # N x B, shared by the channels of a fit
    mix: np.ndarray  # B x len(params): the design is basis @ mix

    def __matmul__(self, params: np.ndarray) -> np.ndarray:
        return self.basis @ (self.mix @ params[self.params])


def _gyro_designs(chi, chi_rate, tau, a, drift: bool) -> list[ChannelDesign]:
    """Per channel, the regressors of (v1, v2, k_xyz, c_xyz[, d_xyz]): the Earth terms
    (a_i0 cos chi - a_i1 sin chi, a_i0 sin chi + a_i1 cos chi), and the channel's own rate
    coefficient, offset and drift, on the basis (cos chi, sin chi, chi', 1[, tau])."""
    basis = np.empty((len(chi), 5 if drift else 4))
    np.cos(chi, out=basis[:, 0])
    np.sin(chi, out=basis[:, 1])
    basis[:, 2], basis[:, 3] = chi_rate, 1.0
    if drift:
        basis[:, 4] = tau
    designs = []
    for i in range(3):
        mix = np.eye(basis.shape[1])
        mix[:2, :2] = [[a[i, 0], a[i, 1]], [-a[i, 1], a[i, 0]]]
        params = [*range(EARTH_RATE_PARAMS.start, EARTH_RATE_PARAMS.stop), AXIS_PARAMS.start + i,
                  OFFSET_PARAMS.start + i] + ([DRIFT_PARAMS.start + i] if drift else [])
        designs.append(ChannelDesign(np.array(params), basis, mix))
    return designs


@dataclass(frozen=True)
class _GyroModel:
    """A gyro fit's regressors (its platform angle, the axis its Earth terms are mixed with) and
    parameters (None while being fitted): any block of its designs, fitted outputs or
    non-rotational part is made when needed, so no session-long (N, 3) array is held for them."""

    chi: np.ndarray
    chi_rate: np.ndarray
    a: np.ndarray  # R_int^IMU of the axis the Earth terms are mixed with
    tau_mean_s: float  # the drift's time origin: the mean sample time
    drift: bool
    params: np.ndarray | None = None

    def designs(self, time_s: np.ndarray, lo: int, hi: int) -> list[ChannelDesign]:
        return _gyro_designs(self.chi[lo:hi], self.chi_rate[lo:hi], time_s[lo:hi] - self.tau_mean_s, self.a,
                             self.drift)

    def fitted(self, time_s: np.ndarray, lo: int, hi: int) -> np.ndarray:
        return np.column_stack([d @ self.params for d in self.designs(time_s, lo, hi)])

    def offset(self, time_s: np.ndarray, lo: int, hi: int) -> np.ndarray:
        """The fitted non-rotational part of samples [lo, hi): the fit less its rate term."""
        out = self.fitted(time_s, lo, hi)
        out -= np.outer(self.chi_rate[lo:hi], self.params[AXIS_PARAMS])
        return out

    def normal_equations(self, time_s: np.ndarray, data, root: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
        """The weighted normal equations of `data(lo, hi)` (the gyros' samples [lo, hi)), summed block by block."""
        gram, rhs = np.zeros((p, p)), np.zeros(p)
        for lo, hi in _spans(len(time_s)):
            block = _normal_equations(_scaled(self.designs(time_s, lo, hi), root[lo:hi]),
                                      data(lo, hi) * root[lo:hi, None], p)
            gram += block[0]
            rhs += block[1]
        return gram, rhs


def _gram(designs: list[ChannelDesign], p: int) -> np.ndarray:
    """Sum over channels of D' D = M' (B' B) M, each channel's block placed at its parameters;
    B' B once per shared basis."""
    gram = np.zeros((p, p))
    basis_grams: dict[int, np.ndarray] = {}
    for d in designs:
        if id(d.basis) not in basis_grams:
            basis_grams[id(d.basis)] = d.basis.T @ d.basis
        gram[np.ix_(d.params, d.params)] += d.mix.T @ basis_grams[id(d.basis)] @ d.mix
    return gram


def _normal_equations(designs: list[ChannelDesign], data: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Channels weighted equally: the three axes of a sensor share one noise spec (weights from
    per-channel residuals would let a noise-free channel with tiny residuals dictate v1, v2
    through its small tilt coefficients)."""
    rhs = np.zeros(p)
    for i, d in enumerate(designs):
        rhs[d.params] += d.mix.T @ (d.basis.T @ data[:, i])
    return _gram(designs, p), rhs


def _free(gram, rhs) -> tuple[np.ndarray, np.ndarray]:
    """Unconstrained least squares: parameters and the inverse information."""
    bread = np.linalg.inv(gram)
    return bread @ rhs, bread


def _on_circle(gram, rhs, amplitude: float) -> tuple[np.ndarray, np.ndarray]:
    """Best fit with (v1, v2) = amplitude (cos phi, sin phi): a 1-D search over phi with the other
    parameters linear; the inverse information is that of (phi, rest) mapped back to
    (v1, v2, rest) through the tangent of the circle."""
    p = len(rhs)

    def mapping(phi, tangent=False):
        t = np.zeros((p, p - 1))
        t[0, 0], t[1, 0] = (-np.sin(phi), np.cos(phi)) if tangent else (np.cos(phi), np.sin(phi))
        t[:2, 0] *= amplitude
        t[2:, 1:] = np.eye(p - 2)
        return t

    def explained(phi):  # the cost is minus the explained sum of squares
        t = mapping(phi)
        h = t.T @ rhs
        return h @ np.linalg.solve(t.T @ gram @ t, h)

    best = max(np.linspace(-np.pi, np.pi, 721), key=explained)
    for half_width in (1e-2, 1e-4, 1e-6, 1e-8):
        best = max(best + np.linspace(-half_width, half_width, 41), key=explained)
    t = mapping(best)
    x = np.linalg.solve(t.T @ gram @ t, t.T @ rhs)
    tangent = mapping(best, tangent=True)
    return t @ x, tangent @ np.linalg.inv(tangent.T @ gram @ tangent) @ tangent.T


@dataclass
class _GyroSolution:
    """The gyro fit's fixed point: parameters, inverse information, and the model they fit."""

    params: np.ndarray
    bread: np.ndarray
    model: _GyroModel


def _iterate_gyros(inp: JointInput, site: Site, options: JointOptions, root: np.ndarray, data, axis: np.ndarray,
                   offset, chi: np.ndarray, tolerance: float = CHI_TOLERANCE) -> _GyroSolution:
    """The gyro fit of `data(lo, hi)` (the gyros' samples [lo, hi)) iterated to its fixed point
    (chi changing by less than `tolerance`, rad): chi needs the platform axis and the Earth terms
    the fit gives. It starts from `axis`, `offset(lo, hi)` (the non-rotational part) and `chi`: a
    fit of nearly the same data takes a few passes, not many."""
    tau_mean_s = float(inp.time_s.mean())
    amplitude = EARTH_RATE * np.cos(np.radians(site.latitude_deg))
    p = GYRO_PARAM_COUNT[options.drift]
    for _ in range(MAX_ITERATIONS):
        previous = chi
        chi, chi_rate = _platform_angle(inp, axis, offset, data)
        model = _GyroModel(chi, chi_rate, int_to_imu(*alpha_beta(axis)), tau_mean_s, options.drift)
        gram, rhs = model.normal_equations(inp.time_s, data, root, p)
        params, bread = _on_circle(gram, rhs, amplitude) if options.fixed_amplitude else _free(gram, rhs)
        model = replace(model, params=params)
        k = params[AXIS_PARAMS]
        axis = k / np.linalg.norm(k)
        offset = partial(model.offset, inp.time_s)
        if np.max(np.abs(chi - previous)) < tolerance:
            break
    return _GyroSolution(params, bread, model)


def fit_gyros(inp: JointInput, site: Site, options: JointOptions = JointOptions(),
              noise: NoiseModel | None = None, least_flicker: np.ndarray | float = 0.0) -> GyroFit:
    """The gyro fit and its covariance. `noise`: the noise model of the covariance (default:
    fitted to the static residuals, its flicker at least `least_flicker`)."""
    inflation = static_inflation(inp.gyro, inp.statics)
    root = _row_weights(inp.gyro, inp)
    data = partial(_f64, inp.gyro)
    mean = _static_mean(inp.gyro, inp.statics)
    fit = _iterate_gyros(inp, site, options, root, data, np.array([0.0, 0.0, 1.0]), lambda lo, hi: mean,
                         np.zeros(len(inp.time_s)))
    params, model = fit.params, fit.model

    def residuals(lo: int, hi: int) -> np.ndarray:
        return data(lo, hi) - model.fitted(inp.time_s, lo, hi)

    ref = residuals(*inp.statics[reference_static(sample_variance(inp.gyro, inp.statics), inp.statics)])
    noise = noise or _fitted_noise(ref, inp.rate_hz, least_flicker)
    scale = _noise_scale(ref, inp.rate_hz)
    del ref  # a static's residuals: not held through the covariance
    spans = _spans(len(inp.time_s))
    parts = _covariance(spans, lambda lo, hi: _scaled(model.designs(inp.time_s, lo, hi), root[lo:hi]),
                        lambda lo, hi: root[lo:hi], inp, fit.bread, noise)
    cov = sum(parts.values())
    fitted = float(np.hypot(*params[EARTH_RATE_PARAMS]))
    radial = params[EARTH_RATE_PARAMS] / fitted
    amplitude_var = radial @ cov[EARTH_RATE_PARAMS, EARTH_RATE_PARAMS] @ radial  # 0 when the amplitude is fixed
    return GyroFit(params, parts, model.chi, model.chi_rate, _rms_about_mean(residuals, spans), scale, noise,
                   (fitted, float(np.sqrt(max(amplitude_var, 0.0)))),
                   _static_chi2(residuals, inp, len(params) - 3, noise, inflation), model, root)


def _rms_about_mean(residuals, spans: list[tuple[int, int]]) -> np.ndarray:
    """Per channel, the standard deviation of `residuals(lo, hi)` over all `spans`, two passes block by block."""
    n = spans[-1][1]
    mean = sum(residuals(lo, hi).sum(axis=0) for lo, hi in spans) / n
    return np.sqrt(sum(((residuals(lo, hi) - mean) ** 2).sum(axis=0) for lo, hi in spans) / n)


def _fitted_noise(residuals: np.ndarray, rate_hz: float, least_flicker: np.ndarray) -> NoiseModel:
    """White + flicker fitted to the Allan deviation of the reference static's `residuals` (the
    longest that does not vibrate: `reference_static`), the
    flicker no lower than `least_flicker` (the datasheet's): a static of minutes resolves the
    white noise well but not flicker below it (the gyros' 0.3 deg/h under 0.7 deg/h of white
    noise at a quarter of 10 min), and a fit that finds none would make every sigma that
    compares statics far apart, or a bias with the turn-on bias, too small. The channels differ as
    the datasheet's floors do (an inclinometer axis along gravity is noisier than the others):
    the model is fitted to the residuals divided by that shape, pooled (a channel's own minutes
    would scatter its flicker widely), and the shape put back."""
    least = np.broadcast_to(np.asarray(least_flicker, dtype=float), (3,))
    shape = np.sqrt(least / least.min()) if least.min() > 0 else np.ones(3)
    white, flicker = fit_noise_model(residuals / shape, rate_hz, FLICKER_TAUS_S)
    return NoiseModel(white * shape**2, np.maximum(flicker * shape**2, least))


def _static_chi2(residuals, inp: JointInput, fitted: int, noise: NoiseModel,
                 inflation: np.ndarray) -> tuple[float, int]:
    """Chi-square of each static's mean residual (per channel) against what the noise model (its
    white noise times the static's `inflation`) lets a mean over that long scatter: large when a
    bias jumped, the platform moved during a 'static', or the model does not hold. `residuals(lo,
    hi)`: those of samples [lo, hi)."""
    total, count = 0.0, 0
    for (start, stop), factor in zip(inp.statics, inflation):
        var = mean_variance(noise, stop - start, inp.rate_hz, factor)
        if np.all(var > 0):  # a given noise-free model (planning a campaign) leaves nothing to compare with
            total += float(np.sum(residuals(start, stop).mean(axis=0) ** 2 / var))
        count += 3
    return total, max(count - fitted, 1)


def mean_variance(noise: NoiseModel, n: int, rate_hz: float, inflation: float = 1.0) -> np.ndarray:
    """Variance of each channel's mean over n consecutive samples under the noise model (its white
    noise times `inflation`, a vibrating static's), less the slowest flicker component: it moves
    every static alike, so fitted offsets take it, not the differences between statics."""
    tau = n / rate_hz
    return inflation * noise.white / n + noise.flicker * sum(_gm_mean_variance(tau, c) for c in FLICKER_TAUS_S[:-1])


def _gm_mean_variance(tau: float, corr: float) -> float:
    """Variance of the mean over tau of a unit Gauss-Markov process of correlation time corr."""
    x = tau / corr
    return 2 / x * (1 - (1 - np.exp(-x)) / x)


def _covariance(spans: list[tuple[int, int]], designs_of, root_of, inp: JointInput, bread: np.ndarray,
                noise: NoiseModel) -> dict[str, np.ndarray]:
    """Parameter covariance under white noise plus flicker (a sum of Gauss-Markov processes) on
    the samples of `spans` ([lo, hi) in time order). Flicker correlates the errors over minutes;
    a white-noise covariance would be optimistic for everything that compares segments far
    apart. Every component counts, the slowest (30000 s) too: over a session it is a nearly
    constant wander of the bias, the difference between the bias the session carries and the
    turn-on bias reported. `bread`
    is the inverse information of the (possibly constrained) fit: cov = bread . (H' Sigma H) . bread.
    The fit is weighted: `designs_of(lo, hi)` are the rows times their root weights `root_of(lo,
    hi)`, which whiten the white noise (a static's inflated variance times its weight is the
    model's), while flicker, common to quiet and vibrating samples, sees the weights themselves.
    The two parts are kept apart (white_noise, bias_instability): their sum is the covariance.
    The rows are taken span by span: a span's designs are all that is held of them."""
    p = len(bread)
    grams, grid = None, None
    flicker = np.any(noise.flicker > 0)
    last_bin = int(np.floor(inp.time_s[spans[-1][1] - 1] / FLICKER_BIN_S))
    for lo, hi in spans:
        designs = designs_of(lo, hi)
        block = [_gram([d], p) for d in designs]
        grams = block if grams is None else [g + b for g, b in zip(grams, block)]
        if not flicker:
            continue
        # Flicker varies over seconds at the fastest, so its quadratic form is taken on sums over
        # FLICKER_BIN_S bins of every channel's columns, laid on a uniform bin grid.
        bins = np.floor(inp.time_s[lo:hi] / FLICKER_BIN_S).astype(np.int64)
        starts = np.flatnonzero(np.diff(bins, prepend=-1))
        if grid is None:
            grid = np.zeros((last_bin + 1, sum(len(d.params) for d in designs)))
        root = root_of(lo, hi)
        binned: dict[int, np.ndarray] = {}  # each shared basis's bin sums, mixed per channel below
        for d in designs:
            if id(d.basis) not in binned:
                binned[id(d.basis)] = np.add.reduceat(d.basis * root[:, None], starts)
        grid[bins[starts]] += np.hstack([binned[id(d.basis)] @ d.mix for d in designs])
    white = sum(noise.white[i] * g for i, g in enumerate(grams))
    meat = np.zeros_like(white)
    if flicker:
        start = 0
        for i, d in enumerate(designs):
            columns = grid[:, start:start + len(d.params)]
            for form in gauss_markov_forms(columns, 1.0 / FLICKER_BIN_S, FLICKER_TAUS_S):
                meat[np.ix_(d.params, d.params)] += noise.flicker[i] * form
            start += len(d.params)
    return {"white_noise": bread @ white @ bread, "bias_instability": bread @ meat @ bread}


def has_drift(gyro_params: np.ndarray) -> bool:
    """Whether a gyro fit's parameters include the drift terms (JointOptions.drift)."""
    return len(gyro_params) == GYRO_PARAM_COUNT[True]


def alpha_beta(axis: np.ndarray) -> tuple[float, float]:
    """alpha, beta of the platform axis k ~ [-sin b, sin a cos b, cos a cos b], exactly (the
    thesis's beta = -atan(k_x / k_z) is off by beta (1 - cos alpha)). k is the axis, not the
    rate, so either turn sense gives the same angles."""
    return float(np.arctan2(axis[1], axis[2])), float(-np.arcsin(axis[0] / np.linalg.norm(axis)))


def _noise_scale(residuals: np.ndarray, rate_hz: float) -> float:
    """How much the reference static's `residuals`' Allan deviation exceeds white noise at long
    averaging times (an eighth and a quarter of the static): 1 for white noise, more when bias
    instability correlates the errors."""
    r = residuals
    taus = np.array([1 / 8, 1 / 4]) * len(r) / rate_hz
    taus = taus[taus * rate_hz >= 2]
    if not len(taus):
        return 1.0
    used, adev = allan_deviation(r, rate_hz, taus)
    white = r.std(axis=0) / np.sqrt(used[:, None] * rate_hz)
    ratio = np.divide(adev, white, out=np.ones_like(adev), where=white > 0)
    return float(max(1.0, np.max(ratio)))


# ---------------------------------------------------------------- accelerometers, inclinometers

@dataclass
class ForceFit:
    params: np.ndarray  # u1, u2 (platform axis tilt in the interface frame), b (3), m/s^2 for b
    # from this sensor's noise alone, the platform axis and g0 taken as exact: white_noise, bias_instability
    cov_parts: dict[str, np.ndarray]
    noise_scale: float
    noise: NoiseModel  # the model the covariance assumes: fitted to the residuals, or given
    sensitivity: np.ndarray  # d params / d (k_x, k_y, k_z, g0): how the axis and g0 errors move them
    statics: tuple[tuple[int, int], ...]  # the static samples the fit uses
    root: np.ndarray  # each static's root weight
    sums: _StaticSums  # of the data, at the fit's platform angles
    data: np.ndarray  # (N, 3) the sensor's samples: a refit at other platform angles sums them again

    @property
    def cov(self) -> np.ndarray:
        return sum(self.cov_parts.values())

    def refit(self, through: np.ndarray, k: np.ndarray, g0: float, chi: np.ndarray | None = None,
              added: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """The parameters for the data plus `added` ((channel, values of all N samples) added to
        that channel; it needs `chi`) taken through the 3 x 3 map `through` (the sensor's output
        is `through` times the data), another axis k, g0 or platform angle `chi` (all samples;
        None: the fit's), with the same weights: how the error budget sees a change of the data.
        The sums are linear in the data, so the map acts on them."""
        sums = self.sums
        if chi is not None:
            sums = _static_sums(self.data, chi, self.statics, self.root, added)
        return _force_params(replace(sums, cross=sums.cross @ through.T), k, g0)[0]


@dataclass(frozen=True)
class _StaticSums:
    """The sums of the statics' platform-angle basis B = (cos chi, sin chi, 1) with itself and
    the data, weighted (W: each static's weight). A channel's design is B times a 3 x 3 matrix
    of the axis and g0, so the force fit's normal equations for any axis and g0 follow from these
    sums: refitting for the sensitivity costs no pass over the samples."""

    gram: np.ndarray  # B' W B
    cross: np.ndarray  # B' W f, one column per channel


def _channel_map(a_row: np.ndarray, g0: float) -> np.ndarray:
    """T with design = B T: columns g0 (a0 cos - a1 sin), g0 (a0 sin + a1 cos), 1."""
    return np.array([[g0 * a_row[0], g0 * a_row[1], 0.0], [-g0 * a_row[1], g0 * a_row[0], 0.0], [0.0, 0.0, 1.0]])


def _force_params(sums: _StaticSums, k: np.ndarray, g0: float):
    """(params, gram, maps, offsets) of f = g0 A R3(chi) u + b, A = int_to_imu(alpha, beta) of
    the platform axis k: linear in (u1, u2, b) once u3 is taken from the previous pass; `offsets`
    is the g0 u3 A[:, 2] the last pass took off the data."""
    a = int_to_imu(*alpha_beta(k))
    maps = [_channel_map(a[i], g0) for i in range(3)]
    u3 = 1.0
    for _ in range(3):
        offsets = g0 * u3 * a[:, 2]
        gram, rhs = np.zeros((5, 5)), np.zeros(5)
        for i, t in enumerate(maps):
            cols = [0, 1, 2 + i]
            gram[np.ix_(cols, cols)] += t.T @ sums.gram @ t
            rhs[cols] += t.T @ (sums.cross[:, i] - offsets[i] * sums.gram[:, 2])  # B' W 1 = B' W B[:, 2]
        params = np.linalg.solve(gram, rhs)
        u3 = np.sqrt(1.0 - params[0] ** 2 - params[1] ** 2)
    return params, gram, maps, offsets


def fit_force(force: np.ndarray, chi: np.ndarray, inp: JointInput, k: np.ndarray, g0: float,
              noise: NoiseModel | None = None, least_flicker: np.ndarray | float = 0.0) -> ForceFit:
    """The accelerometer or inclinometer fit at every static sample, for the gyro-derived
    platform axis k (IMU axes). `noise` as in fit_gyros. The fit takes k and g0 as exact; its
    sensitivity to them lets `solve` carry their uncertainty into the biases (an error d_beta
    moves the X biases by g0 d_beta, one of g0 the Z biases by as much). The statics are taken
    one at a time: the fit holds their sums, not their samples."""
    chis = np.array([chi[s:e].mean() for s, e in inp.statics])
    if np.ptp(np.exp(1j * chis).real) < 0.5 and np.ptp(np.exp(1j * chis).imag) < 0.5:
        raise Underdetermined("the statics cover too few platform angles to separate the tilt from the biases "
                              "(index positions about 90 deg apart are needed)")
    root = 1.0 / np.sqrt(static_inflation(force, inp.statics))  # a static's rows' `_row_weights`
    blocks = _static_blocks(inp.statics, root)
    weight = {(a, b): r for a, b, r in blocks}
    sums = _static_sums(force, chi, inp.statics, root)
    params, gram, maps, offsets = _force_params(sums, k, g0)
    drivers = np.append(k, g0)

    def refit(x):
        return _force_params(sums, x[:3], x[3])[0]

    def designs(a: int, b: int) -> list[ChannelDesign]:
        basis = _angle_basis(chi[a:b])
        return [ChannelDesign(np.array([0, 1, 2 + i]), basis, t) for i, t in enumerate(maps)]

    def root_of(a: int, b: int) -> np.ndarray:
        return np.full(b - a, weight[a, b])

    steps = np.diag([1e-6, 1e-6, 1e-6, 1e-4])  # k is near unit length; g0 in m/s^2
    sensitivity = np.column_stack([(refit(drivers + h) - refit(drivers - h)) / (2 * h.max()) for h in steps])
    a, b = inp.statics[reference_static(sample_variance(force, inp.statics), inp.statics)]
    ref = _f64(force, a, b) - offsets - np.column_stack([d @ params for d in designs(a, b)])
    noise = noise or _fitted_noise(ref, inp.rate_hz, least_flicker)
    scale = _noise_scale(ref, inp.rate_hz)
    del ref  # a static's residuals: not held through the covariance
    parts = _covariance(list(weight), lambda a, b: _scaled(designs(a, b), root_of(a, b)), root_of, inp,
                        np.linalg.inv(gram), noise)
    return ForceFit(params, parts, scale, noise, sensitivity, inp.statics, root, sums, force)


def _angle_basis(chi_rows: np.ndarray) -> np.ndarray:
    """B = (cos chi, sin chi, 1), one row per sample."""
    return np.column_stack([np.cos(chi_rows), np.sin(chi_rows), np.ones(len(chi_rows))])


def _static_sums(force: np.ndarray, chi: np.ndarray, statics, root: np.ndarray,
                 added: tuple[int, np.ndarray] | None = None) -> _StaticSums:
    """The sums over the statics' samples (each static's root weight in `root`), static by
    static; `added`: (channel, values of all samples) added to that channel of `force`."""
    gram, cross = np.zeros((3, 3)), np.zeros((3, 3))
    for a, b, r in _static_blocks(statics, root):
        basis = _angle_basis(chi[a:b])
        values = np.array(force[a:b], dtype=np.float64)
        if added is not None:
            values[:, added[0]] += added[1][a:b]
        weighted = basis * r**2
        gram += weighted.T @ basis
        cross += weighted.T @ values
    return _StaticSums(gram, cross)


# ---------------------------------------------------------------- from fits to estimates

def _triad(primary_a, secondary_a, primary_b, secondary_b) -> np.ndarray:
    """The rotation R with R primary_b = primary_a exactly and R secondary_b close to secondary_a."""
    def frame(p, s):
        t1 = p / np.linalg.norm(p)
        t2 = np.cross(t1, s)
        t2 /= np.linalg.norm(t2)
        return np.column_stack([t1, t2, np.cross(t1, t2)])
    return frame(primary_a, secondary_a) @ frame(primary_b, secondary_b).T


def estimates_from(gyro_params: np.ndarray, incl_params: np.ndarray | None, acc_params: np.ndarray,
                   site: Site, tilt_from_incl: bool = True) -> dict:
    """Every estimate (SI) from the fitted parameters: a pure function, so its Jacobian carries the
    fits' covariances to the estimates. The platform axis's tilt (so pitch and roll) is the
    inclinometers' when `tilt_from_incl`, else the accelerometers' (the quieter sensor gives it:
    `solve`); a unit without inclinometers (`incl_params` None) has no inclinometer biases."""
    k = gyro_params[AXIS_PARAMS]
    alpha, beta = alpha_beta(k)
    a = int_to_imu(alpha, beta)
    omega, up = site.earth_rate_nav, np.array([0.0, 0.0, 1.0])
    u1, u2 = (incl_params if tilt_from_incl and incl_params is not None else acc_params)[TILT_PARAMS]
    u = np.array([u1, u2, np.sqrt(1 - u1**2 - u2**2)])  # Up in the interface frame
    horizontal = omega - (omega @ up) * up
    # v = R_NAV^int Omega. The fit gives v1, v2; v3 (along the interface z axis) hides in c and
    # follows from the attitude, which needs v across u: a fixed point, reached in a few passes.
    v3 = omega @ up
    for _ in range(4):
        v = np.append(gyro_params[EARTH_RATE_PARAMS], v3)
        r_nav_int = _triad(u, v - (v @ u) * u, up, horizontal)
        v3 = (r_nav_int @ omega)[2]
    yaw, pitch, roll = euler_321(a @ r_nav_int)
    gyro_bias = gyro_params[OFFSET_PARAMS] - v3 * a[:, 2]
    return {"pitch": float(pitch), "roll": float(roll), "yaw": float(yaw), "alpha": alpha, "beta": beta,
            **{f"gyro_bias_{x}": float(b) for x, b in zip("xyz", gyro_bias)},
            **{f"acc_bias_{x}": float(b) for x, b in zip("xyz", acc_params[BIAS_PARAMS])},
            **({} if incl_params is None else
               {f"incl_bias_{x}": float(b) for x, b in zip("xyz", incl_params[BIAS_PARAMS])})}


def _jacobian(f, x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    columns = []
    for i, h in enumerate(steps):
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        columns.append((np.array(list(f(up).values())) - np.array(list(f(down).values()))) / (2 * h))
    return np.column_stack(columns)


@dataclass
class JointResult:
    estimates: dict[str, float]  # SI
    # the estimates' covariance (SI, rows in the order of `estimates`) by its parts (BUDGET_PARTS):
    # each term of the error budget on its own; their sum is the covariance
    budget: dict[str, np.ndarray]
    gyro: GyroFit
    incl: ForceFit | None  # None: the unit has no inclinometers
    acc: ForceFit
    jacobian: np.ndarray  # d estimates / d (gyro, [incl,] acc params)
    factory: FactoryEffects | None = None  # the factory residuals the budget's prior covers; None: a perfect sensor
    tilt_from_incl: bool = True  # pitch and roll from the inclinometers' tilt (else the accelerometers')
    temperature: TemperatureEffects | None = None  # the biases' slope with temperature; None: no temperatures

    @property
    def covariance(self) -> np.ndarray:
        return sum(self.budget.values())

    @property
    def sigmas(self) -> dict[str, float]:
        """1-sigma of each estimate, SI: the covariance's diagonal, so the two never disagree."""
        return dict(zip(self.estimates, np.sqrt(np.diag(self.covariance)).tolist()))

    def with_factory_posterior(self, posterior: FactoryPosterior) -> JointResult:
        """The result with what the data saw of the factory residuals (the statics' forces, and what
        else `posterior` holds): each estimate less the terms' estimated move (first order: the
        effects are linear at that size), their share of the covariance the posterior's. It
        replaces any posterior the result had (its move undone first). The posterior's own noise,
        drawn from the same static means as the force fits, is taken as independent of theirs."""
        factory = replace(self.factory, posterior=posterior)
        before = self.factory.posterior
        moved = self.factory.estimates @ (posterior.z - (0.0 if before is None else before.z))
        estimates = {name: value - float(dv) for (name, value), dv in zip(self.estimates.items(), moved)}
        return replace(self, estimates=estimates, factory=factory,
                       budget=self.budget | {"factory_residuals": factory.covariance})

    def sigma_budget(self) -> dict[str, dict[str, float]]:
        """Per estimate, each budget part's 1-sigma (SI), in the order of BUDGET_PARTS: their
        squares add up to the sigma's."""
        parts = [part for part in BUDGET_PARTS if part in self.budget]
        return {name: {part: float(np.sqrt(max(self.budget[part][i, i], 0.0))) for part in parts}
                for i, name in enumerate(self.estimates)}

    @property
    def tilt(self) -> ForceFit:
        """The force fit pitch and roll come from."""
        return self.incl if self.tilt_from_incl and self.incl is not None else self.acc


def solve(inp: JointInput, site: Site, options: JointOptions = JointOptions(),
          noise: SensorNoise | None = None) -> JointResult:
    """Every estimate and its 1-sigma; `noise` replaces the noise models fitted to the residuals
    (whose flicker is at least the STIM300 datasheet's)."""
    along = None if inp.incl is None else _static_mean(inp.incl, inp.statics) / STANDARD_GRAVITY
    least = datasheet_noise(spec.NoiseFigures.datasheet(options.acc_range_g), inp.rate_hz, along)
    gyro = fit_gyros(inp, site, options, noise and noise.gyro, least.gyro.flicker)
    k = gyro.params[AXIS_PARAMS]
    incl = None if inp.incl is None else \
        fit_force(inp.incl, gyro.chi, inp, k, site.gravity, noise and noise.incl, least.incl.flicker)
    acc = fit_force(inp.acc, gyro.chi, inp, k, site.gravity, noise and noise.acc, least.acc.flicker)
    p, q = len(gyro.params), 0 if incl is None else len(incl.params)
    x = np.concatenate([gyro.params, *([] if incl is None else [incl.params]), acc.params])
    tilt_from_incl = incl is not None and _tilt_variance(incl) <= _tilt_variance(acc)

    def chain(params):
        return estimates_from(params[:p], params[p:p + q] if q else None, params[p + q:], site, tilt_from_incl)

    parts = parameter_covariance(gyro, incl, acc, site.gravity_sigma)
    steps = np.sqrt(np.diag(sum(parts.values()))) * 1e-3 + 1e-15
    jac = _jacobian(chain, x, steps)
    budget = {part: jac @ cov @ jac.T for part, cov in parts.items()}
    temperature = temperature_effects(inp, site, options, gyro, incl, acc, tilt_from_incl)
    if temperature is not None:
        budget["temperature"] = temperature.covariance
    factory = None
    if options.factory_residuals:
        sensors = ("gyro", "acc") if incl is None else ("gyro", "acc", "incl")
        terms = spec.factory_terms(options.acc_range_g, sensors)
        factory = factory_effects(inp, site, options, gyro, incl, acc, terms, tilt_from_incl)
        budget["factory_residuals"] = factory.covariance
    return JointResult(chain(x), budget, gyro, incl, acc, jac, factory, tilt_from_incl, temperature)


def _tilt_variance(fit: ForceFit) -> float:
    """How well a force fit alone (its own noise) pins the platform axis's tilt: the quieter of
    the accelerometers (a 10 g unit's: VRW 0.024 m/s/sqrt(h)) and the inclinometers (0.08 at 0 g)
    gives pitch and roll."""
    return float(np.trace(fit.cov[TILT_PARAMS, TILT_PARAMS]))


@dataclass(frozen=True)
class FactoryPosterior:
    """The factory terms after the statics' forces (`gaps.factory_posterior`): z, each term's
    value over its prior sigma, and cov, their covariance in the same units (the prior's: I)."""

    z: np.ndarray
    cov: np.ndarray

    def estimated(self, k: int) -> bool:
        """Whether the data, not the prior, set term k: its sigma at most half the prior's."""
        return bool(self.cov[k, k] <= ESTIMATED_BELOW**2)

    def observed(self, row: np.ndarray, value: float, sigma: float) -> FactoryPosterior:
        """The terms after one more measurement of a combination of them: value = row . z plus
        noise of `sigma` (a Gaussian update of the mean and covariance)."""
        spread = self.cov @ row
        gain = spread / (row @ spread + sigma**2)
        return FactoryPosterior(self.z + gain * (value - row @ self.z), self.cov - np.outer(gain, spread))

    def against_prior(self) -> tuple[float, int]:
        """(chi-square, degrees of freedom) of what the data saw of the terms against the prior:
        with the terms drawn from the prior N(0, I), z is N(0, I - cov) (the prior's variance is
        the posterior's plus that of its mean), so z' (I - cov)^-1 z over the directions the data
        saw (an eigenvalue of I - cov of SEEN_SHARE or more) is chi-square. A unit whose visible
        residuals lie beyond the datasheet's spread makes it large."""
        seen, directions = np.linalg.eigh(np.eye(len(self.z)) - self.cov)
        keep = seen >= SEEN_SHARE
        projected = directions[:, keep].T @ self.z
        return float(np.sum(projected**2 / seen[keep])), int(keep.sum())


ESTIMATED_BELOW = 0.5  # a factory term whose sigma the data bring to this share of the prior's is estimated
SEEN_SHARE = 0.1  # a direction of the factory terms whose variance the data narrowed by this share is seen


@dataclass(frozen=True)
class FactoryEffects:
    """What each factory residual at its 1-sigma does to the fit (`factory_effects`), and what
    the data say of the residuals (`posterior`; None: the prior alone)."""

    terms: tuple[spec.FactoryTerm, ...]
    estimates: np.ndarray  # (estimates, terms): each term's move of every estimate, SI
    # per gyro term (by its index in `terms`): the refitted platform axis k and the statics' mean
    # platform angles, rad: how the static forces' model moves (the turn-angle check's prior)
    gyro_refits: dict[int, tuple[np.ndarray, np.ndarray]]
    posterior: FactoryPosterior | None = None

    @property
    def covariance(self) -> np.ndarray:
        """The factory residuals' share of the estimates' covariance, SI."""
        cov = np.eye(len(self.terms)) if self.posterior is None else self.posterior.cov
        return self.estimates @ cov @ self.estimates.T


def factory_effects(inp: JointInput, site: Site, options: JointOptions, gyro: GyroFit, incl: ForceFit | None,
                    acc: ForceFit, terms: tuple[spec.FactoryTerm, ...], tilt_from_incl: bool) -> FactoryEffects:
    """How each factory residual moves every estimate at its 1-sigma (SI; a column per term):
    the data of the term's triad taken through (I + E), E that element at 1 sigma, and the whole
    chain refitted (the effects are linear to a part in a thousand at that size). The fit itself
    cannot tell them from the tilt and the biases (what the statics' forces see of them comes
    after: `gaps.factory_posterior`), so their prior reaches exactly the estimates they move (a
    misaligned gyro triad tilts the platform axis, so alpha, beta, pitch and roll; the
    misalignment between triads lands in the horizontal biases; a Z scale factor in the Z
    biases), and the fits' weights and platform angles see the data as the sensor gave them."""
    root = gyro.root
    estimates = _Refitted(site, {"incl": incl, "acc": acc}, tilt_from_incl).estimates
    base = estimates(gyro.params)
    columns, refits = [], {}
    for index, term in enumerate(terms):
        through = np.eye(3)
        through[term.row, term.col] += term.sigma
        if term.sensor == "gyro":
            # started where the base fit's axis and non-rotational part go through the same map
            k = through @ gyro.params[AXIS_PARAMS]
            refit_params, refit_chi = _gyro_refit(inp, site, options, root, through, k / np.linalg.norm(k),
                                                  gyro.model, gyro.chi)
            columns.append(estimates(refit_params, refit_chi) - base)
            refits[index] = (refit_params[AXIS_PARAMS], np.array([refit_chi[a:b].mean() for a, b in inp.statics]))
            del refit_chi  # not held through the next term's refit
        else:
            columns.append(estimates(gyro.params, None, term.sensor, through) - base)
    return FactoryEffects(terms, np.column_stack(columns), refits)


@dataclass(frozen=True)
class _Refitted:
    """Every estimate after a change of one sensor's data: the force fits refitted from their
    sums (linear in the data) for the given gyro parameters and platform angle."""

    site: Site
    forces: dict[str, ForceFit | None]  # incl (None: no inclinometers), acc
    tilt_from_incl: bool

    def estimates(self, gyro_params: np.ndarray, chi: np.ndarray | None = None, sensor: str | None = None,
                  through: np.ndarray = np.eye(3), added: tuple[int, np.ndarray] | None = None) -> np.ndarray:
        """SI, in ESTIMATE_NAMES' order; `sensor`'s data taken through `through` plus `added`
        ((channel, values): `ForceFit.refit`)."""
        k = gyro_params[AXIS_PARAMS]
        params = {name: None if fit is None else
                  fit.refit(through if name == sensor else np.eye(3), k, self.site.gravity, chi,
                            added if name == sensor else None)
                  for name, fit in self.forces.items()}
        return np.array(list(estimates_from(gyro_params, params["incl"], params["acc"], self.site,
                                            self.tilt_from_incl).values()))


@dataclass(frozen=True)
class TemperatureEffects:
    """What the biases' slope with temperature does to the fit (`temperature_effects`)."""

    per_degree: dict[str, float]  # gyro, incl, acc: the slope's datasheet 1-sigma, SI per degC
    excursion_c: np.ndarray  # (N,) the session's temperature about its mean, degC
    estimates: np.ndarray  # (estimates, channels): each channel's slope at 1 sigma moves every estimate, SI

    @property
    def covariance(self) -> np.ndarray:
        """The slopes' share of the estimates' covariance, SI: independent channels."""
        return self.estimates @ self.estimates.T


def temperature_effects(inp: JointInput, site: Site, options: JointOptions, gyro: GyroFit, incl: ForceFit | None,
                        acc: ForceFit, tilt_from_incl: bool) -> TemperatureEffects | None:
    """How each channel's bias slope with temperature, at its datasheet 1-sigma
    (`spec.Triad.bias_temperature_sigma`), moves every estimate (SI; a column per channel: gyro,
    [incl,] acc X Y Z): the bias the fit takes as constant follows the session's temperature
    about its mean, so each channel's data get that slope times the excursion and the chain is
    refitted. The gyro fit is refitted at its platform angle: the angle integrates the rate only
    while turning (some seconds), where the excursion's slope moves it by micro-radians. None
    without temperatures."""
    if inp.temperature_c is None or not np.isfinite(inp.temperature_c).any():
        return None
    excursion = np.nan_to_num(inp.temperature_c, nan=float(np.nanmean(inp.temperature_c)))
    excursion -= excursion.mean()  # about the session's mean
    triads = spec.triads(options.acc_range_g)
    per_degree = {"gyro": triads["gyro"].bias_temperature_sigma / 3600 * DEG,
                  "incl": triads["incl"].bias_temperature_sigma * STANDARD_GRAVITY / 1000,
                  "acc": triads["acc"].bias_temperature_sigma * STANDARD_GRAVITY / 1000}
    root = gyro.root
    p = len(gyro.params)
    model = replace(gyro.model, a=int_to_imu(*alpha_beta(gyro.params[AXIS_PARAMS])))
    gram, rhs = model.normal_equations(inp.time_s, partial(_f64, inp.gyro), root, p)
    mix = [(d.params, d.mix) for d in model.designs(inp.time_s, 0, 1)]  # each channel's, the same in every block
    seen = sum(_scaled(model.designs(inp.time_s, lo, hi), root[lo:hi])[0].basis.T
               @ (excursion[lo:hi] * per_degree["gyro"] * root[lo:hi]) for lo, hi in _spans(len(root)))
    solver = partial(_on_circle, amplitude=EARTH_RATE * np.cos(np.radians(site.latitude_deg))) \
        if options.fixed_amplitude else _free
    refitted = _Refitted(site, {"incl": incl, "acc": acc}, tilt_from_incl)
    fitted = solver(gram, rhs)[0]  # the fit's parameters, at the same arithmetic as the moved ones
    base = refitted.estimates(fitted, gyro.chi)
    columns = []
    for sensor in ("gyro", "incl", "acc"):
        if sensor == "incl" and incl is None:
            continue
        for axis in range(3):
            if sensor == "gyro":
                params, channel_mix = mix[axis]
                moved = rhs.copy()
                moved[params] += channel_mix.T @ seen  # the basis is the channels' shared one
                columns.append(refitted.estimates(solver(gram, moved)[0], gyro.chi) - base)
            else:
                added = (axis, excursion * per_degree[sensor])
                columns.append(refitted.estimates(fitted, gyro.chi, sensor, added=added) - base)
    return TemperatureEffects(per_degree, excursion, np.column_stack(columns))


def _gyro_refit(inp: JointInput, site: Site, options: JointOptions, root: np.ndarray, through: np.ndarray,
                axis: np.ndarray, start: _GyroModel, chi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The parameters and platform angle of a gyro fit of the data taken through `through`,
    refitted from `axis`, the non-rotational part of the fit `start` taken through the same map
    and its platform angle `chi`; its other session-long arrays are let go here, not held through
    the next term's refit."""
    def data(lo: int, hi: int) -> np.ndarray:
        return _mapped(_f64(inp.gyro, lo, hi), through)

    def offset(lo: int, hi: int) -> np.ndarray:
        return _mapped(start.offset(inp.time_s, lo, hi), through)

    solution = _iterate_gyros(inp, site, options, root, data, axis, offset, chi, REFIT_TOLERANCE)
    return solution.params, solution.model.chi


def _mapped(values: np.ndarray, through: np.ndarray) -> np.ndarray:
    """values @ through.T for (m, 3) values, as three column products: a threaded BLAS spends
    more on a product this thin than the product costs, once per block of every pass."""
    return values[:, :1] * through[:, 0] + values[:, 1:2] * through[:, 1] + values[:, 2:3] * through[:, 2]


def parameter_covariance(gyro: GyroFit, incl: ForceFit | None, acc: ForceFit, g0_sigma: float) -> dict[str, np.ndarray]:
    """Covariance of (gyro, incl, acc params), or (gyro, acc params) without inclinometers, by its
    parts (white_noise, bias_instability, gravity). The sensors' noises are independent, but the
    force fits use the gyro-derived platform axis and g0: their parameters move with the gyro
    parameters and g0 through their sensitivities, which couples all the blocks.
    With d = (gyro params, g0): x = M d + force noise, cov = M cov(d) M' + blockdiag(0, incl, acc)."""
    from scipy.linalg import block_diag  # when used: start-up (docs/architecture.md)
    p = len(gyro.params)

    def from_drivers(force: ForceFit) -> np.ndarray:
        m = np.zeros((len(force.params), p + 1))
        m[:, AXIS_PARAMS] = force.sensitivity[:, :3]
        m[:, p] = force.sensitivity[:, 3]
        return m

    forces = [f for f in (incl, acc) if f is not None]
    m = np.vstack([np.eye(p, p + 1), *(from_drivers(f) for f in forces)])
    parts = {part: m @ block_diag(gyro.cov_parts[part], np.zeros((1, 1))) @ m.T
             + block_diag(np.zeros((p, p)), *(f.cov_parts[part] for f in forces))
             for part in ("white_noise", "bias_instability")}
    parts["gravity"] = m @ block_diag(np.zeros((p, p)), np.array([[g0_sigma**2]])) @ m.T
    return parts


def white_noise_bound(inp: JointInput, result: JointResult, site: Site, gyro_arw_rad_sqrt_s: float) -> dict:
    """Cramer-Rao bound of every gyro-driven estimate for white gyro noise of the given density
    (angle random walk, rad/sqrt(s)) on this session's samples: the covariance an efficient
    estimator reaches when the noise is white and the accelerometers are perfect."""
    p = len(result.gyro.params)
    designs = _gyro_designs(result.gyro.chi, result.gyro.chi_rate, inp.time_s - inp.time_s.mean(),
                            int_to_imu(*alpha_beta(result.gyro.params[AXIS_PARAMS])), has_drift(result.gyro.params))
    cov = np.linalg.inv(_gram(designs, p)) * gyro_arw_rad_sqrt_s**2 * inp.rate_hz
    jac = result.jacobian[:, :p]
    return dict(zip(result.estimates, np.sqrt(np.diag(jac @ cov @ jac.T)).tolist()))

"""The sensor and its calibration as ROS 2 topics ([ros2]; docs/ros2.md): a `feeds.Feed` over
`calibd.ros2.wire.Publisher`.

- `imu/data_raw`: sensor_msgs/Imu in SI as the sensor sent it; covariances the datasheet's white
  noise over one sample interval (random walk squared times the sample rate), no orientation
  (orientation_covariance[0] = -1, REP 145).
- `imu/data`: the same with the served correction's biases taken out (the `[serve] correction`
  policy, as the corrected pty), its covariances the noise plus the biases' covariance.
- `imu/calibration`: the result document as JSON, latched.
- `imu/alignment`: the IMU housing's orientation in ENU (REP 103), latched: the result's NAV
  (North-West-Up) to IMU rotation turned by 90 degrees about Up (East = -West, North = North).
- `diagnostics`: the daemon's state and the stream's health once a second.
Stamps are the feeds thread's: the sensor's counter on the host's realtime clock.
"""

from __future__ import annotations

import time

import numpy as np
import structlog


from ..config import Ros2Config
from ..correction import ServedCorrection, bias_covariance, noise_covariances, si_biases, through, uncorrectable
from ..results import CalibrationResult, quaternion, result_json
from ..units import DEG
from ..frames import STANDARD_GRAVITY
from ..ros2.messages import Level, Status
from .feeds import STREAM_COUNTS, FeedBatch, Health

log = structlog.get_logger("calibd")

NWU_TO_ENU = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # v_ENU = C v_NWU
NO_ORIENTATION = -1.0  # orientation_covariance[0] of an Imu without an orientation (REP 145)


class Ros2Feed:
    """Publishes to the topics of `config`; Ros2Error (one line) when it cannot start."""

    def __init__(self, config: Ros2Config):
        from ..ros2.wire import Publisher  # here: the ros2 extra is loaded only when [ros2] is given

        self.publisher = Publisher(config.domain_id, {
            "imu_raw": config.data_raw_topic, "imu": config.data_topic, "calibration": config.calibration_topic,
            "alignment": config.alignment_topic, "diagnostics": config.diagnostics_topic}, config.frame_id)
        self._noise: tuple[tuple, np.ndarray, np.ndarray] | None = None  # (rate, range) -> gyro, acc covariances
        self._taken: tuple[ServedCorrection, dict, np.ndarray, np.ndarray] | None = None  # a correction's SI biases
        # and their gyro and accelerometer covariances, worked out once per correction
        self._counts: dict[str, int] = {}
        self._unpublished = False  # the stream's units were said to be unpublishable
        self._serial: str | None = None

    def samples(self, batch: FeedBatch) -> None:
        info = batch.info
        self._serial = info.serial_number
        if uncorrectable(info.format):  # incremental or integrated: not rates
            if not self._unpublished:
                log.warning("ros2_imu_unpublished", why=f"the sensor outputs {', '.join(uncorrectable(info.format))}: "
                                                         "sensor_msgs/Imu carries rates and accelerations")
            self._unpublished = True
            return
        self._unpublished = False
        gyro_noise, acc_noise = self._noise_covariances(info)
        gyro = batch.samples["gyro"].astype(np.float64) * DEG
        acc = batch.samples["acc"].astype(np.float64) * STANDARD_GRAVITY
        self.publisher.imu("imu_raw", batch.stamp_ns, gyro, acc, gyro_noise.ravel(), acc_noise.ravel())
        if batch.correction is not None:
            bias, gyro_bias_cov, acc_bias_cov = self._taken_out(batch.correction)
            maps = batch.correction.maps
            self.publisher.imu("imu", batch.stamp_ns, through(gyro - bias.get("gyro", 0.0), maps.get("gyro")),
                               through(acc - bias.get("acc", 0.0), maps.get("acc")),
                               (gyro_noise + gyro_bias_cov).ravel(), (acc_noise + acc_bias_cov).ravel())

    def _taken_out(self, correction: ServedCorrection) -> tuple[dict, np.ndarray, np.ndarray]:
        """A correction's biases in SI and their covariances (zero for a cluster none is taken
        from), kept while the correction lasts: a result's covariance is read once, not per batch."""
        if self._taken is None or self._taken[0] is not correction:
            bias = si_biases(correction.result)
            self._taken = (correction, bias, *(bias_covariance(correction.result, cluster) if cluster in bias
                                               else np.zeros((3, 3)) for cluster in ("gyro", "acc")))
        return self._taken[1:]

    def _noise_covariances(self, info) -> tuple[np.ndarray, np.ndarray]:
        """The datasheet's white noise of the unit's range at the stream's rate (diagonal, SI^2)."""
        ranges = None if info.configuration is None else info.configuration.acc_range_g
        key = (info.rate_hz, None if ranges is None else max(ranges))
        if self._noise is None or self._noise[0] != key:
            self._noise = (key, *noise_covariances(*key))
        return self._noise[1], self._noise[2]

    def state(self, state: str, detail: str, progress: dict) -> None:
        """The state reaches ROS 2 in the next diagnostics."""

    def result(self, result: CalibrationResult) -> None:
        now = time.time_ns()
        self.publisher.calibration(result_json(result).decode())
        matrix = result.rotation_matrix("nav_to_imu")
        if matrix is not None:
            w, x, y, z = quaternion(NWU_TO_ENU @ matrix.T)  # v_ENU = q v_IMU q*
            self.publisher.alignment(now, (x, y, z, w))

    def health(self, health: Health) -> None:
        """Two statuses: the calibration's state, and the stream's counts (WARN while one grows)."""
        grew = [name for name in STREAM_COUNTS if health.counts.get(name, 0) > self._counts.get(name, 0)]
        self._counts = dict(health.counts)
        state_level = Level.ERROR if health.state == "FAULT" else Level.OK
        if health.flagged_datagrams:
            level, words = Level.ERROR, f"{health.flagged_datagrams} datagrams flagged: {', '.join(health.faults)}"
        elif grew:
            level, words = Level.WARN, "growing: " + ", ".join(grew)
        else:
            level, words = Level.OK, "healthy"
        hardware_id = self._serial or ""
        values = {name: str(count) for name, count in sorted(health.counts.items())}
        self.publisher.diagnostics(time.time_ns(), [
            Status(state_level, "calibd: calibration", f"{health.state}: {health.detail}", hardware_id),
            Status(level, "calibd: stream", words, hardware_id,
                   {**values, "faults": " ".join(health.faults) or "none"})])

    def close(self) -> None:
        self.publisher.close()

"""Corrected samples as an MCAP file of the ROS 2 profile (`calibd apply ... -o OUT.mcap`): what
Foxglove, `ros2 bag play` (rosbag2's MCAP storage) and any MCAP reader take.

One channel, TOPIC, of sensor_msgs/msg/Imu in ROS 2 CDR (the schema's text is rosbags' own
generation of the message definition, not written here): angular velocity and linear
acceleration as apply writes them (SI, the result's biases and estimated factory terms taken
out, in IMU axes or the home frame), the covariances the datasheet's white noise at the
capture's rate plus the covariance of the biases taken out, no orientation (REP 145). Each
message's stamp, log time and publish time are its time: a recording's own stamps, or for a raw
capture, which has no wall clock, the seconds since the power-up's first sample counted from the
epoch (1970-01-01T00:00:00Z + time_s). The result applied is attached whole (`calibd-result.json`)
and apply's record of itself is the metadata `calibd.applied`, so the file says what it is.
"""

from __future__ import annotations

import json

import numpy as np

from stim300.rosimu import ABSENT, IMU, NS_PER_S, ImuEncoder

from .correction import bias_covariance
from .errors import CalibdError

NEEDS_EXTRA = "writing MCAP needs the recordings extra: pip install 'stim300-calib[recordings]'"
TOPIC = "/imu/data"
RESULT_ATTACHMENT = "calibd-result.json"


class McapError(CalibdError):
    """An MCAP file that cannot be written (the package missing); one line."""


def imu_schema_text() -> bytes:
    """sensor_msgs/msg/Imu's ros2msg definition with its dependencies, as rosbags generates it."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise McapError(NEEDS_EXTRA) from None
    text, _ = get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(IMU, ros_version=2)
    return text.encode()


class McapImuWriter:
    """Corrected column blocks (apply's writers' interface: `writer(columns)`) -> Imu messages
    in an MCAP written to the binary file `f`, stamped with a recording's own stamps (`stamp_ns`)
    or a capture's `time_s`; `finish()` writes the summary. `noise`: the gyro
    and accelerometer white-noise covariances at the capture's rate (correction.noise_covariances)."""

    def __init__(self, f, meta: dict, result, result_bytes: bytes, noise: tuple[np.ndarray, np.ndarray],
                 frame_id: str):
        try:
            from mcap.writer import Writer
        except ImportError:
            raise McapError(NEEDS_EXTRA) from None
        self.writer = Writer(f)
        self.writer.start(profile="ros2", library=f"{meta['software']} (mcap)")
        schema = self.writer.register_schema(IMU, "ros2msg", imu_schema_text())
        self.channel = self.writer.register_channel(TOPIC, "cdr", schema)
        self.writer.add_metadata("calibd.applied", {key: json.dumps(value) if not isinstance(value, str) else value
                                                    for key, value in meta.items()})
        self.writer.add_attachment(0, 0, RESULT_ATTACHMENT, "application/json", result_bytes)
        taken = meta["biases_subtracted"]
        self.covariances = [(noise[k] + (bias_covariance(result, cluster) if f"{cluster}_{unit}" in taken else 0.0))
                            .ravel() for k, (cluster, unit) in enumerate((("gyro", "rad_s"), ("acc", "m_s2")))]
        self.encoder = ImuEncoder(frame_id)
        self.sequence = 0

    def __call__(self, columns: dict[str, np.ndarray]) -> None:
        stamps = columns.get("stamp_ns")
        if stamps is None:
            stamps = np.round(columns["time_s"] * NS_PER_S).astype(np.int64)
        vectors = [columns.get(name) for name in ("gyro_rad_s", "acc_m_s2")]
        covariances = [cov if values is not None else ABSENT for values, cov in zip(vectors, self.covariances)]
        vectors = [np.zeros((len(stamps), 3)) if values is None else values for values in vectors]
        messages = self.encoder.encode(stamps, *vectors, *covariances)
        add = self.writer.add_message
        for stamp, data in zip(stamps.tolist(), messages):
            add(self.channel, stamp, data, stamp, self.sequence)
            self.sequence += 1

    def finish(self) -> None:
        self.writer.finish()

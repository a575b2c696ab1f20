"""calibd's ROS 2 topics: the STIM300's samples (sensor_msgs/Imu, raw and corrected), the latest
calibration (std_msgs/String of its JSON document), the alignment (geometry_msgs/QuaternionStamped)
and diagnostics (diagnostic_msgs/DiagnosticArray), written straight to DDS so a ROS 2 node on the
host subscribes without a bridge.

`messages` holds the names, the checks and the Imu encoding and needs no DDS; `wire` the DDS
writers, and it alone imports cyclonedds and rosbags (the ros2 extra). The names here are looked
up when first used (PEP 562), so `import calibd.ros2` loads neither; without the extra, asking for
`Publisher` raises Ros2Error saying how to install it.
"""

from stim300.lazy import lazy_exports

_HOMES = {  # public name -> the module of calibd.ros2 that defines it
    "Ros2Error": "messages", "Status": "messages", "Level": "messages", "dds_topic": "messages",
    "Publisher": "wire", "TOPICS": "wire",
}

__all__ = list(_HOMES)

__getattr__ = lazy_exports(__name__, _HOMES)

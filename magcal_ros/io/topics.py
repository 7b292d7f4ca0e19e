"""Topic names, one place for bags and nodes.

Nodes use relative names (``mag1/raw``), so that a namespace or a remap moves them all;
bags store the absolute names a node in the root namespace publishes (``/mag1/raw``).
"""

from __future__ import annotations

RAW_SUFFIX = "raw"
CORRECTED_SUFFIX = "corrected"
TEMPERATURE_SUFFIX = "temperature"
IMU = "imu"
"""Default IMU topic (sensor_msgs/Imu): relative for the nodes, ``/imu`` in a bag."""
FIELD = "field"
"""Corrected field at the array centre (sensor_msgs/MagneticField, T)."""
GRADIENT = "gradient"
"""Gradient tensor (std_msgs/Float64MultiArray, 3x3 row-major, T/m): three or more sensors."""
BASELINE_GRADIENT = "baseline_gradient"
"""Gradient along the line of a collinear array, e.g. two sensors (geometry_msgs/Vector3Stamped,
``dB_j/ds`` in T/m, platform frame; ``s`` runs from the first sensor towards the last)."""
GRADIENT_STAMPED = "gradient_stamped"
"""The same tensor with the set's stamp and frame (sensor_msgs/JointState: names gradient.xx .. gradient.zz,
position = the 9 components in T/m, row-major)."""
DEFAULT_FRAME_ID = "magcal_array"
"""Default platform frame of every corrected output."""


def raw(name: str) -> str:
    """Relative topic of a sensor's raw readings: ``<name>/raw``."""
    return f"{name.strip('/')}/{RAW_SUFFIX}"


def corrected(name: str) -> str:
    """Relative topic of a sensor's corrected readings: ``<name>/corrected``."""
    return f"{name.strip('/')}/{CORRECTED_SUFFIX}"


def temperature(name: str) -> str:
    """Relative topic of a sensor's temperature (sensor_msgs/Temperature, deg C): ``<name>/temperature``."""
    return f"{name.strip('/')}/{TEMPERATURE_SUFFIX}"


def absolute(topic: str) -> str:
    """The topic in the root namespace, as a bag records it: ``/`` + relative name."""
    return "/" + topic.lstrip("/")


def sensor_of_raw(topic: str) -> str | None:
    """The sensor name of an absolute ``/<name>/raw`` topic, else None."""
    suffix = "/" + RAW_SUFFIX
    if topic.startswith("/") and topic.endswith(suffix) and len(topic) > len(suffix) + 1:
        return topic[1 : -len(suffix)]
    return None


def current_channel(topic: str) -> str:
    """The interference channel of a current topic: the topic without its leading ``/``
    (``/thruster1/battery`` -> ``thruster1/battery``), as calibration files and CSV columns name it."""
    return topic.strip("/")


def current_topic(channel: str) -> str:
    """The absolute topic of an interference channel (inverse of :func:`current_channel`)."""
    return absolute(channel.strip("/"))


RAW_TOPIC_HELP = "/<name>/raw"
"""How help texts name the raw topics."""

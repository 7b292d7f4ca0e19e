"""magcal_ros: calibration of a magnetic gradient tensor array of fluxgates.

The math (everything importable from here) uses numpy only, no ROS. ROS 2 nodes live in
:mod:`magcal_ros.nodes`, rosbag2 I/O in :mod:`magcal_ros.bagio`, the ``magcal`` command
in :mod:`magcal_ros.cli`.
"""

from magcal_ros.calibrate import DEFAULT_METHOD, METHODS, CalibrationResult, SolveOptions, calibrate_array
from magcal_ros.calibration import ArrayCalibration
from magcal_ros.errors import CalibrationFailed, InputError, MagcalError, ObservabilityError
from magcal_ros.geometry import ArrayGeometry
from magcal_ros.recording import Recording
from magcal_ros.sensor_model import SensorErrors

__version__ = "0.1.0"

__all__ = [
    "ArrayCalibration",
    "ArrayGeometry",
    "CalibrationFailed",
    "CalibrationResult",
    "DEFAULT_METHOD",
    "InputError",
    "METHODS",
    "MagcalError",
    "ObservabilityError",
    "Recording",
    "SensorErrors",
    "SolveOptions",
    "calibrate_array",
]

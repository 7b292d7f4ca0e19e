"""magcal_ros: calibration of a magnetic gradient tensor array of fluxgates.

The math (everything importable from here) uses numpy and scipy only, no ROS. ROS 2
nodes live in :mod:`magcal_ros.nodes`, rosbag2 I/O in :mod:`magcal_ros.bagio`, the
``magcal`` command in :mod:`magcal_ros.cli`. Names below are imported on first use, so
that ``import magcal_ros.<module>`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "ArrayCalibration": "magcal_ros.calibration",
    "ArrayGeometry": "magcal_ros.geometry",
    "CalibrationFailed": "magcal_ros.errors",
    "CalibrationResult": "magcal_ros.calibrate",
    "DEFAULT_METHOD": "magcal_ros.calibrate",
    "InputError": "magcal_ros.errors",
    "METHODS": "magcal_ros.calibrate",
    "MagcalError": "magcal_ros.errors",
    "ObservabilityError": "magcal_ros.errors",
    "Recording": "magcal_ros.recording",
    "SensorErrors": "magcal_ros.sensor_model",
    "SolveOptions": "magcal_ros.calibrate",
    "calibrate_array": "magcal_ros.calibrate",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'magcal_ros' has no attribute {name!r}")

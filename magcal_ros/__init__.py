"""magcal_ros: calibration of a magnetic gradient tensor array of fluxgates, with ROS 2 nodes.

Layers, lowest first; a module imports only from its own layer or lower ones:

- :mod:`magcal_ros.core`: the math on numpy arrays (error model, fits, alignment, tensor,
  the calibration object, the set synchroniser, the ``Recording`` type). No I/O, no ROS.
- :mod:`magcal_ros.methods`: the calibration pipeline and the selectable methods.
- :mod:`magcal_ros.sim`: simulated arrays, manoeuvres and the papers' scenarios.
- :mod:`magcal_ros.io`: files and messages: CDR codec, rosbag2, CSV, calibration files.
- :mod:`magcal_ros.nodes`: the two ROS 2 nodes (rclpy).
- :mod:`magcal_ros.app`: the ``magcal`` command, the demo, plots and the replay driver.

The most used names are importable from here, loaded on first use; the functions of
:mod:`magcal_ros.api` (``calibrate``, ``correct``, ``check_health``, ``load_calibration``,
``save_calibration``, ``array_geometry``) are the Python face for notebooks (docs/python_api.md).
"""

from __future__ import annotations

import os

# The solvers work on small matrices (tens of parameters): one BLAS thread is fastest, and a
# node on a busy vehicle computer must not fight other processes for cores. Set before numpy
# loads; a user's own setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from magcal_ros._lazy import lazy_exports  # noqa: E402

__version__ = "0.1.0"

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "ArrayCalibration": "magcal_ros.core.calibration",
        "ArrayGeometry": "magcal_ros.core.geometry",
        "CalibrationFailed": "magcal_ros.errors",
        "CalibrationResult": "magcal_ros.methods.pipeline",
        "DEFAULT_METHOD": "magcal_ros.methods.strategies",
        "InputError": "magcal_ros.errors",
        "METHODS": "magcal_ros.methods.strategies",
        "MagcalError": "magcal_ros.errors",
        "ObservabilityError": "magcal_ros.errors",
        "Recording": "magcal_ros.core.recording",
        "SensorErrors": "magcal_ros.core.sensor_model",
        "SolveOptions": "magcal_ros.methods.pipeline",
        "calibrate_array": "magcal_ros.methods.pipeline",
        "array_geometry": "magcal_ros.api",
        "calibrate": "magcal_ros.api",
        "check_health": "magcal_ros.api",
        "correct": "magcal_ros.api",
        "load_calibration": "magcal_ros.api",
        "save_calibration": "magcal_ros.api",
    },
)

"""The physical bounds of every quantity a calibration holds: one check for files and parameters.

Every reader of a calibration (``magcal correct`` and ``batch``, ``--prior``, both nodes' parameters)
builds it through :meth:`~magcal_ros.core.calibration.ArrayCalibration.from_parameters`, which applies
these bounds (the temperature terms and the output rotation are checked where the calibration is
built, :class:`~magcal_ros.core.calibration.ArrayCalibration`), and reads the calibration health's reference (noise, intensity) through
:func:`check_noise` and :func:`check_intensity`. A value outside them is not a calibration of a
fluxgate array on a vehicle: a unit error (nT for T, mA for A), a sign lost, or a corrupt file. It is
refused naming the key, never applied (a file with ``positions`` of 1e300 m or an interference of
1e30 T/A wrote 7e30 T in every row).

======================================  ==========================================================
key                                     bound
======================================  ==========================================================
``positions``                           within :data:`MAX_POSITION` of the origin (m)
``<name>.matrix``, ``<name>.offset``    gains and offset of a fluxgate (``check_sensor``)
``<name>.interference``                 at most :data:`MAX_INTERFERENCE` T/A per component
``<name>.offset_per_kelvin``            at most :data:`MAX_OFFSET_TEMPCO` T/K per axis
``<name>.matrix_per_kelvin``            at most :data:`MAX_MATRIX_TEMPCO` 1/K per element
``temperature_reference``               within :data:`TEMPERATURE_RANGE` (deg C)
``<name>.calibration_temperatures``     [min, max] deg C, finite, min <= max, within :data:`TEMPERATURE_RANGE`
``<name>.time_offset``                  within +-0.5 s (``MAX_TIME_OFFSET``)
``<name>.covariance``                   finite, symmetric, a non-negative diagonal (T^2)
``output_rotation``                     a rotation (orthonormal, determinant +1)
``<name>.noise``                        0 (unknown) or a noise up to :data:`MAX_NOISE` T
``calibration_intensity``               0 (unknown) or an Earth-like field (T)
======================================  ==========================================================
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.side_streams import TEMPERATURE_RANGE
from magcal_ros.core.units import EARTH_FIELD_RANGE
from magcal_ros.errors import InputError

__all__ = ["MAX_INTERFERENCE", "MAX_MATRIX_TEMPCO", "MAX_NOISE", "MAX_OFFSET_TEMPCO", "MAX_POSITION",
           "TEMPERATURE_RANGE", "check_bounded", "check_covariance", "check_intensity", "check_noise",
           "check_positions", "check_temperature_span"]

Array = NDArray[np.float64]

MAX_POSITION: float = 50.0
"""Largest distance (m) of a sensor from the array's origin: a vehicle's array is metres across."""
MAX_INTERFERENCE: float = 1e-4
"""Largest interference gain (T/A): 100,000 nT per ampere, a cable touching the sensor."""
MAX_OFFSET_TEMPCO: float = 1e-6
"""Largest offset change per kelvin (T/K): 1000 nT/K, beyond a consumer MEMS sensor's."""
MAX_MATRIX_TEMPCO: float = 1e-2
"""Largest gain change per kelvin (1/K): 1 % a kelvin."""
MAX_NOISE: float = 1e-3
"""Largest noise per axis (T) a calibration may record."""


def check_positions(positions: Any) -> None:
    """:class:`InputError` unless every position (m) is finite and within :data:`MAX_POSITION`."""
    p = np.asarray(positions, dtype=float)
    if p.size and (not np.all(np.isfinite(p)) or np.abs(p).max() > MAX_POSITION):
        worst = p.reshape(-1)[np.argmax(np.where(np.isfinite(p), np.abs(p), np.inf).reshape(-1))]
        raise InputError(f"positions must be within {MAX_POSITION:g} m of the array's origin (metres), got {worst:g}")


def check_bounded(name: str, values: Array, limit: float, unit: str) -> Array:
    """``values`` when finite and at most ``limit`` in magnitude; :class:`InputError` naming ``name`` else."""
    v = np.asarray(values, dtype=float)
    if v.size and (not np.all(np.isfinite(v)) or np.abs(v).max() > limit):
        worst = v.reshape(-1)[np.argmax(np.where(np.isfinite(v), np.abs(v), np.inf).reshape(-1))]
        raise InputError(f"{name} must be finite and within +-{limit:g} {unit}, got {worst:g}")
    return v


def check_covariance(name: str, cov: Array) -> None:
    """:class:`InputError` unless a sensor's correction covariance (3, 3, T^2) is finite, symmetric and has a
    non-negative diagonal (NaN throughout: not given)."""
    c = np.asarray(cov, dtype=float)
    if np.all(np.isnan(c)):
        return
    scale = max(float(np.abs(c).max()), 1e-300) if np.all(np.isfinite(c)) else math.inf
    if not np.all(np.isfinite(c)) or np.any(np.diag(c) < 0) or np.abs(c - c.T).max() > 1e-9 * scale:
        raise InputError(f"{name}.covariance must be a finite symmetric 3x3 with a non-negative diagonal (T^2)")


def check_noise(name: str, value: Any) -> float:
    """A sensor's recorded noise per axis (T; 0 unknown); :class:`InputError` naming ``name`` unless 0 or a
    positive noise up to :data:`MAX_NOISE`."""
    v = _finite(name, value)
    if not 0.0 <= v <= MAX_NOISE:
        raise InputError(f"{name} must be 0 (unknown) or a noise in T up to {MAX_NOISE:g}, got {v:g}")
    return v


def check_intensity(name: str, value: Any) -> float:
    """The intensity a calibration was made in (T; 0 unknown); :class:`InputError` naming ``name`` unless 0 or
    Earth-like."""
    f = _finite(name, value)
    low, high = EARTH_FIELD_RANGE
    if not (f == 0.0 or low <= f <= high):
        raise InputError(f"{name} {f:g} T is not Earth-like ({low:g} .. {high:g} T, or 0 for unknown)")
    return f


def check_temperature_span(name: str, value: Any) -> Array:
    """The temperatures (deg C) a sensor was calibrated over as ``[min, max]``; :class:`InputError` naming
    ``name`` unless two finite numbers, min <= max, both within :data:`TEMPERATURE_RANGE` (not kelvin)."""
    try:
        t = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be [min, max] in deg C, got {value!r}") from None
    low, high = TEMPERATURE_RANGE
    if t.size != 2 or not np.all(np.isfinite(t)):
        raise InputError(f"{name} must be two finite numbers [min, max] in deg C, got {t.tolist()}")
    if t[0] > t[1]:
        raise InputError(f"{name} [{t[0]:g}, {t[1]:g}] has its minimum above its maximum (deg C)")
    if t[0] < low or t[1] > high:
        raise InputError(f"{name} [{t[0]:g}, {t[1]:g}] is not a span of temperatures in deg C ({low:g} .. {high:g})")
    return t


def _finite(name: str, value: Any, unit: str = "T") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise InputError(f"{name} must be a finite number ({unit}), got {value!r}")
    return float(value)

"""The Python face of magcal_ros: calibrate, correct and check a calibration on numpy arrays.

What ``magcal calibrate``, ``magcal correct`` and the correction node's ``/diagnostics`` do, for a
notebook or a script, with no ROS and no files (:func:`load_calibration` and :func:`save_calibration` read and write the same
calibration files the nodes load). Each function is a thin front to the package's own code
(:func:`~magcal_ros.methods.pipeline.calibrate_array`,
:meth:`~magcal_ros.core.calibration.ArrayCalibration.outputs`,
:class:`~magcal_ros.core.calibration_health.CalibrationHealth`), so the numbers are theirs.

Conventions: Tesla, metres, the array's platform frame; raw sets are an array (N, S, 3), N sets
of S sensors; stamps integer nanoseconds (or float seconds); ``G[i, j] = dB_j/dx_i`` in T/m. See
``docs/python_api.md``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.geometry import ArrayGeometry, default_names
from magcal_ros.errors import InputError

if TYPE_CHECKING:
    from magcal_ros.core.calibration import ArrayCalibration, CorrectedSets
    from magcal_ros.core.calibration_health import DriftReport
    from magcal_ros.methods.pipeline import CalibrationResult, SolveOptions


def array_geometry(sensors: int, positions: ArrayLike | None = None, names: Sequence[str] | None = None) -> ArrayGeometry:
    """The array of ``sensors`` sensors: ``positions`` (S, 3) m in the platform frame, or by default one
    sensor at the origin or the 0.4 m planar cross for four (any other count needs positions).
    ``names`` default ``mag1, mag2, ...``."""
    names = tuple(names) if names is not None else default_names(sensors)
    if len(names) != sensors:
        raise InputError(f"{len(names)} names for {sensors} sensors")
    if positions is not None:
        return ArrayGeometry(names, np.asarray(positions, dtype=float))
    if sensors in (1, 4):
        return ArrayGeometry.ring(sensors, names=names)
    raise InputError(f"{sensors} sensors: give their positions (S, 3) in m (only one sensor or the four-sensor cross "
                     "have a default)")


def _stamps_ns(stamps: ArrayLike | None) -> NDArray[np.int64] | None:
    """Integer nanoseconds from integer nanoseconds or float seconds."""
    if stamps is None:
        return None
    s = np.asarray(stamps)
    if s.dtype.kind in "iu":
        return s.astype(np.int64)
    if s.dtype.kind != "f" or not np.all(np.isfinite(s)):
        raise InputError("stamps must be integer nanoseconds or finite float seconds")
    return np.rint(s * 1e9).astype(np.int64)


def calibrate(
    raw: ArrayLike,
    positions: ArrayLike | None = None,
    reference_field: float | None = None,
    *,
    names: Sequence[str] | None = None,
    stamps: ArrayLike | None = None,
    prior: ArrayCalibration | None = None,
    currents: ArrayLike | None = None,
    channels: Sequence[str] = (),
    temperatures: ArrayLike | None = None,
    method: str = "ml",
    options: SolveOptions | None = None,
) -> CalibrationResult:
    """Solve an array's calibration from raw sets ``raw`` (N, S, 3) T of a turning array in a uniform field.

    ``positions`` (S, 3) m (default: one sensor, or the 0.4 m cross for four); ``reference_field`` the total
    intensity F in T (None: relative, the sensors' mean gain taken as 1). ``stamps`` (N,) put the sets in
    time order (needed to read the noise from the data and to estimate lags). ``prior``: a previous
    calibration, to recalibrate what this manoeuvre determines and keep the rest. ``currents`` (N, m) A of
    ``channels``: their interference is estimated too; ``temperatures`` (N, S) or (N,) deg C: temperature
    terms. The result's ``calibration`` corrects (:func:`correct`), its ``summary()`` is the line
    ``magcal calibrate`` prints, and ``warnings`` what it warns. Raises
    :class:`~magcal_ros.errors.ObservabilityError` when the manoeuvre does not determine the calibration,
    :class:`~magcal_ros.errors.CalibrationFailed` when a quality gate refuses it (both say why and what to
    do) and :class:`~magcal_ros.errors.InputError` for bad input.
    """
    from magcal_ros.methods.pipeline import calibrate_array

    r = np.asarray(raw, dtype=float)
    if r.ndim != 3 or r.shape[-1] != 3:
        raise InputError(f"raw sets must have shape (N, S, 3) in T, got {r.shape}")
    geo = array_geometry(r.shape[1], positions, names)
    return calibrate_array(r, geo, reference_field, method, options, prior, currents, tuple(channels),
                           _stamps_ns(stamps), temperatures)


def correct(raw: ArrayLike, calibration: ArrayCalibration, currents: ArrayLike | None = None,
            temperatures: ArrayLike | None = None, gradient_method: str | None = None) -> CorrectedSets:
    """Apply ``calibration`` to raw sets (N, S, 3) T: ``.vectors`` (N, S, 3) T, ``.centre`` (N, 3) T (the
    centre field), and ``.tensor`` (N, 3, 3) T/m or ``.baseline`` (N, 3) T/m as the positions allow, in the
    calibration's output frame (its IMU's, or the array's own: the sensors' mean axes). ``currents`` (N, m) A
    of its interference channels and ``temperatures`` (N, S) deg C when it has those terms. The tensor by
    ``gradient_method`` (default: the difference formula for the cross, least squares otherwise), what
    ``magcal correct`` and the correction node publish."""
    from magcal_ros.core.tensor import method_for

    return calibration.outputs(np.asarray(raw, dtype=float), method_for(calibration.geometry, gradient_method),
                               currents, temperatures)


def check_health(raw: ArrayLike, calibration: ArrayCalibration, stamps: ArrayLike, window: float = 60.0,
                 currents: ArrayLike | None = None, temperatures: ArrayLike | None = None) -> DriftReport:
    """Whether ``calibration`` still fits the raw sets (N, S, 3) T stamped ``stamps`` (N,) (ns, or float s),
    as the correction node judges it on ``/diagnostics``: over the last ``window`` s of sets, per sensor the
    part of ``|B|`` that follows the attitude and the sensors' disagreement beyond the measured gradient,
    against the noise the calibration stored. The report's ``drifted``, ``level`` (0 OK, 1 WARN, 2 ERROR),
    ``message`` (``mag3 calibration drifted: ...``) and per sensor ``sensors`` (figures in T)."""
    from magcal_ros.core.calibration_health import CalibrationHealth, DriftThresholds, noise_and_intensity

    if not (np.isfinite(window) and window > 0):
        raise InputError(f"window must be a positive number of seconds, got {window}")
    r = np.asarray(raw, dtype=float)
    ns = _stamps_ns(stamps)
    if ns is None or r.ndim != 3 or len(ns) != len(r):
        raise InputError(f"need raw sets (N, S, 3) and one stamp per set, got {r.shape} and {np.shape(stamps)}")
    noise, intensity = noise_and_intensity(calibration.metadata, calibration.geometry.names)
    health = CalibrationHealth(calibration.geometry, noise, intensity, DriftThresholds(window_ns=int(window * 1e9)))
    vectors = calibration.apply_array(r, currents, temperatures)  # the array frame, as the node judges it
    for stamp, v in zip(ns, vectors):
        health.add(int(stamp), v)
    return health.assess()


def load_calibration(path: str | os.PathLike[str]) -> ArrayCalibration:
    """A calibration file (the ROS 2 parameters file ``magcal calibrate`` writes and the nodes load)."""
    from magcal_ros.io import calibration_file

    return calibration_file.read(path)


def save_calibration(path: str | os.PathLike[str], calibration: ArrayCalibration) -> None:
    """Write ``calibration`` as a calibration file, atomically (an existing file is kept as a backup)."""
    from magcal_ros.io import calibration_file

    calibration_file.write(path, calibration)

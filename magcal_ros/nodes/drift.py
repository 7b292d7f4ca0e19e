"""Calibration health on ``/diagnostics`` for the correction node: its parameters and its status
(the judgement itself is :mod:`magcal_ros.core.calibration_health`).

Parameters: per sensor ``<name>.noise`` (T, 1-sigma per axis at calibration; 0 = unknown) and
``calibration_intensity`` (T, the intensity the calibration maps ``|B|`` to; 0 = unknown), both
written by ``magcal calibrate`` and the calibration node into the calibration file and pushed
with every calibration; ``health_window`` (s, read-only), ``health_warn_factor`` and
``health_error_factor`` (settable while the node runs; the warning factor never above the error
factor). The status is named ``<node>: calibration``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from magcal_ros.core import calibration_bounds as bounds
from magcal_ros.core.calibration_health import (
    DEFAULT_ERROR_FACTOR,
    DEFAULT_WARN_FACTOR,
    DEFAULT_WINDOW,
    MIN_BLOCKS,
    BLOCKS,
    OK,
    DriftReport,
    DriftThresholds,
)
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError
from magcal_ros.nodes import common

SENSOR_SUFFIX = "noise"
"""Per-sensor parameter ``<name>.noise``."""
INTENSITY = "calibration_intensity"
WINDOW_RANGE: tuple[float, float] = (10.0, 3600.0)
FACTOR_RANGE: tuple[float, float] = (1.0, 1e6)
FACTORS: tuple[str, str] = ("health_warn_factor", "health_error_factor")
"""The parameters of the factors on the noise (WARN, ERROR): settable while the node runs."""
MAX_NOISE: float = bounds.MAX_NOISE
STATUS_SUFFIX = ": calibration"
"""The health status is named ``<node full name>: calibration``."""


def declare_reference(node: Any, names: Sequence[str]) -> None:
    """Declare ``<name>.noise`` for ``names`` and ``calibration_intensity`` (what the calibration stored)."""
    d = common.describe
    for name in names:
        node.declare_parameter(
            f"{name}.{SENSOR_SUFFIX}", 0.0,
            d(f"noise of {name} per axis at calibration (T, 1-sigma; the calibration file has it): the calibration "
              "health compares its figures with it; 0 = unknown (the noise seen live is used)",
              constraints=f"0 .. {MAX_NOISE:g} T", numbers=True),
        )
    node.declare_parameter(
        INTENSITY, 0.0,
        d("total intensity (T) the calibration maps |B| to (the calibration file has it): the calibration health "
          "shows how far each sensor's |B| strays from it (<name>.tmi_offset_nT); a recalibration from the running "
          "calibration starts from it; 0 = unknown", constraints="0, or 1e-7 .. 1e-3 T", numbers=True),
    )


def declare_thresholds(node: Any) -> DriftThresholds:
    """Declare ``health_window``, ``health_warn_factor``, ``health_error_factor``; the thresholds they give.

    :class:`InputError` (the node does not start) when the warning factor is above the error factor."""
    d = common.describe
    window = float(node.declare_parameter(
        "health_window", DEFAULT_WINDOW,
        d("seconds of corrected sets the calibration health judges at once (a sliding window, long enough to "
          "span attitude changes; judged once half full; a drift is named about half a window after it happens)",
          read_only=True, numbers=True, floats=WINDOW_RANGE)).value)
    values = {FACTORS[0]: node.declare_parameter(
        FACTORS[0], DEFAULT_WARN_FACTOR,
        d("the calibration health is a WARN (drifted: recalibrate) when a sensor's TMI residual or its "
          "disagreement beyond the gradient exceeds this many times its noise at calibration (and is "
          "significant against the window's scatter); at most health_error_factor", numbers=True,
          floats=FACTOR_RANGE)).value}
    values[FACTORS[1]] = node.declare_parameter(
        FACTORS[1], DEFAULT_ERROR_FACTOR,
        d("... and an ERROR above this many times the noise (at least health_warn_factor)", numbers=True,
          floats=FACTOR_RANGE)).value
    return factors(values, DriftThresholds(int(window * NS_PER_S)))


def factors(values: Mapping[str, Any], current: DriftThresholds) -> DriftThresholds:
    """``current`` with the factors ``health_warn_factor`` and ``health_error_factor`` in ``values`` (those not
    there as they are); :class:`InputError` with the reason for a factor that is not a number in
    :data:`FACTOR_RANGE` or a warning factor above the error factor (a WARN comes before an ERROR)."""
    warn = _number(FACTORS[0], values.get(FACTORS[0], current.warn_factor), "times the noise")
    error = _number(FACTORS[1], values.get(FACTORS[1], current.error_factor), "times the noise")
    low, high = FACTOR_RANGE
    for name, value in zip(FACTORS, (warn, error)):
        if not low <= value <= high:
            raise InputError(f"{name} must be {low:g} .. {high:g} (times the noise), got {value:g}")
    if warn > error:
        raise InputError(f"health_warn_factor {warn:g} is above health_error_factor {error:g}: a WARN must come at a "
                         "smaller figure than an ERROR; set health_warn_factor at most health_error_factor")
    return replace(current, warn_factor=warn, error_factor=error)


def reference(values: dict[str, Any], names: Sequence[str]) -> tuple[tuple[float, ...], float]:
    """The noise per sensor (T, 0 unknown) and the intensity (T, 0 unknown) in parameter ``values``;
    :class:`InputError` naming a bad one (the bounds every reader applies,
    :mod:`~magcal_ros.core.calibration_bounds`)."""
    noise = []
    for name in names:
        value = values.get(f"{name}.{SENSOR_SUFFIX}")
        noise.append(bounds.check_noise(f"{name}.{SENSOR_SUFFIX}", 0.0 if value is None else value))
    value = values.get(INTENSITY)
    return tuple(noise), bounds.check_intensity(INTENSITY, 0.0 if value is None else value)


def _number(name: str, value: Any, unit: str = "T") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise InputError(f"{name} must be a finite number ({unit}), got {value!r}")
    return float(value)


def not_assessed(why: str) -> DriftReport:
    """A report saying why the calibration is not judged (nothing calibrated, a sensor uncorrected)."""
    return DriftReport(OK, f"not assessed: {why}", False, values={"drifted": "false", "figure": ""})


def status(node_name: str, hardware_id: str, report: DriftReport) -> DiagnosticStatus:
    """The calibration health as its own DiagnosticStatus (``<node>: calibration``)."""
    return DiagnosticStatus(level=bytes([report.level]), name=node_name + STATUS_SUFFIX, message=report.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in report.values.items()])


def judged_after(thresholds: DriftThresholds) -> float:
    """Seconds of sets before the first judgement (half the window)."""
    return thresholds.window_ns / NS_PER_S * MIN_BLOCKS / BLOCKS

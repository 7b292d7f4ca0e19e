"""Residuals and noise floors (SI units) used by the summary, tests and benchmarks."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammainccinv

if TYPE_CHECKING:
    from magcal_ros.core.geometry import ArrayGeometry

Array = NDArray[np.float64]

TENSOR_COMPONENTS: tuple[str, ...] = ("xx", "xy", "xz", "yx", "yy", "yz")
"""The six measured components of Li et al.'s (2018) Table 4 (rows x and y of ``G``)."""


def rms(values: ArrayLike, axis: int | tuple[int, ...] | None = None) -> Array:
    """Root mean square."""
    v = np.asarray(values, dtype=float)
    return np.sqrt(np.mean(v * v, axis=axis))


def tmi_rms(vectors: ArrayLike, intensity: float) -> Array:
    """Per-sensor RMS of ``|b| - F`` (T) for vectors (N, S, 3) or (N, 3)."""
    return rms(np.linalg.norm(np.asarray(vectors, dtype=float), axis=-1) - intensity, axis=0)


def tensor_component_rms(g: ArrayLike, truth: ArrayLike | float = 0.0) -> Array:
    """RMS error (T/m) of the six measured components ``xx, xy, xz, yx, yy, yz``."""
    err = np.asarray(g, dtype=float) - np.asarray(truth, dtype=float)
    return rms(err[:, :2, :].reshape(len(err), 6), axis=0)


def tensor_rms(g: ArrayLike, truth: ArrayLike | float = 0.0) -> float:
    """RMS error (T/m) over the six measured components and all sets."""
    return float(rms(tensor_component_rms(g, truth)))


def tensor_floor(noise: float, baseline: float) -> float:
    """Tensor noise floor ``sqrt(2) sigma / d`` (T/m) of the cross difference formula."""
    return float(np.sqrt(2.0) * noise / baseline)


def gradient_floor(noise: float, geometry: "ArrayGeometry", method: str | None = None) -> float | None:
    """The gradient noise floor (T/m) of an array whose sensors carry white noise ``noise`` (T, 1-sigma per
    axis): the RMS over the six measured tensor components (as :func:`tensor_rms`) for three or more
    sensors spread in a plane or in space, over the three components of ``dB/ds`` for sensors on a line,
    None for one sensor position. The planar cross by the difference formula gives :func:`tensor_floor`
    (``sqrt(2) sigma / d``); any other layout (or ``method``) is propagated through its own estimator."""
    from magcal_ros.core.tensor import baseline_gradient, gradient, method_for

    kind = geometry.gradient_kind
    if kind == "none":
        return None
    s = geometry.size
    impulses = np.eye(3 * s).reshape(3 * s, s, 3)  # one unit reading per sensor axis: the estimator's columns
    if kind == "baseline":
        columns = baseline_gradient(impulses, geometry)  # (3S, 3)
        return float(noise * np.sqrt(np.sum(columns**2) / 3.0))
    columns = gradient(impulses, geometry, method_for(geometry, method))[:, :2, :].reshape(3 * s, 6)
    return float(noise * np.sqrt(np.sum(columns**2) / 6.0))


def chi2_isf(p: float, dof: float) -> float:
    """The chi-square quantile with upper tail ``p`` for ``dof`` (real) degrees of freedom: ``P(X > x) = p``
    (the median at 0.5). Through the inverse regularised gamma function: no ``scipy.stats`` import (about a
    second) and no per-call overhead of its distribution objects."""
    return 2.0 * float(gammainccinv(0.5 * dof, p))

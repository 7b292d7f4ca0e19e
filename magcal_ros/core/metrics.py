"""Residuals and noise floors (SI units) used by the summary, tests and benchmarks."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

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

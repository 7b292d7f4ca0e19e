"""Can the collected attitudes determine a calibration? (docs/methods.md, pitfall B)

A full 9-parameter scalar calibration needs readings spread in three dimensions:
rotations about one axis put every reading on one plane (an ellipse), and a quadric
through a planar ellipse is not unique. These checks run before any solve and raise
:class:`ObservabilityError` with what to do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.batched import axis_major
from magcal_ros.errors import InputError, ObservabilityError

Array = NDArray[np.float64]

MIN_SAMPLES: int = 12
"""Fewest synchronized sets accepted (9 scalar + 3 alignment parameters per sensor)."""
MIN_THICKNESS: float = 0.05
"""Smallest accepted ratio of the thinnest to the widest spread of the readings."""
MIN_SPREAD: float = 0.05
"""Smallest accepted widest spread of the readings relative to the field intensity."""
MIN_QUADRIC_RATIO: float = 1e-3
"""Smallest accepted 9th-to-1st singular value ratio of the quadric design matrix."""

_AXIS_NAMES = ("x", "y", "z")


SPHERE_CELLS: int = 42
"""Cells of the direction coverage measure (and of the calibration node's sample buffer)."""


def sphere_cells(count: int = SPHERE_CELLS) -> Array:
    """Roughly uniform unit directions (count, 3), a Fibonacci sphere: centres of direction cells."""
    k = np.arange(count) + 0.5
    z = 1.0 - 2.0 * k / count
    phi = np.pi * (1.0 + 5**0.5) * k
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


_CELLS32 = sphere_cells().astype(np.float32)


@dataclass(frozen=True)
class Excitation:
    """How well a set of raw readings (one sensor or the array centre) excites a calibration."""

    samples: int
    spread: Array
    """Standard deviations along the principal axes, largest first, relative to the mean norm."""
    normal: Array
    """Unit direction of the thinnest spread: the rotation axis if there was only one."""
    coverage: float
    """Fraction of 42 sphere cells visited by the reading directions (0..1; cells decided in single
    precision: a direction within about 1e-7 of a boundary between two counts for both)."""
    quadric_ratio: float
    """9th/1st singular value of the normalised quadric design (0 when not unique)."""

    @property
    def thickness(self) -> float:
        """Thinnest over widest spread: ~0 for a single-axis rotation."""
        return float(self.spread[2] / self.spread[0]) if self.spread[0] > 0 else 0.0

    @property
    def axis_name(self) -> str:
        """Platform axis closest to :attr:`normal`."""
        return _AXIS_NAMES[int(np.argmax(np.abs(self.normal)))]

    def problem(self) -> str | None:
        """Why a calibration cannot be solved from these readings, or None if it can."""
        others = " or ".join(a for a in _AXIS_NAMES if a != self.axis_name)
        if self.samples < 3:
            return f"only {self.samples} synchronized sets; turn the array about at least two axes while collecting"
        if self.spread[0] < MIN_SPREAD:
            return (
                "the readings barely change (the array hardly rotated); turn it through large angles "
                "about at least two axes"
            )
        if self.thickness < MIN_THICKNESS or (self.samples >= 10 and self.quadric_ratio < MIN_QUADRIC_RATIO):
            return (
                f"all readings lie in one plane: the array was rotated about one axis only "
                f"(about {self.axis_name}, normal {np.round(self.normal, 2).tolist()}); "
                f"a full calibration also needs a rotation about {others}"
                + (": pitch or roll the vehicle, not only yaw" if self.axis_name == "z" else "")
            )
        if self.samples < MIN_SAMPLES:
            return (
                f"only {self.samples} synchronized sets; need at least {MIN_SAMPLES}, "
                "collected while turning the array about at least two axes"
            )
        return None

    def check(self) -> None:
        """Raise :class:`ObservabilityError` if :meth:`problem` finds one."""
        why = self.problem()
        if why is not None:
            raise ObservabilityError(why)


def gram_singular_values(gram: Array) -> Array:
    """Singular values of a tall matrix (largest first) from its Gram matrix ``gram`` (its ``D^T D``: faster
    than a QR or SVD of the matrix itself, and summed by chunks of rows), accurate for those above about 1e-7
    of the largest (the quadric ratio is judged at :data:`MIN_QUADRIC_RATIO`)."""
    return np.sqrt(np.clip(np.linalg.eigvalsh(gram)[::-1], 0.0, None))


def centred_quadric_design(xt: Array, scale: float) -> Array:
    """Design matrix (N, 10) of a general quadric in normalised coordinates: points already centred, by
    coordinate ``xt`` (3, N), divided by ``scale`` (the median of their distances from the centre)."""
    a, b, c = xt / max(scale, 1e-300)
    out = np.empty((10, xt.shape[1]))  # filled a monomial at a time, each contiguous; returned as (N, 10)
    np.multiply(a, a, out=out[0])
    np.multiply(b, b, out=out[1])
    np.multiply(c, c, out=out[2])
    np.multiply(a, 2 * b, out=out[3])
    np.multiply(a, 2 * c, out=out[4])
    np.multiply(b, 2 * c, out=out[5])
    np.multiply(a, 2.0, out=out[6])
    np.multiply(b, 2.0, out=out[7])
    np.multiply(c, 2.0, out=out[8])
    out[9] = 1.0
    return out.T


def excitation(readings: ArrayLike) -> Excitation:
    """Measure the excitation of raw readings (N, 3) in T."""
    r = np.asarray(readings, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3:
        raise InputError(f"readings must be (N, 3), got {r.shape}")
    if not np.all(np.isfinite(r)):
        raise InputError("readings contain NaN or infinite values")
    n = len(r)
    if n < 3:
        return Excitation(n, np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.0, 0.0)
    rt = axis_major(r)  # (3, N): every pass below runs along contiguous rows
    scale = float(np.mean(np.sqrt(np.einsum("an,an->n", rt, rt)))) or 1.0
    centred = rt - rt.mean(axis=1)[:, None]
    evals, evecs = np.linalg.eigh(centred @ centred.T / n)
    spread = np.sqrt(np.clip(evals[::-1], 0.0, None)) / scale
    normal = evecs[:, 0] * np.sign(evecs[np.argmax(np.abs(evecs[:, 0])), 0])
    norms = np.sqrt(np.einsum("an,an->n", centred, centred))
    moved = centred if np.all(norms > 0) else centred[:, norms > 0]
    visited = _visited_cells(moved)
    ratio = 0.0
    if n >= 10:
        scale = float(np.median(norms))
        gram = np.zeros((10, 10))
        for lo in range(0, n, EXCITATION_CHUNK):  # a chunk at a time: its design stays in the caches
            design = centred_quadric_design(centred[:, lo : lo + EXCITATION_CHUNK], scale)
            gram += design.T @ design
        sv = gram_singular_values(gram)
        ratio = float(sv[8] / sv[0]) if sv[0] > 0 else 0.0
    return Excitation(n, spread, normal, visited / SPHERE_CELLS, ratio)


EXCITATION_CHUNK: int = 16_384
"""Sets per chunk of :func:`excitation`'s passes over the readings."""


def _visited_cells(moved: Array) -> int:
    """How many of the :data:`SPHERE_CELLS` cells the directions of ``moved`` (3, N, any length) visit: the cell of
    a direction is the nearest centre, the largest dot product; in single precision (half the work; a direction
    within about 1e-7 of a boundary counts for both cells), a chunk of directions at a time."""
    seen = np.zeros(SPHERE_CELLS, dtype=bool)
    for lo in range(0, moved.shape[1], EXCITATION_CHUNK):
        dots = _CELLS32 @ moved[:, lo : lo + EXCITATION_CHUNK].astype(np.float32)  # (cells, chunk)
        seen |= (dots == dots.max(axis=0)).any(axis=1)
    return int(np.count_nonzero(seen))

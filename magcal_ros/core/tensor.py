"""Gradient tensor and centre field from corrected sensor vectors (docs/methods.md, section 4).

``G[i, j] = dB_j / dx_i`` in T/m, platform frame. Inputs are corrected vectors of shape
(N, S, 3) in Tesla, one row per synchronized set.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

GradientMethod = Literal["difference", "least_squares"]
GRADIENT_METHODS: tuple[str, ...] = ("difference", "least_squares")


def _sets(vectors: ArrayLike, geometry: ArrayGeometry) -> Array:
    b = np.asarray(vectors, dtype=float)
    if b.ndim == 2:
        b = b[None]
    if b.ndim != 3 or b.shape[1:] != (geometry.size, 3):
        raise InputError(f"expected vectors of shape (N, {geometry.size}, 3), got {np.shape(vectors)}")
    return b


def centre_field(vectors: ArrayLike) -> Array:
    """Field at the array centre (T): the mean of the sensors, (N, 3)."""
    return np.asarray(vectors, dtype=float).mean(axis=-2)


def baseline_gradient(vectors: ArrayLike, geometry: ArrayGeometry) -> Array:
    """Gradient along the line of a collinear array, ``dB_j/ds`` (N, 3) in T/m, platform frame.

    ``s`` runs along :attr:`ArrayGeometry.baseline` (first sensor towards the last); with two
    sensors this is ``(B_2 - B_1) / L``, with more a least-squares slope.
    """
    if geometry.gradient_kind != "baseline":
        raise InputError(f"the baseline gradient needs sensors on one line; this array's gradient is "
                         f"{geometry.gradient_kind}")
    b = _sets(vectors, geometry)
    axis, _ = geometry.baseline
    s = (geometry.positions - geometry.centre) @ axis
    w = (s - s.mean()) / np.sum((s - s.mean()) ** 2)
    return np.einsum("s,nsa->na", w, b)


def gradient_difference(vectors: ArrayLike, geometry: ArrayGeometry) -> Array:
    """Cross difference formula (Li et al. (2018) eq. 2), (N, 3, 3).

    Rows x and y are measured; the z row follows from symmetry and zero trace. ``Gxy``
    and ``Gyx`` are kept as measured (not symmetrised).
    """
    layout = geometry.cross_layout()
    if layout is None:
        raise InputError("the difference formula needs a planar cross; use gradient_method least_squares")
    b = _sets(vectors, geometry)
    g = np.empty((b.shape[0], 3, 3))
    g[:, 0] = (b[:, layout.plus_x] - b[:, layout.minus_x]) / layout.baseline
    g[:, 1] = (b[:, layout.plus_y] - b[:, layout.minus_y]) / layout.baseline
    g[:, 2, 0] = g[:, 0, 2]
    g[:, 2, 1] = g[:, 1, 2]
    g[:, 2, 2] = -(g[:, 0, 0] + g[:, 1, 1])
    return g


def _symmetric_traceless_basis() -> Array:
    basis = np.zeros((5, 3, 3))
    basis[0, 0, 0], basis[0, 2, 2] = 1.0, -1.0
    basis[1, 1, 1], basis[1, 2, 2] = 1.0, -1.0
    for k, (i, j) in enumerate([(0, 1), (0, 2), (1, 2)], start=2):
        basis[k, i, j] = basis[k, j, i] = 1.0
    return basis


_BASIS = _symmetric_traceless_basis()


def least_squares_operator(geometry: ArrayGeometry) -> Array:
    """Linear map (8, 3S) from stacked sensor vectors to ``[B0 (3), g (5)]``.

    Model ``B_i = B0 + G^T (p_i - p0)`` with ``G`` symmetric and traceless.
    """
    rel = geometry.positions - geometry.centre
    rows = []
    for p in rel:
        block = np.zeros((3, 8))
        block[:, :3] = np.eye(3)
        block[:, 3:] = np.einsum("kij,i->jk", _BASIS, p)
        rows.append(block)
    design = np.vstack(rows)
    if np.linalg.matrix_rank(design) < 8:
        raise InputError(_undetermined(geometry))
    return np.linalg.pinv(design)


def _undetermined(geometry: ArrayGeometry) -> str:
    """Why the positions do not determine a tensor, in words."""
    if geometry.gradient_kind == "none":
        return "one sensor position determines no gradient (only the field)"
    if geometry.gradient_kind == "baseline":
        axis, length = geometry.baseline
        return (f"the {geometry.size} sensors lie on one line (direction {np.round(axis, 3).tolist()}, "
                f"{length:g} m): only the gradient along it (dB/ds) is determined, not the tensor")
    return "sensor positions do not determine a gradient tensor (need a 2-D spread)"


def gradient_least_squares(vectors: ArrayLike, geometry: ArrayGeometry) -> tuple[Array, Array]:
    """Constrained least-squares centre field (N, 3) and tensor (N, 3, 3) for any geometry."""
    b = _sets(vectors, geometry)
    params = b.reshape(b.shape[0], -1) @ least_squares_operator(geometry).T
    return params[:, :3], np.einsum("nk,kij->nij", params[:, 3:], _BASIS)


def method_for(geometry: ArrayGeometry, requested: str | None = None) -> str:
    """The gradient method to use: ``requested`` if given, else ``difference`` for a planar cross
    and ``least_squares`` for any other geometry."""
    if requested:
        return requested
    return "difference" if geometry.cross_layout() is not None else "least_squares"


def gradient(vectors: ArrayLike, geometry: ArrayGeometry, method: str = "difference") -> Array:
    """Gradient tensor (N, 3, 3) by ``method``: ``difference`` (planar cross) or ``least_squares``.

    :class:`InputError` when the positions determine no tensor (the message says what they
    do determine) or when ``difference`` is asked of an array that is not a planar cross.
    """
    if geometry.gradient_kind != "tensor":
        raise InputError(_undetermined(geometry))
    if method == "difference":
        return gradient_difference(vectors, geometry)
    if method == "least_squares":
        return gradient_least_squares(vectors, geometry)[1]
    raise InputError(f"unknown gradient method {method!r}; choose one of {', '.join(GRADIENT_METHODS)}")


def invariants(g: ArrayLike) -> dict[str, Array]:
    """Rotation-independent quantities of tensors (..., 3, 3).

    ``eigenvalues`` of the symmetric part (ascending), Frobenius ``norm``, ``trace`` and
    the second invariant ``i2`` (sum of principal 2x2 minors).
    """
    m = np.asarray(g, dtype=float)
    sym = 0.5 * (m + np.swapaxes(m, -1, -2))
    tr = np.trace(m, axis1=-2, axis2=-1)
    return {
        "eigenvalues": np.linalg.eigvalsh(sym),
        "norm": np.linalg.norm(m, axis=(-2, -1)),
        "trace": tr,
        "i2": 0.5 * (tr**2 - np.trace(m @ m, axis1=-2, axis2=-1)),
    }

"""Alignment of orthogonalised sensors to a reference frame (docs/methods.md, section 3).

Each aligner takes the sensor's orthogonal output ``b`` (N, 3) and the reference's
``B`` (N, 3) of the same sets and returns ``R`` (3, 3) with ``B ~ R b``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.rotation import euler_to_matrix, procrustes
from magcal_ros.errors import InputError

Array = NDArray[np.float64]


def align_procrustes(b: ArrayLike, reference: ArrayLike) -> Array:
    """Least-squares optimum on SO(3) (orthogonal Procrustes, SVD): the default."""
    return procrustes(b, reference)


def li2018_angles(b: ArrayLike, reference: ArrayLike) -> tuple[float, float, float]:
    """Li et al. (2018) eq. 7-10: rows ``Vx``, ``Vy`` of ``T`` by linear least squares, then angles.

    Returns ``(alpha, beta, gamma)`` in rad with ``B ~ T(alpha, beta, gamma) b``. Needs
    N >= 3 sets whose vectors span three dimensions.
    """
    x = np.asarray(b, dtype=float)
    y = np.asarray(reference, dtype=float)
    if len(x) < 3 or np.linalg.matrix_rank(x, tol=1e-9 * np.abs(x).max()) < 3:
        raise InputError("angle alignment needs at least 3 sets whose field vectors span 3-D")
    vx = np.linalg.lstsq(x, y[:, 0], rcond=None)[0]
    vy = np.linalg.lstsq(x, y[:, 1], rcond=None)[0]
    beta = -np.arcsin(np.clip(vx[2], -1.0, 1.0))
    gamma = np.arctan2(vx[1], vx[0])
    alpha = np.arcsin(np.clip(vy[2] / np.cos(beta), -1.0, 1.0))
    return float(alpha), float(beta), float(gamma)


def align_angles(b: ArrayLike, reference: ArrayLike) -> Array:
    """Li et al. (2018)'s least-squares angles as a rotation matrix."""
    return euler_to_matrix(*li2018_angles(b, reference))


def affine_regression(raw: ArrayLike, reference: ArrayLike) -> tuple[Array, Array]:
    """The two-fluxgate gradiometer paper: ``reference ~ W raw - c`` by row-wise least squares (12 unknowns).

    Returns the correction ``(W, offset)`` with ``reference ~ W (raw - offset)``.
    """
    r = np.asarray(raw, dtype=float)
    y = np.asarray(reference, dtype=float)
    design = np.column_stack([r, np.ones(len(r))])
    if np.linalg.matrix_rank(design) < 4:
        raise InputError("affine regression needs readings spread in three dimensions")
    coef = np.linalg.lstsq(design, y, rcond=None)[0]
    w = coef[:3].T
    return w, -np.linalg.solve(w, coef[3])

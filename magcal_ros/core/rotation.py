"""Rotations between sensor and platform frames.

Convention of Li et al. (2018) (eq. 4-6): passive matrices ``Ta`` (heel, about x), ``Tb``
(pitch, about y), ``Tg`` (azimuth, about z) and ``T = Ta(alpha) Tb(beta) Tg(gamma)``
maps a vector from the sensor frame to the platform frame: ``B = T b``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.errors import InputError

Array = NDArray[np.float64]


def heel(alpha: float) -> Array:
    """Passive rotation about x by ``alpha`` rad (Li et al. (2018) ``T_alpha``)."""
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def pitch(beta: float) -> Array:
    """Passive rotation about y by ``beta`` rad (Li et al. (2018) ``T_beta``)."""
    c, s = np.cos(beta), np.sin(beta)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def azimuth(gamma: float) -> Array:
    """Passive rotation about z by ``gamma`` rad (Li et al. (2018) ``T_gamma``)."""
    c, s = np.cos(gamma), np.sin(gamma)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def rq_positive(k: ArrayLike) -> tuple[Array, Array]:
    """``K = U Q`` for a matrix or a stack (..., 3, 3): ``U`` upper triangular with a positive diagonal,
    ``Q`` orthogonal (unique for a non-singular ``K``; from a QR decomposition of the flipped transpose,
    the whole stack at once)."""
    kk = np.asarray(k, dtype=float)
    flip = np.eye(3)[::-1]
    q1, r1 = np.linalg.qr(np.swapaxes(kk, -1, -2) @ flip)  # K^T J = Q1 R1, so K = (J R1^T J)(J Q1^T)
    upper = flip @ np.swapaxes(r1, -1, -2) @ flip
    q = flip @ np.swapaxes(q1, -1, -2)
    signs = np.sign(np.diagonal(upper, axis1=-2, axis2=-1))
    signs[signs == 0] = 1.0
    return upper * signs[..., None, :], signs[..., :, None] * q


def euler_to_matrix(alpha: float, beta: float, gamma: float) -> Array:
    """Sensor-to-platform matrix ``T = Ta(alpha) Tb(beta) Tg(gamma)`` (angles in rad)."""
    return heel(alpha) @ pitch(beta) @ azimuth(gamma)


def matrix_to_euler(t: ArrayLike) -> tuple[float, float, float]:
    """Angles ``(alpha, beta, gamma)`` in rad of ``T`` (inverse of :func:`euler_to_matrix`).

    Uses Li et al. (2018) eq. 10 in its numerically safe atan2 form.
    """
    m = np.asarray(t, dtype=float)
    beta = float(-np.arcsin(np.clip(m[0, 2], -1.0, 1.0)))
    gamma = float(np.arctan2(m[0, 1], m[0, 0]))
    alpha = float(np.arctan2(m[1, 2], m[2, 2]))
    return alpha, beta, gamma


def procrustes(source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None) -> Array:
    """Rotation ``R`` in SO(3) minimising ``sum w_k |target_k - R source_k|^2``.

    ``source`` and ``target`` are (N, 3) arrays of the same vectors in two frames; the
    result maps the source frame into the target frame (orthogonal Procrustes, SVD). A stack of
    targets (K, N, 3) gives the K rotations (K, 3, 3) at once.
    """
    x = np.asarray(source, dtype=float)
    y = np.asarray(target, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or y.shape[-2:] != x.shape or y.ndim > 3:
        raise InputError(f"procrustes needs two (N, 3) arrays, got {x.shape} and {y.shape}")
    w = np.ones(len(x)) if weights is None else np.asarray(weights, dtype=float)
    u, _, vt = np.linalg.svd(np.swapaxes(y * w[:, None], -1, -2) @ x)
    u[..., :, 2] *= np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)[..., None]
    return u @ vt


def rotation_angle(r: ArrayLike) -> float:
    """Angle in rad of the rotation ``r`` (0 for the identity)."""
    m = np.asarray(r, dtype=float)
    return float(np.arccos(np.clip((np.trace(m) - 1.0) / 2.0, -1.0, 1.0)))

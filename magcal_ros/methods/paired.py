"""Reference-free paired-norm calibration (Wu et al. 2013; docs/methods.md, section 2).

Wu et al. (2013)'s correction is ``b = G r`` with the upper-triangular
``G = [[q1, q2, q3], [0, q4, q5], [0, 0, 1]]``: five parameters, gains relative to the z
axis, no offset and no absolute scale. With no reference field, the 2N readings are split
into two groups and ``sum_i (|G r1_i|^2 - |G r2_i|^2)^2`` is minimised: every pair of
readings of a uniform field must have equal corrected norms.

Implementation choices (the paper names no solver and no split):

- pairs: a seeded random permutation of the readings, first half against second half
  (pairs of neighbouring readings along a turn would differ little and carry little
  information); with an odd count the last reading of the permutation is left out;
- start: the pair residual is linear in ``Q = G^T G`` (and in ``w = Q o`` with an
  offset), so a homogeneous least-squares solution (smallest singular vector) gives ``Q``
  up to scale; its Cholesky factor normalised to ``G[2, 2] = 1`` starts
  Levenberg-Marquardt on the paper's own cost (``scipy.optimize.least_squares``);
- offset (extension, ``fit_offset=True``, the default): real sensors have offsets, so
  the pair condition ``|G (r1 - o)| = |G (r2 - o)|`` is solved for ``o`` as well (8
  parameters). ``fit_offset=False`` is the paper's 5-parameter model with ``o = 0``;
- scale: the paper stops at relative gains. The result is scaled so that the mean
  corrected norm equals ``intensity`` (T), or, without a reference, the mean norm of
  the offset-free readings ``mean |r - o|`` (sensor units).

:func:`q_to_angles` and :func:`angles_to_q` map ``q1..q5`` to and from Wu et al.'s (2013)
physical parameters ``(theta, phi, psi, k'xz, k'yz)`` (its eq. 4, typos corrected),
and :func:`j_index` is its accuracy index (eq. 16). Wu et al. (2013)'s angle names differ from
Li et al. and Ding: its ``theta`` is the elevation of the x axis and ``phi`` the azimuth of
its projection, so ``SensorErrors(scale=[1/k'xz, 1/k'yz, 1], angles=(theta, phi, psi))``
is the same sensor.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.scalar_fit import ScalarFit, _readings, _target
from magcal_ros.errors import CalibrationFailed, InputError

Array = NDArray[np.float64]

PARAMETER_NAMES: tuple[str, ...] = ("theta", "phi", "psi", "kxz", "kyz")
"""Wu et al. (2013)'s physical parameters: angles (rad) and gains relative to z."""


def q_to_matrix(q: ArrayLike) -> Array:
    """``G`` (3, 3) from ``q = [q1, q2, q3, q4, q5]``."""
    q1, q2, q3, q4, q5 = np.asarray(q, dtype=float)
    return np.array([[q1, q2, q3], [0.0, q4, q5], [0.0, 0.0, 1.0]])


def matrix_to_q(matrix: ArrayLike) -> Array:
    """``q1..q5`` of an upper-triangular correction matrix, normalised to ``G[2, 2] = 1``."""
    g = np.asarray(matrix, dtype=float) / float(np.asarray(matrix)[2, 2])
    return np.array([g[0, 0], g[0, 1], g[0, 2], g[1, 1], g[1, 2]])


def angles_to_q(theta: float, phi: float, psi: float, kxz: float, kyz: float) -> Array:
    """``q1..q5`` of Wu et al. (2013) eq. 4 from its angles (rad) and relative gains."""
    return np.array(
        [
            kxz / (np.cos(theta) * np.cos(phi)),
            -kyz * np.tan(phi) / np.cos(psi),
            np.tan(phi) * np.tan(psi) - np.tan(theta) / np.cos(phi),
            kyz / np.cos(psi),
            -np.tan(psi),
        ]
    )


def q_to_angles(q: ArrayLike) -> Array:
    """``(theta, phi, psi, k'xz, k'yz)`` (rad, rad, rad, -, -) from ``q1..q5``."""
    q1, q2, q3, q4, q5 = np.asarray(q, dtype=float)
    psi = -np.arctan(q5)
    kyz = q4 * np.cos(psi)
    phi = np.arctan(-q2 / q4)
    theta = np.arctan((np.tan(phi) * np.tan(psi) - q3) * np.cos(phi))
    kxz = q1 * np.cos(theta) * np.cos(phi)
    return np.array([theta, phi, psi, kxz, kyz])


def j_index(estimate: ArrayLike, truth: ArrayLike) -> float:
    """Wu et al. (2013)'s index ``J = sqrt(sum(((p - p_hat) / p)^2))`` over its five parameters."""
    p = np.asarray(truth, dtype=float)
    return float(np.sqrt(np.sum(((p - np.asarray(estimate, dtype=float)) / p) ** 2)))


def split_pairs(count: int, rng: np.random.Generator) -> tuple[Array, Array]:
    """Indices of the two groups: a random permutation, first half against second half."""
    perm = rng.permutation(count)
    half = count // 2
    return perm[:half], perm[half : 2 * half]


def _quadratic(x: Array) -> Array:
    """Monomials (N, 6) with ``x^T Q x = _quadratic(x) @ [Q00, Q11, Q22, Q01, Q02, Q12]``."""
    a, b, c = x.T
    return np.column_stack([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c])


def _sym(v: Array) -> Array:
    return np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])


def linear_start(x1: Array, x2: Array, fit_offset: bool) -> tuple[Array, Array]:
    """Closed-form ``(q, o)`` of the pair condition (homogeneous least squares, scaled units)."""
    design = _quadratic(x1) - _quadratic(x2)
    if fit_offset:
        design = np.column_stack([design, -2.0 * (x1 - x2)])
    _, _, vt = np.linalg.svd(design, full_matrices=False)
    v = vt[-1]
    q = _sym(v[:6])
    if np.trace(q) < 0:
        q, v = -q, -v
    try:
        g = np.linalg.cholesky(q).T
    except np.linalg.LinAlgError:
        raise CalibrationFailed("paired fit: readings do not lie on an ellipsoid (check the rotations)") from None
    o = np.linalg.solve(q, v[6:]) if fit_offset else np.zeros(3)
    return matrix_to_q(g), o


def _pair_residuals(p: Array, x1: Array, x2: Array, fit_offset: bool) -> Array:
    """``|G (x1 - o)|^2 - |G (x2 - o)|^2`` per pair."""
    g = q_to_matrix(p[:5])
    o = p[5:8] if fit_offset else np.zeros(3)
    b1 = (x1 - o) @ g.T
    b2 = (x2 - o) @ g.T
    return np.sum(b1 * b1, axis=1) - np.sum(b2 * b2, axis=1)


def paired_fit(
    readings: ArrayLike,
    intensity: float | None,
    seed: int | None = 0,
    fit_offset: bool = True,
) -> ScalarFit:
    """Wu et al. (2013)'s reference-free calibration of readings (N, 3) in T.

    Returns an upper-triangular matrix ``s G`` (``s`` sets the mean corrected norm to
    ``intensity``, or to ``mean |r - o|`` when None), the offset (T; zeros when
    ``fit_offset`` is False), the target norm, the TMI RMS about it (T) and
    ``method="paired"``. Deterministic for a given ``seed`` (it chooses the pairs).
    """
    r = _readings(readings)
    unit = _target(r, None)  # work in units of the data's spread, like the other fits
    x = r / unit
    i1, i2 = split_pairs(len(x), np.random.default_rng(seed))
    x1, x2 = x[i1], x[i2]
    if len(x1) < (8 if fit_offset else 5):
        raise InputError(f"paired fit needs at least {16 if fit_offset else 10} readings, got {len(x)}")
    q0, o0 = linear_start(x1, x2, fit_offset)
    p0 = np.concatenate([q0, o0]) if fit_offset else q0
    from scipy.optimize import least_squares  # here: scipy.optimize takes a second to import

    sol = least_squares(_pair_residuals, p0, args=(x1, x2, fit_offset), method="lm", xtol=1e-15, ftol=1e-15)
    if not np.all(np.isfinite(sol.x)):
        raise CalibrationFailed("paired fit did not converge (non-finite parameters)")
    g = q_to_matrix(sol.x[:5])
    g = g * np.where(np.diag(g) < 0, -1.0, 1.0)[:, None]  # a row's sign does not change a norm
    offset = sol.x[5:8] * unit if fit_offset else np.zeros(3)
    norms = np.linalg.norm((r - offset) @ g.T, axis=1)
    if intensity is None or intensity == 0:
        f = float(np.mean(np.linalg.norm(r - offset, axis=1)))
    else:
        f = _target(r, intensity)
    matrix = g * (f / float(np.mean(norms)))
    res = np.linalg.norm((r - offset) @ matrix.T, axis=1) - f
    if np.any(np.diag(matrix) <= 1e-6 * np.abs(matrix).max()):
        raise CalibrationFailed("paired fit gave a zero gain: the rotations do not determine the calibration")
    return ScalarFit(matrix, offset, f, float(np.sqrt(np.mean(res**2))), None, "paired")

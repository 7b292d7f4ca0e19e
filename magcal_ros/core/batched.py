"""Small linear algebra over many sets at once, written for speed.

NumPy's ``matmul`` over stacks of 3 x 3 matrices loops in C over each tiny product, and
``linalg.norm`` over rows squares into a temporary: for the (N, S, 3) arrays of a calibration
(N sets, S sensors) both are several times slower than one matrix product per sensor (BLAS)
or an ``einsum``. These helpers give the same numbers (to rounding) at that speed.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def per_sensor(mats: Array, vectors: Array) -> Array:
    """(N, S, R) each sensor's matrix of ``mats`` (S, R, C) applied to its vectors ``vectors`` (N, S, C).

    Finite inputs go through one product with the block-diagonal matrix of all sensors (the zeros add
    nothing; one long product runs two to three times faster than a short one per sensor); elsewhere a
    product per sensor keeps a NaN of one sensor out of the others."""
    n, s, c = vectors.shape
    r = mats.shape[1]
    if s > 1 and np.isfinite(mats).all() and np.isfinite(vectors).all():
        block = np.zeros((s, r, s, c))
        for i in range(s):
            block[i, :, i] = mats[i]
        return (vectors.reshape(n, s * c) @ block.reshape(s * r, s * c).T).reshape(n, s, r)
    out = np.empty((n, s, r))
    for i in range(s):
        np.matmul(vectors[:, i], mats[i].T, out=out[:, i])
    return out


def per_sensor_shared(mats: Array, columns: Array) -> Array:
    """(N, S, R, K) each sensor's matrix of ``mats`` (S, R, C) times the matrices ``columns`` (N, C, K) that
    every sensor shares: one matrix product for all of them."""
    n, c, k = columns.shape
    s, r, _ = mats.shape
    flat = columns.transpose(0, 2, 1).reshape(n * k, c) @ mats.reshape(s * r, c).T  # (N K, S R)
    return np.ascontiguousarray(flat.reshape(n, k, s, r).transpose(0, 2, 3, 1))


def gram2(a: Array, b: Array) -> Array:
    """(N, 2, 2) ``sum_r a_r^T b_r`` over the rows of ``a``, ``b`` (N, ..., 2): per set, by elementwise
    products (no stack of tiny matrix products)."""
    n = a.shape[0]
    a2, b2 = a.reshape(n, -1, 2), b.reshape(n, -1, 2)
    out = np.empty((n, 2, 2))
    for i in range(2):
        for j in range(2):
            out[:, i, j] = np.einsum("nr,nr->n", a2[:, :, i], b2[:, :, j])
    return out


def times_lower2(a: Array, lower: Array) -> Array:
    """(N, ..., R, 2) ``a @ L`` for each set's lower triangular 2 x 2 ``lower`` (N, 2, 2) and its matrices ``a``
    (N, ..., R, 2), by elementwise products (a stack of 2 x 2 products loops in C over each)."""
    shape = (len(lower),) + (1,) * (a.ndim - 2)
    l00, l10, l11 = (lower[:, i, j].reshape(shape) for i, j in ((0, 0), (1, 0), (1, 1)))
    out = np.empty_like(a)
    np.multiply(a[..., 0], l00, out=out[..., 0])
    out[..., 0] += a[..., 1] * l10
    np.multiply(a[..., 1], l11, out=out[..., 1])
    return out


def per_sensor_gram(e: Array, f: Array) -> Array:
    """(S, A, Q) ``sum_n e_n^T f_n`` per sensor for ``e`` (N, S, A) and ``f`` (N, S, Q): one matrix product
    per sensor."""
    return np.stack([e[:, i].T @ f[:, i] for i in range(e.shape[1])])


def per_sensor_dot(cols: Array, v: Array) -> Array:
    """(S, X) ``sum_n sum_a cols[n, s, a, x] v[n, s, a]`` for ``cols`` (N, S, A, X) and ``v`` (N, S, A): one
    matrix-vector product per sensor."""
    x = cols.shape[3]
    return np.stack([cols[:, i].reshape(-1, x).T @ v[:, i].reshape(-1) for i in range(cols.shape[1])])


def row_norms(v: Array) -> Array:
    """(...,) Euclidean norms of the last axis of ``v``."""
    return np.sqrt(np.einsum("...a,...a->...", v, v))


def column_means(x: Array) -> Array:
    """(K,) the mean of each column of ``x`` (N, K), as one matrix-vector product (NumPy's
    ``mean(axis=0)`` over a few columns walks the rows one by one)."""
    return np.ones(len(x)) @ x / max(len(x), 1)


def sensor_means(v: Array) -> Array:
    """(N, 3) each set's mean over its sensors of ``v`` (N, S, 3): one matrix product where every value is finite
    (NumPy's ``mean(axis=1)`` over the middle axis is several times slower); NumPy's mean elsewhere (a NaN
    stays in its own axis)."""
    v = np.asarray(v, dtype=float)
    n, s, _ = v.shape
    if not n or not s or not np.isfinite(v).all():
        return v.mean(axis=1)
    return (v.reshape(n, s * 3) @ np.tile(np.eye(3) / s, (s, 1))).reshape(n, 3)


def axis_major(x: Array) -> Array:
    """(K, N) contiguous: the N rows of ``x`` (N, ...) by column, K the product of the other axes.
    NumPy reduces a few long contiguous rows far faster than many short ones (over the first axis)."""
    return np.ascontiguousarray(np.asarray(x, dtype=float).reshape(len(x), -1).T)


def column_extremes(x: Array) -> tuple[Array, Array]:
    """((K,), (K,)) the smallest and largest value of each column of ``x`` (N, K), N >= 1."""
    columns = axis_major(x)
    return columns.min(axis=1), columns.max(axis=1)


WELL_CONDITIONED: float = 1e-8
"""A symmetric positive definite matrix is solved or inverted directly when each of its columns keeps
this fraction of its squared length away from the columns before it (its Cholesky pivots): far from
the cut-offs at which a pseudo-inverse would drop a direction (1e-15 of the largest eigenvalue)."""


def well_conditioned(mats: Array) -> NDArray[np.bool_]:
    """(K,) True for each symmetric matrix of a stack (K, n, n) that :data:`WELL_CONDITIONED` allows to be
    solved directly (all False when one is not positive definite)."""
    diag = np.diagonal(mats, axis1=-2, axis2=-1)
    if not np.all(diag > 0):
        return np.zeros(len(mats), bool)
    try:
        pivots = np.diagonal(np.linalg.cholesky(mats), axis1=-2, axis2=-1) ** 2
    except np.linalg.LinAlgError:
        return np.zeros(len(mats), bool)
    return np.all(pivots > WELL_CONDITIONED * diag, axis=-1)


def symmetric_inverse(h: Array) -> Array:
    """The pseudo-inverse of a symmetric positive semi-definite matrix (n, n): its inverse when
    :func:`well_conditioned` (a seventh of the time), else by its eigenvalues."""
    if well_conditioned(h[None])[0]:
        inv = np.linalg.inv(h)
        return 0.5 * (inv + inv.T)
    return np.linalg.pinv(h, hermitian=True)

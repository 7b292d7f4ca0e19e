"""Joint maximum likelihood over the whole array (refines the sensor-by-sensor pipeline).

All sensors see the same uniform field ``B_k`` (|B_k| = F) at set ``k``; the raw model is
``r_ik = K_i B_k + o_i + noise`` with white noise on every raw axis. Minimising
``sum |K_i B_k + o_i - r_ik|^2`` over every ``K_i``, ``o_i`` and the field directions
uses all 3 S equations of a set, not only the S norms, so the sensors' relative
calibration (what the tensor needs) is determined by the vector agreement between
sensors. The solver is Levenberg-Marquardt with the per-set directions eliminated by a
Schur complement (cost linear in the number of sets). The free global rotation is fixed
afterwards to the pipeline's convention: the virtual centre sensor ``mean(K_i)`` is upper
triangular in the platform frame.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

Array = NDArray[np.float64]


def _tangent_bases(u: Array) -> Array:
    """(N, 3, 2) orthonormal bases of the planes perpendicular to unit vectors ``u``."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2], axis=2)


def _cost(k: Array, o: Array, u: Array, x: Array) -> float:
    pred = np.einsum("sij,nj->nsi", k, u) + o
    return float(np.sum((pred - x) ** 2))


def refine(
    raw: Array,
    matrices: Array,
    offsets: Array,
    intensity: float,
    iterations: int = 30,
    tolerance: float = 1e-12,
) -> tuple[Array, Array, Array]:
    """Refine per-sensor corrections jointly; returns ``(matrices, offsets, directions)``.

    ``raw`` (N, S, 3) in T; ``matrices`` (S, 3, 3) and ``offsets`` (S, 3) the starting
    corrections ``B = M (r - o)``; ``intensity`` F in T. Works in units of F.
    """
    x = raw / intensity
    s = raw.shape[1]
    k = np.linalg.inv(matrices)
    o = offsets / intensity
    b = np.einsum("sij,nsj->nsi", matrices, x - o).mean(axis=1)
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    cost = _cost(k, o, u, x)
    lam = 1e-6
    eye12 = np.eye(12 * s)
    for _ in range(iterations):
        pb = _tangent_bases(u)  # (N, 3, 2)
        e = np.einsum("sij,nj->nsi", k, u) + o - x  # (N, S, 3) residuals
        # Jacobian of e_ik w.r.t. sensor params [K_i row-major (9), o_i (3)]: rows a=0..2
        # d e_a / d K_ab = u_b ; d e_a / d o_a = 1.  W.r.t. direction step d (2): K_i P_k.
        jd = np.einsum("sij,njk->nsik", k, pb)  # (N, S, 3, 2)
        # Block-diagonal part A (per sensor 12x12)
        uu = u[:, :, None] * u[:, None, :]  # (N, 3, 3)
        suu, su, n = uu.sum(0), u.sum(0), len(u)
        a_blk = np.zeros((12, 12))
        for r in range(3):
            a_blk[3 * r : 3 * r + 3, 3 * r : 3 * r + 3] = suu
            a_blk[3 * r : 3 * r + 3, 9 + r] = su
            a_blk[9 + r, 3 * r : 3 * r + 3] = su
            a_blk[9 + r, 9 + r] = n
        big_a = scipy.linalg.block_diag(*([a_blk] * s))
        # Gradient for sensor params
        g_k = np.einsum("nsa,nb->sab", e, u).reshape(s, 9)
        g_o = e.sum(axis=0)
        g_theta = np.concatenate([g_k, g_o], axis=1).reshape(-1)
        # Cross terms B_k (12 S x 2): d e_a/dK_ab = u_b, so B[(s, a, b), c] = u_b jd[s, a, c]
        b_kk = np.einsum("nb,nsac->nsabc", u, jd).reshape(n, s, 9, 2)
        bmat = np.concatenate([b_kk, jd], axis=2).reshape(n, 12 * s, 2)  # offsets: d e_a/d o_a = 1
        flat_b = bmat.transpose(1, 0, 2).reshape(12 * s, -1)
        cmat = np.einsum("nsai,nsaj->nij", jd, jd)  # (N, 2, 2)
        g_d = np.einsum("nsai,nsa->ni", jd, e)  # (N, 2)
        while True:
            c_l = cmat + lam * np.eye(2) * np.trace(cmat, axis1=1, axis2=2)[:, None, None] / 2
            c_inv = np.linalg.inv(c_l)
            bc = np.einsum("nij,njk->nik", bmat, c_inv)  # (N, 12S, 2)
            flat_bc = bc.transpose(1, 0, 2).reshape(12 * s, -1)
            schur = big_a + lam * np.diag(np.diag(big_a)) - flat_bc @ flat_b.T
            rhs = g_theta - np.einsum("nik,nk->i", bc, g_d)
            step = -np.linalg.lstsq(schur + 1e-12 * np.trace(schur) / len(schur) * eye12, rhs, rcond=None)[0]
            dd = -np.einsum("nij,nj->ni", c_inv, g_d + np.einsum("nik,i->nk", bmat, step))
            upd = step.reshape(s, 12)
            k_new = k + upd[:, :9].reshape(s, 3, 3)
            o_new = o + upd[:, 9:]
            u_new = u + np.einsum("nij,nj->ni", pb, dd)
            u_new /= np.linalg.norm(u_new, axis=1, keepdims=True)
            new_cost = _cost(k_new, o_new, u_new, x)
            if new_cost <= cost:
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
            if lam > 1e8:
                break
        if new_cost > cost:
            break
        done = cost - new_cost <= tolerance * cost
        k, o, u, cost = k_new, o_new, u_new, new_cost
        if done:
            break
    # Gauge: rotate the platform frame so that mean(K_i) is upper triangular (centre sensor).
    upper, q = scipy.linalg.rq(k.mean(axis=0))
    signs = np.sign(np.diag(upper))
    q = signs[:, None] * q
    k = np.einsum("sij,kj->sik", k, q)  # K_i Q^T
    u = u @ q.T
    return np.linalg.inv(k), o * intensity, u

"""Joint maximum a posteriori fit of the whole array, robust to outliers (the final stage of ``ml``).

Model, set ``k`` (uniform field of intensity ``F`` and unit direction ``d_k`` in the platform
frame), sensor ``i`` with channel currents ``u_k`` (A)::

    r_ik = K_i F d_k + E_i u_k + o_i + noise_i

``K_i`` (3x3) is the forward matrix (``K_i = M_i^-1``), ``o_i`` the offset (T), ``E_i``
(3 x m, T/A) the current interference seen in the sensor's raw axes; the correction is
``B = M_i (r - o_i) - M_i E_i u`` (the interference in the platform frame is
``D_i = M_i E_i``). Every set gives 3 equations per sensor, so the sensors' relative
calibration (what the tensor needs) is set by the vector agreement between sensors, not
only by each sensor's norm.

The fit works in units of ``F``: per sensor the parameter matrix ``W_i = [K_i | o_i / F |
E_i / F]`` (3 x (4 + m)) and the features ``phi_k = [d_k, 1, u_k]``, so that the
prediction is ``W_i phi_k`` and the Jacobian of a reading is ``I_3 (x) phi_k``. The
per-set directions are eliminated by a Schur complement (cost linear in the number of
sets). A Gaussian prior on every ``W_i`` (the previous calibration and a drift model, or a
weak one around the starting point) makes the problem well posed whatever the manoeuvre;
the data information (without the prior) is returned for the identifiability analysis.

Outliers: after each fit every reading is compared with what the *other* sensors say the
field was (the mean of the set's other readings, so that a spike on one sensor cannot hide
by dragging the set's direction), and with the intensity; readings beyond a
chi-square bound of the sensor's robust scale get weight 0 and the fit is repeated until
the excluded readings settle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.stats
from numpy.typing import NDArray

from magcal_ros.errors import CalibrationFailed, InputError

Array = NDArray[np.float64]

OUTLIER_PROBABILITY: float = 1e-5
"""A clean reading is excluded with at most this probability (Gaussian noise)."""
MAX_ROBUST_ROUNDS: int = 12
"""Refits at most, each after re-deciding which readings are outliers."""
SOFT_BOUND: float = 16.0
"""Residuals beyond sqrt(SOFT_BOUND) = 4 noise sd (per reading, squared norm over its dof)
are down-weighted in proportion while outliers are being decided."""


@dataclass(frozen=True)
class ParameterPrior:
    """Gaussian prior on each sensor's ``W_i = [K_i | o_i / F | E_i / F]`` (units of F).

    ``mean`` (S, 3, 4 + m); ``sigma`` (S, 3, 4 + m) the 1-sigma of each entry (inf: no prior).
    """

    mean: Array
    sigma: Array

    def precision(self) -> Array:
        """Diagonal precision, flattened per sensor as (S, 3 (4 + m))."""
        s = np.asarray(self.sigma, dtype=float)
        with np.errstate(divide="ignore"):
            prec = np.where(np.isfinite(s), 1.0 / np.maximum(s, 1e-300) ** 2, 0.0)
        return prec.reshape(len(s), -1)


@dataclass(frozen=True)
class JointSolution:
    """Result of :func:`fit_array`, in physical units where it says so."""

    matrices: Array
    """(S, 3, 3) corrections ``M_i = K_i^-1`` (raw axes to platform frame)."""
    offsets: Array
    """(S, 3) T."""
    interference: Array
    """(S, 3, m) ``D_i = M_i E_i`` in T/A, platform frame."""
    directions: Array
    """(N, 3) unit field direction of each set, platform frame."""
    weights: Array
    """(N, S) 1 for readings used, 0 for readings excluded as outliers."""
    sigma: Array
    """(S,) noise per axis of each sensor (T), robust estimate from the residuals."""
    residuals: Array
    """(N, S, 3) raw-space residuals (T)."""
    information: Array
    """(S P, S P) Fisher information of the data on the flattened ``W`` (units of F), directions
    eliminated, noise-whitened; P = 3 (4 + m)."""
    scores: Array
    """(N, S P) per-set contributions to the reduced gradient at the solution (whitened)."""
    w: Array
    """(S, 3, 4 + m) the fitted ``W_i`` (units of F)."""
    intensity: float
    """F (T)."""


def tangent_bases(u: Array) -> Array:
    """(N, 3, 2) orthonormal bases of the planes perpendicular to unit vectors ``u``."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2], axis=2)


def features(directions: Array, currents: Array) -> Array:
    """(N, 4 + m) ``phi_k = [d_k, 1, u_k]``."""
    return np.concatenate([directions, np.ones((len(directions), 1)), currents], axis=1)


class _Normal:
    """Whitened normal equations of the model at one point (directions eliminated)."""

    def __init__(self, w: Array, d: Array, x: Array, u: Array, weights: Array, sigma: Array) -> None:
        s, _, q = w.shape
        n = len(d)
        self.phi = features(d, u)  # (N, q)
        self.basis = tangent_bases(d)  # (N, 3, 2)
        self.e = _predict(w, self.phi) - x  # (N, S, 3)
        ws = weights / sigma[None, :] ** 2  # (N, S) whitening weights
        self.ws = ws
        k = w[:, :, :3]
        self.m = np.matmul(k[None, :, :, :], self.basis[:, None, :, :])  # (N, S, 3, 2) d pred / d delta
        # Block diagonal A_i = I_3 (x) sum_k ws phi phi^T, and the gradient sum_k ws e phi^T
        self.a_blocks = np.stack([(self.phi * ws[:, i : i + 1]).T @ self.phi for i in range(s)])  # (S, q, q)
        we = ws[:, :, None] * self.e  # (N, S, 3)
        self.g_w = np.stack([we[:, i].T @ self.phi for i in range(s)])  # (S, 3, q)
        # Cross terms B_k[(s, a, q), c] = ws_ks phi_kq m_ksac
        wm = ws[:, :, None, None] * self.m  # (N, S, 3, 2)
        self.b = (wm[:, :, :, None, :] * self.phi[:, None, None, :, None]).reshape(n, s * 3 * q, 2)
        flat_m = self.m.reshape(n, s * 3, 2)
        self.c = np.matmul(wm.reshape(n, s * 3, 2).transpose(0, 2, 1), flat_m)  # (N, 2, 2)
        self.g_d = np.sum(wm * self.e[:, :, :, None], axis=(1, 2))  # (N, 2)
        self.cost = float(np.sum(we * self.e))
        self.shape = (s, q)

    def a_matrix(self) -> Array:
        s, q = self.shape
        blocks = [np.kron(np.eye(3), self.a_blocks[i]) for i in range(s)]
        return scipy.linalg.block_diag(*blocks)

    def scores(self) -> Array:
        """(N, S P) each set's contribution to the reduced gradient (directions eliminated, whitened).

        For white noise ``sum_k s_k s_k^T`` estimates :meth:`information`; with time-correlated
        noise the lagged products add to it (see :mod:`magcal_ros.core.uncertainty`).
        """
        s, q = self.shape
        we = self.ws[:, :, None] * self.e
        g = (we[:, :, :, None] * self.phi[:, None, None, :]).reshape(len(self.e), s * 3 * q)
        corr = np.matmul(self.b, np.matmul(_inv2(self.c), self.g_d[:, :, None]))[:, :, 0]
        return g - corr

    def information(self) -> Array:
        """Schur complement ``A - sum_k B_k C_k^-1 B_k^T`` (no damping)."""
        c_inv = _inv2(self.c)
        bc = np.matmul(self.b, c_inv)
        flat_b = self.b.transpose(1, 0, 2).reshape(self.b.shape[1], -1)
        flat_bc = bc.transpose(1, 0, 2).reshape(self.b.shape[1], -1)
        return self.a_matrix() - flat_bc @ flat_b.T


def _predict(w: Array, phi: Array) -> Array:
    """``W_i phi_k`` for every set and sensor: (N, S, 3)."""
    s, _, q = w.shape
    return (phi @ w.reshape(s * 3, q).T).reshape(len(phi), s, 3)


def _inv2(c: Array) -> Array:
    """Inverses of (N, 2, 2) matrices (with a tiny ridge for sets no sensor constrains)."""
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    ridge = 1e-12 * (np.abs(c[:, 0, 0]) + np.abs(c[:, 1, 1]) + 1e-300)
    det = np.where(np.abs(det) > ridge**2, det, det + ridge**2 + 1e-300)
    inv = np.empty_like(c)
    inv[:, 0, 0] = c[:, 1, 1] / det
    inv[:, 1, 1] = c[:, 0, 0] / det
    inv[:, 0, 1] = -c[:, 0, 1] / det
    inv[:, 1, 0] = -c[:, 1, 0] / det
    return inv


def _directions(w: Array, x: Array, u: Array, weights: Array) -> Array:
    """Field direction per set from the current corrections (weighted mean of the sensors)."""
    k = w[:, :, :3]
    rest = x - np.einsum("saq,nq->nsa", w[:, :, 3:], np.concatenate([np.ones((len(x), 1)), u], axis=1))
    b = np.einsum("sab,nsb->nsa", np.linalg.inv(k), rest)
    wsum = np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    mean = np.einsum("ns,nsa->na", weights, b) / wsum
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    fallback = b.mean(axis=1)
    mean = np.where(norm > 0, mean, fallback)
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    out = mean / np.where(norm > 0, norm, 1.0)
    out[~np.isfinite(out).all(axis=1) | (norm[:, 0] == 0)] = np.array([0.0, 0.0, 1.0])
    return out


def _cost(w: Array, d: Array, x: Array, u: Array, weights: Array, sigma: Array) -> float:
    """The whitened data cost of ``W`` with directions ``d`` (no prior)."""
    e = _predict(w, features(d, u)) - x
    return float(np.sum((weights / sigma[None, :] ** 2)[:, :, None] * e * e))


def _solve_lm(
    w: Array, x: Array, u: Array, weights: Array, sigma: Array, prior: ParameterPrior,
    iterations: int, tolerance: float,
) -> tuple[Array, Array, int]:
    """Levenberg-Marquardt on the MAP cost with fixed weights and noise; returns (W, directions, steps).

    The directions are eliminated exactly (Schur complement, computed once per iteration) and
    the damping acts on the reduced system, so a rejected step costs one small solve.
    """
    s, _, q = w.shape
    prec = prior.precision().reshape(-1)
    mean = prior.mean.reshape(-1)
    d = _directions(w, x, u, weights)
    lam = 1e-4
    steps = 0

    def prior_cost(wv: Array) -> float:
        diff = wv.reshape(-1) - mean
        return float(np.sum(prec * diff * diff))

    cur = _Normal(w, d, x, u, weights, sigma)
    cost = cur.cost + prior_cost(w)
    done = False
    for steps in range(1, iterations + 1):
        c_inv = _inv2(cur.c)
        bc = np.matmul(cur.b, c_inv)
        flat_b = cur.b.transpose(1, 0, 2).reshape(cur.b.shape[1], -1)
        flat_bc = bc.transpose(1, 0, 2).reshape(cur.b.shape[1], -1)
        schur = cur.a_matrix() + np.diag(prec) - flat_bc @ flat_b.T
        rhs = cur.g_w.reshape(-1) + prec * (w.reshape(-1) - mean) - np.sum(bc * cur.g_d[:, None, :], axis=(0, 2))
        if not (np.all(np.isfinite(schur)) and np.all(np.isfinite(rhs))):
            break
        diag = np.diag(np.diag(schur)) + 1e-12 * np.trace(schur) / len(schur) * np.eye(len(schur))
        improved = False
        while lam < 1e10:
            try:
                step = -scipy.linalg.solve(schur + lam * diag, rhs, assume_a="sym")
            except (np.linalg.LinAlgError, ValueError):
                lam *= 10
                continue
            dd = -np.matmul(c_inv, (cur.g_d + cur.b.transpose(0, 2, 1) @ step)[:, :, None])[:, :, 0]
            w_new = w + step.reshape(s, 3, q)
            d_new = d + np.matmul(cur.basis, dd[:, :, None])[:, :, 0]
            d_new /= np.linalg.norm(d_new, axis=1, keepdims=True)
            if not np.all(np.isfinite(w_new)) or np.any(np.abs(np.linalg.det(w_new[:, :, :3])) < 1e-12):
                lam *= 10
                continue
            new_cost = _cost(w_new, d_new, x, u, weights, sigma) + prior_cost(w_new)
            if new_cost <= cost:
                lam = max(lam / 10, 1e-12)
                done = cost - new_cost <= tolerance * max(cost, 1e-300)
                w, d, cost = w_new, d_new, new_cost
                cur = _Normal(w, d, x, u, weights, sigma)
                improved = True
                break
            lam *= 10
        if not improved or done:
            break
    return w, d, steps


def _outliers(w: Array, x: Array, u: Array, weights: Array) -> Array:
    """(N, S) True for readings that disagree with the other sensors of their set or with F.

    Each reading's corrected vector is compared with the mean of the set's other used
    readings (three or more sensors), and its norm with 1 (units of F); either test beyond
    the chi-square bound of its sensor's robust scale flags it.
    """
    n, s, _ = x.shape
    k = w[:, :, :3]
    rest = x - np.einsum("saq,nq->nsa", w[:, :, 3:], np.concatenate([np.ones((n, 1)), u], axis=1))
    b = np.einsum("sab,nsb->nsa", np.linalg.inv(k), rest)
    flags = np.zeros((n, s), bool)
    tests = [((np.linalg.norm(b, axis=2) - 1.0) ** 2, 1.0)]
    if s >= 3:
        # leave one out: the mean of the set's *other* used readings
        wsum = weights.sum(axis=1, keepdims=True)
        total = np.einsum("ns,nsa->na", weights, b)
        others = np.maximum(wsum - weights, 0.0)
        ref = (total[:, None, :] - weights[:, :, None] * b) / np.where(others > 0, others, 1.0)[:, :, None]
        q = np.sum((b - ref) ** 2, axis=2)
        q[others == 0] = 0.0  # no other reading: the TMI test only
        tests.append((q, 3.0))
    for q, dof in tests:
        bound = scipy.stats.chi2.isf(OUTLIER_PROBABILITY, dof)
        for i in range(s):
            good = q[weights[:, i] > 0, i]
            scale = np.median(good if len(good) else q[:, i]) / scipy.stats.chi2.median(dof)
            flags[:, i] |= q[:, i] > bound * max(scale, 1e-30)
    return flags


def _robust_sigma(e: Array, weights: Array, dof: float) -> Array:
    """Per-sensor noise per axis from squared residual norms: median scaled for ``dof`` (robust)."""
    sq = np.sum(e * e, axis=2)  # (N, S)
    med = scipy.stats.chi2.median(dof)
    out = np.empty(sq.shape[1])
    for i in range(sq.shape[1]):
        used = sq[weights[:, i] > 0, i]
        out[i] = np.sqrt(np.median(used) / med) if len(used) else np.sqrt(np.median(sq[:, i]) / med)
    return out


def _efficient_sigma(e: Array, weights: Array, dof: float) -> Array:
    """Per-sensor noise per axis from the weighted mean square residual (efficient for clean data)."""
    sq = np.sum(e * e, axis=2)
    used = np.maximum(weights.sum(axis=0), 1.0)
    return np.sqrt(np.sum(weights * sq, axis=0) / (used * dof))


def fit_array(
    raw: Array,
    matrices: Array,
    offsets: Array,
    intensity: float,
    currents: Array | None = None,
    interference: Array | None = None,
    prior: ParameterPrior | None = None,
    weights: Array | None = None,
    robust: bool = True,
    iterations: int = 50,
    tolerance: float = 1e-10,
) -> JointSolution:
    """Joint MAP fit of every sensor from raw sets ``raw`` (N, S, 3) T, starting at
    ``matrices`` (S, 3, 3) / ``offsets`` (S, 3) T / ``interference`` (S, 3, m) T/A.

    ``currents`` (N, m) A; ``prior`` on ``W`` in units of F (default: a weak prior around
    the start that only keeps undetermined directions finite); ``weights`` (N, S) 0/1 to
    exclude readings from the start; ``robust`` re-decides outliers until they settle.
    """
    r = np.asarray(raw, dtype=float)
    n, s, _ = r.shape
    f = float(intensity)
    u = np.zeros((n, 0)) if currents is None else np.asarray(currents, dtype=float).reshape(n, -1)
    m = u.shape[1]
    q = 4 + m
    if not (np.isfinite(f) and f > 0):
        raise InputError(f"intensity must be a positive number of T, got {intensity}")
    k0 = np.linalg.inv(np.asarray(matrices, dtype=float))
    e_raw = np.zeros((s, 3, m)) if interference is None else np.einsum("sab,sbc->sac", k0, interference)
    w = np.concatenate([k0, (np.asarray(offsets, dtype=float) / f)[:, :, None], e_raw / f], axis=2)
    x = r / f
    weights = np.ones((n, s)) if weights is None else np.asarray(weights, dtype=float).copy()
    if prior is None:
        sigma_start = np.full((s, 3, q), 1.0)  # weak: gains of order 1, offsets of order F
        prior = ParameterPrior(w.copy(), sigma_start)
    dof = 3.0 - 2.0 / s if s > 0 else 1.0
    pred = _predict(w, features(_directions(w, x, u, weights), u))
    sigma = np.maximum(_robust_sigma(pred - x, weights, dof), 1e-12)
    for _ in range(MAX_ROBUST_ROUNDS if robust else 1):
        w, d, _ = _solve_lm(w, x, u, weights, sigma, prior, iterations, tolerance)
        e = _predict(w, features(d, u)) - x
        sigma = np.maximum(_robust_sigma(e, weights, dof), 1e-12)
        if not robust:
            break
        # Hard exclusion of outliers, and a soft down-weighting of large residuals so that a
        # spike not yet excluded cannot bend the fit (weights 1 for clean data).
        q = np.sum(e * e, axis=2)
        soft = np.minimum(1.0, SOFT_BOUND * sigma[None, :] ** 2 / np.maximum(q, 1e-300))
        new_weights = soft * ~_outliers(w, x, u, weights > 0.5)
        if np.max(np.abs(new_weights - weights)) < 1e-3:
            break
        weights = new_weights
    else:
        w, d, _ = _solve_lm(w, x, u, weights, sigma, prior, iterations, tolerance)
    if not np.all(np.isfinite(w)):
        raise CalibrationFailed("the joint array fit did not converge (non-finite parameters)")
    # A reading the soft weighting has all but removed (beyond sqrt(2 SOFT_BOUND) noise sd: a
    # spike, a frozen sensor) is excluded, as the outlier tests already treat it: counted as an
    # outlier, and kept out of the residuals the quality gates judge.
    weights = np.where(weights < 0.5, 0.0, weights)
    e = _predict(w, features(d, u)) - x
    sigma = np.maximum(_efficient_sigma(e, weights, dof), 1e-15)
    final = _Normal(w, d, x, u, weights, sigma)
    info, scores = final.information(), final.scores()
    k = w[:, :, :3]
    mats = np.linalg.inv(k)
    return JointSolution(
        matrices=mats,
        offsets=w[:, :, 3] * f,
        interference=np.einsum("sab,sbc->sac", mats, w[:, :, 4:] * f),
        directions=d,
        weights=weights,
        sigma=sigma * f,
        residuals=e * f,
        information=info,
        scores=scores,
        w=w,
        intensity=f,
    )


def fix_rotation_gauge(solution: JointSolution) -> JointSolution:
    """Rotate the platform frame so that the virtual centre sensor ``mean(K_i)`` is upper
    triangular (Li et al.'s convention: the centre sensor's own axes made orthogonal)."""
    k = solution.w[:, :, :3]
    upper, qmat = scipy.linalg.rq(k.mean(axis=0))
    qmat = np.sign(np.diag(upper))[:, None] * qmat
    k_new = np.einsum("sij,kj->sik", k, qmat)  # K_i Q^T
    tinv = np.linalg.inv(_rotation_map(qmat, solution.w.shape))
    w = solution.w.copy()
    w[:, :, :3] = k_new
    mats = np.linalg.inv(k_new)
    return JointSolution(
        matrices=mats,
        offsets=solution.offsets,
        interference=np.einsum("sab,sbc->sac", mats, w[:, :, 4:] * solution.intensity),
        directions=solution.directions @ qmat.T,
        weights=solution.weights,
        sigma=solution.sigma,
        residuals=solution.residuals,
        information=tinv.T @ solution.information @ tinv,
        scores=solution.scores @ tinv,
        w=w,
        intensity=solution.intensity,
    )


def _rotation_map(qmat: Array, shape: tuple[int, ...]) -> Array:
    """The linear map of the flattened ``W`` under ``K_i -> K_i Q^T`` (new = T old)."""
    s, _, q = shape
    t = np.eye(s * 3 * q).reshape(s, 3, q, s * 3 * q)
    t[:, :, :3, :] = np.einsum("saqp,kq->sakp", t[:, :, :3, :], qmat)
    return t.reshape(s * 3 * q, s * 3 * q)


def information_at(w: Array, directions: Array, sigma: Array) -> Array:
    """The information (S P, S P) that sets with unit field ``directions`` (N, 3) would add to
    the fit ``w`` (units of F), every reading used, noise ``sigma`` (S,) in units of F, no currents."""
    n = len(directions)
    u = np.zeros((n, w.shape[2] - 4))
    x = _predict(w, features(directions, u))
    return _Normal(w, directions, x, u, np.ones((n, w.shape[0])), sigma).information()

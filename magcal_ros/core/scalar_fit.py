"""Scalar (TMI-referenced) calibration of one sensor (docs/methods.md, section 2).

Finds an upper-triangular ``M`` and offset ``o`` (T) such that ``|M (r_k - o)| = F`` for
readings ``r_k`` (T) of a uniform field of intensity ``F`` (T) under rotation.

- :func:`algebraic_fit`: closed-form quadric fit with a unit-norm normalisation (the fix
  of docs/methods.md, pitfall A) and an exact decoding (Cholesky) into ``M`` and ``o``; this is
  Li et al.'s (2018) linear method.
- :func:`ml_fit`: maximum likelihood refinement of the norm residual by
  Levenberg-Marquardt (analytic Jacobian), optional robust loss, noise-bias correction
  and a parameter covariance.

With ``intensity=None`` the fit is relative: ``F`` is taken as 1 in units of the mean
reading norm and :attr:`ScalarFit.intensity` reports the scale used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.batched import axis_major
from magcal_ros.errors import CalibrationFailed, InputError

Array = NDArray[np.float64]

_TRIU = np.triu_indices(3)
LOSSES: tuple[str, ...] = ("linear", "huber", "soft_l1", "cauchy")


@dataclass(frozen=True)
class ScalarFit:
    """Result of a scalar calibration: ``b = matrix (r - offset)`` has norm ``intensity``."""

    matrix: Array
    """(3, 3) upper triangular."""
    offset: Array
    """(3,) T."""
    intensity: float
    """Target norm F (T); the relative scale when no reference was given."""
    residual_rms: float
    """RMS of ``|b| - F`` over the fit data (T)."""
    std: Array | None = None
    """1-sigma uncertainty of ``[M00, M01, M02, M11, M12, M22]`` (relative to F) and offset (T)."""
    method: str = "ml"

    def apply(self, readings: ArrayLike) -> Array:
        """Corrected vectors (N, 3) in T."""
        return (np.asarray(readings, dtype=float) - self.offset) @ self.matrix.T

    def tmi_residuals(self, readings: ArrayLike) -> Array:
        """``|b_k| - F`` (T) for readings (N, 3)."""
        return np.linalg.norm(self.apply(readings), axis=1) - self.intensity


def _readings(readings: ArrayLike) -> Array:
    r = np.asarray(readings, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3 or len(r) < 10:
        raise InputError(f"scalar calibration needs (N >= 10, 3) readings, got {r.shape}")
    if not np.all(np.isfinite(r)):
        raise InputError("readings contain NaN or infinite values")
    return r


def _target(r: Array, intensity: float | None) -> float:
    if intensity is None or intensity == 0:
        return float(np.mean(np.linalg.norm(r - r.mean(axis=0), axis=1)))
    if not np.isfinite(intensity) or intensity <= 0:
        raise InputError(f"reference field must be a positive intensity in T, got {intensity}")
    return float(intensity)


def decode_quadric(v: ArrayLike, centre: ArrayLike, scale: float, intensity: float) -> tuple[Array, Array]:
    """``(M, o)`` from quadric coefficients ``v`` fitted in coordinates ``(r - centre)/scale``.

    ``v = [a, b, c, d, e, f, g, h, i, j]`` of ``x^T A x + 2 [g h i] x + j = 0``.
    """
    a, b, c, d, e, f, g, h, i, j = np.asarray(v, dtype=float)
    quad = np.array([[a, d, e], [d, b, f], [e, f, c]])
    lin = np.array([g, h, i])
    try:
        x0 = -np.linalg.solve(quad, lin)
    except np.linalg.LinAlgError:
        raise CalibrationFailed("readings do not fit an ellipsoid (degenerate quadric)") from None
    k = x0 @ quad @ x0 - j
    shape = quad / k
    if not np.all(np.isfinite(shape)) or np.any(np.linalg.eigvalsh(shape) <= 0):
        raise CalibrationFailed("readings do not lie on an ellipsoid: check for a varying field or gross outliers")
    mtm = shape * (intensity / scale) ** 2
    m = np.linalg.cholesky(mtm).T  # upper triangular, M^T M = mtm
    return m, np.asarray(centre, dtype=float) + scale * x0


def algebraic_fit(readings: ArrayLike, intensity: float | None = None) -> ScalarFit:
    """Closed-form quadric fit (Li et al.'s (2018) linear method with a correct normalisation).

    Solves the 10-coefficient quadric by the smallest right singular vector of the
    normalised design matrix (||v|| = 1 instead of the printed constant column, which
    admits the trivial solution) and decodes it exactly into ``M`` and ``o``.
    """
    from magcal_ros.core.observability import centred_quadric_design

    r = _readings(readings)
    f = _target(r, intensity)
    rt = axis_major(r)  # (3, N)
    centre = rt.mean(axis=1)
    xt = rt - centre[:, None]
    scale = float(np.median(np.sqrt(np.einsum("an,an->n", xt, xt))))
    design = centred_quadric_design(xt, scale)
    # the smallest right singular vector: the Gram matrix's last eigenvector (the design is normalised,
    # its condition number ~1/quadric ratio, so squaring it leaves ample precision)
    m, o = decode_quadric(np.linalg.eigh(design.T @ design)[1][:, 0], centre, scale, f)
    res = np.linalg.norm((r - o) @ m.T, axis=1) - f
    return ScalarFit(m, o, f, float(np.sqrt(np.mean(res**2))), method="linear")


def _pack(m: Array, o: Array, f: float) -> Array:
    return np.concatenate([m[_TRIU], o / f])


def _unpack(p: Array, f: float) -> tuple[Array, Array]:
    m = np.zeros((3, 3))
    m[_TRIU] = p[:6]
    return m, p[6:] * f


def _residual_and_jacobian(p: Array, x: Array, target: float) -> tuple[Array, Array]:
    """Norm residual in units of F and its Jacobian, for readings ``x = r / F``."""
    m, o = _unpack(p, 1.0)
    d = x - o
    b = d @ m.T
    nb = np.linalg.norm(b, axis=1)
    u = b / nb[:, None]
    jac = np.empty((len(x), 9))
    for col, (row, c) in enumerate(zip(*_TRIU)):
        jac[:, col] = u[:, row] * d[:, c]
    jac[:, 6:] = -u @ m
    return nb - target, jac


def ml_fit(
    readings: ArrayLike,
    intensity: float | None = None,
    start: ScalarFit | None = None,
    loss: str = "linear",
    loss_scale: float | None = None,
    bias_correction: bool = True,
) -> ScalarFit:
    """Maximum likelihood scalar calibration (Levenberg-Marquardt on ``|M(r-o)| - F``).

    ``start`` defaults to :func:`algebraic_fit`. ``loss`` ``huber``, ``soft_l1`` or
    ``cauchy`` down-weights outliers beyond ``loss_scale`` (T; default 3x the start's
    residual RMS). ``bias_correction`` removes the ``sigma^2 / F`` by which noise inflates
    the mean norm (matters only at strong noise, Wu et al. (2013)).
    """
    if loss not in LOSSES:
        raise InputError(f"unknown loss {loss!r}; choose one of {', '.join(LOSSES)}")
    r = _readings(readings)
    f = _target(r, intensity)
    start = start or algebraic_fit(r, f)
    x = r / f
    p0 = _pack(start.matrix, start.offset, f)
    from scipy.optimize import least_squares  # here: scipy.optimize takes ~0.7 s to import

    def solve(p_init: Array, target: float) -> tuple[Array, Array, Array]:
        def fun(p: Array) -> Array:
            return _residual_and_jacobian(p, x, target)[0]

        def jac(p: Array) -> Array:
            return _residual_and_jacobian(p, x, target)[1]

        if loss == "linear":
            sol = least_squares(fun, p_init, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        else:
            scale = (loss_scale / f) if loss_scale else max(3.0 * start.residual_rms / f, 1e-12)
            sol = least_squares(fun, p_init, jac=jac, method="trf", loss=loss, f_scale=scale, x_scale="jac")
        if not np.all(np.isfinite(sol.x)):
            raise CalibrationFailed("scalar calibration did not converge (non-finite parameters)")
        res, jmat = _residual_and_jacobian(sol.x, x, target)
        return sol.x, res, jmat

    p, res, jmat = solve(p0, 1.0)
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))  # robust to outliers
    if bias_correction and sigma > 1e-4:
        p, res, jmat = solve(p, 1.0 + sigma**2)
        res = res + sigma**2
    m, o = _unpack(p, f)
    sign = np.sign(np.diag(m))
    m = m * sign[:, None]  # keep a positive diagonal (the sign of a row is unobservable)
    dof = max(len(r) - 9, 1)
    s2 = float(res @ res) / dof
    try:
        cov = np.linalg.inv(jmat.T @ jmat) * s2
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
        std[6:] *= f
    except np.linalg.LinAlgError:
        std = np.full(9, np.inf)
    rms = float(np.sqrt(np.mean(res**2))) * f
    return ScalarFit(m, o, f, rms, std, "ml")


TRIM_SIGMAS: float = 5.0
"""Readings whose norm residual exceeds this many robust sd are outliers for a start fit."""


def inliers(fit: ScalarFit, readings: ArrayLike, sigmas: float = TRIM_SIGMAS) -> NDArray[np.bool_]:
    """Readings whose norm residual lies within ``sigmas`` robust sd (MAD) of the median."""
    res = fit.tmi_residuals(readings)
    centre = np.median(res)
    scale = 1.4826 * np.median(np.abs(res - centre))
    return np.abs(res - centre) <= sigmas * max(scale, 1e-12 * fit.intensity)


GROSS_RADIUS: float = 4.0
"""A reading farther than this many times the median distance from the readings' median is
gross (a saturated or corrupted sample): on any rotation the readings lie within about one
field radius of their centre."""
FULL_SCALE_FRACTION: float = 0.02
"""An axis value repeated in this fraction of the readings (and at least 5) at the axis's
extreme is the sensor's full scale: those readings are clipped."""


def gross_readings(readings: ArrayLike) -> NDArray[np.bool_]:
    """(N,) True for readings no rotation explains: far outside the cloud (:data:`GROSS_RADIUS`),
    or clipped at a full-scale value (:func:`clipped_readings`). Algebraic fits weigh a reading
    by its squared distance, so two such samples can bend a closed-form start beyond repair."""
    r = _readings(readings)
    dist = np.linalg.norm(r - np.median(axis_major(r), axis=1), axis=1)
    return (dist > GROSS_RADIUS * max(float(np.median(dist)), 1e-300)) | clipped_readings(r)


def clipped_readings(readings: ArrayLike) -> NDArray[np.bool_]:
    """(N,) True for readings with an axis at a full-scale value: the axis's largest or smallest
    value, repeated exactly in at least :data:`FULL_SCALE_FRACTION` of the readings (and 5)."""
    return clipped_sets(_readings(readings)[:, None, :])[:, 0]


def clipped_sets(raw: Array) -> NDArray[np.bool_]:
    """(N, S) :func:`clipped_readings` of every sensor of finite sets (N, S, 3) at once."""
    return clipped_axes(axis_major(raw)).T


def clipped_axes(columns: Array) -> NDArray[np.bool_]:
    """(S, N) :func:`clipped_sets` from the sets' :func:`~magcal_ros.core.batched.axis_major` form (S 3, N)."""
    k, n = columns.shape
    out = np.zeros((k // 3, n), bool)
    least = max(5, int(np.ceil(FULL_SCALE_FRACTION * n)))
    for extreme in (columns.max(axis=1), columns.min(axis=1)):
        at = columns == extreme[:, None]
        full = np.count_nonzero(at, axis=1) >= least  # (S 3,): that extreme is a full scale
        if full.any():
            out |= (at & full[:, None]).reshape(k // 3, 3, n).any(axis=1)
    return out


def trimmed_algebraic_fit(readings: ArrayLike, intensity: float | None = None, rounds: int = 6) -> tuple[ScalarFit, NDArray[np.bool_]]:
    """The closed-form fit, refitted on its inliers until they settle: a start that spikes cannot bend.

    Gross readings (:func:`gross_readings`) are left out from the first fit. Returns the fit
    and the inlier mask (True: kept). Needs at least half the readings clean.
    """
    r = _readings(readings)
    f = _target(r, intensity)
    keep = ~gross_readings(r)
    if keep.sum() < max(10, len(r) // 2):
        keep[:] = True
    fit = algebraic_fit(r[keep], f)
    for _ in range(rounds):
        new = inliers(fit, r)
        if new.sum() < max(10, len(r) // 2) or np.array_equal(new, keep):
            break
        keep = new
        fit = algebraic_fit(r[keep], f)
    return fit, keep

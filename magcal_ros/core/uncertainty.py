"""Honest parameter covariance of a joint array fit: time-correlated noise and the frame gauge.

The covariance of the fitted ``W`` (see :mod:`magcal_ros.core.array_fit`) is the sandwich
``H^-1 Meat H^-1`` with ``H`` the information (plus the prior's precision) and ``Meat`` a
Newey-West (Bartlett) sum of lagged products of the per-set scores, with the bandwidth taken
from the autocorrelation of the residuals in time. For white noise the meat equals ``H``
and the result is the usual ``H^-1``; real recordings are time-correlated (slow motion,
drift, vibration) and ``H^-1`` alone understates the spread several-fold.

Without an informative prior the data cannot fix the platform frame's orientation (a
global rotation of every sensor); the covariance is then taken in the gauge the solver
reports: the virtual centre sensor's matrix upper triangular.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.batched import column_means, symmetric_inverse

Array = NDArray[np.float64]

MAX_BANDWIDTH_FRACTION: float = 0.1
"""The Newey-West bandwidth never exceeds this fraction of the sets."""


def _correlations(series: Array) -> Iterator[float]:
    """The sample autocorrelation of a (N,) or (N, K) series (averaged over columns) at lags 0, 1,
    2, ... as they are asked for; zeros after lag 0 for a constant or too short series."""
    x = np.asarray(series, dtype=float)
    x = x.reshape(len(x), -1)
    x = x - column_means(x)
    var = float(np.sum(x * x))
    yield 1.0
    for k in itertools.count(1):
        yield float(np.sum(x[: len(x) - k] * x[k:])) / var if var > 0 and 3 <= len(x) and k < len(x) else 0.0


def autocorrelation(series: Array, lags: int) -> Array:
    """Sample autocorrelation of a (N,) or (N, K) series at lags 0..``lags`` (averaged over columns)."""
    out = np.zeros(lags + 1)
    for k, rho in zip(range(lags + 1), _correlations(series)):
        out[k] = rho
    return out


def bandwidth(series: Array) -> int:
    """Newey-West bandwidth (sets): twice the lag at which the residual autocorrelation fades.

    The autocorrelation fades at the first lag below ``2 / sqrt(N)`` (indistinguishable from
    white); the Bartlett taper needs about twice that to take the correlation in fully.
    Capped at :data:`MAX_BANDWIDTH_FRACTION` of the sets. Lags are computed only up to the fade.
    """
    n = len(series)
    cap = max(1, int(MAX_BANDWIDTH_FRACTION * n))
    threshold = 2.0 / np.sqrt(max(n, 1))
    correlations = _correlations(series)
    next(correlations)  # lag 0
    for lag, rho in zip(range(1, cap + 1), correlations):
        if abs(rho) < threshold:
            return min(cap, 2 * (lag - 1))  # Bartlett weights taper: reach twice as far as the correlation
    return cap


def meat(scores: Array, lags: int) -> Array:
    """Bartlett-weighted sum of lagged score products ``sum_l w_l (Gamma_l + Gamma_l^T)``."""
    s = np.asarray(scores, dtype=float)
    out = s.T @ s
    for lag in range(1, lags + 1):
        gamma = s[:-lag].T @ s[lag:]
        out += (1.0 - lag / (lags + 1.0)) * (gamma + gamma.T)
    return out


@dataclass(frozen=True)
class Covariance:
    """Covariance of the flattened ``W`` (units of F) and how it was obtained."""

    matrix: Array
    bandwidth: int
    """Newey-West bandwidth in sets (0: white)."""
    inflation: float
    """How much the time correlation widened the uncertainty (ratio of traces, >= ~1)."""
    jackknife: float = 1.0
    """The block jackknife's share of :attr:`inflation` (1: not applied)."""


def _gauge_inverse(h_post: Array, gauge_constraints: Array | None) -> Array:
    """Inverse of ``h_post`` on the null space of the constraints (pseudo-inverse without)."""
    if gauge_constraints is not None and len(gauge_constraints):
        _, sv, vt = np.linalg.svd(gauge_constraints)
        rank = int(np.sum(sv > 1e-12 * sv[0]))
        basis = vt[rank:].T  # null space of the constraints
        return basis @ symmetric_inverse(basis.T @ h_post @ basis) @ basis.T
    return symmetric_inverse(h_post)


def covariance(
    information: Array,
    scores: Array,
    series: Array,
    prior_precision: Array | None = None,
    gauge_constraints: Array | None = None,
    like: Covariance | None = None,
) -> Covariance:
    """Sandwich covariance of the fitted parameters.

    ``information`` (P, P) and ``scores`` (N, P) whitened, from the fit; ``series`` (N, ...)
    residuals in time order (for the bandwidth); ``prior_precision`` (P,) diagonal or None;
    ``gauge_constraints`` (C, P): linear constraints fixing the frame when the prior does not.
    ``like``: a covariance found on a subset of the same recording whose widening (time
    correlation, jackknife) applies to this information as a whole (``scores`` and ``series``
    are then not used).
    """
    h = np.asarray(information, dtype=float)
    p = len(h)
    prec = np.zeros(p) if prior_precision is None else np.asarray(prior_precision, dtype=float)
    if like is not None:
        inv = _gauge_inverse(h + np.diag(prec), gauge_constraints)
        plain = inv @ (h + np.diag(prec)) @ inv
        return Covariance(0.5 * (plain + plain.T) * like.inflation, like.bandwidth, like.inflation, like.jackknife)
    lags = bandwidth(series)
    white = scores.T @ scores
    correlated = meat(scores, lags)
    # Scale the empirical meat to the model information: the residuals are noise minus the
    # fitted part, which the information accounts for; only the time structure is taken.
    scale = np.trace(h) / max(np.trace(white), 1e-300)
    m_data = correlated * scale
    inv = _gauge_inverse(h + np.diag(prec), gauge_constraints)
    cov = inv @ (m_data + np.diag(prec)) @ inv
    cov = 0.5 * (cov + cov.T)
    plain = inv @ (h + np.diag(prec)) @ inv
    inflation = float(np.trace(cov) / max(np.trace(plain), 1e-300))
    return Covariance(cov, lags if lags > 0 else 0, inflation)


def centre_gauge_constraints(w: Array, size: int | None = None) -> Array:
    """(3, S P) linearised constraints "mean(K_i) is upper triangular" (the reported frame).

    ``w`` (S, 3, q) the linear parameters; ``size`` the parameters per sensor P when more follow
    ``W`` (the temperature and lag blocks), default ``3 q``.
    """
    s, _, q = w.shape
    p = 3 * q if size is None else size
    rows = []
    for a, b in ((1, 0), (2, 0), (2, 1)):
        c = np.zeros((s, p))
        c[:, a * q + b] = 1.0 / s
        rows.append(c.reshape(-1))
    return np.array(rows)

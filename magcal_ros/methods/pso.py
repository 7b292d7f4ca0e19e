"""Particle swarm scalar calibration (Ding 2024; docs/methods.md, section 2).

Minimises the TMI fitness ``RMS_k(|P (r_k - o)| - F)`` over the 12 entries of a general
3x3 inverse matrix ``P`` and the offset ``o`` with a particle swarm. Work is done in units
of F (readings ``x = r / F``, target norm 1, offset ``o / F``).

Improved PSO (``improved=True``, the paper's method):

- inertia ``w`` decreases linearly from ``W_RANGE[0]`` to ``W_RANGE[1]``; the cognitive
  factor ``c1`` decreases from ``C1_RANGE[0]`` to ``C1_RANGE[1]`` and the social factor
  ``c2`` increases from ``C2_RANGE[0]`` to ``C2_RANGE[1]`` (Ding (2024) eqs 12-14);
- the initial positions come from the Circle chaotic map as printed in the paper,
  ``z <- mod(2 z + 0.2 - 0.7 / (2 pi) cos(2 pi z + pi / 2), 1)``, iterated across the
  particles from a seeded random start per dimension, mapped linearly into the bounds.

Plain PSO (``improved=False``, the paper's comparison): constant ``w`` and ``c1 = c2``
(Clerc's constriction values ``PLAIN``), uniform random initial positions.

Choices the paper does not give (it prints no numbers for them):

- factor ranges: the common literature values w 0.9 -> 0.4, c1 2.5 -> 0.5, c2 0.5 -> 2.5;
- search box: ``P`` within ``identity +- matrix_span`` (default 0.5, i.e. gains 0.67..2 and
  cross terms up to 0.5: Li et al.'s (2018) scale factors 0.80..1.31 and Ding's (2024) hull soft
  iron up to 0.15 fit with room), ``o`` within ``+- offset_span * F`` (default 2 % of F,
  about 1000 nT in the Earth's field: Ding's (2024) offsets plus hard iron reach 500 nT);
- velocity clamp ``VMAX_FRACTION`` (20 %) of the box width per dimension; particles that
  leave the box are put back on its wall with zero velocity in that dimension;
- ``r1, r2`` drawn per particle and per dimension.

If the best offset ends on the wall of the box the true offset may lie outside it and
:class:`CalibrationFailed` is raised (use method ``ml``, or a larger ``offset_span``).

The rotation part of ``P`` is not observable from the TMI (any ``Q P`` with ``Q``
orthogonal has the same fitness); the result is reduced to the upper-triangular factor of
``P = Q U`` (QR, positive diagonal), as every scalar fit in :mod:`magcal_ros.core.scalar_fit`.
The swarm's precision is limited by its budget: it approaches, but unlike ``ml`` does not
reliably reach, the noise floor (see ``benchmarks/bench_calibration.py``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.scalar_fit import ScalarFit, _readings, _target
from magcal_ros.errors import CalibrationFailed, InputError

Array = NDArray[np.float64]

DIM: int = 12
"""Decision variables: 9 entries of ``P`` (row-major) and 3 of ``o / F``."""
W_RANGE: tuple[float, float] = (0.9, 0.4)
"""Inertia weight at the first and at the last iteration (improved PSO)."""
C1_RANGE: tuple[float, float] = (2.5, 0.5)
"""Cognitive factor at the first and at the last iteration (improved PSO)."""
C2_RANGE: tuple[float, float] = (0.5, 2.5)
"""Social factor at the first and at the last iteration (improved PSO)."""
PLAIN: tuple[float, float, float] = (0.7298, 1.49618, 1.49618)
"""Constant ``(w, c1, c2)`` of the plain PSO (Clerc's constriction coefficients)."""
VMAX_FRACTION: float = 0.2
"""Velocity limit per dimension as a fraction of the search box width."""


def circle_map(z: Array) -> Array:
    """One step of Ding's (2024) Circle chaotic map on values in [0, 1)."""
    return np.mod(2.0 * z + 0.2 - 0.7 / (2.0 * np.pi) * np.cos(2.0 * np.pi * z + 0.5 * np.pi), 1.0)


def chaotic_unit(particles: int, rng: np.random.Generator, burn_in: int = 20) -> Array:
    """(particles, DIM) values in [0, 1): one chaotic orbit per dimension across particles."""
    z = rng.uniform(0.0, 1.0, DIM)
    for _ in range(burn_in):
        z = circle_map(z)
    out = np.empty((particles, DIM))
    for k in range(particles):
        out[k] = z
        z = circle_map(z)
    return out


def search_box(matrix_span: float, offset_span: float) -> tuple[Array, Array]:
    """Lower and upper bounds (DIM,) around ``P = I``, ``o = 0`` (units of F)."""
    centre = np.concatenate([np.eye(3).reshape(-1), np.zeros(3)])
    half = np.concatenate([np.full(9, matrix_span), np.full(3, offset_span)])
    return centre - half, centre + half


def features(x: Array) -> Array:
    """Quadratic monomials (N, 10) of readings x (N, 3): ``|P (x - o)|^2 = features @ coef``."""
    a, b, c = x.T
    one = np.ones(len(x))
    return np.column_stack([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c, a, b, c, one])


def fitness(positions: Array, phi: Array) -> Array:
    """RMS of ``|P (x - o)| - 1`` per particle, positions (n, DIM), ``phi = features(x)``.

    Uses ``|P (x - o)|^2 = x^T Q x - 2 o^T Q x + o^T Q o`` with ``Q = P^T P``: one
    (N, 10) x (10, n) product per iteration instead of n matrix-vector sweeps.
    """
    p = positions[:, :9].reshape(-1, 3, 3)
    o = positions[:, 9:]
    q = np.einsum("pki,pkj->pij", p, p)
    qo = np.einsum("pij,pj->pi", q, o)
    coef = np.column_stack(
        [q[:, 0, 0], q[:, 1, 1], q[:, 2, 2], q[:, 0, 1], q[:, 0, 2], q[:, 1, 2], -2.0 * qo, np.sum(o * qo, axis=1)]
    )
    norm = np.sqrt(np.clip(phi @ coef.T, 0.0, None))
    return np.sqrt(np.mean((norm - 1.0) ** 2, axis=0))


def _factors(it: int, iterations: int, improved: bool) -> tuple[float, float, float]:
    """``(w, c1, c2)`` at iteration ``it`` (0-based) of ``iterations``."""
    if not improved:
        return PLAIN
    left = (iterations - it) / iterations  # 1 at the start, 1/iterations at the end
    w = W_RANGE[1] + (W_RANGE[0] - W_RANGE[1]) * left
    c1 = C1_RANGE[1] + (C1_RANGE[0] - C1_RANGE[1]) * left
    c2 = C2_RANGE[0] + (C2_RANGE[1] - C2_RANGE[0]) * (1.0 - left)
    return w, c1, c2


def swarm(
    x: Array,
    lower: Array,
    upper: Array,
    particles: int,
    iterations: int,
    rng: np.random.Generator,
    improved: bool = True,
) -> tuple[Array, float]:
    """Run the swarm on readings ``x`` (N, 3) in units of F; best position and fitness."""
    width = upper - lower
    unit = chaotic_unit(particles, rng) if improved else rng.uniform(0.0, 1.0, (particles, DIM))
    pos = lower + unit * width
    vmax = VMAX_FRACTION * width
    vel = rng.uniform(-1.0, 1.0, (particles, DIM)) * vmax
    phi = features(x)
    best_pos, best_fit = pos.copy(), fitness(pos, phi)
    g = int(np.argmin(best_fit))
    for it in range(iterations):
        w, c1, c2 = _factors(it, iterations, improved)
        r1 = rng.uniform(0.0, 1.0, (particles, DIM))
        r2 = rng.uniform(0.0, 1.0, (particles, DIM))
        vel = w * vel + c1 * r1 * (best_pos - pos) + c2 * r2 * (best_pos[g] - pos)
        vel = np.clip(vel, -vmax, vmax)
        pos = pos + vel
        out = (pos < lower) | (pos > upper)
        pos = np.clip(pos, lower, upper)
        vel[out] = 0.0
        fit = fitness(pos, phi)
        better = fit < best_fit
        best_pos[better] = pos[better]
        best_fit[better] = fit[better]
        g = int(np.argmin(best_fit))
    return best_pos[g].copy(), float(best_fit[g])


def upper_triangular(p: Array) -> Array:
    """Upper-triangular ``U`` with a positive diagonal and ``P = Q U`` (Q orthogonal)."""
    _, u = np.linalg.qr(p)
    return u * np.sign(np.diag(u))[:, None]


def pso_fit(
    readings: ArrayLike,
    intensity: float | None,
    particles: int = 50,
    iterations: int = 400,
    seed: int | None = 0,
    improved: bool = True,
    matrix_span: float = 0.5,
    offset_span: float = 0.02,
) -> ScalarFit:
    """Scalar calibration of readings (N, 3) in T by particle swarm (Ding (2024)).

    ``intensity`` is F in T (None: relative, F = mean norm of the centred readings).
    ``matrix_span`` and ``offset_span`` set the search box (fractions of F, see the
    module notes). Deterministic for a given ``seed``. Returns ``method="pso"`` with an
    upper-triangular matrix, the offset (T), F and the TMI RMS (T); no uncertainty.
    """
    if particles < 2 or iterations < 1:
        raise InputError(f"PSO needs >= 2 particles and >= 1 iteration, got {particles} and {iterations}")
    if not (0 < matrix_span < 1) or not (0 < offset_span < 1):
        raise InputError("PSO search spans must be fractions of F in (0, 1)")
    r = _readings(readings)
    f = _target(r, intensity)
    lower, upper = search_box(matrix_span, offset_span)
    best, rms = swarm(r / f, lower, upper, particles, iterations, np.random.default_rng(seed), improved)
    on_wall = np.isclose(best[9:], lower[9:], rtol=0.0, atol=1e-3 * offset_span) | np.isclose(
        best[9:], upper[9:], rtol=0.0, atol=1e-3 * offset_span
    )
    if np.any(on_wall):
        raise CalibrationFailed(
            f"PSO offset ended on its search bound (+-{offset_span:.0%} of F): the offset is larger; "
            "use method 'ml' or a larger offset_span"
        )
    matrix = upper_triangular(best[:9].reshape(3, 3))
    return ScalarFit(matrix, best[9:] * f, f, rms * f, None, "pso")

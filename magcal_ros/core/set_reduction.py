"""A subset of a long recording's sets that keeps what the calibration needs from it.

A calibration determines a few dozen parameters; a mission bag carries hundreds of
thousands of sets. The expensive stages (the robust joint fit, its outlier rounds, the
block jackknife, the identifiability analysis, the quality gates) run on a subset of at most
``target`` sets, and one Gauss-Newton pass over every set then brings the estimate and its
information to the full recording (:func:`magcal_ros.core.array_fit.refine_on_all`).

The subset (:func:`choose_sets`) is made of short runs of consecutive sets, so that the
time order survives (noise correlation, drift with time, the field rates of the lag block
all look at neighbours in time):

- the recording, in time order, is cut into runs of :data:`RUN_LENGTH` sets;
- each run falls in one cell of an equal-angle cube map of the field direction it saw
  (:data:`CUBE_CELLS` per face side, 6 faces);
- every cell keeps up to the same number of runs (water filling: rare attitudes keep all
  their runs, common ones are thinned), spread evenly over the recording's time, so that the
  coverage and the whole time span (temperature, drift) stay.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.batched import axis_major

Array = NDArray[np.float64]

RUN_LENGTH: int = 16
"""Consecutive sets per run of the subset (twice the reach of the field-rate estimate)."""
CUBE_CELLS: int = 4
"""Cells per side of each face of the cube map of field directions (6 x 4 x 4 = 96 cells)."""
SETS_PER_SENSOR: int = 1000
"""Sets per sensor the expensive stages use at most by default (a sensor has 12 parameters:
a thousand sets determine them to a tenth of the noise; the pass over every set does the rest)."""


def solve_budget(sensors: int, limit: int | None = None) -> int:
    """Sets the expensive stages use at most: ``limit``, or :data:`SETS_PER_SENSOR` per sensor
    when it is None; 0 means every set."""
    return SETS_PER_SENSOR * sensors if limit is None else max(0, int(limit))


def direction_proxy(raw: Array) -> Array:
    """(N, 3) rough unit field direction per set from raw sets (N, S, 3): the sensors' mean
    reading minus the centre of its cloud (mid-range per axis). Good enough to sort sets into
    coarse attitude cells before any calibration."""
    r = np.asarray(raw, dtype=float)
    if not len(r):
        return r.mean(axis=1)
    v = axis_major(r).reshape(-1, 3, len(r)).mean(axis=0)  # (3, N): each axis contiguous
    v -= 0.5 * (v.min(axis=1) + v.max(axis=1))[:, None]
    v /= np.maximum(np.sqrt(np.einsum("an,an->n", v, v)), 1e-300)
    return v.T


def cube_cell(directions: Array, cells: int = CUBE_CELLS) -> NDArray[np.int64]:
    """(N,) cell index (0 .. 6 cells^2 - 1) of unit vectors on an equal-angle cube map."""
    d = np.asarray(directions, dtype=float)
    axis = np.argmax(np.abs(d), axis=1)
    rows = np.arange(len(d))
    major = d[rows, axis]
    face = 2 * axis + (major < 0)
    others = np.stack([d[rows, (axis + 1) % 3], d[rows, (axis + 2) % 3]], axis=1) / np.maximum(np.abs(major), 1e-300)[:, None]
    # equal angle: arctan of the face coordinates, in [-pi/4, pi/4]
    uv = np.clip(((np.arctan(others) / (np.pi / 2) + 0.5) * cells).astype(np.int64), 0, cells - 1)
    return face * cells * cells + uv[:, 0] * cells + uv[:, 1]


def choose_sets(directions: Array, order: NDArray[np.int64], target: int,
                run_length: int = RUN_LENGTH) -> NDArray[np.int64]:
    """Indices (into the recording, in time order) of at most about ``target`` sets.

    ``directions`` (N, 3) unit (a proxy is enough), ``order`` (N,) the sets' time order.
    Returns every set (in time order) when ``N <= target``.
    """
    order = np.asarray(order, dtype=np.int64)
    n = len(order)
    if n <= target:
        return order.copy()
    starts = np.arange(0, n, run_length)
    budget = max(1, target // run_length)
    d = np.take(axis_major(directions), order, axis=1)  # (3, N) in time order
    sums = np.add.reduceat(d, starts, axis=1).T
    cell = cube_cell(sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-300))
    counts = np.bincount(cell, minlength=6 * CUBE_CELLS**2)
    # water filling: the largest per-cell quota whose total fits the budget
    low, high = 0, int(counts.max())
    while low < high:
        mid = (low + high + 1) // 2
        if np.minimum(counts, mid).sum() <= budget:
            low = mid
        else:
            high = mid - 1
    quota = low
    take = np.minimum(counts, quota)
    spare = budget - int(take.sum())  # one more run for the fullest cells while the budget lasts
    if spare > 0:
        fuller = np.argsort(-(counts - take), kind="stable")[:spare]
        take[fuller] += (counts[fuller] > take[fuller]).astype(np.int64)
    # In each cell, ``take`` of its runs evenly spread over its members in time order: member
    # round(j (m - 1) / (k - 1)) for j < k (the first alone when k = 1), all cells at once.
    by_cell = np.argsort(cell, kind="stable")  # runs grouped by cell, in time order within each
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])  # where each cell's runs start in by_cell
    grouped = cell[by_cell]  # per grouped run: its cell
    k, m, begin = take[grouped], counts[grouped], first[grouped]  # its cell's take, member count, start
    j = np.arange(len(by_cell)) - begin  # rank within the cell
    keep = j < k  # the first k ranks of a cell stand for its k picks
    kk, mm, jj = k[keep], m[keep], j[keep]
    step = np.where(kk > 1, (mm - 1) / np.maximum(kk - 1, 1), 0.0)
    member = np.round(jj * step).astype(np.int64)
    picked = np.sort(by_cell[begin[keep] + member])
    positions = (starts[picked][:, None] + np.arange(run_length)[None, :]).reshape(-1)
    positions = positions[positions < n]
    return order[positions]

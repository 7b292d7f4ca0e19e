"""Statistics of a recording too large to hold: quantiles and set-to-set noise in bounded memory.

A campaign report (``magcal batch``) summarises each corrected recording while it is read
back chunk by chunk, so its memory does not grow with the recording:

- :class:`LogHistogram`: quantiles of non-negative values (e.g. the TMI residual
  ``| |B| - F |`` in T) from logarithmic bins of a fixed relative width; a quantile is
  exact to within that width (0.1 % by default);
- :class:`StepNoise`: the noise of a slowly varying signal (e.g. the gradient tensor) from
  the differences between consecutive sets: ``sqrt(mean(diff^2) / 2)`` over components,
  which for white noise of standard deviation ``s`` per component is ``s``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray


class LogHistogram:
    """Counts of non-negative values in log-spaced bins between ``low`` and ``high``.

    Values below ``low`` (zero included) count in the lowest bin, values above ``high`` in
    the highest; NaN is ignored. Bin edges grow by the factor ``1 + resolution``.
    """

    def __init__(self, low: float = 1e-15, high: float = 1e-2, resolution: float = 1e-3) -> None:
        if not (0 < low < high and resolution > 0):
            raise ValueError("LogHistogram needs 0 < low < high and resolution > 0")
        self.low = float(low)
        self.step = math.log1p(resolution)
        self.bins = int(math.ceil(math.log(high / low) / self.step)) + 1
        self.counts: NDArray[np.int64] = np.zeros(self.bins, np.int64)

    @property
    def count(self) -> int:
        """Values added so far."""
        return int(self.counts.sum())

    def add(self, values: ArrayLike) -> None:
        """Count ``values`` (any shape; NaN ignored)."""
        v = np.abs(np.asarray(values, dtype=float).reshape(-1))
        v = v[np.isfinite(v)]
        if len(v) == 0:
            return
        with np.errstate(divide="ignore"):
            idx = np.floor(np.log(np.maximum(v, self.low) / self.low) / self.step)
        idx = np.clip(idx, 0, self.bins - 1).astype(np.int64)
        self.counts += np.bincount(idx, minlength=self.bins)

    def quantile(self, q: float) -> float | None:
        """The ``q`` quantile (0..1) as the inverted empirical CDF: the smallest value ``x``
        with at least ``q`` of the values ``<= x``; the bin's geometric centre. None when empty."""
        n = self.count
        if n == 0:
            return None
        rank = max(1, int(math.ceil(q * n - 1e-9)))
        k = int(np.searchsorted(np.cumsum(self.counts), rank))
        return self.low * math.exp((k + 0.5) * self.step) if k > 0 else self.low


class StepNoise:
    """RMS of the differences between consecutive rows, divided by sqrt(2), over all columns.

    Rows are added in order, possibly over several calls; the last row of one call is
    differenced with the first of the next. NaN rows are skipped (their differences ignored).
    """

    def __init__(self) -> None:
        self.total = 0.0
        self.terms = 0
        self.last: NDArray[np.float64] | None = None

    def add(self, rows: ArrayLike) -> None:
        """Add rows (n, c) in order."""
        r = np.asarray(rows, dtype=float)
        if r.size == 0:
            return
        r = r.reshape(len(r), -1)
        if self.last is not None:
            r = np.concatenate([self.last[None], r])
        d = np.diff(r, axis=0)
        d = d[np.all(np.isfinite(d), axis=1)]
        self.total += float(np.sum(d * d))
        self.terms += d.size
        self.last = r[-1].copy()

    def value(self) -> float | None:
        """``sqrt(mean(diff^2) / 2)``, or None with fewer than two rows."""
        return math.sqrt(self.total / self.terms / 2.0) if self.terms else None

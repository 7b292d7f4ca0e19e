"""Noise-aware quality gates: accept a calibration, or refuse it naming the cause that fits.

Rules (documented in docs/quality.md), per sensor, on the fit's residuals in time order:

1. **Noise from the data.** The white-noise level is estimated from second differences of
   the residual in time (they cancel anything that varies slowly: attitude-dependent
   errors, drift, a field step), robustly (median absolute deviation).
2. **A step in the field.** When one split of the TMI residual in time explains a large
   part of it (:data:`STEP_EXPLAINED`) and is highly significant (:data:`STEP_SIGMAS`), the
   field changed during the manoeuvre (iron moved, a vehicle passed, an anomaly was
   crossed): refused, naming size and time.
3. **Residual against noise.** When the sets follow a motion in time (consecutive field
   directions much closer than arbitrary pairs), second differences see the sensor's noise
   and the fit's residual (RMS per axis of the readings used) may exceed it by
   :data:`RESIDUAL_RATIO` at most. Sets in no particular order (synthetic, resampled) do not
   show the noise; their residual may then be at most :data:`MAX_RESIDUAL_FRACTION` of F.
   ``max_residual`` (T) replaces either rule with an absolute bound. Beyond it: a field that
   is not uniform or not constant (iron nearby, a gradient, drift), or a faulty sensor.
4. **Outliers.** At most :data:`MAX_OUTLIER_FRACTION` of a sensor's readings may be
   excluded as outliers; when the excluded readings form long runs in time the field
   changed, otherwise they are spikes.
5. **Collapse.** A residual far below the sensor's quantisation (:func:`quantisation_step`)
   means the fit has more freedom than the data determine: refused.
6. **Reference intensity.** With a reference F the sensors' mean gain must be plausible:
   beyond :data:`MAX_GAIN_ERROR` the reference (or the units) is wrong, and the intensity the
   data imply is reported; beyond :data:`WARN_GAIN_ERROR` a warning.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.batched import WELL_CONDITIONED, axis_major, well_conditioned
from magcal_ros.core.scalar_fit import clipped_axes
from magcal_ros.core.stamps import ns_to_seconds
from magcal_ros.core.uncertainty import autocorrelation, bandwidth
from magcal_ros.core.units import NT

Array = NDArray[np.float64]

RESIDUAL_RATIO: float = 17.0
"""Largest accepted fit residual (RMS per axis) over the white noise the data show. Generous:
strongly time-correlated noise (AR(1) 0.98) already leaves 7-9x, and a field that is not
uniform leaves tens to thousands."""
WARN_RATIO: float = 3.5
"""A residual beyond this many times the white noise is reported as a warning."""
MAX_OUTLIER_FRACTION: float = 0.25
"""Largest accepted fraction of a sensor's readings excluded as outliers."""
STUCK_FRACTION: float = 0.5
"""An axis that reads one exact value in more than this fraction of a manoeuvre is stuck (at least
one half: such a value is the median, which is how :func:`stuck_axis` finds it)."""
MIN_RUN: int = 10
"""Excluded readings in runs of at least this many consecutive sets count as a run."""
MAX_GAIN_ERROR: float = 0.2
"""Largest accepted mean sensor gain error implied by a reference intensity (20 %)."""
WARN_GAIN_ERROR: float = 0.03
"""A mean gain error beyond this (3 %) is reported as a warning."""
ORDER_FRACTION: float = 0.3
"""Sets are in time order when consecutive field directions differ by less than this fraction
of the typical angle between any two; then second differences read the sensor noise."""
MAX_RESIDUAL_FRACTION: float = 0.05
"""Largest accepted residual (RMS per axis), as a fraction of F, when the noise cannot be read
from the data: consumer sensors with up to 3-4 % noise pass. A field that is not uniform or not
constant is left to the step test then (a fluxgate's 300 nT step is 0.3 % of F)."""
STEP_EXPLAINED: float = 0.25
"""A single step explaining this much of the TMI residual's variance ..."""
STEP_SIGMAS: float = 5.0
"""... and this significant (its size over its standard error, widened for time correlation) ..."""
STEP_NOISE: float = 20.0
"""... and, for sets in time order, this many white-noise sd in size is a change of the field."""
COLLAPSE_RATIO: float = 0.43
"""A residual below this fraction of the quantisation noise means a collapsed fit."""


def white_noise(series: Array) -> Array:
    """Per-column white-noise sd of a time-ordered (N, K) series from its second differences (robust)."""
    x = np.asarray(series, dtype=float).reshape(len(series), -1)
    if len(x) < 5:
        return np.full(x.shape[1], np.nan)
    d2 = np.diff(axis_major(x), n=2, axis=1)  # (K, N - 2): each column's series contiguous
    mad = np.median(np.abs(d2 - np.median(d2, axis=1)[:, None]), axis=1)
    return 1.4826 * mad / np.sqrt(6.0)


def quantisation_step(readings: Array) -> float:
    """The smallest step between distinct values of a sensor's readings (T), 0 if none is evident.

    A quantised sensor shows readings on a grid: the typical spacing of sorted distinct
    values of each axis. Continuous readings (a fluxgate, a simulation) give 0.
    """
    r = np.asarray(readings, dtype=float).reshape(len(readings), -1)
    steps = []
    for col in r.T:
        u = np.unique(col)
        if len(u) < 3 or len(u) > 0.5 * len(col):
            return 0.0
        steps.append(float(np.median(np.diff(u))))
    return float(min(steps)) if steps else 0.0


@dataclass(frozen=True)
class Step:
    """The best single step of a series: where, how large, and how much of it it explains."""

    index: int
    size: float
    explained: float
    """Fraction of the series' variance the step explains (0..1)."""
    t_statistic: float = 0.0
    """Step size over its standard error (the scatter left around the two levels)."""


def best_step(series: Array) -> Step:
    """The split of a (N,) series into two constant parts that explains most of its variance."""
    x = np.asarray(series, dtype=float)
    n = len(x)
    if n < 4:
        return Step(0, 0.0, 0.0)
    c = np.cumsum(x - x.mean())
    k = np.arange(1, n)
    gain = c[:-1] ** 2 * n / (k * (n - k))  # between-group sum of squares for a split after k
    j = int(np.argmax(gain))
    total = float(np.sum((x - x.mean()) ** 2))
    split = j + 1
    size = float(x[split:].mean() - x[:split].mean())
    left = max(total - float(gain[j]), 1e-300)
    # Standard error of the step, widened by the time correlation of what is left (Bartlett).
    rest = np.concatenate([x[:split] - x[:split].mean(), x[split:] - x[split:].mean()])
    lags = bandwidth(rest)
    rho = autocorrelation(rest, lags)
    tau = max(1.0, 1.0 + 2.0 * float(np.sum((1.0 - np.arange(1, lags + 1) / (lags + 1.0)) * rho[1:])))
    se = np.sqrt(tau * left / max(n - 2, 1) * (1.0 / split + 1.0 / (n - split)))
    return Step(split, size, float(gain[j] / total) if total > 0 else 0.0, abs(size) / se)


def in_time_order(directions: Array) -> bool:
    """True when consecutive field directions are much closer than arbitrary pairs: the sets
    follow a continuous motion in time (a recording), not shuffled or independent attitudes."""
    d = np.asarray(directions, dtype=float)
    if len(d) < 10:
        return False
    step = np.median(np.arccos(np.clip(np.einsum("na,na->n", d[1:], d[:-1]), -1.0, 1.0)))
    a, b = _pairs(len(d))
    spread = np.median(np.arccos(np.clip(np.einsum("na,na->n", d[a], d[b]), -1.0, 1.0)))
    return bool(step < ORDER_FRACTION * spread)


@functools.lru_cache(maxsize=8)
def _pairs(n: int) -> NDArray[np.int64]:
    """(2, min(n, 2000)) the same pseudo-random pairs of n items on every call (read-only)."""
    out = np.random.default_rng(0).integers(0, n, (2, min(n, 2000)))
    out.flags.writeable = False
    return out


def longest_runs(mask: Array) -> float:
    """Fraction of the true entries of a boolean (N,) series that lie in runs of >= :data:`MIN_RUN`."""
    m = np.asarray(mask, dtype=bool)
    if not m.any():
        return 0.0
    edges = np.diff(np.concatenate([[0], m.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    lengths = ends - starts
    return float(lengths[lengths >= MIN_RUN].sum() / m.sum())


DRIFT_EXPLAINED: float = 0.3
"""A smooth function of time explaining this much of a sensor's residual variance ..."""
DRIFT_NOISE: float = 5.0
"""... changing by this many white-noise sd over the recording ..."""
DRIFT_OVER_ATTITUDE: float = 2.0
"""... and this many times what a function of the attitude explains: the offsets drifted in time."""
TIMING_EXPLAINED: float = 0.3
"""The field's rate of change explaining this much of a residual: the reading is not taken at its stamp."""
STEP_MARGIN: float = 0.05
"""A drift must explain this much more than a single step (else the field changed at one time)."""
DRIFT_DEGREE: int = 3
"""Degree of the polynomial in time that stands for a drift."""


@dataclass(frozen=True)
class ResidualShape:
    """What a sensor's residual follows, beyond its white noise."""

    drift: float
    """Change (T) over the recording of the part that follows time (0: none found)."""
    duration: float
    """s the recording spans."""
    time_explained: float
    """Fraction of the residual variance an offset and a gain that follow time smoothly explain."""
    attitude_explained: float
    """Fraction a quadratic function of the field direction explains."""
    rate_explained: float
    """Fraction a linear function of the field's rate of change explains (timing)."""
    step_explained: float
    """Fraction the best single step of offset and gain in time explains (a sudden change)."""

    @property
    def drifts(self) -> bool:
        """The residual follows time, smoothly, rather than attitude (offsets that wander: temperature)."""
        return self.drift > 0 and self.time_explained > DRIFT_EXPLAINED and (
            self.time_explained > DRIFT_OVER_ATTITUDE * self.attitude_explained) and (
            self.time_explained > self.step_explained + STEP_MARGIN)

    @property
    def timing(self) -> bool:
        """The residual follows the turn rate: readings not taken at their stamps (a lag)."""
        return self.rate_explained > TIMING_EXPLAINED and self.rate_explained > self.time_explained


def _explained(y: Array, x: Array) -> float:
    """Fraction of the variance of ``y`` (N, 3) a least-squares fit on the columns of ``x`` (N, K) explains."""
    return _fit_explained(y, np.column_stack([np.ones(len(y)), x]))[0]


def _fit_explained(y: Array, design: Array, gram: Array | None = None) -> tuple[float, Array | None]:
    """The fraction of the variance of ``y`` (N, M) the columns of ``design`` (N, K, a constant among them)
    explain, and the coefficients (K, M) (None when there is nothing to explain); ``gram``: ``design^T design``
    where it is known (several ``y`` on one design)."""
    total = float(np.sum((y - y.mean(axis=0)) ** 2))
    if total <= 0 or len(y) <= design.shape[1] + 2:
        return 0.0, None
    gram = design.T @ design if gram is None else gram
    if well_conditioned(gram[None])[0]:  # the normal equations: a tenth of the SVD's time
        coef = np.linalg.solve(gram, design.T @ y)
    else:  # (columns near dependence: the minimum-norm solution)
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    return float(1.0 - np.sum((y - design @ coef) ** 2) / total), coef


def _segment_sse(sums: Array) -> Array:
    """Residual sums of squares of ``y`` fitted on ``[1, d]``, from the sums (K, 5, 5) of ``z z^T``,
    ``z = [1, d, y]``, over K segments (centred, so a direction component that does not vary drops out)."""
    n = np.maximum(sums[:, 0, 0], 1e-300)
    mean = sums[:, 0, 1:] / n[:, None]
    centred = sums[:, 1:, 1:] - n[:, None, None] * mean[:, :, None] * mean[:, None, :]  # d and y about their means
    try:  # the last Cholesky pivot of [d, y]'s scatter is what d leaves of y's: the SSE
        pivots = np.diagonal(np.linalg.cholesky(centred), axis1=1, axis2=2) ** 2
        if np.all(pivots[:, :3] > WELL_CONDITIONED * np.diagonal(centred, axis1=1, axis2=2)[:, :3]):
            return np.where(sums[:, 0, 0] > 0, pivots[:, 3], 0.0)
    except np.linalg.LinAlgError:  # (d constant in a segment, or y fitted exactly by it)
        pass
    cdd, cdy, cyy = centred[:, :3, :3], centred[:, :3, 3], centred[:, 3, 3]
    fit = np.einsum("ka,kab,kb->k", cdy, np.linalg.pinv(cdd, rcond=1e-12, hermitian=True), cdy)
    return np.where(sums[:, 0, 0] > 0, np.maximum(cyy - fit, 0.0), 0.0)


def _step_explained(y: Array, d: Array, splits: NDArray[np.int64]) -> float:
    """The largest fraction of the variance of ``y`` (N,) that a step at one of ``splits`` explains:
    an offset and a gain along the direction ``d`` (N, 3) that change at the split, that is
    ``[1, d]`` fitted before and after it apart (running sums: every split for the price of one)."""
    total = float(np.sum((y - y.mean()) ** 2))
    if total <= 0 or len(y) <= 7 + 3:  # as _explained with the step's seven columns
        return 0.0
    z = np.concatenate([np.ones((1, len(y))), np.asarray(d, dtype=float).T, y[None]])  # (5, N), each row contiguous
    zz = (z[:, None, :] * z[None, :, :]).reshape(25, -1)
    # the sums of the rows before each split: the pieces between the splits summed, then those sums run
    n = len(y)
    cuts = np.unique(splits[(splits > 0) & (splits < n)])
    running = np.cumsum(np.add.reduceat(zz, np.concatenate([[0], cuts]).astype(np.int64), axis=1), axis=1)
    # (running[:, j]: the rows before cuts[j]; the last column every row)
    before = running[:, np.searchsorted(cuts, np.clip(splits, 0, n))]
    before[:, splits <= 0] = 0.0
    before = before.T.reshape(-1, 5, 5)  # rows < split
    sse = _segment_sse(before) + _segment_sse(running[:, -1].reshape(1, 5, 5) - before)
    return float(np.max(1.0 - sse / total))


@dataclass(frozen=True)
class ShapeBasis:
    """What every sensor's :func:`residual_shape` shares over one time order: the span (s), the drift's design
    (the constant, polynomials in time alone and times the direction, the direction) and the quadratic function
    of the direction (with the constant), each with its Gram matrix, and the splits a step is tried at."""

    span: float
    design: Array
    design_gram: Array
    quad: Array
    quad_gram: Array
    splits: NDArray[np.int64]


def shape_basis(times: Array, directions: Array) -> ShapeBasis | None:
    """The :class:`ShapeBasis` of sets at ``times`` (N,) s with field ``directions`` (N, 3), in time order; None
    where they are too few or span no time (no shape to tell)."""
    t = np.asarray(times, dtype=float)
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    if len(t) < 4 * (DRIFT_DEGREE + 10) or span <= 0:
        return None
    x = (t - t[0]) / span * 2.0 - 1.0
    poly = np.column_stack([np.polynomial.legendre.legval(x, np.eye(DRIFT_DEGREE + 1)[k])
                            for k in range(1, DRIFT_DEGREE + 1)])
    d = np.asarray(directions, dtype=float)
    design = np.column_stack([np.ones(len(t)), poly, (poly[:, :, None] * d[:, None, :]).reshape(len(d), -1), d])
    # (d_z^2 = 1 - d_x^2 - d_y^2 for unit directions: with the constant, it adds nothing)
    quad = np.column_stack([np.ones(len(t)), d, d[:, [0, 0, 1, 1, 2]] * d[:, [0, 1, 1, 2, 0]]])
    return ShapeBasis(span, design, design.T @ design, quad, quad.T @ quad,
                      np.linspace(len(t) * 0.05, len(t) * 0.95, 37).astype(int))


def residual_shape(tmi: Array, residual: Array, used: NDArray[np.bool_], times: Array, directions: Array,
                   rates: Array | None, noise: float, basis: ShapeBasis | None = None) -> ResidualShape:
    """How one sensor's residual follows time (``times`` (N,) s), the field direction
    (``directions`` (N, 3)) and its rate of change (``rates`` (N, 3) 1/s, or None), against its
    white ``noise`` (T); all in time order (``basis``: their :func:`shape_basis`, where already built).

    Time against attitude is read off the TMI residual ``tmi`` (N,) T (corrected norm minus F, every
    reading: excluded readings are where a drift shows most): an offset and a gain that follow time
    smoothly (polynomials in time, alone and times the direction) against a quadratic function of the
    direction. The rate from the vector residual ``residual`` (N, 3) T of the ``used`` readings (a
    reading late by ``tau`` is off by ``tau`` times the rate, across the field: the norm hides it).
    """
    y = np.asarray(tmi, dtype=float).reshape(-1, 1)
    basis = shape_basis(times, directions) if basis is None else basis
    if basis is None:
        t = np.asarray(times, dtype=float)
        return ResidualShape(0.0, float(t[-1] - t[0]) if len(t) > 1 else 0.0, 0.0, 0.0, 0.0, 0.0)
    span, design = basis.span, basis.design
    time_part, coef = _fit_explained(y, design, basis.design_gram)
    attitude_part = _fit_explained(y, basis.quad, basis.quad_gram)[0]
    # A sudden change (iron moved) is a step, not a drift: the best single split, offset and gain.
    step_part = _step_explained(y[:, 0], np.asarray(directions, dtype=float), basis.splits)
    rate_part = 0.0
    if rates is not None and used.sum() > 20:
        rate_part = _explained(np.asarray(residual, dtype=float)[used], np.asarray(rates, dtype=float)[used])
    if coef is None:  # nothing varies
        return ResidualShape(0.0, span, time_part, attitude_part, rate_part, step_part)
    drifting = design[:, : design.shape[1] - 3]  # without the direction's own columns
    trend = drifting @ coef[: drifting.shape[1]]
    change = float(np.ptp(trend))
    drift = change if change > DRIFT_NOISE * noise else 0.0
    return ResidualShape(drift, span, time_part, attitude_part, rate_part, step_part)


def drift_warning(name: str, shape: ResidualShape) -> str:
    """``mag1's offsets drift with time: about 60 nT over 200 s; ...`` (what to do)."""
    return (f"{name}'s offsets drift with time: about {shape.drift / NT:.0f} nT over {shape.duration:.0f} s; "
            "record the sensors' temperature (temperature.<name> columns, <name>/temperature topics) or calibrate "
            "over a shorter time")


@dataclass
class Verdict:
    """What the gates decided: a refusal (``cause``) or None, and warnings either way."""

    cause: str | None = None
    warnings: list[str] = field(default_factory=list)
    noise: Array | None = None
    """(S,) white-noise estimate per sensor (T)."""
    residual: Array | None = None
    """(S,) fit residual per axis per sensor (T)."""
    excluded: Array | None = None
    """(S,) readings excluded as outliers per sensor."""
    drift: list[str] = field(default_factory=list)
    """``mag1 46 nT over 200 s`` for each sensor whose offsets drift with time."""


def saturated(name: str, fraction: float) -> str:
    """Why a sensor with ``fraction`` of its readings clipped at full scale is refused."""
    return (f"{name} is saturated: {fraction:.0%} of its readings have an axis at its full-scale value; use a "
            "larger range, or mount it farther from the iron that drives it there")


def stuck_axis(readings: Array) -> tuple[int, float, float] | None:
    """(axis, value T, fraction) of an axis of one sensor's readings (N, 3) that holds one exact value
    in more than :data:`STUCK_FRACTION` of them, or None. A turning sensor's axis sweeps the field;
    even one clipped at full scale on one side cannot stay there for most of a rotation."""
    columns = axis_major(readings)
    return _stuck_in(columns, _may_hold_half(columns))


def _stuck_in(columns: Array, candidates: NDArray[np.bool_]) -> tuple[int, float, float] | None:
    """:func:`stuck_axis` of one sensor's readings by axis (3, N), each contiguous, looking only at the
    axes ``candidates`` (3,) marks (:func:`_may_hold_half`)."""
    n = columns.shape[1]
    for axis in np.flatnonzero(candidates):
        # a value held in more than half the readings holds the middle of their sorted order
        value = np.partition(columns[axis], [max(n // 2 - 1, 0), n // 2])[n // 2]  # (two kth: NumPy's faster path)
        count = int(np.count_nonzero(columns[axis] == value))
        if count > STUCK_FRACTION * n:
            return int(axis), float(value), count / n
    return None


def _may_hold_half(columns: Array) -> NDArray[np.bool_]:
    """(K,) False where no value of a series ``columns`` (K, N) fills more than half of it.

    Such a value fills both entries of one of the pairs (0, 1), (2, 3), ... (for an odd N: or the last
    entry and one of the two before it), so a series whose pairs are distinct is ruled out at once."""
    k, n = columns.shape
    if n < 3:
        return np.full(k, n > 0)
    half = n // 2
    out = (columns[:, 0 : 2 * half : 2] == columns[:, 1 : 2 * half : 2]).any(axis=1)
    if n % 2:
        out |= (columns[:, -1] == columns[:, -2]) | (columns[:, -1] == columns[:, -3])
    return out


def stuck(names: tuple[str, ...], index: int, axis: int, value: float, fraction: float) -> str:
    """Why a sensor with a stuck axis is refused, and which sensors to calibrate instead."""
    name = names[index]
    others = [n for n in names if n != name]
    leave = (f"calibrate the others without it (magcal --sensors {','.join(others)}; calibration node: "
             f"sensor_names without {name})") if others else "check the sensor and its cable"
    return (f"{name}'s {'xyz'[axis]} axis is stuck at {value:.6g} T in {fraction:.0%} of its readings while the "
            f"array turned: a sensor fault, not the field; {leave}")


def saturation(names: tuple[str, ...], raw: Array) -> tuple[NDArray[np.bool_], str | None]:
    """(N, S) True for readings clipped at a sensor's full scale, and the cause of a refusal when a
    sensor has an axis stuck at one value (:func:`stuck_axis`) or more clipped readings than outlier
    exclusion may take (:data:`MAX_OUTLIER_FRACTION`)."""
    columns = axis_major(raw)  # (S 3, N)
    candidates = _may_hold_half(columns).reshape(-1, 3)
    for i in np.flatnonzero(candidates.any(axis=1)):
        found = _stuck_in(columns[3 * i : 3 * i + 3], candidates[i])
        if found is not None:
            return np.zeros(raw.shape[:2], bool), stuck(names, int(i), *found)
    clipped = clipped_axes(columns).T
    for i, name in enumerate(names):
        if clipped[:, i].mean() > MAX_OUTLIER_FRACTION:
            return clipped, saturated(name, float(clipped[:, i].mean()))
    return clipped, None


def implied_intensity(intensity: float, implied_gain: float) -> float:
    """The field intensity (T) the data imply when a reference ``intensity`` F made the sensors' mean gain
    ``implied_gain``: the calibration maps the readings onto a sphere of radius F, so its matrices scale
    them by ``F / F_true`` and the gains they imply are ``F_true / F`` (sensors of unit gain): the data
    imply ``F_true = F * gain``. (A reference 51.5 uT against a 55 uT field: gains +6.8 %, 55 uT.)"""
    return intensity * implied_gain


@dataclass
class _Fit:
    """What every gate reads: the fit's residuals (N, S, 3) T, weights (N, S), TMI residuals (N, S) T,
    the per-sensor noise and residual (S,) T, seconds since the start (or set indices), and whether
    the sets follow a continuous motion."""

    names: tuple[str, ...]
    residuals: Array
    weights: Array
    tmi_residuals: Array
    raw: Array
    clipped: NDArray[np.bool_]
    noise: Array
    resid: Array
    t: Array
    timed: bool
    smooth: bool
    shapes: list[ResidualShape | None]

    def at(self, index: int) -> str:
        """Where set ``index`` lies, for a message."""
        if not self.timed:
            return f"at set {index}"
        return f"at t = {self.t[min(index, len(self.t) - 1)] - self.t[0]:.1f} s"

    def step_of(self, i: int) -> tuple[Step, int]:
        """The best step of sensor ``i``'s used TMI residuals and the set index where it lies."""
        rows = np.flatnonzero(self.weights[:, i] > 0)
        step = best_step(self.tmi_residuals[rows, i])
        return step, int(rows[min(step.index, len(rows) - 1)]) if len(rows) else 0


def _noise_and_residual(weights: Array, residuals: Array) -> tuple[Array, Array]:
    """(S,) white noise and RMS residual per axis (T) of each sensor's used readings (NaN when too few)."""
    s = weights.shape[1]
    noise, resid = np.full(s, np.nan), np.full(s, np.nan)
    for i in range(s):
        used = weights[:, i] > 0
        e = residuals[used, i]
        if used.sum() >= 5:
            noise[i] = float(np.nanmean(white_noise(e)))
        if used.any():
            resid[i] = float(np.sqrt(np.mean(e * e)))  # per axis, like the noise
    return noise, resid


def _outlier_gate(fit: _Fit, excluded: Array) -> str | None:
    """Refused when a sensor lost more than :data:`MAX_OUTLIER_FRACTION` of its readings, naming why."""
    n = len(fit.weights)
    for i, name in enumerate(fit.names):
        frac = excluded[i] / n
        if frac <= MAX_OUTLIER_FRACTION:
            continue
        shape = fit.shapes[i]
        if fit.clipped[:, i].sum() > 0.5 * excluded[i]:
            return saturated(name, float(fit.clipped[:, i].mean()))
        if shape is not None and shape.drifts:
            return f"{drift_warning(name, shape)} ({frac:.0%} of its readings no longer fit one calibration)"
        if longest_runs(fit.weights[:, i] == 0) > 0.5:
            step = best_step(fit.tmi_residuals[:, i])
            return (f"the field was not constant during the manoeuvre: {name}'s readings change by about "
                    f"{abs(step.size) / NT:.0f} nT {fit.at(step.index)} ({frac:.0%} of them no longer fit); "
                    "repeat the manoeuvre away from moving iron, or calibrate each part separately")
        return (f"too many outliers: {frac:.0%} of {name}'s readings are spikes far from the rest "
                f"(more than {MAX_OUTLIER_FRACTION:.0%}); check the sensor, its cable and nearby switching loads")
    return None


def _step_gate(fit: _Fit) -> str | None:
    """Refused when one sensor's TMI residual steps: the field changed during the manoeuvre."""
    for i, name in enumerate(fit.names):
        step, index = fit.step_of(i)
        # In time order the white noise is known and a change of the field must dwarf it (slow,
        # correlated noise also splits well); sets in no order leave only the step's significance.
        big = abs(step.size) > STEP_NOISE * fit.noise[i] if fit.smooth else step.t_statistic > 2 * STEP_SIGMAS
        if step.explained > STEP_EXPLAINED and step.t_statistic > STEP_SIGMAS and big:
            return (f"the field was not constant during the manoeuvre: {name}'s readings change by about "
                    f"{step.size / NT:+.0f} nT {fit.at(index)} (moving iron, a passing vehicle, an anomaly); "
                    "repeat the manoeuvre, or calibrate each part separately")
    return None


def _residual_limit(fit: _Fit, i: int, max_residual: float | None, intensity: float | None) -> tuple[float, str] | None:
    """(limit T, the rule in words) for sensor ``i``'s residual, or None where no limit applies."""
    if max_residual is not None:
        return max_residual, f"the given limit max residual {max_residual / NT:.3g} nT"
    if fit.smooth:
        return (RESIDUAL_RATIO * fit.noise[i],
                f"{RESIDUAL_RATIO:g}x the sensor noise the data show ({fit.noise[i] / NT:.3g} nT)")
    if intensity is not None:
        return (MAX_RESIDUAL_FRACTION * intensity,
                f"{MAX_RESIDUAL_FRACTION:.1%} of F (the sets are not in time order, so the sensor noise "
                "cannot be read from them)")
    return None


def _residual_warning(fit: _Fit, i: int, strict: bool, verdict: Verdict) -> None:
    """The warning for sensor ``i`` whose residual is within its limit but shaped (drift, timing, excess)."""
    name, shape = fit.names[i], fit.shapes[i]
    if shape is not None and shape.drifts:
        verdict.warnings.append(drift_warning(name, shape))
        verdict.drift.append(f"{name} {shape.drift / NT:.0f} nT over {shape.duration:.0f} s")
    elif shape is not None and shape.timing:
        verdict.warnings.append(
            f"{name}'s residual follows the turn rate: its readings are not taken at their stamps (a lag or "
            "a clock error); give the sensors' own streams so that their lags are estimated")
    elif fit.smooth and not strict and fit.resid[i] > WARN_RATIO * fit.noise[i]:
        verdict.warnings.append(
            f"{name}'s residual ({fit.resid[i] / NT:.3g} nT) is {fit.resid[i] / fit.noise[i]:.1f}x the white noise "
            "the data show: time-correlated noise, or a field that is not quite uniform")


def _residual_cause(fit: _Fit, i: int) -> str:
    """Why sensor ``i``'s residual is above its limit, from the residual's shape."""
    name, shape = fit.names[i], fit.shapes[i]
    step, index = fit.step_of(i)
    if step.explained > STEP_EXPLAINED:
        return (f"the field was not constant during the manoeuvre: it changed by about {step.size / NT:+.0f} nT "
                f"{fit.at(index)} (moving iron, a passing vehicle, an anomaly)")
    if shape is not None and shape.drifts:
        return drift_warning(name, shape).split(": ", 1)[0].replace(f"{name}'s offsets", "the offsets") + (
            f" (about {shape.drift / NT:.0f} nT over {shape.duration:.0f} s): record the sensors' temperature or "
            "calibrate over a shorter time")
    if shape is not None and shape.timing:
        return ("the residual follows the turn rate: the readings are not taken at their stamps (a lag, a clock "
                "error, sensors not sampled together); give the sensors' own streams (a bag) so that the sets are "
                "formed at one instant and the lags estimated")
    return ("the field was not uniform or not constant during the manoeuvre (iron nearby, the vehicle moving "
            "through a gradient, drift), or the sensor is faulty")


def _residual_gate(fit: _Fit, max_residual: float | None, intensity: float | None, verdict: Verdict) -> str | None:
    """Refused when a sensor's residual is above its limit (naming the cause its shape shows); warnings
    for residuals within it that drift, follow the turn rate or exceed the noise."""
    for i, name in enumerate(fit.names):
        limit = _residual_limit(fit, i, max_residual, intensity)
        if limit is None:
            continue
        value, rule = limit
        if not np.isfinite(fit.resid[i]) or not np.isfinite(value) or fit.resid[i] <= value:
            _residual_warning(fit, i, max_residual is not None, verdict)
            continue
        return (f"{name}'s residual after calibration is {fit.resid[i] / NT:.3g} nT, above {rule}: "
                f"{_residual_cause(fit, i)}; to accept it anyway raise the limit (magcal --max-residual, or the "
                "calibration node's max_residual parameter)")
    return None


def _collapse_gate(fit: _Fit) -> str | None:
    """Refused when a residual is far below the readings' quantisation: the fit has collapsed."""
    for i, name in enumerate(fit.names):
        q = quantisation_step(fit.raw[:, i])
        if q > 0 and fit.resid[i] < COLLAPSE_RATIO * q / np.sqrt(12.0):
            return (f"{name}'s residual ({fit.resid[i] / NT:.3g} nT) is far below its quantisation ({q / NT:.3g} nT "
                    "steps): the fit has collapsed because the manoeuvre does not determine the calibration; "
                    "turn the sensor about at least two axes")
    return None


def _reference_gate(implied_gain: float | None, intensity: float | None, verdict: Verdict) -> str | None:
    """Refused when the reference intensity is far from what the data imply; a warning when it is off."""
    if implied_gain is None or intensity is None:
        return None
    error = implied_gain - 1.0
    implied = implied_intensity(intensity, implied_gain)
    if abs(error) > MAX_GAIN_ERROR:
        return (f"the reference intensity {intensity / NT:.0f} nT disagrees with the data, which imply about "
                f"{implied / NT:.0f} nT (sensor gains would be off by {error:+.0%}): check --reference-field/--site "
                "and that the readings are in Tesla")
    if abs(error) > WARN_GAIN_ERROR:
        verdict.warnings.append(
            f"the reference intensity {intensity / NT:.0f} nT makes the sensor gains {error:+.1%} off "
            f"(the data imply about {implied / NT:.0f} nT): check the reference, unless the sensors' gains "
            "are known to be that far from 1")
    return None


def _excluded_warnings(fit: _Fit, excluded: Array, verdict: Verdict) -> None:
    """A warning per sensor with readings excluded as outliers (and how many were at full scale)."""
    for i, name in enumerate(fit.names):
        if excluded[i]:
            at_full_scale = int(np.sum(fit.clipped[:, i] & (fit.weights[:, i] == 0)))
            why = f" ({at_full_scale} at its full-scale value: saturated)" if at_full_scale else ""
            verdict.warnings.append(f"{int(excluded[i])} outlying readings of {name} excluded{why}")


def judge(
    names: tuple[str, ...],
    residuals: Array,
    weights: Array,
    tmi_residuals: Array,
    raw: Array,
    stamps_ns: Array | None = None,
    max_residual: float | None = None,
    implied_gain: float | None = None,
    intensity: float | None = None,
    directions: Array | None = None,
    clipped: NDArray[np.bool_] | None = None,
    rates: Array | None = None,
    smooth: bool | None = None,
) -> Verdict:
    """Apply the gates to a fit, in order (outliers, a step of the field, the residual, a collapse, the
    reference intensity); the first that refuses gives the cause.

    ``residuals`` (N, S, 3) T and ``weights`` (N, S) of the fit; ``tmi_residuals`` (N, S) T
    (corrected norm minus F, all readings); ``raw`` (N, S, 3) T; all in time order.
    ``implied_gain``: the sensors' mean gain when a reference intensity was given;
    ``intensity`` F (T); ``directions`` (N, 3) unit field directions (smoothness);
    ``clipped`` (N, S) the readings at full scale (default: from :func:`saturation`); ``rates``
    (N, 3) the field direction's rate of change (1/s), to tell a timing error; ``smooth`` whether
    the sets follow a continuous motion (:func:`in_time_order` of ``directions`` when None).
    """
    verdict = Verdict(excluded=np.sum(weights == 0, axis=0).astype(float))
    noise, resid = _noise_and_residual(weights, residuals)
    verdict.noise, verdict.residual = noise, resid
    t = ns_to_seconds(stamps_ns) if stamps_ns is not None else np.arange(len(raw), dtype=float)
    if clipped is None:
        clipped = saturation(names, raw)[0]
    if smooth is None:
        smooth = directions is not None and in_time_order(directions)
    smooth = bool(smooth and directions is not None)
    shapes: list[ResidualShape | None] = [None] * len(names)
    if smooth and stamps_ns is not None:
        basis = shape_basis(t, directions)  # type: ignore[arg-type]
        shapes = [residual_shape(tmi_residuals[:, i], residuals[:, i], weights[:, i] > 0, t, directions,  # type: ignore[arg-type]
                                 rates, noise[i], basis) for i in range(len(names))]
    fit = _Fit(names, residuals, weights, tmi_residuals, raw, clipped, noise, resid, t, stamps_ns is not None,
               smooth, shapes)
    verdict.cause = (_outlier_gate(fit, verdict.excluded) or _step_gate(fit)
                     or _residual_gate(fit, max_residual, intensity, verdict) or _collapse_gate(fit)
                     or _reference_gate(implied_gain, intensity, verdict))
    if verdict.cause is None:
        _excluded_warnings(fit, verdict.excluded, verdict)
    return verdict

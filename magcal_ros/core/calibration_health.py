"""Whether a running calibration still fits, judged from the corrected data themselves (no ROS).

A calibration is a snapshot: at sea the hull's magnetisation changes (a payload powered, a
battery swapped, a hard landing) and the corrected field goes wrong in a body-fixed way. Two
figures per sensor, over a sliding window of ``window`` seconds of sets (long enough to span
attitude changes), both compared with the noise the calibration stored:

- **TMI residual**: the part of ``|B_i|`` that follows the vehicle's attitude. A hard-iron
  change ``o`` on sensor ``i`` makes ``|B_i| - F ~ o . b`` (``b`` the field direction in the
  platform frame), which varies with heading; so do a scale or soft-iron change. A field
  that changes along the track (geology, the diurnal variation) does not follow the
  attitude. Per sensor the block means of ``|B_i|`` are fitted with a constant, a linear
  trend in time and a linear function of the block-mean field direction; the figure is the
  RMS over the window's sets of the fitted attitude part (beyond constant and trend).
- **Disagreement**: how far the sensors disagree beyond what the measured gradient
  explains: the residual of the least-squares fit of a centre field and a symmetric,
  traceless gradient (or, for sensors on a line, a gradient along it) to the corrected
  vectors, averaged over the window. A field, however non-uniform, is smooth over the array
  and leaves (nearly) none; a body-fixed change of one sensor leaves a constant residual
  at every attitude, also when the vehicle runs straight.

A passing magnetic target is a local, transient anomaly: the fits are robust. Tukey's
bisquare on one-second block means (scale from the median absolute deviation, starting from
the weighted median so that a few blocks far off cannot steer the first fit) marks the blocks
where the field did something the model does not expect (a target passing, a block straddling
a jump); those are left out and the rest fitted by least squares, so that the tests below
keep their stated level. A target lasting less than about half the window cannot raise an
alarm. Straight running gives the TMI fit no attitude to follow: its attitude part is then
no larger than the noise (and not significant); the disagreement still sees a body-fixed
change. A drift is named about half a window after it happens (when the blocks after it are
the majority), and stays named.

A sensor is **drifted** when a figure is both above ``warn_factor`` (WARN) or
``error_factor`` (ERROR) times its noise at calibration and significant against the
window's own scatter at the false-alarm probability :data:`FALSE_ALARM` (an F test of the
attitude part; a t test of each residual component, Bonferroni over the three). The false
alarm rate designed for: on clean data with white noise the significance tests alone alarm
with probability ``FALSE_ALARM`` (1e-6) per sensor and evaluation; the magnitude condition
on top (10 times the noise by default) makes a false alarm there practically impossible, so
what remains is model error, bounded by the factor: strong targets (250-400 nT at the array)
passed during a straight leg leave the TMI figure below 3-4 times the noise; an ambient
gradient ``g`` makes a sensor's TMI follow the attitude by up to ``g`` times its distance
from the centre (0.2 m on the default cross: 50 nT/m gives 10 nT). The disagreement names
one sensor when an offset of that sensor alone explains :data:`ATTRIBUTED` of it (a residual
spreads over all sensors), else every sensor it flags.

A change that looks the same at every attitude flown and at every sensor (a common offset
along the vertical during level yaw turns) cannot be told from a change of the field
itself; it shows only as ``tmi_offset`` (``|B_i|`` against the calibrated intensity) and
never raises an alarm.

Cost: :meth:`CalibrationHealth.add` copies one set into a buffer (about a microsecond);
:meth:`CalibrationHealth.assess` (once per status period) reduces the buffered sets to
one-second block sums with numpy and fits the window's blocks (a few milliseconds). Blocks
are cut by the sets' stamps, so the result does not depend on when ``assess`` runs nor on
how fast a recording is replayed.

Units: T in and out (nT only in the values for people); stamps int64 ns; platform frame.
"""

from __future__ import annotations

import functools
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.stamps import format_seconds
from magcal_ros.core.sync import RESTART_JUMP
from magcal_ros.core.tensor import least_squares_operator
from magcal_ros.core.units import NS_PER_S, NT

Array = NDArray[np.float64]

OK, WARN, ERROR = 0, 1, 2
"""Levels, as diagnostic_msgs/DiagnosticStatus numbers them."""
BLOCKS: int = 60
"""Blocks per window: the window is judged from block means (one second each for 60 s)."""
MIN_BLOCKS: int = 30
"""Blocks the window must hold before it is judged (half of it)."""
FALSE_ALARM: float = 1e-6
"""Significance level of each test, per sensor and evaluation."""
BISQUARE: float = 4.685
"""Tukey's bisquare constant (95 % efficiency on Gaussian data)."""
ROBUST_ITERATIONS: int = 12
ATTRIBUTED: float = 0.95
"""The disagreement names one sensor when an offset of that sensor alone explains this much of it."""
RIDGE: float = 1e-12
"""Relative ridge of the normal equations (directions the data do not determine stay at 0)."""
RANK_TOLERANCE: float = 1e-9
"""An eigenvalue of the information below this fraction of its trace is a direction not determined."""
RESTART_NS: int = int(RESTART_JUMP * NS_PER_S)
"""Stamps this far behind the newest: the source restarted (the synchroniser's rule)."""
DEFAULT_WINDOW: float = 60.0
"""Seconds of sets judged at once (default of the correction node's ``health_window``)."""
DEFAULT_WARN_FACTOR: float = 10.0
DEFAULT_ERROR_FACTOR: float = 30.0
DRIFTED_SENSORS: str = "drifted_sensors"
"""Key of the value listing the sensors the health names as drifted (comma-separated; empty: none)."""


@dataclass(frozen=True)
class DriftThresholds:
    """When a calibration counts as drifted: the window (ns) and the factors on the noise."""

    window_ns: int = int(DEFAULT_WINDOW * NS_PER_S)
    warn_factor: float = DEFAULT_WARN_FACTOR
    error_factor: float = DEFAULT_ERROR_FACTOR
    false_alarm: float = FALSE_ALARM


@dataclass(frozen=True)
class SensorDrift:
    """One sensor's figures over the window (T)."""

    name: str
    tmi_residual: float
    """RMS of the attitude-following part of ``|B|`` (beyond a constant and a trend)."""
    tmi_significant: bool
    disagreement: float
    """Norm of the window's mean residual of the field-and-gradient fit (NaN: the array has none)."""
    disagreement_significant: bool
    noise: float
    """The noise it is compared with: at calibration, or live when that is unknown."""
    noise_live: float
    """Noise per axis seen now (successive differences of ``|B|``)."""
    tmi_offset: float
    """Median ``|B|`` minus the calibrated intensity (NaN: intensity unknown)."""

    @property
    def ratio(self) -> float:
        """The larger significant figure over the noise (0 when neither is significant)."""
        figures = [f for f, sig in ((self.tmi_residual, self.tmi_significant),
                                    (self.disagreement, self.disagreement_significant)) if sig and np.isfinite(f)]
        return max(figures, default=0.0) / self.noise if self.noise > 0 else 0.0


@dataclass(frozen=True)
class DriftReport:
    """One judgement of the window: level, message, values for /diagnostics."""

    level: int
    message: str
    drifted: bool
    sensors: tuple[SensorDrift, ...] = ()
    window_s: float = 0.0
    sets: int = 0
    values: dict[str, str] = field(default_factory=dict)


def residual_projector(geometry: ArrayGeometry) -> Array | None:
    """(3S, 3S) projector onto what a centre field plus the gradient the positions determine
    cannot explain (stacked vectors ``[B_1, ..., B_S]``); None when nothing is left (one or two
    sensors)."""
    s = geometry.size
    if geometry.gradient_kind == "tensor":
        op = least_squares_operator(geometry)  # (8, 3S): pseudo-inverse of the design
        design = np.linalg.pinv(op)
    elif geometry.gradient_kind == "baseline":
        axis, _ = geometry.baseline
        along = (geometry.positions - geometry.centre) @ axis
        design = np.vstack([np.hstack([np.eye(3), a * np.eye(3)]) for a in along])
        op = np.linalg.pinv(design)
    else:
        return None
    p = np.eye(3 * s) - design @ op
    return p if np.linalg.matrix_rank(p, tol=1e-9) > 0 else None


def _wls(x: Array, y: Array, w: Array, ranks: bool = False) -> tuple[Array, Array, Array | None]:
    """Weighted least squares of every column of ``y`` (K, C) on ``x`` (K, p), weights ``w`` (K, C):
    coefficients (C, p), weighted residual sums of squares (C,) and, with ``ranks``, the ranks (C,).
    A direction the data do not determine (a regressor that never varied) gets a coefficient of
    about 0 (a ridge of 1e-12 of the information)."""
    a = np.einsum("kp,kc,kq->cpq", x, w, x)
    b = np.einsum("kp,kc,kc->cp", x, w, y)
    top = np.maximum(np.trace(a, axis1=1, axis2=2), 1e-300)
    eye = np.eye(x.shape[1])
    coef = np.linalg.solve(a + RIDGE * top[:, None, None] * eye, b[:, :, None])[:, :, 0]
    r = y - x @ coef.T
    rank = np.sum(np.linalg.eigvalsh(a) > RANK_TOLERANCE * top[:, None], axis=1) if ranks else None
    return coef, np.sum(w * r * r, axis=0), rank


def _weighted_median(y: Array, n: Array) -> Array:
    """Per column of ``y`` (K, C), the median with weights ``n`` (K,)."""
    order = np.argsort(y, axis=0)
    cum = np.cumsum(n[order], axis=0)
    k = np.argmax(cum >= 0.5 * cum[-1], axis=0)
    cols = np.arange(y.shape[1])
    return y[order[k, cols], cols]


def robust_weights(x: Array, y: Array, n: Array, iterations: int = ROBUST_ITERATIONS) -> Array:
    """Bisquare weights (K, C), 0..1, of the block means in each column of ``y`` (K, C), with ``n`` (K,)
    sets each, under the model ``x`` (K, p; its first column the constant): a residual is judged per
    set (times ``sqrt(n)``) against the median absolute deviation. The iterations start from the
    weighted median (the constant alone), so that a few blocks far off (a target passing) cannot
    steer the first fit."""
    root = np.sqrt(n)[:, None]
    r = (y - _weighted_median(y, n)) * root
    rho = np.ones_like(y)
    for k in range(iterations + 1):
        scale = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
        u = r / (BISQUARE * np.where(scale > 0, scale, np.inf))
        new = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if k and np.max(np.abs(new - rho)) < 1e-4:
            return new
        rho = new
        coef, _, _ = _wls(x, y, n[:, None] * rho)
        r = (y - x @ coef.T) * root
    return rho


@functools.lru_cache(maxsize=256)
def _f_critical(alpha: float, p: int, dof: int) -> float:
    from scipy import stats  # here: importing scipy.stats costs ~1 s, which `magcal correct` need not pay

    return float(stats.f.isf(alpha, p, dof))


@functools.lru_cache(maxsize=256)
def _t_critical(alpha: float, dof: int) -> float:
    from scipy import stats

    return float(stats.t.isf(alpha, dof))


def attitude_part_of(y: Array, directions: Array, tau: Array, n: Array, common: Array | None
                     ) -> tuple[Array, Array, Array, Array, Array]:
    """The fits of :func:`attitude_part` for columns ``y`` (K, C) nT: residual sums of squares and
    ranks with and without the directions, and the weights; ``common`` (K,): a regressor of the
    base model (the other sensors' mean intensity) or None."""
    base = np.column_stack([np.ones_like(tau), tau] + ([] if common is None else [common]))
    full = np.column_stack([base, directions - np.average(directions, axis=0, weights=n)])
    keep = robust_weights(full, y, n) > 0  # blocks beyond the bisquare's reach are out; the rest count fully
    w = n[:, None] * keep.astype(float)
    _, rss_full, rank_full = _wls(full, y, w, ranks=True)
    _, rss_base, rank_base = _wls(base, y, w, ranks=True)
    assert rank_full is not None and rank_base is not None
    return rss_full, rss_base, rank_full, rank_base, w


def attitude_part(tmi: Array, directions: Array, tau: Array, n: Array, alpha: float) -> tuple[Array, Array]:
    """The attitude-following part of block-mean intensities ``tmi`` (K, S) in T, per column: its RMS
    over the sets (T) beyond a constant and a trend in ``tau`` (K,), and whether an F test at
    ``alpha`` finds it significant. ``directions`` (K, 3): block-mean unit field directions."""
    y = (tmi - _weighted_median(tmi, n)) / NT  # nT about the median: well scaled
    if y.shape[1] >= 3:  # the field itself changing (a target, geology) is common to every sensor: each
        # sensor is judged beyond what the others' mean intensity follows (a drift is one sensor's own)
        others = (y.sum(axis=1, keepdims=True) - y) / (y.shape[1] - 1)
        cols = [attitude_part_of(y[:, [c]], directions, tau, n, others[:, c]) for c in range(y.shape[1])]
    else:
        cols = [attitude_part_of(y, directions, tau, n, None)]
    rss_full = np.concatenate([c[0] for c in cols])
    rss_base = np.concatenate([c[1] for c in cols])
    rank_full = np.concatenate([c[2] for c in cols])
    rank_base = np.concatenate([c[3] for c in cols])
    w = np.concatenate([c[4] for c in cols], axis=1)
    rho = (w > 0).astype(float)
    q = np.maximum(rss_base - rss_full, 0.0)
    figure = np.sqrt(q / np.maximum(np.sum(w, axis=0), 1e-300)) * NT
    significant = np.zeros(y.shape[1], bool)
    for c in range(y.shape[1]):
        p = int(rank_full[c] - rank_base[c])
        dof = int(np.floor(np.sum(rho[:, c]))) - int(rank_full[c])
        if p > 0 and dof >= 3 and rss_full[c] > 0:
            significant[c] = (q[c] / p) / (rss_full[c] / dof) > _f_critical(alpha, p, dof)
    return figure, significant


def mean_residual(residual: Array, n: Array, alpha: float) -> tuple[Array, Array]:
    """Robust window means (K, 3S) -> (S, 3) T of the block-mean residuals ``residual`` of S sensors,
    and per sensor whether a t test of any of its components is significant at ``alpha``
    (Bonferroni over the three). Components the geometry leaves at zero stay zero."""
    k, c = residual.shape
    spread = np.max(np.abs(residual), axis=0)
    live = spread > 0
    y = residual / np.where(live, spread, 1.0)
    ones = np.ones((k, 1))
    rho = (robust_weights(ones, y, n) > 0).astype(float)
    w = n[:, None] * rho
    used = np.sum(rho, axis=0)
    total = np.maximum(np.sum(w, axis=0), 1e-300)
    m = np.sum(w * y, axis=0) / total
    s2 = np.sum(w * (y - m) ** 2, axis=0) / np.maximum(used - 1.0, 1e-300)
    t = np.abs(m) * np.sqrt(total / np.where(s2 > 0, s2, np.inf))
    crit = np.array([_t_critical(alpha / 6.0, max(int(u) - 1, 1)) for u in used])
    significant = live & (used >= 3) & ((t > crit) | ((s2 <= 0) & (m != 0)))
    mean = np.where(live & (used >= 3), m * spread, 0.0)
    return mean.reshape(-1, 3), significant.reshape(-1, 3).any(axis=1)


def attribute(means: Array, projector: Array) -> tuple[int, float]:
    """The one sensor whose own offset best explains the window's mean residuals ``means`` (S, 3), and
    the fraction of their energy it explains (1: a change of that sensor alone)."""
    m = means.reshape(-1)
    energy = float(m @ m)
    if not energy > 0:
        return 0, 0.0
    best, explained = 0, -1.0
    for j in range(len(means)):
        basis = projector[:, 3 * j:3 * j + 3]  # what an offset of sensor j leaves in the residual
        coef, *_ = np.linalg.lstsq(basis, m, rcond=1e-9)
        fit = basis @ coef
        share = float(fit @ fit) / energy
        if share > explained:
            best, explained = j, share
    return best, explained


@dataclass
class _Blocks:
    """Closed one-block sums of the window, oldest first."""

    index: deque[int] = field(default_factory=deque)
    count: deque[int] = field(default_factory=deque)
    direction: deque[Array] = field(default_factory=deque)
    intensity: deque[Array] = field(default_factory=deque)
    residual: deque[Array] = field(default_factory=deque)
    diff2: deque[Array] = field(default_factory=deque)
    diffs: deque[int] = field(default_factory=deque)

    def append(self, *row: object) -> None:
        for column, value in zip((self.index, self.count, self.direction, self.intensity, self.residual, self.diff2,
                                  self.diffs), row):
            column.append(value)  # type: ignore[attr-defined]

    def drop_before(self, first: int) -> None:
        while self.index and self.index[0] < first:
            for column in (self.index, self.count, self.direction, self.intensity, self.residual, self.diff2,
                           self.diffs):
                column.popleft()

    def clear(self) -> None:
        self.drop_before(np.iinfo(np.int64).max)

    def __len__(self) -> int:
        return len(self.index)


class CalibrationHealth:
    """The health of one calibration: feed every corrected set with :meth:`add`, judge with :meth:`assess`.

    ``noise`` (S,) T per axis at calibration (NaN or 0 where unknown: the live noise is used);
    ``intensity`` T the calibration maps ``|B|`` to (None: unknown, ``tmi_offset`` not given).
    """

    def __init__(self, geometry: ArrayGeometry, noise: ArrayLike | None = None, intensity: float | None = None,
                 thresholds: DriftThresholds = DriftThresholds(), capacity: int = 4096) -> None:
        self.geometry = geometry
        s = geometry.size
        given = np.full(s, np.nan) if noise is None else np.asarray(noise, dtype=float).reshape(s)
        self.noise = np.where(np.isfinite(given) & (given > 0), given, np.nan)
        self.intensity = float(intensity) if intensity else None
        self.thresholds = thresholds
        self._block_ns = max(thresholds.window_ns // BLOCKS, 1)
        self._projector = residual_projector(geometry)
        self._buf = np.empty((capacity, s, 3))
        self._stamps = np.empty(capacity, dtype=np.int64)
        self._n = 0
        self._blocks = _Blocks()
        self._last_tmi: Array | None = None
        self._last_stamp = 0
        self._report: DriftReport | None = None
        self._judged: tuple[int, int] | None = None
        self.sets = 0
        """Sets taken since the last reset."""

    # -- hot path ---------------------------------------------------------------------
    def add(self, stamp_ns: int, vectors: ArrayLike) -> None:
        """Take one corrected set (S, 3) T stamped ``stamp_ns``."""
        n = self._n
        if n == len(self._stamps):
            self._digest()
            n = self._n
            if n == len(self._stamps):  # one block holds more than the buffer: grow it
                self._buf = np.concatenate([self._buf, np.empty_like(self._buf)])
                self._stamps = np.concatenate([self._stamps, np.empty_like(self._stamps)])
        self._buf[n] = vectors
        self._stamps[n] = stamp_ns
        self._n = n + 1

    # -- blocks -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every set (a new calibration is in force)."""
        self._n = 0
        self._blocks.clear()
        self._last_tmi = None
        self._last_stamp = 0
        self._report = None
        self._judged = None
        self.sets = 0

    def _digest(self) -> None:
        """Reduce the buffered sets of every block that is over (a later set has come) to block sums."""
        n = self._n
        if n == 0:
            return
        stamps = self._stamps[:n]
        # A stamp jumping back as far as the synchroniser's restart: the source restarted, the window starts again.
        newest = np.maximum.accumulate(np.concatenate([[self._last_stamp], stamps]))[:-1]
        back = np.flatnonzero(stamps < newest - RESTART_NS)
        if len(back):
            self._blocks.clear()
            self._last_tmi = None
            self._last_stamp = 0
            self.sets = 0
            self._keep(int(back[-1]), n)
            n, stamps = self._n, self._stamps[: self._n]
        if np.any(np.diff(stamps) < 0):  # sets completed out of order: put them in order
            order = np.argsort(stamps, kind="stable")
            self._buf[:n] = self._buf[order]
            self._stamps[:n] = stamps[order]
        closed = self._last_stamp // self._block_ns if self._last_stamp else None
        late = int(np.searchsorted(stamps // self._block_ns, closed, side="right")) if closed is not None else 0
        if late:  # sets of a block already closed: too late to count
            self._keep(late, n)
            n, stamps = self._n, self._stamps[: self._n]
            if n == 0:
                return
        blocks = stamps // self._block_ns
        done = int(np.searchsorted(blocks, blocks[-1], side="left"))
        if done == 0:
            return
        v = self._buf[:done]
        tmi = np.linalg.norm(v, axis=2)
        centre = v.mean(axis=1)
        direction = centre / np.maximum(np.linalg.norm(centre, axis=1, keepdims=True), 1e-300)
        residual = (v.reshape(done, -1) @ self._projector.T if self._projector is not None
                    else np.zeros((done, 0)))
        previous = self._last_tmi if self._last_tmi is not None else tmi[:1]
        gap_ok = np.diff(np.concatenate([[self._last_stamp or stamps[0]], stamps[:done]])) < self._block_ns
        gap_ok[0] &= self._last_tmi is not None  # the first set has no predecessor
        diff = np.diff(np.concatenate([previous, tmi]), axis=0)
        diff2 = np.where(gap_ok[:, None], diff * diff, 0.0)
        starts = np.flatnonzero(np.concatenate([[True], np.diff(blocks[:done]) != 0]))
        counts = np.diff(np.concatenate([starts, [done]]))
        sums = [np.add.reduceat(a, starts, axis=0) for a in (direction, tmi, residual, diff2)]
        diffs = np.add.reduceat(gap_ok.astype(np.int64), starts)
        for k, start in enumerate(starts):
            c = int(counts[k])
            self._blocks.append(int(blocks[start]), c, sums[0][k] / c, sums[1][k] / c, sums[2][k] / c, sums[3][k],
                                int(diffs[k]))
        self._last_tmi = tmi[-1:]
        self._last_stamp = int(stamps[done - 1])
        self.sets += done
        self._keep(done, n)
        self._blocks.drop_before(int(blocks[-1]) - BLOCKS)

    def _keep(self, first: int, n: int) -> None:
        """Keep buffered sets ``first..n`` (moved to the front)."""
        rest = n - first
        if rest and first:
            self._buf[:rest] = self._buf[first:n]
            self._stamps[:rest] = self._stamps[first:n]
        self._n = rest

    # -- judgement --------------------------------------------------------------------
    def assess(self) -> DriftReport:
        """Judge the window as it stands (see the module docstring)."""
        self._digest()
        b = self._blocks
        key = (b.index[-1], len(b)) if len(b) else None
        if self._report is not None and key is not None and key == self._judged:
            return self._report  # no block closed since: the same judgement
        self._judged = key
        names = self.geometry.names
        th = self.thresholds
        in_window = int(sum(b.count))
        base = {"window_s": "", "sets": str(in_window), "warn_factor": f"{th.warn_factor:g}",
                "error_factor": f"{th.error_factor:g}", "false_alarm": f"{th.false_alarm:g}"}
        span_s = (b.index[-1] - b.index[0] + 1) * self._block_ns / NS_PER_S if len(b) else 0.0
        base["window_s"] = f"{span_s:.0f}"
        base["newest_stamp"] = format_seconds(self._last_stamp) if self._last_stamp else ""
        if len(b) < MIN_BLOCKS:
            need = MIN_BLOCKS * self._block_ns / NS_PER_S
            return DriftReport(OK, f"collecting: {span_s:.0f} s of sets, {need:.0f} s needed to judge the calibration",
                               False, (), span_s, in_window, {**base, "drifted": "false", "figure": ""})
        index = np.asarray(b.index, dtype=float)
        n = np.asarray(b.count, dtype=float)
        directions = np.stack(b.direction)
        tmi = np.stack(b.intensity)
        residual = np.stack(b.residual)
        diff2 = np.stack(b.diff2)
        diffs = max(int(np.sum(b.diffs)), 1)
        live = np.sqrt(np.sum(diff2, axis=0) / diffs / 2.0)
        tau = (index - index.mean()) / BLOCKS
        spread = float(np.degrees(np.max(np.arccos(np.clip(
            directions @ (directions.mean(axis=0) / np.linalg.norm(directions.mean(axis=0))), -1.0, 1.0)))))
        tmi_figure, tmi_significant = attitude_part(tmi, directions, tau, n, th.false_alarm)
        if self._projector is not None:
            means, dis_significant = mean_residual(residual, n, th.false_alarm)
            dis = np.linalg.norm(means, axis=1)
        else:
            means, dis, dis_significant = None, np.full(len(names), np.nan), np.zeros(len(names), bool)
        sensors = []
        for i, name in enumerate(names):
            reference = self.noise[i] if np.isfinite(self.noise[i]) else live[i]
            offset = float(np.median(tmi[:, i]) - self.intensity) if self.intensity else float("nan")
            sensors.append(SensorDrift(name, float(tmi_figure[i]), bool(tmi_significant[i]), float(dis[i]),
                                       bool(dis_significant[i]), float(reference), float(live[i]), offset))
        sets = int(n.sum())
        report = self._judge(tuple(sensors), span_s, spread, sets, base, means)
        self._report = report
        return report

    def _judge(self, sensors: tuple[SensorDrift, ...], span_s: float, spread: float, sets: int,
               base: dict[str, str], means: Array | None) -> DriftReport:
        th = self.thresholds
        values = dict(base)
        values["attitude_change_deg"] = f"{spread:.1f}"
        for s in sensors:
            values[f"{s.name}.tmi_residual_nT"] = f"{s.tmi_residual / NT:.3g}"
            values[f"{s.name}.disagreement_nT"] = f"{s.disagreement / NT:.3g}" if np.isfinite(s.disagreement) else ""
            values[f"{s.name}.noise_nT"] = f"{s.noise / NT:.3g}"
            values[f"{s.name}.noise_live_nT"] = f"{s.noise_live / NT:.3g}"
            values[f"{s.name}.tmi_offset_nT"] = f"{s.tmi_offset / NT:.4g}" if np.isfinite(s.tmi_offset) else ""
            values[f"{s.name}.drift"] = f"{s.ratio:.3g}"
        figure = max(s.ratio for s in sensors)
        values["figure"] = f"{figure:.3g}"
        warn = th.warn_factor
        by_tmi = [s for s in sensors if s.tmi_significant and s.tmi_residual > 0 and s.tmi_residual >= warn * s.noise]
        by_dis = [s for s in sensors if s.disagreement_significant and s.disagreement > 0
                  and s.disagreement >= warn * s.noise]
        drifted = bool(by_tmi or by_dis)
        values["drifted"] = str(drifted).lower()
        against = "at calibration" if np.all(np.isfinite(self.noise)) else "live (noise at calibration unknown)"
        if not drifted:
            values[DRIFTED_SENSORS] = ""
            worst_tmi = max(sensors, key=lambda s: s.tmi_residual)
            text = (f"calibration fits: TMI residual {worst_tmi.tmi_residual / NT:.2g} nT at most against "
                    f"{worst_tmi.noise / NT:.2g} nT {against}")
            dis = [s for s in sensors if np.isfinite(s.disagreement)]
            if dis:
                text += f", sensors agree within {max(s.disagreement for s in dis) / NT:.2g} nT beyond the gradient"
            return DriftReport(OK, text + f" ({span_s:.0f} s, {sets} sets)", False, sensors, span_s, sets, values)
        named = {s.name for s in by_tmi}
        if by_dis and means is not None and self._projector is not None:
            culprit, explained = attribute(means, self._projector)
            named |= {sensors[culprit].name} if explained >= ATTRIBUTED else {s.name for s in by_dis}
        which = [s for s in sensors if s.name in named]
        values[DRIFTED_SENSORS] = ",".join(s.name for s in which)
        level = ERROR if figure >= th.error_factor else WARN
        parts = []
        several = len(which) > 1
        if by_tmi:
            t = max(by_tmi, key=lambda s: s.tmi_residual / s.noise)
            parts.append(f"TMI residual {t.tmi_residual / NT:.3g} nT" + (f" ({t.name})" if several else "")
                         + f" against {t.noise / NT:.2g} nT {against}")
        if by_dis:
            d = max(by_dis, key=lambda s: s.disagreement / s.noise)
            parts.append(f"sensors disagree by {d.disagreement / NT:.3g} nT beyond the gradient"
                         + (f" ({d.name})" if several else "") + f" against {d.noise / NT:.2g} nT noise")
        message = f"{', '.join(s.name for s in which)} calibration drifted: {'; '.join(parts)}: recalibrate"
        return DriftReport(level, message, True, sensors, span_s, sets, values)

    @property
    def latest(self) -> DriftReport | None:
        """The last report :meth:`assess` gave (None since the last reset)."""
        return self._report


def noise_and_intensity(metadata: dict[str, object], names: Sequence[str]) -> tuple[Array | None, float | None]:
    """The noise per sensor (S,) T and the intensity T a calibration's provenance records (None where absent)."""
    noise = metadata.get("noise")
    values = None
    if isinstance(noise, (list, tuple)) and len(noise) == len(names):
        values = np.asarray(noise, dtype=float)
    intensity = metadata.get("intensity")
    f = float(intensity) if isinstance(intensity, (int, float)) and not isinstance(intensity, bool) else None
    return values, (f if f and np.isfinite(f) and f > 0 else None)

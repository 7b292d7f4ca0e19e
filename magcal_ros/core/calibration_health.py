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
  RMS over the window's sets of the fitted attitude part (beyond constant and trend). It is
  taken twice: beyond what the other sensors' mean intensity follows (a target or geology
  changes the field for every sensor), and against the field's own intensity (``tmi_field``:
  constant and trend alone), which sees a change common to every sensor as well (their
  differences cannot); the second on the **steady** blocks only (:func:`steady_blocks`:
  where the spread of the sensors' vectors about their mean, the gradient the array sees,
  is within twice what noise gives of its quiet level: a target passing raises it, also
  when it fills half the window; a hull change common to every sensor does not).
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
the majority), and stays named: until, for a whole window of sets, the windows whose field
direction turned by :data:`RELEASE_DEG` find the calibration fits (straight and level, a change
common to every sensor is seen only while its step is in the window, after which nothing tells
it from the field; in a short window of steady turning its attitude part can pass for a trend).

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
from the centre (0.2 m on the default cross: 50 nT/m gives 10 nT).

**Who drifted** (``drifted_sensors``, never a sensor that did not move): the sensors whose TMI
figure is over the factor, when there are any. Else, when the disagreement is over it, the
sensors against each other (each one's mean reading minus the array's, ``o_i - mean(o)`` for
hard-iron changes ``o``) since the calibration last fitted: when more than half of them agree
(:func:`moved_sensors`), the others moved. The disagreement alone cannot tell (an offset of any
one sensor explains three of the four dimensions of a cross's residual: one sensor's change and
two others' look alike), nor can the sensors' differences tell two of four that moved from the
other two: then the message says "several sensors" (no one sensor explains it) or "one or more
sensors", and names none; "and other sensors" when those named do not explain the disagreement
alone. What differences never tell: a majority that moved alike looks like the others moving
the opposite way. Messages are at most :data:`MESSAGE_LIMIT` characters and end with the action.

Cost: :meth:`CalibrationHealth.add` copies one set into a buffer (about a microsecond);
:meth:`CalibrationHealth.assess` (once per status period) reduces the buffered sets to
one-second block sums with numpy and fits the window's blocks (a few milliseconds). Blocks
are cut by the sets' stamps, so the result does not depend on when ``assess`` runs nor on
how fast a recording is replayed.

Units: T in and out (nT only in the values for people); stamps int64 ns; platform frame.
"""

from __future__ import annotations

import functools
import itertools
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.stamps import format_seconds
from magcal_ros.core import calibration_bounds as bounds
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
"""Sensors explain the disagreement when offsets of theirs alone explain this much of its energy."""
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
"""Key of the value listing the sensors the health names as drifted (comma-separated; empty: none, or it
cannot tell which)."""
MESSAGE_LIMIT: int = 128
"""Longest status message: what ``ros2 topic echo`` shows of a string (its default truncation)."""


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
    tmi_field: float = 0.0
    """RMS of the attitude-following part of ``|B|`` against the field's own intensity (a constant and a
    trend), on the blocks where the field is steady: sees a change common to every sensor too."""
    tmi_field_significant: bool = False

    @property
    def tmi_figure(self) -> float:
        """The larger significant TMI figure (T; 0 when neither is significant)."""
        return max((f for f, sig in ((self.tmi_residual, self.tmi_significant),
                                     (self.tmi_field, self.tmi_field_significant)) if sig and np.isfinite(f)),
                   default=0.0)

    @property
    def ratio(self) -> float:
        """The largest significant figure over the noise (0 when none is significant)."""
        dis = self.disagreement if self.disagreement_significant and np.isfinite(self.disagreement) else 0.0
        return max(self.tmi_figure, dis) / self.noise if self.noise > 0 else 0.0

    def tmi_over(self, factor: float) -> bool:
        """Whether a significant TMI figure reaches ``factor`` times the noise."""
        return self.tmi_figure > 0 and self.tmi_figure >= factor * self.noise

    def disagreement_over(self, factor: float) -> bool:
        """Whether a significant disagreement reaches ``factor`` times the noise."""
        d = self.disagreement
        return bool(self.disagreement_significant and d > 0 and d >= factor * self.noise)


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


def attitude_part(tmi: Array, directions: Array, tau: Array, n: Array, alpha: float,
                  relative: bool = True) -> tuple[Array, Array]:
    """The attitude-following part of block-mean intensities ``tmi`` (K, S) in T, per column: its RMS
    over the sets (T) beyond a constant and a trend in ``tau`` (K,), and whether an F test at
    ``alpha`` finds it significant. ``directions`` (K, 3): block-mean unit field directions.
    ``relative`` (three sensors or more): each sensor beyond what the others' mean intensity follows;
    else against the field's intensity alone."""
    y = (tmi - _weighted_median(tmi, n)) / NT  # nT about the median: well scaled
    if relative and y.shape[1] >= 3:  # the field itself changing (a target, geology) is common to every sensor: each
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


STEADY_QUANTILE: float = 0.1
"""The window's quiet spread: this quantile of the blocks' spread over the array."""
STEADY_FLOOR: float = 2.0
"""A block is steady while its spread is within this many times what the sensors' noise alone gives a block
of its sets of the quiet spread."""


def steady_blocks(vectors: Array, n: Array, noise: Array) -> NDArray[np.bool_]:
    """(K,) the blocks where the field over the array is as steady as it gets in the window: the spread of
    the sensors' block-mean vectors ``vectors`` (K, S, 3) T about their mean (the gradient, and what the
    sensors disagree by) within :data:`STEADY_FLOOR` times the spread noise alone gives (``noise`` (S,) T per
    axis, ``n`` (K,) sets) of the window's quiet spread (:data:`STEADY_QUANTILE`). A target passing raises
    the gradient the array sees, also when it fills half the window; a hull change common to every sensor
    does not."""
    s = vectors.shape[1]
    if s < 2:
        return np.ones(len(vectors), bool)
    spread = np.linalg.norm((vectors - vectors.mean(axis=1, keepdims=True)).reshape(len(vectors), -1), axis=1)
    floor = np.sqrt(3.0 * (s - 1) * np.mean(noise**2) / n)
    return np.asarray(spread <= np.quantile(spread, STEADY_QUANTILE) + STEADY_FLOOR * floor)


def explained(means: Array, projector: Array, sensors: Sequence[int]) -> float:
    """The fraction of the energy of the window's mean residuals ``means`` (S, 3) that offsets of ``sensors``
    alone explain (1: a change of those sensors alone; 0 for no sensors or no residual)."""
    m = means.reshape(-1)
    energy = float(m @ m)
    if not energy > 0 or not len(sensors):
        return 0.0
    basis = np.hstack([projector[:, 3 * j:3 * j + 3] for j in sensors])  # what their offsets leave in the residual
    coef, *_ = np.linalg.lstsq(basis, m, rcond=1e-9)
    fit = basis @ coef
    return float(fit @ fit) / energy


RELEASE_DEG: float = 15.0
"""A drift named stays named until, for a whole window of sets, the judgements of windows whose field direction
(platform frame) turned by this much (deg, from the window's mean) find the calibration fits."""
MAX_GROUPED: int = 10
"""Largest array whose sensors :func:`moved_sensors` sorts into groups (2^S subsets)."""


def moved_sensors(jumps: Array, tolerance: Array) -> tuple[int, ...] | None:
    """Which sensors moved, from each one's jump ``jumps`` (S, 3) T: how far its reading against the array's
    mean moved since the calibration last fitted (``o_i - mean(o)`` for hard-iron changes ``o``). The sensors
    that did not move share one jump: when more than half the sensors agree pairwise within ``tolerance``
    (S,) T (the larger of the pair's), that group did not move and the others did. None when no majority
    agrees (half the sensors or more moved: which ones, their differences cannot tell, since sensors that
    moved alike agree as well as sensors that did not move). What they cannot tell either: a majority that
    moved alike looks like the rest moving the other way (a hull change is not alike at all but one sensor)."""
    s = len(jumps)
    if s > MAX_GROUPED:
        return None
    gap = np.linalg.norm(jumps[:, None, :] - jumps[None, :, :], axis=2)
    agree = gap < np.maximum(tolerance[:, None], tolerance[None, :])
    for size in range(s, s // 2, -1):
        groups = [g for g in itertools.combinations(range(s), size) if agree[np.ix_(g, g)].all()]
        if groups:
            return tuple(i for i in range(s) if i not in groups[0]) if len(groups) == 1 else None
    return None


@dataclass
class _Blocks:
    """Closed one-block sums of the window, oldest first."""

    index: deque[int] = field(default_factory=deque)
    count: deque[int] = field(default_factory=deque)
    direction: deque[Array] = field(default_factory=deque)
    intensity: deque[Array] = field(default_factory=deque)
    vectors: deque[Array] = field(default_factory=deque)
    """Block-mean vectors (S, 3) T."""
    diff2: deque[Array] = field(default_factory=deque)
    diffs: deque[int] = field(default_factory=deque)

    def append(self, *row: object) -> None:
        for column, value in zip((self.index, self.count, self.direction, self.intensity, self.vectors, self.diff2,
                                  self.diffs), row):
            column.append(value)  # type: ignore[attr-defined]

    def drop_before(self, first: int) -> None:
        while self.index and self.index[0] < first:
            for column in (self.index, self.count, self.direction, self.intensity, self.vectors, self.diff2,
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
        self._shift = 0
        """Added to every stamp since the sets' stamps last jumped back (a source restarted): the window
        and what it found go on, in a time that never runs backwards."""
        self._newest = 0
        """Newest stamp taken, shifted (ns)."""
        self.restarts = 0
        """Times the sets' stamps jumped back further than the synchroniser's restart (``stamp_restarts``)."""
        self._report: DriftReport | None = None
        self._judged: tuple[int, int] | None = None
        self._relative: Array | None = None
        """(S, 3) T: each sensor's reading against the array's mean when the calibration last fitted."""
        self._named: tuple[int, DriftReport] | None = None
        """(newest stamp, report) of the last judgement that named a drift, until it is cleared."""
        self._clear_since: int | None = None
        """Newest stamp of the first judgement since, with a turn, that found the calibration fits."""
        self.sets = 0
        """Sets taken since the last reset."""

    # -- hot path ---------------------------------------------------------------------
    def add(self, stamp_ns: int, vectors: ArrayLike) -> None:
        """Take one corrected set (S, 3) T stamped ``stamp_ns``. Stamps jumping back further than the
        synchroniser's restart (a source restarted) go on from the newest: the window is not lost."""
        stamp_ns += self._shift
        if stamp_ns < self._newest - RESTART_NS:
            self._shift += self._newest + 1 - stamp_ns
            stamp_ns = self._newest + 1
            self.restarts += 1
        if stamp_ns > self._newest:
            self._newest = stamp_ns
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

    def set_factors(self, warn: float, error: float) -> None:
        """New warning and error factors (the window and its sets stay): the next :meth:`assess` judges afresh."""
        self.thresholds = replace(self.thresholds, warn_factor=warn, error_factor=error)
        self._judged = None

    # -- blocks -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every set (a new calibration is in force)."""
        self._n = 0
        self._blocks.clear()
        self._last_tmi = None
        self._last_stamp = 0
        self._shift = self._newest = 0
        self._report = None
        self._judged = None
        self._relative = None
        self._named = self._clear_since = None
        self.sets = 0

    def _digest(self) -> None:
        """Reduce the buffered sets of every block that is over (a later set has come) to block sums."""
        n = self._n
        if n == 0:
            return
        stamps = self._stamps[:n]
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
        previous = self._last_tmi if self._last_tmi is not None else tmi[:1]
        gap_ok = np.diff(np.concatenate([[self._last_stamp or stamps[0]], stamps[:done]])) < self._block_ns
        gap_ok[0] &= self._last_tmi is not None  # the first set has no predecessor
        diff = np.diff(np.concatenate([previous, tmi]), axis=0)
        diff2 = np.where(gap_ok[:, None], diff * diff, 0.0)
        starts = np.flatnonzero(np.concatenate([[True], np.diff(blocks[:done]) != 0]))
        counts = np.diff(np.concatenate([starts, [done]]))
        sums = [np.add.reduceat(a, starts, axis=0) for a in (direction, tmi, v, diff2)]
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
        base["newest_stamp"] = format_seconds(self._last_stamp - self._shift) if self._last_stamp else ""
        base["stamp_restarts"] = str(self.restarts)
        if len(b) < MIN_BLOCKS:
            need = MIN_BLOCKS * self._block_ns / NS_PER_S
            return DriftReport(OK, f"collecting: {span_s:.0f} s of sets, {need:.0f} s needed to judge the calibration",
                               False, (), span_s, in_window, {**base, "drifted": "false", "figure": ""})
        index = np.asarray(b.index, dtype=float)
        n = np.asarray(b.count, dtype=float)
        directions = np.stack(b.direction)
        tmi = np.stack(b.intensity)
        vectors = np.stack(b.vectors)
        diff2 = np.stack(b.diff2)
        diffs = max(int(np.sum(b.diffs)), 1)
        live = np.sqrt(np.sum(diff2, axis=0) / diffs / 2.0)
        tau = (index - index.mean()) / BLOCKS
        spread = float(np.degrees(np.max(np.arccos(np.clip(
            directions @ (directions.mean(axis=0) / np.linalg.norm(directions.mean(axis=0))), -1.0, 1.0)))))
        tmi_figure, tmi_significant = attitude_part(tmi, directions, tau, n, th.false_alarm)
        noise = np.where(np.isfinite(self.noise), self.noise, live)
        steady = steady_blocks(vectors, n, noise)
        if steady.sum() >= MIN_BLOCKS // 2:
            field_figure, field_significant = attitude_part(tmi[steady], directions[steady], tau[steady], n[steady],
                                                            th.false_alarm, relative=False)
        else:
            field_figure, field_significant = np.zeros(len(names)), np.zeros(len(names), bool)
        means = relative = None
        dis, dis_significant = np.full(len(names), np.nan), np.zeros(len(names), bool)
        if self._projector is not None:
            means, dis_significant = mean_residual(vectors.reshape(len(n), -1) @ self._projector.T, n, th.false_alarm)
            dis = np.linalg.norm(means, axis=1)
            apart = vectors - vectors.mean(axis=1, keepdims=True)  # each sensor against the array's mean
            relative, _ = mean_residual(apart.reshape(len(n), -1), n, th.false_alarm)
        sensors = []
        for i, name in enumerate(names):
            reference = noise[i]
            offset = float(np.median(tmi[:, i]) - self.intensity) if self.intensity else float("nan")
            sensors.append(SensorDrift(name, float(tmi_figure[i]), bool(tmi_significant[i]), float(dis[i]),
                                       bool(dis_significant[i]), float(reference), float(live[i]), offset,
                                       float(field_figure[i]), bool(field_significant[i])))
        sets = int(n.sum())
        report = self._latch(self._judge(tuple(sensors), span_s, spread, sets, base, means, relative), spread)
        if not report.drifted and relative is not None and not any(
                s.disagreement >= th.warn_factor * s.noise for s in sensors):
            self._relative = relative  # the sensors against each other while the calibration fits
        self._report = report
        return report

    def _latch(self, report: DriftReport, spread: float) -> DriftReport:
        """``report``, or the drift named before while it is not cleared: a drift stays named until the
        judgements of windows whose field direction turned by :data:`RELEASE_DEG` (``spread``, deg) find the
        calibration fits for a whole window of sets (straight and level, a change common to every sensor looks
        like the field itself; in a short window of steady turning its attitude part can look like a trend)."""
        if report.drifted:
            self._named, self._clear_since = (self._last_stamp, report), None
            return report
        if self._named is None:
            return report
        if spread >= RELEASE_DEG:
            self._clear_since = self._clear_since or self._last_stamp
            if self._last_stamp - self._clear_since >= self.thresholds.window_ns:
                self._named = self._clear_since = None
                return report
        stamp, named = self._named
        ago = (self._last_stamp - stamp) / NS_PER_S
        who = named.values.get(DRIFTED_SENSORS, "").replace(",", ", ") or "one or more sensors"
        text = within([f"{who} calibration drifted {ago:.0f} s ago, not seen since (kept until a window of turns "
                       "shows it fits)", f"sensors' calibration drifted {ago:.0f} s ago"], ": recalibrate")
        values = {**report.values, "drifted": "true", DRIFTED_SENSORS: named.values.get(DRIFTED_SENSORS, ""),
                  "figure": named.values.get("figure", "")}
        return DriftReport(named.level, text, True, report.sensors, report.window_s, report.sets, values)

    def _values(self, sensors: tuple[SensorDrift, ...], spread: float, base: dict[str, str]) -> dict[str, str]:
        """The report's values: the window's, then each sensor's figures (nT) and ratio."""
        values = dict(base)
        values["attitude_change_deg"] = f"{spread:.1f}"
        for s in sensors:
            values[f"{s.name}.tmi_residual_nT"] = f"{s.tmi_residual / NT:.3g}"
            values[f"{s.name}.tmi_field_nT"] = f"{s.tmi_field / NT:.3g}"
            values[f"{s.name}.disagreement_nT"] = f"{s.disagreement / NT:.3g}" if np.isfinite(s.disagreement) else ""
            values[f"{s.name}.noise_nT"] = f"{s.noise / NT:.3g}"
            values[f"{s.name}.noise_live_nT"] = f"{s.noise_live / NT:.3g}"
            values[f"{s.name}.tmi_offset_nT"] = f"{s.tmi_offset / NT:.4g}" if np.isfinite(s.tmi_offset) else ""
            values[f"{s.name}.drift"] = f"{s.ratio:.3g}"
        return values

    def _judge(self, sensors: tuple[SensorDrift, ...], span_s: float, spread: float, sets: int,
               base: dict[str, str], means: Array | None, relative: Array | None) -> DriftReport:
        th = self.thresholds
        values = self._values(sensors, spread, base)
        figure = max(s.ratio for s in sensors)
        values["figure"] = f"{figure:.3g}"
        by_tmi = [i for i, s in enumerate(sensors) if s.tmi_over(th.warn_factor)]
        by_dis = [i for i, s in enumerate(sensors) if s.disagreement_over(th.warn_factor)]
        drifted = bool(by_tmi or by_dis)
        values["drifted"] = str(drifted).lower()
        live = "" if np.all(np.isfinite(self.noise)) else " seen live"
        if not drifted:
            values[DRIFTED_SENSORS] = ""
            worst = max(max(s.tmi_residual, s.tmi_field) for s in sensors)
            agree = [s.disagreement for s in sensors if np.isfinite(s.disagreement)]
            text = f"calibration fits: TMI residual {worst / NT:.2g} nT" + (
                f", sensors agree within {max(agree) / NT:.2g} nT" if agree else "")
            noise = max(s.noise for s in sensors)
            return DriftReport(OK, within([f"{text} at most (noise {noise / NT:.2g} nT{live}; {span_s:.0f} s, "
                                           f"{sets} sets)", text]), False, sensors, span_s, sets, values)
        named, who = self._who(sensors, by_tmi, by_dis, means, relative)
        values[DRIFTED_SENSORS] = ",".join(sensors[i].name for i in named)
        level = ERROR if figure >= th.error_factor else WARN
        return DriftReport(level, _drift_message(sensors, who, len(named), by_tmi, by_dis, live), True, sensors,
                           span_s, sets, values)

    def _who(self, sensors: tuple[SensorDrift, ...], by_tmi: list[int], by_dis: list[int], means: Array | None,
             relative: Array | None) -> tuple[list[int], str]:
        """(the sensors named as drifted, who drifted in words). The TMI names the sensors whose own ``|B|``
        follows the attitude; when it names none, the sensors against each other since the calibration last
        fitted (:func:`moved_sensors`); the disagreement says whether they explain it all. When none is named:
        "several sensors" when the sensors against each other, or the disagreement, show that no one sensor
        alone moved, else "one or more sensors"."""
        if not by_dis or means is None or self._projector is None:
            return list(by_tmi), ", ".join(sensors[i].name for i in by_tmi)
        moved: tuple[int, ...] | None = ()
        if relative is not None and self._relative is not None:
            tolerance = self.thresholds.warn_factor * np.array([s.noise for s in sensors])
            moved = moved_sensors(relative - self._relative, tolerance)  # None: no one sensor alone moved
        named = list(by_tmi) or list(moved or ())
        if named:
            agree = len(named) > 1 if moved is None else set(moved) <= set(named)  # with the sensors' jumps
            whole = agree and explained(means, self._projector, named) >= ATTRIBUTED
            return named, ", ".join(sensors[i].name for i in named) + ("" if whole else " and other sensors")
        one = moved is not None and max(explained(means, self._projector, [j])
                                        for j in range(len(sensors))) >= ATTRIBUTED
        return named, "one or more sensors" if one else "several sensors"

    @property
    def latest(self) -> DriftReport | None:
        """The last report :meth:`assess` gave (None since the last reset)."""
        return self._report


def within(candidates: Sequence[str], tail: str = "", limit: int = MESSAGE_LIMIT) -> str:
    """The first of ``candidates`` (most detailed first) that fits in ``limit`` characters with ``tail`` after
    it; else the last, cut short before ``tail``, which is always kept (the action)."""
    for text in candidates:
        if len(text) + len(tail) <= limit:
            return text + tail
    return candidates[-1][: max(limit - len(tail) - 3, 0)] + "..." + tail


def _drift_message(sensors: tuple[SensorDrift, ...], who: str, count: int, by_tmi: list[int], by_dis: list[int],
                   live: str) -> str:
    """``<who> calibration drifted: TMI residual 312 nT (mag2), disagreement 150 nT beyond the gradient (mag3),
    against 1 nT noise: recalibrate``, shortened to :data:`MESSAGE_LIMIT` characters with the action kept:
    without "beyond the gradient", without the sensors of the figures, then with the sensors counted."""
    figures = []  # (words, value, sensor)
    if by_tmi:
        t = sensors[max(by_tmi, key=lambda i: sensors[i].tmi_figure / sensors[i].noise)]
        figures.append(("TMI residual", t.tmi_figure, t.name))
    if by_dis:
        d = sensors[max(by_dis, key=lambda i: sensors[i].disagreement / sensors[i].noise)]
        figures.append(("disagreement", d.disagreement, d.name))
    noise = f"against {max(s.noise for s in sensors) / NT:.2g} nT noise{live}"
    several = count != 1

    def text(head: str, gradient: bool, named: bool) -> str:
        parts = [f"{words} {value / NT:.3g} nT" + (" beyond the gradient" if gradient and words == "disagreement"
                                                   else "") + (f" ({name})" if named and several else "")
                 for words, value, name in figures]
        return f"{head} calibration drifted: " + ", ".join(parts + [noise])

    counted = f"{count} sensors" + (" and others" if who.endswith(" and other sensors") else "") if count > 1 else who
    return within([text(who, True, True), text(who, False, True), text(who, False, False),
                   text(counted, False, False)], ": recalibrate")


def noise_and_intensity(metadata: dict[str, object], names: Sequence[str]) -> tuple[Array | None, float | None]:
    """The noise per sensor (S,) T and the intensity T a calibration's provenance records (None where absent;
    a noise NaN where unknown); :class:`InputError` for a value no calibration can have
    (:mod:`~magcal_ros.core.calibration_bounds`)."""
    noise = metadata.get("noise")
    values = None
    if isinstance(noise, (list, tuple)) and len(noise) == len(names):
        values = np.array([np.nan if v is None or (isinstance(v, float) and np.isnan(v))
                           else bounds.check_noise(f"{n} noise", v) for n, v in zip(names, noise)], dtype=float)
    intensity = metadata.get("intensity")
    f = None
    if isinstance(intensity, (int, float)) and not isinstance(intensity, bool) and not np.isnan(intensity):
        f = bounds.check_intensity("intensity", intensity) or None
    return values, f


UNKNOWN_INTERFERENCE = "unknown_interference"
"""Key of the calibration health's value naming the current channels that vary with an unknown interference."""


def with_unknown_currents(report: DriftReport, named: dict[str, str]) -> DriftReport:
    """``report`` with the current channels ``named`` (channel -> how it varied, in words;
    :class:`~magcal_ros.core.interference.CurrentWatch`) that vary while the calibration does not know their
    interference: at least a WARN, drifted (a recalibration learns their gains), the channels in the message
    and under :data:`UNKNOWN_INTERFERENCE`, how they varied under ``unknown_interference_detail``."""
    values = dict(report.values)
    values[UNKNOWN_INTERFERENCE] = ",".join(named)
    if not named:
        return replace(report, values=values)
    values["drifted"] = "true"
    values["unknown_interference_detail"] = "; ".join(named.values())
    message = f"{', '.join(named)} {'varies' if len(named) == 1 else 'vary'}, interference unknown: recalibrate"
    if report.drifted:
        values["sensor_health"] = report.message
    return replace(report, level=max(report.level, WARN), message=message, drifted=True, values=values)

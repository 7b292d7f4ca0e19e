"""One sensor's sample clock, estimated from its stamps: rate and phase, robust to jitter and outliers.

A sensor sampled at a fixed rate but stamped on receipt has jitter in its stamps, not in its
samples: sample ``n`` was taken at ``a + b n`` (ns; ``b`` the period as the stamping clock
counts it, so a sensor clock 50 ppm off is a period 50 ppm off) and stamped a little later
and unevenly. :class:`SampleClock` recovers ``n`` and ``a + b n`` from the stamps:

1. **Learning.** The first :data:`LEARN_INTERVALS` + 1 stamps of a run are held. A first
   period is the median of their intervals (a lost sample or a late stamp cannot move a
   median of 32; one pair of stamps never gives a period). Two readings of the sample
   indices are tried: consecutive stamps are consecutive samples unless their interval
   exceeds 1.75 such periods, and the grid (between 0.8 and 1.25 times that period) on
   which the stamps sit best (the strongest line of their periodogram); for each, a
   straight line is fitted to (index, stamp) and the indices re-read from it, twice. The
   grid reading wins only with less than half the residual scale of the consecutive one (a
   finer grid always fits a little better); stamps further from that line than the tracking's gate
   (below) are left out of it (late deliveries), and the held samples are released with their
   fitted instants.
2. **Tracking.** Each further stamp gets the index nearest to the line (``round((t - a) / b)``)
   and the fitted instant of that index. Stamps within :data:`GATE_SIGMAS` times the residual
   scale of the line update it (least squares with exponential forgetting over
   :data:`MEMORY` samples, so a slowly drifting rate is followed); a stamp outside keeps its
   index and fitted instant without moving the line (an outlier: a late delivery). The fitted
   instant at the newest sample is then uncertain by about ``2 sigma / sqrt(MEMORY)``: 0.03 ms
   for 0.5 ms of jitter.
3. **Ambiguity.** A stamp more than :data:`AMBIGUOUS` of a period from the nearest instant of
   the line, or one that claims the index of its predecessor, is held until the next stamp:
   its index is the one between its predecessor's and its successor's nearest to the line;
   if there is none, it is dropped (``None``). :data:`RELEARN_AFTER` such or outlying stamps
   in a row mean the clock changed (a phase step): learning starts again.
4. **Pauses.** A stamp more than ``pause_ns`` after the previous one starts learning again (the
   sensor may come back at another phase or rate); samples missing before it are not counted
   as lost. Otherwise each skipped index is a sample lost before the stamps were seen
   (:attr:`lost`, in :attr:`gaps` runs).

Stamps should be offered strictly increasing (the synchroniser's acceptance rule sees to it); one
that is not after the stamp before it while learning is dropped (``None``), as an ambiguous one is.
A sensor whose stamps do not fit a fixed rate (residual scale above :data:`IRREGULAR` of a
period) is not clocked: its samples keep their stamps (``instant == stamp``).
Plain Python floats throughout: this runs once per message in a live node.
"""

from __future__ import annotations

import math
from typing import Any

LEARN_INTERVALS: int = 32
"""Stamp intervals a run is learnt from (median period, then a fitted line)."""
MEMORY: int = 1000
"""Effective number of recent samples the line is fitted to (exponential forgetting)."""
GATE_SIGMAS: float = 4.0
"""A stamp further than this many residual standard deviations from the line does not move it."""
MIN_GATE: float = 0.01
"""The gate is at least this fraction of a period (stamps with no jitter at all)."""
AMBIGUOUS: float = 0.3
"""A stamp further than this fraction of a period from the line's nearest instant is ambiguous."""
RELEARN_AFTER: int = 8
"""Outlying or ambiguous stamps in a row that make the clock learn again."""
IRREGULAR: float = 0.3
"""A run whose residual scale exceeds this fraction of its period is not clocked (stamps kept)."""
PAUSE: int = 1_000_000_000
"""Default ``pause_ns``: a silence this long (ns) ends a run."""
FOLLOW_WAIT: int = 4 * LEARN_INTERVALS
"""Stamps a run that follows another clock's restart holds at most while that clock learns."""

Released = list[tuple[Any, "int | None"]]
"""Samples released by one call: (payload, fitted instant ns, or None when dropped)."""


def _median(values: list[float]) -> float:
    v = sorted(values)
    m = len(v) // 2
    return v[m] if len(v) % 2 else 0.5 * (v[m - 1] + v[m])


def fit_line(index: list[int], y: list[float]) -> tuple[float, float]:
    """Least-squares ``y = a + b index`` (plain floats); ``(a, b)``."""
    n = len(index)
    mi = sum(index) / n
    my = sum(y) / n
    sxx = sum((i - mi) * (i - mi) for i in index)
    sxy = sum((i - mi) * (v - my) for i, v in zip(index, y))
    b = sxy / sxx if sxx > 0 else 0.0
    return my - b * mi, b


def _coherence(y: list[float], period: float) -> tuple[float, float]:
    """How well the times ``y`` sit on a grid of ``period`` (0..1) and the grid's phase (ns)."""
    c = sn = 0.0
    w = 2.0 * math.pi / period
    for v in y:
        c += math.cos(w * v)
        sn += math.sin(w * v)
    return math.hypot(c, sn) / len(y), math.atan2(sn, c) / w


def _inliers(index: list[int], y: list[float], a: float, b: float, gate: float) -> list[int]:
    """Positions of the stamps ``y`` (ns) within ``gate`` (ns) of the line ``a + b index``."""
    return [j for j, (i, v) in enumerate(zip(index, y)) if abs(v - (a + b * i)) <= gate]


def _consecutive_indices(y: list[float], period: float) -> list[int]:
    """Sample indices of the times ``y``: consecutive, unless an interval exceeds 1.75 ``period``
    (samples lost in between)."""
    index = [0]
    for i in range(1, len(y)):
        step = (y[i] - y[i - 1]) / period
        index.append(index[-1] + (max(1, int(round(step))) if step > 1.75 else 1))
    return index


def _grid_indices(y: list[float], guess: float) -> list[int]:
    """Sample indices of the times ``y`` (ns, increasing): the period between 0.8 and 1.25 times
    ``guess`` on whose grid they sit best (the strongest line of their periodogram; lost samples and
    jitter up to a fifth of a period leave it in place), each time's index the nearest grid point."""
    span = y[-1] - y[0]
    cycles = max(span / guess, 1.0)
    step = 0.1 / cycles  # a tenth of a cycle of drift over the span between candidates
    best = (-1.0, guess, 0.0)
    ratio = 0.8
    while ratio <= 1.25:
        coh, phase = _coherence(y, guess * ratio)
        if coh > best[0]:
            best = (coh, guess * ratio, phase)
        ratio += step
    for k in range(-10, 11):  # refine
        p = best[1] * (1.0 + 0.1 * k * step)
        coh, phase = _coherence(y, p)
        if coh > best[0]:
            best = (coh, p, phase)
    _, period, phase = best
    index = [int(round((v - phase) / period)) for v in y]
    if any(index[i + 1] <= index[i] for i in range(len(index) - 1)):  # jitter beyond the grid: in order
        index = [0]
        for i in range(1, len(y)):
            index.append(index[-1] + max(1, int(round((y[i] - y[i - 1]) / period))))
    return [i - index[0] for i in index]


class SampleClock:
    """Streaming estimate of one sensor's sample clock (see the module docstring).

    :meth:`offer` takes each accepted stamp (ns, strictly increasing) with an opaque payload
    and returns the samples it releases, in order, each with its fitted instant (ns) or None
    when it was dropped as ambiguous; :meth:`finish` releases what is still held.
    """

    __slots__ = ("memory", "pause_ns", "_lam", "lost", "gaps", "dropped", "_learn", "_held", "ready", "regular",
                 "_t0", "_n0", "_n", "_a", "_b", "_s0", "_s1", "_s2", "_y1", "_y2", "_var", "_bad", "_last",
                 "_raw_count", "_hint", "_shift", "_follow", "_before")

    def __init__(self, memory: int = MEMORY, pause_ns: int = PAUSE) -> None:
        if memory < 2:
            raise ValueError("memory must be at least 2 samples")
        self.memory = memory
        self.pause_ns = int(pause_ns)
        self._lam = 1.0 - 1.0 / memory
        self.lost = 0
        """Samples lost before their stamps were seen (skipped sample indices)."""
        self.gaps = 0
        """Runs of lost samples."""
        self.dropped = 0
        """Samples dropped as ambiguous (no free index between their neighbours)."""
        self._last = -(2**62)
        self._learn: list[tuple[int, Any]] = []
        self._held: tuple[int, Any, float] | None = None
        self.ready = False
        """True while the line is in use (after learning)."""
        self.regular = True
        self._raw_count = 0
        self._hint: tuple[int, float, int] | None = None
        """After a restart: the old run's newest instant (ns), its period (ns) and its correction (ns)."""
        self._shift = 0
        """Added to every stamp of this run (a restart placed on the old grid)."""
        self._follow: SampleClock | None = None
        """The clock whose restart this run's stamps share (its correction is this run's too)."""
        self._before: tuple[int, float] | None = None
        """(stamp ns, period ns) of the sample before this clock's first, counted by a clock it took over from
        (:meth:`carry_counts`): the samples lost between them are this clock's to count."""
        self._reset_fit()

    def _reset_fit(self) -> None:
        self._t0 = 0
        self._n0 = 0
        self._n = 0
        self._a = self._b = 0.0
        self._s0 = self._s1 = self._s2 = self._y1 = self._y2 = 0.0
        self._var = 0.0
        self._bad = 0

    # -- state ------------------------------------------------------------------------
    @property
    def period_ns(self) -> float | None:
        """The sample period (ns) of the current run, None while learning or not clocked."""
        return self._b if self.ready else None

    @property
    def jitter_ns(self) -> float | None:
        """Standard deviation (ns) of the stamps about the line, None while learning."""
        return self._var ** 0.5 if self.ready else None

    @property
    def shift(self) -> int:
        """What this run adds to its stamps (ns): a restart's placement corrected onto the old grid."""
        return self._shift

    @property
    def pending(self) -> int:
        """Samples held (learning or ambiguous)."""
        return len(self._learn) + (self._held is not None)

    def instant(self, index: int) -> int:
        """Fitted instant (ns) of absolute sample ``index`` of the current run."""
        return self._t0 + int(round(self._a + self._b * (index - self._n0)))

    # -- input ------------------------------------------------------------------------
    def offer(self, stamp: int, payload: Any = None) -> Released:
        """One accepted stamp (ns); the samples this releases (see the class docstring)."""
        out: Released = []
        if self._before is not None:
            self._count_from_before(stamp)
        pause = stamp - self._last > self.pause_ns
        self._last = stamp
        stamp += self._shift
        if not self.ready:
            if pause and self._learn:
                out += self._flush_learning()
            return self._learning(stamp, payload, out)
        if pause:
            out += self._resolve_held(None)
            self._relearn()
            return self._learning(stamp, payload, out)
        y = float(stamp - self._t0)
        pos = (y - self._a) / self._b
        if self._held is not None:
            out += self._resolve_held(pos)
            if not self.ready:  # the held stamp made the clock learn again
                return self._learning(stamp, payload, out)
            y = float(stamp - self._t0)  # the origin may have moved
            pos = (y - self._a) / self._b
        k = int(round(pos))
        last = self._n - self._n0
        if k <= last or abs(pos - k) > AMBIGUOUS:
            self._held = (stamp, payload, pos)
            return out
        out.append((payload, self._assign(k, y)))
        return out

    def finish(self) -> Released:
        """Release everything held (end of the stream): learning samples fitted with what there is,
        an ambiguous sample at its nearest free index."""
        out = self._resolve_held(None) if self.ready else []
        if self._learn:
            out += self._flush_learning()
        return out

    def restart(self, follow: "SampleClock | None" = None) -> Released:
        """A new run starts (the sensor's driver restarted): release what is held, then learn afresh.

        The sensor itself is taken to have kept sampling: where the new run's line falls within a
        quarter period of the old one's grid (the old line carried on), it is moved onto it, so the
        new run's instants keep the old run's precision rather than that of the stamps that placed it.
        ``follow``: another sensor's clock whose stamps made the same jump (one stamping clock
        restarted for both). This run then takes that clock's correction once it is known, not one
        of its own: the sensors stay aligned exactly as their stamps say, whichever restarted first."""
        hint = (self.instant(self._n), self._b, self._shift) if self.ready and follow is None else None
        out = self.finish()
        self._relearn()
        self._hint = hint
        self._follow = follow
        self._shift = 0
        self._last = -(2**62)
        return out

    def carry_counts(self, old: "SampleClock", stamps: list[int]) -> None:
        """Go on from ``old``'s counts of lost samples (this clock takes over from it and is about to be
        offered ``stamps`` (ns) again, which ``old`` counted already: what it counted between them is left
        for this clock to count)."""
        lost, gaps = old.lost, old.gaps
        held = [t for t, _ in old._learn]
        period = old.period_ns or (_median([b - a for a, b in zip(held, held[1:])]) if len(held) > 1 else None)
        if old.period_ns:
            missing = self._missing(stamps, period)
            lost, gaps = lost - sum(missing), gaps - len(missing)
        elif len(held) > 3:  # still learning: what it held before ``stamps`` is not offered again, count it here
            missing = self._missing([t for t in held if not stamps or t < stamps[0]] + stamps[:1], period)
            lost, gaps = lost + sum(missing), gaps + len(missing)
        self.lost, self.gaps, self.dropped = max(lost, 0), max(gaps, 0), old.dropped
        if not stamps and old._last > -(2**62) and period:  # the next stamp offered follows old's last
            self._before = (old._last, period)

    def _count_from_before(self, stamp: int) -> None:
        """Count the samples lost between the sample before this clock's first (:attr:`_before`) and ``stamp``
        (ns, this clock's first), unless a pause lies between them (:meth:`_missing`)."""
        last, period = self._before  # type: ignore[misc]
        self._before = None
        missing = self._missing([last, stamp], period)
        self.lost += sum(missing)
        self.gaps += len(missing)

    def _missing(self, stamps: list[int], period: float) -> list[int]:
        """The samples lost in each gap of ``stamps`` (ns) at ``period`` (ns) that is not a pause (gaps with none left
        out)."""
        if period <= 0:
            return []
        missing = [round((b - a) / period) - 1 for a, b in zip(stamps, stamps[1:]) if b - a <= self.pause_ns]
        return [m for m in missing if m > 0]

    # -- learning ---------------------------------------------------------------------
    def _learning(self, stamp: int, payload: Any, out: Released) -> Released:
        if not self.regular:
            self._raw_count += 1
            out.append((payload, stamp))
            if self._raw_count >= 16 * LEARN_INTERVALS:  # try again now and then
                self.regular, self._raw_count = True, 0
            return out
        if self._learn and stamp <= self._learn[-1][0]:
            out.append((payload, None))  # not after the stamp before it: no index can be read from it
            return out
        self._learn.append((stamp, payload))
        if len(self._learn) > LEARN_INTERVALS:
            out += self._bootstrap()
        return out

    def _relearn(self) -> None:
        self.ready = False
        self._reset_fit()

    def _flush_learning(self) -> Released:
        """A run ended before its clock was learnt: release its samples (fitted when there are a few;
        no losses counted from so few stamps) and learn the next run afresh. A run that follows another
        clock still follows it (a pause, or a quiet spell of the receiver, does not part two sensors that one
        stamping clock serves: each snapped onto its own old grid, they would stand apart by up to half a
        period)."""
        if len(self._learn) > 3:
            out = self._bootstrap(final=True)
        else:
            out = [(p, s) for s, p in self._learn]
            self._learn = []
        self._relearn()
        return out

    def _bootstrap(self, final: bool = False) -> Released:
        """Fit the learning stamps (module docstring, 1.); release them with their fitted instants."""
        follow = self._follow
        if follow is not None and not final:
            if not follow.ready and len(self._learn) <= FOLLOW_WAIT:
                return []  # the clock this run follows is still learning its correction
            if len(self._learn) > LEARN_INTERVALS + 1:  # learnt from the same stamps as without the wait
                extra = self._learn[LEARN_INTERVALS + 1:]
                del self._learn[LEARN_INTERVALS + 1:]
                end = self._learn[-1][0]  # a raw stamp: a following run has no shift while it learns
                out = self._fit_learning(False)
                newest, self._last = self._last, end
                for stamp, payload in extra:
                    out += self.offer(stamp, payload)
                self._last = newest
                return out
        return self._fit_learning(final)

    def _fit_learning(self, final: bool) -> Released:
        """:meth:`_bootstrap` on the stamps held."""
        follow = self._follow
        stamps = [s for s, _ in self._learn]
        t0 = stamps[0]
        y = [float(s - t0) for s in stamps]
        period = _median([y[i + 1] - y[i] for i in range(len(y) - 1)])
        best: tuple[float, list[int], float, float] | None = None
        for index in (_consecutive_indices(y, period), _grid_indices(y, period)):
            a, b = fit_line(index, y)
            for _ in range(2):  # the indices re-read from the line
                again = [int(round((v - a) / b)) for v in y] if b > 0 else index
                if all(again[i + 1] > again[i] for i in range(len(again) - 1)):
                    index = [i - again[0] for i in again]
                a, b = fit_line(index, y)
            sigma = 1.4826 * _median([abs(v - (a + b * i)) for i, v in zip(index, y)])
            # A finer grid always fits a little better: the grid reading wins only by a factor of two
            # (the consecutive one misread a jitter as a loss, or the reverse).
            if b > 0 and (best is None or sigma < 0.5 * best[0]):
                best = (sigma, index, a, b)
        assert best is not None
        sigma, index, a, b = best
        clean = _inliers(index, y, a, b, max(GATE_SIGMAS * sigma, MIN_GATE * b))
        if 2 * len(clean) > len(index) and len(clean) < len(index):  # late deliveries bend no line
            a, b = fit_line([index[i] for i in clean], [y[i] for i in clean])
        else:
            clean = list(range(len(index)))
        released = self._learn
        self._learn = []
        if b <= 0 or sigma > IRREGULAR * b:
            if not final:
                self.regular = False  # not a fixed-rate sensor: stamps as they are
            return [(p, s) for s, p in released]
        if final:
            return [(p, t0 + int(round(a + b * i))) for (_, p), i in zip(released, index)]
        for i in range(1, len(index)):
            step = index[i] - index[i - 1]
            if step > 1:
                self.lost += step - 1
                self.gaps += 1
        self._t0, self._n0, self._n = t0, 0, index[-1]
        lam, last = self._lam, index[-1]
        s0 = s1 = s2 = y1 = y2 = 0.0
        for i, v in ((index[j], y[j]) for j in clean):
            w = lam ** (last - i)
            s0 += w
            s1 += w * i
            s2 += w * i * i
            y1 += w * v
            y2 += w * i * v
        if follow is not None and not final:  # the same correction as the clock this run follows
            self._follow = None
            shift = follow._shift
            self._shift = shift
            a += shift
            y1 += shift * s0
            y2 += shift * s1
        elif self._hint is not None:  # a restart: onto the old grid if it is within a quarter period
            shift = self._snap(t0 + a, b)
            if shift:  # every stamp of this run moves with it
                self._shift = shift
                a += shift
                y1 += shift * s0
                y2 += shift * s1
            self._hint = None
        self._s0, self._s1, self._s2, self._y1, self._y2 = s0, s1, s2, y1, y2
        self._a, self._b = a, b
        self._var = sigma * sigma
        self._bad = 0
        self.ready = True
        return [(p, t0 + int(round(a + b * i))) for (_, p), i in zip(released, index)]

    def _snap(self, first: float, period: float) -> int:
        """The correction (ns) of a run after a restart whose line starts at ``first`` (ns, as placed): the old
        run's correction carried on, plus the new line's distance from the old grid where that is within a
        quarter period (the placement's own error); the old correction alone where it is not."""
        assert self._hint is not None
        before, old, carried = self._hint
        off = before - (first + carried)
        off -= round(off / old) * old
        return int(round(carried + off)) if abs(off) <= 0.25 * period else carried

    # -- tracking ---------------------------------------------------------------------
    def _assign(self, k: int, y: float) -> int:
        """Sample index ``k`` (relative to the origin) for a stamp at ``y``; update the line; the instant."""
        a, b = self._a, self._b
        step = k - (self._n - self._n0)
        if step > 1:
            self.lost += step - 1
            self.gaps += 1
        self._n = self._n0 + k
        fitted = a + b * k
        instant = self._t0 + int(round(fitted))
        r = y - fitted
        var = self._var
        gate = max(GATE_SIGMAS * var ** 0.5, MIN_GATE * b)
        if r > gate or r < -gate:  # an outlier (a late delivery) moves neither the line nor its scale (clipped,
            self._bad += 1  # late ones, all on one side, pulled the line a gate's width each and widened the gate)
            self._tracked(k)
            return instant
        self._bad = 0
        lam = self._lam
        self._s0 = s0 = self._s0 * lam + 1.0
        self._s1 = s1 = self._s1 * lam + k
        self._s2 = s2 = self._s2 * lam + k * k
        self._y1 = y1 = self._y1 * lam + y
        self._y2 = y2 = self._y2 * lam + k * y
        det = s0 * s2 - s1 * s1
        if det > 0:
            b2 = (s0 * y2 - s1 * y1) / det
            if b2 > 0:
                self._b = b2
                self._a = (y1 - b2 * s1) / s0
        rate = 1.0 / s0  # a running mean at first, then the fit's memory
        self._var = var + rate * (r * r - var)
        self._tracked(k)
        return instant

    def _tracked(self, k: int) -> None:
        """After sample ``k`` (relative): learn again after :data:`RELEARN_AFTER` outliers in a row, else keep the
        origin near the newest samples."""
        if self._bad >= RELEARN_AFTER:
            self._relearn()
        elif k > self.memory:
            self._recentre(k)

    def _recentre(self, k: int) -> None:
        """Move the origin to index ``k`` (relative) so the sums stay well conditioned."""
        dn = float(k)
        shift = int(round(self._a + self._b * k))
        dt = float(shift)
        s0, s1, y1 = self._s0, self._s1, self._y1
        self._s1 = s1 - dn * s0
        self._s2 = self._s2 - 2.0 * dn * s1 + dn * dn * s0
        self._y1 = y1 - dt * s0
        self._y2 = self._y2 - dt * s1 - dn * y1 + dn * dt * s0
        self._a = self._a + self._b * dn - dt
        self._n0 += k
        self._t0 += shift

    def _resolve_held(self, next_pos: float | None) -> Released:
        """Place the held ambiguous sample between its predecessor and the next stamp (at ``next_pos``)."""
        held = self._held
        if held is None:
            return []
        self._held = None
        stamp, payload, pos = held
        last = self._n - self._n0
        upper = int(round(next_pos)) if next_pos is not None else None
        candidates = [c for c in (int(pos // 1), int(pos // 1) + 1) if c > last and (upper is None or c < upper)]
        if not candidates:
            self.dropped += 1
            self._bad += 1
            if self._bad >= RELEARN_AFTER:
                self._relearn()
            return [(payload, None)]
        k = min(candidates, key=lambda c: abs(c - pos))
        instant = self._assign(k, float(stamp - self._t0))  # it moves the line too: no one-sided truncation
        return [(payload, instant)]

"""Sets of sensors sampled at different instants: each sensor resampled at the reference's instants.

After per-sensor acceptance (:mod:`magcal_ros.core.sync_rules`) every accepted sample gets
its *instant*: the fitted instant of its index on the sensor's sample clock
(:mod:`magcal_ros.core.sample_clock`; its stamp where the stamps do not fit a fixed rate),
minus the sensor's time offset (a sample stamped ``t`` is the field at ``t - offset``).

For every sample instant ``T`` of the reference sensor (the first), in order, and each
other sensor: its samples on either side of ``T`` (``a <= T <= b``) and the one before ``a`` (``p``)
give its reading at ``T`` by the quadratic through the three (Lagrange), when ``p`` is of the same
segment and ``t_a - t_p`` is at least half of ``t_b - t_a`` and within the gap limit; otherwise by the line
``v_a + (v_b - v_a) (T - t_a) / (t_b - t_a)`` (a sample at exactly ``T`` as it is). The line cuts the chord
of a turning field (``h^2 |B''| / 8``: 0.7 nT at 10 Hz in a 6 deg/s turn), an error that follows the motion
and that a fit takes for calibration; the quadratic is a few hundred times closer and needs no later
sample. The set waits until every other sensor has a sample at or after
``T``: at most one sample of the slowest sensor, plus its transport delay. It is dropped
and counted when

- ``t_b - t_a`` exceeds the gap limit (``max_gap_ns``; 0: :data:`MAX_GAP_PERIODS` periods
  of that sensor, so two lost samples in a row are bridged, three are not), or ``t_b`` is
  the first sample after a restart of that sensor (where the new segment sits relative to
  the old one is only as good as its arrival): ``gap``;
- a sensor has no sample before ``T`` (it started later), or none after it arrives before the
  end (offline) or before the newest stamp and the latest arrival are both ``lag_ns`` past it
  (live; :meth:`~magcal_ros.core.sync_rules.AcceptanceRule.waited`): ``unmatched``.

Every member of a set carries the set's stamp: the reference sample's instant, written in
the reference's own stamp clock. Samples of the other sensors count as ``used`` when they
were a neighbour of a set instant or lie between two sets no more than the reference's gap
limit apart (a sensor faster than the reference), ``unmatched`` otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.acceptance import reading_fault_list
from magcal_ros.core.sync_rules import (
    DEFAULT_LAG,
    RESTART_JUMP,
    Accepted,
    AcceptanceRule,
    SetBatch,
    SyncedSet,
    SyncStats,
    Vector,
    empty_batch,
)
from magcal_ros.core.units import NS_PER_S

MAX_GAP_PERIODS: float = 3.5
"""Default gap limit in sample periods of the interpolated sensor."""
_NO_LIMIT = 2**62


def _weights(taus: list[int], t: int, a: int, b: int, prior: int) -> tuple[float, float, float]:
    """Weights of the samples ``prior``, ``a``, ``b`` at instant ``t`` (ns): the quadratic through the three
    (Lagrange); the line through ``a`` and ``b`` (``prior``'s weight 0) when ``prior`` < 0."""
    ta, tb = taus[a], taus[b]
    if prior < 0:
        f = (t - ta) / (tb - ta)
        return (0.0, 1.0 - f, f)
    tp = taus[prior]
    return ((t - ta) * (t - tb) / ((tp - ta) * (tp - tb)), (t - tp) * (t - tb) / ((ta - tp) * (ta - tb)),
            (t - tp) * (t - ta) / ((tb - tp) * (tb - ta)))


class InterpolatingSynchronizer(AcceptanceRule):
    """Sets at the reference sensor's sample instants (see the module docstring)."""

    mode = "interpolate"

    def __init__(
        self,
        sensors: int,
        max_gap_ns: int = 0,
        time_offsets_ns: Sequence[int] | None = None,
        lag_ns: int = int(DEFAULT_LAG * NS_PER_S),
        max_pending: int = 10_000,
        restart_ns: int = int(RESTART_JUMP * NS_PER_S),
        reject_zero: bool = True,
        stats: SyncStats | None = None,
        pause_ns: int | None = None,
    ) -> None:
        super().__init__(sensors, stats, restart_ns, reject_zero, clocked=True, pause_ns=pause_ns)
        self.max_gap_ns = int(max_gap_ns)
        self.offsets = [int(t) for t in (time_offsets_ns or [0] * sensors)]
        if len(self.offsets) != sensors:
            raise ValueError(f"{len(self.offsets)} time offsets for {sensors} sensors")
        self.lag_ns = int(lag_ns)
        self.max_pending = int(max_pending)
        self.tolerance_ns = 0
        self._tau: list[list[int]] = [[] for _ in range(sensors)]
        """Sample instants (common timeline, offsets applied), per sensor, increasing."""
        self._vals: list[list[Vector]] = [[] for _ in range(sensors)]
        self._out: list[int] = []
        """Reference samples: the set stamp in the reference's own clock."""
        self._used: list[list[bool]] = [[] for _ in range(sensors)]
        self._head = [0] * sensors
        self._prev: int | None = None
        """Instant of the last set formed."""
        self._fence: list[set[int]] = [set() for _ in range(sensors)]
        """Per sensor, the instants of the first samples after its restarts still queued: no set bridges them."""
        self._fresh = [False] * sensors

    # -- state ------------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Messages held, learning or queued (samples kept as a neighbour included)."""
        queued = sum(len(t) - h for t, h in zip(self._tau, self._head))
        clocks = sum(s.clock.pending for s in self.streams if s.clock is not None)
        return queued + clocks + self.held

    @property
    def effective_tolerance_ns(self) -> int:
        """No exact window: 0."""
        return 0

    def gap_limit(self, index: int) -> int:
        """The largest span (ns) between two samples of sensor ``index`` a set may bridge."""
        if self.max_gap_ns:
            return self.max_gap_ns
        period = self.streams[index].best_period()
        return _NO_LIMIT if period is None else int(MAX_GAP_PERIODS * period)

    def reset(self) -> None:
        """Drop everything queued or held (counted) and forget each sensor's history."""
        st = self.stats
        for k in range(self.size):
            h = self._head[k]
            if k == 0:
                st.unmatched += len(self._tau[0]) - h
            else:
                used = sum(self._used[k][h:])
                st.used += used
                st.unmatched += len(self._tau[k]) - h - used
            clock = self.streams[k].clock
            if clock is not None:
                st.unmatched += clock.pending
        self._tau = [[] for _ in range(self.size)]
        self._vals = [[] for _ in range(self.size)]
        self._used = [[] for _ in range(self.size)]
        self._out = []
        self._head = [0] * self.size
        self._prev = None
        self._fence = [set() for _ in range(self.size)]
        self._fresh = [False] * self.size
        self.forget()

    # -- input ------------------------------------------------------------------------
    def add_all(self, index: int, stamp_ns: int, x: float, y: float, z: float,
                receipt_ns: int | None = None) -> list[SyncedSet]:
        """Offer one message of sensor ``index``; the sets it completes, in order."""
        accepted = self.accept(index, stamp_ns, (x, y, z), self.fault(x, y, z), receipt_ns)
        if not accepted:
            return []
        self._clock_in(index, accepted)
        return self._form(False)

    def release_quiet_sets(self, now_ns: int) -> list[SyncedSet]:
        """Live, on the receiver's clock (ns): the sets that the messages held for sensors quiet for
        :data:`~magcal_ros.core.sync_rules.HOLD_NS` complete (:meth:`release_quiet_holds`)."""
        released = self.release_quiet_holds(now_ns)
        for index, accepted in released:
            self._clock_in(index, accepted)
        finished = self._finish_quiet_clocks(now_ns)
        return self._form(False) if released or finished else []

    def _finish_quiet_clocks(self, now_ns: int) -> bool:
        """Live: a sensor quiet for :data:`~magcal_ros.core.sync_rules.HOLD_NS` whose sample clock still holds
        samples (learning its period: a stream, a restart or a revision that ended within its first
        :data:`~magcal_ros.core.sample_clock.LEARN_INTERVALS` samples) has them fitted with what there is, as
        at the end of a recording; otherwise they waited for samples that do not come. Whether any was."""
        finished = False
        for k, s in enumerate(self.streams):
            clock = s.clock
            if clock is None or not clock.pending or not s.quiet(now_ns):
                continue
            for payload, instant in clock.finish():
                self._push(k, payload, instant)
            finished = True
        return finished

    def add(self, index: int, stamp_ns: int, x: float, y: float, z: float,
            receipt_ns: int | None = None) -> SyncedSet | None:
        """Offer one message; the last set it completes, if any (see :meth:`add_all`)."""
        formed = self.add_all(index, stamp_ns, x, y, z, receipt_ns)
        return formed[-1] if formed else None

    def add_batch(self, index: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64],
                  receipts: NDArray[np.int64] | None = None) -> None:
        """Queue messages of sensor ``index`` in its order; :meth:`pop` releases the sets."""
        s = np.asarray(stamps, dtype=np.int64).reshape(-1).tolist()
        v = np.asarray(vectors, dtype=float).reshape(-1, 3)
        faults = reading_fault_list(v, self.max_reading)
        rows = v.tolist()
        r = [None] * len(s) if receipts is None else np.asarray(receipts, dtype=np.int64).reshape(-1).tolist()
        accept, clock_in = self.accept, self._clock_in
        for i, t in enumerate(s):
            row = rows[i]
            accepted = accept(index, t, (row[0], row[1], row[2]), faults[i], r[i])
            if accepted:
                clock_in(index, accepted)

    def _offered(self, index: int, accepted: Accepted, kept: Accepted) -> None:
        self._clock_in(index, accepted)

    def pop(self, final: bool = False) -> SetBatch:
        """Release the sets decided so far (everything, dropping what is left, when ``final``)."""
        if final:
            for k in range(self.size):
                self._clock_in(k, self.release_held(k))
                clock = self.streams[k].clock
                if clock is not None:
                    for payload, instant in clock.finish():
                        self._push(k, payload, instant)
        sets = self._form(final)
        if final:
            self._discard_all()
        if not sets:
            return empty_batch(self.size)
        return SetBatch(np.array([s.stamps for s in sets], dtype=np.int64),
                        np.array([s.values for s in sets], dtype=float))

    def _clock_in(self, index: int, accepted: list[tuple[int, int, Any, int, bool]]) -> None:
        clock = self.streams[index].clock
        assert clock is not None
        push = self._push
        for stamp, common, value, _, restart in accepted:
            if restart:
                for payload, instant in self.restart_clock(index):
                    push(index, payload, instant)
                self._fresh[index] = True
            for payload, instant in clock.offer(common, (stamp, common, value)):
                push(index, payload, instant)

    def _push(self, index: int, payload: tuple[int, int, Vector | None], instant: int | None) -> None:
        """Queue one clocked sample (dropped when ambiguous or not after the previous instant)."""
        stamp, common, value = payload
        if value is None:
            return  # a non-finite reading: counted already, its stamp only kept the clock going
        if instant is None:
            self.stats.glitch += 1
            return
        tau = instant - self.offsets[index]
        q = self._tau[index]
        if q and tau <= q[-1]:
            self.stats.glitch += 1
            return
        q.append(tau)
        self._vals[index].append(value)
        if self._fresh[index]:  # the first sample of a new segment (a restart)
            self._fence[index].add(tau)
            self._fresh[index] = False
        if index == 0:  # in the reference's own clock, whatever placed it on the common time line
            clock = self.streams[0].clock
            self._out.append(stamp + (instant - common - clock.shift) - self.offsets[0])  # type: ignore[union-attr]
        else:
            self._used[index].append(False)

    # -- the rule ---------------------------------------------------------------------
    def _form(self, final: bool) -> list[SyncedSet]:
        """Sets at the queued reference instants whose neighbours are known."""
        out: list[SyncedSet] = []
        tau0 = self._tau[0]
        head = self._head
        taus_all, vals_all, used_all, fences = self._tau, self._vals, self._used, self._fence
        st = self.stats
        others = range(1, self.size)
        while head[0] < len(tau0):
            i0 = head[0]
            t = tau0[i0]
            verdict = 0  # 0 a set, 1 unmatched, 2 gap
            picks: list[tuple[int, int, int]] = []  # (a, b, the sample before a or -1)
            for k in others:
                taus = taus_all[k]
                h, n = head[k], len(taus)
                j = h
                while j < n and taus[j] < t:
                    j += 1
                if j == n:
                    if final or self._give_up(t, k):
                        verdict = 1
                        break
                    self._compact()
                    return out
                if taus[j] == t:
                    picks.append((j, j, -1))
                    continue
                if j == h:
                    verdict = 1  # this sensor's samples start after t
                    break
                span = taus[j] - taus[j - 1]
                limit = self.gap_limit(k)
                if span > limit or taus[j] in fences[k]:  # too far apart, or across a restart
                    verdict = 2
                    break
                # the sample before a as well when it is of the same segment and near: a quadratic through three
                prior = j - 2 if j - 2 >= h and span <= 2 * (taus[j - 1] - taus[j - 2]) <= 2 * limit \
                    and taus[j - 1] not in fences[k] else -1
                picks.append((j - 1, j, prior))
            head[0] = i0 + 1
            if verdict:
                if verdict == 1:
                    st.unmatched += 1
                else:
                    st.gap += 1
                self._discard_before(t, formed=False)
                continue
            values: list[Vector] = [self._vals[0][i0]]
            for k, (a, b, prior) in zip(others, picks):
                vals, used = vals_all[k], used_all[k]
                if a == b:
                    values.append(vals[a])
                    used[a] = True
                    continue
                wp, wa, wb = _weights(taus_all[k], t, a, b, prior)
                va, vb = vals[a], vals[b]
                vp = vals[prior] if prior >= 0 else va  # weight 0 without it
                values.append((wp * vp[0] + wa * va[0] + wb * vb[0], wp * vp[1] + wa * va[1] + wb * vb[1],
                               wp * vp[2] + wa * va[2] + wb * vb[2]))
                used[a] = used[b] = True
                if prior >= 0:
                    used[prior] = True
            stamp = self._out[i0]
            out.append(SyncedSet((stamp,) * self.size, tuple(values)))
            st.sets += 1
            st.used += 1
            self._discard_before(t, formed=True)
            self._prev = t
        if not final:
            self._give_up_unreferenced()
        self._compact()
        return out

    def _give_up_unreferenced(self) -> None:
        """Live bound while the reference sensor has no instant queued (silent): another sensor's samples that
        waited :attr:`lag_ns` for one are given up (``unmatched``), each sensor's latest such sample kept as the
        neighbour a later instant may still need."""
        st = self.stats
        for k in range(1, self.size):
            taus, used = self._tau[k], self._used[k]
            h, n = self._head[k], len(taus)
            j = h
            while j + 1 < n and self.waited(taus[j + 1], (0,)):
                j += 1
            if j > h:
                kept = sum(used[h:j])
                st.used += kept
                st.unmatched += j - h - kept
                self._head[k] = j

    def _give_up(self, t: int, silent: int) -> bool:
        """Live bounds: a set instant that waited too long for sensor ``silent`` (:meth:`waited`), or a
        queue too long."""
        if self.waited(t, (silent,)):
            return True
        return any(len(q) - h > self.max_pending for q, h in zip(self._tau, self._head))

    def _discard_before(self, t: int, formed: bool) -> None:
        """Forget the other sensors' samples no later instant can need (before the last one at or
        before ``t``), counting each as used or unmatched."""
        st = self.stats
        prev = self._prev
        between = formed and prev is not None and t - prev <= self.gap_limit(0)
        for k in range(1, self.size):
            taus, used = self._tau[k], self._used[k]
            h, n = self._head[k], len(taus)
            j = h
            while j + 1 < n and taus[j + 1] <= t:
                j += 1
            j = max(h, j - 1)  # the sample before it too: the next set's quadratic may need it
            for i in range(h, j):
                if used[i] or (between and taus[i] >= prev):  # type: ignore[operator]
                    st.used += 1
                else:
                    st.unmatched += 1
            self._head[k] = j

    def _discard_all(self) -> None:
        """End of the stream: every sample left is used or unmatched."""
        st = self.stats
        st.unmatched += len(self._tau[0]) - self._head[0]
        self._head[0] = len(self._tau[0])
        for k in range(1, self.size):
            used = self._used[k][self._head[k]:]
            st.used += sum(used)
            st.unmatched += len(used) - sum(used)
            self._head[k] = len(self._tau[k])
        self._compact()

    def _compact(self) -> None:
        for k in range(self.size):
            h = self._head[k]
            if h and (h >= 4096 or h == len(self._tau[k])):
                fence = self._fence[k]
                if fence:  # restarts no set can reach any more
                    first = self._tau[k][h] if h < len(self._tau[k]) else None
                    self._fence[k] = {f for f in fence if first is None or f >= first}
                del self._tau[k][:h]
                del self._vals[k][:h]
                if k == 0:
                    del self._out[:h]
                else:
                    del self._used[k][:h]
                self._head[k] = 0

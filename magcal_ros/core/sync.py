"""The one rule that groups per-sensor messages into sets, for bags, CSV and live nodes.

Input: for each sensor, its messages in the order that sensor produced them (a topic's
order in a bag, or on the wire), each a header stamp (integer ns) and a vector (T).
Every message first goes through per-sensor acceptance
(:mod:`magcal_ros.core.sync_rules`: zero, repeated and out-of-order stamps, glitches,
restarts, non-finite readings). Sets are then formed in one of two modes:

- **exact** (sensors sampled together and stamped alike): accepted messages wait in one
  queue per sensor. Repeatedly, with the head (oldest) message of every queue in view: the
  earliest head is the *anchor* ``t0``; if every head lies within ``[t0, t0 + w]`` the
  heads form a set, otherwise the anchor alone is dropped (``unmatched``). The window
  ``w`` is ``tolerance_ns``, capped at half of each member sensor's sample period (the
  median of its last 8 stamp intervals), so that a window can never hold two samples of
  one sensor. A set's stamps are its members' own header stamps.
- **interpolate** (sensors sampled at different instants, or stamped on receipt): each
  sensor's stamps give its sample clock (:mod:`magcal_ros.core.sample_clock`) and so each
  sample's instant; a set is formed at every sample instant of the reference sensor (the
  first), the other sensors interpolated at it (the quadratic through their samples on either side and
  the one before, see below), never across more than ``max_gap`` (such sets are dropped and counted, ``gap``);
  see :mod:`magcal_ros.core.sync_interpolate`. Every member of a set carries the set's
  instant.

:class:`StreamSynchronizer` is what readers and nodes use: mode ``auto`` (default) decides
from the first :data:`DECIDE_AFTER` stamps of every sensor (:func:`choose_mode`), ``exact``
or ``interpolate`` force one; per-sensor time offsets (``time_offsets_ns``: a sensor's
sample stamped ``t`` is the field at ``t - offset``) need interpolation.

The rule depends only on each sensor's own message sequence, never on how the sensors'
messages interleave, so a recording gives the same sets on the ship (streaming,
:meth:`StreamSynchronizer.add`, one message at a time, a set released the moment its last
member arrives) and on shore (batches, :meth:`StreamSynchronizer.add_batch` and
:meth:`StreamSynchronizer.pop`). Two bounds keep memory finite in a live node and are the
only departures from that: a head that waited ``lag_ns`` (the newest stamp that far past it and,
where arrivals are known, the latest arrival that far past the silent sensor's last one), or
beyond ``max_pending`` queued messages of one sensor, is given up (``unmatched``) while
another sensor is silent; and where a sensor restarts alone, its new stamps are placed by
their arrival (bag time offline, the node's clock live).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from magcal_ros.core import acceptance
from magcal_ros.core.acceptance import reading_fault_list
from magcal_ros.core.sync_interpolate import MAX_GAP_PERIODS, InterpolatingSynchronizer
from magcal_ros.core.sample_clock import SampleClock
from magcal_ros.core.sync_revision import ExactMonitor
from magcal_ros.core.sync_rules import (
    DEFAULT_LAG,
    DEFAULT_SYNC_TOLERANCE,
    DROP_FIELDS,
    LEAD_WINDOW,
    MAX_TIME_OFFSET,
    NEVER,
    NO_CAP,
    PERIOD_WINDOW,
    RESTART_JUMP,
    SUSPECT_PERIODS,
    TAIL,
    TIMED_MIN,
    Accepted,
    BACKLOG_INTERVAL,
    AcceptanceRule,
    Batch,
    SetBatch,
    SyncedSet,
    SyncStats,
    Vector,
    arrival_order,
    empty_batch,
    median_int,
    tolerance_ns,
)
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

__all__ = [
    "DEFAULT_LAG", "DEFAULT_MAX_GAP", "DEFAULT_SYNC_MODE", "DEFAULT_SYNC_TOLERANCE", "DROP_FIELDS", "MAX_GAP_PERIODS",
    "PERIOD_WINDOW", "RESTART_JUMP", "SYNC_MODES", "SetBatch", "SetSynchronizer", "StreamSynchronizer", "SyncStats",
    "SyncedSet", "choose_mode", "max_gap_ns", "stream_synchronizer", "synchronise_streams", "time_offset_ns",
    "tolerance_ns",
]

SyncMode = Literal["auto", "exact", "interpolate"]
SYNC_MODES: tuple[str, ...] = ("auto", "exact", "interpolate")
DEFAULT_SYNC_MODE: str = "auto"
DEFAULT_MAX_GAP: float = 0.0
"""Default ``max_gap`` (s): 0 means :data:`MAX_GAP_PERIODS` sample periods of the interpolated sensor."""
RUN_BLOCK: int = 64
"""Queued messages per sensor from which the exact rule looks for a run of matching sets with numpy."""
DECIDE_AFTER: int = 32
"""Stamps of every sensor mode ``auto`` looks at before choosing ..."""
DECIDE_EARLY: tuple[int, int] = (8, NS_PER_S)
"""... or at least 8 stamps of every sensor spanning 1 s (slow sensors)."""
MAX_INTERPOLATION_STEP: float = 0.2
"""Mode ``auto`` does not interpolate for a systematic stamp offset when the reference sensor's field
turns by more than this (rad, median) from one reading to the next: the samples do not resolve the motion."""
EXACT_FRACTION: float = 0.9
"""Mode ``auto`` matches exactly when the exact window holds at least this fraction of the sets
(:func:`choose_mode`)."""


def max_gap_ns(seconds: Any) -> int:
    """``max_gap`` in seconds as integer ns (``ValueError`` unless 0 <= g < 60 s; 0 = automatic)."""
    try:
        g = float(seconds)
    except (TypeError, ValueError):
        raise ValueError(f"max_gap must be a number of seconds, got {seconds!r}") from None
    if not (0.0 <= g < 60.0) or not math.isfinite(g):
        raise ValueError(f"max_gap must be between 0 (automatic) and 60 s, got {seconds!r}")
    return int(round(g * NS_PER_S))


def time_offset_ns(seconds: Any, name: str = "time_offset") -> int:
    """A sensor's time offset in seconds as integer ns (``ValueError`` naming ``name`` unless finite
    and within +-:data:`MAX_TIME_OFFSET`)."""
    try:
        t = float(seconds)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number of seconds, got {seconds!r}") from None
    if not math.isfinite(t) or abs(t) > MAX_TIME_OFFSET:
        raise ValueError(f"{name} must be a finite number of seconds within +-{MAX_TIME_OFFSET:g} s, got {seconds!r}")
    return int(round(t * NS_PER_S))


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`SYNC_MODES` (``ValueError`` naming them otherwise)."""
    if mode not in SYNC_MODES:
        raise ValueError(f"sync mode must be one of {', '.join(SYNC_MODES)}, got {mode!r}")
    return mode


class SetSynchronizer(AcceptanceRule):
    """Exact matching of ``sensors`` message streams into complete sets (see the module docstring).

    ``clocked``: keep each sensor's sample clock in the streaming path (its period and the
    samples lost before the node, for health reports).
    """

    mode = "exact"

    def __init__(
        self,
        sensors: int,
        tolerance_ns: int = int(DEFAULT_SYNC_TOLERANCE * NS_PER_S),
        lag_ns: int = int(DEFAULT_LAG * NS_PER_S),
        max_pending: int = 10_000,
        restart_ns: int = int(RESTART_JUMP * NS_PER_S),
        reject_zero: bool = True,
        stats: SyncStats | None = None,
        clocked: bool = True,
        pause_ns: int | None = None,
        max_reading: float = math.inf,
    ) -> None:
        """``reject_zero``: drop stamps 0 and negative as unstamped or faulty (header stamps; a CSV's
        relative clock may start at 0). ``max_reading``: largest reading magnitude accepted (T)."""
        super().__init__(sensors, stats, restart_ns, reject_zero, clocked, pause_ns)
        self.max_reading = float(max_reading)
        if tolerance_ns < 0:
            raise ValueError("tolerance must be >= 0")
        self.tolerance_ns = int(tolerance_ns)
        self.lag_ns = int(lag_ns)
        self.max_pending = int(max_pending)
        self._stamps: list[list[int]] = [[] for _ in range(sensors)]
        """Common-timeline stamps of the queued messages (the rule compares these)."""
        self._raws: list[list[int]] = [[] for _ in range(sensors)]
        """Their header stamps (what the sets carry)."""
        self._caps: list[list[int]] = [[] for _ in range(sensors)]
        self._values: list[list[Vector]] = [[] for _ in range(sensors)]
        self._arrays: list[NDArray[np.float64]] = [np.empty((0, 3)) for _ in range(sensors)]
        self._head = [0] * sensors
        self._formed: list[SetBatch] = []
        """Sets :meth:`add_rows` formed, for the next :meth:`pop`."""
        self._starts: list[set[int]] = [set() for _ in range(sensors)]
        """Common stamps of queued messages that start a new segment of their sensor (for :meth:`queued`)."""
        self._faulty: list[list[tuple[int, int]]] = [[] for _ in range(sensors)]
        """(stamp, common stamp) of accepted messages with a faulty reading since the last consumed message of
        each sensor: no set holds them, but their stamps count for a sample clock (:meth:`queued`)."""
        self._consumed: list[int] = [NEVER] * sensors
        """Common stamp of each sensor's last consumed message."""
        self.monitor: ExactMonitor | None = None
        """Judges the rule's decisions where mode ``auto`` chose it (:mod:`~magcal_ros.core.sync_revision`)."""

    # -- state ------------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Messages queued or held, not yet in a set or dropped."""
        return sum(len(s) - h for s, h in zip(self._stamps, self._head)) + self.held

    @property
    def effective_tolerance_ns(self) -> int:
        """The window in use: the tolerance, capped at half the shortest sample period."""
        shortest = self.min_period_ns
        return self.tolerance_ns if shortest is None else min(self.tolerance_ns, shortest // 2)

    def reset(self) -> None:
        """Drop every queued message (counted as unmatched) and forget each sensor's history."""
        self.stats.unmatched += sum(len(s) - h for s, h in zip(self._stamps, self._head))
        for k in range(self.size):
            self._stamps[k], self._raws[k], self._caps[k], self._values[k] = [], [], [], []
            self._arrays[k] = np.empty((0, 3))
            self._head[k] = 0
            self._starts[k] = set()
            self._faulty[k] = []
        self.forget()

    def queued(self) -> list[Accepted]:
        """Per sensor, its queued messages as acceptance let them through (no segment starts among them);
        the queues are emptied (for another rule to take them)."""
        out: list[Accepted] = []
        for k in range(self.size):
            h = self._head[k]
            raws, commons, caps = self._raws[k][h:], self._stamps[k][h:], self._caps[k][h:]
            streaming = len(self._values[k]) == len(self._stamps[k])
            values = self._values[k][h:] if streaming else [tuple(v) for v in self._arrays[k][h:].tolist()]
            starts = self._starts[k]
            after = self._stamps[k][h - 1] if h else self._consumed[k]
            rows = [(r, c, v, cap, c in starts) for r, c, v, cap in zip(raws, commons, values, caps)]
            rows += [(r, c, None, NO_CAP, c in starts) for r, c in self._faulty[k] if c > after]
            rows.sort(key=lambda row: row[1])
            out.append(rows)
            self._faulty[k] = []
            self._stamps[k], self._raws[k], self._caps[k], self._values[k] = [], [], [], []
            self._arrays[k] = np.empty((0, 3))
            self._head[k] = 0
        return out

    # -- streaming --------------------------------------------------------------------
    def add_all(self, index: int, stamp_ns: int, x: float, y: float, z: float,
                receipt_ns: int | None = None) -> list[SyncedSet]:
        """Offer one message of sensor ``index`` (``receipt_ns``: when it arrived, for restarts);
        the sets it completes (a held suspect released with it may complete one more)."""
        accepted = self.accept(index, stamp_ns, (x, y, z), self.fault(x, y, z), receipt_ns)
        if not accepted:
            return []
        self._queue(index, accepted)
        return self._formed_sets()

    def release_quiet_sets(self, now_ns: int) -> list[SyncedSet]:
        """Live, on the receiver's clock (ns): the sets that the messages held for sensors quiet for
        :data:`~magcal_ros.core.sync_rules.HOLD_NS` complete (:meth:`release_quiet_holds`)."""
        released = self.release_quiet_holds(now_ns)
        for index, accepted in released:
            self._queue(index, accepted)
        return self._formed_sets() if released else []

    def _formed_sets(self) -> list[SyncedSet]:
        """The sets the queued messages complete, in order."""
        formed = self._advance(final=False)
        if not formed:
            self._compact(keep_values=True)  # messages given up for a silent sensor are consumed too
            return []
        stamps, values = self._raws, self._values
        out = [SyncedSet(tuple(stamps[k][i] for k, i in enumerate(members)),
                         tuple(values[k][i] for k, i in enumerate(members))) for members in formed]
        self._compact(keep_values=True)
        return out

    def add(self, index: int, stamp_ns: int, x: float, y: float, z: float,
            receipt_ns: int | None = None) -> SyncedSet | None:
        """Offer one message of sensor ``index``; the (last) set it completes, if any (see :meth:`add_all`)."""
        formed = self.add_all(index, stamp_ns, x, y, z, receipt_ns)
        return formed[-1] if formed else None

    def _as_values(self, index: int) -> None:
        """Sensor ``index``'s queued readings as the streaming path keeps them (a list of tuples): a queue holds
        one form at a time, whichever path fed it last."""
        if len(self._arrays[index]):
            self._values[index] = [tuple(r) for r in self._arrays[index].tolist()]
            self._arrays[index] = np.empty((0, 3))

    def _as_arrays(self, index: int) -> None:
        """Sensor ``index``'s queued readings as the batch path keeps them (an (n, 3) array)."""
        if self._values[index]:
            self._arrays[index] = np.asarray(self._values[index], dtype=float).reshape(-1, 3)
            self._values[index] = []

    def _queue(self, index: int, accepted: list[tuple[int, int, Any, int, bool]]) -> None:
        for k, a in enumerate(self._arrays):  # (queues a batch fed: their readings as the streaming path's from here)
            if len(a):
                self._as_values(k)
        clock = self.streams[index].clock
        for stamp, common, value, cap, restart in accepted:
            if restart:
                self._starts[index].add(common)
            if clock is not None:
                if restart:
                    self.restart_clock(index)
                clock.offer(common)
            if value is None:
                self._faulty[index].append((stamp, common))
                continue
            self._stamps[index].append(common)
            self._raws[index].append(stamp)
            self._caps[index].append(cap)
            self._values[index].append(value)

    # -- batches ----------------------------------------------------------------------
    def add_batch(self, index: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64],
                  receipts: NDArray[np.int64] | None = None) -> None:
        """Queue messages of sensor ``index`` in its order: stamps (n,) ns, vectors (n, 3) T,
        ``receipts`` (n,) ns when they arrived (bag times; used only where a sensor restarts alone)."""
        s = np.asarray(stamps, dtype=np.int64).reshape(-1)
        v = np.asarray(vectors, dtype=float).reshape(-1, 3)
        r = None if receipts is None else np.asarray(receipts, dtype=np.int64).reshape(-1)
        if not len(s):
            return
        if not self.streams[index].busy and self._plain(index, s, r):
            self._batch_fast(index, s, v, r)
        else:
            self._batch_scalar(index, s, v, r)

    def _plain_streams(self, batches: Sequence[Batch]) -> bool:
        return all(not self.streams[k].busy and self._plain(k, s, r) for k, (s, _, r) in enumerate(batches))

    def _offered(self, index: int, accepted: Accepted, kept: Accepted) -> None:
        kept += accepted

    def _offered_all(self, kept: list[Accepted]) -> None:
        for k, rows in enumerate(kept):
            self._queue_rows(k, rows)

    def _plain(self, index: int, s: NDArray[np.int64], r: NDArray[np.int64] | None = None) -> bool:
        """True when no message of ``s`` (receipts ``r``) is a suspect, a step or part of a backlog: the
        vectorised path then equals the scalar one (anything else takes the scalar path)."""
        st = self.streams[index]
        if self.reject_zero:
            keep = s > 0
            s, r = s[keep], None if r is None else r[keep]
        if not len(s):
            return True
        prev = np.maximum.accumulate(np.concatenate([[st.last], s[:-1]]))
        if np.any(s < prev):  # a stamp behind its sequence, by any amount
            return False
        new = s > prev
        acc = s[new]
        if not len(acc):
            return True
        iv = np.diff(np.concatenate([[st.last], acc])) if st.last != NEVER else np.diff(acc)
        hist = np.asarray(st.intervals, dtype=np.int64)
        full = np.concatenate([hist, iv])
        unknown = full[len(hist):PERIOD_WINDOW]  # intervals before a period is known
        if np.any(unknown > self.restart_ns):
            return False
        first = max(len(hist), PERIOD_WINDOW)
        if len(full) <= first:
            return True
        w = np.sort(sliding_window_view(full, PERIOD_WINDOW), axis=1)
        median = (w[:, PERIOD_WINDOW // 2 - 1] + w[:, PERIOD_WINDOW // 2]) // 2  # of full[i : i + 8]
        at = np.arange(first, len(full))
        d, period = full[at], median[at - PERIOD_WINDOW]
        crowded = (4 * d < period) & (d < BACKLOG_INTERVAL)
        if np.any(SUSPECT_PERIODS[1] * d > SUSPECT_PERIODS[0] * period) or np.any(crowded):
            return False
        gap = 2 * d > 3 * period  # whole periods missing: lost samples, unless the arrivals saw no gap
        if r is None or not gap.any():
            return True
        if st.last_receipt is None and st.last != NEVER:
            return False
        racc = r[new]
        known = np.asarray(st.arrivals, dtype=np.int64).reshape(-1, 2)
        common = np.concatenate([known[:, 0], acc + st.base])
        receipt = np.concatenate([known[:, 1], racc])
        first_new = len(known) + len(acc) - len(iv)  # the arrival of full[len(hist)] in ``common``
        for j in np.flatnonzero(gap).tolist():
            i = first_new + int(at[j]) - len(hist)  # in ``common``; in ``acc``: i - len(known)
            w0 = max(0, i - LEAD_WINDOW)
            if i - w0 < TIMED_MIN:
                continue
            lead = int((common[w0:i] - receipt[w0:i]).max())
            bounds = st.floor_bounds(int(common[i]))  # the floor before this batch: lower than or as the rule's
            if bounds is not None:
                lead = max(lead, bounds[0])
            if 2 * (common[i] - receipt[i] - lead) > period[j]:
                return False  # a stamp ahead of its arrival: a step the rule may see (one message at a time)
            whole = d[j] / period[j]
            if 10 * abs(whole - round(whole)) > 1:
                return False  # a gap off whole periods: the rule may hold it (off the sensor's grid)
        return True

    def add_rows(self, stamps: NDArray[np.int64], vectors: NDArray[np.float64]) -> None:
        """Queue the rows of a table: every sensor's message at each of ``stamps`` (n,) ns, ``vectors``
        (n, S, 3) T, in order. Each sensor's messages are what :meth:`add_batch` takes; where nothing
        is queued and every sensor's acceptance passes every row as it is (stamps newer than all
        before, no suspect, every reading usable, one timeline), the rows are the sets the rule
        forms, and they are formed here at once (released by the next :meth:`pop`)."""
        s = np.asarray(stamps, dtype=np.int64).reshape(-1)
        v = np.asarray(vectors, dtype=float).reshape(len(s), self.size, 3)
        if not len(s):
            return
        sensors = range(self.size)
        plain = (all(len(self._stamps[k]) == self._head[k] and not self.streams[k].busy
                     and self.streams[k].base == 0 for k in sensors)
                 and not (self.reject_zero and s[0] <= 0) and bool(np.all(s[1:] > s[:-1]))
                 and all(s[0] > self.streams[k].last and self._plain(k, s) for k in sensors))
        faults = [acceptance.reading_faults(v[:, k], self.max_reading) for k in sensors] if plain else []
        if not plain or any(mask.any() for f in faults for mask in f.values()):
            for k in sensors:
                self.add_batch(k, s, v[:, k])
            return
        for k in sensors:  # each sensor's acceptance, as add_batch would keep it; nothing to queue
            self._accept_batch(k, s, v[:, k], None, faults[k])
        self.stats.sets += len(s)
        self.stats.used += self.size * len(s)
        self._formed.append(SetBatch(np.repeat(s[:, None], self.size, axis=1), v.copy()))

    def _batch_fast(self, index: int, s: NDArray[np.int64], v: NDArray[np.float64],
                    r: NDArray[np.int64] | None) -> None:
        """Vectorised acceptance of a batch without suspects (same outcome as :meth:`accept`)."""
        accepted = self._accept_batch(index, s, v, r)
        if accepted is None:
            return
        kept, values, caps = accepted
        st = self.streams[index]
        self._as_arrays(index)
        self._raws[index].extend(kept.tolist())
        self._stamps[index].extend((kept + st.base).tolist() if st.base else kept.tolist())
        self._caps[index].extend(caps.tolist())
        self._arrays[index] = np.concatenate([self._arrays[index], values])

    def _accept_batch(self, index: int, s: NDArray[np.int64], v: NDArray[np.float64], r: NDArray[np.int64] | None,
                      known: Mapping[str, NDArray[np.bool_]] | None = None,
                      ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]] | None:
        """The acceptance of :meth:`_batch_fast` (counts, the sensor's stamp history): the accepted
        usable messages' stamps, readings and window caps, or None when none is left. ``known``: the
        readings' faults (:func:`~magcal_ros.core.acceptance.reading_faults`) when already found, for a
        batch whose every stamp is accepted."""
        stats, st = self.stats, self.streams[index]
        if self.reject_zero:
            faults = acceptance.stamp_faults(s)
            for name, mask in faults.items():
                stats.count(name, int(mask.sum()))
            bad = np.logical_or.reduce(list(faults.values()))
            if bad.any():
                s, v = s[~bad], v[~bad]
                r = None if r is None else r[~bad]
        if not len(s):
            return None
        prev = np.maximum.accumulate(np.concatenate([[st.last], s[:-1]]))
        ordered = s > prev
        stats.duplicate += int(np.count_nonzero(s == prev))
        stats.out_of_order += int(np.count_nonzero(s < prev))
        s, v = s[ordered], v[ordered]
        if r is not None:
            r = r[ordered]
        if not len(s):
            return None
        caps = self._batch_caps(index, s)
        st.last = int(s[-1])
        st.lastc = st.last + st.base
        st.last_receipt = None if r is None else int(r[-1])
        if r is not None:
            st.heard = st.last_receipt
            st.note_leads(s + st.base, r)
        st.since += len(s)
        if st.since > PERIOD_WINDOW:
            st.before = None
        st.tail = (st.tail + (s[-TAIL:] + st.base).tolist())[-TAIL:]
        self.newest = max(self.newest, st.lastc)
        self.arrived(st.last_receipt)
        faults = acceptance.reading_faults(v, self.max_reading) if known is None else known
        for name, mask in faults.items():
            stats.count(name, int(mask.sum()))
        finite = ~np.logical_or.reduce(list(faults.values()))  # usable readings
        if not finite.all():
            self._faulty[index].extend(zip(s[~finite].tolist(), (s[~finite] + st.base).tolist()))
        return s[finite], v[finite], caps[finite]

    def _batch_scalar(self, index: int, s: NDArray[np.int64], v: NDArray[np.float64],
                      r: NDArray[np.int64] | None) -> None:
        """Message-by-message acceptance (suspects in the batch)."""
        faults = reading_fault_list(v, self.max_reading)
        receipts = [None] * len(s) if r is None else r.tolist()
        out: list[tuple[int, int, Any, int, bool]] = []
        for i, t in enumerate(s.tolist()):
            out += self.accept(index, t, v[i], faults[i], receipts[i])
        self._queue_rows(index, out)

    def _queue_rows(self, index: int, accepted: list[tuple[int, int, Any, int, bool]]) -> None:
        self._starts[index].update(a[1] for a in accepted if a[4])
        self._faulty[index].extend((a[0], a[1]) for a in accepted if a[2] is None)
        rows = [a for a in accepted if a[2] is not None]
        if not rows:
            return
        self._as_arrays(index)
        self._raws[index].extend(a[0] for a in rows)
        self._stamps[index].extend(a[1] for a in rows)
        self._caps[index].extend(a[3] for a in rows)
        self._arrays[index] = np.concatenate([self._arrays[index], np.asarray([a[2] for a in rows], dtype=float)])

    def _batch_caps(self, index: int, s: NDArray[np.int64]) -> NDArray[np.int64]:
        """Window caps of newly accepted stamps ``s`` (the values :meth:`accept` computes)."""
        st = self.streams[index]
        caps = np.full(len(s), NO_CAP, dtype=np.int64)
        if st.last == NEVER:
            first, s_iv = 1, np.diff(s)
            st.new_grid(st.last, int(s[0]))  # (a first stamp: no grid before it to keep)
        else:
            first, s_iv = 0, np.diff(np.concatenate([[st.last], s]))
        # The first few need the short history: compute them one by one, like accept().
        head = min(len(s_iv), max(0, PERIOD_WINDOW - len(st.intervals)))
        for j in range(head):
            caps[first + j] = st.record(int(s_iv[j]), self.pause_ns, int(s[first + j]))
        if head < len(s_iv):
            iv = np.concatenate([np.asarray(st.intervals, dtype=np.int64), s_iv[head:]])
            w = np.sort(sliding_window_view(iv, PERIOD_WINDOW)[1:], axis=1)  # windows ending at new ones
            period = (w[:, PERIOD_WINDOW // 2 - 1] + w[:, PERIOD_WINDOW // 2]) // 2
            caps[first + head :] = period // 2
            before = np.concatenate([[st.period if st.period else 0], period[:-1]]).astype(np.float64)
            new = s_iv[head:]
            known = before > 0
            steps = np.where(known, np.maximum(np.round(new / np.where(known, before, 1.0)), 1.0), 0.0)
            ends = s[first + head:]  # the stamp each new interval ends at
            start = 0
            for p in np.flatnonzero(new > self.pause_ns).tolist():  # a pause starts the grid again (SensorStream.record)
                st.grow_grid(steps[start:p], new[start:p], known[start:p])
                st.new_grid(int(ends[p] - new[p]), int(ends[p]))
                start = p + 1
            st.grow_grid(steps[start:], new[start:], known[start:])
            self._fresh_caps(st, iv, len(iv) - len(new), caps[first + head:])
            st.intervals = iv[-PERIOD_WINDOW:].tolist()
            st.period = int(period[-1])
        return caps

    def _fresh_caps(self, st: Any, iv: NDArray[np.int64], start: int, caps: NDArray[np.int64]) -> None:
        """The caps (in place) of the stamps whose intervals ``iv[start:]`` follow a pause by fewer than
        :data:`PERIOD_WINDOW` (what :meth:`SensorStream.record` returns one by one: half the median of the
        intervals since the pause); ``st.fresh`` brought up to date."""
        new = iv[start:]
        n = len(new)
        marks = np.where(new > self.pause_ns, np.arange(n), -(2**40))
        marks[0] = max(int(marks[0]), -1 - st.fresh if st.fresh < PERIOD_WINDOW else -(2**40))
        since = np.arange(n) - np.maximum.accumulate(marks)  # intervals since the last pause, the pause's own 0
        for j in np.flatnonzero((since > 0) & (since < PERIOD_WINDOW)).tolist():
            caps[j] = median_int(iv[start + j + 1 - int(since[j]):start + j + 1].tolist()) // 2
        st.fresh = int(min(since[-1], PERIOD_WINDOW))

    def pop(self, final: bool = False) -> SetBatch:
        """Release the sets the queued messages decide (and drop everything left when ``final``)."""
        for k in range(self.size):  # (a queue the streaming path fed: its readings as arrays from here)
            self._as_arrays(k)
        if final:
            for k in range(self.size):
                self._queue_rows(k, self.release_held(k))
        formed = self._advance(final)
        s = self.size
        batches, self._formed = self._formed, []  # (sets add_rows formed come first: older than any queued)
        if formed:
            idx = np.asarray(formed, dtype=np.int64).reshape(-1, s)
            stamps = np.stack([np.asarray(self._raws[k], dtype=np.int64)[idx[:, k]] for k in range(s)], axis=1)
            vectors = np.stack([self._arrays[k][idx[:, k]] for k in range(s)], axis=1)
            batches.append(SetBatch(stamps, vectors))
        self._compact(keep_values=False)
        if not batches:
            return empty_batch(s)
        if len(batches) == 1:
            return batches[0]
        return SetBatch(np.concatenate([b.stamps for b in batches]), np.concatenate([b.vectors for b in batches]))

    # -- the rule ---------------------------------------------------------------------
    def _advance(self, final: bool) -> list[tuple[int, ...]]:
        """Apply the set rule to the queues; returns the member indices of each set formed. Stops where the
        :attr:`monitor` ends exact matching (the rest stays queued for the rule that takes over)."""
        formed: list[tuple[int, ...]] = []
        scalar_steps = 0  # steps of the one-set-at-a-time rule before trying a run again
        while self.monitor is None or self.monitor.reason is None:
            if scalar_steps:
                scalar_steps -= 1
            elif min(len(q) - h for q, h in zip(self._stamps, self._head)) >= RUN_BLOCK:
                if self._form_run(formed) < RUN_BLOCK // 2:
                    scalar_steps = RUN_BLOCK
                continue
            if not self._decide_next(formed, final):
                break
        self.stats.sets += len(formed)
        self.stats.used += self.size * len(formed)
        return formed

    def _form_run(self, formed: list[tuple[int, ...]]) -> int:
        """Form the run of matching sets at the heads (up to the end of the monitor's block); how many."""
        head, sensors = self._head, range(self.size)
        n = self._matched_run()
        if self.monitor is not None:
            n = min(n, self.monitor.room)
        if n:
            formed.extend(zip(*(range(head[k], head[k] + n) for k in sensors)))
            if self.monitor is not None:
                self.monitor.formed([self._stamps[k][head[k]:head[k] + n] for k in sensors], self.tolerance_ns)
            for k in sensors:
                head[k] += n
        return n

    def _decide_next(self, formed: list[tuple[int, ...]], final: bool) -> bool:
        """One decision of the rule at the heads (a set, or the anchor dropped); False when none can be
        made yet."""
        stamps, caps, head, sensors = self._stamps, self._caps, self._head, range(self.size)
        try:  # every sensor has a head: the common case, kept tight
            t = [stamps[k][head[k]] for k in sensors]
        except IndexError:
            return self._decide_short(final)
        t0 = min(t)
        cap = min([caps[k][head[k]] for k in sensors])  # half the period each head's sensor had when it came
        window = min(self.tolerance_ns, cap)
        if max(t) - t0 <= window:
            formed.append(tuple(head))
            for k in sensors:
                head[k] += 1
            if self.monitor is not None:
                self.monitor.formed([[x] for x in t], window)
            return True
        self.stats.unmatched += 1
        if self.monitor is not None:
            # by the heads' own periods (twice their cap): the same on both paths (the streams' latest estimates
            # are not: offline they have seen every message already)
            if cap != NO_CAP and 2 * (max(t) - t0) < min(2 * cap, self._shortest_step()):
                self.monitor.missed(t, window)  # one instant, beyond the window
        head[t.index(t0)] += 1
        return True

    def _shortest_step(self) -> int:
        """The shortest step (ns) of any sensor's stamps to its head from the stamp before it: heads further apart
        than half of it are not one instant, whatever the period estimates (which lag a rate that changed in a
        pause: at 2 kHz after 50 Hz, samples lost as a sensor came back looked like a clock 4 ms off)."""
        stamps = self._stamps
        return min(stamps[k][h] - (stamps[k][h - 1] if h else self._consumed[k]) for k, h in enumerate(self._head))

    def _decide_short(self, final: bool) -> bool:
        """A decision while some sensor has nothing queued: only what its next message cannot change."""
        stamps, head, streams, sensors = self._stamps, self._head, self.streams, range(self.size)
        avail = [k for k in sensors if head[k] < len(stamps[k])]
        if not avail:
            return False
        t = [stamps[k][head[k]] for k in avail]
        t0 = min(t)
        silent = [k for k in sensors if head[k] >= len(stamps[k])]
        dead = any(streams[k].lastc >= t0 + self.tolerance_ns and not streams[k].busy for k in silent)
        stale = self.waited(t0, silent)
        crowded = max(len(stamps[k]) - head[k] for k in avail) > self.max_pending
        if final or dead or stale or crowded:
            self.stats.unmatched += 1
            head[avail[t.index(t0)]] += 1
            return True
        return False

    def _matched_run(self) -> int:
        """How many sets the rule forms in a row from the current heads (every queue holding at least
        :data:`RUN_BLOCK`): the leading sets whose heads all lie within the window, checked with numpy in
        blocks that double while every set matches. The rule's outcome, without its per-set Python."""
        stamps, caps, head = self._stamps, self._caps, self._head
        sensors = range(self.size)
        avail = min(len(stamps[k]) - head[k] for k in sensors)
        tol = self.tolerance_ns
        done, block = 0, RUN_BLOCK
        while done < avail:
            b = min(block, avail - done)
            t = np.array([stamps[k][head[k] + done : head[k] + done + b] for k in sensors], dtype=np.int64)
            c = np.array([caps[k][head[k] + done : head[k] + done + b] for k in sensors], dtype=np.int64)
            ok = t.max(axis=0) - t.min(axis=0) <= np.minimum(c.min(axis=0), tol)
            if not ok.all():
                return done + int(np.argmin(ok))
            done += b
            block *= 2
        return done

    def _compact(self, keep_values: bool) -> None:
        """Forget consumed messages once enough have piled up."""
        for k in range(self.size):
            h = self._head[k]
            if h and (h >= 4096 or not keep_values or h == len(self._stamps[k])):
                self._consumed[k] = after = self._stamps[k][h - 1]
                if self._faulty[k]:
                    self._faulty[k] = [f for f in self._faulty[k] if f[1] > after]
                del self._stamps[k][:h]
                del self._raws[k][:h]
                del self._caps[k][:h]
                if keep_values:
                    del self._values[k][:h]
                else:
                    self._arrays[k] = self._arrays[k][h:]
                self._head[k] = 0


def _as_batch(batch: Any) -> Batch:
    stamps, vectors, receipts = batch
    s = np.asarray(stamps, dtype=np.int64).reshape(-1)
    return s, np.asarray(vectors, dtype=float).reshape(-1, 3), \
        None if receipts is None else np.asarray(receipts, dtype=np.int64).reshape(-1)


# --------------------------------------------------------------------------- choosing the mode


def _median(values: list[float]) -> float:
    v = sorted(values)
    m = len(v) // 2
    return v[m] if len(v) % 2 else 0.5 * (v[m - 1] + v[m])


def clean_stamps(stamps: Sequence[int]) -> list[int]:
    """Nonzero stamps strictly newer than every earlier one (what the rule could accept)."""
    out: list[int] = []
    last = NEVER
    for t in stamps:
        if t != 0 and t > last:
            out.append(t)
            last = t
    return out


def choose_mode(stamps: Sequence[Sequence[int]], tolerance: int, names: Sequence[str] | None = None,
                offsets: Sequence[int] | None = None, coarse: bool = False) -> tuple[str, str]:
    """``exact`` or ``interpolate`` for sensors whose first stamps are ``stamps`` (ns, per sensor,
    increasing), and why, in words.

    Exact when the exact rule would keep the sets: of the reference (first) sensor's stamps
    that have a stamp of every other sensor within half a period (samples not lost), at
    least :data:`EXACT_FRACTION` have all of them within the window (``tolerance``, capped
    at half the shortest period), and no sensor's stamps sit off the reference's by more
    than a quarter of the window in the median: the sensors are sampled together and
    stamped alike. Interpolate otherwise, and always with time offsets. ``coarse``: the field
    jumps between consecutive samples (independent attitudes, a motion far faster than the
    sampling): interpolating between samples would make fields no sensor saw, so stamps that
    coincide within the window are matched exactly even when one sensor's sit off the others'.
    """
    names = list(names) if names is not None else [f"sensor {k + 1}" for k in range(len(stamps))]
    if offsets is not None and any(offsets):
        return "interpolate", "time offsets are set"
    if len(stamps) < 2:
        return "exact", "one sensor"
    if any(len(s) < 4 for s in stamps):
        short = [n for n, s in zip(names, stamps) if len(s) < 4]
        return "interpolate", (f"too few stamps of {', '.join(short)} to tell (not heard yet): sets wait for it, "
                               "exact matching would be chosen on the others' stamps alone")
    periods = [_median([float(b - a) for a, b in zip(s[:-1], s[1:])]) for s in stamps]
    window = min(float(tolerance), min(periods) / 2)
    half = min(periods) / 2
    offsets_by: list[list[float]] = [[] for _ in stamps]
    present = matched = 0
    for t in stamps[0]:
        d = [0.0]
        for other in stamps[1:]:
            i = bisect.bisect_left(other, t)
            near = [other[j] - t for j in (i - 1, i) if 0 <= j < len(other)]
            d.append(float(min(near, key=abs)))
        if max(abs(x) for x in d) > half:
            continue  # a sample lost, or not sampled together at all
        present += 1
        matched += max(d) - min(d) <= window
        for k, x in enumerate(d):
            offsets_by[k].append(x)
    if present < 4:
        return "interpolate", f"the stamps of {', '.join(names)} do not coincide within half a period"
    if matched < EXACT_FRACTION * present:
        return "interpolate", (f"the stamps of {', '.join(names)} spread beyond {window / 1e6:.3g} ms in "
                               f"{1 - matched / present:.0%} of the sets")
    for k in range(1, len(stamps)):
        middle = _median(offsets_by[k])
        if abs(middle) > window / 4 and not coarse:
            return "interpolate", f"{names[k]} is sampled {middle / 1e6:.3g} ms after {names[0]} (median)"
    return "exact", f"the stamps of {', '.join(names)} coincide within {window / 1e6:.3g} ms"


class StreamSynchronizer:
    """The set synchroniser readers and nodes use: mode ``auto`` | ``exact`` | ``interpolate``.

    ``max_gap_ns``: interpolation never bridges more (0: :data:`MAX_GAP_PERIODS` periods of
    the interpolated sensor). ``time_offsets_ns`` (per sensor): a sample stamped ``t`` is the
    field at ``t - offset``; non-zero offsets need interpolation. ``names`` only name sensors
    in :attr:`reason`. In mode ``auto`` the first :data:`DECIDE_AFTER` messages of every
    sensor (or 8 spanning a second, for slow sensors) are held (counted in :attr:`pending`)
    until the mode is chosen; the same messages then go through the chosen rule, so the sets
    do not depend on when that happened.
    """

    def __init__(
        self,
        sensors: int,
        tolerance_ns: int = int(DEFAULT_SYNC_TOLERANCE * NS_PER_S),
        mode: str = DEFAULT_SYNC_MODE,
        max_gap_ns: int = 0,
        time_offsets_ns: Sequence[int] | None = None,
        lag_ns: int = int(DEFAULT_LAG * NS_PER_S),
        max_pending: int = 10_000,
        restart_ns: int = int(RESTART_JUMP * NS_PER_S),
        reject_zero: bool = True,
        names: Sequence[str] | None = None,
        stats: SyncStats | None = None,
        max_reading: float = math.inf,
    ) -> None:
        if sensors < 1:
            raise ValueError("need at least one sensor")
        self.max_reading = float(max_reading)
        offsets = [int(t) for t in (time_offsets_ns or [0] * sensors)]
        if len(offsets) != sensors:
            raise ValueError(f"{len(offsets)} time offsets for {sensors} sensors")
        if check_mode(mode) == "exact" and any(offsets):
            raise ValueError("time offsets need sync mode interpolate (or auto): exact matching cannot shift stamps")
        if tolerance_ns < 0 or max_gap_ns < 0:
            raise ValueError("tolerance and max_gap must be >= 0")
        self.size = sensors
        self.requested = mode
        self.max_gap_ns = int(max_gap_ns)
        self.time_offsets_ns = offsets
        self.names = list(names) if names is not None else [f"sensor {k + 1}" for k in range(sensors)]
        self._tolerance = int(tolerance_ns)
        self.lag_ns, self.max_pending, self.restart_ns = int(lag_ns), int(max_pending), int(restart_ns)
        self.reject_zero = reject_zero
        self.stats = stats if stats is not None else SyncStats()
        self.pause_ns = self.restart_ns
        self.engine: SetSynchronizer | InterpolatingSynchronizer | None = None
        self.reason = ""
        """Why the mode in use was chosen (empty while choosing)."""
        self._held: list[list[tuple[int, float, float, float, int | None, int]]] = [[] for _ in range(sensors)]
        self._arrivals = 0
        """Messages held while choosing (their order, for the replay)."""
        self._held_batches: list[list[tuple[Any, Any, Any]]] = [[] for _ in range(sensors)]
        self._placed: list[tuple[int, int | None]] | None = None
        """Placements kept from a synchroniser this one replaced (see :meth:`keep_placements`)."""
        if mode != "auto" or any(offsets):
            chosen = "interpolate" if any(offsets) else mode
            self._start(chosen, "time offsets are set" if chosen != mode else f"sync mode {mode}")

    # -- state ------------------------------------------------------------------------
    @property
    def mode(self) -> str | None:
        """``exact`` or ``interpolate`` once chosen, None while mode ``auto`` is still choosing."""
        return None if self.engine is None else self.engine.mode

    @property
    def tolerance_ns(self) -> int:
        """The exact rule's tolerance (ns)."""
        return self._tolerance

    @tolerance_ns.setter
    def tolerance_ns(self, value: int) -> None:
        self._tolerance = int(value)
        if isinstance(self.engine, SetSynchronizer):
            self.engine.tolerance_ns = self._tolerance

    @property
    def pending(self) -> int:
        """Messages held, queued, not yet in a set or dropped."""
        if self.engine is None:
            return sum(len(h) for h in self._held) + sum(len(b[0]) for h in self._held_batches for b in h)
        return self.engine.pending

    @property
    def effective_tolerance_ns(self) -> int:
        """The exact window in use (the tolerance capped at half the shortest period); the tolerance while
        interpolating or choosing."""
        return self.engine.effective_tolerance_ns if isinstance(self.engine, SetSynchronizer) else self._tolerance

    @property
    def min_period_ns(self) -> int | None:
        """Shortest sample period estimate of the sensors (ns)."""
        return None if self.engine is None else self.engine.min_period_ns

    def period_ns(self, index: int) -> int | None:
        """Sample period estimate of sensor ``index`` (ns; a fit over many samples), None before."""
        return None if self.engine is None else self.engine.period_ns(index)

    def lost(self, index: int) -> int:
        """Samples of sensor ``index`` lost before they reached the synchroniser."""
        return 0 if self.engine is None else self.engine.lost(index)

    def gaps(self, index: int) -> int:
        """Runs of lost samples of sensor ``index``."""
        return 0 if self.engine is None else self.engine.gaps(index)

    def set_pause(self, pause_ns: int) -> None:
        """A sensor silent longer than ``pause_ns`` paused: its gap is not counted as lost samples."""
        self.pause_ns = int(pause_ns)
        if self.engine is not None:
            self.engine.set_pause(self.pause_ns)

    def _start(self, mode: str, reason: str) -> None:
        if mode == "exact":
            self.engine = SetSynchronizer(self.size, self._tolerance, self.lag_ns, self.max_pending, self.restart_ns,
                                          self.reject_zero, self.stats, pause_ns=self.pause_ns)
        else:
            self.engine = InterpolatingSynchronizer(self.size, self.max_gap_ns, self.time_offsets_ns, self.lag_ns,
                                                    self.max_pending, self.restart_ns, self.reject_zero, self.stats,
                                                    pause_ns=self.pause_ns)
        self.engine.max_reading = self.max_reading
        self.reason = reason
        for stream, (base, follows) in zip(self.engine.streams, self._placed or []):
            stream.base, stream.follows = base, follows

    def placements(self) -> list[tuple[int, int | None]] | None:
        """Each sensor's placement on the common time line: (base ns, the sensor whose clock it follows or
        None); None before any was made."""
        if self.engine is None:
            return self._placed
        return [(s.base, s.follows) for s in self.engine.streams]

    def keep_placements(self, placed: list[tuple[int, int | None]] | None) -> None:
        """Go on placing each sensor's stamps as ``placed`` (:meth:`placements` of the synchroniser this one
        replaces, for the same sensors): a sensor whose driver restarted before a reconfiguration (new time
        offsets, say) keeps its segment's placement instead of being paired ``jump`` seconds off."""
        if placed is None or len(placed) != self.size:
            return
        self._placed = list(placed)
        if self.engine is not None:
            for stream, (base, follows) in zip(self.engine.streams, self._placed):
                stream.base, stream.follows = base, follows

    # -- choosing ---------------------------------------------------------------------
    def _candidates(self) -> list[list[int]]:
        out = []
        for k in range(self.size):
            stamps = [m[0] for m in self._held[k] if acceptance.reading_fault(*m[1:4], self.max_reading) is None]
            for s, v, _ in self._held_batches[k]:
                ok = ~np.logical_or.reduce(list(acceptance.reading_faults(v, self.max_reading).values()))
                stamps += s[ok].tolist()
                if len(stamps) > 4 * DECIDE_AFTER:
                    break
            out.append(clean_stamps(stamps)[:DECIDE_AFTER])
        return out

    def _ready(self, final: bool) -> bool:
        if final:
            return True
        counts = [len(h) + sum(len(b[0]) for b in hb) for h, hb in zip(self._held, self._held_batches)]
        if max(counts) >= 8 * DECIDE_AFTER:  # a sensor stays silent: choose with what there is
            return True
        if min(counts) < DECIDE_EARLY[0]:
            return False
        candidates = self._candidates()  # (a sensor whose stamps jumped back early has few: enough of its messages)
        return all(len(c) >= DECIDE_AFTER or n >= 2 * DECIDE_AFTER or
                   (len(c) >= DECIDE_EARLY[0] and c[-1] - c[0] >= DECIDE_EARLY[1]) for c, n in zip(candidates, counts))

    def _coarse(self) -> bool:
        """Whether the reference sensor's field jumps between consecutive readings (median angle beyond
        :data:`MAX_INTERPOLATION_STEP`): a motion its samples do not resolve."""
        rows = [m[1:4] for m in self._held[0]]
        vectors = np.array(rows, dtype=float).reshape(-1, 3)
        for _, v, _ in self._held_batches[0]:
            vectors = np.concatenate([vectors, v[: 4 * DECIDE_AFTER]])
        vectors = vectors[np.all(np.isfinite(vectors), axis=1)][: 4 * DECIDE_AFTER]
        if len(vectors) < 4:
            return False
        unit = vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-300)
        steps = np.arccos(np.clip(np.sum(unit[1:] * unit[:-1], axis=1), -1.0, 1.0))
        return bool(np.median(steps) > MAX_INTERPOLATION_STEP)

    def _decide(self) -> None:
        coarse = self._coarse()
        mode, why = choose_mode(self._candidates(), self._tolerance, self.names, self.time_offsets_ns, coarse=coarse)
        self._start(mode, why)
        if mode == "exact" and isinstance(self.engine, SetSynchronizer):
            self.engine.monitor = ExactMonitor(self.names, coarse)

    def _revised(self) -> bool:
        """Whether exact matching, chosen by mode ``auto``, just ended (:mod:`~magcal_ros.core.sync_revision`):
        the messages it still queued, and everything after, go to interpolation, with each sensor's
        acceptance (placements, steps held) as it was and its sample clock learnt afresh."""
        old = self.engine
        if not isinstance(old, SetSynchronizer) or old.monitor is None or old.monitor.reason is None:
            return False
        why = old.monitor.reason
        self._start("interpolate", f"exact matching ended ({why}), interpolating from then on")
        new = self.engine
        assert isinstance(new, InterpolatingSynchronizer)
        new.streams, new.newest, new.latest_arrival = old.streams, old.newest, old.latest_arrival
        rows_of = old.queued()
        for st, rows in zip(new.streams, rows_of):
            clock, st.clock = st.clock, SampleClock(pause_ns=self.pause_ns)
            if clock is not None:
                st.clock.carry_counts(clock, [row[1] for row in rows])
        queued = sorted((row[1], k, i, row) for k, rows in enumerate(rows_of) for i, row in enumerate(rows))
        for _, k, _, row in queued:  # in time, as they came: a sensor that follows another's restart waits for it
            new._clock_in(k, [row])
        return True

    def _replay(self) -> list[SyncedSet]:
        """Feed what was held while choosing into the chosen rule: messages in the order they came (each
        sensor's in its own order), then batches sensor by sensor."""
        engine = self.engine
        assert engine is not None
        out: list[SyncedSet] = []
        held = sorted((m[5], k, m) for k, h in enumerate(self._held) for m in h)
        for _, k, (stamp, x, y, z, receipt, _) in held:
            out += engine.add_all(k, stamp, x, y, z, receipt)
        for k in range(self.size):
            for s, v, r in self._held_batches[k]:
                engine.add_batch(k, s, v, r)
        self._held = [[] for _ in range(self.size)]
        self._held_batches = [[] for _ in range(self.size)]
        return out

    # -- input ------------------------------------------------------------------------
    def _replay_held(self) -> None:
        """Feed the messages held while choosing into the chosen rule as batches (:meth:`add_streams`: in the
        order they came where that matters, as :meth:`_replay` offers them one at a time), each sensor's held
        messages before its held batches."""
        assert self.engine is not None
        batches = []
        for h, hb in zip(self._held, self._held_batches):
            parts = [(np.array([m[0] for m in h], dtype=np.int64), np.array([m[1:4] for m in h], dtype=float).reshape(-1, 3),
                      None if any(m[4] is None for m in h) else np.array([m[4] for m in h], dtype=np.int64))] + hb
            receipts = None if any(r is None for _, _, r in parts) else np.concatenate([r for _, _, r in parts])
            batches.append((np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), receipts))
        self._held = [[] for _ in range(self.size)]
        self._held_batches = [[] for _ in range(self.size)]
        self.engine.add_streams(batches)

    def add(self, index: int, stamp_ns: int, x: float, y: float, z: float,
            receipt_ns: int | None = None) -> list[SyncedSet]:
        """Offer one message of sensor ``index`` (``receipt_ns``: when it arrived, node clock); the sets
        it completes, in order (usually none or one)."""
        engine = self.engine
        if engine is not None:
            out = engine.add_all(index, stamp_ns, x, y, z, receipt_ns)
            return out + self._formed_after_revision(False)
        self._held[index].append((stamp_ns, x, y, z, receipt_ns, self._arrivals))
        self._arrivals += 1
        if not self._ready(False):
            return []
        self._decide()
        return self._replay() + self._formed_after_revision(False)

    def add_batch(self, index: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64],
                  receipts: NDArray[np.int64] | None = None) -> None:
        """Queue messages of sensor ``index`` in its order (stamps (n,) ns, vectors (n, 3) T, receipts (n,)
        ns or None); :meth:`pop` releases the sets."""
        if self.engine is not None:
            self.engine.add_batch(index, stamps, vectors, receipts)
            return
        s = np.asarray(stamps, dtype=np.int64).reshape(-1)
        self._held_batches[index].append((s, np.asarray(vectors, dtype=float).reshape(-1, 3),
                                          None if receipts is None else np.asarray(receipts, dtype=np.int64)))

    def add_streams(self, batches: Sequence[Batch]) -> None:
        """Queue a stretch of every sensor's messages: per sensor ``(stamps (n,) ns, vectors (n, 3) T,
        receipts (n,) ns or None)``, each in its order; :meth:`pop` releases the sets. Where every
        message's arrival is known they are offered in the order they arrived (by receipt), as a live
        node offers them, wherever the order can matter (while the mode is chosen, and around a
        suspect stamp), so that a recording gives the sets a node would; each sensor's batch at once
        otherwise."""
        batches = [_as_batch(b) for b in batches]
        if self.engine is None:
            if any(b[2] is None for b in batches):
                for k, (st, v, r) in enumerate(batches):
                    self.add_batch(k, st, v, r)
                return
            fed = [0] * self.size
            for k, i in arrival_order([b[2] for b in batches]):  # type: ignore[misc]
                st, v, r = batches[k]
                x, y, z = v[i].tolist()
                self._held[k].append((int(st[i]), x, y, z, int(r[i]), self._arrivals))  # type: ignore[index]
                self._arrivals += 1
                fed[k] = i + 1
                if self._ready(False):
                    break
            else:
                return
            self._decide()
            self._replay_held()
            batches = [(st[f:], v[f:], None if r is None else r[f:]) for (st, v, r), f in zip(batches, fed)]
        assert self.engine is not None
        self.engine.add_streams(batches)

    def pop(self, final: bool = False) -> SetBatch:
        """Release the sets decided so far (everything, dropping what is left, when ``final``)."""
        if self.engine is None:
            if not self._ready(final):
                return empty_batch(self.size)
            self._decide()
            self._replay_held()  # as batches: the queue keeps one form of its readings
        assert self.engine is not None
        batch = self.engine.pop(final)
        if self._revised():
            batch = _join(batch, self.engine.pop(final))
        return batch

    def release_quiet(self, now_ns: int) -> list[SyncedSet]:
        """Live, called now and then with the receiver's clock (ns, the clock of the arrivals given to :meth:`add`):
        the sets completed by the messages held for a sensor whose latest came more than
        :data:`~magcal_ros.core.sync_rules.HOLD_NS` before, decided as at the end of its stream (they wait for
        its later messages; at the end of a collection none come)."""
        if self.engine is None:
            return []
        return self.engine.release_quiet_sets(now_ns) + self._formed_after_revision(False)

    def _formed_after_revision(self, final: bool) -> list[SyncedSet]:
        """Live: where exact matching just ended, the sets interpolation forms from what it queued."""
        if not self._revised():
            return []
        assert isinstance(self.engine, InterpolatingSynchronizer)
        return self.engine._form(final)

    def reset(self) -> None:
        """Drop everything queued or held (counted as unmatched) and choose the mode afresh (``auto``)."""
        self.stats.unmatched += sum(len(h) for h in self._held) + sum(len(b[0]) for h in self._held_batches for b in h)
        if self.engine is not None:
            self.engine.reset()
        self._held = [[] for _ in range(self.size)]
        self._held_batches = [[] for _ in range(self.size)]
        if self.requested == "auto" and not any(self.time_offsets_ns):
            self.engine, self.reason = None, ""


def stream_synchronizer(
    names: Sequence[str],
    tolerance: float = DEFAULT_SYNC_TOLERANCE,
    mode: str = DEFAULT_SYNC_MODE,
    max_gap: float = DEFAULT_MAX_GAP,
    time_offsets: Mapping[str, float] | None = None,
    **bounds: Any,
) -> StreamSynchronizer:
    """A :class:`StreamSynchronizer` for sensors ``names`` from user settings in seconds:
    ``tolerance`` (exact window), ``mode`` (``auto`` | ``exact`` | ``interpolate``), ``max_gap``
    (0: automatic) and ``time_offsets`` by sensor name (missing: 0). ``bounds``: ``lag_ns``,
    ``max_pending``, ``restart_ns``, ``reject_zero``, ``max_reading`` (T). :class:`InputError` naming a bad value, a
    sensor that is not one of ``names``, or time offsets with mode ``exact``."""
    try:
        tol = tolerance_ns(tolerance)
        gap = max_gap_ns(max_gap)
        check_mode(mode)
        offsets = dict(time_offsets or {})
        strangers = sorted(set(offsets) - set(names))
        if strangers:
            raise ValueError(f"time offset for {', '.join(strangers)}, not a sensor here ({', '.join(names)})")
        shifts = [time_offset_ns(offsets.get(n, 0.0), f"{n}.time_offset") for n in names]
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if mode == "exact" and any(shifts):
        lagging = ", ".join(f"{n} {t / 1e6:g} ms" for n, t in zip(names, shifts) if t)
        raise InputError(f"time offsets ({lagging}) need sync mode interpolate or auto: exact matching pairs "
                         "stamps as they are")
    return StreamSynchronizer(len(names), tol, mode, gap, shifts, names=names, **bounds)


def _join(a: SetBatch, b: SetBatch) -> SetBatch:
    if not len(a):
        return b
    if not len(b):
        return a
    return SetBatch(np.concatenate([a.stamps, b.stamps]), np.concatenate([a.vectors, b.vectors]))


def synchronise_streams(
    streams: Sequence[tuple[NDArray[np.int64], NDArray[np.float64]]],
    time_offsets: Sequence[float] | None = None,
    mode: str = "interpolate",
    max_gap: float = DEFAULT_MAX_GAP,
    tolerance: float = DEFAULT_SYNC_TOLERANCE,
    receipts: Sequence[NDArray[np.int64] | None] | None = None,
    names: Sequence[str] | None = None,
    reject_zero: bool = True,
    max_reading: float = math.inf,
) -> tuple[SetBatch, SyncStats, str]:
    """Sets from per-sensor streams: ``streams[k] = (stamps (n_k,) ns, vectors (n_k, 3) T)`` in each
    sensor's order, ``time_offsets`` (s) per sensor (a sample stamped ``t`` is the field at
    ``t - offset``), by the rule of :class:`StreamSynchronizer` in ``mode``.

    Returns the sets (interpolation: every member at the set's instant, the first sensor's
    sample instant), the counters and the mode used. Offline, so nothing is given up for lag.
    ``receipts``: per sensor, when each message arrived (bag times; None: unknown); readings
    beyond ``max_reading`` (T) are dropped (``out_of_range``). :class:`InputError` for a bad setting.
    """
    names = list(names) if names is not None else [f"sensor {k + 1}" for k in range(len(streams))]
    offsets = dict(zip(names, time_offsets)) if time_offsets is not None else None
    sync = stream_synchronizer(names, tolerance, mode, max_gap, offsets, lag_ns=2**62, max_pending=2**62,
                               reject_zero=reject_zero, max_reading=max_reading)
    sync.add_streams([(stamps, vectors, None if receipts is None else receipts[k])
                      for k, (stamps, vectors) in enumerate(streams)])
    batch = sync.pop(final=True)
    return batch, sync.stats, str(sync.mode)

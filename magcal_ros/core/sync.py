"""The one rule that groups per-sensor messages into synchronized sets, for bags and live nodes.

Input: for each sensor, its messages in the order that sensor produced them (a topic's
order in a bag, or on the wire), each a header stamp (integer ns) and a vector (T).

1. **Per-sensor acceptance.** A message is dropped and counted when its stamp is 0 (never
   stamped) or negative (``zero_stamp``, ``negative_stamp``), not newer than the sensor's
   previous stamp (``duplicate`` or ``out_of_order``), or its vector is NaN or infinite
   (``nonfinite``) or beyond any magnetometer's reading in the Earth's field
   (``out_of_range``; both by :mod:`magcal_ros.core.acceptance`, and the stamp still
   counts as the sensor's previous one). A stamp more than ``restart_ns`` behind the
   sensor's previous one means a source restarted: every queued message is dropped and
   all sensors start afresh (``restarts``).
2. **Sets.** Accepted messages wait in one queue per sensor. Repeatedly, with the head
   (oldest) message of every queue in view: the earliest head is the *anchor* ``t0``;
   if every head lies within ``[t0, t0 + w]`` the heads form a set, otherwise the
   anchor alone is dropped (``unmatched``). The window ``w`` is ``tolerance_ns``, capped
   at half of each member sensor's sample period (the median of its last 8 stamp
   intervals), so that a window can never hold two samples of one sensor: at 2 kHz a
   1 ms tolerance would otherwise pair sample ``n`` of one sensor with ``n + 1`` of
   another after a loss.

The rule depends only on each sensor's own message sequence, never on how the sensors'
messages interleave, so a recording gives the same sets on the ship (streaming,
:meth:`SetSynchronizer.add`, one message at a time, a set released the moment its last
member arrives) and on shore (batches, :meth:`SetSynchronizer.add_batch` and
:meth:`SetSynchronizer.pop`, vectorised acceptance). Two bounds keep memory finite in a
live node and are the only departures from that: a head older than ``lag_ns`` behind
the newest stamp seen, or beyond ``max_pending`` queued messages of one sensor, is given
up (``unmatched``) while another sensor is silent; and sets around a restart depend on
arrival order. A set's stamp is its first sensor's stamp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from magcal_ros.core import acceptance
from magcal_ros.core.units import NS_PER_S

DEFAULT_SYNC_TOLERANCE: float = 1e-3
"""Default largest spread (s) of the header stamps of one set, for nodes and offline tools."""
DEFAULT_LAG: float = 1.0
"""Default time (s) a live synchronizer waits for a silent sensor before giving a set up."""
RESTART_JUMP: float = 1.0
"""A stamp this far (s) behind its sensor's previous one means the source restarted."""
PERIOD_WINDOW: int = 8
"""Stamp intervals in each sensor's sample period estimate (median)."""

_NO_CAP = 2**62
_NEVER = -(2**62)
Vector = tuple[float, float, float]


@dataclass
class SyncStats:
    """What the synchronizer did, message by message (one vocabulary for bags and nodes)."""

    sets: int = 0
    """Complete sets released."""
    unmatched: int = 0
    """Messages in no set: a partner sample was missing, too far in time, or never came."""
    nonfinite: int = 0
    """Messages with a NaN or infinite reading."""
    duplicate: int = 0
    """Messages whose stamp repeats the sensor's previous one."""
    out_of_order: int = 0
    """Messages whose stamp is older than the sensor's previous one."""
    zero_stamp: int = 0
    """Messages with header stamp 0 (the driver never stamped them)."""
    malformed: int = 0
    """Messages that could not be decoded (live nodes only; a bag refuses them)."""
    restarts: int = 0
    """Stamps jumped back by more than a second: the source restarted, queues were reset."""
    negative_stamp: int = 0
    """Messages with a negative header stamp (before 1970: a clock or driver fault)."""
    out_of_range: int = 0
    """Messages with a finite reading beyond :data:`~magcal_ros.core.units.MAX_READING` (T)."""

    def dropped(self) -> int:
        """Messages dropped for any reason."""
        return sum(v for k, v in self.as_dict().items() if k not in ("sets", "restarts"))

    def count(self, fault: str, n: int = 1) -> None:
        """Add ``n`` messages to the counter ``fault`` (a name of :mod:`magcal_ros.core.acceptance`)."""
        setattr(self, fault, getattr(self, fault) + n)

    def as_dict(self) -> dict[str, int]:
        """Counters by name."""
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}

    def describe(self) -> str:
        """One line for users: sets, then each non-zero drop count in words."""
        parts = [f"{self.sets} sets"]
        for name, value in self.as_dict().items():
            if name != "sets" and value:
                parts.append(f"{value} {_PHRASES[name]}")
        return ", ".join(parts)


_PHRASES = {
    "unmatched": "messages without a complete set dropped",
    "nonfinite": "messages with NaN/inf readings dropped",
    "duplicate": "repeated stamps dropped",
    "out_of_order": "out-of-order stamps dropped",
    "zero_stamp": "zero (unset) stamps dropped",
    "malformed": "undecodable messages dropped",
    "restarts": "source restarts (stamps jumped back)",
    "negative_stamp": "negative (before 1970) stamps dropped",
    "out_of_range": "readings beyond any magnetometer's range dropped",
}


@dataclass(frozen=True)
class SyncedSet:
    """One set from the streaming path: per-sensor stamps (ns) and raw vectors (T), sensor order."""

    stamps: tuple[int, ...]
    values: tuple[Vector, ...]

    @property
    def stamp(self) -> int:
        """The set's stamp (ns): its first sensor's."""
        return self.stamps[0]


@dataclass(frozen=True)
class SetBatch:
    """Sets from the batch path, in stamp order: per-sensor stamps (N, S) ns, vectors (N, S, 3) T."""

    stamps: NDArray[np.int64]
    vectors: NDArray[np.float64]

    @property
    def set_stamps(self) -> NDArray[np.int64]:
        """The stamp of each set (its first sensor's), ns."""
        return self.stamps[:, 0]

    def __len__(self) -> int:
        return len(self.stamps)

    def take(self, keep: Any) -> "SetBatch":
        """The sets selected by ``keep`` (boolean mask or indices)."""
        return SetBatch(self.stamps[keep], self.vectors[keep])


def tolerance_ns(seconds: Any) -> int:
    """A tolerance in seconds as integer nanoseconds (``ValueError`` unless 0 <= t < 1 s)."""
    t = float(seconds)
    if not (0.0 <= t < 1.0) or not math.isfinite(t):
        raise ValueError(f"sync tolerance must be between 0 and 1 s, got {seconds!r}")
    return int(round(t * NS_PER_S))


def _median_int(values: list[int]) -> int:
    v = sorted(values)
    m = len(v) // 2
    return v[m] if len(v) % 2 else (v[m - 1] + v[m]) // 2


class SetSynchronizer:
    """Groups ``sensors`` message streams into complete sets (see the module docstring)."""

    def __init__(
        self,
        sensors: int,
        tolerance_ns: int = int(DEFAULT_SYNC_TOLERANCE * NS_PER_S),
        lag_ns: int = int(DEFAULT_LAG * NS_PER_S),
        max_pending: int = 10_000,
        restart_ns: int = int(RESTART_JUMP * NS_PER_S),
        reject_zero: bool = True,
        max_reading: float = math.inf,
    ) -> None:
        """``reject_zero``: drop stamps 0 and negative as unstamped or faulty (header stamps; a CSV's
        relative clock may start at 0). ``max_reading``: largest magnitude of a reading (T) accepted;
        real sensor data pass :data:`~magcal_ros.core.units.MAX_READING` (counted ``out_of_range``
        beyond), synthetic streams may carry any finite value."""
        if sensors < 1:
            raise ValueError("need at least one sensor")
        if tolerance_ns < 0:
            raise ValueError("tolerance must be >= 0")
        self.size = sensors
        self.tolerance_ns = int(tolerance_ns)
        self.lag_ns = int(lag_ns)
        self.max_pending = int(max_pending)
        self.restart_ns = int(restart_ns)
        self.reject_zero = reject_zero
        self.max_reading = float(max_reading)
        self.stats = SyncStats()
        self.min_period_ns: int | None = None
        """Shortest sample period estimate seen (ns), None before two stamps of a sensor."""
        self._stamps: list[list[int]] = [[] for _ in range(sensors)]
        self._caps: list[list[int]] = [[] for _ in range(sensors)]
        self._values: list[list[Vector]] = [[] for _ in range(sensors)]
        self._arrays: list[NDArray[np.float64]] = [np.empty((0, 3)) for _ in range(sensors)]
        self._head = [0] * sensors
        self._last = [_NEVER] * sensors
        self._intervals: list[list[int]] = [[] for _ in range(sensors)]
        self._periods: list[int | None] = [None] * sensors
        self._newest = _NEVER

    # -- state ------------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Messages queued, not yet in a set or dropped."""
        return sum(len(s) - h for s, h in zip(self._stamps, self._head))

    @property
    def effective_tolerance_ns(self) -> int:
        """The window actually used: the tolerance, capped at half the shortest sample period."""
        if self.min_period_ns is None:
            return self.tolerance_ns
        return min(self.tolerance_ns, self.min_period_ns // 2)

    def period_ns(self, index: int) -> int | None:
        """Sample period estimate (ns) of sensor ``index``: median of its last stamp intervals; None before two."""
        return self._periods[index]

    def reset(self) -> None:
        """Drop every queued message (counted as unmatched) and forget each sensor's history."""
        self.stats.unmatched += self.pending
        for k in range(self.size):
            self._stamps[k], self._caps[k], self._values[k] = [], [], []
            self._arrays[k] = np.empty((0, 3))
            self._head[k] = 0
            self._last[k] = _NEVER
            self._intervals[k] = []
            self._periods[k] = None
        self._newest = _NEVER

    def _period(self, index: int, interval: int) -> int:
        """Record one stamp interval of sensor ``index``; its window cap (ns)."""
        iv = self._intervals[index]
        iv.append(interval)
        if len(iv) > PERIOD_WINDOW:
            del iv[0]
        period = _median_int(iv)
        self._periods[index] = period
        if self.min_period_ns is None or period < self.min_period_ns:
            self.min_period_ns = period
        return period // 2

    # -- streaming --------------------------------------------------------------------
    def add(self, index: int, stamp_ns: int, x: float, y: float, z: float) -> SyncedSet | None:
        """Offer one message of sensor ``index``; return the set it completes, if any."""
        st = self.stats
        if stamp_ns <= 0 and self.reject_zero:
            st.count(acceptance.stamp_fault(stamp_ns))  # type: ignore[arg-type]
            return None
        last = self._last[index]
        if stamp_ns <= last:
            if last - stamp_ns > self.restart_ns:
                st.restarts += 1
                self.reset()
                last = _NEVER
            elif stamp_ns == last:
                st.duplicate += 1
                return None
            else:
                st.out_of_order += 1
                return None
        cap = _NO_CAP if last == _NEVER else self._period(index, stamp_ns - last)
        self._last[index] = stamp_ns
        if stamp_ns > self._newest:
            self._newest = stamp_ns
        fault = acceptance.reading_fault(x, y, z, self.max_reading)
        if fault is not None:
            st.count(fault)
            return None
        self._stamps[index].append(stamp_ns)
        self._caps[index].append(cap)
        self._values[index].append((x, y, z))
        formed = self._advance(final=False)
        if not formed:
            return None
        members = formed[-1]
        synced = SyncedSet(
            tuple(self._stamps[k][i] for k, i in enumerate(members)),
            tuple(self._values[k][i] for k, i in enumerate(members)),
        )
        self._compact(keep_values=True)
        return synced

    # -- batches ----------------------------------------------------------------------
    def add_batch(self, index: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64]) -> None:
        """Queue messages of sensor ``index`` in its order: stamps (n,) ns, vectors (n, 3) T."""
        s = np.asarray(stamps, dtype=np.int64)
        v = np.asarray(vectors, dtype=float).reshape(-1, 3)
        while len(s):
            s, v = self._accept_batch(index, s, v)

    def _accept_batch(self, index: int, s: NDArray[np.int64], v: NDArray[np.float64]) -> tuple[Any, Any]:
        """Accept messages up to the first restart; returns what is left after it."""
        st = self.stats
        if self.reject_zero:
            faults = acceptance.stamp_faults(s)
            for name, mask in faults.items():
                st.count(name, int(mask.sum()))
            bad = np.logical_or.reduce(list(faults.values()))
            if bad.any():
                s, v = s[~bad], v[~bad]
        if not len(s):
            return s, v
        prev = np.maximum.accumulate(np.concatenate([[self._last[index]], s[:-1]]))
        restart = np.flatnonzero(prev - s > self.restart_ns)
        rest: tuple[Any, Any] = (s[:0], v[:0])
        if len(restart):
            cut = int(restart[0])
            rest = (s[cut:], v[cut:])
            s, v, prev = s[:cut], v[:cut], prev[:cut]
        ordered = s > prev
        st.duplicate += int(np.count_nonzero(s == prev))
        st.out_of_order += int(np.count_nonzero(s < prev))
        s, v = s[ordered], v[ordered]
        if len(s):
            caps = self._batch_caps(index, s)
            self._last[index] = int(s[-1])
            self._newest = max(self._newest, int(s[-1]))
            faults = acceptance.reading_faults(v, self.max_reading)
            for name, mask in faults.items():
                st.count(name, int(mask.sum()))
            finite = ~np.logical_or.reduce(list(faults.values()))  # accepted readings
            self._stamps[index].extend(s[finite].tolist())
            self._caps[index].extend(caps[finite].tolist())
            self._arrays[index] = np.concatenate([self._arrays[index], v[finite]])
        if len(rest[0]):
            st.restarts += 1
            self.reset()
        return rest

    def _batch_caps(self, index: int, s: NDArray[np.int64]) -> NDArray[np.int64]:
        """Window caps of newly accepted stamps ``s`` (same values :meth:`add` computes)."""
        last = self._last[index]
        caps = np.full(len(s), _NO_CAP, dtype=np.int64)
        if last == _NEVER:
            first, s_iv = 1, np.diff(s)
        else:
            first, s_iv = 0, np.diff(np.concatenate([[last], s]))
        history = self._intervals[index]
        # The first few need the short history: compute them one by one, like add().
        head = min(len(s_iv), max(0, PERIOD_WINDOW - len(history)))
        for j in range(head):
            caps[first + j] = self._period(index, int(s_iv[j]))
        if head < len(s_iv):
            iv = np.concatenate([np.asarray(self._intervals[index], dtype=np.int64), s_iv[head:]])
            w = np.sort(sliding_window_view(iv, PERIOD_WINDOW)[1:], axis=1)  # windows ending at new ones
            period = (w[:, PERIOD_WINDOW // 2 - 1] + w[:, PERIOD_WINDOW // 2]) // 2
            caps[first + head :] = period // 2
            self._intervals[index] = iv[-PERIOD_WINDOW:].tolist()
            self._periods[index] = int(period[-1])
            low = int(period.min())
            if self.min_period_ns is None or low < self.min_period_ns:
                self.min_period_ns = low
        return caps

    def pop(self, final: bool = False) -> SetBatch:
        """Release the sets the queued messages decide (and drop everything left when ``final``)."""
        formed = self._advance(final)
        s = self.size
        if formed:
            idx = np.asarray(formed, dtype=np.int64).reshape(-1, s)
            stamps = np.stack([np.asarray(self._stamps[k], dtype=np.int64)[idx[:, k]] for k in range(s)], axis=1)
            vectors = np.stack([self._arrays[k][idx[:, k]] for k in range(s)], axis=1)
        else:
            stamps, vectors = np.empty((0, s), np.int64), np.empty((0, s, 3))
        self._compact(keep_values=False)
        return SetBatch(stamps, vectors)

    # -- the rule ---------------------------------------------------------------------
    def _advance(self, final: bool) -> list[tuple[int, ...]]:
        """Apply the set rule to the queues; returns the member indices of each set formed."""
        stamps, caps, head, last = self._stamps, self._caps, self._head, self._last
        tol, st = self.tolerance_ns, self.stats
        sensors = range(self.size)
        formed: list[tuple[int, ...]] = []
        while True:
            try:  # every sensor has a head: the common case, kept tight
                t = [stamps[k][head[k]] for k in sensors]
            except IndexError:
                pass
            else:
                t0 = min(t)
                if max(t) - t0 <= min(tol, min([caps[k][head[k]] for k in sensors])):
                    formed.append(tuple(head))
                    for k in sensors:
                        head[k] += 1
                else:
                    st.unmatched += 1
                    head[t.index(t0)] += 1
                continue
            avail = [k for k in sensors if head[k] < len(stamps[k])]
            if not avail:
                break
            t = [stamps[k][head[k]] for k in avail]
            t0 = min(t)
            anchor = avail[t.index(t0)]
            # A sensor has nothing queued: decide only what its next message cannot change.
            dead = any(last[k] >= t0 + tol for k in sensors if head[k] >= len(stamps[k]))
            stale = self._newest - t0 > self.lag_ns
            crowded = max(len(stamps[k]) - head[k] for k in avail) > self.max_pending
            if final or dead or stale or crowded:
                st.unmatched += 1
                head[anchor] += 1
                continue
            break
        st.sets += len(formed)
        return formed

    def _compact(self, keep_values: bool) -> None:
        """Forget consumed messages once enough have piled up."""
        for k in range(self.size):
            h = self._head[k]
            if h and (h >= 4096 or not keep_values or h == len(self._stamps[k])):
                del self._stamps[k][:h]
                del self._caps[k][:h]
                if keep_values:
                    del self._values[k][:h]
                else:
                    self._arrays[k] = self._arrays[k][h:]
                self._head[k] = 0

"""Group per-sensor samples into synchronized sets by header stamp (no ROS import).

A set is one finite sample per sensor whose stamps all lie within ``tolerance_ns`` of
each other; a sample joins the open set nearest to its stamp. Samples arrive one topic
at a time, in order within each topic; a set that can no longer complete (a sensor
moved past it, it is older than ``stale_ns``, or too many sets are open) is dropped and
counted, never mixed with another. Stamps are integer nanoseconds, so matching is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

Vector = tuple[float, float, float]


@dataclass
class SyncStats:
    """Counters of what the synchronizer did (since start or the last reset)."""

    complete: int = 0
    """Sets delivered."""
    incomplete: int = 0
    """Sets dropped because a sensor's sample never came (or was bad)."""
    bad_value: int = 0
    """Samples dropped for NaN or infinite components."""
    out_of_order: int = 0
    """Samples dropped because their stamp was not newer than the sensor's previous one."""
    duplicate: int = 0
    """Samples dropped because their stamp repeated the sensor's previous one."""
    time_jumps: int = 0
    """Times the stamps jumped back by more than ``jump_back_ns`` (source restarted): state reset."""

    def dropped_samples(self) -> int:
        """Samples dropped before they could join a set."""
        return self.bad_value + self.out_of_order + self.duplicate

    def as_dict(self) -> dict[str, int]:
        """Counters by name."""
        return dict(self.__dict__)


@dataclass
class _Slot:
    lo: int
    hi: int
    stamps: list[int]
    values: list[Vector | None]
    filled: int = 0


@dataclass(frozen=True)
class SyncedSet:
    """One synchronized set: per-sensor stamps (ns) and raw vectors (T), sensor order."""

    stamps: tuple[int, ...]
    values: tuple[Vector, ...]

    @property
    def stamp(self) -> int:
        """The set's stamp (ns): the first sensor's."""
        return self.stamps[0]


@dataclass
class SetSynchronizer:
    """Synchronizer for ``size`` sensors (indices 0..size-1)."""

    size: int
    tolerance_ns: int
    max_pending: int = 50
    """Most open (incomplete) sets kept; the oldest is dropped beyond this."""
    stale_ns: int = 1_000_000_000
    """Open sets older than this behind the newest stamp are dropped."""
    jump_back_ns: int = 1_000_000_000
    """A stamp this far behind a sensor's previous one means the source restarted."""
    stats: SyncStats = field(default_factory=SyncStats)

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError("need at least one sensor")
        if self.tolerance_ns < 0:
            raise ValueError("tolerance must be >= 0")
        self._pending: list[_Slot] = []
        self._last: list[int] = [-(2**62)] * self.size

    @property
    def pending(self) -> int:
        """Open (incomplete) sets."""
        return len(self._pending)

    def reset(self) -> None:
        """Forget open sets and per-sensor history (counters are kept)."""
        self.stats.incomplete += len(self._pending)
        self._pending.clear()
        self._last = [-(2**62)] * self.size

    def add(self, index: int, stamp_ns: int, x: float, y: float, z: float) -> SyncedSet | None:
        """Offer one sample of sensor ``index``; return the set it completes, if any."""
        last = self._last[index]
        if stamp_ns <= last:
            if last - stamp_ns > self.jump_back_ns:
                self.stats.time_jumps += 1
                self.reset()
            else:
                if stamp_ns == last:
                    self.stats.duplicate += 1
                else:
                    self.stats.out_of_order += 1
                return None
        self._last[index] = stamp_ns
        self._expire(index, stamp_ns)
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            self.stats.bad_value += 1
            return None
        pending = self._pending
        tol = self.tolerance_ns
        best, best_gap = -1, tol + 1
        for k in range(len(pending) - 1, -1, -1):
            slot = pending[k]
            if slot.values[index] is not None:
                continue
            lo = slot.lo if slot.lo < stamp_ns else stamp_ns
            hi = slot.hi if slot.hi > stamp_ns else stamp_ns
            gap = abs(stamp_ns - slot.lo)
            if hi - lo <= tol and gap < best_gap:
                best, best_gap = k, gap
                if gap == 0:
                    break
        if best >= 0:
            k, slot = best, pending[best]
            slot.lo = slot.lo if slot.lo < stamp_ns else stamp_ns
            slot.hi = slot.hi if slot.hi > stamp_ns else stamp_ns
            slot.values[index] = (x, y, z)
            slot.stamps[index] = stamp_ns
            slot.filled += 1
            if slot.filled < self.size:
                return None
            # Older open sets can no longer be delivered in order: drop them.
            self.stats.incomplete += k
            del pending[: k + 1]
            self.stats.complete += 1
            return SyncedSet(tuple(slot.stamps), tuple(slot.values))  # type: ignore[arg-type]
        slot = _Slot(stamp_ns, stamp_ns, [0] * self.size, [None] * self.size, 1)
        slot.values[index] = (x, y, z)
        slot.stamps[index] = stamp_ns
        if self.size == 1:
            self.stats.complete += 1
            return SyncedSet((stamp_ns,), ((x, y, z),))
        pending.append(slot)
        if len(pending) > self.max_pending:
            pending.pop(0)
            self.stats.incomplete += 1
        return None

    def _expire(self, index: int, stamp_ns: int) -> None:
        """Drop open sets at the head that sensor ``index`` moved past, or that went stale."""
        pending = self._pending
        while pending:
            head = pending[0]
            passed = head.values[index] is None and stamp_ns > head.lo + self.tolerance_ns
            if passed or stamp_ns - head.hi > self.stale_ns:
                pending.pop(0)
                self.stats.incomplete += 1
            else:
                break

"""Streaming synchronisation of per-sensor messages into sets, vectorised with numpy.

A set is one message per sensor whose header stamps all lie within ``tolerance`` of each
other; its stamp is the first sensor's. Each message joins at most one set (the nearest
first-sensor message); messages that end up in no complete set are dropped and counted,
never mixed. Messages are fed in chunks as they come out of a bag; sets are released once no
later message can still complete them, so memory stays bounded by the chunk size plus
``lag`` seconds of data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

NS_PER_S = 1_000_000_000
_FAR = 2**62


@dataclass
class SyncStats:
    """Counters of a synchronisation run."""

    sets: int = 0
    """Complete sets released."""
    dropped_messages: int = 0
    """Messages that ended up in no complete set (incomplete sets, duplicates)."""
    nonfinite_sets: int = 0
    """Complete sets dropped because a reading was NaN or infinite."""

    def describe(self) -> str:
        """One line for users."""
        parts = [f"{self.sets} sets"]
        if self.dropped_messages:
            parts.append(f"{self.dropped_messages} messages without a complete set dropped")
        if self.nonfinite_sets:
            parts.append(f"{self.nonfinite_sets} sets with NaN/inf readings dropped")
        return ", ".join(parts)


@dataclass(frozen=True)
class SetBatch:
    """Complete sets in stamp order: per-sensor stamps (N, S) ns and vectors (N, S, 3) T."""

    stamps: NDArray[np.int64]
    vectors: NDArray[np.float64]

    @property
    def set_stamps(self) -> NDArray[np.int64]:
        """The stamp of each set (first sensor's header stamp), ns."""
        return self.stamps[:, 0]

    def __len__(self) -> int:
        return len(self.stamps)

    def take(self, keep: NDArray[np.bool_]) -> "SetBatch":
        """The sets where ``keep`` is true."""
        return SetBatch(self.stamps[keep], self.vectors[keep])


class SetSynchronizer:
    """Group per-sensor (stamp, vector) streams into complete sets."""

    def __init__(self, sensors: int, tolerance: float = 0.0, lag: float = 1.0) -> None:
        """``tolerance`` (s): largest stamp difference within a set; ``lag`` (s): reordering allowed."""
        if sensors < 1:
            raise ValueError("need at least one sensor")
        self.count = sensors
        self.tol = int(round(max(0.0, tolerance) * NS_PER_S))
        self.lag = int(round(max(0.0, lag) * NS_PER_S))
        self.stats = SyncStats()
        self._stamps: list[NDArray[np.int64]] = [np.empty(0, np.int64) for _ in range(sensors)]
        self._vectors: list[NDArray[np.float64]] = [np.empty((0, 3)) for _ in range(sensors)]
        self._latest = np.full(sensors, -_FAR, dtype=np.int64)

    def add(self, sensor: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64]) -> None:
        """Queue messages of ``sensor``: stamps (n,) ns, vectors (n, 3) T."""
        if len(stamps) == 0:
            return
        self._stamps[sensor] = np.concatenate([self._stamps[sensor], stamps])
        self._vectors[sensor] = np.concatenate([self._vectors[sensor], vectors])
        self._latest[sensor] = max(int(self._latest[sensor]), int(stamps.max()))

    def pending(self) -> int:
        """Messages queued and not yet released or dropped."""
        return sum(len(s) for s in self._stamps)

    def pop(self, final: bool = False) -> SetBatch:
        """Release the sets no later message can change (all of them when ``final``)."""
        cutoff = _FAR if final else int(self._latest.min()) - self.tol - self.lag
        for k in range(self.count):
            s = self._stamps[k]
            if len(s) > 1 and np.any(s[1:] < s[:-1]):
                order = np.argsort(s, kind="stable")
                self._stamps[k], self._vectors[k] = s[order], self._vectors[k][order]
        ref = self._stamps[0]
        m = int(np.searchsorted(ref, cutoff, side="left"))
        r = ref[:m]
        idx = np.zeros((m, self.count), dtype=np.int64)
        idx[:, 0] = np.arange(m)
        ok = np.ones(m, dtype=bool)
        for k in range(1, self.count):
            best, good = self._match(r, self._stamps[k])
            idx[:, k] = best
            ok &= good
        # All stamps of a set within the tolerance of each other, not only of the reference.
        cand = np.flatnonzero(ok)
        if len(cand) and self.count > 1:
            st = np.stack([self._stamps[k][idx[cand, k]] for k in range(self.count)], axis=1)
            ok[cand[st.max(axis=1) - st.min(axis=1) > self.tol]] = False
        used = idx[ok]
        batch = SetBatch(
            np.stack([self._stamps[k][used[:, k]] for k in range(self.count)], axis=1),
            np.stack([self._vectors[k][used[:, k]] for k in range(self.count)], axis=1),
        )
        # Forget released references, matched partners, and partners too old to match later.
        self.stats.dropped_messages += m - len(used)
        self._stamps[0], self._vectors[0] = ref[m:], self._vectors[0][m:]
        horizon = cutoff - self.tol if not final else _FAR
        for k in range(1, self.count):
            s = self._stamps[k]
            keep = np.ones(len(s), dtype=bool)
            keep[used[:, k]] = False
            stale = keep & (s < horizon)
            self.stats.dropped_messages += int(stale.sum())
            keep &= ~stale
            self._stamps[k], self._vectors[k] = s[keep], self._vectors[k][keep]
        self.stats.sets += len(batch)
        return batch

    def _match(self, ref: NDArray[np.int64], s: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Nearest message of ``s`` for each reference stamp; each message used at most once."""
        m = len(ref)
        if len(s) == 0 or m == 0:
            return np.zeros(m, np.int64), np.zeros(m, bool)
        j = np.searchsorted(s, ref)
        left = np.clip(j - 1, 0, len(s) - 1)
        right = np.clip(j, 0, len(s) - 1)
        dl = np.abs(ref - s[left])
        dr = np.abs(s[right] - ref)
        best = np.where(dr < dl, right, left)
        dist = np.minimum(dl, dr)
        good = dist <= self.tol
        # A message claimed by several references goes to the closest one.
        cand = np.flatnonzero(good)
        if len(cand) > 1:
            order = cand[np.lexsort((dist[cand], best[cand]))]
            first = np.ones(len(order), dtype=bool)
            first[1:] = best[order[1:]] != best[order[:-1]]
            good[order[~first]] = False
        return best, good


def drop_nonfinite(batch: SetBatch, stats: SyncStats) -> SetBatch:
    """``batch`` without sets holding NaN or infinite readings (counted in ``stats``)."""
    finite = np.all(np.isfinite(batch.vectors), axis=(1, 2))
    if np.all(finite):
        return batch
    stats.nonfinite_sets += int((~finite).sum())
    stats.sets -= int((~finite).sum())
    return batch.take(finite)

"""Bounded stores of synchronized raw sets (no ROS import): :class:`SetBuffer` keeps a spread of
attitudes for a calibration manoeuvre, :class:`MissionWindow` the latest seconds of a mission.

:class:`SetBuffer` files each set under the sphere cell (one of :data:`CELLS` roughly uniform
directions) nearest to the direction of its array-centre raw reading, which is the field
direction in the array frame and so a proxy for the attitude. Below ``capacity`` every
set is kept; when full, a new set replaces a random set of the most crowded cell (its
own cell if that is the most crowded), so a long stationary stretch cannot push out the
rare attitudes a calibration needs.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.observability import SPHERE_CELLS, sphere_cells
from magcal_ros.core.recording import ImuSamples, Recording

CELLS: int = SPHERE_CELLS


class SetBuffer:
    """Up to ``capacity`` raw sets (S, 3) in T with their stamps (ns), the currents (A) of
    ``channels`` interference channels, the sensors' temperatures (deg C) and the IMU (orientation
    x, y, z, w to ENU and angular velocity rad/s) at each set; NaN where a set has none."""

    def __init__(self, capacity: int, sensors: int, seed: int | None = 0, channels: int = 0) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = capacity
        self.sensors = sensors
        self._raw = np.empty((capacity, sensors, 3))
        self._currents = np.zeros((capacity, channels))
        self._temperatures = np.full((capacity, sensors), np.nan)
        self._imu = np.full((capacity, 7), np.nan)
        self._stamps = np.zeros(capacity, dtype=np.int64)
        self._cells = np.zeros(capacity, dtype=np.int64)
        self._counts = np.zeros(CELLS, dtype=np.int64)
        self._dirs = sphere_cells(CELLS)
        self._rng = np.random.default_rng(seed)
        self._size = 0
        self.offered = 0
        """Sets offered since the last clear (kept or not)."""

    def __len__(self) -> int:
        return self._size

    def clear(self) -> None:
        """Forget every set."""
        self._size = 0
        self._counts[:] = 0
        self.offered = 0

    def add(self, stamp_ns: int, values: tuple[tuple[float, float, float], ...], currents: Sequence[float] = (),
            temperatures: Sequence[float] | None = None, imu: Sequence[float] | None = None) -> None:
        """Store one set (S raw vectors, T; the channels' currents, A; the sensors' temperatures, deg C; the IMU's
        orientation and angular velocity, 7 numbers), replacing a crowded one when full."""
        raw = np.asarray(values, dtype=float)
        cell = int(np.argmax(self._dirs @ raw.sum(axis=0)))
        self.offered += 1
        if self._size < self.capacity:
            slot = self._size
            self._size += 1
        else:
            target = int(np.argmax(self._counts))
            if self._counts[cell] >= self._counts[target]:
                target = cell
            members = np.flatnonzero(self._cells[: self._size] == target)
            slot = int(members[self._rng.integers(len(members))])
            self._counts[target] -= 1
        self._raw[slot] = raw
        self._currents[slot] = currents
        self._temperatures[slot] = np.nan if temperatures is None else temperatures
        self._imu[slot] = np.nan if imu is None else imu
        self._stamps[slot] = stamp_ns
        self._cells[slot] = cell
        self._counts[cell] += 1

    def snapshot(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Copies of the stored stamps (N,) ns and raw sets (N, S, 3) T, in stamp order."""
        stamps, raw, _ = self.snapshot_all()
        return stamps, raw

    def snapshot_all(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Copies of the stored stamps (N,) ns, raw sets (N, S, 3) T and currents (N, m) A, in stamp order."""
        order = np.argsort(self._stamps[: self._size], kind="stable")
        return self._stamps[order].copy(), self._raw[order].copy(), self._currents[order].copy()

    def collected(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
                                 NDArray[np.float64]]:
        """Copies, in stamp order, of the stamps (N,) ns, raw sets (N, S, 3) T, currents (N, m) A, temperatures
        (N, S) deg C and IMU (N, 7): orientation x, y, z, w and angular velocity rad/s (NaN: none at that set)."""
        order = np.argsort(self._stamps[: self._size], kind="stable")
        return (self._stamps[order].copy(), self._raw[order].copy(), self._currents[order].copy(),
                self._temperatures[order].copy(), self._imu[order].copy())

    def restore(self, stamps: NDArray[np.int64], raw: NDArray[np.float64], currents: NDArray[np.float64],
                temperatures: NDArray[np.float64], imu: NDArray[np.float64]) -> None:
        """Hold exactly these sets, as :meth:`collected` gave them (stamps (N,) ns, raw (N, S, 3) T, currents (N, m)
        A, temperatures (N, S) deg C, IMU (N, 7)), and no other: sets added since are forgotten."""
        n = len(stamps)
        if n > self.capacity:
            raise ValueError(f"{n} sets do not fit in {self.capacity}")
        self._stamps[:n], self._raw[:n], self._currents[:n] = stamps, raw, currents
        self._temperatures[:n], self._imu[:n] = temperatures, imu
        self._cells[:n] = np.argmax(raw.sum(axis=1) @ self._dirs.T, axis=1) if n else 0
        self._counts[:] = np.bincount(self._cells[:n], minlength=CELLS)
        self._size = n

    @property
    def cells_visited(self) -> int:
        """Number of sphere cells holding at least one set."""
        return int(np.count_nonzero(self._counts))


def collected_recording(names: Sequence[str], channels: Sequence[str], stamps: NDArray[np.int64],
                        raw: NDArray[np.float64], currents: NDArray[np.float64], temperatures: NDArray[np.float64],
                        imu: NDArray[np.float64], imu_frame_id: str = "") -> tuple[Recording, list[str]]:
    """The collected sets (see :meth:`SetBuffer.collected`) as a :class:`Recording`, and notes for users.

    The temperatures and the IMU come with the sets when any set has them: then sets collected
    without them (before the first temperature or IMU sample arrived) are left out, and a note
    says how many; when no set has them, the recording has none.
    """
    rec = Recording(tuple(names), stamps, raw, tuple(channels), currents)
    notes = []
    have_t = np.all(np.isfinite(temperatures), axis=1)
    if np.any(have_t):
        if not np.all(have_t):
            notes.append(f"{int(np.sum(~have_t))} sets collected before every sensor's temperature arrived left out")
        rec = rec.take(have_t).with_temperatures(temperatures[have_t])
        imu = imu[have_t]
    have_imu = np.any(np.isfinite(imu), axis=1)
    if np.any(have_imu):
        if not np.all(have_imu):
            notes.append(f"{int(np.sum(~have_imu))} sets collected before the IMU arrived left out")
        rec = rec.take(have_imu).with_imu(ImuSamples(imu[have_imu, :4], imu[have_imu, 4:], imu_frame_id))
    return rec, notes


IMU_SHARE: float = 0.5
"""A mission window's sets go to a recalibration with the IMU when at least this share of them has its attitude
(those without are then left out); below it, all of them without the IMU."""


class MissionSets(NamedTuple):
    """Sets of a mission window: stamps (N,) ns, raw sets (N, S, 3) T, currents (N, m) A, each sensor's
    temperature (N, S) deg C (None: not heard) and the IMU at each set (N, 7): orientation x, y, z, w IMU frame
    to world ENU and angular velocity rad/s IMU frame, NaN where the IMU gave none (None: no IMU)."""

    stamps: NDArray[np.int64]
    raw: NDArray[np.float64]
    currents: NDArray[np.float64]
    temperatures: NDArray[np.float64] | None = None
    imu: NDArray[np.float64] | None = None

    def take(self, keep: NDArray[np.bool_]) -> "MissionSets":
        """The sets selected by ``keep`` (boolean mask)."""
        t = None if self.temperatures is None else self.temperatures[keep]
        imu = None if self.imu is None else self.imu[keep]
        return MissionSets(self.stamps[keep], self.raw[keep], self.currents[keep], t, imu)

    def recording(self, names: Sequence[str], channels: Sequence[str], imu_frame_id: str = "") -> Recording:
        """These sets as a :class:`Recording` (:func:`collected_recording`: with their temperatures and IMU when
        they have them)."""
        n, sensors = self.raw.shape[:2]
        temperatures = np.full((n, sensors), np.nan) if self.temperatures is None else self.temperatures
        imu = np.full((n, 7), np.nan) if self.imu is None else self.imu
        rec, _ = collected_recording(names, channels, self.stamps, self.raw, self.currents, temperatures, imu,
                                     imu_frame_id)
        return rec


_MissionSet = tuple[int, tuple[tuple[float, float, float], ...], tuple[float, ...], tuple[float, ...] | None,
                    tuple[float, ...] | None]
"""stamp ns, raw vectors T, currents A, temperatures deg C or None, IMU (7 numbers) or None."""


class MissionWindow:
    """The latest ``seconds_ns`` of a mission's synchronized raw sets (with their currents, temperatures and the
    IMU's attitude), at most one set every ``spacing_ns`` (a set closer than that to the last one kept is
    skipped), so that a long window at a high rate stays small: per set S x 3 readings, m currents, S
    temperatures and 7 numbers of attitude."""

    def __init__(self, seconds_ns: int, spacing_ns: int, sensors: int, channels: int = 0) -> None:
        self.seconds_ns = max(int(seconds_ns), 1)
        self.spacing_ns = max(int(spacing_ns), 0)
        self.sensors = sensors
        self.channels = channels
        self._sets: deque[_MissionSet] = deque()
        self._next = -(2**62)
        self.newest = 0
        """Stamp (ns) of the newest set seen (kept or not): the mission's time."""

    def __len__(self) -> int:
        return len(self._sets)

    def due(self, stamp_ns: int) -> bool:
        """Whether a set stamped ``stamp_ns`` would be kept (the caller then fetches its currents). A stamp
        more than the window before the newest means the source restarted: a new mission, the window
        starts again."""
        if stamp_ns < self.newest - self.seconds_ns:
            self.clear()
            self.newest = stamp_ns
        elif stamp_ns > self.newest:
            self.newest = stamp_ns
        return stamp_ns >= self._next

    def add(self, stamp_ns: int, values: tuple[tuple[float, float, float], ...], currents: Sequence[float] = (),
            temperatures: Sequence[float] | None = None, imu: Sequence[float] | None = None) -> None:
        """Keep one set (S raw vectors, T; the channels' currents, A; each sensor's temperature, deg C, or None;
        the IMU's orientation x, y, z, w to ENU and angular velocity rad/s, IMU frame, or None) if :meth:`due`;
        forget sets older than the window."""
        if not self.due(stamp_ns):
            return
        self._sets.append((stamp_ns, tuple(values), tuple(currents),
                           None if temperatures is None else tuple(temperatures),
                           None if imu is None else tuple(float(x) for x in imu)))
        self._next = stamp_ns + self.spacing_ns
        self.newest = max(self.newest, stamp_ns)
        first = stamp_ns - self.seconds_ns
        while self._sets and self._sets[0][0] < first:
            self._sets.popleft()

    def clear(self) -> None:
        """Forget every set."""
        self._sets.clear()
        self._next = -(2**62)

    def snapshot(self, since_ns: int | None = None) -> MissionSets:
        """The sets stamped ``since_ns`` or later; temperatures where every one of them has its sensors'
        (sets kept before the temperatures were first heard are left out then), None where none has.

        The IMU: when at least :data:`IMU_SHARE` of those sets have its attitude, the sets without one (kept
        before the IMU was first heard, or while it was stale) are left out and every set left has it;
        otherwise the IMU is None (too few attitudes to fit its blocks: a recalibration without it, which
        keeps the running output frame)."""
        rows = [s for s in self._sets if since_ns is None or s[0] >= since_ns]
        if any(r[3] is not None for r in rows):
            rows = [r for r in rows if r[3] is not None]
        with_imu = [r for r in rows if r[4] is not None]
        attitudes = bool(with_imu) and len(with_imu) >= IMU_SHARE * len(rows)
        if attitudes:
            rows = with_imu
        stamps = np.array([r[0] for r in rows], dtype=np.int64)
        raw = np.array([r[1] for r in rows], dtype=float).reshape(len(rows), self.sensors, 3)
        currents = np.array([r[2] for r in rows], dtype=float).reshape(len(rows), self.channels)
        heard = bool(rows) and rows[0][3] is not None
        temperatures = np.array([r[3] for r in rows], dtype=float).reshape(len(rows), self.sensors) if heard else None
        imu = np.array([r[4] for r in rows], dtype=float).reshape(len(rows), 7) if attitudes else None
        return MissionSets(stamps, raw, currents, temperatures, imu)

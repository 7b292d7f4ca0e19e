"""The one data type that flows from every source to every sink: synchronized raw sets
(and, when recorded, the currents of the interference channels, the sensors' temperatures
and the IMU at each set)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcal_ros.errors import InputError

Array = NDArray[np.float64]


QUATERNION_TOLERANCE: float = 1e-3
"""Largest accepted departure of a known orientation quaternion's norm from 1 (it is then normalised)."""


@dataclass(frozen=True)
class ImuSamples:
    """The IMU at each set: what ``sensor_msgs/Imu`` says, matched to the set instants.

    ``orientation`` (N, 4) quaternions ``x, y, z, w`` of the rotation from the IMU frame to
    the world frame ENU (REP 103/145: the vector ``v_world = R(q) v_imu``); a row of NaN
    where the orientation is unknown (an IMU that gives none, or none near the set).
    ``angular_velocity`` (N, 3) rad/s in the IMU frame; a row of NaN where unknown.
    ``frame_id``: the IMU's frame (the output frame of a calibration made with it; ``""``
    when the source does not say, e.g. a CSV file).
    """

    orientation: Array
    angular_velocity: Array
    frame_id: str = ""

    def __post_init__(self) -> None:
        q = np.array(self.orientation, dtype=float).reshape(-1, 4)
        w = np.array(self.angular_velocity, dtype=float).reshape(-1, 3)
        if len(q) != len(w):
            raise InputError(f"IMU needs one orientation and one angular velocity per set, got {len(q)} and {len(w)}")
        unknown = ~np.all(np.isfinite(q), axis=1)
        q[unknown] = np.nan
        norm = np.linalg.norm(q[~unknown], axis=1)
        if np.any(np.abs(norm - 1.0) > QUATERNION_TOLERANCE):
            bad = int(np.flatnonzero(~unknown)[np.argmax(np.abs(norm - 1.0))])
            raise InputError(f"IMU orientation of set {bad} is not a unit quaternion (norm {float(np.linalg.norm(q[bad])):.6g})")
        rows = np.flatnonzero(~unknown)[np.abs(norm - 1.0) > 1e-12]  # a unit quaternion stays bit for bit
        q[rows] /= np.linalg.norm(q[rows], axis=1, keepdims=True)
        w[~np.all(np.isfinite(w), axis=1)] = np.nan
        object.__setattr__(self, "orientation", q)
        object.__setattr__(self, "angular_velocity", w)
        object.__setattr__(self, "frame_id", str(self.frame_id or ""))

    def __len__(self) -> int:
        return len(self.orientation)

    @property
    def has_orientation(self) -> bool:
        """True when any set has a known orientation."""
        return bool(np.any(np.isfinite(self.orientation[:, 0])))

    @property
    def has_angular_velocity(self) -> bool:
        """True when any set has a known angular velocity."""
        return bool(np.any(np.isfinite(self.angular_velocity[:, 0])))

    def take(self, keep: NDArray[np.bool_] | NDArray[np.int64]) -> "ImuSamples":
        """The sets selected by a mask or index array."""
        return ImuSamples(self.orientation[keep], self.angular_velocity[keep], self.frame_id)

    @classmethod
    def unknown(cls, count: int, frame_id: str = "") -> "ImuSamples":
        """``count`` sets with neither orientation nor angular velocity known."""
        return cls(np.full((count, 4), np.nan), np.full((count, 3), np.nan), frame_id)


@dataclass(frozen=True)
class Recording:
    """Synchronized sets: ``stamps`` (N,) int64 ns, ``vectors`` (N, S, 3) T, sensor ``names`` (S).

    ``stamps`` are the sets' header stamps in integer nanoseconds, exactly as recorded.
    ``vectors`` are in each sensor's own axes (raw) or in the platform frame (corrected).
    ``currents`` (N, m) are the currents (A) of the interference ``channels`` (m names,
    e.g. thrusters) at each set; none by default. ``temperatures`` (N, S) are each sensor's
    temperature (deg C) at each set, ``imu`` the IMU at each set (:class:`ImuSamples`); None
    when not recorded. Every selection (:meth:`select`, :meth:`take`, :meth:`window`,
    :meth:`with_currents`) keeps them with their sets.
    """

    names: tuple[str, ...]
    stamps: NDArray[np.int64]
    vectors: Array
    channels: tuple[str, ...] = ()
    currents: Array | None = None
    """(N, len(channels)) A; None or omitted: no channels."""
    temperatures: Array | None = None
    """(N, S) deg C, finite; None: not recorded."""
    imu: ImuSamples | None = None
    """The IMU at each set; None: no IMU."""

    def __post_init__(self) -> None:
        v = np.asarray(self.vectors, dtype=float)
        t = np.asarray(self.stamps)
        if t.dtype.kind not in "iu":
            raise InputError(f"recording stamps must be integer nanoseconds, got dtype {t.dtype}")
        t = t.astype(np.int64).reshape(-1)
        if v.ndim != 3 or v.shape[1:] != (len(self.names), 3) or len(t) != len(v):
            raise InputError(
                f"recording needs stamps (N,) and vectors (N, {len(self.names)}, 3), got {t.shape} and {v.shape}"
            )
        channels = tuple(str(c) for c in self.channels)
        u = np.zeros((len(t), 0)) if self.currents is None else np.asarray(self.currents, dtype=float)
        if u.ndim == 1 and len(channels) == 1:
            u = u[:, None]
        if u.shape != (len(t), len(channels)):
            raise InputError(f"recording needs currents (N, {len(channels)}) for channels {list(channels)}, got {u.shape}")
        if len(set(channels)) != len(channels) or not all(channels):
            raise InputError(f"current channel names must be unique and non-empty, got {list(channels)}")
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "stamps", t)
        object.__setattr__(self, "vectors", v)
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "currents", u)
        if self.temperatures is not None:
            temp = np.asarray(self.temperatures, dtype=float)
            if temp.ndim == 1 and len(self.names) == 1:
                temp = temp[:, None]
            if temp.shape != (len(t), len(self.names)) or not np.all(np.isfinite(temp)):
                raise InputError(f"recording needs finite temperatures (N, {len(self.names)}) deg C, got {temp.shape}")
            object.__setattr__(self, "temperatures", temp)
        if self.imu is not None and len(self.imu) != len(t):
            raise InputError(f"recording has {len(t)} sets but the IMU {len(self.imu)}")

    def __len__(self) -> int:
        return len(self.stamps)

    def select(self, names: tuple[str, ...] | list[str]) -> "Recording":
        """The same sets restricted to (and ordered as) ``names``."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise InputError(f"recording has no sensor {', '.join(missing)} (it has {', '.join(self.names)})")
        idx = [self.names.index(n) for n in names]
        temperatures = None if self.temperatures is None else self.temperatures[:, idx]
        return replace(self, names=tuple(names), vectors=self.vectors[:, idx], temperatures=temperatures)

    def select_channels(self, channels: tuple[str, ...] | list[str]) -> "Recording":
        """The same sets with only the current ``channels`` (in that order)."""
        missing = [c for c in channels if c not in self.channels]
        if missing:
            have = ", ".join(self.channels) or "none"
            raise InputError(f"recording has no current of channel {', '.join(missing)} (it has {have})")
        idx = [self.channels.index(c) for c in channels]
        return replace(self, channels=tuple(channels), currents=self.currents[:, idx])  # type: ignore[index]

    def with_currents(self, channels: tuple[str, ...] | list[str], currents: Array) -> "Recording":
        """The same sets with ``currents`` (N, m) A of ``channels`` instead of the present ones."""
        return replace(self, channels=tuple(channels), currents=currents)

    def with_temperatures(self, temperatures: Array | None) -> "Recording":
        """The same sets with each sensor's temperature (N, S) deg C (None: none)."""
        return replace(self, temperatures=temperatures)

    def with_imu(self, imu: ImuSamples | None) -> "Recording":
        """The same sets with the IMU at each set (None: none)."""
        return replace(self, imu=imu)

    def window(self, start_ns: int | None = None, end_ns: int | None = None) -> "Recording":
        """Sets with ``start_ns <= stamp <= end_ns`` (either bound optional)."""
        keep = np.ones(len(self), bool)
        if start_ns is not None:
            keep &= self.stamps >= start_ns
        if end_ns is not None:
            keep &= self.stamps <= end_ns
        return self.take(keep)

    def take(self, keep: NDArray[np.bool_] | NDArray[np.int64]) -> "Recording":
        """The sets selected by a mask or index array."""
        return replace(
            self, stamps=self.stamps[keep], vectors=self.vectors[keep], currents=self.currents[keep],  # type: ignore[index]
            temperatures=None if self.temperatures is None else self.temperatures[keep],
            imu=None if self.imu is None else self.imu.take(keep),
        )

"""The one data type that flows from every source to every sink: synchronized raw sets
(and the currents of the interference channels at each set, when recorded)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.errors import InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Recording:
    """Synchronized sets: ``stamps`` (N,) int64 ns, ``vectors`` (N, S, 3) T, sensor ``names`` (S).

    ``stamps`` are the sets' header stamps in integer nanoseconds, exactly as recorded.
    ``vectors`` are in each sensor's own axes (raw) or in the platform frame (corrected).
    ``currents`` (N, m) are the currents (A) of the interference ``channels`` (m names,
    e.g. thrusters) at each set; none by default.
    """

    names: tuple[str, ...]
    stamps: NDArray[np.int64]
    vectors: Array
    channels: tuple[str, ...] = ()
    currents: Array | None = None
    """(N, len(channels)) A; None or omitted: no channels."""

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

    def __len__(self) -> int:
        return len(self.stamps)

    def select(self, names: tuple[str, ...] | list[str]) -> "Recording":
        """The same sets restricted to (and ordered as) ``names``."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise InputError(f"recording has no sensor {', '.join(missing)} (it has {', '.join(self.names)})")
        idx = [self.names.index(n) for n in names]
        return Recording(tuple(names), self.stamps, self.vectors[:, idx], self.channels, self.currents)

    def select_channels(self, channels: tuple[str, ...] | list[str]) -> "Recording":
        """The same sets with only the current ``channels`` (in that order)."""
        missing = [c for c in channels if c not in self.channels]
        if missing:
            have = ", ".join(self.channels) or "none"
            raise InputError(f"recording has no current of channel {', '.join(missing)} (it has {have})")
        idx = [self.channels.index(c) for c in channels]
        return Recording(self.names, self.stamps, self.vectors, tuple(channels), self.currents[:, idx])  # type: ignore[index]

    def with_currents(self, channels: tuple[str, ...] | list[str], currents: Array) -> "Recording":
        """The same sets with ``currents`` (N, m) A of ``channels`` instead of the present ones."""
        return Recording(self.names, self.stamps, self.vectors, tuple(channels), currents)

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
        return Recording(self.names, self.stamps[keep], self.vectors[keep], self.channels, self.currents[keep])  # type: ignore[index]

"""The one data type that flows from every source to every sink: synchronized raw sets."""

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
    """

    names: tuple[str, ...]
    stamps: NDArray[np.int64]
    vectors: Array

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
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "stamps", t)
        object.__setattr__(self, "vectors", v)

    def __len__(self) -> int:
        return len(self.stamps)

    def select(self, names: tuple[str, ...] | list[str]) -> "Recording":
        """The same sets restricted to (and ordered as) ``names``."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise InputError(f"recording has no sensor {', '.join(missing)} (it has {', '.join(self.names)})")
        idx = [self.names.index(n) for n in names]
        return Recording(tuple(names), self.stamps, self.vectors[:, idx])

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
        return Recording(self.names, self.stamps[keep], self.vectors[keep])

"""What a single message must be to be used at all: a stamp after 1970 and a physical reading.

One rule for bags, CSV and the live nodes, applied by the synchronizer's acceptance step
(:mod:`magcal_ros.core.sync`). Each fault has the name of the :class:`~magcal_ros.core.sync.SyncStats`
counter that counts it:

- ``zero_stamp``: header stamp 0 (the driver never stamped the message);
- ``negative_stamp``: header stamp before 1970 (``sec < 0``: a clock or driver fault);
- ``nonfinite``: a NaN or infinite component;
- ``out_of_range``: a finite reading whose magnitude exceeds
  :data:`~magcal_ros.core.units.MAX_READING` (T): no magnetometer reads that in the Earth's field.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.units import MAX_READING

STAMP_FAULTS: tuple[str, ...] = ("zero_stamp", "negative_stamp")
READING_FAULTS: tuple[str, ...] = ("nonfinite", "out_of_range")


def stamp_fault(stamp_ns: int) -> str | None:
    """The fault of a header stamp (ns), or None when it is after 1970."""
    if stamp_ns > 0:
        return None
    return "zero_stamp" if stamp_ns == 0 else "negative_stamp"


def reading_fault(x: float, y: float, z: float, limit: float = MAX_READING) -> str | None:
    """The fault of one reading (T), or None when it is finite and at most ``limit`` in magnitude."""
    m = x * x + y * y + z * z
    if m <= limit * limit and m != math.inf:  # the common case; False for NaN and inf
        return None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return "nonfinite"
    return "out_of_range" if math.hypot(x, y, z) > limit else None


def stamp_faults(stamps: NDArray[np.int64]) -> dict[str, NDArray[np.bool_]]:
    """Per fault name, the mask of stamps (N,) ns with that fault."""
    s = np.asarray(stamps, dtype=np.int64)
    return {"zero_stamp": s == 0, "negative_stamp": s < 0}


def reading_faults(vectors: NDArray[np.float64], limit: float = MAX_READING) -> dict[str, NDArray[np.bool_]]:
    """Per fault name, the mask of readings (N, 3) T with that fault (``limit``: largest magnitude, T)."""
    v = np.asarray(vectors, dtype=float).reshape(-1, 3)
    finite = np.all(np.isfinite(v), axis=1)
    big = np.hypot(np.hypot(v[:, 0], v[:, 1]), v[:, 2]) > limit
    return {"nonfinite": ~finite, "out_of_range": finite & big}


def reading_fault_list(vectors: NDArray[np.float64], limit: float = MAX_READING) -> list[str | None]:
    """Per reading (N, 3) T, its fault name or None (:func:`reading_faults` as a list)."""
    faults = reading_faults(vectors, limit)
    out: list[str | None] = [None] * len(faults["nonfinite"])
    for name in READING_FAULTS:
        for i in np.flatnonzero(faults[name]).tolist():
            out[i] = name
    return out

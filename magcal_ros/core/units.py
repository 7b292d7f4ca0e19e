"""Unit constants, one per fact, and the check that readings are in Tesla.

Code and files are SI (Tesla, metres, seconds); papers quote nT.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from magcal_ros.errors import InputError

NT: float = 1e-9
"""One nanotesla in Tesla."""

MU0_OVER_4PI: float = 1e-7
"""mu_0 / (4 pi) in T m / A."""

NS_PER_S: int = 1_000_000_000
"""Nanoseconds per second: stamps are integer nanoseconds (ROS ``sec`` and ``nanosec``)."""

EARTH_FIELD_RANGE: tuple[float, float] = (1e-7, 1e-3)
"""Accepted magnitude (T) of an Earth field (a reference intensity, the median raw reading):
the Earth's is 20-70 uT; the margins cover sensor errors and hull iron. Readings in nT, uT,
mT or Gauss all fall outside."""

MAX_READING: float = 2 * EARTH_FIELD_RANGE[1]
"""Largest magnitude (T) of one raw reading the tools and nodes accept: an Earth field (at most
the top of :data:`EARTH_FIELD_RANGE`) plus the largest offset a calibration may hold (as
much again). Beyond it a reading is not a magnetometer's in the Earth's field (a corrupt
message, a wrong unit, 1e30): it is dropped and counted (``out_of_range``), never used. A
single reading has no lower bound: a hard-iron offset can cancel the field at one attitude."""


def check_tesla(vectors: ArrayLike, names: Sequence[str], where: str) -> None:
    """Refuse readings (N, S, 3) whose median magnitude per sensor is not an Earth field in T.

    Raises :class:`InputError` with one line naming ``where``, the sensor, its median
    ``|B|`` and "units must be Tesla". Non-finite rows are ignored.
    """
    v = np.asarray(vectors, dtype=float)
    if v.size == 0:
        return
    v3 = v.reshape(len(v), -1, 3)
    norms = np.sqrt(np.einsum("nsa,nsa->sn", v3, v3))  # (S, N)
    lo, hi = EARTH_FIELD_RANGE
    for name, column in zip(names, norms):
        finite = column if np.isfinite(column).all() else column[np.isfinite(column)]
        if len(finite) == 0:
            continue
        middle = (len(finite) + 1) // 2  # the median's lower middle value, counted from either end
        if np.count_nonzero(finite < lo) < middle and np.count_nonzero(finite > hi) < middle:
            continue  # both middle values, and so the median, lie in the range
        median = float(np.median(finite))
        if not lo <= median <= hi:
            raise InputError(
                f"{where}: median |B| of {name} is {median:.4g}, not an Earth field ({lo:g} .. {hi:g} T): "
                "units must be Tesla"
            )

"""The sensors' temperatures: recorded samples and their match to sets.

A fluxgate's offset and gain follow its temperature. Per sensor, the calibration's
temperature terms (:class:`~magcal_ros.core.calibration.ArrayCalibration`) correct with
``dT = T - temperature_reference``::

    B = (matrix + dT matrix_tempco) (raw - offset - dT offset_tempco) - interference u

Temperatures come per sensor (``<name>/temperature``, ``sensor_msgs/Temperature``, deg C)
and are matched to sets by the rule of every side stream (:mod:`magcal_ros.core.matching`):
the latest value stamped at most :data:`DEFAULT_TEMPERATURE_TOLERANCE` before the set. A
temperature changes slowly (a glider crossing the thermocline: a few kelvin a minute; a
UUV's electronics warming: 20 K in an hour) and its sensors publish at 0.1-10 Hz, so the
tolerance is seconds, not the milliseconds of the field sensors: 10 s old at 0.1 K/min is
0.02 K, far below what an offset tempco of a fraction of a nT/K can show.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.matching import MatchStats, checked_samples
from magcal_ros.core.side_streams import TEMPERATURE, SideCounts, refuse_units

Array = NDArray[np.float64]

DEFAULT_TEMPERATURE_TOLERANCE: float = 10.0
"""Largest age (s) of a sensor's latest temperature at a set's stamp; older is stale."""


@dataclass(frozen=True)
class TemperatureSamples:
    """The recorded temperatures of one sensor: ``stamps`` (n,) int64 ns, ``values`` (n,) deg C."""

    sensor: str
    stamps: NDArray[np.int64]
    values: Array
    counts: SideCounts | None = None
    """What the recorded samples came to, when they went through the stream's acceptance."""

    def __post_init__(self) -> None:
        t, v = checked_samples(f"{self.sensor}: need integer ns stamps and one temperature", self.stamps, self.values)
        object.__setattr__(self, "stamps", t)
        object.__setattr__(self, "values", v)


@dataclass
class TemperatureStats(MatchStats):
    """Sets dropped because a sensor had no fresh temperature (one line for users)."""

    NOUN = "temperature"
    OWNER = "sensor"


def check_temperatures(values: Array, where: str) -> None:
    """:class:`InputError` naming ``where`` when most finite temperatures lie outside :data:`TEMPERATURE_RANGE`
    (not deg C: kelvin?); a single one outside is a bad sample, no value (:mod:`~magcal_ros.core.side_streams`)."""
    refuse_units(TEMPERATURE, np.asarray(values, dtype=float).reshape(-1).tolist(), where)

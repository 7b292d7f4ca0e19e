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

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

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


# -- the temperatures a calibration was made at ------------------------------------------------------
TEMPERATURE_MARGIN: float = 2.0
"""How far (K) beyond the temperatures a calibration was made at (its ``calibration_temperatures``) a
sensor may be before a correction says so. A fluxgate's offset moves by a fraction of a nT per kelvin and
its gain by tens of ppm per kelvin (about 0.5-1 nT/K in a 50 uT field): 2 K away the calibration is off
by about the noise floor (1 nT), and a sensor's temperature reading itself is rarely better than 0.5 K.
Beyond it the error grows with the distance (a dive 16 K colder: 20-30 times the TMI noise floor).
A calibration with temperature terms extrapolates its linear terms there just the same."""


def temperature_span(temperatures: ArrayLike | None, sensors: int) -> Array | None:
    """(S, 2) deg C: each sensor's lowest and highest finite temperature of ``temperatures`` (N, S), or (N,)
    one for every sensor; a row NaN for a sensor without any; None when no temperatures are given."""
    if temperatures is None:
        return None
    t = np.asarray(temperatures, dtype=float)
    if t.ndim == 1:
        t = np.repeat(t[:, None], sensors, axis=1)
    if t.ndim != 2 or t.shape[1] != sensors or not len(t):
        return None
    finite = np.isfinite(t)
    low = np.where(finite, t, np.inf).min(axis=0)
    high = np.where(finite, t, -np.inf).max(axis=0)
    known = finite.any(axis=0)
    span = np.column_stack([np.where(known, low, np.nan), np.where(known, high, np.nan)])
    return None if not known.any() else span


def span_with_prior(span: Array | None, names: tuple[str, ...], prior: Any) -> Array | None:
    """The temperatures (S, 2) deg C a calibration of sensors ``names`` made over ``span`` (its sets') from a
    ``prior`` calibration (or None) holds over: what the prior held over too, where it was fitted (a
    recalibration from a short window keeps what the window does not determine, and its temperature
    dependence with it); unknown (None, or a NaN row) where the prior's is."""
    if prior is None or span is None:
        return span
    theirs = prior.temperature_span
    if theirs is None:
        return None
    rows = [theirs[prior.geometry.names.index(n)] if n in prior.geometry.names else (np.nan, np.nan) for n in names]
    before = np.asarray(rows, dtype=float)
    return np.column_stack([np.minimum(span[:, 0], before[:, 0]), np.maximum(span[:, 1], before[:, 1])])


@dataclass
class SpanExcursions:
    """Sets corrected at temperatures more than :data:`TEMPERATURE_MARGIN` beyond the calibration's
    (``span`` (S, 2) deg C, NaN rows unknown), counted per sensor as they come (chunks of a bag, the
    sets of a live node): how many, and how far (K) below and above at most."""

    names: tuple[str, ...]
    span: Array
    margin: float = TEMPERATURE_MARGIN
    counts: NDArray[np.int64] = field(init=False)
    below: Array = field(init=False)
    """(S,) K: the farthest below the span's minimum (0: never)."""
    above: Array = field(init=False)
    """(S,) K: the farthest above the span's maximum (0: never)."""

    def __post_init__(self) -> None:
        self.span = np.asarray(self.span, dtype=float).reshape(len(self.names), 2)
        self.counts = np.zeros(len(self.names), np.int64)
        self.below = np.zeros(len(self.names))
        self.above = np.zeros(len(self.names))
        known = np.all(np.isfinite(self.span), axis=1)
        self._limits = [(float(lo) - self.margin, float(hi) + self.margin) if k else (-math.inf, math.inf)
                        for (lo, hi), k in zip(self.span, known)]

    def add_one(self, values: Sequence[float], fresh: Sequence[bool]) -> list[str]:
        """:meth:`add` for one set's temperatures (S,) deg C, plain numbers (the live hot path)."""
        first: list[str] = []
        for i, (t, ok) in enumerate(zip(values, fresh)):
            low, high = self._limits[i]
            if not ok or low <= t <= high or math.isnan(t):
                continue
            if not self.counts[i]:
                first.append(self.names[i])
            self.counts[i] += 1
            if t < low:
                self.below[i] = max(self.below[i], low + self.margin - t)
            else:
                self.above[i] = max(self.above[i], t - high + self.margin)
        return first

    def add(self, temperatures: ArrayLike, fresh: ArrayLike | None = None) -> list[str]:
        """Count sets' temperatures (N, S) deg C (``fresh`` (N, S): which are values; default finite ones);
        the sensors out of the span for the first time."""
        t = np.asarray(temperatures, dtype=float).reshape(-1, len(self.names))
        ok = np.isfinite(t) if fresh is None else np.asarray(fresh, bool).reshape(t.shape) & np.isfinite(t)
        low = np.where(ok, self.span[:, 0] - t, 0.0)  # NaN span rows compare False below
        high = np.where(ok, t - self.span[:, 1], 0.0)
        out = (low > self.margin) | (high > self.margin)
        first = [n for n, c, o in zip(self.names, self.counts, out.any(axis=0)) if o and not c]
        self.counts += out.sum(axis=0)
        self.below = np.maximum(self.below, np.nan_to_num(low, nan=0.0).max(axis=0, initial=0.0) * out.any(axis=0))
        self.above = np.maximum(self.above, np.nan_to_num(high, nan=0.0).max(axis=0, initial=0.0) * out.any(axis=0))
        return first

    def describe(self, index: int) -> str:
        """Sensor ``index``'s excursion in words (empty when none), e.g. ``mag2: 5,210 sets up to 16.1 K below
        the calibrated temperatures 18.2..19.0 C``."""
        if not self.counts[index]:
            return ""
        far = [f"{d:.1f} K {w}" for d, w in ((self.below[index], "below"), (self.above[index], "above"))
               if d > self.margin]
        lo, hi = self.span[index]
        sets = "set" if self.counts[index] == 1 else "sets"
        return (f"{self.names[index]}: {self.counts[index]:,} {sets} up to {' and '.join(far)} the calibrated "
                f"temperatures {lo:.1f}..{hi:.1f} C")

    def notes(self) -> list[str]:
        """One line per sensor that left the span (none: empty), saying what it means."""
        lines = [d for i in range(len(self.names)) if (d := self.describe(i))]
        if lines:
            lines[-1] += (f" (more than {self.margin:g} K outside the temperatures the calibration was made at: "
                          "applied there it extrapolates; calibrate at these temperatures or over a wider span)")
        return lines

"""Temperature profiles of a simulated recording (deg C per set) and the sensors' temperature coefficients.

Profiles (``magcal simulate``):

- ``steps`` ``T1,T2,...``: the sets in equal consecutive blocks, one per temperature (tumbles at
  5, 15 and 25 C, say);
- ``ramp`` ``T0,T1``: a warming (or cooling) from T0 to T1 over the recording, exponential with
  the time constant a third of the recording (electronics warming after launch: fast, then
  levelling off);
- ``thermocline`` ``SURFACE,DEEP[,DIVES]``: a glider's dives: depth goes down and up ``DIVES``
  times (default 1) and the water is ``SURFACE`` above a thermocline at 30 % of the dive
  depth, ``DEEP`` below it, with a sharp transition; each dive crosses it twice.

Each sensor's offset moves by ``offset tempco`` (T/K per axis, raw axes) and its sensitivity by
``gain tempco`` (1/K per axis) about the reference temperature (see
:class:`~magcal_ros.sim.simulator.ArraySimulation`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.side_streams import TEMPERATURE_RANGE
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

PROFILES: tuple[str, ...] = ("steps", "ramp", "thermocline")
THERMOCLINE_DEPTH: float = 0.3
"""Depth of the thermocline as a fraction of the dive depth."""
THERMOCLINE_WIDTH: float = 0.04
"""Its thickness, the same fraction."""


def _check(values: Sequence[float], count: int | tuple[int, int], what: str) -> Array:
    v = np.asarray(values, dtype=float).reshape(-1)
    lo, hi = (count, count) if isinstance(count, int) else count
    if not (lo <= len(v) <= hi) or not np.all(np.isfinite(v)):
        raise InputError(f"{what}")
    return v


def temperature_profile(kind: str, values: Sequence[float], count: int) -> Array:
    """(count,) temperatures in deg C of a profile (module docstring)."""
    if count < 1:
        raise InputError("a temperature profile needs at least one set")
    k = np.arange(count)
    if kind == "steps":
        v = _check(values, (1, 1000), "--temperatures needs temperatures in deg C, e.g. 5,15,25")
        out = v[np.minimum(k * len(v) // count, len(v) - 1)]
    elif kind == "ramp":
        t0, t1 = _check(values, 2, "--temperature-ramp needs two temperatures in deg C, e.g. 5,25")
        x = k / max(count - 1, 1)
        out = t0 + (t1 - t0) * (1.0 - np.exp(-3.0 * x)) / (1.0 - np.exp(-3.0))
    elif kind == "thermocline":
        v = _check(values, (2, 3), "--thermocline needs SURFACE,DEEP[,DIVES] (deg C, deg C, count), e.g. 25,4,2")
        surface, deep = v[0], v[1]
        dives = v[2] if len(v) == 3 else 1.0
        if not dives > 0:
            raise InputError("--thermocline: the number of dives must be positive")
        depth = 0.5 * (1.0 - np.cos(2.0 * np.pi * dives * k / max(count, 1)))
        warm = 1.0 / (1.0 + np.exp((depth - THERMOCLINE_DEPTH) / THERMOCLINE_WIDTH))
        top = 1.0 / (1.0 + np.exp(-THERMOCLINE_DEPTH / THERMOCLINE_WIDTH))
        bottom = 1.0 / (1.0 + np.exp((1.0 - THERMOCLINE_DEPTH) / THERMOCLINE_WIDTH))
        out = deep + (surface - deep) * (warm - bottom) / (top - bottom)
    else:
        raise InputError(f"unknown temperature profile {kind!r}; choose one of {', '.join(PROFILES)}")
    lo, hi = TEMPERATURE_RANGE
    if out.min() < lo or out.max() > hi:
        raise InputError(f"temperatures must lie in {lo:g} .. {hi:g} deg C")
    return np.asarray(out, dtype=float)


def draw_tempcos(rng: np.random.Generator, sensors: int, offset_sd: float, gain_sd: float) -> tuple[Array, Array]:
    """Per sensor and axis: offset tempcos (S, 3) T/K and gain tempcos (S, 3) 1/K, normal with the given spreads."""
    for name, v in (("--tempco-offset", offset_sd), ("--tempco-gain", gain_sd)):
        if not (np.isfinite(v) and v >= 0):
            raise InputError(f"{name} must be a finite spread >= 0")
    return rng.normal(0.0, offset_sd, (sensors, 3)), rng.normal(0.0, gain_sd, (sensors, 3))

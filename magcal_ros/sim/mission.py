"""A survey mission with known truth: yaw turns or straight legs with pitch and roll wobble,
magnetic targets passed on the way, and the hull's hard iron jumping mid-run.

The platform runs along the world x axis (north) at ``speed`` while its heading follows the
legs (a vehicle circling while it drifts along a line; the geometry of its track matters
only for how near the targets come). A target is a point dipole at ``distance`` below the
track at the instant of closest approach, so it is passed once, a transient anomaly that is
smooth over the array. A hard-iron step replaces the simulation from ``step_at`` on by
another one (:func:`~magcal_ros.sim.simulator.hard_iron_moved`): the same sensors, their
platform-fixed field moved.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.field import Dipole
from magcal_ros.core.recording import Recording
from magcal_ros.errors import InputError
from magcal_ros.sim.attitudes import yaw_pitch_roll
from magcal_ros.sim.simulator import ArraySimulation, Truth

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Leg:
    """A stretch of the mission: ``seconds`` long at ``yaw_rate_deg_s`` (0: a straight leg)."""

    seconds: float
    yaw_rate_deg_s: float = 6.0


@dataclass(frozen=True)
class Target:
    """A magnetic object passed at ``seconds`` from the start, ``distance`` m below the track,
    with dipole ``moment`` (A m^2, world frame NED)."""

    seconds: float
    distance: float
    moment: tuple[float, float, float] = (0.0, 0.0, 60.0)


def wobble(count: int, rate: float, amplitude_deg: float, rng: np.random.Generator) -> Array:
    """(count, 2) smooth pitch and roll (deg) within +-``amplitude_deg``: a few slow swells
    (periods 4-20 s) with random phases, scaled so that the largest excursion is the amplitude."""
    t = np.arange(count) / rate
    out = np.zeros((count, 2))
    for axis in range(2):
        periods = rng.uniform(4.0, 20.0, 3)
        phases = rng.uniform(0.0, 2.0 * np.pi, 3)
        out[:, axis] = np.sum(np.sin(2.0 * np.pi * t[:, None] / periods + phases), axis=1)
    peak = np.max(np.abs(out), axis=0)
    return out * (amplitude_deg / np.maximum(peak, 1e-12))


def mission_attitudes(legs: Sequence[Leg], rate: float, wobble_deg: float, rng: np.random.Generator,
                      heading_deg: float = 0.0) -> Array:
    """(N, 3, 3) platform-to-world rotations of the legs flown one after the other at ``rate`` sets/s."""
    rates = np.concatenate([np.full(int(round(leg.seconds * rate)), leg.yaw_rate_deg_s) for leg in legs])
    if len(rates) == 0:
        raise InputError("a mission needs at least one set")
    yaw = heading_deg + np.concatenate([[0.0], np.cumsum(rates[:-1]) / rate])
    tilt = wobble(len(rates), rate, wobble_deg, rng) if wobble_deg > 0 else np.zeros((len(rates), 2))
    return yaw_pitch_roll(yaw, tilt[:, 0], tilt[:, 1])


def mission(
    sim: ArraySimulation,
    legs: Sequence[Leg],
    rng: np.random.Generator,
    rate: float = 100.0,
    wobble_deg: float = 5.0,
    speed: float = 1.5,
    targets: Sequence[Target] = (),
    step: ArraySimulation | None = None,
    step_at: float = 0.0,
    start: float = 0.0,
    currents: Array | None = None,
) -> tuple[Recording, Truth]:
    """Simulate the legs (raw recording and truth, as :meth:`ArraySimulation.run`).

    ``targets`` are added to ``sim``'s dipoles; from ``step_at`` s on the readings are those of
    ``step`` (the array after its hard iron moved), when given. Stamps from ``start`` s;
    ``currents`` (N, m) A of the thrusters at each set (default: off).
    """
    rot = mission_attitudes(legs, rate, wobble_deg, rng, float(rng.uniform(0.0, 360.0)))
    n = len(rot)
    t = np.arange(n) / rate
    track = np.column_stack([speed * t, np.zeros(n), np.zeros(n)])
    dipoles = tuple(Dipole(np.array([speed * g.seconds, 0.0, g.distance]), np.asarray(g.moment, dtype=float))
                    for g in targets)
    before = replace(sim, dipoles=sim.dipoles + dipoles)
    rec, truth = before.run(rot, rng, rate=rate, start=start, currents=currents, track=track)
    if step is None:
        return rec, truth
    k = int(round(step_at * rate))
    after_rec, _ = replace(step, dipoles=step.dipoles + dipoles).run(rot, rng, rate=rate, start=start,
                                                                     currents=currents, track=track)
    vectors = np.concatenate([rec.vectors[:k], after_rec.vectors[k:]])
    return Recording(rec.names, rec.stamps, vectors, rec.channels, rec.currents), truth

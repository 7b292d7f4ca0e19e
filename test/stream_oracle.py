"""Sensor streams with known truth, written for the tests from the definitions (not the package's
simulator), and the invariants every published set must satisfy.

Each sensor samples at its own instants ``phase + n (1 + ppm 1e-6) / rate`` (seconds after the
start) and its driver stamps each sample ``delay`` after it, with uniform jitter. A stream may
break its rules in any of these ways:

- a *step*: from a true time on, every later stamp of the sensor is ``jump`` seconds off (a driver
  restart whose clock starts over: back; a clock that stepped: either way; any size, sub-second
  included);
- a *glitch*: one message stamped ``shift`` seconds off;
- a *duplicate*: one message delivered twice;
- a *silence*: no samples in an interval (the sensor paused);
- a *stall*: the driver delivers nothing in an interval, then its backlog at once: with
  ``restamp`` the backlog is stamped on delivery (a driver stamping on receipt), otherwise
  with its true stamps;
- *loss*: samples never delivered, at random;
- a *bad reading*: NaN or 1e30 T;
- a *late topic*: the receiver takes none of the sensor's messages for a while (a loaded machine
  serving other topics), then takes them at the sensor's own pace, so they stay that late, for a
  while more, then drains the topic a little faster than it fills until it has caught up; the
  stamps are right throughout (the other sensors' topics on time).

Every message also has its receipt (bag time, or the node's arrival time): its sample instant plus
a transport delay, in its sensor's order (a topic delivers in order); a stall delays it to the
stall's end; a *busy receiver* (:func:`busy_receiver`, all sensors at once) takes nothing for a while,
then drains its queue a little faster than the sensors fill it.

The reading encodes the truth: ``x = X0 + SCALE * instant`` (T), so a reading interpolated
between two samples encodes the instant it stands for. :func:`set_instants` decodes a set's
members; a set is right when they agree within the sync tolerance plus the stamps' own noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

START_NS = 1_700_000_000 * 1_000_000_000
"""Stamp (ns) of true time 0."""
X0 = 1e-5
"""Reading x at true time 0 (T)."""
SCALE = 1e-6
"""Reading x per second of true time (T/s): 100 s of recording stay below 2e-4 T."""
YZ = (2e-5, -4e-5)
"""The readings' y and z (T)."""


@dataclass
class SensorPlan:
    """How one sensor samples, is stamped and breaks its rules (seconds after the start)."""

    rate: float = 50.0
    phase: float = 0.0
    ppm: float = 0.0
    delay: float = 0.002
    """Stamp delay after the sample (s), the same for every sensor of a plan (a difference is a lag)."""
    jitter: float = 0.0
    """Half-width of the uniform stamp jitter (s)."""
    transport: float = 0.001
    """Receipt delay after the stamp delay (s)."""
    loss: float = 0.0
    steps: list[tuple[float, float]] = field(default_factory=list)
    glitches: list[tuple[float, float]] = field(default_factory=list)
    duplicates: list[float] = field(default_factory=list)
    silences: list[tuple[float, float]] = field(default_factory=list)
    stalls: list[tuple[float, float, bool]] = field(default_factory=list)
    """(start, length, restamp)."""
    bad: list[float] = field(default_factory=list)
    """True times of a NaN or 1e30 T reading (the sample nearest each)."""
    late: list[tuple[float, float, float, float]] = field(default_factory=list)
    """(start, block, hold, drain): the topic's messages late by ``block`` s from ``start`` for ``hold`` s more,
    then taken one every ``drain`` periods (below 1) until on time."""
    depth: int | None = None
    """The receiver's history depth for the topic (keep last): while it is late, a message that more than
    ``depth - 1`` later ones reach before it is taken is lost. None: unbounded."""


@dataclass
class Stream:
    """One sensor's messages in its order: stamps and receipts (ns), readings (T), and the truth."""

    stamps: NDArray[np.int64]
    receipts: NDArray[np.int64]
    vectors: NDArray[np.float64]
    instants: NDArray[np.float64]
    """True sample instant of each message (s after the start)."""
    trusted: NDArray[np.bool_]
    """Messages whose stamp is right (not a glitch, a stall's restamped backlog, a duplicate's copy, a
    bad reading, or within two periods of a step): the ones a rule must not lose without cause."""


def _nearest(instants: NDArray[np.float64], t: float) -> int:
    return int(np.argmin(np.abs(instants - t)))


def make_stream(plan: SensorPlan, duration: float, rng: np.random.Generator) -> Stream:
    """The messages of one sensor over ``duration`` s (module docstring)."""
    period = (1.0 + plan.ppm * 1e-6) / plan.rate
    t = plan.phase + np.arange(int(np.floor((duration - plan.phase) / period))) * period
    keep = np.ones(len(t), bool)
    for a, b in plan.silences:
        keep &= ~((t >= a) & (t < b))
    if plan.loss:
        keep &= rng.random(len(t)) >= plan.loss
    t = t[keep]
    n = len(t)
    stamp = t + plan.delay + rng.uniform(-plan.jitter, plan.jitter, n)
    receipt = t + plan.delay + plan.transport + rng.uniform(0.0, 0.2 * plan.transport, n)
    trusted = np.ones(n, bool)
    for at, jump in plan.steps:
        after = t >= at
        stamp[after] += jump
        trusted &= ~((t >= at - 2 * period) & (t < at + 2 * period))
    for start, length, restamp in plan.stalls:
        inside = (t >= start) & (t < start + length)
        end = start + length
        k = np.flatnonzero(inside)
        receipt[k] = end + plan.transport + 1e-5 * np.arange(len(k))
        if restamp:  # stamped on delivery by the driver's clock (stepped as its other stamps)
            offset = sum(jump for at, jump in plan.steps if at <= end)
            stamp[k] = end + offset + 1e-5 * np.arange(len(k))
            trusted[k] = False
    for start, block, hold, drain in plan.late:
        kept = late_topic(receipt, period, start, block, hold, drain, plan.depth)
        t, stamp, receipt, trusted = t[kept], stamp[kept], receipt[kept], trusted[kept]
    n = len(t)
    receipt = np.maximum.accumulate(receipt)  # a topic delivers in order
    x = X0 + SCALE * t
    vectors = np.column_stack([x, np.full(n, YZ[0]), np.full(n, YZ[1])])
    for at, shift in plan.glitches:
        if n:
            i = _nearest(t, at)
            stamp[i] += shift
            trusted[i] = False
    for at in plan.bad:
        if n:
            i = _nearest(t, at)
            vectors[i] = (np.nan, 0.0, 0.0) if i % 2 else (1e30, 0.0, 0.0)
            trusted[i] = False
    order = np.arange(n)
    for at in plan.duplicates:
        if n:
            i = _nearest(t, at)
            order = np.insert(order, int(np.searchsorted(order, i)) + 1, i)
    stamps = np.round((START_NS + stamp[order] * 1e9)).astype(np.int64)
    receipts = np.round((START_NS + receipt[order] * 1e9)).astype(np.int64)
    dup = np.zeros(len(order), bool)
    dup[1:] = order[1:] == order[:-1]
    tr = trusted[order] & ~dup
    return Stream(stamps, receipts, vectors[order], t[order], tr)


def late_topic(receipt: NDArray[np.float64], period: float, start: float, block: float, hold: float,
               drain: float, depth: int | None = None) -> NDArray[np.bool_]:
    """One topic's receipts (s, in place) from ``start``: none taken for ``block`` s, then one a period until
    ``start + block + hold``, then one every ``drain`` periods until they are on time again. The messages kept:
    with a history ``depth``, one that ``depth`` later ones reach before its turn is lost."""
    kept = np.ones(len(receipt), bool)
    come = receipt.copy()
    free, paced = start + block, start + block + hold
    for i in np.flatnonzero(receipt >= start):
        if come[i] >= free and free > paced:
            break  # caught up
        taken = max(come[i], free)
        if depth is not None and int(np.searchsorted(come, taken, side="right")) - (i + 1) >= depth:
            kept[i] = False  # overwritten in the history before its turn
            continue
        receipt[i] = taken
        free = taken + (period if taken < paced else drain * period)
    return kept


def arrivals(streams: list[Stream]) -> list[tuple[int, int, int]]:
    """(receipt ns, sensor, message) of every message in the order a node receives them: by receipt,
    each sensor's messages in their own order."""
    events = [(int(r), k, i) for k, s in enumerate(streams) for i, r in enumerate(s.receipts.tolist())]
    events.sort()
    return events


def busy_receiver(streams: list[Stream], start: float, length: float, service: float) -> None:
    """The receiver is busy from ``start`` for ``length`` s (seconds after the start), then takes what queued
    one message every ``service`` s until it has caught up: every later receipt (ns) moves, in place."""
    events = arrivals(streams)
    free = START_NS + int((start + length) * 1e9)
    begin = START_NS + int(start * 1e9)
    step = int(service * 1e9)
    for receipt, k, i in events:
        if receipt < begin:
            continue
        if receipt >= free:
            break
        streams[k].receipts[i] = free
        free += step


def true_lost(stream: Stream, plan: SensorPlan) -> int:
    """Samples never delivered between the stream's first and last (s instants on the sensor's own grid)."""
    period = (1.0 + plan.ppm * 1e-6) / plan.rate
    index = np.round((stream.instants - plan.phase) / period).astype(np.int64)
    return int(index[-1] - index[0] + 1 - len(np.unique(index))) if len(index) else 0


def set_instants(values: Any) -> NDArray[np.float64]:
    """The true instant (s after the start) each member of a set's readings (S, 3) stands for."""
    v = np.asarray(values, dtype=float).reshape(-1, 3)
    return (v[:, 0] - X0) / SCALE


def spread(values: Any) -> float:
    """How far apart (s) the true instants of a set's members are."""
    t = set_instants(values)
    return float(t.max() - t.min())

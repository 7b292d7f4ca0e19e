"""Generated streams against a truth oracle: every published set stands for one true instant.

Hypothesis draws arrays of one to four sensors, each on its own sample clock (rate, phase, drift,
jitter, loss) and breaking its rules at random (steps of the stamps back or forward of any size
from 1.5 periods to minutes, glitches, repeats, pauses, stalls delivering a backlog, NaN and
1e30 T readings; :mod:`stream_oracle`). The same messages go through the set rule offline (each
sensor's batch, receipts as bag times) and live (one message at a time in arrival order), and:

- every published set's members stand for one true instant, within the exact window plus the
  stamps' jitter (the readings encode the instant they were sampled at);
- every message ends in a set or a drop counter (or is still pending, live): nothing is lost
  without being counted;
- where every sensor sampled cleanly around a reference sample (away from any fault), a set is
  published there (the rule does not drop what it could use: after a restart, a step, a backlog);
- live and offline publish the same sets;
- a sensor whose only fault is random loss counts exactly the samples it lost (live, as a node's
  diagnostics report them),
  also where the receiver was busy and then drained its queue a little faster than it filled
  (arrivals that then do not keep the stamps' time must not make a lost sample a step).

CI runs a fixed number of examples derandomised (the same every run); ``MAGCAL_PROPERTY_EXAMPLES``
runs more (``benchmarks/bench_stream_properties.py`` prints the figures of a longer run).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from stream_oracle import SensorPlan, Stream, arrivals, busy_receiver, make_stream, set_instants, true_lost

from magcal_ros.core import side_streams as side
from magcal_ros.core.sync import stream_synchronizer, synchronise_streams
from magcal_ros.core.units import NS_PER_S

EXAMPLES = int(os.environ.get("MAGCAL_PROPERTY_EXAMPLES", "25"))


def leave_out_local_constants(patch: pytest.MonkeyPatch) -> None:
    """Hypothesis mixes into its draws the constants of every module of this repository imported so far: which
    modules those are (and what they hold) changes the examples a seed draws. Left out (undone with ``patch``),
    the examples depend on the strategies alone."""
    from hypothesis.internal.conjecture import providers

    if hasattr(providers, "_get_local_constants"):
        empty = type(providers._local_constants)()
        patch.setattr(providers, "_get_local_constants", lambda: empty)
        providers.CONSTANTS_CACHE.cache.clear()


@pytest.fixture(autouse=True, scope="module")
def _same_examples_in_any_run() -> Iterator[None]:
    """The derandomised examples of this file alone and of the whole suite the same (the modules imported
    before depend on the test files that ran first: a failure found in one and not the other)."""
    with pytest.MonkeyPatch.context() as patch:
        leave_out_local_constants(patch)
        yield
TOLERANCE = 1e-3
"""The default exact window (s)."""
CLEAN = 1.0
"""Seconds around a fault (or the start) where a reference sample need not make a set."""
COVERAGE = 0.97
"""Fraction of the clean reference samples that must make a set."""


@dataclass
class Case:
    plans: list[SensorPlan]
    duration: float
    seed: int
    busy: tuple[float, float, float] | None = None
    """The receiver busy (start s, length s, service s per message), or None."""

    @property
    def period(self) -> float:
        return 1.0 / min(p.rate for p in self.plans)


def _signed(draw: st.DrawFn, low: float, high: float) -> float:
    """A size between ``low`` and ``high`` seconds, log-uniform, either sign."""
    size = float(np.exp(draw(st.floats(np.log(low), np.log(high)))))
    return size if draw(st.booleans()) else -size


@st.composite
def faults(draw: st.DrawFn, plan: SensorPlan, duration: float) -> SensorPlan:
    """Up to three faults of one sensor, one at a time (each a second or more after the last one ended),
    none in its first two seconds."""
    period = 1.0 / plan.rate
    free = 2.0
    for _ in range(draw(st.integers(0, 3))):
        at = free + draw(st.floats(0.0, 4.0))
        if at > duration - 3.0:
            break
        kind = draw(st.sampled_from(["step", "step", "glitch", "duplicate", "silence", "stall", "restamped", "bad"]))
        length = draw(st.floats(0.2, 3.0))
        if kind == "step":
            plan.steps.append((at, _signed(draw, 1.5 * period, 120.0)))
        elif kind == "glitch":
            plan.glitches.append((at, _signed(draw, 3.0 * period, 120.0)))
        elif kind == "duplicate":
            plan.duplicates.append(at)
        elif kind == "silence":
            plan.silences.append((at, at + length))
        elif kind in ("stall", "restamped"):
            plan.stalls.append((at, length, kind == "restamped"))
        else:
            plan.bad.append(at)
        free = at + (length if kind in ("silence", "stall", "restamped") else 0.0) + 1.0
    return plan


@st.composite
def cases(draw: st.DrawFn) -> Case:
    sensors = draw(st.integers(1, 4))
    rate = draw(st.sampled_from([20.0, 50.0, 100.0, 200.0]))
    period = 1.0 / rate
    synchronous = draw(st.booleans())
    jitter = draw(st.sampled_from([0.0, 0.02, 0.08])) * period
    duration = draw(st.floats(12.0, 30.0))
    plans = []
    for _ in range(sensors):
        plan = SensorPlan(rate=rate, phase=0.0 if synchronous else draw(st.floats(0.0, 0.95 * period)),
                          ppm=0.0 if synchronous else draw(st.floats(-100.0, 100.0)), jitter=jitter,
                          loss=draw(st.sampled_from([0.0, 0.0, 0.02])))
        plans.append(draw(faults(plan, duration)))
    busy = None
    if draw(st.booleans()):  # drained at 0.3 .. 0.95 of the time the sensors took to fill the queue
        busy = (draw(st.floats(2.0, duration - 4.0)), draw(st.floats(0.1, 2.0)),
                draw(st.floats(0.3, 0.95)) / (sensors * rate))
    return Case(plans, duration, draw(st.integers(0, 2**31 - 1)), busy)


def streams_of(case: Case) -> list[Stream]:
    rng = np.random.default_rng(case.seed)
    streams = [make_stream(p, case.duration, rng) for p in case.plans]
    if case.busy is not None:
        busy_receiver(streams, *case.busy)
    return streams


def only_lossy(plan: SensorPlan) -> bool:
    """Whether random loss is the sensor's only fault."""
    return not (plan.steps or plan.glitches or plan.duplicates or plan.silences or plan.stalls or plan.bad)


def check_lost(case: Case, streams: list[Stream], sync) -> None:  # type: ignore[no-untyped-def]
    """A sensor whose only fault is random loss counts exactly what it lost (live: a node's diagnostics), but for
    losses among the messages still pending at the end (at most the synchroniser's ``pending``, any sensor's):
    a live node counts a loss once the sample after it reaches its clock."""
    for k, (plan, stream) in enumerate(zip(case.plans, streams)):
        if only_lossy(plan):
            whole = true_lost(stream, plan)
            seen = true_lost(replace(stream, instants=stream.instants[: max(0, len(stream.instants) - sync.pending)]),
                             plan)
            assert seen <= sync.lost(k) <= whole, (k, sync.lost(k), seen, whole)


def offline(streams: list[Stream]):  # type: ignore[no-untyped-def]
    names = [f"mag{k + 1}" for k in range(len(streams))]
    return synchronise_streams([(s.stamps, s.vectors) for s in streams], mode="auto",
                               receipts=[s.receipts for s in streams], names=names,
                               max_reading=2e-3)


def live(streams: list[Stream]):  # type: ignore[no-untyped-def]
    names = [f"mag{k + 1}" for k in range(len(streams))]
    sync = stream_synchronizer(names, max_reading=2e-3)
    sets = []
    for receipt, k, i in arrivals(streams):
        s = streams[k]
        x, y, z = s.vectors[i].tolist()
        sets += sync.add(k, int(s.stamps[i]), x, y, z, receipt)
    return sets, sync


def bound(case: Case) -> float:
    """How far apart (s) a set's members may stand: the exact window (capped at half a period) plus
    the jitter of two stamps and of a step's placement."""
    return min(TOLERANCE, 0.5 * case.period) + 3.0 * case.plans[0].jitter + 2e-6


def disturbed(case: Case) -> list[tuple[float, float]]:
    """Intervals (s) around every fault of every sensor, where sets may be lost for cause."""
    out = [(-1.0, CLEAN + 40 * case.period)]
    for p in case.plans:
        out += [(t - CLEAN, t + CLEAN + 40 * case.period) for t, _ in p.steps]
        out += [(t - CLEAN, t + CLEAN) for t, _ in p.glitches]
        out += [(t - CLEAN, t + CLEAN) for t in p.duplicates + p.bad]
        out += [(a - CLEAN, b + CLEAN + 40 * case.period) for a, b in p.silences]
        out += [(a - CLEAN, a + n + CLEAN + 40 * case.period) for a, n, _ in p.stalls]
    out.append((case.duration - CLEAN, case.duration + 1.0))
    return out


def clean_reference(case: Case, streams: list[Stream], mode: str) -> np.ndarray:
    """True instants of the reference sensor's trusted samples away from every fault, with every other
    sensor's trusted samples at the same instant (exact matching: within :func:`bound`) or around it
    (interpolation: within 1.5 periods each side)."""
    t = streams[0].instants[streams[0].trusted]
    keep = np.ones(len(t), bool)
    for a, b in disturbed(case):
        keep &= ~((t >= a) & (t <= b))
    for s in streams[1:]:
        own = np.sort(s.instants[s.trusted])
        period = 1.0 / case.plans[0].rate
        i = np.searchsorted(own, t)
        before = np.where(i > 0, t - own[np.maximum(i - 1, 0)], np.inf)
        after = np.where(i < len(own), own[np.minimum(i, len(own) - 1)] - t, np.inf)
        if mode == "exact":
            keep &= np.minimum(before, after) <= bound(case)
        else:
            keep &= (before <= 1.5 * period) & (after <= 1.5 * period)
    return t[keep]


def check_sets(case: Case, vectors: np.ndarray, label: str) -> np.ndarray:
    """Every set's members stand for one instant; the instants of the sets (the reference member's)."""
    if not len(vectors):
        return np.zeros(0)
    instants = np.array([set_instants(v) for v in vectors])
    spread = instants.max(axis=1) - instants.min(axis=1)
    worst = int(np.argmax(spread))
    assert spread[worst] <= bound(case), (f"{label}: set {worst} of {len(vectors)} pairs readings "
                                          f"{spread[worst] * 1e3:.3f} ms apart (bound {bound(case) * 1e3:.3f} ms): "
                                          f"{instants[worst]}")
    return instants[:, 0]


def check_coverage(case: Case, streams: list[Stream], published: np.ndarray, mode: str, revised: bool = False) -> None:
    """The sets made cover :data:`COVERAGE` of the clean reference samples of ``mode``; where exact matching ended
    during the recording (``revised``: mode ``auto`` then interpolates from that point), of the samples clean for
    both (a lost sample makes no exact set before the revision, and the oracle does not know when it came)."""
    label = f"offline ({mode})"
    wanted = clean_reference(case, streams, mode)
    if revised:
        wanted = np.intersect1d(wanted, clean_reference(case, streams, "exact"))
    if len(wanted) < 20:
        return
    period = 1.0 / case.plans[0].rate
    got = np.sort(published)
    i = np.clip(np.searchsorted(got, wanted), 1, max(len(got) - 1, 1))
    near = np.minimum(np.abs(got[i - 1] - wanted), np.abs(got[np.minimum(i, len(got) - 1)] - wanted)) \
        if len(got) else np.full(len(wanted), np.inf)
    made = near <= 0.25 * period
    assert made.mean() >= COVERAGE, (f"{label}: sets at {made.mean():.1%} of {len(wanted)} clean reference samples; "
                                     f"first missing at {wanted[~made][:5]} s")


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(cases())
# three sensors at 100 Hz, the third's driver stalled 2 s and stamped its backlog on delivery, its clock later
# stepping back 81 s, then on 4.3 s: the backlog's count, still held, placed the last step's segment the stall's
# length late (1.96 s off for the rest). A backlog tells of the gap right after it only
@example(Case([SensorPlan(rate=100.0, phase=0.0095, ppm=85.32437986139607, jitter=0.0002, loss=0.02,
                          steps=[(6.560011653237737, -2.617293166385296)],
                          silences=[(4.930525679274382, 5.560011653237737)], bad=[3.9305256792743823]),
               SensorPlan(rate=100.0, phase=0.00019617385952666125, ppm=-18.258216305729192, jitter=0.0002,
                          steps=[(4.207763260332651, 0.2946338338618022)]),
               SensorPlan(rate=100.0, phase=1.192092896e-07, ppm=19.408805696315284, jitter=0.0002,
                          steps=[(7.227405450393645, -81.06649250143042), (11.170981560810128, 4.324108120055084)],
                          stalls=[(2.6279183257115823, 1.9583399723974544, True)])], 20.662303013260107, 212615))
# found by the whole suite's draws: a step of mag3 12.27 periods ahead while a busy receiver's drain had left
# its arrivals keeping no time (taken as lost samples: that sensor 56 ms off, every later set lost)
@example(Case([SensorPlan(rate=200.0), SensorPlan(rate=200.0), SensorPlan(rate=200.0, steps=[(4.0314, 0.05633)]),
               SensorPlan(rate=200.0, loss=0.02, steps=[(5.3545, 1.0), (9.4855, 1.0)])],
              17.016, 551, (2.9892, 0.5477, 0.00048939)))
# a step 7.04 periods ahead that the arrivals showed, placed by the stamps as the receiver fell busy: the old
# sequence's placement took it back (a 7-period step on the grid looked like a few bad stamps): 350 ms off
@example(Case([SensorPlan(rate=20.0, jitter=0.004, loss=0.02),
               SensorPlan(rate=20.0, jitter=0.004, steps=[(2.0, -44.1455), (3.94581, 0.35180)]),
               SensorPlan(rate=20.0, jitter=0.004, silences=[(2.2782, 3.1941)]),
               SensorPlan(rate=20.0, jitter=0.004, loss=0.02, glitches=[(2.28271, -2.7585)],
                          stalls=[(3.78271, 3.0, True), (11.78271, 1.30117, True)])],
              22.112, 6033, (4.0, 1.46021, 0.0042153)))
# a step 0.72 s ahead (14.4 periods) held for its arrivals to place it while the others went on: by then its first
# stamp was in line with another sensor's latest, taken for one clock again (0.72 s off for the rest)
@example(Case([SensorPlan(rate=20.0, phase=0.03132, ppm=-60.17, jitter=0.004, duplicates=[2.042382318950155]),
               SensorPlan(rate=20.0, ppm=16.707, jitter=0.004, loss=0.02, duplicates=[2.042382318950155]),
               SensorPlan(rate=20.0, phase=0.019942134509738186, jitter=0.004, loss=0.02,
                          steps=[(3.7770658385394555, 0.7196495028899342)])],
              20.506147985158492, 1642, (6.45504282507214, 1.8513276482875791, 0.015609746014365234)))
# a step a second ahead as the receiver fell busy: its receipt late by the queue hid the step (taken for a pause:
# 1 s off for the rest); the other sensors' arrivals in the same queue show how late the receiver was
@example(Case([SensorPlan(rate=100.0, ppm=4.07, jitter=0.0008, steps=[(3.7705800494949933, 1.0000001192092967)]),
               SensorPlan(rate=100.0, phase=0.00716655990038838, jitter=0.0008, loss=0.02),
               SensorPlan(rate=100.0, ppm=2.56, jitter=0.0008),
               SensorPlan(rate=100.0, jitter=0.0008, loss=0.02, steps=[(4.695527418150858, 1.00001000005)])],
              14.739054008586997, 13151, (4.68910038833442, 1.5851226835142644, 0.0019217778522445292)))
# two lost samples taken from a busy receiver's queue: a bound from another sensor's message a period early made
# them look like a step (placed 20 ms off); two sensors' backlog after a driver stall (true stamps) is no queue
@example(Case([SensorPlan(rate=100.0), SensorPlan(rate=100.0, loss=0.02, steps=[(2.0, -1.0)])],
              13.0, 236, (2.0, 1.0, 0.0025)))
@example(Case([SensorPlan(rate=100.0, jitter=0.0002, stalls=[(3.3031270713693957, 1.6803863960582714, False)]),
               SensorPlan(rate=100.0, jitter=0.0002, silences=[(2.5, 2.8685467942437937),
                                                               (6.102317055889484, 6.827898458440179)]),
               SensorPlan(rate=100.0, jitter=0.0002, loss=0.02,
                          stalls=[(3.3031270713693957, 1.6803863960582714, False)]),
               SensorPlan(rate=100.0, jitter=0.0002, silences=[(2.0, 3.1)])],
              18.77228124323634, 4))
# two sensors of one clock stepping back a second, twice, a second apart: the second jump of one matched the
# other's first (the same stamps, a second earlier) while that other still placed its second: 1 s off thereafter
@example(Case([SensorPlan(rate=200.0, phase=0.0008, jitter=0.0004, steps=[(3.000000001, -1.0), (4.000000001, -1.0)],
                          duplicates=[2.0]),
               SensorPlan(rate=200.0, phase=0.001, jitter=0.0004), SensorPlan(rate=200.0, ppm=-4.3, jitter=0.0004),
               SensorPlan(rate=200.0, jitter=0.0004, steps=[(3.000000001, -1.0), (4.000000001, -1.0)],
                          duplicates=[2.0])],
              26.683, 0))
# a busy receiver's queue still draining when a sensor paused 2.2 s: the arrivals before the pause late by the queue,
# the one after it on time, so they saw less time pass than the stamps: the pause was taken for a step forward and
# placed after the last sample (2.2 s off thereafter)
@example(Case([SensorPlan(rate=100.0, silences=[(5.8149, 8.0263)]), SensorPlan(rate=100.0, steps=[(3.7235, -59.223)])],
              22.6745, 2, (2.00001, 1.786377, 0.0028478)))
# the same with a driver's stall whose backlog it stamped on delivery (2.55 s off thereafter)
@example(Case([SensorPlan(rate=100.0, phase=0.00179, jitter=0.0008, stalls=[(4.6828, 2.5578, True)]),
               SensorPlan(rate=100.0, phase=0.0095)], 12.106, 70989270, (2.5606, 1.961484, 0.0017814)))
# stamps 31.7 s ahead while the receiver delivered its queue in a bunch: taken for a pause (no set thereafter)
@example(Case([SensorPlan(rate=200.0), SensorPlan(rate=200.0, steps=[(2.2, 31.727)], silences=[(5.0555, 6.3055)])],
              14.673, 275, (2.00001, 0.593783, 0.00083333)))
# a step back of 1.84 periods put the new stamps within a quarter period of another sensor's, of its own phase:
# taken for one clock again (in line with it) and left unplaced, 9.2 ms off thereafter
@example(Case([SensorPlan(rate=200.0, phase=0.00169), SensorPlan(rate=200.0, steps=[(2.0, -0.009177)])], 12.0, 92))
# two sensors' stamps stepping a second back and forward at once while a queue drains: the one forward was put
# after the other's new data as if it had been silent through it (one clock), though its messages kept coming
@example(Case([SensorPlan(rate=50.0, steps=[(7.0, -1.0)]), SensorPlan(rate=50.0), SensorPlan(rate=50.0),
               SensorPlan(rate=50.0, steps=[(7.0, 1.0)])], 12.62, 189506115, (3.238, 1.3057, 0.0038967)))
# a sample lost among the first few: the grid's period, counted from the median of fewer than eight intervals, took
# a double interval for one, 0.8 % long, and a step forward placed by it lay 2.7 ms off (no exact set thereafter)
@example(Case([SensorPlan(rate=50.0), SensorPlan(rate=50.0, loss=0.02, steps=[(2.4538, 1.0)])], 21.39, 74))
# a step forward of 1.77 periods (on the grid to a quarter period) 0.8 s after a queue drained: the window of arrivals
# still held the backlog, so they were taken to keep no time and the step for lost samples
@example(Case([SensorPlan(rate=200.0, steps=[(10.8148, 0.0088337)]), SensorPlan(rate=200.0)], 14.0, 3224,
              (8.3467, 1.65453, 0.0005)))
# one sensor's stamps a second ahead: a lost sample of another, a second later, jumped over the same stamps and was
# taken for one clock's jump with the first (received within 5 s), so placed a second off
@example(Case([SensorPlan(rate=200.0, loss=0.02, steps=[(3.0, 1.0)]), SensorPlan(rate=200.0),
               SensorPlan(rate=200.0, loss=0.02)], 19.069527288112393, 17035815))
# one clock restarting twice to the same origin: the second jump of one sensor, a second later, reached the stamp the
# other's first had reached and was placed as that one (one sensor silent through it would do so): a second off
@example(Case([SensorPlan(rate=200.0, steps=[(2.0, -8.1208), (3.0, -1.0)]), SensorPlan(rate=200.0, steps=[(2.0, -8.1208)])],
              20.6, 1))
# one clock's jump of two sensors whose placements differed by an earlier step of one of them: the second took the
# first's placement rather than its shift (15 ms off thereafter)
@example(Case([SensorPlan(rate=200.0, jitter=0.0001, steps=[(7.6737, 17.3764)]),
               SensorPlan(rate=200.0, jitter=0.0001, steps=[(3.25, 0.0140668), (7.6737, 17.3764)])], 13.0, 3))
# two sensors stepping 1.84 periods at once, one back and one forward: the shift of the one placed first, added to
# the other's placement after its own step rather than before it, put that one two periods off
@example(Case([SensorPlan(rate=200.0, steps=[(2.0, 0.0091772)]), SensorPlan(rate=200.0, steps=[(2.0, -0.0091772)])],
              12.0, 0))
# a step of 2.01 periods back (with a second's restart) between synchronous sensors: the new stamps fell in line with
# another sensor's, taken for one clock again, though the arrivals (0.1 ms jitter, the other sensor's on time) put
# the segment two periods later (10 ms off thereafter)
@example(Case([SensorPlan(rate=200.0, jitter=0.0001, steps=[(3.5053362, 1.0), (10.616656, -1.0100502)],
                          silences=[(7.7416392, 9.1940538)]),
               SensorPlan(rate=200.0, jitter=0.0001, stalls=[(6.0, 2.676551, True), (13.2733676, 1.3495036, True)]),
               SensorPlan(rate=200.0, jitter=0.0001, glitches=[(12.088446, -1.0)], stalls=[(6.2727147, 2.0192872, False)],
                          bad=[5.2727147]),
               SensorPlan(rate=200.0, jitter=0.0001)], 29.7515, 0))
# a second's step forward while the receiver was blocked: the queue's delay (1.6 s) hid it from the receipts and it
# was taken for a pause (a second off thereafter); now held until the other sensor's arrivals are on time again
@example(Case([SensorPlan(rate=50.0), SensorPlan(rate=50.0, steps=[(6.7, 1.0)])], 12.27, 3, (6.3757, 1.8393, 0.0022222)))
# the same at 20 Hz with a millisecond of jitter: a step of 1.05 s back in line with another sensor a period off
@example(Case([SensorPlan(rate=20.0, phase=0.0008302, ppm=32.564695, jitter=0.001, steps=[(3.5381136, -1.0)]),
               SensorPlan(rate=20.0, jitter=0.001, steps=[(2.8666015, -1.0486462)]),
               SensorPlan(rate=20.0, jitter=0.001, steps=[(4.2049266, -11.8577965), (7.492127, -6.2329073)]),
               SensorPlan(rate=20.0, ppm=6.1e-05, jitter=0.001)], 12.8358, 0))
# a step of 5.9 periods forward, then two samples lost before the new segment's period was known: the gap was taken
# for a second step and, placed with no period, put back on the old sequence (30 ms off thereafter); now placed by
# its arrivals to half the period before the step
@example(Case([SensorPlan(rate=200.0, loss=0.02, steps=[(16.0414282, 0.0293147)]), SensorPlan(rate=200.0, loss=0.02)],
              23.3889, 3))
# one clock's two sensors stepping 142 ms forward while the receiver was blocked: one was held as a jump the queue
# hid, the other, taking the same jump as its partner's, was not, and after 32 untimed messages its stamps put it
# back on its old sequence (a pause, which the first then followed: no sets for the rest of the recording in exact
# mode); now it waits as long as its partner
@example(Case([SensorPlan(rate=50.0, steps=[(8.9405027, 0.14227)]), SensorPlan(rate=50.0),
               SensorPlan(rate=50.0, steps=[(8.9405027, 0.14227)])], 16.3308, 2, (8.357195, 1.5531768, 0.0033333)))
# a 52 ms step forward (2.6 periods) of one of two sensors at 50 Hz while the receiver was blocked for 2 s: the first
# message after it came before the other sensor's that would tell when it came to the queue, and its arrival, late as
# every one then, not early, so the step was taken for lost samples; the sensor was off by 52 ms (0.6 of a period
# off the other's grid) for the rest of the recording and, in exact mode, no set formed after the step (7.6 % of the
# clean reference samples). A jump off the sensor's sample grid after a late message of its own is now held as one
# the queue may hide (lost samples keep the grid: not held)
@example(Case([SensorPlan(rate=50.0, jitter=0.0004, loss=0.02, steps=[(3.1015722784911555, 0.052)]),
               SensorPlan(rate=50.0, jitter=0.0004, loss=0.02)], 10.953313047906832, 2, (3.0, 1.9533130479068315, 0.003)))
# two sensors at 200 Hz stepping back about a second 0.44 s apart, by 1.0 and 1.00223 s: the second, placed by its
# arrivals, took the first's shift as one clock's jump (2.2 ms apart, within half a period) and was paired 2.2 ms off
# for the rest; that shift puts its samples 0.45 of a period off its own grid, which one clock's jump keeps
@example(Case([SensorPlan(rate=200.0, jitter=0.0001, steps=[(4.23705, -1.0)]),
               SensorPlan(rate=200.0, phase=0.0041055, ppm=2.0, jitter=0.0001, loss=0.02, steps=[(3.79744, -1.00223)]),
               SensorPlan(rate=200.0, jitter=0.0001), SensorPlan(rate=200.0, jitter=0.0001)], 12.0, 0))
# one sensor at 50 Hz, the receiver blocked 0.53 s from just after a lost sample: the first message of the drain
# trails its arrival as one a step back during a silence would, and was taken for one (a restart: the lost sample
# never counted); the receiver delivered nothing else meanwhile, so it is lost samples, as a gap the arrivals saw
@example(Case([SensorPlan(rate=50.0, jitter=0.0016, loss=0.02)], 19.93187, 0, (13.16288, 0.52838, 0.0125306)))
# three sensors at 200 Hz, the receiver blocked 0.88 s from just after one's lost sample while another steps forward:
# that sensor's first drained message and its next trail alike, and it was taken for a step back (its loss uncounted)
@example(Case([SensorPlan(rate=200.0, loss=0.02), SensorPlan(rate=200.0, steps=[(4.13468, 0.65369)]),
               SensorPlan(rate=200.0, loss=0.02)], 10.58235, 286, (3.70299, 0.87935, 0.00095892)))
# four sensors at 100 Hz: exact matching ends on the message after one sensor's lost sample, with nothing queued;
# the old clock never saw that message and the new one had no stamp before it: the loss was counted by neither
@example(Case([SensorPlan(rate=100.0, jitter=0.0004, steps=[(5.33429, 0.028982)], silences=[(4.03279, 6.00516)]),
               SensorPlan(rate=100.0, jitter=0.0004, loss=0.02), SensorPlan(rate=100.0, jitter=0.0004),
               SensorPlan(rate=100.0, jitter=0.0004, loss=0.02)], 12.00516, 3610))
# two sensors of one clock at 50 Hz stepping back a second together, then one of them a second more, a second later:
# its second jump left the stamps the other's first had left, and it took that for one clock's jump (no step: a
# second off for the rest); the same stamps a second apart in time are another instant (the other's base then)
@example(Case([SensorPlan(rate=50.0, jitter=0.0016, steps=[(4.32722, -1.0), (5.32722, -1.0)], stalls=[(2.58864, 0.73858, False)]),
               SensorPlan(rate=50.0, jitter=0.0016, steps=[(4.32722, -1.0)],
                          stalls=[(2.58864, 0.73858, False), (5.32722, 0.2, False)])], 17.96103, 0))
# three sensors at 200 Hz: one steps back a second and forward again a second later, from the stamps another
# sensor's step forward had left a second before (the receiver busy meanwhile): taken for that jump, a second off
@example(Case([SensorPlan(rate=200.0, phase=0.000683, jitter=0.0001, steps=[(2.0, -4.23648)]),
               SensorPlan(rate=200.0, phase=0.004614, ppm=87.6, jitter=0.0001, steps=[(6.92208, -1.0), (7.92208, 1.0)],
                          duplicates=[2.15565]),
               SensorPlan(rate=200.0, phase=0.000244, jitter=0.0001, steps=[(6.92208, 1.0), (7.92208, 1.0)],
                          duplicates=[2.15565])], 16.98675, 55403, (6.75988, 0.30993, 0.00091949)))
# four sensors at 20 Hz with 4 ms stamp jitter, one silent 2.8 s and stepping 19 s ahead 2 s after: the silence,
# counted in a short median 3 % off, put two periods too many into its grid, whose span then gave a period 1.6 %
# short, and the step was placed 10 ms early (16.9 ms pairing against a 13 ms bound). A pause starts the grid again
@example(Case([SensorPlan(rate=20.0, phase=0.02657, jitter=0.004), SensorPlan(rate=20.0, phase=0.04582, ppm=51.6, jitter=0.004),
               SensorPlan(rate=20.0, ppm=20.2, jitter=0.004),
               SensorPlan(rate=20.0, jitter=0.004, steps=[(4.0141, -0.2219), (9.9263, 19.1007)],
                          silences=[(5.0142, 7.8091)])], 17.6105, 4386))
# four sensors at 20 Hz with 4 ms stamp jitter: one steps 17.5 s ahead, then 0.2 s back a second later. The second
# step went onto the grid of the one-second segment between, whose period (its two ends' jitter over 11 periods) was
# 1.3 % long: placed 12.5 ms late (14.1 ms pairing against a 13 ms bound). The grids before a step now pool their
# spans and periods (the sensor samples at the rate it had)
@example(Case([SensorPlan(rate=20.0, phase=0.03864, ppm=-36.8, jitter=0.004, late=[(3.42714, 0.15657, 1.35693, 0.73981)],
                          depth=100),
               SensorPlan(rate=20.0, phase=0.01494, jitter=0.004, loss=0.02, steps=[(7.11269, 1.86637)],
                          silences=[(2.75272, 3.91703)], stalls=[(8.11269, 1.7232, True)],
                          late=[(13.76012, 0.40862, 2.92404, 0.50653)], depth=100),
               SensorPlan(rate=20.0, phase=0.01355, jitter=0.004, steps=[(2.26009, 17.45857), (3.26009, -0.20531)],
                          late=[(16.56463, 0.33333, 2.38053, 0.39715)]),
               SensorPlan(rate=20.0, jitter=0.004, loss=0.02, steps=[(2.0, -16.05859)],
                          late=[(18.63652, 0.43326, 0.49585, 0.36059)])], 26.90637, 403))
def test_every_published_set_stands_for_one_true_instant(case: Case) -> None:
    check_case(case)


def check_case(case: Case) -> None:
    """Offline and live on one generated recording: every published set stands for one true instant (or is
    interpolated to it), the clean samples are covered, the two paths give the same sets and count every message."""
    streams = streams_of(case)
    offered = sum(len(s.stamps) for s in streams)
    batch, stats, mode = offline(streams)
    assert stats.used + stats.dropped() == offered, stats.describe()
    published = check_sets(case, batch.vectors, f"offline ({mode})")
    sets, sync = live(streams)
    check_coverage(case, streams, published, mode, revised="exact matching ended" in sync.reason)
    assert sync.stats.used + sync.stats.dropped() + sync.pending == offered
    check_sets(case, np.array([s.values for s in sets]).reshape(-1, len(streams), 3), "live")
    n = len(sets)
    assert len(batch) - n <= sync.pending + 5, (n, len(batch), sync.pending)  # live never saw the end
    assert np.array_equal(batch.stamps[:n], np.array([s.stamps for s in sets], dtype=np.int64).reshape(n, -1))
    assert np.array_equal(batch.vectors[:n], np.array([s.values for s in sets]).reshape(n, -1, 3))
    assert sync.mode == mode
    check_lost(case, streams, sync)


def check_pairing(case: Case) -> None:
    """Offline and live on one generated recording: every published set stands for one true instant (or is
    interpolated to it), and the two paths give the same sets in the same mode."""
    streams = streams_of(case)
    batch, _, mode = offline(streams)
    check_sets(case, batch.vectors, f"offline ({mode})")
    sets, sync = live(streams)
    check_sets(case, np.array([s.values for s in sets]).reshape(-1, len(streams), 3), "live")
    n = len(sets)
    assert np.array_equal(batch.stamps[:n], np.array([s.stamps for s in sets], dtype=np.int64).reshape(n, -1))
    assert sync.mode == mode


@st.composite
def hidden_steps(draw: st.DrawFn, mixed: bool = False) -> Case:
    """A receiver blocked for a while, then draining its queue, with one sensor's stamps stepping forward while it
    was blocked by anything from a few periods to the block's length: the queue's delay hides the step from the
    receipts until they are on time again (a pause of the same size looks the same until then). ``mixed``: each
    sensor at a rate of its own. Drawn by the benchmark (benchmarks/bench_stream_properties.py) and, a few
    derandomised draws, by the suite."""
    choices = [20.0, 40.0, 50.0, 100.0, 200.0] if mixed else [20.0, 50.0, 100.0, 200.0]
    rate = draw(st.sampled_from(choices))
    sensors = draw(st.integers(2, 4))
    rates = [draw(st.sampled_from(choices)) if mixed else rate for _ in range(sensors)]
    jitter = draw(st.sampled_from([0.0, 0.0004]))
    start, length = draw(st.floats(3.0, 5.0)), draw(st.floats(0.5, 2.0))
    at = start + draw(st.floats(0.05, 0.95)) * length
    size = draw(st.floats(2.6 / rate, 0.95 * length))
    which = draw(st.integers(0, sensors - 1))
    rates[which] = rate  # (the step at least 2.6 of its sensor's periods)
    plans = [SensorPlan(rate=rates[k], jitter=jitter, loss=draw(st.sampled_from([0.0, 0.02])),
                        steps=[(at, size)] if k == which else []) for k in range(sensors)]
    service = draw(st.floats(0.3, 0.95)) / sum(rates)
    return Case(plans, start + length + 6.0, draw(st.integers(0, 2**31 - 1)), (start, length, service))



@pytest.mark.parametrize("size", [-0.05, -0.7, -2.0, 0.3])
@pytest.mark.parametrize("one_clock", [False, True])
def test_a_step_of_the_stamps_while_a_sensor_is_silent_is_placed_by_its_arrivals(size: float, one_clock: bool) -> None:
    """A sensor silent from 4 to 8 s whose clock stepped by ``size`` at 5 s (alone, or with the other sensor's,
    one clock stamping both): it resumes with stamps that cover 4 s plus the step while its arrivals saw 4 s
    pass. A step back (2.5 periods to 2 s at 50 Hz) was taken for a shorter pause and that sensor paired the step
    off for the rest of the recording; a step forward was seen already."""
    plans = [SensorPlan(rate=50.0, jitter=0.0004, steps=[(5.0, size)] if one_clock else []),
             SensorPlan(rate=50.0, jitter=0.0004, steps=[(5.0, size)], silences=[(4.0, 8.0)])]
    check_case(Case(plans, 14.0, 5))


@pytest.mark.parametrize("size", [-0.1, -0.33])
@pytest.mark.parametrize("rate", [20.0, 50.0])
def test_a_step_back_in_a_silence_is_seen_while_another_topic_is_late_on_its_own(size: float, rate: float) -> None:
    """A sensor silent from 4 to 4.5 s whose stamps step back by ``size`` meanwhile, while the other sensor's topic is
    taken 0.5 s late from 2 s for 3 s more: that topic's lateness is its own (its order broken against the first
    sensor's on-time messages), not a receiver's queue. Read as one, the receiver looked late with every sensor, so
    the arrivals' trail after the silence was put down to a queue and the step back taken for a pause (paired the
    step's size off for the rest)."""
    check_case(Case([SensorPlan(rate=rate, silences=[(4.0, 4.5)], steps=[(4.2, size)]),
                     SensorPlan(rate=rate, late=[(2.0, 0.5, 3.0, 0.5)])], 12.0, 0))


@st.composite
def silent_steps(draw: st.DrawFn) -> Case:
    """One sensor silent for a while (0.3-4 s) whose stamps step either way inside the silence (from 2.6 periods to
    3 s), alone or with another sensor's (one clock stamping both): on resuming, its stamps cover the silence plus
    the step while its arrivals saw the silence pass."""
    rate = draw(st.sampled_from([20.0, 50.0, 100.0, 200.0]))
    sensors = draw(st.integers(2, 4))
    jitter = draw(st.sampled_from([0.0, 0.0004]))
    start, length = draw(st.floats(3.0, 5.0)), draw(st.floats(0.3, 4.0))
    at = start + draw(st.floats(0.05, 0.95)) * length
    size = _signed(draw, 2.6 / rate, 3.0)
    which = draw(st.integers(0, sensors - 1))
    partner = draw(st.one_of(st.none(), st.integers(0, sensors - 1).filter(lambda k: k != which)))
    plans = [SensorPlan(rate=rate, jitter=jitter, loss=draw(st.sampled_from([0.0, 0.02])),
                     steps=[(at, size)] if k in (which, partner) else [],
                     silences=[(start, start + length)] if k == which else []) for k in range(sensors)]
    return Case(plans, start + length + 6.0, draw(st.integers(0, 2**31 - 1)))


@settings(max_examples=EXAMPLES // 2, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(silent_steps())
# two sensors of one clock at 20 Hz, one silent while the clock steps back 1 s; a third sensor, losing samples, had
# jumped over two lost ones to the very stamp the silent one resumed on (a second later): the silent one took that
# jump for one clock's and was paired a second off for the rest (lost samples are now no jump of the clock)
@example(Case([SensorPlan(rate=20.0, steps=[(3.0685, -1.0)]), SensorPlan(rate=20.0),
               SensorPlan(rate=20.0, steps=[(3.0685, -1.0)], silences=[(3.013, 4.1237)]), SensorPlan(rate=20.0, loss=0.02)],
              10.1237, 100958))
def test_a_step_of_any_size_inside_a_silence_keeps_every_set_one_instant(case: Case) -> None:
    """Every published set stands for one true instant, live as offline, whichever way the stamps of a silent
    sensor (and of another sensor on its clock) stepped while it was silent. (The coverage and the loss counts,
    which :func:`check_case` checks too, are the general draw's: in the benchmark's 150 draws of this family 4
    fell short of the coverage on short 20 Hz recordings.)"""
    check_pairing(case)


@settings(max_examples=EXAMPLES // 2, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(hidden_steps())
# three sensors at 200 Hz, one stepping 0.38 s ahead while the receiver is blocked: its segment, placed right, lost
# two samples six messages on, and that gap was taken for the old sequence going on (the step a few bad stamps):
# 380 ms off for the rest. The old sequence goes on only where it needs no more lost samples than the new one
@example(Case([SensorPlan(rate=200.0), SensorPlan(rate=200.0), SensorPlan(rate=200.0, loss=0.02, steps=[(3.5543, 0.38046)])],
              9.7445, 3, (3.0, 0.7445, 0.0011049)))
def test_a_step_a_blocked_receiver_hides_keeps_every_set_one_instant(case: Case) -> None:
    """Every published set stands for one true instant, live as offline, where one sensor's stamps step forward
    while the receiver is blocked. (A few of the family still fail, 1-2 of 200 in the benchmark's draws: see
    docs/synchronisation.md. These draws fail on the code that decided a suspect before the queue's order was
    read.)"""
    check_pairing(case)


@settings(max_examples=EXAMPLES // 2, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(hidden_steps(mixed=True))
# 200 Hz stepping 0.93 s while the receiver is blocked 1 s, the other sensor at 20 Hz: a suspect waited for the
# other's next message in the queue for 4 of its own, a fifth of the other's period, then was decided without the
# queue's order and the step taken for a pause (paired 0.93 s off for the rest)
@example(Case([SensorPlan(rate=200.0, steps=[(3.8027, 0.9324)]), SensorPlan(rate=20.0, loss=0.02)],
              10.38, 2, (3.3815, 0.99999, 0.0042626)))
# the same at 100 Hz beside 20 Hz, a 0.23 s step: 0.23 s off
@example(Case([SensorPlan(rate=20.0, jitter=0.0004, loss=0.02),
               SensorPlan(rate=100.0, jitter=0.0004, loss=0.02, steps=[(4.096, 0.23132)])],
              10.9, 505, (3.8755, 1.0262, 0.0041667)))
# 200 Hz stepping 0.81 s as a 1 s block ends, the other sensor at 100 Hz and drained at 1.2 ms a message: the other's
# messages around the step's first came 1.2 ms apart, a tenth of its period, so they were read as its driver's
# backlog and bounded nothing, with no third sensor late to show the receiver's drain (the step taken for a pause,
# 0.81 s off); the step's own sensor late too shows it
@example(Case([SensorPlan(rate=100.0), SensorPlan(rate=200.0, loss=0.02, steps=[(4.6827, 0.80905)])],
              10.74, 0, (3.697, 1.0442, 0.0011511)))
# the same with 200 Hz beside 50 Hz, a 0.3 s step: 0.3 s off
@example(Case([SensorPlan(rate=200.0, loss=0.02, steps=[(3.025, 0.3)]), SensorPlan(rate=50.0)], 9.5, 0,
              (3.0, 0.5, 0.0012)))
def test_a_step_a_blocked_receiver_hides_at_mixed_rates_keeps_every_set_one_instant(case: Case) -> None:
    """As :func:`test_a_step_a_blocked_receiver_hides_keeps_every_set_one_instant`, each sensor at a rate of its own
    (20-200 Hz): a suspect waits for a slower sensor's message in the queue as long as two of its periods take."""
    check_pairing(case)


@st.composite
def late_topics(draw: st.DrawFn) -> Case:
    """A general recording (:func:`cases`) where one or more sensors' topics are taken late for a while: none of
    its messages for 20-600 ms (a loaded machine serving other topics), then at the sensor's pace, so they stay that
    late, for up to 3 s more, then drained a little faster than they come (a third of them with a history of 100
    messages, the nodes' default: those that overflow it meanwhile lost, the oldest first). The stamps are right
    throughout: a rule
    that reads a topic's delay as a step of its stamps pairs that sensor off. Drawn by the benchmark and, a few
    derandomised draws, by the suite."""
    case = draw(cases())
    chosen = draw(st.lists(st.integers(0, len(case.plans) - 1), min_size=1, max_size=len(case.plans), unique=True))
    for k in chosen:
        start, block, hold, drain = (draw(st.floats(2.0, max(2.0, case.duration - 4.0))), draw(st.floats(0.02, 0.6)),
                                     draw(st.floats(0.0, 3.0)), draw(st.floats(0.3, 0.95)))
        case.plans[k] = apart(case.plans[k], start - 1.0, start + block + hold + block / (1.0 - drain) + 1.0)
        case.plans[k].late.append((start, block, hold, drain))
        case.plans[k].depth = draw(st.sampled_from([None, None, 100]))
    return case


def apart(plan: SensorPlan, a: float, b: float) -> SensorPlan:
    """``plan`` without its faults between ``a`` and ``b`` s (a topic's delay on its own: the stamps' faults while
    the receipts are late by a delay that holds are another question)."""
    def out(t0: float, t1: float) -> bool:
        return t1 < a or t0 > b

    return replace(plan, steps=[f for f in plan.steps if out(f[0], f[0])],
                   glitches=[f for f in plan.glitches if out(f[0], f[0])],
                   duplicates=[t for t in plan.duplicates if out(t, t)], bad=[t for t in plan.bad if out(t, t)],
                   silences=[f for f in plan.silences if out(*f)], stalls=[f for f in plan.stalls if out(f[0], f[0] + f[1])])


HIDDEN_BY_A_QUEUE = {
    # 100 Hz, two sensors: a step of 23 whole periods while the receiver is blocked 0.78 s (a gap on the grid)
    "whole periods": Case([SensorPlan(rate=100.0, steps=[(5.4989, 0.23004)]), SensorPlan(rate=100.0)], 11.7,
                          2147483647, (4.9207, 0.784, 0.003644)),
    # 20 Hz, three sensors: a step of 0.75 s about as large as the queue's delay, so its first message looks on time
    "as large as the delay": Case([SensorPlan(rate=20.0, loss=0.02), SensorPlan(rate=20.0),
                                   SensorPlan(rate=20.0, steps=[(4.4472, 0.75175)])], 10.86, 10, (4.0365, 0.8214, 0.014162)),
    # 50 Hz, two sensors: two samples lost before a 2.6-period step, the drained arrivals keeping no time
    "after lost samples": Case([SensorPlan(rate=50.0, loss=0.02, steps=[(3.025, 0.052)]), SensorPlan(rate=50.0, loss=0.02)],
                               9.5, 59, (3.0, 0.5, 0.0052616)),
    # 50 Hz, two sensors losing samples, a receiver blocked 1.5 s: a 0.94 s step, and the other sensor's next message in
    # the queue came only after more than one of the stepping sensor's own. Decided at the first of them, without the
    # queue's order, the step was taken for a pause (paired 0.94 s off for the rest): the wait goes on for up to
    # WAIT_MESSAGES of its own (a mutant ending it at the first lived through the suite; drawn from hidden steps)
    "the partner's message two behind": Case([SensorPlan(rate=50.0, jitter=0.0004, loss=0.02, steps=[(3.5, 0.94)]),
                                              SensorPlan(rate=50.0, jitter=0.0004, loss=0.02)],
                                             10.5, 2, (3.0, 1.5, 0.003)),
    # the same, the step 0.24 s later on the other sensor: the first sensor's own gap in the drain, read from the
    # queue's order, is no jump a queue hides (it had been held until its arrivals came on time, and nothing of it
    # told the step's sensor the queue's order)
    "while another's gap is placed": Case([SensorPlan(rate=50.0, loss=0.02),
                                           SensorPlan(rate=50.0, loss=0.02, steps=[(3.2647, 0.052)])],
                                          9.5, 59, (3.0, 0.5, 0.0052616)),
    # 50 Hz, three sensors sampled apart with 1.6 ms jitter, a receiver blocked 1.6 s that then drains slower than the
    # sensors fill its queue (never catching up): one sensor's stamps 1.5 periods ahead as it blocks. The gap looked
    # like a lost sample seen late and was taken (30 ms off for the rest); it lies half a period off the sensor's
    # grid, so it is held and decided by the queue's order
    "half a period off the grid": Case([SensorPlan(rate=50.0, ppm=99.0, jitter=0.0016),
                                        SensorPlan(rate=50.0, phase=0.012136, ppm=63.3, jitter=0.0016),
                                        SensorPlan(rate=50.0, phase=0.018162, ppm=92.2, jitter=0.0016, steps=[(2.0, 0.03)])],
                                       8.0, 5166, (2.00001, 1.5941, 0.0061986)),
    # 200 Hz, two sensors sampled together losing samples, drained at 1 ms a message: a 13 ms step (2.6 periods) whose
    # first message came right after its own previous (the other sensor's sample between them lost), a bunch; the other
    # sensor late too shows the receiver's drain, whose order is read
    "its own previous in the bunch": Case([SensorPlan(rate=200.0, loss=0.02),
                                           SensorPlan(rate=200.0, loss=0.02, steps=[(3.53796, 0.013)])],
                                          9.7583, 13159458, (3.20602, 0.55224, 0.0010119)),
    # 200 Hz, three sensors sampled together, a receiver blocked 0.9 s that then drains at 0.5 ms a message: a 0.47 s
    # step of the one losing samples. Another sensor's two messages around the step's first, 1 ms apart, came bunched
    # and were not read for the queue's order (a driver's backlog); the third sensor late too shows the receiver's
    # drain, whose order is that of the messages' coming
    "a fast drain": Case([SensorPlan(rate=200.0, jitter=0.0004),
                          SensorPlan(rate=200.0, jitter=0.0004, loss=0.02, steps=[(3.0868042689, 0.4664846382)]),
                          SensorPlan(rate=200.0, jitter=0.0004)], 9.9098933464, 1681141, (3.0, 0.9098933464, 0.0005)),
    # 200 Hz, four sensors, a receiver blocked 1.56 s as one sensor's stamps step 1 s back, then draining barely faster
    # than the sensors fill it (0.87 ms a message against 1.25), the stepping sensor's driver stalling a second later
    # (its backlog restamped). The queue's order bounded the new segment at its first decision, but not tightly, so it
    # waited for the arrivals to catch up; they never did before the stall ended the segment, 200 messages on, when
    # the others' arrivals that had ordered its first messages were gone: placed by its own, 1.26 s late. Now by the
    # order its first decision read, where that is earlier (a drawn recording of the benchmark, seed 66, simplified)
    "a drain outlasting the others' arrivals": Case([SensorPlan(rate=200.0, jitter=0.0004),
                                                     SensorPlan(rate=200.0, jitter=0.0004),
                                                     SensorPlan(rate=200.0, phase=0.0028768, ppm=-10.9, jitter=0.0004),
                                                     SensorPlan(rate=200.0, phase=0.0011629, ppm=11.1, jitter=0.0004,
                                                                steps=[(2.0, -1.0)], stalls=[(3.0, 2.7921, True)])],
                                                    9.0, 310443, (2.00001, 1.5638, 0.00086869)),
}


@pytest.mark.parametrize("name", list(HIDDEN_BY_A_QUEUE))
def test_a_step_a_blocked_receiver_hides_is_read_from_the_queues_order(name: str) -> None:
    """A receiver blocked, then draining its queue, while one sensor's stamps step forward: every arrival is late, so
    the step looks like a pause, and the sensor was paired the step's size off for the rest of the recording. The
    queue delivers in the order the messages came, so another sensor's message delivered after the step's first one
    tells when that one came at the latest (and one delivered before, at the earliest): its decision waits for one,
    and the new segment is placed between those bounds. Offline and live, every set one instant, all counted."""
    check_case(HIDDEN_BY_A_QUEUE[name])


@settings(max_examples=EXAMPLES // 2, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(late_topics())
# two sensors at 20 Hz, the second's topic taken 0.5 s late for 3 s; the first silent for 0.5 s meanwhile, on time
# before and after: the second's late messages, read as a busy receiver's queue, put the first's resumption 0.45 s
# early, a step forward, and it was paired 0.45 s off for the rest
@example(Case([SensorPlan(rate=20.0, silences=[(4.0, 4.5)], late=[(2.0, 0.25, 0.0, 0.5)]),
               SensorPlan(rate=20.0, late=[(2.0, 0.5, 2.0, 0.5)])], 12.0, 0))
# a third sensor's topic 0.4 s late while the second's driver stalled and stamped its backlog on delivery, the first
# on time: the third's order placed the second's next segment 0.4 s early (paired 0.4 s off for the rest)
@example(Case([SensorPlan(rate=100.0, jitter=0.0008, loss=0.02, duplicates=[2.3398161103469013]),
               SensorPlan(rate=100.0, jitter=0.0008, stalls=[(5.120513212128063, 2.718521811052925, True),
                                                            (13.406881279464194, 2.6030891035767594, True)],
                          bad=[12.037388892060267]),
               SensorPlan(rate=100.0, jitter=0.0008, glitches=[(2.5926871892539562, -18.106564065838338)],
                          late=[(15.507315762265074, 0.40332135754830667, 0.5, 0.5091040009671908)])],
              23.11309625173192, 63480, (18.775435442173293, 1.4899417077396129, 0.001630583394108103)))
# two sensors at 200 Hz: the first's topic taken 0.57 s late for 2.4 s while the second's driver stalled 2.58 s and
# stamped its backlog on delivery (dropped). With a receiver blocked 1.5 s meanwhile no arrival placed the second's
# next segment, which went one period after its last sample, as if nothing had been sampled (2.59 s off for the
# rest); without it, the first's late messages read as a queue's order put it 0.55 s early. The backlog held the
# gap's samples: the segment goes at least that many periods on, and where its stamps are as far on (its lost
# samples allowed), on its stamps
@example(Case([SensorPlan(rate=200.0, jitter=0.0001, loss=0.02, late=[(2.00001, 0.569, 2.383, 0.52)]),
               SensorPlan(rate=200.0, jitter=0.0001, loss=0.02, stalls=[(2.0, 2.58, True)])], 12.0, 849,
              (2.43, 1.54, 0.002)))
@example(Case([SensorPlan(rate=200.0, jitter=0.0001, loss=0.02, late=[(2.00001, 0.569, 2.383, 0.52)]),
               SensorPlan(rate=200.0, jitter=0.0001, loss=0.02, stalls=[(2.0, 2.58, True)])], 12.0, 849))
# two sensors at 100 Hz: the first silent 1.8 s, on time after; the second's topic 20 ms late meanwhile, at its own
# pace: its messages, read as a receiver's queue, put the first's resumption two periods early (20 ms off for the
# rest). A queue drained faster than it filled delivers what it held closer together than stamped: messages that
# kept their stamps' pace came through none
@example(Case([SensorPlan(rate=100.0, jitter=0.0008, silences=[(3.0, 4.8)]),
               SensorPlan(rate=100.0, jitter=0.0008, late=[(3.3, 0.02, 2.2, 0.32)])], 13.0, 1))
# two sensors at 200 Hz: the second's topic taken 0.6 s late, its history of 100 overflowing (20 samples lost), then
# drained at 0.42 periods a message: its arrivals behind its stamps read as a step back, placed by the stamps alone
# before they caught up, one period after its last sample (100 ms off). Held while they catch up, they place it on
# its stamps, and the 20 samples count as lost
@example(Case([SensorPlan(rate=200.0, jitter=0.0001),
               SensorPlan(rate=200.0, jitter=0.0001, late=[(4.8, 0.6, 0.0, 0.42)], depth=100)], 12.0, 1))
# the same, the topic then served 1.3 s at its own pace, 0.5 s late, before it drained, 2 % of its samples lost: its
# arrivals trail the stamps as after a step back in a silence, steadily, and the segment went where they put it (0.5 s
# off for the rest). Held until the topic drains (as long as a message may wait), two lost samples in a row going on
# from it, its least delayed arrival puts it back on its stamps
@example(Case([SensorPlan(rate=200.0, jitter=0.0001),
               SensorPlan(rate=200.0, jitter=0.0001, loss=0.02, late=[(4.8, 0.55, 1.3, 0.5)], depth=100)], 12.0, 2))
def test_a_topic_taken_late_for_a_while_keeps_every_set_one_instant(case: Case) -> None:
    """A loaded machine delays one topic's messages alike for a while, the stamps right throughout: every published
    set stands for one true instant, the clean samples are covered, live and offline agree and losses are counted
    (all of :func:`check_case`)."""
    check_case(case)


def test_the_oracle_sees_a_wrong_pairing() -> None:
    """The invariant is not vacuous: one sensor's stamps a period late make every set wrong."""
    case = Case([SensorPlan(rate=50.0) for _ in range(2)], 5.0, 1)
    streams = streams_of(case)
    streams[1].stamps += NS_PER_S // 50
    batch, _, _ = offline(streams)
    spreads = [float(np.ptp(set_instants(v))) for v in batch.vectors]
    assert len(spreads) > 200 and min(spreads) > 0.019


# -- side streams ------------------------------------------------------------------------------------
@st.composite
def side_streams(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """A temperature stream as a topic delivers it (stamps ns in delivery order, values deg C, which samples
    are true values) and a tolerance (ns): a regular rhythm with neighbours swapped, pauses, values out
    of range or not a number, and single stamps far off the sequence either way (from half again as far as
    the rule calls far, once the stream's rhythm is known, to three years)."""
    rate = draw(st.sampled_from([0.5, 2.0, 10.0, 50.0]))
    far = max(side.FAR_MIN, side.FAR_PERIODS * NS_PER_S / rate) / NS_PER_S  # s: what the rule holds as far off
    n = draw(st.integers(30, 300))
    t = (np.arange(n) / rate + draw(st.floats(0.0, 1.0))) * 1e9 + START
    pauses = draw(st.lists(st.integers(5, n - 5), max_size=3, unique=True))
    for at in pauses:
        t[at:] += draw(st.floats(1.0, 60.0)) * 1e9
    t = np.round(t).astype(np.int64)
    values = np.asarray(draw(st.lists(st.floats(-40.0, 60.0), min_size=n, max_size=n)))
    true = np.ones(n, bool)
    faults = draw(st.lists(st.tuples(st.integers(3, n - 3), st.sampled_from(["swap", "range", "nan", "ahead",
                                                                            "behind"])), max_size=6,
                           unique_by=lambda f: f[0] // 3))
    done: list[int] = []
    for at, kind in faults:
        if any(abs(at - p) <= 2 for p in pauses + done):
            continue  # one fault at a time: a swap at a pause's edge is a glitch to any rule
        done.append(at)
        if kind == "swap":
            t[[at, at + 1]] = t[[at + 1, at]]
            values[[at, at + 1]] = values[[at + 1, at]]
        elif kind in ("range", "nan"):
            values[at] = draw(st.sampled_from([-300.0, 1e30, 151.0, -61.0])) if kind == "range" else np.nan
            true[at] = False
        elif at >= 6:  # (the first samples' rhythm is not yet known: only far beyond a minute is far there)
            t[at] += int(np.sign(0.5 - (kind == "behind")) * far * 10 ** draw(st.floats(np.log10(1.5), 7.0)) * 1e9)
            true[at] = False
    return t, values, true, int(draw(st.sampled_from([2.0, 10.0, 30.0])) * 1e9)


START = 1_700_000_000 * 1_000_000_000


@settings(max_examples=EXAMPLES * 4, derandomize=True, database=None, deadline=None)
@given(side_streams())
def test_a_side_stream_gives_each_set_its_latest_true_value_live_and_offline(stream: tuple) -> None:  # type: ignore[type-arg]
    """Every set gets the latest true sample stamped within the tolerance before it (never a value out of
    range, not a number, or stamped far off the sequence), and the live store (one sample at a time, in
    delivery order) gives what the offline rule gives; every sample counted once."""
    from magcal_ros.core.matching import LatestValues, accept_streams, match_latest
    from magcal_ros.core.temperature import TemperatureSamples

    stamps, values, true, tol = stream
    store = LatestValues(1, tol, keep_ns=10**18, check=side.TEMPERATURE.check)
    for s, v in zip(stamps.tolist(), values.tolist()):
        store.add(0, s, v)
    accepted, counts = accept_streams([TemperatureSamples("mag1", stamps, values)], side.TEMPERATURE.check)
    c = store.counts[0]
    assert c.received == len(stamps) and c.accepted + c.dropped() + c.held == c.received
    # each fault counted as what it is, live and offline, and every true sample taken (nothing else)
    low, high = side.TEMPERATURE_RANGE
    bad = int(np.sum(~np.isfinite(values)))
    out = int(np.sum((values < low) | (values > high)))  # (NaN compares false)
    want = (int(np.sum(true)), bad, out, int(np.sum(~true)) - bad - out)
    for got in (c, counts[0]):
        assert (got.accepted + got.held, got.nonfinite, got.out_of_range, got.glitch) == want, (got, want)
    assert sorted(accepted[0].stamps.tolist()) == sorted(stamps[true].tolist())
    sets = np.sort(np.random.default_rng(len(stamps)).integers(stamps[true].min(), stamps[true].max(), 200))
    offline, fresh = match_latest(sets, accepted, tol)
    ts, vs = stamps[true], values[true]
    order = np.argsort(ts, kind="stable")
    ts, vs = ts[order], vs[order]
    for t, got, ok in zip(sets.tolist(), offline[:, 0], fresh[:, 0]):
        live, live_ok = store.at(t)
        k = np.searchsorted(ts, t, side="right") - 1
        want_ok = k >= 0 and t - ts[k] <= tol
        assert ok == want_ok and (not ok or got == vs[k]), (t, got, vs[k] if k >= 0 else None)
        assert live_ok == [ok] and (not ok or live[0] == got)


@settings(max_examples=EXAMPLES * 2, derandomize=True, database=None, deadline=None)
@given(st.lists(st.lists(st.integers(-4, 4), min_size=1, max_size=150), min_size=2, max_size=4),
       st.sampled_from([500_000, 2_500_000, 20_000_000]), st.integers(0, 2**16))
def test_stamps_in_any_order_never_fail_and_every_message_is_counted(moves: list[list[int]], period: int,
                                                                      seed: int) -> None:
    """Each sensor's message ``i`` stamped on grid slot ``i + move`` (stamps that go back, repeat or cross a few
    periods), arriving a little after slot ``i``: live and offline, no exception, and every message ends in a
    set, a drop counter or (live) pending. (A sensor clock learnt from stamps that went back divided by a zero
    period.)"""
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000 * NS_PER_S
    streams = []
    for k, move in enumerate(moves):
        sensor = np.arange(len(move)) + np.array(move, dtype=np.int64)
        stamps = t0 + sensor * period
        receipts = t0 + np.arange(len(sensor), dtype=np.int64) * period + rng.integers(0, period, len(sensor))
        vectors = np.tile([2e-5, 1e-6 * (k + 1), 4e-5], (len(sensor), 1))
        streams.append(Stream(stamps, np.maximum.accumulate(receipts), vectors, np.zeros(len(sensor)),
                              np.ones(len(sensor), dtype=bool)))
    offered = sum(len(m) for m in moves)
    batch, stats, _ = offline(streams)
    assert stats.used + stats.dropped() == offered, stats.describe()
    sets, sync = live(streams)
    assert sync.stats.used + sync.stats.dropped() + sync.pending == offered, sync.stats.describe()
    assert np.all(np.diff([s.stamps[0] for s in sets]) > 0)

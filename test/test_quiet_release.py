"""Messages held for a sensor that then falls quiet: decided on the receiver's clock, not left waiting.

A live synchroniser holds some messages until the sensor's later ones decide them: a new segment's first
messages, a suspect stamp, a jump a busy receiver's queue may have hidden. At the end of a collection (the
crew's replay, a driver stopped) no later message comes, and before the fix every set of a collection whose
messages a queue delivered late stayed unformed until the next collection started: a calibration node
formed none of 400 sets for three minutes on a loaded test machine. Now a node asks
``StreamSynchronizer.release_quiet(now)`` every half second, and a sensor quiet for ``HOLD_NS`` has its held
messages decided as at the end of its stream: what the next message would have decided, or a recording's
end does offline.

The recordings: sensors on one wall clock (as a driver restamping at the instants due), collections of a
few hundred sets apart by pauses of seconds, a receiver busy through part or all of a collection that then
drains its queue. The truth is each reading's instant (:mod:`stream_oracle`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from stream_oracle import (START_NS, SensorPlan, Stream, arrivals, busy_receiver, make_stream, set_instants,
                           spread)

from magcal_ros.core.matching import LatestValues
from magcal_ros.core.sync import StreamSynchronizer, stream_synchronizer
from magcal_ros.core.sync_rules import HOLD_NS

NAMES = ("mag1", "mag2", "mag3", "mag4")
EXAMPLES = 12
STILL_NS = HOLD_NS + 1
"""How long after the latest arrival the receiver's clock is read: just past the hold."""


def collections(rate: float, sizes: list[int], pauses: list[float], phases: list[float],
                rng: np.random.Generator) -> tuple[list[Stream], list[tuple[float, float]]]:
    """Four sensors at ``rate`` Hz (each at its ``phases`` s into the period) recording ``sizes`` samples at a
    time, ``pauses`` s apart; (streams, the collections' spans in s)."""
    spans, t = [], 1.0
    for n, pause in zip(sizes, pauses):
        spans.append((t, t + n / rate))
        t += n / rate + pause
    silences = [(0.0, spans[0][0])] + [(a[1], b[0]) for a, b in zip(spans, spans[1:])]
    streams = [make_stream(SensorPlan(rate=rate, phase=p, delay=0.0005, transport=0.0003,
                                      silences=silences), spans[-1][1], rng) for p in phases]
    return streams, spans


def fed(sync: StreamSynchronizer, streams: list[Stream], ticks: Sequence[int] = (), start: int = 0,
        stop: int | None = None) -> list[Any]:
    """The messages that arrived from ``start`` to before ``stop`` (ns; None: the end) in arrival order, and
    ``release_quiet`` at each of ``ticks`` (ns) in that time once it comes; the sets formed."""
    sets: list[Any] = []
    pending = sorted(t for t in ticks if start <= t and (stop is None or t < stop))
    for receipt, k, i in arrivals(streams):
        if receipt < start or stop is not None and receipt >= stop:
            continue
        while pending and pending[0] <= receipt:
            sets += sync.release_quiet(pending.pop(0))
        s = streams[k]
        sets += sync.add(k, int(s.stamps[i]), *s.vectors[i].tolist(), receipt)
    for t in pending:
        sets += sync.release_quiet(t)
    return sets


def in_span(sets: list[Any], span: tuple[float, float]) -> int:
    """Sets whose members' instants lie in ``span`` (s after the start)."""
    return sum(1 for x in sets if span[0] - 1e-3 <= set_instants(x.values).min() <= span[1] + 1e-3)


def synchronizer() -> StreamSynchronizer:
    return stream_synchronizer(list(NAMES), max_reading=2e-3)


def busy_through(streams: list[Stream], span: tuple[float, float], before: float, after: float,
                 service: float) -> None:
    """The receiver takes nothing from ``before`` s ahead of ``span`` to ``after`` s past its end, then drains
    its queue at ``service`` s a message."""
    start = span[0] - before
    busy_receiver(streams, start, span[1] + after - start, service)


def stalled() -> tuple[list[Stream], list[tuple[float, float]]]:
    """Three collections at 400 Hz, all four sensors stamped alike, the receiver busy from the end of the second
    until after the third (0.7 s later), then draining its queue at 66 us a message."""
    streams, spans = collections(400.0, [800, 500, 400], [2.5, 0.7, 0.0], [0.0] * 4, np.random.default_rng(11))
    busy_through(streams, spans[-1], 0.95, 0.22, 6.6e-5)
    return streams, spans


def true_sets(streams: list[Stream], span: tuple[float, float]) -> int:
    """Instants in ``span`` (s) every sensor sampled (the sensors sample together here)."""
    return min(int(np.sum((s.instants >= span[0] - 1e-3) & (s.instants <= span[1] + 1e-3))) for s in streams)


def latest(streams: list[Stream]) -> int:
    return max(int(s.receipts[-1]) for s in streams)


def test_a_collection_a_busy_receiver_delivered_late_forms_once_its_sensors_are_quiet() -> None:
    """The case seen on a loaded machine: 400 sets at 400 Hz, all four sensors stamped alike, the receiver busy
    from before the collection until after it. Every sensor's segment is held as a jump the queue may hide;
    nothing forms from the messages alone, and every set forms, each of one instant, once the receiver's clock
    passes the hold. Before the hold has passed, nothing is released."""
    streams, spans = stalled()
    sync = synchronizer()
    sets = fed(sync, streams)
    assert in_span(sets, spans[0]) == true_sets(streams, spans[0]) and \
        in_span(sets, spans[1]) == true_sets(streams, spans[1])
    assert in_span(sets, spans[-1]) == 0 and sync.pending > 1590  # the stall: everything held
    assert sync.release_quiet(latest(streams) + HOLD_NS - 1) == []
    released = sync.release_quiet(latest(streams) + STILL_NS)
    assert in_span(released, spans[-1]) == len(released) == true_sets(streams, spans[-1])
    assert max(spread(x.values) for x in released) < 1e-6
    assert sync.pending == 0


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(rate=st.sampled_from([100.0, 200.0, 400.0]),
       sizes=st.lists(st.integers(150, 500), min_size=2, max_size=3),
       pause=st.floats(0.5, 3.0), apart=st.booleans(),
       lead=st.floats(0.0, 1.0), after=st.floats(-0.5, 0.5), service=st.floats(5e-5, 6e-4),
       seed=st.integers(0, 2**16))
@example(rate=400.0, sizes=[500, 400], pause=0.7, apart=False, lead=0.79, after=0.22, service=6.6e-5, seed=11)
def test_a_quiet_release_decides_as_the_next_collection_would(rate: float, sizes: list[int], pause: float,
                                                               apart: bool, lead: float, after: float,
                                                               service: float, seed: int) -> None:
    """For generated collections with the receiver busy through part or all of the last but one (from ``lead`` of
    the pause and half a second before it, into the collection before when that is longer than the pause): the sets
    formed when the receiver's clock passes the hold after that collection (live, a node's timer) are the
    sets the next collection's messages would have released, the same in number, members and order; the
    collection is whole by then (its sets all formed, each of one instant), whatever its messages' arrivals."""
    rng = np.random.default_rng(seed)
    phases = list(rng.uniform(0.0, 1.0 / rate, 4)) if apart else [0.0] * 4
    quiet = HOLD_NS / 1e9 + 2.0  # the last collection comes once the receiver's clock has passed the hold
    streams, spans = collections(rate, [*sizes, 120], [pause] * (len(sizes) - 1) + [quiet, 0.0], phases, rng)
    span = spans[-2]
    busy_through(streams, span, lead * (pause + 0.5), max(after, -0.5 * (span[1] - span[0])), service)
    end = max(int(s.receipts[np.searchsorted(s.instants, span[1] + 1e-9) - 1]) for s in streams)
    ticks = list(range(end + 1, end + STILL_NS + 10**9, 500_000_000))  # every half second, as a node does
    next_one = min(int(s.receipts[np.searchsorted(s.instants, spans[-1][0] - 1e-9)]) for s in streams)
    without = fed(synchronizer(), streams)
    sync = synchronizer()
    by_then = fed(sync, streams, ticks, stop=next_one)
    with_ticks = by_then + fed(sync, streams, start=next_one)
    assert [x.stamps for x in with_ticks] == [x.stamps for x in without]
    assert in_span(by_then, span) >= true_sets(streams, span) - 2, (in_span(by_then, span), true_sets(streams, span))
    assert max(spread(x.values) for x in with_ticks) < 0.25 / rate


def interpolating() -> StreamSynchronizer:
    return stream_synchronizer(list(NAMES), mode="interpolate", max_reading=2e-3)


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(rate=st.sampled_from([50.0, 100.0, 400.0]), size=st.integers(4, 40),
       phases=st.lists(st.floats(0.05, 0.45), min_size=3, max_size=3), seed=st.integers(0, 2**16))
@example(rate=50.0, size=28, phases=[0.1, 0.2, 0.3], seed=5)
def test_a_stream_that_ends_while_its_clocks_learn_forms_its_sets_once_quiet(rate: float, size: int,
                                                                            phases: list[float], seed: int) -> None:
    """Interpolating, each sensor's sample clock learns its period from its first 32 intervals, holding those
    samples meanwhile. A stream that ends sooner (a short collection, or what follows a restart or a revision
    of the mode) waited live for samples that never came, and its sets never formed (offline the recording's
    end fits them). Once its sensors are quiet for the hold, the live synchroniser forms the sets offline
    forms, the same stamps, every instant but the edges' (the sensors sample ``phases`` of a period after the
    reference)."""
    rng = np.random.default_rng(seed)
    streams, _ = collections(rate, [size], [0.0], [0.0] + [p / rate for p in phases], rng)
    live = interpolating()
    before = fed(live, streams)
    sets = before + live.release_quiet(latest(streams) + STILL_NS)
    offline = interpolating()
    offline.add_streams([(s.stamps, s.vectors, s.receipts) for s in streams])
    batch = offline.pop(final=True)
    assert [x.stamps[0] for x in sets] == batch.stamps[:, 0].tolist()
    assert len(sets) >= size - 2 and len(before) < len(sets)
    assert max(spread(x.values) for x in sets) < 0.02 / rate  # interpolated to the reference's instant


def test_sets_after_a_revision_to_interpolation_form_once_the_sensors_are_quiet() -> None:
    """Seen over DDS: a node matching exactly (a replay whose sensors stamp alike) gets a second replay whose
    sensors stamp 0.2, 0.4 and 0.6 ms after the first, 60 sets at 50 Hz delivered at 400 sets/s. Exact
    matching ends at the 33rd set (the sensors' offsets moved) and interpolation learns each sensor's clock
    afresh: the last 28 sets waited for samples that never came (112 messages pending a minute later). Once
    the sensors are quiet for the hold they form; at most the set at the revision itself is lost (counted)."""
    rng = np.random.default_rng(5)
    sync = synchronizer()
    first, second = 1_780_000_000 * 10**9, 1_900_000_000 * 10**9 + 123_457
    messages = []
    for j in range(800):  # 400 Hz, stamped alike (+-0.1 ms), arriving 0.05-0.9 ms after
        for k in range(4):
            messages.append((k, first + j * 2_500_000 + (int(rng.integers(-100_000, 100_000)) if k else 0),
                             5 * 10**12 + j * 2_500_000 + int(rng.integers(50_000, 900_000))))
    for j in range(60):  # then sensor k 0.2 k ms after the first, stamps 20 ms apart arriving 2.5 ms apart
        for k in range(4):
            messages.append((k, second + j * 20_000_000 + (k * 200_000 + int(rng.integers(-100_000, 100_000)) if k
                                                           else 0), 5 * 10**12 + 12 * 10**9 + j * 2_500_000 +
                             int(rng.integers(50_000, 900_000))))
    sets = []
    for k, stamp, receipt in sorted(messages, key=lambda m: m[2]):
        sets += sync.add(k, stamp, 1e-5, 2e-5, 3e-5, receipt)
    last = max(m[2] for m in messages)
    assert sync.mode == "interpolate" and "exact matching ended" in sync.reason
    sets += sync.release_quiet(last + STILL_NS)
    later = sorted(x.stamps[0] for x in sets if x.stamps[0] >= second)
    assert set(later) <= {second + j * 20_000_000 for j in range(60)}
    assert len(later) >= 59 and sync.pending < 12


def joined(first: Stream, then: Stream) -> Stream:
    """One sensor's messages: ``first``'s, then ``then``'s."""
    return Stream(*(np.concatenate([getattr(first, f.name), getattr(then, f.name)]) for f in fields(Stream)))


MISSION = 3.0
"""s after the start at which the mission follows the probes."""


def probed_mission(rate: float, phases: list[float], probe: float, jump: float, stall: tuple[float, float] | None,
                   seed: int, slow: float = 1.03, start: float = MISSION, speed: float = 1.0) -> list[Stream]:
    """As the soak runs the nodes: four sensors on one stamping clock (each ``phases`` of a period after it) send
    ``probe`` s of probes at ``rate`` / ``slow`` (a few lost), then, from ``start`` s, 40 s of the mission:
    every stamp ``jump`` s ahead of the probes', and mag3's driver restarting 17 s in (its stamps 30 s back),
    sent at ``speed`` x real time (its stamps at the mission's pace, its receipts that much closer together).
    The receiver stalls for ``stall[1]`` s from ``stall[0]`` s into the mission (receipts), then drains its queue
    (None: it never stalls)."""
    rng = np.random.default_rng(seed)
    streams = []
    begin = START_NS + int(start * 1e9)
    for k, phase in enumerate(phases):
        probes = make_stream(SensorPlan(rate=rate / slow, phase=phase / rate, jitter=5e-4, loss=0.06), probe, rng)
        steps = [(0.0, jump)] + ([(start + 17.0, -30.0)] if k == 2 else [])
        mission = make_stream(SensorPlan(rate=rate, phase=start + phase / rate, jitter=5e-4, steps=steps),
                              start + 40.0, rng)
        mission.receipts = begin + np.rint((mission.receipts - begin) / speed).astype(np.int64)
        streams.append(joined(probes, mission))
    if stall is not None:
        busy_receiver(streams, start + stall[0], stall[1], 5e-4)
    return streams


def quiet_ticks(streams: list[Stream]) -> list[int]:
    """Receiver times (ns) of the quiet release, every half second as a node runs it, until the last message's
    hold has passed."""
    end = max(int(s.receipts[-1]) for s in streams)
    return list(range(START_NS, end + STILL_NS + 10**9, 500_000_000))


def worst_spread(streams: list[Stream], start: float = MISSION, settle: float = 1.0) -> tuple[float, int, Any]:
    """Fed to an interpolating synchroniser with the quiet release every half second (as a node runs it): the
    widest spread (s) of the sets after the mission's first ``settle`` s (it starts at ``start`` s; a set with a
    member of the mission counts), how many there are, and the placements."""
    sync = interpolating()
    sets = [x for x in fed(sync, streams, quiet_ticks(streams)) if set_instants(x.values).max() > start + settle]
    return max(spread(x.values) for x in sets), len(sets), sync.placements()


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(phases=st.lists(st.floats(0.0, 0.99), min_size=4, max_size=4), probe=st.floats(33.0, 37.0),
       jump=st.floats(20.0, 60.0), stall=st.none() | st.tuples(st.floats(0.3, 0.7), st.floats(1.5, 2.8)),
       slow=st.sampled_from([1.0, 1.03]), seed=st.integers(0, 2**16))
@example(phases=[0.38, 0.62, 0.78, 0.08], probe=36.7, jump=27.573, stall=(0.53, 5.5), slow=1.026, seed=5)  # 0.14
@example(phases=[0.04, 0.78, 0.9, 0.33], probe=35.9, jump=25.163, stall=(0.55, 5.7), slow=1.026, seed=11)  # 0.15
@example(phases=[0.68, 0.06, 0.56, 0.27], probe=36.5, jump=28.0, stall=None, slow=1.03, seed=3)  # 0.28 periods
def test_sensors_on_one_clock_keep_one_correction_through_a_stall_and_a_restart(
        phases: list[float], probe: float, jump: float, stall: tuple[float, float] | None, slow: float,
        seed: int) -> None:
    """Seen in the soak on a loaded machine (20 Hz, probes a little slower than the mission): the receiver stalled
    for seconds just after the mission started, while the sensors' sample clocks learnt the mission's stamps, and
    the half-second quiet release fitted them with what there was. The sensors that share one stamping clock then
    no longer took one correction: one snapped onto its probes' grid, the others (whose probes were too few to
    learn a clock) did not, 8 ms apart for the rest of the mission (the tensor 5x the floor, every recalibration
    refused). Without a stall, mag3's clock dropped the correction it carried when its driver restarted (up to a
    quarter period off the others). Now every set of the mission, its first second aside, stands for one instant
    within a tenth of a period (``probe``: samples of the probes; the comments: how many periods apart the
    examples' sets stood before). Generated stalls end within 2.8 s; longer ones, whose backlog comes as the hold
    of a new segment ends, are the next test's."""
    rate = 20.0
    streams = probed_mission(rate, phases, probe * slow / rate, jump, stall, seed, slow)
    worst, count, placed = worst_spread(streams)
    assert worst < 0.1 / rate, (worst, placed)
    assert count >= 0.9 * 39.0 * rate


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(phases=st.lists(st.floats(0.0, 0.99), min_size=4, max_size=4), probe=st.floats(33.0, 37.0),
       jump=st.floats(20.0, 60.0), stall=st.tuples(st.floats(0.3, 0.7), st.floats(2.8, 4.9)),
       slow=st.sampled_from([1.0, 1.03]), seed=st.integers(0, 2**16))
@example(phases=[0.79, 0.45, 0.93, 0.4], probe=36.3, jump=23.026, stall=(0.44, 3.73), slow=1.03, seed=26460)  # 24
@example(phases=[0.06, 0.6, 0.11, 0.66], probe=36.0, jump=57.636, stall=(0.46, 4.53), slow=1.0, seed=26191)  # 25
def test_a_mission_start_a_stall_delivers_as_the_hold_ends_is_placed_by_the_queues_order(
        phases: list[float], probe: float, jump: float, stall: tuple[float, float], slow: float, seed: int) -> None:
    """The soak's mission (20 Hz, stamps 20-60 s ahead of the probes', mag3 restarting) with the receiver stalled
    for 2.8-4.9 s a few samples in: each sensor's new segment is held for its arrivals, and the stall's backlog
    comes as the hold's 5 s of receipts end, still draining. Its first messages came on time and the queue's order
    places it, but the segment used to go to its stamps alone, one period after the last probe: the whole mission
    paired whole seconds off its instants, every sensor alike (the comments: periods off before; the first example
    ended its wait for the arrivals to catch up at the hold's end, the second had passed the hold at its first
    decision). Now every set of the mission, its first second aside, stands for one instant within a tenth of a
    period."""
    rate = 20.0
    streams = probed_mission(rate, phases, probe * slow / rate, jump, stall, seed, slow)
    worst, count, placed = worst_spread(streams)
    assert worst < 0.1 / rate, (worst, placed)
    assert count >= 0.9 * 39.0 * rate


def with_currents(streams: list[Stream], store: LatestValues, start: float) -> tuple[int, int]:
    """Fed as :func:`worst_spread` feeds them, with a current stamped as each of the first sensor's readings and
    received a millisecond before it into ``store``: (sets of the mission after ``start`` s, those whose current
    was still in the store when they formed)."""
    sync, ref = interpolating(), streams[0]
    events = sorted([(r, 0, k, i) for r, k, i in arrivals(streams)] + [(int(r) - 10**6, 1, 0, i) for i, r in
                                                                       enumerate(ref.receipts)]
                    + [(t, 2, 0, 0) for t in quiet_ticks(streams)])
    count = found = 0
    for receipt, kind, k, i in events:
        formed: list[Any] = []
        if kind == 1:
            store.add(0, int(ref.stamps[i]), float(i))
        elif kind == 2:
            formed = sync.release_quiet(receipt)
        else:
            s = streams[k]
            formed = sync.add(k, int(s.stamps[i]), *s.vectors[i].tolist(), receipt)
        for x in formed:
            if set_instants(x.values).min() > start:
                count += 1
                found += store.at(x.stamp)[1][0]
    return count, found


def test_the_sets_of_a_held_segment_find_the_currents_sent_with_their_readings() -> None:
    """A new segment held for its arrivals forms its sets up to ``HOLD_NS`` after their readings came (the soak's
    mission start, a receiver stalled 3.7 s a few samples in, the hold ending as it drains). A current sent with
    each reading used to be gone by then (a live store kept 2 s of stamps): the correction node withheld those
    sets as without a current. Now the store keeps ``KEEP_NS`` and every set of the mission finds its current."""
    rate = 20.0
    streams = probed_mission(rate, [0.79, 0.45, 0.93, 0.4], 36.3 * 1.03 / rate, 23.026, (0.44, 3.73), 26460, 1.03)
    count, found = with_currents(streams, LatestValues(1, 100_000_000), MISSION)
    assert count >= 0.9 * 40.0 * rate and found == count, (count, found)


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(phases=st.lists(st.floats(0.0, 0.99), min_size=4, max_size=4), probe=st.floats(25.0, 37.0),
       jump=st.floats(20.0, 60.0), speed=st.sampled_from([2.0, 4.0, 10.0]),
       stall=st.none() | st.tuples(st.floats(0.0, 0.3), st.floats(0.1, 0.8)), slow=st.sampled_from([1.0, 1.03]),
       seed=st.integers(0, 2**16))
@example(phases=[0.4, 0.1, 0.7, 0.9], probe=27.0, jump=29.0, speed=2.0, stall=(0.0, 0.3), slow=1.03, seed=68)
def test_a_mission_sent_faster_than_its_probes_pairs_no_probe_with_it(
        phases: list[float], probe: float, jump: float, speed: float, stall: tuple[float, float] | None, slow: float,
        seed: int) -> None:
    """The soak sends its mission at 2x real time after probes at real time: from the step on, the stamps run
    twice as fast as the arrivals, which looks like a queue draining while the new segment is held. Placed by
    those arrivals, its first sample went before the probes' last, and the first set of the mission paired mag1's
    first reading with the other sensors' probes (7,000x the floor: the soak's first minute at 260x). Now no set
    of the mission, its first reading on, pairs readings more than a tenth of a period apart."""
    rate = 20.0
    streams = probed_mission(rate, phases, probe * slow / rate, jump, stall, seed, slow, speed=speed)
    worst, count, placed = worst_spread(streams, settle=0.0)
    assert worst < 0.1 / rate, (worst, placed)
    assert count >= 0.9 * 40.0 * rate


@settings(max_examples=8, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(rate=st.sampled_from([40.0, 50.0, 100.0]), phases=st.lists(st.floats(0.0, 0.99), min_size=4, max_size=4),
       probe=st.floats(33.0, 37.0), jump=st.floats(20.0, 60.0), slow=st.sampled_from([1.0, 1.03, 0.97]),
       seed=st.integers(0, 2**16))
@example(rate=40.0, phases=[0.14, 0.71, 0.27, 0.13], probe=33.2, jump=26.993, slow=1.03, seed=12569)  # 0.98 periods
@example(rate=100.0, phases=[0.76, 0.52, 0.15, 0.96], probe=34.6, jump=31.809, slow=1.03, seed=55508)  # 0.84
@example(rate=100.0, phases=[0.15, 0.48, 0.89, 0.42], probe=35.4, jump=20.98, slow=1.0, seed=44135)  # 0.73
def test_a_mission_after_probes_at_another_rate_is_placed_by_its_arrivals(
        rate: float, phases: list[float], probe: float, jump: float, slow: float, seed: int) -> None:
    """The soak's case at the rates a gradiometer runs at: probes at 3 % of another rate (or at the mission's rate,
    a fifth of a second to a second of them), a silence, the mission with its stamps 20-60 s ahead. Each sensor's new
    segment used to be put on its probes' grid carried over the silence: at the other rate, or with a period that
    few probes leave uncertain by a tenth of a per cent, that grid lands anywhere on the new samples, and the
    sensors were placed up to a period apart (the comments: the examples before) although their arrivals placed
    each to a tenth of a millisecond. Now a grid that cannot place the segment (its new stamps at another rate, or
    its own period too uncertain that far on) leaves it to the arrivals, and the sensors of one stamping clock are
    placed alike: every set of the mission stands for one instant within a tenth of a period."""
    streams = probed_mission(rate, phases, probe * slow / rate, jump, None, seed, slow)
    worst, count, placed = worst_spread(streams)
    assert worst < 0.1 / rate, (worst * rate, placed)
    assert count >= 0.9 * 39.0 * rate


@settings(max_examples=4, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(rate=st.sampled_from([20.0, 40.0]), phases=st.lists(st.floats(0.0, 0.99), min_size=4, max_size=4),
       gap=st.floats(0.05, 2.0), jump=st.floats(20.0, 60.0), slow=st.sampled_from([1.03, 0.97, 1.01, 0.99]),
       seed=st.integers(0, 2**16))
@example(rate=20.0, phases=[0.15, 0.81, 0.68, 0.78], gap=0.1, jump=27.665, slow=0.97, seed=52583)  # 0.32 periods
def test_a_driver_restarted_at_another_rate_is_placed_by_its_arrivals(
        rate: float, phases: list[float], gap: float, jump: float, slow: float, seed: int) -> None:
    """Half a minute at one rate, then the drivers restart at another (1-3 % apart) after ``gap`` s, their stamps
    ``jump`` s ahead. The old grid, well known after half a minute, lies a period or two before the new segment, so it
    is certain that far on, but the segment's first stamps are placed on it by whole old periods each: their mean
    index (eight periods among sixteen stamps) carries the two rates' difference too, a third of a period at 3 %
    (the comment: the example before). The old grid then does not place the segment (its stamps run at another rate
    by more than their own noise and enough to misplace it): every set of the mission stands for one instant within
    a tenth of a period."""
    probes = 30.0
    streams = probed_mission(rate, phases, probes, jump, None, seed, slow, start=probes + gap)
    worst, count, placed = worst_spread(streams, probes + gap)
    assert worst < 0.1 / rate, (worst * rate, placed)
    assert count >= 0.9 * 39.0 * rate


@pytest.mark.parametrize("kind", ["correction", "calibration"])
def test_both_nodes_form_a_late_delivered_collection_on_their_timer(kind: str) -> None:
    """The nodes' raw callbacks (in this process, arrivals given) with the stalled collection above, then the
    node's quiet-release timer with its clock past the hold: every set of the collection is formed (the
    correction node's set count, the calibration node's collected sets)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import MagneticField

    from magcal_ros.app.ros_driver import isolate_this_process, pick_domain_id
    from magcal_ros.nodes.calibration_node import CalibrationNode
    from magcal_ros.nodes.correction_node import CorrectionNode

    streams, spans = stalled()
    domain = pick_domain_id()
    isolate_this_process(domain)
    context = Context()
    params = ["-p", f"uncorrected_sensors:={list(NAMES)}"] if kind == "correction" else []
    rclpy.init(context=context, domain_id=domain, args=["test", "--ros-args", *params])
    node: Any = CorrectionNode(context=context) if kind == "correction" else CalibrationNode(context=context)
    try:
        if kind == "calibration":
            node._collecting = True
        msg = MagneticField()
        for receipt, k, i in arrivals(streams):
            s = streams[k]
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(s.stamps[i]), 10**9)
            msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = s.vectors[i].tolist()
            if kind == "correction":
                node._raw_callback(k)(serialize_message(msg), {"received_timestamp": receipt})
            else:
                node._raw_callback(k)(msg, {"received_timestamp": receipt})

        def formed() -> int:
            return node._sync.stats.sets if kind == "correction" else node._buffer.offered + len(node._pending)

        assert formed() == true_sets(streams, spans[0]) + true_sets(streams, spans[1])
        now = latest(streams) + STILL_NS
        if kind == "correction":
            node._now = lambda: now
        else:
            node._receipt_clock = lambda: now
        node._release_quiet()
        assert formed() == sum(true_sets(streams, span) for span in spans)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)

"""Exact matching chosen from a recording's first stamps ends when the stamps show otherwise, live and offline alike.

The monitor (:class:`~magcal_ros.core.sync_revision.ExactMonitor`) is checked against its rule written out
again here, on generated blocks of sets; the synchroniser against the truth of generated sensor clocks that
drift apart after the choice.
"""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st
from stream_oracle import SensorPlan, Stream, set_instants
from test_stream_properties import _same_examples_in_any_run  # noqa: F401  (the same draws in any run)
from test_stream_properties import Case, bound, check_lost, live, offline, streams_of

from magcal_ros.core.sync_revision import EVENTS, WIDE, WIDE_FRACTION, ExactMonitor

WINDOW = 1_000_000
"""The exact window of the generated blocks (ns)."""


def expected_reasons(stamps: np.ndarray, missed: np.ndarray, names: list[str], coarse: bool) -> dict[int, str | None]:
    """The rule, written out: for ``stamps`` (sets, sensors) ns handed over in order, ``missed`` (sets,) those the
    window missed (each one at its edge), the verdict at the end of each block: {sets handed over: reason}. A
    block ends after :data:`EVENTS` sets, or at a miss that brings its sets at the edge beyond
    :data:`WIDE_FRACTION` of a whole block."""
    out: dict[int, str | None] = {}
    start = 0
    for i in range(len(stamps)):
        block, miss = stamps[start:i + 1], missed[start:i + 1]
        wide = int(np.sum((block.max(axis=1) - block.min(axis=1) > WIDE * WINDOW) | miss))
        if len(block) < EVENTS and not (missed[i] and wide > WIDE_FRACTION * EVENTS):
            continue
        start = i + 1
        out[i + 1] = None
        if wide > WIDE_FRACTION * len(block):
            out[i + 1] = f"{wide} of {len(block)} sets at the edge of the {WINDOW / 1e6:.3g} ms window"
        elif not coarse:
            for k in range(1, stamps.shape[1]):
                middle = int(np.sort(block[:, k] - block[:, 0])[len(block) // 2])
                if 4 * abs(middle) > WINDOW:
                    out[i + 1] = f"{names[k]}'s stamps moved to {middle / 1e6:.3g} ms after {names[0]}'s"
                    break
    return out


@st.composite
def blocks(draw: st.DrawFn) -> tuple[np.ndarray, list[int], bool]:
    """Two blocks of sets of 2-4 sensors: each sensor's stamps off the first's by an offset of its own (from well
    inside a quarter of the window to beyond it) plus a spread drawn per set, some sets at the window's edge;
    the sizes in which the sets are handed to the monitor; whether the field is coarse."""
    sensors = draw(st.integers(2, 4))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    offsets = [0.0] + [draw(st.floats(-0.6, 0.6)) * WINDOW for _ in range(sensors - 1)]
    scale = draw(st.sampled_from([0.0, 0.05, 0.2, 0.45])) * WINDOW
    n = 2 * EVENTS
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64)[:, None] * 20_000_000 + \
        np.round(np.array(offsets)[None, :] + rng.uniform(-scale, scale, (n, sensors))).astype(np.int64)
    edge = draw(st.integers(0, 8))
    for i in rng.choice(n, edge, replace=False):  # a set at the window's edge: its last sensor 0.95 window off
        stamps[i, -1] = stamps[i, 0] + int(0.95 * WINDOW)
    sizes = draw(st.lists(st.integers(1, EVENTS), min_size=1, max_size=12))
    missed = np.zeros(n, bool)
    missed[draw(st.lists(st.integers(0, n - 1), max_size=8))] = True
    return stamps, missed, sizes, draw(st.booleans())


@settings(max_examples=300, derandomize=True, database=None, deadline=None)
@given(blocks())
def test_the_monitor_ends_exact_matching_by_its_rule_block_by_block(
        drawn: tuple[np.ndarray, np.ndarray, list[int], bool]) -> None:
    """Every block of :data:`EVENTS` sets, handed over in any pieces (a set the window missed alone), is judged on
    its own sets: sets at the window's edge or missed beyond :data:`WIDE_FRACTION` of the block, or (unless the
    field is coarse) a sensor's median offset from the first beyond a quarter of the window, end exact matching,
    naming the cause; nothing is judged before a block is whole."""
    stamps, missed, sizes, coarse = drawn
    names = [f"mag{k + 1}" for k in range(stamps.shape[1])]
    want = expected_reasons(stamps, missed, names, coarse)
    monitor = ExactMonitor(names, coarse)
    done, k = 0, 0
    while done < len(stamps):
        before = monitor.reason
        if missed[done]:
            monitor.missed(stamps[done].tolist(), WINDOW)
            n = 1
        else:
            n = min(sizes[k % len(sizes)], monitor.room, len(stamps) - done)
            n = int(np.argmax(np.append(missed[done:done + n], True)))  # up to the next missed one
            k += 1
            monitor.formed([stamps[done:done + n, j].tolist() for j in range(stamps.shape[1])], WINDOW)
        done += n
        if done not in want:
            assert monitor.reason == before and monitor.room < EVENTS
            continue
        got = monitor.reason
        assert (got is None) == (want[done] is None) and (got is None or got.startswith(want[done])), (got, want)
        assert monitor.room == EVENTS


@settings(max_examples=12, derandomize=True, database=None, deadline=None)
@given(st.floats(80.0, 1000.0), st.sampled_from([20.0, 50.0, 100.0]), st.integers(2, 4), st.data())
def test_exact_matching_chosen_from_coinciding_first_stamps_ends_when_a_clock_drifts_away(
        ppm: float, rate: float, sensors: int, data: st.DataObject) -> None:
    """One sensor's clock runs 80-1000 ppm fast: its first stamps coincide with the others' (exact matching is
    chosen), then drift a quarter of the window away within seconds (at 20 Hz and 318 ppm, past the window
    before a block of sets was whole: exact matching formed no set for the rest of the recording, in silence).
    Both paths end exact matching at the same set (or, drifting fast, never choose it), say why (naming the
    sensor, or the sets at the window's edge), interpolate from there to the end of the recording and give the
    same sets, losing no more than a few dozen; no set stands for readings further apart than the bound; with 2 %
    of the samples lost, each lost sample is counted once across the switch."""
    which = data.draw(st.integers(1, sensors - 1))
    loss = data.draw(st.sampled_from([0.0, 0.02]))
    case = Case([SensorPlan(rate=rate, ppm=ppm if k == which else 0.0, loss=loss) for k in range(sensors)], 12.0,
                data.draw(st.integers(0, 2**31 - 1)))
    streams = streams_of(case)
    batch, _, mode = offline(streams)
    sets, sync = live(streams)
    assert mode == sync.mode == "interpolate"
    why = sync.reason  # whichever shows first: the drifting sensor's median offset, or sets at the window's edge;
    # or, drifting fast, exact matching never chosen
    assert why.startswith(f"exact matching ended (mag{which + 1}'s stamps moved to") or \
        why.startswith("exact matching ended (") and "sets at the edge of the 1 ms window" in why or \
        why.startswith(f"mag{which + 1} is sampled"), why
    assert np.array_equal(batch.stamps, np.array([s.stamps for s in sets]))
    check_lost(case, streams, sync)  # each lost sample counted once, across the switch of the sample clocks
    instants = np.array([set_instants(v) for v in batch.vectors])
    assert np.ptp(instants, axis=1).max() <= bound(case)
    assert instants[-1, 0] > case.duration - 0.5 and len(batch) > case.duration * rate * (1 - 4 * loss) - 40


@settings(max_examples=20, derandomize=True, database=None, deadline=None)
@given(st.integers(0, 3), st.integers(1, 20), st.integers(1, 12), st.sampled_from([False, True]))
@example(0, 1, 9, False)
@example(0, 1, 9, True)
def test_samples_lost_after_a_pause_at_a_new_rate_keep_exact_matching(lossy: int, first: int, lost: int,
                                                                       batch: bool) -> None:
    """Four sensors on one clock at 50 Hz, a pause, then 2 kHz; one sensor loses ``lost`` samples ``first``
    samples after it came back, while every period estimate still says 20 ms (heads a few new periods apart
    looked like one instant beyond the window: four such misses ended exact matching, and the sets came out at
    interpolated instants; and the window, capped at half a 20 ms period, paired neighbouring samples). The lossy
    sensor's messages arrive as many new periods before the others' as it lost (its next stamp comes with the
    others' first after the loss: every period estimate still the old one). Exact
    matching holds and every complete set is published, each at one stamp, live and offline."""
    t0 = 1_700_000_000 * 10**9
    slow = t0 + np.arange(300, dtype=np.int64) * 20_000_000
    fast = slow[-1] + 1_500_000_000 + np.arange(120, dtype=np.int64) * 500_000
    stamps = np.concatenate([slow, fast])
    gone = np.zeros(len(stamps), dtype=bool)
    gone[len(slow) + first:len(slow) + first + lost] = True
    streams = []
    for k in range(4):
        s = stamps[~gone] if k == lossy else stamps
        receipts = s + 2_000_000 + (0 if k == lossy else lost * 500_000)
        streams.append(Stream(s, receipts, np.tile([2e-5, 1e-6 * k, 4e-5], (len(s), 1)), np.zeros(len(s)),
                              np.ones(len(s), dtype=bool)))
    complete = set(stamps[~gone].tolist())
    if batch:
        result, _, mode = offline(streams)
        got = result.stamps
    else:
        sets, sync = live(streams)
        got, mode = np.array([s.stamps for s in sets]), sync.mode
    assert mode == "exact"
    assert np.all(got == got[:, :1])  # every set at one stamp
    made = set(got[:, 0].tolist())
    assert made <= complete and len(complete - made) <= 1  # live: the last may wait for the end


@settings(max_examples=40, derandomize=True, database=None, deadline=None)
@given(st.integers(0, 2**31 - 1))
@example(19)
def test_exact_matching_that_ends_in_the_first_second_ends_alike_live_and_offline_and_loses_no_count(
        seed: int) -> None:
    """Two sensors at 100 Hz whose stamps jitter by up to 0.8 ms against the 1 ms window, one losing 2 % of its
    samples: exact matching, chosen from the first stamps, often ends within the first second. Live and offline
    end it at the same set and publish the same sets, and the samples lost before it ended are counted.
    (The miss that can end a block early was judged against the sensors' latest period estimates: offline they
    had seen the whole recording, live only its first tenth of a second, so live formed sets offline had not;
    and the sample clock that took over from one still learning left the samples lost before uncounted.)"""
    case = Case([SensorPlan(rate=100.0, jitter=0.0008), SensorPlan(rate=100.0, jitter=0.0008, loss=0.02)], 3.0, seed)
    streams = streams_of(case)
    result, _, mode = offline(streams)
    sets, sync = live(streams)
    got = np.array([s.stamps for s in sets], dtype=np.int64).reshape(len(sets), -1)
    assert sync.mode == mode
    assert len(result) - len(got) <= sync.pending + 1
    assert np.array_equal(result.stamps[: len(got)], got)
    check_lost(case, streams, sync)

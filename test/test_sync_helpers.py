"""The small rules the stream acceptance is made of, each against its contract, at its edges.

``test_stream_properties.py`` checks the synchroniser as a whole against a truth oracle; these tests pin
each helper of ``core/sync_rules.py`` that the acceptance decides by (a sample grid, one clock's stamps, a
backlog delivered at once, arrivals that keep the stamps' time, a segment whose arrivals caught up): every
generated input against the rule restated here, and the boundary of each comparison from both sides. They
kill the mutants of these helpers that a mutation run (docs/mutation_report.md) found alive.
"""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal_ros.core import sync_rules as sr
from magcal_ros.core.sync import SetSynchronizer
from magcal_ros.core.units import NS_PER_S

MS = NS_PER_S // 1000
EXAMPLES = 300
FIXED = settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None)
periods = st.integers(min_value=1_000, max_value=2 * NS_PER_S)
stamps = st.integers(min_value=-(10**15), max_value=10**15)


def _distance_to_grid(value: int, anchor: int, period: int) -> int:
    """How far (ns) ``value`` lies from the nearest point ``anchor + k period`` (exact integers)."""
    r = (value - anchor) % period
    return min(r, period - r)


# -- a sample grid ------------------------------------------------------------------------------------
@FIXED
@given(common=stamps, anchor=stamps, period=periods)
def test_a_stamp_is_on_a_grid_within_a_quarter_period_of_one_of_its_points(common: int, anchor: int,
                                                                           period: int) -> None:
    dist = _distance_to_grid(common, anchor, period)
    if abs(4 * dist - period) <= 4 or abs(common - anchor) > 10**12:  # float rounding at the edge, far stamps
        return
    assert sr._on_grid(common, (float(anchor), float(period))) == (4 * dist <= period)


@pytest.mark.parametrize(("offset", "on"), [(0, True), (250_000, True), (250_001, False), (-250_000, True),
                                            (-250_001, False), (750_000, True), (749_999, False),
                                            (5_000_000, True), (5_250_001, False), (-3_000_000, True)])
def test_a_grids_quarter_period_is_inclusive_either_side_of_any_point(offset: int, on: bool) -> None:
    anchor = 7_000_000_000
    assert sr._on_grid(anchor + offset, (float(anchor), float(MS))) is on


def test_no_grid_holds_no_stamp() -> None:
    assert sr._on_grid(0, None) is False


# -- one clock's stamps -------------------------------------------------------------------------------
@FIXED
@given(offset=st.integers(min_value=-3 * NS_PER_S, max_value=3 * NS_PER_S), period=periods,
       phase=st.integers(min_value=-NS_PER_S, max_value=NS_PER_S),
       tol=st.one_of(st.none(), st.integers(min_value=0, max_value=NS_PER_S)))
def test_in_line_means_a_neighbour_sample_as_the_two_lay_before(offset: int, period: int, phase: int,
                                                                 tol: int | None) -> None:
    """Within a period and a quarter of the other's latest, and on the other's grid shifted by ``phase`` to
    ``tol`` (at most a quarter period)."""
    limit = period / 4 if tol is None else min(tol, period / 4)
    dist = _distance_to_grid(offset, phase, period)
    near_edge = abs(dist - limit) <= 2 or abs(abs(offset) - 1.25 * period) <= 2
    if near_edge:
        return
    expected = abs(offset) <= 1.25 * period and dist <= limit
    assert sr._in_line(offset, (0.0, float(period)), float(phase), None if tol is None else float(tol)) == expected


@pytest.mark.parametrize(("offset", "phase", "tol", "line"), [
    (1_250_000, 0.0, None, True), (1_250_001, 0.0, None, False), (-1_250_000, 0.0, None, True),
    (1_000_000, 0.0, None, True), (1_000_000 + 250_000, 0.0, None, True), (750_000, 0.0, None, True),
    (749_999, 0.0, None, False), (300_000, 100_000.0, None, True), (350_001, 100_000.0, None, False),
    (1_100_000, 100_000.0, None, True), (100_000, 0.0, 100_000.0, True), (100_001, 0.0, 100_000.0, False),
    (200_000, 0.0, 900_000.0, True), (250_001, 0.0, 900_000.0, False), (-900_000, 100_000.0, None, True),
])
def test_in_line_edges_a_period_and_a_quarter_and_the_phase_tolerance(offset: int, phase: float,
                                                                     tol: float | None, line: bool) -> None:
    """1 ms period: the reach is inclusive, the tolerance is the smaller of ``tol`` and a quarter period."""
    assert sr._in_line(offset, (0.0, float(MS)), phase, tol) is line


def test_in_line_takes_no_phase_by_default() -> None:
    assert sr._in_line(-250_000, (0.0, float(MS))) is True and sr._in_line(250_000, (0.0, float(MS))) is True
    assert sr._in_line(-250_001, (0.0, float(MS))) is False


@pytest.mark.parametrize(("offset", "line"), [(MS, True), (-MS, True), (MS + 1, False), (-MS - 1, False), (0, True)])
def test_in_line_without_a_period_is_within_a_millisecond(offset: int, line: bool) -> None:
    assert sr._in_line(offset, None) is line
    assert sr._in_line(offset, None, 5e5, 1.0) is line  # phase and tolerance need a period


# -- a backlog delivered at once ----------------------------------------------------------------------
@pytest.mark.parametrize(("gap", "period", "result"), [(249, 1000, True), (250, 1000, False), (0, 1000, True),
                                                      (-5, 1000, True), (251, 1000, False), (1000, 1000, False)])
def test_bunched_is_under_a_quarter_period_after_the_previous_receipt(gap: int, period: int, result: bool) -> None:
    assert sr.bunched(10**12 + gap, 10**12, period) is result


@pytest.mark.parametrize(("lead_growth", "period", "result"), [
    (0, MS, True), (MS - 1, MS, True), (MS, MS, False), (-5 * MS, MS, True), (NS_PER_S - 1, None, True),
    (NS_PER_S, None, False),
])
def test_caught_up_over_the_last_four_messages(lead_growth: int, period: int | None, result: bool) -> None:
    """The stamps' lead over the arrivals grew by less than a period (a second without one) from the fifth
    last held message to the last; what came before those five does not count."""
    held = [(k * MS, None, None, k * MS - 10 * MS) for k in range(8)]  # arrivals 10 ms late, lead constant
    held[0] = (0, None, None, 10**9)  # older messages, wildly late, do not count
    held[1] = (MS, None, None, -(10**9))
    stamp, payload, fault, receipt = held[-1]
    held[-1] = (stamp, payload, fault, receipt - lead_growth)
    assert sr.caught_up(held, period) is result
    assert sr.caught_up(held[-4:], period) is False  # four messages tell nothing yet
    assert sr.caught_up(held[-5:], period) is result


# -- arrivals that keep the stamps' time --------------------------------------------------------------
def _pairs(stamps_ns: list[int], receipts_ns: list[int]) -> list[tuple[int, int]]:
    return list(zip(stamps_ns, receipts_ns))


@FIXED
@given(intervals=st.lists(st.integers(min_value=-MS, max_value=50 * MS), min_size=0, max_size=40),
       delays=st.lists(st.integers(min_value=0, max_value=30 * MS), min_size=41, max_size=41))
def test_the_arrival_ratio_is_the_upper_median_of_receipt_over_stamp_intervals(intervals: list[int],
                                                                                delays: list[int]) -> None:
    common = np.concatenate([[0], np.cumsum(intervals)]).astype(int).tolist()
    receipts = [c + d for c, d in zip(common, delays)]
    pairs = _pairs(common, receipts)
    ratios = sorted((r1 - r0) / (c1 - c0) for (c0, r0), (c1, r1) in zip(pairs, pairs[1:]) if c1 > c0)
    got = sr.arrival_ratio(pairs)
    if len(pairs) < sr.TIMED_MIN or not ratios:
        assert got is None
    else:
        assert got == ratios[len(ratios) // 2]


def test_the_arrival_ratio_needs_timed_min_pairs_and_takes_the_upper_median() -> None:
    common = [k * 10 * MS for k in range(sr.TIMED_MIN)]
    assert sr.arrival_ratio(_pairs(common[:-1], common[:-1])) is None
    assert sr.arrival_ratio(_pairs(common, common)) == 1.0
    # 16 pairs, 15 intervals: ratios 1 (x7), 2 (x8) -> the median of an odd count, the eighth, is 2
    receipts = [0]
    for k in range(1, sr.TIMED_MIN):
        receipts.append(receipts[-1] + (10 * MS if k <= 7 else 20 * MS))
    assert sr.arrival_ratio(_pairs(common, receipts)) == 2.0
    # 17 pairs, 16 intervals: 8 of ratio 1 then 8 of ratio 3 -> the upper of the two middle ones, 3
    common17 = [k * 10 * MS for k in range(17)]
    receipts17 = [0]
    for k in range(1, 17):
        receipts17.append(receipts17[-1] + (10 * MS if k <= 8 else 30 * MS))
    assert sr.arrival_ratio(_pairs(common17, receipts17)) == 3.0
    # intervals that do not advance are left out, not counted as ratios
    flat = [0] * sr.TIMED_MIN
    assert sr.arrival_ratio(_pairs(flat, common)) is None


def _timed_oracle(pairs: list[tuple[int, int]]) -> bool:
    """The rule restated: enough pairs, the median ratio within 0.5 .. 2, and the least delayed arrival's lead
    the same in the newer half as in the older to one (median) interval."""
    if len(pairs) < sr.TIMED_MIN:
        return False
    ratios = sorted((r1 - r0) / (c1 - c0) for (c0, r0), (c1, r1) in zip(pairs, pairs[1:]) if c1 > c0)
    if not ratios or not 0.5 <= ratios[len(ratios) // 2] <= 2.0:
        return False
    ivs = sorted(c1 - c0 for (c0, _), (c1, _) in zip(pairs, pairs[1:]) if c1 > c0)
    half = len(pairs) // 2
    newer = max(c - r for c, r in pairs[half:])
    older = max(c - r for c, r in pairs[:half])
    return abs(newer - older) <= ivs[len(ivs) // 2]


@FIXED
@given(n=st.integers(min_value=10, max_value=60), period=st.integers(min_value=MS, max_value=100 * MS),
       speed=st.sampled_from([0.3, 0.5, 0.9, 1.0, 1.1, 2.0, 2.5]),
       drift=st.integers(min_value=-3, max_value=3), seed=st.integers(min_value=0, max_value=2**31))
def test_timed_arrivals_follow_the_rule_on_replays_backlogs_and_jitter(n: int, period: int, speed: float, drift: int,
                                                                       seed: int) -> None:
    rng = np.random.default_rng(seed)
    common = (np.arange(n) * period).tolist()
    # a replay at ``speed``, arrivals late by a jitter and by a lead that moves ``drift`` tenths of a period a message
    late = rng.integers(0, period, n) + (np.arange(n) * drift * period) // 10
    receipts = (np.round(np.arange(n) * period / speed) + late - late.min()).astype(int).tolist()
    pairs = _pairs(common, receipts)
    assert sr.timed_arrivals(pairs) == _timed_oracle(pairs)


def test_timed_arrivals_edges_of_the_ratio_and_of_the_leads_move() -> None:
    n, p = 20, 10 * MS
    common = [k * p for k in range(n)]
    for speed, timed in ((0.5, True), (2.0, True), (0.49, False), (2.01, False)):
        receipts = [round(c / speed) for c in common]
        pairs = _pairs(common, receipts)
        # the lead moves with the speed: exact speeds 0.5 and 2 keep the ratio, but the leads move too
        assert sr.timed_arrivals(pairs) == _timed_oracle(pairs)
        if not timed:
            assert sr.timed_arrivals(pairs) is False
    # on time, then the newer half's least delayed arrival exactly one interval later: still timed; more: not
    for shift, timed in ((p, True), (p + 1, False), (-p, True), (-p - 1, False)):
        receipts = [c + (0 if k < n // 2 else shift) for k, c in enumerate(common)]
        receipts = [max(r, receipts[k - 1] + 1) if k else r for k, r in enumerate(receipts)]
        assert sr.timed_arrivals(_pairs(common, receipts)) is _timed_oracle(_pairs(common, receipts)) is timed


def _alternating(ratios: tuple[float, float], n: int = sr.TIMED_MIN, period: int = 10 * MS) -> list[tuple[int, int]]:
    """``n`` pairs 10 ms apart whose receipt intervals alternate between the two ``ratios`` of the stamp
    interval (the first of them one more time): the lead over the arrivals swings and comes back."""
    pairs, receipt = [(0, 0)], 0
    for k in range(1, n):
        receipt += round(ratios[(k - 1) % 2] * period)
        pairs.append((k * period, receipt))
    return pairs


@pytest.mark.parametrize(("ratios", "timed"), [
    ((0.5, 1.5), True), ((0.49, 1.51), False), ((2.0, 0.0), True), ((2.01, -0.01), False), ((2.5, -0.5), False),
    ((1.0, 1.0), True),
])
def test_timed_arrivals_take_a_median_ratio_of_exactly_one_half_and_two(ratios: tuple[float, float],
                                                                       timed: bool) -> None:
    """Receipt intervals alternating so that the upper median ratio is the first of ``ratios`` while the lead
    only swings (the same at its least in both halves): the ratio's bounds 0.5 and 2 are inclusive."""
    pairs = _alternating(ratios)
    assert sr.arrival_ratio(pairs) == pytest.approx(ratios[0])
    assert sr.timed_arrivals(pairs) is timed


@pytest.mark.parametrize(("move", "timed"), [(2 * 10 * MS, True), (2 * 10 * MS + 1, False), (-2 * 10 * MS, True)])
def test_the_leads_move_is_measured_against_the_median_interval_of_advancing_stamps(move: int, timed: bool) -> None:
    """Intervals of 1, 2 and 3 units (10 ms) a third each, every stamp twice (intervals of 0 between): the lead
    of the newer half's least delayed arrival moved by ``move``; within the median interval (2 units) it is timed.
    Neither the lower third's interval (1 unit) nor the repeated stamps' (0) is the measure."""
    unit = 10 * MS
    common, k = [], 0
    for iv in [1, 2, 3] * 6:
        common += [k * unit, k * unit]
        k += iv
    half = len(common) // 2
    pairs = [(c, c - (move if i >= half else 0)) for i, c in enumerate(common)]
    assert sr.arrival_ratio(pairs) == 1.0
    assert sr.timed_arrivals(pairs) is timed


# -- the order messages arrived in ---------------------------------------------------------------------
@FIXED
@given(st.lists(st.lists(st.integers(min_value=0, max_value=50), max_size=12).map(sorted), min_size=1, max_size=5))
def test_arrival_order_sorts_by_receipt_then_sensor_then_message(receipts: list[list[int]]) -> None:
    arrays = [np.asarray(r, dtype=np.int64) for r in receipts]
    expected = [(k, i) for _, k, i in sorted((t, k, i) for k, r in enumerate(receipts) for i, t in enumerate(r))]
    assert sr.arrival_order(arrays) == expected


def test_arrival_order_of_messages_received_at_once_keeps_each_sensors_order() -> None:
    same = np.array([5, 5, 5], dtype=np.int64)
    assert sr.arrival_order([same, np.array([3, 5], dtype=np.int64)]) == [(1, 0), (0, 0), (0, 1), (0, 2), (1, 1)]
    assert sr.arrival_order([np.zeros(0, dtype=np.int64)]) == []
    # plain Python integers: they index the sensors' message lists
    assert all(type(k) is int and type(i) is int for k, i in sr.arrival_order([same, same[:1]]))


# -- numbers -----------------------------------------------------------------------------------------
@FIXED
@given(st.lists(st.integers(min_value=-(2**40), max_value=2**40), min_size=1, max_size=17))
def test_the_integer_median_rounds_halves_down(values: list[int]) -> None:
    assert sr.median_int(values) == math.floor(statistics.median(values))


def test_the_integer_median_of_an_even_count_is_the_mean_of_the_middle_two_rounded_down() -> None:
    assert sr.median_int([1, 2]) == 1
    assert sr.median_int([4, 1, 3, 2]) == 2
    assert sr.median_int([-3, -2]) == -3
    assert sr.median_int([7]) == 7
    assert sr.median_int([9, 1, 5]) == 5


@pytest.mark.parametrize(("seconds", "ns"), [(0, 0), (0.0005, 500_000), ("0.001", 1_000_000), (0.999999999, 999_999_999),
                                             (-0.0, 0), (2.4e-9, 2), (2.6e-9, 3)])
def test_a_sync_tolerance_is_rounded_to_whole_nanoseconds(seconds: object, ns: int) -> None:
    assert sr.tolerance_ns(seconds) == ns


@pytest.mark.parametrize("seconds", [1.0, 1, -1e-9, float("nan"), float("inf"), -float("inf"), "1.5"])
def test_a_sync_tolerance_outside_zero_to_one_second_is_refused_naming_it(seconds: object) -> None:
    with pytest.raises(ValueError, match=r"^sync tolerance must be between 0 and 1 s, got "):
        sr.tolerance_ns(seconds)


# -- one sensor's intervals ----------------------------------------------------------------------------
def _stream_with(intervals: list[int], last: int = 10 * NS_PER_S) -> sr.SensorStream:
    """A sensor whose recent intervals (ns) were ``intervals`` (recorded one by one), its last stamp ``last``."""
    s = sr.SensorStream(None)
    s.last = s.lastc = last
    s.grid_first = stamp = last - sum(intervals)
    for iv in intervals:
        stamp += iv
        s.record(iv, 10 * NS_PER_S, stamp)
    return s


@FIXED
@given(intervals=st.lists(st.integers(min_value=1, max_value=5 * NS_PER_S), min_size=1, max_size=30),
       pause=st.integers(min_value=1, max_value=6 * NS_PER_S))
def test_record_keeps_the_last_eight_intervals_their_median_and_the_window_cap(intervals: list[int],
                                                                              pause: int) -> None:
    """The short period is the integer median of the last :data:`PERIOD_WINDOW` intervals; the window cap is
    half of it, or half the median of the intervals since the last pause (longer than ``pause``) while fewer
    than a window of them came; the grid counts each interval in whole short periods once a window is full, and
    starts again at the stamp after a pause, the grid before kept (span and periods) where it held a window."""
    s = sr.SensorStream(None)
    s.grid_first = 0
    fresh, periods, first, stamp = sr.PERIOD_WINDOW, 0, 0, 0
    past = (0, 0)
    for k, iv in enumerate(intervals):
        before = sr.median_int(intervals[max(0, k - sr.PERIOD_WINDOW) : k]) if k >= sr.PERIOD_WINDOW else None
        stamp += iv
        cap = s.record(iv, pause, stamp)
        fresh = 0 if iv > pause else min(fresh + 1, sr.PERIOD_WINDOW)
        if iv > pause:
            if periods >= sr.PERIOD_WINDOW:  # a grid of a window or more is kept for the pooled period
                past = (past[0] + stamp - iv - first, past[1] + periods)
            periods, first = 0, stamp
        elif before:
            periods += max(1, round(iv / before))
        else:
            first += iv
        window = intervals[max(0, k + 1 - sr.PERIOD_WINDOW) : k + 1]
        assert s.intervals == window
        assert s.period == sr.median_int(window)
        assert s.fresh == fresh
        expected = sr.median_int(window[-fresh:]) // 2 if 0 < fresh < sr.PERIOD_WINDOW else sr.median_int(window) // 2
        assert cap == expected
        assert s.grid_periods == periods and s.grid_first == first and s.grid_past == past
        assert s.suspect_period() == (s.period if k + 1 >= sr.PERIOD_WINDOW else None)


@FIXED
@given(intervals=st.lists(st.integers(min_value=1, max_value=3 * NS_PER_S), min_size=1, max_size=60),
       cuts=st.lists(st.integers(min_value=1, max_value=60), max_size=4),
       pause=st.integers(min_value=NS_PER_S // 10, max_value=2 * NS_PER_S))
def test_a_batch_of_stamps_leaves_the_sensors_intervals_and_grid_as_one_by_one(intervals: list[int], cuts: list[int],
                                                                             pause: int) -> None:
    """The offline path's vectorised acceptance of a sensor's stamps (in batches cut anywhere) leaves the same window
    caps, intervals, short period, pause count and sample grid as recording them one by one (pauses included)."""
    stamps = (10 * NS_PER_S + np.concatenate([[0], np.cumsum(intervals)])).astype(np.int64)
    one = sr.SensorStream(None)
    one.last = one.grid_first = int(stamps[0])
    want = [sr.NO_CAP] + [one.record(int(b - a), pause, int(b)) for a, b in zip(stamps[:-1].tolist(), stamps[1:].tolist())]
    sync = SetSynchronizer(1, pause_ns=pause)
    got: list[int] = []
    for chunk in np.split(stamps, sorted({c for c in cuts if c < len(stamps)})):
        got += sync._batch_caps(0, chunk).tolist()
        sync.streams[0].last = int(chunk[-1])
    batch = sync.streams[0]
    assert got == want
    assert (batch.intervals, batch.period, batch.fresh) == (one.intervals, one.period, one.fresh)
    assert (batch.grid_first, batch.grid_periods, batch.grid_past) == (one.grid_first, one.grid_periods, one.grid_past)


def test_the_window_cap_after_a_pause_comes_from_the_intervals_since_and_the_pause_itself_resets_it() -> None:
    s = _stream_with([20 * MS] * 8)
    assert s.record(10 * NS_PER_S, 10 * NS_PER_S, 0) == 10 * MS  # equal to the pause: not a pause
    assert s.record(10 * NS_PER_S + 1, 10 * NS_PER_S, 0) == s.period // 2  # a pause: nothing since it yet
    assert s.fresh == 0
    assert s.record(4 * MS, 10 * NS_PER_S, 0) == 2 * MS  # one interval since the pause: its half
    assert s.record(6 * MS + 1, 10 * NS_PER_S, 0) == 2_500_000  # two: their median (5 ms, rounded down) halved
    assert s.fresh == 2


@pytest.mark.parametrize(("interval", "result"), [(99_999, True), (100_000, False), (0, True), (400_000, False)])
def test_crowded_is_under_a_quarter_period_of_a_fast_sensor(interval: int, result: bool) -> None:
    """At 2.5 kHz (400 us) a quarter period is shorter than the backlog interval: it decides, strictly."""
    s = _stream_with([400_000] * 8)
    assert s.crowded(interval, 400_000) is result


def test_crowded_needs_an_interval_under_the_backlog_interval_and_regular_recent_intervals() -> None:
    slow = _stream_with([4 * NS_PER_S] * 8)  # 0.25 Hz: a quarter period is a second
    assert slow.crowded(sr.BACKLOG_INTERVAL - 1, 4 * NS_PER_S) is True
    assert slow.crowded(sr.BACKLOG_INTERVAL, 4 * NS_PER_S) is False  # faster than any magnetometer: a rate
    # the median deviation of the recent intervals from the period under a quarter period, strictly
    p = 10 * MS
    edge = _stream_with([p - p // 4] * 5 + [p] * 3)  # median deviation exactly a quarter period
    assert edge.crowded(100_000, p) is False
    inside = _stream_with([p - p // 4 + 4] * 5 + [p] * 3)
    assert inside.crowded(100_000, p) is True


@FIXED
@given(intervals=st.lists(st.integers(min_value=1, max_value=10**9), min_size=1, max_size=8))
def test_the_jitter_is_six_median_deviations_of_the_intervals_from_the_short_period(intervals: list[int]) -> None:
    s = _stream_with(intervals)
    short = sr.median_int(intervals)
    assert s.jitter() == 6.0 * sr.median_int([abs(i - short) for i in intervals])
    assert sr.SensorStream(None).jitter() == 0.0


@FIXED
@given(offsets=st.lists(st.integers(min_value=-400, max_value=400), min_size=1, max_size=sr.TAIL),
       period=st.integers(min_value=10_000, max_value=10**8), start=stamps)
def test_the_anchor_is_the_last_stamp_with_the_tails_jitter_averaged_out(offsets: list[int], period: int,
                                                                          start: int) -> None:
    """Stamps ``start + k period + offset``: the anchor lies at the last grid point plus the mean offset."""
    s = sr.SensorStream(None)
    s.tail = [start + k * period + o for k, o in enumerate(offsets)]
    expected = start + (len(offsets) - 1) * period + sum(offsets) / len(offsets)
    assert s.anchor(float(period)) == pytest.approx(expected, abs=1e-6 * period + 1e-3)


# -- what a stamp is -----------------------------------------------------------------------------------
@pytest.mark.parametrize(("step", "kind"), [
    (0, sr.DUPLICATE), (-1, sr.BEHIND), (-5 * NS_PER_S, sr.BEHIND), (10 * MS, sr.OK), (25 * MS, sr.OK),
    (25 * MS + 1, sr.AHEAD), (sr.BACKLOG_INTERVAL - 1, sr.CROWDED), (sr.BACKLOG_INTERVAL, sr.OK), (1, sr.CROWDED),
])
def test_classify_by_the_short_period_suspects_beyond_five_halves_of_it(step: int, kind: int) -> None:
    s = _stream_with([10 * MS] * 8)
    assert s.classify(s.last + step, None, NS_PER_S) == kind


def _timed_stream(period: int = 10 * MS, late: int = MS) -> sr.SensorStream:
    """A sensor sampled every ``period`` whose messages all came ``late`` ns after their stamps (arrivals that
    keep time), its last stamp at 10 s."""
    s = _stream_with([period] * 8)
    commons = np.arange(s.last - 39 * period, s.last + 1, period, dtype=np.int64)
    s.note_leads(commons, commons + late)
    s.last_receipt = s.last + late
    return s


@pytest.mark.parametrize(("interval", "seen", "kind"), [
    (20 * MS, 10 * MS, sr.AHEAD), (20 * MS, 20 * MS, sr.OK), (15 * MS + 1, 5 * MS, sr.AHEAD),
    (15 * MS, 5 * MS, sr.OK), (20 * MS, 14 * MS, sr.AHEAD), (20 * MS, 16 * MS, sr.OK),
])
def test_a_gap_of_two_periods_the_arrivals_did_not_see_is_a_step_else_lost_samples(interval: int, seen: int,
                                                                                    kind: int) -> None:
    """Over one and a half periods (10 ms) and under five halves: lost samples where the arrivals saw the time
    pass, a suspect step forward where they saw less of it than half a period short of the stamps."""
    s = _timed_stream()
    assert s.timed()
    assert s.classify(s.last + interval, s.last_receipt + seen, NS_PER_S) == kind
    assert s.classify(s.last + interval, None, NS_PER_S) == sr.OK  # no receipt: lost samples


def test_a_message_is_bunched_with_the_previous_only_if_that_one_has_a_receipt() -> None:
    s = sr.SensorStream(None)
    assert s.bunched(10**9, MS) is False
    s.last_receipt = 10**9
    assert s.bunched(10**9 + 249_999, MS) is True
    assert s.bunched(10**9 + 250_000, MS) is False


def test_classify_before_a_period_is_known_suspects_only_a_restarts_jump() -> None:
    s = _stream_with([10 * MS] * 3)  # three intervals: no suspect period yet
    assert s.suspect_period() is None
    assert s.classify(s.last + NS_PER_S, None, NS_PER_S) == sr.OK
    assert s.classify(s.last + NS_PER_S + 1, None, NS_PER_S) == sr.AHEAD
    first = sr.SensorStream(None)
    assert first.classify(123, None, NS_PER_S) == sr.OK  # the first stamp of a sensor


@pytest.mark.parametrize(("after_old", "interval", "kind"), [
    (1, 30 * MS + 1, sr.AHEAD), (1, 25 * MS, sr.OK), (1, 25 * MS + 1, sr.AHEAD), (0, 30 * MS, sr.OK),
    (NS_PER_S, 30 * MS, sr.AHEAD), (NS_PER_S + 1, 30 * MS, sr.OK),
])
def test_classify_takes_a_jump_back_into_the_sequence_a_step_just_left_as_suspect(after_old: int, interval: int,
                                                                                   kind: int) -> None:
    """Up to ``restart_ns`` (1 s) after the old segment's last stamp, an interval of more than five halves of
    the old segment's period (10 ms) is suspect, although this segment's own period (20 ms) would take it."""
    s = _stream_with([20 * MS] * 8)
    old_last = 20 * NS_PER_S
    s.before = (old_last, 0, 10 * MS)
    stamp = old_last + after_old
    s.last = stamp - interval
    assert s.classify(stamp, None, NS_PER_S) == kind


# -- the stamps' lead over the arrivals ----------------------------------------------------------------
leads = st.lists(st.tuples(st.integers(min_value=0, max_value=10**13), st.integers(min_value=-(10**9), max_value=10**8)),
                 min_size=1, max_size=40)


def _floor_oracle(notes: list[tuple[int, int]]) -> tuple[int, int]:
    """(max of lead + common // LEAD_DRIFT, max of lead - common // LEAD_DRIFT) over (common, lead) notes."""
    return (max(lead + c // sr.LEAD_DRIFT for c, lead in notes), max(lead - c // sr.LEAD_DRIFT for c, lead in notes))


@FIXED
@given(notes=leads, split=st.integers(min_value=0, max_value=40), one_by_one=st.booleans())
def test_the_floor_is_the_least_delay_ever_seen_with_the_receipt_clocks_drift_allowed(
        notes: list[tuple[int, int]], split: int, one_by_one: bool) -> None:
    """Messages noted one by one or in batches give the same floor: the largest lead (common - receipt, ns)
    plus and minus the drift a receipt clock may have had by then; its bounds at a common stamp widen by the
    drift since."""
    s = sr.SensorStream(None)
    assert s.floor is None and s.floor_bounds(10**12) is None
    commons = np.array([c for c, _ in notes], dtype=np.int64)
    receipts = np.array([c - lead for c, lead in notes], dtype=np.int64)
    if one_by_one:
        for c, r in zip(commons.tolist(), receipts.tolist()):
            s.note_lead(c, r)
    else:
        s.note_leads(commons[:split], receipts[:split])
        s.note_leads(commons[split:], receipts[split:])
    floor = _floor_oracle(notes)
    assert s.floor == floor and all(type(v) is int for v in s.floor)
    at = int(commons.max()) + 12_345
    assert s.floor_bounds(at) == (floor[0] - at // sr.LEAD_DRIFT, floor[1] + at // sr.LEAD_DRIFT)
    # the lead: the recent arrivals' largest, or the floor's least bound at the last common stamp if larger
    s.lastc = at
    recent = max(c - r for c, r in list(zip(commons.tolist(), receipts.tolist()))[-sr.LEAD_WINDOW:])
    assert s.lead() == max(recent, floor[0] - at // sr.LEAD_DRIFT)


def test_a_message_without_a_receipt_leaves_the_lead_alone_and_an_empty_batch_too() -> None:
    s = sr.SensorStream(None)
    s.note_lead(10**9, None)
    s.note_leads(np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert s.floor is None and not s.arrivals


def test_the_lead_after_the_recent_arrivals_all_came_late_is_the_floors() -> None:
    """A receiver draining a queue longer than the window: the window's arrivals are all 2 s late, the floor
    remembers the on-time ones (lead 0 at 1 s, so at least -2 ns of drift by 10 s)."""
    s = sr.SensorStream(None)
    s.note_lead(NS_PER_S, NS_PER_S)
    for k in range(sr.LEAD_WINDOW):
        c = 2 * NS_PER_S + k * MS
        s.note_lead(c, c + 2 * NS_PER_S)
    s.lastc = 10 * NS_PER_S
    assert max(c - r for c, r in s.arrivals) == -2 * NS_PER_S
    assert s.lead() == s.floor[0] - 10 * NS_PER_S // sr.LEAD_DRIFT
    assert abs(s.lead()) < 2 * MS


@pytest.mark.parametrize(("lead", "result"), [(5 * MS, False), (5 * MS + 1, True), (4 * MS, False)])
def test_ahead_of_is_half_a_period_beyond_the_streams_lead_on_the_common_timeline(lead: int, result: bool) -> None:
    s = _timed_stream(late=MS)  # lead -1 ms
    s.base = 7 * NS_PER_S  # common = stamp + base
    stamp = 3 * NS_PER_S
    arrival = stamp + s.base + MS - lead  # the stamp leads its arrival by ``lead`` more than the stream's
    assert s.lead() == -MS
    assert s.ahead_of(stamp, arrival, 10 * MS) is result


def test_unseen_needs_a_receipt_a_previous_receipt_and_timed_arrivals() -> None:
    s = _timed_stream()
    assert s.unseen(s.last + 20 * MS, None, 10 * MS) is None
    assert s.unseen(s.last + 20 * MS, s.last_receipt + 10 * MS, 10 * MS) is True
    untimed = _stream_with([10 * MS] * 8)
    untimed.last_receipt = untimed.last
    assert untimed.unseen(untimed.last + 20 * MS, untimed.last + 10 * MS, 10 * MS) is None
    none_before = _timed_stream()
    none_before.last_receipt = None
    assert none_before.unseen(none_before.last + 20 * MS, none_before.last + 10 * MS, 10 * MS) is None


@pytest.mark.parametrize(("stamp_gap", "receipt_gap", "result"), [
    (20 * MS, 15 * MS, False), (20 * MS, 15 * MS - 1, True),  # the interval beyond the arrivals' by half a period
    (20 * MS, MS, True), (20 * MS, 0, True),  # bunched (within a quarter period): the lead alone decides
    (4 * MS, 0, False), (16 * MS, 2 * MS, True),
])
def test_unseen_is_the_stamps_running_ahead_of_the_arrivals_by_half_a_period(stamp_gap: int, receipt_gap: int,
                                                                            result: bool) -> None:
    s = _timed_stream(late=MS)
    assert s.unseen(s.last + stamp_gap, s.last_receipt + receipt_gap, 10 * MS) is result


@pytest.mark.parametrize(("receipt_gap", "result"), [(15_500_000, False), (15 * MS, False), (15 * MS - 1, True)])
def test_unseen_needs_the_interval_beyond_the_arrivals_too_not_the_lead_alone(receipt_gap: int, result: bool) -> None:
    """The previous message came on time (1 ms earlier than the stream's lead says): a stamp 20 ms on whose
    arrival came 15.5 ms on leads by over half a period (10 ms) more than the stream's stamps do, but its
    interval beyond the arrivals' (4.5 ms) is under half a period: not a step. At exactly half a period, not
    either."""
    s = _timed_stream(late=MS)
    s.last_receipt = s.last
    assert s.ahead_of(s.last + 20 * MS, s.last + receipt_gap, 10 * MS)
    assert s.unseen(s.last + 20 * MS, s.last + receipt_gap, 10 * MS) is result


def test_timed_looks_at_the_recent_arrivals_when_the_whole_window_does_not_keep_time() -> None:
    s = sr.SensorStream(None)
    for k in range(100):  # a backlog: stamps 10 ms apart, delivered 1 ms apart (the lead grows)
        s.note_lead(k * 10 * MS, 5 * NS_PER_S + k * MS)
    assert not s.timed()
    for k in range(100, 100 + sr.RECENT):  # then on time
        s.note_lead(k * 10 * MS, k * 10 * MS + MS)
    assert not sr.timed_arrivals(s.arrivals) and s.timed()


def test_the_arrival_window_keeps_its_last_lead_window_messages() -> None:
    s = sr.SensorStream(None)
    for k in range(sr.LEAD_WINDOW + 5):
        s.note_lead(k, k)
    assert len(s.arrivals) == sr.LEAD_WINDOW and s.arrivals[0] == (5, 5)
    assert s.jumps.maxlen == sr.JUMPS_KEPT and s.base == 0 and s.since == 0 and s.burst_count == 0
    assert s.last == s.lastc == s.grid_first == s.burst_from == sr.NEVER
    assert s.hidden is False and s.seen_step is False and s.tail == [] and not s.busy
    clock = _Clock(None)
    assert sr.SensorStream(clock).clock is clock
    assert s.held is s.placing is s.placed_at is s.follows is s.heard is s.last_receipt is s.before is None


@pytest.mark.parametrize(("lead_off", "result"), [(5 * MS, True), (5 * MS + 1, False), (-5 * MS, True),
                                                  (-5 * MS - 1, False), (0, True)])
def test_resumed_on_time_is_within_half_a_period_of_the_floors_bounds(lead_off: int, result: bool) -> None:
    s = sr.SensorStream(None)
    s.note_lead(NS_PER_S, NS_PER_S + MS)  # lead -1 ms at 1 s
    s.base = 2 * NS_PER_S
    stamp = 8 * NS_PER_S
    low, high = s.floor_bounds(stamp + s.base)
    receipt = stamp + s.base - (high if lead_off > 0 else low) - lead_off
    assert s.resumed_on_time(stamp, receipt, 10 * MS) is result
    assert s.resumed_on_time(stamp, None, 10 * MS) is False
    assert sr.SensorStream(None).resumed_on_time(stamp, receipt, 10 * MS) is False


@pytest.mark.parametrize(("held_lead", "next_lead", "result"), [
    (-7 * MS, -7 * MS, True), (-6 * MS, -6 * MS, False), (-6 * MS - 1, -6 * MS - 1, True),
    (-7 * MS, -9 * MS, True), (-7 * MS, -9 * MS - 500_000, False), (-7 * MS, -5 * MS, True), (-7 * MS, -4 * MS, False),
])
def test_behind_alike_is_both_trailing_their_arrivals_by_the_same_half_period(held_lead: int, next_lead: int,
                                                                             result: bool) -> None:
    """The stream's lead is -1 ms: a held stamp trailing its arrival by more than half a period (10 ms) beyond it,
    and the next one by the same amount to a quarter period."""
    s = _timed_stream(late=MS)
    s.base = 3 * NS_PER_S + 7  # leads on the common timeline
    held = (s.last - 50 * MS, None, None, s.last - 50 * MS + s.base - held_lead)
    message = (s.last - 40 * MS, None, None, s.last - 40 * MS + s.base - next_lead)
    assert s.behind_alike(held, message, 10 * MS) is result
    assert s.behind_alike(held[:3] + (None,), message, 10 * MS) is False
    assert s.behind_alike(held, message[:3] + (None,), 10 * MS) is False
    assert _stream_with([10 * MS] * 8).behind_alike(held, message, 10 * MS) is False  # arrivals that keep no time


# -- the sample grid of a segment ----------------------------------------------------------------------
class _Clock:
    def __init__(self, period_ns: float | None) -> None:
        self.period_ns = period_ns


def _on_a_grid(period: int = 10 * MS, periods: int = 20, jitter: list[int] | None = None) -> sr.SensorStream:
    """A segment sampled every ``period`` for ``periods`` periods, its last stamp at 10 s (stamps off the
    grid by ``jitter``)."""
    s = sr.SensorStream(None)
    s.last = s.lastc = 10 * NS_PER_S
    s.grid_first = s.last - periods * period
    s.grid_periods = periods
    s.intervals = [period + (0 if jitter is None else jitter[k]) for k in range(sr.PERIOD_WINDOW)]
    s.period = sr.median_int(s.intervals)
    s.tail = [s.last - k * period for k in range(sr.TAIL - 1, -1, -1)]
    return s


def test_the_grid_period_pools_the_grids_before_a_step_or_a_pause_while_the_rate_holds() -> None:
    """A step of the stamps or a pause starts a new grid; the grids before it (a window of periods or more) keep
    their span and periods, and the period is the spans' sum over the periods' sum: a segment a few periods long
    after a step is placed with the rate of everything before it. A rate the recent intervals do not keep (one
    eighth off) is the current grid's alone."""
    s = _on_a_grid(periods=sr.PERIOD_WINDOW)
    s.grid_first -= 80  # this grid: 10 ns a period long
    s.grid_past = (1_000 * 10 * MS + 30, 1_000)  # earlier grids: 30 ns over 1,000 periods
    pooled = (1_000 * 10 * MS + 30 + sr.PERIOD_WINDOW * 10 * MS + 80) / (1_000 + sr.PERIOD_WINDOW)
    assert s.grid_period() == pooled
    s.grid_periods, s.grid_first = 2, s.last - 2 * 10 * MS - 20  # a short grid adds its own periods too
    assert s.grid_period() == (1_000 * 10 * MS + 30 + 2 * 10 * MS + 20) / 1_002
    s.grid_periods = 0
    assert s.grid_period() == (1_000 * 10 * MS + 30) / 1_000
    s.intervals = [12 * MS] * sr.PERIOD_WINDOW  # the recent rate is another: the grids before do not count
    s.period = 12 * MS
    assert s.grid_period() == 12 * MS
    s.grid_periods, s.grid_first = sr.PERIOD_WINDOW, s.last - sr.PERIOD_WINDOW * 12 * MS
    assert s.grid_period() == 12 * MS
    s.new_grid(s.last, s.last)  # kept: a window of periods
    assert s.grid_past == (1_000 * 10 * MS + 30 + sr.PERIOD_WINDOW * 12 * MS, 1_000 + sr.PERIOD_WINDOW)
    s.grid_periods = sr.PERIOD_WINDOW - 1
    s.new_grid(s.last, s.last)  # not kept: fewer (its two ends' jitter over too few periods)
    assert s.grid_past[1] == 1_000 + sr.PERIOD_WINDOW


def test_a_step_of_the_stamps_keeps_the_grid_it_ends_for_the_period() -> None:
    """The acceptance rule keeps a sensor's grid when its stamps step (a restart) and starts the next at the
    new stamp."""
    rule = SetSynchronizer(1)
    stamps = [10 * NS_PER_S + k * 10 * MS for k in range(40)]
    for t in stamps:
        rule.add(0, t, 1.0, 2.0, 3.0, t + MS)
    s = rule.streams[0]
    periods, span = s.grid_periods, s.last - s.grid_first
    assert periods >= sr.PERIOD_WINDOW and span == periods * 10 * MS
    jump = stamps[-1] + 60 * NS_PER_S
    for k in range(2 * sr.PERIOD_WINDOW + 4):  # (a new segment's first messages wait for their placement)
        rule.add(0, jump + k * 10 * MS, 1.0, 2.0, 3.0, stamps[-1] + (k + 1) * 10 * MS + MS)
    assert s.grid_past == (span, periods)
    assert s.grid_first >= jump and s.last == jump + (2 * sr.PERIOD_WINDOW + 3) * 10 * MS


def test_the_grid_period_is_the_segments_span_over_its_periods_once_they_are_a_window() -> None:
    s = _on_a_grid(periods=sr.PERIOD_WINDOW)
    s.grid_first -= 4  # a span 4 ns longer over 8 periods
    assert s.grid_period() == (s.last - s.grid_first) / sr.PERIOD_WINDOW
    s.grid_periods = sr.PERIOD_WINDOW - 1
    assert s.grid_period() == s.suspect_period() == 10 * MS
    s.intervals = s.intervals[:-1]
    assert s.grid_period() is None and s.suspect_period() is None and s.best_period() is None
    s.clock = _Clock(9_999_999.5)
    assert s.best_period() == 9_999_999.5
    s.clock = _Clock(None)
    assert s.best_period() is None


@pytest.mark.parametrize(("offset", "off"), [(2_500_000, False), (2_500_001, True), (-2_500_001, True),
                                             (7_500_000, False), (7_499_999, True), (30 * MS, False),
                                             (30 * MS + 2_600_000, True)])
def test_off_grid_is_beyond_a_quarter_period_of_the_segments_grid(offset: int, off: bool) -> None:
    s = _on_a_grid()
    assert s.off_grid(s.last + offset) is off
    s.base = 3 * NS_PER_S + 3_300_000  # on the common timeline: the stamp and the grid move alike
    s.tail = [c + s.base for c in s.tail]
    assert s.off_grid(s.last + offset) is off


def test_off_grid_allows_the_stamps_jitter_and_says_nothing_without_a_grid_it_trusts() -> None:
    jittery = _on_a_grid(jitter=[0, 700_000, -700_000, 700_000, -700_000, 0, 0, 700_000])
    limit = jittery.jitter()
    assert limit > 2_500_000 and 2 * limit < 10 * MS
    assert jittery.off_grid(jittery.last + 3 * MS) is False
    assert jittery.off_grid(jittery.last + int(limit) + 2) is True
    wild = _on_a_grid(jitter=[0, 1_000_000, -1_000_000, 1_000_000, -1_000_000, 0, 1_000_000, -1_000_000])
    assert 2 * wild.jitter() >= 10 * MS and wild.off_grid(wild.last + 5 * MS) is False  # too jittery to tell
    no_tail = _on_a_grid()
    no_tail.tail = []
    assert no_tail.off_grid(no_tail.last + 5 * MS) is False
    moved = _on_a_grid()  # the recent intervals (10 ms) no longer keep the segment's grid (12 ms): no grid
    moved.grid_first = moved.last - 20 * 12 * MS
    assert moved.off_grid(moved.last + 5 * MS) is False
    kept = _on_a_grid()  # a grid of 11 ms against recent intervals of 10: within an eighth, still kept
    kept.grid_first = kept.last - 20 * 11 * MS
    kept.tail = [kept.last - k * 11 * MS for k in range(sr.TAIL - 1, -1, -1)]
    assert kept.off_grid(kept.last + 11 * MS) is False and kept.off_grid(kept.last + 5 * MS) is True
    assert sr.SensorStream(None).off_grid(123) is False


def test_off_grid_edges_of_the_grid_kept_and_of_the_jitter_allowed() -> None:
    """A grid of 9 ms against recent intervals of 8 (off by exactly an eighth: kept); a grid of 12.5 ms against
    intervals of 12 +- 1 ms whose jitter allows exactly half the short period (too jittery: nothing said)."""
    eighth = _on_a_grid(period=8 * MS)
    eighth.grid_first = eighth.last - 20 * 9 * MS
    eighth.tail = [eighth.last - k * 9 * MS for k in range(sr.TAIL - 1, -1, -1)]
    assert eighth.grid_period() == 9 * MS and eighth.off_grid(eighth.last + 4 * MS) is True
    half = _on_a_grid(period=12 * MS, jitter=[-MS, MS, -MS, MS, -MS, MS, -MS, MS])
    assert half.period == 12 * MS and 2 * half.jitter() == 12 * MS
    half.grid_first = half.last - 20 * 12_500_000
    half.tail = [half.last - k * 12_500_000 for k in range(sr.TAIL - 1, -1, -1)]
    assert half.off_grid(half.last + 6_250_000) is False


# -- what the rule reads off other sensors -------------------------------------------------------------
def test_the_shift_of_a_jump_is_its_base_after_less_the_previous_jumps() -> None:
    s = sr.SensorStream(None)
    assert sr._shift(s) == 0
    s.jumps.append((1, 2, None, 5 * NS_PER_S))
    assert sr._shift(s) == 5 * NS_PER_S
    s.jumps.append((3, 4, 10, 3 * NS_PER_S))
    assert sr._shift(s) == -2 * NS_PER_S


def test_the_latest_message_by_a_receipt_is_the_last_that_came_by_then() -> None:
    s = sr.SensorStream(None)
    s.base = 100
    for k in range(5):
        s.note_lead(1_000 + k * 10 + s.base, 2_000 + k * 10)
    s.last, s.last_receipt = 1_040, 2_040
    assert sr._latest_by(s, None) == (1_040, 2_040)
    assert sr._latest_by(s, 2_040) == (1_040, 2_040)
    assert sr._latest_by(s, 2_039) == (1_030, 2_030)
    assert sr._latest_by(s, 2_000) == (1_000, 2_000)
    assert sr._latest_by(s, 1_999) is None
    s.last_receipt = None
    assert sr._latest_by(s, 5) == (1_040, None)


def test_lateness_is_against_the_streams_lead() -> None:
    s = _timed_stream(late=MS)  # lead -1 ms
    s.base = 5
    assert sr._lateness(s, (100, 100 + 5 + 4 * MS)) == 3 * MS
    assert sr._lateness(s, (100, 100 + 5 + MS)) == 0


@pytest.mark.parametrize(("off", "late", "result"), [(5 * MS, 0, False), (5 * MS + 1, 0, True),
                                                    (-5 * MS - 1, 0, True), (8 * MS, 3 * MS, False),
                                                    (8 * MS + 1, 3 * MS, True), (5 * MS + 1, -3 * MS, True)])
def test_arrivals_disown_a_placement_half_a_period_beyond_the_others_lateness(off: int, late: int,
                                                                             result: bool) -> None:
    other = _timed_stream(late=MS)  # lead -1 ms
    latest = (other.last, other.last + MS + late)  # the other's latest message, ``late`` later than its lead
    grid = (0.0, float(10 * MS))
    assert sr._arrivals_disown(other, latest, off, grid) is result
    assert sr._arrivals_disown(other, latest, off, None) is False
    assert sr._arrivals_disown(other, (latest[0], None), off, grid) is False
    assert sr._arrivals_disown(sr.SensorStream(None), latest, off, grid) is False
    untimed = _stream_with([10 * MS] * 8)
    untimed.note_lead(1, 1)
    assert sr._arrivals_disown(untimed, latest, off, grid) is False


@pytest.mark.parametrize(("receipt", "since", "stale"), [(1, 2, True), (2, 2, False), (3, 2, False),
                                                         (None, 2, False), (1, None, False)])
def test_another_sensors_latest_is_stale_if_it_came_before_this_ones_previous(receipt, since, stale) -> None:
    assert sr._stale(receipt, since) is stale


def test_an_empty_batch_has_the_shapes_and_types_of_one() -> None:
    b = sr.empty_batch(3)
    assert b.stamps.shape == (0, 3) and b.stamps.dtype == np.int64
    assert b.vectors.shape == (0, 3, 3) and b.vectors.dtype == np.float64 and len(b) == 0


@pytest.mark.parametrize(("more", "result"), [(700 * MS, True), (5 * MS, False), (5 * MS + 1, True), (0, False),
                                              (-700 * MS, False)])
def test_trails_is_the_arrivals_seeing_more_of_a_gap_than_the_stamps_by_half_a_period(more: int, result: bool) -> None:
    """After a 3.3 s gap of the stamps, the arrivals saw ``more`` time pass (its message as late as the stream's):
    beyond half a period (10 ms) the stamps stepped back in the gap."""
    s = _timed_stream(late=MS)
    stamp = s.last + 3_300 * MS
    receipt = s.last_receipt + 3_300 * MS + more
    assert s.trails(stamp, receipt, 10 * MS) is result
    assert s.trails(stamp, None, 10 * MS) is False
    untimed = _stream_with([10 * MS] * 8)
    untimed.last_receipt = untimed.last
    assert untimed.trails(stamp, receipt, 10 * MS) is False

"""The side-stream acceptance and the calibration file's bounds at their edges, one rule at a time.

``test_stream_properties.py`` checks the side streams' acceptance as a whole against a truth oracle;
these tests pin each rule's boundary (inclusive or not), what each fault is called and what the
refusals name: the mutants of ``core/side_streams.py`` and ``core/calibration_bounds.py`` that a
mutation run (docs/mutation_report.md) found alive before them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcal_ros.core import calibration_bounds as cb
from magcal_ros.core import side_streams as side
from magcal_ros.core.units import EARTH_FIELD_RANGE, NS_PER_S
from magcal_ros.errors import InputError

MS = NS_PER_S // 1000


# -- values ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("value", "fault"), [
    (-60.0, None), (150.0, None), (20.0, None), (-60.0001, "out_of_range"), (150.0001, "out_of_range"),
    (float("nan"), "nonfinite"), (float("inf"), "nonfinite"), (-float("inf"), "nonfinite"), ("25", None),
])
def test_a_scalar_streams_range_is_inclusive_and_a_non_number_is_not_out_of_range(value: object, fault: str) -> None:
    assert side.scalar_check(-60.0, 150.0)(value) == fault
    assert side.TEMPERATURE.check(value) == fault


Q = (1.0, 0.0, 0.0, 0.0)
W = (0.0, 0.0, 0.0)
NAN3, NAN4 = (math.nan,) * 3, (math.nan,) * 4


@pytest.mark.parametrize(("q", "w", "parts", "fault"), [
    (Q, W, (True, True, True), None),
    ((1.001, 0.0, 0.0, 0.0), (side.MAX_RATE, 0.0, 0.0), (True, True, True), None),  # both bounds inclusive
    ((0.9991, 0.0, 0.0, 0.0), (0.0, 0.0, -side.MAX_RATE), (True, True, True), None),
    ((1.0011, 0.0, 0.0, 0.0), W, (False, True, True), None),  # an orientation off the unit norm: gyro only
    ((2.0, 0.0, 0.0, 0.0), NAN3, (False, False, True), "out_of_range"),
    (Q, (0.0, side.MAX_RATE * 1.001, 0.0), (True, False, True), None),
    (NAN4, (40.0, 0.0, 0.0), (False, False, True), "out_of_range"),
    (NAN4, NAN3, (False, False, False), "nonfinite"),
    ((math.nan, 0.0, 0.0, 1.0), (math.inf, 0.0, 0.0), (False, False, False), "nonfinite"),
    ((1.0, 0.0, 0.0, math.inf), W, (False, True, True), None),
])
def test_an_imu_sample_is_a_value_while_either_part_is_usable(q: tuple, w: tuple, parts: tuple, fault: str) -> None:  # type: ignore[type-arg]
    assert side.imu_parts((q, w)) == parts
    assert side.imu_check((q, w)) == fault
    assert side.IMU.check((q, w)) == fault


def test_usable_imu_normalises_orientations_keeps_unit_ones_bit_for_bit_and_blanks_unusable_parts() -> None:
    half = math.sqrt(0.5)
    samples = [((1, 0, 0, 0), (0, 0, 1)),  # integers, as a CSV reader may give them
               ((half, half, 0.0, 0.0), (0.1, 0.2, 0.3)),
               ((0.0, 0.0, 1.0005, 0.0), (40, 0, 0)),  # a slightly long orientation; a gyro beyond its range
               ((2, 0, 0, 0), (0, 0, 0))]  # no orientation
    q, w = side.usable_imu(samples)
    assert q.shape == (4, 4) and w.shape == (4, 3) and q.dtype == float and w.dtype == float
    assert q[0].tolist() == [1.0, 0.0, 0.0, 0.0] and q[1].tolist() == [half, half, 0.0, 0.0]
    assert np.allclose(q[2], [0.0, 0.0, 1.0, 0.0], rtol=0, atol=1e-15)
    assert np.all(np.isnan(q[3])) and np.all(np.isnan(w[2]))
    assert w[0].tolist() == [0.0, 0.0, 1.0] and w[3].tolist() == [0.0, 0.0, 0.0]
    q, w = side.usable_imu([((2, 0, 0, 0), (0, 0, 1)), ((1, 0, 0, 0), (40, 0, 0))])  # integers only
    assert np.all(np.isnan(q[0])) and q[1].tolist() == [1.0, 0.0, 0.0, 0.0] and np.all(np.isnan(w[1]))
    empty_q, empty_w = side.usable_imu([])
    assert empty_q.shape == (0, 4) and empty_w.shape == (0, 3)


def test_a_stream_is_a_units_error_only_when_more_than_half_of_its_numbers_are_out_of_range() -> None:
    check = side.TEMPERATURE.check
    nan, k = math.nan, 293.0  # kelvin
    assert not side.bulk_out_of_range(check, [k, k, k, 20.0, 21.0, 22.0])  # exactly half
    assert side.bulk_out_of_range(check, [k, k, k, k, 21.0, 22.0])
    assert side.bulk_out_of_range(check, [nan, nan, nan, k, k, 20.0])  # NaN are no number, not in range
    assert not side.bulk_out_of_range(check, [nan, nan, nan])
    assert not side.bulk_out_of_range(check, [])
    with pytest.raises(InputError) as err:
        side.refuse_units(side.TEMPERATURE, [20.0, 300.0, 294.0, 295.0], "mag2 temperature")
    assert str(err.value) == ("mag2 temperature: temperature 300 deg C and most others are out of range: "
                              "temperatures must be in deg C")
    with pytest.raises(InputError) as err:
        side.refuse_units(side.IMU, [((2.0, 0, 0, 0), (50.0, 0, 0))] * 2, "imu")
    assert "IMU sample ((2.0, 0, 0, 0), (50.0, 0, 0))" in str(err.value)
    assert str(err.value).endswith("IMU samples must be in the ROS convention")


def test_what_a_stream_lost_is_told_in_one_line_and_nothing_when_it_lost_nothing() -> None:
    c = side.SideCounts(received=300, accepted=296, nonfinite=1, out_of_range=1, glitch=2)
    assert c.dropped() == 4 and c.as_dict()["glitch"] == 2
    assert c.describe("mag1 temperature") == ("mag1 temperature: 4 of 300 samples dropped (1 not a number, "
                                              "1 out of range, 2 far off the stream's stamps)")
    assert side.SideCounts(received=300, accepted=299, held=1).describe("mag1 temperature") == ""


# -- stamps ------------------------------------------------------------------------------------------
def _rule(n: int = 20, period: int = 100 * MS) -> side.SideAcceptance:
    """A rule that took ``n`` samples 0, period, ... (its rhythm known)."""
    rule = side.SideAcceptance(side.TEMPERATURE.check)
    for k in range(n):
        assert rule.offer(k * period, 20.0) == [(k * period, 20.0)]
    return rule


def test_the_rhythm_is_the_median_of_the_last_sixteen_intervals_and_sets_how_far_is_far() -> None:
    rule = side.SideAcceptance(side.TEMPERATURE.check)
    assert rule.interval is None and rule.far() == side.FAR_EARLY
    for t in (0, 4 * NS_PER_S, 8 * NS_PER_S):
        rule.offer(t, 20.0)
    assert rule.interval is None  # two intervals: not yet a rhythm
    rule.offer(12 * NS_PER_S, 20.0)
    assert rule.interval == 4 * NS_PER_S and rule.far() == side.FAR_PERIODS * 4 * NS_PER_S
    rule = _rule(20, 100 * MS)
    assert rule.interval == 100 * MS and rule.far() == side.FAR_MIN  # at least FAR_MIN
    t = 19 * 100 * MS
    for _ in range(side.INTERVALS // 2 + 1):  # more than half of the last 16 intervals at 300 ms
        t += 300 * MS
        rule.offer(t, 20.0)
    assert rule.interval == 300 * MS
    rule.offer(t, 20.0)  # a repeated stamp is no interval
    assert rule.interval == 300 * MS and rule.last == t


def test_a_repeated_stamp_adds_no_interval_to_the_rhythm() -> None:
    rule = side.SideAcceptance(side.TEMPERATURE.check)
    for t in (0, 100, 200, 500, 800, 800):  # intervals 100, 100, 300, 300 (a zero would make it 100)
        rule.offer(t * MS, 20.0)
    assert rule.interval == 300 * MS and rule.counts.accepted == 6


@pytest.mark.parametrize(("intervals", "rhythm"), [
    ([1000] * 9 + [100] * 16, 100),
    ([1000] * 8 + [100] * 8, 1000),  # the window is sixteen intervals, not fifteen: 8 of each, the upper middle
    ([1000, 100] + [100] * 8 + [1000] * 7, 100),  # the oldest goes first: 9 short ones of the last sixteen
])
def test_the_rhythm_forgets_intervals_older_than_the_last_sixteen(intervals: list[int], rhythm: int) -> None:
    rule = side.SideAcceptance(side.TEMPERATURE.check)
    t = 0
    rule.offer(t, 20.0)
    for dt in intervals:  # ms
        t += dt * MS
        rule.offer(t, 20.0)
    assert rule.interval == rhythm * MS and rule.counts.accepted == len(intervals) + 1


def test_a_stamp_exactly_as_far_as_far_goes_is_taken_one_beyond_is_held() -> None:
    rule = _rule()
    last = rule.last
    assert rule.offer(last + side.FAR_MIN, 21.0) == [(last + side.FAR_MIN, 21.0)]
    rule = _rule()
    assert rule.offer(last + side.FAR_MIN + 1, 21.0) == [] and rule.counts.held == 1
    # the next one goes on from the old sequence: the held one was a glitch
    assert rule.offer(last + 100 * MS, 22.0) == [(last + 100 * MS, 22.0)]
    assert rule.counts.glitch == 1 and rule.counts.held == 0 and rule.counts.accepted == 21


@pytest.mark.parametrize("sign", [1, -1])
def test_a_held_stamp_is_kept_when_the_next_lies_nearer_to_it_or_as_near(sign: int) -> None:
    rule = _rule()
    last = rule.last
    jump = sign * 3 * NS_PER_S  # beyond FAR_MIN (2 s), its half within
    assert rule.offer(last + jump, 21.0) == []
    tie = last + jump // 2  # as near to both: the stream goes on from the held one
    assert rule.offer(tie, 22.0) == [(last + jump, 21.0), (tie, 22.0)]
    assert rule.counts.glitch == 0 and rule.counts.accepted == 22


def test_a_stream_that_ends_on_a_held_stamp_keeps_it() -> None:
    rule = _rule()
    far = rule.last + 3 * side.FAR_MIN
    assert rule.offer(far, 21.0) == [] and rule.counts.held == 1
    assert rule.finish() == [(far, 21.0)]
    c = rule.counts
    assert (c.held, c.accepted, c.glitch, c.received) == (0, 21, 0, 21) and rule.last == far
    assert rule.finish() == [] and rule.counts.accepted == 21
    stamps, values, counts = side.accepted_samples(side.TEMPERATURE.check, [0, 100 * MS, 50 * NS_PER_S + 1],
                                                   [20.0, 21.0, 22.0])
    assert stamps == [0, 100 * MS, 50 * NS_PER_S + 1] and values == [20.0, 21.0, 22.0] and counts.held == 0


def test_a_sample_is_due_once_the_streams_rhythm_says_it_is_stamped_at_or_before_the_set() -> None:
    rule = side.SideAcceptance(side.TEMPERATURE.check)
    assert not rule.due(10 * NS_PER_S)  # nothing yet: no rhythm
    rule = _rule(5, 100 * MS)
    last = rule.last
    assert not rule.due(last + 100 * MS - 1) and rule.due(last + 100 * MS)
    rule.offer(last + 20 * NS_PER_S, 21.0)  # held
    assert rule.due(last + 20 * NS_PER_S) and not rule.due(last + 100 * MS - 1)
    rule = _rule(5, 100 * MS)
    behind = rule.last - 20 * NS_PER_S
    rule.offer(behind, 21.0)  # held, far behind: due at its own stamp, not before
    assert rule.due(behind) and not rule.due(behind - 1)


# -- waiting sets ------------------------------------------------------------------------------------
def test_a_set_waits_while_a_sample_is_due_and_at_most_the_longest_wait_of_awake_time() -> None:
    waiting = side.WaitingSets(max_wait_ns=500 * MS, awake_step_ns=100 * MS)
    due = {1}
    waiting.add(1, 0, "a")
    waiting.add(2, 0, "b")
    assert len(waiting) == 2
    assert waiting.release(50 * MS, lambda s: s in due) == []  # "a" waits; "b" behind it too
    due.clear()
    assert waiting.release(60 * MS, lambda s: s in due) == ["a", "b"] and len(waiting) == 0
    waiting.add(3, 100 * MS, "c")
    t = 100 * MS
    for _ in range(5):  # 500 ms awake: not more than the wait
        t += 100 * MS
        assert waiting.release(t, lambda s: True) == []
    assert waiting.release(t + 1, lambda s: True) == ["c"]


def test_awake_time_adds_the_clocks_small_steps_and_never_a_step_back() -> None:
    waiting = side.WaitingSets(max_wait_ns=500 * MS, awake_step_ns=50 * MS)
    waiting.add(1, 0, "a")
    for t in range(10, 500, 10):  # 490 ms in steps of 10 ms
        assert waiting.release(t * MS, lambda s: True) == []
    assert waiting.release(501 * MS, lambda s: True) == ["a"]
    waiting = side.WaitingSets(max_wait_ns=500 * MS, awake_step_ns=100 * MS)
    waiting.add(1, 0, "a")
    # awake: 100 (a stall, capped), back 50 ms (nothing), +40 from the latest clock, then +100 three times
    for t in (10_000, 9_950, 10_040, 10_140, 10_240, 10_340, 10_395):
        assert waiting.release(t * MS, lambda s: True) == [], t  # 495 ms awake at the last
    assert waiting.release(10_401 * MS, lambda s: True) == ["a"]
    waiting = side.WaitingSets(max_wait_ns=500 * MS, awake_step_ns=50 * MS)
    waiting.add(1, 0, "a")
    for t in range(80, 641, 80):  # steps of 80 ms count 50 each: 400 ms awake
        assert waiting.release(t * MS, lambda s: True) == [], t
    assert waiting.release(740 * MS, lambda s: True) == []  # 450
    assert waiting.release(790 * MS, lambda s: True) == []  # 500: not more than the wait
    assert waiting.release(791 * MS, lambda s: True) == ["a"]


def test_a_stall_of_the_node_counts_as_one_awake_step_and_force_and_clear_release_everything() -> None:
    waiting = side.WaitingSets(max_wait_ns=500 * MS, awake_step_ns=100 * MS)
    waiting.add(1, 0, "a")
    assert waiting.release(10 * NS_PER_S, lambda s: True) == []  # a 10 s stall: 100 ms of awake time
    assert waiting.release(10 * NS_PER_S - NS_PER_S, lambda s: True) == []  # the clock going back counts nothing
    assert waiting.release(10 * NS_PER_S + 401 * MS, lambda s: True) == []  # 501 ms: 100 + 100 (capped) + ...
    waiting.add(2, 10 * NS_PER_S + 401 * MS, "b")
    assert waiting.release(10 * NS_PER_S + 402 * MS, lambda s: True, force=True) == ["a", "b"]
    waiting.add(3, 0, "c")
    waiting.add(4, 0, "d")
    assert waiting.clear() == 2 and len(waiting) == 0 and waiting.clear() == 0
    assert side.WaitingSets().max_wait_ns == side.MAX_WAIT and side.WaitingSets().awake_step_ns == side.AWAKE_STEP


# -- calibration bounds ------------------------------------------------------------------------------
def test_a_bounded_value_may_reach_its_limit_and_a_refusal_names_the_worst_element() -> None:
    v = cb.check_bounded("mag1.interference", np.array([[1e-6, -cb.MAX_INTERFERENCE]]), cb.MAX_INTERFERENCE, "T/A")
    assert v.dtype == float and v.shape == (1, 2)
    with pytest.raises(InputError) as err:
        cb.check_bounded("mag1.interference", np.array([[1e-6, 2e-6], [3e-6, -5e-4]]), cb.MAX_INTERFERENCE, "T/A")
    assert str(err.value) == "mag1.interference must be finite and within +-0.0001 T/A, got -0.0005"
    with pytest.raises(InputError, match="got nan$"):
        cb.check_bounded("mag1.interference", [[1e-6, math.nan], [2e-4, 0.0]], cb.MAX_INTERFERENCE, "T/A")
    assert cb.check_bounded("x", [1, 2], 2.0, "m").dtype == float
    cb.check_positions([[cb.MAX_POSITION, 0.0, -cb.MAX_POSITION]])
    with pytest.raises(InputError, match="got 51$"):
        cb.check_positions([[0.0, 0.0, 0.0], [1.0, 51.0, 0.0]])
    with pytest.raises(InputError, match="got nan$"):
        cb.check_positions([[0.0, 60.0, 0.0], [1.0, math.nan, 0.0]])
    cb.check_positions(np.zeros((0, 3)))


def test_a_covariance_is_finite_symmetric_to_its_own_scale_with_a_non_negative_diagonal() -> None:
    good = np.diag([4e-18, 1e-18, 0.0])  # T^2: nT-sized sigmas; a zero variance is a kept parameter's
    good[0, 1] = good[1, 0] = 1e-18
    cb.check_covariance("mag1", good)
    cb.check_covariance("mag1", np.full((3, 3), math.nan))  # not given
    cb.check_covariance("mag1", np.zeros((3, 3)))
    rounded = good.copy()
    rounded[0, 1] *= 1 + 1e-12  # symmetric to rounding
    cb.check_covariance("mag1", rounded)
    skew = good.copy()
    skew[0, 1] *= 1.001  # 1e-21 T^2 apart: asymmetric at the covariance's own scale
    negative = good.copy()
    negative[2, 2] = -1e-20
    partial = good.copy()
    partial[1, 2] = math.nan
    for bad in (skew, negative, partial, np.full((3, 3), math.inf)):
        with pytest.raises(InputError) as err:
            cb.check_covariance("mag1", bad)
        assert str(err.value) == "mag1.covariance must be a finite symmetric 3x3 with a non-negative diagonal (T^2)"


def test_noise_and_intensity_take_zero_for_unknown_and_their_bounds_inclusive() -> None:
    assert cb.check_noise("mag1.noise", 0) == 0.0 and cb.check_noise("mag1.noise", cb.MAX_NOISE) == cb.MAX_NOISE
    for bad in (-1e-9, cb.MAX_NOISE * 1.001):
        with pytest.raises(InputError, match="^mag1.noise must be 0"):
            cb.check_noise("mag1.noise", bad)
    low, high = EARTH_FIELD_RANGE
    for good in (0.0, low, high, 5e-5):
        assert cb.check_intensity("calibration_intensity", good) == good
    for bad in (1.0, -5e-5, low * 0.99, high * 1.01):
        with pytest.raises(InputError, match="^calibration_intensity "):
            cb.check_intensity("calibration_intensity", bad)
    for bad in (math.nan, True, "5e-5", None):
        with pytest.raises(InputError, match=r"^mag1.noise must be a finite number \(T\)"):
            cb.check_noise("mag1.noise", bad)
        with pytest.raises(InputError, match=r"^calibration_intensity must be a finite number"):
            cb.check_intensity("calibration_intensity", bad)


@pytest.mark.parametrize("span", [[5.0, 5.0], [-60.0, 150.0], np.array([[0.0], [10.0]])])
def test_a_temperature_span_may_be_one_temperature_and_reach_both_ends_of_the_range(span: object) -> None:
    assert cb.check_temperature_span("mag1.calibration_temperatures", span).shape == (2,)


@pytest.mark.parametrize(("span", "says"), [
    ([30.0, 20.0], "[30, 20] has its minimum above its maximum"),
    ([-61.0, 20.0], "[-61, 20] is not a span of temperatures in deg C (-60 .. 150)"),
    ([20.0, 151.0], "[20, 151] is not a span of temperatures in deg C"),
    ([273.0, 300.0], "[273, 300] is not a span"),
    ([1.0, 2.0, 3.0], "must be two finite numbers [min, max] in deg C, got [1.0, 2.0, 3.0]"),
    ("warm", "must be [min, max] in deg C, got 'warm'"),
])
def test_a_temperature_span_that_is_not_one_is_refused_naming_its_numbers(span: object, says: str) -> None:
    with pytest.raises(InputError) as err:
        cb.check_temperature_span("mag1.calibration_temperatures", span)
    assert str(err.value).startswith("mag1.calibration_temperatures ") and says in str(err.value)


# -- matching a stream's latest value to the sets ------------------------------------------------------
def test_the_latest_sample_within_the_tolerance_inclusive_and_the_last_recorded_of_equal_stamps() -> None:
    from magcal_ros.core.matching import finite_sorted, latest_before

    st = np.array([100, 200, 200, 300]) * MS
    idx, fresh = latest_before(st, np.array([50, 100, 199, 200, 250, 350, 351]) * MS, 50 * MS)
    assert idx.tolist() == [0, 0, 0, 2, 2, 3, 3]  # of equal stamps, the one recorded last
    assert fresh.tolist() == [False, True, False, True, True, True, False]
    idx, fresh = latest_before([], [1, 2], 10)
    assert idx.tolist() == [0, 0] and fresh.tolist() == [False, False]
    assert idx.dtype == np.int64 and fresh.dtype == bool
    stamps = np.random.default_rng(1).integers(0, 5, 500)  # many ties: a sort that is not stable reorders them
    ties = finite_sorted(stamps, np.arange(500.0))
    assert ties[1].tolist() == np.argsort(stamps, kind="stable").tolist()
    stamps, values = finite_sorted([30, 10, 20, 10], [[1.0, 2.0], [3.0, 4.0], [5.0, math.nan], [7.0, 8.0]])
    assert stamps.tolist() == [10, 10, 30] and values.tolist() == [[3.0, 4.0], [7.0, 8.0], [1.0, 2.0]]
    stamps, values = finite_sorted(np.zeros(0, np.int64), np.zeros((0, 3)))
    assert stamps.dtype == np.int64 and values.shape == (0, 3)


def test_each_stream_gives_each_set_its_latest_value_offline_and_live_a_stale_one_zero() -> None:
    from magcal_ros.core.matching import AcceptedSamples, LatestValues, match_latest

    a = AcceptedSamples(np.array([0, 100, 100, 200]) * MS, np.array([1.0, 2.0, 3.0, 4.0]))
    b = AcceptedSamples(np.array([150, 400]) * MS, np.array([-1.0, 1e30]))
    sets = np.array([100, 160, 260, 400]) * MS
    empty = AcceptedSamples(np.zeros(0, np.int64), np.zeros(0))
    values, fresh = match_latest(sets, [empty, a, b], 100 * MS)  # a stream without a sample: stale throughout
    assert values[:, 0].tolist() == [0.0] * 4 and fresh.dtype == bool and not np.any(fresh[:, 0])
    assert values[:, 1:].tolist() == match_latest(sets, [a, b], 100 * MS)[0].tolist()
    values, fresh = match_latest(sets, [a, b], 100 * MS)
    assert values.tolist() == [[3.0, 0.0], [3.0, -1.0], [4.0, 0.0], [0.0, 1e30]]
    assert fresh.tolist() == [[True, False], [True, True], [True, False], [False, True]]
    values, fresh = match_latest(sets, [a, b], 100 * MS, check=side.CURRENT.check)  # 1e30 A: no value
    assert values[3].tolist() == [0.0, 0.0] and fresh[3].tolist() == [False, False]
    live = LatestValues(2, 100 * MS, check=side.CURRENT.check)
    for j, s in ((0, a), (1, b)):
        for t, v in zip(s.stamps.tolist(), s.values.tolist()):
            live.add(j, t, v)
    assert [live.at(int(t)) for t in sets] == [([3.0, 0.0], [True, False]), ([3.0, -1.0], [True, True]),
                                               ([4.0, 0.0], [True, False]), ([0.0, 0.0], [False, False])]
    assert live.channels == 2 and live.received == [4, 1] and live.latest(0) == 4.0 and live.latest(1) == -1.0
    assert live.counts[1].out_of_range == 1 and LatestValues(1, 10).latest(0) is None


def test_a_live_store_keeps_its_last_seconds_and_at_most_its_count_whatever_the_arrival_order() -> None:
    from magcal_ros.core.matching import LatestValues

    store = LatestValues(1, 100 * MS, keep_ns=NS_PER_S)
    assert store.keep_ns == NS_PER_S and LatestValues(1, 600 * MS, keep_ns=NS_PER_S).keep_ns == 1200 * MS
    for t in (1000, 1100, 1050, 2000):  # ms; one out of order
        store.add(0, t * MS, float(t))
    assert store.at(1000 * MS) == ([1000.0], [True])  # exactly keep_ns behind the newest: kept
    store.add(0, 2001 * MS, 2001.0)
    assert store.at(1000 * MS) == ([0.0], [False]) and store.at(1100 * MS) == ([1100.0], [True])
    assert store.at(1060 * MS) == ([1050.0], [True])
    store.add(0, 2001 * MS, 7.0)  # the same stamp again: the one received last wins
    assert store.at(2001 * MS) == ([7.0], [True]) and store.received == [6]
    few = LatestValues(1, NS_PER_S, keep_ns=10 * NS_PER_S, most=3)
    for t in range(5):
        few.add(0, t * 100 * MS, float(t))
    assert few.at(100 * MS) == ([0.0], [False]) and few.at(200 * MS) == ([2.0], [True])
    assert few.at(450 * MS) == ([4.0], [True])
    finite = LatestValues(1, NS_PER_S)  # no range of its own: any number is a value
    for t, v in ((0, 1e300), (100, math.nan), (200, -1e300)):
        finite.add(0, t * MS, v)
    assert finite.received == [2] and finite.counts[0].nonfinite == 1


def test_a_live_store_says_a_sample_is_due_when_any_of_its_streams_does() -> None:
    from magcal_ros.core.matching import LatestValues

    store = LatestValues(2, 50 * MS)
    assert not store.due(10 * NS_PER_S)
    for k in range(5):
        store.add(1, k * 100 * MS, 1.0)
    assert not store.due(499 * MS) and store.due(500 * MS)


def test_the_sets_without_a_value_are_counted_per_stream_and_told_in_one_line() -> None:
    from magcal_ros.core.imu import ImuStats
    from magcal_ros.core.interference import CurrentStats
    from magcal_ros.core.matching import checked_samples

    stats = CurrentStats(("a", "b"), NS_PER_S // 2)
    keep = stats.keep(np.array([[True, True], [False, True], [False, False], [True, True]]))
    assert keep.tolist() == [True, False, False, True]
    stats.keep(np.array([[True, False]]))
    assert (stats.sets, stats.dropped, stats.stale) == (5, 3, [2, 2])
    assert stats.describe() == ("3 of 5 sets dropped without a current of every channel within 0.5 s before "
                                "the set (a: 2, b: 2)")
    stats.samples = [side.SideCounts(received=9, accepted=8, out_of_range=1), side.SideCounts(received=5, accepted=5)]
    assert stats.note() == stats.describe() + "; a current: 1 of 9 samples dropped (1 out of range)"
    imu = ImuStats(("imu",), NS_PER_S // 10)
    imu.keep(np.array([True, False, True]))
    assert imu.describe() == "1 of 3 sets dropped without an IMU sample within 0.1 s before the set (imu: 1)"
    assert ImuStats(("imu",), 1).note() == ""
    t, v = checked_samples("mag1 temperature", np.array([1, 2], np.uint32), [20, 21])
    assert t.dtype == np.int64 and v.dtype == float
    for stamps, values in (([1.0, 2.0], [20.0, 21.0]), ([1, 2], [20.0])):
        with pytest.raises(InputError, match="^mag1: one temperature per stamp$"):
            checked_samples("mag1: one temperature", stamps, values)

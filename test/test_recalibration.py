"""Recalibration during the mission (no middleware): what a window of the mission determines,
the held-out check, when the node recalibrates, and the rolling window of sets."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tensor_floor, tensor_rms
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.methods import recalibration
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.methods.progress import Assessment
from magcal_ros.nodes.buffer import MissionWindow
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.mission import Leg, mission, mission_attitudes
from magcal_ros.sim.simulator import ArraySimulation, Thruster, hard_iron_moved, random_sensor_errors
from magcal_ros.sim.temperature import draw_tempcos

INTENSITY = 51_500 * NT
NOISE = 1.0 * NT
S = NS_PER_S


@pytest.fixture(scope="module")
def drifted_array() -> tuple[ArraySimulation, ArraySimulation, ArrayCalibration]:
    """An array, the same after its hard iron moved by 300-800 nT, and the calibration that ran before."""
    rng = np.random.default_rng(21)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(INTENSITY, 60.0, 5.0),
                          noise=NOISE)
    running = replace(sim.true_calibration(), metadata={"intensity": INTENSITY})
    return sim, hard_iron_moved(sim, rng), running


@pytest.fixture
def drifted(drifted_array: tuple) -> tuple[ArraySimulation, ArraySimulation, ArrayCalibration, np.random.Generator]:
    """:func:`drifted_array` and a generator of its own for each test: what a test draws does not depend on
    which tests ran before it in the same process (pytest-xdist deals them out differently run to run)."""
    return (*drifted_array, np.random.default_rng(22))


def _window(sim: ArraySimulation, legs: list[Leg], rng: np.random.Generator, wobble: float = 5.0,
            sets: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    rec, _ = mission(sim, legs, rng, rate=100.0, wobble_deg=wobble)
    keep = np.unique(np.linspace(0, len(rec) - 1, sets).round().astype(int))
    return rec.stamps[keep], rec.vectors[keep]


def _solve(stamps: np.ndarray, raw: np.ndarray, running: ArrayCalibration) -> tuple:
    fit, held = recalibration.split(stamps)
    result = calibrate_array(raw[fit], running.geometry, None, "ml", None, running, None, (), stamps[fit])
    return result, fit, held


def test_a_minute_of_turns_after_the_jump_recalibrates_to_the_floor(drifted: tuple) -> None:
    """The window determines every offset, holds on its held-out fifth, and on fresh attitudes of the same
    kind the tensor is within 1.2x the floor sqrt(2) sigma / d (the drifted calibration: hundreds of times);
    on uniformly random ones, which a minute of yaw turns with 6 deg of wobble does not span, within 1.4x
    (1.03-1.30x over 30 draws of the window)."""
    sim, moved, running, rng = drifted
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    assert 0.15 < held.mean() < 0.25 and not np.any(fit & held)
    judged = recalibration.judge(result, running, raw[fit], raw[held], drifted=sim.geometry.names)
    why, figures = judged.problem, judged.figures
    assert why is None, why
    assert figures is not None and figures.sets == held.sum() and judged.kept == ()
    assert np.all(figures.tmi_new < 1.2 * NOISE) and np.all(figures.tmi_old > 100 * NOISE)
    assert figures.describe().startswith(f"{held.sum()} held-out sets: TMI RMS ")
    floor = tensor_floor(NOISE, 0.4)
    for fresh, bound in ((mission(moved, [Leg(60.0, 6.0)], rng, rate=20.0)[0], 1.2),
                         (moved.run(uniform_random(1000, rng), rng)[0], 1.4)):
        g = result.calibration.field_and_gradient(fresh.vectors)[2]
        g_old = running.field_and_gradient(fresh.vectors)[2]
        assert tensor_rms(g) < bound * floor and tensor_rms(g_old) > 100 * floor
    moved_by = [np.linalg.norm(m.hard_iron - s.hard_iron) / NT for m, s in zip(moved.sensors, sim.sensors)]
    text = recalibration.changes(running, result.calibration)
    shown = [float(part.split()[-2]) for part in text.split(": ", 1)[1].split(";")[0].split(", ")]
    assert np.allclose(shown, moved_by, rtol=0.05), (text, moved_by)


def test_a_window_without_attitude_change_never_pushes(drifted: tuple) -> None:
    """Straight and level, +-0.3 deg of wobble: the offsets across the track are not determined to a few
    times the noise; the verdict refuses, naming them, and what to fly."""
    _, moved, running, rng = drifted
    stamps, raw = _window(moved, [Leg(60.0, 0.0)], rng, wobble=0.3)
    result, fit, held = _solve(stamps, raw, running)
    judged = recalibration.judge(result, running, raw[fit], raw[held])
    why, figures = judged.problem, judged.figures
    assert why is not None and figures is None and judged.result is None
    assert why.startswith("the sets do not determine what changed (mag1 offset x (+- ")
    assert "turn through a full circle of heading" in why
    missing = recalibration.undetermined_offsets(result)
    assert missing and len(set(missing)) == len(missing)  # each sensor's own offsets, once
    for entry in missing:
        sensor, rest = entry.split(" ", 1)
        q = next(q for q in result.identifiability.quantities if q.sensor == sensor and rest.startswith(q.name))
        assert q.status == "kept" or q.sigma > 3.0 * NOISE / NT, entry
    n = len(missing)
    assert why.count(" offset ") == min(n, 4) and (n <= 4 or f" and {n - 4} more)" in why)


def test_the_held_out_sets_are_the_fourth_and_eighth_of_ten_stretches_in_time() -> None:
    stamps = np.arange(1000, dtype=np.int64) * 10_000_000 + 5 * NS_PER_S
    fit, held = recalibration.split(stamps[::-1])  # in any order
    assert list(np.flatnonzero(held[::-1])) == list(range(300, 400)) + list(range(700, 800))
    assert np.array_equal(fit, ~held)
    assert [len(m) for m in recalibration.split([])] == [0, 0]
    assert [list(m) for m in recalibration.split([7])] == [[True], [False]]


def test_a_calibration_that_does_not_hold_on_held_out_sets_is_refused(drifted: tuple) -> None:
    """Fitted before the jump, checked on sets after it (as when the window straddles a second change):
    the held-out TMI residual is far above the fit's, and nothing may be pushed."""
    sim, moved, running, rng = drifted
    stamps, raw = _window(sim, [Leg(60.0, 6.0)], rng)
    result, fit, _ = _solve(stamps, raw, running)
    _, after = _window(moved, [Leg(20.0, 6.0)], rng, sets=300)
    far = replace(running, offsets=running.offsets + 3000 * NT)  # a running calibration the fit beats everywhere
    judged = recalibration.judge(result, far, raw[fit], after)
    why = judged.problem
    assert why is not None and "held-out sets" in why and "more than 1.5x" in why and judged.result is None
    # no better than the running calibration on its own held-out sets: refused too
    _, held = recalibration.split(stamps)
    why = recalibration.judge(replace(result, calibration=running), running, raw[fit], raw[held]).problem
    assert why is not None and "no better for any sensor" in why
    assert recalibration.judge(result, None, raw[fit], raw[held]).problem.startswith("there is no running calibration")


def test_advice_says_what_to_fly() -> None:
    ready = Assessment(800, True, None, ("scale z",), "enough to recalibrate from the prior: ...")
    assert recalibration.advice(ready, True, 60.0) == (
        "what is being flown determines what changed (the offsets): call ~/start, keep flying it for 60 s, then "
        "call ~/calibrate")
    straight = Assessment(800, True, None, ("offset x", "offset y", "scale z"), "enough to recalibrate ...")
    assert recalibration.advice(straight, True, 60.0).startswith(
        "the sets flown since do not determine offset x, offset y: call ~/start, turn through a full circle")
    assert "no running calibration" in recalibration.advice(straight, False, 60.0)


def test_the_watch_recalibrates_once_per_interval_and_ignores_stale_reports() -> None:
    watch = recalibration.DriftWatch(window_ns=60 * S, interval_ns=600 * S)
    assert watch.due(100 * S) == (False, "")
    assert watch.report(True, "mag1 calibration drifted: ...", 100 * S)
    assert not watch.report(True, "mag1 calibration drifted: again", 110 * S)  # named once
    due, why = watch.due(130 * S)
    assert not due and why == "collecting sets since the drift was named: 30 of 60 s"
    assert watch.due(160 * S)[0] and watch.window_start(170 * S) == 110 * S
    watch.attempted(160 * S, pushed=False)
    assert watch.due(175 * S) == (False, "trying again in 15 s") and not watch.due(189 * S)[0]
    assert watch.due(190 * S)[0]
    twin = replace(watch)  # a failed attempt, then the health says the calibration fits: nothing to refine
    twin.attempted(190 * S, pushed=False)
    twin.report(False, "calibration fits", 195 * S)
    assert not twin.refining and twin.due(2000 * S) == (False, "")
    watch.attempted(190 * S, pushed=True)
    assert watch.since is None and watch.settling
    assert not watch.report(True, "stale: judged on the old calibration", 191 * S) and watch.since is None
    watch.report(False, "collecting: ...", 195 * S)  # the health judges the new calibration afresh
    assert watch.report(True, "drifted again", 300 * S)
    due, why = watch.due(400 * S)
    assert not due and why.startswith("recalibrated 210 s ago, next in 390 s (recalibrate_interval): call ~/calibrate")
    assert watch.due(780 * S)[1].startswith("recalibrated 590 s ago, next in 10 s")
    assert watch.due(790 * S)[0]


def test_a_push_is_refined_once_from_every_set_flown_since_its_drift_was_named() -> None:
    """One window determines what changed only to within its noise: REFINE_WINDOWS windows after the drift was
    named, the sets flown since are fitted once more (within the interval: it is the same drift), once; a drift
    named anew before replaces the refinement; an attempt that did not push leaves nothing to refine."""
    watch = recalibration.DriftWatch(window_ns=60 * S, interval_ns=600 * S)
    assert recalibration.REFINE_WINDOWS == 4
    watch.report(True, "payload/battery varies ...", 100 * S)
    watch.attempted(160 * S, pushed=True)
    assert watch.refining and watch.due(339 * S) == (False, "")
    assert watch.due(340 * S) == (True, "") and watch.window_start(340 * S) == 100 * S
    assert watch.window_start(400 * S) == 160 * S  # at most REFINE_WINDOWS windows back
    watch.report(False, "calibration fits", 345 * S)  # the health judging the push: the refinement stays due
    assert watch.refining and watch.due(350 * S)[0]
    watch.attempted(350 * S, pushed=False)
    assert not watch.refining and not watch.due(2000 * S)[0]  # tried once
    watch.report(True, "mag1 calibration drifted: ...", 2000 * S)
    watch.attempted(2060 * S, pushed=True)
    watch.report(False, "calibration fits", 2070 * S)
    watch.attempted(2240 * S, pushed=True)  # refined and pushed: nothing more to refine
    assert not watch.refining and watch.settling and not watch.due(5000 * S)[0]
    watch.report(False, "calibration fits", 5001 * S)
    watch.report(True, "mag2 calibration drifted: ...", 5010 * S)
    watch.attempted(5070 * S, pushed=True)
    watch.report(False, "calibration fits", 5080 * S)
    assert watch.report(True, "mag3 calibration drifted: ...", 5100 * S)  # anew before the refinement was due
    assert not watch.refining and watch.window_start(5300 * S) == 5240 * S
    watch.attempted(5130 * S, pushed=False)  # an attempt that did not push leaves nothing to refine
    assert not watch.refining
    watch.attempted(5400 * S, pushed=True)  # pushed 300 s after the drift was named: refined on a new window
    assert watch.refining and not watch.due(5459 * S)[0] and watch.due(5460 * S)[0]


def test_a_refinement_is_pushed_whole_unless_a_sensor_is_worse(drifted: tuple) -> None:
    """A push's refinement (every set since the drift, four windows) is better in expectation for every sensor but
    need not show it on its held-out fifth: judged as a refinement, a fit no better than the running calibration
    there is pushed whole (no sensor keeps the push's); one that fits a sensor worse is refused all the same."""
    sim, moved, running, rng = drifted
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    pushed = result.calibration  # the push: the running calibration the refinement is judged against
    judged = recalibration.judge(result, pushed, raw[fit], raw[held])
    assert judged.problem is not None and "no better for any sensor" in judged.problem
    judged = recalibration.judge(result, pushed, raw[fit], raw[held], refine=True)
    assert judged.problem is None and judged.kept == () and judged.result is not None
    np.testing.assert_array_equal(judged.result.calibration.offsets, result.calibration.offsets)
    worse = replace(result, calibration=replace(pushed, offsets=pushed.offsets + np.array([[5.0, 0, 0]] + [[0, 0, 0]] * 3)
                                                * NT))
    judged = recalibration.judge(worse, pushed, raw[fit], raw[held], refine=True)
    assert judged.problem is not None and "worse for mag1" in judged.problem


def test_a_small_real_improvement_shows_on_the_same_sets_and_noise_does_not() -> None:
    """A refinement's gain (a payload's interference 0.15 nT/A better known, a current of 1-3 A: a few tenths of nT
    of TMI on 1 nT of noise) moves the held-out TMI RMS by less than 3 sigma / sqrt(sets), but the noise both
    calibrations see on the same sets cancels in their difference: improved. A refit that moved by noise only
    (and one identical to the running calibration) is not."""
    rng = np.random.default_rng(5)
    n, names = 960, ("mag1", "mag2")
    t = np.arange(n) * 0.05
    current = 2.0 + np.sin(2 * np.pi * t / 20.0)
    noise = rng.normal(0.0, NOISE, (n, 2))
    r_new = noise.copy()
    r_old = noise + np.column_stack([0.15 * NT * current, np.zeros(n)])  # mag1's gain off by 0.15 nT/A, mag2 alike
    refit = noise + rng.normal(0.0, 0.03 * NOISE, (n, 2))  # a refit by noise only

    def judged(old: np.ndarray, new: np.ndarray) -> recalibration.HeldOut:
        rms = lambda r: np.sqrt(np.mean(r**2, axis=0))  # noqa: E731
        return recalibration.HeldOut(n, rms(new), rms(old), rms(new), float("nan"), float("nan"), float("nan"),
                                     np.full(2, NOISE), names, recalibration.paired_error(old, new))

    better = judged(r_old, r_new)
    gain = better.tmi_old - better.tmi_new
    assert gain[0] < better.slack[0]  # within what noise moves one RMS by
    assert list(better.improved()) == [True, False]
    assert better.change_problem(()) is None and better.change_problem(("mag1",)) is None
    assert not judged(noise, refit).improved().any() and not judged(noise, noise).improved().any()
    assert recalibration.paired_error(noise[:19], noise[:19]) is None  # too few sets: the RMS alone decides


def test_a_sensor_the_health_did_not_name_takes_the_new_calibration_only_for_a_gain_that_matters() -> None:
    """On 400 held-out sets the new calibration leaves both sensors' noise 0.7 % smaller (a refit that lines up
    with the noise of the sets it is judged on): far beyond the paired standard error, but what it removes is
    0.12 noise sd. Named by the health, mag1 counts as improved; mag2, not named, keeps its running
    calibration. A systematic error of 0.8 noise sd that the new one removes counts for either."""
    rng = np.random.default_rng(6)
    n, names = 400, ("mag1", "mag2")
    t = np.arange(n) * 0.05
    noise = rng.normal(0.0, NOISE, (n, 2))

    def held(r_old: np.ndarray, r_new: np.ndarray) -> recalibration.HeldOut:
        rms = lambda r: np.sqrt(np.mean(r**2, axis=0))  # noqa: E731
        return recalibration.HeldOut(n, rms(r_new), rms(r_old), rms(r_new), float("nan"), float("nan"),
                                     float("nan"), np.full(2, NOISE), names, recalibration.paired_error(r_old, r_new))

    small = held(noise, noise * (1.0 - 0.0072))
    large = held(noise + 0.8 * NOISE * np.sqrt(2.0) * np.sin(2 * np.pi * t / 7.0)[:, None], noise)
    assert np.all(small.tmi_old - small.tmi_new > 10 * small.paired)  # far beyond the paired test
    assert small.excess == pytest.approx(0.12 * NOISE, rel=0.1)
    assert list(small.improved()) == [True, True]
    assert list(small.improved(("mag1",))) == [True, False]
    assert small.change_problem(("mag1",)) is None
    why = small.change_problem(())  # nothing named: a push must gain what matters somewhere
    assert why is not None and why.startswith("on 400 held-out sets the new calibration is no better for any sensor")
    assert large.excess == pytest.approx(0.8 * NOISE, rel=0.2)
    assert list(large.improved(("mag1",))) == [True, True]


def test_the_paired_standard_error_is_the_spread_of_the_rms_difference_per_sensor() -> None:
    """Against repetition: 600 windows of 400 held-out sets, two sensors of 1 and 4 nT noise whose running
    calibrations leave 0.5 and 3 nT of error (the same in every stretch of the 20: where it varies between them,
    the error is larger, on the safe side). Each sensor's paired standard error (mean over the
    windows) is the spread of its ``rms(old) - rms(new)`` over them, to 15 %; and it needs 40 sets."""
    rng = np.random.default_rng(8)
    n, reps = 400, 600
    t = np.arange(n) * 0.05
    scale = np.array([1.0, 4.0]) * NOISE
    systematic = np.sin(2 * np.pi * t / 0.5)[:, None] * np.array([0.5, 3.0]) * NOISE * np.sqrt(2.0)
    gains, errors = [], []
    rms = lambda r: np.sqrt(np.mean(r**2, axis=0))  # noqa: E731
    for _ in range(reps):
        r_new = rng.normal(0.0, 1.0, (n, 2)) * scale
        r_old = r_new + systematic
        gains.append(rms(r_old) - rms(r_new))
        errors.append(recalibration.paired_error(r_old, r_new))
    spread, predicted = np.std(gains, axis=0, ddof=1), np.mean(errors, axis=0)
    np.testing.assert_allclose(predicted, spread, rtol=0.15)
    noise = rng.normal(0.0, NOISE, (40, 2))
    assert recalibration.paired_error(noise, noise * 0.99) is not None
    assert recalibration.paired_error(noise[:39], noise[:39] * 0.99) is None


def test_with_too_few_held_out_sets_for_the_paired_test_each_rms_alone_decides() -> None:
    """30 held-out sets (no paired standard error): a sensor improved by more than 3 sigma / sqrt(30) is
    better, one improved by less is not, whether named or not (0.8 noise sd removed matters)."""
    names = ("mag1", "mag2")
    slack = 3 * NOISE / np.sqrt(30)
    held = recalibration.HeldOut(30, np.full(2, NOISE), NOISE + np.array([1.2, 0.8]) * slack, np.full(2, NOISE),
                                 float("nan"), float("nan"), float("nan"), np.full(2, NOISE), names, None)
    assert list(held.improved()) == [True, False]
    assert list(held.improved(("mag2",))) == [True, False]


def _with_payload(seed: int) -> tuple[ArraySimulation, ArrayCalibration, np.ndarray, np.ndarray]:
    """An array, its true calibration with a payload channel (interference 5-20 nT/A per axis), and 500 sets
    of random attitudes with the payload's current (0-3 A) in the raw readings."""
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(INTENSITY, 60.0, 5.0),
                          noise=NOISE)
    gains = rng.uniform(5.0, 20.0, (4, 3, 1)) * rng.choice([-1.0, 1.0], (4, 3, 1)) * NT
    truth = replace(sim.true_calibration(), channels=("payload",), interference=gains,
                    metadata={"intensity": INTENSITY})
    rec, _ = sim.run(uniform_random(500, rng), rng)
    currents = rng.uniform(0.0, 3.0, (500, 1))
    raw = rec.vectors + np.einsum("sij,sjc,nc->nsi", np.linalg.inv(truth.matrices), gains, currents)
    return sim, truth, raw, currents


def test_the_held_out_check_applies_each_calibrations_own_interference_and_the_paired_test() -> None:
    """Both calibrations subtract the payload's interference on the held-out sets (the running one too: without
    it every sensor would look improved by tens of nT). The running one has mag1's offset 0.8 nT off (0.46 nT
    of TMI): the held-out RMS moves by less than 3 sigma / sqrt(sets), the paired difference shows it; the
    other sensors are the same calibration, to the bit."""
    from types import SimpleNamespace

    sim, truth, raw, currents = _with_payload(9)
    offsets = truth.offsets.copy()
    offsets[0] += 0.8 * NT * np.array([1.0, -1.0, 1.0]) / np.sqrt(3.0)
    running = replace(truth, offsets=offsets)
    result = SimpleNamespace(calibration=truth, intensity=INTENSITY, noise=np.full(4, NOISE))
    check = recalibration.held_out(result, running, raw[:100], raw[100:], currents[:100], currents[100:])
    assert check.sets == 400 and np.all(check.tmi_new < 1.1 * NOISE)
    np.testing.assert_array_equal(check.tmi_old[1:], check.tmi_new[1:])
    assert 0 < check.tmi_old[0] - check.tmi_new[0] < check.slack[0]
    assert list(check.improved(("mag1",))) == [True, False, False, False]


def test_a_sensor_kept_as_running_keeps_its_interference_and_only_a_calibration_of_the_same_form_lends_it() -> None:
    """mag2 kept: its matrix, offset and interference gains are the running calibration's, the other sensors'
    the new one's. A running calibration of another form lends nothing (the new one is pushed whole): other
    channels, temperature terms, other time offsets, another output frame."""
    _, truth, _, _ = _with_payload(10)
    rng = np.random.default_rng(11)
    new = replace(truth, offsets=truth.offsets + rng.normal(0.0, 5.0, (4, 3)) * NT,
                  interference=truth.interference + rng.normal(0.0, 1.0, (4, 3, 1)) * NT)
    kept = recalibration.keep_running(new, truth, ["mag2"])
    np.testing.assert_array_equal(kept.offsets[1], truth.offsets[1])
    np.testing.assert_array_equal(kept.interference[1], truth.interference[1])
    np.testing.assert_array_equal(kept.matrices[1], truth.matrices[1])
    np.testing.assert_array_equal(kept.offsets[[0, 2, 3]], new.offsets[[0, 2, 3]])
    np.testing.assert_array_equal(kept.interference[[0, 2, 3]], new.interference[[0, 2, 3]])
    assert recalibration.keep_running(new, truth, []) is new
    tempco = replace(truth, temperature_reference=20.0, offset_tempco=np.full((4, 3), 0.1 * NT))
    turned = replace(truth, output_rotation=np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    others = [replace(truth, channels=("thruster",)), tempco, replace(truth, time_offsets=np.full(4, 1e-3)), turned]
    for running in others:
        assert not recalibration.same_form(new, running) and recalibration.keep_running(new, running, ["mag2"]) is new
    assert not recalibration.same_form(tempco, truth)
    assert recalibration.same_form(new, truth)


def test_what_a_calibration_must_hold_on_the_held_out_sets_against_what_it_left_on_its_own() -> None:
    """On 400 held-out sets (slack 3 sigma / 20 = 0.15 nT): each sensor's TMI residual within 1.5x what it
    left on the sets fitted plus the slack (the first sensor beyond it named), the sensors' disagreement
    beyond the gradient within 1.5x the fit's and within 3x what their noise leaves, each plus the slack."""
    names = ("mag1", "mag2", "mag3")
    slack = 3 * NOISE / 20

    def held(tmi_new: list[float], disagreement: float = 1.0, fit: float = 1.0, noise: float = 0.6) -> recalibration.HeldOut:
        return recalibration.HeldOut(400, np.array(tmi_new) * NOISE, np.full(3, 2 * NOISE), np.full(3, NOISE),
                                     disagreement * NOISE, fit * NOISE, noise * NOISE, np.full(3, NOISE), names)

    assert held([1.5 + 0.5 * slack / NOISE] * 3).problem() is None
    why = held([1.0, 1.5 + 2 * slack / NOISE, 3.0]).problem()
    assert why is not None and why.startswith("on 400 held-out sets mag2's TMI residual is 1.8 nT, more than 1.5x "
                                              "the 1 nT on the sets fitted"), why
    assert held([1.0] * 3, disagreement=1.5 + 0.5 * slack / NOISE).problem() is None
    why = held([1.0] * 3, disagreement=1.5 + 2 * slack / NOISE).problem()
    assert why is not None and "disagree by 1.8 nT beyond the gradient, more than 1.5x the 1 nT on the sets" in why
    assert held([1.0] * 3, disagreement=1.8 + 0.5 * slack / NOISE, fit=2.0).problem() is None
    why = held([1.0] * 3, disagreement=1.8 + 2 * slack / NOISE, fit=2.0).problem()
    assert why is not None and why.endswith("more than 3x the 0.6 nT their noise leaves (a sensor turned against "
                                            "the others)"), why


def test_what_a_recalibration_changed_is_said_in_nt_ppm_and_degrees() -> None:
    """mag2's corrected field at zero reading moved by 500 nT, mag4's matrix by 40 ppm, the output frame
    (from the running one, itself turned 10 deg about z) by 2.5 deg about x: said as such."""
    _, truth, _, _ = _with_payload(12)

    def about(axis: int, deg: float) -> np.ndarray:
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        i, j = [k for k in range(3) if k != axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        return r

    old = replace(truth, output_rotation=about(2, 10.0))
    offsets, matrices = truth.offsets.copy(), truth.matrices.copy()
    offsets[1] += np.linalg.solve(truth.matrices[1], np.array([300.0, 0.0, 400.0]) * NT)
    matrices[3] = (np.eye(3) + np.diag([40e-6, -20e-6, 0.0])) @ truth.matrices[3]
    new = replace(truth, offsets=offsets, matrices=matrices, output_rotation=about(0, 2.5) @ about(2, 10.0))
    assert recalibration.changes(old, new) == ("offsets moved: mag1 0 nT, mag2 500 nT, mag3 0 nT, mag4 0 nT; "
                                               "matrices changed by at most 40 ppm; output frame turned by 2.500 deg")
    assert recalibration.changes(old, replace(new, output_rotation=old.output_rotation)).endswith("at most 40 ppm")


def test_the_mission_window_keeps_the_latest_seconds_evenly() -> None:
    window = MissionWindow(seconds_ns=10 * S, spacing_ns=S // 20, sensors=2, channels=1)
    for k in range(3000):  # 30 s at 100 Hz
        t = 1000 * S + k * (S // 100)
        if window.due(t):
            window.add(t, ((1e-5, 0.0, 0.0), (0.0, 1e-5, 0.0)), (float(k),))
    stamps, raw, currents, temperatures, imu = window.snapshot()
    assert imu is None  # no IMU
    assert temperatures is None  # none heard
    assert window.newest == 1000 * S + 2999 * (S // 100)
    assert len(stamps) == 201 and np.all(np.diff(stamps) == S // 20)  # 10 s at 20 Hz
    assert raw.shape == (201, 2, 3) and currents.shape == (201, 1) and currents[-1, 0] == 2995.0
    assert len(window.snapshot(stamps[-1] - 2 * S)[0]) == 41
    window.add(5 * S, ((1e-5, 0.0, 0.0), (0.0, 1e-5, 0.0)), (0.0,))  # the source restarted
    assert len(window) == 1


def test_the_recalibration_status_says_what_is_done_within_128_characters() -> None:
    """Who drifted and what is done or to do, at most 128 characters (what ``ros2 topic echo`` shows) with the
    action at the end; the long texts (the health's message, the advice, the last attempt) in the values."""
    record = {"recalibrations": "0", "attempts": "0", "last_recalibration": "", "last_attempt": ""}
    watch = recalibration.DriftWatch(window_ns=60 * S, interval_ns=600 * S)
    warn, text, values = recalibration.status("/magcal_correction", False, watch, 10 * S, "calibration fits: ...", "",
                                              record)
    assert not warn and text == "calibration of /magcal_correction fits" and values["drifted"] == "false"
    health = "mag2 calibration drifted: TMI residual 40 nT, against 1 nT noise: recalibrate"
    watch.report(True, health, 20 * S, ("mag2",))
    warn, text, values = recalibration.status("/magcal_correction", False, watch, 30 * S, "", "call ~/start, ...",
                                              record)
    assert warn and text == "calibration of /magcal_correction drifted (mag2); to fix it: call ~/start, ..."
    assert values["advice"] == "call ~/start, ..." and values["since_drift_s"] == "10" and values["health"] == health
    assert values["newest_stamp"] == "30.000000000"  # the newest set seen: how far into the mission the node is
    advice = ("the sets flown since do not determine offset x, offset y: call ~/start, turn through a full circle of "
              "heading with some pitch and roll, then call ~/calibrate")
    warn, text, values = recalibration.status("/magcal_correction", False, watch, 30 * S, "", advice, record)
    assert text == ("calibration of /magcal_correction drifted (mag2); to fix it: fly what advice says, call ~/start, "
                    "then ~/calibrate") and values["advice"] == advice
    last = ("not recalibrated: on 196 held-out sets drifted mag2 is not better (TMI residual 40 nT against 41 nT "
            "running)")
    warn, text, values = recalibration.status("/magcal_correction", True, watch, 30 * S, "", "",
                                              {**record, "last_attempt": last})
    assert warn and text == ("calibration of /magcal_correction drifted (mag2); auto_recalibrate: collecting sets "
                             "since the drift was named: 10 of 60 s")  # the last attempt: in the values
    assert values["last_attempt"] == last
    watch.report(True, health, 25 * S, ("mag1", "mag3", "mag4"))
    long_name = "/vehicle_with_a_long_namespace/survey_array_port/magcal_correction"
    for now in (30 * S, 70 * S, 500 * S):
        if now == 500 * S:
            watch.attempted(400 * S, pushed=True)
            watch.report(False, "collecting", 401 * S)
            watch.report(True, health, 450 * S, ("mag2",))
        warn, text, _ = recalibration.status(long_name, True, watch, now, "", "", {**record, "last_attempt": last})
        assert warn and len(text) <= 128 and text.endswith(("of 60 s", "recalibrating", "to fix it now")), text
    text = recalibration.status(long_name, False, watch, 500 * S, "", advice, record)[1]
    assert len(text) <= 128 and text.endswith("; to fix it: fly what advice says, call ~/start, then ~/calibrate")
    pushed = {**record, "recalibrations": "1", "last_recalibration": "recalibrated ... " + "x" * 300}
    text = recalibration.status(long_name, True, recalibration.DriftWatch(60 * S, 600 * S), 10 * S, "calibration fits",
                                "", pushed)[1]
    assert text == f"calibration of {long_name} fits; recalibrated during the mission: 1"


def test_a_sensor_turned_against_the_others_is_refused_though_its_tmi_fits(drifted: tuple) -> None:
    """The right recalibration with mag2 turned by 0.5 deg (about the vehicle's z): every |B| is as good
    (a rotation keeps intensity) and the sensors disagree as much on the fitted sets as on the held-out
    ones, but far beyond what their noise leaves after field and gradient: refused, saying so."""
    from scipy.spatial.transform import Rotation

    _, moved, running, rng = drifted
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    assert recalibration.judge(result, running, raw[fit], raw[held]).problem is None
    turn = Rotation.from_euler("z", 0.5, degrees=True).as_matrix()
    cal = result.calibration
    matrices = cal.matrices.copy()
    matrices[1] = turn @ matrices[1]
    turned = replace(result, calibration=replace(cal, matrices=matrices))
    judged = recalibration.judge(turned, running, raw[fit], raw[held])
    why, figures = judged.problem, judged.figures
    assert figures is not None and np.all(figures.tmi_new < 1.2 * NOISE)  # the TMI cannot tell
    assert why is not None and "a sensor turned against the others" in why, why
    # what white noise leaves beyond field and gradient: sigma sqrt(4 / 12) for a cross of four
    assert figures.disagreement_noise == pytest.approx(NOISE * np.sqrt(4 / 12), rel=0.2)


def _one_moved(seed: int, index: int) -> tuple[ArraySimulation, ArraySimulation, ArrayCalibration, np.random.Generator]:
    """An array whose sensor ``index`` alone jumps by 500 nT along a random axis (a payload beside it), and the
    true calibration from before as the running one."""
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(INTENSITY, 60.0, 5.0),
                          noise=NOISE)
    running = replace(sim.true_calibration(), metadata={"intensity": INTENSITY})
    sensors = list(sim.sensors)
    axis = rng.normal(size=3)
    jump = 500 * NT * axis / np.linalg.norm(axis)
    sensors[index] = replace(sensors[index], hard_iron=sensors[index].hard_iron + jump)
    return sim, replace(sim, sensors=tuple(sensors)), running, rng


@pytest.mark.parametrize("seed, index", [(40, 0), (41, 1), (42, 2), (43, 3), (44, 0), (45, 1), (46, 2), (47, 3)])
def test_one_sensors_jump_is_fixed_on_the_first_window_and_the_others_keep_their_calibration(seed: int,
                                                                                               index: int) -> None:
    """A minute of turns after one sensor jumped, the health naming it: the first window is pushed. The
    sensors that never moved fit no better than before (a coin toss against the running calibration): they
    are judged by not getting worse beyond what noise leaves on the held-out sets and keep their running
    calibration exactly; the moved one is at its noise on held-out sets and the tensor at the floor
    sqrt(2) sigma / d on fresh attitudes."""
    sim, moved, running, rng = _one_moved(seed, index)
    names = sim.geometry.names
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    judged = recalibration.judge(result, running, raw[fit], raw[held], drifted=(names[index],))
    assert judged.problem is None, judged.problem
    assert judged.kept == tuple(n for n in names if n != names[index])
    assert judged.result is not None and judged.figures is not None
    pushed = judged.result.calibration
    others = [i for i in range(4) if i != index]
    np.testing.assert_array_equal(pushed.offsets[others], running.offsets[others])
    np.testing.assert_array_equal(pushed.matrices[others], running.matrices[others])
    assert judged.figures.tmi_new[index] < 1.2 * NOISE < 50 * NOISE < judged.figures.tmi_old[index]
    fresh, _ = moved.run(uniform_random(1000, rng), rng)
    assert tensor_rms(pushed.field_and_gradient(fresh.vectors)[2]) < 1.2 * tensor_floor(NOISE, 0.4)


@pytest.mark.parametrize("ppm, taken", [(3.0, False), (12.0, True)])
def test_a_sensor_the_health_did_not_name_keeps_its_calibration_for_a_gain_below_a_quarter_of_its_noise(
        ppm: float, taken: bool) -> None:
    """mag1 jumped and is named; mag3's running matrix is ``ppm`` off in scale (3 ppm: 0.15 nT of TMI, 0.16 noise
    sd removed by the new calibration; 12 ppm: 0.6 nT). On 4,000 held-out sets both are beyond three paired
    standard errors, but only the second matters: mag3 keeps its running calibration for 3 ppm, takes the new
    one for 12."""
    _, moved, running, rng = _one_moved(63, 0)
    stamps, raw = _window(moved, [Leg(200.0, 6.0)], rng, sets=20000)
    result, fit, held = _solve(stamps, raw, running)
    matrices = running.matrices.copy()
    matrices[2] = matrices[2] * (1 + ppm * 1e-6)
    stale = replace(running, matrices=matrices)
    new = result.calibration
    new_m, new_o = new.matrices.copy(), new.offsets.copy()
    new_m[2], new_o[2] = running.matrices[2], running.offsets[2]  # the new calibration right for mag3
    result = replace(result, calibration=replace(new, matrices=new_m, offsets=new_o))
    check = recalibration.held_out(result, stale, raw[fit], raw[held])
    assert check.sets == 4000 and check.tmi_old[2] - check.tmi_new[2] > 3 * check.paired[2]
    assert (check.excess[2] > 0.25 * check.noise[2]) == taken
    judged = recalibration.judge(result, stale, raw[fit], raw[held], drifted=("mag1",))
    assert judged.problem is None and judged.result is not None, judged.problem
    assert ("mag3" in judged.kept) != taken, judged.kept
    expected = running if taken else stale
    np.testing.assert_array_equal(judged.result.calibration.matrices[2], expected.matrices[2])


def test_the_judgement_per_sensor_refuses_what_misses_the_named_sensor_or_spoils_another() -> None:
    """mag1 moved. Named mag2 instead: mag2 does not improve, refused. A result that also moves mag3 by 5 nT
    (an error 30 times what noise leaves on 400 held-out sets) is refused naming mag3; by 0.02 nT (within the
    noise allowance) it passes and mag3 keeps its running calibration."""
    sim, moved, running, rng = _one_moved(48, 0)
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    why = recalibration.judge(result, running, raw[fit], raw[held], drifted=("mag2",)).problem
    assert why is not None and why.startswith("on 400 held-out sets drifted mag2 is not better (TMI residual "), why
    for shift, refused in ((5.0, True), (0.02, False)):
        cal = result.calibration
        offsets = cal.offsets.copy()
        offsets[2] += shift * NT
        spoiled = replace(result, calibration=replace(cal, offsets=offsets))
        judged = recalibration.judge(spoiled, running, raw[fit], raw[held], drifted=("mag1",))
        if refused:
            assert judged.problem is not None and judged.result is None
            assert judged.problem.startswith("on 400 held-out sets the new calibration is worse for mag3"), \
                judged.problem
        else:
            assert judged.problem is None and "mag3" in judged.kept
            np.testing.assert_array_equal(judged.result.calibration.offsets[2], running.offsets[2])


def test_the_watch_keeps_every_sensor_named_until_the_drift_is_fixed() -> None:
    watch = recalibration.DriftWatch(window_ns=60 * S, interval_ns=600 * S)
    assert watch.report(True, "mag1 calibration drifted: ...", 100 * S, ("mag1",))
    watch.report(True, "several sensors calibration drifted: ...", 110 * S, ())
    assert watch.sensors == ("mag1",)  # a report naming none keeps those named before
    watch.report(True, "mag1, mag3 calibration drifted: ...", 120 * S, ("mag1", "mag3"))
    assert watch.sensors == ("mag1", "mag3")
    _, _, values = recalibration.status("/c", True, watch, 130 * S, "", "", {})
    assert values["drifted_sensors"] == "mag1,mag3"
    watch.attempted(160 * S, pushed=True)
    assert watch.sensors == ()
    watch.report(False, "collecting", 170 * S)
    assert watch.report(True, "mag2 calibration drifted: ...", 200 * S, ("mag2",)) and watch.sensors == ("mag2",)
    watch.report(False, "calibration fits", 210 * S)
    assert watch.sensors == ()


def test_a_calibration_keeping_sensors_as_they_run_is_saved_and_read_back(tmp_path: Path) -> None:
    """The running calibration as the correction node holds it (no covariance known) and a fit with one: the
    sensors kept take the running matrix and offset, and the covariance the fit gives them (a file gives one
    for every sensor or none); the file reads back the same. Over DDS the mixed one could not be written."""
    from magcal_ros.io import calibration_file as calfile

    sim, moved, running, rng = _one_moved(49, 3)
    running = replace(running, covariances=None)
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    assert result.calibration.covariances is not None and np.all(np.isfinite(result.calibration.covariances))
    judged = recalibration.judge(result, running, raw[fit], raw[held], drifted=("mag4",))
    assert judged.problem is None and judged.kept == ("mag1", "mag2", "mag3")
    pushed = judged.result.calibration
    np.testing.assert_array_equal(pushed.covariances, result.calibration.covariances)
    np.testing.assert_array_equal(pushed.offsets[:3], running.offsets[:3])
    path = tmp_path / "calibration.yaml"
    calfile.write(path, pushed)
    back = calfile.read(path)
    np.testing.assert_array_equal(back.offsets, pushed.offsets)
    np.testing.assert_allclose(back.covariances, pushed.covariances, rtol=1e-12)
    known = replace(running, covariances=np.stack([np.eye(3) * (2e-9) ** 2] * 4))
    merged = recalibration.keep_running(result.calibration, known, ("mag1",))
    np.testing.assert_array_equal(merged.covariances[0], known.covariances[0])
    np.testing.assert_array_equal(merged.covariances[1:], result.calibration.covariances[1:])


def test_a_hull_change_common_to_every_sensor_is_recalibrated_against_the_reference_intensity() -> None:
    """+500 nT on every sensor's x axis at once: the tensor cannot see it (every sensor alike), the vectors are
    500 nT off. A minute of turns, fitted with the reference intensity and all four named: pushed on the first
    window, every sensor changed, the corrected vectors within 1.5 sigma RMS of the true field on fresh attitudes
    (before: about 500 nT)."""
    rng = np.random.default_rng(50)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(INTENSITY, 60.0, 5.0),
                          noise=NOISE)
    running = replace(sim.true_calibration(), metadata={"intensity": INTENSITY})
    moved = replace(sim, sensors=tuple(replace(s, hard_iron=s.hard_iron + np.array([500.0, 0.0, 0.0]) * NT)
                                       for s in sim.sensors))
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    fit, held = recalibration.split(stamps)
    result = calibrate_array(raw[fit], geo, INTENSITY, "ml", None, running, None, (), stamps[fit])
    judged = recalibration.judge(result, running, raw[fit], raw[held], drifted=geo.names)
    assert judged.problem is None and judged.kept == (), judged.problem
    fresh, truth = moved.run(uniform_random(1000, rng), rng)
    error = lambda cal: np.sqrt(np.mean((cal.apply(fresh.vectors) - truth.field) ** 2))  # noqa: E731
    assert error(judged.result.calibration) < 1.5 * NOISE and error(running) > 200 * NOISE


def _payload_leg(seed: int, steps: bool, wobble: float = 0.3) -> tuple:
    """An array whose payload (20-90 nT/A at the sensors) was off during the calibration manoeuvre (the running
    calibration knows no interference), then a straight leg (+-0.3 deg of wobble) with the payload at 1 <-> 3 A
    (every 4 s, or ``steps`` False: smoothly over 30 s); the sets at 20/s, their seconds and currents."""
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross()
    payload = Thruster("payload/battery", np.array([0.0, 0.0, 0.45]), np.array([0.03, -0.02, 0.05]))
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                          earth_field(INTENSITY, 60.0, 5.0), noise=NOISE, thrusters=(payload,))
    truth = sim.true_calibration()
    running = replace(truth, channels=(), interference=None, metadata={"intensity": INTENSITY})
    rate = 20.0
    attitudes = mission_attitudes([Leg(60.0, 0.0)], rate, wobble, rng)
    t = np.arange(len(attitudes)) / rate
    current = np.where((t // 4) % 2 == 0, 1.0, 3.0) if steps else 2.0 + np.sin(2 * np.pi * t / 30.0)
    rec, _ = sim.run(attitudes, rng, rate=rate, currents=current[:, None])
    return sim, truth, running, (t * NS_PER_S).astype(np.int64), rec.vectors, current[:, None], rng


@pytest.mark.parametrize("seed", [3, 4])
def test_a_payload_switched_on_during_a_straight_leg_is_learnt_from_its_steps(seed: int) -> None:
    """The straight leg determines no offset across the track, so the whole fit is not pushed; the payload's
    steps determine its interference: the running calibration with those gains is pushed (matrices and offsets
    kept exactly), the gains within 1 nT/A of the truth, and fresh sets with the payload on at the floor (the
    running calibration: tens of times it)."""
    sim, truth, running, stamps, raw, currents, rng = _payload_leg(seed, steps=True)
    fit, held = recalibration.split(stamps)
    result = calibrate_array(raw[fit], running.geometry, None, "ml", None, running, currents[fit],
                             ("payload/battery",), stamps[fit])
    assert recalibration.undetermined_offsets(result)  # the whole fit may not be pushed
    judged = recalibration.judge(result, running, raw[fit], raw[held], currents[fit], currents[held],
                                 ("mag1", "mag2", "mag3", "mag4"), seconds_fit=stamps[fit] / 1e9)
    assert judged.problem is None and judged.result is not None, judged.problem
    assert "interference of payload/battery learnt from the currents' steps" in judged.scope
    pushed = judged.result.calibration
    assert np.array_equal(pushed.matrices, running.matrices) and np.array_equal(pushed.offsets, running.offsets)
    assert pushed.channels == ("payload/battery",)
    assert np.max(np.abs(pushed.interference - truth.interference)) < 1.0 * NT
    fresh_attitudes = uniform_random(1000, rng)
    on = rng.uniform(0.5, 3.5, (1000, 1))
    fresh, _ = sim.run(fresh_attitudes, rng, currents=on)
    floor = tensor_floor(NOISE, 0.4)
    assert tensor_rms(pushed.field_and_gradient(fresh.vectors, currents=on)[2]) < 1.2 * floor
    assert tensor_rms(running.field_and_gradient(fresh.vectors)[2]) > 10 * floor


def test_a_channel_the_steps_do_not_determine_keeps_the_running_gains_or_none() -> None:
    """The payload steps on the leg, a thruster's current stays put: the payload's gains are learnt, the
    thruster's are the running calibration's to the bit (a channel it does not know gets none)."""
    _, truth, running, stamps, raw, currents, rng = _payload_leg(3, steps=True)
    thruster = rng.normal(0.0, 30.0, (4, 3, 1)) * NT
    known = replace(running, channels=("thruster",), interference=thruster)
    both = np.column_stack([currents, np.full(len(currents), 2.0)])  # the thruster at a steady 2 A, no effect
    channels = ("payload/battery", "thruster")
    for prior, expected in ((known, thruster[:, :, 0]), (running, np.zeros((4, 3)))):
        out = recalibration.interference_only(prior, raw, both, channels, stamps / 1e9)
        assert out is not None
        learnt, gains = out[1], out[0].interference
        assert learnt == ("payload/battery",) and out[0].channels == channels
        np.testing.assert_array_equal(gains[:, :, 1], expected)
        assert np.max(np.abs(gains[:, :, 0] - truth.interference[:, :, 0])) < 1.0 * NT
    assert recalibration.interference_only(running, raw, both[:, 1:], ("thruster",), stamps / 1e9) is None


def test_a_window_whose_current_steps_do_not_fix_what_the_health_named_is_refused_saying_so() -> None:
    """On the payload's straight leg mag1's hard iron also moved by 200 nT and the health names mag1: the
    window determines the payload's gains, not mag1's offsets across the track, and the running calibration
    with those gains does not fix mag1 (it disagrees with the others by tens of nT beyond the gradient): refused,
    saying what was tried."""
    sim, truth, running, stamps, raw, currents, rng = _payload_leg(4, steps=True)
    raw = raw.copy()
    raw[:, 0] += np.array([120.0, -100.0, 120.0]) * NT
    fit, held = recalibration.split(stamps)
    result = calibrate_array(raw[fit], running.geometry, None, "ml", None, running, currents[fit],
                             ("payload/battery",), stamps[fit])
    judged = recalibration.judge(result, running, raw[fit], raw[held], currents[fit], currents[held], ("mag1",),
                                 seconds_fit=stamps[fit] / 1e9)
    assert judged.result is None and judged.problem is not None
    assert judged.problem.startswith("the sets do not determine what changed ("), judged.problem
    assert "; with only the interference of payload/battery from the currents' steps: on " in judged.problem
    assert judged.problem.endswith("(a sensor turned against the others)")  # mag1 still 200 nT off


def test_a_current_that_only_varies_smoothly_on_a_straight_leg_is_not_learnt() -> None:
    """The same leg with the payload's current varying smoothly (a 30 s sine): the field's own smooth change
    cannot be told from it, so nothing is learnt and the verdict still asks for turns."""
    _, _, running, stamps, raw, currents, _ = _payload_leg(3, steps=False)
    fit, held = recalibration.split(stamps)
    result = calibrate_array(raw[fit], running.geometry, None, "ml", None, running, currents[fit],
                             ("payload/battery",), stamps[fit])
    judged = recalibration.judge(result, running, raw[fit], raw[held], currents[fit], currents[held],
                                 seconds_fit=stamps[fit] / 1e9)
    assert judged.result is None and judged.problem.startswith("the sets do not determine what changed")


def test_a_calibration_with_temperature_terms_is_recalibrated_from_the_mission_window() -> None:
    """The running calibration has temperature terms (true tempcos, 0.5 nT/K and 20 ppm/K), the hull's iron
    moves, and a minute of turns is flown while the water cools from 12 to 8 C. The mission window keeps each
    set's temperatures as the calibration node does; the fit and the held-out check use them (without them
    the check cannot apply a calibration with temperature terms: no recalibration was ever pushed), and the
    prior's matrices and offsets are taken at the window's reference temperature (at the file's, 10 K away, the
    fit came out at 5.6x the floor). Fresh tumbling sets at 10 C, within the temperatures flown: the tensor
    within 1.2x the floor. (Its terms per kelvin, moved by a window that spans 4 K in one turn, extrapolate
    less well: 2.4x at 4 C.)"""
    rng = np.random.default_rng(8)
    geo = ArrayGeometry.cross()
    offset_tc, gain_tc = draw_tempcos(rng, geo.size, 0.5 * NT, 20e-6)
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(INTENSITY, 60.0, 5.0),
                          noise=NOISE, offset_tempco=offset_tc, gain_tempco=gain_tc)
    running = replace(sim.true_calibration(), metadata={"intensity": INTENSITY})
    assert running.has_temperature_terms
    moved = hard_iron_moved(sim, rng)
    attitudes = mission_attitudes([Leg(60.0, 6.0)], 20.0, 5.0, rng)
    temps = np.linspace(12.0, 8.0, len(attitudes))[:, None] + rng.normal(0.0, 0.05, (len(attitudes), geo.size))
    rec, _ = moved.run(attitudes, rng, rate=20.0, start=1000.0, temperatures=temps)
    window = MissionWindow(seconds_ns=120 * S, spacing_ns=0, sensors=geo.size)
    for k in range(len(rec)):
        window.add(int(rec.stamps[k]), tuple(map(tuple, rec.vectors[k])), (), tuple(temps[k]))
    sets = window.snapshot()
    assert sets.temperatures is not None and np.array_equal(sets.temperatures, temps)
    fit, held = recalibration.split(sets.stamps)
    part = sets.take(fit)
    result = calibrate_array(part.raw, geo, None, "ml", None, running, None, (), part.stamps, part.temperatures)
    judged = recalibration.judge(result, running, sets.raw[fit], sets.raw[held], drifted=geo.names,
                                 temperatures=(sets.temperatures[fit], sets.temperatures[held]))
    assert judged.problem is None and judged.result is not None, judged.problem
    cold = np.full((1000, geo.size), 10.0)
    fresh, _ = moved.run(uniform_random(1000, rng), rng, temperatures=cold)
    floor = tensor_floor(NOISE, 0.4)
    pushed = judged.result.calibration
    assert tensor_rms(pushed.field_and_gradient(fresh.vectors, temperatures=cold)[2]) < 1.2 * floor
    assert tensor_rms(running.field_and_gradient(fresh.vectors, temperatures=cold)[2]) > 100 * floor


def test_a_recalibration_during_the_mission_keeps_the_running_time_offsets(drifted: tuple) -> None:
    """A window whose fit found a lag for one sensor (here put in by hand, 0.2 ms: what a calibration node's own
    placement of a restarted driver gave in a soak) pushes the running time offsets, and says so: each node places
    a restarted driver by its own arrivals, and the correction node's placement was right."""
    sim, moved, running, rng = drifted
    stamps, raw = _window(moved, [Leg(60.0, 6.0)], rng)
    result, fit, held = _solve(stamps, raw, running)
    lagged = replace(result, calibration=replace(result.calibration, time_offsets=np.array([0.0, 0.0, 2e-4, 0.0])))
    judged = recalibration.judge(lagged, running, raw[fit], raw[held], drifted=sim.geometry.names)
    placed = replace(running, time_offsets=np.array([0.0, 1e-4, 0.0, 3e-4]))  # a running calibration's own
    np.testing.assert_array_equal(recalibration.with_running_timing(lagged, placed).calibration.time_offsets,
                                  placed.time_offsets)
    assert judged.problem is None, judged.problem
    np.testing.assert_array_equal(judged.result.calibration.time_offsets, running.time_offsets)
    assert recalibration.timing_note(lagged.calibration, judged.result.calibration) == \
        " (time offsets kept as running; the window's: mag3 0.20 ms)"
    assert recalibration.timing_note(running, judged.result.calibration) == ""

"""Long recordings: the expensive stages run on a subset, one pass over every set refines it.

Truth here is the full solve on the same data (every set in every stage): the reduced solve
must give the same calibration within the full solve's stated 1-sigma, state the same
uncertainty, and keep the manoeuvre's validity envelope. The subset itself must keep rare
attitudes and the whole time span.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.set_reduction import RUN_LENGTH, choose_sets, direction_proxy, solve_budget
from magcal_ros.core.units import NT
from magcal_ros.methods.pipeline import SolveOptions, calibrate_array
from magcal_ros.sim.attitudes import sea_manoeuvre, tumble
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

F = 50_000 * NT


def _array(seed: int) -> ArraySimulation:
    rng = np.random.default_rng(seed)
    sensors = tuple(random_sensor_errors(rng, hard_iron_sd=100 * NT, soft_iron_sd=0.01) for _ in range(4))
    return ArraySimulation(ArrayGeometry.cross(), sensors, earth_field(F, 60.0, -5.0), noise=1 * NT)


def _quantities(result) -> dict[tuple[str, str], tuple[float, float]]:
    return {(q.sensor, q.name): (q.value, q.sigma) for q in result.identifiability.quantities
            if q.status not in ("held",) and q.sigma > 0}


@pytest.fixture(scope="module")
def tumbling() -> tuple:
    sim = _array(11)
    rec, _ = sim.run(tumble(6000, 2.0, 5), rng=6, rate=50.0, continuous=True)
    full = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps, options=SolveOptions(max_solve_sets=0))
    reduced = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps,
                              options=SolveOptions(max_solve_sets=1500))
    return full, reduced


def test_the_reduced_solve_gives_the_full_solves_calibration_within_its_one_sigma(tumbling) -> None:
    full, reduced = tumbling
    a, b = _quantities(full), _quantities(reduced)
    assert a.keys() == b.keys() and len(a) >= 40
    z = np.array([(b[k][0] - a[k][0]) / a[k][1] for k in a])
    assert np.max(np.abs(z)) < 1.0, sorted(zip(np.abs(z), a))[-3:]
    assert np.sqrt(np.mean(z**2)) < 0.35  # far closer than the subset alone (about 1.7 sigma RMS)
    # the same stated uncertainty: the information of every set, not the subset's
    ratio = np.array([b[k][1] / a[k][1] for k in a])
    assert np.all((ratio > 0.7) & (ratio < 1.4)), (ratio.min(), ratio.max())
    assert np.median(ratio) == pytest.approx(1.0, abs=0.15)
    assert "solved on" in reduced.summary() and "of 6000 sets" in reduced.summary()
    assert "refined on all" in reduced.summary() and "solved on" not in full.summary()
    assert reduced.samples == full.samples == 6000


def test_the_reduction_keeps_the_manoeuvres_envelope() -> None:
    sim = _array(12)
    rec, _ = sim.run(sea_manoeuvre(6000, pitch_deg=20.0, roll_deg=15.0, turns=3.0, rng=3), rng=4, rate=20.0,
                     continuous=True)
    full = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps, options=SolveOptions(max_solve_sets=0))
    reduced = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps,
                              options=SolveOptions(max_solve_sets=1500))
    assert not full.envelope.whole_sphere  # a limited manoeuvre: the envelope means something
    # within one step of the envelope's 5-deg grid (its edge is where the predicted error
    # crosses 1.5x the noise: a few percent of uncertainty move it by a step)
    assert reduced.envelope.pitch_deg == pytest.approx(full.envelope.pitch_deg, abs=5.0)
    assert reduced.envelope.roll_deg == pytest.approx(full.envelope.roll_deg, abs=5.0)
    assert reduced.envelope.ratio_sphere == pytest.approx(full.envelope.ratio_sphere, rel=0.1)
    assert reduced.envelope.inclination_deg == pytest.approx(full.envelope.inclination_deg, abs=0.1)


def test_the_subset_keeps_rare_attitudes_and_the_whole_time_span() -> None:
    gen = np.random.default_rng(1)
    n = 40_000
    d = np.tile([[0.0, 0.0, 1.0]], (n, 1)) + 0.01 * gen.normal(size=(n, 3))  # parked, pointing up ...
    rare = slice(20_000, 20_480)  # ... but for 30 runs through the lower hemisphere
    d[rare] = gen.normal(size=(480, 3))
    d[rare, 2] = -np.abs(d[rare, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    order = np.arange(n)
    keep = choose_sets(d, order, 2000)
    assert len(keep) <= 2000 and np.all(np.diff(keep) > 0)  # in time order, within the budget
    runs = np.unique(keep // RUN_LENGTH)
    assert np.all(np.isin(np.arange(rare.start, rare.stop) // RUN_LENGTH, runs))  # every rare run kept
    assert keep[0] < 0.05 * n and keep[-1] > 0.95 * n  # the whole time span
    assert np.all(np.diff(keep.reshape(-1, RUN_LENGTH), axis=1) == 1)  # runs of consecutive sets
    assert np.array_equal(choose_sets(d[:100], order[:100], 2000), order[:100])  # short: every set


def test_budget_and_proxy() -> None:
    assert solve_budget(4) == 4000 and solve_budget(1) == 1000 and solve_budget(4, 0) == 0
    raw = np.array([[[1.0, 0, 0]], [[-1.0, 0, 0]], [[0, 3.0, 0]], [[0, -1.0, 0]]]) + 5.0
    proxy = direction_proxy(raw)
    assert np.allclose(np.linalg.norm(proxy, axis=1), 1.0)
    assert np.allclose(proxy[0], np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0))  # minus the mid-range (5, 6, 5)


def test_the_pass_over_every_set_on_spare_cores_gives_the_same_result_to_the_bit(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The pass over every set runs its chunks (and the jackknife's parts) in threads when cores are
    free and adds them up in their order: the calibration, its uncertainty and its envelope are
    exactly those of one chunk after another."""
    from magcal_ros.core import array_fit

    sim = _array(13)
    rec, _ = sim.run(tumble(3000, 2.0, 7), rng=8, rate=50.0, continuous=True)
    monkeypatch.setitem(array_fit.refine_on_all.__kwdefaults__, "chunk", 97)  # several chunks in every part
    out = {}
    for workers in ("1", "2"):
        monkeypatch.setenv("MAGCAL_WORKERS", workers)
        out[workers] = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps,
                                       options=SolveOptions(max_solve_sets=1000))
    one, two = out["1"], out["2"]
    assert "refined on all" in two.summary()
    np.testing.assert_array_equal(two.calibration.matrices, one.calibration.matrices)
    np.testing.assert_array_equal(two.calibration.offsets, one.calibration.offsets)
    assert _quantities(two) == _quantities(one)
    assert two.envelope == one.envelope and two.inflation == one.inflation


def test_a_long_recordings_pass_sums_a_spread_samples_normal_equations_and_weighs_every_set(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond ``PASS_SETS`` sets the pass sums the normal equations of one set in k (spread over the whole
    recording, every part of the jackknife), but decides the outliers on every set: spikes in sets outside the
    sample are excluded all the same, the calibration agrees with the one from every set's normal equations
    within the sample's stated uncertainty (which is the larger by about sqrt(k)), and corrects fresh sets at
    the truth's tensor floor."""
    from magcal_ros.core import array_fit

    import truth_tools as tt

    sim = _array(11)
    rec, _ = sim.run(tumble(6000, 2.0, 5), rng=6, rate=50.0, continuous=True)
    raw = rec.vectors.copy()
    spikes = np.arange(7, 6000, 600)  # 10 sets, none a multiple of 5: outside the sample
    raw[spikes, 2, 0] += 3000 * NT
    opts = SolveOptions(max_solve_sets=1500)
    every = calibrate_array(raw, sim.geometry, F, stamps=rec.stamps, options=opts)
    monkeypatch.setattr(array_fit, "PASS_SETS", 1400)  # 6,000 sets: one in ceil(6000 / 1400) = 5
    sampled = calibrate_array(raw, sim.geometry, F, stamps=rec.stamps, options=opts)
    assert "refined on all (outliers on every set, the normal equations of 1 set in 5)" in sampled.summary()
    assert "1 set in" not in every.summary()
    assert sampled.outliers[2] >= len(spikes) and sampled.outliers[2] == every.outliers[2]
    a, b = _quantities(every), _quantities(sampled)
    assert a.keys() == b.keys() and len(a) >= 40
    # the sample's estimate less every set's: the sample's variance less every set's (1 - 1/5 of it)
    z = np.array([(b[k][0] - a[k][0]) / np.sqrt(max(b[k][1] ** 2 - a[k][1] ** 2, 1e-300)) for k in a])
    assert np.max(np.abs(z)) < 3.5 and np.sqrt(np.mean(z**2)) < 1.4, sorted(zip(np.abs(z), a))[-3:]
    ratio = np.median([b[k][1] / a[k][1] for k in a])
    assert abs(ratio / np.sqrt(5.0) - 1.0) < 0.15, ratio
    fresh, _ = sim.run(tumble(3000, 2.0, 17), rng=18)
    floor = tt.rms(tt.cross_rows(tt.correct(*tt.true_correction(sim), fresh.vectors), sim.geometry.positions))
    cal = sampled.calibration
    got = tt.rms(tt.cross_rows(tt.correct(cal.matrices, cal.offsets, fresh.vectors), sim.geometry.positions))
    assert got < 1.05 * floor, (got / floor)


def test_pieces_run_side_by_side_with_spare_cores_and_one_by_one_without(monkeypatch: pytest.MonkeyPatch) -> None:
    """``map_in_threads`` keeps the items' order; with two workers two items are in flight at once (a
    barrier both must reach; one at a time would never pass it), with ``MAGCAL_WORKERS=1`` none is."""
    import threading

    from magcal_ros.core.parallel import map_in_threads, workers

    monkeypatch.setenv("MAGCAL_WORKERS", "2")
    assert workers() == 2
    barrier = threading.Barrier(2, timeout=120)
    assert map_in_threads(lambda x: (barrier.wait(), x * x)[1], [1, 2, 3, 4]) == [1, 4, 9, 16]
    monkeypatch.setenv("MAGCAL_WORKERS", "1")
    main = threading.get_ident()
    assert map_in_threads(lambda x: (threading.get_ident() == main, x), [3, 1]) == [(True, 3), (True, 1)]
    monkeypatch.setenv("MAGCAL_WORKERS", "zero")
    assert workers() == 1

"""Unit tests of the papers' scalar methods: particle swarm (002) and paired norms (003)."""

from __future__ import annotations

import numpy as np
import pytest
import truth_tools as tt

from magcal_ros.core.metrics import tmi_rms
from magcal_ros.core.sensor_model import SensorErrors
from magcal_ros.core.units import NT
from magcal_ros.errors import CalibrationFailed, InputError
from magcal_ros.methods.paired import (
    angles_to_q,
    j_index,
    matrix_to_q,
    paired_fit,
    q_to_angles,
    q_to_matrix,
    split_pairs,
)
from magcal_ros.methods.pipeline import SolveOptions, calibrate_array
from magcal_ros.methods.pso import (
    chaotic_unit,
    circle_map,
    features,
    fitness,
    pso_fit,
    search_box,
    upper_triangular,
)
from magcal_ros.sim import scenarios as sc
from magcal_ros.sim.attitudes import li2018_grid, uniform_random

F = 50_000 * NT


def readings(sensor: SensorErrors, count: int = 200, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Raw readings (count, 3) of a field of intensity F under random rotations."""
    rng = np.random.default_rng(seed)
    b = uniform_random(count, rng) @ np.array([0.0, 0.0, F])
    k, o = sensor.forward()
    return b @ k.T + o + rng.normal(0.0, noise, (count, 3))


SENSOR = SensorErrors(
    scale=[1.05, 0.97, 1.02],
    angles=np.radians([1.0, -0.7, 0.5]),
    offset=np.array([300.0, -150.0, 80.0]) * NT,
    misalignment=np.radians([3.0, -2.0, 5.0]),
)


def true_upper(sensor: SensorErrors) -> np.ndarray:
    """Upper-triangular factor of the true correction (what a scalar fit can observe)."""
    return upper_triangular(sensor.correction()[0])


# --- particle swarm ---------------------------------------------------------------------


def test_circle_map_stays_in_unit_interval() -> None:
    z = circle_map(np.linspace(0.0, 0.999, 1000))
    assert np.all((z >= 0.0) & (z < 1.0))
    u = chaotic_unit(50, np.random.default_rng(0))
    assert u.shape == (50, 12) and np.all((u >= 0) & (u < 1))
    assert np.std(u) > 0.2  # spread over the interval, not collapsed onto a fixed point


def test_fitness_matches_direct_norms() -> None:
    rng = np.random.default_rng(1)
    lower, upper = search_box(0.5, 0.02)
    pos = lower + rng.uniform(0, 1, (7, 12)) * (upper - lower)
    x = readings(SENSOR, 50) / F
    direct = [
        np.sqrt(np.mean((np.linalg.norm((x - p[9:]) @ p[:9].reshape(3, 3).T, axis=1) - 1.0) ** 2)) for p in pos
    ]
    assert np.allclose(fitness(pos, features(x)), direct, rtol=1e-10, atol=1e-14)


def test_pso_recovers_sensor_and_is_deterministic() -> None:
    r = readings(SENSOR, noise=0.5 * NT)
    fit = pso_fit(r, F, seed=3)
    again = pso_fit(r, F, seed=3)
    assert fit.method == "pso" and fit.std is None and fit.intensity == F
    assert np.array_equal(fit.matrix, again.matrix) and np.array_equal(fit.offset, again.offset)
    assert np.allclose(fit.matrix, np.triu(fit.matrix)) and np.all(np.diag(fit.matrix) > 0)
    assert np.abs(fit.matrix - true_upper(SENSOR)).max() < 1e-4
    assert np.abs(fit.offset - SENSOR.offset).max() < 2 * NT
    assert fit.residual_rms < 0.6 * NT


def test_pso_relative_without_reference() -> None:
    r = readings(SENSOR)
    fit = pso_fit(r, None, seed=0)
    assert fit.residual_rms < 1e-6 * fit.intensity
    assert np.allclose(fit.matrix * F / fit.intensity, true_upper(SENSOR), atol=1e-6)


def test_pso_offset_outside_box_is_refused() -> None:
    far = SensorErrors(offset=np.array([3000.0, 0.0, 0.0]) * NT)  # 6 % of F, box is 2 %
    with pytest.raises(CalibrationFailed, match="offset"):
        pso_fit(readings(far), F, particles=20, iterations=50)
    assert pso_fit(readings(far), F, offset_span=0.1).residual_rms < 1e-3 * NT


def test_pso_bad_arguments() -> None:
    with pytest.raises(InputError):
        pso_fit(readings(SENSOR), F, particles=1)
    with pytest.raises(InputError):
        pso_fit(readings(SENSOR), F, matrix_span=2.0)


# --- paired norms -----------------------------------------------------------------------


def test_q_angles_round_trip() -> None:
    q = angles_to_q(*sc.WU2013_TRUTH)
    # Wu et al. (2013)'s true G (digest, checked with sympy).
    expected = [[0.954766, -0.084247, -0.063473], [0.0, 1.050841, 0.040021], [0.0, 0.0, 1.0]]
    assert np.allclose(q_to_matrix(q), expected, atol=1e-6)
    assert np.allclose(q_to_angles(q), sc.WU2013_TRUTH, atol=1e-14)
    assert np.allclose(matrix_to_q(3.0 * q_to_matrix(q)), q)
    assert np.allclose(np.linalg.inv(sc.wu2013_sensor().triangular), q_to_matrix(q))
    assert j_index(sc.WU2013_TRUTH, sc.WU2013_TRUTH) == 0.0


def test_split_pairs_is_a_partition() -> None:
    a, b = split_pairs(11, np.random.default_rng(0))
    assert len(a) == len(b) == 5 and len(set(a) | set(b)) == 10


def test_paired_with_offset_recovers_sensor() -> None:
    r = readings(SENSOR, noise=0.5 * NT)
    fit = paired_fit(r, F)
    assert fit.method == "paired" and fit.intensity == F
    assert np.allclose(fit.matrix, np.triu(fit.matrix)) and np.all(np.diag(fit.matrix) > 0)
    assert np.abs(fit.offset - SENSOR.offset).max() < 2 * NT
    assert np.abs(fit.matrix - true_upper(SENSOR)).max() < 1e-4
    assert fit.residual_rms < 1 * NT


def test_paired_paper_model_without_offset() -> None:
    no_offset = SensorErrors(scale=SENSOR.scale, angles=SENSOR.angles)
    r = readings(no_offset)
    fit = paired_fit(r, None, fit_offset=False)
    assert np.array_equal(fit.offset, np.zeros(3))
    assert fit.intensity == pytest.approx(np.mean(np.linalg.norm(r, axis=1)))
    assert np.allclose(matrix_to_q(fit.matrix), matrix_to_q(true_upper(no_offset)), atol=1e-12)


def test_paired_needs_enough_readings() -> None:
    with pytest.raises(InputError):
        paired_fit(readings(SENSOR, 12), F)


# --- both methods in the array pipeline -------------------------------------------------


@pytest.mark.parametrize("method, reference, tmi_bound, tensor_bound", [
    ("pso", sc.LI2018_F, 1.01, 1.015), ("paired", sc.LI2018_F, 1.04, 1.035), ("paired", None, 1.04, 1.035)])
def test_pipeline_methods(method: str, reference: float | None, tmi_bound: float, tensor_bound: float) -> None:
    """On the fit data (576 sets of Li et al.'s grid) against the true calibration on the same
    data. Measured over 10 noise seeds (mean / sd / max), worst sensor's TMI and the tensor:
    pso 0.996 / 0.0015 / 0.998 and 1.001 / 0.002 / 1.004; paired (with or without F, the
    same up to scale) 1.006 / 0.005 / 1.015 and 1.009 / 0.004 / 1.015. The summary's own
    tensor figure against sqrt(2) sigma / d: 1.002..1.011 / 0.015 / 1.04 (sampling of 576 sets)."""
    sim = sc.li2018_simulation()
    rec, _ = sim.run(li2018_grid()[::3], rng=2)
    opts = SolveOptions(pso_particles=40, pso_iterations=300)
    res = calibrate_array(rec.vectors, sim.geometry, reference, method=method, options=opts)
    ideal = tt.correct(*tt.true_correction(sim), rec.vectors)
    floor = tmi_rms(ideal, sc.LI2018_F)
    assert res.relative == (reference is None)
    scale = sc.LI2018_F / res.intensity
    b = tt.correct(res.calibration.matrices * scale, res.calibration.offsets, rec.vectors)
    assert np.all(tmi_rms(b, sc.LI2018_F) < tmi_bound * floor)
    pos = sim.geometry.positions
    assert tt.rms(tt.cross_rows(b, pos)) < tensor_bound * tt.rms(tt.cross_rows(ideal, pos))
    assert res.tensor_after * scale < 1.1 * tt.difference_floor(1 * NT, sc.LI2018_BASELINE)

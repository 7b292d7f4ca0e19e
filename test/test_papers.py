"""Reproduce the five papers' simulations with their own parameters (METHODS.md, digest).

Truth always comes from the simulator (its platform field, its true corrections), never
from the solver under test. Noise floors are measured on the same noisy data by applying
the true correction with the tests' own numpy (:mod:`truth_tools`, not the package's
``apply`` / ``gradient``), so each tolerance is stated relative to what noise allows.
Bounds quote the spread measured over seeds (mean / sd / max).
"""

from __future__ import annotations

import numpy as np
import pytest
import truth_tools as tt

from magcal_ros.core.alignment import align_procrustes, li2018_angles
from magcal_ros.core.metrics import tensor_component_rms, tensor_floor, tmi_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.rotation import matrix_to_euler
from magcal_ros.core.scalar_fit import ml_fit
from magcal_ros.core.sensor_model import SensorErrors
from magcal_ros.core.tensor import gradient
from magcal_ros.core.units import NT
from magcal_ros.errors import ObservabilityError
from magcal_ros.methods.paired import j_index, matrix_to_q, paired_fit, q_to_angles
from magcal_ros.methods.pipeline import CalibrationResult, calibrate_array
from magcal_ros.methods.pso import pso_fit
from magcal_ros.sim import scenarios as sc
from magcal_ros.sim.attitudes import (
    li2018_grid,
    coaxial2022_grid,
    three_rotations,
    uniform_random,
)
from magcal_ros.sim.simulator import ArraySimulation, Truth

# ---------------------------------------------------------------------------------------
# Li et al. (2018): 1728-set grid, sigma = 1 nT on the orthogonal sensor output.


@pytest.fixture(scope="module")
def li() -> tuple[ArraySimulation, Recording, Truth]:
    sim = sc.li2018_simulation()
    rec, truth = sim.run(li2018_grid(), rng=1)
    return sim, rec, truth


@pytest.fixture(scope="module")
def li_ml(li: tuple[ArraySimulation, Recording, Truth]) -> CalibrationResult:
    sim, rec, _ = li
    return calibrate_array(rec.vectors, sim.geometry, sc.LI2018_F, method="ml")


@pytest.mark.parametrize("method, angle_bound", [("ml", 4e-6), ("linear", 10e-6)])
def test_li2018_table1_sensor_parameters(request: pytest.FixtureRequest, li, method: str,
                                           angle_bound: float) -> None:
    """All 36 sensor parameters. With N = 1728 and sigma/F = 1.7e-5 the fit's 1-sigma is
    about 1e-6 (relative) for gains, 6e-5 deg for angles and 0.05 nT for offsets (the fit's
    own ``std``); the bounds are ~10 sigma. The paper's PMED (its Table 1) is 2e-5..4e-3 %.

    These parameters do not change when a sensor is rotated, so the sensor-to-sensor
    rotation (what the tensor needs) is checked too, against the truth: measured over 10
    noise seeds (worst sensor, mean / sd / max) 1.5 / 0.2 / 1.8 urad (ml) and 2.6 / 0.9 /
    4.1 urad (linear); bounds mean + 8 sd; an aligner off by 5e-5 rad fails them."""
    sim, rec, _ = li
    if method == "ml":
        res = request.getfixturevalue("li_ml")
    else:
        res = calibrate_array(rec.vectors, sim.geometry, sc.LI2018_F, method=method)
    for i, true in enumerate(sim.sensors):
        est = SensorErrors.from_correction(res.calibration.matrices[i], res.calibration.offsets[i])
        assert np.degrees(np.abs(est.angles - true.angles)).max() < 1e-3
        assert np.abs(est.scale / true.scale - 1.0).max() < 1e-5
        assert np.abs(est.offset - true.offset).max() < 0.5 * NT
    assert tt.relative_angles(res.calibration.matrices, tt.true_forward(sim)).max() < angle_bound


def test_li2018_table2_tmi(li, li_ml: CalibrationResult) -> None:
    """TMI RMSE per sensor: paper 0.98..1.02 nT after, 6715..9042 nT before. After over the
    floor (worst sensor, |ratio - 1|) over 10 noise seeds: 0.0035 / 0.0020 / 0.0079."""
    sim, rec, _ = li
    floor = tt.rms(np.linalg.norm(tt.correct(*tt.true_correction(sim), rec.vectors), axis=2) - sc.LI2018_F, axis=0)
    assert np.all(np.abs(floor / NT - 1.0) < 0.05)  # sigma = 1 nT by construction
    after = li_ml.tmi_after
    assert np.all(np.abs(after / NT - 1.0) < 0.05)
    assert np.all(np.abs(after / floor - 1.0) < 0.015)
    before = li_ml.tmi_before / NT
    assert np.allclose(before, sc.REPORTED["000"]["tmi_before"], rtol=0.15)


@pytest.mark.parametrize("samples", [[0, 4, 8], list(range(12))])
def test_li2018_table3_misalignment(li, samples: list[int]) -> None:
    """Misalignment angles from 3 samples 120 deg apart (and 12, 30 deg apart) on the first
    z turn, aligned to the simulator's platform field B_oc as the paper does. One sample's
    direction noise is sigma/F = 1.7e-5 rad; over 30 noise seeds the worst error was 6e-5."""
    _, rec, truth = li
    for i, preset in enumerate(sc.LI2018_MISALIGNMENT_RAD):
        fit = ml_fit(rec.vectors[:, i], sc.LI2018_F)
        b = fit.apply(rec.vectors[samples, i])
        b_oc = truth.field[samples, i]
        assert np.abs(np.array(li2018_angles(b, b_oc)) - preset).max() < 1e-4
        assert np.abs(np.array(matrix_to_euler(align_procrustes(b, b_oc))) - preset).max() < 1e-4


def test_li2018_table4_tensor(li, li_ml: CalibrationResult) -> None:
    """Six tensor components: paper 3.47..3.96 nT/m after alignment (floor 3.54), tens of
    thousands before and still thousands after scalar calibration only.

    Per component (1728 sets: sd 1.7 %) the worst |after / floor - 1| over 10 noise seeds was
    0.027 / 0.007 / 0.038; over all six against the realized floor (the true calibration on
    the same data) 0.9988 / 0.0004 / 0.9993."""
    sim, rec, _ = li
    floor = tensor_floor(1 * NT, sc.LI2018_BASELINE)
    assert floor / NT == pytest.approx(3.5355, abs=1e-3)
    assert tt.difference_floor(1 * NT, sc.LI2018_BASELINE) == pytest.approx(floor, rel=1e-12)
    g_after = li_ml.calibration.field_and_gradient(rec.vectors)[2]
    after = tensor_component_rms(g_after)
    assert np.all(np.abs(after / floor - 1.0) < 0.07)
    pos = sim.geometry.positions
    realized = tt.rms(tt.cross_rows(tt.correct(*tt.true_correction(sim), rec.vectors), pos))
    assert tt.rms(g_after[:, :2]) / realized < 1.005
    before = tensor_component_rms(gradient(rec.vectors, sim.geometry)) / NT
    assert np.all((before > 1e4) & (before < 1e5))
    scalar_only = np.stack([ml_fit(rec.vectors[:, i], sc.LI2018_F).apply(rec.vectors[:, i]) for i in range(4)], 1)
    assert np.all(tensor_component_rms(gradient(scalar_only, sim.geometry)) / NT > 1e3)


def test_li2018_single_z_rotation_refused(li) -> None:
    """Pitfall B: the paper's samples from one z turn cannot determine 9 parameters."""
    sim, rec, _ = li
    with pytest.raises(ObservabilityError, match=r"rotation about x or y"):
        calibrate_array(rec.vectors[:12], sim.geometry, sc.LI2018_F)
    with pytest.raises(ObservabilityError):
        calibrate_array(rec.vectors[:10], sim.geometry, sc.LI2018_F)  # the paper's 10 samples


def test_li2018_fresh_data(li, li_ml: CalibrationResult) -> None:
    """Calibrate on the grid, evaluate on 500 new attitudes with new noise. Over 10 seeds:
    worst component |ratio - 1| 0.011 / 0.005 / 0.024, worst sensor TMI 1.005 / 0.003 / 1.012."""
    sim, _, _ = li
    fresh, _ = sim.run(uniform_random(500, 11), rng=12)
    est = li_ml.calibration.field_and_gradient(fresh.vectors)
    ideal = tt.correct(*tt.true_correction(sim), fresh.vectors)
    ratio = tensor_component_rms(est[2]) / tt.rms(tt.cross_rows(ideal, sim.geometry.positions), axis=0).reshape(6)
    assert np.all(np.abs(ratio - 1.0) < 0.04)
    tmi = tmi_rms(est[0], sc.LI2018_F) / tt.rms(np.linalg.norm(ideal, axis=2) - sc.LI2018_F, axis=0)
    assert np.all(tmi < 1.02)


def test_random_48_attitudes_fresh_data() -> None:
    """48 random attitudes (a short manoeuvre), on new data against the true calibration on the
    same data. Measured over 20 seeds (mean / sd / max): tensor 1.041 / 0.009 / 1.058 (bound:
    mean + 5 sd, a 10 % worse method reaches 1.145); TMI over the array 1.057 / 0.022 / 1.116
    (bound mean + 3.8 sd; 10 % worse: 1.163); worst sensor 1.09 / 0.036 / 1.197 (too spread
    for a 10 % bound from one seed; kept at 1.15)."""
    sim = sc.li2018_simulation()
    rec, _ = sim.run(uniform_random(48, 21), rng=22)
    res = calibrate_array(rec.vectors, sim.geometry, sc.LI2018_F, method="ml")
    fresh, _ = sim.run(uniform_random(500, 23), rng=24)
    g = res.calibration.field_and_gradient(fresh.vectors)[2]
    ideal = tt.correct(*tt.true_correction(sim), fresh.vectors)
    assert tt.rms(g[:, :2]) / tt.rms(tt.cross_rows(ideal, sim.geometry.positions)) < 1.09
    tmi = tmi_rms(res.calibration.apply(fresh.vectors), sc.LI2018_F)
    tmi_ideal = tt.rms(np.linalg.norm(ideal, axis=2) - sc.LI2018_F, axis=0)
    assert np.sqrt(np.mean(tmi**2) / np.mean(tmi_ideal**2)) < 1.14
    assert np.all(tmi / tmi_ideal < 1.15)


# ---------------------------------------------------------------------------------------
# Ding (2024): 300 random attitudes, uniform noise of peak-to-peak a on the raw output.


def _ding_sensor0(table: int, a_nt: float) -> tuple[np.ndarray, float, float]:
    """Sensor-0 readings, the truth floor on them (T) and the raw TMI RMS (T)."""
    sim = sc.ding2024_simulation(table, a_nt * NT)
    rec, truth = sim.run(uniform_random(300, 7), rng=3)
    r = rec.vectors[:, 0]
    m, o = sim.sensors[0].correction()
    floor = float(np.sqrt(np.mean((np.linalg.norm((r - o) @ m.T, axis=1) - sc.DING2024_F) ** 2)))
    before = float(np.sqrt(np.mean((np.linalg.norm(r, axis=1) - sc.DING2024_F) ** 2)))
    return r, floor, before


# The noise levels differ only in scale: the same uniform draws times a, a fit that is exact
# without noise and invariant to the noise scale. So the ratio to the floor is the same at every
# level (measured 0.97134 Table 1, 0.97264 Table 2 at 2, 5 and 10 nT) and is tested once, at
# 2 nT; what differs between the levels, the residual itself, is tested against the paper.


@pytest.mark.parametrize("table", [1, 2])
@pytest.mark.parametrize("a_nt", [0.0, 2.0])
def test_ding2024_ml_at_noise_floor(table: int, a_nt: float) -> None:
    """Noise-free: exact. At a = 2 nT: at the floor the true calibration gives on the same data."""
    r, floor, _ = _ding_sensor0(table, a_nt)
    fit = ml_fit(r, sc.DING2024_F)
    if a_nt == 0:
        assert fit.residual_rms < 1e-12 * sc.DING2024_F
        return
    sd = a_nt * NT / np.sqrt(12)
    assert abs(floor / sd - 1.0) < 0.15  # hull soft iron scales the raw noise by ~10 %
    # 9 fitted parameters absorb 9/300 of the noise power: the fit sits ~1.5 % below the floor.
    assert 0.95 < fit.residual_rms / floor < 1.0


@pytest.mark.parametrize("table", [1, 2])
def test_ding2024_residual_follows_the_noise_level(table: int) -> None:
    """Paper (improved PSO, = ML): 0.58 / 1.42 / 2.84 nT (Table 1), 0.532 / 1.329 / 2.659 nT
    (Table 2) at a = 2 / 5 / 10 nT; measured 0.553 / 1.382 / 2.764 and 0.533 / 1.332 / 2.663:
    proportional to a (to 1e-5) and within 5 % of the paper's."""
    levels = [a for a in sc.DING2024_NOISE_PP_NT if a > 0]
    res = np.array([ml_fit(_ding_sensor0(table, a)[0], sc.DING2024_F).residual_rms / NT for a in levels])
    per_level = res / np.array(levels)
    assert np.ptp(per_level) < 1e-4 * per_level.mean()
    reported = np.array(sc.REPORTED["002"][f"table{table}_improved"][1:])
    assert np.all(np.abs(res / reported - 1.0) < 0.05)


@pytest.mark.parametrize("table", [1, 2])
@pytest.mark.parametrize("a_nt", [0.0, 2.0])
def test_ding2024_array_ml(table: int, a_nt: float) -> None:
    """The array pipeline, default method: 4 sensors with the paper's errors (and random
    2-deg misalignments), on the fit data and on 500 new attitudes with new noise (one noise
    level: the ratios do not depend on it, see above)."""
    sim = sc.ding2024_simulation(table, a_nt * NT)
    rec, _ = sim.run(uniform_random(300, 7), rng=3)
    res = calibrate_array(rec.vectors, sim.geometry, sc.DING2024_F, method="ml")
    if a_nt == 0:
        assert np.all(res.tmi_after < 1e-12 * sc.DING2024_F)
        return
    truth_cal = tt.true_correction(sim)
    floor = tt.rms(np.linalg.norm(tt.correct(*truth_cal, rec.vectors), axis=2) - sc.DING2024_F, axis=0)
    assert np.all(np.abs(res.tmi_after / floor - 1.0) < 0.05)
    # New data: 9 parameters from 300 sets add ~9/600 = 1.5 % in expectation; per sensor
    # the excess scatters (measured up to 3.7 %), over the array it stays within 2 %.
    fresh, _ = sim.run(uniform_random(500, 8), rng=9)
    new = tmi_rms(res.calibration.apply(fresh.vectors), sc.DING2024_F)
    ideal = tt.rms(np.linalg.norm(tt.correct(*truth_cal, fresh.vectors), axis=2) - sc.DING2024_F, axis=0)
    assert np.all(new / ideal < 1.05)
    assert np.sqrt(np.mean(new**2) / np.mean(ideal**2)) < 1.02


@pytest.mark.parametrize("a_nt", sc.DING2024_NOISE_PP_NT)
def test_ding2024_pso_small_budget(a_nt: float) -> None:
    """Improved PSO, 30 particles x 150 iterations (the paper's budget is larger).

    Measured on Table 1 over 10 seeds at this budget: 0.03..0.8 nT at a = 0 (raw 6825 nT);
    for a >= 2 nT the median is within 2 % of the floor, the worst seed up to 4.5x it.
    Plain PSO at the same budget: median 1.9..3.2 nT. Both reach the ML optimum at 50 x 400.
    """
    r, floor, before = _ding_sensor0(1, a_nt)
    improved = [pso_fit(r, sc.DING2024_F, 30, 150, seed=s).residual_rms for s in range(5)]
    plain = [pso_fit(r, sc.DING2024_F, 30, 150, seed=s, improved=False).residual_rms for s in range(5)]
    assert max(improved) < before / 100
    assert np.median(improved) <= np.median(plain)
    if a_nt > 0:
        assert np.median(improved) < 1.25 * floor


@pytest.mark.parametrize("table", [1, 2])
def test_ding2024_pso_default_budget(table: int) -> None:
    """With the default 50 x 400 both PSO variants reach the ML optimum (a = 2 nT)."""
    r, floor, _ = _ding_sensor0(table, 2.0)
    best = ml_fit(r, sc.DING2024_F).residual_rms
    for improved in (True, False):
        fit = pso_fit(r, sc.DING2024_F, seed=0, improved=improved)
        assert fit.residual_rms / best - 1.0 < 1e-3
        assert fit.residual_rms < floor


# ---------------------------------------------------------------------------------------
# Wu et al. (2013): no reference field, strong noise, index J over (theta, phi, psi, k'xz, k'yz).


def _wu_j(sd_units: float, seeds: range) -> tuple[float, float]:
    """Mean J of the paired method (paper's 5-parameter model) and of ML over ``seeds``."""
    sim = sc.wu2013_simulation(sd_units)
    jp, jm = [], []
    for seed in seeds:
        rec, _ = sim.run(three_rotations(480), rng=seed)  # 2N = 1440, N = 720 pairs
        r = rec.vectors[:, 0]
        pf = paired_fit(r, None, seed=seed, fit_offset=False)
        jp.append(j_index(q_to_angles(matrix_to_q(pf.matrix)), sc.WU2013_TRUTH))
        jm.append(j_index(q_to_angles(matrix_to_q(ml_fit(r, None).matrix)), sc.WU2013_TRUTH))
    return float(np.mean(jp)), float(np.mean(jm))


def test_wu2013_noise_free() -> None:
    jp, jm = _wu_j(0.0, range(1))
    assert jp < 1e-10 and jm < 1e-10


def test_wu2013_strong_noise() -> None:
    """sd = 1e-2 units (100 nT, 0.5 % of |B|). The extracted paper gives no J values.

    Measured over 30 seeds (mean / sd / max): J 0.0207 / 0.0101 / 0.049 (paired) and
    0.0221 / 0.0150 / 0.063 (ML, which also fits an offset). One seed's J scatters by 50 %,
    so no handful of seeds can resolve 10 %: the means over these six seeds (0.0252 paired,
    0.0247 ML; five disjoint groups of six gave 0.017..0.025) are held within 1.1x. The same
    noise draws at a tenth of the sd give a tenth of J (9.9x measured): linear, no breakdown.
    """
    jp, jm = _wu_j(1e-2, range(6))
    assert jp < 0.0275 and jm < 0.027
    assert jm < 1.25 * jp
    jp3, _ = _wu_j(1e-3, range(6))
    assert 9.5 < jp / jp3 < 10.5


# ---------------------------------------------------------------------------------------
# The two-fluxgate gradiometer paper: two sensors, three turns of 10 points, regression of sensor 2 onto sensor 1.


def _ptp(values: np.ndarray) -> np.ndarray:
    return np.ptp(values, axis=0) / NT


def test_gradiometer_regression() -> None:
    """Peak-to-peak over 30 points varies a lot between runs: medians over 20 runs.

    Paper: TMI 3138.6 -> 4.6 and 2633.0 -> 4.1 nT; difference after 5.4 / 5.6 / 5.9 nT.
    Measured (sd 1 nT): before 3131 / 2472, after ~3.4 / 4.1, difference ~5.4 / 5.3 / 5.3.
    """
    sim = sc.gradiometer_simulation()
    f = float(np.linalg.norm(sim.earth))
    rows = []
    for seed in range(20):
        rec, _ = sim.run(three_rotations(10), rng=seed)
        res = calibrate_array(rec.vectors, sim.geometry, f, method="regression")
        raw, b = rec.vectors, res.calibration.apply(rec.vectors)
        rows.append(
            np.concatenate(
                [
                    _ptp(np.linalg.norm(raw, axis=2) - f),
                    _ptp(np.linalg.norm(b, axis=2) - f),
                    _ptp(raw[:, 0] - raw[:, 1]),
                    _ptp(b[:, 0] - b[:, 1]),
                ]
            )
        )
        # Two sensors: the baseline gradient dB/ds (uniform field: 0) at its floor sqrt(2) sigma / d.
        assert res.gradient_kind == "baseline" and res.tensor_after < 1.6 * np.sqrt(2) * 1e-9 / 0.5
    med = np.median(rows, axis=0)
    rep = sc.REPORTED["001"]

    def within(values: np.ndarray, reported: tuple[float, ...], low: float, high: float) -> bool:
        ref = np.array(reported)
        return bool(np.all((values > low * ref) & (values < high * ref)))

    assert within(med[0:2], rep["tmi_ptp_before"], 0.5, 2.0)
    assert within(med[2:4], rep["tmi_ptp_after"], 0.5, 1.5)
    assert within(med[4:7], rep["diff_ptp_before"], 0.5, 2.0)
    assert within(med[7:10], rep["diff_ptp_after"], 0.5, 1.5)


# ---------------------------------------------------------------------------------------
# The JNWPU 2022 coaxial calibration paper: 144-attitude grid, F 48750 nT, residual axis angle between sensors.


def axis_angles_deg(matrices: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Angle (deg) between each corrected axis of sensor i and the same axis of sensor 1.

    ``E_i = M_i K_i`` maps the true platform field to sensor i's corrected output; its
    rows are the directions the corrected axes measure along, in the true platform frame.
    """
    e = np.einsum("sij,sjk->sik", matrices, forward)
    u = e / np.linalg.norm(e, axis=2, keepdims=True)
    cos = np.clip(np.einsum("sjk,jk->sj", u, u[0]), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


@pytest.mark.parametrize("method, bound_deg", [("reference", 0.0025), ("ml", 0.0015)])
def test_coaxial2022_axis_angle(method: str, bound_deg: float) -> None:
    """Paper: about 1 deg (up to 2) before, < 0.01 deg after alignment.

    Measured over 20 noise seeds (worst axis, deg, mean / sd / max): reference 0.00096 /
    0.00031 / 0.0018, ml 0.00063 / 0.00016 / 0.0010; the bounds are the mean + 5 sd, below
    the 0.0029 deg of an aligner off by 5e-5 rad."""
    sim = sc.coaxial2022_simulation()
    rec, _ = sim.run(coaxial2022_grid(), rng=5)
    forward = np.stack([s.forward()[0] for s in sim.sensors])
    before = axis_angles_deg(np.tile(np.eye(3), (4, 1, 1)), forward)
    assert 0.5 < before.max() < 5.0
    res = calibrate_array(rec.vectors, sim.geometry, sc.COAXIAL2022_F, method=method)
    assert axis_angles_deg(res.calibration.matrices, forward).max() < bound_deg

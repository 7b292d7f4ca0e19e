"""The gradient of every supported geometry in a non-uniform field, against the simulator's truth.

A uniform field (every calibration manoeuvre) is blind to a tensor that takes the wrong
sensor for a row: every difference is zero whichever sensors it subtracts. Here the
array turns through 40 attitudes 1.6 m from a dipole (as ``ArraySimulation`` places one),
noise-free, and the package's gradient is compared with

- the same finite-difference estimator written independently (:mod:`truth_tools`:
  the cross difference, the symmetric traceless least-squares fit, the baseline slope)
  on the same fields: equal to rounding, so any wiring, sign or baseline error shows;
- the simulator's true gradient at the centre (``Truth.gradient``; along a baseline
  ``dB/ds = a . G``): within the truncation of the finite differences, which is measured
  with the independent estimator on the exact fields and shown to vanish as the
  geometry shrinks (so it is truncation, not a wrong formula);
- and with two sensors' readings swapped (the wrong sensor for a row), the same
  comparison fails by far.

The simulator's truth itself is checked against a dipole written here and differentiated
numerically.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import truth_tools as tt

from magcal_ros.core.field import Dipole
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.sensor_model import SensorErrors
from magcal_ros.core.tensor import (
    baseline_gradient,
    centre_field,
    gradient,
    gradient_least_squares,
    invariants,
)
from magcal_ros.errors import InputError
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation, Truth

EARTH = np.array([2.0e-5, 0.0, 4.5e-5])
DIPOLE = Dipole(np.array([1.2, -0.6, 0.8]), np.array([40.0, -25.0, 60.0]))  # 1.56 m from the centre
ATTITUDES = uniform_random(40, 1)
SHRINK = 8.0

GEOMETRIES: dict[str, list[list[float]]] = {
    "cross": [[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]],
    "six sensors in 3-D": [[0.25, 0, 0], [-0.2, 0.05, 0], [0, 0.3, 0.05], [0.05, -0.25, 0], [0, 0, 0.2],
                           [0.02, 0.03, -0.22]],
    "planar triangle": [[0.3, 0, 0], [-0.15, 0.26, 0], [-0.15, -0.26, 0]],
    "baseline": [[0, 0, 0], [0.5, 0, 0]],
}
# (geometry, package estimator); truncation at the real size, measured: 4.7 / 4.5 / 5.0 / 27 / 7.4 %
CASES = [("cross", "difference"), ("cross", "least_squares"), ("six sensors in 3-D", "least_squares"),
         ("planar triangle", "least_squares"), ("baseline", "baseline")]


def simulate(positions: list[list[float]], shrink: float = 1.0) -> tuple[ArrayGeometry, Truth]:
    """Noise-free truth of the array (shrunk about its centre by ``shrink``) near the dipole."""
    pos = np.asarray(positions, dtype=float)
    pos = pos.mean(axis=0) + (pos - pos.mean(axis=0)) / shrink
    geo = ArrayGeometry(tuple(f"s{i}" for i in range(len(pos))), pos)
    sim = ArraySimulation(geo, tuple(SensorErrors() for _ in pos), EARTH, noise=0.0, dipoles=(DIPOLE,))
    return geo, sim.run(ATTITUDES, 0)[1]


def package(kind: str, b: np.ndarray, geo: ArrayGeometry) -> np.ndarray:
    return baseline_gradient(b, geo) if kind == "baseline" else gradient(b, geo, kind)


def independent(kind: str, b: np.ndarray, positions: np.ndarray) -> np.ndarray:
    if kind == "baseline":
        return tt.baseline_slope(b, positions)
    if kind == "difference":
        return tt.cross_difference(b, positions)
    return tt.least_squares_tensor(b, positions)


def true_gradient(kind: str, truth: Truth, geo: ArrayGeometry) -> np.ndarray:
    if kind == "baseline":
        axis = (geo.positions[-1] - geo.positions[0]) / np.linalg.norm(geo.positions[-1] - geo.positions[0])
        return np.einsum("i,nij->nj", axis, truth.gradient)
    return truth.gradient


def relative_error(g: np.ndarray, truth: np.ndarray) -> float:
    return float(tt.rms(g - truth) / tt.rms(truth))


def test_the_simulated_truth_is_the_dipole_field_and_its_gradient() -> None:
    """Truth.field and Truth.gradient against a dipole written here, differentiated numerically."""
    geo, truth = simulate(GEOMETRIES["six sensors in 3-D"])

    def world(p: np.ndarray) -> np.ndarray:
        return EARTH + tt.dipole_field(p, DIPOLE.position, DIPOLE.moment)

    for k in (0, 17, 39):
        rot = ATTITUDES[k]
        field = np.array([rot.T @ world(rot @ p) for p in geo.positions])
        np.testing.assert_allclose(truth.field[k], field, rtol=0, atol=1e-12 * np.abs(field).max())
        g = rot.T @ tt.numerical_gradient(world, rot @ geo.centre) @ rot
        np.testing.assert_allclose(truth.gradient[k], g, rtol=0, atol=1e-7 * np.abs(g).max())
    assert tt.rms(truth.gradient) > 1e-6, "the dipole gives a strong gradient (T/m)"


@pytest.mark.parametrize("name, kind", CASES)
def test_gradient_in_a_dipole_field(name: str, kind: str) -> None:
    geo, truth = simulate(GEOMETRIES[name])
    g_true = true_gradient(kind, truth, geo)
    g = package(kind, truth.field, geo)
    # 1. the same estimator written independently, on the same exact fields: equal to rounding
    reference = independent(kind, truth.field, geo.positions)
    assert tt.rms(g - reference) < 1e-10 * tt.rms(g_true)
    # 2. what the finite differences allow: the independent estimator's error on the exact
    #    fields, and it is truncation: shrinking the array 8x shrinks it 64x (centred layouts:
    #    second order), 14x (six sensors) or 8x (the triangle: first order).
    truncation = relative_error(reference, g_true)
    small_geo, small_truth = simulate(GEOMETRIES[name], SHRINK)
    small = relative_error(independent(kind, small_truth.field, small_geo.positions),
                           true_gradient(kind, small_truth, small_geo))
    assert small < 1.25 * truncation / SHRINK and small < 0.05
    assert relative_error(g, g_true) <= truncation * (1 + 1e-9)
    # 3. the wrong sensor for a row: any two sensors swapped is far outside the truncation
    #    (measured: 5.3x it for the triangle, 7-27x for the others)
    for i, j in itertools.combinations(range(geo.size), 2):
        order = list(range(geo.size))
        order[i], order[j] = j, i
        wrong = relative_error(package(kind, truth.field[:, order], geo), g_true)
        assert wrong > 2.5 * truncation and wrong > 0.3, (i, j, wrong, truncation)


@pytest.mark.parametrize("name", list(GEOMETRIES))
def test_centre_field_is_the_mean_of_the_sensors(name: str) -> None:
    """The centre field (N, 3) is the sensors' mean, the field at the centre to second order for
    any layout (the positions' mean is the centre): in the dipole's field it is off by 1.9 .. 10.5 %
    of the dipole's part (measured), and 64x less on an array 8x smaller."""
    geo, truth = simulate(GEOMETRIES[name])
    c = centre_field(truth.field)
    assert c.shape == (len(ATTITUDES), 3)
    np.testing.assert_allclose(c, truth.field.mean(axis=1), rtol=0, atol=1e-15)

    def error(t: Truth) -> float:
        dipole_part = t.centre - np.einsum("nji,j->ni", ATTITUDES, EARTH)
        return float(tt.rms(centre_field(t.field) - t.centre) / tt.rms(dipole_part))

    big, small = error(truth), error(simulate(GEOMETRIES[name], SHRINK)[1])
    assert big < 0.12 and small < 1.25 * big / SHRINK**2


def test_invariants_of_a_batch_of_measured_tensors() -> None:
    """Rows x and y are measured, so Gxy and Gyx differ; the invariants of a batch (N, 3, 3)
    against numpy one tensor at a time."""
    g = np.random.default_rng(2).normal(0.0, 1e-6, (7, 3, 3))
    inv = invariants(g)
    for k, m in enumerate(g):
        sym = 0.5 * (m + m.T)
        np.testing.assert_allclose(inv["eigenvalues"][k], np.linalg.eigvalsh(sym), rtol=1e-12, atol=1e-20)
        assert inv["norm"][k] == pytest.approx(np.sqrt(np.sum(m * m)), rel=1e-12)
        assert inv["trace"][k] == pytest.approx(np.trace(m), rel=1e-12)
        assert inv["i2"][k] == pytest.approx(0.5 * (np.trace(m) ** 2 - np.trace(m @ m)), rel=1e-10)


@pytest.mark.parametrize("name", ["six sensors in 3-D", "planar triangle"])
def test_least_squares_centre_field_of_an_array_away_from_the_origin(name: str) -> None:
    """The least-squares fit also gives the field B0 at the array's centre; with the whole array
    0.7 m off the platform origin (its centre is not the origin) B0 and G equal the independent
    fit's (B0 is what it is relative to the truth: the centre-field test above)."""
    pos = np.asarray(GEOMETRIES[name]) + np.array([0.5, -0.4, 0.3])
    geo, truth = simulate(pos.tolist())
    b0, g = gradient_least_squares(truth.field, geo)
    b0_ref, g_ref = tt.least_squares_tensor(truth.field, geo.positions, with_centre=True)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-10 * tt.rms(g_ref))
    np.testing.assert_allclose(b0, b0_ref, rtol=0, atol=1e-10 * tt.rms(b0_ref))


def test_positions_that_determine_no_tensor_are_refused_saying_what_they_do_determine() -> None:
    one = ArrayGeometry(("a",), [[0.0, 0.0, 0.0]])
    line = ArrayGeometry(("a", "b", "c"), [[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.5, 0.0, 0.0]])
    with pytest.raises(InputError, match="one sensor position determines no gradient"):
        gradient(np.zeros((1, 1, 3)), one)
    with pytest.raises(InputError, match=r"on one line .*only the gradient along it"):
        gradient(np.zeros((1, 3, 3)), line, "least_squares")
    with pytest.raises(InputError, match="needs sensors on one line"):
        baseline_gradient(np.zeros((1, 4, 3)), ArrayGeometry.cross())


def test_one_set_may_be_given_alone_and_a_wrong_shape_is_refused() -> None:
    """A single set (S, 3) gives the same tensor as the batch of one (1, S, 3), for the difference
    formula and least squares; vectors of the wrong sensor count or width are an InputError, whichever
    of the two is wrong. (Mutation survivors of tensor._sets: the single set dropped, `or` as `and`.)"""
    geo = ArrayGeometry.cross()
    rng = np.random.default_rng(21)
    one = rng.normal(0.0, 5e-5, (4, 3))
    for method in ("difference", "least_squares"):
        np.testing.assert_array_equal(gradient(one, geo, method), gradient(one[None], geo, method))
    for bad in (np.zeros((2, 3, 3)), np.zeros((2, 4, 2)), np.zeros((4, 3, 1))):
        with pytest.raises(InputError, match=r"expected vectors of shape \(N, 4, 3\)"):
            gradient(bad, geo, "least_squares")

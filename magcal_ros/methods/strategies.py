"""The selectable calibration methods, each a strategy: a reference, a scalar solver and an aligner.

A method is data, not code paths: :func:`magcal_ros.methods.pipeline.calibrate_array` runs
the same steps for all of them and asks the method's strategies what to do at each.

- **reference**: which readings define the platform frame: the virtual centre sensor
  ``mean(r_1..r_S)`` (Li et al. 2018) or sensor 1 (the two-fluxgate gradiometer paper
  and the JNWPU 2022 coaxial calibration).
- **scalar solver**: a one-sensor scalar (TMI) calibration ``(readings, F, options) ->
  ScalarFit``.
- **aligner**: how each sensor is brought into the reference frame: scalar-calibrate it
  and rotate it (Procrustes, or Li et al.'s Euler angles), or regress it affinely onto
  the reference (gradiometer paper), which needs no scalar fit of its own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.alignment import affine_regression, align_angles, align_procrustes
from magcal_ros.core.batched import sensor_means
from magcal_ros.core.scalar_fit import ScalarFit, algebraic_fit, ml_fit

if TYPE_CHECKING:
    from magcal_ros.methods.pipeline import SolveOptions

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SensorFit:
    """One sensor's correction ``B = matrix (raw - offset)`` and the 1-sigma of its scalar fit."""

    matrix: Array
    offset: Array
    std: Array


ScalarSolver = Callable[[Array, "float | None", "SolveOptions"], ScalarFit]
Aligner = Callable[[Array, Array, float, ScalarSolver, "SolveOptions"], SensorFit]
Reference = Callable[[Array], "tuple[Array, int | None]"]


def _no_std() -> Array:
    return np.full(9, np.nan)


# -- scalar solvers -----------------------------------------------------------------
def solve_ml(r: Array, f: float | None, o: "SolveOptions") -> ScalarFit:
    """Closed-form start, then maximum likelihood (:func:`~magcal_ros.core.scalar_fit.ml_fit`); without the
    noise's bias correction when the joint fit follows (``o.joint``: a start, the joint fit has no such bias; with
    residuals the start does not model, a temperature drift or currents, the correction was a second fit)."""
    return ml_fit(r, f, loss=o.loss, loss_scale=o.loss_scale, bias_correction=not o.joint)


def solve_linear(r: Array, f: float | None, o: "SolveOptions") -> ScalarFit:
    """Li et al. (2018): the linear quadric fit, decoded in closed form."""
    return algebraic_fit(r, f)


def solve_pso(r: Array, f: float | None, o: "SolveOptions") -> ScalarFit:
    """Ding (2024): improved particle swarm on the TMI residual."""
    from magcal_ros.methods.pso import pso_fit

    return pso_fit(r, f, particles=o.pso_particles, iterations=o.pso_iterations, seed=o.seed)


def solve_paired(r: Array, f: float | None, o: "SolveOptions") -> ScalarFit:
    """Wu et al. (2013): reference-free paired-norm fit."""
    from magcal_ros.methods.paired import paired_fit

    return paired_fit(r, f, seed=o.seed)


# -- aligners -------------------------------------------------------------------------
def _rotated(rotate: Callable[[Array, Array], Array]) -> Aligner:
    """An aligner that scalar-calibrates the sensor, then rotates it onto the reference."""

    def align(raw: Array, reference: Array, intensity: float, solver: ScalarSolver, o: "SolveOptions") -> SensorFit:
        fit = solver(raw, intensity, o)
        rot = rotate(fit.apply(raw), reference)
        return SensorFit(rot @ fit.matrix, fit.offset, fit.std if fit.std is not None else _no_std())

    return align


align_by_procrustes: Aligner = _rotated(align_procrustes)
align_by_angles: Aligner = _rotated(align_angles)


def align_by_regression(raw: Array, reference: Array, intensity: float, solver: ScalarSolver,
                        o: "SolveOptions") -> SensorFit:
    """Affine regression of the raw readings onto the reference vectors (no scalar fit)."""
    w, offset = affine_regression(raw, reference)
    return SensorFit(w, offset, _no_std())


# -- references -----------------------------------------------------------------------
def centre_reference(raw: Array) -> tuple[Array, int | None]:
    """The virtual centre sensor: mean of the raw readings of all sensors (no sensor of its own)."""
    return sensor_means(raw), None


def first_reference(raw: Array) -> tuple[Array, int | None]:
    """Sensor 1 is the reference (it keeps its scalar fit as its correction)."""
    return raw[:, 0], 0


@dataclass(frozen=True)
class Method:
    """A named calibration method: its strategies and what it needs."""

    name: str
    source: str
    description: str
    scalar: ScalarSolver
    aligner: Aligner
    reference: Reference
    needs_reference_field: bool
    joint: bool = False
    """Finish with the joint array fit (:mod:`magcal_ros.core.array_fit`)."""


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("ml", "magcal_ros", "closed-form start, per-sensor maximum likelihood, Procrustes alignment, "
               "then joint maximum likelihood over the array; works without a reference field",
               solve_ml, align_by_procrustes, centre_reference, False, joint=True),
        Method("linear", "Li et al. 2018", "linear quadric fit decoded in closed form, "
               "least-squares Euler angles to the array centre",
               solve_linear, align_by_angles, centre_reference, True),
        Method("pso", "Ding 2024", "improved particle swarm on the TMI residual, Procrustes alignment",
               solve_pso, align_by_procrustes, centre_reference, True),
        Method("paired", "Wu et al. 2013", "reference-free paired-norm fit of relative gains "
               "and angles, Procrustes alignment", solve_paired, align_by_procrustes, centre_reference, False),
        Method("regression", "two-fluxgate gradiometer paper", "linear scalar fit of sensor 1, affine "
               "regression of the others onto it", solve_linear, align_by_regression, first_reference, True),
        Method("reference", "JNWPU 2022 coaxial calibration", "linear scalar fit per sensor, Euler-angle "
               "alignment to sensor 1", solve_linear, align_by_angles, first_reference, True),
    )
}
DEFAULT_METHOD = "ml"

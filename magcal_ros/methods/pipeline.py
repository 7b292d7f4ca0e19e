"""The array calibration pipeline, the same for every method (:mod:`magcal_ros.methods.strategies`).

1. check that the attitudes can determine a calibration (:mod:`magcal_ros.core.observability`);
2. scalar-calibrate the method's reference (the virtual centre sensor or sensor 1); its
   orthogonal output defines the platform frame;
3. bring every other sensor into that frame with the method's aligner;
4. optionally refine jointly over the array (:mod:`magcal_ros.core.joint_fit`);
5. check the result and summarise it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.array_fit import fit_array, fix_rotation_gauge
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tensor_rms, tmi_rms
from magcal_ros.core.observability import Excitation, excitation
from magcal_ros.core.tensor import gradient
from magcal_ros.core.units import NT
from magcal_ros.errors import CalibrationFailed, InputError, ObservabilityError
from magcal_ros.methods.strategies import DEFAULT_METHOD, METHODS, SensorFit

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SolveOptions:
    """Knobs shared by the methods."""

    loss: str = "linear"
    """Robust loss of the ML fit: linear, huber, soft_l1, cauchy."""
    loss_scale: float | None = None
    """Residual (T) beyond which the robust loss down-weights a set."""
    gradient_method: str = "difference"
    pso_particles: int = 50
    pso_iterations: int = 400
    seed: int | None = 0
    joint: bool = True
    """Refine method ml jointly over the array (skipped with a robust loss)."""
    max_relative_std: float = 1e-2
    """Reject a calibration whose parameters are this uncertain (fraction of F)."""


@dataclass(frozen=True)
class CalibrationResult:
    """A solved calibration with its diagnostics."""

    calibration: ArrayCalibration
    method: str
    samples: int
    intensity: float
    """Reference intensity F (T); estimated when ``relative``."""
    relative: bool
    tmi_before: Array
    """Per-sensor RMS of ``|raw| - F`` (T)."""
    tmi_after: Array
    """Per-sensor RMS of ``|corrected| - F`` (T) on the fit data."""
    tensor_before: float
    """RMS (T/m) of the six measured tensor components from raw data (uniform field: 0)."""
    tensor_after: float
    excitation: Excitation
    std: Array
    """(S, 9) 1-sigma parameter uncertainty per sensor (6 matrix entries / F, 3 offsets T)."""
    seconds: float
    extras: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        """One line: samples, TMI and tensor residuals before and after."""
        mode = "relative, F estimated" if self.relative else "F"
        return (
            f"calibrated {self.calibration.geometry.size} sensors from {self.samples} sets "
            f"(method {self.method}, {mode} {self.intensity / NT:.1f} nT): "
            f"TMI RMS {np.max(self.tmi_before) / NT:.2f} -> {np.max(self.tmi_after) / NT:.3f} nT, "
            f"tensor RMS {self.tensor_before / NT:.1f} -> {self.tensor_after / NT:.3f} nT/m, "
            f"coverage {self.excitation.coverage:.0%}"
        )


def check_raw(raw: ArrayLike, geometry: ArrayGeometry) -> Array:
    """Raw sets as (N, S, 3) finite floats, or :class:`InputError`."""
    r = np.asarray(raw, dtype=float)
    if r.ndim != 3 or r.shape[1:] != (geometry.size, 3):
        raise InputError(f"raw sets must have shape (N, {geometry.size}, 3), got {r.shape}")
    bad = ~np.all(np.isfinite(r), axis=(1, 2))
    if np.any(bad):
        raise InputError(f"{int(bad.sum())} sets contain NaN or infinite values (first at index {int(np.argmax(bad))})")
    return r


def _tensor_residual(vectors: Array, geometry: ArrayGeometry, method: str) -> float:
    """Tensor RMS (T/m) of a uniform-field recording; NaN for fewer than 4 sensors (no tensor).

    A two-sensor gradiometer (the two-fluxgate gradiometer paper) is calibrated like any array but has no full tensor.
    """
    if geometry.size < 4:
        return float("nan")
    return tensor_rms(gradient(vectors, geometry, method))


def calibrate_array(
    raw: ArrayLike,
    geometry: ArrayGeometry,
    reference_field: float | None = None,
    method: str = DEFAULT_METHOD,
    options: SolveOptions | None = None,
) -> CalibrationResult:
    """Solve the array calibration from raw sets (N, S, 3) in T of a uniform field.

    ``reference_field`` is the total intensity F in T (None or 0: relative calibration,
    F estimated from the data). Raises :class:`ObservabilityError` when the attitudes
    cannot determine it, :class:`InputError` for bad input and
    :class:`CalibrationFailed` when the solution fails its checks.
    """
    t0 = time.perf_counter()
    opts = options or SolveOptions()
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    spec = METHODS[method]
    f_ref = float(reference_field) if reference_field else None
    if spec.needs_reference_field and f_ref is None:
        raise InputError(
            f"method {method!r} ({spec.source}) needs a reference field intensity in T "
            "(--reference-field / reference_field); method 'ml' or 'paired' works without one"
        )
    if f_ref is not None and not (np.isfinite(f_ref) and 1e-7 <= f_ref <= 1e-3):
        raise InputError(f"reference field {f_ref} T is not an Earth-like intensity (1e-7 .. 1e-3 T): units are Tesla")
    r = check_raw(raw, geometry)
    centre_raw = r.mean(axis=1)
    exc = excitation(centre_raw)
    exc.check()

    ref_raw, ref_index = spec.reference(r)
    ref_fit = spec.scalar(ref_raw, f_ref, opts)
    intensity = ref_fit.intensity
    ref_vec = ref_fit.apply(ref_raw)

    matrices, offsets, stds = [], [], []
    for i in range(geometry.size):
        if i == ref_index:
            fit = SensorFit(ref_fit.matrix, ref_fit.offset, ref_fit.std if ref_fit.std is not None else np.full(9, np.nan))
        else:
            fit = spec.aligner(r[:, i], ref_vec, intensity, spec.scalar, opts)
        matrices.append(fit.matrix)
        offsets.append(fit.offset)
        stds.append(fit.std)
    if spec.joint and opts.joint and opts.loss == "linear":
        sol = fix_rotation_gauge(fit_array(r, np.stack(matrices), np.stack(offsets), intensity, robust=False))
        matrices, offsets = list(sol.matrices), list(sol.offsets)
    std = np.stack(stds)
    rel_std = np.concatenate([std[:, :6], std[:, 6:] / intensity], axis=1)
    if np.any(rel_std > opts.max_relative_std):
        raise ObservabilityError(
            f"the calibration is poorly determined (parameter uncertainty up to {np.nanmax(rel_std):.1%} of F); "
            "collect more sets over a wider range of attitudes about at least two axes"
        )
    created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    try:
        cal = ArrayCalibration(geometry, np.stack(matrices), np.stack(offsets), {})
    except InputError as exc:
        raise CalibrationFailed(f"solution rejected: {exc}") from None
    corrected = cal.apply(r)
    tmi_after = tmi_rms(corrected, intensity)
    if np.max(tmi_after) > 0.01 * intensity:
        raise CalibrationFailed(
            f"TMI residual after calibration is {np.max(tmi_after) / NT:.0f} nT (> 1% of F): "
            "the field was not uniform during the manoeuvre, the reference field is wrong, or a sensor is faulty"
        )
    tmi_before = tmi_rms(r, intensity)
    result = CalibrationResult(
        calibration=cal,
        method=method,
        samples=len(r),
        intensity=intensity,
        relative=f_ref is None,
        tmi_before=tmi_before,
        tmi_after=tmi_after,
        tensor_before=_tensor_residual(r, geometry, opts.gradient_method),
        tensor_after=_tensor_residual(corrected, geometry, opts.gradient_method),
        excitation=exc,
        std=std,
        seconds=time.perf_counter() - t0,
    )
    meta = {
        "method": method,
        "source": spec.source,
        "created": created,
        "samples": len(r),
        "reference_field": f_ref or 0.0,
        "intensity": intensity,
        "tmi_rms_before": [float(x) for x in tmi_before],
        "tmi_rms_after": [float(x) for x in tmi_after],
        "tensor_rms_before": result.tensor_before,
        "tensor_rms_after": result.tensor_after,
        "coverage": exc.coverage,
        "summary": result.summary(),
    }
    object.__setattr__(cal, "metadata", meta)
    return result

"""The array calibration pipeline, the same for every method (:mod:`magcal_ros.methods.strategies`).

1. check the input (shapes, finite values, Tesla, enough sets that vary);
2. find spikes with a trimmed closed-form fit per sensor, and start the method on the sets
   whose readings are all clean: the reference (virtual centre sensor or sensor 1) is
   scalar-calibrated and defines the platform frame, every other sensor is brought into it
   by the method's aligner; with a prior calibration, start from it instead;
3. refine jointly over the array (method ``ml``, or any fit with a prior or currents): a
   robust maximum a posteriori fit of every sensor, outliers re-decided until they settle;
4. the covariance of the result (time-correlated noise included) and what it determines
   (:mod:`magcal_ros.core.identifiability`): without a prior an undetermined quantity is a
   refusal naming the rotation that would determine it, and a weak one (determined near the
   attitudes flown only) a warning beside the envelope it bounds; with a prior it is kept;
5. noise-aware quality gates (:mod:`magcal_ros.core.quality`) and the validity envelope.

:func:`calibrate_array` runs these as named stages, each a short function of one state (``_Run``: the
checked input, the start, the current solution and its analysis): ``_checked_input``, ``_choose_sets``,
``_find_spikes``, ``_start_solution``, ``_switch_on_blocks``, ``_fit``, ``_hold_undetermined``,
``_retry_from_spheres``, ``_refuse_undetermined``, ``_refine_on_every_set``, ``_analyse_result``,
``_refuse_what_failed``, ``_gate`` and ``_report``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core import identifiability as ident
from magcal_ros.core import quality, uniformity
from magcal_ros.core.array_fit import (
    JointSolution,
    ParameterPrior,
    Refinement,
    direction_rates,
    fit_array,
    fix_rotation_gauge,
    leave_out_estimates,
    refine_on_all,
)
from magcal_ros.core.attitude_blocks import AttitudeInputs
from magcal_ros.core.batched import sensor_means
from magcal_ros.core.calibration import ArrayCalibration, check_sensor
from magcal_ros.core.forward_model import ForwardModel
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.interference import describe_undetermined, undetermined_channels
from magcal_ros.core.metrics import rms, tensor_rms, tmi_rms
from magcal_ros.core.observability import (
    MIN_SAMPLES,
    MIN_SPREAD,
    Excitation,
    excitation,
)
from magcal_ros.core.prior import DriftModel
from magcal_ros.core.recording import ImuSamples
from magcal_ros.core.scalar_fit import ScalarFit, trimmed_algebraic_fit
from magcal_ros.core.set_reduction import choose_sets, direction_proxy, solve_budget
from magcal_ros.core.temperature import span_with_prior, temperature_span
from magcal_ros.core.tensor import baseline_gradient, gradient
from magcal_ros.core.uncertainty import Covariance, centre_gauge_constraints, covariance
from magcal_ros.core.units import EARTH_FIELD_RANGE, NS_PER_S, NT, check_tesla
from magcal_ros.errors import (
    CalibrationFailed,
    InputError,
    MagcalError,
    ObservabilityError,
)
from magcal_ros.methods import attitude as imu_blocks
from magcal_ros.methods.strategies import DEFAULT_METHOD, METHODS, Method, SensorFit

Array = NDArray[np.float64]

@dataclass(frozen=True)
class SolveOptions:
    """Knobs shared by the methods."""

    loss: str = "linear"
    """Loss of the per-sensor ML start (the joint fit always excludes outliers itself)."""
    loss_scale: float | None = None
    """Residual (T) beyond which a robust start loss down-weights a reading."""
    gradient_method: str = "difference"
    pso_particles: int = 50
    pso_iterations: int = 400
    seed: int | None = 0
    joint: bool = True
    """Refine method ml jointly over the array."""
    robust: bool = True
    """Find and exclude outlying readings in every stage."""
    max_residual: float | None = None
    """Accept a fit whose residual (T, per axis) is below this, whatever the noise (None: noise rule)."""
    drift: DriftModel = field(default_factory=DriftModel)
    """How far a prior calibration may have drifted (partial recalibration)."""
    inclination_deg: float | None = None
    """Field inclination for the validity envelope (None: from the data, assuming level on average)."""
    mounting: Array | None = None
    """(3, 3) sensor-to-platform rotation of a single sensor (None: its own axes made orthogonal)."""
    max_solve_sets: int | None = None
    """Sets the expensive stages use at most (a subset keeping the attitude coverage and the time
    order; one pass over every set then refines the result), so that long recordings cost
    little more than this many sets. None: 1000 per sensor; 0: every set in every stage."""
    progress: Callable[[str], None] | None = None
    """Called with the name of each stage of a long solve as it starts (a progress display)."""
    site_field: Array | None = None
    """(3,) the site's field (T, world NED, e.g. the WMM at --site): with the IMU's orientation its
    direction is held instead of fitted; None: fitted."""


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
    """Per-sensor RMS of ``|corrected| - F`` (T) on the fit data (outliers excluded)."""
    tensor_before: float
    """RMS (T/m) of the gradient the array measures (tensor rows x and y, or the baseline
    gradient) in the uniform field of the manoeuvre; NaN for one sensor."""
    tensor_after: float
    excitation: Excitation
    identifiability: ident.Identifiability
    envelope: ident.Envelope
    noise: Array
    """(S,) noise per axis of each sensor (T), from the fit."""
    outliers: Array
    """(S,) readings excluded as outliers."""
    warnings: list[str]
    seconds: float
    prior: bool = False
    inflation: float = 1.0
    """Widening of the uncertainty by time-correlated noise."""
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def gradient_kind(self) -> str:
        """``tensor``, ``baseline`` or ``none``."""
        return self.calibration.geometry.gradient_kind

    def summary(self) -> str:
        """One line: sets, TMI and gradient residuals before and after, validity, what changed."""
        mode = "relative: no reference, F taken as" if self.relative else "F"
        size = self.calibration.geometry.size
        what = f"{size} sensors" if size > 1 else "1 sensor"
        parts = [
            (f"calibrated {what} from {self.samples} sets (method {self.method}, {mode} {self.intensity / NT:.1f} nT): "
             f"TMI RMS {np.max(self.tmi_before) / NT:.2f} -> {np.max(self.tmi_after) / NT:.3f} nT")
        ]
        if self.gradient_kind != "none":
            label = "tensor" if self.gradient_kind == "tensor" else "baseline gradient"
            parts.append(f"{label} RMS {self.tensor_before / NT:.1f} -> {self.tensor_after / NT:.3f} nT/m")
        parts.append(f"frame: {self.frame()}")
        parts.append(self.envelope.describe())
        if self.prior:
            ana, names = self.identifiability, self.calibration.geometry.names
            parts.append(f"updated ({ident.by_sensor(ana.updated(), names)}), kept from the prior "
                         f"({ident.by_sensor(ana.kept(), names)})")
        if int(self.outliers.sum()):
            parts.append(f"{int(self.outliers.sum())} outlying readings excluded")
        if self.extras.get("uniformity") is not None and self.extras["uniformity"].detected:
            parts.append(f"NOT uniform: {self.extras['uniformity'].gradient / NT:.3g} nT/m across the array")
        if self.extras.get("drift"):
            parts.append(f"offsets drift with time ({', '.join(self.extras['drift'])}): record the sensors' "
                         "temperature or calibrate over a shorter time")
        parts += self.block_notes()
        if self.extras.get("solved_on"):
            used, total, stride = self.extras["solved_on"]  # stride: the refinement's (0: not refined)
            refined = "" if not stride else ", refined on all" + (
                f" (outliers on every set, the normal equations of 1 set in {stride})" if stride > 1 else "")
            parts.append(f"solved on {used} of {total} sets (runs of consecutive sets chosen to keep the attitude "
                         f"coverage and the time span){refined}")
        parts.append(f"coverage {self.excitation.coverage:.0%}")
        return ", ".join(parts)

    def frame(self) -> str:
        """The frame the corrected outputs are in, in a few words (:meth:`frame_note` says more)."""
        cal = self.calibration
        if cal.rotated:
            return f"the IMU's ({cal.frame_id or 'its frame'})"
        if cal.geometry.size == 1:
            return "platform frame (mounting given)" if self.extras.get("mounting") else "sensor axes made orthogonal"
        return "the array's (the sensors' mean axes)"

    def frame_note(self) -> str:
        """What the outputs' frame is and how to have the vehicle's: the sentence the answer and the file
        carry. An array's own frame is its virtual centre sensor's, the mean of its sensors' axes: it
        differs from the vehicle's by the sensors' mean misalignment (a degree or two when mounted by
        hand), so a heading taken from ``field`` is off by as much until an IMU or a known mounting turns it."""
        cal = self.calibration
        if cal.rotated:
            frame = cal.frame_id or "(the recording names none: magcal correct --frame-id, or frame_id in the file)"
            how = "was fitted from its orientations" if self.extras.get("imu") is not None else \
                "is kept from the running or prior calibration (no IMU in this solve)"
            return (f"outputs in the IMU's frame {frame}: output_rotation (array to IMU) {how}, so vectors, "
                    "field and gradient are in the vehicle's navigation frame")
        if cal.geometry.size == 1:
            if self.extras.get("mounting"):
                return "output in the platform frame: the given mounting turns the sensor's corrected axes into it"
            return ("output in the sensor's own axes made orthogonal, not the vehicle's: give its mounting (magcal "
                    "--mounting ROLL,PITCH,YAW) or calibrate with the vehicle's IMU for the vehicle's frame")
        return ("outputs in the array's own frame: the mean of the sensors' axes (a virtual centre sensor), not the "
                "vehicle's: they differ by the sensors' mean misalignment, typically 1-2 deg, so a heading from the "
                "field is off by as much; calibrate with the vehicle's IMU (magcal --imu, the calibration node's "
                "imu_topic) to have every output in its frame, or put a known rotation array -> vehicle in the "
                "file's output_rotation and frame_id")

    def lags(self) -> list[str]:
        """``mag3 reads 5.00 +- 0.01 ms late`` for each sensor whose lag behind the first is significant
        (beyond :data:`LAG_SIGMAS` sigma and :data:`MIN_LAG` s)."""
        out = []
        for q in significant_lags(self.identifiability):
            side = "late" if q.value > 0 else "early"
            out.append(f"{q.sensor} reads {abs(q.value):.2f} +- {q.sigma:.2g} ms {side}")
        return out

    def block_notes(self) -> list[str]:
        """What the temperature and lag blocks found, in words, for the summary."""
        notes = []
        lags = self.lags()
        if lags:
            first = self.calibration.geometry.names[0]
            notes.append(f"time offsets (relative to {first}, applied by correct and the correction node): "
                         + "; ".join(lags))
        span = self.extras.get("temperature_range")
        if span is not None and self.calibration.temperature_reference is not None:
            notes.append(f"temperature terms fitted over {span[0]:.1f}..{span[1]:.1f} C (reference "
                         f"{self.calibration.temperature_reference:.1f} C)")
        elif span is not None:
            notes.append(f"no temperature term significant over {span[0]:.1f}..{span[1]:.1f} C (each within "
                         f"{TEMPERATURE_SIGMAS:g} sigma of zero): none stored, so the sensors' temperatures are not needed")
        held = self.identifiability.held()
        if held:
            notes.append("not determined, held at zero: " + ", ".join(f"{q.sensor} {q.name}" for q in held[:8])
                         + (" ..." if len(held) > 8 else ""))
        notes += list(self.extras.get("block_notes", ()))
        return notes


def check_raw(raw: ArrayLike, geometry: ArrayGeometry) -> Array:
    """Raw sets as (N, S, 3) finite floats in Tesla, or :class:`InputError`."""
    r = np.asarray(raw, dtype=float)
    if r.ndim != 3 or r.shape[1:] != (geometry.size, 3):
        raise InputError(f"raw sets must have shape (N, {geometry.size}, 3), got {r.shape}")
    finite = np.isfinite(r)
    if not finite.all():
        bad = ~np.all(finite, axis=(1, 2))
        raise InputError(f"{int(bad.sum())} sets contain NaN or infinite values (first at index {int(np.argmax(bad))})")
    check_tesla(r, geometry.names, "raw sets")
    return r


def _gradient_residual(vectors: Array, geometry: ArrayGeometry, method: str) -> float:
    """RMS (T/m) of what the array measures of the gradient in a uniform field (should be 0)."""
    kind = geometry.gradient_kind
    if kind == "tensor":
        if method == "difference" and geometry.cross_layout() is None:
            method = "least_squares"  # the summary of a non-cross array: the calibration does not depend on it
        return tensor_rms(gradient(vectors, geometry, method))
    if kind == "baseline":
        return float(rms(baseline_gradient(vectors, geometry)))
    return float("nan")


def _order(stamps: ArrayLike | None, n: int) -> NDArray[np.int64]:
    if stamps is None:
        return np.arange(n)
    s = np.asarray(stamps)
    if s.shape != (n,):
        raise InputError(f"stamps must have one entry per set ({n}), got {s.shape}")
    return np.argsort(s, kind="stable")


def _start(spec: Any, r: Array, clean: Array, f_ref: float | None, opts: SolveOptions) -> tuple[Array, Array, float]:
    """The method's own solution on the clean sets: matrices (S, 3, 3), offsets (S, 3), F."""
    rc = r[clean]
    ref_raw, ref_index = spec.reference(rc)
    ref_fit = spec.scalar(ref_raw, f_ref, opts)
    intensity = ref_fit.intensity
    ref_vec = ref_fit.apply(ref_raw)
    fits = []
    for i in range(r.shape[1]):
        if i == ref_index:
            fits.append(SensorFit(ref_fit.matrix, ref_fit.offset, np.full(9, np.nan)))
        else:
            fits.append(spec.aligner(rc[:, i], ref_vec, intensity, spec.scalar, opts))
    return np.stack([f.matrix for f in fits]), np.stack([f.offset for f in fits]), intensity


def _unit_mean_gain(matrices: Array, intensity: float) -> tuple[Array, float]:
    """A relative start rescaled so that the sensors' mean gain is 1: ``(M / g, F / g)``, ``g`` the
    geometric mean of ``|det M_i|^(1/3)``. Without a reference only ``M F`` is determined; the raw
    readings' own scale (a fluxgate's gain is within percent of 1) then fixes ``F``. The scalar fit's
    relative ``F`` (the spread of the readings about their centroid) is the field's only when the
    manoeuvre covers the sphere: yaw circles put the centroid on the vertical field and measure
    just the horizontal component. Unchanged when a matrix is singular (a start that failed)."""
    det = np.abs(np.linalg.det(matrices))
    if not (np.all(np.isfinite(det)) and np.all(det > 0)):
        return matrices, intensity
    g = float(np.exp(np.mean(np.log(det)) / 3.0))
    return matrices / g, intensity / g


def _start_directions(r: Array, matrices: Array, offsets: Array) -> Array:
    """(N, 3) unit field direction of each set from a start: the mean of the sensors' corrections."""
    b = np.einsum("sij,nsj->nsi", matrices, r - offsets).mean(axis=1)
    return b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)


def _crude_start(r: Array, f: float | None) -> tuple[Array, Array, float]:
    """A start that always exists: unit gains, offsets at each sensor's centroid."""
    offsets = r.mean(axis=0)
    norms = np.linalg.norm(r - offsets, axis=2)
    intensity = f if f else float(np.median(norms))
    gains = intensity / np.maximum(np.median(norms, axis=0), 1e-300)
    return gains[:, None, None] * np.eye(3)[None], offsets, intensity


def _sensor_like(matrix: Array, offset: Array, quadric_ratio: float) -> bool:
    """True when a closed-form correction is one a sensor can have (:func:`check_sensor`, positive
    determinant) with gains within :data:`START_SPREAD` of each other, or any gains when the manoeuvre
    determines the quadric well (``quadric_ratio``, :class:`Excitation`'s, at least
    :data:`START_QUADRIC_RATIO`): a start the joint fit can take as it is (a stretched one from a
    narrow manoeuvre, a wobbly yaw circle, comes from a quadric the closed form got astray)."""
    try:
        check_sensor("start", matrix, offset)
    except InputError:
        return False
    sv = np.linalg.svd(matrix, compute_uv=False)
    return bool(np.linalg.det(matrix) > 0 and (sv[0] < START_SPREAD * sv[-1] or quadric_ratio >= START_QUADRIC_RATIO))


START_SPREAD: float = 1.5
"""Largest ratio of a one-sensor closed-form start's gains for the joint fit to start from it directly
after a narrow manoeuvre."""
START_QUADRIC_RATIO: float = 0.1
"""A manoeuvre whose quadric design's 9th/1st singular value reaches this determines a closed-form start
whatever its gains (a consumer sensor's differ by 2x): a wide tumble gives 0.15-0.3, a yaw circle with
20-45 deg of wobble 0.01-0.05."""


def _plausible(sol: JointSolution, geometry: ArrayGeometry) -> bool:
    """True when every sensor's solved correction is one a sensor can have (no collapsed gains)."""
    try:
        for name, m, o in zip(geometry.names, sol.matrices, sol.offsets):
            check_sensor(name, m, o)
    except InputError:
        return False
    return True


def _sphere_start(r: Array, clean: Array, f: float | None) -> tuple[Array, Array, float]:
    """A start that noisy, narrow manoeuvres cannot collapse: each sensor's best sphere through
    its clean readings (isotropic gain, offset at the centre); the centroid where a sphere does
    not fit."""
    _, crude_o, _ = _crude_start(r, f)
    centres, radii = crude_o.copy(), np.linalg.norm(r - crude_o, axis=2).mean(axis=0)
    for i in range(r.shape[1]):
        x = r[clean, i] if clean.sum() >= 10 else r[:, i]
        a = np.column_stack([2.0 * x, np.ones(len(x))])
        sol, *_ = np.linalg.lstsq(a, np.sum(x * x, axis=1), rcond=None)
        r2 = sol[3] + sol[:3] @ sol[:3]
        if np.all(np.isfinite(sol)) and r2 > 0:
            centres[i], radii[i] = sol[:3], np.sqrt(r2)
    intensity = f if f else float(np.median(radii))
    gains = intensity / np.maximum(radii, 1e-300)
    return gains[:, None, None] * np.eye(3)[None], centres, intensity


def _prior_start(prior: ArrayCalibration, geometry: ArrayGeometry, r: Array, f_ref: float | None,
                 channels: tuple[str, ...]) -> tuple[Array, Array, Array, float]:
    """A start at the prior: matrices (S, 3, 3), offsets (S, 3) T, interference (S, 3, m) T/A of
    ``channels`` (0 for channels the prior does not know) and F (given, or the median corrected norm)."""
    idx = [prior.geometry.names.index(nm) for nm in geometry.names if nm in prior.geometry.names]
    if len(idx) != geometry.size:
        missing = [nm for nm in geometry.names if nm not in prior.geometry.names]
        raise InputError(f"the prior calibration has no sensor {', '.join(missing)}")
    interference = np.zeros((geometry.size, 3, len(channels)))
    for c, name in enumerate(channels):
        if name in prior.channels:
            interference[:, :, c] = prior.interference[idx][:, :, prior.channels.index(name)]  # type: ignore[index]
    matrices, offsets = prior.matrices[idx], prior.offsets[idx]
    if f_ref:
        intensity = f_ref
    else:  # the prior's correction with the currents off
        intensity = float(np.median(np.linalg.norm(np.einsum("sij,nsj->nsi", matrices, r - offsets), axis=2)))
    return matrices, offsets, interference, intensity


def _prior_of(prior: ArrayCalibration | None, geometry: ArrayGeometry, f: float, channels: tuple[str, ...],
              opts: SolveOptions, blocks: BlockInputs | None = None) -> ParameterPrior | None:
    model = None if blocks is None else blocks.model(geometry.size, len(channels))
    if prior is not None and blocks is not None and blocks.reference is not None:
        prior = prior.at_reference(blocks.reference)  # its matrices and offsets where the fit's hold
    return None if prior is None else opts.drift.prior(prior, geometry, f, channels, model)


MIN_TEMPERATURE_SPAN: float = 1.0
"""Sensor temperatures spanning less than this (K) determine no temperature coefficient: the
temperature block is left out (and the summary says why)."""
MAX_LAG_STEP: float = 0.15
"""The lag block needs a continuous motion: the field direction may change by at most this
(rad, median) between consecutive sets."""
LAG_SIGMAS: float = 3.0
"""A sensor's lag is reported when it exceeds this many of its 1-sigma ..."""
MIN_LAG: float = 5e-5
"""... and this (s): 0.05 ms moves the field by 2.5 nT at 1 rad/s."""


def significant_lags(ana: ident.Identifiability) -> list[ident.Quantity]:
    """The ``time offset`` quantities (ms) beyond :data:`LAG_SIGMAS` sigma and :data:`MIN_LAG`: the
    lags a calibration stores and applies (the others are 0: a sensor read on time is synchronised
    exactly, never interpolated for a lag that is only noise)."""
    return [q for q in ana.quantities if q.name == "time offset" and q.status != "held"
            and abs(q.value) > max(LAG_SIGMAS * q.sigma, MIN_LAG * 1e3)]


TEMPERATURE_SIGMAS: float = 3.0
"""Temperature terms are stored when at least one exceeds this many of its 1-sigma."""


def significant_temperature_terms(ana: ident.Identifiability) -> bool:
    """True when any offset or gain per kelvin is beyond :data:`TEMPERATURE_SIGMAS` sigma: the
    calibration then carries the temperature terms (and needs the sensors' temperatures); else
    none (a correction that waited for temperatures to apply terms that are only noise)."""
    return any(q.name.startswith(("offset tempco", "gain tempco")) and q.status != "held"
               and abs(q.value) > TEMPERATURE_SIGMAS * q.sigma for q in ana.quantities)


def _stored_time_offsets(ana: ident.Identifiability, names: tuple[str, ...], offsets: Array | None) -> Array | None:
    """(S,) s: the fitted lags where significant, else 0; None without a lag block."""
    if offsets is None:
        return None
    keep = {q.sensor for q in significant_lags(ana)}
    return np.array([t if n in keep else 0.0 for n, t in zip(names, offsets)])


HOLD_ROUNDS: int = 3
"""Refits at most, each holding at zero the temperature and lag quantities still undetermined."""


@dataclass(frozen=True)
class BlockInputs:
    """What the temperature and lag blocks of the forward model need, per set."""

    temperatures: Array | None = None
    """(N, S) sensor temperature minus :attr:`reference` (K); None: no temperature block."""
    reference: float | None = None
    """Reference temperature (deg C)."""
    times: Array | None = None
    """(N,) s from the first set; None: no lag block."""
    held: NDArray[np.bool_] | None = None
    """(S, P) parameters held at zero (undetermined temperature or lag quantities)."""
    notes: tuple[str, ...] = ()
    """Why a block was left out, for the summary."""
    attitude: AttitudeInputs | None = None
    """The IMU's attitudes at the sets (the global blocks); None: no IMU."""

    def model(self, sensors: int, channels: int) -> ForwardModel:
        """The forward model these inputs switch on."""
        temperature, lag = self.temperatures is not None, self.times is not None and sensors > 1
        if self.attitude is not None:
            return self.attitude.model(sensors, channels, temperature, lag)
        return ForwardModel(sensors, channels, temperature, lag)

    def fit_options(self, keep: Any = slice(None)) -> dict[str, Any]:
        """Keyword arguments of :func:`~magcal_ros.core.array_fit.fit_array` for the sets ``keep``."""
        return {"temperatures": None if self.temperatures is None else self.temperatures[keep],
                "times": None if self.times is None else self.times[keep], "held": self.held,
                "attitude": None if self.attitude is None else self.attitude.take(keep)}


def block_inputs(temperatures: ArrayLike | None, stamps: ArrayLike | None, directions: Array, sensors: int,
                 order: NDArray[np.int64], prior_terms: bool = False) -> BlockInputs:
    """Which optional blocks the data can feed: temperatures (N, S) deg C spanning at least
    :data:`MIN_TEMPERATURE_SPAN` (any span where ``prior_terms``: the prior's temperature terms are kept, the
    sets moving them only as far as they determine); stamps (N,) ns of sets that follow a continuous motion
    (``directions`` (N, 3) from the start, two or more sensors)."""
    n = len(directions)
    notes: list[str] = []
    dtemp = reference = None
    if temperatures is not None:
        t = np.asarray(temperatures, dtype=float)
        if t.ndim == 1:
            t = np.repeat(t[:, None], sensors, axis=1)
        if t.shape != (n, sensors) or not np.all(np.isfinite(t)):
            raise InputError(f"temperatures must be finite, one per set and sensor ({n}, {sensors}) deg C, "
                             f"got shape {t.shape}")
        span = float(t.max() - t.min())
        if span < MIN_TEMPERATURE_SPAN and not prior_terms:
            notes.append(f"temperature span {span:.1f} K: too small to determine temperature coefficients "
                         f"(needs {MIN_TEMPERATURE_SPAN:g} K); none fitted")
        else:
            reference = float(np.round(np.median(t), 1))
            dtemp = t - reference
    times = None
    if stamps is not None and sensors > 1 and n >= 10:
        d = directions[order]
        step = float(np.median(np.arccos(np.clip(np.sum(d[1:] * d[:-1], axis=1), -1.0, 1.0))))
        if quality.in_time_order(d) and step < MAX_LAG_STEP:
            st = np.asarray(stamps).astype(np.int64)
            times = (st - st.min()).astype(float) / NS_PER_S
    return BlockInputs(dtemp, reference, times, None, tuple(notes))


def _holdable_undetermined(ana: ident.Identifiability, model: ForwardModel, names: tuple[str, ...],
                           held: NDArray[np.bool_] | None) -> NDArray[np.bool_] | None:
    """(S, P) the held parameters plus those of temperature and lag quantities now undetermined
    (None when nothing new is to be held)."""
    out = np.zeros((model.sensors, model.size), bool) if held is None else held.copy()
    new = False
    for q in ana.undetermined():
        index = ident.held_parameter(q.name, model)
        if index is not None and not out[names.index(q.sensor), index]:
            out[names.index(q.sensor), index] = True
            new = True
    return out if new else None


JACKKNIFE_BLOCKS: int = 8
"""Time blocks of the delete-one-block jackknife that checks the covariance of a recording."""
JACKKNIFE_MIN_SETS: int = 400
"""Recordings shorter than this are not jackknifed."""

def _jackknife_inflation(raw: Array, sol: JointSolution, order: NDArray[np.int64], currents: Array,
                         prior: ParameterPrior | None, cov: Array, blocks: BlockInputs) -> float:
    """How much wider a delete-one-block jackknife says the parameters scatter than ``cov`` (>= 1).

    Real recordings change slowly (temperature, motion, coverage from one minute to the
    next); the block-to-block scatter of the solution shows what the residuals' own
    correlation cannot. Median of the per-parameter variance ratios, parameters the data
    determine only. Each block's refit is one Gauss-Newton step from the solution, the IMU's global
    blocks with the sensors' (:func:`~magcal_ros.core.array_fit.leave_out_estimates`; on tumbles with
    correlated noise the factors of full refits were within 3 %, at an eighth of the cost).
    """
    options = blocks.fit_options()
    est = leave_out_estimates(sol, raw, jackknife_parts(order),
                              currents if sol.model.channels else None, prior,
                              temperatures=options["temperatures"], times=options["times"],
                              gauge=centre_gauge_constraints(sol.w, sol.model.size) if prior is None else None)
    return _jackknife_factor(est, cov, prior)


def jackknife_parts(order: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    """The delete-one-block jackknife's parts of sets in time ``order``: :data:`JACKKNIFE_BLOCKS` blocks."""
    return list(np.array_split(order, JACKKNIFE_BLOCKS))


def _jackknife_factor(est: Array, cov: Array, prior: ParameterPrior | None) -> float:
    """The median ratio of the delete-one-block scatter of the estimates ``est`` (K, P) to the
    variances of ``cov``, over the parameters the data determine (>= 1)."""
    var_jack = (len(est) - 1) / len(est) * np.sum((est - est.mean(axis=0)) ** 2, axis=0)
    var_model = np.diag(cov)
    good = (var_model > 0) & (var_jack > 0)
    if prior is not None:  # parameters the prior holds do not scatter; judge the data's ones
        prec = prior.precision().reshape(-1)
        good &= var_model < 0.25 / np.maximum(prec, 1e-300)
    if good.sum() < 3:
        return 1.0
    return float(max(1.0, np.median(var_jack[good] / var_model[good])))


@dataclass(frozen=True)
class _AllSets:
    """Every set of a long recording whose expensive stages ran on a subset."""

    raw: Array
    currents: Array
    stamps: Array | None
    temperatures: ArrayLike | None

    @property
    def count(self) -> int:
        return len(self.raw)


def _refine(sol: JointSolution, full: _AllSets, prior: ParameterPrior | None, blocks: BlockInputs,
            with_channels: bool, gauge: bool) -> Refinement:
    """The subset's solution refined by one pass over every set (same blocks, same held
    quantities), with the delete-one-block jackknife of every set in time order."""
    n, s = full.raw.shape[:2]
    temps = None
    if blocks.temperatures is not None and full.temperatures is not None:
        t = np.asarray(full.temperatures, dtype=float)
        temps = (np.repeat(t[:, None], s, axis=1) if t.ndim == 1 else t) - blocks.reference
    times = None
    if blocks.times is not None and full.stamps is not None:
        st = full.stamps.astype(np.int64)
        times = (st - st.min()).astype(float) / NS_PER_S
    parts = jackknife_parts(_order(full.stamps, n))
    out = refine_on_all(sol, full.raw, full.currents if with_channels else None, prior, temperatures=temps,
                        times=times, gauge=centre_gauge_constraints(sol.w, sol.model.size) if gauge else None,
                        parts=parts)
    return replace(out, solution=fix_rotation_gauge(out.solution)) if gauge else out


def _analyse(sol: JointSolution, raw: Array, geometry: ArrayGeometry, order: NDArray[np.int64],
             prior: ParameterPrior | None, channels: tuple[str, ...], currents: Array,
             jackknife: bool = True, blocks: BlockInputs | None = None,
             like: Covariance | None = None, leave_out: Array | None = None,
             in_order: bool | None = None) -> tuple[ident.Identifiability, Any]:
    """Covariance (time-correlated, gauge-fixed or prior-held) and identifiability of a solution.

    ``jackknife``: for a recording in time order, widen the covariance by the block jackknife
    (``in_order``: whether it is, :func:`quality.in_time_order` of the directions when None).
    ``like``: the covariance of the subset this solution was refined from: its widening for the
    time correlation applies, and the jackknife is ``leave_out`` (K, P) (every set's, in time order).
    Parameters the fit kept fixed (held at zero, the lag gauge) get no variance.
    """
    blocks = blocks or BlockInputs()
    model = sol.model
    series = sol.residuals[order].reshape(len(order), -1)
    prec = None if prior is None else prior.fitted_to(model).precision().reshape(-1)
    rows = [] if prior is not None else [centre_gauge_constraints(sol.w, model.size)]
    if sol.fixed is not None and sol.fixed.any():
        rows.append(np.eye(model.sensors * model.size)[sol.fixed.reshape(-1)])
    constraints = np.concatenate(rows) if rows else None
    if like is not None:
        like = replace(like, inflation=like.inflation / like.jackknife, jackknife=1.0)
    cov = covariance(sol.information, sol.scores[order], series, prec, constraints, like)
    factor = 1.0
    if in_order is None and jackknife and len(order) >= JACKKNIFE_MIN_SETS:
        in_order = quality.in_time_order(sol.directions[order])
    if jackknife and len(order) >= JACKKNIFE_MIN_SETS and in_order:
        if like is None:
            factor = _jackknife_inflation(raw, sol, order, currents, prior, cov.matrix, blocks)
        elif leave_out is not None and len(leave_out) > 1:
            factor = _jackknife_factor(leave_out, cov.matrix, prior)
    if factor != 1.0:
        cov = replace(cov, matrix=cov.matrix * factor, inflation=cov.inflation * factor, jackknife=factor)
    prior_cov = None if prec is None else np.diag(np.where(prec > 0, 1.0 / np.maximum(prec, 1e-300), 1e30))
    scales = ident.EffectScales(
        np.sqrt(np.mean(currents**2, axis=0)) if currents.size else None,
        None if blocks.temperatures is None else np.sqrt(np.mean(blocks.temperatures**2, axis=0)),
        0.0 if sol.rates is None else float(np.sqrt(np.mean(np.sum(sol.rates**2, axis=1)))),
    )
    ana = ident.analyse(geometry.names, sol.theta, sol.intensity, cov.matrix, sol.sigma, prior_cov, channels,
                        model=model, scales=scales, held=blocks.held)
    return ana, cov


def _manoeuvre_axis(directions: Array) -> tuple[str, float]:
    """The platform axis the field directions turned about, and how flat they were (0: one plane)."""
    exc = excitation(directions)
    return exc.axis_name, exc.thickness


def _named(ana: ident.Identifiability, quantities: list[ident.Quantity]) -> str:
    """``offset z, scale z`` in the analysis' order, at most six (then ``...``)."""
    order = [q.name for q in ana.quantities]
    names = sorted({q.name for q in quantities}, key=order.index)
    return ", ".join(names[:6]) + (" ..." if len(names) > 6 else "")


def _other_axes(axis: str) -> str:
    """``x or y`` for ``z``."""
    return " or ".join(a for a in ("x", "y", "z") if a != axis)


def _refusal(ana: ident.Identifiability, sol: JointSolution, env: ident.Envelope) -> str:
    """Why a manoeuvre is refused, in words: what it leaves undetermined and what to fly."""
    missing = ana.undetermined()
    sensors = sorted({q.sensor for q in missing})
    who = "every sensor" if len(sensors) == len({q.sensor for q in ana.quantities}) else ", ".join(sensors)
    axis, flat = _manoeuvre_axis(sol.directions)
    others = _other_axes(axis)
    if flat < 0.05:
        how = f"the array was rotated about one axis only (about {axis})"
    else:
        how = f"the array turned mostly about {axis} (the rotations about {others} were too small)"
    advice = f"a full calibration also needs a rotation about {others}"
    if axis == "z":
        advice += ": pitch and roll the vehicle, not only yaw"
    envelope = "" if env.pitch_deg <= 0 else f" (as flown it would be {env.describe()})"
    return (f"the manoeuvre does not determine {_named(ana, missing)} of {who}: "
            f"{how}; {advice}{envelope}; or give the previous calibration as a prior to recalibrate only what "
            "this manoeuvre determines")


def _weak_warning(ana: ident.Identifiability, sol: JointSolution, env: ident.Envelope) -> str:
    """What a manoeuvre determined only near the attitudes flown, where the result holds, and what
    to fly to widen it."""
    weak = ana.weak()
    worst = max(weak, key=lambda q: q.effect)
    axis, _ = _manoeuvre_axis(sol.directions)
    others = _other_axes(axis)
    fly = "pitch and roll the vehicle more" if axis == "z" else f"turn it about {others} too"
    where = (f"{env.describe()}" if env.empty else f"{env.describe()} only, outside it the predicted TMI error "
             f"exceeds {ident.ENVELOPE_RATIO:g}x the noise")
    return (f"{_named(ana, weak)} determined only near the attitudes flown "
            f"(the manoeuvre turned mostly about {axis}; worst {worst.describe()}): {where}; to widen it {fly} "
            f"(a rotation about {others})")


# -- interference channels the data cannot determine: not solved, the rest refitted ------------
def _undetermined_channels(ana: ident.Identifiability, directions: Array, u: Array, channels: tuple[str, ...],
                           prior: ArrayCalibration | None) -> list[int]:
    """Channels (indices) whose interference the data cannot determine and no prior holds.

    Those whose identifiability is undetermined, and those whose currents never vary or vary
    in lockstep with another channel or the attitude (an exact degeneracy the covariance's
    pseudo-inverse does not show).
    """
    if not channels:
        return []
    flagged = set(np.flatnonzero(undetermined_channels(u, directions)).tolist())
    names = {f"interference {c} {a}": j for j, c in enumerate(channels) for a in ident.AXES}
    flagged |= {names[q.name] for q in ana.undetermined() + ana.weak() if q.name in names}
    held = set(prior.channels) if prior is not None else set()
    return sorted(j for j in flagged if channels[j] not in held)


def _without_channels(unsolved: list[int], raw: ArrayLike, geometry: ArrayGeometry, reference_field: float | None,
                      method: str, options: SolveOptions | None, prior: ArrayCalibration | None, u: Array,
                      channels: tuple[str, ...], stamps: ArrayLike | None,
                      temperatures: ArrayLike | None = None, imu: ImuSamples | None = None) -> CalibrationResult:
    """The calibration without the ``unsolved`` channels, with a warning naming them."""
    mask = np.isin(np.arange(len(channels)), unsolved)
    note = f"interference not solved (undetermined): {describe_undetermined(channels, u, mask)}"
    keep = [j for j in range(len(channels)) if not mask[j]]
    try:
        result = calibrate_array(raw, geometry, reference_field, method, options, prior, u[:, keep],
                                 tuple(channels[j] for j in keep), stamps, temperatures, imu)
    except MagcalError as exc:
        raise type(exc)(f"{note}; without them: {exc}") from None
    result.warnings.insert(0, note)
    result.calibration.metadata["warnings"] = list(result.warnings)
    result.calibration.metadata["interference_undetermined"] = [channels[j] for j in unsolved]
    return result


def _inclination(opts: SolveOptions, vertical: Array) -> float:
    """Field inclination (rad) for the envelope: given, or from the data assuming level on average
    (``vertical`` (N,): the z component of each set's field direction, platform frame)."""
    if opts.inclination_deg is not None:
        return float(np.radians(opts.inclination_deg))
    return float(np.mean(np.arcsin(_middle(np.clip(vertical, -1.0, 1.0)))))  # (arcsin is monotonic)


def _middle(x: Array) -> Array:
    """The middle value of an odd number of values, the two middle ones of an even number: their mean is
    the median."""
    low, high = (len(x) - 1) // 2, len(x) // 2
    return np.partition(x, [low, high])[low : high + 1]


def _vector_covariances(sol: JointSolution, cov: Array) -> Array:
    """(S, 3, 3) covariance of each corrected vector: noise plus calibration error over the manoeuvre
    (from the sensor block's parameters; the others are small beside them)."""
    s, _, q = sol.w.shape
    p = sol.model.size
    mats = np.linalg.inv(sol.w[:, :, :3])
    d = sol.directions
    phi = np.concatenate([d, np.ones((len(d), 1)), np.zeros((len(d), q - 4))], axis=1)
    moments = phi.T @ phi / len(d)  # (q, q) the mean of phi phi^T over the manoeuvre
    out = np.empty((s, 3, 3))
    for i in range(s):
        # db = -M dW phi F: the mean of J C J^T over the sets is F^2 M (sum over q, r of C_bq,cr E[phi_q phi_r]) M^T
        block = cov[i * p : i * p + 3 * q, i * p : i * p + 3 * q].reshape(3, q, 3, q)
        inner = np.einsum("bqcr,qr->bc", block, moments)
        cal = sol.intensity**2 * mats[i] @ inner @ mats[i].T
        out[i] = sol.sigma[i] ** 2 * np.eye(3) + 0.5 * (cal + cal.T)
    return out


# -- the pipeline, stage by stage ---------------------------------------------------------------
@dataclass(frozen=True)
class _Call:
    """The arguments of :func:`calibrate_array` as the caller gave them (its second solves, without
    undetermined channels or without the reference, call it again with them)."""

    raw: ArrayLike
    geometry: ArrayGeometry
    reference_field: float | None
    method: str
    options: SolveOptions | None
    prior: ArrayCalibration | None
    currents: ArrayLike | None
    channels: tuple[str, ...]
    stamps: ArrayLike | None
    temperatures: ArrayLike | None
    imu: ImuSamples | None


@dataclass
class _Run:
    """What the stages of one :func:`calibrate_array` share: the checked input, the start, the current
    solution and its analysis. The sets are those the expensive stages use: every set, or the subset of a
    long recording (:attr:`full` then holds every set). Frames: raw sensor axes in, platform (array) frame
    out; units T, A, ns."""

    call: _Call
    spec: Method
    opts: SolveOptions
    channels: tuple[str, ...]
    f_ref: float | None
    """Reference intensity (T): given, or the prior's; None: relative (the fit estimates F)."""
    joint: bool
    """The joint fit is the method's last step (method ml, or any with a prior or currents)."""
    t0: float
    """``time.perf_counter()`` at the call."""
    # -- the sets
    r: Array
    """(N, S, 3) raw sets (T, sensor axes)."""
    u: Array
    """(N, m) currents (A) of :attr:`channels`."""
    stamps: ArrayLike | None
    """(N,) int ns, or None."""
    temperatures: ArrayLike | None
    """(N, S) or (N,) deg C, or None."""
    order: NDArray[np.int64]
    """The sets in time order."""
    excitation: Excitation
    """Of every set (before any subset)."""
    clipped: NDArray[np.bool_]
    """(N, S) readings at a sensor's full scale."""
    full: _AllSets | None = None
    # -- the start
    clean_reading: NDArray[np.bool_] = field(init=False)
    """(N, S) readings on their sensor's trimmed closed-form fit (no spike)."""
    clean: NDArray[np.bool_] = field(init=False)
    """(N,) sets whose readings are all clean (every set when too few are)."""
    trimmed: ScalarFit | None = None
    """The last sensor's trimmed closed-form fit; None when it failed, or not robust."""
    matrices: Array = field(init=False)
    """(S, 3, 3) start matrices, raw axes to platform frame."""
    offsets: Array = field(init=False)
    """(S, 3) start offsets (T, raw axes)."""
    intensity: float = field(init=False)
    """Start F (T)."""
    start_interference: Array | None = None
    """(S, 3, m) T/A: the prior's, else None."""
    start_failed: Exception | None = None
    """Why the method's own start failed (the crude start taken instead); None once a start succeeded."""
    # -- the fit
    weights: Array = field(init=False)
    """(N, S) 1 for the readings the fit starts with, 0 for spikes."""
    blocks: BlockInputs = field(default_factory=BlockInputs)
    param_prior: ParameterPrior | None = None
    sol: JointSolution = field(init=False)
    ana: ident.Identifiability = field(init=False)
    cov: Covariance = field(init=False)
    # -- the result
    excluded: Array | None = None
    """(S,) readings excluded on every set (after the refinement), None: from :attr:`sol`'s weights."""
    pass_stride: int = 0
    """The refinement summed the normal equations of one set in this many (0: not refined)."""
    keep: NDArray[np.int64] | None = None
    """The sets of the subset (indices into every set), None: every set."""
    vertical: Array = field(init=False)
    """(N,) z component of each set's field direction (platform frame), for the envelope."""
    smooth: bool = False
    """The field directions follow a continuous motion in time order."""
    unsolved: list[int] = field(default_factory=list)
    """Channels whose interference the data do not determine (solved again without them)."""
    env: ident.Envelope = field(init=False)
    imu: imu_blocks.ImuReport | None = None
    """What the IMU's blocks found (with their 1-sigma), once analysed (stage 11)."""

    @property
    def geometry(self) -> ArrayGeometry:
        return self.call.geometry

    @property
    def free(self) -> bool:
        """No prior: the rotation gauge is fixed, and what the data do not determine is refused."""
        return self.call.prior is None

    @property
    def refines_on_every_set(self) -> bool:
        """A subset's joint solution is refined by a pass over every set (with the IMU's blocks the subset's
        solution stands: the pass has no global blocks)."""
        return self.full is not None and self.fits_jointly and self.blocks.attitude is None

    @property
    def fits_jointly(self) -> bool:
        """The joint fit runs: the method's last step, or in place of a method's start that failed."""
        return self.joint or self.start_failed is not None

    def stage(self, name: str) -> None:
        """Announce a stage of a long solve to :attr:`SolveOptions.progress`."""
        if self.opts.progress:
            self.opts.progress(name)


@dataclass(frozen=True)
class _Gated:
    """A result that passed the quality gates, and what the report says of it."""

    calibration: ArrayCalibration
    thermal: bool
    """The temperature terms are significant (stored)."""
    mounted: bool
    """A single sensor's mounting rotation was applied."""
    corrected: Array
    """(N, S, 3) the sets corrected (T, platform frame), each sensor at the set's instant."""
    tmi_residual: Array
    """(N, S) ``|corrected| - F`` (T)."""
    uniformity: Any
    """:class:`~magcal_ros.core.uniformity.Uniformity` or None."""
    verdict: quality.Verdict
    warnings: list[str]


def _reference_intensity(call: _Call, spec: Method) -> float | None:
    """F (T): given, else the prior's, else None (relative); :class:`InputError` when the method needs it or
    it is not an Earth-like intensity in Tesla."""
    f_ref = float(call.reference_field) if call.reference_field else None
    if f_ref is None and call.prior is not None and call.prior.metadata.get("intensity"):
        f_ref = float(call.prior.metadata["intensity"])
    if spec.needs_reference_field and f_ref is None:
        raise InputError(
            f"method {call.method!r} ({spec.source}) needs a reference field intensity in T "
            "(--reference-field / reference_field); method 'ml' or 'paired' works without one"
        )
    low, high = EARTH_FIELD_RANGE
    if f_ref is not None and not (np.isfinite(f_ref) and low <= f_ref <= high):
        raise InputError(f"reference field {f_ref} T is not an Earth-like intensity ({low:g} .. {high:g} T): "
                         "units are Tesla")
    return f_ref


def _check_manoeuvre(r: Array, exc: Excitation, prior: ArrayCalibration | None) -> None:
    """:class:`ObservabilityError` for too few sets (N, S, 3), or readings that barely change without a prior."""
    n = len(r)
    if n < MIN_SAMPLES:
        axis, flat = _manoeuvre_axis(sensor_means(r))
        one_axis = f"; and the array was rotated about one axis only (about {axis}): turn it about " + " or ".join(
            a for a in "xyz" if a != axis) + " too" if flat < 0.05 else ""
        raise ObservabilityError(f"only {n} synchronized sets; need at least {MIN_SAMPLES}, collected while turning "
                                 f"the array about at least two axes{one_axis}")
    if exc.spread[0] < MIN_SPREAD and prior is None:
        raise ObservabilityError("the readings barely change (the array hardly rotated); turn it through large "
                                 "angles about at least two axes")


def _checked_input(call: _Call, t0: float) -> _Run:
    """Stage 1, check the input: a known method, raw sets (N, S, 3) finite in T, currents (N, m) A one
    column per channel, what needs method ml, the reference intensity, enough sets that vary, no sensor
    saturated. The run's state on every set."""
    opts = call.options or SolveOptions()
    if call.method not in METHODS:
        raise InputError(f"unknown method {call.method!r}; choose one of {', '.join(METHODS)}")
    spec = METHODS[call.method]
    r = check_raw(call.raw, call.geometry)
    n = len(r)
    u = np.zeros((n, 0)) if call.currents is None else np.asarray(call.currents, dtype=float).reshape(n, -1)
    channels = tuple(call.channels)
    if u.shape[1] != len(channels) or not np.all(np.isfinite(u)):
        raise InputError(f"currents must be finite, one column per channel ({len(channels)}), got shape {u.shape}")
    joint = (spec.joint and opts.joint) or call.prior is not None or bool(channels)
    if (call.prior is not None or channels) and not spec.joint:
        raise InputError(f"a prior calibration and current channels need method 'ml', not {call.method!r}")
    f_ref = _reference_intensity(call, spec)
    order = _order(call.stamps, n)
    exc = excitation(sensor_means(r))
    _check_manoeuvre(r, exc, call.prior)
    clipped, saturated = quality.saturation(call.geometry.names, r)
    if saturated:
        raise CalibrationFailed(saturated)
    return _Run(call, spec, opts, channels, f_ref, joint, t0, r, u, call.stamps, call.temperatures, order, exc,
                clipped)


def _choose_sets(run: _Run) -> None:
    """Stage 2, choose the sets: a long recording's expensive stages run on a subset keeping the attitude
    coverage and the time order (:func:`choose_sets`); every set is kept in :attr:`_Run.full`. The IMU's
    blocks too (their attitudes taken on every set, then the subset's)."""
    n, s = run.r.shape[:2]
    budget = solve_budget(s, run.opts.max_solve_sets)
    if not budget or n <= budget:
        return
    keep = choose_sets(direction_proxy(run.r), run.order, budget)
    run.keep = keep
    stamps = None if run.stamps is None else np.asarray(run.stamps)
    run.full = _AllSets(run.r, run.u, stamps, run.temperatures)
    run.r, run.u, run.clipped = run.r[keep], run.u[keep], run.clipped[keep]
    run.stamps = None if stamps is None else stamps[keep]
    run.temperatures = None if run.temperatures is None else np.asarray(run.temperatures, dtype=float)[keep]
    run.order = _order(run.stamps, len(keep))


def _find_spikes(run: _Run) -> None:
    """Stage 3a: each sensor's trimmed closed-form fit marks its spikes (when robust); the clean sets are
    those without one (every set when fewer than :data:`MIN_SAMPLES` are)."""
    n, s = run.r.shape[:2]
    run.clean_reading = np.ones((n, s), bool)
    if run.opts.robust:
        for i in range(s):
            try:
                run.trimmed, run.clean_reading[:, i] = trimmed_algebraic_fit(run.r[:, i], run.f_ref)
            except (MagcalError, np.linalg.LinAlgError):
                run.trimmed = None  # degenerate data: the identifiability analysis names why
    run.clean = run.clean_reading.all(axis=1)
    if run.clean.sum() < MIN_SAMPLES:
        run.clean[:] = True


def _closed_form_will_do(run: _Run) -> bool:
    """One sensor fitted jointly whose trimmed closed form is a sensor's correction: the joint fit is its
    maximum-likelihood fit, so the method's own start (a scalar fit, then the sensor aligned onto itself)
    would solve it twice over (collapsed, as on a narrow noisy manoeuvre, it will not do)."""
    t = run.trimmed
    return (run.geometry.size == 1 and run.joint and t is not None
            and run.clean_reading[:, 0].sum() >= MIN_SAMPLES and _sensor_like(t.matrix, t.offset,
                                                                              run.excitation.quadric_ratio))


def _start_solution(run: _Run) -> None:
    """Stage 3b, start: the prior; else one sensor's closed form (:func:`_closed_form_will_do`); else the
    method's own solution on the clean sets, the crude start when it fails (remembered in
    :attr:`_Run.start_failed`). A relative start has the sensors' mean gain 1."""
    if run.call.prior is not None:
        run.matrices, run.offsets, run.start_interference, run.intensity = _prior_start(
            run.call.prior, run.geometry, run.r, run.f_ref, run.channels)
        return
    if _closed_form_will_do(run):
        matrices, offsets, intensity = run.trimmed.matrix[None], run.trimmed.offset[None], run.trimmed.intensity
    else:
        try:
            matrices, offsets, intensity = _start(run.spec, run.r, run.clean, run.f_ref, run.opts)
        except (MagcalError, np.linalg.LinAlgError, ValueError) as exc:
            run.start_failed = exc
            matrices, offsets, intensity = _crude_start(run.r, run.f_ref)
    if run.f_ref is None:
        matrices, intensity = _unit_mean_gain(matrices, intensity)
    run.matrices, run.offsets, run.intensity = matrices, offsets, intensity


def _switch_on_blocks(run: _Run) -> None:
    """Stage 3c: the start's weights, the model's optional blocks the data can feed (temperatures, lags,
    the IMU's attitudes; joint fit only) and the prior's parameters."""
    run.weights = run.clean_reading.astype(float)
    imu, n, s = run.call.imu, run.r.shape[0], run.r.shape[1]
    if run.fits_jointly:
        prior = run.call.prior
        run.blocks = block_inputs(run.temperatures, run.stamps, _start_directions(run.r, run.matrices, run.offsets),
                                  s, run.order, prior is not None and prior.has_temperature_terms)
    elif run.temperatures is not None:
        raise InputError(f"temperature terms need method 'ml', not {run.call.method!r}")
    if imu is not None and (imu.has_orientation or imu.has_angular_velocity):
        if not run.fits_jointly:
            raise InputError(f"calibrating with the IMU needs method 'ml', not {run.call.method!r}")
        imu_blocks.check_follows(imu, run.r)
        every = run.full is not None  # the attitudes of every set (a gyro integrates from set to set), then the subset's
        att = imu_blocks.attitude_for(imu, run.full.stamps if every else run.stamps, run.geometry,
                                      run.full.count if every else n, run.opts.site_field)
        att = imu_blocks.with_mounting_prior(att, run.call.prior)
        run.blocks = replace(run.blocks, attitude=att if att is None or run.keep is None else att.take(run.keep))
    run.param_prior = _prior_of(run.call.prior, run.geometry, run.intensity, run.channels, run.opts, run.blocks)


def _solve(run: _Run, matrices: Array, offsets: Array, intensity: float, interference: Array | None,
           start: Array | None = None) -> JointSolution:
    """The joint fit from a start (matrices (S, 3, 3), offsets (S, 3) T, F T, interference (S, 3, m) T/A or
    None; ``start`` the parameters (S, P) instead), with the run's blocks and prior; gauge fixed when free."""
    # the jackknife's parts when it will run on these sets (without a pass over every set): their shares of the
    # normal equations come with the fit's last evaluation
    on_these = not run.refines_on_every_set
    parts = jackknife_parts(run.order) if on_these and len(run.order) >= JACKKNIFE_MIN_SETS else None
    fitted = fit_array(run.r, matrices, offsets, intensity, run.u, interference, run.param_prior, run.weights,
                       robust=run.opts.robust, start=start, parts=parts, **run.blocks.fit_options())
    return fix_rotation_gauge(fitted) if run.free else fitted


def _quick_analysis(run: _Run, sol: JointSolution) -> tuple[ident.Identifiability, Covariance]:
    """What ``sol`` determines, without the jackknife (which only widens)."""
    return _analyse(sol, run.r, run.geometry, run.order, run.param_prior, run.channels, run.u, jackknife=False,
                    blocks=run.blocks)


def _fit(run: _Run) -> None:
    """Stage 4, fit: the joint fit from the start, or (a method without it) the method's own solution
    evaluated in its own frame; then what it determines."""
    if run.fits_jointly:
        run.sol = _solve(run, run.matrices, run.offsets, run.intensity, run.start_interference)
    else:
        run.sol = fit_array(run.r, run.matrices, run.offsets, run.intensity, run.u, None, None, run.weights,
                            robust=False, iterations=0)
    run.ana, run.cov = _quick_analysis(run, run.sol)


def _hold_undetermined(run: _Run) -> None:
    """Stage 5: temperature and lag quantities the data do not determine held at zero and the rest refitted,
    at most :data:`HOLD_ROUNDS` times."""
    for _ in range(HOLD_ROUNDS):
        held = _holdable_undetermined(run.ana, run.sol.model, run.geometry.names, run.blocks.held)
        if held is None:
            return
        run.blocks = replace(run.blocks, held=held)
        sol = run.sol
        run.sol = _solve(run, sol.matrices, sol.offsets, sol.intensity, None, start=np.where(held, 0.0, sol.theta))
        run.ana, run.cov = _quick_analysis(run, run.sol)


def _retry_from_spheres(run: _Run) -> None:
    """Stage 6: a closed-form start on noisy, narrow data can land on a collapsed ellipsoid the joint fit
    cannot leave (or the method's start failed, or something is undetermined): without a prior, fit again
    from spheres (:func:`_sphere_start`) and keep that if it is plausible and determines more."""
    badness = (run.start_failed is not None or not _plausible(run.sol, run.geometry), len(run.ana.undetermined()))
    if not (run.free and run.fits_jointly and any(badness)):
        return
    matrices, offsets, intensity = _sphere_start(run.r, run.clean, run.f_ref)
    if run.f_ref is None:
        matrices, intensity = _unit_mean_gain(matrices, intensity)
    retry = _solve(run, matrices, offsets, intensity, None)
    ana, cov = _quick_analysis(run, retry)
    if _plausible(retry, run.geometry) and (False, len(ana.undetermined())) < badness:
        run.sol, run.ana, run.cov, run.start_failed = retry, ana, cov, None


def _envelope(run: _Run, vertical: Array) -> ident.Envelope:
    """The attitudes where the solution holds (``vertical`` (N,): each set's field direction's z)."""
    sol = run.sol
    return ident.envelope(sol.w, run.cov.matrix, sol.sigma, sol.intensity, _inclination(run.opts, vertical))


def _refuse_undetermined(run: _Run) -> None:
    """Stage 7: without a prior, what the data do not determine is refused (before paying for the
    jackknife), naming the rotation that would determine it."""
    if run.free and run.ana.undetermined():
        raise ObservabilityError(_refusal(run.ana, run.sol, _envelope(run, run.sol.directions[:, 2])))


def _refine_on_every_set(run: _Run) -> tuple[Covariance | None, Array | None]:
    """Stage 8: a subset's joint solution refined by one pass over every set. The subset's covariance and
    the leave-one-block-out estimates (K, P) of every set for the analysis (None, None: not refined)."""
    run.vertical = run.sol.directions[:, 2]
    if not run.refines_on_every_set:
        return None, None
    run.stage(f"refine on all {run.full.count} sets")
    refined = _refine(run.sol, run.full, run.param_prior, run.blocks, bool(run.channels), run.free)
    run.sol, run.excluded, run.vertical = refined.solution, refined.excluded, refined.vertical
    run.pass_stride = refined.stride
    return run.cov, refined.leave_out


def _analyse_result(run: _Run, like: Covariance | None, leave_out: Array | None) -> None:
    """Stage 9, analyse: the result's covariance (time-correlated, jackknifed) and what it determines, and
    the channels whose interference it does not."""
    run.smooth = quality.in_time_order(run.sol.directions[run.order])
    run.ana, run.cov = _analyse(run.sol, run.r, run.geometry, run.order, run.param_prior, run.channels, run.u,
                                blocks=run.blocks, like=like, leave_out=leave_out, in_order=run.smooth)
    run.unsolved = _undetermined_channels(run.ana, run.sol.directions, run.u, run.channels, run.call.prior)


def _refuse_what_failed(run: _Run) -> None:
    """Stage 10: the validity envelope; without a prior what is still undetermined is refused, and a method
    start that failed with no sphere start to replace it is."""
    run.env = _envelope(run, run.vertical)
    if run.free and run.ana.undetermined():
        raise ObservabilityError(_refusal(run.ana, run.sol, run.env))
    if run.start_failed is not None:
        raise CalibrationFailed(f"calibration not possible: {run.start_failed}")


def _mounting(run: _Run) -> Array | None:
    """A single sensor's (3, 3) sensor-to-platform rotation, or None; :class:`InputError` when it is not one."""
    if run.opts.mounting is None:
        return None
    if run.geometry.size != 1:
        raise InputError("a mounting rotation applies to a single sensor; an array defines its own frame")
    mounting = np.asarray(run.opts.mounting, dtype=float)
    if mounting.shape != (3, 3) or not np.allclose(mounting @ mounting.T, np.eye(3), atol=1e-6):
        raise InputError("mounting must be a 3x3 rotation matrix (sensor to platform)")
    return mounting


def _calibration(run: _Run, mounting: Array | None) -> tuple[ArrayCalibration, bool]:
    """The calibration the solution gives (output frame turned by ``mounting``), and whether it carries the
    temperature terms (significant ones, or the prior's); :class:`CalibrationFailed` when it is no sensor's."""
    sol, ana, blocks = run.sol, run.ana, run.blocks
    matrices = sol.matrices if mounting is None else mounting[None] @ sol.matrices
    vector_cov = _vector_covariances(sol, run.cov.matrix)
    if mounting is not None:
        vector_cov = mounting[None] @ vector_cov @ mounting.T[None]
    prior = run.call.prior  # a prior's terms are kept: a window that barely changes temperature keeps them as they were
    thermal = sol.model.temperature and (significant_temperature_terms(ana) or
                                         (prior is not None and prior.has_temperature_terms))
    try:
        cal = ArrayCalibration(
            run.geometry, matrices, sol.offsets, {}, vector_cov, run.channels,
            sol.interference if run.channels else None,
            time_offsets=imu_blocks.with_array_lag(_stored_time_offsets(ana, run.geometry.names, sol.time_offsets),
                                                   run.imu, run.geometry.size),
            temperature_reference=blocks.reference if thermal else None,
            offset_tempco=sol.offset_tempco if thermal else None,
            matrix_tempco=-matrices * sol.gain_tempco[:, None, :] if thermal else None,
            temperature_span=span_with_prior(temperature_span(run.call.temperatures, run.geometry.size),
                                             run.geometry.names, run.call.prior),  # made at, per sensor
            **imu_blocks.output_frame(sol, run.call.prior),
        )
    except InputError as exc:
        raise CalibrationFailed(f"solution rejected: {exc}") from None
    return cal, thermal


def _corrected(run: _Run, cal: ArrayCalibration, thermal: bool) -> Array:
    """(N, S, 3) the sets corrected by ``cal`` (T, array frame, the site gradient's field taken off), every
    sensor brought to the set's instant: what the gates judge."""
    sol, blocks = run.sol, run.blocks
    temps = blocks.temperatures + blocks.reference if thermal else None
    corrected = imu_blocks.without_site_field(cal.apply_array(run.r, run.u if run.channels else None, temps), sol)
    if sol.time_offsets is not None and sol.rates is not None:
        corrected = corrected + sol.intensity * sol.time_offsets[None, :, None] * sol.rates[:, None, :]
    return corrected


def _judge(run: _Run, corrected: Array, tmi_residual: Array) -> tuple[Any, quality.Verdict]:
    """The uniformity of the field over the array and the noise-aware quality gates' verdict;
    :class:`CalibrationFailed` naming the cause when either refuses (with a prior, a reference the data
    disagree with named as the cause when it is)."""
    sol, order, s = run.sol, run.order, run.geometry.size
    implied = None  # the mean sensor gain a given reference implies (None: relative or prior)
    if run.f_ref is not None and run.free:
        implied = float(np.mean(np.abs(np.linalg.det(sol.matrices)) ** (-1.0 / 3.0)))
    uniform = uniformity.check(corrected[order][(sol.weights[order] > 0).all(axis=1)], run.geometry.positions)
    if uniform is not None and uniform.refused and run.opts.max_residual is None:
        raise CalibrationFailed(f"{uniform.describe()}; to accept it anyway give a max residual (magcal "
                                "--max-residual, the calibration node's max_residual)")
    rates = sol.rates
    if rates is None and run.stamps is not None and s > 1:  # (one sensor's direction takes up any lag)
        rates = direction_rates(sol.directions, np.asarray(run.stamps, dtype=float) / NS_PER_S)
    stamps = None if run.stamps is None else np.asarray(run.stamps)[order]
    verdict = quality.judge(run.geometry.names, sol.residuals[order], sol.weights[order], tmi_residual[order],
                            run.r[order], stamps, run.opts.max_residual, implied, sol.intensity,
                            sol.directions[order], run.clipped[order], None if rates is None else rates[order],
                            smooth=run.smooth)
    if verdict.cause:
        call = run.call
        given = (call.raw, call.currents, call.stamps, call.temperatures)
        raise CalibrationFailed(_reference_misfit(given, run.geometry, call.reference_field, call.method,
                                                  call.options, call.prior, run.channels, call.imu)
                                or verdict.cause)
    return uniform, verdict


def _envelope_warning(run: _Run) -> str | None:
    """Without a prior: what the manoeuvre determined only near the attitudes flown, or where the result
    holds when that is not everywhere (None: everywhere)."""
    ana, env = run.ana, run.env
    if ana.weak():
        return _weak_warning(ana, run.sol, env)
    if env.empty:
        return f"{env.describe()}: more sets, or more attitudes, would bring the calibration error below the noise"
    if not env.whole_sphere:
        least = sorted({q.name for q in sorted(ana.quantities, key=lambda q: -q.effect)[:4]})
        return (f"{env.describe()} (least determined: {', '.join(least)}); outside it the predicted TMI "
                f"error exceeds {ident.ENVELOPE_RATIO:g}x the noise")
    return None


def _warnings(run: _Run, verdict: quality.Verdict, uniform: Any) -> list[str]:
    """The gates' warnings, a field that is not quite uniform, the envelope, and a prior's intensity used."""
    warnings = list(verdict.warnings) + ([uniform.describe()] if uniform is not None and uniform.detected else [])
    if run.free:
        note = _envelope_warning(run)
        if note is not None:
            warnings.append(note)
    elif not run.call.reference_field:
        warnings.append(f"used the prior's intensity {run.sol.intensity / NT:.1f} nT: if the site changed, give "
                        "the new reference field")
    return warnings


def _gate(run: _Run) -> _Gated:
    """Stage 11, gate: the calibration (a single sensor's mounting applied), the sets it corrects, the
    uniformity and quality gates, and the warnings."""
    mounting = _mounting(run)
    run.imu = imu_blocks.imu_report(run.sol, run.order, None if run.param_prior is None else
                                    run.param_prior.fitted_to(run.sol.model).precision().reshape(-1))
    cal, thermal = _calibration(run, mounting)
    corrected = _corrected(run, cal, thermal)
    tmi_residual = np.linalg.norm(corrected, axis=2) - run.sol.intensity
    uniform, verdict = _judge(run, corrected, tmi_residual)
    return _Gated(cal, thermal, mounting is not None, corrected, tmi_residual, uniform, verdict,
                  _warnings(run, verdict, uniform))


def _report(run: _Run, gated: _Gated) -> CalibrationResult:
    """Stage 12, report: the result with its diagnostics (residuals before and after, analysis, envelope,
    what the blocks found), and the calibration's provenance."""
    sol, cov, blocks, s = run.sol, run.cov, run.blocks, run.geometry.size
    imu_report = run.imu
    used = sol.weights > 0
    clean_sets = used.all(axis=1)
    span = None if blocks.temperatures is None else (float(blocks.temperatures.min() + blocks.reference),
                                                     float(blocks.temperatures.max() + blocks.reference))
    n = len(run.r)
    result = CalibrationResult(
        calibration=gated.calibration,
        method=run.call.method,
        samples=n if run.full is None else run.full.count,
        intensity=sol.intensity,
        relative=run.f_ref is None,
        tmi_before=tmi_rms(run.r, sol.intensity),
        tmi_after=np.array([rms(gated.tmi_residual[used[:, i], i]) for i in range(s)]),
        tensor_before=_gradient_residual(run.r[clean_sets], run.geometry, run.opts.gradient_method),
        tensor_after=_gradient_residual(gated.corrected[clean_sets], run.geometry, run.opts.gradient_method),
        excitation=run.excitation,
        identifiability=run.ana,
        envelope=run.env,
        noise=sol.sigma,
        outliers=np.sum(~used, axis=0).astype(float) if run.excluded is None else run.excluded,
        warnings=gated.warnings,
        seconds=time.perf_counter() - run.t0,
        prior=not run.free,
        inflation=cov.inflation,
        extras={"mounting": gated.mounted, "bandwidth": cov.bandwidth, "uniformity": gated.uniformity,
                "temperature_range": span, "temperature_stored": gated.thermal,
                "block_notes": blocks.notes + tuple(() if imu_report is None else imu_report.notes()),
                "drift": gated.verdict.drift, "imu": imu_report,
                "solved_on": None if run.full is None else (n, run.full.count, run.pass_stride)},
    )
    object.__setattr__(gated.calibration, "metadata",
                       provenance(result, run.spec.source, run.call.reference_field, gated.verdict))
    return replace(result, seconds=time.perf_counter() - run.t0)


def calibrate_array(
    raw: ArrayLike,
    geometry: ArrayGeometry,
    reference_field: float | None = None,
    method: str = DEFAULT_METHOD,
    options: SolveOptions | None = None,
    prior: ArrayCalibration | None = None,
    currents: ArrayLike | None = None,
    channels: tuple[str, ...] = (),
    stamps: ArrayLike | None = None,
    temperatures: ArrayLike | None = None,
    imu: ImuSamples | None = None,
) -> CalibrationResult:
    """Solve the array calibration from raw sets (N, S, 3) in T of a uniform, constant field.

    ``reference_field``: total intensity F in T (None or 0: relative, or the prior's).
    ``prior``: the previous calibration; undetermined quantities are kept at it (partial
    recalibration, method ``ml``). ``currents`` (N, m) A of ``channels``: their interference
    is estimated too. ``stamps`` (N,) int ns put the sets in time order (default: as given);
    when the sets follow a continuous motion, each sensor's lag relative to the first is
    estimated too. ``temperatures`` (N, S) or (N,) deg C: offsets and gains linear in each
    sensor's temperature are estimated (when the temperatures span enough). ``imu``: the
    vehicle's IMU at each set (orientation and/or gyro): the array-to-IMU rotation, the field's
    direction and (with orientations) a constant site gradient are fitted too
    (:mod:`magcal_ros.methods.attitude`), and every output is in the IMU's frame.
    Raises :class:`ObservabilityError` when the manoeuvre cannot determine the calibration
    (naming what is missing and what to fly), :class:`InputError` for bad input and
    :class:`CalibrationFailed` when the result fails a quality gate (naming the cause).
    """
    t0 = time.perf_counter()
    call = _Call(raw, geometry, reference_field, method, options, prior, currents, channels, stamps, temperatures,
                 imu)
    run = _checked_input(call, t0)
    _choose_sets(run)
    run.stage("start")
    _find_spikes(run)
    _start_solution(run)
    _switch_on_blocks(run)
    run.stage("joint fit")
    _fit(run)
    _hold_undetermined(run)
    _retry_from_spheres(run)
    _refuse_undetermined(run)
    run.stage("uncertainty")
    like, leave_out = _refine_on_every_set(run)
    _analyse_result(run, like, leave_out)
    if run.unsolved:  # solved again from every set as given, without those channels
        every = np.asarray(currents, dtype=float).reshape(np.shape(raw)[0], -1)
        return _without_channels(run.unsolved, raw, geometry, reference_field, method, options, prior, every,
                                 run.channels, stamps, temperatures, imu)
    _refuse_what_failed(run)
    return _report(run, _gate(run))


def _reference_misfit(given: tuple[Any, Any, Any, Any], geometry: ArrayGeometry, reference: float | None, method: str,
                      options: SolveOptions | None, prior: ArrayCalibration | None, channels: tuple[str, ...],
                      imu: ImuSamples | None) -> str | None:
    """Why a recalibration from a prior was refused when the reference intensity is what does not fit: the
    prior keeps gains the manoeuvre cannot determine, so a reference the data disagree with
    leaves a residual no uniform field explains. Solved again without the reference (the intensity the
    prior's kept gains give these data): when that passes the gates, the reference is the cause and the
    intensity the data imply is said; None when it fails too (the first cause stands), or without a prior
    or a given reference."""
    if prior is None or not reference:
        return None
    raw, currents, stamps, temperatures = given
    free = replace(prior, metadata={k: v for k, v in prior.metadata.items() if k != "intensity"})
    try:
        result = calibrate_array(raw, geometry, None, method, options, free, currents, channels, stamps, temperatures, imu)
    except MagcalError:
        return None
    implied = result.intensity
    return (f"the reference intensity {reference / NT:.0f} nT does not fit the data with the gains the prior "
            f"keeps (this manoeuvre does not determine them): they imply about {implied / NT:.0f} nT (the reference is "
            f"{reference / implied - 1.0:+.1%} off); check --reference-field/--site (or the calibration node's "
            "reference_field/site), or fly pitch and roll as well so that the gains are determined again")


def provenance_key(name: str) -> str:
    """A quantity name as a ROS parameter key: ``offset z`` -> ``offset_z``,
    ``interference thruster1/battery x`` -> ``interference_thruster1_battery_x``."""
    return name.replace("non-orthogonality", "nonorthogonality").replace("-", "").replace(" ", "_").replace("/", "_")


def provenance(result: CalibrationResult, source: str, reference_field: float | None,
               verdict: quality.Verdict) -> dict[str, Any]:
    """The calibration file's provenance block (ROS parameter names and types only)."""
    ana = result.identifiability
    uncertainty: dict[str, dict[str, float]] = {}
    for q in ana.quantities:
        uncertainty.setdefault(q.sensor, {})[f"{provenance_key(q.name)}_{q.unit.replace('/', '_per_')}"] = q.sigma
    names = result.calibration.geometry.names
    meta: dict[str, Any] = {
        "method": result.method,
        "source": source,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),  # noqa: UP017 (datetime.UTC: Python 3.11+)
        "samples": result.samples,
        "reference_field": float(reference_field or 0.0),
        "intensity": result.intensity,
        "tmi_rms_before": [float(x) for x in result.tmi_before],
        "tmi_rms_after": [float(x) for x in result.tmi_after],
        "coverage": result.excitation.coverage,
        "valid_envelope": {"pitch_deg": result.envelope.pitch_deg, "roll_deg": result.envelope.roll_deg},
        "noise": [float(x) for x in result.noise],
        "outliers_excluded": {"total": int(result.outliers.sum()),
                              **{nm: int(k) for nm, k in zip(names, result.outliers)}},
        "uncertainty": uncertainty,
        "uncertainty_inflation": result.inflation,
        "summary": result.summary(),
        "output_frame": result.frame_note(),
    }
    if np.isfinite(result.tensor_before) and np.isfinite(result.tensor_after):  # no tensor of one sensor
        meta["tensor_rms_before"], meta["tensor_rms_after"] = result.tensor_before, result.tensor_after
    if ana.weak():
        meta["weak"] = [f"{q.sensor} {q.name}" for q in ana.weak()]
    if result.prior:
        meta["updated"] = [f"{q.sensor} {q.name}" for q in ana.updated()] or ["nothing"]
        meta["kept"] = [f"{q.sensor} {q.name}" for q in ana.kept()] or ["nothing"]
    if result.extras.get("uniformity") is not None:
        meta.update(result.extras["uniformity"].provenance())
    if ana.held():
        meta["held"] = [f"{q.sensor} {q.name}" for q in ana.held()]
    if result.extras.get("temperature_range") is not None:
        meta["temperature_range"] = [float(t) for t in result.extras["temperature_range"]]
    if result.lags():
        meta["lags"] = result.lags()
    if result.extras.get("drift"):
        meta["drift"] = list(result.extras["drift"])
    if result.extras.get("imu") is not None:
        meta.update(result.extras["imu"].provenance())
    if result.warnings:
        meta["warnings"] = list(result.warnings)
    return meta

"""What a manoeuvre determines: physical quantities, their 1-sigma, what to fly next, and where
the calibration is valid.

The covariance of a joint fit (:mod:`magcal_ros.core.uncertainty`) is mapped, sensor by
sensor, onto the quantities an engineer reasons in: offsets (nT), scale factors,
non-orthogonality and misalignment angles (deg), current interference (nT/A). A quantity
whose 1-sigma *effect* on the field (the offset itself, or the scale or angle times F, or
the interference times the RMS current) exceeds :data:`UNDETERMINED_EFFECT` times the
sensor noise (or :data:`UNDETERMINED_FRACTION` of F) is undetermined: the data cannot fix
it. Above :data:`WEAK_EFFECT` it is
*weak*: fixed near the attitudes flown, not far from them, so the calibration holds inside
its envelope only. With a prior, a quantity whose uncertainty the data did not at least
halve is *kept* at the prior, the others *updated*.

The same covariance predicts the TMI error at any attitude; over pitch and roll (the
array's z axis taken as the vehicle's vertical, full yaw) it gives the envelope inside which
the predicted error stays within :data:`ENVELOPE_RATIO` times the noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.forward_model import ForwardModel
from magcal_ros.core.rotation import rq_positive
from magcal_ros.core.units import NT
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

UNDETERMINED_EFFECT: float = 400.0
"""A quantity is undetermined when its 1-sigma effect exceeds this many noise sd: 600 sets of a
yaw circle with +-3 deg of wobble leave scale z at 1,500-6,500 sd (refused without a prior),
a glider's +-5/+-2 deg of pitch and roll at 70-110 (weak: valid within about +-9 deg)."""
UNDETERMINED_FRACTION: float = 0.15
"""... or when its 1-sigma effect exceeds this fraction of F, whatever the noise: a consumer
sensor (0.5 % noise) turned in yaw with a few degrees of hand wobble leaves scale z at 25-200 %
of F, only 50-300 of its large noise sd."""
WEAK_EFFECT: float = 30.0
"""A quantity is weak when its 1-sigma effect exceeds this many noise sd (+-10/+-4 deg of
pitch and roll: 15-25 sd; +-15 deg of pitch: about 10; a full tumble: below 1)."""
KEPT_FRACTION: float = 0.5
"""With a prior, a quantity whose posterior 1-sigma is above this fraction of the prior's is kept."""
ENVELOPE_RATIO: float = 1.5
"""The envelope: predicted TMI error within this factor of the noise."""
AXES = ("x", "y", "z")
NONORTHOGONALITY = ("x-z", "x-y", "y-z")


@dataclass(frozen=True)
class Quantity:
    """One physical quantity of one sensor: value, 1-sigma, and what the data did to it."""

    sensor: str
    name: str
    """e.g. ``offset z``, ``scale x``, ``non-orthogonality x-z``, ``misalignment about y``."""
    unit: str
    """``nT``, ``ppm``, ``deg``, ``nT/A``, ``nT/K``, ``ppm/K`` or ``ms`` (value and sigma are in this unit)."""
    value: float
    sigma: float
    effect: float
    """1-sigma effect on the field (T)."""
    status: str
    """``determined``, ``weak`` (determined near the attitudes flown only), ``undetermined``,
    ``updated`` or ``kept`` (the last two with a prior), or ``held`` (a temperature or lag
    quantity the data did not determine, held at zero)."""
    prior_sigma: float | None = None

    def describe(self) -> str:
        """``mag1 offset z 12.3 +- 0.4 nT``; a scale as a gain with its 1-sigma in ppm:
        ``mag1 scale z 1.0381 +- 1300 ppm``."""
        sigma = f"{float(f'{self.sigma:.2g}'):g}"  # two significant digits, no exponent below 1e6
        if self.unit == "ppm":
            return f"{self.sensor} {self.name} {self.value * 1e-6:.5f} +- {sigma} ppm"
        return f"{self.sensor} {self.name} {self.value:.4g} +- {sigma} {self.unit}"


def _phys_many(thetas: Array, f: float, model: ForwardModel) -> Array:
    """Physical vectors (B, Q) of B parameter vectors (B, P) of one sensor, in :func:`quantity_names`
    order: offsets (T), scales, angles (rad), misalignment (rad), interference D (T/A, platform frame,
    row-major), then offset per kelvin (T/K, raw axes), gain per kelvin (1/K), time offset (s).

    The decomposition is :meth:`~magcal_ros.core.sensor_model.SensorErrors.from_forward`'s (``K = (C A) T^T``), for a whole stack
    at once; ``K`` and ``-K`` (with ``-D``) predict the same readings and are taken with ``det > 0``.
    """
    b = len(thetas)
    w_row = thetas[:, : 3 * model.q].reshape(b, 3, model.q)
    det = np.linalg.det(w_row[:, :, :3])
    k = w_row[:, :, :3] * np.where(det < 0, -1.0, 1.0)[:, None, None]
    if not np.all(np.isfinite(k)) or np.any(det == 0):
        raise InputError("K must be a finite 3x3 matrix with positive determinant")
    upper, q = rq_positive(k)
    scale = np.linalg.norm(upper, axis=2)
    a = upper / scale[:, :, None]
    angles = np.stack([np.arcsin(np.clip(a[:, 0, 2], -1, 1)), np.arctan2(a[:, 0, 1], a[:, 0, 0]),
                       np.arcsin(np.clip(a[:, 1, 2], -1, 1))], axis=1)
    t = np.swapaxes(q, 1, 2)  # sensor to platform, angles as rotation.matrix_to_euler
    misalignment = np.stack([np.arctan2(t[:, 1, 2], t[:, 2, 2]), -np.arcsin(np.clip(t[:, 0, 2], -1, 1)),
                             np.arctan2(t[:, 0, 1], t[:, 0, 0])], axis=1)
    d = np.linalg.solve(k, w_row[:, :, 4 : 4 + model.channels] * f)
    parts = [w_row[:, :, 3] * f, scale, angles, misalignment, d.reshape(b, -1)]
    if model.temperature:
        parts += [w_row[:, :, model.offset_tempco_column] * f, thetas[:, model.gain_slice]]
    if model.lag:
        parts.append(thetas[:, model.lag_index : model.lag_index + 1])
    return np.concatenate(parts, axis=1)


def physical_jacobian(theta: Array, f: float, model: ForwardModel) -> tuple[Array, Array]:
    """Physical values (S, Q) and d phys / d theta (S, Q, P) by central differences."""
    s, p = model.sensors, model.size
    t = np.asarray(theta, dtype=float).reshape(s, p)
    steps = np.where(np.arange(p) < 3 * model.q, 1e-6 * np.maximum(1.0, np.abs(t)), 1e-6 * np.maximum(1e-3, np.abs(t)))
    # per sensor: the point, then +h and -h along every parameter, in one stack
    stack = np.repeat(t[:, None, :], 2 * p + 1, axis=1)  # (S, 2P + 1, P)
    eye = np.eye(p)
    stack[:, 1 : p + 1] += eye[None] * steps[:, None, :]
    stack[:, p + 1 :] -= eye[None] * steps[:, None, :]
    phys = _phys_many(stack.reshape(-1, p), f, model).reshape(s, 2 * p + 1, -1)
    values = phys[:, 0]
    jac = np.swapaxes((phys[:, 1 : p + 1] - phys[:, p + 1 :]) / (2 * steps[:, :, None]), 1, 2)
    return values, jac


def quantity_names(channels: Sequence[str], with_mounting: bool,
                   model: ForwardModel | None = None) -> list[tuple[str, str]]:
    """``(name, unit)`` of each physical quantity, in :func:`physical_jacobian` order."""
    out = [(f"offset {a}", "nT") for a in AXES] + [(f"scale {a}", "ppm") for a in AXES]
    out += [(f"non-orthogonality {p}", "deg") for p in NONORTHOGONALITY]
    out += [(f"misalignment about {a}", "deg") for a in AXES] if with_mounting else [("", "")] * 3
    out += [(f"interference {c} {a}", "nT/A") for a in AXES for c in channels]
    if model is not None and model.temperature:
        out += [(f"offset tempco {a}", "nT/K") for a in AXES] + [(f"gain tempco {a}", "ppm/K") for a in AXES]
    if model is not None and model.lag:
        out.append(("time offset", "ms"))
    return out


def by_sensor(quantities: Sequence[Quantity], sensors: Sequence[str]) -> str:
    """Quantities named with their sensors, grouped by the sensors that have them, in the order of
    ``sensors``: ``every sensor: offset x, offset y; mag2, mag3: time offset`` (``every sensor`` when all of
    ``sensors`` have it and there are several), ``nothing`` for none. Quantities of the same name under two
    statuses (updated and kept) are then told apart by their sensors."""
    names: dict[str, list[str]] = {}
    for q in quantities:
        names.setdefault(q.name, [])
        if q.sensor not in names[q.name]:
            names[q.name].append(q.sensor)
    rank = {s: k for k, s in enumerate(sensors)}
    groups: dict[tuple[str, ...], list[str]] = {}
    for name, who in names.items():
        groups.setdefault(tuple(sorted(who, key=lambda s: rank.get(s, len(rank)))), []).append(name)
    every = tuple(sensors)
    parts = [f"{'every sensor' if who == every and len(every) > 1 else ', '.join(who)}: {', '.join(items)}"
             for who, items in groups.items()]
    return "; ".join(parts) or "nothing"


def held_parameter(name: str, model: ForwardModel) -> int | None:
    """The parameter index a quantity of a holdable block stands for (None for other quantities)."""
    if name.startswith("offset tempco ") and model.offset_tempco_column is not None:
        return model.w_index(AXES.index(name[-1]), model.offset_tempco_column)
    if name.startswith("gain tempco ") and model.gain_slice is not None:
        return model.gain_slice.start + AXES.index(name[-1])
    if name == "time offset" and model.lag_index is not None:
        return model.lag_index
    return None


_UNIT_SCALE: dict[str, float] = {"nT": 1.0 / NT, "ppm": 1e6, "deg": 180.0 / np.pi, "nT/A": 1.0 / NT,
                                  "nT/K": 1.0 / NT, "ppm/K": 1e6, "ms": 1e3}
"""What one SI unit of each quantity is in the unit it is reported in."""


@dataclass(frozen=True)
class EffectScales:
    """What turns a quantity's 1-sigma into its effect on the field: the RMS current of each
    channel (A), the RMS temperature excursion of each sensor from the reference (K), and the
    RMS rate of change of the field direction (1/s)."""

    current_rms: Array | None = None
    temperature_rms: Array | None = None
    rate_rms: float = 0.0


@dataclass(frozen=True)
class Identifiability:
    """Per-sensor physical quantities with their uncertainty and status."""

    quantities: list[Quantity]
    noise: Array
    """(S,) noise sd per axis (T) used for the thresholds."""
    with_prior: bool
    covariance: Array = field(repr=False)
    """(S P, S P) parameter covariance (units of F) it was computed from."""

    def undetermined(self) -> list[Quantity]:
        """Quantities the data cannot fix (no prior)."""
        return [q for q in self.quantities if q.status == "undetermined"]

    def weak(self) -> list[Quantity]:
        """Quantities determined near the attitudes flown only (no prior): they bound the envelope."""
        return [q for q in self.quantities if q.status == "weak"]

    def kept(self) -> list[Quantity]:
        """Quantities left at the prior."""
        return [q for q in self.quantities if q.status == "kept"]

    def updated(self) -> list[Quantity]:
        """Quantities the data updated (with a prior)."""
        return [q for q in self.quantities if q.status == "updated"]

    def held(self) -> list[Quantity]:
        """Temperature and lag quantities held at zero because the data did not determine them."""
        return [q for q in self.quantities if q.status == "held"]

    def by_name(self, sensor: str, name: str) -> Quantity:
        """The quantity ``name`` of ``sensor``."""
        return next(q for q in self.quantities if q.sensor == sensor and q.name == name)


def analyse(
    names: Sequence[str],
    theta: Array,
    intensity: float,
    cov: Array,
    noise: Array,
    prior_cov: Array | None = None,
    channels: Sequence[str] = (),
    current_rms: Array | None = None,
    *,
    model: ForwardModel | None = None,
    scales: EffectScales | None = None,
    held: NDArray[np.bool_] | None = None,
) -> Identifiability:
    """Physical quantities of every sensor from the fitted parameters and their covariance.

    ``theta`` (S, P) of ``model`` (or ``W`` (S, 3, 4 + m) of the plain model when ``model`` is
    None); ``prior_cov`` (S P, S P) marks the quantities as updated/kept; without it they are
    determined, weak or undetermined by their effect against ``noise`` (S,) T. ``held`` (S, P)
    marks parameters of the temperature and lag blocks the caller held at zero: their
    quantities are ``held``.
    """
    t = np.asarray(theta, dtype=float)
    s = t.shape[0]
    if model is None:
        model = ForwardModel(s, t.shape[2] - 4 if t.ndim == 3 else 0)
    t = t.reshape(s, model.size)
    sc = scales or EffectScales(current_rms)
    m = model.channels
    values, jac = physical_jacobian(t, intensity, model)
    with_mounting = s > 1 or prior_cov is not None
    labels = quantity_names(channels, with_mounting, model)
    rms = np.ones(m) if sc.current_rms is None else np.asarray(sc.current_rms, dtype=float)
    temp_rms = np.ones(s) if sc.temperature_rms is None else np.asarray(sc.temperature_rms, dtype=float)
    p = model.size
    out: list[Quantity] = []
    for i, sensor in enumerate(names):
        block = cov[i * p : (i + 1) * p, i * p : (i + 1) * p]
        sig = np.sqrt(np.clip(np.einsum("qj,jk,qk->q", jac[i], block, jac[i]), 0, None))
        psig = None
        if prior_cov is not None:
            pb = prior_cov[i * p : (i + 1) * p, i * p : (i + 1) * p]
            psig = np.sqrt(np.clip(np.einsum("qj,jk,qk->q", jac[i], pb, jac[i]), 0, None))
        for j, (label, unit) in enumerate(labels):
            if not label:
                continue
            current = rms[(j - 12) % m] if unit == "nT/A" and m else 1.0
            effect = _effect(sig[j], unit, current, temp_rms[i], sc.rate_rms, intensity)
            index = held_parameter(label, model)
            prior_j = None
            if held is not None and index is not None and held[i, index]:
                status = "held"
            elif psig is None:
                undetermined = effect > min(UNDETERMINED_EFFECT * noise[i], UNDETERMINED_FRACTION * intensity)
                status = ("undetermined" if undetermined
                          else "weak" if effect > WEAK_EFFECT * noise[i] else "determined")
            else:
                prior_j = float(psig[j]) * _UNIT_SCALE[unit]
                status = "kept" if sig[j] > KEPT_FRACTION * psig[j] else "updated"
            out.append(Quantity(sensor, label, unit, float(values[i, j]) * _UNIT_SCALE[unit],
                                float(sig[j]) * _UNIT_SCALE[unit], float(effect), status, prior_j))
    return Identifiability(out, np.asarray(noise, dtype=float), prior_cov is not None, cov)


def _effect(sigma: float, unit: str, current_rms: float, temperature_rms: float, rate_rms: float,
            intensity: float) -> float:
    """1-sigma effect on the field (T) of a quantity with 1-sigma ``sigma`` (SI units): an offset
    as it is, an interference gain times the channel's RMS current (A), a coefficient per kelvin
    times the RMS temperature excursion (K), a lag times the RMS turn rate of the field, a scale or
    angle times F."""
    if unit == "nT":
        return sigma
    if unit == "nT/A":
        return sigma * current_rms
    if unit == "nT/K":
        return sigma * temperature_rms
    if unit == "ppm/K":
        return sigma * temperature_rms * intensity
    if unit == "ms":
        return sigma * rate_rms * intensity
    return sigma * intensity


# -- predicted TMI error ------------------------------------------------------------------
VARIANCE_CHUNK: int = 8192
"""Directions evaluated at a time by :func:`predicted_tmi_variance` (keeps the work in cache)."""


def predicted_tmi_variance(w: Array, cov: Array, directions: Array, chunk: int = VARIANCE_CHUNK,
                           combine: Array | None = None) -> Array:
    """Predicted variance of ``|b_i| / F`` from the calibration alone at each direction: (A, S);
    with ``combine`` (S,) the sum of the sensors' variances weighted by it: (A, 1), as cheap as one sensor.

    From ``b = M (r - o - E u)`` with ``r = K F d + E u + o``: a parameter error gives
    ``db = -M (dK F d + do + dE u)`` and the TMI error ``d^T db`` (no current, u = 0), which is
    ``-(d^T M) (x) [d, 1]`` applied to the sensor's ``dW``: a quadratic form per direction. As
    ``(d^T M) (x) [d, 1] = (d (x) [d, 1]) (M (x) I_4)``, every sensor's form acts on the same
    numbers per direction, the 9 distinct ones of ``d (x) [d, 1]``: one product for all sensors.
    """
    forms = _variance_forms(w, cov, combine)
    d = np.asarray(directions, dtype=float)
    out = np.empty((len(d), len(forms)))
    for lo in range(0, len(d), chunk):
        out[lo : lo + chunk] = _quadratic_forms(forms, d[lo : lo + chunk].T).T
    return np.clip(out, 0, None)


def _variance_forms(w: Array, cov: Array, combine: Array | None = None) -> Array:
    """(S, 9, 9) each sensor's quadratic form of :func:`predicted_tmi_variance` in the 9 distinct
    numbers of ``d (x) [d, 1]`` (``d_a d_b`` for a <= b, then ``d``); (1, 9, 9) their sum weighted by ``combine``."""
    s, _, q = w.shape
    p = cov.shape[0] // s  # parameters per sensor: W first, then any non-linear ones
    mats = np.linalg.inv(w[:, :, :3])
    keep = (np.arange(3)[:, None] * q + np.arange(4)[None, :]).reshape(-1)  # K and o entries
    forms = np.empty((s, 12, 12))
    for i in range(s):
        t = (mats[i][:, None, :, None] * np.eye(4)[None, :, None, :]).reshape(12, 12)  # M (x) I_4
        forms[i] = t @ cov[i * p : (i + 1) * p, i * p : (i + 1) * p][np.ix_(keep, keep)] @ t.T
    fold = _FOLD.T @ forms @ _FOLD  # (S, 9, 9)
    if combine is not None:  # a weighted sum of quadratic forms in the same numbers: one form
        fold = np.einsum("s,sab->ab", np.asarray(combine, dtype=float), fold)[None]
    return fold


def _quadratic_forms(forms: Array, dt: Array) -> Array:
    """(S, A) the forms (S, 9, 9) of :func:`_variance_forms` at directions given by component, ``dt`` (3, A)."""
    z = np.empty((9, dt.shape[1]))  # the 9 numbers, each contiguous
    for k, (i, j) in enumerate(zip(*_PAIRS)):
        np.multiply(dt[i], dt[j], out=z[k])
    z[6:] = dt
    fz = (forms.reshape(-1, 9) @ z).reshape(len(forms), 9, -1)  # (S, 9, A)
    fz *= z
    return fz.sum(axis=1)


_PAIRS = (np.array([0, 1, 2, 0, 0, 1]), np.array([0, 1, 2, 1, 2, 2]))
"""The distinct products ``d_a d_b`` (a <= b) of a direction."""


def _fold() -> Array:
    """(12, 9): ``d (x) [d, 1]`` from its distinct entries (the products of :data:`_PAIRS`, then ``d``)."""
    out = np.zeros((12, 9))
    for a in range(3):
        for b in range(3):
            out[4 * a + b, next(k for k in range(6) if {_PAIRS[0][k], _PAIRS[1][k]} == {a, b})] = 1.0
        out[4 * a + 3, 6 + a] = 1.0
    return out


_FOLD = _fold()


def attitude_directions(inclination: float, pitch_deg: Array, roll_deg: Array, yaw_steps: int = 12) -> Array:
    """Unit field directions in the platform frame for every (yaw, pitch, roll) combination.

    World NED field of ``inclination`` (rad); platform to world ``R = Rz(yaw) Ry(pitch)
    Rx(roll)``; the platform-frame field is ``R^T B``. Returns (P, R, Y, 3).
    """
    return np.moveaxis(_attitude_components(inclination, pitch_deg, roll_deg, yaw_steps), 0, -1)


def _attitude_components(inclination: float, pitch_deg: Array, roll_deg: Array, yaw_steps: int = 12) -> Array:
    """:func:`attitude_directions` component first: (3, P, R, Y), each component contiguous."""
    b = np.array([np.cos(inclination), 0.0, np.sin(inclination)])
    yaw = np.arange(yaw_steps) * 2 * np.pi / yaw_steps
    p = np.radians(np.asarray(pitch_deg, dtype=float))[:, None, None]
    r = np.radians(np.asarray(roll_deg, dtype=float))[None, :, None]
    # world -> body: Rx(roll)^T Ry(pitch)^T Rz(yaw)^T b
    x1, y1, z1 = np.cos(yaw) * b[0], -np.sin(yaw) * b[0], b[2]  # (Y,): Rz^T b (b has no east part)
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    out = np.empty((3, p.shape[0], r.shape[1], yaw_steps))
    out[0] = cp * x1 - sp * z1  # Ry^T: (P, 1, Y), the same at every roll
    z2 = sp * x1 + cp * z1
    np.multiply(cr, y1, out=out[1])  # Rx^T: (P, R, Y)
    out[1] += sr * z2
    np.multiply(cr, z2, out=out[2])
    out[2] -= sr * y1
    return out


@dataclass(frozen=True)
class Envelope:
    """Where the calibration is valid: |pitch| <= pitch_deg and |roll| <= roll_deg, any yaw."""

    pitch_deg: float
    roll_deg: float
    inclination_deg: float
    """Inclination (deg) assumed for the prediction."""
    ratio_inside: float
    """Worst predicted TMI error / noise inside the envelope."""
    ratio_sphere: float
    """RMS predicted TMI error / noise over all attitudes (uniform over rotations)."""
    ratio_outside: float
    """RMS predicted TMI error / noise over the attitudes outside the envelope (1 if none)."""

    @property
    def whole_sphere(self) -> bool:
        """True when every attitude is inside."""
        return self.pitch_deg >= 90.0 and self.roll_deg >= 180.0

    @property
    def empty(self) -> bool:
        """True when no attitude is within :data:`ENVELOPE_RATIO` of the noise (too few sets, or a
        calibration error everywhere)."""
        return self.pitch_deg <= 0 and self.roll_deg <= 0

    def describe(self) -> str:
        """``valid within pitch +-P deg, roll +-R deg``, ``valid over the whole sphere``, or for an
        empty envelope ``not within 1.5x the noise at any attitude (about Nx over the sphere)``."""
        if self.whole_sphere:
            return "valid over the whole sphere"
        if self.empty:
            return (f"not within {ENVELOPE_RATIO:g}x the noise at any attitude (about {self.ratio_sphere:.1f}x "
                    "over the sphere)")
        return f"valid within pitch +-{self.pitch_deg:.0f} deg, roll +-{self.roll_deg:.0f} deg"


PITCH_GRID = np.concatenate([np.arange(0, 30, 1.0), np.arange(30, 91, 5.0)])
"""Pitch limits tried (deg): 1-deg steps where envelopes usually end, coarser beyond."""
ROLL_GRID = np.concatenate([np.arange(0, 30, 1.0), np.arange(30, 181, 5.0)])


ROLL_HARMONICS: int = 4
"""Degree in the roll angle of the predicted TMI variance at a fixed pitch and yaw: a quadratic form
in the direction's products and components, each a trigonometric polynomial of degree 2 in roll."""


def _roll_basis(roll_deg: Array) -> Array:
    """(R, 2 H + 1) ``[1, cos r, sin r, ..., cos H r, sin H r]`` with H = :data:`ROLL_HARMONICS`."""
    r = np.radians(np.asarray(roll_deg, dtype=float))[:, None] * np.arange(1, ROLL_HARMONICS + 1)[None, :]
    return np.column_stack([np.ones(len(r)), np.stack([np.cos(r), np.sin(r)], axis=2).reshape(len(r), -1)])


_PROBES = np.arange(2 * ROLL_HARMONICS + 1) * 360.0 / (2 * ROLL_HARMONICS + 1)
"""Rolls (deg) at which the variance is computed; the others are interpolated."""
_FROM_PROBES = np.linalg.inv(_roll_basis(_PROBES))
"""(2 H + 1, 2 H + 1): the roll polynomial's coefficients from its values at :data:`_PROBES`."""


def variance_grid(w: Array, cov: Array, inclination: float, pitch_deg: Array, roll_deg: Array,
                  combine: Array | None = None) -> Array:
    """(P, R, Y, S) :func:`predicted_tmi_variance` at every attitude of :func:`attitude_directions`
    (S = 1 with ``combine``: the sensors' variances summed with those weights).

    Along roll the variance is a trigonometric polynomial of degree :data:`ROLL_HARMONICS`, so it
    is computed exactly (to rounding) from ``2 H + 1`` rolls and interpolated to the others: the
    work of a few rolls instead of every one.
    """
    return np.clip(_variance_by_yaw(w, cov, inclination, pitch_deg, roll_deg, combine), 0.0, None).transpose(3, 2, 0, 1)


def _variance_by_yaw(w: Array, cov: Array, inclination: float, pitch_deg: Array, roll_deg: Array,
                     combine: Array | None) -> Array:
    """:func:`variance_grid` before clipping, yaw first: (Y, S, R, P), each (R, P) contiguous."""
    comps = _attitude_components(inclination, pitch_deg, _PROBES)  # (3, P, K, Y)
    _, p, k, y = comps.shape
    at_probes = _quadratic_forms(_variance_forms(w, cov, combine), comps.reshape(3, -1))  # (S, P K Y)
    np.maximum(at_probes, 0.0, out=at_probes)  # as predicted_tmi_variance
    interpolate = _roll_basis(roll_deg) @ _FROM_PROBES  # (R, K)
    return interpolate @ np.ascontiguousarray(at_probes.reshape(-1, p, k, y).transpose(3, 0, 2, 1))  # (Y, S, K, P)


_GRID_P = np.concatenate([-PITCH_GRID[:0:-1], PITCH_GRID])
_GRID_R = np.concatenate([-ROLL_GRID[:0:-1], ROLL_GRID])
_GRID_WEIGHT = (np.cos(np.radians(_GRID_P)) * np.gradient(_GRID_P))[:, None] * np.gradient(_GRID_R)[None, :]
"""(P, R) weight of each pitch and roll of the signed grids, uniform over rotations: the yaw-pitch-roll
measure is cos(pitch) d(yaw) d(pitch) d(roll), and the grids are not evenly spaced."""


def envelope(w: Array, cov: Array, noise: Array, intensity: float, inclination: float) -> Envelope:
    """The largest |pitch| x |roll| box (any yaw) where the predicted TMI error / noise stays
    within :data:`ENVELOPE_RATIO`; ``noise`` (S,) and ``intensity`` in T, ``inclination`` rad.

    The ratio at an attitude is ``sqrt(1 + var_cal / sigma^2)`` (calibration error added to
    the noise), RMS over the sensors; a box is valid when its worst attitude (any yaw, both
    signs of pitch and roll) is. Among valid boxes the one with the largest solid angle wins.
    """
    f_noise = np.asarray(noise, dtype=float)
    grid_p, grid_r = _GRID_P, _GRID_R
    sigma_f = f_noise / intensity  # noise in units of F, like the predicted variance
    # the squared ratio less one, (Y, R, P): the sensors' variances over their noise, averaged
    var = _variance_by_yaw(w, cov, inclination, grid_p, grid_r, combine=1.0 / sigma_f**2 / len(sigma_f))[:, 0]
    np.maximum(var, 0.0, out=var)
    yaws = len(var)
    worst = np.sqrt(1.0 + var.max(axis=0).T)  # over yaw, (P, R)
    # fold signs: a box |p| <= P, |r| <= R
    npos, rpos = len(PITCH_GRID), len(ROLL_GRID)
    folded = np.maximum.reduce([
        worst[npos - 1 :, rpos - 1 :], worst[npos - 1 :, rpos - 1 :: -1][:, :rpos],
        worst[npos - 1 :: -1, rpos - 1 :][:npos], worst[npos - 1 :: -1, rpos - 1 :: -1][:npos, :rpos],
    ])
    cum = np.maximum.accumulate(np.maximum.accumulate(folded, axis=0), axis=1)  # worst inside box
    valid = cum <= ENVELOPE_RATIO
    # per pitch limit its widest valid roll limit; the box of largest solid angle (the first on a tie)
    has = valid.any(axis=1)
    widest = len(ROLL_GRID) - 1 - np.argmax(valid[:, ::-1], axis=1)
    area = np.where(has, (np.sin(np.radians(PITCH_GRID)) + 0.01) * (ROLL_GRID[widest] + 1.0), -1.0)
    i = int(np.argmax(area))
    j = int(widest[i]) if has[i] else 0
    inside = float(cum[i, j]) if valid[i, j] else float(folded[0, 0])
    pitch_lim = float(PITCH_GRID[i]) if valid[i, j] else 0.0
    roll_lim = float(ROLL_GRID[j]) if valid[i, j] else 0.0
    weight = _GRID_WEIGHT
    over_yaw = yaws + var.sum(axis=0).T  # the squared ratio summed over yaw (every yaw weighs the same)
    sphere = float(np.sqrt(np.sum(weight * over_yaw) / (np.sum(weight) * yaws)))
    out = (np.abs(grid_p)[:, None] > pitch_lim) | (np.abs(grid_r)[None, :] > roll_lim)
    outside = float(np.sqrt(np.sum((weight * over_yaw)[out]) / (np.sum(weight[out]) * yaws))) \
        if out.any() else 1.0
    return Envelope(pitch_lim, roll_lim, float(np.degrees(inclination)), inside, sphere, outside)


# -- what to fly next ----------------------------------------------------------------------
TILT_DEG: float = 15.0
"""Tilt of the candidate manoeuvres :func:`advise` compares."""
CANDIDATES: tuple[tuple[str, float, float], ...] = (
    ("pitch nose down", -TILT_DEG, 0.0), ("pitch nose up", TILT_DEG, 0.0),
    ("roll to port", 0.0, -TILT_DEG), ("roll to starboard", 0.0, TILT_DEG),
)


@dataclass(frozen=True)
class Advice:
    """What to fly next, in words, and what it would leave undetermined."""

    text: str
    worst_effect: float
    """Largest 1-sigma effect of a quantity, in noise sd, after flying it (as flown when enough)."""


def tilted(directions: Array, pitch_deg: float, roll_deg: float) -> Array:
    """Platform-frame field directions seen after tilting the vehicle by pitch, then roll (deg)."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    return directions @ (ry @ rx)  # R^T d for each row d, with R = Ry Rx


def advise(names: Sequence[str], w: Array, intensity: float, information: Array, directions: Array,
           noise: Array, constraints: Array | None = None, model: ForwardModel | None = None) -> Advice:
    """The candidate tilt (:data:`CANDIDATES`, flown through the same yaw turns as so far) that
    best determines what is still undetermined or weak; "enough" when nothing is undetermined
    (with the tilt that would widen the envelope when something is weak).

    Only the attitude-dependent blocks (sensor, interference) are judged: temperature and lag are
    determined by temperature span and turn rate, which no tilt changes (``information`` and
    ``constraints`` of a ``model`` with those blocks are restricted to the others).
    """
    from magcal_ros.core.array_fit import information_at

    if model is not None and model.extras + int(model.temperature) > 0:
        base = ForwardModel(model.sensors, model.channels)
        keep = np.array([i * model.size + model.w_index(a, c)
                         for i in range(model.sensors) for a in range(3) for c in range(base.q)])
        information = information[np.ix_(keep, keep)]
        constraints = None if constraints is None else constraints[:, keep]
        w = w[:, :, : base.q]

    def judged(info: Array) -> tuple[int, int, float]:
        """(undetermined, weak, worst effect in noise sd) with information ``info``."""
        if constraints is not None and len(constraints):
            _, sv, vt = np.linalg.svd(constraints)
            basis = vt[int(np.sum(sv > 1e-12 * sv[0])):].T
            cov = basis @ np.linalg.pinv(basis.T @ info @ basis, hermitian=True) @ basis.T
        else:
            cov = np.linalg.pinv(info, hermitian=True)
        ana = analyse(names, w, intensity, cov, noise)
        worst = max(q.effect / max(ana.noise[names.index(q.sensor)], 1e-30) for q in ana.quantities)
        return len(ana.undetermined()), len(ana.weak()), worst

    now = judged(information)
    if not now[0] and not now[1]:
        return Advice("enough for a calibration: call ~/calibrate (more attitudes widen the envelope)", now[2])
    sigma_f = np.asarray(noise, dtype=float) / intensity
    best = None
    for words, pitch, roll in CANDIDATES:
        extra = information_at(w, tilted(directions, pitch, roll), sigma_f)
        score = judged(information + extra)
        if best is None or score < best[1]:
            best = (words, score)
    assert best is not None
    words, score = best
    if not now[0]:
        return Advice(f"enough for a calibration valid near the attitudes flown: call ~/calibrate; to widen its "
                      f"envelope, {words} {TILT_DEG:.0f} deg and keep turning", now[2])
    return Advice(f"{words} {TILT_DEG:.0f} deg and keep turning", score[2])

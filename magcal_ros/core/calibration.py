"""The array calibration: per sensor ``B = matrix (raw - offset) - interference @ u``.

This is the object the solver returns, the calibration file stores and the correction
node applies. Matrices map raw sensor axes (T) into the platform frame (T); ``u`` are the
currents (A) of the interference channels, when the calibration has any. ``time_offsets``
(s) say when each sensor's readings were taken: a reading stamped ``t`` is the field at
``t - time_offset`` (positive: the sensor reads late); they are applied where sets are
formed (:mod:`magcal_ros.core.sync`), not by :meth:`ArrayCalibration.apply`.

With temperature terms (``dT = T - temperature_reference``, T the sensor's temperature in
deg C) the correction is ``B = (matrix + dT matrix_tempco) (raw - offset - dT offset_tempco)
- interference @ u``. With an ``output_rotation`` ``R`` (array frame to the output frame,
e.g. the IMU's) every output is turned: vectors and centre field ``R v``, tensor ``R G R^T``,
baseline gradient ``R g``; the gradient itself is formed in the array frame, where the
positions are.
"""

from __future__ import annotations

from collections.abc import Sequence
import functools
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core import calibration_bounds as bounds
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.sync_rules import MAX_TIME_OFFSET
from magcal_ros.core.tensor import baseline_gradient, centre_field, gradient
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

MAX_CONDITION: float = 100.0
"""Largest accepted condition number of a correction matrix (fluxgate errors are percent-level)."""
GAIN_RANGE: tuple[float, float] = (0.1, 10.0)
"""Accepted range of a correction matrix's singular values."""
MAX_OFFSET: float = 1e-3
"""Largest accepted offset magnitude (T): 1 mT, twenty times the Earth's field."""
MAX_OFFSET_TEMPCO: float = bounds.MAX_OFFSET_TEMPCO
MAX_MATRIX_TEMPCO: float = bounds.MAX_MATRIX_TEMPCO
TEMPERATURE_REFERENCE_RANGE: tuple[float, float] = bounds.TEMPERATURE_RANGE
ROTATION_TOLERANCE: float = 1e-6
"""Largest departure of an output rotation from orthonormal (entries of ``R R^T - I``)."""


def check_sensor(name: str, matrix: ArrayLike, offset: ArrayLike) -> tuple[Array, Array]:
    """Validate one sensor's correction; return it as (3, 3) and (3,) arrays.

    Raises :class:`InputError` naming the sensor for a wrong length, a non-finite value,
    or a singular or absurd matrix (gains outside ``GAIN_RANGE``) or offset.
    """
    m = np.asarray(matrix, dtype=float)
    o = np.asarray(offset, dtype=float)
    if m.size != 9:
        raise InputError(f"{name}.matrix needs 9 numbers (row-major 3x3), got {m.size}")
    if o.size != 3:
        raise InputError(f"{name}.offset needs 3 numbers (T), got {o.size}")
    m, o = m.reshape(3, 3), o.reshape(3)
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(o))):
        raise InputError(f"{name}: matrix and offset must be finite")
    sv = np.linalg.svd(m, compute_uv=False)
    if sv[-1] <= 0 or sv[0] / sv[-1] > MAX_CONDITION:
        raise InputError(f"{name}.matrix is singular or ill-conditioned (singular values {sv})")
    if sv[0] > GAIN_RANGE[1] or sv[-1] < GAIN_RANGE[0]:
        raise InputError(f"{name}.matrix gains {sv} are outside {GAIN_RANGE}: not a fluxgate correction")
    if np.linalg.norm(o) > MAX_OFFSET:
        raise InputError(f"{name}.offset {o} T exceeds {MAX_OFFSET} T: units must be Tesla")
    return m, o


@dataclass(frozen=True)
class CorrectedSets:
    """What a calibration makes of raw sets, platform frame: the outputs the array supports."""

    vectors: Array
    """(N, S, 3) corrected vectors (T)."""
    centre: Array
    """(N, 3) field at the array centre (T): the mean of the sensors."""
    tensor: Array | None
    """(N, 3, 3) gradient tensor ``G[i, j] = dB_j/dx_i`` (T/m), when the positions determine it."""
    baseline: Array | None
    """(N, 3) ``dB_j/ds`` along the line of a collinear array (T/m), e.g. two sensors."""


@dataclass(frozen=True)
class AffineOutputs:
    """:meth:`ArrayCalibration.outputs` of one set as one affine map, for the live hot path:
    ``y = matrix @ x + offset`` with ``x`` the raw vectors (3 S numbers, T, sensor order) followed by
    the currents (one per channel, A), and ``y`` the corrected vectors (3 S), the centre field (3), then
    the tensor (9, row-major, T/m) or the baseline gradient (3, T/m) when the geometry gives one; all in
    the output frame."""

    matrix: Array
    """(K, 3 S + m)."""
    offset: Array
    """(K,)."""
    sensors: int
    kind: str
    """``tensor``, ``baseline`` or ``none`` (what follows the centre field)."""


@dataclass(frozen=True)
class ArrayCalibration:
    """Per-sensor corrections of an array, with its geometry and provenance."""

    geometry: ArrayGeometry
    matrices: Array
    """(S, 3, 3): raw sensor axes to platform frame."""
    offsets: Array
    """(S, 3): raw offsets in T."""
    metadata: dict[str, Any] = field(default_factory=dict)
    """Provenance: method, time, sample count, residuals (free-form, YAML-safe)."""
    covariances: Array | None = None
    """(S, 3, 3) covariance (T^2) of each corrected vector, platform frame: sensor noise plus
    calibration uncertainty, typical over attitudes. None, or all-NaN for a sensor: unknown."""
    channels: tuple[str, ...] = ()
    """Names of the current channels whose interference is subtracted (may be empty)."""
    interference: Array | None = None
    """(S, 3, m) interference gains (T/A, platform frame), one column per channel."""
    time_offsets: Array | None = None
    """(S,) s: sensor ``i``'s reading stamped ``t`` is the field at ``t - time_offsets[i]`` (reads
    late when positive). None: zeros."""
    # -- temperature terms and output frame ----------------------------------------------------
    temperature_reference: float | None = None
    """Temperature (deg C) at which ``matrices`` and ``offsets`` hold; None: no temperature terms."""
    offset_tempco: Array | None = None
    """(S, 3) T/K, raw sensor axes: the offset at ``dT`` is ``offsets + dT offset_tempco`` (default 0)."""
    matrix_tempco: Array | None = None
    """(S, 3, 3) 1/K: the matrix at ``dT`` is ``matrices + dT matrix_tempco`` (default 0)."""
    output_rotation: Array | None = None
    """(3, 3) rotation from the array (platform) frame to the output frame; None: identity."""
    frame_id: str | None = None
    """The output frame's name (e.g. the IMU's); None: the user's choice (``magcal_array`` by default)."""
    temperature_span: Array | None = None
    """(S, 2) deg C: per sensor the lowest and highest temperature of the sets the calibration was made
    from (``<name>.calibration_temperatures``; a row NaN: unknown for that sensor); None: unknown (no
    temperatures given, or a file from before). Applied far outside it the calibration extrapolates
    (:class:`~magcal_ros.core.temperature.SpanExcursions`)."""

    def __post_init__(self) -> None:
        m = np.asarray(self.matrices, dtype=float)
        o = np.asarray(self.offsets, dtype=float)
        s = self.geometry.size
        if m.shape != (s, 3, 3) or o.shape != (s, 3):
            raise InputError(f"need {s} matrices (3x3) and offsets (3), got {m.shape} and {o.shape}")
        checked = [check_sensor(n, mi, oi) for n, mi, oi in zip(self.geometry.names, m, o)]
        object.__setattr__(self, "matrices", np.stack([c[0] for c in checked]))
        object.__setattr__(self, "offsets", np.stack([c[1] for c in checked]))
        channels = tuple(str(c) for c in self.channels)
        if len(set(channels)) != len(channels) or not all(channels):
            raise InputError(f"interference channel names must be unique and non-empty, got {list(channels)}")
        d = np.zeros((s, 3, len(channels))) if self.interference is None else np.asarray(self.interference, dtype=float)
        if d.shape != (s, 3, len(channels)) or not np.all(np.isfinite(d)):
            raise InputError(f"interference must be {s} finite 3 x {len(channels)} matrices (T/A), got shape {d.shape}")
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "interference", d)
        lag = np.zeros(s) if self.time_offsets is None else np.asarray(self.time_offsets, dtype=float).reshape(-1)
        if lag.shape != (s,) or not np.all(np.isfinite(lag)) or np.any(np.abs(lag) > MAX_TIME_OFFSET):
            raise InputError(f"time_offsets must be {s} finite numbers of seconds within +-{MAX_TIME_OFFSET:g} s, "
                             f"got {lag.tolist()}")
        object.__setattr__(self, "time_offsets", lag)
        if self.covariances is not None:
            c = np.asarray(self.covariances, dtype=float)
            known = np.all(np.isfinite(c.reshape(len(c), -1)), axis=1) if c.ndim == 3 else np.zeros(0, bool)
            unknown = np.all(np.isnan(c.reshape(len(c), -1)), axis=1) if c.ndim == 3 else np.zeros(0, bool)
            if (c.shape != (s, 3, 3) or not np.all(known | unknown)
                    or np.any(np.linalg.eigvalsh(0.5 * (c[known] + c[known].swapaxes(1, 2))) < -1e-30)):
                raise InputError(f"covariances must be {s} positive semi-definite 3x3 matrices (T^2), "
                                 "or all NaN for a sensor whose covariance is unknown")
            object.__setattr__(self, "covariances", c)
        self._check_temperature_and_frame()
        self._check_temperature_span()

    def _check_temperature_span(self) -> None:
        """Validate :attr:`temperature_span` (bounds of :func:`~magcal_ros.core.calibration_bounds.check_temperature_span`)."""
        if self.temperature_span is None:
            return
        span = np.asarray(self.temperature_span, dtype=float)
        s = self.geometry.size
        if span.shape != (s, 2):
            raise InputError(f"temperature_span must be {s} pairs [min, max] (deg C), got shape {span.shape}")
        for name, row in zip(self.geometry.names, span):
            if not np.all(np.isnan(row)):
                bounds.check_temperature_span(f"{name}.calibration_temperatures", row)
        object.__setattr__(self, "temperature_span", None if np.all(np.isnan(span)) else span)

    # -- temperature terms and output frame ----------------------------------------------------
    def _check_temperature_and_frame(self) -> None:
        """Validate and normalise the temperature terms and the output rotation (neutral defaults)."""
        s, names = self.geometry.size, self.geometry.names
        ref = self.temperature_reference
        if ref is not None:
            ref = float(ref)
            lo, hi = TEMPERATURE_REFERENCE_RANGE
            if not (np.isfinite(ref) and lo <= ref <= hi):
                raise InputError(f"temperature_reference {ref} is not a temperature in deg C ({lo:g} .. {hi:g})")
        a = np.zeros((s, 3)) if self.offset_tempco is None else np.asarray(self.offset_tempco, dtype=float)
        g = np.zeros((s, 3, 3)) if self.matrix_tempco is None else np.asarray(self.matrix_tempco, dtype=float)
        if a.shape != (s, 3) or g.shape != (s, 3, 3) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(g))):
            raise InputError(f"temperature terms must be {s} finite offset_per_kelvin (3, T/K) and matrix_per_kelvin "
                             f"(9, 1/K), got shapes {a.shape} and {g.shape}")
        for name, ai, gi in zip(names, a, g):
            if np.max(np.abs(ai)) > MAX_OFFSET_TEMPCO:
                raise InputError(f"{name}.offset_per_kelvin {ai.tolist()} exceeds {MAX_OFFSET_TEMPCO:g} T/K: units "
                                 "must be T/K")
            if np.max(np.abs(gi)) > MAX_MATRIX_TEMPCO:
                raise InputError(f"{name}.matrix_per_kelvin exceeds {MAX_MATRIX_TEMPCO:g} per K: units must be 1/K")
        if ref is None and (np.any(a) or np.any(g)):
            raise InputError("temperature terms (offset_per_kelvin, matrix_per_kelvin) need temperature_reference "
                             "(deg C)")
        r = np.eye(3) if self.output_rotation is None else np.asarray(self.output_rotation, dtype=float)
        if r.size != 9 or not np.all(np.isfinite(r)):
            raise InputError(f"output_rotation needs 9 finite numbers (row-major 3x3), got {r.size}")
        r = r.reshape(3, 3)
        if np.max(np.abs(r @ r.T - np.eye(3))) > ROTATION_TOLERANCE or np.linalg.det(r) <= 0:
            raise InputError("output_rotation must be a rotation matrix (orthonormal, determinant +1)")
        frame = self.frame_id
        if frame is not None and (not isinstance(frame, str) or not frame.strip()):
            frame = None
        object.__setattr__(self, "temperature_reference", ref)
        object.__setattr__(self, "offset_tempco", a)
        object.__setattr__(self, "matrix_tempco", g)
        object.__setattr__(self, "output_rotation", r)
        object.__setattr__(self, "frame_id", frame.strip() if frame else None)

    @functools.cached_property
    def has_temperature_terms(self) -> bool:
        """True when the correction depends on the sensors' temperatures (a reference and a non-zero term)."""
        return self.temperature_reference is not None and bool(np.any(self.offset_tempco) or np.any(self.matrix_tempco))

    @functools.cached_property
    def rotated(self) -> bool:
        """True when the outputs are turned into another frame (``output_rotation`` is not the identity)."""
        return not np.array_equal(self.output_rotation, np.eye(3))

    def _temperature_delta(self, temperatures: ArrayLike | None, count: int) -> Array:
        """``dT`` (N, S) K of the sensors' temperatures (N, S) deg C (:class:`InputError` when missing or bad)."""
        if temperatures is None:
            raise InputError(f"this calibration corrects for temperature: give the temperatures (deg C) of "
                             f"{', '.join(self.geometry.names)}")
        t = np.asarray(temperatures, dtype=float)
        s = self.geometry.size
        if t.ndim == 1 and s == 1:
            t = t[:, None]
        if t.shape != (count, s) or not np.all(np.isfinite(t)):
            raise InputError(f"need finite temperatures (N, {s}) deg C, one per sensor and set, got shape {t.shape}")
        return t - self.temperature_reference  # type: ignore[operator]

    def at_reference(self, reference: float) -> "ArrayCalibration":
        """The same correction with its matrices and offsets at ``reference`` deg C (its terms per kelvin kept):
        itself without temperature terms."""
        if not self.has_temperature_terms:
            return self
        dt = float(reference) - float(self.temperature_reference)  # type: ignore[arg-type]
        return replace(self, matrices=self.matrices + dt * self.matrix_tempco,
                                   offsets=self.offsets + dt * self.offset_tempco, temperature_reference=float(reference))

    def to_output_frame(self, vectors: Array) -> Array:
        """Vectors (..., 3) from the array frame into the output frame (``R v``)."""
        return vectors @ self.output_rotation.T if self.rotated else vectors  # type: ignore[union-attr]

    # -- construction ----------------------------------------------------------------------------
    @classmethod
    def identity(cls, geometry: ArrayGeometry) -> "ArrayCalibration":
        """No correction: identity matrices, zero offsets."""
        s = geometry.size
        return cls(geometry, np.tile(np.eye(3), (s, 1, 1)), np.zeros((s, 3)), {"method": "identity"})

    def apply(self, raw: ArrayLike, currents: ArrayLike | None = None, temperatures: ArrayLike | None = None) -> Array:
        """Corrected vectors (N, S, 3) in T, output frame, from raw (N, S, 3) in T.

        ``currents`` (N, m) in A, one column per :attr:`channels`: their interference is
        subtracted. Required when the calibration has channels. ``temperatures`` (N, S) deg C:
        required when it has temperature terms. The output frame is the platform (array)
        frame unless :attr:`output_rotation` turns it (:meth:`apply_array` stays in it).
        """
        return self.to_output_frame(self.apply_array(raw, currents, temperatures))

    def apply_array(self, raw: ArrayLike, currents: ArrayLike | None = None,
                    temperatures: ArrayLike | None = None) -> Array:
        """Corrected vectors (N, S, 3) in T in the array (platform) frame: :meth:`apply` before the output rotation."""
        r = np.asarray(raw, dtype=float)
        if self.has_temperature_terms:
            dt = self._temperature_delta(temperatures, len(r))
            m = self.matrices + dt[:, :, None, None] * self.matrix_tempco
            b = (m @ (r - self.offsets - dt[:, :, None] * self.offset_tempco)[..., None])[..., 0]
        else:
            b = np.einsum("sij,nsj->nsi", self.matrices, r - self.offsets)
        if self.channels:
            if currents is None:
                raise InputError(f"this calibration subtracts current interference: give the currents of "
                                 f"{', '.join(self.channels)}")
            u = np.asarray(currents, dtype=float).reshape(len(r), -1)
            if u.shape[1] != len(self.channels):
                raise InputError(f"{u.shape[1]} current channels given, the calibration has {len(self.channels)}")
            b = b - np.einsum("sac,nc->nsa", self.interference, u)
        return b

    def outputs(self, raw: ArrayLike, method: str = "difference", currents: ArrayLike | None = None,
                temperatures: ArrayLike | None = None) -> CorrectedSets:
        """Corrected vectors, centre field and the gradient the geometry determines (see :class:`CorrectedSets`),
        in the output frame (the gradient is formed in the array frame, then turned)."""
        b = self.apply_array(raw, currents, temperatures)
        kind = self.geometry.gradient_kind
        tensor = gradient(b, self.geometry, method) if kind == "tensor" else None
        baseline = baseline_gradient(b, self.geometry) if kind == "baseline" else None
        if self.rotated:
            rot = self.output_rotation
            b = self.to_output_frame(b)
            tensor = None if tensor is None else rot @ tensor @ rot.T
            baseline = None if baseline is None else self.to_output_frame(baseline)
        return CorrectedSets(b, centre_field(b), tensor, baseline)

    def affine_outputs(self, method: str = "difference") -> AffineOutputs | None:
        """:meth:`outputs` of one set as an :class:`AffineOutputs` map (None with temperature terms,
        where the matrix depends on the temperature). The map is read off :meth:`outputs` itself (at
        zero and at each unit input), so it is that correction, merely precomputed."""
        if self.has_temperature_terms:
            return None
        s, m = self.geometry.size, len(self.channels)
        probes = np.vstack([np.zeros(3 * s + m), np.eye(3 * s + m)])
        out = self.outputs(probes[:, : 3 * s].reshape(-1, s, 3), method, probes[:, 3 * s :] if m else None)
        parts = [out.vectors.reshape(len(probes), -1), out.centre]
        if out.tensor is not None:
            parts.append(out.tensor.reshape(len(probes), 9))
        elif out.baseline is not None:
            parts.append(out.baseline)
        y = np.hstack(parts)
        return AffineOutputs(np.ascontiguousarray((y[1:] - y[0]).T), y[0].copy(), s, self.geometry.gradient_kind)

    def field_and_gradient(
        self, raw: ArrayLike, method: str = "difference", currents: ArrayLike | None = None,
        temperatures: ArrayLike | None = None,
    ) -> tuple[Array, Array, Array]:
        """Corrected vectors (N, S, 3), centre field (N, 3) and tensor (N, 3, 3) from raw sets, output frame."""
        b = self.apply_array(raw, currents, temperatures)
        g = gradient(b, self.geometry, method)
        if self.rotated:
            g = self.output_rotation @ g @ self.output_rotation.T  # type: ignore[union-attr]
            b = self.to_output_frame(b)
        return b, centre_field(b), g

    def to_parameters(self) -> dict[str, Any]:
        """ROS parameters of the correction node (``sensor_names``, ``positions``, per-sensor)."""
        params: dict[str, Any] = {
            "sensor_names": list(self.geometry.names),
            "positions": [float(x) for x in self.geometry.positions.reshape(-1)],
        }
        if self.channels:
            params["interference_channels"] = list(self.channels)
        for i, (name, m, o) in enumerate(zip(self.geometry.names, self.matrices, self.offsets)):
            params[name] = {"matrix": [float(x) for x in m.reshape(-1)], "offset": [float(x) for x in o]}
            if self.covariances is not None and np.all(np.isfinite(self.covariances[i])):
                params[name]["covariance"] = [float(x) for x in self.covariances[i].reshape(-1)]
            if self.channels:
                params[name]["interference"] = [float(x) for x in self.interference[i].reshape(-1)]  # type: ignore[index]
            if np.any(self.time_offsets):  # type: ignore[arg-type]
                params[name]["time_offset"] = float(self.time_offsets[i])  # type: ignore[index]
        for key, value in self._temperature_and_frame_parameters().items():
            if isinstance(value, dict):
                params[key].update(value)
            else:
                params[key] = value
        return params

    def _temperature_and_frame_parameters(self) -> dict[str, Any]:
        """``temperature_reference`` and per sensor ``offset_per_kelvin``, ``matrix_per_kelvin`` (when the
        calibration has a reference); per sensor ``calibration_temperatures`` ([min, max] deg C, when known);
        ``output_rotation`` and ``frame_id`` (when it has an output frame)."""
        out: dict[str, Any] = {}
        if self.temperature_reference is not None:
            out["temperature_reference"] = float(self.temperature_reference)
            for i, name in enumerate(self.geometry.names):
                out[name] = {"offset_per_kelvin": [float(x) for x in self.offset_tempco[i]],  # type: ignore[index]
                             "matrix_per_kelvin": [float(x) for x in self.matrix_tempco[i].reshape(-1)]}  # type: ignore[index]
        if self.temperature_span is not None:
            for name, row in zip(self.geometry.names, self.temperature_span):
                if np.all(np.isfinite(row)):
                    out.setdefault(name, {})["calibration_temperatures"] = [float(x) for x in row]
        if self.rotated or self.frame_id:
            out["output_rotation"] = [float(x) for x in self.output_rotation.reshape(-1)]  # type: ignore[union-attr]
        if self.frame_id:
            out["frame_id"] = self.frame_id
        return out

    @classmethod
    def from_parameters(
        cls, params: dict[str, Any], metadata: dict[str, Any] | None = None, uncorrected: Sequence[str] = ()
    ) -> "ArrayCalibration":
        """Inverse of :meth:`to_parameters`.

        Every sensor needs its ``matrix`` and ``offset``: a missing block is an
        :class:`InputError` naming the sensor, unless the sensor is listed in
        ``uncorrected`` (then identity and zero, on purpose). ``covariance`` is optional
        and must be given for all sensors or none.
        """
        geometry = _geometry_of(params)
        names = geometry.names
        channels = _channels_of(params)
        blocks = [_sensor_block(name, params.get(name), channels, name in uncorrected) for name in names]
        mats, offs, covs, infs, lags = (list(x) for x in zip(*blocks))
        for name, cov in zip(names, covs):
            bounds.check_covariance(name, cov)
        if "calibration_intensity" in params:
            bounds.check_intensity("calibration_intensity", params["calibration_intensity"])
        given = [not np.isnan(c).all() for c in covs]
        if any(given) and not all(g or n in uncorrected for g, n in zip(given, names)):
            raise InputError("calibration gives a covariance for some sensors but not all")
        if not any(given):
            covs = []
        checked = [check_sensor(n, m, o) for n, m, o in zip(names, mats, offs)]
        for name, lag in zip(names, lags):
            if not np.isfinite(lag) or abs(lag) > MAX_TIME_OFFSET:
                raise InputError(f"{name}.time_offset {lag} s is not a lag (finite, within +-{MAX_TIME_OFFSET:g} s)")
        return cls(geometry, np.stack([c[0] for c in checked]), np.stack([c[1] for c in checked]), dict(metadata or {}),
                   np.stack(covs) if covs else None, tuple(channels), np.stack(infs) if channels else None,  # type: ignore[arg-type]
                   np.asarray(lags, dtype=float), **_temperature_and_frame(params, names))


# -- reading a calibration's parameters --------------------------------------------------------------
def _geometry_of(params: dict[str, Any]) -> ArrayGeometry:
    """The array's sensor names and positions (m) from a calibration's parameters."""
    try:
        names = tuple(params["sensor_names"])
        bounds.check_positions(params["positions"])
        return ArrayGeometry(names, np.asarray(params["positions"], dtype=float))
    except KeyError as exc:
        raise InputError(f"calibration is missing {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise InputError(f"calibration has malformed sensor_names/positions: {exc}") from None


def _channels_of(params: dict[str, Any]) -> list[str]:
    """The interference channels' names (none when not given)."""
    channels = params.get("interference_channels") or []
    if not isinstance(channels, (list, tuple)) or not all(isinstance(c, str) for c in channels):
        raise InputError("interference_channels must be a list of channel names")
    return list(channels)


def _sensor_mapping(name: str, block: Any, uncorrected: bool) -> dict[str, Any]:
    """Sensor ``name``'s block of parameters; an uncorrected sensor may have none (identity, zero)."""
    if block is None or block == {}:
        if not uncorrected:
            raise InputError(f"calibration has no matrix and offset for sensor {name!r}; calibrate it, or list it as "
                             "uncorrected to use its raw readings on purpose")
        block = {}
    if not isinstance(block, dict):
        raise InputError(f"calibration entry {name!r} must be a mapping with matrix and offset")
    if not uncorrected and not {"matrix", "offset"} <= set(block):
        missing = sorted({"matrix", "offset"} - set(block))
        raise InputError(f"calibration entry {name!r} has no {' or '.join(missing)}")
    return block


def _sensor_block(name: str, block: Any, channels: list[str],
                  uncorrected: bool) -> tuple[Array, Array, Array, Array | None, float]:
    """Sensor ``name``'s matrix (9,), offset (3,) T, covariance (3, 3) (NaN when not given), interference
    (3, channels) T/A (None without channels) and lag (s), checked against their bounds."""
    block = _sensor_mapping(name, block, uncorrected)
    try:
        matrix = np.asarray(block.get("matrix", np.eye(3).reshape(-1)), dtype=float)
        offset = np.asarray(block.get("offset", [0.0, 0.0, 0.0]), dtype=float)
        cov = (np.asarray(block["covariance"], dtype=float).reshape(3, 3) if "covariance" in block
               else np.full((3, 3), np.nan))
        lag = block.get("time_offset", 0.0)
        if isinstance(lag, bool) or not isinstance(lag, (int, float)):
            raise InputError(f"{name}.time_offset must be a number of seconds, got {lag!r}")
        gains = None
        if channels:
            gains = np.asarray(block.get("interference", np.zeros(3 * len(channels))), dtype=float)
            if gains.size != 3 * len(channels):
                raise InputError(f"{name}.interference needs {3 * len(channels)} numbers (3 x "
                                 f"{len(channels)} row-major, T/A), got {gains.size}")
            bounds.check_bounded(f"{name}.interference", gains, bounds.MAX_INTERFERENCE, "T/A")
            gains = gains.reshape(3, len(channels))
        if "noise" in block:
            bounds.check_noise(f"{name}.noise", block["noise"])
    except (TypeError, ValueError):
        raise InputError(f"calibration entry {name!r} has a non-numeric matrix, offset, covariance or "
                         "interference") from None
    return matrix, offset, cov, gains, float(lag)


# -- temperature terms and output frame in parameters ----------------------------------------------
def _unset(value: Any) -> bool:
    """A parameter value that says "not given": None, an empty string or list, NaN."""
    if value is None or (isinstance(value, (str, list, tuple)) and len(value) == 0):
        return True
    return isinstance(value, float) and not np.isfinite(value)


def _numbers(value: Any, count: int, what: str, unit: str) -> Array:
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be {count} numbers ({unit})") from None
    if v.size != count:
        raise InputError(f"{what} needs {count} numbers ({unit}), got {v.size}")
    return v


def _temperature_span(params: dict[str, Any], names: Sequence[str]) -> Array | None:
    """(S, 2) deg C of the sensors' ``calibration_temperatures`` (NaN where a sensor has none; None when
    none has), each checked (:func:`~magcal_ros.core.calibration_bounds.check_temperature_span`)."""
    rows = []
    for name in names:
        block = params.get(name) if isinstance(params.get(name), dict) else {}
        value = block.get("calibration_temperatures")  # type: ignore[union-attr]
        rows.append(np.full(2, np.nan) if _unset(value) else
                    bounds.check_temperature_span(f"{name}.calibration_temperatures", value))
    return None if all(np.isnan(r).all() for r in rows) else np.stack(rows)


def _temperature_and_frame(params: dict[str, Any], names: Sequence[str]) -> dict[str, Any]:
    """The temperature terms and output frame of a parameter dict (see :meth:`ArrayCalibration.to_parameters`)."""
    ref = params.get("temperature_reference")
    if _unset(ref):
        ref = None
    elif isinstance(ref, bool) or not isinstance(ref, (int, float)):
        raise InputError(f"temperature_reference must be a number (deg C), got {ref!r}")
    offsets, matrices = [], []
    for name in names:
        block = params.get(name) if isinstance(params.get(name), dict) else {}
        a, g = block.get("offset_per_kelvin"), block.get("matrix_per_kelvin")  # type: ignore[union-attr]
        offsets.append(np.zeros(3) if _unset(a) else _numbers(a, 3, f"{name}.offset_per_kelvin", "T/K"))
        matrices.append(np.zeros((3, 3)) if _unset(g) else _numbers(g, 9, f"{name}.matrix_per_kelvin",
                                                                    "row-major 3x3, 1/K").reshape(3, 3))
    rot = params.get("output_rotation")
    rotation = None if _unset(rot) else _numbers(rot, 9, "output_rotation", "row-major 3x3").reshape(3, 3)
    frame = params.get("frame_id")
    if not _unset(frame) and not isinstance(frame, str):
        raise InputError(f"frame_id must be a frame name, got {frame!r}")
    return {
        "temperature_span": _temperature_span(params, names),
        "temperature_reference": None if ref is None else float(ref),
        "offset_tempco": np.stack(offsets),
        "matrix_tempco": np.stack(matrices),
        "output_rotation": rotation,
        "frame_id": None if _unset(frame) else frame,
    }

"""The array calibration: per sensor ``B = matrix (raw - offset) - interference @ u``.

This is the object the solver returns, the calibration file stores and the correction
node applies. Matrices map raw sensor axes (T) into the platform frame (T); ``u`` are the
currents (A) of the interference channels, when the calibration has any. ``time_offsets``
(s) say when each sensor's readings were taken: a reading stamped ``t`` is the field at
``t - time_offset`` (positive: the sensor reads late); they are applied where sets are
formed (:mod:`magcal_ros.core.sync`), not by :meth:`ArrayCalibration.apply`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

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

    @classmethod
    def identity(cls, geometry: ArrayGeometry) -> "ArrayCalibration":
        """No correction: identity matrices, zero offsets."""
        s = geometry.size
        return cls(geometry, np.tile(np.eye(3), (s, 1, 1)), np.zeros((s, 3)), {"method": "identity"})

    def apply(self, raw: ArrayLike, currents: ArrayLike | None = None) -> Array:
        """Corrected vectors (N, S, 3) in T, platform frame, from raw (N, S, 3) in T.

        ``currents`` (N, m) in A, one column per :attr:`channels`: their interference is
        subtracted. Required when the calibration has channels.
        """
        r = np.asarray(raw, dtype=float)
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

    def outputs(self, raw: ArrayLike, method: str = "difference", currents: ArrayLike | None = None) -> CorrectedSets:
        """Corrected vectors, centre field and the gradient the geometry determines (see :class:`CorrectedSets`)."""
        b = self.apply(raw, currents)
        kind = self.geometry.gradient_kind
        return CorrectedSets(
            b, centre_field(b),
            gradient(b, self.geometry, method) if kind == "tensor" else None,
            baseline_gradient(b, self.geometry) if kind == "baseline" else None,
        )

    def field_and_gradient(
        self, raw: ArrayLike, method: str = "difference", currents: ArrayLike | None = None
    ) -> tuple[Array, Array, Array]:
        """Corrected vectors (N, S, 3), centre field (N, 3) and tensor (N, 3, 3) from raw sets."""
        b = self.apply(raw, currents)
        return b, centre_field(b), gradient(b, self.geometry, method)

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
        return params

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
        try:
            names = tuple(params["sensor_names"])
            geometry = ArrayGeometry(names, np.asarray(params["positions"], dtype=float))
        except KeyError as exc:
            raise InputError(f"calibration is missing {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"calibration has malformed sensor_names/positions: {exc}") from None
        channels = params.get("interference_channels") or []
        if not isinstance(channels, (list, tuple)) or not all(isinstance(c, str) for c in channels):
            raise InputError("interference_channels must be a list of channel names")
        mats, offs, covs, infs, lags = [], [], [], [], []
        for name in names:
            block = params.get(name)
            if block is None or block == {}:
                if name not in uncorrected:
                    raise InputError(
                        f"calibration has no matrix and offset for sensor {name!r}; calibrate it, or list it as "
                        "uncorrected to use its raw readings on purpose"
                    )
                block = {}
            if not isinstance(block, dict):
                raise InputError(f"calibration entry {name!r} must be a mapping with matrix and offset")
            if name not in uncorrected and not {"matrix", "offset"} <= set(block):
                missing = sorted({"matrix", "offset"} - set(block))
                raise InputError(f"calibration entry {name!r} has no {' or '.join(missing)}")
            try:
                mats.append(np.asarray(block.get("matrix", np.eye(3).reshape(-1)), dtype=float))
                offs.append(np.asarray(block.get("offset", [0.0, 0.0, 0.0]), dtype=float))
                covs.append(np.asarray(block["covariance"], dtype=float).reshape(3, 3) if "covariance" in block
                            else np.full((3, 3), np.nan))
                lag = block.get("time_offset", 0.0)
                if isinstance(lag, bool) or not isinstance(lag, (int, float)):
                    raise InputError(f"{name}.time_offset must be a number of seconds, got {lag!r}")
                lags.append(float(lag))
                if channels:
                    gains = np.asarray(block.get("interference", np.zeros(3 * len(channels))), dtype=float)
                    if gains.size != 3 * len(channels):
                        raise InputError(f"{name}.interference needs {3 * len(channels)} numbers (3 x "
                                         f"{len(channels)} row-major, T/A), got {gains.size}")
                    infs.append(gains.reshape(3, len(channels)))
            except (TypeError, ValueError):
                raise InputError(f"calibration entry {name!r} has a non-numeric matrix, offset, covariance or "
                                 "interference") from None
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
                   np.stack(covs) if covs else None, tuple(channels), np.stack(infs) if channels else None,
                   np.asarray(lags, dtype=float))

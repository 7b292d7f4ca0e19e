"""The array calibration: one ``matrix`` and ``offset`` per sensor, ``B = matrix (raw - offset)``.

This is the object the solver returns, the calibration file stores and the correction
node applies. Matrices map raw sensor axes (T) into the platform frame (T).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.tensor import centre_field, gradient
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
class ArrayCalibration:
    """Per-sensor corrections of an array, with its geometry and provenance."""

    geometry: ArrayGeometry
    matrices: Array
    """(S, 3, 3): raw sensor axes to platform frame."""
    offsets: Array
    """(S, 3): raw offsets in T."""
    metadata: dict[str, Any] = field(default_factory=dict)
    """Provenance: method, time, sample count, residuals (free-form, YAML-safe)."""

    def __post_init__(self) -> None:
        m = np.asarray(self.matrices, dtype=float)
        o = np.asarray(self.offsets, dtype=float)
        s = self.geometry.size
        if m.shape != (s, 3, 3) or o.shape != (s, 3):
            raise InputError(f"need {s} matrices (3x3) and offsets (3), got {m.shape} and {o.shape}")
        checked = [check_sensor(n, mi, oi) for n, mi, oi in zip(self.geometry.names, m, o)]
        object.__setattr__(self, "matrices", np.stack([c[0] for c in checked]))
        object.__setattr__(self, "offsets", np.stack([c[1] for c in checked]))

    @classmethod
    def identity(cls, geometry: ArrayGeometry) -> "ArrayCalibration":
        """No correction: identity matrices, zero offsets."""
        s = geometry.size
        return cls(geometry, np.tile(np.eye(3), (s, 1, 1)), np.zeros((s, 3)), {"method": "identity"})

    def apply(self, raw: ArrayLike) -> Array:
        """Corrected vectors (N, S, 3) in T, platform frame, from raw (N, S, 3) in T."""
        r = np.asarray(raw, dtype=float)
        return np.einsum("sij,nsj->nsi", self.matrices, r - self.offsets)

    def field_and_gradient(self, raw: ArrayLike, method: str = "difference") -> tuple[Array, Array, Array]:
        """Corrected vectors (N, S, 3), centre field (N, 3) and tensor (N, 3, 3) from raw sets."""
        b = self.apply(raw)
        return b, centre_field(b), gradient(b, self.geometry, method)

    def to_parameters(self) -> dict[str, Any]:
        """ROS parameters of the correction node (``sensor_names``, ``positions``, per-sensor)."""
        params: dict[str, Any] = {
            "sensor_names": list(self.geometry.names),
            "positions": [float(x) for x in self.geometry.positions.reshape(-1)],
        }
        for name, m, o in zip(self.geometry.names, self.matrices, self.offsets):
            params[name] = {"matrix": [float(x) for x in m.reshape(-1)], "offset": [float(x) for x in o]}
        return params

    @classmethod
    def from_parameters(cls, params: dict[str, Any], metadata: dict[str, Any] | None = None) -> "ArrayCalibration":
        """Inverse of :meth:`to_parameters`; missing sensor blocks mean identity/zero."""
        try:
            names = tuple(params["sensor_names"])
            geometry = ArrayGeometry(names, np.asarray(params["positions"], dtype=float))
        except KeyError as exc:
            raise InputError(f"calibration is missing {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"calibration has malformed sensor_names/positions: {exc}") from None
        mats, offs = [], []
        for name in names:
            block = params.get(name, {}) or {}
            if not isinstance(block, dict):
                raise InputError(f"calibration entry {name!r} must be a mapping with matrix and offset")
            try:
                mats.append(np.asarray(block.get("matrix", np.eye(3).reshape(-1)), dtype=float))
                offs.append(np.asarray(block.get("offset", [0.0, 0.0, 0.0]), dtype=float))
            except (TypeError, ValueError):
                raise InputError(f"calibration entry {name!r} has non-numeric matrix or offset") from None
        checked = [check_sensor(n, m, o) for n, m, o in zip(names, mats, offs)]
        return cls(geometry, np.stack([c[0] for c in checked]), np.stack([c[1] for c in checked]), dict(metadata or {}))

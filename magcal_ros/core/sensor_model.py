"""Per-sensor error model (docs/methods.md, section 1).

A raw reading ``r`` (T, sensor axes) of the platform-frame field ``B`` (T) is
``r = K B + o`` with ``K = C A T^T (I + S)`` and ``o = C A T^T h + o_s``:

- ``C = diag(scale)``, ``A`` the non-orthogonality of angles ``(phi, theta, psi)`` (z is
  the reference axis, y lies in the y-z plane, so ``C A`` is upper triangular),
- ``T`` the sensor-to-platform misalignment in Li et al.'s (2018) Euler convention,
- ``S`` and ``h`` the hull soft and hard iron at the sensor, in the platform frame,
- ``o_s`` the sensor's own offset.

The correction is ``b = M (r - o)``, ``M = K^-1``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.rotation import euler_to_matrix, matrix_to_euler, rq_positive
from magcal_ros.errors import InputError

Array = NDArray[np.float64]


def nonorthogonality(phi: float, theta: float, psi: float) -> Array:
    """Non-orthogonality matrix ``A`` of docs/methods.md, section 1 (angles in rad)."""
    return np.array(
        [
            [np.cos(theta) * np.cos(phi), np.sin(theta) * np.cos(phi), np.sin(phi)],
            [0.0, np.cos(psi), np.sin(psi)],
            [0.0, 0.0, 1.0],
        ]
    )


def _vec3(value: ArrayLike, name: str) -> Array:
    v = np.asarray(value, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


@dataclass(frozen=True)
class SensorErrors:
    """Physical error parameters of one sensor (SI units, angles in rad)."""

    scale: Array = field(default_factory=lambda: np.ones(3))
    angles: Array = field(default_factory=lambda: np.zeros(3))
    """Non-orthogonality ``(phi, theta, psi)``."""
    offset: Array = field(default_factory=lambda: np.zeros(3))
    """Sensor offset ``o_s`` (T, sensor axes)."""
    misalignment: Array = field(default_factory=lambda: np.zeros(3))
    """Euler angles ``(alpha, beta, gamma)`` of ``T`` (sensor to platform)."""
    hard_iron: Array = field(default_factory=lambda: np.zeros(3))
    """Hull hard iron ``h`` (T, platform frame)."""
    soft_iron: Array = field(default_factory=lambda: np.zeros((3, 3)))
    """Hull soft iron ``S`` (dimensionless, platform frame)."""

    def __post_init__(self) -> None:
        for name in ("scale", "angles", "offset", "misalignment", "hard_iron"):
            object.__setattr__(self, name, _vec3(getattr(self, name), name))
        s = np.asarray(self.soft_iron, dtype=float)
        if s.shape != (3, 3) or not np.all(np.isfinite(s)):
            raise InputError("soft_iron must be a finite 3x3 matrix")
        object.__setattr__(self, "soft_iron", s)
        if np.any(self.scale <= 0):
            raise InputError("scale factors must be positive")

    @property
    def triangular(self) -> Array:
        """``C A``: the upper-triangular part of ``K`` (scale and non-orthogonality)."""
        return np.diag(self.scale) @ nonorthogonality(*self.angles)

    @property
    def rotation(self) -> Array:
        """``T``: sensor-to-platform rotation."""
        return euler_to_matrix(*self.misalignment)

    def forward(self) -> tuple[Array, Array]:
        """``(K, o)`` such that ``r = K B + o`` for the platform-frame field ``B``."""
        ca_t = self.triangular @ self.rotation.T
        k = ca_t @ (np.eye(3) + self.soft_iron)
        o = ca_t @ self.hard_iron + self.offset
        return k, o

    def correction(self) -> tuple[Array, Array]:
        """True ``(M, o)`` of the correction ``B = M (r - o)``."""
        k, o = self.forward()
        return np.linalg.inv(k), o

    @classmethod
    def from_forward(cls, k: ArrayLike, offset: ArrayLike) -> "SensorErrors":
        """Decompose ``r = K B + o`` into scale, non-orthogonality and misalignment.

        ``K = (C A) T^T`` by an RQ decomposition with a positive diagonal. Hull soft iron
        cannot be told apart from these from data and is folded into them; hard iron is
        folded into ``offset``.
        """
        kk = np.asarray(k, dtype=float)
        if kk.shape != (3, 3) or not np.all(np.isfinite(kk)) or np.linalg.det(kk) <= 0:
            raise InputError("K must be a finite 3x3 matrix with positive determinant")
        upper, q = rq_positive(kk)
        scale = np.linalg.norm(upper, axis=1)
        a = upper / scale[:, None]
        phi = float(np.arcsin(np.clip(a[0, 2], -1, 1)))
        theta = float(np.arctan2(a[0, 1], a[0, 0]))
        psi = float(np.arcsin(np.clip(a[1, 2], -1, 1)))
        return cls(
            scale=scale,
            angles=np.array([phi, theta, psi]),
            offset=np.asarray(offset, dtype=float),
            misalignment=np.array(matrix_to_euler(q.T)),
        )

    @classmethod
    def from_correction(cls, matrix: ArrayLike, offset: ArrayLike) -> "SensorErrors":
        """Inverse of :meth:`correction`: physical parameters of ``B = M (r - o)``."""
        return cls.from_forward(np.linalg.inv(np.asarray(matrix, dtype=float)), offset)

"""Magnetic fields: the geomagnetic field and point dipoles (SI units).

World frame: x north, y east, z down (NED), as in the papers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.units import MU0_OVER_4PI

Array = NDArray[np.float64]


def earth_field(intensity: float, inclination_deg: float, declination_deg: float) -> Array:
    """Field vector (T, NED) of total intensity ``intensity`` (T) and the given angles (deg)."""
    inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
    return intensity * np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])


@dataclass(frozen=True)
class Dipole:
    """A point dipole: ``position`` (m, world frame) and ``moment`` (A m^2, world frame)."""

    position: Array
    moment: Array

    def field(self, points: ArrayLike) -> Array:
        """Field (T) at ``points`` (..., 3) in metres."""
        r = np.asarray(points, dtype=float) - np.asarray(self.position, dtype=float)
        dist = np.linalg.norm(r, axis=-1, keepdims=True)
        u = r / dist
        m = np.asarray(self.moment, dtype=float)
        mu = np.sum(u * m, axis=-1, keepdims=True)
        return MU0_OVER_4PI * (3.0 * mu * u - m) / dist**3

    def gradient(self, points: ArrayLike) -> Array:
        """Gradient tensor ``G[..., i, j] = dB_j / dx_i`` (T/m) at ``points`` (..., 3)."""
        r = np.asarray(points, dtype=float) - np.asarray(self.position, dtype=float)
        m = np.asarray(self.moment, dtype=float)
        d = np.linalg.norm(r, axis=-1)[..., None, None]
        rr = r[..., :, None] * r[..., None, :]
        mr = np.sum(m * r, axis=-1)[..., None, None]
        rm = r[..., :, None] * m[None, :] if r.ndim == 1 else r[..., :, None] * m[..., None, :]
        eye = np.eye(3)
        g = 3.0 * (rm + np.swapaxes(rm, -1, -2) + mr * eye) / d**5 - 15.0 * mr * rr / d**7
        return MU0_OVER_4PI * g

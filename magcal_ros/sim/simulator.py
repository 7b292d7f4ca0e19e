"""Simulated array recordings with known truth.

The platform sits at ``position`` (m, world NED) and takes the attitudes ``R_k``
(platform to world). Sensor ``i`` at ``p_i`` (platform frame) sees the platform-frame
field ``B_ik = R_k^T (B_earth + sum dipole(position + R_k p_i))`` and reads
``r = K_i B + o_i`` (:mod:`magcal_ros.core.sensor_model`) plus noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.field import Dipole
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.recording import Recording
from magcal_ros.core.sensor_model import SensorErrors
from magcal_ros.core.stamps import seconds_to_ns
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

NoiseKind = Literal["gaussian", "uniform"]
NoiseDomain = Literal["raw", "sensor"]


@dataclass(frozen=True)
class Truth:
    """What a perfect calibration would give, per set, platform frame (T, T/m)."""

    field: Array
    """(N, S, 3) field at each sensor."""
    centre: Array
    """(N, 3) field at the array centre."""
    gradient: Array
    """(N, 3, 3) gradient at the array centre, ``G[i, j] = dB_j/dx_i``."""
    attitudes: Array
    """(N, 3, 3) platform-to-world rotations."""
    calibration: ArrayCalibration
    """The true per-sensor corrections (raw to the true platform frame)."""


@dataclass(frozen=True)
class ArraySimulation:
    """A sensor array with known errors in a known field."""

    geometry: ArrayGeometry
    sensors: tuple[SensorErrors, ...]
    earth: Array
    """Uniform background field (T, world frame)."""
    noise: float = 1.0 * NT
    """Noise standard deviation per axis (T)."""
    noise_kind: NoiseKind = "gaussian"
    noise_domain: NoiseDomain = "raw"
    noise_correlation: float = 0.0
    """AR(1) coefficient of the noise from one set to the next (0: white; 0.9: slow, as on a
    real vehicle); the noise keeps its standard deviation ``noise``."""
    """``raw``: added to the reading; ``sensor``: added to the sensor's ideal orthogonal
    output before scale and non-orthogonality (Li et al.'s (2018) simulation)."""
    dipoles: tuple[Dipole, ...] = ()
    position: Array = field(default_factory=lambda: np.zeros(3))
    """Array centre position (m, world frame)."""

    def __post_init__(self) -> None:
        if len(self.sensors) != self.geometry.size:
            raise InputError(f"{self.geometry.size} sensors in the geometry but {len(self.sensors)} error sets")
        if self.noise < 0 or not np.isfinite(self.noise):
            raise InputError("noise must be a finite standard deviation >= 0")
        if self.noise_kind not in ("gaussian", "uniform") or self.noise_domain not in ("raw", "sensor"):
            raise InputError("noise_kind must be gaussian|uniform and noise_domain raw|sensor")
        if not (0.0 <= self.noise_correlation < 1.0):
            raise InputError("noise_correlation must be in [0, 1)")

    def true_calibration(self) -> ArrayCalibration:
        """Corrections that map raw readings exactly into the true platform frame."""
        pairs = [s.correction() for s in self.sensors]
        return ArrayCalibration(
            self.geometry, np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]), {"method": "truth"}
        )

    def _noise(self, shape: tuple[int, ...], rng: np.random.Generator) -> Array:
        if self.noise_kind == "gaussian":
            n = rng.normal(0.0, self.noise, shape)
        else:
            half = self.noise * np.sqrt(3.0)  # uniform with standard deviation `noise`
            n = rng.uniform(-half, half, shape)
        rho = self.noise_correlation
        if rho:
            scale = np.sqrt(1.0 - rho * rho)
            for k in range(1, shape[0]):  # AR(1) along the sets, same marginal sd
                n[k] = rho * n[k - 1] + scale * n[k]
        return n

    def platform_field(self, attitudes: ArrayLike) -> tuple[Array, Array, Array]:
        """Noise-free (N, S, 3) sensor fields, (N, 3) centre field, (N, 3, 3) centre gradient."""
        rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
        world_pos = self.position + np.einsum("nij,sj->nsi", rot, self.geometry.positions)
        centre_pos = self.position + rot @ self.geometry.centre
        b_world = np.broadcast_to(self.earth, world_pos.shape).copy()
        c_world = np.broadcast_to(self.earth, centre_pos.shape).copy()
        g_world = np.zeros((len(rot), 3, 3))
        for d in self.dipoles:
            b_world += d.field(world_pos)
            c_world += d.field(centre_pos)
            g_world += d.gradient(centre_pos)
        b = np.einsum("nji,nsj->nsi", rot, b_world)
        c = np.einsum("nji,nj->ni", rot, c_world)
        g = np.einsum("nki,nkl,nlj->nij", rot, g_world, rot)
        return b, c, g

    def run(
        self,
        attitudes: ArrayLike,
        rng: np.random.Generator | int | None = None,
        rate: float = 10.0,
        start: float = 0.0,
    ) -> tuple[Recording, Truth]:
        """Raw recording and truth for the given attitudes, ``rate`` sets per second from ``start`` (s).

        Stamps are integer nanoseconds (``start`` rounded to the nanosecond, then ``k / rate``).
        """
        gen = np.random.default_rng(rng)
        rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
        b, c, g = self.platform_field(rot)
        raw = np.empty_like(b)
        for i, s in enumerate(self.sensors):
            ca = s.triangular
            z = np.einsum("ij,nj->ni", s.rotation.T, np.einsum("ij,nj->ni", np.eye(3) + s.soft_iron, b[:, i]) + s.hard_iron)
            if self.noise_domain == "sensor":
                z = z + self._noise(z.shape, gen)
            raw[:, i] = z @ ca.T + s.offset
            if self.noise_domain == "raw":
                raw[:, i] += self._noise(z.shape, gen)
        stamps = seconds_to_ns(start) + np.rint(np.arange(len(rot)) * (NS_PER_S / rate)).astype(np.int64)
        rec = Recording(self.geometry.names, stamps, raw)
        return rec, Truth(b, c, g, rot, self.true_calibration())


def random_sensor_errors(
    rng: np.random.Generator | int | None,
    scale_sd: float = 0.02,
    angle_sd_deg: float = 1.0,
    offset_sd: float = 200 * NT,
    misalignment_sd_deg: float = 2.0,
    hard_iron_sd: float = 0.0,
    soft_iron_sd: float = 0.0,
) -> SensorErrors:
    """One sensor's errors drawn with the given spreads (defaults: a typical fluxgate)."""
    gen = np.random.default_rng(rng)
    return SensorErrors(
        scale=1.0 + gen.normal(0, scale_sd, 3),
        angles=np.radians(gen.normal(0, angle_sd_deg, 3)),
        offset=gen.normal(0, offset_sd, 3),
        misalignment=np.radians(gen.normal(0, misalignment_sd_deg, 3)),
        hard_iron=gen.normal(0, hard_iron_sd, 3),
        soft_iron=gen.normal(0, soft_iron_sd, (3, 3)),
    )

"""Simulated array recordings with known truth.

The platform sits at ``position`` (m, world NED) and takes the attitudes ``R_k``
(platform to world). Sensor ``i`` at ``p_i`` (platform frame) sees the platform-frame
field ``B_ik = R_k^T (B_earth + sum dipole(position + R_k p_i))`` and reads
``r = K_i B + o_i`` (:mod:`magcal_ros.core.sensor_model`) plus noise.

Thrusters (or any current on the platform) add, at set ``k``, the platform-fixed field
``D_i u_k``: ``D_i`` (3 x m, T/A) is the field at ``p_i`` of a dipole of moment
``moment_per_ampere`` (A m^2 per A, platform frame) at the thruster's position (platform
frame), ``u_k`` the thrusters' currents (A). The sensor reads ``K_i (B_ik + D_i u_k) + o_i``;
the truth field ``B_ik`` excludes it and the true calibration carries ``D`` as its
interference.
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
    """The true per-sensor corrections (raw to the true platform frame), with the thrusters'
    interference gains (T/A) when there are thrusters."""
    currents: Array = field(default_factory=lambda: np.zeros((0, 0)))
    """(N, m) thruster currents (A) at each set, channels as ``calibration.channels``."""


@dataclass(frozen=True)
class Thruster:
    """A current-carrying device fixed to the platform, seen as a point dipole per ampere.

    ``position`` (m) and ``moment_per_ampere`` (A m^2 / A) in the platform frame; ``channel``
    names its current (e.g. ``thruster1/battery``).
    """

    channel: str
    position: Array
    moment_per_ampere: Array

    def gains(self, positions: ArrayLike) -> Array:
        """(S, 3) field per ampere (T/A, platform frame) at ``positions`` (S, 3) m, platform frame."""
        return Dipole(np.asarray(self.position, dtype=float), np.asarray(self.moment_per_ampere, dtype=float)).field(positions)


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
    thrusters: tuple[Thruster, ...] = ()
    """Platform-fixed current interference, one channel each."""

    def __post_init__(self) -> None:
        if len(self.sensors) != self.geometry.size:
            raise InputError(f"{self.geometry.size} sensors in the geometry but {len(self.sensors)} error sets")
        if self.noise < 0 or not np.isfinite(self.noise):
            raise InputError("noise must be a finite standard deviation >= 0")
        if self.noise_kind not in ("gaussian", "uniform") or self.noise_domain not in ("raw", "sensor"):
            raise InputError("noise_kind must be gaussian|uniform and noise_domain raw|sensor")
        if not (0.0 <= self.noise_correlation < 1.0):
            raise InputError("noise_correlation must be in [0, 1)")
        for t in self.thrusters:
            if np.min(np.linalg.norm(self.geometry.positions - np.asarray(t.position, dtype=float), axis=1)) < 1e-3:
                raise InputError(f"thruster {t.channel} lies on a sensor position: move it away")

    @property
    def channels(self) -> tuple[str, ...]:
        """The thrusters' current channels."""
        return tuple(t.channel for t in self.thrusters)

    def interference(self) -> Array:
        """(S, 3, m) the thrusters' field per ampere at each sensor (T/A, platform frame)."""
        gains = [t.gains(self.geometry.positions) for t in self.thrusters]
        return np.stack(gains, axis=2) if gains else np.zeros((self.geometry.size, 3, 0))

    def true_calibration(self) -> ArrayCalibration:
        """Corrections that map raw readings exactly into the true platform frame (and the
        thrusters' true interference)."""
        pairs = [s.correction() for s in self.sensors]
        return ArrayCalibration(
            self.geometry, np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]), {"method": "truth"},
            None, self.channels, self.interference() if self.thrusters else None,
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

    def platform_field(self, attitudes: ArrayLike, track: ArrayLike | None = None) -> tuple[Array, Array, Array]:
        """Noise-free (N, S, 3) sensor fields, (N, 3) centre field, (N, 3, 3) centre gradient.

        ``track`` (N, 3) m, world frame: the platform's position at each set (a vehicle passing
        the dipoles); default :attr:`position` throughout."""
        rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
        where = self.position if track is None else np.asarray(track, dtype=float).reshape(len(rot), 1, 3)
        world_pos = where + np.einsum("nij,sj->nsi", rot, self.geometry.positions)
        centre_pos = (where[:, 0] if track is not None else where) + rot @ self.geometry.centre
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
        currents: ArrayLike | None = None,
        track: ArrayLike | None = None,
    ) -> tuple[Recording, Truth]:
        """Raw recording and truth for the given attitudes, ``rate`` sets per second from ``start`` (s).

        Stamps are integer nanoseconds (``start`` rounded to the nanosecond, then ``k / rate``).
        ``currents`` (N, m) A of the thrusters at each set (default: all off); the recording
        carries them as its channels. ``track`` (N, 3) m: the platform's world position at each
        set (see :meth:`platform_field`).
        """
        gen = np.random.default_rng(rng)
        rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
        m = len(self.thrusters)
        u = np.zeros((len(rot), m)) if currents is None else np.asarray(currents, dtype=float)
        if u.shape != (len(rot), m) or not np.all(np.isfinite(u)):
            raise InputError(f"need finite currents (A) of shape ({len(rot)}, {m}), got {u.shape}")
        b, c, g = self.platform_field(rot, track)
        seen = b + np.einsum("sac,nc->nsa", self.interference(), u)  # the platform's own field added
        raw = np.empty_like(b)
        for i, s in enumerate(self.sensors):
            ca = s.triangular
            z = np.einsum("ij,nj->ni", s.rotation.T, np.einsum("ij,nj->ni", np.eye(3) + s.soft_iron, seen[:, i]) + s.hard_iron)
            if self.noise_domain == "sensor":
                z = z + self._noise(z.shape, gen)
            raw[:, i] = z @ ca.T + s.offset
            if self.noise_domain == "raw":
                raw[:, i] += self._noise(z.shape, gen)
        stamps = seconds_to_ns(start) + np.rint(np.arange(len(rot)) * (NS_PER_S / rate)).astype(np.int64)
        rec = Recording(self.geometry.names, stamps, raw, self.channels, u)
        return rec, Truth(b, c, g, rot, self.true_calibration(), u)


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


def hard_iron_moved(sim: ArraySimulation, rng: np.random.Generator, low: float = 300 * NT,
                    high: float = 800 * NT) -> ArraySimulation:
    """The same array after its hull's hard iron moved by ``low``..``high`` T per axis, random
    signs, on every sensor (a new payload, a magnetised hull): what partial recalibration is for."""
    from dataclasses import replace

    moved = tuple(replace(s, hard_iron=s.hard_iron + rng.choice([-1.0, 1.0], 3) * rng.uniform(low, high, 3))
                  for s in sim.sensors)
    return replace(sim, sensors=moved)

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

A constant world-frame gradient ``G_w`` (``world_gradient``, T/m, ``G[i, j] = dB_j/dx_i``)
over the array adds ``G_w^T (R_k p_i)`` to the world field at sensor ``i`` (a site that is
not uniform: a pier, a ship).

Temperature (``temperatures`` per set, deg C): with ``dT = T - temperature_reference`` the
sensor reads ``r = D(dT) K B + o + dT a`` with ``D = diag(1 / (1 - g dT))``: per axis an
offset tempco ``a`` (T/K, raw axes) and a sensitivity that changes by ``g`` (1/K) per kelvin
to first order, the hull's iron included in ``o`` as before. The form makes the true
correction exactly linear in ``dT``: ``matrix_tempco = -M diag(g)``, ``offset_tempco = a``.

IMU (``imu``, :mod:`magcal_ros.sim.imu`): orientation and gyro of the platform's attitude,
the true calibration's ``output_rotation`` is its mounting and ``frame_id`` its frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.field import Dipole
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import ImuStream
from magcal_ros.core.recording import Recording
from magcal_ros.core.sensor_model import SensorErrors
from magcal_ros.core.stamps import seconds_to_ns
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.errors import InputError
from magcal_ros.sim.attitudes import AttitudePath
from magcal_ros.sim.imu import ImuModel, simulate_imu

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
    temperatures: Array | None = None
    """(N, S) the sensors' true temperatures (deg C) at each set; None: no temperature."""
    imu_orientation: Array | None = None
    """(N, 4) the IMU's true orientation at each set, IMU frame -> world ENU (x, y, z, w); None: no IMU."""
    imu_angular_velocity: Array | None = None
    """(N, 3) the IMU's true angular velocity (rad/s, IMU frame) at each set; NaN without a path in time."""
    imu_stream: ImuStream | None = None
    """The IMU's measured stream at its own rate (or at the set stamps); None: no IMU."""


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
    world_gradient: Array | None = None
    """(3, 3) T/m, world frame (NED), symmetric and traceless: a constant gradient over the array."""
    temperature_reference: float = 20.0
    """Temperature (deg C) at which the sensors' errors are ``sensors``."""
    offset_tempco: Array | None = None
    """(S, 3) T/K, raw axes: each sensor's offset change per kelvin."""
    gain_tempco: Array | None = None
    """(S, 3) 1/K: each sensor axis' sensitivity change per kelvin (first order)."""
    temperature_noise: float = 0.0
    """1-sigma (K) of the recorded temperatures' reading noise (the sensors follow the true ones)."""
    imu: ImuModel | None = None
    """The vehicle's IMU; None: none."""

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
        if self.world_gradient is not None:
            g = np.asarray(self.world_gradient, dtype=float).reshape(3, 3)
            scale = max(float(np.max(np.abs(g))), 1e-30)
            if not np.all(np.isfinite(g)) or np.max(np.abs(g - g.T)) > 1e-9 * scale or abs(np.trace(g)) > 1e-9 * scale:
                raise InputError("a world gradient must be symmetric and traceless (a field with no sources nearby)")
            object.__setattr__(self, "world_gradient", g)
        s = self.geometry.size
        for name in ("offset_tempco", "gain_tempco"):
            v = getattr(self, name)
            if v is not None:
                v = np.asarray(v, dtype=float)
                if v.shape != (s, 3) or not np.all(np.isfinite(v)):
                    raise InputError(f"{name} must be finite, 3 per sensor ({s} sensors)")
                object.__setattr__(self, name, v)
        if not (np.isfinite(self.temperature_noise) and self.temperature_noise >= 0):
            raise InputError("temperature noise must be a finite number >= 0")

    @property
    def channels(self) -> tuple[str, ...]:
        """The thrusters' current channels."""
        return tuple(t.channel for t in self.thrusters)

    def interference(self) -> Array:
        """(S, 3, m) the thrusters' field per ampere at each sensor (T/A, platform frame)."""
        gains = [t.gains(self.geometry.positions) for t in self.thrusters]
        return np.stack(gains, axis=2) if gains else np.zeros((self.geometry.size, 3, 0))

    @property
    def temperature_dependent(self) -> bool:
        """True when the sensors follow their temperature (a non-zero tempco)."""
        return bool(np.any(self._tempcos()[0]) or np.any(self._tempcos()[1]))

    def _tempcos(self) -> tuple[Array, Array]:
        s = self.geometry.size
        a = np.zeros((s, 3)) if self.offset_tempco is None else self.offset_tempco
        g = np.zeros((s, 3)) if self.gain_tempco is None else self.gain_tempco
        return a, g  # type: ignore[return-value]

    def true_calibration(self) -> ArrayCalibration:
        """Corrections that map raw readings exactly into the true platform frame (and the
        thrusters' true interference); with tempcos, the exact temperature terms; with an IMU,
        its mounting as the output rotation and its frame, and the array's lag behind it as every
        sensor's time offset."""
        pairs = [s.correction() for s in self.sensors]
        matrices = np.stack([p[0] for p in pairs])
        extra: dict[str, object] = {}
        if self.temperature_dependent:
            a, g = self._tempcos()
            extra.update(temperature_reference=self.temperature_reference, offset_tempco=a,
                         matrix_tempco=-matrices * g[:, None, :])  # -M diag(g)
        if self.imu is not None:
            extra.update(output_rotation=self.imu.mounting, frame_id=self.imu.frame_id)
            if self.imu.array_lag:  # every sensor's stamps that late on the IMU's clock
                extra.update(time_offsets=np.full(self.geometry.size, self.imu.array_lag))
        return ArrayCalibration(
            self.geometry, matrices, np.stack([p[1] for p in pairs]), {"method": "truth"},
            None, self.channels, self.interference() if self.thrusters else None, **extra,  # type: ignore[arg-type]
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

    def readings(self, index: int, field: ArrayLike, rng: np.random.Generator,
                 temperature: ArrayLike | None = None) -> Array:
        """Raw readings (n, 3) T of sensor ``index`` seeing the platform-frame ``field`` (n, 3) T (its
        errors, hull iron and noise; noise drawn from ``rng``). ``temperature`` (n,) deg C of a sensor
        that follows its temperature: the field part of each raw axis scaled by ``1 / (1 - g dT)`` and
        the offset moved by ``a dT`` (its tempcos ``a`` T/K and ``g`` 1/K, ``dT`` about the reference)."""
        s = self.sensors[index]
        seen = np.asarray(field, dtype=float).reshape(-1, 3)
        ca = s.triangular
        if temperature is None or not self.temperature_dependent:
            z = np.einsum("ij,nj->ni", s.rotation.T, np.einsum("ij,nj->ni", np.eye(3) + s.soft_iron, seen) + s.hard_iron)
            if self.noise_domain == "sensor":
                z = z + self._noise(z.shape, rng)
            raw = z @ ca.T + s.offset
        else:
            a_t, g_t = self._tempcos()
            dt = np.asarray(temperature, dtype=float).reshape(-1, 1) - self.temperature_reference
            zf = np.einsum("ij,nj->ni", s.rotation.T, np.einsum("ij,nj->ni", np.eye(3) + s.soft_iron, seen))
            if self.noise_domain == "sensor":
                zf = zf + self._noise(zf.shape, rng)
            iron = ca @ (s.rotation.T @ s.hard_iron)
            raw = (zf @ ca.T) / (1.0 - g_t[index] * dt) + iron + s.offset + dt * a_t[index]
        if self.noise_domain == "raw":
            raw = raw + self._noise(raw.shape, rng)
        return raw

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
        if self.world_gradient is not None:  # B_j += sum_i x_i G_ij, x the offset from the rotation centre
            gw = self.world_gradient
            b_world += (world_pos - self.position) @ gw
            c_world += (centre_pos - self.position) @ gw
            g_world += gw
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
        temperatures: ArrayLike | None = None,
        continuous: bool = False,
        track: ArrayLike | None = None,
    ) -> tuple[Recording, Truth]:
        """Raw recording and truth for the given attitudes, ``rate`` sets per second from ``start`` (s).

        Stamps are integer nanoseconds (``start`` rounded to the nanosecond, then ``k / rate``).
        ``currents`` (N, m) A of the thrusters at each set (default: all off); the recording
        carries them as its channels. ``temperatures`` (N,) or (N, S) deg C: the sensors' true
        temperatures (recorded with ``temperature_noise``); None: no temperature (the sensors at
        the reference). ``continuous``: the attitudes are a path flown in time, sampled at the
        sets (the IMU then has a gyro). With an IMU the recording carries it (measured at each set).
        ``track`` (N, 3) m: the platform's world position at each set (see :meth:`platform_field`).
        """
        gen = np.random.default_rng(rng)
        rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
        m = len(self.thrusters)
        u = np.zeros((len(rot), m)) if currents is None else np.asarray(currents, dtype=float)
        if u.shape != (len(rot), m) or not np.all(np.isfinite(u)):
            raise InputError(f"need finite currents (A) of shape ({len(rot)}, {m}), got {u.shape}")
        temp = None
        if temperatures is not None:
            temp = np.asarray(temperatures, dtype=float)
            temp = np.repeat(temp[:, None], self.geometry.size, axis=1) if temp.ndim == 1 else temp
            if temp.shape != (len(rot), self.geometry.size) or not np.all(np.isfinite(temp)):
                raise InputError(f"need finite temperatures (deg C) of shape ({len(rot)},) or ({len(rot)}, "
                                 f"{self.geometry.size}), got {temp.shape}")
        elif self.temperature_dependent:
            raise InputError("the sensors follow their temperature: give the temperature of each set")
        b, c, g = self.platform_field(rot, track)
        seen = b + np.einsum("sac,nc->nsa", self.interference(), u)  # the platform's own field added
        raw = np.empty_like(b)
        for i in range(len(self.sensors)):
            raw[:, i] = self.readings(i, seen[:, i], gen, None if temp is None else temp[:, i])
        stamps = seconds_to_ns(start) + np.rint(np.arange(len(rot)) * (NS_PER_S / rate)).astype(np.int64)
        recorded = None
        if temp is not None:
            recorded = temp + (gen.normal(0.0, self.temperature_noise, temp.shape) if self.temperature_noise else 0.0)
        out = None
        if self.imu is not None:
            path = AttitudePath.through(rot, (stamps - stamps[0]) / NS_PER_S) if continuous and len(rot) > 1 else None
            out = simulate_imu(self.imu, rot, stamps, path, gen)
        rec = Recording(self.geometry.names, stamps, raw, self.channels, u, recorded, None if out is None else out.measured)
        truth = Truth(b, c, g, rot, self.true_calibration(), u, temp,
                      None if out is None else out.true_orientation, None if out is None else out.true_angular_velocity,
                      None if out is None else out.stream)
        return rec, truth


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

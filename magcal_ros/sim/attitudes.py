"""Attitude schedules of a calibration manoeuvre.

Every schedule returns (N, 3, 3) rotation matrices ``R_k`` from the platform frame to
the world frame, so the platform-frame field is ``B_k = R_k^T B_world``.

Some schedules are a path flown in time (:data:`CONTINUOUS_SCHEDULES`: consecutive
attitudes a few degrees apart); sampled at the set instants they become a continuous
attitude (:class:`AttitudePath`), whose angular velocity is what a gyro measures. The grids
and random attitudes jump from one attitude to the next: no vehicle flies them, and they
have no angular velocity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

AXES = {"x": 0, "y": 1, "z": 2}


def _tf() -> Any:
    """``scipy.spatial.transform``, imported on first use: it takes a third of a second, which every
    ``magcal`` command would pay (the simulate options are built from this package)."""
    from scipy.spatial import transform

    return transform


def _about(axis: str, angles_rad: Array) -> Array:
    return _tf().Rotation.from_rotvec(np.outer(angles_rad, np.eye(3)[AXES[axis]])).as_matrix()


def single_axis(axis: str = "z", count: int = 36, start_deg: float = 0.0) -> Array:
    """One full turn about a platform ``axis`` in ``count`` equal steps (docs/methods.md, pitfall B)."""
    angles = np.radians(start_deg) + np.arange(count) * 2.0 * np.pi / count
    return _about(axis, angles)


def nested_grid(steps_deg: tuple[float, float, float]) -> Array:
    """Nested turns: z innermost, then y, then x, with the given step per axis (deg).

    The field seen by the platform is ``Rx Ry Rz B_world``: a full z turn, then one y
    step, and so on (Li et al. (2018) section 5.1). ``(30, 30, 30)`` gives Li et al.'s (2018) 12^3 grid.
    """
    out = []
    sx, sy, sz = (np.radians(s) for s in steps_deg)
    nx, ny, nz = (int(round(2 * np.pi / s)) for s in (sx, sy, sz))
    for i in range(nx):
        rx = _about("x", np.array([i * sx]))[0]
        for j in range(ny):
            ry = _about("y", np.array([j * sy]))[0]
            rz = _about("z", np.arange(nz) * sz)
            seen = rx @ ry @ rz  # field in platform = seen @ B_world
            out.append(np.swapaxes(seen, 1, 2))
    return np.concatenate(out)


def li2018_grid() -> Array:
    """Li et al. (2018): 30 deg steps about z, y, x: 1728 attitudes."""
    return nested_grid((30.0, 30.0, 30.0))


def coaxial2022_grid() -> Array:
    """The JNWPU 2022 coaxial calibration paper: x every 60 deg, y every 90 deg, z every 60 deg: 144 attitudes."""
    return nested_grid((60.0, 90.0, 60.0))


def three_rotations(count: int = 10) -> Array:
    """The two-fluxgate gradiometer paper: one turn about each of x, y and z with ``count`` points each."""
    return np.concatenate([single_axis(a, count) for a in "xyz"])


def uniform_random(count: int, rng: np.random.Generator | int | None = None) -> Array:
    """``count`` attitudes drawn uniformly from SO(3)."""
    gen = np.random.default_rng(rng)
    return _tf().Rotation.random(count, random_state=gen).as_matrix()


def yaw_pitch_roll(yaw_deg: Array, pitch_deg: Array, roll_deg: Array) -> Array:
    """Platform-to-world rotations ``Rz(yaw) Ry(pitch) Rx(roll)`` (NED, the vehicle convention), (N, 3, 3)."""
    angles = np.column_stack([yaw_deg, pitch_deg, roll_deg])
    return _tf().Rotation.from_euler("ZYX", angles, degrees=True).as_matrix()


def sea_manoeuvre(
    count: int,
    pitch_deg: float = 5.0,
    roll_deg: float = 2.0,
    turns: float = 2.0,
    wobble_deg: float = 0.0,
    rng: np.random.Generator | int | None = None,
) -> Array:
    """What a vehicle at sea flies: ``turns`` full yaw circles while pitch and roll swing
    slowly through +-``pitch_deg`` and +-``roll_deg`` (a glider's dives and climbs, a UUV's
    trim), plus a smooth random ``wobble_deg`` (waves, a hand). Consecutive attitudes are
    close, as in a real recording sampled in time."""
    gen = np.random.default_rng(rng)
    k = np.arange(count) / max(count - 1, 1)
    phase = gen.uniform(0, 2 * np.pi, 2)
    yaw = 360.0 * turns * k + gen.uniform(0, 360)
    pitch = pitch_deg * np.sin(2 * np.pi * 3.0 * turns * k + phase[0])
    roll = roll_deg * np.sin(2 * np.pi * 5.3 * turns * k + phase[1])
    if wobble_deg > 0:
        walk = np.cumsum(gen.normal(0.0, 1.0, (count, 2)), axis=0)
        walk -= np.linspace(walk[0], walk[-1], count)  # no net drift
        smooth = np.apply_along_axis(lambda c: np.convolve(c, np.ones(9) / 9, mode="same"), 0, walk)
        smooth *= wobble_deg / max(np.abs(smooth).max(), 1e-12)
        pitch, roll = pitch + smooth[:, 0], roll + smooth[:, 1]
    return yaw_pitch_roll(yaw, pitch, roll)


def tumble(count: int, step_deg: float = 3.0, rng: np.random.Generator | int | None = None) -> Array:
    """A smooth random tumble through all attitudes (a hand turning a sensor): the attitude turns
    about a slowly wandering axis by about ``step_deg`` per sample."""
    gen = np.random.default_rng(rng)
    axis = gen.normal(size=3)
    rotation = _tf().Rotation
    out = [rotation.random(random_state=gen)]
    for _ in range(count - 1):
        axis = 0.97 * axis + 0.25 * gen.normal(size=3)
        step = rotation.from_rotvec(np.radians(step_deg) * axis / np.linalg.norm(axis))
        out.append(out[-1] * step)
    return rotation.concatenate(out).as_matrix()


SCHEDULES = {
    "single-axis": lambda n, rng: single_axis("z", n),
    "li2018": lambda n, rng: li2018_grid(),
    "coaxial2022": lambda n, rng: coaxial2022_grid(),
    "three-axes": lambda n, rng: three_rotations(max(1, n // 3)),
    "random": lambda n, rng: uniform_random(n, rng),
    "tumble": lambda n, rng: tumble(n, rng=rng),
    "sea": lambda n, rng: sea_manoeuvre(n, rng=rng),
}
"""Schedules by name: ``f(count, rng) -> (N, 3, 3)``; grids ignore ``count``."""

CONTINUOUS_SCHEDULES: tuple[str, ...] = ("single-axis", "sea", "tumble")
"""Schedules that are a path in time (consecutive attitudes close): a gyro sees their turn rate."""


@dataclass(frozen=True)
class AttitudePath:
    """A continuous attitude through ``attitudes`` (N, 3, 3) platform to world at ``times`` (N,) s: a
    cubic spline on rotations (continuous angular velocity and acceleration, exactly the given
    attitude at each given time)."""

    times: NDArray[np.float64]
    spline: Any

    @classmethod
    def through(cls, attitudes: ArrayLike, times: ArrayLike) -> "AttitudePath":
        """The path through ``attitudes`` at increasing ``times`` (s)."""
        t = np.asarray(times, dtype=float)
        return cls(t, _tf().RotationSpline(t, _tf().Rotation.from_matrix(np.asarray(attitudes, dtype=float))))

    def attitude(self, times: ArrayLike) -> Array:
        """Platform-to-world rotations (n, 3, 3) at ``times`` (s, within the path's span)."""
        return self.spline(np.asarray(times, dtype=float)).as_matrix()  # type: ignore[no-any-return]

    def angular_velocity(self, times: ArrayLike) -> Array:
        """Angular velocity (n, 3) rad/s in the platform frame (``dR/dt = R [w]x``) at ``times`` (s)."""
        return np.asarray(self.spline(np.asarray(times, dtype=float), 1), dtype=float).reshape(-1, 3)

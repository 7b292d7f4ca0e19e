"""Attitude schedules of a calibration manoeuvre.

Every schedule returns (N, 3, 3) rotation matrices ``R_k`` from the platform frame to
the world frame, so the platform-frame field is ``B_k = R_k^T B_world``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Array = NDArray[np.float64]

AXES = {"x": 0, "y": 1, "z": 2}


def _about(axis: str, angles_rad: Array) -> Array:
    return Rotation.from_rotvec(np.outer(angles_rad, np.eye(3)[AXES[axis]])).as_matrix()


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


def paper000_grid() -> Array:
    """Li et al. (2018): 30 deg steps about z, y, x: 1728 attitudes."""
    return nested_grid((30.0, 30.0, 30.0))


def paper004_grid() -> Array:
    """The JNWPU 2022 coaxial calibration paper: x every 60 deg, y every 90 deg, z every 60 deg: 144 attitudes."""
    return nested_grid((60.0, 90.0, 60.0))


def three_rotations(count: int = 10) -> Array:
    """The two-fluxgate gradiometer paper: one turn about each of x, y and z with ``count`` points each."""
    return np.concatenate([single_axis(a, count) for a in "xyz"])


def uniform_random(count: int, rng: np.random.Generator | int | None = None) -> Array:
    """``count`` attitudes drawn uniformly from SO(3)."""
    gen = np.random.default_rng(rng)
    return Rotation.random(count, random_state=gen).as_matrix()


SCHEDULES = {
    "single-axis": lambda n, rng: single_axis("z", n),
    "paper000": lambda n, rng: paper000_grid(),
    "paper004": lambda n, rng: paper004_grid(),
    "three-axes": lambda n, rng: three_rotations(max(1, n // 3)),
    "random": lambda n, rng: uniform_random(n, rng),
}
"""Schedules by name: ``f(count, rng) -> (N, 3, 3)``; grids ignore ``count``."""

"""Array geometry: sensor names and positions in the platform frame (metres), and what gradient
the positions determine: none (one sensor), the gradient along a line (two sensors, or any
collinear array), or the full tensor (three or more sensors spread in a plane or in space)."""

from __future__ import annotations

import functools
import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.errors import InputError

Array = NDArray[np.float64]

DEFAULT_NAMES: tuple[str, ...] = ("mag1", "mag2", "mag3", "mag4")
DEFAULT_BASELINE: float = 0.4


def default_names(count: int) -> tuple[str, ...]:
    """``mag1``, ``mag2``, ... ``mag<count>``: the sensor names when none are given."""
    return tuple(f"mag{i + 1}" for i in range(count))


_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a sensor, or None. A sensor name is a relative ROS name: one or more
    tokens of letters, digits and underscores (not starting with a digit) joined by single ``/``
    (``mag1``, ``front/mag1``), because it becomes the topic ``<name>/raw`` and the parameters
    ``<name>.matrix``; ``mag 1``, ``../x``, ``/mag1``, ``mag1.x`` and ``~/mag1`` are not."""
    text = str(name)
    if not text:
        return "a sensor name must not be empty"
    bad = next((t for t in text.split("/") if not _NAME_TOKEN.fullmatch(t)), None)
    if bad is None:
        return None
    what = "an empty token (a leading, trailing or double '/')" if bad == "" else f"the token {bad!r}"
    return (f"sensor name {text!r} is not a valid relative ROS name ({what}): use letters, digits and "
            "underscores, not starting with a digit, tokens joined by '/'")


def check_names(names: Iterable[str]) -> None:
    """:class:`InputError` naming the first sensor name that is not a valid relative ROS name."""
    for name in names:
        why = name_problem(name)
        if why:
            raise InputError(why)


@dataclass(frozen=True)
class CrossLayout:
    """Indices of a planar cross: sensors at +x, +y, -x, -y and the baseline ``d`` (m)."""

    plus_x: int
    plus_y: int
    minus_x: int
    minus_y: int
    baseline: float


@dataclass(frozen=True)
class ArrayGeometry:
    """Sensor names and positions (S, 3) in metres, platform frame."""

    names: tuple[str, ...]
    positions: Array

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.names)
        pos = np.asarray(self.positions, dtype=float)
        if len(names) < 1:
            raise InputError("an array needs at least one sensor")
        if len(set(names)) != len(names) or not all(names):
            raise InputError(f"sensor names must be unique and non-empty, got {list(names)}")
        check_names(names)
        if pos.size != 3 * len(names):
            raise InputError(
                f"positions needs 3 numbers per sensor: {3 * len(names)} for {len(names)} sensors, "
                f"got {pos.size}"
            )
        pos = pos.reshape(len(names), 3)
        if not np.all(np.isfinite(pos)):
            raise InputError("positions must be finite")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "positions", pos)

    @classmethod
    def cross(cls, baseline: float = DEFAULT_BASELINE, names: tuple[str, ...] = DEFAULT_NAMES) -> "ArrayGeometry":
        """The default planar cross: +x, +y, -x, -y at ``baseline / 2`` from the centre."""
        h = baseline / 2.0
        pos = np.array([[h, 0, 0], [0, h, 0], [-h, 0, 0], [0, -h, 0]], dtype=float)
        return cls(tuple(names), pos)

    @classmethod
    def ring(cls, count: int, diameter: float = DEFAULT_BASELINE, names: tuple[str, ...] | None = None) -> "ArrayGeometry":
        """``count`` sensors equally spaced on a circle of ``diameter`` (m) in the x-y plane, the first at
        +x and counter-clockwise (about +z); one sensor sits at the centre. Four give :meth:`cross`
        exactly, two a line along x of length ``diameter``."""
        names = default_names(count) if names is None else tuple(names)
        if count == 4:
            return cls.cross(diameter, names)
        if count == 1:
            return cls(names, np.zeros(3))
        angle = 2.0 * np.pi * np.arange(count) / max(count, 1)
        h = diameter / 2.0
        pos = np.column_stack([h * np.cos(angle), h * np.sin(angle), np.zeros(count)])
        pos[np.abs(pos) < 1e-12 * h] = 0.0  # exact zeros where the circle meets an axis
        return cls(names, pos)

    @classmethod
    def single(cls, name: str = "mag1") -> "ArrayGeometry":
        """One sensor at the origin (no gradient)."""
        return cls((name,), np.zeros(3))

    @property
    def size(self) -> int:
        """Number of sensors."""
        return len(self.names)

    @property
    def centre(self) -> Array:
        """Mean sensor position (m): where the centre field and the tensor are given."""
        return self.positions.mean(axis=0)

    @functools.cached_property
    def spread_rank(self) -> int:
        """Dimension spanned by the sensor positions: 0 (one point), 1 (a line), 2 (a plane), 3."""
        rel = self.positions - self.centre
        if self.size < 2:
            return 0
        sv = np.linalg.svd(rel, compute_uv=False)
        return int(np.sum(sv > 1e-6 * max(sv[0], 1e-12)))

    @property
    def gradient_kind(self) -> str:
        """``none`` (one position), ``baseline`` (positions on a line: dB/ds along it) or ``tensor``."""
        return {0: "none", 1: "baseline"}.get(self.spread_rank, "tensor")

    @property
    def baseline(self) -> tuple[Array, float]:
        """Unit direction of a collinear array (from its first to its last sensor) and its length (m)."""
        rel = self.positions - self.centre
        _, _, vt = np.linalg.svd(rel)
        axis = vt[0] * np.sign(vt[0] @ (self.positions[-1] - self.positions[0]) or 1.0)
        proj = rel @ axis
        return axis, float(proj.max() - proj.min())

    def cross_layout(self, tolerance: float = 1e-6) -> CrossLayout | None:
        """The cross indices if the sensors form a planar cross about the centre, else None.

        Computed once per geometry for the default tolerance (the correction hot path).
        """
        return self._default_cross if tolerance == 1e-6 else self._find_cross(tolerance)

    @functools.cached_property
    def _default_cross(self) -> CrossLayout | None:
        return self._find_cross(1e-6)

    def _find_cross(self, tolerance: float) -> CrossLayout | None:
        if self.size != 4:
            return None
        rel = self.positions - self.centre
        found: dict[tuple[int, float], int] = {}
        for i, p in enumerate(rel):
            axis = int(np.argmax(np.abs(p)))
            if axis == 2 or np.linalg.norm(np.delete(p, axis)) > tolerance:
                return None
            found[(axis, float(np.sign(p[axis])))] = i
        keys = [(0, 1.0), (1, 1.0), (0, -1.0), (1, -1.0)]
        if sorted(found) != sorted(keys):
            return None
        px, py, mx, my = (found[k] for k in keys)
        dx = rel[px, 0] - rel[mx, 0]
        dy = rel[py, 1] - rel[my, 1]
        if abs(dx - dy) > tolerance or dx <= 0:
            return None
        return CrossLayout(px, py, mx, my, float(dx))

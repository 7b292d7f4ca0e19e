"""The one forward model of a raw reading, as named blocks with named parameters.

A set ``k`` is one reading of every sensor at one instant in a field of intensity ``F`` and
unit direction ``d_k`` (platform frame). Sensor ``i`` reads (T)::

    r_ik = F (I - dT_ik diag(g_i))^-1 K_i d~_ik  +  o_i  +  E_i u_k  +  c_i dT_ik  +  noise

with the blocks

=============== ======================================= ==========================================
block            parameters (per sensor)                 enters when
=============== ======================================= ==========================================
``sensor``       ``K_i`` forward matrix (3x3, the         always (``M_i = K_i^-1`` corrects)
                 inverse of the correction), ``o_i``
                 offset (T, raw axes)
``interference`` ``E_i`` (3 x m, T/A, raw axes)           current channels are given
``temperature``  ``c_i`` offset per kelvin (T/K, raw      sensor temperatures are given; ``dT`` is
                 axes), ``g_i`` gain per kelvin (1/K,     the temperature minus the reference (K)
                 per raw axis; the correction is then
                 exactly linear in ``dT``:
                 ``M_i (I - dT diag(g_i))``)
``lag``          ``tau_i`` (s): the reading stamped       the sets follow a continuous motion in
                 ``t`` is the field at ``t - tau_i``      time (two or more sensors); ``tau`` of the
                                                          first (reference) sensor is 0
=============== ======================================= ==========================================

``d~_ik = normalise(d_k - tau_i d'_k)`` is the direction the sensor saw, ``d'_k`` the rate of
change of the field direction (1/s) at the set. A common lag of every sensor, like a common
rotation of every ``K_i``, is absorbed by the directions: only lags relative to the reference
sensor (and the frame up to the gauge of :mod:`magcal_ros.core.uncertainty`) are determined.

The solver (:mod:`magcal_ros.core.array_fit`) works in units of ``F`` on one flat parameter
vector per sensor: ``W_i = [K_i | o_i / F | E_i / F | c_i / F]`` (3 x q, row-major, linear in
the features ``[d~, 1, u, dT]``), then ``g_i`` (3), then ``tau_i`` (1). This module is the one
place that says where each block's parameters sit in that vector and what they are called.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

BLOCKS: tuple[str, ...] = ("sensor", "interference", "temperature", "lag")
"""The blocks of the forward model, in parameter order."""
HOLDABLE: tuple[str, ...] = ("temperature", "lag")
"""Blocks whose quantities are held at zero (and named) when the data cannot determine them,
instead of refusing the calibration: a recording without temperature span or without motion
simply does not show these effects."""


@dataclass(frozen=True)
class ForwardModel:
    """Which blocks are on, and where their parameters sit in a sensor's parameter vector."""

    sensors: int
    channels: int = 0
    """Current channels ``m`` (interference block when > 0)."""
    temperature: bool = False
    lag: bool = False

    @property
    def q(self) -> int:
        """Columns of ``W_i``: ``[K (3) | o (1) | E (m) | c (1 with temperature)]``."""
        return 4 + self.channels + int(self.temperature)

    @property
    def extras(self) -> int:
        """Non-linear parameters after ``W_i``: ``g`` (3, temperature), ``tau`` (1, lag)."""
        return 3 * int(self.temperature) + int(self.lag)

    @property
    def size(self) -> int:
        """Parameters per sensor ``P``."""
        return 3 * self.q + self.extras

    @property
    def blocks(self) -> tuple[str, ...]:
        """The blocks that are on."""
        on = {"sensor": True, "interference": self.channels > 0, "temperature": self.temperature, "lag": self.lag}
        return tuple(b for b in BLOCKS if on[b])

    # -- where things are ------------------------------------------------------------------
    @property
    def offset_tempco_column(self) -> int | None:
        """Column of ``W_i`` holding ``c_i / F`` (None without temperature)."""
        return 4 + self.channels if self.temperature else None

    @property
    def gain_slice(self) -> slice | None:
        """Slice of the parameter vector holding ``g_i`` (None without temperature)."""
        return slice(3 * self.q, 3 * self.q + 3) if self.temperature else None

    @property
    def lag_index(self) -> int | None:
        """Index of ``tau_i`` in the parameter vector (None without lag)."""
        return 3 * self.q + 3 * int(self.temperature) if self.lag else None

    def w_index(self, row: int, column: int) -> int:
        """Index of ``W_i[row, column]`` in the parameter vector."""
        return row * self.q + column

    def matrix_indices(self) -> Array:
        """Indices of the 9 entries of ``K_i`` (row-major)."""
        return np.array([self.w_index(a, b) for a in range(3) for b in range(3)])

    def block_of(self, index: int) -> str:
        """The block a parameter index belongs to."""
        if index >= 3 * self.q:
            return "temperature" if self.gain_slice is not None and index < self.gain_slice.stop else "lag"
        column = index % self.q
        if column < 4:
            return "sensor"
        return "interference" if column < 4 + self.channels else "temperature"

    def holdable_mask(self) -> NDArray[np.bool_]:
        """(P,) True for the parameters of :data:`HOLDABLE` blocks."""
        return np.array([self.block_of(j) in HOLDABLE for j in range(self.size)])

    # -- packing ---------------------------------------------------------------------------
    def split(self, theta: Array) -> tuple[Array, Array | None, Array | None]:
        """``W`` (S, 3, q), ``g`` (S, 3) or None, ``tau`` (S,) or None from ``theta`` (S, P)."""
        t = np.asarray(theta, dtype=float).reshape(self.sensors, self.size)
        w = t[:, : 3 * self.q].reshape(self.sensors, 3, self.q)
        g = t[:, self.gain_slice] if self.gain_slice is not None else None
        tau = t[:, self.lag_index] if self.lag_index is not None else None
        return w, g, tau

    def join(self, w: Array, g: Array | None = None, tau: Array | None = None) -> Array:
        """Inverse of :meth:`split` (missing ``g``/``tau`` are zeros): (S, P)."""
        parts = [np.asarray(w, dtype=float).reshape(self.sensors, 3 * self.q)]
        if self.temperature:
            parts.append(np.zeros((self.sensors, 3)) if g is None else np.asarray(g, dtype=float).reshape(-1, 3))
        if self.lag:
            parts.append(np.zeros((self.sensors, 1)) if tau is None else np.asarray(tau, dtype=float).reshape(-1, 1))
        return np.concatenate(parts, axis=1)

    def widen(self, w_small: Array) -> Array:
        """``W`` of a model without the temperature column, given that column as zeros."""
        w = np.asarray(w_small, dtype=float)
        if w.shape[2] == self.q:
            return w
        if self.temperature and w.shape[2] == self.q - 1:
            return np.concatenate([w, np.zeros((w.shape[0], 3, 1))], axis=2)
        raise ValueError(f"W has {w.shape[2]} columns, the model {self.q}")

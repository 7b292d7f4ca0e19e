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

and, when the vehicle's IMU is given, global blocks (one set of parameters for the whole array,
after every sensor's; see :mod:`magcal_ros.core.attitude_blocks`)

=================== =================================== ==========================================
global block         parameters                          enters when
=================== =================================== ==========================================
``mounting``         ``A`` rotation array frame -> IMU   the IMU gives orientations, or angular
                     frame (3 small angles about the     velocities the sets follow in time
                     current estimate, IMU frame)
``field direction``  ``f_g`` unit field direction (2     one per reference: the world frame ENU
                     tangent parameters each)            (orientation), or each continuous
                                                         gyro segment's first attitude
``site gradient``    ``G_w`` (5: xx, xy, xz, yy, yz;     orientations are given: a constant
                     symmetric, traceless, T/m, world    world-frame gradient over the array
                     ENU, in units of F per m)
``array lag``        ``lag`` (s): the array's sets       the IMU gives its angular velocity: the
                     stamped ``t`` are the field at      attitude at ``t`` turned back by it
                     ``t - lag`` on the IMU's clock
=================== =================================== ==========================================

Each set ``k`` with a known attitude ``Q_k`` (IMU frame -> its reference) adds the residual
``(d_k - A^T exp(lag [w_k]x) Q_k^T f_g) / sigma_att`` (``w_k`` the IMU's angular velocity at the set,
IMU frame: the attitude the IMU had ``lag`` earlier) that ties its free direction to the IMU, and with the
gradient each sensor at ``p_i`` (array frame, about the centre) sees the extra field
``F R_k^T Gamma R_k p_i`` with ``R_k = Q_k A`` (array -> world) and ``Gamma = G_w / F``.

``d~_ik = normalise(d_k - tau_i d'_k)`` is the direction the sensor saw, ``d'_k`` the rate of
change of the field direction (1/s) at the set. A common lag of every sensor, like a common
rotation of every ``K_i``, is absorbed by the directions: only lags relative to the reference
sensor (and the frame up to the gauge of :mod:`magcal_ros.core.uncertainty`) are determined; the
IMU's attitudes determine the common one (``array lag``).

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
"""The per-sensor blocks of the forward model, in parameter order."""
GLOBAL_BLOCKS: tuple[str, ...] = ("mounting", "field direction", "site gradient", "array lag")
"""The global blocks (one set of parameters for the array, after every sensor's), in order."""
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
    mounting: bool = False
    """Global block: the rotation from the array frame to the IMU frame (3)."""
    field_groups: int = 0
    """Global block: field directions, one per attitude reference (2 each)."""
    site_gradient: bool = False
    """Global block: a constant world-frame gradient over the array (5)."""
    array_lag: bool = False
    """Global block: how late (s) the array's stamps are on the IMU's clock (1): the IMU's attitude at a set's
    stamp ``t`` is turned back to ``t - lag`` with its angular velocity."""

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

    @property
    def global_size(self) -> int:
        """Global parameters ``G`` after the ``S P`` per-sensor ones (0 without an IMU)."""
        return 3 * int(self.mounting) + 2 * self.field_groups + 5 * int(self.site_gradient) + int(self.array_lag)

    @property
    def global_blocks(self) -> tuple[str, ...]:
        """The global blocks that are on."""
        on = {"mounting": self.mounting, "field direction": self.field_groups > 0,
              "site gradient": self.site_gradient, "array lag": self.array_lag}
        return tuple(b for b in GLOBAL_BLOCKS if on[b])

    @property
    def mounting_slice(self) -> slice | None:
        """Slice of the global vector holding the mounting's small angles (rad, IMU frame)."""
        return slice(0, 3) if self.mounting else None

    def field_slice(self, group: int) -> slice:
        """Slice of the global vector holding field direction ``group``'s 2 tangent parameters."""
        start = 3 * int(self.mounting) + 2 * group
        return slice(start, start + 2)

    @property
    def gradient_slice(self) -> slice | None:
        """Slice of the global vector holding ``G_w / F`` (1/m): xx, xy, xz, yy, yz."""
        if not self.site_gradient:
            return None
        start = 3 * int(self.mounting) + 2 * self.field_groups
        return slice(start, start + 5)

    @property
    def array_lag_index(self) -> int | None:
        """Index in the global vector of the array's lag behind the IMU (s), None without the block."""
        return self.global_size - 1 if self.array_lag else None

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
        return (np.arange(3)[:, None] * self.q + np.arange(3)[None, :]).reshape(-1)

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

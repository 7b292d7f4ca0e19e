"""The IMU's blocks of the forward model: array-to-IMU rotation, field direction, site gradient.

Frames (see :mod:`magcal_ros.core.imu`): ``A`` turns array (platform) vectors into the IMU
frame, ``v_imu = A v_array``; a set's attitude ``Q_k`` turns IMU vectors into its reference
frame: the world ENU when the IMU gives orientations, or the IMU frame at the first set of a
continuous stretch of gyro readings (the angular velocity integrated between sets). The
field's unit direction ``f_g`` in reference ``g`` then gives every set's direction in the
array frame, ``d_k = A^T Q_k^T f_g``; the joint fit (:mod:`magcal_ros.core.array_fit`) adds
``(d_k - A^T Q_k^T f_g) / sigma_att`` to its residuals, ``sigma_att`` (rad) the IMU's attitude
error, estimated from those residuals (robust median) the way each sensor's noise is.

With orientations a constant world-frame gradient ``G_w`` (T/m, symmetric, traceless, ENU,
``G[i, j] = dB_j / dx_i``) adds ``R_k^T G_w R_k p_i`` (``R_k = Q_k A``, array to world) to the
field at sensor ``i`` (``p_i`` about the array centre): a pier's or a ship's gradient is then
part of the model instead of calibration error.

Parameters are small increments about the current state (re-centred after every step):
three angles (rad) rotating ``A`` on the left (about the IMU axes), two tangent coordinates
per field direction, the five gradient entries ``xx, xy, xz, yy, yz`` in units of F per m.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.forward_model import ForwardModel
from magcal_ros.core.imu import quat_exp, quat_to_matrix
from magcal_ros.core.metrics import chi2_isf
from magcal_ros.core.rotation import procrustes
from magcal_ros.core.uncertainty import autocorrelation, bandwidth
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

MIN_ATTITUDE_SIGMA: float = 1e-6
"""Floor (rad) of the attitude residuals' 1-sigma (an IMU without error)."""
GYRO_GAP: float = 5.0
"""A stamp interval this many times the typical one ends a gyro segment (its integration)."""
MIN_SEGMENT_SETS: int = 10
"""A gyro segment shorter than this is not used (its field direction would be nearly free)."""
WEAK_GLOBAL_SIGMA: float = 1.0
"""1-sigma of the weak prior on every global parameter (rad, unit tangent, 1/m in units of F)."""
GRADIENT_BASIS: Array = np.array([
    [[1, 0, 0], [0, 0, 0], [0, 0, -1]],
    [[0, 1, 0], [1, 0, 0], [0, 0, 0]],
    [[0, 0, 1], [0, 0, 0], [1, 0, 0]],
    [[0, 0, 0], [0, 1, 0], [0, 0, -1]],
    [[0, 0, 0], [0, 0, 1], [0, 1, 0]],
], dtype=float)
"""Symmetric traceless 3x3 matrices of the gradient's parameters xx, xy, xz, yy, yz."""
GRADIENT_NAMES: tuple[str, ...] = ("xx", "xy", "xz", "yy", "yz")
ARRAY_LAG = "array lag behind the IMU"
"""The name of the array lag block's quantity (ms)."""


def skew(v: Array) -> Array:
    """(..., 3, 3) cross-product matrices ``[v]x`` of (..., 3) vectors."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape + (3,))
    for (i, j), (k, sign) in zip(((0, 1), (0, 2), (1, 2)), ((2, -1.0), (1, 1.0), (0, -1.0))):
        np.multiply(v[..., k], sign, out=out[..., i, j])
        np.negative(out[..., i, j], out=out[..., j, i])
    return out


def rotation_of(rotvec: Array) -> Array:
    """(3, 3) rotation of a rotation vector (rad)."""
    return quat_to_matrix(quat_exp(np.asarray(rotvec, dtype=float)))


def tangent(u: Array) -> Array:
    """(3, 2) orthonormal basis of the plane perpendicular to the unit vector ``u``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(u, e1)])


def gradient_matrix(params: Array) -> Array:
    """(3, 3) symmetric traceless matrix of the 5 parameters ``xx, xy, xz, yy, yz``."""
    return np.einsum("j,jab->ab", np.asarray(params, dtype=float), GRADIENT_BASIS)


def gradient_params(g: Array) -> Array:
    """The 5 parameters ``xx, xy, xz, yy, yz`` of a symmetric traceless (3, 3) matrix."""
    return np.array([g[0, 0], g[0, 1], g[0, 2], g[1, 1], g[1, 2]], dtype=float)


@dataclass(frozen=True)
class AttitudeInputs:
    """What the IMU gives each set, for the global blocks."""

    rotations: Array
    """(N, 3, 3) ``Q_k``: IMU frame -> the set's reference frame (identity where ``groups`` < 0)."""
    groups: NDArray[np.int64]
    """(N,) the set's reference (0 .. count - 1), -1: no attitude."""
    count: int
    """Number of references (field directions)."""
    world: bool
    """The references are the world frame ENU (one, from orientations); False: gyro segments."""
    positions: Array | None = None
    """(S, 3) m, sensor positions about the array centre (array frame): fit the site gradient
    (orientations only); None: no gradient block."""
    field: Array | None = None
    """(3,) unit field direction in the world frame ENU to hold (the site's model); None: fitted."""
    frame_id: str = ""
    """The IMU's frame (the output frame of the calibration)."""
    rates: Array | None = None
    """(N, 3) rad/s, IMU frame: the IMU's angular velocity at each set (0 where it gives none), which turns
    its attitude back by the array's lag; None: no array lag block."""
    mounting_prior: tuple[Array, float] | None = None
    """(``A`` (3, 3), 1-sigma rad per axis): the array-to-IMU rotation a calibration before this one found (the
    mount is rigid: a hull change or a payload moves no axis), a prior on the mounting in place of the weak one;
    None: the weak one. A short stretch of yaw turns leaves the mounting's yaw nearly free (it trades with the
    field's declination), the prior holds it."""
    times: Array | None = None
    """(N,) s: each set's stamp, so that the attitude residuals can be read in time order (their time
    correlation, :meth:`correlation`); None: taken as independent."""

    def __post_init__(self) -> None:
        if self.positions is not None and not self.world:
            raise InputError("the site gradient needs the IMU's orientation (a world frame)")
        if self.field is not None and not self.world:
            raise InputError("a given field direction needs the IMU's orientation (a world frame)")

    @property
    def known(self) -> NDArray[np.bool_]:
        """(N,) sets with an attitude."""
        return self.groups >= 0

    def model(self, sensors: int, channels: int = 0, temperature: bool = False, lag: bool = False) -> ForwardModel:
        """The forward model with these global blocks on."""
        return ForwardModel(sensors, channels, temperature, lag, True, self.count, self.positions is not None,
                            self.rates is not None)

    def take(self, keep: NDArray[np.bool_] | NDArray[np.int64]) -> "AttitudeInputs":
        """The sets selected by a mask or index array (every reference kept)."""
        return replace(self, rotations=self.rotations[keep], groups=self.groups[keep],
                       rates=None if self.rates is None else self.rates[keep],
                       times=None if self.times is None else self.times[keep])

    def correlation(self, e: Array) -> float:
        """How many sets' worth of attitude residuals (N, 3) rad tell as much as one independent residual
        (>= 1): the ratio of their long-run variance to their variance, in time order (a Bartlett sum of the
        autocorrelation over the Newey-West bandwidth); 1 without :attr:`times`. An IMU's attitude errors are
        smooth in time (its slow wander; a sample interpolated between the IMU's): weighed as independent, a
        minute of them outweighed a prior on the mounting by the correlation time over the set interval."""
        if self.times is None:
            return 1.0
        known = self.known
        series = np.asarray(e, dtype=float)[known][np.argsort(self.times[known], kind="stable")]
        if len(series) < 3:
            return 1.0
        lags = bandwidth(series)
        rho = autocorrelation(series, lags)[1:]
        taper = 1.0 - np.arange(1, lags + 1) / (lags + 1.0)
        return max(1.0, 1.0 + 2.0 * float(np.sum(taper * rho)))

    def global_precision(self, model: ForwardModel) -> Array:
        """(G,) precision of the global parameters' prior: the weak one (:data:`WEAK_GLOBAL_SIGMA`), the
        mounting's from :attr:`mounting_prior` where there is one."""
        out = np.full(model.global_size, WEAK_GLOBAL_SIGMA ** -2.0)
        if self.mounting_prior is not None and model.mounting_slice is not None:
            out[model.mounting_slice] = max(self.mounting_prior[1], MIN_ATTITUDE_SIGMA) ** -2.0
        return out

    def prior_state(self, start: "GlobalState") -> "GlobalState":
        """The global prior's mean: ``start`` with the prior's mounting where there is one."""
        if self.mounting_prior is None:
            return start
        return replace(start, mounting=np.asarray(self.mounting_prior[0], dtype=float))

    def fixed(self, model: ForwardModel) -> NDArray[np.bool_]:
        """(G,) global parameters kept at their start: a held field direction."""
        out = np.zeros(model.global_size, bool)
        if self.field is not None:
            out[model.field_slice(0)] = True
        return out


@dataclass(frozen=True)
class GlobalState:
    """The global blocks' current values (frames and units of the module docstring)."""

    mounting: Array
    """(3, 3) ``A``: array frame -> IMU frame."""
    fields: Array
    """(count, 3) unit field direction of each reference."""
    gradient: Array
    """(3, 3) ``G_w / F`` (1/m), world ENU; zeros without the gradient block."""
    lag: float = 0.0
    """s: how late the array's stamps are on the IMU's clock (0 without the array lag block)."""

    def moved(self, step: Array, model: ForwardModel) -> "GlobalState":
        """The state after a step of the global parameters (model layout)."""
        a = self.mounting
        if model.mounting_slice is not None:
            a = rotation_of(step[model.mounting_slice]) @ a
        fields = self.fields.copy()
        for g in range(model.field_groups):
            f = fields[g] + tangent(fields[g]) @ step[model.field_slice(g)]
            fields[g] = f / np.linalg.norm(f)
        grad = self.gradient
        if model.gradient_slice is not None:
            grad = grad + gradient_matrix(step[model.gradient_slice])
        lag = self.lag if model.array_lag_index is None else self.lag + float(step[model.array_lag_index])
        return GlobalState(a, fields, grad, lag)

    def deviation(self, start: "GlobalState", model: ForwardModel) -> Array:
        """(G,) where this state lies from ``start`` in the global parameters (for the weak prior)."""
        out = np.zeros(model.global_size)
        if model.mounting_slice is not None:
            r = self.mounting @ start.mounting.T
            angle = np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
            axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
            out[model.mounting_slice] = 0.5 * axis * (angle / np.sin(angle) if angle > 1e-8 else 1.0)
        for g in range(model.field_groups):
            out[model.field_slice(g)] = tangent(self.fields[g]).T @ (self.fields[g] - start.fields[g])
        if model.gradient_slice is not None:
            out[model.gradient_slice] = gradient_params(self.gradient)
        if model.array_lag_index is not None:
            out[model.array_lag_index] = self.lag
        return out

    def rotated(self, qmat: Array) -> "GlobalState":
        """The state after the array frame turned by ``qmat`` (``d -> Q d``): ``A -> A Q^T``."""
        return replace(self, mounting=self.mounting @ np.asarray(qmat).T)


def rotate(rotvecs: Array, v: Array) -> Array:
    """(N, 3) vectors ``v`` (N, 3) turned by the rotations of rotation vectors ``rotvecs`` (N, 3) rad (Rodrigues);
    ``v`` (N, 3, K): K vectors per rotation, each turned by it."""
    angle = np.linalg.norm(rotvecs, axis=1, keepdims=True)
    axis = rotvecs / np.maximum(angle, 1e-300)
    c, s = np.cos(angle), np.sin(angle)
    if v.ndim == 3:
        axis, c, s = axis[..., None], c[..., None], s[..., None]
    return v * c + np.cross(axis, v, axis=1) * s + axis * np.sum(axis * v, axis=1, keepdims=True) * (1.0 - c)


def _back(att: AttitudeInputs, state: GlobalState, v: Array) -> Array:
    """IMU-frame vectors (N, 3), or (N, 3, K), at the sets' stamps as the IMU saw them ``lag`` earlier:
    ``exp(lag [w]x) v`` (``Q(t - lag) = Q(t) exp(-lag [w]x)``); ``v`` itself without the array lag block."""
    if att.rates is None or state.lag == 0.0:
        return v
    return rotate(state.lag * att.rates, v)


def reference_field(att: AttitudeInputs, state: GlobalState) -> Array:
    """(N, 3) ``u_k = exp(lag [w_k]x) Q_k^T f_g``: each set's field direction in the IMU frame at the array's
    sample instant (zeros without attitude)."""
    f = state.fields[np.maximum(att.groups, 0)]
    u = _back(att, state, np.einsum("nji,nj->ni", att.rotations, f))
    return np.where(att.known[:, None], u, 0.0)


def attitude_residuals(att: AttitudeInputs, state: GlobalState, d: Array) -> Array:
    """(N, 3) ``d_k - A^T Q_k^T f_g`` (rad, small); zeros for sets without attitude."""
    e = d - reference_field(att, state) @ state.mounting
    return np.where(att.known[:, None], e, 0.0)


def attitude_jacobian(att: AttitudeInputs, state: GlobalState, model: ForwardModel) -> Array:
    """(N, 3, G) derivative of :func:`attitude_residuals` by the global parameters."""
    n = len(att.groups)
    jac = np.zeros((n, 3, model.global_size))
    u = reference_field(att, state)
    at = state.mounting.T
    if model.mounting_slice is not None:
        jac[:, :, model.mounting_slice] = -_before_each(at, skew(u))
    for g in range(model.field_groups):
        rows = att.groups == g
        t = tangent(state.fields[g])
        cols = np.matmul(att.rotations[rows].transpose(0, 2, 1), t)  # (n, 3, 2) Q^T t
        part = replace(att, rates=None if att.rates is None else att.rates[rows])
        cols = _back(part, state, cols)
        jac[rows, :, model.field_slice(g)] = -_before_each(at, cols)
    if model.array_lag_index is not None and att.rates is not None:
        jac[:, :, model.array_lag_index] = -np.cross(att.rates, u) @ state.mounting
    return jac


def _before_each(m: Array, mats: Array) -> Array:
    """(N, 3, K) ``m @ mats[k]`` for one (3, 3) ``m`` and each of ``mats`` (N, 3, K): one matrix product."""
    n, _, k = mats.shape
    return (m @ mats.transpose(1, 0, 2).reshape(3, n * k)).reshape(3, n, k).transpose(1, 0, 2)


def _after_each(mats: Array, m: Array) -> Array:
    """(N, 3, 3) ``mats[k] @ m`` for each of ``mats`` (N, 3, 3) and one (3, 3) ``m``: one matrix product."""
    return (mats.reshape(-1, 3) @ m).reshape(mats.shape)


def _times_positions(mats: Array, positions: Array) -> Array:
    """(N, S, 3) each set's matrix of ``mats`` (N, 3, 3) times each sensor's position (S, 3): one matrix product
    (a stack of tiny ones loops per set)."""
    n, s = len(mats), len(positions)
    return (mats.reshape(n * 3, 3) @ positions.T).reshape(n, 3, s).transpose(0, 2, 1)


def _congruent(mats: Array, g: Array) -> Array:
    """(N, 3, 3) ``M_k^T G M_k`` for each of ``mats`` (N, 3, 3)."""
    return np.matmul(mats.transpose(0, 2, 1), np.matmul(g, mats))


def gradient_field(att: AttitudeInputs, state: GlobalState) -> Array | None:
    """(N, S, 3) ``R_k^T Gamma R_k p_i`` (units of F, array frame), or None without the block."""
    if att.positions is None:
        return None
    ra = _after_each(att.rotations, state.mounting)  # array -> world
    w = _congruent(ra, state.gradient)
    h = _times_positions(w, att.positions)
    return np.where(att.known[:, None, None], h, 0.0)


def gradient_columns(model: ForwardModel) -> NDArray[np.int64]:
    """The global parameters :func:`gradient_field` depends on (the mounting's, the gradient's), in order."""
    every = np.arange(model.global_size)
    mounting = every[:0] if model.mounting_slice is None else every[model.mounting_slice]
    return np.concatenate([mounting, every[model.gradient_slice]])


def gradient_jacobian(att: AttitudeInputs, state: GlobalState, model: ForwardModel,
                      compact: bool = False) -> Array | None:
    """(N, S, 3, G) derivative of :func:`gradient_field` by the global parameters (None without the block);
    ``compact``: by those of :func:`gradient_columns` only (N, S, 3, C), the others' columns being zero."""
    if att.positions is None or model.gradient_slice is None:
        return None
    n, s = len(att.groups), len(att.positions)
    cols = gradient_columns(model)
    jac = np.zeros((n, s, 3, len(cols)))
    mounted = 0 if model.mounting_slice is None else 3  # the mounting's columns first, then the gradient's
    ra = _after_each(att.rotations, state.mounting)
    rp = _times_positions(ra, att.positions)  # R p, world
    # d h / d gradient_j = R^T E_j R p for the 5 basis matrices at once: (E_j R p)^T R per set, batched
    j = len(GRADIENT_BASIS)
    erp = (rp.reshape(n * s, 3) @ GRADIENT_BASIS.transpose(2, 0, 1).reshape(3, j * 3)).reshape(n, s * j, 3)
    jac[:, :, :, mounted:] = np.matmul(erp, ra).reshape(n, s, j, 3).transpose(0, 1, 3, 2)
    if mounted:
        # h = A^T W A p with W = Q^T Gamma Q; A -> exp([da]) A: dh = A^T ([W A p]x - W [A p]x) da, both terms
        # linear in a vector: A^T [v]x = v . T (T (3, 3, 3) from A), A^T W [A p]x from A^T W (W symmetric)
        wq = _congruent(att.rotations, state.gradient)
        ap = att.positions @ state.mounting.T  # (S, 3) A p
        wap = _times_positions(wq, ap)
        by_vector = np.einsum("bk,bcm->mkc", state.mounting, skew(np.eye(3)))  # (3 m, 3 k, 3 c): A^T [e_m]x
        at_w = (wq.reshape(n * 3, 3) @ state.mounting).reshape(n, 3, 3).transpose(0, 2, 1)  # A^T W
        at_w_ap = (at_w.reshape(n * 3, 3) @ skew(ap).transpose(1, 0, 2).reshape(3, s * 3)).reshape(n, 3, s, 3)
        jac[:, :, :, :mounted] = (wap.reshape(n * s, 3) @ by_vector.reshape(3, 9)).reshape(n, s, 3, 3) \
            - at_w_ap.transpose(0, 2, 1, 3)
    jac[~att.known] = 0.0  # (built here: zeroed in place)
    if compact:
        return jac
    full = np.zeros((n, s, 3, model.global_size))
    full[..., cols] = jac
    return full


def robust_sigma(e: Array, weights: Array, share: float = 0.0) -> float:
    """1-sigma (rad) per tangent axis of attitude residuals (N, 3): the median of ``|e|^2`` over
    the weighted sets, scaled for their degrees of freedom, ``2 (1 - share)`` with ``share`` the part of the
    sets' directions the attitudes' weight fitted (the directions follow a trusted IMU and leave it small
    residuals: read for 2 dof, its error came out small, it was trusted more, down to the floor); floored at
    :data:`MIN_ATTITUDE_SIGMA`."""
    sq = np.sum(e * e, axis=1)[weights > 0]
    if not len(sq):
        return 1.0
    dof = 2.0 * (1.0 - min(max(share, 0.0), 0.99))
    return float(max(np.sqrt(np.median(sq) / chi2_isf(0.5, dof)), MIN_ATTITUDE_SIGMA))


# -- from the IMU's samples ---------------------------------------------------------------------------
def gyro_attitudes(angular_velocity: Array, times: Array) -> tuple[Array, NDArray[np.int64], int]:
    """Relative attitudes from the gyro: ``(Q (N, 3, 3), groups (N,), count)``.

    ``angular_velocity`` (N, 3) rad/s IMU frame (NaN: none) at the sets, ``times`` (N,) s in
    time order. Consecutive sets with a gyro reading and no gap (:data:`GYRO_GAP`) form a
    segment; ``Q_k`` turns IMU vectors at set ``k`` into the IMU frame at the segment's first
    set (the rate taken constant between sets at the mean of the two readings). Segments of
    fewer than :data:`MIN_SEGMENT_SETS` sets are dropped (group -1).
    """
    w = np.asarray(angular_velocity, dtype=float)
    t = np.asarray(times, dtype=float)
    n = len(t)
    q = np.tile(np.eye(3), (n, 1, 1))
    groups = np.full(n, -1, np.int64)
    ok = np.all(np.isfinite(w), axis=1)
    dt = np.diff(t)
    positive = dt[dt > 0]
    typical = float(np.median(positive)) if len(positive) else 1.0
    count, start = 0, None
    bounds = []
    for k in range(n):
        new = start is None or not ok[k] or not ok[k - 1] or not (0 < t[k] - t[k - 1] <= GYRO_GAP * typical)
        if new:
            if start is not None:
                bounds.append((start, k))
            start = k if ok[k] else None
    if start is not None:
        bounds.append((start, n))
    for a, b in bounds:
        if b - a < MIN_SEGMENT_SETS:
            continue
        for k in range(a + 1, b):
            q[k] = q[k - 1] @ rotation_of(0.5 * (w[k - 1] + w[k]) * (t[k] - t[k - 1]))
        groups[a:b] = count
        count += 1
    return q, groups, count


def attitude_inputs(orientation: Array, angular_velocity: Array, stamps: Array, positions: Array | None,
                    gradient: bool, field_world: Array | None = None, frame_id: str = "") -> AttitudeInputs | None:
    """The global blocks' inputs from the IMU at each set (None when it gives nothing usable).

    ``orientation`` (N, 4) quaternions IMU -> world ENU (NaN rows: none) and ``angular_velocity``
    (N, 3) rad/s; ``stamps`` (N,) int ns. Orientations are used when the IMU gives any (with
    ``gradient``, the site gradient block too, sensors at ``positions`` (S, 3) m); otherwise the
    gyro, integrated in continuous segments. ``field_world`` (3,) the site's field (world ENU,
    any units): its direction is held. With the angular velocity at :data:`MIN_SEGMENT_SETS` sets or more,
    the array's lag behind the IMU is a block too (:func:`lag_rates`).
    """
    q = np.asarray(orientation, dtype=float)
    rates = lag_rates(angular_velocity)
    known = np.all(np.isfinite(q), axis=1)
    n = len(q)
    field = None if field_world is None else np.asarray(field_world, dtype=float) / np.linalg.norm(field_world)
    if known.sum() >= MIN_SEGMENT_SETS:
        rot = np.tile(np.eye(3), (n, 1, 1))
        rot[known] = quat_to_matrix(q[known])
        centred = None
        if gradient and positions is not None and len(positions) > 1:
            p = np.asarray(positions, dtype=float)
            centred = p - p.mean(axis=0)
        return AttitudeInputs(rot, np.where(known, 0, -1).astype(np.int64), 1, True, centred, field, frame_id, rates,
                              times=_seconds(stamps))
    w = np.asarray(angular_velocity, dtype=float)
    if np.sum(np.all(np.isfinite(w), axis=1)) < MIN_SEGMENT_SETS:
        return None
    times = _seconds(stamps)
    order = np.argsort(times, kind="stable")
    rot_o, groups_o, count = gyro_attitudes(w[order], times[order])
    if count == 0:
        return None
    rot, groups = np.empty_like(rot_o), np.empty_like(groups_o)
    rot[order], groups[order] = rot_o, groups_o
    return AttitudeInputs(rot, groups, count, False, None, None, frame_id, rates, times=times)


def _seconds(stamps: Array) -> Array:
    """(N,) s of int ns ``stamps`` from the first."""
    st = np.asarray(stamps).astype(np.int64)
    return (st - st.min()).astype(float) / NS_PER_S if len(st) else np.zeros(0)


def lag_rates(angular_velocity: Array) -> Array | None:
    """(N, 3) rad/s: the IMU's angular velocity at each set (0 where it gives none) for the array lag block,
    or None (no block) when it gives one at fewer than :data:`MIN_SEGMENT_SETS` sets."""
    w = np.asarray(angular_velocity, dtype=float).reshape(-1, 3)
    ok = np.all(np.isfinite(w), axis=1)
    if ok.sum() < MIN_SEGMENT_SETS:
        return None
    return np.where(ok[:, None], w, 0.0)


# -- the closed-form start ----------------------------------------------------------------------------
START_TOLERANCE: float = 1e-12
"""The closed-form start's alternation stops once no element of the mounting moves more than this."""
START_SETS: int = 500
"""Sets (evenly spread) on which the 24 axis rotations are tried; the best is then refined on every set."""


def _axis_rotations() -> list[Array]:
    """The 24 rotations that permute the axes (with signs): starts for the alternating fit."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


def _alternate(starts: Array, d: Array, rot: Array, groups: NDArray[np.int64], count: int, field: Array | None,
               rounds: int) -> tuple[Array, Array, Array]:
    """Alternating Procrustes from each mounting of ``starts`` (K, 3, 3) at once: fields then mounting, at most
    ``rounds`` times (fewer once no mounting moves, :data:`START_TOLERANCE`); (A (K, 3, 3), fields (K, G, 3),
    costs (K,))."""
    a = np.array(starts, dtype=float)
    n = len(d)
    member = (groups[None, :] == np.arange(count)[:, None]).astype(float)  # (G, N) each set's group
    fields = np.zeros((len(a), count, 3))
    # Q A d is linear in A: (Q_ij d_l) times A_jl, one matrix product for every set and start (K tiny products
    # for each set loop in numpy)
    qd = (rot[:, :, :, None] * d[:, None, None, :]).reshape(n * 3, 9)
    qt = np.ascontiguousarray(rot.transpose(0, 2, 1))  # (N, 3, 3) Q^T
    by_group = [(rows, qt[rows].reshape(-1, 3)) for rows in (groups == g for g in range(count))]  # Q^T stacked

    def world(mounts: Array) -> Array:
        return (qd @ mounts.reshape(-1, 9).T).reshape(n, 3, -1).transpose(2, 0, 1)  # (K, N, 3) Q A d: should be f_g

    def toward(f: Array) -> Array:  # (K, N, 3) Q^T f_g of each set's group
        out = np.empty((len(f), n, 3))
        for g, (rows, stacked) in enumerate(by_group):
            out[:, rows] = (stacked @ f[:, g].T).reshape(-1, 3, len(f)).transpose(2, 0, 1)
        return out

    for _ in range(rounds):
        if field is not None:
            fields[:] = field
        else:
            m = np.matmul(member, world(a))  # (K, G, 3) each group's sum
            fields = m / np.maximum(np.linalg.norm(m, axis=2, keepdims=True), 1e-300)
        target = toward(fields)  # Q^T f: should be A d
        a, before = procrustes(d, target), a
        if np.max(np.abs(a - before)) < START_TOLERANCE:
            break
    cost = np.sum((world(a) - fields[:, groups]) ** 2, axis=(1, 2))
    return a, fields, cost


def initial_state(att: AttitudeInputs, directions: Array) -> GlobalState:
    """A and the field directions in closed form from the calibrated directions (N, 3): alternating
    Procrustes (Wahba's problem for ``A``, the mean for each ``f_g``) from each of the 24 axis
    rotations (on :data:`START_SETS` of the sets), the best refined on every set; the gradient at zero."""
    known = att.known
    d, rot, groups = directions[known], att.rotations[known], att.groups[known]
    few = slice(None, None, max(1, len(d) // START_SETS))
    a, _, cost = _alternate(np.stack(_axis_rotations()), d[few], rot[few], groups[few], att.count, att.field, 8)
    best = int(np.argmin(cost))
    a, fields, _ = _alternate(a[best : best + 1], d, rot, groups, att.count, att.field, 200)
    return GlobalState(a[0], fields[0], np.zeros((3, 3)))


# -- in physical words --------------------------------------------------------------------------------
def roll_pitch_yaw(a: Array) -> Array:
    """(3,) deg: roll, pitch, yaw of ``A = Rz(yaw) Ry(pitch) Rx(roll)``."""
    pitch = -np.arcsin(np.clip(a[2, 0], -1.0, 1.0))
    roll = np.arctan2(a[2, 1], a[2, 2])
    yaw = np.arctan2(a[1, 0], a[0, 0])
    return np.degrees(np.array([roll, pitch, yaw]))


@dataclass(frozen=True)
class GlobalQuantity:
    """One global quantity with its 1-sigma, in the unit it is reported in."""

    block: str
    name: str
    unit: str
    value: float
    sigma: float

    def describe(self) -> str:
        return f"{self.name} {self.value:.3f} +- {float(f'{self.sigma:.2g}'):g} {self.unit}"


def global_quantities(state: GlobalState, cov: Array, model: ForwardModel, intensity: float,
                      world: bool) -> list[GlobalQuantity]:
    """The global blocks in physical words with 1-sigma from their covariance ``cov`` (G, G):
    the mounting as roll, pitch, yaw (deg), each world field direction as declination and
    inclination (deg, ENU: declination east of the world's north, inclination down), the
    gradient's entries (nT/m, world ENU), the array's lag behind the IMU (ms)."""
    out: list[GlobalQuantity] = []
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if model.mounting_slice is not None:
        sl = model.mounting_slice
        base = roll_pitch_yaw(state.mounting)
        jac = np.empty((3, 3))
        for j in range(3):
            h = np.zeros(3)
            h[j] = 1e-6
            jac[:, j] = (roll_pitch_yaw(rotation_of(h) @ state.mounting)
                         - roll_pitch_yaw(rotation_of(-h) @ state.mounting)) / 2e-6
        s = np.sqrt(np.clip(np.diag(jac @ cov[sl, sl] @ jac.T), 0.0, None))
        for name, v, e in zip(("roll", "pitch", "yaw"), base, s):
            out.append(GlobalQuantity("mounting", f"array to IMU {name}", "deg", float(v), float(e)))
    if world and model.field_groups:
        sl = model.field_slice(0)
        f = state.fields[0]

        def angles(v: Array) -> Array:
            v = v / np.linalg.norm(v)
            return np.degrees(np.array([np.arctan2(v[0], v[1]), -np.arcsin(np.clip(v[2], -1.0, 1.0))]))

        t = tangent(f)
        jac = np.column_stack([(angles(f + 1e-6 * t[:, j]) - angles(f - 1e-6 * t[:, j])) / 2e-6 for j in range(2)])
        s = np.sqrt(np.clip(np.diag(jac @ cov[sl, sl] @ jac.T), 0.0, None))
        for name, v, e in zip(("declination", "inclination"), angles(f), s):
            out.append(GlobalQuantity("field direction", f"field {name}", "deg", float(v), float(e)))
    if model.gradient_slice is not None:
        sl = model.gradient_slice
        values = gradient_params(state.gradient) * intensity / NT
        for name, v, e in zip(GRADIENT_NAMES, values, sig[sl] * intensity / NT):
            out.append(GlobalQuantity("site gradient", f"site gradient {name}", "nT/m", float(v), float(e)))
    if model.array_lag_index is not None:
        k = model.array_lag_index
        out.append(GlobalQuantity("array lag", ARRAY_LAG, "ms", state.lag * 1e3, float(sig[k]) * 1e3))
    return out

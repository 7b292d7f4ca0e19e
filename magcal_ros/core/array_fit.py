"""Joint maximum a posteriori fit of the whole array, robust to outliers (the final stage of ``ml``).

The model is :class:`~magcal_ros.core.forward_model.ForwardModel`: per set ``k`` a unit field
direction ``d_k`` (platform frame), per sensor ``i`` its blocks (forward matrix and offset,
current interference, temperature, lag). Every set gives 3 equations per sensor, so the
sensors' relative calibration (what the tensor needs) is set by the vector agreement between
sensors, not only by each sensor's norm.

The fit works in units of ``F`` on one parameter vector per sensor (see the model's layout).
The per-set directions are eliminated by a Schur complement (cost linear in the number of
sets). A Gaussian prior on every parameter (the previous calibration and a drift model, or a
weak one around the starting point) makes the problem well posed whatever the manoeuvre; the
data information (without the prior) is returned for the identifiability analysis.

Outliers: after each fit every reading is compared with what the *other* sensors say the
field was (the mean of the set's other readings, so that a spike on one sensor cannot hide
by dragging the set's direction), and with the intensity; readings beyond a
chi-square bound of the sensor's robust scale get weight 0 and the fit is repeated until
the excluded readings settle.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core import attitude_blocks as att_blocks
from magcal_ros.core.attitude_blocks import AttitudeInputs, GlobalState
from magcal_ros.core.batched import (gram2, per_sensor, per_sensor_dot, per_sensor_shared,
                                     row_norms, times_lower2)
from magcal_ros.core.forward_model import ForwardModel
from magcal_ros.core.metrics import chi2_isf
from magcal_ros.core.parallel import map_in_threads
from magcal_ros.core.rotation import rq_positive
from magcal_ros.errors import CalibrationFailed, InputError

Array = NDArray[np.float64]

OUTLIER_PROBABILITY: float = 1e-5
"""A clean reading is excluded with at most this probability (Gaussian noise)."""
MAX_ROBUST_ROUNDS: int = 12
"""Refits at most, each after re-deciding which readings are outliers."""
SOFT_BOUND: float = 16.0
"""Residuals beyond sqrt(SOFT_BOUND) = 4 noise sd (per reading, squared norm over its dof)
are down-weighted in proportion while outliers are being decided."""
RATE_HALF_WINDOW: int = 4
"""Sets on each side of a set in the local quadratic fit that gives the field direction's rate."""
RATE_GAP: float = 5.0
"""A stamp interval this many times the typical one breaks the rate estimate (a gap in the data)."""


@dataclass(frozen=True)
class ParameterPrior:
    """Gaussian prior on each sensor's parameter vector (units of F; layout of the model).

    ``mean`` and ``sigma`` (S, P), or (S, 3, q) for a model with no extra parameters; the
    1-sigma of each entry (inf: no prior).
    """

    mean: Array
    sigma: Array

    def precision(self) -> Array:
        """Diagonal precision, flattened per sensor as (S, P)."""
        s = np.asarray(self.sigma, dtype=float)
        with np.errstate(divide="ignore"):
            prec = np.where(np.isfinite(s), 1.0 / np.maximum(s, 1e-300) ** 2, 0.0)
        return prec.reshape(len(s), -1)

    def flat_mean(self) -> Array:
        """The mean as (S, P)."""
        m = np.asarray(self.mean, dtype=float)
        return m.reshape(len(m), -1)

    def fitted_to(self, model: ForwardModel) -> "ParameterPrior":
        """This prior on ``model``'s parameters: blocks it does not know get no prior (inf)."""
        mean, sigma = self.flat_mean(), np.asarray(self.sigma, dtype=float).reshape(len(self.mean), -1)
        if mean.shape[1] == model.size:
            return ParameterPrior(mean, sigma)
        base = ForwardModel(model.sensors, model.channels)
        if mean.shape[1] != base.size:
            raise InputError(f"prior has {mean.shape[1]} parameters per sensor, the model {model.size}")
        out_mean, out_sigma = np.zeros((model.sensors, model.size)), np.full((model.sensors, model.size), np.inf)
        wm = model.widen(mean.reshape(model.sensors, 3, base.q))
        ws = np.concatenate([sigma.reshape(model.sensors, 3, base.q),
                             np.full((model.sensors, 3, model.q - base.q), np.inf)], axis=2)
        out_mean[:, : 3 * model.q] = wm.reshape(model.sensors, -1)
        out_sigma[:, : 3 * model.q] = ws.reshape(model.sensors, -1)
        return ParameterPrior(out_mean, out_sigma)


@dataclass(frozen=True)
class SetInputs:
    """What a set carries besides the raw readings: currents, temperatures, time."""

    currents: Array
    """(N, m) A of the interference channels."""
    temperatures: Array | None = None
    """(N, S) temperature of each sensor minus the reference (K); None: no temperature block."""
    times: Array | None = None
    """(N,) s, the sets' stamps (for the lag block's field rates); None: no lag block."""

    def rest_features(self, sensors: int) -> Array:
        """(N, S, 1 + m [+ 1]): ``[1, u_k, dT_ik]`` per set and sensor."""
        n = len(self.currents)
        parts = [np.ones((n, sensors, 1)), np.broadcast_to(self.currents[:, None, :], (n, sensors,
                                                                                       self.currents.shape[1]))]
        if self.temperatures is not None:
            parts.append(self.temperatures[:, :, None])
        return np.concatenate(parts, axis=2)


@dataclass(frozen=True)
class PartSums:
    """Each part's share of a solution's normal equations (the delete-one-block jackknife's parts): their
    information (directions eliminated) and summed scores, every parameter (the sensors', then the global
    ones), whitened, units of F."""

    parts: tuple[NDArray[np.int64], ...]
    """The parts: indices of the sets the solution was fitted on."""
    information: Array
    """(K, Q, Q) each part's information."""
    scores: Array
    """(K, Q) each part's scores summed over its sets."""

    def matches(self, parts: list[NDArray[np.int64]]) -> bool:
        """Whether ``parts`` are these."""
        return len(parts) == len(self.parts) and all(np.array_equal(a, b) for a, b in zip(parts, self.parts))

    def mapped(self, full: Array) -> "PartSums":
        """The sums for the parameters ``new = full^-1 old`` (a change of the parameters' frame)."""
        return replace(self, information=full.T @ self.information @ full,
                       scores=self.scores @ full)


@dataclass(frozen=True)
class JointSolution:
    """Result of :func:`fit_array`, in physical units where it says so."""

    matrices: Array
    """(S, 3, 3) corrections ``M_i = K_i^-1`` (raw axes to platform frame)."""
    offsets: Array
    """(S, 3) T."""
    interference: Array
    """(S, 3, m) ``D_i = M_i E_i`` in T/A, platform frame."""
    directions: Array
    """(N, 3) unit field direction of each set, platform frame."""
    weights: Array
    """(N, S) 1 for readings used, 0 for readings excluded as outliers."""
    sigma: Array
    """(S,) noise per axis of each sensor (T), robust estimate from the residuals."""
    residuals: Array
    """(N, S, 3) raw-space residuals (T)."""
    information: Array
    """(S P, S P) Fisher information of the data on the parameters (units of F), directions
    eliminated, noise-whitened; P = ``model.size``."""
    scores: Array
    """(N, S P) per-set contributions to the reduced gradient at the solution (whitened)."""
    w: Array
    """(S, 3, q) the fitted ``W_i`` (units of F): the linear part of the parameters."""
    intensity: float
    """F (T)."""
    model: ForwardModel
    theta: Array
    """(S, P) every parameter (units of F where linear; ``g`` in 1/K, ``tau`` in s)."""
    rates: Array | None = None
    """(N, 3) rate of change of the field direction (1/s) the lag block used; None without it."""
    fixed: Array | None = None
    """(S, P) parameters the fit kept at their start (held, or the lag gauge); None: none."""
    globals: GlobalState | None = None
    """The global blocks (IMU: mounting, field directions, site gradient); None without an IMU.
    ``information`` and ``scores`` then have the global parameters eliminated (marginal on the
    sensors' parameters); ``full_information`` and ``full_scores`` keep them (after the sensors')."""
    full_information: Array | None = None
    """(S P + G, S P + G) information with the global parameters (None without them)."""
    full_scores: Array | None = None
    """(N, S P + G) per-set scores with the global parameters (None without them)."""
    attitude: AttitudeInputs | None = None
    """The IMU's attitudes the global blocks used."""
    attitude_sigma: float | None = None
    """1-sigma (rad) per axis of the attitude residuals (the IMU's attitude error as the fit saw it)."""
    attitude_residuals: Array | None = None
    """(N, 3) rad: ``d_k - A^T Q_k^T f_g`` (zeros for sets without attitude)."""
    attitude_weights: Array | None = None
    """(N,) weight of each set's attitude residual (0: none, or excluded)."""
    attitude_correlation: float = 1.0
    """The attitude residuals' time correlation the fit weighed them by
    (:meth:`~magcal_ros.core.attitude_blocks.AttitudeInputs.correlation`): each set's precision is its weight over
    ``attitude_sigma**2`` times this."""
    part_sums: PartSums | None = None
    """The parts' shares of the normal equations when :func:`fit_array` was given parts (for
    :func:`leave_out_estimates`)."""

    def site_field(self) -> Array | None:
        """(N, S, 3) T, array frame: the site gradient's field at each sensor (None without the block)."""
        if self.globals is None or self.attitude is None:
            return None
        h = att_blocks.gradient_field(self.attitude, self.globals)
        return None if h is None else h * self.intensity

    @property
    def offset_tempco(self) -> Array | None:
        """(S, 3) offset change per kelvin (T/K, raw axes), None without temperature."""
        col = self.model.offset_tempco_column
        return None if col is None else self.w[:, :, col] * self.intensity

    @property
    def gain_tempco(self) -> Array | None:
        """(S, 3) gain change per kelvin of each raw axis (1/K), None without temperature."""
        sl = self.model.gain_slice
        return None if sl is None else self.theta[:, sl]

    @property
    def time_offsets(self) -> Array | None:
        """(S,) s each sensor reads late (relative to the first), None without the lag block."""
        idx = self.model.lag_index
        return None if idx is None else self.theta[:, idx]


def tangent_bases(u: Array) -> Array:
    """(N, 3, 2) orthonormal bases of the planes perpendicular to unit vectors ``u``."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    out = np.empty((len(u), 3, 2))
    e1, e2 = out[:, :, 0], out[:, :, 1]
    use_x = np.abs(x) < 0.9  # u x (1, 0, 0) = (0, z, -y), else u x (0, 1, 0) = (-z, 0, x)
    e1[:, 0] = np.where(use_x, 0.0, -z)
    e1[:, 1] = np.where(use_x, z, 0.0)
    e1[:, 2] = np.where(use_x, -y, x)
    e1 /= np.sqrt(np.einsum("na,na->n", e1, e1))[:, None]
    e2[:, 0] = y * e1[:, 2] - z * e1[:, 1]  # u x e1
    e2[:, 1] = z * e1[:, 0] - x * e1[:, 2]
    e2[:, 2] = x * e1[:, 1] - y * e1[:, 0]
    return out


def features(directions: Array, currents: Array) -> Array:
    """(N, 4 + m) ``phi_k = [d_k, 1, u_k]`` (the linear features of a model without temperature or lag)."""
    return np.concatenate([directions, np.ones((len(directions), 1)), currents], axis=1)


def direction_rates(directions: Array, times: Array) -> Array:
    """(N, 3) rate of change (1/s) of unit field directions (N, 3) at ``times`` (N,) s.

    A local quadratic fit over :data:`RATE_HALF_WINDOW` sets on each side (in time order), never
    across a gap of more than :data:`RATE_GAP` typical intervals; perpendicular to the direction.
    Sets with fewer than three neighbours in reach get rate 0.
    """
    d = np.asarray(directions, dtype=float)
    t = np.asarray(times, dtype=float)
    n = len(d)
    out = np.zeros_like(d)
    if n < 3:
        return out
    ordered = bool(np.all(t[1:] >= t[:-1]))
    order = None if ordered else np.argsort(t, kind="stable")
    ts, ds = (t, d) if order is None else (t[order], d[order])
    dt = np.diff(ts)
    positive = dt[dt > 0]
    if not len(positive):
        return out
    typical = float(np.median(positive))
    h = RATE_HALF_WINDOW
    segment = np.full(n + 2 * h, -1, dtype=np.int64)  # padded by h on each side: a segment no set is in
    segment[h : n + h] = np.concatenate([[0], np.cumsum((dt > RATE_GAP * typical) | (dt <= 0))])
    padded = _Padded(np.pad(ts, h), np.pad(ds, ((h, h), (0, 0))), segment)
    sorted_out = out if order is None else np.zeros((n, 3))

    def block(lo: int) -> None:  # a block of sets at a time: memory stays bounded on long recordings
        hi = min(lo + RATE_BLOCK, n)
        sorted_out[lo:hi] = _local_slopes(padded, typical, lo, hi)

    map_in_threads(block, range(0, n, RATE_BLOCK))  # (blocks apart: spare cores take some)
    if order is not None:
        out[order] = sorted_out
    return out


RATE_BLOCK = 16_384
"""Sets per block of :func:`direction_rates`."""


@dataclass(frozen=True)
class _Padded:
    """Time-ordered stamps (N + 2 h,) s, directions (N + 2 h, 3) and gap-free segments (N + 2 h,), padded
    by h = :data:`RATE_HALF_WINDOW` on each side (segment -1 there)."""

    times: Array
    directions: Array
    segment: NDArray[np.int64]


def _local_slopes(padded: _Padded, typical: float, lo: int, hi: int) -> Array:
    """(hi - lo, 3) :func:`direction_rates` at the time-ordered sets ``lo:hi`` (0 where fewer than three
    neighbours are in reach): a neighbour offset at a time, each a contiguous slice."""
    h = RATE_HALF_WINDOW
    here = slice(lo + h, hi + h)
    t0, seg = padded.times[here], padded.segment[here]
    offsets = range(-h, h + 1)
    valid = np.stack([padded.segment[lo + h + o : hi + h + o] == seg for o in offsets])  # (W, M)
    x = np.stack([padded.times[lo + h + o : hi + h + o] - t0 for o in offsets]) / typical
    x[~valid] = 0.0
    wgt = valid.astype(float)
    x2 = x * x
    s0, s1, s2 = wgt.sum(axis=0), x.sum(axis=0), x2.sum(axis=0)
    s3, s4 = (x2 * x).sum(axis=0), (x2 * x2).sum(axis=0)
    # The slope is the middle row of the inverse of the Hankel normal matrix [[s0 s1 s2] [s1 s2 s3]
    # [s2 s3 s4]] times the right side (the neighbours weighted by 1, x, x^2): its cofactors, over its
    # determinant, folded into one weight per neighbour (no batched solve).
    r0, r1, r2 = s2 * s3 - s1 * s4, s0 * s4 - s2 * s2, s1 * s2 - s0 * s3
    det = s0 * (s2 * s4 - s3 * s3) + s1 * r0 + s2 * (s1 * s3 - s2 * s2)
    enough = (s0 >= 3) & (np.abs(det) > 1e-9 * np.maximum(s0**3, 1e-300))
    coef = wgt * (r0 + r1 * x + r2 * x2) / (np.where(enough, det, 1.0) * typical)  # (W, M)
    slope = np.zeros((hi - lo, 3))
    for i, o in enumerate(offsets):
        slope += coef[i][:, None] * padded.directions[lo + h + o : hi + h + o]
    d = padded.directions[here]
    slope -= np.sum(slope * d, axis=1, keepdims=True) * d
    return np.where(enough[:, None], slope, 0.0)


@dataclass(frozen=True)
class _Att:
    """The global blocks at one point: the IMU's attitudes, the state, the attitude residuals' precision."""

    inputs: AttitudeInputs
    state: GlobalState
    precision: Array
    """(N,) weight / (sigma_att^2 correlation) of each set's attitude residual (0: none)."""
    correlation: float = 1.0
    """The attitude residuals' time correlation the precision divides by (:meth:`AttitudeInputs.correlation`)."""

    def h(self) -> Array | None:
        """(N, S, 3) the site gradient's field at each sensor (units of F), None without the block (computed once
        per state: a fit asks for it at each evaluation, each trial step and each residual)."""
        return self._h

    @cached_property
    def _h(self) -> Array | None:
        return att_blocks.gradient_field(self.inputs, self.state)

    def moved(self, step: Array, model: ForwardModel) -> "_Att":
        return replace(self, state=self.state.moved(step, model))

    def take(self, keep: NDArray[np.int64]) -> "_Att":
        """The sets ``keep`` (indices) only."""
        return replace(self, inputs=self.inputs.take(keep), precision=self.precision[keep])


def _lagged(d: Array, rates: Array, tau: Array) -> tuple[Array, Array]:
    """The direction each sensor saw ``tau`` (S,) s before the set's instant, to first order in the
    direction's ``rates`` (N, 3) 1/s: (``dl`` (N, S, 3) unit, ``1 / |d - tau r|`` (N, S)). ``d - tau r`` for every
    sensor is one matrix product of the rows ``[d, r]`` (a broadcast over the small axes loops in C over each)."""
    n, s = len(d), len(tau)
    dl = (np.stack([d, rates], axis=2).reshape(n * 3, 2) @ np.stack([np.ones(s), -tau])).reshape(n, 3, s)
    dl = np.ascontiguousarray(dl.transpose(0, 2, 1))
    inv = 1.0 / row_norms(dl)
    dl *= inv[..., None]
    return dl, inv


def _lag_derivatives(d: Array, rates: Array, tau: Array, dl: Array, inv: Array) -> Array:
    """(N, S, 3) ``d dl / d tau`` of :func:`_lagged`'s directions: ``-(r + dl (dl . (-r)) / |l|) / |l|`` for
    ``l = d - tau r``."""
    a = np.einsum("na,na->n", d, rates)
    rr = np.einsum("na,na->n", rates, rates)
    q = (tau[None, :] * rr[:, None] - a[:, None]) * inv  # (l . (-r)) / |l|
    out = dl * q[..., None]
    for i in range(len(tau)):
        out[:, i] += rates
    out *= -inv[..., None]
    return out


STRUCTURED: bool = True
""":class:`_Eval` builds the products of the linear blocks from their features (False: from the dense
Jacobian, the reference the structured products are tested against)."""


class _Eval:
    """The model at one point: prediction, residuals, Jacobians and the whitened normal equations
    (directions eliminated by their 2 x 2 blocks)."""

    def __init__(self, model: ForwardModel, theta: Array, d: Array, x: Array, inputs: SetInputs, rates: Array | None,
                 weights: Array, sigma: Array, att: _Att | None = None) -> None:
        n, s, _ = x.shape
        p, q = model.size, model.q
        ng = model.global_size if att is not None else 0
        h = None if att is None else att.h()
        w, g, tau = model.split(theta)
        k = w[:, :, :3]
        psi = inputs.rest_features(s)  # (N, S, q - 3)
        self.basis = tangent_bases(d)  # (N, 3, 2)
        # Direction each sensor saw (lag), and its derivatives.
        if tau is not None and rates is not None:
            dl, inv = _lagged(d, rates, tau)
            d_tau = _lag_derivatives(d, rates, tau, dl, inv)  # d dl / d tau (N, S, 3)
        else:
            dl = np.broadcast_to(d[:, None, :], (n, s, 3))
            d_tau = inv = None
        seen = dl if h is None else dl + h  # the field each sensor saw, units of F
        kd = per_sensor(k, seen)
        k_dir = per_sensor_shared(k, self.basis)  # K d dl / d d
        if inv is not None:  # with the lag d dl / d d (tangent) = (I - dl dl^T) basis / |l|, l = d - tau r, where
            # dl^T basis = -tau (r^T basis) / |l| (the basis is perpendicular to d)
            k_dir *= inv[:, :, None, None]
            k_dl = (kd if h is None else per_sensor(k, dl)) * (tau[None, :] * inv * inv)[..., None]
            rb = np.einsum("na,nac->nc", rates, self.basis)
            for c in range(2):
                k_dir[..., c] += k_dl * rb[:, None, None, c]
        gain = 1.0 / (1.0 - inputs.temperatures[:, :, None] * g[None, :, :]) \
            if g is not None and inputs.temperatures is not None else np.ones((1, 1, 1))
        self.pred = gain * kd + per_sensor(w[:, :, 3:], psi)
        self.e = self.pred - x
        self.m = gain[..., None] * k_dir  # (N, S, 3, 2) d pred / d direction
        ws = weights / sigma[None, :] ** 2
        self.ws = ws
        wm = ws[:, :, None, None] * self.m
        self.c = gram2(wm, self.m)  # (N, 2, 2)
        self.g_d = np.einsum("nsa,nsac->nc", self.e, wm)  # (N, 2)
        self.cost = float(np.sum(ws[:, :, None] * self.e * self.e))
        self.shape = (s, p)
        self.globals = ng
        extras = p - 3 * q  # the gain tempcos' and the lag's columns, after every axis's linear ones
        temperature = model.gain_slice is not None and inputs.temperatures is not None
        lag = model.lag_index is not None and d_tau is not None
        self._globals_rows: tuple[Array, Array] | None = None
        self._rows: Array | None = None  # the sets' direction rows, once built (:meth:`_direction_rows`)
        self._a_blocks: Array | None = None  # the sums over every set, once asked for (:attr:`a_blocks`)
        self._a_globals: tuple[Array, Array] | None = None
        if STRUCTURED and extras == 3 * int(temperature) + int(lag):
            x_cols = None
            if extras:
                x_cols = np.zeros((n, s, 3, extras))
                if temperature:
                    for a in range(3):
                        x_cols[:, :, a, a] = inputs.temperatures * kd[:, :, a] * gain[:, :, a] ** 2
                if lag:
                    x_cols[:, :, :, -1] = gain * per_sensor(k, d_tau)
            g_sum = self._structured(_sets_last_features(seen, psi, gain), x_cols, ws)
            b = None
        else:
            self._features = None
            jac = np.zeros((n, s, 3, p))
            for a in range(3):
                jac[:, :, a, a * q : a * q + 3] = gain[:, :, a, None] * seen if gain.shape[0] > 1 else seen
                jac[:, :, a, a * q + 3 : a * q + q] = psi
            if model.gain_slice is not None and inputs.temperatures is not None:
                for a in range(3):
                    jac[:, :, a, model.gain_slice.start + a] = inputs.temperatures * kd[:, :, a] * gain[:, :, a] ** 2
            if model.lag_index is not None and d_tau is not None:
                jac[:, :, :, model.lag_index] = gain * per_sensor(k, d_tau)
            wj = jac * ws[:, :, None, None]
            self._dense = (jac, wj)
            b = np.matmul(wj.transpose(0, 1, 3, 2), self.m).reshape(n, s * p, 2)
            self._set_scores = np.einsum("nsap,nsa->nsp", wj, self.e).reshape(n, s * p)
            g_sum = np.ones(n) @ self._set_scores
        g_theta = g_sum.reshape(-1)  # (S P,) summed over the sets
        if ng:  # the global blocks: the site gradient in the readings, the attitude residuals
            assert att is not None
            # the readings' Jacobian by the globals is the site gradient's, by its own columns only (the others zero)
            gj = att_blocks.gradient_jacobian(att.inputs, att.state, model, compact=True)
            cols = np.zeros(0, np.int64) if gj is None else att_blocks.gradient_columns(model)
            jac_g = np.zeros((n, s, 3, 0)) if gj is None else gain[..., None] * np.matmul(k[None], gj)
            wjg = jac_g * ws[:, :, None, None]
            ea = att_blocks.attitude_residuals(att.inputs, att.state, d)
            ja = att_blocks.attitude_jacobian(att.inputs, att.state, model)
            pa = att.precision
            self._global_jac, self._global_cols = (jac_g, wjg, ja, pa), cols
            per_set_g = pa[:, None] * np.matmul(ea[:, None, :], ja)[:, 0]
            per_set_g[:, cols] += np.einsum("nsag,nsa->ng", wjg, self.e)
            g_global = per_set_g.sum(axis=0)
            b_g = np.matmul((ja * pa[:, None, None]).transpose(0, 2, 1), self.basis)
            b_g[:, cols] += np.matmul(wjg.reshape(n, s * 3, len(cols)).transpose(0, 2, 1), self.m.reshape(n, s * 3, 2))
            self.c = self.c + pa[:, None, None] * np.eye(2)[None]  # basis^T basis = I
            self.g_d = self.g_d + pa[:, None] * np.einsum("nac,na->nc", self.basis, ea)
            self.cost += float(np.sum(pa[:, None] * ea * ea))
            if self._features is None:
                b = np.concatenate([b, b_g], axis=1)
                self._set_scores = np.concatenate([self.set_scores, per_set_g], axis=1)
            else:  # the globals' rows of B and of the scores, joined to the sensors' when these are built
                self._globals_rows = (b_g, per_set_g)
            self.g_theta = np.concatenate([g_theta.reshape(-1), g_global])
        else:
            self.g_theta = g_theta.reshape(-1)
        self._b = b

    def _structured(self, phi: Array, x_cols: Array | None, ws: Array) -> Array:
        """The sensors' normal matrices from the features, without the (N, S, 3, P) Jacobian: axis a has
        ``phi`` (S, 1 or 3, q, N, the sets last; shared by the axes without temperature) in its own q columns and
        zeros elsewhere, then the extra columns ``x_cols`` (N, S, 3, X: a gain tempco in its axis only, the lag
        in every axis). The gradient summed over the sets, (S, P); each set's is built when asked for."""
        s, q = phi.shape[0], phi.shape[2]
        lin, p = 3 * q, self.shape[1]
        wphi = phi * np.ascontiguousarray(ws.T)[:, None, None, :]
        g_sum = np.empty((s, p))
        g_sum[:, :lin] = _axis_sums(self.e, wphi)
        wx = None
        if x_cols is not None:
            wx = x_cols * ws[:, :, None, None]
            g_sum[:, lin:] = per_sensor_dot(wx, self.e)
        self._set_scores = None
        self._features = (wphi, wx)  # the direction couplings B and the scores, built when asked for
        self._unweighted = (phi, x_cols)
        return g_sum

    @property
    def a_blocks(self) -> Array:
        """(S, P, P) each sensor's normal matrix over every set (built once, when asked for: an evaluation whose
        information comes from its parts' (:meth:`part_information`) never sums them whole)."""
        if self._a_blocks is None:
            self._a_blocks = self._sensor_blocks(slice(None))
        return self._a_blocks

    @property
    def a_sg(self) -> Array | None:
        """(S, P, G) the sensors' and the global parameters' cross blocks over every set; None without globals."""
        return self._full_globals()[0]

    @property
    def a_gg(self) -> Array | None:
        """(G, G) the global parameters' own normal matrix over every set; None without globals."""
        return self._full_globals()[1]

    def _full_globals(self) -> tuple[Array | None, Array | None]:
        if not self.globals:
            return None, None
        if self._a_globals is None:
            self._a_globals = self._global_blocks(slice(None))
        return self._a_globals

    def _sensor_blocks(self, rows: slice | NDArray[np.int64]) -> Array:
        """(S, P, P) each sensor's normal matrix ``sum_k J_k^T W J_k`` over the sets ``rows``."""
        p = self.shape[1]
        if self._features is None:
            jac, wj = (a[rows] for a in self._dense)
            return np.stack([wj[:, i].reshape(-1, p).T @ jac[:, i].reshape(-1, p) for i in range(self.shape[0])])
        (wphi, wx), (phi, x_cols) = self._features, self._unweighted
        return _linear_blocks(phi[..., rows], wphi[..., rows], None if x_cols is None else x_cols[rows],
                              None if wx is None else wx[rows], p)

    def _global_blocks(self, rows: slice | NDArray[np.int64]) -> tuple[Array, Array]:
        """The global parameters' normal matrices over the sets ``rows``: with the sensors' (S, P, G) and their
        own (G, G), the attitude residuals' included."""
        jac_g, wjg, ja, pa = (a[rows] for a in self._global_jac)
        s, p = self.shape
        cols, ng, nc = self._global_cols, self.globals, jac_g.shape[3]
        a_sg = np.zeros((s, p, ng))
        a_gg = (ja * pa[:, None, None]).reshape(-1, ng).T @ ja.reshape(-1, ng)
        if not nc:
            return a_sg, a_gg
        if self._features is None:
            wj = self._dense[1][rows]
            a_sg[:, :, cols] = np.stack([wj[:, i].reshape(-1, p).T @ jac_g[:, i].reshape(-1, nc) for i in range(s)])
        else:
            wphi, wx = self._features
            a_sg[:, :, cols] = _summed_by_features(wphi[..., rows], None if wx is None else wx[rows], jac_g, p)
        a_gg[np.ix_(cols, cols)] += wjg.reshape(-1, nc).T @ jac_g.reshape(-1, nc)
        return a_sg, a_gg

    def _by_features(self, v: Array) -> Array:
        """(N, S P, ...) each set's structured Jacobian rows times ``v`` (N, S, 3, ...) (whitened, ``J^T W v``
        per set): each axis's features times ``v`` in its linear columns, then the extra columns."""
        wphi, wx = self._features  # type: ignore[misc]
        s, _, q, n = wphi.shape
        tail = v.shape[3:]
        out = np.empty((n, s, self.shape[1]) + tail)
        by_set = _axes(wphi).transpose(3, 0, 1, 2)  # (N, S, 3, q), a view
        out[:, :, : 3 * q] = (v[:, :, :, None] * by_set.reshape((n, s, 3, q) + (1,) * len(tail))).reshape(
            (n, s, 3 * q) + tail)
        if wx is not None:
            out[:, :, 3 * q :] = np.einsum("nsax,nsa...->nsx...", wx, v)
        return out.reshape((n, s * self.shape[1]) + tail)

    @property
    def set_scores(self) -> Array:
        """(N, S P + G) each set's contribution to the gradient, its direction held (whitened)."""
        if self._set_scores is None:
            own = self._by_features(self.e)
            self._set_scores = own if self._globals_rows is None else \
                np.concatenate([own, self._globals_rows[1]], axis=1)
        return self._set_scores

    @property
    def b(self) -> Array:
        """(N, S P + G, 2) the couplings ``J^T W M`` of the parameters with each set's direction."""
        if self._b is None:
            own = self._by_features(self.m)
            self._b = own if self._globals_rows is None else np.concatenate([own, self._globals_rows[0]], axis=1)
        return self._b

    def b_times(self, step: Array) -> Array:
        """(N, 2) ``B_k^T step`` for each set: how a parameter step pulls each set's direction (from the
        features when the blocks are structured, without building ``B``)."""
        if self._b is not None or self._features is None:
            return np.einsum("npc,p->nc", self.b, step)
        wphi, wx = self._features
        s, q = wphi.shape[0], wphi.shape[2]
        p, lin = self.shape[1], 3 * q
        st = step[: s * p].reshape(s, p)
        pulled = np.matmul(st[:, :lin].reshape(s, 3, 1, q), _axes(wphi))[:, :, 0].transpose(2, 0, 1)  # (N, S, 3)
        if wx is not None:
            pulled = pulled + np.einsum("nsax,sx->nsa", wx, st[:, lin:])
        out = np.einsum("nsac,nsa->nc", self.m, pulled)
        if self._globals_rows is not None:
            out += np.einsum("ngc,g->nc", self._globals_rows[0], step[s * p :])
        return out

    def reduced(self) -> tuple[Array, Array, float]:
        """The normal equations with each set's direction at its optimum: (information ``A - sum_k B_k
        C_k^-1 B_k^T``, gradient ``g - sum_k B_k C_k^-1 g_k``, cost), whitened, no damping.

        With the structured blocks ``B_k C_k^-1 B_k^T = (B_k L_k)(B_k L_k)^T``, ``L_k L_k^T = C_k^-1``,
        and ``B_k L_k`` is the features times ``M_k L_k``: no ``B`` is built."""
        c_inv = _inv2(self.c)
        y = np.einsum("nab,nb->na", c_inv, self.g_d)
        cost = self.cost - float(np.sum(self.g_d * y))
        if self._b is not None or self._features is None:
            flat_b = self.b.transpose(0, 2, 1).reshape(-1, self.b.shape[1])  # (2 N, S P + G)
            info = self.a_matrix() - np.matmul(self.b, c_inv).transpose(0, 2, 1).reshape(-1, self.b.shape[1]).T @ flat_b
            return info, self.g_theta - y.reshape(-1) @ flat_b, cost
        wphi, wx = self._features
        s, q = wphi.shape[0], wphi.shape[2]
        lin = 3 * q
        my = np.einsum("nsac,nc->nsa", self.m, y)  # M_k C_k^-1 g_k
        corr = np.empty((s, self.shape[1]))
        corr[:, :lin] = _axis_sums(my, wphi)
        if wx is not None:
            corr[:, lin:] = per_sensor_dot(wx, my)
        corr_all = corr.reshape(-1)
        if self._globals_rows is not None:
            corr_all = np.concatenate([corr_all, np.einsum("ngc,nc->g", self._globals_rows[0], y)])
        flat = self._direction_rows(c_inv)
        flat = flat.reshape(flat.shape[0], -1)
        return self.a_matrix() - flat @ flat.T, self.g_theta - corr_all, cost

    def _direction_rows(self, c_inv: Array | None = None) -> Array:
        """(S P + G, 2, N) ``(B_k L_k)^T``, ``L_k L_k^T = C_k^-1``, each set's rows of the information its
        direction takes (``B_k C_k^-1 B_k^T`` is their product), built from the features (kept once built).
        The sets run along the last axis: the products below are long contiguous loops."""
        if self._rows is not None:
            return self._rows
        lower = _chol2(_inv2(self.c) if c_inv is None else c_inv)
        if self._features is None:
            self._rows = times_lower2(self.b, lower).transpose(1, 2, 0)
            return self._rows
        wphi, wx = self._features
        s, _, q, n = wphi.shape
        p, lin = self.shape[1], 3 * q
        g = np.ascontiguousarray(times_lower2(self.m, lower).transpose(1, 2, 3, 0))  # (S, 3, 2, N): M_k L_k
        globals_b = None if self._globals_rows is None else self._globals_rows[0]  # (N, G, 2)
        flat = np.empty((s * p + (0 if globals_b is None else globals_b.shape[1]), 2, n))
        rows = flat[: s * p].reshape(s, p, 2, n)
        # written in place: splitting an axis of the view is a view too
        np.multiply(g[:, :, None], wphi[:, :, :, None], out=rows[:, :lin].reshape(s, 3, q, 2, n))
        if wx is not None:  # sum_a g[s, a, c, n] wx[n, s, a, x]
            wxt = np.ascontiguousarray(wx.transpose(1, 2, 3, 0))  # (S, 3, X, N)
            extra = rows[:, lin:]
            np.multiply(g[:, 0, None], wxt[:, 0, :, None], out=extra)
            for a in (1, 2):
                extra += g[:, a, None] * wxt[:, a, :, None]
        if globals_b is not None:  # the globals' columns: B_k L_k from their rows of B
            flat[s * p :] = times_lower2(globals_b, lower).transpose(1, 2, 0)
        self._rows = flat
        return flat

    def part_information(self, rows: NDArray[np.int64]) -> Array:
        """The information (directions eliminated, as :meth:`information`) of the sets ``rows`` alone: the part
        of the sums over the sets that they add."""
        rows = _as_slice(rows)
        blocks = self._global_blocks(rows) if self.globals else (None, None)
        flat = self._direction_rows()[:, :, rows]
        flat = flat.reshape(flat.shape[0], -1)
        return self._assembled(self._sensor_blocks(rows), *blocks) - flat @ flat.T

    def a_matrix(self) -> Array:
        """The normal matrix of the sensors' (block diagonal) and the global parameters (directions kept)."""
        return self._assembled(self.a_blocks, self.a_sg, self.a_gg)

    def _assembled(self, a_blocks: Array, a_sg: Array | None, a_gg: Array | None) -> Array:
        """The normal matrix from the sensors' blocks (S, P, P) and, with global parameters, their cross (S, P, G)
        and own (G, G) blocks."""
        s, p = self.shape
        a = np.zeros((s * p, s * p))
        for i in range(s):
            a[i * p : (i + 1) * p, i * p : (i + 1) * p] = a_blocks[i]
        if not self.globals or a_sg is None or a_gg is None:
            return a
        cross = a_sg.reshape(s * p, self.globals)
        return np.block([[a, cross], [cross.T, a_gg]])

    def scores(self) -> Array:
        """(N, S P + G) each set's contribution to the reduced gradient (directions eliminated, whitened).

        For white noise ``sum_k s_k s_k^T`` estimates :meth:`information`; with time-correlated
        noise the lagged products add to it (see :mod:`magcal_ros.core.uncertainty`).
        """
        y = np.einsum("nab,nb->na", _inv2(self.c), self.g_d)  # C_k^-1 g_k: each set's score less B_k C_k^-1 g_k
        if self._b is not None or self._features is None:
            return self.set_scores - np.einsum("npc,nc->np", self.b, y)
        own = self._by_features(self.e - np.einsum("nsac,nc->nsa", self.m, y))  # B_k is J_k^T W M_k: linear in M
        if self._globals_rows is None:
            return own
        b_g, per_set_g = self._globals_rows
        return np.concatenate([own, per_set_g - np.einsum("ngc,nc->ng", b_g, y)], axis=1)

    def information(self) -> Array:
        """Schur complement ``A - sum_k B_k C_k^-1 B_k^T`` (no damping)."""
        return self.reduced()[0]


def _as_slice(rows: NDArray[np.int64]) -> slice | NDArray[np.int64]:
    """``rows`` (indices) as a slice where they are a run of consecutive ones (its arrays' parts are then views,
    not copies), else as they are."""
    rows = np.asarray(rows)
    if len(rows) and rows[-1] - rows[0] == len(rows) - 1 and np.all(np.diff(rows) == 1):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


def _sets_last_features(seen: Array, psi: Array, gain: Array) -> Array:
    """(S, 1 or 3, q, N) each axis's linear features ``[gain_a seen, psi]`` with the sets along the last axis
    (one for every axis without temperature, ``gain`` (1, 1, 1)): the sums over the sets below are then long
    contiguous products. ``seen`` (N, S, 3) the field each sensor saw, ``psi`` (N, S, q - 3) the rest's
    features, ``gain`` (N, S, 3) or (1, 1, 1)."""
    n, s, _ = seen.shape
    axes = 1 if gain.shape[0] == 1 else 3
    out = np.empty((s, axes, 3 + psi.shape[2], n))
    seen_t = seen.transpose(1, 2, 0)  # (S, 3, N), a view
    if axes == 1:
        out[:, 0, :3] = seen_t
    else:
        np.multiply(np.ascontiguousarray(gain.transpose(1, 2, 0))[:, :, None, :], seen_t[:, None], out=out[:, :, :3])
    out[:, :, 3:] = psi.transpose(1, 2, 0)[:, None]
    return out


def _axes(features: Array) -> Array:
    """(S, 3, q, N) each axis's features from (S, 1 or 3, q, N) (shared by the axes: a view)."""
    s, _, q, n = features.shape
    return np.broadcast_to(features, (s, 3, q, n))


def _linear_blocks(phi: Array, wphi: Array, x_cols: Array | None, wx: Array | None, p: int) -> Array:
    """(S, P, P) each sensor's normal matrix from its features (:meth:`_Eval._structured`: ``phi`` (S, 1 or 3,
    q, N) in each axis's q columns, the extra columns ``x_cols`` (N, S, 3, X) after them; ``wphi``, ``wx`` the
    same weighted), summed over the N sets."""
    s, axes, q, n = phi.shape
    lin = 3 * q
    a_blocks = np.zeros((s, p, p))
    own = np.matmul(wphi, phi.transpose(0, 1, 3, 2))  # (S, 1 or 3, q, q)
    for i in range(s):
        for a in range(3):
            a_blocks[i, a * q : (a + 1) * q, a * q : (a + 1) * q] = own[i, min(a, axes - 1)]
    if x_cols is not None and wx is not None:
        x = x_cols.shape[3]
        cross = np.matmul(_axes(phi), np.ascontiguousarray(wx.transpose(1, 2, 0, 3))).reshape(s, lin, x)
        a_blocks[:, :lin, lin:] = cross
        a_blocks[:, lin:, :lin] = cross.transpose(0, 2, 1)
        for i in range(s):
            a_blocks[i, lin:, lin:] = wx[:, i].reshape(n * 3, x).T @ x_cols[:, i].reshape(n * 3, x)
    return a_blocks


def _summed_by_features(wphi: Array, wx: Array | None, v: Array, p: int) -> Array:
    """(S, P, G) the structured Jacobian's whitened products with ``v`` (N, S, 3, G) summed over the sets
    (``sum_k J_k^T W v_k`` for each sensor; features as :func:`_linear_blocks`)."""
    s, q = wphi.shape[0], wphi.shape[2]
    n, g = v.shape[0], v.shape[3]
    out = np.empty((s, p, g))
    vt = v.transpose(1, 2, 0, 3)  # (S, 3, N, G): the sets summed by matrix products
    out[:, : 3 * q] = np.matmul(_axes(wphi), vt).reshape(s, 3 * q, g)
    if wx is not None:
        x = wx.shape[3]
        out[:, 3 * q :] = [wx[:, i].reshape(3 * n, x).T @ v[:, i].reshape(3 * n, g) for i in range(s)]
    return out


def _axis_sums(v: Array, features: Array) -> Array:
    """(S, 3 q) ``sum_n v[n, s, a] features[s, a, j, n]`` for ``v`` (N, S, 3) and each axis's features (S, 1
    or 3, q, N; one for every axis: a matrix product per sensor)."""
    s, axes, q, _ = features.shape
    vt = v.transpose(1, 2, 0)  # (S, 3, N)
    if axes == 1:
        return np.matmul(vt, features[:, 0].transpose(0, 2, 1)).reshape(s, 3 * q)
    return np.matmul(features, vt[..., None]).reshape(s, 3 * q)


def _chol2(c: Array) -> Array:
    """(N, 2, 2) lower factors ``L`` with ``L L^T = c`` of symmetric positive semi-definite 2 x 2 matrices
    (zero where ``c`` is)."""
    a = np.maximum(c[:, 0, 0], 0.0)
    la = np.sqrt(a)
    lb = np.divide(c[:, 1, 0], la, out=np.zeros_like(la), where=la > 0)
    out = np.zeros_like(c)
    out[:, 0, 0] = la
    out[:, 1, 0] = lb
    out[:, 1, 1] = np.sqrt(np.maximum(c[:, 1, 1] - lb * lb, 0.0))
    return out


def _inv2(c: Array) -> Array:
    """Inverses of (N, 2, 2) matrices (with a tiny ridge for sets no sensor constrains)."""
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    ridge = 1e-12 * (np.abs(c[:, 0, 0]) + np.abs(c[:, 1, 1]) + 1e-300)
    det = np.where(np.abs(det) > ridge**2, det, det + ridge**2 + 1e-300)
    inv = np.empty_like(c)
    inv[:, 0, 0] = c[:, 1, 1] / det
    inv[:, 1, 1] = c[:, 0, 0] / det
    inv[:, 0, 1] = -c[:, 0, 1] / det
    inv[:, 1, 0] = -c[:, 1, 0] / det
    return inv


def corrected_directions(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs,
                         rates: Array | None, h: Array | None = None) -> Array:
    """(N, S, 3) each reading inverted through its sensor's model (units of F), brought back to the
    set's instant (lag removed to first order): what each sensor says the set's field was
    (``h`` (N, S, 3), the site gradient's field at each sensor, taken off)."""
    b = _inverted(model, theta, x, inputs)
    if h is not None:
        b = b - h
    return _lag_removed(b, model.split(theta)[2], rates)


def _inverted(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs) -> Array:
    """(N, S, 3) each reading inverted through its sensor's model (units of F), the lag left in."""
    s = x.shape[1]
    w, g, _ = model.split(theta)
    rest = x - per_sensor(w[:, :, 3:], inputs.rest_features(s))
    if g is not None and inputs.temperatures is not None:
        rest = rest * (1.0 - inputs.temperatures[:, :, None] * g[None, :, :])
    return per_sensor(np.linalg.inv(w[:, :, :3]), rest)


def _lag_removed(b: Array, tau: Array | None, rates: Array | None) -> Array:
    """The inverted readings ``b`` (N, S, 3, changed in place) brought back to the set's instant: each sensor
    saw the field ``tau`` (S,) s earlier, the field turning at ``rates`` (N, 3) 1/s (first order)."""
    if tau is not None and rates is not None:
        size = row_norms(b) * tau[None, :]
        for i in range(b.shape[1]):
            b[:, i] += size[:, i, None] * rates
    return b


def _directions(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, rates: Array | None,
                weights: Array, h: Array | None = None) -> Array:
    """Field direction per set from the current corrections (weighted mean of the sensors)."""
    return _mean_direction(corrected_directions(model, theta, x, inputs, rates, h), weights)


def _mean_direction(b: Array, weights: Array) -> Array:
    """(N, 3) unit weighted mean of the sensors' corrected readings ``b`` (N, S, 3)."""
    wsum = np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    mean = np.einsum("ns,nsa->na", weights, b) / wsum
    size = row_norms(mean)
    if np.all(size > 0) and np.all(np.isfinite(size)):  # every set has a direction
        return mean / size[:, None]
    norm = size[:, None]
    if not np.all(norm > 0):
        mean = np.where(norm > 0, mean, b.mean(axis=1))
        norm = row_norms(mean)[:, None]
    out = mean / np.where(norm > 0, norm, 1.0)
    out[~np.isfinite(out).all(axis=1) | (norm[:, 0] == 0)] = np.array([0.0, 0.0, 1.0])
    return out


def _prediction(model: ForwardModel, theta: Array, d: Array, inputs: SetInputs, rates: Array | None,
                h: Array | None = None) -> Array:
    """(N, S, 3) predicted readings (units of F); ``h`` (N, S, 3) the site gradient's field at each sensor."""
    w, g, tau = model.split(theta)
    s = w.shape[0]
    if tau is not None and rates is not None:
        dl = _lagged(d, rates, tau)[0]
    else:
        dl = np.broadcast_to(d[:, None, :], (len(d), s, 3))
    if h is not None:
        dl = dl + h
    kd = per_sensor(w[:, :, :3], dl)
    if g is not None and inputs.temperatures is not None:
        kd = kd / (1.0 - inputs.temperatures[:, :, None] * g[None, :, :])
    return kd + per_sensor(w[:, :, 3:], inputs.rest_features(s))


def _cost(model: ForwardModel, theta: Array, d: Array, x: Array, inputs: SetInputs, rates: Array | None,
          weights: Array, sigma: Array, att: _Att | None = None) -> float:
    """The whitened data cost of ``theta`` with directions ``d`` (no prior), the attitude residuals included."""
    e = _prediction(model, theta, d, inputs, rates, None if att is None else att.h()) - x
    cost = float(np.sum((weights / sigma[None, :] ** 2)[:, :, None] * e * e))
    if att is not None:
        ea = att_blocks.attitude_residuals(att.inputs, att.state, d)
        cost += float(np.sum(att.precision[:, None] * ea * ea))
    return cost


def _invertible(model: ForwardModel, theta: Array) -> bool:
    """Finite parameters whose every sensor matrix ``K`` can be inverted (a correction exists)."""
    return bool(np.all(np.isfinite(theta)) and np.all(np.abs(np.linalg.det(model.split(theta)[0][:, :, :3])) > 1e-12))


SETTLED: float = 1e-2
"""A fit has settled when a step it refused promised to lower the whitened cost (its sum of squared
residuals over their noise, and the prior's) by no more than this: the step would move the parameters
by a tenth of their standard deviation. (With a noisy sensor the reduced rows are the cost's
gradient only to first order in the noise: near the optimum their steps need not lower it.)"""


def _damped_step(schur: Array, rhs: Array, free: NDArray[np.bool_], size: int, lam: float,
                 accept: Callable[[Array], bool], negligible: float = 0.0) -> tuple[float, bool]:
    """One Levenberg-Marquardt step on a reduced system: ``-(S + lam D)^-1 rhs`` on the ``free`` parameters
    (``D`` the diagonal of ``S``), ``lam`` raised tenfold until ``accept(step)`` (size ``size``) takes one,
    then lowered tenfold; returns (lam, whether a step was taken). The cost is ``c + 2 rhs.step +
    step.S.step`` to second order: once a step the cost refused promised a decrease of ``negligible`` or
    less, the search ends (converged; a larger ``lam`` only promises less)."""
    diag = np.diag(np.diag(schur)) + 1e-12 * np.trace(schur) / len(schur) * np.eye(len(schur))
    while lam < 1e10:
        step = np.zeros(size)
        try:
            step[free] = -np.linalg.solve(schur + lam * diag, rhs)
        except (np.linalg.LinAlgError, ValueError):
            lam *= 10
            continue
        if accept(step):
            return max(lam / 10, 1e-12), True
        moved = step[free]
        if -(2.0 * float(rhs @ moved) + float(moved @ schur @ moved)) <= negligible:
            return lam, False
        lam *= 10
    return lam, False


def _promised_decrease(schur: Array, rhs: Array) -> float:
    """The decrease ``rhs^T S^-1 rhs`` of the cost's quadratic model ``c + 2 rhs.step + step.S.step`` at its
    minimum (the undamped step); infinite where ``S`` cannot be solved."""
    try:
        return float(rhs @ np.linalg.solve(schur, rhs))
    except (np.linalg.LinAlgError, ValueError):
        return float("inf")


def _solve_lm(
    model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, rates: Array | None, weights: Array,
    sigma: Array, prior: ParameterPrior, iterations: int, tolerance: float, fixed: NDArray[np.bool_],
    att: _Att | None = None, global_start: GlobalState | None = None, renoise: "Renoise | None" = None,
) -> tuple[Array, Array, Array, _Att | None]:
    """Levenberg-Marquardt on the MAP cost with fixed weights, noise and rates; returns (theta, directions,
    the sensors' noise it ended with, global blocks).

    ``renoise``, called once at the first accepted step's point, may give the sensors' noise and the global
    blocks anew (the start's residuals carried what it did not model): the fit goes on with them.

    The directions are eliminated exactly (Schur complement, computed once per iteration) and
    the damping acts on the reduced system, so a rejected step costs one small solve. Parameters
    marked ``fixed`` (S, P) keep their values. With the global blocks (``att``) their parameters
    join the reduced system after the sensors'; a weak prior (:data:`~magcal_ros.core.attitude_blocks.
    WEAK_GLOBAL_SIGMA`) about ``global_start`` keeps the directions the data leave free finite.
    One sensor whose readings are linear in the model (:func:`_rank_one`): :func:`_solve_rank_one`.
    A step whose decrease of the cost is the one the quadratic model promised for its minimum (to
    :data:`SETTLED`) ends the fit without another evaluation: what a further step could gain is the
    model's error, no more than that difference.
    """
    if att is None and _rank_one(model):
        theta, d, _ = _solve_rank_one(model, theta, x, inputs, weights, sigma, prior, iterations, tolerance, fixed)
        return theta, d, sigma, None
    s, p = theta.shape
    ng = model.global_size if att is not None else 0
    free = np.concatenate([~fixed.reshape(-1), ~att.inputs.fixed(model) if att is not None else np.zeros(0, bool)])
    prec = np.concatenate([prior.precision().reshape(-1), np.zeros(0) if att is None else
                           att.inputs.global_precision(model)])
    mean = prior.flat_mean().reshape(-1)
    g_start = global_start if global_start is not None else (None if att is None else att.state)
    d = _directions(model, theta, x, inputs, rates, weights, None if att is None else att.h())
    lam = 1e-4

    def deviation(tv: Array, a: _Att | None) -> Array:
        dev = tv.reshape(-1) - mean
        if a is None or g_start is None:
            return dev
        return np.concatenate([dev, a.state.deviation(g_start, model)])

    def prior_cost(tv: Array, a: _Att | None) -> float:
        diff = deviation(tv, a)
        return float(np.sum(prec * diff * diff))

    cur: _Eval | None = _Eval(model, theta, d, x, inputs, rates, weights, sigma, att)
    cost = cur.cost + prior_cost(theta, att)
    done = False
    for _ in range(iterations):
        if cur is None:  # (evaluated here, not after the step: the last accepted step needs no evaluation)
            cur = _Eval(model, theta, d, x, inputs, rates, weights, sigma, att)
        info, grad, at_best = cur.reduced()
        schur = (info + np.diag(prec))[np.ix_(free, free)]
        rhs = (grad + prec * deviation(theta, att))[free]
        if not (np.all(np.isfinite(schur)) and np.all(np.isfinite(rhs))):
            break
        at = cur
        c_inv = _inv2(at.c)
        negligible = max(tolerance * cost, SETTLED)
        promised = cur.cost - at_best + _promised_decrease(schur, rhs)  # the directions' share, the parameters'

        def accept(step: Array) -> bool:
            nonlocal theta, d, cost, att, done, cur
            t_new = theta + step[: s * p].reshape(s, p)
            if not _invertible(model, t_new):
                return False
            dd = -np.einsum("nab,nb->na", c_inv, at.g_d + at.b_times(step))  # noqa: B023 (called within this iteration)
            a_new = None if att is None else att.moved(step[s * p :], model)
            d_new = d + np.einsum("nac,nc->na", at.basis, dd)  # noqa: B023
            d_new /= row_norms(d_new)[:, None]
            new_cost = _cost(model, t_new, d_new, x, inputs, rates, weights, sigma, a_new) + prior_cost(t_new, a_new)  # noqa: B023
            if new_cost > cost:
                return False
            done = cost - new_cost <= tolerance * max(cost, 1e-300) or \
                abs(promised - (cost - new_cost)) <= negligible  # noqa: B023
            theta, d, cost, att, cur = t_new, d_new, new_cost, a_new, None
            return True

        lam, improved = _damped_step(schur, rhs, free, s * p + ng, lam, accept, negligible)
        anew = renoise(theta, d, att) if improved and renoise is not None else None
        renoise = None
        if anew is not None:  # weighed anew: the cost is another function, its steps start again
            sigma, att = anew
            cur = _Eval(model, theta, d, x, inputs, rates, weights, sigma, att)
            cost, done = cur.cost + prior_cost(theta, att), False
        if not improved or done:
            break
    return theta, d, sigma, att


def _solve_rank_one(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, weights: Array, sigma: Array,
                    prior: ParameterPrior, iterations: int, tolerance: float,
                    fixed: NDArray[np.bool_]) -> tuple[Array, Array, int]:
    """:func:`_solve_lm` for one sensor whose readings are linear in the model: each set's direction at its
    optimum in closed form (its corrected reading's, :func:`_rank_one_parts`, one reduced row per set
    instead of a 2 x 2 block to eliminate) and the cost those rows linearise (each set's residual along the
    normal of its direction's plane, as in :func:`_single_sensor_pass`). Returns (theta, directions, steps)."""
    free = ~fixed.reshape(-1)
    prec = prior.precision().reshape(-1)
    mean = prior.flat_mean().reshape(-1)
    ws = weights[:, 0] / sigma[0] ** 2

    root = np.sqrt(ws)

    def evaluate(th: Array) -> tuple[Array, Array, Array, float]:
        """Rows and residuals scaled by the root of their weight, directions, cost."""
        _, d, _, unit, along, rest = _rank_one_parts(model, th, x, inputs)
        along *= root
        dev = th.reshape(-1) - mean
        return _kron_rows(unit * root, d, rest), along, d, float(along @ along) + float(np.sum(prec * dev * dev))

    rows, along, d, cost = evaluate(theta)
    lam, steps, done = 1e-4, 0, False
    for steps in range(1, iterations + 1):
        schur = (rows @ rows.T + np.diag(prec))[np.ix_(free, free)]
        rhs = (rows @ along + prec * (theta.reshape(-1) - mean))[free]
        if not (np.all(np.isfinite(schur)) and np.all(np.isfinite(rhs))):
            break

        def accept(step: Array) -> bool:
            nonlocal theta, rows, along, d, cost, done
            t_new = theta + step.reshape(theta.shape)
            if not _invertible(model, t_new):
                return False
            new = evaluate(t_new)
            if new[3] > cost:
                return False
            done = cost - new[3] <= tolerance * max(cost, 1e-300)
            theta, (rows, along, d, cost) = t_new, new
            return True

        lam, improved = _damped_step(schur, rhs, free, theta.size, lam, accept, max(tolerance * cost, SETTLED))
        if not improved or done:
            break
    return theta, np.ascontiguousarray(d.T), steps


def _outliers(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, rates: Array | None,
              weights: Array, h: Array | None = None) -> Array:
    """(N, S) True for readings that disagree with the other sensors of their set or with F.

    Each reading's corrected vector is compared with the mean of the set's other used
    readings (three or more sensors), and its norm with 1 (units of F); either test beyond
    the chi-square bound of its sensor's robust scale flags it.
    """
    n, s, _ = x.shape
    b = corrected_directions(model, theta, x, inputs, rates, h)
    flags = np.zeros((n, s), bool)
    tests = [((np.linalg.norm(b, axis=2) - 1.0) ** 2, 1.0)]
    if s >= 3:
        # leave one out: the mean of the set's *other* used readings
        wsum = weights.sum(axis=1, keepdims=True)
        total = np.einsum("ns,nsa->na", weights, b)
        others = np.maximum(wsum - weights, 0.0)
        ref = (total[:, None, :] - weights[:, :, None] * b) / np.where(others > 0, others, 1.0)[:, :, None]
        q = np.sum((b - ref) ** 2, axis=2)
        q[others == 0] = 0.0  # no other reading: the TMI test only
        tests.append((q, 3.0))
    for q, dof in tests:
        bound = chi2_isf(OUTLIER_PROBABILITY, dof)
        for i in range(s):
            good = q[weights[:, i] > 0, i]
            scale = np.median(good if len(good) else q[:, i]) / chi2_isf(0.5, dof)
            flags[:, i] |= q[:, i] > bound * max(scale, 1e-30)
    return flags


def residual_dof(sigma: Array | None, sensors: int, attitude: float = 0.0) -> Array:
    """(S,) each sensor's residual degrees of freedom per set: 3 less its share of the set's two direction
    parameters, in proportion to the weight ``1 / sigma**2`` (S,) the fit gave it (equal shares without), the
    IMU's attitude sharing with its precision ``attitude`` (1/rad^2, the same units: a direction is a unit
    vector in units of F). A sensor the fit trusted most leaves the smallest residuals: with a single
    ``3 - 2 / S`` its noise came out low and the others' high, and the robust rounds took one round per halving
    of the error."""
    if sigma is None:
        return np.full(sensors, 3.0 - 2.0 / sensors)
    trust = 1.0 / np.maximum(np.asarray(sigma, dtype=float), 1e-300) ** 2
    return 3.0 - 2.0 * trust / (np.sum(trust) + attitude)


def attitude_share(sigma: Array, att: "_Att | None") -> float:
    """The share of each set's direction the IMU's attitude had in a fit that weighed the sensors by ``sigma``
    (S,) units of F and the attitudes by ``att``'s precision (their typical one; 0 without)."""
    p = _attitude_precision(att)
    return p / (float(np.sum(1.0 / np.maximum(np.asarray(sigma, dtype=float), 1e-300) ** 2)) + p)


def _attitude_precision(att: "_Att | None") -> float:
    """The typical precision (1/rad^2) of the attitudes' residuals in ``att`` (0 without)."""
    if att is None:
        return 0.0
    known = att.precision[att.precision > 0]
    return float(np.median(known)) if len(known) else 0.0


def _robust_sigma(e: Array, weights: Array, dof: Array) -> Array:
    """Per-sensor noise per axis from squared residual norms: median scaled for each sensor's ``dof`` (S,)
    (robust)."""
    sq = np.sum(e * e, axis=2)  # (N, S)
    out = np.empty(sq.shape[1])
    for i in range(sq.shape[1]):
        med = chi2_isf(0.5, float(dof[i]))
        used = sq[weights[:, i] > 0, i]
        out[i] = np.sqrt(np.median(used) / med) if len(used) else np.sqrt(np.median(sq[:, i]) / med)
    return out


def _efficient_sigma(e: Array, weights: Array, dof: Array) -> Array:
    """Per-sensor noise per axis from the weighted mean square residual (efficient for clean data)."""
    sq = np.sum(e * e, axis=2)
    used = np.maximum(weights.sum(axis=0), 1.0)
    return np.sqrt(np.sum(weights * sq, axis=0) / (used * dof))


def weak_prior(theta: Array) -> ParameterPrior:
    """The default prior around a start: wide enough to let the data decide everything they
    determine, finite so that undetermined directions stay put (gains of order 1, offsets of
    order F, gain per kelvin of order 1/K, lags of order 1 s)."""
    t = np.asarray(theta, dtype=float)
    return ParameterPrior(t.copy(), np.ones_like(t))


def fixed_parameters(model: ForwardModel, held: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """(S, P) parameters the fit keeps at their start: ``held`` ones, and the reference (first)
    sensor's lag, the gauge of a common lag (every lag is relative to that sensor's)."""
    fixed = np.zeros((model.sensors, model.size), bool) if held is None else np.asarray(held, bool).copy()
    if model.lag_index is not None:
        fixed[0, model.lag_index] = True
    return fixed


def _start_parameters(model: ForwardModel, s: int, f: float, start: Array | None, matrices: Array, offsets: Array,
                      interference: Array | None) -> Array:
    """The fit's start (S, P) in units of F: ``start`` when given, else from the matrices (S, 3, 3), offsets
    (S, 3) T and interference (S, 3, m) T/A, the other blocks at zero."""
    if start is not None:
        return np.asarray(start, dtype=float).reshape(s, model.size).copy()
    k0 = np.linalg.inv(np.asarray(matrices, dtype=float))
    e_raw = np.zeros((s, 3, model.channels)) if interference is None else np.einsum("sab,sbc->sac", k0, interference)
    w = np.concatenate([k0, (np.asarray(offsets, dtype=float) / f)[:, :, None], e_raw / f], axis=2)
    return model.join(model.widen(w))


def _completed_prior(model: ForwardModel, s: int, theta: Array, prior: ParameterPrior | None) -> ParameterPrior:
    """``prior`` with the weak prior around ``theta`` on every parameter it does not cover (all of them
    when there is none)."""
    weak = weak_prior(theta)
    if prior is None:
        return weak
    given = prior.fitted_to(model)
    sig = np.asarray(given.sigma, dtype=float).reshape(s, -1)
    open_ = ~np.isfinite(sig)
    return ParameterPrior(np.where(open_, weak.mean, given.flat_mean()), np.where(open_, weak.sigma, sig))


def _start_residuals(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, rates: Array | None,
                     weights: Array, attitude: bool, h: Array | None) -> Array:
    """The start's residuals (N, S, 3) in units of F, each field direction at its optimum (``attitude``: the
    fit has the IMU's blocks, ``h`` their site-gradient field or None)."""
    if not attitude and _rank_one(model):
        k, d, size, _, _, _ = _rank_one_parts(model, theta, x, inputs)
        return np.asarray(_rank_one_residuals(k, d, size).T[:, None, :])
    return _prediction(model, theta, _directions(model, theta, x, inputs, rates, weights, h), inputs, rates, h) - x


def fit_array(
    raw: Array,
    matrices: Array,
    offsets: Array,
    intensity: float,
    currents: Array | None = None,
    interference: Array | None = None,
    prior: ParameterPrior | None = None,
    weights: Array | None = None,
    robust: bool = True,
    iterations: int = 50,
    tolerance: float = 1e-10,
    *,
    temperatures: Array | None = None,
    times: Array | None = None,
    start: Array | None = None,
    held: NDArray[np.bool_] | None = None,
    attitude: AttitudeInputs | None = None,
    attitude_start: GlobalState | None = None,
    parts: list[NDArray[np.int64]] | None = None,
) -> JointSolution:
    """Joint MAP fit of every sensor from raw sets ``raw`` (N, S, 3) T, starting at
    ``matrices`` (S, 3, 3) / ``offsets`` (S, 3) T / ``interference`` (S, 3, m) T/A.

    ``currents`` (N, m) A; ``temperatures`` (N, S) K about the reference: fit the temperature
    block; ``times`` (N,) s: fit the lag block (two or more sensors; the sets must follow a
    continuous motion); ``start`` (S, P): a full start of every parameter (overrides the
    matrices, offsets and interference); ``held`` (S, P): parameters kept at their start (see
    :func:`fixed_parameters`); ``attitude``: the IMU's attitudes at the sets, fit the global blocks
    (:mod:`magcal_ros.core.attitude_blocks`) from ``attitude_start`` (default: their closed-form
    start from the sensors' directions); ``parts`` (indices of the sets): keep each one's share of the
    normal equations (:class:`PartSums`, what :func:`leave_out_estimates` of these parts takes); ``prior`` on the parameters in units of F (default: a weak prior
    around the start that only keeps undetermined directions finite; parameters it does not
    cover get the weak prior); ``weights`` (N, S) 0/1 to exclude readings from the start;
    ``robust`` re-decides outliers until they settle.
    """
    r = np.asarray(raw, dtype=float)
    n, s, _ = r.shape
    f = float(intensity)
    u = np.zeros((n, 0)) if currents is None else np.asarray(currents, dtype=float).reshape(n, -1)
    if not (np.isfinite(f) and f > 0):
        raise InputError(f"intensity must be a positive number of T, got {intensity}")
    temps = None if temperatures is None else np.asarray(temperatures, dtype=float).reshape(n, s)
    t = None if times is None or s < 2 else np.asarray(times, dtype=float).reshape(n)
    if attitude is not None and len(attitude.groups) != n:
        raise InputError(f"the IMU has {len(attitude.groups)} sets, the readings {n}")
    model = (ForwardModel(s, u.shape[1], temps is not None, t is not None) if attitude is None
             else attitude.model(s, u.shape[1], temps is not None, t is not None))
    inputs = SetInputs(u, temps, t)
    theta = _start_parameters(model, s, f, start, matrices, offsets, interference)
    x = r / f
    weights = np.ones((n, s)) if weights is None else np.asarray(weights, dtype=float).copy()
    prior = _completed_prior(model, s, theta, prior)
    fixed = fixed_parameters(model, held)
    if model.lag_index is not None:
        theta[0, model.lag_index] = 0.0

    def rates_of(th: Array) -> Array | None:
        return None if t is None else direction_rates(_directions(model, th, x, inputs, None, weights), t)

    rates = rates_of(theta)
    att = None
    if attitude is not None:
        state = attitude_start or att_blocks.initial_state(attitude, _directions(model, theta, x, inputs, rates,
                                                                                  weights))
        att = _attitude_weights(_Att(attitude, state, attitude.known.astype(float)),
                                _directions(model, theta, x, inputs, rates, weights), soft=False)
    g_start = None if att is None else att.inputs.prior_state(att.state)

    def h_of(a: _Att | None) -> Array | None:
        return None if a is None else a.h()

    e = _start_residuals(model, theta, x, inputs, rates, weights, att is not None, h_of(att))
    sigma = np.maximum(_robust_sigma(e, weights, residual_dof(None, s)), 1e-12)
    if robust:  # the first round weighs the sensors alike (their median noise): the start's residuals carry
        # what it did not model (temperature, currents), unevenly; with even weights the first estimate of each
        # sensor's noise is unbiased whatever they are, and the next round weighs by it (unless alike)
        sigma = np.full(s, float(np.median(sigma)))
        att = _first_round_attitudes(att, sigma)
    even = robust
    for _ in range(MAX_ROBUST_ROUNDS if robust else 1):
        renoise = _renoised(model, x, inputs, rates, weights, sigma) if even else None
        theta, d, sigma, att = _solve_lm(model, theta, x, inputs, rates, weights, sigma, prior, iterations,
                                         tolerance, fixed, att, g_start, renoise)
        fit_sigma = sigma  # the weights the directions were fitted with: each sensor's residual dof
        if t is not None:
            rates = direction_rates(d, t)
        e = _prediction(model, theta, d, inputs, rates, h_of(att)) - x
        sigma = np.maximum(_robust_sigma(e, weights, residual_dof(fit_sigma, s, _attitude_precision(att))), 1e-12)
        if not robust:
            break
        # Hard exclusion of outliers, and a soft down-weighting of large residuals so that a
        # spike not yet excluded cannot bend the fit (weights 1 for clean data).
        qq = np.sum(e * e, axis=2)
        soft = np.minimum(1.0, SOFT_BOUND * sigma[None, :] ** 2 / np.maximum(qq, 1e-300))
        new_weights = soft * ~_outliers(model, theta, x, inputs, rates, weights > 0.5, h_of(att))
        att, moved = (None, 0.0) if att is None else _attitude_reweighed(att, d, attitude_share(fit_sigma, att))
        if _weights_settled(new_weights - weights, qq, sigma, model.size) and moved < 1e-2 and \
                (not even or float(np.max(np.abs(sigma / fit_sigma - 1.0))) < SETTLED_SIGMA):
            break
        weights, even = new_weights, False
    else:
        theta, d, sigma, att = _solve_lm(model, theta, x, inputs, rates, weights, sigma, prior, iterations,
                                         tolerance, fixed, att, g_start)
        fit_sigma = sigma
    if not np.all(np.isfinite(theta)):
        raise CalibrationFailed("the joint array fit did not converge (non-finite parameters)")
    return _final_solution(model, theta, d, x, inputs, rates, weights, fit_sigma, att, f, fixed, parts)


FIRST_SHARE: float = 0.01
"""The largest share of each set's direction the IMU's attitudes may have in the first robust round."""


def _first_round_attitudes(att: "_Att | None", sigma: Array) -> "_Att | None":
    """``att`` for the first robust round, its attitudes' share of each set's direction (against the sensors
    weighed at ``sigma`` (S,), the start's residuals' common noise) at most :data:`FIRST_SHARE`. The start's
    residuals carry what it did not model (a temperature drift, currents: tens of nT where the noise is 1 nT),
    so against them the IMU's attitudes, weighed by their own residuals, would take a share of the directions
    (several per cent) they lose once the sensors' noise is known, pulling the first round's directions toward
    the IMU by that share of its error: residuals half again the noise, and a round more."""
    if att is None:
        return None
    share = attitude_share(sigma, att)  # p / (field + p): scaling p by c gives c p / (field + c p)
    if share <= FIRST_SHARE:
        return att
    scale = FIRST_SHARE * (1.0 - share) / ((1.0 - FIRST_SHARE) * share)
    return replace(att, precision=att.precision * scale)


Renoise = Callable[[Array, Array, "_Att | None"], "tuple[Array, _Att | None] | None"]
"""Given (theta, directions, global blocks) at a fit's first step, the sensors' noise (S,) and global blocks
to go on with, or None to keep them (:func:`_solve_lm`)."""

RENOISED: float = 0.5
"""The first robust round weighs anew once its first step has brought the sensors' common noise below this
fraction of the start's (:func:`_renoised`)."""


def _renoised(model: ForwardModel, x: Array, inputs: SetInputs, rates: Array | None, weights: Array,
              sigma: Array) -> Renoise:
    """For the first robust round (the sensors weighed alike at ``sigma`` (S,), the start's residuals' common
    noise; with the IMU the attitudes' share capped by :func:`_first_round_attitudes`): once the first step has
    taken up what the start did not model (a temperature drift, currents: residuals tens of times the noise
    fall to it), the sensors weighed alike at their common noise there and the attitudes by their residuals,
    uncapped, for the rest of the round. Without it the round ended at the start's weights and a second did
    the same fit again at the right ones (an evaluation and a step more: a third of the IMU's fit)."""

    def renoise(theta: Array, d: Array, att: _Att | None) -> tuple[Array, _Att | None] | None:
        h = None if att is None else att.h()
        e = _prediction(model, theta, d, inputs, rates, h) - x
        new = _robust_sigma(e, weights, residual_dof(sigma, model.sensors, _attitude_precision(att)))
        common = float(np.median(new))
        if not common < RENOISED * float(np.max(sigma)):
            return None
        share = attitude_share(sigma, att)
        return np.full(model.sensors, max(common, 1e-12)), None if att is None else _attitude_weights(att, d,
                                                                                                      share=share)
    return renoise


def _final_solution(model: ForwardModel, theta: Array, d: Array, x: Array, inputs: SetInputs, rates: Array | None,
                    weights: Array, fit_sigma: Array, att: _Att | None, f: float, fixed: NDArray[np.bool_],
                    parts: list[NDArray[np.int64]] | None) -> JointSolution:
    """The solution at the fit's end (``fit_sigma`` the noise it weighed the sensors by): outliers out, each
    sensor's noise, the information and scores (and the ``parts``' shares), the global blocks' report."""
    s = model.sensors
    # A reading the soft weighting has all but removed (beyond sqrt(2 SOFT_BOUND) noise sd: a
    # spike, a frozen sensor) is excluded, as the outlier tests already treat it: counted as an
    # outlier, and kept out of the residuals the quality gates judge.
    weights = np.where(weights < 0.5, 0.0, weights)
    e = _prediction(model, theta, d, inputs, rates, None if att is None else att.h()) - x
    share = attitude_share(fit_sigma, att)
    sigma = np.maximum(_efficient_sigma(e, weights, residual_dof(fit_sigma, s, _attitude_precision(att))), 1e-15)
    extra: dict[str, Any] = {}
    if att is not None:  # the attitudes weighed as the solution reports them (:func:`_solution_globals`)
        ea = att_blocks.attitude_residuals(att.inputs, att.state, d)
        used = att.precision > 0
        extra = {"globals": att.state, "attitude": att.inputs, "attitude_sigma": att_blocks.robust_sigma(ea, used, share),
                 "attitude_residuals": ea, "attitude_correlation": att.correlation,
                 "attitude_weights": np.where(used, att.precision / max(float(np.max(att.precision)), 1e-300), 0.0)}
        att = replace(att, precision=_attitude_precision_of(extra["attitude_weights"], extra["attitude_sigma"],
                                                            att.correlation))
    if att is None and _rank_one(model):
        info, scores = _rank_one_information(model, theta, x, inputs, weights, sigma[0])
    else:
        final = _Eval(model, theta, d, x, inputs, rates, weights, sigma, att)
        scores = final.scores()
        if parts:
            extra["part_sums"] = _part_sums(final, scores, parts)
        # the information is additive over the sets: where the parts hold every set once, their sum
        info = extra["part_sums"].information.sum(axis=0) if parts and _partition(parts, len(x)) else \
            final.information()
    if att is None:
        return _solution(model, theta, d, weights, sigma * f, e * f, info, scores, f, rates, fixed, **extra)
    red_info, red_scores = _eliminate_globals(info, scores, s * model.size, att.inputs.fixed(model),
                                              att.inputs.global_precision(model))
    extra.update(full_information=info, full_scores=scores)
    return _solution(model, theta, d, weights, sigma * f, e * f, red_info, red_scores, f, rates, fixed, **extra)


def _partition(parts: list[NDArray[np.int64]], n: int) -> bool:
    """Whether ``parts`` (indices) hold each of ``n`` sets exactly once."""
    every = np.concatenate(parts)
    return len(every) == n and bool(np.all(np.bincount(every, minlength=n) == 1))


def _part_sums(ev: "_Eval", scores: Array, parts: list[NDArray[np.int64]]) -> PartSums:
    """Each part's share of the normal equations of ``ev`` (whose per-set ``scores`` are given)."""
    return PartSums(tuple(np.asarray(idx) for idx in parts), np.stack([ev.part_information(idx) for idx in parts]),
                    np.stack([scores[idx].sum(axis=0) for idx in parts]))


SETTLED_MOVE: float = 0.03
"""Robust rounds stop once the weights' change could move no parameter by more than this fraction of its
1-sigma (:func:`_weights_settled`)."""


SETTLED_SIGMA: float = 0.05
"""After the first robust round (the sensors weighed alike) another follows when a sensor's noise estimate is
more than this fraction (its weight twice that) from the common one."""


def _weights_settled(change: Array, qq: Array, sigma: Array, parameters: int) -> bool:
    """Whether a change (N, S) of the readings' weights leaves the fit where it is: no weight moved by 1e-3,
    or the parameters' move it implies is below :data:`SETTLED_MOVE` of their 1-sigma. A reading pulls a
    parameter by its weight change times its residual in noise sd (``sqrt(qq)`` of (N, S) squared norms over
    ``sigma`` (S,)) times its leverage's square root, about ``sqrt(parameters / N)`` for ``parameters`` per
    sensor: the pulls' sum times that bounds the move (a spike excluded pulls by tens of noise sd and is
    followed by another round; 4,000 sets' last few tenths of a noise sd in all move nothing)."""
    change = np.abs(change)
    if np.max(change, initial=0.0) < 1e-3:
        return True
    pull = float(np.sum(change * np.sqrt(qq) / sigma[None, :]))
    return pull * np.sqrt(parameters / max(len(change), 1)) < SETTLED_MOVE


def _attitude_reweighed(att: _Att, d: Array, share: float) -> tuple[_Att, float]:
    """The global blocks reweighed at directions ``d`` (:func:`_attitude_weights`; ``share`` of the directions
    the attitudes had in their fit) and how far their largest precision moved (a fraction of the largest)."""
    before = att.precision
    att = _attitude_weights(att, d, share=share)
    return att, float(np.max(np.abs(att.precision - before)) / max(float(np.max(before)), 1e-300))


def _attitude_weights(att: _Att, d: Array, soft: bool = True, share: float = 0.0) -> _Att:
    """The global blocks with the attitude residuals' precision from their robust 1-sigma at directions
    ``d`` (N, 3) (``share``: of the directions the attitudes had in the fit that gave them), large residuals (an
    IMU glitch) down-weighted in proportion beyond 4 sigma; each weighed by its share of the information their
    time correlation leaves (:meth:`~magcal_ros.core.attitude_blocks.AttitudeInputs.correlation`)."""
    ea = att_blocks.attitude_residuals(att.inputs, att.state, d)
    known = att.inputs.known
    sig = att_blocks.robust_sigma(ea, known, share)
    weight = known.astype(float)
    if soft:
        qq = np.sum(ea * ea, axis=1) / 2.0
        weight *= np.minimum(1.0, SOFT_BOUND * sig**2 / np.maximum(qq, 1e-300))
    correlation = att.inputs.correlation(ea)
    return _Att(att.inputs, att.state, _attitude_precision_of(weight, sig, correlation), correlation)


def _eliminate_globals(info: Array, scores: Array, sp: int, fixed: NDArray[np.bool_],
                       precision: Array) -> tuple[Array, Array]:
    """Information (S P, S P) and scores (N, S P) of the sensors' parameters with the global ones
    eliminated (their prior's ``precision`` (G,) included, fixed ones held): the marginal the sensors' analysis
    uses."""
    keep = np.flatnonzero(~fixed) + sp
    h_gg = info[np.ix_(keep, keep)] + np.diag(precision[~fixed])
    h_sg = info[:sp][:, keep]
    k = np.linalg.solve(h_gg, h_sg.T)  # H_gg^-1 H_gs
    red = info[:sp, :sp] - h_sg @ k
    return 0.5 * (red + red.T), scores[:, :sp] - scores[:, keep] @ k


def _solution(model: ForwardModel, theta: Array, d: Array, weights: Array, sigma: Array, residuals: Array,
              info: Array, scores: Array, f: float, rates: Array | None, fixed: Array | None,
              **extra: Any) -> JointSolution:
    w = model.split(theta)[0]
    mats = np.linalg.inv(w[:, :, :3])
    m = model.channels
    return JointSolution(
        matrices=mats,
        offsets=w[:, :, 3] * f,
        interference=np.einsum("sab,sbc->sac", mats, w[:, :, 4 : 4 + m] * f),
        directions=d,
        weights=weights,
        sigma=sigma,
        residuals=residuals,
        information=info,
        scores=scores,
        w=w.copy(),
        intensity=f,
        model=model,
        theta=np.asarray(theta, dtype=float).copy(),
        rates=rates,
        fixed=fixed,
        **extra,
    )


def fix_rotation_gauge(solution: JointSolution) -> JointSolution:
    """Rotate the platform frame so that the virtual centre sensor ``mean(K_i)`` is upper
    triangular (Li et al.'s convention: the centre sensor's own axes made orthogonal)."""
    k = solution.w[:, :, :3]
    qmat = rq_positive(k.mean(axis=0))[1]
    model = solution.model
    theta = solution.theta.copy()
    w = theta[:, : 3 * model.q].reshape(model.sensors, 3, model.q)
    w[:, :, :3] = np.einsum("sij,kj->sik", k, qmat)  # K_i Q^T
    theta[:, : 3 * model.q] = w.reshape(model.sensors, -1)
    tinv = rotation_map(qmat.T, model)  # the inverse map (Q orthogonal)
    extra: dict[str, Any] = {}
    if solution.globals is not None and solution.full_information is not None and solution.full_scores is not None:
        # the global parameters do not turn with the frame (A's angles are about the IMU axes)
        full = np.zeros((len(tinv) + model.global_size,) * 2)
        full[: len(tinv), : len(tinv)] = tinv
        full[len(tinv) :, len(tinv) :] = np.eye(model.global_size)
        extra = {"globals": solution.globals.rotated(qmat), "full_information": full.T @ solution.full_information @ full,
                 "full_scores": solution.full_scores @ full, "attitude": solution.attitude,
                 "attitude_sigma": solution.attitude_sigma,
                 "attitude_residuals": None if solution.attitude_residuals is None else solution.attitude_residuals @ qmat.T,
                 "attitude_weights": solution.attitude_weights, "attitude_correlation": solution.attitude_correlation}
        if solution.part_sums is not None:
            extra["part_sums"] = solution.part_sums.mapped(full)
    elif solution.part_sums is not None and solution.globals is None:
        extra["part_sums"] = solution.part_sums.mapped(tinv)
    rotated = _solution(model, theta, solution.directions @ qmat.T, solution.weights, solution.sigma,
                        solution.residuals, tinv.T @ solution.information @ tinv, solution.scores @ tinv,
                        solution.intensity, None if solution.rates is None else solution.rates @ qmat.T,
                        solution.fixed, **extra)
    return rotated


def rotation_map(qmat: Array, model: ForwardModel) -> Array:
    """The linear map of the flattened parameters under ``K_i -> K_i Q^T`` (new = T old)."""
    s, p = model.sensors, model.size
    t = np.eye(s * p).reshape(s, p, s * p)
    kidx = model.matrix_indices().reshape(3, 3)  # kidx[a, b] = index of K[a, b]
    for a in range(3):
        block = t[:, kidx[a], :].copy()  # (S, 3, sP): rows K[a, :]
        t[:, kidx[a], :] = np.einsum("sqp,kq->skp", block, qmat)
    return t.reshape(s * p, s * p)


def information_at(w: Array, directions: Array, sigma: Array, model: ForwardModel | None = None) -> Array:
    """The information (S P, S P) that sets with unit field ``directions`` (N, 3) would add to
    the fit ``w`` (units of F), every reading used, noise ``sigma`` (S,) in units of F, no
    currents, at the reference temperature and standing still (so no information on the
    temperature and lag blocks)."""
    n = len(directions)
    s = w.shape[0]
    if model is None:
        model = ForwardModel(s, w.shape[2] - 4)
    inputs = SetInputs(np.zeros((n, model.channels)), np.zeros((n, s)) if model.temperature else None,
                       np.arange(n, dtype=float) if model.lag else None)
    theta = model.join(w)
    rates = np.zeros((n, 3)) if model.lag else None
    x = _prediction(model, theta, directions, inputs, rates)
    return _Eval(model, theta, directions, x, inputs, rates, np.ones((n, s)), sigma).information()



SECOND_ORDER: float = 0.05
"""A refinement step is taken without checking the cost again when the model's second-order terms
over it (the square of its largest parameter change, units of F) stay below this fraction of the
sensors' noise (units of F): a step of 1e-3 (a gain of 0.1 %, an offset of F / 1000) for a fluxgate's
1 nT in 50 uT, of 0.05 for a consumer sensor's 6 %."""
PASS_SETS: int = 50_000
"""Above this many sets :func:`refine_on_all` sums the normal equations of an evenly spread sample of at most
this many (the sets whose index is a multiple of ``ceil(N / PASS_SETS)``): outliers, weights and directions
are still decided on every set. At 50,000 sets the parameters' own scatter adds under 0.1 % to a
four-fluxgate cross's tensor noise; the pass's cost then stops growing with N but for the cheap per-set work."""
REFINE_CHUNK: int = 5_000
"""Sets per chunk of :func:`refine_on_all` (bounds its memory: about 2 kB per set and sensor; at 5,000 a
chunk's arrays stay near the cores' caches: the pass over 200,000 sets takes a fifth less CPU than at 20,000)."""


def _fit_prior(solution: JointSolution, prior: ParameterPrior | None) -> tuple[Array, Array]:
    """Flat mean and precision of the prior a fit used (the weak prior where ``prior`` is silent)."""
    s, p = solution.theta.shape
    given = (weak_prior(solution.theta) if prior is None else prior).fitted_to(solution.model)
    sig = np.asarray(given.sigma, dtype=float).reshape(s, -1)
    mean = np.where(np.isfinite(sig), given.flat_mean(), solution.theta).reshape(-1)
    return mean, np.where(np.isfinite(sig), 1.0 / np.maximum(sig, 1e-300) ** 2, 1.0).reshape(-1)


def _free(solution: JointSolution) -> NDArray[np.bool_]:
    """(S P,) the parameters the fit moved (not held, not the lag gauge)."""
    fixed = solution.fixed if solution.fixed is not None else np.zeros(solution.theta.shape, bool)
    return ~np.asarray(fixed, bool).reshape(-1)


def _step_basis(free: NDArray[np.bool_], gauge: Array | None) -> Array:
    """(S P, r) a basis of the steps that move only ``free`` parameters and keep the linear
    ``gauge`` constraints (C, S P) (the frame's rotation when no prior fixes it)."""
    basis = np.eye(len(free))[:, free]
    if gauge is not None and len(gauge):
        _, sv, vt = np.linalg.svd(np.asarray(gauge, dtype=float) @ basis)
        rank = int(np.sum(sv > 1e-12 * sv[0]))
        basis = basis @ vt[rank:].T
    return basis


def leave_out_estimates(solution: JointSolution, raw: Array, parts: list[NDArray[np.int64]],
                        currents: Array | None = None, prior: ParameterPrior | None = None, *,
                        temperatures: Array | None = None, times: Array | None = None,
                        gauge: Array | None = None) -> Array:
    """(K, S P) the parameters refitted without each of the ``parts`` (indices of sets of ``raw``,
    the sets ``solution`` was fitted on), by one Gauss-Newton step from the solution: the fit
    of the other sets moves by ``(H - H_k)^-1 g_k`` with ``H_k``, ``g_k`` the part's information
    and gradient (the whole gradient is zero at the solution). ``gauge`` as in :func:`refine_on_all`.
    With the IMU's global blocks the step is taken in the sensors' and the global parameters
    together (their weak prior included, held ones kept) and the sensors' part returned.
    The parts' shares of the normal equations are the solution's own when its fit was given these parts
    (:class:`PartSums`: the same readings), else from one evaluation of every set.
    """
    model = solution.model
    s = model.sensors
    _, prec = _fit_prior(solution, prior)
    att = _solution_globals(solution)
    sums = solution.part_sums
    if sums is None or not sums.matches(parts):
        r = np.asarray(raw, dtype=float)
        n = len(r)
        u = np.zeros((n, model.channels)) if currents is None else np.asarray(currents, dtype=float).reshape(n, -1)
        inputs = SetInputs(u, None if temperatures is None else np.asarray(temperatures, dtype=float),
                           None if times is None else np.asarray(times, dtype=float))
        ev = _Eval(model, solution.theta, solution.directions, r / solution.intensity, inputs, solution.rates,
                   solution.weights, solution.sigma / solution.intensity, att)
        sums = _part_sums(ev, ev.scores(), parts)
    infos, grads = sums.information, sums.scores
    if att is None:
        return _leave_out(solution.theta, solution.information + np.diag(prec), infos, grads,
                          _step_basis(_free(solution), gauge))
    assert solution.full_information is not None
    sp, ng = s * model.size, model.global_size
    fixed = att.inputs.fixed(model)
    total = solution.full_information + np.diag(np.concatenate([prec, att.inputs.global_precision(model)]))
    wide = None if gauge is None else np.concatenate([gauge, np.zeros((len(gauge), ng))], axis=1)
    start = np.concatenate([solution.theta.reshape(-1), np.zeros(ng)])
    est = _leave_out(start, total, infos, grads, _step_basis(np.concatenate([_free(solution), ~fixed]), wide))
    return est[:, :sp]


def _solution_globals(solution: JointSolution) -> _Att | None:
    """The global blocks of a solution as its fit left them (the attitude residuals' precision from their
    weights and 1-sigma), None without an IMU."""
    if solution.globals is None or solution.attitude is None:
        return None
    weights = (solution.attitude.known.astype(float) if solution.attitude_weights is None
               else solution.attitude_weights)
    correlation = solution.attitude_correlation
    return _Att(solution.attitude, solution.globals,
                _attitude_precision_of(weights, float(solution.attitude_sigma or 0.0), correlation), correlation)


def _attitude_precision_of(weights: Array, sigma: float, correlation: float) -> Array:
    """(N,) 1/rad^2 each attitude residual's precision from its weight, their 1-sigma (rad) and time correlation."""
    return weights / (max(sigma, 1e-12) ** 2 * correlation)


@dataclass(frozen=True)
class _Pass:
    """One pass of the normal equations over every set, chunked (units of F, whitened)."""

    cost: float
    """Data cost with each set's direction at its optimum (to second order)."""
    information: Array
    """Schur complement of the data (directions eliminated), (S P, S P)."""
    gradient: Array
    """Reduced gradient of the data cost / 2, (S P,)."""
    weights: Array
    """(N, S) the weights used (0: an outlier)."""
    part_information: Array
    """(K, S P, S P) the information of each part of the sets."""
    part_gradient: Array
    """(K, S P) the gradient of each part."""
    vertical: Array
    """(N,) the z component of each set's field direction."""


def _full_pass(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, lag: tuple[Array, Array] | None,
               sigma: Array, chunk: int, parts: list[NDArray[np.int64]], weights: Array | None = None,
               stride: int = 1) -> _Pass:
    """The normal equations at ``theta`` over every set (per part, ``chunk`` sets at a time), or over the sets
    whose index is a multiple of ``stride``; outliers decided at the noise ``sigma`` (units of F) unless
    ``weights`` are given, and every set's direction, on every set. ``lag``: with a lag block, the field's
    rates (N, 3) 1/s and every set's readings inverted at ``theta`` (N, S, 3), the lag left in."""
    s, p = theta.shape
    rates, inverted = (None, None) if lag is None else lag
    bound = chi2_isf(OUTLIER_PROBABILITY, 3.0 - 2.0 / s)  # per reading, its dof in the fit
    if _rank_one(model):
        return _single_sensor_pass(model, theta, x, inputs, sigma[0], chunk, parts, weights, bound)
    infos = np.zeros((len(parts), s * p, s * p))
    grads = np.zeros((len(parts), s * p))
    cost = 0.0
    used = np.empty((len(x), s)) if weights is None else weights
    vertical = np.empty(len(x))

    def one(sl: NDArray[np.int64]) -> tuple[Array, Array, float]:
        """The reduced normal equations of the sets ``sl`` (their weights and verticals filled in)."""
        xc, inc, rc = _take_sets(x, inputs, rates, sl)
        b = None if inverted is None else _lag_removed(inverted[sl], model.split(theta)[2], rc)
        d, w = _weighed_directions(model, theta, xc, inc, rc, sigma, bound, None if weights is None else used[sl], b)
        used[sl] = w
        vertical[sl] = d[:, 2]
        if stride > 1:  # the normal equations of the sample
            keep = sl % stride == 0
            if not np.any(keep):
                return np.zeros((s * p, s * p)), np.zeros(s * p), 0.0
            (xc, inc, rc), d, w = _take_sets(xc, inc, rc, keep), d[keep], w[keep]
        return _Eval(model, theta, d, xc, inc, rc, w, sigma).reduced()  # each direction at its optimum

    step = chunk * min(stride, 4)  # sets a task takes (their directions' arrays bounded: 4 chunks at most)
    tasks = [(k, part[lo : lo + step]) for k, part in enumerate(parts) for lo in range(0, len(part), step)]
    # the chunks side by side on spare cores, added up in their order (the same sums as one by one)
    for (k, _), (info, grad, c) in zip(tasks, map_in_threads(one, [sl for _, sl in tasks])):
        infos[k] += info
        grads[k] += grad
        cost += c
    infos = 0.5 * (infos + infos.transpose(0, 2, 1))
    return _Pass(cost, infos.sum(axis=0), grads.sum(axis=0), used, infos, grads, vertical)


def _take_sets(x: Array, inputs: SetInputs, rates: Array | None,
               sl: NDArray[np.int64] | NDArray[np.bool_]) -> tuple[Array, SetInputs, Array | None]:
    """The readings, inputs and field rates of the sets ``sl`` (indices or a mask)."""
    inc = SetInputs(inputs.currents[sl], None if inputs.temperatures is None else inputs.temperatures[sl],
                    None if inputs.times is None else inputs.times[sl])
    return x[sl], inc, None if rates is None else rates[sl]


def _weighed_directions(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, rates: Array | None,
                        sigma: Array, bound: float, weights: Array | None,
                        corrected: Array | None = None) -> tuple[Array, Array]:
    """Each set's direction (N, 3) and its readings' weights (N, S) at ``theta``: the weights given, or decided
    from the residuals at the noise ``sigma`` (units of F: beyond the outlier ``bound`` out, large ones weigh
    less); the direction is the weighted mean of the sensors' corrected readings (``corrected``, when given)."""
    s = x.shape[1]
    b = corrected_directions(model, theta, x, inputs, rates) if corrected is None else corrected
    if weights is None:
        d = _mean_direction(b, np.ones((len(x), s)))
        e = _prediction(model, theta, d, inputs, rates) - x
        weights = _weigh(np.einsum("nsa,nsa->ns", e, e) / sigma[None, :] ** 2, bound)
        if s == 1 or np.all(weights == 1.0):  # one sensor: its weight does not move its own direction
            return d, weights
    return _mean_direction(b, weights), weights


def _rank_one(model: ForwardModel) -> bool:
    """One sensor whose readings are linear in the model (no gain or lag block, no global blocks):
    :func:`_single_sensor_pass` applies."""
    return model.sensors == 1 and model.size == 3 * model.q and model.lag_index is None


def _weigh(q: Array, bound: float) -> Array:
    """Weights of readings from their squared whitened residuals ``q``: beyond the outlier ``bound`` 0,
    large ones less (down to a half; below it 0)."""
    w = np.where(q > bound, 0.0, np.minimum(1.0, SOFT_BOUND / np.maximum(q, 1e-300)))
    return np.where(w < 0.5, 0.0, w)


def _rank_one_parts(model: ForwardModel, theta: Array, x: Array,
                    inputs: SetInputs) -> tuple[Array, Array, Array, Array, Array, Array | None]:
    """One sensor, readings linear in the model (no gain or lag block), readings ``x`` (N, 1, 3) F, each
    set's direction at its optimum ``d`` (the corrected reading ``b = K^-1 (x - rest)`` normalised):
    (``K`` (3, 3), ``d`` (3, N), ``|b|`` (N,), the unit normals ``nu / |nu|`` (3, N), the residual along
    them (N,), the rest of the features ``[u, dT]`` (q - 4, N) or None without any). Sets run along the
    last axis: every product below is then a long contiguous loop.

    With its direction free, a set constrains the model only along the normal ``nu`` of the plane
    its direction's tangents map to, ``K^-T d``: the Schur complement of the direction is
    ``w J^T nu nu^T J`` with ``nu^T J = nu (x) phi``, ``phi = [d, 1, u, dT]`` (rank one per set, the
    rows of :func:`_kron_rows`), where :class:`_Eval` eliminates a 2 x 2 block per set. The residual is
    ``e = K d + rest - x = K (d - b) = (1 - |b|) K d``, along ``nu``: ``(1 - |b|) / |K^-T d|``."""
    w = np.asarray(theta, dtype=float).reshape(3, model.q)
    k = w[:, :3]
    k_inv = np.linalg.inv(k)
    xt = x[:, 0].T  # (3, N)
    rest = None
    if model.q == 4:  # the offset alone
        b = k_inv @ xt
        b -= (k_inv @ w[:, 3])[:, None]
    else:
        rest = inputs.rest_features(1)[:, 0, 1:].T  # (q - 4, N)
        b = k_inv @ (xt - w[:, 3:4] - w[:, 4:] @ rest)
    size = np.sqrt(np.einsum("an,an->n", b, b))
    if size.min() > 0:
        d = np.divide(b, size, out=b)
    else:
        d = b / np.where(size > 0, size, 1.0)
        d[:, size == 0] = [[0.0], [0.0], [1.0]]
    nu = k_inv.T @ d
    nu_size = np.sqrt(np.einsum("an,an->n", nu, nu))
    nu /= nu_size
    return k, d, size, nu, (1.0 - size) / nu_size, rest


def _rank_one_residuals(k: Array, d: Array, size: Array) -> Array:
    """(3, N) each set's residual ``e = (1 - |b|) K d`` from :func:`_rank_one_parts`'s ``K``, ``d``, ``|b|``."""
    return (1.0 - size) * (k @ d)


def _kron_rows(unit: Array, d: Array, rest: Array | None) -> Array:
    """(P, N) the rows ``nu (x) phi`` of :func:`_rank_one_parts` from (possibly scaled) normals ``unit`` (3, N)."""
    q = 4 + (0 if rest is None else len(rest))
    out = np.empty((3, q, unit.shape[1]))
    np.multiply(unit[:, None, :], d[None, :, :], out=out[:, :3])
    out[:, 3] = unit
    if rest is not None:
        np.multiply(unit[:, None, :], rest[None, :, :], out=out[:, 4:])
    return out.reshape(-1, unit.shape[1])


def _rank_one_information(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, weights: Array,
                          sigma: float) -> tuple[Array, Array]:
    """One sensor linear in the model (:func:`_rank_one_parts`): the information (P, P) and each set's
    score (N, P) with its direction at its optimum, what :class:`_Eval` gives by eliminating 2 x 2 blocks."""
    _, d, _, unit, along, rest = _rank_one_parts(model, theta, x, inputs)
    rows = _kron_rows(unit, d, rest)
    wr = rows * (weights[:, 0] / sigma**2)
    return wr @ rows.T, (wr * along).T


def _single_sensor_pass(model: ForwardModel, theta: Array, x: Array, inputs: SetInputs, sigma: float,
                        chunk: int, parts: list[NDArray[np.int64]], weights: Array | None, bound: float) -> _Pass:
    """:func:`_full_pass` for one sensor (see :func:`_rank_one_parts`): each chunk of the parts,
    in their order, at once."""
    n, p = len(x), model.size
    order = np.concatenate(parts)
    ends = np.cumsum([len(pt) for pt in parts])
    in_place = n > 0 and bool(np.all(order[1:] - order[:-1] == 1)) and order[0] == 0  # (slices, not copies)
    infos = np.zeros((len(parts), p, p))
    grads = np.zeros((len(parts), p))
    cost = 0.0
    used = np.empty((n, 1)) if weights is None else weights
    vertical = np.empty(n)
    for lo in range(0, len(order), chunk):
        sl = slice(lo, min(lo + chunk, n)) if in_place else order[lo : lo + chunk]
        xs = x[sl] if in_place else np.take(x, sl, axis=0)
        us = inputs.currents[sl] if in_place else np.take(inputs.currents, sl, axis=0)
        k, d, size, unit, along, rest = _rank_one_parts(model, theta, xs, SetInputs(us))
        if weights is None:  # by the squared residual at the fit's noise
            e = _rank_one_residuals(k, d, size)
            used[sl, 0] = _weigh(np.einsum("an,an->n", e, e) / sigma**2, bound)
        root = np.sqrt(used[sl, 0]) / sigma  # rows scaled by the root of their weight: products of one matrix
        rows = _kron_rows(unit * root, d, rest)
        along *= root
        vertical[sl] = d[2]
        start = lo
        for kk in range(int(np.searchsorted(ends, lo, side="right")), len(parts)):
            stop = min(int(ends[kk]), lo + len(along))
            a, z = start - lo, stop - lo
            infos[kk] += rows[:, a:z] @ rows[:, a:z].T
            grads[kk] += rows[:, a:z] @ along[a:z]
            start = stop
            if stop == lo + len(along):
                break
        cost += float(along @ along)
    infos = 0.5 * (infos + infos.transpose(0, 2, 1))
    return _Pass(cost, infos.sum(axis=0), grads.sum(axis=0), used, infos, grads, vertical)


def _leave_out(theta: Array, total: Array, infos: Array | list[Array], grads: Array | list[Array],
               basis: Array) -> Array:
    """(K, S P) the solution without each part: ``theta + (H - H_k)^-1 g_k`` within ``basis``
    (``total`` = H with the prior; the whole gradient is zero at ``theta``)."""
    h_all = basis.T @ (total - np.asarray(infos)) @ basis  # (K, b, b): every part at once
    g_all = np.asarray(grads) @ basis  # (K, b)
    try:
        steps = np.linalg.solve(h_all, g_all[:, :, None])[:, :, 0] @ basis.T
        if np.all(np.isfinite(steps)):
            return theta.reshape(-1) + steps
    except (np.linalg.LinAlgError, ValueError):
        pass
    out = []  # (one part at a time: a singular one leaves no step)
    for h, g in zip(h_all, g_all):
        try:
            step = basis @ np.linalg.solve(h, g)
        except (np.linalg.LinAlgError, ValueError):
            step = np.zeros(len(total))
        out.append(theta.reshape(-1) + step)
    return np.array(out)


@dataclass(frozen=True)
class Refinement:
    """What :func:`refine_on_all` found over every set."""

    solution: JointSolution
    """The refined parameters with the information of every set (residuals, weights, scores
    and directions stay the subset's)."""
    excluded: Array
    """(S,) readings excluded as outliers over every set."""
    leave_out: Array
    """(K, S P) the parameters without each of the given parts (a delete-one-part jackknife)."""
    vertical: Array
    """(N,) the z component of every set's field direction (platform frame)."""
    stride: int = 1
    """The normal equations were summed over every ``stride``-th set (1: every set; :data:`PASS_SETS`)."""


def refine_on_all(solution: JointSolution, raw: Array, currents: Array | None = None,
                  prior: ParameterPrior | None = None, *, temperatures: Array | None = None,
                  times: Array | None = None, gauge: Array | None = None,
                  parts: list[NDArray[np.int64]] | None = None, chunk: int = REFINE_CHUNK) -> Refinement:
    """One Gauss-Newton step of ``solution`` (fitted on a subset) over every set of ``raw``
    (N, S, 3) T, chunked so that memory does not grow with N (beyond :data:`PASS_SETS` sets the normal
    equations are an evenly spread sample's, the outliers and directions every set's).

    Outliers are re-decided at the subset's noise; the directions are eliminated as in the
    fit. The step is kept only when it lowers the full cost (at the same weights), unless it
    is small (:data:`SECOND_ORDER`). ``gauge`` (C, S P): linear constraints the step keeps (the
    frame's rotation when no prior fixes it). ``parts``: index arrays of the sets (default:
    one part), for the leave-one-part-out estimates.
    """
    model = solution.model
    f = solution.intensity
    r = np.asarray(raw, dtype=float)
    n, s, _ = r.shape
    x = r / f
    u = np.zeros((n, 0)) if currents is None else np.asarray(currents, dtype=float).reshape(n, -1)
    inputs = SetInputs(u, None if temperatures is None else np.asarray(temperatures, dtype=float).reshape(n, s),
                       None if times is None else np.asarray(times, dtype=float).reshape(n))
    parts = [np.arange(n)] if parts is None else [np.asarray(pt, dtype=np.int64) for pt in parts]
    sigma = solution.sigma / f
    theta = solution.theta
    mean, prec = _fit_prior(solution, prior)
    basis = _step_basis(_free(solution), gauge)

    def lag_at(th: Array) -> tuple[Array, Array] | None:
        """The field's rates (N, 3) 1/s at ``th`` and every set's inverted readings (N, S, 3), the lag left in."""
        if inputs.times is None or model.lag_index is None:
            return None
        inverted = np.concatenate([_inverted(model, th, x[lo:lo + chunk], SetInputs(
            u[lo:lo + chunk], None if inputs.temperatures is None else inputs.temperatures[lo:lo + chunk]))
            for lo in range(0, n, chunk)])
        return direction_rates(_mean_direction(inverted, np.ones((n, s))), inputs.times), inverted

    def total(ps: _Pass, th: Array) -> float:
        diff = th.reshape(-1) - mean
        return ps.cost + float(np.sum(prec * diff * diff))

    stride = 1 if _rank_one(model) else max(1, -(-n // PASS_SETS))  # (one linear sensor: every set, cheaply)
    first = _full_pass(model, theta, x, inputs, lag_at(theta), sigma, chunk, parts, stride=stride)
    h_all = first.information + np.diag(prec)
    try:
        step = -basis @ np.linalg.solve(basis.T @ h_all @ basis,
                                        basis.T @ (first.gradient + prec * (theta.reshape(-1) - mean)))
    except (np.linalg.LinAlgError, ValueError):
        step = np.zeros(s * model.size)
    best, best_pass = theta, first
    grads = first.part_gradient  # each part's gradient at the solution kept (linear in the step)
    if np.any(step) and np.all(np.isfinite(step)) and np.max(np.abs(step)) ** 2 <= SECOND_ORDER * float(np.min(sigma)):
        best = theta + step.reshape(s, model.size)  # linear to far below the noise: no second pass
        grads = first.part_gradient + np.einsum("kpq,q->kp", first.part_information, step)
    elif np.any(step) and np.all(np.isfinite(step)):
        t_new = theta + step.reshape(s, model.size)
        if np.all(np.abs(np.linalg.det(model.split(t_new)[0][:, :, :3])) > 1e-12):
            second = _full_pass(model, t_new, x, inputs, lag_at(t_new), sigma, chunk, parts, first.weights, stride)
            if total(second, t_new) <= total(first, theta):
                best, best_pass, grads = t_new, second, second.part_gradient
    out = _solution(model, best, solution.directions, solution.weights, solution.sigma, solution.residuals,
                    best_pass.information, solution.scores, f, solution.rates, solution.fixed)
    leave = _leave_out(best, best_pass.information + np.diag(prec), best_pass.part_information, grads, basis) \
        if len(parts) > 1 else np.zeros((0, s * model.size))
    return Refinement(out, np.sum(best_pass.weights == 0, axis=0).astype(float), leave, best_pass.vertical, stride)

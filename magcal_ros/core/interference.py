"""Current interference (thrusters, pumps, payload): currents matched to sets, which channels a
run determines, and the gains from a still run.

A current ``u_j`` (A) flowing near the array adds a field proportional to it, fixed to the
platform and different at each sensor. Per sensor ``i`` the corrected field is::

    b_ik = M_i (r_ik - o_i) - D_i u_k

with ``u_k`` (m,) the channel currents of set ``k`` (A) and ``D_i`` (3 x m, T/A, platform
frame) the interference gains (:class:`~magcal_ros.core.calibration.ArrayCalibration`
``interference``; :meth:`~magcal_ros.core.calibration.ArrayCalibration.apply` subtracts it).
``D`` is linear once ``M`` and ``o`` are known: it is estimated jointly with them from a
manoeuvre during which the currents vary (:mod:`magcal_ros.core.array_fit`), or afterwards
from a still run with the currents stepped (:func:`estimate_interference`). A channel is
determined only when its current varies on its own: a current that never varies acts as a
constant offset, two currents in lockstep (or a current that follows the attitude) cannot
be told apart (:func:`undetermined_channels`).
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.stamps import seconds_to_ns
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

DEFAULT_CURRENT_TOLERANCE: float = 0.5
"""Largest age (s) of a channel's latest current value at a set's stamp; older is stale."""
MIN_CURRENT_VARIATION: float = 1e-3
"""A channel whose current varies by less than this RMS (A) never varies."""


# -- currents matched to sets ---------------------------------------------------------------
@dataclass(frozen=True)
class CurrentSamples:
    """The recorded values of one current channel: ``stamps`` (n,) int64 ns, ``values`` (n,) A."""

    channel: str
    stamps: NDArray[np.int64]
    values: Array

    def __post_init__(self) -> None:
        t = np.asarray(self.stamps)
        v = np.asarray(self.values, dtype=float).reshape(-1)
        if t.dtype.kind not in "iu" or t.shape != v.shape:
            raise InputError(f"channel {self.channel}: need integer ns stamps and one current per stamp")
        object.__setattr__(self, "stamps", t.astype(np.int64))
        object.__setattr__(self, "values", v)


def match_currents(
    set_stamps: ArrayLike, samples: Sequence[CurrentSamples], tolerance_ns: int
) -> tuple[Array, NDArray[np.bool_]]:
    """The current of every channel at every set: ``(currents (N, m) A, fresh (N, m))``.

    For a set stamped ``t`` a channel's current is its latest value stamped in
    ``[t - tolerance_ns, t]`` (never a value newer than the set; of equal stamps the one
    recorded last); ``fresh`` is False (and the current 0) when there is none. Non-finite
    values are no values.
    """
    t = np.asarray(set_stamps).astype(np.int64).reshape(-1)
    u = np.zeros((len(t), len(samples)))
    fresh = np.zeros((len(t), len(samples)), bool)
    for j, s in enumerate(samples):
        ok = np.isfinite(s.values)
        order = np.argsort(s.stamps[ok], kind="stable")
        st, val = s.stamps[ok][order], s.values[ok][order]
        if not len(st):
            continue
        idx = np.searchsorted(st, t, side="right") - 1
        at = np.maximum(idx, 0)
        fresh[:, j] = (idx >= 0) & (t - st[at] <= tolerance_ns)
        u[:, j] = np.where(fresh[:, j], val[at], 0.0)
    return u, fresh


@dataclass
class CurrentStats:
    """Sets dropped because a channel had no fresh current (one line for users)."""

    channels: tuple[str, ...]
    tolerance_ns: int
    sets: int = 0
    """Sets looked at."""
    dropped: int = 0
    """Sets without a fresh current of every channel."""
    stale: list[int] = field(default_factory=list)
    """Per channel: sets at which it had no fresh current."""

    def keep(self, fresh: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Count ``fresh`` (N, m) from :func:`match_currents`; the sets to keep (N,)."""
        if not self.stale:
            self.stale = [0] * len(self.channels)
        ok = np.all(fresh, axis=1)
        self.sets += len(ok)
        self.dropped += int(np.sum(~ok))
        for j, n in enumerate(np.sum(~fresh, axis=0)):
            self.stale[j] += int(n)
        return ok

    def describe(self) -> str:
        """``12 sets dropped without a current of every channel within 0.5 s (a: 12)``."""
        per = ", ".join(f"{c}: {n}" for c, n in zip(self.channels, self.stale) if n)
        return (f"{self.dropped} of {self.sets} sets dropped without a current of every channel within "
                f"{self.tolerance_ns / NS_PER_S:g} s before the set ({per})")


def tolerance_of(seconds: float) -> int:
    """A current tolerance in s as integer ns; :class:`InputError` unless finite and >= 0."""
    if not (np.isfinite(seconds) and seconds >= 0):
        raise InputError(f"the current tolerance must be a finite number of seconds >= 0, got {seconds}")
    return int(seconds_to_ns(seconds))


class LatestCurrents:
    """The currents of the channels as a live node receives them, matched to each set by the
    rule of :func:`match_currents`: a channel's current at a set stamped ``t`` is its latest
    value stamped in ``[t - tolerance_ns, t]``.

    Values may arrive in any order, before or after the set; each channel keeps those of the
    last ``keep_ns`` (behind its newest stamp) and at most ``most`` of them. Non-finite values
    are no values. Stamps are int ns, currents A.
    """

    def __init__(self, channels: int, tolerance_ns: int, keep_ns: int = 2 * NS_PER_S, most: int = 4096) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.keep_ns = max(int(keep_ns), 2 * self.tolerance_ns)
        self.most = most
        self._stamps: list[list[int]] = [[] for _ in range(channels)]
        self._values: list[list[float]] = [[] for _ in range(channels)]
        self.received = [0] * channels
        """Values received per channel (finite ones)."""

    @property
    def channels(self) -> int:
        """Number of channels."""
        return len(self._stamps)

    def add(self, channel: int, stamp_ns: int, value: float) -> None:
        """Keep one value (A) of ``channel`` stamped ``stamp_ns``."""
        if not np.isfinite(value):
            return
        st, val = self._stamps[channel], self._values[channel]
        k = bisect.bisect_right(st, stamp_ns)  # after equal stamps: the one received last wins
        st.insert(k, int(stamp_ns))
        val.insert(k, float(value))
        self.received[channel] += 1
        old = bisect.bisect_left(st, st[-1] - self.keep_ns)
        old = max(old, len(st) - self.most)
        if old > 0:
            del st[:old], val[:old]

    def latest(self, channel: int) -> float | None:
        """The newest value of ``channel`` (A), or None."""
        val = self._values[channel]
        return val[-1] if val else None

    def at(self, stamp_ns: int) -> tuple[list[float], list[bool]]:
        """Every channel's current (A) at a set stamped ``stamp_ns`` and whether it is fresh (a
        value stamped in ``[t - tolerance, t]``); a stale channel's current is 0."""
        currents, fresh = [], []
        for st, val in zip(self._stamps, self._values):
            k = bisect.bisect_right(st, stamp_ns) - 1
            ok = k >= 0 and stamp_ns - st[k] <= self.tolerance_ns
            currents.append(val[k] if ok else 0.0)
            fresh.append(ok)
        return currents, fresh


# -- what a run determines ------------------------------------------------------------------
def undetermined_channels(currents: ArrayLike, regressors: ArrayLike | None = None) -> NDArray[np.bool_]:
    """(m,) True for the channels whose gains the currents ``(N, m)`` A cannot determine.

    The part of channel ``j``'s current that a constant, the other channels and
    ``regressors`` (N, k) (e.g. the field directions of a manoeuvre) do not explain varies
    by ``v_j`` (RMS, A). Its gains then have a 1-sigma of ``noise / (sqrt(N) v_j)``, an
    effect at the channel's RMS current ``rms_j`` of ``rms_j / (sqrt(N) v_j)`` noise sd:
    the channel is undetermined when that exceeds
    :data:`~magcal_ros.core.identifiability.WEAK_EFFECT` (a weak interference has no
    envelope to hold in: it is left out like an undetermined one), or when ``v_j`` is below
    :data:`MIN_CURRENT_VARIATION` (the current never varies, or varies in lockstep).
    """
    from magcal_ros.core.identifiability import (
        WEAK_EFFECT,  # here: the live nodes need no scipy
    )

    u = np.asarray(currents, dtype=float)
    n, m = u.shape
    extra = np.zeros((n, 0)) if regressors is None else np.asarray(regressors, dtype=float).reshape(n, -1)
    out = np.zeros(m, bool)
    for j in range(m):
        x = np.concatenate([np.ones((n, 1)), extra, np.delete(u, j, axis=1)], axis=1)
        coef = np.linalg.lstsq(x, u[:, j], rcond=None)[0]
        v = float(np.sqrt(np.mean((u[:, j] - x @ coef) ** 2)))
        rms = float(np.sqrt(np.mean(u[:, j] ** 2)))
        out[j] = v < MIN_CURRENT_VARIATION or rms > WEAK_EFFECT * np.sqrt(n) * v
    return out


def describe_undetermined(channels: Sequence[str], currents: ArrayLike, mask: ArrayLike) -> str:
    """Why the channels in ``mask`` are undetermined, in words (one clause per kind)."""
    u = np.asarray(currents, dtype=float)
    bad = [j for j in np.flatnonzero(np.asarray(mask, bool))]
    never = [j for j in bad if undetermined_channels(u[:, [j]])[0]]
    rest = [j for j in bad if j not in never]
    parts = []
    if never:
        levels = ", ".join(f"{channels[j]} ({np.mean(u[:, j]):.3g} A)" for j in never)
        parts.append(f"{levels} never varied (a constant current is part of the offsets)")
    if rest:
        names = ", ".join(channels[j] for j in rest)
        parts.append(f"{names} varied in lockstep with {'each other' if len(rest) > 1 else 'another channel'} "
                     "or with the attitude")
    return "; ".join(parts)


# -- the still run --------------------------------------------------------------------------
@dataclass(frozen=True)
class InterferenceEstimate:
    """Interference gains from a still run, platform frame of the held calibration."""

    gains: Array
    """(S, 3, m) T/A; 0 for undetermined channels."""
    sigma: Array
    """(S, 3, m) 1-sigma of ``gains`` (T/A); inf for undetermined channels."""
    field: Array
    """(S, 3) the constant field (T) at each sensor during the run, currents off."""
    residual: Array
    """(S,) RMS per axis (T) of what the model leaves."""
    undetermined: NDArray[np.bool_]
    """(m,) channels not solved (see :func:`undetermined_channels`)."""


def estimate_interference(raw: ArrayLike, currents: ArrayLike, calibration: ArrayCalibration) -> InterferenceEstimate:
    """Interference gains from a still run: raw sets (N, S, 3) T, channel currents (N, m) A.

    The vehicle does not move, so with the calibration's matrices and offsets held the
    corrected field of sensor ``i`` is ``M_i (r_ik - o_i) = B_i + D_i u_k`` plus noise: one
    unknown constant field ``B_i`` per sensor (a site gradient or the sensors' small
    disagreement cannot bias the gains) and the gains ``D_i`` (T/A, platform frame), by
    linear least squares. The calibration's own interference is not applied. Channels the
    currents cannot determine are not solved (gains 0, sigma inf); the 1-sigma assumes
    white noise, estimated per sensor and axis from the residuals.
    """
    r = np.asarray(raw, dtype=float)
    u = np.asarray(currents, dtype=float)
    s = calibration.geometry.size
    if r.ndim != 3 or r.shape[1:] != (s, 3) or u.ndim != 2 or len(u) != len(r):
        raise InputError(f"need raw sets (N, {s}, 3) and currents (N, m), got {r.shape} and {u.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(u))):
        raise InputError("raw sets and currents must be finite")
    n, m = u.shape
    bad = undetermined_channels(u) if m else np.zeros(0, bool)
    solved = np.flatnonzero(~bad)
    x = np.concatenate([np.ones((n, 1)), u[:, solved]], axis=1)
    if n < x.shape[1] + 2:
        raise InputError(f"{n} sets cannot determine {len(solved)} channels: record more sets")
    b = np.einsum("sij,nsj->nsi", calibration.matrices, r - calibration.offsets).reshape(n, 3 * s)
    coef, *_ = np.linalg.lstsq(x, b, rcond=None)  # (1 + k, 3 S)
    e = b - x @ coef
    var = np.sum(e * e, axis=0) / (n - x.shape[1])  # (3 S,) per sensor and axis
    xtx_inv = np.linalg.inv(x.T @ x)
    gains = np.zeros((s, 3, m))
    sigma = np.full((s, 3, m), np.inf)
    gains[:, :, solved] = coef[1:].T.reshape(s, 3, len(solved))
    sigma[:, :, solved] = np.sqrt(np.outer(var, np.diag(xtx_inv)[1:])).reshape(s, 3, len(solved))
    residual = np.sqrt(np.mean(e.reshape(n, s, 3) ** 2, axis=(0, 2)))
    return InterferenceEstimate(gains, sigma, coef[0].reshape(s, 3), residual, bad)

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
be told apart (:func:`undetermined_channels`). Nor is a channel whose current varies only within
its reading noise (a payload switched off reads its monitor's milliamperes of noise): the reading
is then not the current, and a gain regressed on it is attenuated towards zero by
``var(true) / (var(true) + var(noise))`` (errors in variables), whatever the number of sets
(:func:`reading_noise`, :data:`NOISE_RATIO`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.matching import LatestValues, MatchStats, checked_samples, match_latest
from magcal_ros.core.side_streams import CURRENT, SideCounts, refuse_units
from magcal_ros.core.stamps import seconds_to_ns
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

DEFAULT_CURRENT_TOLERANCE: float = 0.5
"""Largest age (s) of a channel's latest current value at a set's stamp; older is stale."""
MIN_CURRENT_VARIATION: float = 1e-3
"""A channel whose current varies by less than this RMS (A) never varies."""
NOISE_RATIO: float = 3.0
"""A channel whose current varies (RMS, A) by less than this many times its reading noise
(:func:`reading_noise`) is undetermined: at 3x the gain regressed on the noisy reading is attenuated
by at most 1 - 1/(1 + 1/9) = 10 % (errors in variables), below that the reading is mostly noise."""
MAX_READING_NOISE: float = 0.1
"""Largest sample-to-sample scatter (A, 1 sigma) taken for a current monitor's reading noise (shunt and
hall monitors of a vehicle read to milliamperes, tens at most). A current whose set-to-set changes are
larger changes truly at every set (a PWM-driven load read at the set rate, or simulated random
currents): its first differences are the current, not noise."""


def check_currents(values: ArrayLike, where: str) -> None:
    """:class:`InputError` naming ``where`` when most finite currents exceed :data:`MAX_CURRENT` in magnitude
    (not amperes); a single one beyond is a bad sample, no value (:mod:`~magcal_ros.core.side_streams`)."""
    refuse_units(CURRENT, np.asarray(values, dtype=float).reshape(-1).tolist(), where)


# -- currents matched to sets ---------------------------------------------------------------
@dataclass(frozen=True)
class CurrentSamples:
    """The recorded values of one current channel: ``stamps`` (n,) int64 ns, ``values`` (n,) A."""

    channel: str
    stamps: NDArray[np.int64]
    values: Array
    counts: SideCounts | None = None
    """What the recorded samples came to, when they went through the channel's acceptance."""

    def __post_init__(self) -> None:
        t, v = checked_samples(f"channel {self.channel}: need integer ns stamps and one current", self.stamps,
                               self.values)
        object.__setattr__(self, "stamps", t)
        object.__setattr__(self, "values", v)


def match_currents(
    set_stamps: ArrayLike, samples: Sequence[CurrentSamples], tolerance_ns: int
) -> tuple[Array, NDArray[np.bool_]]:
    """The current of every channel at every set: ``(currents (N, m) A, fresh (N, m))``.

    For a set stamped ``t`` a channel's current is its latest value stamped in
    ``[t - tolerance_ns, t]`` (never a value newer than the set; of equal stamps the one
    recorded last); ``fresh`` is False (and the current 0) when there is none. Non-finite
    values are no values. The rule of every side stream (:func:`~magcal_ros.core.matching.match_latest`).
    """
    return match_latest(set_stamps, samples, tolerance_ns)


@dataclass
class CurrentStats(MatchStats):
    """Sets dropped because a channel had no fresh current (one line for users)."""

    NOUN: ClassVar[str] = "current"
    OWNER: ClassVar[str] = "channel"

    @property
    def channels(self) -> tuple[str, ...]:
        """The current channels (the streams)."""
        return self.streams


def tolerance_of(seconds: float, what: str = "current") -> int:
    """A tolerance in s as integer ns; :class:`InputError` unless finite and >= 0."""
    if not (np.isfinite(seconds) and seconds >= 0):
        raise InputError(f"the {what} tolerance must be a finite number of seconds >= 0, got {seconds}")
    return int(seconds_to_ns(seconds))


LatestCurrents = LatestValues
"""The currents of the channels as a live node receives them (A), matched to each set by the rule
of :func:`match_currents` (see :class:`~magcal_ros.core.matching.LatestValues`)."""


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
        out[j] = v < MIN_CURRENT_VARIATION or rms > WEAK_EFFECT * np.sqrt(n) * v or within_noise(u[:, j], v)
    return out


def reading_noise(current: ArrayLike) -> float:
    """The reading noise (A, 1 sigma) of one channel's currents (N,) in set order, from the data.

    A real current holds or moves slowly from one set to the next (steps, ramps), its reading adds
    independent noise to every set: the first differences are then ``sqrt(2)`` noise except at the few
    steps. Robust scale of the differences (1.4826 median absolute difference, so that steps in fewer
    than half of them do not count) over ``sqrt(2)``; 0 for fewer than 3 sets or a held reading (a
    monitor read slower than the sets repeats its value: its noise does not show)."""
    u = np.asarray(current, dtype=float).reshape(-1)
    if len(u) < 3:
        return 0.0
    return float(1.4826 * np.median(np.abs(np.diff(u))) / np.sqrt(2.0))


def within_noise(current: ArrayLike, variation: float | None = None) -> bool:
    """Whether a channel's current (N,) A varies only within its reading noise: its variation (RMS about
    the mean, A; or ``variation`` given, e.g. what other regressors leave) below :data:`NOISE_RATIO` times
    :func:`reading_noise`, that noise a monitor's (at most :data:`MAX_READING_NOISE`)."""
    u = np.asarray(current, dtype=float).reshape(-1)
    noise = reading_noise(u)
    v = float(np.std(u)) if variation is None else variation
    return 0.0 < noise <= MAX_READING_NOISE and v < NOISE_RATIO * noise


WATCH_SAMPLES: int = 400
"""Latest readings per watched channel its variation is judged over (40 s of a 10 Hz monitor)."""
WATCH_MIN_VARIATION: float = 0.05
"""A watched current that varies by less than this RMS (A) is not named: at a payload's tens of nT/A it moves
the field by about a fluxgate's noise, and a monitor that reads in steps of milliamperes varies by that much."""


class CurrentWatch:
    """Channels whose interference the running calibration does not know (left undetermined by its manoeuvre,
    or new): each one's latest readings (A), and which have varied beyond their reading noise since the watch
    began. A channel named stays named (its interference is still unknown when its current holds again) until
    a new watch, with a new calibration, begins."""

    def __init__(self, channels: Sequence[str], samples: int = WATCH_SAMPLES) -> None:
        self.channels = tuple(channels)
        self._values = [deque(maxlen=samples) for _ in self.channels]
        self.named: dict[str, str] = {}
        """Channel -> how it varied, in words, for the channels named so far (in naming order)."""

    def add(self, index: int, stamp_ns: int, value: float) -> None:
        """One reading (A) of channel ``index`` (its stamp does not matter: the latest readings as they come);
        not a current (:data:`~magcal_ros.core.side_streams.CURRENT`'s check): ignored."""
        if CURRENT.check(value) is None:
            self._values[index].append(float(value))

    def judge(self) -> list[str]:
        """The channels named by this judgement (newly): a current that varies by at least
        :data:`WATCH_MIN_VARIATION` RMS and :data:`NOISE_RATIO` times its reading noise over its latest
        readings."""
        new = []
        for name, values in zip(self.channels, self._values):
            if name in self.named or len(values) < 3:
                continue
            u = np.fromiter(values, float, len(values))
            v, noise = float(np.std(u)), reading_noise(u)
            if v >= max(WATCH_MIN_VARIATION, NOISE_RATIO * noise):
                self.named[name] = (f"{name} varies ({u.min():.3g} .. {u.max():.3g} A, {v:.2g} A RMS over its last "
                                    f"{len(u)} readings, reading noise {noise:.2g} A)")
                new.append(name)
        return new


def describe_undetermined(channels: Sequence[str], currents: ArrayLike, mask: ArrayLike) -> str:
    """Why the channels in ``mask`` are undetermined, in words (one clause per kind)."""
    u = np.asarray(currents, dtype=float)
    bad = [j for j in np.flatnonzero(np.asarray(mask, bool))]
    noisy = [j for j in bad if within_noise(u[:, j])]
    never = [j for j in bad if j not in noisy and undetermined_channels(u[:, [j]])[0]]
    rest = [j for j in bad if j not in never and j not in noisy]
    parts = []
    if never:
        levels = ", ".join(f"{channels[j]} ({np.mean(u[:, j]):.3g} A)" for j in never)
        parts.append(f"{levels} never varied (a constant current is part of the offsets)")
    if noisy:
        levels = ", ".join(f"{channels[j]} ({np.std(u[:, j]):.2g} A RMS, reading noise {reading_noise(u[:, j]):.2g} A)"
                           for j in noisy)
        parts.append(f"{levels} varied only within {'its' if len(noisy) == 1 else 'their'} reading noise (e.g. a "
                     "load switched off: a gain regressed on a reading that is mostly noise is not the channel's)")
    if rest:
        names = ", ".join(channels[j] for j in rest)
        parts.append(f"{names} varied in lockstep with {'each other' if len(rest) > 1 else 'another channel'} "
                     "or with the attitude")
    return "; ".join(parts)


# -- the still run --------------------------------------------------------------------------
@dataclass(frozen=True)
class InterferenceEstimate:
    """Interference gains (a still run, or the currents' steps in a mission), platform frame of the held
    calibration."""

    gains: Array
    """(S, 3, m) T/A; 0 for undetermined channels."""
    sigma: Array
    """(S, 3, m) 1-sigma of ``gains`` (T/A); inf for undetermined channels."""
    field: Array
    """(S, 3) the field (T) at each sensor during the run, currents off (its mean over the sets)."""
    residual: Array
    """(S,) RMS per axis (T) of what the model leaves."""
    undetermined: NDArray[np.bool_]
    """(m,) channels not solved (see :func:`undetermined_channels`)."""


def estimate_interference(raw: ArrayLike, currents: ArrayLike, calibration: ArrayCalibration,
                          temperatures: ArrayLike | None = None) -> InterferenceEstimate:
    """Interference gains from a still run: raw sets (N, S, 3) T, channel currents (N, m) A (and the
    sensors' temperatures (N, S) deg C when the calibration has temperature terms).

    The vehicle does not move, so with the calibration's matrices and offsets held the
    corrected field of sensor ``i`` is ``M_i (r_ik - o_i) = B_i + D_i u_k`` plus noise: one
    unknown constant field ``B_i`` per sensor (a site gradient or the sensors' small
    disagreement cannot bias the gains) and the gains ``D_i`` (T/A, platform frame), by
    linear least squares. The calibration's own interference is not applied. Channels the
    currents cannot determine are not solved (gains 0, sigma inf); the 1-sigma assumes
    white noise, estimated per sensor and axis from the residuals.
    """
    n = len(np.asarray(raw))
    return _regressed_gains(raw, currents, calibration, np.ones((n, 1)), temperatures, "")


def _regressed_gains(raw: ArrayLike, currents: ArrayLike, calibration: ArrayCalibration, nuisance: Array,
                     temperatures: ArrayLike | None, why: str) -> InterferenceEstimate:
    """Per sensor and axis, the corrected field (``calibration``'s matrices and offsets held, its own interference
    not applied) as the columns of ``nuisance`` (N, k) (a constant field; a smooth one) plus ``D_i u``, by linear
    least squares; channels ``nuisance`` explains are not solved (gains 0, sigma inf). ``why``: what the sets
    need more of, for the error when there are too few."""
    r = np.asarray(raw, dtype=float)
    u = np.asarray(currents, dtype=float)
    s = calibration.geometry.size
    if r.ndim != 3 or r.shape[1:] != (s, 3) or u.ndim != 2 or len(u) != len(r):
        raise InputError(f"need raw sets (N, {s}, 3) and currents (N, m), got {r.shape} and {u.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(u))):
        raise InputError("raw sets and currents must be finite")
    n, m = u.shape
    k = nuisance.shape[1]
    bad = undetermined_channels(u, nuisance if k > 1 else None) if m else np.zeros(0, bool)
    solved = np.flatnonzero(~bad)
    x = np.concatenate([nuisance, u[:, solved]], axis=1)
    if n < x.shape[1] + 2:
        raise InputError(f"{n} sets cannot determine {len(solved)} channels{why}: record more sets")
    held = replace(calibration, channels=(), interference=None)  # its own interference is not applied
    b = held.apply_array(r, temperatures=temperatures).reshape(n, 3 * s)
    coef, *_ = np.linalg.lstsq(x, b, rcond=None)  # (k + solved, 3 S)
    e = b - x @ coef
    var = np.sum(e * e, axis=0) / (n - x.shape[1])  # (3 S,) per sensor and axis
    # the gains' variance: the currents' part the nuisance leaves (Frisch-Waugh), inverted (an empty knot
    # interval of the spline leaves the whole normal matrix singular, this part not)
    part = u[:, solved] - nuisance @ np.linalg.lstsq(nuisance, u[:, solved], rcond=None)[0]
    inv = np.linalg.inv(part.T @ part) if len(solved) else np.zeros((0, 0))
    gains = np.zeros((s, 3, m))
    sigma = np.full((s, 3, m), np.inf)
    gains[:, :, solved] = coef[k:].T.reshape(s, 3, len(solved))
    sigma[:, :, solved] = np.sqrt(np.outer(var, np.diag(inv))).reshape(s, 3, len(solved))
    residual = np.sqrt(np.mean(e.reshape(n, s, 3) ** 2, axis=(0, 2)))
    return InterferenceEstimate(gains, sigma, np.mean(x[:, :k] @ coef[:k], axis=0).reshape(s, 3), residual, bad)


# -- the mission: the currents' steps under a smooth field -----------------------------------
STEP_KNOTS: float = 0.5
"""Knot spacing (s) of the smooth field :func:`interference_from_steps` fits under a current's steps: a
cubic spline this fine follows a vehicle's wobble and turns to well under the noise."""


def smooth_basis(seconds: ArrayLike, knots_s: float = STEP_KNOTS) -> Array:
    """(N, K) cubic B-spline basis over the times ``seconds`` (N,) s (in order), knots every ``knots_s``: any
    smooth function of time (the field a moving vehicle's sensors see) is a combination of its columns."""
    from scipy.interpolate import BSpline  # here: the live correction node needs no scipy

    t = np.asarray(seconds, dtype=float).reshape(-1)
    lo, hi = float(t.min()), float(t.max())
    inner = np.linspace(lo, hi, max(int(np.ceil((hi - lo) / knots_s)), 1) + 1)
    knots = np.concatenate([[lo] * 3, inner, [hi] * 3])
    return BSpline.design_matrix(np.clip(t, lo, hi), knots, 3).toarray()


def interference_from_steps(raw: ArrayLike, currents: ArrayLike, calibration: ArrayCalibration,
                            seconds: ArrayLike) -> InterferenceEstimate:
    """Interference gains from the steps of the currents while the vehicle moves: raw sets (N, S, 3) T at times
    ``seconds`` (N,) s, channel currents (N, m) A, the calibration's matrices and offsets held (its own
    interference not applied; no temperature terms).

    The field each sensor sees changes smoothly as the vehicle turns and wobbles; a current that steps (a payload
    switched, a thruster's demand changed) moves it at once. Per sensor and axis, the corrected field is a
    cubic spline in time (:func:`smooth_basis`) plus ``D_i u_k``, by linear least squares: what the spline cannot
    follow of the currents determines the gains, on a straight leg too (where the offsets across the track are
    not determined and the calibration's are kept). Channels whose currents only vary smoothly are not solved
    (:func:`undetermined_channels` with the spline as regressors: gains 0, sigma inf)."""
    if calibration.has_temperature_terms:
        raise InputError("interference from the currents' steps needs a calibration without temperature terms")
    return _regressed_gains(raw, currents, calibration, smooth_basis(seconds), None, " under a smooth field")

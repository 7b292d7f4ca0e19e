"""The vehicle's IMU (``sensor_msgs/Imu``): quaternions, the recorded stream, and its value at each set.

Conventions (REP 103/145, as ``sensor_msgs/Imu`` gives them): ``orientation`` is the
quaternion ``x, y, z, w`` of the rotation ``R`` from the IMU frame to the world frame ENU,
``v_world = R v_imu``; ``angular_velocity`` (rad/s) is in the IMU frame, so
``dR/dt = R [w]x``. A NED system's orientation (IMU to north-east-down) becomes ENU by
``R_enu = C R_ned`` with ``C`` the fixed swap of the world axes (:data:`NED_TO_ENU`); the IMU's
own frame and its angular velocity are left as they are.

Matching to sets (:func:`match_imu`): the rule of every side stream
(:mod:`magcal_ros.core.matching`: a set needs a sample stamped at most ``tolerance`` before
it), refined because the attitude changes fast. A vehicle turning at 30 deg/s turns 0.3
deg in the 10 ms between two samples of a 100 Hz IMU, and 0.3 deg of the Earth's field is
about 250 nT, hundreds of times a fluxgate's noise. So:

- when samples bracket the set instant at most ``tolerance`` apart (a gap longer than that
  is not bridged: the same live, where the set would wait for the next sample no longer),
  the orientation is interpolated on the sphere of rotations (slerp:
  constant angular velocity between the two samples; its error is of second order in the
  sample interval) and the angular velocity linearly;
- otherwise (the end of a recording, a gap after the set) the latest sample within
  ``tolerance`` is propagated to the set instant with its own angular velocity,
  ``R(t) = R(t_k) exp([w_k (t - t_k)]x)`` (first order), or taken as it is when it has none.

Latest-before alone would lag by half a sample interval on average, an attitude error
proportional to the turn rate, biased along the turn: worse on every count. Live nodes do
the same one set at a time (:class:`LatestImu`), waiting for the sample after a set for up
to ``tolerance``.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.matching import KEEP_NS, MatchStats, latest_before
from magcal_ros.core.recording import ImuSamples
from magcal_ros.core.side_streams import SideAcceptance, SideCounts, imu_check, usable_imu
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

DEFAULT_IMU_TOLERANCE: float = 0.1
"""Largest distance (s) between a set and the IMU samples used for it (an IMU runs at 50-400 Hz)."""
IMU_FRAMES: tuple[str, ...] = ("enu", "ned")
"""World frames an orientation may be given in; everything inside is ENU."""
NED_TO_ENU: Array = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""World NED coordinates to world ENU coordinates (a rotation by 180 deg about (1, 1, 0)/sqrt(2))."""
_NED_TO_ENU_Q: Array = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0])


# -- quaternions (x, y, z, w), vectorised over leading axes ---------------------------------------
def quat_multiply(a: ArrayLike, b: ArrayLike) -> Array:
    """Hamilton product ``a b`` (rotation ``R(a) R(b)``) of quaternions ``x, y, z, w``."""
    p, q = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    x1, y1, z1, w1 = np.moveaxis(p, -1, 0)
    x2, y2, z2, w2 = np.moveaxis(q, -1, 0)
    return np.stack([
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
    ], axis=-1)


def quat_to_matrix(q: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) ``x, y, z, w`` (NaN stays NaN)."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def matrix_to_quat(m: ArrayLike) -> Array:
    """Unit quaternions (..., 4) ``x, y, z, w`` with ``w >= 0`` of rotation matrices (..., 3, 3)."""
    r = np.asarray(m, dtype=float)
    shape = r.shape[:-2]
    r = r.reshape(-1, 3, 3)
    out = np.empty((len(r), 4))
    tr = np.trace(r, axis1=1, axis2=2)
    # The largest of 4w^2, 4x^2, 4y^2, 4z^2 gives a well-conditioned branch.
    cand = np.stack([1 + tr, 1 + 2 * r[:, 0, 0] - tr, 1 + 2 * r[:, 1, 1] - tr, 1 + 2 * r[:, 2, 2] - tr], axis=1)
    k = np.argmax(cand, axis=1)
    for i in range(len(r)):
        m_, s = r[i], np.sqrt(max(cand[i, k[i]], 0.0)) * 2.0  # s = 4 * the chosen component
        if k[i] == 0:
            out[i] = [(m_[2, 1] - m_[1, 2]) / s, (m_[0, 2] - m_[2, 0]) / s, (m_[1, 0] - m_[0, 1]) / s, s / 4]
        elif k[i] == 1:
            out[i] = [s / 4, (m_[0, 1] + m_[1, 0]) / s, (m_[0, 2] + m_[2, 0]) / s, (m_[2, 1] - m_[1, 2]) / s]
        elif k[i] == 2:
            out[i] = [(m_[0, 1] + m_[1, 0]) / s, s / 4, (m_[1, 2] + m_[2, 1]) / s, (m_[0, 2] - m_[2, 0]) / s]
        else:
            out[i] = [(m_[0, 2] + m_[2, 0]) / s, (m_[1, 2] + m_[2, 1]) / s, s / 4, (m_[1, 0] - m_[0, 1]) / s]
    out *= np.where(out[:, 3:4] < 0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape(*shape, 4)


def quat_exp(rotvec: ArrayLike) -> Array:
    """Quaternions (..., 4) of rotation vectors (..., 3) (axis times angle, rad)."""
    v = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a, with its series near 0
    k = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([v * k, np.cos(half)], axis=-1)


def quat_log(q: ArrayLike) -> Array:
    """Rotation vectors (..., 3) of unit quaternions (..., 4) (the shorter rotation)."""
    p = np.asarray(q, dtype=float)
    p = p * np.where(p[..., 3:4] < 0, -1.0, 1.0)
    s = np.linalg.norm(p[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, p[..., 3:4])
    k = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)
    return p[..., :3] * k


def slerp(q0: ArrayLike, q1: ArrayLike, fraction: ArrayLike) -> Array:
    """Rotation a ``fraction`` (..., ) of the way from ``q0`` to ``q1`` along the shorter arc."""
    a, b = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
    f = np.asarray(fraction, dtype=float)[..., None]
    delta = quat_multiply(a * np.array([-1.0, -1.0, -1.0, 1.0]), b)  # a^-1 b
    return quat_multiply(a, quat_exp(f * quat_log(delta)))


def ned_to_enu(orientation: ArrayLike) -> Array:
    """Orientations (..., 4) IMU -> world NED as IMU -> world ENU (``R_enu = C R_ned``)."""
    return quat_multiply(np.broadcast_to(_NED_TO_ENU_Q, np.shape(orientation)), orientation)


def imu_frame(name: str) -> str:
    """A world frame name (``enu`` or ``ned``), lower case; :class:`InputError` for any other."""
    frame = str(name).strip().lower()
    if frame not in IMU_FRAMES:
        raise InputError(f"IMU orientation frame must be {' or '.join(IMU_FRAMES)}, got {name!r}")
    return frame


# -- the recorded stream ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ImuStream:
    """Every sample of an IMU: ``stamps`` (n,) int64 ns, ``orientation`` (n, 4) IMU -> world ENU
    (NaN rows: none), ``angular_velocity`` (n, 3) rad/s IMU frame (NaN rows: none), ``frame_id``."""

    stamps: NDArray[np.int64]
    orientation: Array
    angular_velocity: Array
    frame_id: str = ""
    counts: SideCounts | None = None
    """What the recorded samples came to, when they went through the stream's acceptance."""

    def __post_init__(self) -> None:
        t = np.asarray(self.stamps)
        if t.dtype.kind not in "iu":
            raise InputError("IMU stamps must be integer nanoseconds")
        per_set = ImuSamples(self.orientation, self.angular_velocity, self.frame_id)  # validates and normalises
        if len(per_set) != t.size:
            raise InputError(f"IMU has {t.size} stamps but {len(per_set)} samples")
        useful = np.isfinite(per_set.orientation[:, 0]) | np.isfinite(per_set.angular_velocity[:, 0])
        order = np.argsort(t.reshape(-1)[useful], kind="stable")  # ties: the sample recorded last comes last
        object.__setattr__(self, "stamps", t.reshape(-1).astype(np.int64)[useful][order])
        object.__setattr__(self, "orientation", per_set.orientation[useful][order])
        object.__setattr__(self, "angular_velocity", per_set.angular_velocity[useful][order])

    def __len__(self) -> int:
        return len(self.stamps)


def _at(stamps: NDArray[np.int64], q: Array, w: Array, t: NDArray[np.int64],
        tolerance_ns: int) -> tuple[Array, Array, NDArray[np.bool_]]:
    """The rule of the module docstring on sorted samples: orientation (N, 4), angular velocity (N, 3), fresh (N,)."""
    n = len(t)
    q_out, w_out = np.full((n, 4), np.nan), np.full((n, 3), np.nan)
    at, fresh = latest_before(stamps, t, tolerance_ns)
    if not np.any(fresh):
        return q_out, w_out, fresh
    nxt = np.minimum(at + 1, len(stamps) - 1)
    t0, t1 = stamps[at], stamps[nxt]
    exact = t0 == t
    bracket = fresh & ~exact & (nxt > at) & (t1 > t) & (t1 - t0 <= tolerance_ns)
    span = np.where(bracket, t1 - t0, 1).astype(float)
    frac = np.where(bracket, (t - t0) / span, 0.0)
    dt = np.where(fresh, (t - t0) / NS_PER_S, 0.0)
    q0, q1, w0, w1 = q[at], q[nxt], w[at], w[nxt]
    both_q = bracket & np.isfinite(q0[:, 0]) & np.isfinite(q1[:, 0])
    both_w = bracket & np.isfinite(w0[:, 0]) & np.isfinite(w1[:, 0])
    # Latest sample, propagated with its own angular velocity when it has one.
    step = np.where(np.isfinite(w0), w0, 0.0) * dt[:, None]
    q_out[fresh] = quat_multiply(q0[fresh], quat_exp(step[fresh]))
    w_out[fresh] = w0[fresh]
    if np.any(both_q):
        q_out[both_q] = slerp(q0[both_q], q1[both_q], frac[both_q])
    if np.any(both_w):
        f = frac[both_w, None]
        w_out[both_w] = (1.0 - f) * w0[both_w] + f * w1[both_w]
    return q_out, w_out, fresh


def match_imu(set_stamps: ArrayLike, stream: ImuStream, tolerance_ns: int) -> tuple[ImuSamples, NDArray[np.bool_]]:
    """The IMU at every set (rule of the module docstring): ``(ImuSamples, fresh (N,))``.

    A stale set (no sample stamped at most ``tolerance_ns`` before it) gets NaN rows.
    """
    t = np.asarray(set_stamps).astype(np.int64).reshape(-1)
    q, w, fresh = _at(stream.stamps, stream.orientation, stream.angular_velocity, t, tolerance_ns)
    return ImuSamples(q, w, stream.frame_id), fresh


@dataclass
class ImuStats(MatchStats):
    """Sets dropped because the IMU had no sample near them (one line for users)."""

    NOUN = "IMU sample"
    OWNER = ""


class LatestImu:
    """The IMU as a live node receives it, matched to each set by :func:`match_imu`'s rule.

    Samples may arrive in any order; the last ``keep_ns`` (behind the newest stamp) are
    kept, at most ``most``. :meth:`ready` says whether a set can be matched now: once a
    sample newer than the set arrived (it is bracketed), or once ``tolerance`` has passed
    (``now_ns``, the newest set stamp, is more than ``tolerance`` after the set): then the
    latest sample is propagated, or the set is stale.
    """

    def __init__(self, tolerance_ns: int, keep_ns: int = KEEP_NS, most: int = 4096) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.keep_ns = max(int(keep_ns), 4 * self.tolerance_ns)
        self.most = most
        self._stamps: list[int] = []
        self._q: list[tuple[float, float, float, float]] = []
        self._w: list[tuple[float, float, float]] = []
        self.received = 0
        """Samples kept (with an orientation or an angular velocity)."""
        self.frame_id = ""
        self._rule = SideAcceptance(imu_check)

    def add(self, stamp_ns: int, orientation: ArrayLike, angular_velocity: ArrayLike, frame_id: str = "") -> None:
        """Offer one sample (quaternion x, y, z, w IMU -> ENU or NaN; rad/s IMU frame or NaN): kept when the
        stream's acceptance lets it through (:mod:`~magcal_ros.core.side_streams`: an orientation that is not
        a unit quaternion, an angular velocity beyond any gyro, are none; a stamp far off the stream's
        sequence is a glitch)."""
        sample = (np.asarray(orientation, dtype=float).reshape(4).tolist(),
                  np.asarray(angular_velocity, dtype=float).reshape(3).tolist())
        if frame_id:
            self.frame_id = frame_id
        for stamp, kept in self._rule.offer(int(stamp_ns), sample):
            q, w = usable_imu([kept])
            self._keep(stamp, q[0], w[0])

    @property
    def counts(self) -> SideCounts:
        """What the stream's samples came to (values, drops by cause)."""
        return self._rule.counts

    def due(self, stamp_ns: int) -> bool:
        """Whether a sample the stream's rhythm says is stamped at or before ``stamp_ns`` has not come."""
        return self._rule.due(stamp_ns)

    def _keep(self, stamp_ns: int, q: Array, w: Array) -> None:
        k = bisect.bisect_right(self._stamps, stamp_ns)
        self._stamps.insert(k, int(stamp_ns))
        self._q.insert(k, tuple(q.tolist()))  # type: ignore[arg-type]
        self._w.insert(k, tuple(w.tolist()))  # type: ignore[arg-type]
        self.received += 1
        old = max(bisect.bisect_left(self._stamps, self._stamps[-1] - self.keep_ns), len(self._stamps) - self.most)
        if old > 0:
            del self._stamps[:old], self._q[:old], self._w[:old]

    @property
    def newest(self) -> int | None:
        """Stamp (ns) of the newest sample kept, or None."""
        return self._stamps[-1] if self._stamps else None

    def ready(self, stamp_ns: int, now_ns: int, waited_ns: int = 0) -> bool:
        """Whether a set stamped ``stamp_ns`` can be matched now (see the class docstring), or since it
        arrived it waited ``waited_ns`` (receipt clock) beyond the tolerance: a stream's last set, after
        which no newer sample or set comes, is matched too."""
        newest = self.newest
        return ((newest is not None and newest > stamp_ns) or now_ns - stamp_ns > self.tolerance_ns
                or waited_ns > self.tolerance_ns)

    def at(self, stamp_ns: int) -> tuple[Array, Array, bool]:
        """Orientation (4,), angular velocity (3,) at a set stamped ``stamp_ns`` and whether it is fresh."""
        k = bisect.bisect_right(self._stamps, stamp_ns)
        lo = max(k - 1, 0)
        st = np.array(self._stamps[lo : k + 1], np.int64)
        if not len(st):
            return np.full(4, np.nan), np.full(3, np.nan), False
        q, w, fresh = _at(st, np.array(self._q[lo : k + 1]), np.array(self._w[lo : k + 1]),
                          np.array([stamp_ns], np.int64), self.tolerance_ns)
        return q[0], w[0], bool(fresh[0])

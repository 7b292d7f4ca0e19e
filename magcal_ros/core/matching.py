"""Side streams matched to sets: the one rule for currents, temperatures and the IMU.

A set stamped ``t`` takes a stream's latest value stamped in ``[t - tolerance, t]``: never a
value newer than the set, of equal stamps the one recorded last. Only samples the stream's
acceptance lets through are values (:mod:`magcal_ros.core.side_streams`: a number in the
stream's range, a stamp not far off its sequence), offline and live alike. A set without such a value is *stale* for that stream; what happens to it (dropped
offline, withheld or not collected live) is counted per stream (:class:`MatchStats`).
The IMU refines the rule where it matters (:mod:`magcal_ros.core.imu`): a fast-turning
vehicle's attitude is interpolated to the set instant when samples bracket it.

Offline (bags) the streams' samples are matched in batches (:func:`latest_before`,
:func:`match_latest`); live nodes keep the last seconds of each stream and match one set
at a time with the same rule (:class:`LatestValues`). Stamps are int64 nanoseconds.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.side_streams import Check, SideAcceptance, SideCounts, accepted_samples
from magcal_ros.core.sync_rules import HOLD_NS
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

Array = NDArray[np.float64]


class Samples(Protocol):
    """A stream of scalar values: ``stamps`` (n,) int64 ns and ``values`` (n,)."""

    stamps: NDArray[np.int64]
    values: Array


def latest_before(
    sample_stamps: ArrayLike, set_stamps: ArrayLike, tolerance_ns: int
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """For each set, the index of the latest sample stamped in ``[t - tolerance_ns, t]``.

    ``sample_stamps`` (n,) must be sorted (ties: the sample recorded last comes last).
    Returns ``(index (N,), fresh (N,))``; ``index`` is clipped to 0 where ``fresh`` is False.
    """
    st = np.asarray(sample_stamps, dtype=np.int64).reshape(-1)
    t = np.asarray(set_stamps).astype(np.int64).reshape(-1)
    if not len(st):
        return np.zeros(len(t), np.int64), np.zeros(len(t), bool)
    idx = np.searchsorted(st, t, side="right") - 1
    at = np.maximum(idx, 0)
    fresh = (idx >= 0) & (t - st[at] <= tolerance_ns)
    return at, fresh


def finite_sorted(stamps: ArrayLike, values: ArrayLike) -> tuple[NDArray[np.int64], Array]:
    """The samples with finite values (every component), in stable stamp order."""
    st = np.asarray(stamps, dtype=np.int64).reshape(-1)
    v = np.asarray(values, dtype=float)
    if not len(st):  # a topic with no message
        return st, v.reshape((0,) + v.shape[1:]) if v.ndim else v.reshape(0)
    ok = np.all(np.isfinite(v.reshape(len(st), -1)), axis=1)
    order = np.argsort(st[ok], kind="stable")
    return st[ok][order], v[ok][order]


def match_latest(set_stamps: ArrayLike, samples: Sequence[Samples], tolerance_ns: int,
                 check: Check | None = None) -> tuple[Array, NDArray[np.bool_]]:
    """Every stream's value at every set: ``(values (N, m), fresh (N, m))`` by the module's rule.

    ``check``: the streams' value check (:mod:`~magcal_ros.core.side_streams`); each stream's samples
    then pass its acceptance in their recorded order (see :func:`accept_streams` for the counts). A
    stale set's value is 0 (and ``fresh`` False).
    """
    if check is not None:
        samples = accept_streams(samples, check)[0]
    t = np.asarray(set_stamps).astype(np.int64).reshape(-1)
    out = np.zeros((len(t), len(samples)))
    fresh = np.zeros((len(t), len(samples)), bool)
    for j, s in enumerate(samples):
        st, val = finite_sorted(s.stamps, s.values)
        if not len(st):
            continue
        at, fresh[:, j] = latest_before(st, t, tolerance_ns)
        out[:, j] = np.where(fresh[:, j], val[at], 0.0)
    return out, fresh


@dataclass(frozen=True)
class AcceptedSamples:
    """A side stream's samples its acceptance let through: ``stamps`` (n,) int64 ns, ``values`` (n,)."""

    stamps: NDArray[np.int64]
    values: Array


def accept_streams(samples: Sequence[Samples], check: Check) -> tuple[list[AcceptedSamples], list[SideCounts]]:
    """Each recorded stream through its acceptance in its recorded order: the samples let through, and
    per stream what was dropped."""
    out, counts = [], []
    for s in samples:
        stamps, values, c = accepted_samples(check, np.asarray(s.stamps).tolist(), np.asarray(s.values).tolist())
        out.append(AcceptedSamples(np.asarray(stamps, np.int64), np.asarray(values, dtype=float)))
        counts.append(c)
    return out, counts


@dataclass
class MatchStats:
    """Sets dropped because a stream had no fresh value (one line for users).

    ``streams`` name the streams (channels, sensors); subclasses say what they carry.
    """

    NOUN: ClassVar[str] = "value"
    """What one stream carries, in the one-line description (``current``, ``temperature``)."""
    OWNER: ClassVar[str] = ""
    """What the streams belong to (``channel``, ``sensor``); empty for a single stream."""

    streams: tuple[str, ...]
    tolerance_ns: int
    samples: list[SideCounts] = field(default_factory=list)
    """Per stream, what its samples came to (drops by cause: out of range, far off its stamps)."""
    sets: int = 0
    """Sets looked at."""
    dropped: int = 0
    """Sets without a fresh value of every stream."""
    stale: list[int] = field(default_factory=list)
    """Per stream: sets at which it had no fresh value."""

    def keep(self, fresh: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Count ``fresh`` (N, m) (e.g. from :func:`match_latest`); the sets to keep (N,)."""
        f = np.asarray(fresh, bool).reshape(len(fresh), -1)
        if not self.stale:
            self.stale = [0] * len(self.streams)
        ok = np.all(f, axis=1)
        self.sets += len(ok)
        self.dropped += int(np.sum(~ok))
        for j, n in enumerate(np.sum(~f, axis=0)):
            self.stale[j] += int(n)
        return ok

    def note(self) -> str:
        """What users should hear: the sets dropped (:meth:`describe`) and the samples that were no value, or
        empty when nothing was lost."""
        parts = [self.describe()] if self.dropped else []
        parts += [line for c, name in zip(self.samples, self.streams)
                  if (line := c.describe(f"{name} {self.NOUN}".strip()))]
        return "; ".join(parts)

    def describe(self) -> str:
        """``12 of 900 sets dropped without a current of every channel within 0.5 s before the set (a: 12)``."""
        per = ", ".join(f"{c}: {n}" for c, n in zip(self.streams, self.stale) if n)
        article = "an" if self.NOUN[:1].lower() in "aeiou" else "a"
        every = f" of every {self.OWNER}" if self.OWNER else ""
        return (f"{self.dropped} of {self.sets} sets dropped without {article} {self.NOUN}{every} within "
                f"{self.tolerance_ns / NS_PER_S:g} s before the set ({per})")


def checked_samples(what: str, stamps: ArrayLike, values: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """A side stream's recorded ``stamps`` (n,) as int64 ns and ``values`` (n,) as floats;
    :class:`InputError` naming ``what`` (``mag1: ... one temperature``) unless the stamps are
    integers and there is one value per stamp."""
    t = np.asarray(stamps)
    v = np.asarray(values, dtype=float).reshape(-1)
    if t.dtype.kind not in "iu" or t.shape != v.shape:
        raise InputError(f"{what} per stamp")
    return t.astype(np.int64), v


KEEP_NS: int = 2 * NS_PER_S + HOLD_NS
"""How far (ns of stamps, behind the newest) a live store keeps side-stream values by default: the sets of a new
segment the synchroniser holds for up to ``HOLD_NS`` come that much later than their values, and still find them."""


class LatestValues:
    """Scalar streams as a live node receives them, matched to each set by the module's rule: a
    stream's value at a set stamped ``t`` is its latest value stamped in ``[t - tolerance_ns, t]``.

    Every sample passes its stream's acceptance first (``check``: the value check,
    :mod:`~magcal_ros.core.side_streams`; :attr:`counts` per stream). Values may arrive in any order,
    before or after the set; each stream keeps those of the last ``keep_ns`` (behind its newest
    stamp) and at most ``most`` of them. Stamps are int ns.
    """

    def __init__(self, streams: int, tolerance_ns: int, keep_ns: int = KEEP_NS, most: int = 4096,
                 check: Check | None = None) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.keep_ns = max(int(keep_ns), 2 * self.tolerance_ns)
        self.most = most
        self._stamps: list[list[int]] = [[] for _ in range(streams)]
        self._values: list[list[float]] = [[] for _ in range(streams)]
        self._rules = [SideAcceptance(check or _finite) for _ in range(streams)]
        self.received = [0] * streams
        """Values kept per stream (samples its acceptance let through)."""

    @property
    def channels(self) -> int:
        """Number of streams."""
        return len(self._stamps)

    @property
    def counts(self) -> list[SideCounts]:
        """Per stream, what its samples came to (values, drops by cause)."""
        return [r.counts for r in self._rules]

    def add(self, stream: int, stamp_ns: int, value: float) -> None:
        """Offer one sample of ``stream`` stamped ``stamp_ns``: kept when its acceptance lets it through."""
        for stamp, v in self._rules[stream].offer(int(stamp_ns), value):
            self._keep(stream, stamp, float(v))

    def _keep(self, stream: int, stamp_ns: int, value: float) -> None:
        st, val = self._stamps[stream], self._values[stream]
        k = bisect.bisect_right(st, stamp_ns)  # after equal stamps: the one received last wins
        st.insert(k, int(stamp_ns))
        val.insert(k, value)
        self.received[stream] += 1
        old = bisect.bisect_left(st, st[-1] - self.keep_ns)
        old = max(old, len(st) - self.most)
        if old > 0:
            del st[:old], val[:old]

    def latest(self, stream: int) -> float | None:
        """The newest value of ``stream``, or None."""
        val = self._values[stream]
        return val[-1] if val else None

    def due(self, stamp_ns: int) -> bool:
        """Whether some stream has a sample due at a set stamped ``stamp_ns`` that has not come
        (:meth:`~magcal_ros.core.side_streams.SideAcceptance.due`): the set should wait for it."""
        return any(r.due(stamp_ns) for r in self._rules)

    def at(self, stamp_ns: int) -> tuple[list[float], list[bool]]:
        """Every stream's value at a set stamped ``stamp_ns`` and whether it is fresh (a value
        stamped in ``[t - tolerance, t]``); a stale stream's value is 0."""
        values, fresh = [], []
        for st, val in zip(self._stamps, self._values):
            k = bisect.bisect_right(st, stamp_ns) - 1
            ok = k >= 0 and stamp_ns - st[k] <= self.tolerance_ns
            values.append(val[k] if ok else 0.0)
            fresh.append(ok)
        return values, fresh


def _finite(value: float) -> str | None:
    """The check of a stream with no range of its own: any number."""
    return None if np.isfinite(value) else "nonfinite"

"""What a side stream's sample must be to be a value: one rule for currents, temperatures and the IMU.

Streams that are not field sensors (a current channel, a sensor's temperature, the IMU) give
each set a value (:mod:`magcal_ros.core.matching`). Before that, every sample passes this
acceptance, in the order its stream delivered it, offline (a bag's topic, a CSV's column) as
live (a node's subscription):

- a value that is not a number (``nonfinite``) or outside what the stream can carry
  (``out_of_range``: a temperature outside -60 .. 150 deg C, a current beyond 1e4 A, an
  orientation that is not a unit quaternion, an angular velocity beyond 35 rad/s): no value;
- a stamp far off the stream's sequence, ahead or behind (more than :data:`FAR_PERIODS` of its
  intervals, and at least :data:`FAR_MIN`), is held until the next sample: kept when the next
  lies nearer to it than to the sequence before (the stream paused, or its clock stepped), dropped
  (``glitch``) when the stream goes on where it was. One sample stamped three years ahead therefore costs that sample, and
  never pushes the stream's later values out of the store that keeps its last seconds.

Samples are counted per stream (:class:`SideCounts`), for the offline notes and ``/diagnostics``.
A stream whose values are mostly out of range is a units error (kelvin for deg C, mA for A),
refused by the readers that can refuse (:func:`bulk_out_of_range`); a single bad sample is only
dropped.

A set waits for a sample that is due (:meth:`SideAcceptance.due`): one the stream's own rhythm
says is stamped at or before the set but has not arrived, for at most :data:`MAX_WAIT`; so a
current stamped with the set and delivered a few milliseconds after the sensors is used live as
it is offline.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from magcal_ros.core.units import NS_PER_S

FAR_PERIODS: int = 8
"""A sample stamped more than this many of its stream's intervals (median) ahead is held (a suspect) ..."""
FAR_MIN: int = 2 * NS_PER_S
"""... and never less far than this (ns): a slow stream's rhythm is loose."""
FAR_EARLY: int = 60 * NS_PER_S
"""How far off (ns) a stamp is a suspect before the stream's rhythm is known (its first samples)."""
INTERVALS: int = 16
"""Stamp intervals of a stream whose median is its rhythm."""
MAX_WAIT: int = NS_PER_S // 2
"""Longest a set waits (ns, node clock) for a side-stream sample that is due."""
AWAKE_STEP: int = NS_PER_S // 10
"""Longest step of a node's clock between two looks at its waiting sets that counts whole towards their wait
(:class:`WaitingSets`): a longer one is a stall of the process, not time it could have received in."""
MAX_CURRENT: float = 1e4
"""Largest magnitude (A) of a current a vehicle's channel can carry; beyond it the values are not
amperes (mA?) or a broken reading."""
TEMPERATURE_RANGE: tuple[float, float] = (-60.0, 150.0)
"""Temperatures (deg C) a fluxgate on a vehicle can have; outside: not deg C, or a broken reading."""
MAX_RATE: float = 35.0
"""Largest angular velocity (rad/s, 2000 deg/s: a MEMS gyro's range) an IMU sample can report."""
QUATERNION_NORM: float = 1e-3
"""How far from 1 a quaternion's norm may be and still be an orientation (renormalised)."""

Check = Callable[[Any], "str | None"]
"""A stream's value check: the fault name (``nonfinite``, ``out_of_range``) or None."""


def scalar_check(low: float, high: float) -> Check:
    """The check of a scalar stream whose values lie in ``[low, high]``."""
    def check(value: Any) -> str | None:
        v = float(value)
        if not math.isfinite(v):
            return "nonfinite"
        return None if low <= v <= high else "out_of_range"

    return check


@dataclass
class SideCounts:
    """What one side stream delivered: every sample ends in exactly one of ``accepted`` or a fault
    counter (or is still ``held``): ``received == accepted + dropped() + held``."""

    received: int = 0
    accepted: int = 0
    nonfinite: int = 0
    out_of_range: int = 0
    glitch: int = 0
    held: int = 0

    def dropped(self) -> int:
        """Samples that gave no value."""
        return self.nonfinite + self.out_of_range + self.glitch

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    def describe(self, stream: str) -> str:
        """``mag1 temperature: 2 of 300 samples dropped (1 out of range, 1 far off the stream's stamps)``, or
        empty when every sample was a value."""
        parts = [f"{n} {_WORDS[name]}" for name, n in self.as_dict().items() if name in _WORDS and n]
        if not parts:
            return ""
        return f"{stream}: {self.dropped()} of {self.received} samples dropped ({', '.join(parts)})"


_WORDS = {"nonfinite": "not a number", "out_of_range": "out of range", "glitch": "far off the stream's stamps"}


class SideAcceptance:
    """The acceptance of one side stream (module docstring): :meth:`offer` each sample in its order,
    get back the samples it lets through (a held one first); :meth:`finish` at the end."""

    def __init__(self, check: Check) -> None:
        self.check = check
        self.counts = SideCounts()
        self.last: int | None = None
        """Stamp (ns) of the latest sample let through."""
        self._intervals: list[int] = []
        self._held: tuple[int, Any] | None = None

    @property
    def interval(self) -> int | None:
        """The stream's rhythm: the median of its last :data:`INTERVALS` stamp intervals (ns), None before 3."""
        iv = sorted(self._intervals)
        return iv[len(iv) // 2] if len(iv) >= 3 else None

    def far(self) -> int:
        """How far off its sequence (ns) a stamp is a suspect (:data:`FAR_EARLY` while the rhythm is unknown)."""
        interval = self.interval
        return max(FAR_MIN, FAR_PERIODS * interval) if interval else FAR_EARLY

    def offer(self, stamp: int, value: Any) -> list[tuple[int, Any]]:
        """One sample (stamp ns, value); the samples let through."""
        counts = self.counts
        counts.received += 1
        fault = self.check(value)
        if fault is not None:
            counts.nonfinite += fault == "nonfinite"
            counts.out_of_range += fault == "out_of_range"
            return []
        out: list[tuple[int, Any]] = []
        held = self._held
        if held is not None:
            self._held = None
            counts.held -= 1
            if self.last is None or abs(stamp - held[0]) <= abs(stamp - self.last):  # the stream goes on from it
                self._take(held, out)
            else:
                counts.glitch += 1
        if self.last is not None and abs(stamp - self.last) > self.far():
            self._held = (stamp, value)
            counts.held += 1
            return out
        self._take((stamp, value), out)
        return out

    def finish(self) -> list[tuple[int, Any]]:
        """End of the stream: a held sample is kept (nothing contradicts it)."""
        out: list[tuple[int, Any]] = []
        if self._held is not None:
            self.counts.held -= 1
            self._take(self._held, out)
            self._held = None
        return out

    def _take(self, sample: tuple[int, Any], out: list[tuple[int, Any]]) -> None:
        stamp = sample[0]
        if self.last is not None and stamp > self.last:
            self._intervals.append(stamp - self.last)
            if len(self._intervals) > INTERVALS:
                del self._intervals[0]
        if self.last is None or stamp > self.last:
            self.last = stamp
        self.counts.accepted += 1
        out.append(sample)

    def due(self, stamp: int) -> bool:
        """Whether a sample stamped at or before ``stamp`` (ns) is due and has not come: the stream's last
        sample plus its rhythm is not after the set (or a held sample waits for its successor)."""
        if self._held is not None and self._held[0] <= stamp:
            return True
        interval = self.interval
        return self.last is not None and interval is not None and self.last + interval <= stamp


def accepted_samples(check: Check, stamps: Any, values: Any) -> tuple[list[int], list[Any], SideCounts]:
    """A recorded stream through :class:`SideAcceptance`, in its recorded order: the stamps and values let
    through (in that order) and the counts."""
    rule = SideAcceptance(check)
    kept: list[tuple[int, Any]] = []
    for t, v in zip(stamps, values):
        kept += rule.offer(int(t), v)
    kept += rule.finish()
    return [t for t, _ in kept], [v for _, v in kept], rule.counts


def bulk_out_of_range(check: Check, values: Any) -> bool:
    """Whether most of a stream's finite values are out of range (a units error, not a bad sample)."""
    faults = [check(v) for v in values]
    finite = [f for f in faults if f != "nonfinite"]
    return bool(finite) and sum(f == "out_of_range" for f in finite) > len(finite) // 2


def imu_check(value: Any) -> str | None:
    """The check of an IMU sample ``(orientation (4,), angular velocity (3,))``: a value while either part
    is usable (:func:`imu_parts`)."""
    q_ok, w_ok, finite = imu_parts(value)
    if q_ok or w_ok:
        return None
    return "out_of_range" if finite else "nonfinite"


def imu_parts(value: Any) -> tuple[bool, bool, bool]:
    """(orientation usable, angular velocity usable, any part finite) of an IMU sample: an orientation
    is a quaternion of norm 1 within :data:`QUATERNION_NORM`, an angular velocity is within
    :data:`MAX_RATE` rad/s."""
    q, w = value
    q_finite = all(math.isfinite(float(x)) for x in q)
    w_finite = all(math.isfinite(float(x)) for x in w)
    q_ok = q_finite and abs(math.sqrt(sum(float(x) * float(x) for x in q)) - 1.0) <= QUATERNION_NORM
    w_ok = w_finite and math.sqrt(sum(float(x) * float(x) for x in w)) <= MAX_RATE
    return q_ok, w_ok, q_finite or w_finite


@dataclass(frozen=True)
class SideKind:
    """One kind of side stream: what it carries and the check of its values."""

    noun: str
    """What one sample is, in notes (``current``, ``temperature``, ``IMU sample``)."""
    unit: str
    check: Check


CURRENT = SideKind("current", "A", scalar_check(-MAX_CURRENT, MAX_CURRENT))
TEMPERATURE = SideKind("temperature", "deg C", scalar_check(*TEMPERATURE_RANGE))
IMU = SideKind("IMU sample", "", imu_check)


def refuse_units(kind: SideKind, values: Any, where: str) -> None:
    """:class:`~magcal_ros.errors.InputError` naming ``where`` when most of a stream's values are out of
    range for ``kind``: a units error (kelvin for deg C, mA for A), which dropping samples would hide."""
    from magcal_ros.errors import InputError

    values = list(values)
    if bulk_out_of_range(kind.check, values):
        bad = next(v for v in values if kind.check(v) == "out_of_range")
        raise InputError(f"{where}: {kind.noun} {_show(bad)} {kind.unit} and most others are out of range: "
                         f"{kind.noun}s must be in {kind.unit or 'the ROS convention'}")


def _show(value: Any) -> str:
    try:
        return f"{float(value):g}"
    except TypeError:
        return str(value)


def usable_imu(samples: Any) -> tuple[Any, Any]:
    """IMU samples ``[(orientation (4,), angular velocity (3,)), ...]`` as arrays (n, 4) and (n, 3), each
    unusable part (:func:`imu_parts`) a row of NaN, each orientation normalised."""
    import numpy as np

    q = np.array([s[0] for s in samples], dtype=float).reshape(-1, 4)
    w = np.array([s[1] for s in samples], dtype=float).reshape(-1, 3)
    for i, sample in enumerate(samples):
        q_ok, w_ok, _ = imu_parts(sample)
        if q_ok:
            norm = np.linalg.norm(q[i])
            if abs(norm - 1.0) > 1e-12:  # a unit quaternion stays bit for bit
                q[i] /= norm
        else:
            q[i] = np.nan
        if not w_ok:
            w[i] = np.nan
    return q, w


class WaitingSets:
    """Sets a live node holds while a side-stream sample is due for them (:meth:`SideAcceptance.due`), in
    the order they formed: each is released once nothing is due at its stamp, or once it waited
    :data:`MAX_WAIT` (``now``: the node's clock, ns) for a sample that does not come. So a set uses the
    samples stamped at or before it that arrive a little after it, as offline, where every sample is at
    hand; only a sample delayed beyond the wait can make the two differ.

    The wait counts the time the node was awake to receive: a step of its clock between two calls longer
    than :data:`AWAKE_STEP` (the process was not scheduled, on a loaded computer) counts as that step. A node
    that wakes from such a stall handles its timers before the messages queued meanwhile: counted whole,
    the stall released sets just before their due sample was taken in (a payload's current of the set
    before applied)."""

    def __init__(self, max_wait_ns: int = MAX_WAIT, awake_step_ns: int | None = None) -> None:
        self.max_wait_ns = int(max_wait_ns)
        self.awake_step_ns = int(AWAKE_STEP if awake_step_ns is None else awake_step_ns)
        self._sets: deque[tuple[int, int, Any]] = deque()
        self._awake = 0
        """ns the node was awake (clock steps capped at :attr:`awake_step_ns`)."""
        self._last: int | None = None

    def __len__(self) -> int:
        return len(self._sets)

    def _tick(self, now: int) -> int:
        """The awake time at node clock ``now`` (ns)."""
        if self._last is not None and now > self._last:
            self._awake += min(now - self._last, self.awake_step_ns)
        self._last = now if self._last is None else max(self._last, now)
        return self._awake

    def add(self, stamp: int, arrival: int, item: Any) -> None:
        """Hold ``item``, a set stamped ``stamp`` (ns) that formed at ``arrival`` (node clock, ns)."""
        self._sets.append((stamp, self._tick(arrival), item))

    def release(self, now: int, due: Callable[[int], bool], force: bool = False) -> list[Any]:
        """The held sets that may go now, oldest first (every one with ``force``)."""
        out = []
        sets = self._sets
        awake = self._tick(now)
        while sets:
            stamp, formed, item = sets[0]
            if not (force or awake - formed > self.max_wait_ns or not due(stamp)):
                break
            out.append(item)
            sets.popleft()
        return out

    def clear(self) -> int:
        """Drop every held set; how many there were."""
        n = len(self._sets)
        self._sets.clear()
        return n

"""What both set synchronisers share: the counters, the set types, and per-sensor acceptance.

Acceptance sees each sensor's messages in the order that sensor produced them (a topic's
order in a bag, or on the wire) and decides, message by message, what enters the set
rule (:mod:`magcal_ros.core.sync`):

- stamp 0 (never stamped): dropped (``zero_stamp``; a CSV's relative clock may start at 0);
- the previous stamp again: dropped (``duplicate``); up to ``restart_ns`` older: dropped
  (``out_of_order``);
- a *suspect* stamp is held until the sensor's next messages decide it. One more than
  ``restart_ns`` older than the previous stamp is a *restart* when the next stamp follows
  it (within ``restart_ns``), a single bad stamp otherwise (dropped, ``glitch``); one more than
  ``restart_ns`` ahead likewise (a restart forward, or a glitch). One
  further ahead than :data:`SUSPECT_PERIODS` sample periods (the median of the sensor's
  last :data:`PERIOD_WINDOW` intervals, once it has that many) is kept once a stamp at
  or after it arrives (the sensor resumed after a silence or lost samples), and is a
  glitch when the sequence goes on below it. At the end of a stream a suspect ahead is
  kept, one behind is a glitch;
- a negative stamp (before 1970: a clock or driver fault): dropped (``negative_stamp``);
- a NaN or infinite reading (``nonfinite``) or one beyond any magnetometer's range
  (``out_of_range``, :mod:`magcal_ros.core.acceptance`): dropped, its stamp still counts as
  the sensor's previous one.

A restart starts a new segment of that sensor only. Its stamps are placed on the common
timeline of the sets: when another sensor's stamps made the same jump (within half of
``restart_ns``), by exactly that sensor's shift (the stamping clock restarted for both);
otherwise after the sensor's last sample by the time its messages took to arrive (bag
time offline, the node's clock live), rounded to whole sample periods. The sets on
either side of a restart are kept; only the first sensor making a jump counts as a
``restarts``. A sensor placed by another's shift *follows* it (:attr:`SensorStream.follows`):
its sample clock takes that sensor's correction after the restart, not one of its own
(:meth:`~magcal_ros.core.sample_clock.SampleClock.restart`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core import acceptance
from magcal_ros.core.sample_clock import SampleClock
from magcal_ros.core.units import NS_PER_S

DEFAULT_SYNC_TOLERANCE: float = 1e-3
"""Default largest spread (s) of the header stamps of one set (exact matching)."""
DEFAULT_LAG: float = 5.0
"""Default time (s) a live synchronizer waits for a silent sensor before giving a set up: both the
stamps and the arrivals must run this far ahead of it. Longer than a reliable DDS writer's default
heartbeat period (3 s in Fast DDS): a reader that lost a sample holds that topic's later samples
until the sample is sent again, so a sensor can be silent that long while its messages wait."""
RESTART_JUMP: float = 1.0
"""A stamp this far (s) behind its sensor's previous one is a restart (or a glitch)."""
PERIOD_WINDOW: int = 8
"""Stamp intervals in each sensor's short period estimate (median): the exact window cap and
the suspect rule."""
MAX_TIME_OFFSET: float = 0.5
"""Largest accepted time offset (lag) of a sensor (s)."""
SUSPECT_PERIODS: tuple[int, int] = (5, 2)
"""A stamp more than 5/2 sample periods after the previous one is a suspect (held one message)."""

NO_CAP = 2**62
NEVER = -(2**62)
Vector = tuple[float, float, float]

OK, DUPLICATE, OUT_OF_ORDER, BEHIND, AHEAD = range(5)
"""Verdicts of :meth:`SensorStream.classify`."""


@dataclass
class SyncStats:
    """What the synchronizer did, message by message (one vocabulary for bags and nodes).

    Every message offered ends in exactly one of: a set (``used``), a drop counter, or
    still pending: ``used + dropped() + pending == offered``.
    """

    sets: int = 0
    """Complete sets released."""
    unmatched: int = 0
    """Messages in no set: a partner sample was missing, too far in time, or never came."""
    nonfinite: int = 0
    """Messages with a NaN or infinite reading."""
    duplicate: int = 0
    """Messages whose stamp repeats the sensor's previous one."""
    out_of_order: int = 0
    """Messages whose stamp is older than the sensor's previous one."""
    zero_stamp: int = 0
    """Messages with header stamp 0 (the driver never stamped them)."""
    malformed: int = 0
    """Messages that could not be decoded (live nodes only; a bag refuses them)."""
    restarts: int = 0
    """Stamps jumped back by more than a second and went on from there: a new segment."""
    glitch: int = 0
    """Messages whose stamp was far off their sensor's sequence (a single bad stamp)."""
    gap: int = 0
    """Reference samples dropped because another sensor had no samples within ``max_gap`` around them
    (interpolation)."""
    used: int = 0
    """Messages that went into sets (interpolation: also samples resampled between two sets)."""
    negative_stamp: int = 0
    """Messages with a negative header stamp (before 1970: a clock or driver fault)."""
    out_of_range: int = 0
    """Messages with a finite reading beyond :data:`~magcal_ros.core.units.MAX_READING` (T)."""

    def dropped(self) -> int:
        """Messages dropped for any reason."""
        return sum(getattr(self, name) for name in DROP_FIELDS)

    def disorder(self) -> str | None:
        """Why a recording cannot be read in its order, or None: more messages dropped for stamps behind
        their sensor's previous one (``out_of_order``, and ``glitch`` once a second or more behind) than
        sets formed (rows sorted backwards, storage times reversed)."""
        behind = self.out_of_order + self.glitch
        if behind <= max(self.sets, DISORDER_MIN):
            return None
        return (f"{behind} messages dropped as out of order or far off their sensor's sequence against {self.sets} "
                "sets formed: the recording is not in time order (rows sorted backwards? storage times reversed?); "
                "sort it by stamp")

    def count(self, fault: str, n: int = 1) -> None:
        """Add ``n`` messages to the counter ``fault`` (a name of :mod:`magcal_ros.core.acceptance`)."""
        setattr(self, fault, getattr(self, fault) + n)

    def as_dict(self) -> dict[str, int]:
        """Counters by name."""
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}

    def describe(self) -> str:
        """One line for users: sets, then each non-zero drop count in words."""
        parts = [f"{self.sets} sets"]
        for name, value in self.as_dict().items():
            if name in _PHRASES and value:
                parts.append(f"{value} {_PHRASES[name]}")
        return ", ".join(parts)


DISORDER_MIN: int = 10
"""Out-of-order messages a recording may have whatever its length before :meth:`SyncStats.disorder` refuses it."""
DROP_FIELDS: tuple[str, ...] = ("unmatched", "nonfinite", "duplicate", "out_of_order", "zero_stamp", "malformed",
                                "glitch", "gap", "negative_stamp", "out_of_range")
"""The counters of dropped messages."""
_PHRASES = {
    "unmatched": "messages without a complete set dropped",
    "nonfinite": "messages with NaN/inf readings dropped",
    "duplicate": "repeated stamps dropped",
    "out_of_order": "out-of-order stamps dropped",
    "zero_stamp": "zero (unset) stamps dropped",
    "malformed": "undecodable messages dropped",
    "restarts": "source restarts (stamps jumped back)",
    "glitch": "messages with a stamp far off their sensor's sequence dropped",
    "gap": "sets dropped for a gap longer than max_gap in another sensor's samples",
    "negative_stamp": "negative (before 1970) stamps dropped",
    "out_of_range": "readings beyond any magnetometer's range dropped",
}


@dataclass(frozen=True)
class SyncedSet:
    """One set from the streaming path: per-sensor stamps (ns) and raw vectors (T), sensor order.

    Exact matching: each sensor's own header stamp. Interpolation: every sensor at the set's
    instant (the reference sensor's sample instant)."""

    stamps: tuple[int, ...]
    values: tuple[Vector, ...]

    @property
    def stamp(self) -> int:
        """The set's stamp (ns): its first sensor's."""
        return self.stamps[0]


@dataclass(frozen=True)
class SetBatch:
    """Sets from the batch path, in stamp order: per-sensor stamps (N, S) ns, vectors (N, S, 3) T."""

    stamps: NDArray[np.int64]
    vectors: NDArray[np.float64]

    @property
    def set_stamps(self) -> NDArray[np.int64]:
        """The stamp of each set (its first sensor's), ns."""
        return self.stamps[:, 0]

    def __len__(self) -> int:
        return len(self.stamps)

    def take(self, keep: Any) -> "SetBatch":
        """The sets selected by ``keep`` (boolean mask or indices)."""
        return SetBatch(self.stamps[keep], self.vectors[keep])


def empty_batch(sensors: int) -> SetBatch:
    """A batch of no sets for ``sensors`` sensors."""
    return SetBatch(np.empty((0, sensors), np.int64), np.empty((0, sensors, 3)))


def tolerance_ns(seconds: Any) -> int:
    """A tolerance in seconds as integer nanoseconds (``ValueError`` unless 0 <= t < 1 s)."""
    t = float(seconds)
    if not (0.0 <= t < 1.0) or not math.isfinite(t):
        raise ValueError(f"sync tolerance must be between 0 and 1 s, got {seconds!r}")
    return int(round(t * NS_PER_S))


def median_int(values: list[int]) -> int:
    """Median of integers, halves rounded down (the short period estimate)."""
    v = sorted(values)
    m = len(v) // 2
    return v[m] if len(v) % 2 else (v[m - 1] + v[m]) // 2


class SensorStream:
    """Acceptance state of one sensor: its previous stamp, short period, a held suspect, its
    placement on the common timeline (``base``: common = stamp + base) and its sample clock."""

    __slots__ = ("last", "lastc", "base", "last_receipt", "intervals", "period", "held", "clock", "placed_at",
                 "before", "follows")

    def __init__(self, clock: SampleClock | None) -> None:
        self.last = NEVER
        """Previous accepted stamp (ns, the sensor's own clock)."""
        self.lastc = NEVER
        """The same on the common timeline."""
        self.base = 0
        self.last_receipt: int | None = None
        self.intervals: list[int] = []
        self.period: int | None = None
        """Median of the last :data:`PERIOD_WINDOW` intervals (ns), None before the first."""
        self.held: tuple[int, Any, bool, int | None, bool] | None = None
        """A suspect: (stamp, payload, reading fault or None, receipt, behind)."""
        self.clock = clock
        self.placed_at: int | None = None
        """Common time of this sensor's latest restart placement (None: never restarted)."""
        self.before: tuple[int, int] | None = None
        """(last stamp, base) of the segment before the latest restart, while the stamps may still
        return to it (two bad stamps in a row look like a restart until the old sequence goes on)."""
        self.follows: int | None = None
        """The sensor whose stamps the latest restart's share (placed by its shift), None: placed alone."""

    def suspect_period(self) -> int | None:
        """The period the suspect rule uses: the short median once the window is full."""
        return self.period if len(self.intervals) >= PERIOD_WINDOW else None

    def best_period(self) -> float | None:
        """The best period estimate (ns): the sample clock's, else the full-window median."""
        if self.clock is not None and self.clock.period_ns is not None:
            return self.clock.period_ns
        return self.suspect_period()

    def classify(self, stamp: int, restart_ns: int) -> int:
        """OK, DUPLICATE, OUT_OF_ORDER, or a suspect BEHIND / AHEAD (see the module docstring)."""
        last = self.last
        if stamp <= last:
            if last - stamp > restart_ns:
                return BEHIND
            return DUPLICATE if stamp == last else OUT_OF_ORDER
        if last != NEVER:
            period = self.suspect_period()
            if period is not None and SUSPECT_PERIODS[1] * (stamp - last) > SUSPECT_PERIODS[0] * period:
                return AHEAD
            if period is None and stamp - last > restart_ns:  # before a period is known: a jump as far as a restart's
                return AHEAD
        return OK

    def record(self, interval: int) -> int:
        """Record one accepted stamp interval; the exact rule's window cap (half the short period)."""
        iv = self.intervals
        iv.append(interval)
        if len(iv) > PERIOD_WINDOW:
            del iv[0]
        self.period = median_int(iv)
        return self.period // 2


Accepted = list[tuple[int, int, Any, int, bool]]
"""Messages accepted by one call: (stamp, common stamp, payload, window cap, starts a new segment),
in order; the payload is None for a faulty reading (counted, but its stamp still counts)."""


class AcceptanceRule:
    """Per-sensor acceptance and restart placement for ``sensors`` sensors (module docstring).

    ``clocked``: each sensor keeps a :class:`~magcal_ros.core.sample_clock.SampleClock`
    (its period, losses; the interpolating synchroniser's sample instants). :attr:`max_reading`
    (T) is the largest reading magnitude accepted: real sensor data pass
    :data:`~magcal_ros.core.units.MAX_READING` (``out_of_range`` beyond); synthetic streams may
    carry any finite value (the default).
    """

    max_reading: float = math.inf
    lag_ns: int = int(DEFAULT_LAG * NS_PER_S)
    """Live bound: how long a message waits for a silent sensor (ns; see :meth:`waited`)."""

    def __init__(self, sensors: int, stats: SyncStats | None, restart_ns: int, reject_zero: bool,
                 clocked: bool, pause_ns: int | None = None) -> None:
        if sensors < 1:
            raise ValueError("need at least one sensor")
        self.size = sensors
        self.stats = stats if stats is not None else SyncStats()
        self.restart_ns = int(restart_ns)
        self.reject_zero = reject_zero
        self.clocked = clocked
        self.pause_ns = int(pause_ns if pause_ns is not None else restart_ns)
        self.streams = [self._new_stream() for _ in range(sensors)]
        self.newest = NEVER
        """Newest common stamp accepted from any sensor."""
        self.latest_arrival: int | None = None
        """Latest arrival (receipt ns) of an accepted message, None while unknown."""

    def _new_stream(self) -> SensorStream:
        return SensorStream(SampleClock(pause_ns=self.pause_ns) if self.clocked else None)

    def forget(self) -> None:
        """Forget every sensor's history (held suspects are counted as glitches)."""
        self.stats.glitch += sum(s.held is not None for s in self.streams)
        self.streams = [self._new_stream() for _ in range(self.size)]
        self.newest = NEVER
        self.latest_arrival = None

    def set_pause(self, pause_ns: int) -> None:
        """A silence longer than ``pause_ns`` is a pause of the sensor, not a loss (sample clocks)."""
        self.pause_ns = int(pause_ns)
        for s in self.streams:
            if s.clock is not None:
                s.clock.pause_ns = self.pause_ns

    def arrived(self, receipt: int | None) -> None:
        """Note an accepted message's arrival (ns; None: unknown) for :attr:`latest_arrival`."""
        if receipt is not None and (self.latest_arrival is None or receipt > self.latest_arrival):
            self.latest_arrival = receipt

    def waited(self, t: int, silent: Iterable[int]) -> bool:
        """Whether a message at common stamp ``t`` (ns) has waited long enough for the ``silent`` sensors
        (nothing queued): the newest stamp is more than :attr:`lag_ns` past ``t``, and where arrivals are
        known, each silent sensor's last message arrived more than that before the latest one. Stamps
        alone would give messages up that are waiting in the middleware while a node that fell behind
        reads another topic first."""
        lag = self.lag_ns
        if self.newest - t <= lag:
            return False
        now = self.latest_arrival
        if now is None:
            return True
        streams = self.streams
        for k in silent:
            last = streams[k].last_receipt
            if last is not None and now - last <= lag:
                return False
        return True

    @property
    def held(self) -> int:
        """Suspect messages held."""
        return sum(s.held is not None for s in self.streams)

    def fault(self, x: float, y: float, z: float) -> str | None:
        """The fault of a reading (T) under this rule's :attr:`max_reading`, None when usable."""
        return acceptance.reading_fault(x, y, z, self.max_reading)

    def accept(self, index: int, stamp: int, payload: Any, fault: str | None, receipt: int | None) -> Accepted:
        """Offer one message of sensor ``index`` (``fault``: its reading's, see :meth:`fault`); the
        messages it lets through (a held suspect first)."""
        if stamp <= 0 and self.reject_zero:
            self.stats.count(acceptance.stamp_fault(stamp) or "zero_stamp")
            return []
        s = self.streams[index]
        out: Accepted = []
        held = s.held
        if held is not None:
            before, behind = held[0], held[4]
            if behind:  # a restart if the next stamp goes on from it, else a glitch
                s.held = None
                if before < stamp <= before + self.restart_ns:
                    self._take(index, before, held[1], held[2], held[3], True, out)
                else:
                    self.stats.glitch += 1
            elif before - s.last > self.restart_ns:  # far ahead: a restart (forward) if the next stamp goes on from it
                if before < stamp <= before + self.restart_ns:
                    s.held = None
                    self._take(index, before, held[1], held[2], held[3], True, out)
                elif stamp > s.last:  # the sequence went on below it: a single bad stamp
                    s.held = None
                    self.stats.glitch += 1
            elif stamp >= before:  # ahead: kept once a later stamp confirms it
                s.held = None
                self._take(index, before, held[1], held[2], held[3], False, out)
            elif stamp > s.last:  # the sequence went on below it: a single late stamp
                s.held = None
                self.stats.glitch += 1
        verdict = s.classify(stamp, self.restart_ns)
        if verdict == OK:
            self._take(index, stamp, payload, fault, receipt, False, out)
        elif verdict == DUPLICATE:
            self.stats.duplicate += 1
        elif verdict == OUT_OF_ORDER:
            self.stats.out_of_order += 1
        else:
            if s.held is not None:
                self.stats.glitch += 1
            s.held = (stamp, payload, fault, receipt, verdict == BEHIND)
        return out

    def release_held(self, index: int) -> Accepted:
        """End of stream for sensor ``index``: a suspect ahead is kept, one behind is a glitch."""
        s = self.streams[index]
        held, s.held = s.held, None
        out: Accepted = []
        if held is not None:
            if held[4] or held[0] - s.last > self.restart_ns:  # behind, or unconfirmed far ahead
                self.stats.glitch += 1
            else:
                self._take(index, held[0], held[1], held[2], held[3], False, out)
        return out

    def _take(self, index: int, stamp: int, payload: Any, fault: str | None, receipt: int | None, restart: bool,
              out: Accepted) -> None:
        s = self.streams[index]
        if restart:
            s.before = (s.last, s.base)
            self._place(index, stamp, receipt)
            s.intervals, s.period = [], None
            cap = NO_CAP
        elif s.before is not None and 0 < stamp - s.before[0] <= self.restart_ns and stamp > s.last:
            # The old sequence goes on: what looked like a restart was a few bad stamps. Back to
            # the old placement (the messages in between stay where they were put).
            s.base = s.before[1]
            s.before = None
            s.intervals, s.period = [], None
            cap = NO_CAP
        else:
            cap = NO_CAP if s.last == NEVER else s.record(stamp - s.last)
        s.last = stamp
        s.lastc = c = stamp + s.base
        s.last_receipt = receipt
        if c > self.newest:
            self.newest = c
        self.arrived(receipt)
        if fault is not None:
            self.stats.count(fault)
            payload = None
        out.append((stamp, c, payload, cap, restart))

    def _place(self, index: int, stamp: int, receipt: int | None) -> None:
        """Place sensor ``index``'s new segment starting at ``stamp`` on the common timeline."""
        s = self.streams[index]
        s.follows = None
        period = s.best_period()
        if receipt is not None and s.last_receipt is not None:
            estimate = s.lastc + max(receipt - s.last_receipt, 0)
        else:
            estimate = s.lastc + int(period or 0)
        for j, other in enumerate(self.streams):  # the same jump as another sensor's: the same clock
            if j != index and abs(stamp + other.base - estimate) <= self.restart_ns // 2:
                s.base = other.base
                s.follows = self._leader(index, j)
                break
        else:
            for j, other in enumerate(self.streams):  # back in line with another sensor's latest stamps
                if j != index and other.lastc != NEVER and abs(stamp + other.base - other.lastc) <= self.restart_ns // 2:
                    s.base = other.base
                    s.follows = self._leader(index, j)
                    s.placed_at = stamp + s.base
                    return
            if period:
                steps = max(1, int(round((estimate - s.lastc) / period)))
                estimate = s.lastc + int(round(steps * period))
            s.base = max(estimate, s.lastc + 1) - stamp
            self.stats.restarts += 1
        s.placed_at = stamp + s.base

    def _leader(self, index: int, j: int) -> int:
        """The sensor whose clock sensor ``index`` follows when placed by sensor ``j``'s shift."""
        first = self.streams[j].follows
        return j if first is None or first == index else first

    def restart_clock(self, index: int) -> Any:
        """Restart sensor ``index``'s sample clock for its new segment (following the clock of the sensor
        whose shift placed it); the samples that releases."""
        s = self.streams[index]
        leader = self.streams[s.follows].clock if s.follows is not None else None
        return s.clock.restart(leader) if s.clock is not None else []

    # -- health -------------------------------------------------------------------
    def period_ns(self, index: int) -> int | None:
        """Sample period estimate (ns) of sensor ``index``: its sample clock's (a fit over many
        samples), else the median of its last intervals once there are :data:`PERIOD_WINDOW`; None before."""
        p = self.streams[index].best_period()
        return None if p is None else int(round(p))

    def lost(self, index: int) -> int:
        """Samples of sensor ``index`` lost before they reached the synchroniser (sample clock)."""
        c = self.streams[index].clock
        return c.lost if c is not None else 0

    def gaps(self, index: int) -> int:
        """Runs of lost samples of sensor ``index``."""
        c = self.streams[index].clock
        return c.gaps if c is not None else 0

    @property
    def min_period_ns(self) -> int | None:
        """Shortest sample period estimate of the sensors (ns), None before any."""
        periods = [p for p in (self.period_ns(k) for k in range(self.size)) if p]
        return min(periods) if periods else None

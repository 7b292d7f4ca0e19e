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
from collections import deque
from collections.abc import Iterable, Sequence
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

OK, DUPLICATE, BEHIND, AHEAD, CROWDED, BURST = range(6)
"""Verdicts of :meth:`SensorStream.classify` (BURST: a held stamp inside a backlog delivered at once)."""
LEAD_WINDOW: int = 256
"""Messages over which a sensor's stamp lead over its arrivals is taken at its largest (the least delayed
arrival): long enough for a backlog to catch up, short enough to follow a receipt clock that drifts from
the stamps' (counted in messages, so a pause does not age it)."""
BACKLOG_INTERVAL: int = 200_000
"""Stamps closer than this (ns, 5 kHz) are a backlog delivered at once, not a sensor's rate."""
BACKLOG_LOSS: float = 0.03
"""The share of a stall's samples its backlog may have lost: a backlog stamped on delivery this much short of the gap
before it still shows the sensor sampled through it (:meth:`SensorStream.backlog_fills`)."""
MAX_STALL: int = 10 * NS_PER_S
"""Longest stall (ns) a driver delivers a backlog after: stamps crowding after a longer silence are a
faster rate, not a backlog."""
LEAD_DRIFT: int = 5_000
"""A receipt clock may drift from the stamps' by one part in this (200 ppm) in the least delay of a sensor's
arrivals (:attr:`SensorStream.floor`)."""
RECENT: int = 32
"""... or over the last this many, where the window's older part was a backlog drained (:meth:`SensorStream.timed`)."""
TIMED_MIN: int = 16
"""Arrivals needed before they are trusted to keep the stamps' time."""
PACED_PAUSE: int = 4
"""A gap of the stamps longer than this many ``restart_ns`` whose arrival came at least half of it later at the
arrivals' own pace (a replay at another speed, a busy receiver) is a pause of the sensor, not a step. Shorter
gaps are left to the stamps: sensors whose stamps all jump by a second or so (a replay started again) would
otherwise be judged one by one, some paused and some stepped, and never pair again."""
WAIT_MESSAGES: int = 4
"""How many of its own messages a suspect ahead from a busy receiver's queue waits at least for another sensor's
message delivered after it (:meth:`AcceptanceRule._queue_unread`); more where another sensor is slower
(:meth:`AcceptanceRule._wait_messages`)."""
MAX_WAIT_MESSAGES: int = 64
"""... and at most (a sensor at 200 Hz beside one at 5 Hz)."""
PLACE_MESSAGES: int = 16
"""Messages of a new segment whose arrivals place it (the least delayed of them decides; their stamps'
jitter averages out)."""
MAX_PLACE_MESSAGES: int = 256
"""... or, where the arrivals never catch up with the stamps (a recording replayed faster than it was made,
arrivals too jittery), this many: then the stamps alone place the segment."""
HOLD_NS: int = int(DEFAULT_LAG * NS_PER_S)
"""How long (ns of its receipts) a new segment after a jump a queue hid waits for its arrivals to come on time
again: as long as a live node lets a message wait by default; the same offline (which waits for everything), so
that both paths place it alike whatever the node's ``lag``."""
TAIL: int = 16
JUMPS_KEPT: int = 32
"""Jumps of its stamps a sensor remembers for the sensors stamped by the same clock (:attr:`SensorStream.jumps`)."""
LOST_PERIODS: int = 4
"""A gap of its stamps up to this many sample periods that a sensor took as no step is its own lost samples, not a
pause of the clock that stamps it: not remembered among its jumps for the sensors of the same clock (another
sensor's jump from the same stamp, a clock's step while it was silent, is not this one)."""
SAME_STAMP: int = 10_000
"""Two sensors whose stamps jumped to the same stamp, to this (ns), jumped by one clock."""
SAME_JUMP: int = NS_PER_S // 1000
"""Two sensors' jumps of their stamps are one clock's when they agree to this (ns) or a quarter period, the
less, in size, and start within a period and a quarter of each other."""
"""The last stamps of a segment that anchor its grid where a step leaves it (their jitter averaged)."""
SHARED_STEP: int = NS_PER_S // 2
"""Sensors whose stamps step within this time (ns) of each other by the same jump share one stamping
clock ..."""
SHARED_MARGIN: int = 50_000_000
"""... when their placements agree within this (ns) and the shared jump keeps the sample grid: each is
placed by its own arrivals, which a loaded computer delays by tens of milliseconds."""


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
    burst: int = 0
    """Messages stamped far closer together than their sensor samples: a backlog stamped as it was
    delivered, whose stamps say nothing of when its samples were taken."""
    side_value: int = 0
    """Messages of CSV rows whose current or temperature is out of its range (no value)."""

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
                                "glitch", "gap", "negative_stamp", "out_of_range", "burst", "side_value")
"""The counters of dropped messages."""
_PHRASES = {
    "unmatched": "messages without a complete set dropped",
    "nonfinite": "messages with NaN/inf readings dropped",
    "duplicate": "repeated stamps dropped",
    "out_of_order": "out-of-order stamps dropped",
    "zero_stamp": "zero (unset) stamps dropped",
    "malformed": "undecodable messages dropped",
    "restarts": "source restarts or stamp steps (placed on the common time line)",
    "glitch": "messages with a stamp far off their sensor's sequence dropped",
    "gap": "sets dropped for a gap longer than max_gap in another sensor's samples",
    "negative_stamp": "negative (before 1970) stamps dropped",
    "out_of_range": "readings beyond any magnetometer's range dropped",
    "burst": "messages of a backlog stamped on delivery dropped",
    "side_value": "messages of rows whose current or temperature is out of range dropped",
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


Message = tuple[int, Any, "str | None", "int | None"]
"""One message of a sensor as acceptance holds it: (stamp ns, payload, reading fault or None, receipt ns or None)."""


class SensorStream:
    """Acceptance state of one sensor: its previous stamp, short period, a held suspect, its
    placement on the common timeline (``base``: common = stamp + base), the lead of its stamps
    over their arrivals, and its sample clock."""

    __slots__ = ("last", "lastc", "base", "last_receipt", "intervals", "period", "held", "clock", "before",
                 "follows", "arrivals", "placing", "since", "placed_at", "grid_first", "grid_periods", "grid_past",
                 "tail", "burst_from", "burst_count", "seen_step", "jumps", "heard", "floor", "hidden", "fresh", "waiting", "waited",
                 "queued_at", "trailing")

    def __init__(self, clock: SampleClock | None) -> None:
        self.last = NEVER
        """Previous accepted stamp (ns, the sensor's own clock)."""
        self.lastc = NEVER
        """The same on the common timeline."""
        self.base = 0
        self.last_receipt: int | None = None
        self.heard: int | None = None
        """Receipt (ns) of the latest message offered, taken or held (None: unknown): the sensor is not silent."""
        self.intervals: list[int] = []
        self.period: int | None = None
        """Median of the last :data:`PERIOD_WINDOW` intervals (ns), None before the first."""
        self.fresh = PERIOD_WINDOW
        """Intervals recorded since the last pause (at most :data:`PERIOD_WINDOW`): the window cap comes from
        them alone until the window is full of them (the sensor may have come back at another rate)."""
        self.held: tuple[int, Any, str | None, int | None, int] | None = None
        """A suspect: (stamp, payload, reading fault or None, receipt, kind: BEHIND, AHEAD, CROWDED or BURST)."""
        self.waiting: list[Message] | None = None
        """The messages after a suspect ahead that a busy receiver's queue delivered, held until another sensor's
        message delivered after the suspect tells when it came to the queue (:meth:`AcceptanceRule._queue_unread`)."""
        self.waited: int | None = None
        """The receipt (ns) of the latest suspect that waited so: it is decided when the wait ends."""
        self.clock = clock
        self.before: tuple[int, int, int] | None = None
        """(last stamp, base) of the segment before the latest step, for its first :data:`PERIOD_WINDOW`
        messages (without arrivals, two bad stamps in a row look like a step until the old sequence
        goes on); then forgotten: a segment keeps its placement."""
        self.follows: int | None = None
        """The sensor whose stamps the latest restart's share (placed by its shift), None: placed alone."""
        self.arrivals: deque[tuple[int, int]] = deque(maxlen=LEAD_WINDOW)
        """(common stamp, receipt) ns of the last :data:`LEAD_WINDOW` messages taken with an arrival: the
        largest ``common - receipt`` is how far the stamps run ahead of the least delayed arrivals."""
        self.placing: list[Message] | None = None
        """The first messages of a new segment, held until their arrivals place it."""
        self.since = 0
        """Messages taken since the latest step (for :attr:`before`)."""
        self.placed_at: int | None = None
        """Common stamp (ns) where the latest step placed this sensor's new segment (None: never)."""
        self.grid_first = NEVER
        """First stamp (ns) of the current segment ..."""
        self.grid_periods = 0
        """... and the sample periods from it to the last stamp (each interval in whole short periods)."""
        self.grid_past = (0, 0)
        """(span ns, periods) of the sensor's earlier grids, each of :data:`PERIOD_WINDOW` periods or more, summed:
        a step of the stamps or a pause starts a new grid, but the sensor samples at the rate it had."""
        self.tail: list[int] = []
        """The last :data:`TAIL` common stamps (ns) of the current segment."""
        self.burst_from = NEVER
        """First stamp (ns) of the current run of crowded stamps after a gap ..."""
        self.burst_count = 0
        """... and its messages: a backlog holds no more samples than the gap before it; a longer run is a
        faster rate."""
        self.jumps: deque[tuple[int, int, int | None, int]] = deque(maxlen=JUMPS_KEPT)
        """The latest jumps of the stamps this sensor took, a pause or a step: (stamp before, stamp after, its
        receipt or None, base after; ns). Sensors stamped by one clock make the same jump: the first to decide
        it decides for all (:meth:`AcceptanceRule._partner`)."""
        self.floor: tuple[int, int] | None = None
        """The least delay the sensor's arrivals ever had: ``max(common - receipt + common // LEAD_DRIFT)`` and
        ``max(common - receipt - common // LEAD_DRIFT)`` (ns) over every message taken, so that the lead of its
        least delayed arrivals at common stamp ``c`` is at least ``floor[0] - c // LEAD_DRIFT`` and, the least
        delayed it saw being on time, at most ``floor[1] + c // LEAD_DRIFT`` (a receipt clock may drift from the
        stamps': :meth:`resumed_on_time`)."""
        self.queued_at: int | None = None
        """Where (ns, common) the queue's order put the first of the new segment being placed when the segment was
        first held long enough to decide (:meth:`AcceptanceRule._waits_to_catch_up`); None: it did not."""
        self.hidden = False
        """Whether the new segment being placed follows a jump forward a busy receiver's queue hid (a pause or a
        step): placed by its arrivals once they catch up, else taken as a pause."""
        self.trailing = False
        """Whether the new segment being placed follows a gap its arrivals saw longer than its stamps did (a step
        back in a silence, or a topic served late at its own pace: alike until it drains)."""
        self.seen_step = False
        """Whether the latest step forward was one the arrivals showed (they did not see the time pass): not
        a few bad stamps that the old sequence's placement could take back."""

    @property
    def busy(self) -> bool:
        """Whether messages are held (a suspect, or a new segment being placed)."""
        return self.held is not None or self.placing is not None

    def holds(self) -> int:
        """How many messages are held: a suspect, those waiting after it, a new segment's first."""
        return (self.held is not None) + len(self.waiting or ()) + len(self.placing or ())

    def quiet(self, now_ns: int) -> bool:
        """Whether its latest message arrived more than :data:`HOLD_NS` before ``now_ns`` (the receiver's clock):
        what it holds waits for messages that do not come."""
        return self.heard is not None and now_ns - self.heard > HOLD_NS

    def suspect_period(self) -> int | None:
        """The period the suspect rule uses: the short median once the window is full."""
        return self.period if len(self.intervals) >= PERIOD_WINDOW else None

    def best_period(self) -> float | None:
        """The best period estimate (ns): the sample clock's, else the full-window median."""
        if self.clock is not None and self.clock.period_ns is not None:
            return self.clock.period_ns
        return self.suspect_period()

    def grid_period(self) -> float | None:
        """The sample period (ns) over the current segment: its span over the periods it holds (lost samples
        counted), a precision the short median lacks when a step is placed many periods on; the short
        median while the segment holds fewer than :data:`PERIOD_WINDOW` periods. The same on every path
        (the sample clock is fed only where a path needs it)."""
        short = self.suspect_period()
        span, periods = self.grid_past
        own = self.grid_periods >= PERIOD_WINDOW
        if self.grid_periods:
            span, periods = span + self.last - self.grid_first, periods + self.grid_periods
        if periods >= PERIOD_WINDOW and (short is None or 8 * abs(span / periods - short) <= short):
            return span / periods  # with the grids before (the same rate): each adds its span's precision
        return (self.last - self.grid_first) / self.grid_periods if own else short

    def grid_spread(self) -> float:
        """The standard deviation (ns) of :meth:`grid_period`: one interval's (a quarter of :meth:`jitter`) over the
        periods its spans hold (a span's error is its two ends' jitter, an interval's); the short median's while the
        segment holds fewer than :data:`PERIOD_WINDOW` periods and no grid came before it."""
        past = self.grid_past[1]
        periods = past + self.grid_periods if past or self.grid_periods >= PERIOD_WINDOW else len(self.intervals)
        return self.jitter() / 4.0 / max(periods, 1)

    def new_grid(self, last: int, first: int) -> None:
        """A step or a pause: the grid ends at stamp ``last`` (ns; its span and periods kept where it held a
        window of periods) and another starts at stamp ``first``."""
        if self.grid_periods >= PERIOD_WINDOW:
            span, periods = self.grid_past
            self.grid_past = (span + last - self.grid_first, periods + self.grid_periods)
        self.grid_first, self.grid_periods = first, 0

    def grow_grid(self, steps: NDArray[np.float64], intervals: NDArray[np.int64], known: NDArray[np.bool_]) -> None:
        """Add ``intervals`` (ns) to the grid at once: ``steps`` periods each where the period is ``known``; where
        it is not, the grid starts after them (what :meth:`record` does one by one)."""
        self.grid_periods += int(steps.sum())
        self.grid_first += int(intervals[~known].sum())

    def anchor(self, period: float) -> float:
        """The common time (ns) of the last sample on the segment's grid of ``period``: the last stamp with
        the jitter of the last few averaged out."""
        tail = self.tail
        last = tail[-1]
        return last + sum((c - last) - round((c - last) / period) * period for c in tail) / len(tail)

    def off_grid(self, stamp: int) -> bool:
        """Whether ``stamp`` (ns, this segment) lies off the segment's sample grid by more than a quarter
        period and than its stamps' jitter allows (six median deviations of its intervals, about four
        standard deviations): lost samples keep a sensor's grid, a step of its stamps moves it. False
        while the grid is unknown, not kept by the recent intervals or too jittery to tell."""
        period, short = self.grid_period(), self.period
        if period is None or not self.tail or short is None or 8 * abs(period - short) > short:
            return False  # no grid, or one the recent intervals do not keep
        limit = max(short / 4, self.jitter())
        if 2 * limit >= short:
            return False
        k = (stamp + self.base - self.anchor(period)) / period
        return abs(k - round(k)) * period > limit

    def jitter(self) -> float:
        """How far (ns) a stamp may lie off the sensor's sample grid by its jitter alone: six median deviations of
        its recent intervals from their median (about four standard deviations); 0 before an interval."""
        short = self.period
        return 0.0 if short is None else 6.0 * median_int([abs(i - short) for i in self.intervals])

    def unseen(self, stamp: int, receipt: int | None, period: int) -> bool | None:
        """Whether the arrivals did not see the time that ``stamp`` (ns, in this segment, ``receipt`` ns)
        says passed since the previous one: the stamps stepped forward. Both its lead over its arrival
        beyond the largest recent one (an arrival is never early; a late one makes it smaller) and its
        interval beyond the arrivals' exceed half the ``period`` (ns); the lead alone where the arrivals come
        bunched (a backlog delivered at once says nothing of time between its messages, but none of them came
        before it was stamped). None while unknown."""
        last = self.last_receipt
        if receipt is None or last is None or not self.timed():
            return None
        if self.bunched(receipt, period):
            return self.ahead_of(stamp, receipt, period)
        return 2 * (stamp - self.last - (receipt - last)) > period and self.ahead_of(stamp, receipt, period)

    def trails(self, stamp: int, receipt: int | None, period: int) -> bool:
        """Whether the arrivals saw more time pass since the previous message than ``stamp`` (ns, this segment;
        ``receipt`` ns) says, by over half the ``period`` (ns), and the stamp trails its arrival by as much beyond
        the stamps' lead (:meth:`lead`): the stamps stepped back during a gap (a sensor silent while its clock
        went back resumes with stamps that cover less time than passed). False while the arrivals keep no time."""
        last = self.last_receipt
        if receipt is None or last is None or not self.timed():
            return False
        return 2 * ((receipt - last) - (stamp - self.last)) > period and \
            2 * (self.lead() - (stamp + self.base - receipt)) > period

    def ahead_of(self, stamp: int, arrival: int, period: int) -> bool:
        """Whether ``stamp`` (ns, this segment) runs more than half a ``period`` (ns) further ahead of its ``arrival``
        (ns) than the sensor's stamps do (:meth:`lead`): an arrival is never early, so the stamps stepped forward."""
        return 2 * (stamp + self.base - arrival - self.lead()) > period

    def bunched(self, receipt: int, period: int) -> bool:
        """Whether a message received at ``receipt`` (ns) came bunched with this sensor's previous (:func:`bunched`)."""
        return self.last_receipt is not None and bunched(receipt, self.last_receipt, period)

    def lead(self) -> int:
        """How far (ns) the stamps run ahead of the least delayed of the recent arrivals, or of the least delayed
        the sensor ever had (:attr:`floor`, drift allowed) where all the recent ones came late (a busy receiver
        draining a queue longer than :data:`LEAD_WINDOW` messages)."""
        recent = max(c - r for c, r in self.arrivals)
        bounds = self.floor_bounds(self.lastc)
        return recent if bounds is None else max(recent, bounds[0])

    def timed(self) -> bool:
        """Whether the arrivals keep the stamps' time: over the last :data:`LEAD_WINDOW` (at least
        :data:`TIMED_MIN`), the arrivals advance as the stamps do from one message to the next, to a factor
        of two in the median, and the stamps' lead over the least delayed arrivals holds to an interval.
        Not so for a recording replayed faster or slower than it was made, nor for a backlog drained by a
        busy receiver, whose arrivals then place and tell nothing."""
        arrivals = self.arrivals
        return timed_arrivals(arrivals) or len(arrivals) > RECENT and timed_arrivals(list(arrivals)[-RECENT:])

    def behind_alike(self, held: tuple[Any, ...], message: tuple[Any, ...], period: int) -> bool:
        """Whether a stamp behind its sequence (``held``) and the next (``message``; (stamp, ..., receipt))
        both trail their arrivals by the same amount, more than half a ``period`` (ns) beyond the recent
        least: the stamps stepped back, even where the next one, a lost sample later, is ahead of the old
        sequence again (one late message would trail alone)."""
        if held[3] is None or message[3] is None or not self.timed():
            return False
        top = self.lead()
        lead_h = held[0] + self.base - held[3]
        lead_n = message[0] + self.base - message[3]
        return 2 * (top - lead_h) > period and 4 * abs(lead_h - lead_n) < period

    def note_lead(self, common: int, receipt: int | None) -> None:
        """Raise the lead envelope with one taken message's common stamp and receipt (ns)."""
        if receipt is None:
            return
        self.arrivals.append((common, receipt))
        lead, drift = common - receipt, common // LEAD_DRIFT
        self._raise_floor(lead + drift, lead - drift)

    def note_leads(self, commons: NDArray[np.int64], receipts: NDArray[np.int64]) -> None:
        """:meth:`note_lead` for many taken messages (ns arrays, in order)."""
        if not len(commons):
            return
        self.arrivals.extend(zip(commons[-LEAD_WINDOW:].tolist(), receipts[-LEAD_WINDOW:].tolist()))
        lead, drift = commons - receipts, commons // LEAD_DRIFT
        self._raise_floor(int(np.max(lead + drift)), int(np.max(lead - drift)))

    def _raise_floor(self, low: int, high: int) -> None:
        floor = self.floor
        self.floor = (low, high) if floor is None else (max(floor[0], low), max(floor[1], high))

    def floor_bounds(self, common: int) -> tuple[int, int] | None:
        """(least, most) lead (ns) of the least delayed arrivals at common stamp ``common`` (ns) by :attr:`floor`, the
        receipt clock's drift allowed; None before an arrival."""
        floor = self.floor
        if floor is None:
            return None
        drift = common // LEAD_DRIFT
        return floor[0] - drift, floor[1] + drift

    def resumed_on_time(self, stamp: int, receipt: int | None, period: int) -> bool:
        """Whether a stamp ahead of the sequence (ns, this segment; ``receipt`` ns) ends a pause its arrival saw
        where the recent arrivals keep no time (a busy receiver's queue delayed those before the gap): it leads its
        arrival as the least delayed arrivals the sensor ever had do (:attr:`floor`), to half a ``period`` (ns).
        A step forward of the stamps leads by its size more (unless the queue's delay before it was as large,
        to half a period, and gone after it)."""
        common = stamp + self.base
        bounds = None if receipt is None else self.floor_bounds(common)
        if bounds is None:
            return False
        return bounds[0] - period // 2 <= common - receipt <= bounds[1] + period // 2

    def backlog_periods(self) -> int:
        """Sample periods the backlog dropped since this sensor's last stamp held (stamped on delivery: its count,
        one more for the sample after it; 0 without one): a new segment goes at least that far after the last
        sample, wherever its arrivals put it."""
        return self.burst_count + 1 if self.burst_count and self.burst_from > self.last else 0

    def backlog_fills(self, stamp: int, receipt: int | None, period: float | None) -> bool:
        """Whether the backlog just dropped (stamped on delivery: :attr:`burst_count` messages) holds the samples of
        the whole gap from this sensor's last stamp to its next ``stamp`` (ns), received at ``receipt`` (ns) no
        earlier than its stamps allow: the sensor sampled through a stall and its stamps went on with its clock (no
        step). Its count may miss a few lost samples (:data:`BACKLOG_LOSS`, and :data:`LOST_PERIODS` more), never
        hold more than the gap; a stamp further ahead of its arrival than the sensor's are stepped forward."""
        rhythm = self.grid_period() or period
        held = self.backlog_periods() * (rhythm or 0)
        if not held:
            return False
        gap = stamp - self.last
        if not held - rhythm / 2 <= gap <= held / (1.0 - BACKLOG_LOSS) + LOST_PERIODS * rhythm:
            return False
        return receipt is None or not self.arrivals or not self.ahead_of(stamp, receipt, int(rhythm))

    def crowded(self, interval: int, period: int) -> bool:
        """Whether a stamp ``interval`` (ns) is far shorter than the sensor samples (a backlog stamped as it
        was delivered): under a quarter of the short ``period`` and under :data:`BACKLOG_INTERVAL` (faster than
        any magnetometer is read: a faster rate is learnt, not dropped), while the sensor's recent intervals
        are regular (their median deviation under a quarter period: a stream of irregular stamps has no
        backlog to tell)."""
        if 4 * interval >= period or interval >= BACKLOG_INTERVAL:
            return False
        return 4 * median_int([abs(i - period) for i in self.intervals]) < period

    def classify(self, stamp: int, receipt: int | None, restart_ns: int) -> int:
        """OK, DUPLICATE, CROWDED, or a suspect BEHIND / AHEAD (see the module docstring)."""
        last = self.last
        if stamp <= last:
            return DUPLICATE if stamp == last else BEHIND
        if last == NEVER:
            return OK
        d = stamp - last
        before = self.before
        if before is not None and 0 < stamp - before[0] <= restart_ns and \
                SUSPECT_PERIODS[1] * d > SUSPECT_PERIODS[0] * before[2]:
            return AHEAD  # a jump back into the sequence a step has just left
        period = self.suspect_period()
        if period is None:  # before a period is known: a jump as far as a restart's
            return AHEAD if d > restart_ns else OK
        if self.crowded(d, period):
            return CROWDED
        if SUSPECT_PERIODS[1] * d > SUSPECT_PERIODS[0] * period:
            return AHEAD
        if 2 * d > 3 * period and self.odd_gap(stamp, receipt, period):
            return AHEAD
        return OK

    def odd_gap(self, stamp: int, receipt: int | None, period: int) -> bool:
        """Whether a gap of whole periods (``stamp`` ns, received at ``receipt`` ns) may be more than lost samples:
        the arrivals saw no gap (:meth:`unseen`) or, arrivals keeping time to decide it, it lies off the sensor's
        grid (:meth:`off_grid`). (Not where the arrivals saw more time pass than the stamps: one late message does
        that too, and holding it took lost samples delivered late for steps back.) The cheap tests first: most gaps
        are lost samples that the arrivals saw as such."""
        last = self.last_receipt
        if receipt is None or last is None:
            return False
        seen = (receipt - last) - (stamp - self.last)
        off = self.off_grid(stamp)
        if not self.bunched(receipt, period) and -period <= 2 * seen and not off:
            return False
        return bool(self.unseen(stamp, receipt, period) or off and self.timed())

    def record(self, interval: int, pause_ns: int, stamp: int) -> int:
        """Record one accepted stamp interval, ending at ``stamp`` (ns); the exact rule's window cap (half the short
        period; after a pause longer than ``pause_ns``, of the intervals since). A pause starts the sample grid
        again at ``stamp``: the periods across it, counted in the short median, may be a few off (a 2 % error in
        the median is a period in 50), and the grid's span would then give a period as far off."""
        before = self.suspect_period()
        if interval > pause_ns:
            self.fresh = 0
            self.new_grid(stamp - interval, stamp)
        else:
            self.fresh = min(self.fresh + 1, PERIOD_WINDOW)
            if before:
                self.grid_periods += max(1, int(round(interval / before)))
            else:  # the grid starts where a period is known to count its intervals in (the median of a full
                # window: that of the first few may be a lost sample's double interval, which then counts two as one)
                self.grid_first += interval
        iv = self.intervals
        iv.append(interval)
        if len(iv) > PERIOD_WINDOW:
            del iv[0]
        self.period = median_int(iv)
        if 0 < self.fresh < PERIOD_WINDOW:
            return median_int(iv[-self.fresh:]) // 2
        return self.period // 2


Batch = tuple[NDArray[np.int64], NDArray[np.float64], "NDArray[np.int64] | None"]
"""One sensor's messages in its order: stamps (n,) ns, vectors (n, 3) T, receipts (n,) ns or None."""


def arrival_order(receipts: Sequence[NDArray[np.int64]]) -> list[tuple[int, int]]:
    """(sensor, message) pairs of every sensor's messages in the order they arrived: by receipt (ns), each
    sensor's in its own order, a lower sensor index first at equal receipts."""
    k = np.concatenate([np.full(len(r), j, np.int64) for j, r in enumerate(receipts)])
    i = np.concatenate([np.arange(len(r), dtype=np.int64) for r in receipts])
    t = np.concatenate([np.asarray(r, dtype=np.int64) for r in receipts])
    order = np.lexsort((i, k, t))
    return list(zip(k[order].tolist(), i[order].tolist()))



def arrival_ratio(arrivals: Sequence[tuple[int, int]]) -> float | None:
    """The median ratio of receipt to stamp intervals of (common stamp, receipt) pairs (ns, in order): 1 live,
    the inverse of the speed of a replay; None with fewer than :data:`TIMED_MIN`."""
    if len(arrivals) < TIMED_MIN:
        return None
    pairs = list(arrivals)
    ratios = sorted((r1 - r0) / (c1 - c0) for (c0, r0), (c1, r1) in zip(pairs, pairs[1:]) if c1 > c0)
    return ratios[len(ratios) // 2] if ratios else None


def timed_arrivals(arrivals: Sequence[tuple[int, int]]) -> bool:
    """Whether (common stamp, receipt) pairs (ns, in order) advance alike: the median ratio of receipt to
    stamp intervals within 0.5 .. 2 and the stamps' lead over the arrivals not growing (see
    :meth:`SensorStream.timed`)."""
    ratio = arrival_ratio(arrivals)
    if ratio is None or not 0.5 <= ratio <= 2.0:
        return False
    pairs = list(arrivals)
    intervals = sorted(c1 - c0 for (c0, _), (c1, _) in zip(pairs, pairs[1:]) if c1 > c0)
    # A backlog drained a little faster than it was stamped (or a receiver falling behind) has such a
    # ratio too, but its stamps' lead over the arrivals moves all along: the least delayed of the newer
    # half lead by over an interval more (or less) than those of the older half.
    half = len(pairs) // 2
    interval = intervals[len(intervals) // 2]
    return abs(max(c - r for c, r in pairs[half:]) - max(c - r for c, r in pairs[:half])) <= interval


def _on_grid(common: int, grid: tuple[float, float] | None) -> bool:
    """Whether a common stamp (ns) falls on a sample ``grid`` (anchor ns, period ns) to a quarter period."""
    if grid is None:
        return False
    steps = (common - grid[0]) / grid[1]
    return abs(steps - round(steps)) <= 0.25


def _in_line(offset: int, grid: tuple[float, float] | None, phase: float = 0.0, tol: float | None = None) -> bool:
    """Whether a stamp ``offset`` (ns) from another sensor's latest is that sensor's sample or its neighbour's
    (within a period and a quarter) as the two sensors' samples lay before (``phase`` ns after the other's
    samples, to ``tol`` ns, at most a quarter period; within a millisecond while no period is known): the two
    are stamped by one clock."""
    if grid is None:
        return abs(offset) <= NS_PER_S // 1000
    period = grid[1]
    k = round((offset - phase) / period)
    limit = 0.25 * period if tol is None else min(tol, 0.25 * period)
    return abs(offset) <= 1.25 * period and abs(offset - phase - k * period) <= limit


ANEW_SIGMAS: float = 4.0
"""A new segment's period differs from its old grid's when it does by this many standard deviations of its own
estimate ..."""
ANEW_DRIFT: float = 0.125
"""... and by enough that the old grid, carried over the silence at the old period, would misplace the segment's first
sample by this fraction of a period or more; an old grid whose own period's error, carried over the silence, may
misplace it by half as much (one standard deviation) places nothing either."""


def sampled_anew(stamps: Sequence[int], period: float, periods: float, spread: float) -> bool:
    """Whether a sensor's old sample grid of ``period`` (ns; its standard deviation ``spread`` ns), carried over
    ``periods`` of silence (from its last sample to the new segment's first, by the arrivals), cannot place the new
    segment whose first ``stamps`` (ns, those held to place it) came: the grid is too uncertain that far on, or the
    stamps run at another rate (the sensor started sampling anew: a driver restarted at another rate). The new period
    is the stamps' least-squares line over their sample indices (counted in old periods: lost samples kept), its
    standard deviation from that line's residuals; a rate's difference misplaces the segment over the silence and
    over the stamps' mean index (each stamp is brought back to the first by whole old periods) (:data:`ANEW_SIGMAS`,
    :data:`ANEW_DRIFT`). Too few stamps, or one out of order, say nothing of the rate."""
    far = max(periods, 1.0)
    if 2.0 * spread * far > ANEW_DRIFT * period:
        return True
    if len(stamps) < PLACE_MESSAGES // 2:
        return False
    t = np.asarray(stamps, dtype=float) - stamps[0]
    k = np.concatenate([[0.0], np.cumsum(np.round(np.diff(t) / period))])
    if np.any(np.diff(k) <= 0):
        return False
    far += float(k.mean())
    kc = k - k.mean()
    new = float(kc @ t) / float(kc @ kc)
    residual = t - t.mean() - new * kc
    sd = math.sqrt(float(residual @ residual) / max(len(t) - 2, 1) / float(kc @ kc))
    change = abs(new - period)
    return change > ANEW_SIGMAS * sd and change * far > ANEW_DRIFT * period


def bunched(receipt: int, previous: int, period: int) -> bool:
    """Whether a message received at ``receipt`` (ns) came within a quarter ``period`` (ns) of the one received at
    ``previous``: a backlog delivered at once, whose arrivals (and their order) say nothing of time."""
    return 4 * (receipt - previous) < period


def _shift(stream: SensorStream) -> int:
    """How far (ns) the latest jump of a sensor's stamps moved its placement (its base after less before)."""
    jumps = stream.jumps
    return jumps[-1][3] - (jumps[-2][3] if len(jumps) > 1 else 0) if jumps else 0


def _latest_by(stream: SensorStream, receipt: int | None) -> tuple[int, int | None] | None:
    """(stamp, receipt) ns of the latest message ``stream`` had taken by ``receipt`` (ns; None: its latest now);
    None when none of the messages it remembers (:data:`LEAD_WINDOW`) came that early."""
    if receipt is None or stream.last_receipt is None or stream.last_receipt <= receipt:
        return stream.last, stream.last_receipt
    for common, r in reversed(stream.arrivals):
        if r <= receipt:
            return common - stream.base, r
    return None


def _lateness(stream: SensorStream, latest: tuple[int, int]) -> int:
    """How much later (ns) ``stream``'s message ``latest`` (stamp, receipt ns) came than its stamps' lead over the least
    delayed arrivals says (:meth:`SensorStream.lead`)."""
    return stream.lead() - (latest[0] + stream.base - latest[1])


def _arrivals_disown(other: SensorStream, latest: tuple[int, int | None], off: int,
                     grid: tuple[float, float] | None) -> bool:
    """Whether a new segment's arrivals place it ``off`` (ns, either way) from where lining its stamps up with
    ``other``'s would, by more than half a period beyond how late ``other``'s own ``latest`` message (stamp, receipt
    ns) came then (a receiver busy for both delays both alike): its stamps fell in line with that sensor's by
    whole periods, not back onto one clock."""
    if grid is None or latest[1] is None or not other.arrivals or not other.timed():
        return False
    late = max(0, _lateness(other, (latest[0], latest[1])))
    return 2 * (abs(off) - late) > grid[1]


def _stale(receipt: int | None, since: int | None) -> bool:
    """Whether another sensor's latest message (received at ``receipt`` ns) came before this one's previous
    (``since`` ns): its latest stamp is where its topic was held back, not where its stamps are now."""
    return receipt is not None and since is not None and receipt < since


def held_timed(held: list[Message]) -> bool:
    """Whether the arrivals of a new segment's last :data:`PLACE_MESSAGES` held messages keep their stamps' time
    (:func:`timed_arrivals`)."""
    return timed_arrivals([(m[0], int(m[3])) for m in held[-PLACE_MESSAGES:]])  # type: ignore[arg-type]


def caught_up(held: list[Message], period: int | None) -> bool:
    """Whether the arrivals of a new segment's held messages have caught up with their stamps: over the last
    four, the stamps' lead over the arrivals grew by less than a period (a backlog delivered at once
    arrives late and catches up: its lead grows by a period a message)."""
    if len(held) < 5:
        return False
    a, b = held[-5], held[-1]
    grew = (b[0] - b[3]) - (a[0] - a[3])  # type: ignore[operator]
    return grew < (period or NS_PER_S)


def _best_lead(messages: list[Message]) -> int:
    """The largest lead (ns) of ``messages``' stamps over their arrivals: the least delayed one's."""
    return max(m[0] - int(m[3]) for m in messages)  # type: ignore[arg-type]


DRAIN_MESSAGES: int = 8
"""Held messages of a new segment that show whether a receiver's queue was draining as they came
(:func:`queue_drained`)."""


def queue_drained(held: list[Message], period: int) -> bool:
    """Whether a new segment's ``held`` messages could have come through a receiver draining its queue: fewer than
    :data:`DRAIN_MESSAGES` (too few to tell), or the least delayed of the later ones leads its arrival by a quarter
    ``period`` (ns) more than the first does (a queue drained faster than it filled delivers them closer together
    than they were stamped until it has caught up: the first, taken from deepest in it, the latest; the jitter's
    spread is less). Where none came that much less late than the first, another sensor's messages late meanwhile
    were late on their own topic, and their order in the receiver says nothing of when this sensor's came."""
    if len(held) < DRAIN_MESSAGES:
        return True
    first = held[0][0] - int(held[0][3])  # type: ignore[arg-type]
    return 4 * (_best_lead(held[1:]) - first) >= period


def catching_up(held: list[Message], period: int | None) -> bool:
    """Whether the arrivals of a new segment's ``held`` messages are catching up with their stamps, still within
    :data:`HOLD_NS` of receipts (:func:`draining`; once it has caught up, the arrivals place the segment as they
    would have without the queue)."""
    return draining(held, period) and held[-1][3] - held[0][3] <= HOLD_NS  # type: ignore[operator]


def draining(held: list[Message], period: int | None) -> bool:
    """Whether the arrivals of a new segment's ``held`` messages come through a queue draining faster than it
    filled: over the last :data:`PLACE_MESSAGES`, the least delayed of the newer half leads its arrival by half a
    ``period`` (ns) more than that of the older half."""
    if period is None or len(held) < PLACE_MESSAGES:
        return False
    recent = held[-PLACE_MESSAGES:]
    half = PLACE_MESSAGES // 2
    return 2 * (_best_lead(recent[half:]) - _best_lead(recent[:half])) > period


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
        """Forget every sensor's history (held suspects and unplaced messages are counted as glitches)."""
        self.stats.glitch += self.held
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
            last = streams[k].heard
            if last is not None and now - last <= lag:
                return False
        return True

    @property
    def held(self) -> int:
        """Messages held: suspects, and the first messages of new segments being placed."""
        return sum(s.holds() for s in self.streams)

    def fault(self, x: float, y: float, z: float) -> str | None:
        """The fault of a reading (T) under this rule's :attr:`max_reading`, None when usable."""
        return acceptance.reading_fault(x, y, z, self.max_reading)

    # -- streams ----------------------------------------------------------------------
    def add_batch(self, index: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64],
                  receipts: NDArray[np.int64] | None = None) -> None:
        raise NotImplementedError

    def add_streams(self, batches: Sequence[Batch]) -> None:
        """Queue a stretch of every sensor's messages (per sensor ``(stamps, vectors, receipts)``, see
        :data:`Batch`): in the order they arrived where every arrival is known and the order can matter
        (a decision that looks at another sensor: a step), each sensor's batch at once otherwise."""
        if any(b[2] is None for b in batches) or self._plain_streams(batches):
            for k, (stamps, vectors, receipts) in enumerate(batches):
                self.add_batch(k, stamps, vectors, receipts)
            return
        faults = [acceptance.reading_fault_list(v, self.max_reading) for _, v, _ in batches]
        rows = [v.tolist() for _, v, _ in batches]
        stamps = [b[0].tolist() for b in batches]
        receipts = [b[2].tolist() for b in batches]  # type: ignore[union-attr]
        kept: list[Accepted] = [[] for _ in batches]
        for k, i in arrival_order([b[2] for b in batches]):  # type: ignore[misc]
            x, y, z = rows[k][i]
            accepted = self.accept(k, stamps[k][i], (x, y, z), faults[k][i], receipts[k][i])
            if accepted:
                self._offered(k, accepted, kept[k])
        self._offered_all(kept)

    def _plain_streams(self, batches: Sequence[Batch]) -> bool:
        """Whether each sensor's batch can be taken on its own (nothing in them looks at another sensor)."""
        return False

    def _offered(self, index: int, accepted: "Accepted", kept: "Accepted") -> None:
        """Queue what one message let through (``kept``: this sensor's, for :meth:`_offered_all`)."""
        raise NotImplementedError

    def _offered_all(self, kept: "list[Accepted]") -> None:
        """After :meth:`add_streams` offered every message."""

    # -- one message ------------------------------------------------------------------
    def accept(self, index: int, stamp: int, payload: Any, fault: str | None, receipt: int | None) -> Accepted:
        """Offer one message of sensor ``index`` (``fault``: its reading's, see :meth:`fault`); the
        messages it lets through (held ones first)."""
        if stamp <= 0 and self.reject_zero:
            self.stats.count(acceptance.stamp_fault(stamp) or "zero_stamp")
            return []
        s = self.streams[index]
        if receipt is not None:
            s.heard = receipt
        out: Accepted = []
        message = (stamp, payload, fault, receipt)
        if s.waiting is not None:
            return self._wait_for_queue(index, message)
        if s.placing is not None and self._placing(index, message, out):
            return out
        if s.held is not None and self._decide(index, message, out):
            return out
        if s.last == NEVER:  # its first message: where others of its clock placed that stamp
            s.base = self._first_base(index, stamp, s.base)
        verdict = s.classify(stamp, receipt, self.restart_ns)
        if verdict == OK:
            self._take(index, message, False, out)
        elif verdict == DUPLICATE:
            self.stats.duplicate += 1
        else:
            s.held = (stamp, payload, fault, receipt, verdict)
        return out

    def _decide(self, index: int, message: Message, out: Accepted) -> bool:
        """Decide the held suspect of sensor ``index`` with its next ``message``; whether that message was
        taken up by the decision (else it goes through the rule itself)."""
        s = self.streams[index]
        held = s.held
        assert held is not None
        kind = held[4]
        if message[0] == held[0]:  # the suspect again
            self.stats.duplicate += 1
            return True
        if kind == BEHIND:
            return self._decide_behind(index, message, out)
        step = message[0] - held[0]
        period = s.suspect_period()
        if step > 0 and period is not None and s.crowded(step, period) and \
                (kind == BURST or kind == AHEAD and held[0] - s.last <= MAX_STALL):
            # After a stall, stamps closer than the sensor samples: a backlog delivered at once ...
            if kind != BURST:
                s.burst_from, s.burst_count = held[0], 1
            self.stats.burst += 1
            s.held = None
            s.burst_count += 1
            rhythm = s.grid_period() or period
            if s.burst_count * rhythm <= 1.25 * (s.burst_from - s.last) + 2 * rhythm:  # no more than the gap held
                s.held = (*message, BURST)
                return True
            s.intervals, s.period = [], None  # ... or more than the gap held: the sensor's rate went up (learnt)
            self._take(index, message, False, out)
            return True
        s.held = None
        if kind == BURST:  # the last of a backlog
            self.stats.burst += 1
            return False
        if kind == CROWDED:  # short intervals with no gap before them: jitter, or a faster rate (learnt)
            self._take(index, held[:4], False, out)
            return False
        if step > 0 and (step <= self.restart_ns or held[0] - s.last <= self.restart_ns):  # the held one goes on
            if self._queue_unread(index, held):
                s.held, s.waiting = held, [message]
                return True
            partner = self._partner(index, held[0], held[3])
            if partner is not None:  # another sensor made this jump of one clock: as it did
                return self._jump_with(index, partner, [held[:4], message], out)
            if self._stepped_ahead(index, held):
                self._step(index, [held[:4], message], out)
                return True
            if period is None or held[0] - s.last > LOST_PERIODS * period:  # lost samples are no jump of the clock
                s.jumps.append((s.last, held[0], held[3], s.base))
            self._take(index, held[:4], False, out)  # a pause or lost samples
            return False
        self.stats.glitch += 1  # the sequence went on below it: a single bad stamp
        return False

    def _queue_unread(self, index: int, held: tuple[int, Any, str | None, int | None, int]) -> bool:
        """Whether a suspect ahead (``held``) came from a busy receiver's queue (every other sensor's latest message
        later than its stamps' lead says by over half a period) before any other sensor's message delivered after
        it: the queue's order tells when it came only once one is (:meth:`_came_between`; a step forward as large as the
        queue's delay makes the suspect look on time), so its decision waits for one, for up to
        :meth:`_wait_messages` of its own."""
        s = self.streams[index]
        receipt, period = held[3], s.suspect_period()
        if receipt is None or period is None or receipt == s.waited or \
                len(s.waiting or ()) >= self._wait_messages(index, period, held[0] - s.last) or \
                not s.arrivals:
            return False
        for j, other in enumerate(self.streams):
            if j != index and other.arrivals and receipt < other.arrivals[-1][1] <= receipt + self.restart_ns // 4:
                return False
        return self._receiver_late(index, receipt, period)

    def _wait_messages(self, index: int, period: int, ahead: int) -> int:
        """How many of its own messages sensor ``index`` (period ``period`` ns) waits at most for another sensor's
        message with a suspect ``ahead`` ns of its sequence: :data:`WAIT_MESSAGES`; for a gap lost samples cannot
        explain (over :data:`LOST_PERIODS`), as many as two periods of the slowest other sensor take (one of its
        samples lost: at 200 Hz beside 20 Hz, 20), at most :data:`MAX_WAIT_MESSAGES`. (Its messages held meanwhile
        tell the other sensors nothing: a lost sample's suspect held for the long wait misplaced another's step.)"""
        if ahead <= LOST_PERIODS * period:
            return WAIT_MESSAGES
        slowest = max((o.suspect_period() or 0 for j, o in enumerate(self.streams) if j != index), default=0)
        return min(max(WAIT_MESSAGES, -(-2 * slowest // max(period, 1))), MAX_WAIT_MESSAGES)

    def _wait_for_queue(self, index: int, message: Message) -> Accepted:
        """A message of sensor ``index`` while its suspect waits (:attr:`SensorStream.waiting`): held too while the
        queue's order is still unread, else the suspect decided with the first of them and each offered again."""
        s = self.streams[index]
        waiting = s.waiting
        assert waiting is not None and s.held is not None
        waiting.append(message)
        return [] if self._queue_unread(index, s.held) else self._end_wait(index)

    def _end_wait(self, index: int) -> Accepted:
        """End sensor ``index``'s wait: its suspect decided with the messages that waited after it, each offered again
        (one of them may start another wait, with fewer)."""
        s = self.streams[index]
        waiting = s.waiting
        assert waiting is not None
        s.waiting, s.waited = None, None if s.held is None else s.held[3]
        out: Accepted = []
        for m in waiting:
            out += self.accept(index, *m)
        return out

    def _stepped_ahead(self, index: int, held: tuple[int, Any, str | None, int | None, int]) -> bool:
        """Whether a confirmed stamp ahead of its sequence is a step of the stamps (else samples were lost
        or the sensor paused): where arrivals keep time, when they did not see the time pass; otherwise, unless
        it is a long gap its arrival saw pass at the arrivals' pace (:data:`PACED_PAUSE`: a sensor silent for a
        while in a replay at another speed or on a busy receiver), when it is more than ``restart_ns`` ahead or
        off the sensor's sample grid; where a busy receiver delivered it in a bunch, when it runs ahead of what
        the other sensors' arrivals in the same queue say (:meth:`_ahead_of_queue`)."""
        s = self.streams[index]
        s.seen_step = s.trailing = False
        if s.before is not None and 0 < held[0] - s.before[0] <= self.restart_ns and \
                self._old_sequence_goes_on(index, held[0], s.before[2]):
            return True  # back to the sequence a step had just left: a few bad stamps (placed back on it)
        period = s.suspect_period() or self.restart_ns
        low, came = (None, None) if held[3] is None else self._came_between(index, held[3], s.last_receipt, period)
        unseen = s.unseen(held[0], held[3], period) if came == held[3] else self._ahead_of_queue(index, held[0],
                                                                                                 came, period)
        s.seen_step = unseen is True
        placed = low is not None and 2 * (came - low) <= 3 * period  # the queue's order bounds when it came (to 1.5
        # periods): a step would show against it, so a gap it leaves is no jump a queue hides (not held for arrivals)
        if unseen is False and not placed and s.timed() and self._hidden_by_queue(index, held, came, period):
            s.hidden = True  # a queue's delay hides how far the stamps went: placed by the arrivals once they catch up
            return True
        if unseen is False and came == held[3] and s.trails(held[0], held[3], period) and \
                not self._receiver_late(index, held[3], period):
            s.seen_step = s.trailing = True  # the arrivals saw more of the gap pass than the stamps: they stepped back
            return True  # (not where the receiver was late with every sensor: a queue delayed this arrival)
        if unseen is not None:
            return unseen
        if s.resumed_on_time(held[0], held[3], period):
            return False  # a pause seen by arrivals late by a draining queue before it, on time after
        ratio = arrival_ratio(s.arrivals)
        jump = held[0] - s.last
        if held[3] is not None and s.last_receipt is not None and ratio is not None and \
                jump > PACED_PAUSE * self.restart_ns and 2 * (held[3] - s.last_receipt) >= ratio * jump:
            return False  # arrivals that keep no time (a replay at another speed, a busy receiver) saw the gap pass
        return held[0] - s.last > self.restart_ns or s.off_grid(held[0])

    def _hidden_by_queue(self, index: int, held: tuple[int, Any, str | None, int | None, int], came: int | None,
                         period: int) -> bool:
        """Whether a stamp ahead of its sequence (``held``, taken from a busy receiver's queue: delivered bunched,
        later than it came, ``came`` ns, or off the sensor's sample grid after a message of its own that came late,
        before any other sensor's told when it came) arrived later than its stamp says by more than half a
        ``period`` (ns): the queue's delay hides a step forward of the stamps up to that size as well as it hides a
        pause. (Lost samples keep the grid: a gap on it, every arrival late on a loaded receiver, is not held.)"""
        s = self.streams[index]
        receipt = held[3]
        if receipt is None or came == receipt and not s.bunched(receipt, period) and \
                not (self._own_late(index, period) and s.off_grid(held[0])):
            return False
        return 2 * _lateness(s, (held[0], receipt)) > period and self._receiver_late(index, receipt, period)

    def _own_late(self, index: int, period: int) -> bool:
        """Whether sensor ``index``'s previous message came later than its stamps' lead says by more than half a
        ``period`` (ns)."""
        s = self.streams[index]
        return s.last_receipt is not None and 2 * _lateness(s, (s.last, s.last_receipt)) > period

    def _receiver_late(self, index: int, receipt: int, period: int) -> bool:
        """Whether the receiver was late with every sensor at ``receipt`` (ns): each other sensor's latest message
        received by then, within a quarter of ``restart_ns``, came later than its stamps' lead says by more than
        half a ``period`` (ns) (one sensor's driver late alone delays only its own messages)."""
        return bool(self._late_others(index, receipt, period))

    def _late_others(self, index: int, receipt: int, period: int) -> list[int]:
        """The other sensors late at ``receipt`` (ns) as :meth:`_receiver_late` judges them; none where any of them was
        on time."""
        late, on_time = self._others_at(index, receipt, period)
        return [] if on_time else late

    def _others_at(self, index: int, receipt: int, period: int,
                   mates: list[int] | None = None) -> tuple[list[int], bool]:
        """(the other sensors whose latest message received by ``receipt`` (ns), within a quarter of ``restart_ns``,
        came later than its stamps' lead says by more than half a ``period`` (ns); whether any such latest came on
        time), among ``mates`` (default :meth:`_queue_mates`): sensors whose topic waited in a queue of their own
        tell nothing."""
        late = []
        for j in self._queue_mates(index, period) if mates is None else mates:
            other = self.streams[j]
            latest = _latest_by(other, receipt)
            if latest is None or latest[1] is None or receipt - latest[1] > self.restart_ns // 4:
                continue
            if 2 * _lateness(other, (latest[0], latest[1])) <= period:
                return late, True
            late.append(j)
        return late, False

    def _queue_mates(self, index: int, period: int) -> list[int]:
        """The other sensors with arrivals whose topic shares sensor ``index``'s queue (not :meth:`_own_queue`)."""
        return [j for j, other in enumerate(self.streams)
                if j != index and other.arrivals and not self._own_queue(index, j, period)]

    def _own_queue(self, index: int, j: int, period: int) -> bool:
        """Whether sensor ``j``'s topic waited in a queue of its own at sensor ``index``'s previous message: a message
        of ``j`` that came more than two periods (``period``, ns) before that one (each when its stamps' lead says) was
        delivered after it. A receiver takes its queue in the order the messages came; a topic served late on its
        own (a loaded machine, a driver's backlog) breaks that order, and its lateness and order then tell nothing
        of when ``index``'s messages came."""
        s, other = self.streams[index], self.streams[j]
        if s.last_receipt is None or not s.arrivals:
            return False
        came, lead = s.lastc - s.lead(), other.lead()
        for common, r in reversed(other.arrivals):
            if r <= s.last_receipt:
                return False
            if came - (common - lead) > 2 * period:
                return True
        return False

    def _decide_behind(self, index: int, message: Message, out: Accepted) -> bool:
        """The held suspect is behind its sequence: a step back when ``message`` goes on from it below the
        old sequence (or, a period or two back, on its grid rather than the old one's: one period after
        the suspect and less than a period past the old sequence's last stamp, while the suspect lies
        clearly behind that stamp or the message does not fall short of it), else a single late or bad
        stamp."""
        s = self.streams[index]
        held = s.held
        assert held is not None
        s.held = None
        stamp, h = message[0], held[0]
        after = stamp - h
        if 0 < after <= self.restart_ns:
            partner = self._partner(index, h, held[3])
            if partner is not None:  # another sensor made this jump of one clock: as it did
                return self._jump_with(index, partner, [held[:4], message], out)
            period = s.suspect_period()
            below = s.last - stamp > (period or 0) // 2  # clearly below the old sequence, not its jitter
            if below or (period is not None and ((0 <= stamp - s.last or 2 * (s.last - h) > period)
                                                 and 4 * (stamp - s.last) < 3 * period
                                                 and period <= 2 * after <= 3 * period
                                                 or s.behind_alike(held, message, period))):
                self._step(index, [held[:4], message], out)
                return True
        self.stats.count("out_of_order" if s.last - h <= self.restart_ns else "glitch")
        return False

    def release_quiet_holds(self, now_ns: int) -> list[tuple[int, Accepted]]:
        """Live, on the receiver's clock at ``now_ns``: every sensor that holds messages and whose latest came more
        than :data:`HOLD_NS` before has them decided as at the end of its stream (:meth:`release_held`), with
        ``(sensor, the messages let through)`` for each. A hold waits for the sensor's later messages; where none
        come (the end of a collection, a driver stopped), it would otherwise wait until the next one. The
        decision is the one that next message would have made, or the end of a recording does offline."""
        out: list[tuple[int, Accepted]] = []
        for k, s in enumerate(self.streams):
            if s.holds() and s.quiet(now_ns):
                accepted = self.release_held(k)
                if accepted:
                    out.append((k, accepted))
        return out

    def release_held(self, index: int) -> Accepted:
        """End of stream for sensor ``index``: a new segment is placed with what there is; a suspect
        ahead is kept, one behind (or the last of a backlog) dropped."""
        s = self.streams[index]
        out: Accepted = []
        while s.waiting is not None:
            out += self._end_wait(index)
        if s.placing is not None:
            self._place_held(index, out)
        held, s.held = s.held, None
        if held is not None:
            if held[4] == BURST:
                self.stats.burst += 1
            elif held[4] == CROWDED:
                self._take(index, held[:4], False, out)
            elif held[4] == BEHIND or held[0] - s.last > self.restart_ns:  # behind, or unconfirmed far ahead
                self.stats.glitch += 1
            else:
                self._take(index, held[:4], False, out)
        return out

    # -- steps ------------------------------------------------------------------------
    def _step(self, index: int, messages: list[Message], out: Accepted) -> None:
        """Sensor ``index``'s stamps stepped: ``messages`` start its new segment. Where their arrivals are
        known they are held until :data:`PLACE_MESSAGES` have come (the least delayed places the segment);
        otherwise the segment is placed at once."""
        s = self.streams[index]
        if not s.timed() or any(m[3] is None for m in messages):
            moved = self._place(index, [messages[0][0]], None, messages[0][3])
            self._take(index, messages[0], moved, out)
            for m in messages[1:]:
                self._take(index, m, False, out)
            return
        s.placing, s.queued_at = list(messages), None

    def _placing(self, index: int, message: Message, out: Accepted) -> bool:
        """Add ``message`` to the new segment being placed (placing it once there are enough); whether it
        was taken up (a message that does not go on from the segment ends the placing and goes through
        the rule)."""
        s = self.streams[index]
        held = s.placing
        assert held is not None
        step = message[0] - held[-1][0]
        period = s.suspect_period()
        limit = self.restart_ns if period is None else min(self.restart_ns, SUSPECT_PERIODS[0] * period // 2)
        if s.trailing and period is not None:  # (held for seconds: lost samples go on from it)
            limit = max(limit, LOST_PERIODS * period)
        if message[3] is None or not (0 < step <= limit):
            self._place_held(index, out)
            return False
        held.append(message)
        if len(held) < PLACE_MESSAGES:
            return True
        timed = held_timed(held)
        s.trailing = s.trailing and (timed or len(held) > PLACE_MESSAGES)  # (first held at pace: no queue's drain)
        if s.trailing:  # a topic late at its own pace trails as a step back does until it drains: it waits for the
            if held[-1][3] - held[0][3] > HOLD_NS:  # type: ignore[operator]  drain as long as a message may wait
                self._place_held(index, out)
        elif timed and caught_up(held, period):
            self._place_held(index, out)
        elif s.hidden:  # a jump a queue hid waits for arrivals on time again as long as a message may wait
            if held[-1][3] - held[0][3] > HOLD_NS:  # type: ignore[operator]
                self._place_held(index, out, by_arrival=False)
        elif len(held) >= MAX_PLACE_MESSAGES or (not timed and len(held) >= 2 * PLACE_MESSAGES
                                                  and not self._waits_to_catch_up(index, held, period)):
            # arrivals that do not keep the stamps' time: the stamps alone place it, unless a queue still drains
            # them as long as a message may wait (a stall of seconds: its first messages came on time)
            self._place_held(index, out, by_arrival=draining(held, period))
        return True

    def _waits_to_catch_up(self, index: int, held: list[Message], period: int | None) -> bool:
        """Whether sensor ``index``'s new segment, ``held`` with arrivals that do not keep its stamps' time, waits for
        them to catch up (:func:`catching_up`) rather than being placed now: not where, at the first such decision
        (:data:`PLACE_MESSAGES` twice held), a queue's order bounds it (:meth:`_placed_by_queue`: placed by that, as
        before; a long drain may outlast the wait)."""
        if not catching_up(held, period):
            return False
        s = self.streams[index]
        if len(held) > 2 * PLACE_MESSAGES:
            return True
        s.queued_at, bounded = self._placed_by_queue(index, held, s.suspect_period() or self.restart_ns, int(s.lead()))
        return not bounded

    def _place_held(self, index: int, out: Accepted, by_arrival: bool = True) -> None:
        """Place the held new segment of sensor ``index`` by its least delayed arrival (or, ``by_arrival``
        False, by its stamps alone) and let it through."""
        s = self.streams[index]
        held = s.placing
        assert held is not None and s.arrivals
        s.placing = None
        first = held[0]
        lead = s.lead()
        # each message's arrival says where the segment lies; a late one says too late: the earliest wins
        period = s.suspect_period() or self.restart_ns
        hidden, s.hidden = s.hidden, False
        trailing, s.trailing = s.trailing, False
        if trailing:  # by the least delayed of every held arrival: a late topic's drain puts it back
            estimate, by_arrival = first[0] + int(lead) - _best_lead(held), True
        elif hidden:  # by the latest arrivals alone, on time again (a queue's order placed the drained ones)
            estimate = min(first[0] + int(m[3]) + int(lead) - m[0] for m in held[-PLACE_MESSAGES:])  # type: ignore[arg-type]
            if self._hidden_pause(index, held, estimate if by_arrival else None, period, out):
                return
        else:
            estimate, bounded = self._placed_by_queue(index, held, period, int(lead))
            by_arrival = by_arrival or bounded  # a queue's order places what the drained arrivals' pace could not
            if s.queued_at is not None and not bounded and not held_timed(held):
                # still draining when the wait (or the hold) ended: the others' arrivals that ordered its first
                # messages are gone by now, and its own, late, say too late; the order they gave when it was first
                # decided places it if earlier (not its stamps alone: a stall's backlog as the hold ran out)
                estimate, by_arrival = min(estimate, s.queued_at), True
        moved = self._place(index, [m[0] for m in held], estimate if by_arrival else None, first[3])
        self._take(index, first, moved, out)
        for m in held[1:]:
            self._take(index, m, False, out)

    def _placed_by_queue(self, index: int, held: list[Message], period: int, lead: int) -> tuple[int, bool]:
        """Where (ns, common) the first of a new segment's ``held`` messages of sensor ``index`` lies by their arrivals
        (``lead``: the stamps' over the least delayed, ns), and whether a queue's order bounds it both ways to half a
        ``period`` (ns). Each message came no later than its receipt nor than the queue's order allows, and no earlier
        than that order allows (:meth:`_came_between`). Where the tightest bounds all of them set lie within half a
        period (to a quarter of a period crossed: their delays), their middle; else the earliest of each message's
        own (the middle of its bounds, or its latest where it has no earliest): where the sensors sample together,
        a message's bounds are a period apart, with the truth at one end and their middle between two samples."""
        first = held[0][0]
        if not queue_drained(held, period):  # its own arrivals kept their stamps' pace: no queue held them
            return first + lead - _best_lead(held), False
        receipts = [self.streams[index].last_receipt] + [m[3] for m in held]
        lowest: int | None = None
        latest: int | None = None
        each: int | None = None
        for k, m in enumerate(held):
            low, high = self._came_between(index, int(m[3]), receipts[k], period)  # type: ignore[arg-type]
            shift = first + lead - m[0]
            own = high if low is None or low > high else (low + high) // 2
            each = own + shift if each is None else min(each, own + shift)
            latest = high + shift if latest is None else min(latest, high + shift)
            if low is not None:
                lowest = low + shift if lowest is None else max(lowest, low + shift)
        assert each is not None and latest is not None
        if lowest is not None and -period < 4 * (latest - lowest) < 2 * period:
            return (lowest + latest) // 2, True
        return each, False

    def _hidden_pause(self, index: int, held: list[Message], estimate: int | None, period: int, out: Accepted) -> bool:
        """A jump forward a queue hid (:meth:`_hidden_by_queue`), its segment ``held``: taken as a pause (the stamps go
        on as before, every message let through; True) unless the arrivals on time again put it more than half a
        ``period`` (ns) earlier (``estimate`` ns; None: they never came on time), or another sensor made the same jump
        of one clock (placed as it was: False, :meth:`_place`)."""
        s = self.streams[index]
        first = held[0]
        partner = self._partner(index, first[0], first[3])
        if partner is not None and partner[1] is not None or \
                estimate is not None and 2 * (first[0] + s.base - estimate) > period:
            return False
        s.jumps.append((s.last, first[0], first[3], s.base))
        for m in held:
            self._take(index, m, False, out)
        return True

    def _ahead_of_queue(self, index: int, stamp: int, arrival: int, period: int) -> bool:
        """Whether ``stamp`` (ns), taken from a busy receiver's queue, runs more than half a ``period`` (ns) further
        ahead of its ``arrival`` (ns; when it came to the queue at the latest, :meth:`_came_between`) than the sensor's stamps
        do: the stamps stepped forward (the receipts alone, late by the queue, hid it)."""
        return self.streams[index].ahead_of(stamp, arrival, period)

    def _came_between(self, index: int, receipt: int, previous: int | None, period: int) -> tuple[int | None, int]:
        """(earliest or None: unknown, latest) ns when sensor ``index``'s message received at ``receipt`` (ns; its
        previous at ``previous``) came to a receiver that then took it from its queue: a queue delivers in the
        order the messages came, so it came after the latest of another sensor's delivered before it and no later
        than the first delivered after it, each of which came when its stamps' lead says (their least delay): the
        earliest every other sensor allows and the latest any of them does (one whose lead is not yet known right
        must not make it look early); (None, ``receipt``) where the receiver was not late by half the
        ``period`` (ns), or where the message came bunched with its own previous while no other sensor was late, or no
        other sensor's message was delivered within a quarter of ``restart_ns`` after it. Another sensor's messages that
        came bunched (a driver's backlog delivered at once, whose order says nothing of when its messages came) bound it
        only where a third sensor, or this one's previous message, was late too: then the receiver was draining its
        queue, which every sensor's messages came to on time."""
        if previous is None:
            return None, receipt
        mates = self._queue_mates(index, period)
        late, on_time = self._others_at(index, receipt, period, mates)
        if on_time or bunched(receipt, previous, period) and not late:
            return None, receipt  # (one on time: no queue held the receiver; a topic late on its own bounds nothing)
        lower, upper = None, None
        s = self.streams[index]  # its previous message late (its lead still right): the receiver's drain too
        own_late = s.last_receipt is not None and 2 * _lateness(s, (s.last, s.last_receipt)) > period
        for j in mates:
            other = self.streams[j]
            after, before = None, None
            for common, r in reversed(other.arrivals):
                if r < receipt:
                    before = (common, r)
                    break
                after = (common, r)
            if after is None or before is None or after[1] - receipt > self.restart_ns // 4 or \
                    bunched(after[1], before[1], other.suspect_period() or self.restart_ns) and \
                    not (own_late or any(k != j for k in late)):  # a third sensor late too: the receiver's drain too
                continue
            lead = other.lead()
            upper = after[0] - lead if upper is None else max(upper, after[0] - lead)
            lower = before[0] - lead if lower is None else max(lower, before[0] - lead)
        if upper is None or 2 * (receipt - upper) <= period:
            return None, receipt
        return lower, upper

    def _take(self, index: int, message: Message, restart: bool, out: Accepted) -> None:
        stamp, payload, fault, receipt = message
        s = self.streams[index]
        if s.last == NEVER:  # its first stamp: where others of its clock that jump to it follow it
            s.jumps.append((NEVER, stamp, receipt, s.base))
        if restart or s.last == NEVER:
            s.intervals, s.period, s.fresh = [], None, PERIOD_WINDOW
            s.since = 0
            s.new_grid(s.last, stamp)  # (a first stamp: no grid before it to keep)
            s.tail = []
            cap = NO_CAP
        else:
            cap = NO_CAP if s.last == NEVER else s.record(stamp - s.last, self.pause_ns, stamp)
            s.since += 1
            if s.since > PERIOD_WINDOW:
                s.before = None
        s.last = stamp
        s.lastc = c = stamp + s.base
        s.last_receipt = receipt
        s.burst_count = 0  # a backlog dropped before tells of the gap before this message only
        tail = s.tail
        tail.append(c)
        if len(tail) > TAIL:
            del tail[0]
        s.note_lead(c, receipt)
        if c > self.newest:
            self.newest = c
        self.arrived(receipt)
        if fault is not None:
            self.stats.count(fault)
            payload = None
        out.append((stamp, c, payload, cap, restart))

    def _place(self, index: int, stamps: list[int], estimate: int | None, receipt: int | None = None) -> bool:
        """Place sensor ``index``'s new segment, whose first stamps are ``stamps`` (the first received at
        ``receipt`` ns, None: unknown), on the common timeline: as another sensor that made the same jump of its
        stamps placed its own (one clock stamps both); else its first sample at ``estimate`` (ns, from its
        arrivals; None, or at or before its last sample: unknown, one period after it) on its old sample grid (each
        stamp's jitter averaged out; by its arrivals alone where that grid cannot place it, :func:`sampled_anew`),
        unless that is where another sensor's stamps (or its own old segment's) put it. Whether the
        segment moved: False where it went back onto its own old placement (the stamps went on: the gap before it
        is lost samples, counted as such, not a restart)."""
        s = self.streams[index]
        partner = self._partner(index, stamps[0], receipt)
        if partner is not None and partner[1] is not None:
            self._follow(index, partner, stamps[0], receipt)
            return True
        s.follows = None
        if estimate is not None and estimate <= s.lastc:  # arrivals that put its first sample at or before the old
            estimate = None  # segment's last changed their pace with the step (a replay at another speed): stamps
        period = s.grid_period()
        short = s.suspect_period()
        if period and short and 8 * abs(period - short) > short:
            period = short  # the rate changed within the segment (after a pause): the recent one
        margin = self.restart_ns // 2
        known = period or (s.before[2] if s.before is not None else 0)  # (no period yet: the one before a step)
        if estimate is not None and known:  # placed by arrivals: to half a period
            margin = min(margin, int(known) // 2)
        stamp = stamps[0]
        grid = None
        anchor = s.anchor(period) if period else 0.0
        if not period or estimate is not None and \
                sampled_anew(stamps, period, (estimate - anchor) / period, s.grid_spread()):
            base = (s.lastc if estimate is None else estimate) - stamp
        else:
            grid = (anchor, period)
            steps = 1 if estimate is None else max(1, round((estimate - anchor) / period))
            if estimate is None:  # nor after the data others placed there since (one clock, this one silent)
                since = self._placed_since(index, stamp, period, receipt)
                steps = max(steps, math.ceil((since - period / 2 - anchor) / period))
            backlog = s.backlog_periods()
            if steps < backlog:  # fewer periods than a stall's backlog held: it sampled through it
                steps = backlog
                if s.backlog_fills(stamp, receipt, period):  # its stamps as far on: they went on, no step
                    steps = max(steps, round((stamp + s.base - anchor) / period))
            first = anchor + steps * period  # the sensor kept sampling: whole periods after its last sample
            base = int(round(sum(first + round((t - stamp) / period) * period - t for t in stamps) / len(stamps)))
        base = max(base, s.lastc + 1 - stamp)
        estimate = stamp + base
        old = s.base
        s.before = (s.last, old, int(period or 0)) if s.before is None else s.before
        s.base = base
        shared = self._shared_base(index, stamps, estimate, margin, grid, receipt, old)
        s.placed_at = estimate
        if shared is not None:
            s.base, s.follows = shared
        s.jumps.append((s.last, stamp, receipt, s.base))
        if shared is not None:
            if s.base != s.before[1]:
                return True
            s.before = None
            return False
        self.stats.restarts += 1
        return True

    def _placed_since(self, index: int, stamp: int, period: float, receipt: int | None) -> float:
        """The earliest common stamp (ns; :data:`NEVER`: no limit) for the new ``stamp`` (ns) of sensor ``index``
        (sample ``period`` ns) by the data other sensors placed after jumps of their stamps from at or after its
        last stamp and up to ``stamp`` (one clock stamps them all): a period (theirs or its own, the longer)
        after that data, or where ``stamp`` lies inside it, where it lies there. A sensor silent through a piece
        the others were placed in goes after that piece, not back over it (placed one period after its own last
        sample, its stamps would pair with the piece's). Not where its own message came (``receipt`` ns) too soon
        after its previous one for the silence that one clock's jumps would mean (it was not silent)."""
        s = self.streams[index]
        floor: float = NEVER
        for j, other in enumerate(self.streams):
            if j == index:
                continue
            records = list(other.jumps)
            for k, (a, b, _, base) in enumerate(records):
                if a >= s.last - SAME_STAMP and b <= stamp + SAME_STAMP and \
                        not self._kept_talking(index, receipt, (stamp - s.last) - (b - a)):
                    end = records[k + 1][0] if k + 1 < len(records) else other.last
                    floor = max(floor, stamp + base if stamp <= end else end + base + max(period, other.grid_period() or 0))
        return floor

    def _kept_talking(self, index: int, receipt: int | None, silence: int) -> bool:
        """Whether sensor ``index``'s message received at ``receipt`` (ns) came too soon after its previous one for
        the sensor to have been silent for ``silence`` (ns): under a quarter of it (a busy receiver's queue, drained
        at no more than three times the rate it filled, keeps a silent sensor's messages that far apart)."""
        last = self.streams[index].last_receipt
        return receipt is not None and last is not None and 4 * (receipt - last) < silence

    def _first_base(self, index: int, stamp: int, base: int) -> int:
        """The base (ns) of a sensor's first ``stamp`` (ns): that of another sensor whose stamps jumped to it, or
        whose current segment (from its latest jump on) holds it (one clock stamps both: the sensor started late,
        after the others' stamps had been placed); ``base`` otherwise (its own: 0, or a placement kept from a
        synchroniser this one replaced)."""
        for j, other in enumerate(self.streams):
            if j == index or not other.jumps:
                continue
            _, b, _, placed = other.jumps[-1]
            if b - SAME_STAMP <= stamp <= other.last + SAME_STAMP:
                return placed
        return base

    def _partner(self, index: int, stamp: int, receipt: int | None) -> tuple[int, int | None] | None:
        """(sensor, its base after, ns; None while it is still placing its new segment) of another sensor whose
        stamps made the jump sensor ``index``'s make now (from its previous stamp to ``stamp``, received at
        ``receipt``; ns): the same size to :data:`SAME_JUMP` or a quarter period, from a stamp within a period and
        a quarter of this one's, or a jump of any size to this very stamp (to :data:`SAME_STAMP`: one sensor had
        been silent, the other not); received within :attr:`lag_ns` where both receipts are known. One clock
        stamps both: whichever decided the jump first (a pause, or a step and where it lies) decides it for the
        other, whatever each one's arrivals say (a loaded computer takes one topic's messages well before
        another's)."""
        s = self.streams[index]
        if s.last == NEVER:
            return None
        period = s.grid_period()
        tol = SAME_JUMP if not period else min(SAME_JUMP, int(period) // 4)
        near = 1.25 * period if period else SAME_JUMP
        size = stamp - s.last

        def same(a: int, b: int, r: int | None) -> bool:
            return (abs(b - a - size) <= tol and abs(a - s.last) <= near or abs(b - stamp) <= SAME_STAMP
                    and silent_since(r)) and (receipt is None or r is None or abs(r - receipt) <= self.lag_ns)

        def silent_since(r: int | None) -> bool:
            """Whether this sensor may have been silent since the other's jump to its stamp (received at ``r``):
            its previous message came before that jump (to half of ``restart_ns``), else it jumped there itself
            later (a restart to the same origin)."""
            return r is None or s.last_receipt is None or 2 * (s.last_receipt - r) <= self.restart_ns

        def placing(other: SensorStream) -> bool:  # it places a new segment after this jump
            return other.placing is not None and same(other.last, other.placing[0][0], other.placing[0][3])

        def deciding(other: SensorStream, r: int | None) -> bool:
            """Whether ``other``'s jump received at ``r`` is an older one of the same stamps (half of
            ``restart_ns`` before this one's receipt) and ``other`` holds this one undecided or places it."""
            if r is None or receipt is None or 2 * (receipt - r) <= self.restart_ns:
                return False
            held = other.held
            return held is not None and held[4] in (AHEAD, BEHIND) and same(other.last, held[0], held[3]) or \
                placing(other)

        def later_alike(a: int, r: int | None, base: int, before: int) -> bool:
            """Whether the other's jump from ``a`` received at ``r`` came as much before or after this one as the two
            sensors' bases say the same stamps lie apart in time: the same stamps at another instant (a lost sample
            each, say; or a step of this sensor alone from the stamps another left by the same step before, its base
            ``before`` then), not one clock's jump. The stamps it left where they are this one's last (the same jump),
            else those it went to (``base`` its after it)."""
            if r is None or receipt is None:
                return False
            apart = r - receipt
            other_base = before if abs(a - s.last) <= near else base
            return abs(apart - (other_base - s.base)) < abs(apart)

        others = [(j, other) for j, other in enumerate(self.streams) if j != index]
        for j, other in others:  # one that decided the jump (unless it is making it again: a step repeated from
            jumps = other.jumps
            for k in range(len(jumps) - 1, -1, -1):  # the same stamp to the same stamp, not decided yet) ...
                a, b, r, base = jumps[k]
                if same(a, b, r) and not later_alike(a, r, base, jumps[k - 1][3] if k else base):
                    return (j, None) if deciding(other, r) else (j, base)
        for j, other in others:  # ... else one still placing it
            if placing(other):
                return j, None
        return None

    def _follow(self, index: int, partner: tuple[int, int | None], stamp: int, receipt: int | None) -> None:
        """Place sensor ``index``'s new segment from ``stamp`` (ns) where its ``partner`` (sensor, base ns) placed
        its own."""
        s = self.streams[index]
        j, base = partner
        assert base is not None
        s.before = (s.last, s.base, int(s.grid_period() or 0)) if s.before is None else s.before
        s.base = base
        s.follows = self._leader(index, j)
        s.placed_at = stamp + base
        s.jumps.append((s.last, stamp, receipt, base))

    def _jump_with(self, index: int, partner: tuple[int, int | None], messages: list[Message],
                   out: Accepted) -> bool:
        """Take the first of ``messages`` (a held stamp and the next), whose stamp jumped as ``partner``'s (sensor,
        base after ns, None: still placing) did: a pause where it kept this sensor's base, the first of a new
        segment placed alike where it moved it; or both, a new segment to place like that sensor's while it
        places its own (held as long as that one is). Whether the next message was taken too."""
        s = self.streams[index]
        first = messages[0]
        if partner[1] is None:
            self._step(index, messages, out)
            if s.placing is not None:  # it waits as long as the other does: a jump a queue hid (one clock's)
                s.hidden = self.streams[partner[0]].hidden
            return True
        if partner[1] == s.base:
            s.jumps.append((s.last, first[0], first[3], s.base))
            self._take(index, first, False, out)
        else:
            self._follow(index, partner, first[0], first[3])
            self._take(index, first, True, out)
        return False

    def _shared_base(self, index: int, stamps: list[int], estimate: int, margin: int,
                     grid: tuple[float, float] | None, receipt: int | None, old: int) -> tuple[int, int | None] | None:
        """(base, sensor followed) where the new segment of sensor ``index`` at ``estimate`` lines up with
        another sensor's placement or its own old segment's (a few bad stamps had looked like a step); None
        when it stands alone. ``margin``: how far apart (ns) a placement may be from where another sensor's
        recent step put it (by arrivals half a period; without them, half of ``restart_ns``); with one that did
        not step, half of that and at most a millisecond (the stamps are back in line with its own). With a sensor
        whose stamps stepped within :data:`SHARED_STEP` (the same jump of one stamping clock), within that margin or
        :data:`SHARED_MARGIN`, where that puts the new stamps on the old sample ``grid`` (anchor, period ns) to a
        quarter period (one clock's jump keeps each sensor's grid; another clock's jump of a size close by does
        not): arrivals a loaded computer delays can place either a period off, the shared jump moves both alike (this sensor's base before the step, ``old`` ns, by that sensor's shift). First of all, where the new stamps are another sensor's latest to half a period
        or its neighbour's (the sensors are stamped by one clock again, whatever each one's arrivals say, unless
        they put it more than half a period further than that sensor's own arrivals were late then:
        :func:`_arrivals_disown`), that sensor's placement: its latest when ``stamp`` was received (``receipt``
        ns; a segment placed by its arrivals was held while the others went on)."""
        s = self.streams[index]
        stamp = stamps[0]
        by_arrival = margin < self.restart_ns // 2
        for j, other in enumerate(self.streams):  # its stamps now those of another sensor: one clock again
            if j == index or other.last == NEVER or other.busy:
                continue
            latest = _latest_by(other, receipt)
            if latest is not None and self._in_line_with(index, j, stamps, latest[0], grid) and \
                    not _stale(latest[1], s.last_receipt) and \
                    not (by_arrival and _arrivals_disown(other, latest, estimate - stamp - other.base, grid)):
                return other.base, self._leader(index, j)
        for j, other in enumerate(self.streams):
            if j == index or other.last == NEVER:
                continue
            recent = other.placed_at is not None and abs(estimate - other.placed_at) <= SHARED_STEP
            base = old + _shift(other) if recent else other.base  # one clock's jump moves both alike
            off = abs(stamp + base - estimate)
            if recent:  # (the shared jump keeps this sensor's sample grid: not another clock's jump of a size close by)
                near = (off <= margin or by_arrival and off <= SHARED_MARGIN) and \
                    (grid is None or _on_grid(stamp + base, grid))
            else:
                near = off <= min(margin // 2, NS_PER_S // 1000)
            if near:
                return base, self._leader(index, j)
        before = s.before  # back just after the old sequence's last stamp (on its grid; where arrivals say so too)
        if before is not None and 0 < stamp - before[0] <= self.restart_ns and \
                (abs(stamp + before[1] - estimate) <= margin if by_arrival else
                 not s.seen_step and (grid is None or _on_grid(stamp + before[1], grid)) and
                 self._old_sequence_goes_on(index, stamp, grid[1] if grid else before[2])):
            return before[1], None
        return None

    def _old_sequence_goes_on(self, index: int, stamp: int, period: float) -> bool:
        """Whether sensor ``index``'s ``stamp`` (ns) goes on from the sequence its latest step left (the step was a
        few bad stamps) with no more samples lost than going on from the new segment would take (``period`` ns; 0:
        unknown, True): a gap of two lost samples after a step 0.38 s ahead is not the old sequence back 76 periods
        on."""
        s = self.streams[index]
        before = s.before
        if not period or before is None:
            return True
        old = (stamp - before[0]) / period - (s.since + 1)
        new = (stamp - s.last) / period - 1
        return old <= new

    def _in_line_with(self, index: int, j: int, stamps: list[int], latest: int, grid: tuple[float, float] | None) -> bool:
        """Whether sensor ``index``'s new ``stamps`` (ns, its first ones after a step) are sensor ``j``'s stamps again
        (its ``latest``, ns, taken by then): the first lies within a period and a quarter of it, on its grid as the two
        sensors' samples lay before the step (:func:`_in_line`). With a period known, the first stamp's offset is
        averaged over ``stamps`` (each brought back by whole periods) and held to the noise of that average: four
        standard deviations of the stamps' jitter (:meth:`SensorStream.jitter`), at least a twentieth of a period
        (while the relative phase is unknown, a quarter period and the first stamp alone)."""
        s, other = self.streams[index], self.streams[j]
        offset = stamps[0] - latest
        if grid is None or s.lastc == NEVER:
            return _in_line(offset, grid)
        period = grid[1]
        commons = [c for c, _ in other.arrivals] or other.tail
        near = min(commons, key=lambda c: abs(c - s.lastc), default=None)
        if near is None or abs(near - s.lastc) > 1.25 * period:
            return _in_line(offset, grid)
        mean = sum(t - stamps[0] - round((t - stamps[0]) / period) * period for t in stamps) / len(stamps)
        sigma = max(s.jitter(), other.jitter()) / 4 / math.sqrt(2)  # one stamp's, from its intervals' spread
        tol = max(4 * sigma * math.sqrt(1 / len(stamps) + 1), period / 20)
        return _in_line(round(offset + mean), grid, float(s.lastc - near), tol)

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

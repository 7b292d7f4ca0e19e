"""Health of a live sensor array, as the nodes report it on ``/diagnostics`` (no ROS import).

Per sensor: messages received, the last stamp, its sample period and the samples lost
before the node, both from the synchroniser's sample clock of the sensor
(:mod:`magcal_ros.core.sample_clock`: a line fitted to many stamps, never a period from one
pair of stamps): every sample index the stamps skip is a sample lost (DDS queue overflow,
a lossy link), in runs counted as gaps. A silence longer than ``silent_after_ns`` is a
pause of the sensor (reported as silent while it lasts), not a loss; after it (and after a
restart) the clock is learnt afresh, so a sensor that comes back at another rate is not
miscounted. Every ``assess`` (the status period) turns the counters into a level and a
message:

- ERROR: no output (set published or collected) for ``stale_after_ns``;
- WARN: a sensor silent (no message for ``silent_after_ns``) or late (its newest stamp
  that far behind the array's newest), more than ``max_drop_fraction`` of the messages of
  the last period dropped or lost, or the synchroniser's window capped below
  ``sync_tolerance`` (the sample period is shorter than twice the tolerance);
- OK otherwise.

Times are node-clock nanoseconds (simulated time with ``use_sim_time``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from typing import Any

from magcal_ros.core.sync import DROP_FIELDS
from magcal_ros.core.units import NS_PER_S

OK, WARN, ERROR = 0, 1, 2
"""Levels, as diagnostic_msgs/DiagnosticStatus numbers them."""



@dataclass(frozen=True)
class HealthLimits:
    """When the array counts as unhealthy (ns, fraction)."""

    silent_after_ns: int
    stale_after_ns: int
    max_drop_fraction: float


@dataclass
class Assessment:
    """One health report: level, one-line message, key/value details."""

    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)
    """Lines to log once (the synchroniser's window started being capped)."""


def _ms(ns: float) -> str:
    return f"{ns / 1e6:.3g}"


class ArrayHealth:
    """Per-sensor counters for one synchroniser; ``seen`` is the hot path, ``assess`` the report.

    ``sync``: a :class:`~magcal_ros.core.sync.StreamSynchronizer` (or an exact
    :class:`~magcal_ros.core.sync.SetSynchronizer`): its per-sensor periods and losses.
    """

    def __init__(self, names: tuple[str, ...], sync: Any, limits: HealthLimits, now_ns: int) -> None:
        self.names = names
        self.sync = sync
        self.limits = limits
        sync.set_pause(limits.silent_after_ns)
        n = len(names)
        self.received = [0] * n
        self._last = [0] * n
        self._heard = [now_ns] * n
        self._counted = [0] * n
        self._last_output = now_ns
        self._outputs = 0
        self._window: dict[str, int] = {"offered": 0, "dropped": 0}
        self._capped = False

    @property
    def lost(self) -> list[int]:
        """Samples lost before the node, per sensor (skipped sample indices)."""
        return [self.sync.lost(k) for k in range(len(self.names))]

    @property
    def gaps(self) -> list[int]:
        """Runs of lost samples, per sensor."""
        return [self.sync.gaps(k) for k in range(len(self.names))]

    def seen(self, index: int, stamp_ns: int) -> None:
        """Count one message of sensor ``index`` (call before the synchroniser sees it)."""
        self.received[index] += 1
        last = self._last[index]
        if stamp_ns > last or (stamp_ns and last - stamp_ns > self.sync.restart_ns):
            self._last[index] = stamp_ns  # newest stamp (a restart starts a new sequence)

    def _placed_last(self) -> list[int]:
        """Each sensor's newest stamp (ns) on the common time line: a sensor whose driver restarted (stamps
        jumped back) and was placed where it belongs is not behind the others (0: none yet)."""
        sync = self.sync
        if hasattr(sync, "placements"):
            bases = [b for b, _ in sync.placements() or [(0, None)] * len(self._last)]
        else:
            bases = [s.base for s in getattr(sync, "streams", ())] or [0] * len(self._last)
        return [last + base if last else 0 for last, base in zip(self._last, bases)]

    def output(self, count: int, now_ns: int) -> None:
        """Outputs so far (sets published or collected), at node time ``now_ns``."""
        if count != self._outputs:
            self._outputs, self._last_output = count, now_ns

    def _cap(self) -> tuple[str | None, str | None]:
        """(diagnostic text, log line once) when the synchroniser caps its window."""
        sync = self.sync
        window, tol = sync.effective_tolerance_ns, sync.tolerance_ns
        if window >= tol or not sync.min_period_ns:
            self._capped = False
            return None, None
        rate = NS_PER_S / sync.min_period_ns
        text = (f"sync window capped at {_ms(window)} ms (sync_tolerance {_ms(tol)} ms is more than half "
                f"the {rate:.0f} Hz sample period)")
        first = not self._capped
        self._capped = True
        line = (f"{text}: sets are matched within {_ms(window)} ms; set sync_tolerance to at most "
                f"{_ms(window)} ms to silence this") if first else None
        return text, line

    def assess(self, now_ns: int, counters: dict[str, int], output_what: str, extra: str | None = None) -> Assessment:
        """The report at node time ``now_ns``; ``counters``: SyncStats counters (messages)."""
        lim = self.limits
        problems: list[tuple[int, str]] = []
        values: dict[str, str] = {}
        silent, late = [], []
        lost_by = self.lost
        placed = self._placed_last()
        newest = max(placed) if any(self._last) else 0
        for k, name in enumerate(self.names):
            if self.received[k] != self._counted[k]:
                self._counted[k], self._heard[k] = self.received[k], now_ns
            quiet = now_ns - self._heard[k]
            if quiet > lim.silent_after_ns:
                silent.append(f"{name} ({quiet / NS_PER_S:.1f} s)")
            elif self._last[k] and newest - placed[k] > lim.silent_after_ns:
                late.append(f"{name} ({(newest - placed[k]) / NS_PER_S:.1f} s behind)")
            period = self.sync.period_ns(k)
            values[f"{name}.received"] = str(self.received[k])
            values[f"{name}.lost"] = str(lost_by[k])
            values[f"{name}.gaps"] = str(self.sync.gaps(k))
            values[f"{name}.period_ms"] = _ms(period) if period else ""
        if now_ns - self._last_output > lim.stale_after_ns:
            what = f"no {output_what} for {(now_ns - self._last_output) / NS_PER_S:.1f} s"
            problems.append((ERROR, what + (f" ({extra})" if extra else "")))
        elif extra:
            problems.append((WARN, extra))
        if silent:
            problems.append((WARN, "silent: " + ", ".join(silent)))
        if late:
            problems.append((WARN, "late: " + ", ".join(late)))
        lost = sum(lost_by)
        dropped = sum(counters.get(k, 0) for k in DROP_FIELDS)
        offered = sum(self.received) + counters.get("malformed", 0) + lost
        window_offered = offered - self._window["offered"]
        window_dropped = dropped + lost - self._window["dropped"]
        self._window = {"offered": offered, "dropped": dropped + lost}
        if window_offered > 0 and window_dropped > lim.max_drop_fraction * window_offered:
            named = [f"{n} {c}" for n, c in zip(self.names, lost_by) if c]
            # Drops are decided a little after their messages arrive: never more than what came.
            fraction = min(window_dropped, window_offered) / window_offered
            problems.append((WARN, f"dropping {fraction:.1%} of messages"
                             + (f" (lost before the node, total: {', '.join(named)})" if named else "")))
        cap, line = self._cap()
        if cap:
            problems.append((WARN, cap))
        values.update({k: str(v) for k, v in counters.items()})
        values["lost"] = str(lost)
        values["sync_tolerance_ms"] = _ms(self.sync.tolerance_ns)
        values["sync_window_ms"] = _ms(self.sync.effective_tolerance_ns)
        values["sync_mode"] = str(getattr(self.sync, "mode", "exact") or "choosing")
        level = max((lv for lv, _ in problems), default=OK)
        message = "; ".join(text for _, text in problems) if problems else "ok"
        return Assessment(level, message, values, [line] if line else [])


def _duration(ns: int) -> str:
    """``500 ms`` below a second, ``10 s`` from a second on."""
    return f"{_ms(ns)} ms" if ns < NS_PER_S else f"{ns / NS_PER_S:.3g} s"


class StreamHealth:
    """Sets met without a fresh value of a side stream (a current channel, a sensor's temperature, the
    IMU; see :mod:`magcal_ros.core.matching`): counted per stream, shown as ``<name>.stale_<noun>``
    and a WARN naming the stream and its topic in the period it happens."""

    NOUN = "value"
    """What the stream carries, in keys and messages."""
    UNIT = ""
    """Suffix of the key of the newest value (``<name>.<noun>_<unit>``); empty: no such key."""
    STALE_KEY = "{name}.stale_{noun}"
    RECEIVED_KEY = "{name}.{noun}_received"
    DROPPED_KEY = "{name}.{noun}_{cause}"
    """Samples that were no value, by cause (``out_of_range``, ``glitch``: far off the stream's stamps,
    ``nonfinite``)."""

    def __init__(self, names: tuple[str, ...], topics: tuple[str, ...], tolerance_ns: int) -> None:
        self.channels = names
        self.topics = topics
        self.tolerance_ns = tolerance_ns
        self.stale = [0] * len(names)
        self._reported = [0] * len(names)
        self._dropped = [0] * len(names)

    def count(self, fresh: list[bool]) -> bool:
        """Count one set (``fresh`` per stream); True when every stream is fresh."""
        ok = True
        for j, f in enumerate(fresh):
            if not f:
                self.stale[j] += 1
                ok = False
        return ok

    def assess(self, store: Any, what: str) -> tuple[str | None, dict[str, str]]:
        """(WARN text naming the streams that were stale, or dropped samples, since the last call, or None;
        values).

        ``store``: the streams' live store (values kept per stream ``received``, the newest value by
        ``latest(j)``, what each stream's samples came to ``counts``: :mod:`~magcal_ros.core.side_streams`);
        ``what``: what happened to stale sets (``withheld``, ``not collected``)."""
        received, counts = _per_stream(store.received), _per_stream(store.counts)
        values: dict[str, str] = {}
        late, bad = [], []
        noun = self.NOUN
        for j, name in enumerate(self.channels):
            values[self.STALE_KEY.format(name=name, noun=noun)] = str(self.stale[j])
            values[self.RECEIVED_KEY.format(name=name, noun=noun)] = str(received[j])
            c = counts[j]
            for cause in ("out_of_range", "glitch", "nonfinite"):
                values[self.DROPPED_KEY.format(name=name, noun=noun, cause=cause)] = str(getattr(c, cause))
            if self.UNIT:
                latest = store.latest(j)
                values[f"{name}.{noun}_{self.UNIT}"] = "" if latest is None else f"{latest:.6g}"
            new = self.stale[j] - self._reported[j]
            if new:
                never = " (none received yet)" if not received[j] else ""
                late.append(f"{name} on {self.topics[j]}{never}: {new} sets")
            dropped = c.dropped() - self._dropped[j]
            if dropped:
                bad.append(f"{dropped} of {name} on {self.topics[j]} ({c.describe(name).split('(')[-1].rstrip(')')})")
        self._reported = list(self.stale)
        self._dropped = [c.dropped() for c in counts]
        parts = []
        if late:
            parts.append(f"stale {noun} (no value within {_duration(self.tolerance_ns)} before the set), sets {what}: "
                         + ", ".join(late))
        if bad:
            parts.append(f"{noun} samples dropped: " + ", ".join(bad))
        return ("; ".join(parts) or None), values


def _per_stream(x: Any) -> list[Any]:
    """A store's per-stream list (a single stream's value as a list of one)."""
    return list(x) if isinstance(x, list) else [x]


class CurrentHealth(StreamHealth):
    """Sets met without a fresh current, per interference channel (see
    :class:`~magcal_ros.core.interference.LatestCurrents`): counted, shown as
    ``<channel>.stale_current`` (``current_received``, ``current_A``) and a WARN naming the channel
    in the period it happens."""

    NOUN = "current"
    UNIT = "A"


class TemperatureHealth(StreamHealth):
    """Sets met without a fresh temperature, per sensor: ``<name>.stale_temperature``
    (``temperature_received``, ``temperature_C``) and a WARN naming the sensor and its topic."""

    NOUN = "temperature"
    UNIT = "C"


class ImuHealth(StreamHealth):
    """Sets met without an IMU sample (the stream named ``imu``): ``imu.stale``, ``imu.received`` and a WARN
    naming the topic."""

    NOUN = "IMU"
    STALE_KEY = "{name}.stale"
    RECEIVED_KEY = "{name}.received"
    DROPPED_KEY = "{name}.{cause}"


class TemperatureSpanHealth:
    """Sets corrected more than :data:`~magcal_ros.core.temperature.TEMPERATURE_MARGIN` outside the
    temperatures the calibration was made at (``<name>.calibration_temperatures``), per sensor: shown as
    ``<name>.temperature_beyond_calibration`` (sets so far), ``<name>.temperature_beyond_calibration_K``
    (the farthest outside, K) and ``<name>.calibration_temperatures_C`` (``min..max``) for every sensor
    whose span is known, and a WARN naming the sensors in the period it happens. ``span`` None (a
    calibration that does not record it): no key, nothing said."""

    def __init__(self, names: tuple[str, ...], span: Any) -> None:
        from magcal_ros.core.temperature import SpanExcursions  # (numpy only)

        self.watch = None if span is None else SpanExcursions(names, span)
        self._reported = [0] * len(names)

    def count(self, values: Any, fresh: Any) -> list[str]:
        """Count one set's temperatures (S,) deg C (``fresh`` per sensor); the sensors beyond for the first time."""
        return [] if self.watch is None else self.watch.add_one(values, fresh)

    def assess(self) -> tuple[str | None, dict[str, str]]:
        """(WARN text naming the sensors with sets beyond since the last call, or None; values)."""
        w = self.watch
        if w is None:
            return None, {}
        values: dict[str, str] = {}
        new = []
        for i, name in enumerate(w.names):
            lo, hi = w.span[i]
            if math.isnan(lo):  # unknown for this sensor
                continue
            values[f"{name}.temperature_beyond_calibration"] = str(int(w.counts[i]))
            values[f"{name}.temperature_beyond_calibration_K"] = f"{max(w.below[i], w.above[i]):.3g}"
            values[f"{name}.calibration_temperatures_C"] = f"{lo:.1f}..{hi:.1f}"
            if w.counts[i] > self._reported[i]:
                new.append(w.describe(i))
        self._reported = [int(c) for c in w.counts]
        if not new:
            return None, values
        return (f"beyond the calibrated temperatures (more than {w.margin:g} K): " + "; ".join(new)), values

"""Whether exact matching, chosen from a recording's first stamps, still holds: the choice revised.

Mode ``auto`` chooses exact matching when the first stamps of every sensor coincide
(:func:`~magcal_ros.core.sync.choose_mode`). Stamps can mislead: two sensors on clocks a
hundred parts per million apart coincide at first and drift a millisecond apart in ten seconds;
stamps jittered near the edge of the window fit it in the first 32 and not later. The exact rule
would then drop the sets it cannot match, in silence. :class:`ExactMonitor` judges the sets the
exact rule forms, in blocks of :data:`EVENTS`: a block in which some sensor's stamps sit off the
reference's by more than a quarter of the window in the median (unless the field jumps between
samples, as for the first choice), or in which more than :data:`WIDE_FRACTION` of the sets spread
over more than :data:`WIDE` of the window (their spreads reach its edge: about a tenth or more of the
sets would not fit it), ends exact matching:
the synchroniser interpolates from there on and says why.

The monitor sees only the sets, which are the same live and offline, so a recording switches at the
same set on both paths.
"""

from __future__ import annotations

from collections.abc import Sequence

EVENTS: int = 64
"""Sets in a block the monitor judges."""
WIDE: float = 0.9
"""A set spread over more than this fraction of the window is at its edge ..."""
WIDE_FRACTION: float = 0.05
"""... and a block with more such sets than this fraction ends exact matching."""


class ExactMonitor:
    """Judges the exact rule's sets block by block (module docstring). ``names`` name the sensors in
    :attr:`reason`; ``coarse``: the field jumps between samples (a systematic offset then does not
    call for interpolation)."""

    def __init__(self, names: Sequence[str], coarse: bool = False) -> None:
        self.names = list(names)
        self.coarse = coarse
        self.events = 0
        self.wide = 0
        self.offsets: list[list[int]] = [[] for _ in self.names]
        """Per sensor, its stamp less the reference's (ns) in the block's sets."""
        self.reason: str | None = None
        """Why exact matching ended (None while it holds)."""

    @property
    def room(self) -> int:
        """Sets left in the current block."""
        return EVENTS - self.events

    def formed(self, stamps: Sequence[Sequence[int]], window: int) -> None:
        """Sets formed: ``stamps[k]`` the common stamps (ns) of sensor ``k`` in them (at most :attr:`room`
        sets), under the exact ``window`` (ns)."""
        ref = stamps[0]
        low, high = list(ref), list(ref)
        for k in range(1, len(stamps)):
            self.offsets[k].extend(t - r for t, r in zip(stamps[k], ref))
            low = [min(a, b) for a, b in zip(low, stamps[k])]
            high = [max(a, b) for a, b in zip(high, stamps[k])]
        self._judged(len(ref), sum(b - a > WIDE * window for a, b in zip(low, high)), window)

    def missed(self, stamps: Sequence[int], window: int) -> None:
        """A set the exact rule could not form although its sensors' next stamps (``stamps[k]`` of sensor ``k``,
        ns) lie within half a sample period of each other: one instant beyond the ``window`` (ns), a set at its
        edge (counted as one). Without it a clock that drifted past the window within a block formed no more
        sets, and the block that would have ended exact matching was never whole. Judged at once when the block
        already holds more sets at the edge than a whole block may (each miss is a set lost; the sets formed are
        counted in runs, so only a miss, one at a time on both paths, ends a block early)."""
        for k in range(1, len(stamps)):
            self.offsets[k].append(stamps[k] - stamps[0])
        self._judged(1, 1, window, early=self.wide + 1 > WIDE_FRACTION * EVENTS)

    def _judged(self, events: int, wide: int, window: int, early: bool = False) -> None:
        """Count ``events`` sets, ``wide`` of them at the window's edge; judge the block once it is whole (or
        ``early``)."""
        self.wide += wide
        self.events += events
        if self.events >= EVENTS or early:
            self.reason = self._judge(window)
            self.events = self.wide = 0
            self.offsets = [[] for _ in self.names]

    def _judge(self, window: int) -> str | None:
        if self.wide > WIDE_FRACTION * self.events:
            return (f"{self.wide} of {self.events} sets at the edge of the {window / 1e6:.3g} ms window: the stamps do "
                    "not coincide")
        if self.coarse:
            return None
        for k in range(1, len(self.names)):
            v = sorted(self.offsets[k])
            if not v:
                continue
            middle = v[len(v) // 2]
            if 4 * abs(middle) > window:
                return f"{self.names[k]}'s stamps moved to {middle / 1e6:.3g} ms after {self.names[0]}'s (median)"
        return None

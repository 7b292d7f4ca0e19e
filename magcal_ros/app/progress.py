"""A progress bar on stderr for long offline runs: done/total, rate and time left.

Silent when the stream is not a terminal (pipes, logs, CI) or when asked to be quiet,
so scripted use sees only the final summary.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def _clock(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def _si(value: float) -> str:
    for unit, scale in (("M", 1e6), ("k", 1e3)):
        if value >= scale:
            return f"{value / scale:.1f}{unit}"
    return f"{value:.0f}"


class ProgressBar:
    """Counts work items and redraws one line at most ``interval`` seconds apart.

    Use as a callable (``bar(n)`` adds ``n`` items) and a context manager.
    """

    def __init__(
        self,
        total: int | None,
        label: str = "",
        unit: str = "msg",
        stream: TextIO | None = None,
        enabled: bool | None = None,
        interval: float = 0.2,
        width: int = 28,
    ) -> None:
        """``enabled`` None: draw only when ``stream`` is a terminal."""
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            enabled = bool(isatty and isatty())
        self.enabled = enabled
        self.total = total if total and total > 0 else None
        self.label = label
        self.unit = unit
        self.interval = interval
        self.width = width
        self.done = 0
        self.start = time.monotonic()
        self._last = 0.0
        self._drawn = False

    def set_total(self, total: int | None) -> None:
        """Set or change the expected number of items (e.g. once a bag's metadata is read)."""
        self.total = total if total and total > 0 else None

    def __call__(self, n: int = 1) -> None:
        """Add ``n`` finished items."""
        self.done += n
        if self.enabled:
            now = time.monotonic()
            if now - self._last >= self.interval:
                self._last = now
                self._draw(now)

    def line(self, now: float | None = None) -> str:
        """The text of the bar for the current count."""
        now = time.monotonic() if now is None else now
        elapsed = max(now - self.start, 1e-9)
        rate = self.done / elapsed
        head = f"{self.label} " if self.label else ""
        if self.total:
            frac = min(1.0, self.done / self.total)
            fill = int(round(frac * self.width))
            left = (self.total - self.done) / rate if rate > 0 else float("inf")
            eta = _clock(left) if left != float("inf") else "?"
            return (
                f"{head}[{'#' * fill}{'.' * (self.width - fill)}] {frac:4.0%} "
                f"{_si(self.done)}/{_si(self.total)} {self.unit}  {_si(rate)} {self.unit}/s  "
                f"elapsed {_clock(elapsed)}  left {eta}"
            )
        return f"{head}{_si(self.done)} {self.unit}  {_si(rate)} {self.unit}/s  elapsed {_clock(elapsed)}"

    def _draw(self, now: float) -> None:
        self.stream.write("\r" + self.line(now) + "\x1b[K")
        self.stream.flush()
        self._drawn = True

    def clear(self) -> None:
        """Erase the drawn bar so a line of other output can be printed; the next update redraws it."""
        if self.enabled and self._drawn:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self._drawn = False

    def close(self) -> None:
        """Draw the final state and end the line (only if anything was drawn)."""
        if self.enabled and self._drawn:
            self._draw(time.monotonic())
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc: object) -> None:
        if exc[0] is not None and self.enabled and self._drawn:
            self.stream.write("\n")  # leave the error message on its own line
            self.stream.flush()
            self._drawn = False
            return
        self.close()

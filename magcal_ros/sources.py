"""Open a recording from a path: CSV file or rosbag2 directory (sqlite3 or mcap)."""

from __future__ import annotations

import os
from pathlib import Path

from magcal_ros.errors import InputError
from magcal_ros.recording import Recording, read_csv


def is_csv(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` names a CSV recording (by its ``.csv`` ending)."""
    return str(path).lower().endswith(".csv")


def read_recording(
    path: str | os.PathLike[str],
    names: tuple[str, ...] | None = None,
    start: float | None = None,
    end: float | None = None,
) -> Recording:
    """Synchronized raw sets from ``path``, restricted to sensors ``names`` and a time window."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p} does not exist")
    if is_csv(p):
        rec = read_csv(p)
        if names:
            rec = rec.select(tuple(names))
    else:
        from magcal_ros.bagio import read_bag_recording

        rec = read_bag_recording(p, names)
    rec = rec.window(start, end)
    if len(rec) == 0:
        raise InputError(f"{p}: no synchronized sets in the selected time window")
    return rec

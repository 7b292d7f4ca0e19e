"""Open a recording from a path: CSV file or rosbag2 directory (sqlite3 or mcap)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from magcal_ros.errors import InputError
from magcal_ros.recording import Recording, read_csv

if TYPE_CHECKING:
    from magcal_ros.sync import SyncStats


def is_csv(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` names a CSV recording (by its ``.csv`` ending)."""
    return str(path).lower().endswith(".csv")


def read_recording(path: str | os.PathLike[str], **options: Any) -> Recording:
    """Synchronized raw sets from ``path`` (options as :func:`open_recording`)."""
    return open_recording(path, **options)[0]


def open_recording(
    path: str | os.PathLike[str],
    names: tuple[str, ...] | None = None,
    start: float | None = None,
    end: float | None = None,
    tolerance: float | None = None,
    nonfinite: str = "drop",
    progress: Callable[[int], None] | None = None,
) -> tuple[Recording, SyncStats | None]:
    """Synchronized raw sets from ``path``, restricted to sensors ``names`` and a time window.

    CSV rows are sets already (NaN rows are an error); bag topics ``/<name>/raw`` are
    synchronised by header stamp within ``tolerance`` seconds (default
    :data:`magcal_ros.bagio.DEFAULT_SYNC_TOLERANCE`), and sets with NaN readings are
    dropped (``nonfinite="drop"``) or refused (``"error"``). ``start``/``end`` in seconds.
    Also returns the bag's synchronisation counters (None for CSV).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p} does not exist")
    if is_csv(p):
        if p.is_dir():
            raise InputError(f"{p} is a directory, not a CSV file")
        stats = None
        try:
            rec = read_csv(p)
        except InputError as exc:
            raise (exc if str(p) in str(exc) else InputError(f"{p}: {exc}")) from None
        if names:
            rec = rec.select(tuple(names))
    else:
        from magcal_ros.bagio import DEFAULT_SYNC_TOLERANCE, read_bag_sets

        if p.is_file() and p.suffix not in (".db3", ".mcap"):
            raise InputError(f"{p}: not a recording: give a rosbag2 directory or a .csv file")
        tol = DEFAULT_SYNC_TOLERANCE if tolerance is None else tolerance
        rec, stats = read_bag_sets(p, names, tolerance=tol, nonfinite=nonfinite, progress=progress)  # type: ignore[arg-type]
    rec = rec.window(start, end)
    if len(rec) == 0:
        raise InputError(f"{p}: no synchronized sets in the selected time window")
    return rec, stats

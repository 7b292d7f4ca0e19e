"""A recording of synchronized raw sets, and its CSV form.

CSV layout (INTERFACES.md): header ``stamp,mag1.x,mag1.y,mag1.z,mag2.x,...``; stamp in
seconds, fields in Tesla, one synchronized set per row.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.atomic import atomic_path
from magcal_ros.errors import InputError

Array = NDArray[np.float64]
AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True)
class Recording:
    """Synchronized sets: ``stamps`` (N,) s, ``vectors`` (N, S, 3) T, sensor ``names`` (S)."""

    names: tuple[str, ...]
    stamps: Array
    vectors: Array

    def __post_init__(self) -> None:
        v = np.asarray(self.vectors, dtype=float)
        t = np.asarray(self.stamps, dtype=float).reshape(-1)
        if v.ndim != 3 or v.shape[1:] != (len(self.names), 3) or len(t) != len(v):
            raise InputError(
                f"recording needs stamps (N,) and vectors (N, {len(self.names)}, 3), got {t.shape} and {v.shape}"
            )
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "stamps", t)
        object.__setattr__(self, "vectors", v)

    def __len__(self) -> int:
        return len(self.stamps)

    def select(self, names: tuple[str, ...] | list[str]) -> "Recording":
        """The same sets restricted to (and ordered as) ``names``."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise InputError(f"recording has no sensor {', '.join(missing)} (it has {', '.join(self.names)})")
        idx = [self.names.index(n) for n in names]
        return Recording(tuple(names), self.stamps, self.vectors[:, idx])

    def window(self, start: float | None = None, end: float | None = None) -> "Recording":
        """Sets with ``start <= stamp <= end`` (seconds, either bound optional)."""
        keep = np.ones(len(self), bool)
        if start is not None:
            keep &= self.stamps >= start
        if end is not None:
            keep &= self.stamps <= end
        return Recording(self.names, self.stamps[keep], self.vectors[keep])


def csv_header(names: tuple[str, ...] | list[str], suffixes: tuple[str, ...] = AXIS_NAMES) -> list[str]:
    """Header row: ``stamp`` then ``<name>.<suffix>`` per sensor."""
    return ["stamp"] + [f"{n}.{a}" for n in names for a in suffixes]


def parse_header(header: list[str]) -> tuple[str, ...]:
    """Sensor names of a CSV header; :class:`InputError` if it is not the contract's layout."""
    if not header or header[0].strip() != "stamp":
        raise InputError("CSV header must start with 'stamp' (then mag1.x,mag1.y,mag1.z,...)")
    cols = [c.strip() for c in header[1:]]
    if len(cols) == 0 or len(cols) % 3:
        raise InputError(f"CSV needs 3 columns per sensor after 'stamp', got {len(cols)}")
    names = []
    for k in range(0, len(cols), 3):
        stem = cols[k].rsplit(".", 1)[0]
        if [c for c in cols[k : k + 3]] != [f"{stem}.{a}" for a in AXIS_NAMES]:
            raise InputError(f"CSV columns {cols[k:k + 3]} must be {stem}.x,{stem}.y,{stem}.z")
        names.append(stem)
    return tuple(names)


def read_csv(path: str | os.PathLike[str]) -> Recording:
    """Read a CSV recording; non-finite values, ragged rows or an empty file are errors."""
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            text = fh.read()
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path} is not a text CSV file") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{path} is empty: expected a header 'stamp,mag1.x,...' and data rows")
    names = parse_header(rows[0])
    width = 1 + 3 * len(names)
    if len(rows) == 1:
        raise InputError(f"{path} has a header but no data rows")
    data = np.empty((len(rows) - 1, width))
    for i, row in enumerate(rows[1:], start=2):
        if len(row) != width:
            raise InputError(f"{path} line {i}: {len(row)} columns, header has {width}")
        try:
            data[i - 2] = [float(c) for c in row]
        except ValueError:
            raise InputError(f"{path} line {i}: non-numeric value") from None
        if not np.all(np.isfinite(data[i - 2])):
            raise InputError(f"{path} line {i}: NaN or infinite value")
    return Recording(names, data[:, 0], data[:, 1:].reshape(len(data), len(names), 3))


def format_rows(stamps: Array, columns: Array) -> str:
    """CSV body lines for ``stamps`` (N,) and ``columns`` (N, K), full double precision."""
    table = np.column_stack([stamps, columns])
    buf = io.StringIO()
    np.savetxt(buf, table, delimiter=",", fmt="%.17g")
    return buf.getvalue()


def write_csv(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write ``recording`` atomically as CSV."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(csv_header(recording.names)) + "\n")
            fh.write(format_rows(recording.stamps, recording.vectors.reshape(len(recording), -1)))

"""CSV recordings: raw sets in, corrected sets out.

Raw layout: header ``stamp,mag1.x,mag1.y,mag1.z,mag2.x,...``; stamp in decimal seconds,
fields in Tesla, one synchronized set per row; optionally, after the sensor columns, one
column ``current.<channel>`` per interference channel (A, the channel's current at the set). Stamps are parsed and written exactly as
decimal digits (9 decimals on output), never through a float, so nanoseconds survive.

Rows go through the same acceptance rule as bag messages
(:mod:`magcal_ros.core.sync`): a row whose stamp is 0, repeats or goes back is dropped
and counted, a row with a NaN or infinite value (a current included) is refused or
dropped like a bag's.

Corrected layout (``magcal correct``): ``stamp``, ``<name>.x,<name>.y,<name>.z`` per
sensor (T, platform frame), ``field.x,field.y,field.z`` (centre field, T), then what the
array's positions determine: ``gradient.xx, gradient.xy, ..., gradient.zz``
(``gradient.ij = dB_j/dx_i``, T/m; three or more sensors), ``baseline_gradient.x,y,z``
(``dB_j/ds`` along the line, T/m; two or more collinear sensors), or nothing (one sensor).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.calibration import CorrectedSets
from magcal_ros.core.acceptance import reading_faults
from magcal_ros.core.geometry import check_names
from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import format_seconds_column, parse_seconds
from magcal_ros.core.sync import SetSynchronizer, SyncStats
from magcal_ros.core.units import MAX_READING, check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io.atomic import atomic_path

AXIS_NAMES: tuple[str, ...] = ("x", "y", "z")
TENSOR_COLUMNS: tuple[str, ...] = tuple(f"gradient.{i}{j}" for i in AXIS_NAMES for j in AXIS_NAMES)
FIELD_COLUMNS: tuple[str, ...] = tuple(f"field.{a}" for a in AXIS_NAMES)
BASELINE_COLUMNS: tuple[str, ...] = tuple(f"baseline_gradient.{a}" for a in AXIS_NAMES)
CURRENT_PREFIX = "current."
"""Columns ``current.<channel>``: a channel's current (A)."""
NonFinite = Literal["drop", "error"]


def csv_header(names: Sequence[str], suffixes: tuple[str, ...] = AXIS_NAMES) -> list[str]:
    """Header row: ``stamp`` then ``<name>.<suffix>`` per sensor."""
    return ["stamp"] + [f"{n}.{a}" for n in names for a in suffixes]


def corrected_header(names: Sequence[str], gradient: str = "tensor") -> list[str]:
    """``stamp, <name>.x.., field.x..`` then ``gradient.xx..gradient.zz`` (``tensor``),
    ``baseline_gradient.x..z`` (``baseline``) or nothing (``none``: one sensor)."""
    extra = {"tensor": TENSOR_COLUMNS, "baseline": BASELINE_COLUMNS, "none": ()}[gradient]
    return csv_header(list(names)) + list(FIELD_COLUMNS) + list(extra)


def parse_header(header: list[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Sensor names and current channels of a CSV header; :class:`InputError` if it is not
    the contract's layout (``stamp``, three columns per sensor, then ``current.<channel>``)."""
    if header:
        header = [header[0].lstrip("\ufeff")] + header[1:]  # a byte order mark is not a column name
    if not header or header[0].strip() != "stamp":
        raise InputError("CSV header must start with 'stamp' (then mag1.x,mag1.y,mag1.z,...)")
    cols = [c.strip() for c in header[1:]]
    sensors = len(cols)
    for k, c in enumerate(cols):  # the first current column no sensor triple claims
        if c.startswith(CURRENT_PREFIX) and k % 3 == 0:
            stem = c.rsplit(".", 1)[0]
            if cols[k : k + 3] != [f"{stem}.{a}" for a in AXIS_NAMES]:
                sensors = k
                break
    sensor_cols, current_cols = cols[:sensors], cols[sensors:]
    if len(sensor_cols) == 0 or len(sensor_cols) % 3:
        raise InputError(f"CSV needs 3 columns per sensor after 'stamp' (then current.<channel> columns), "
                         f"got {len(sensor_cols)}")
    names = []
    for k in range(0, len(sensor_cols), 3):
        stem = sensor_cols[k].rsplit(".", 1)[0]
        if sensor_cols[k : k + 3] != [f"{stem}.{a}" for a in AXIS_NAMES]:
            raise InputError(f"CSV columns {sensor_cols[k:k + 3]} must be {stem}.x,{stem}.y,{stem}.z")
        names.append(stem)
    check_names(names)
    channels = tuple(c[len(CURRENT_PREFIX):] for c in current_cols)
    bad = [c for c in current_cols if not c.startswith(CURRENT_PREFIX) or not c[len(CURRENT_PREFIX):]]
    if bad:
        raise InputError(f"CSV column {bad[0]!r} after the current columns: only current.<channel> columns "
                         "(amperes) may follow the sensor columns")
    if len(set(channels)) != len(channels):
        raise InputError(f"CSV names a current channel twice: {', '.join(current_cols)}")
    return tuple(names), channels


def _read_text(path: str | os.PathLike[str], header_only: bool = False) -> str:
    """The text of a CSV file (a UTF-8 byte order mark dropped), or up to its first non-blank line."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            if not header_only:
                return fh.read()
            line = fh.readline()
            while line and not line.strip(" \t\r\n,"):
                line = fh.readline()
            return line
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path} is not a text CSV file") from None


def _rows(text: str) -> list[list[str]]:
    """Non-blank rows; LF, CRLF and CR-only (classic Mac) line endings alike."""
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    try:
        return [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    except csv.Error as exc:
        raise InputError(f"not a readable CSV file ({exc})") from None


def read_csv_names(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """Sensor names of a CSV recording, from its header alone."""
    text = _read_text(path, header_only=True)
    try:
        rows = _rows(text)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    if not rows:
        raise InputError(f"{path} is empty: expected a header 'stamp,mag1.x,...' and data rows")
    try:
        return parse_header(rows[0])[0]
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def read_csv(path: str | os.PathLike[str], nonfinite: NonFinite = "error") -> tuple[Recording, SyncStats]:
    """Read a CSV recording and the counts of rows it dropped (per message, as for a bag).

    Ragged rows, text values or an empty file are :class:`InputError`; NaN or infinite
    values are refused (``nonfinite="error"``) or their rows dropped (``"drop"``).
    """
    text = _read_text(path)
    try:
        rows = _rows(text)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    if not rows:
        raise InputError(f"{path} is empty: expected a header 'stamp,mag1.x,...' and data rows")
    try:
        names, channels = parse_header(rows[0])
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    width = 1 + 3 * len(names) + len(channels)
    if len(rows) == 1:
        raise InputError(f"{path} has a header but no data rows")
    stamps = np.empty(len(rows) - 1, np.int64)
    data = np.empty((len(rows) - 1, width - 1))
    for i, row in enumerate(rows[1:], start=2):
        if len(row) != width:
            raise InputError(f"{path} line {i}: {len(row)} columns, header has {width}")
        try:
            stamps[i - 2] = parse_seconds(row[0])
        except InputError as exc:
            raise InputError(f"{path} line {i}: stamp: {exc}") from None
        try:
            data[i - 2] = [float(c) for c in row[1:]]
        except ValueError:
            raise InputError(f"{path} line {i}: non-numeric value") from None
        if nonfinite == "error" and not np.all(np.isfinite(data[i - 2])):
            raise InputError(f"{path} line {i}: NaN or infinite value (pass --drop-nonfinite to skip such rows)")
    vectors = data[:, : 3 * len(names)].reshape(len(data), len(names), 3)
    check_tesla(vectors, names, str(path))  # a file in nT is a units error, not readings out of range
    currents = data[:, 3 * len(names) :]
    # Each sensor's messages carry their row number (scaled into the accepted range of a
    # reading), so the sets the rule keeps name their rows (and so their currents); a faulty
    # reading goes in as it is, to be dropped and counted by the rule; a row with a
    # non-finite current is a non-finite row.
    scale = MAX_READING / 2 / max(len(data), 1)
    row = np.arange(len(data), dtype=float) * scale
    row_ok = np.all(np.isfinite(currents), axis=1)
    sync = SetSynchronizer(len(names), 0, max_pending=len(data) + 1, reject_zero=False, max_reading=MAX_READING)
    for k in range(len(names)):
        faulty = np.logical_or.reduce(list(reading_faults(vectors[:, k]).values()))
        tags = np.where(row_ok[:, None], np.stack([row, np.zeros_like(row), np.zeros_like(row)], axis=1), np.nan)
        sync.add_batch(k, stamps, np.where(faulty[:, None], vectors[:, k], tags))
    sets = sync.pop(final=True)
    if len(sets) == 0:
        raise InputError(f"{path}: no usable rows ({sync.stats.describe()})")
    rows_kept = np.rint(sets.vectors[:, 0, 0] / scale).astype(np.int64)
    return Recording(names, sets.set_stamps, vectors[rows_kept], channels, currents[rows_kept]), sync.stats


def format_rows(stamps: NDArray[np.int64], columns: NDArray[np.float64]) -> str:
    """CSV body lines: exact stamps (9 decimals) and ``columns`` (N, K) in full double precision."""
    buf = io.StringIO()
    np.savetxt(buf, np.asarray(columns, dtype=float), delimiter=",", fmt="%.17g")
    body = buf.getvalue().splitlines()
    return "".join(f"{t},{line}\n" for t, line in zip(format_seconds_column(stamps), body))


def write_csv(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write ``recording`` atomically as CSV (its currents as ``current.<channel>`` columns, A)."""
    header = csv_header(recording.names) + [CURRENT_PREFIX + c for c in recording.channels]
    columns = np.concatenate([recording.vectors.reshape(len(recording), -1), recording.currents], axis=1)  # type: ignore[list-item]
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(header) + "\n")
            fh.write(format_rows(recording.stamps, columns))


def write_corrected_csv(
    path: str | os.PathLike[str], stamps: NDArray[np.int64], names: Sequence[str], sets: CorrectedSets
) -> None:
    """Write corrected sets atomically (columns as :func:`corrected_header` for the array's gradient)."""
    n = len(stamps)
    parts = [sets.vectors.reshape(n, -1), sets.centre.reshape(n, 3)]
    kind = "none"
    if sets.tensor is not None:
        parts.append(sets.tensor.reshape(n, 9))
        kind = "tensor"
    elif sets.baseline is not None:
        parts.append(sets.baseline.reshape(n, 3))
        kind = "baseline"
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(corrected_header(names, kind)) + "\n")
            fh.write(format_rows(stamps, np.concatenate(parts, axis=1)))

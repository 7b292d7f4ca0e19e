"""CSV recordings: raw sets in, corrected sets out.

Raw layout: header ``stamp,mag1.x,mag1.y,mag1.z,mag2.x,...``; stamp in decimal seconds,
fields in Tesla, one synchronized set per row. After the sensor columns, in any order:

- ``current.<channel>``: an interference channel's current at the set (A);
- ``temperature.<name>``: a sensor's temperature (deg C), one per sensor, or a single
  ``temperature`` column for every sensor;
- ``imu.qx,imu.qy,imu.qz,imu.qw``: the IMU's orientation at the set, the quaternion of the
  rotation from the IMU frame to the world frame ENU as ``sensor_msgs/Imu`` gives it
  (``imu_frame="ned"``: to north-east-down, turned into ENU on reading); empty or NaN cells:
  unknown at that set;
- ``imu.wx,imu.wy,imu.wz``: the IMU's angular velocity (rad/s, IMU frame); empty or NaN:
  unknown.

Stamps are parsed and written exactly as decimal digits (9 decimals on output), never
through a float, so nanoseconds survive.

Rows go through the same acceptance rule as bag messages
(:mod:`magcal_ros.core.sync`): a row whose stamp is 0, repeats or goes back is dropped
and counted, a row with a NaN or infinite value (a current or a temperature included; an
IMU cell only means "unknown") is refused or dropped like a bag's.

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
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.calibration import CorrectedSets
from magcal_ros.core.acceptance import reading_faults
from magcal_ros.core.geometry import check_names
from magcal_ros.core.imu import imu_frame, ned_to_enu
from magcal_ros.core.recording import ImuSamples, Recording
from magcal_ros.core.stamps import format_seconds_column, parse_seconds, parse_seconds_column
from magcal_ros.core.sync import SetSynchronizer, SyncStats
from magcal_ros.core import side_streams as side
from magcal_ros.io.input_files import MAX_HEADER_BYTES, regular_file
from magcal_ros.core.interference import check_currents
from magcal_ros.core.parallel import as_array, fill_in_child
from magcal_ros.core.temperature import check_temperatures
from magcal_ros.core.units import MAX_READING, check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io.atomic import atomic_path

AXIS_NAMES: tuple[str, ...] = ("x", "y", "z")
TENSOR_COLUMNS: tuple[str, ...] = tuple(f"gradient.{i}{j}" for i in AXIS_NAMES for j in AXIS_NAMES)
FIELD_COLUMNS: tuple[str, ...] = tuple(f"field.{a}" for a in AXIS_NAMES)
BASELINE_COLUMNS: tuple[str, ...] = tuple(f"baseline_gradient.{a}" for a in AXIS_NAMES)
CURRENT_PREFIX = "current."
"""Columns ``current.<channel>``: a channel's current (A)."""
TEMPERATURE_PREFIX = "temperature."
"""Columns ``temperature.<name>``: a sensor's temperature (deg C)."""
TEMPERATURE_COLUMN = "temperature"
"""One column: the temperature (deg C) of every sensor."""
IMU_ORIENTATION_COLUMNS: tuple[str, ...] = ("imu.qx", "imu.qy", "imu.qz", "imu.qw")
"""The IMU's orientation quaternion x, y, z, w (IMU frame to world ENU)."""
IMU_RATE_COLUMNS: tuple[str, ...] = ("imu.wx", "imu.wy", "imu.wz")
"""The IMU's angular velocity (rad/s, IMU frame)."""
EXTRA_COLUMNS_HELP = ("current.<channel> (A), temperature.<name> or temperature (deg C), imu.qx,imu.qy,imu.qz,imu.qw "
                      "and imu.wx,imu.wy,imu.wz")
NonFinite = Literal["drop", "error"]


def csv_header(names: Sequence[str], suffixes: tuple[str, ...] = AXIS_NAMES) -> list[str]:
    """Header row: ``stamp`` then ``<name>.<suffix>`` per sensor."""
    return ["stamp"] + [f"{n}.{a}" for n in names for a in suffixes]


def corrected_header(names: Sequence[str], gradient: str = "tensor") -> list[str]:
    """``stamp, <name>.x.., field.x..`` then ``gradient.xx..gradient.zz`` (``tensor``),
    ``baseline_gradient.x..z`` (``baseline``) or nothing (``none``: one sensor)."""
    extra = {"tensor": TENSOR_COLUMNS, "baseline": BASELINE_COLUMNS, "none": ()}[gradient]
    return csv_header(list(names)) + list(FIELD_COLUMNS) + list(extra)


@dataclass(frozen=True)
class CsvLayout:
    """What the columns of a raw CSV hold (see the module docstring)."""

    names: tuple[str, ...]
    """Sensor names, three columns each, in header order."""
    extra: tuple[str, ...]
    """The columns after the sensor columns, in header order."""
    channels: tuple[str, ...]
    """Current channels, in header order."""
    temperatures: tuple[str, ...]
    """Sensors with a ``temperature.<name>`` column, or ``("",)`` for one ``temperature`` column, or ()."""

    def columns(self, names: Sequence[str]) -> list[int]:
        """Indices into :attr:`extra` of the columns ``names``."""
        return [self.extra.index(n) for n in names]

    @property
    def has_orientation(self) -> bool:
        """True when the IMU's orientation columns are there."""
        return IMU_ORIENTATION_COLUMNS[0] in self.extra

    @property
    def has_rate(self) -> bool:
        """True when the IMU's angular velocity columns are there."""
        return IMU_RATE_COLUMNS[0] in self.extra


def _extra_kind(column: str) -> str | None:
    """``current``, ``temperature`` or ``IMU`` for an extra column's name, else None."""
    if column.startswith(CURRENT_PREFIX):
        return "current"
    if column == TEMPERATURE_COLUMN or column.startswith(TEMPERATURE_PREFIX):
        return "temperature"
    if column in IMU_ORIENTATION_COLUMNS or column in IMU_RATE_COLUMNS:
        return "IMU"
    return None


def _sensor_columns(cols: list[str]) -> int:
    """How many of ``cols`` are sensor columns: up to the first extra column no sensor triple claims."""
    for k, c in enumerate(cols):
        if k % 3 == 0 and _extra_kind(c) is not None:
            stem = c.rsplit(".", 1)[0]
            if cols[k : k + 3] != [f"{stem}.{a}" for a in AXIS_NAMES]:
                return k
    return len(cols)


def _sensor_names(sensor_cols: list[str]) -> list[str]:
    """The sensor names of the ``<name>.x,<name>.y,<name>.z`` triples, refused if they are not triples."""
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
    return names


def _check_extra(extra: list[str]) -> None:
    """Refuse an extra column of no known kind, or one named twice."""
    first = _extra_kind(extra[0]) if extra else None
    for c in extra:
        kind = _extra_kind(c)
        if kind is None or c in (CURRENT_PREFIX, TEMPERATURE_PREFIX):
            raise InputError(f"CSV column {c!r} after the {first} columns: only {EXTRA_COLUMNS_HELP} columns may "
                             "follow the sensor columns")
    twice = sorted({c for c in extra if extra.count(c) > 1})
    if twice:
        kind = _extra_kind(twice[0])
        what = {"current": "a current channel", "temperature": "a temperature", "IMU": "an IMU column"}[kind or "IMU"]
        raise InputError(f"CSV names {what} twice: {', '.join(c for c in extra if c == twice[0])}")


def _check_imu_columns(extra: list[str]) -> None:
    """Refuse an IMU given in part (some of its orientation or rate columns)."""
    for group in (IMU_ORIENTATION_COLUMNS, IMU_RATE_COLUMNS):
        present = [c for c in group if c in extra]
        if present and len(present) != len(group):
            raise InputError(f"CSV has {', '.join(present)} but not {', '.join(c for c in group if c not in extra)}: "
                             f"the IMU needs all of {','.join(group)}")


def _temperature_names(extra: list[str], names: list[str]) -> tuple[str, ...]:
    """The sensors with a temperature column (``("",)``: one column for all), refused unless every
    sensor has one or there is one for all."""
    temps = tuple(c[len(TEMPERATURE_PREFIX):] for c in extra if c.startswith(TEMPERATURE_PREFIX))
    if TEMPERATURE_COLUMN in extra:
        if temps:
            raise InputError("CSV has a 'temperature' column for every sensor and temperature.<name> columns: give one "
                             "or the other")
        return ("",)
    strangers = [t for t in temps if t not in names]
    if strangers:
        raise InputError(f"CSV column temperature.{strangers[0]}: no sensor {strangers[0]} (sensors: {', '.join(names)})")
    missing = [n for n in names if n not in temps]
    if temps and missing:
        raise InputError(f"CSV has the temperature of {', '.join(temps)} but not of {', '.join(missing)}: give "
                         "temperature.<name> for every sensor, or one 'temperature' column for all")
    return temps


def parse_columns(header: list[str]) -> CsvLayout:
    """The layout of a raw CSV header; :class:`InputError` (one line) if it is not the contract's
    (``stamp``, three columns per sensor, then the extra columns of the module docstring in any order)."""
    if header:
        header = [header[0].lstrip("\ufeff")] + header[1:]  # a byte order mark is not a column name
    if not header or header[0].strip() != "stamp":
        raise InputError("CSV header must start with 'stamp' (then mag1.x,mag1.y,mag1.z,...)")
    cols = [c.strip() for c in header[1:]]
    sensors = _sensor_columns(cols)
    names = _sensor_names(cols[:sensors])
    extra = cols[sensors:]
    _check_extra(extra)
    channels = tuple(c[len(CURRENT_PREFIX):] for c in extra if c.startswith(CURRENT_PREFIX))
    temperatures = _temperature_names(extra, names)
    _check_imu_columns(extra)
    return CsvLayout(tuple(names), tuple(extra), channels, temperatures)


def parse_header(header: list[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Sensor names and current channels of a CSV header (see :func:`parse_columns`)."""
    layout = parse_columns(header)
    return layout.names, layout.channels


def _read_text(path: str | os.PathLike[str], header_only: bool = False) -> str:
    """The text of a CSV file (a UTF-8 byte order mark dropped), or up to its first non-blank line (at most
    :data:`~magcal_ros.io.input_files.MAX_HEADER_BYTES`); only a regular file is read."""
    regular_file(path, "CSV recording")
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            if not header_only:
                return fh.read()
            line = fh.readline(MAX_HEADER_BYTES)
            while line and not line.strip(" \t\r\n,"):
                line = fh.readline(MAX_HEADER_BYTES)
            if len(line) >= MAX_HEADER_BYTES and not line.endswith("\n"):
                raise InputError(f"{path}: no header line in its first {MAX_HEADER_BYTES} bytes: not a CSV recording")
            return line
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path} is not a text CSV file") from None


def _plain_table(text: str) -> tuple[list[str], int, int] | None:
    """The header cells and where the body (the lines after the header) starts and ends in ``text``, for
    a CSV without quoting or blank lines (what ``magcal`` and most loggers write); None when it needs
    the full CSV reader. Offsets, not a copy: a long recording's text is hundreds of MB."""
    start, end = 0, len(text)
    while start < end and text[start] == "\n":
        start += 1
    while end > start and text[end - 1] == "\n":
        end -= 1
    if '"' in text or "\r" in text or text.find("\n\n", start, end) >= 0:
        return None
    split = text.find("\n", start, end)
    header = text[start:end] if split < 0 else text[start:split]
    if not header.strip(" \t,"):
        return None
    return header.split(","), (end if split < 0 else split + 1), end


SYNC_ROWS = 65_536
"""Rows of a CSV formed into sets at a time (see :func:`read_csv`)."""

CHUNK_CHARS = 4 << 20
"""A long CSV body is parsed this many characters (whole lines) at a time: memory stays bounded."""


PARALLEL_CHARS = 16 << 20
"""A CSV body at least this long is parsed in two halves side by side when a second core is free."""


def _body_chunks(text: str, start: int, end: int) -> list[tuple[int, int]]:
    """Offsets of whole lines of ``text[start:end]``, about :data:`CHUNK_CHARS` at a time."""
    out = []
    while start < end:
        stop = text.find("\n", min(start + CHUNK_CHARS, end), end)
        stop = end if stop < 0 else stop
        out.append((start, stop))
        start = stop + 1
    return out


Columns = tuple[NDArray[np.int64], NDArray[np.float64]]


def _fast_columns(text: str, start: int, end: int, width: int, checked: list[int], nonfinite: NonFinite,
                  optional: set[int]) -> Columns | None:
    """:func:`_fast_chunk` over the body ``text[start:end]`` a chunk at a time (a long body's second half
    in a forked child meanwhile, :mod:`magcal_ros.core.parallel`); None when any line is not regular."""
    chunks = _body_chunks(text, start, end)

    def parse(span: list[tuple[int, int]]) -> Columns | None:
        parts = []
        for a, b in span:
            part = _fast_chunk(text[a:b], width, checked, nonfinite, optional)
            if part is None:
                return None
            parts.append(part)
        if not parts:
            return None
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    half = next((i for i, (a, _) in enumerate(chunks) if a - start >= (end - start) // 2), len(chunks))
    if end - start < PARALLEL_CHARS or half in (0, len(chunks)):
        return parse(chunks)
    first, second = chunks[:half], chunks[half:]
    rows = sum(text.count("\n", a, b) + 1 for a, b in second)

    def fill(buf: memoryview) -> bool:
        got = parse(second)
        if got is None or len(got[0]) != rows:
            return False
        as_array(buf, np.int64, (rows,))[:] = got[0]
        as_array(buf, np.float64, (rows, width - 1), 8 * rows)[:] = got[1]
        return True

    child = fill_in_child(8 * rows * width, fill)
    if child is None:
        return parse(chunks)
    try:
        head = parse(first)
        buf = child.result()
    except BaseException:  # (Ctrl-C too: the child is stopped and reaped, not left behind)
        child.cancel()
        raise
    if head is None:
        if buf is not None:
            buf.close()
        return None
    if buf is None:  # the child found an irregular line (or failed): this process looks again
        tail = parse(second)
        return None if tail is None else (np.concatenate([head[0], tail[0]]), np.concatenate([head[1], tail[1]]))
    n = len(head[0])
    stamps = np.empty(n + rows, np.int64)
    data = np.empty((n + rows, width - 1))
    stamps[:n], data[:n] = head
    del head
    stamps[n:] = as_array(buf, np.int64, (rows,))
    data[n:] = as_array(buf, np.float64, (rows, width - 1), 8 * rows)
    buf.close()
    return stamps, data


def _fast_chunk(body: str, width: int, checked: list[int], nonfinite: NonFinite,
                optional: set[int]) -> tuple[NDArray[np.int64], NDArray[np.float64]] | None:
    """Stamps (N,) ns and values (N, width - 1) of body lines that are all regular (the right
    number of cells, every value a number, finite where ``nonfinite`` is "error"), parsed at
    once; None when any line is not (the row-by-row reader then names it). An empty cell of
    an ``optional`` column (the IMU's) is NaN."""
    if not body:
        return None
    rows = body.count("\n") + 1
    if not optional:  # every cell a number: parsed in C, the stamps exactly from their text
        try:
            flat = np.fromstring(body.replace("\n", ","), sep=",")
            stamps = parse_seconds_column([line.partition(",")[0] for line in body.split("\n")])
        except (ValueError, InputError):
            return None
        if flat.size != rows * width or len(stamps) != rows:
            return None
        data = flat.reshape(rows, width)[:, 1:]
        if nonfinite == "error" and not np.all(np.isfinite(data)):
            return None
        return stamps, data
    cells = body.replace("\n", ",").split(",")
    if len(cells) != rows * width:
        return None
    table = np.array(cells, dtype=object).reshape(rows, width)
    for k in optional:
        col = np.char.strip(table[:, k].astype(str))
        table[:, k] = np.where(col == "", "nan", col)
    try:
        data = table[:, 1:].astype(str).astype(float)
        stamps = parse_seconds_column(table[:, 0].tolist())
    except (ValueError, InputError):
        return None
    if nonfinite == "error" and not np.all(np.isfinite(data[:, [k - 1 for k in checked]])):
        return None
    return stamps, data


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


def _layout(path: str | os.PathLike[str], text: str) -> tuple[CsvLayout, list[list[str]] | None, Any]:
    """The header's layout, the rows read one by one (None where the fast reader may take the table) and
    the fast reader's parse of the table (None where the text is not a plain table)."""
    parsed = _plain_table(text)
    rows = None
    if parsed is None:
        try:
            rows = _rows(text)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
    header = [parsed[0]] if parsed is not None else rows
    if not header:
        raise InputError(f"{path} is empty: expected a header 'stamp,mag1.x,...' and data rows")
    try:
        return parse_columns(header[0]), rows, parsed
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def _parse_rows(path: str | os.PathLike[str], rows: list[list[str]], width: int, checked: list[int],
                imu_cols: set[int], nonfinite: NonFinite) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Stamps (ns) and values of the data rows read one at a time, each fault named with its line."""
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
            data[i - 2] = [float(c) if k not in imu_cols or c.strip() else np.nan for k, c in enumerate(row[1:], 1)]
        except ValueError:
            raise InputError(f"{path} line {i}: non-numeric value") from None
        if nonfinite == "error" and not np.all(np.isfinite(data[i - 2, [k - 1 for k in checked]])):
            raise InputError(f"{path} line {i}: NaN or infinite value (pass --drop-nonfinite to skip such rows)")
    return stamps, data


def _table(path: str | os.PathLike[str],
           nonfinite: NonFinite) -> tuple[NDArray[np.int64], NDArray[np.float64], CsvLayout]:
    """Stamps (ns), values (N, columns - 1) and the layout of a CSV recording: the fast reader where the
    table is regular, else row by row (which finds and names the fault)."""
    text = _read_text(path)
    layout, rows, parsed = _layout(path, text)
    width = 1 + 3 * len(layout.names) + len(layout.extra)
    imu_cols = {1 + 3 * len(layout.names) + k for k, c in enumerate(layout.extra) if _extra_kind(c) == "IMU"}
    checked = [k for k in range(1, width) if k not in imu_cols]
    fast = None if parsed is None else _fast_columns(text, parsed[1], parsed[2], width, checked, nonfinite, imu_cols)
    del text
    if fast is not None:
        return fast[0], fast[1], layout
    if rows is None:  # irregular somewhere: the row-by-row reading finds and names it
        rows = _rows(_read_text(path))
    return (*_parse_rows(path, rows, width, checked, imu_cols, nonfinite), layout)


def _side_columns(path: str | os.PathLike[str], layout: CsvLayout,
                  extra: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.bool_]]:
    """Currents (N, channels) A, temperatures (N, sensors) deg C or None, and the rows with a value out of
    range (made NaN: no value); a column in the wrong units is refused."""
    names = layout.names
    currents = extra[:, layout.columns(CURRENT_PREFIX + c for c in layout.channels)]
    temperatures = None
    if layout.temperatures == ("",):
        temperatures = np.repeat(extra[:, layout.columns([TEMPERATURE_COLUMN])], len(names), axis=1)
    elif layout.temperatures:
        temperatures = extra[:, layout.columns(TEMPERATURE_PREFIX + n for n in names)]
    out_t = np.zeros(len(extra), bool)
    if temperatures is not None:
        check_temperatures(temperatures, str(path))  # a column in kelvin is a units error ...
        temperatures, out_t = no_value(side.TEMPERATURE, temperatures)  # ... one sample out of range is no value
    check_currents(currents, str(path))
    currents, out_of_range = no_value(side.CURRENT, currents)
    return currents, temperatures, out_of_range | out_t


def _kept_rows(stamps: NDArray[np.int64], vectors: NDArray[np.float64],
               row_ok: NDArray[np.bool_]) -> tuple[NDArray[np.int64], SyncStats]:
    """The rows the synchronisation rule keeps, and its counts.

    Each sensor's messages carry their row number (scaled into the accepted range of a reading), so
    the sets the rule keeps name their rows (and so their currents and temperatures); a faulty reading
    goes in as it is, to be dropped and counted by the rule; a row whose side values are not finite
    (``row_ok`` False) is a non-finite row."""
    n, sensors = vectors.shape[:2]
    scale = MAX_READING / 2 / max(n, 1)
    row = np.arange(n, dtype=float) * scale
    sync = SetSynchronizer(sensors, 0, max_pending=n + 1, reject_zero=False, max_reading=MAX_READING)
    kept_parts = []
    for a in range(0, n, SYNC_ROWS):  # a block at a time, as a bag is read: memory stays bounded
        b = slice(a, a + SYNC_ROWS)
        tags = np.where(row_ok[b, None], row[b, None] * np.array([1.0, 0.0, 0.0]), np.nan)
        offered = np.empty((len(tags), sensors, 3))
        for k in range(sensors):
            faulty = np.logical_or.reduce(list(reading_faults(vectors[b, k]).values()))
            offered[:, k] = np.where(faulty[:, None], vectors[b, k], tags)
        sync.add_rows(stamps[b], offered)  # a row is every sensor's message at its stamp
        sets = sync.pop(final=a + SYNC_ROWS >= n)
        kept_parts.append(np.rint(sets.vectors[:, 0, 0] / scale).astype(np.int64))
    return (np.concatenate(kept_parts) if kept_parts else np.empty(0, np.int64)), sync.stats


def _imu_columns(path: str | os.PathLike[str], layout: CsvLayout, extra: NDArray[np.float64], kept: NDArray[np.int64],
                 frame: str) -> ImuSamples | None:
    """The IMU samples of the kept rows (orientations in ENU), or None without IMU columns."""
    if not (layout.has_orientation or layout.has_rate):
        return None
    n = len(extra)
    q = (extra[:, layout.columns(IMU_ORIENTATION_COLUMNS)] if layout.has_orientation
         else np.full((n, 4), np.nan))[kept]
    if frame == "ned":
        q = ned_to_enu(q)
    w = (extra[:, layout.columns(IMU_RATE_COLUMNS)] if layout.has_rate else np.full((n, 3), np.nan))[kept]
    samples = list(zip(q.tolist(), w.tolist()))
    side.refuse_units(side.IMU, [x for x in samples if side.imu_check(x) != "nonfinite"], str(path))
    q, w = side.usable_imu(samples)  # an orientation that is not a unit quaternion, a rate beyond any gyro: none
    try:
        return ImuSamples(q, w)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def read_csv(
    path: str | os.PathLike[str], nonfinite: NonFinite = "error", imu_orientation_frame: str = "enu"
) -> tuple[Recording, SyncStats]:
    """Read a CSV recording and the counts of rows it dropped (per message, as for a bag).

    Ragged rows, text values or an empty file are :class:`InputError`; NaN or infinite
    values are refused (``nonfinite="error"``) or their rows dropped (``"drop"``), but for
    the IMU's columns, where they mean "unknown at this set". Readings beyond any
    magnetometer's range are dropped and counted (``out_of_range``). ``imu_orientation_frame``:
    the world frame of the ``imu.q*`` columns, ``enu`` (``sensor_msgs/Imu``) or ``ned``
    (turned into ENU).
    """
    frame = imu_frame(imu_orientation_frame)
    stamps, data, layout = _table(path, nonfinite)
    names = layout.names
    vectors = data[:, : 3 * len(names)].reshape(len(data), len(names), 3)
    check_tesla(vectors, names, str(path))  # a file in nT is a units error, not readings out of range
    extra = data[:, 3 * len(names) :]
    currents, temperatures, out_of_range = _side_columns(path, layout, extra)
    row_ok = np.all(np.isfinite(currents), axis=1)
    if temperatures is not None:
        row_ok &= np.all(np.isfinite(temperatures), axis=1)
    kept, stats = _kept_rows(stamps, vectors, row_ok)
    _count_side_rows(stats, out_of_range, vectors)
    if len(kept) == 0:
        raise InputError(f"{path}: no usable rows ({stats.describe()})")
    imu = _imu_columns(path, layout, extra, kept, frame)
    return Recording(names, stamps[kept], vectors[kept], layout.channels, currents[kept],
                     None if temperatures is None else temperatures[kept], imu), stats


def no_value(kind: side.SideKind, values: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A side column's values (N, k) with those out of ``kind``'s range made NaN (no value: the row is dropped
    and counted, not refused), and the rows that had one."""
    v = np.array(values, dtype=float)
    lo, hi = (side.TEMPERATURE_RANGE if kind is side.TEMPERATURE else (-side.MAX_CURRENT, side.MAX_CURRENT))
    out = np.isfinite(v) & ((v < lo) | (v > hi))
    v[out] = np.nan
    return v, out.reshape(len(v), -1).any(axis=1)


def _count_side_rows(stats: SyncStats, bad_rows: NDArray[np.bool_], vectors: NDArray[np.float64]) -> None:
    """The messages of rows dropped for a current or temperature out of its range count as such (the rule
    counted their usable readings as non-finite: the rows went in as NaN)."""
    if not bad_rows.any():
        return
    usable = sum(int((~np.logical_or.reduce(list(reading_faults(vectors[bad_rows, k]).values()))).sum())
                 for k in range(vectors.shape[1]))
    stats.nonfinite -= usable
    stats.side_value += usable


def format_rows(stamps: NDArray[np.int64], columns: NDArray[np.float64]) -> str:
    """CSV body lines: exact stamps (9 decimals) and ``columns`` (N, K) in full double precision."""
    buf = io.StringIO()
    np.savetxt(buf, np.asarray(columns, dtype=float), delimiter=",", fmt="%.17g")
    body = buf.getvalue().splitlines()
    return "".join(f"{t},{line}\n" for t, line in zip(format_seconds_column(stamps), body))


def write_csv(path: str | os.PathLike[str], recording: Recording) -> None:
    """Write ``recording`` atomically as CSV: its currents as ``current.<channel>`` columns (A), its
    temperatures as ``temperature.<name>`` (deg C), its IMU as ``imu.q*`` (ENU) and ``imu.w*`` (rad/s)."""
    header = csv_header(recording.names) + [CURRENT_PREFIX + c for c in recording.channels]
    parts = [recording.vectors.reshape(len(recording), -1), recording.currents]
    if recording.temperatures is not None:
        header += [TEMPERATURE_PREFIX + n for n in recording.names]
        parts.append(recording.temperatures)
    imu = recording.imu
    if imu is not None and (imu.has_orientation or not imu.has_angular_velocity):
        header += list(IMU_ORIENTATION_COLUMNS)
        parts.append(imu.orientation)
    if imu is not None and imu.has_angular_velocity:
        header += list(IMU_RATE_COLUMNS)
        parts.append(imu.angular_velocity)
    columns = np.concatenate(parts, axis=1)  # type: ignore[arg-type]
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(header) + "\n")
            fh.write(format_rows(recording.stamps, columns))


def write_corrected_csv(
    path: str | os.PathLike[str], stamps: NDArray[np.int64], names: Sequence[str], sets: CorrectedSets,
    withheld: bool = False,
) -> None:
    """Write corrected sets atomically (columns as :func:`corrected_header` for the array's gradient);
    ``withheld``: ``nan`` in the field and gradient columns (a sensor left raw on purpose)."""
    n = len(stamps)
    parts = [sets.vectors.reshape(n, -1), sets.centre.reshape(n, 3)]
    kind = "none"
    if sets.tensor is not None:
        parts.append(sets.tensor.reshape(n, 9))
        kind = "tensor"
    elif sets.baseline is not None:
        parts.append(sets.baseline.reshape(n, 3))
        kind = "baseline"
    if withheld:
        parts[1:] = [np.full_like(p, np.nan) for p in parts[1:]]
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(corrected_header(names, kind)) + "\n")
            fh.write(format_rows(stamps, np.concatenate(parts, axis=1)))

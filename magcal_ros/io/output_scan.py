"""Read a corrected output back in chunks (for a campaign report), and count what an input offered.

``magcal correct`` writes a bag with ``/<name>/corrected`` and ``/field``
(``sensor_msgs/MagneticField``), plus ``/gradient`` (``std_msgs/Float64MultiArray``, 3x3) or
``/baseline_gradient`` (``geometry_msgs/Vector3Stamped``); or a CSV with ``stamp``,
``<name>.x..z``, ``field.x..z`` and ``gradient.*`` or ``baseline_gradient.*`` columns.
:func:`output_chunks` yields what a summary needs from either, a bounded number of
messages or rows at a time, so memory stays flat however long the recording.

An output with a sensor left raw on purpose (``magcal correct --uncorrected``) withholds the
centre field and the gradient: a bag has no ``/field`` and no gradient topic (the sets are then
stamped by the first sensor's ``/<name>/corrected``), a CSV has ``nan`` in those columns.
:func:`corrected_names` finds the sensors of an output, :func:`read_output` reads all of it.
"""

from __future__ import annotations

import csv
import itertools
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.stamps import parse_seconds
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.cdr import FLOAT64_MULTI_ARRAY, MAGNETIC_FIELD, VECTOR3_STAMPED, decode_magnetic_fields
from magcal_ros.io.csv_recording import BASELINE_COLUMNS, FIELD_COLUMNS, TENSOR_COLUMNS

CHUNK = 65536
"""Messages (bag) or rows (CSV) per chunk."""


@dataclass
class OutputChunk:
    """Part of a corrected output, in stamp order within each stream."""

    vectors: list[NDArray[np.float64]]
    """Per sensor (calibration order), corrected vectors (n_k, 3) in T."""
    field_stamps: NDArray[np.int64]
    """Stamps (ns) of the sets (``/field`` header stamps, CSV ``stamp``)."""
    gradient: NDArray[np.float64] = field(default_factory=lambda: np.empty((0, 0)))
    """Gradient rows (m, 9) tensor row-major, (m, 3) baseline gradient, or (0, 0): T/m."""
    centre: NDArray[np.float64] = field(default_factory=lambda: np.empty((0, 3)))
    """The centre field (m, 3) T (``/field``, CSV ``field.*``); (0, 3) when withheld."""


def _trailing_doubles(messages: list[bytes], count: int, what: str) -> NDArray[np.float64]:
    """The last ``count`` float64 of each CDR message (the data of a 3x3 Float64MultiArray or a
    Vector3Stamped's vector: both end the message, 8-aligned)."""
    if not messages:
        return np.empty((0, count))
    width = 8 * count
    if any(len(m) < 4 + width or m[0] != 0 or m[1] > 1 for m in messages):
        raise InputError(f"{what}: malformed message")
    tails = np.frombuffer(b"".join(m[-width:] for m in messages), np.uint8).reshape(len(messages), width)
    little = np.array([m[1] == 1 for m in messages])
    out = np.empty((len(messages), count))
    if np.any(little):
        out[little] = tails[little].copy().view("<f8")
    if not np.all(little):
        out[~little] = tails[~little].copy().view(">f8")
    return out


def _bag_chunks(path: Path, names: Sequence[str]) -> Iterator[OutputChunk]:
    from magcal_ros.io.bag_reader import message_rows, open_bag

    with open_bag(path) as reader:
        by_topic = {(c.topic, c.msgtype): c for c in reader.connections}
        wanted = [topics.absolute(topics.corrected(n)) for n in names]
        missing = [t for t in wanted if (t, MAGNETIC_FIELD) not in by_topic]
        if missing:
            raise InputError(f"{path}: not a corrected output of these sensors (no {', '.join(missing)})")
        field_conn = by_topic.get(("/" + topics.FIELD, MAGNETIC_FIELD))  # None: withheld (a sensor left raw)
        grad = by_topic.get((topics.absolute(topics.GRADIENT), FLOAT64_MULTI_ARRAY))
        base = by_topic.get((topics.absolute(topics.BASELINE_GRADIENT), VECTOR3_STAMPED))
        grad_conn, width = (grad, 9) if grad is not None else (base, 3) if base is not None else (None, 0)
        conns = [by_topic[(t, MAGNETIC_FIELD)] for t in wanted]
        field_id = conns[0].id if field_conn is None else field_conn.id
        conns += [] if field_conn is None else [field_conn]
        if grad_conn is not None:
            conns.append(grad_conn)

        def decode(lists: dict[int, list[bytes]]) -> OutputChunk:
            vectors = [decode_magnetic_fields(lists[c.id], str(path))[1] for c in conns[: len(names)]]
            stamps = decode_magnetic_fields(lists[field_id], str(path))[0]
            g = _trailing_doubles(lists[grad_conn.id], width, str(path)) if grad_conn is not None else np.empty((0, 0))
            centre = decode_magnetic_fields(lists[field_id], str(path))[1] if field_conn is not None else np.empty((0, 3))
            return OutputChunk(vectors, stamps, g, centre)

        rows = iter(message_rows(reader, conns))
        while True:
            block = list(itertools.islice(rows, CHUNK))
            lists: dict[int, list[bytes]] = {c.id: [] for c in conns}
            for cid, _, data in block:
                lists[cid].append(data)
            yield decode(lists)
            if len(block) < CHUNK:
                break


def _csv_chunks(path: Path, names: Sequence[str]) -> Iterator[OutputChunk]:
    try:
        fh = open(path, encoding="utf-8-sig", newline="")
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror}") from None
    with fh:
        rows = (r for r in csv.reader(fh) if r and any(c.strip() for c in r))
        header = next(rows, None)
        if header is None:
            raise InputError(f"{path} is empty")
        col = {name: i for i, name in enumerate(header)}
        need = ["stamp", *[f"{n}.{a}" for n in names for a in "xyz"], *FIELD_COLUMNS]
        missing = [c for c in need if c not in col]
        if missing:
            raise InputError(f"{path}: not a corrected output of these sensors (no column {', '.join(missing)})")
        extra: tuple[str, ...] = ()
        if all(c in col for c in TENSOR_COLUMNS):
            extra = TENSOR_COLUMNS
        elif all(c in col for c in BASELINE_COLUMNS):
            extra = BASELINE_COLUMNS
        vec_cols = [col[f"{n}.{a}"] for n in names for a in "xyz"] + [col[c] for c in FIELD_COLUMNS]
        extra_cols = [col[c] for c in extra]

        def decode(block: list[list[str]]) -> OutputChunk:
            try:
                stamps = np.array([parse_seconds(r[0]) for r in block], np.int64)
                values = np.array([[float(r[i]) for i in vec_cols + extra_cols] for r in block]).reshape(len(block), -1)
            except (ValueError, IndexError, InputError):
                raise InputError(f"{path}: malformed row") from None
            v = values[:, : len(vec_cols) - 3].reshape(len(block), len(names), 3)
            g = values[:, len(vec_cols):] if extra_cols else np.empty((0, 0))
            return OutputChunk([v[:, k] for k in range(len(names))], stamps, g, values[:, len(vec_cols) - 3 : len(vec_cols)])

        block: list[list[str]] = []
        for row in rows:
            block.append(row)
            if len(block) >= CHUNK:
                yield decode(block)
                block = []
        yield decode(block)


def output_chunks(path: str | os.PathLike[str], names: Sequence[str]) -> Iterator[OutputChunk]:
    """The corrected output at ``path`` (bag directory, or ``.csv``) in chunks, sensors ``names``."""
    p = Path(path)
    if str(p).lower().endswith(".csv"):
        return _csv_chunks(p, names)
    return _bag_chunks(p, names)


def corrected_names(path: str | os.PathLike[str]) -> tuple[str, ...] | None:
    """The sensors of a corrected output (``/<name>/corrected`` topics in bag order, or the ``<name>.x``
    columns before ``field.x`` of a CSV), or None when ``path`` is not one (a raw recording)."""
    p = Path(path)
    if str(p).lower().endswith(".csv"):
        try:
            with open(p, encoding="utf-8-sig", newline="") as fh:
                header = next((r for r in csv.reader(fh) if r and any(c.strip() for c in r)), [])
        except (OSError, csv.Error, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read {p}: {exc}") from None
        if FIELD_COLUMNS[0] not in header:
            return None
        return tuple(c[:-2] for c in header[1 : header.index(FIELD_COLUMNS[0])] if c.endswith(".x"))
    from magcal_ros.io.bag_reader import open_bag

    with open_bag(p) as reader:
        found = [c.topic for c in reader.connections if c.msgtype == MAGNETIC_FIELD and c.topic.endswith("/corrected")]
    names = tuple(dict.fromkeys(t[1 : -len("/corrected")] for t in found))
    return names or None


@dataclass(frozen=True)
class CorrectedOutput:
    """A whole corrected output in memory (:func:`read_output`): SI units, the outputs' frame."""

    names: tuple[str, ...]
    stamps: NDArray[np.int64]
    """(N,) the sets' stamps (ns)."""
    vectors: NDArray[np.float64]
    """(N, S, 3) corrected vectors (T)."""
    centre: NDArray[np.float64] | None
    """(N, 3) centre field (T); None when withheld (a sensor left raw)."""
    gradient: NDArray[np.float64] | None
    """(N, 9) tensor row-major or (N, 3) ``dB/ds`` (T/m); None for one sensor or when withheld."""


def read_output(path: str | os.PathLike[str], names: Sequence[str] | None = None) -> CorrectedOutput:
    """The corrected output at ``path`` in memory (sensors ``names``, default :func:`corrected_names`);
    :class:`InputError` when it is not one."""
    found = tuple(names) if names else corrected_names(path)
    if not found:
        raise InputError(f"{path}: not a corrected output (no /<name>/corrected topics, no field.x column)")
    chunks = list(output_chunks(path, found))
    stamps = np.concatenate([c.field_stamps for c in chunks])
    vectors = np.stack([np.concatenate([c.vectors[k] for c in chunks]) for k in range(len(found))], axis=1)
    if not len(stamps) or len(vectors) != len(stamps):
        raise InputError(f"{path}: no corrected sets" if not len(stamps) else
                         f"{path}: the sensors' corrected vectors do not pair with the sets")
    rows = [c.gradient for c in chunks if c.gradient.size]
    gradient = np.concatenate(rows) if rows else None
    centre = np.concatenate([c.centre for c in chunks])
    centre = centre if len(centre) == len(stamps) and np.any(np.isfinite(centre)) else None
    if gradient is not None and (len(gradient) != len(stamps) or not np.any(np.isfinite(gradient))):
        gradient = None
    return CorrectedOutput(found, stamps, vectors, centre, gradient)


def input_samples(path: str | os.PathLike[str], names: Sequence[str]) -> int:
    """What a recording offered for ``names``: the most messages any ``/<name>/raw`` topic of a
    bag holds (from its metadata), or a CSV's data rows."""
    p = Path(path)
    if str(p).lower().endswith(".csv"):
        try:
            with open(p, encoding="utf-8-sig", newline="") as fh:
                return max(0, sum(1 for r in csv.reader(fh) if r and any(c.strip() for c in r)) - 1)
        except (OSError, csv.Error, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read {p}: {exc}") from None
    from magcal_ros.io.bag_reader import open_bag

    with open_bag(p) as reader:
        counts = [sum(c.msgcount for c in reader.connections
                      if c.topic == topics.absolute(topics.raw(n)) and c.msgtype == MAGNETIC_FIELD) for n in names]
    return max(counts, default=0)

"""rosbag2 input and output with ``rosbags`` (pure Python; sqlite3 and mcap storages).

Topics (INTERFACES.md): ``/<name>/raw`` and ``/<name>/corrected`` are
``sensor_msgs/msg/MagneticField`` in Tesla; ``/field`` is the corrected centre field
(MagneticField, platform frame); ``/gradient`` is ``std_msgs/msg/Float64MultiArray``, 3x3
row-major ``G[i][j] = dB_j/dx_i`` in T/m. Bag time of everything written for a set is the
set's stamp (the first sensor's header stamp); ``/field`` precedes ``/gradient``.

Messages are decoded and encoded in batches with numpy (:mod:`magcal_ros.cdr`), read and
synchronised in chunks (:mod:`magcal_ros.bagsource`), and written through
:class:`~magcal_ros.bagsink.BagSink`, which inserts whole batches into the storage: memory
stays flat and the cost per message is a few array copies, not a Python object. Every
output bag is written to a temporary directory and renamed at the end; every input
failure is one :class:`~magcal_ros.errors.InputError` line.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from magcal_ros.atomic import atomic_path
from magcal_ros.bagsink import STORAGES, BagSink, SetLayout, Storage, check_storage
from magcal_ros.bagsource import (
    CHUNK_MESSAGES,
    DEFAULT_SYNC_TOLERANCE,
    NonFinite,
    Progress,
    SetReader,
    bag_error,
    is_read_error,
)
from magcal_ros.calibration import ArrayCalibration
from magcal_ros.cdr import (
    FLOAT64_MULTI_ARRAY,
    MAGNETIC_FIELD,
    gradient_template,
    magnetic_field_template,
    ns_to_seconds,
    seconds_to_ns,
)
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.recording import Recording
from magcal_ros.sync import SetBatch, SyncStats

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.rosbag2 import Reader

__all__ = [
    "CHUNK_MESSAGES", "DEFAULT_FRAME_ID", "DEFAULT_SYNC_TOLERANCE", "FIELD_TOPIC", "GRADIENT_TOPIC", "STORAGES",
    "BagSink", "CorrectionReport", "SetLayout", "SetReader", "Storage", "check_bag_output",
    "check_storage", "correct_bag", "corrected_topic", "open_bag", "raw_topic", "read_bag_recording",
    "read_bag_sets", "resolve_sensor_topics", "sensor_names_of", "write_corrected_bag", "write_recording_bag",
]

DEFAULT_FRAME_ID = "magcal_array"
SETS_PER_WRITE = 8192
"""Sets encoded and inserted per storage call."""


def raw_topic(name: str) -> str:
    """``/<name>/raw``."""
    return f"/{name.strip('/')}/raw"


def corrected_topic(name: str) -> str:
    """``/<name>/corrected``."""
    return f"/{name.strip('/')}/corrected"


FIELD_TOPIC = "/field"
GRADIENT_TOPIC = "/gradient"


# --------------------------------------------------------------------------- errors


@contextlib.contextmanager
def open_bag(path: str | os.PathLike[str]) -> Iterator["Reader"]:
    """An open rosbags ``Reader``; any failure becomes one :class:`InputError` line."""
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise InputError(f"{p} does not exist")
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # rosbags, apsw, yaml, OS errors: all mean "unreadable bag"
        raise bag_error(p, exc) from None
    try:
        yield reader
    except MagcalError:
        raise
    except Exception as exc:
        if not is_read_error(exc):
            raise
        raise bag_error(p, exc) from None
    finally:
        with contextlib.suppress(Exception):
            reader.close()


BAG_FILE_SUFFIXES: tuple[str, ...] = (".db3", ".mcap", ".yaml", ".db3-shm", ".db3-wal", ".db3-journal", ".zstd")


def check_bag_output(path: str | os.PathLike[str], source: str | os.PathLike[str] | None = None) -> None:
    """Refuse an output path that would destroy something that is not a previous bag.

    An existing rosbag2 directory (metadata.yaml plus storage files only) is replaced;
    an existing file or any other directory is an :class:`InputError`.
    """
    p = Path(path)
    if source is not None and p.exists() and p.resolve() == Path(source).resolve():
        raise InputError(f"{p}: output must differ from the input")
    if not p.exists():
        return
    if p.is_file():
        raise InputError(f"{p} exists and is a file; a rosbag2 output is a directory")
    entries = list(p.iterdir())
    if entries and not (
        (p / "metadata.yaml").is_file() and all(e.is_file() and e.name.endswith(BAG_FILE_SUFFIXES) for e in entries)
    ):
        raise InputError(f"{p} exists and is not a rosbag2 directory; refusing to replace it")


def _storage_of(path: Path) -> Storage:
    """Storage of an input bag (for ``storage=None`` outputs): ``mcap`` or ``sqlite3``."""
    if path.suffix == ".mcap" or (path.is_dir() and any(path.glob("*.mcap"))):
        return "mcap"
    return "sqlite3"


# --------------------------------------------------------------------------- topics


def field_topics(reader: "Reader") -> dict[str, list["Connection"]]:
    """MagneticField topics of an open bag: ``{topic: connections}``."""
    out: dict[str, list[Connection]] = {}
    for conn in reader.connections:
        if conn.msgtype == MAGNETIC_FIELD:
            out.setdefault(conn.topic, []).append(conn)
    return out


def sensor_names_of(reader: "Reader") -> tuple[str, ...]:
    """Sensor names of all ``/<name>/raw`` MagneticField topics, sorted."""
    names = [t[1:-4] for t in field_topics(reader) if t.startswith("/") and t.endswith("/raw") and len(t) > 5]
    return tuple(sorted(names))


def resolve_sensor_topics(
    reader: "Reader",
    path: str | os.PathLike[str],
    names: Sequence[str] | None = None,
    topics: Sequence[str] | None = None,
) -> tuple[tuple[str, ...], list[list["Connection"]]]:
    """Sensor names and their connections: ``topics`` if given, else ``/<name>/raw`` of ``names``.

    ``names`` default to every ``*/raw`` MagneticField topic of the bag (sorted).
    Raises :class:`InputError` naming a missing topic or a topic of the wrong type.
    """
    fields = field_topics(reader)
    for given in (names, topics):
        if given is not None and len(set(given)) != len(given):
            raise InputError(f"sensors must be listed once each, got {', '.join(given)}")
    if topics:
        tlist = [t if t.startswith("/") else "/" + t for t in topics]
        if names is None:
            names = [t[1:-4] if t.endswith("/raw") else t.strip("/") for t in tlist]
        if len(names) != len(tlist):
            raise InputError(f"{len(names)} sensor names for {len(tlist)} topics")
    else:
        if names is None:
            names = sensor_names_of(reader)
            if not names:
                listing = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
                raise InputError(f"{path}: no /<name>/raw sensor_msgs/msg/MagneticField topics (topics: {listing})")
        tlist = [raw_topic(n) for n in names]
    conns = []
    for t in tlist:
        if t not in fields:
            other = [c.msgtype for c in reader.connections if c.topic == t]
            if other:
                raise InputError(f"{path}: topic {t} has type {other[0]}, expected {MAGNETIC_FIELD}")
            have = ", ".join(sorted(fields)) or "none"
            raise InputError(f"{path}: no topic {t} (MagneticField topics: {have})")
        conns.append(fields[t])
    return tuple(names), conns


# --------------------------------------------------------------------------- reading


def read_bag_sets(
    path: str | os.PathLike[str],
    names: Sequence[str] | None = None,
    topics: Sequence[str] | None = None,
    tolerance: float = DEFAULT_SYNC_TOLERANCE,
    nonfinite: NonFinite = "drop",
    progress: Progress | None = None,
) -> tuple[Recording, SyncStats]:
    """Synchronized raw sets of a bag and the synchronisation counters.

    ``names``: sensors (topics ``/<name>/raw``; default all ``*/raw`` MagneticField
    topics, sorted); ``topics``: explicit topic per sensor instead. ``tolerance`` (s):
    largest header stamp difference within a set. Stamps of the recording are the sets'
    header stamps in seconds; vectors are in Tesla, sensor axes.
    """
    with open_bag(path) as reader:
        names_t, conns = resolve_sensor_topics(reader, path, names, topics)
        sets = SetReader(reader, path, conns, tolerance, nonfinite, progress=progress)
        stamps: list[NDArray[np.int64]] = []
        vectors: list[NDArray[np.float64]] = []
        for batch in sets:
            stamps.append(batch.set_stamps)
            vectors.append(batch.vectors)
        stats = sets.stats
    if not stamps:
        raise InputError(f"{path}: no complete synchronized sets of {', '.join(raw_topic(n) for n in names_t)} ({stats.describe()})")
    rec = Recording(names_t, ns_to_seconds(np.concatenate(stamps)), np.concatenate(vectors))
    return rec, stats


def read_bag_recording(path: str | os.PathLike[str], names: Sequence[str] | None = None, **options: Any) -> Recording:
    """Synchronized raw sets of a rosbag2 directory (sqlite3 or mcap) as a :class:`Recording`.

    Options as :func:`read_bag_sets` (which also returns how many messages were dropped).
    """
    return read_bag_sets(path, names, **options)[0]


# --------------------------------------------------------------------------- writing


def write_recording_bag(
    path: str | os.PathLike[str],
    recording: Recording,
    storage: Storage = "sqlite3",
    frame_ids: Sequence[str] | None = None,
) -> None:
    """Write ``recording`` as a rosbag2 directory with topics ``/<name>/raw``.

    One ``sensor_msgs/msg/MagneticField`` per sensor and set: header stamp = the set's
    stamp, ``frame_id`` = the sensor name (or ``frame_ids``), field in T, covariance zero;
    bag time = the stamp. Atomic: written to a temporary directory, renamed at the end.
    """
    check_storage(storage)
    names = recording.names
    frames = list(frame_ids) if frame_ids is not None else list(names)
    if len(frames) != len(names):
        raise InputError(f"{len(frames)} frame ids for {len(names)} sensors")
    check_bag_output(path)
    stamps = seconds_to_ns(recording.stamps)
    templates = [magnetic_field_template(f) for f in frames]
    with atomic_path(path) as tmp, BagSink.create(tmp, storage) as sink:
        conns = [sink.add_topic(raw_topic(n), MAGNETIC_FIELD) for n in names]
        layout = sink.layout([(c, t.template) for c, t in zip(conns, templates)])
        for a in range(0, len(recording), SETS_PER_WRITE):
            ts = stamps[a : a + SETS_PER_WRITE]
            blocks = layout.new(len(ts))
            for k, tmpl in enumerate(templates):
                tmpl.fill(blocks, layout.offsets[k], ts, recording.vectors[a : a + SETS_PER_WRITE, k])
            sink.write_sets(layout, blocks, ts)


# --------------------------------------------------------------------------- correcting


@dataclass(frozen=True)
class CorrectionOutput:
    """Topics and templates of corrected output for ``names``."""

    layout: SetLayout
    sensor_template: Any
    field_template: Any
    gradient_template: Any
    sensors: int

    def encode(self, batch: SetBatch, calibration: ArrayCalibration, gradient_method: str) -> NDArray[np.uint8]:
        """Filled blocks for ``batch``: corrected vectors, centre field and tensor per set."""
        b, centre, g = calibration.field_and_gradient(batch.vectors, gradient_method)
        blocks = self.layout.new(len(batch))
        off = self.layout.offsets
        for k in range(self.sensors):
            self.sensor_template.fill(blocks, off[k], batch.stamps[:, k], b[:, k])
        self.field_template.fill(blocks, off[self.sensors], batch.set_stamps, centre)
        self.gradient_template.fill(blocks, off[self.sensors + 1], g)
        return blocks


def correction_output(sink: BagSink, names: Sequence[str], frame_id: str) -> CorrectionOutput:
    """Register ``/<name>/corrected``, ``/field`` and ``/gradient`` on ``sink``."""
    mf = magnetic_field_template(frame_id)
    gt = gradient_template()
    parts = [(sink.add_topic(corrected_topic(n), MAGNETIC_FIELD), mf.template) for n in names]
    parts.append((sink.add_topic(FIELD_TOPIC, MAGNETIC_FIELD), mf.template))
    parts.append((sink.add_topic(GRADIENT_TOPIC, FLOAT64_MULTI_ARRAY), gt.template))
    return CorrectionOutput(sink.layout(parts), mf, mf, gt, len(names))


@dataclass(frozen=True)
class CorrectionReport:
    """What :func:`correct_bag` did."""

    stats: SyncStats
    input_messages: int
    copied_messages: int
    output: str
    storage: str


def _window(batch: SetBatch, start: float | None, end: float | None) -> SetBatch:
    if start is None and end is None:
        return batch
    t = batch.set_stamps
    keep = np.ones(len(t), bool)
    if start is not None:
        keep &= t >= seconds_to_ns(start)
    if end is not None:
        keep &= t <= seconds_to_ns(end)
    return batch.take(keep)


def correct_bag(
    in_path: str | os.PathLike[str],
    calibration: ArrayCalibration,
    out_path: str | os.PathLike[str],
    storage: Storage | None = None,
    copy_topics: Sequence[str] | Literal["all"] = (),
    progress: Progress | None = None,
    frame_id: str = DEFAULT_FRAME_ID,
    gradient_method: str = "difference",
    tolerance: float = DEFAULT_SYNC_TOLERANCE,
    nonfinite: NonFinite = "drop",
    start: float | None = None,
    end: float | None = None,
) -> CorrectionReport:
    """Correct every synchronized set of ``in_path`` and write a new bag at ``out_path``.

    Writes ``/<name>/corrected`` (MagneticField, T, frame ``frame_id``, each sensor's own
    header stamp), ``/field`` (centre field, stamped with the set's stamp) and ``/gradient``
    (Float64MultiArray 3x3 row-major, T/m), all at bag time = the set's stamp; plus the
    input topics in ``copy_topics`` (``"all"``: every topic) unchanged with their bag
    times. ``storage`` defaults to the input's. Streaming and atomic: nothing is left at
    ``out_path`` on failure.
    """
    names = calibration.geometry.names
    inp = Path(in_path)
    out_storage = check_storage(storage) if storage else _storage_of(inp)
    check_bag_output(out_path, inp)
    with open_bag(inp) as reader:
        _, conns = resolve_sensor_topics(reader, inp, names)
        outputs = {corrected_topic(n) for n in names} | {FIELD_TOPIC, GRADIENT_TOPIC}
        if copy_topics == "all":
            extra = list(reader.connections)
        else:
            have = {c.topic for c in reader.connections}
            wanted = [t if t.startswith("/") else "/" + t for t in copy_topics]
            missing = [t for t in wanted if t not in have]
            if missing:
                raise InputError(f"{inp}: no topic {', '.join(missing)} to copy (topics: {', '.join(sorted(have))})")
            extra = [c for c in reader.connections if c.topic in wanted]
        clash = sorted({c.topic for c in extra} & outputs)
        if clash:
            raise InputError(f"{inp}: cannot copy {', '.join(clash)}: the corrected output writes that topic")
        with atomic_path(out_path) as tmp, BagSink.create(tmp, out_storage) as sink:
            out = correction_output(sink, names, frame_id)
            copy_map: dict[int, Connection] = {}
            by_topic: dict[tuple[str, str], Connection] = {}
            for c in extra:
                key = (c.topic, c.msgtype)
                if key not in by_topic:
                    by_topic[key] = sink.add_copy_of(c)
                copy_map[c.id] = by_topic[key]
            copied = [0]

            def on_extra(items: list[tuple[Connection, int, bytes]]) -> None:
                sink.write_messages([(copy_map[c.id], t, d) for c, t, d in items if c.id in copy_map])
                copied[0] += len(items)

            sets = SetReader(reader, inp, conns, tolerance, nonfinite, extra=extra, on_extra=on_extra, progress=progress)
            n_in = 0
            for batch in sets:
                batch = _window(batch, start, end)
                for a in range(0, len(batch), SETS_PER_WRITE):
                    part = SetBatch(batch.stamps[a : a + SETS_PER_WRITE], batch.vectors[a : a + SETS_PER_WRITE])
                    sink.write_sets(out.layout, out.encode(part, calibration, gradient_method), part.set_stamps)
                n_in += len(batch)
            if sets.stats.sets == 0:
                raise InputError(f"{inp}: no complete synchronized sets of {', '.join(raw_topic(n) for n in names)} ({sets.stats.describe()})")
            if n_in == 0:
                raise InputError(f"{inp}: no synchronized sets in the selected time window")
    return CorrectionReport(sets.stats, n_in, copied[0], str(out_path), out_storage)


def write_corrected_bag(
    path: str | os.PathLike[str],
    recording: Recording,
    calibration: ArrayCalibration,
    storage: Storage = "sqlite3",
    frame_id: str = DEFAULT_FRAME_ID,
    gradient_method: str = "difference",
) -> None:
    """Corrected output of an in-memory ``recording`` (e.g. from CSV) as a bag; see :func:`correct_bag`."""
    check_bag_output(path)
    rec = recording.select(calibration.geometry.names)
    stamps = seconds_to_ns(rec.stamps)
    with atomic_path(path) as tmp, BagSink.create(tmp, check_storage(storage)) as sink:
        out = correction_output(sink, rec.names, frame_id)
        for a in range(0, len(rec), SETS_PER_WRITE):
            ts = stamps[a : a + SETS_PER_WRITE]
            part = SetBatch(np.repeat(ts[:, None], len(rec.names), axis=1), rec.vectors[a : a + SETS_PER_WRITE])
            sink.write_sets(out.layout, out.encode(part, calibration, gradient_method), ts)


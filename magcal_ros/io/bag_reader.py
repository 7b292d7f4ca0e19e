"""Streaming synchronized sets out of rosbag2 bags, with as little per-message Python as possible.

- sqlite3 (uncompressed): the storage files are queried directly with the query rosbags
  itself runs, so each message costs one row tuple and one list append;
- mcap (indexed, uncompressed or with chunk compression rosbags supports): each chunk is
  read once and every MagneticField message of a sensor is gathered with one numpy fancy
  index through the chunk's message index, no per-message Python at all;
- anything else: ``Reader.messages``.

Messages are decoded in batches (:mod:`magcal_ros.io.cdr`) and synchronised in chunks
(:mod:`magcal_ros.core.sync`); memory stays bounded by the chunk size.
"""

from __future__ import annotations

import contextlib
import itertools
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.imu import ImuStream, ned_to_enu
from magcal_ros.core.interference import CurrentSamples, check_currents
from magcal_ros.core import side_streams as side
from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import format_seconds
from magcal_ros.core.sync import (
    DEFAULT_MAX_GAP,
    DEFAULT_SYNC_MODE,
    DEFAULT_SYNC_TOLERANCE,
    SetBatch,
    StreamSynchronizer,
    SyncStats,
    stream_synchronizer,
)
from magcal_ros.core.temperature import TemperatureSamples, check_temperatures
from magcal_ros.core.units import MAX_READING, check_tesla
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.io import topics as topic_names
from magcal_ros.io.atomic import write_failure
from magcal_ros.io.cdr import (
    CURRENT_TYPES,
    IMU,
    MAGNETIC_FIELD,
    TEMPERATURE,
    decode_current,
    decode_imu,
    decode_magnetic_field_rows,
    decode_magnetic_fields,
    decode_temperature,
)

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.rosbag2 import Reader

NonFinite = Literal["drop", "error"]
Progress = Callable[[int], None]
"""Progress callback: called with the number of input messages just processed. If it also
has a ``set_total(n)`` method, that is called first with the messages the run will read."""

CHUNK_MESSAGES = 65536
"""Input messages decoded and synchronised per chunk."""


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (or its type name)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


COMPRESSION_MODULES: tuple[str, ...] = ("zstd", "backports.zstd", "compression", "lz4")
STORAGE_MODULES: tuple[str, ...] = ("rosbags", "apsw", "sqlite3", "yaml", "ruamel", "mcap", *COMPRESSION_MODULES)
"""Packages that read bag storage: an exception raised inside them is about the bag."""


def _in_packages(module: str, packages: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def _raised_in_storage(exc: BaseException) -> bool:
    """True when the innermost Python frame of ``exc``'s traceback belongs to a storage package."""
    tb = exc.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    return _in_packages(str(tb.tb_frame.f_globals.get("__name__", "")), STORAGE_MODULES)


def _storage_exception(exc: BaseException) -> bool:
    """True for the exception types rosbags and its storage libraries raise on unreadable bags."""
    import apsw
    from rosbags.rosbag2 import ReaderError
    from rosbags.serde import SerdeError

    return isinstance(exc, (ReaderError, SerdeError, apsw.Error, EOFError)) or _in_packages(type(exc).__module__, COMPRESSION_MODULES)


def is_read_error(exc: BaseException) -> bool:
    """True for failures of the input itself while only reading, False for bugs in magcal_ros.

    Storage, decompression, deserialisation and I/O errors (rosbags, apsw, compression
    libraries, ``OSError``, ``EOFError``) are the bag's; so is anything raised inside a
    storage package's own code (rosbags choking on malformed data). An ``AttributeError``
    or ``TypeError`` raised in magcal_ros is a bug and must surface as one.
    """
    return _storage_exception(exc) or isinstance(exc, OSError) or _raised_in_storage(exc)


def bag_error(path: str | os.PathLike[str], exc: BaseException) -> MagcalError:
    """A one-line :class:`MagcalError` for a failure while reading the bag ``path``.

    The real cause first: a missing file, no permission, SQLite failing to write its
    temporary files (a file size limit or a full disk, not the bag's fault), an I/O error;
    only what remains is a corrupt or unreadable bag.
    """
    if isinstance(exc, MagcalError):
        return exc
    if isinstance(exc, FileNotFoundError):
        missing = Path(exc.filename).name if getattr(exc, "filename", None) else "metadata.yaml"
        return InputError(f"{path}: not a rosbag2 directory or bag file (no {missing})")
    if isinstance(exc, PermissionError):
        return InputError(f"{path}: permission denied")
    cause = write_failure(exc)
    if cause is not None:
        return MagcalError(f"cannot read {path}: SQLite could not write its temporary files: {cause}")
    if isinstance(exc, OSError):
        return InputError(f"cannot read {path}: {exc.strerror or first_line(exc)}")
    return InputError(f"{path}: corrupt or unreadable rosbag2 ({type(exc).__name__}: {first_line(exc)})")


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
    except Exception as exc:
        if not is_read_error(exc):
            raise
        raise bag_error(p, exc) from None
    try:
        yield reader
    except MagcalError:
        raise
    except Exception as exc:
        # The caller may also be writing (an output bag): only the storage libraries' own
        # exception types are about this bag here; SetReader maps errors while reading.
        if not _storage_exception(exc):
            raise
        raise bag_error(p, exc) from None
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _plain_sqlite_files(reader: "Reader") -> list[Path] | None:
    """The storage files of an uncompressed sqlite3 bag directory, else None."""
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

    storages = getattr(reader.storage, "storages", None)
    if not storages or reader.compression_mode or not all(isinstance(s, Sqlite3Reader) for s in storages):
        return None
    paths = [getattr(s, "path", None) for s in storages]
    return paths if all(isinstance(p, Path) for p in paths) else None  # type: ignore[return-value]


def _sqlite_cursors(files: list[Path], by_key: dict[tuple[str, str], int]) -> Iterator[Iterable[tuple[int, int, bytes]]]:
    """Per storage file, a cursor over (connection id, bag time, data) in bag time order."""
    import apsw

    for f in files:
        db = apsw.Connection(f"file:{f}?immutable=1", flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI)
        try:
            idmap = {tid: by_key[(name, typ)] for tid, name, typ in db.execute("SELECT id, name, type FROM topics") if (name, typ) in by_key}
            if not idmap:
                continue
            query = f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({','.join(map(str, idmap))}) ORDER BY timestamp"
            cursor = db.execute(query)
            if all(k == v for k, v in idmap.items()):
                yield cursor
            else:
                yield ((idmap[t], ts, d) for t, ts, d in cursor)
        finally:
            db.close()


def message_rows(reader: "Reader", connections: Sequence["Connection"]) -> Iterable[tuple[int, int, bytes]]:
    """``(connection id, bag time ns, serialized bytes)`` of ``connections``, in bag time order.

    For uncompressed sqlite3 bags the storage files are queried directly (the same query
    rosbags runs, without its per-message Python layers); anything else goes through
    ``Reader.messages``.
    """
    files = _plain_sqlite_files(reader)
    if files is None:
        return ((c.id, t, d) for c, t, d in reader.messages(connections=list(connections)))
    by_key = {(c.topic, c.msgtype): c.id for c in connections}
    return itertools.chain.from_iterable(_sqlite_cursors(files, by_key))


def _indexed_mcaps(reader: "Reader", connections: Sequence["Connection"]) -> list[Any] | None:
    """The mcap storages of a bag if every wanted message is reachable through chunk indexes."""
    from rosbags.rosbag2.storage_mcap import McapReader

    storages = getattr(reader.storage, "storages", None)
    if not storages or reader.compression_mode or not all(isinstance(s, McapReader) for s in storages):
        return None
    keys = {(c.topic, c.msgtype) for c in connections}
    indexed = listed = 0
    for st in storages:
        if not all(hasattr(st, a) for a in ("chunks", "bio", "connections")):
            return None
        ids = {c.id for c in st.connections if (c.topic, c.msgtype) in keys}
        listed += sum(c.msgcount for c in st.connections if c.id in ids)
        indexed += sum(n for ch in st.chunks for cid, n in ch.channel_count.items() if cid in ids)
    return storages if indexed == listed else None


@dataclass
class _ChannelBatch:
    """Messages of one channel in one chunk: bag times (n,) ns and payloads."""

    times: NDArray[np.int64]
    rows: list[NDArray[np.uint8]]
    """Equal-length payload groups, each (n_i, L_i)."""
    order: list[NDArray[np.int64]]
    """Positions (into ``times``) of each group's rows."""


def _u64(u: NDArray[np.uint8], at: NDArray[np.int64]) -> NDArray[np.int64]:
    """Little-endian uint64 at byte positions ``at`` of ``u``."""
    return u[at[:, None] + np.arange(8)].copy().view("<u8")[:, 0].astype(np.int64)


def _mcap_chunk(storage: Any, chunk: Any, ids: set[int], what: str) -> dict[int, _ChannelBatch]:
    """Read and decompress one chunk; gather the payloads of channels ``ids`` via its message index."""
    from rosbags.rosbag2.storage_mcap import decompress

    bio = storage.bio
    bio.seek(chunk.chunk_start_offset + 9 + 24)
    crc = int.from_bytes(bio.read(4), "little")
    bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
    data = bio.read(chunk.compressed_size)
    if len(data) != chunk.compressed_size:
        raise InputError(f"{what}: truncated mcap chunk")
    u = np.frombuffer(decompress(data, chunk.compression, chunk.uncompressed_size, crc), np.uint8)
    out: dict[int, _ChannelBatch] = {}
    for cid in sorted(ids & set(chunk.message_index_offsets)):
        bio.seek(chunk.message_index_offsets[cid])
        head = bio.read(15)
        if len(head) != 15 or head[0] != 0x07 or int.from_bytes(head[9:11], "little") != cid:
            raise InputError(f"{what}: malformed mcap message index")
        size = int.from_bytes(head[11:15], "little")
        pairs = np.frombuffer(bio.read(size), "<u8")
        if len(pairs) * 8 != size or size % 16:
            raise InputError(f"{what}: truncated mcap message index")
        pairs = pairs.reshape(-1, 2).astype(np.int64)
        order = np.argsort(pairs[:, 0], kind="stable")
        times, offs = pairs[order, 0], pairs[order, 1]
        if len(offs) and (offs.min() < 0 or offs.max() + 31 > len(u)):
            raise InputError(f"{what}: mcap message index points outside its chunk")
        lengths = _u64(u, offs + 1) - 22
        ok = (u[offs] == 0x05) & (u[offs + 9] == (cid & 0xFF)) & (u[offs + 10] == (cid >> 8)) & (lengths >= 0)
        if not np.all(ok) or np.any(offs + 31 + lengths > len(u)):
            raise InputError(f"{what}: mcap message index does not match its chunk")
        rows, where = [], []
        for length in np.unique(lengths):
            idx = np.flatnonzero(lengths == length)
            rows.append(u[offs[idx, None] + 31 + np.arange(int(length))])
            where.append(idx)
        out[cid] = _ChannelBatch(times, rows, where)
    return out


@dataclass
class _Pending:
    """Raw messages of one chunk, per sensor."""

    messages: list[list[bytes]]
    times: list[list[int]]
    """Bag time (ns) of each message: when the recorder received it."""

    @classmethod
    def empty(cls, sensors: int) -> "_Pending":
        return cls([[] for _ in range(sensors)], [[] for _ in range(sensors)])


def _joined(parts: list[tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]],
            ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
    """One sensor's messages from the batches of one chunk (several connections of one topic), in order."""
    if len(parts) == 1:
        return parts[0]
    if not parts:
        return np.empty(0, np.int64), np.empty((0, 3)), np.empty(0, np.int64)
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


class SetReader:
    """Stream synchronized raw sets out of an open bag, in chunks.

    Iterating yields :class:`~magcal_ros.core.sync.SetBatch` in stamp order; ``stats`` counts
    sets and dropped messages. Messages of ``extra`` connections are handed to
    ``on_extra`` as ``(connection, bag time ns, bytes)`` in bag time order. ``sync_mode``,
    ``max_gap`` (s) and ``time_offsets`` (s per sensor name) as
    :func:`~magcal_ros.core.sync.stream_synchronizer` takes them; bag times are each
    message's receipt (they place a sensor that restarted alone).
    """

    def __init__(
        self,
        reader: "Reader",
        path: str | os.PathLike[str],
        connections: list[list["Connection"]],
        tolerance: float = DEFAULT_SYNC_TOLERANCE,
        nonfinite: NonFinite = "drop",
        extra: Sequence["Connection"] = (),
        on_extra: Callable[[list[tuple["Connection", int, bytes]]], None] | None = None,
        progress: Progress | None = None,
        chunk: int = CHUNK_MESSAGES,
        sync_mode: str = DEFAULT_SYNC_MODE,
        max_gap: float = DEFAULT_MAX_GAP,
        time_offsets: dict[str, float] | None = None,
    ) -> None:
        self.reader = reader
        self.path = str(path)
        self.index: dict[int, int] = {}
        for k, conns in enumerate(connections):
            for c in conns:
                self.index[c.id] = k
        self.extra = list(extra)
        for c in self.extra:
            self.index.setdefault(c.id, -1)
        self.names = [topic_names.sensor_of_raw(conns[0].topic) or conns[0].topic for conns in connections]
        self.sync: StreamSynchronizer = stream_synchronizer(self.names, tolerance, sync_mode, max_gap, time_offsets,
                                                            max_pending=4 * chunk, max_reading=MAX_READING)
        self.nonfinite = nonfinite
        self.on_extra = on_extra
        self.progress = progress
        self.chunk = chunk
        self.connections = [c for conns in connections for c in conns]
        self.wanted = {c.id: c for c in self.connections + self.extra}
        self._extras: list[tuple[Connection, int, bytes]] = []
        self._units_checked = [False] * len(connections)

    @property
    def stats(self) -> SyncStats:
        """Counters so far."""
        return self.sync.stats

    def __iter__(self) -> Iterator[SetBatch]:
        listed = sum(c.msgcount for c in self.wanted.values())
        set_total = getattr(self.progress, "set_total", None)
        if callable(set_total):
            set_total(listed)
        mcaps = _indexed_mcaps(self.reader, list(self.wanted.values()))
        feed = self._feed_mcap(mcaps) if mcaps is not None else self._feed_rows()
        n = total = 0
        while True:
            try:
                count = next(feed)
            except StopIteration:
                break
            except MagcalError:
                raise
            except Exception as exc:
                if not is_read_error(exc):
                    raise
                raise bag_error(self.path, exc) from None
            n += count
            if n >= self.chunk:
                total += n
                yield from self._release(n, final=False)
                n = 0
        total += n
        if total < listed:
            raise InputError(
                f"{self.path}: truncated bag: its metadata lists {listed} messages on the topics read, "
                f"only {total} are in the storage"
            )
        yield from self._release(n, final=True)

    def _feed_rows(self) -> Iterator[int]:
        """Queue messages from :func:`message_rows`; yields how many were queued each time."""
        wanted, index = self.wanted, self.index
        copy_ids = {c.id for c in self.extra}
        pending = _Pending.empty(self.sync.size)
        extras = self._extras
        n = 0
        for cid, bagtime, data in message_rows(self.reader, list(wanted.values())):
            k = index[cid]
            if k >= 0:
                pending.messages[k].append(data)
                pending.times[k].append(bagtime)
            if copy_ids and cid in copy_ids:
                extras.append((wanted[cid], bagtime, data))
            n += 1
            if n >= self.chunk:
                self._decode(pending)
                yield n
                pending, n = _Pending.empty(self.sync.size), 0
        self._decode(pending)
        yield n

    def _decode(self, pending: _Pending) -> None:
        self.sync.add_streams([self._checked(k, *decode_magnetic_fields(msgs, self.path),
                                             np.asarray(pending.times[k], dtype=np.int64))
                               for k, msgs in enumerate(pending.messages)])

    def _checked(self, k: int, stamps: NDArray[np.int64], vectors: NDArray[np.float64],
                 receipts: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
        """One sensor's decoded messages (in its order) for the synchronizer, once its units are checked."""
        if self.nonfinite == "error":
            bad = ~np.all(np.isfinite(vectors), axis=1)
            if np.any(bad):
                raise InputError(
                    f"{self.path}: {int(bad.sum())} NaN or infinite readings on /{self.names[k]}/raw "
                    f"(first stamped {format_seconds(int(stamps[np.argmax(bad)]))} s); "
                    "pass --drop-nonfinite to skip them"
                )
        if not self._units_checked[k]:  # a bag in nT is a units error, not readings out of range
            finite = vectors[np.all(np.isfinite(vectors), axis=1)]
            if len(finite):
                check_tesla(finite[:, None, :], [self.names[k]], self.path)
                self._units_checked[k] = True
        return stamps, vectors, receipts

    def _feed_mcap(self, storages: list[Any]) -> Iterator[int]:
        """Queue messages chunk by chunk through the mcap message indexes."""
        keys = {(c.topic, c.msgtype): c.id for c in self.wanted.values()}
        copy_ids = {c.id for c in self.extra}
        for st in storages:
            local = {c.id: keys[(c.topic, c.msgtype)] for c in st.connections if (c.topic, c.msgtype) in keys}
            ids = set(local)
            chunks = sorted(
                (ch for ch in st.chunks if any(ch.channel_count.get(cid, 0) for cid in ids)),
                key=lambda ch: (ch.message_start_time, ch.chunk_start_offset),
            )
            for ch in chunks:
                n = 0
                parts: list[list[tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]]] = \
                    [[] for _ in range(self.sync.size)]
                for cid, batch in _mcap_chunk(st, ch, ids, self.path).items():
                    gid = local[cid]
                    n += len(batch.times)
                    k = self.index[gid]
                    if k >= 0:
                        stamps = np.empty(len(batch.times), np.int64)
                        vectors = np.empty((len(batch.times), 3))
                        for rows, where in zip(batch.rows, batch.order):
                            stamps[where], vectors[where] = decode_magnetic_field_rows(rows, self.path)
                        parts[k].append(self._checked(k, stamps, vectors, batch.times))
                    if gid in copy_ids:
                        conn = self.wanted[gid]
                        times = batch.times.tolist()
                        for rows, where in zip(batch.rows, batch.order):
                            self._extras.extend((conn, times[i], r.tobytes()) for i, r in zip(where.tolist(), rows))
                self.sync.add_streams([_joined(p) for p in parts])
                yield n

    def _release(self, n: int, final: bool) -> Iterator[SetBatch]:
        """Hand over queued copies, release complete sets, report progress."""
        if self._extras and self.on_extra is not None:
            self._extras.sort(key=lambda item: item[1])
            self.on_extra(self._extras)
        self._extras = []
        batch = self.sync.pop(final=final)
        if self.progress is not None and n:
            self.progress(n)
        if len(batch):
            yield batch


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
    names = [topic_names.sensor_of_raw(t) for t in field_topics(reader)]
    return tuple(sorted(n for n in names if n))


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
        tlist = [topic_names.absolute(topic_names.raw(n)) for n in names]
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


@dataclass(frozen=True)
class SideReading:
    """The connections of a side stream's topics in an open bag, and how their messages become the stream's
    samples: ``decode`` takes ``(connection id, bag time ns, bytes)`` rows of those connections in bag time
    order (:func:`message_rows`, or one reading's share of :func:`read_side_rows`)."""

    connections: list["Connection"]
    decode: Callable[[Iterable[tuple[int, int, bytes]]], Any]

    def read(self, reader: "Reader") -> Any:
        """The samples, from a pass over these connections alone."""
        return self.decode(message_rows(reader, self.connections))


def read_side_rows(reader: "Reader", readings: Sequence[SideReading]) -> list[list[tuple[int, int, bytes]]]:
    """One pass over the messages of every reading's connections, in bag time order: each reading's rows.

    The side topics of a bag (currents, temperatures, the IMU: low rate) are read together, once; each
    reading then decodes its own rows (:attr:`SideReading.decode`) with its own errors.
    """
    owners: dict[int, list[int]] = {}
    conns: list[Connection] = []
    for k, r in enumerate(readings):
        for c in r.connections:
            if c.id not in owners:
                owners[c.id] = []
                conns.append(c)
            owners[c.id].append(k)
    out: list[list[tuple[int, int, bytes]]] = [[] for _ in readings]
    if conns:  # Reader.messages reads every topic when given none
        for row in message_rows(reader, conns):
            for k in owners[row[0]]:
                out[k].append(row)
    return out


def read_current_samples(reader: "Reader", path: str | os.PathLike[str], topics: Sequence[str]) -> list[CurrentSamples]:
    """Every value of the current topics ``topics`` of an open bag, one channel per topic.

    Types ``sensor_msgs/msg/BatteryState`` (``current`` at its header stamp, or at its bag
    time when that is zero) or
    ``std_msgs/msg/Float64`` (``data`` at its bag time), amperes; channel names by
    :func:`~magcal_ros.io.topics.current_channel`. A separate pass over these (low-rate)
    topics only, so the MagneticField fast paths are untouched. Raises :class:`InputError`
    naming a missing topic, a topic of another type or a message that does not decode.
    """
    return current_reading(reader, path, topics).read(reader)


def current_reading(reader: "Reader", path: str | os.PathLike[str], topics: Sequence[str]) -> SideReading:
    """The current topics ``topics`` of an open bag as a :class:`SideReading` (as :func:`read_current_samples`
    reads them); :class:`InputError` naming a topic named twice, missing or of another type."""
    wanted = [topic_names.absolute(t) for t in topics]
    if len(set(wanted)) != len(wanted) or not all(t.strip("/") for t in wanted):
        raise InputError(f"current topics must be named once each, got {', '.join(topics)}")
    conns = typed_connections(reader, path, wanted, CURRENT_TYPES, "current", "A")
    return SideReading(conns, lambda rows: _current_samples(path, wanted, conns, rows))


def _current_samples(path: str | os.PathLike[str], wanted: list[str], conns: list["Connection"],
                     rows: Iterable[tuple[int, int, bytes]]) -> list[CurrentSamples]:
    """The current channels of the absolute topics ``wanted`` from their connections' rows."""
    index = {c.id: wanted.index(c.topic) for c in conns}
    types = {c.id: c.msgtype for c in conns}
    stamps: list[list[int]] = [[] for _ in wanted]
    values: list[list[float]] = [[] for _ in wanted]
    for cid, bag_time, data in rows:
        try:
            stamp, current = decode_current(types[cid], data, bag_time)
        except InputError as exc:
            raise InputError(f"{path}: {wanted[index[cid]]}: {exc}") from None
        stamps[index[cid]].append(stamp)
        values[index[cid]].append(current)
    out = []
    for t, st, v in zip(wanted, stamps, values):
        check_currents(np.array(v), f"{path}: {t}")
        kept_t, kept_v, counts = side.accepted_samples(side.CURRENT.check, st, v)
        out.append(CurrentSamples(topic_names.current_channel(t), np.array(kept_t, np.int64), np.array(kept_v, float),
                                  counts))
    return out


def typed_connections(reader: "Reader", path: str | os.PathLike[str], wanted: Sequence[str], types: Sequence[str],
                      what: str, unit: str) -> list["Connection"]:
    """The connections of the absolute topics ``wanted``, each of one of ``types``; :class:`InputError`
    naming a missing topic (and the topics of those types there are) or a topic of another type."""
    conns: list[Connection] = []
    for t in wanted:
        found = [c for c in reader.connections if c.topic == t]
        if not found:
            have = ", ".join(sorted({c.topic for c in reader.connections if c.msgtype in types})) or "none"
            kinds = "/".join(k.rsplit("/", 1)[-1] for k in types)
            raise InputError(f"{path}: no {what} topic {t} ({kinds} topics: {have})")
        wrong = [c.msgtype for c in found if c.msgtype not in types]
        if wrong:
            raise InputError(f"{path}: topic {t} has type {wrong[0]}, expected {' or '.join(types)} ({unit})")
        conns += found
    return conns


def temperature_topics(reader: "Reader", names: Sequence[str]) -> list[str] | None:
    """``/<name>/temperature`` of every sensor when the bag has them all as ``sensor_msgs/msg/Temperature``
    with messages; None when it has none of them (a topic recorded without a message counts as none);
    :class:`InputError` naming the missing ones when it has some."""
    wanted = [topic_names.absolute(topic_names.temperature(n)) for n in names]
    have = {c.topic for c in reader.connections if c.msgtype == TEMPERATURE and getattr(c, "msgcount", 1) > 0}
    found = [t for t in wanted if t in have]
    if not found:
        return None
    missing = [t for t in wanted if t not in have]
    if missing:
        raise InputError(f"the bag has {', '.join(found)} but not {', '.join(missing)} (sensor_msgs/msg/Temperature): "
                         "every sensor needs its temperature; name the topics with --temperature-topics")
    return wanted


def read_temperature_samples(reader: "Reader", path: str | os.PathLike[str], names: Sequence[str],
                             topics: Sequence[str]) -> list[TemperatureSamples]:
    """Every temperature (deg C) of each sensor of ``names`` from its topic in ``topics`` (one per
    sensor, or one topic for all), ``sensor_msgs/msg/Temperature`` at its header stamp (the bag time when
    that is zero). A separate pass over these low-rate topics. :class:`InputError` naming a missing or
    mistyped topic, a message that does not decode, or temperatures that are not deg C."""
    return temperature_reading(reader, path, names, topics).read(reader)


def temperature_reading(reader: "Reader", path: str | os.PathLike[str], names: Sequence[str],
                        topics: Sequence[str]) -> SideReading:
    """The temperature topics ``topics`` of the sensors ``names`` as a :class:`SideReading` (as
    :func:`read_temperature_samples` reads them); :class:`InputError` for a count of topics that fits
    neither one per sensor nor one for all, or a missing or mistyped topic."""
    wanted = [topic_names.absolute(t) for t in topics]
    if len(wanted) == 1 and len(names) > 1:
        wanted = wanted * len(names)
    if len(wanted) != len(names):
        raise InputError(f"{len(wanted)} temperature topics for {len(names)} sensors ({', '.join(names)}): give one "
                         "per sensor, or one for all")
    unique = list(dict.fromkeys(wanted))
    conns = typed_connections(reader, path, unique, (TEMPERATURE,), "temperature", "deg C")
    return SideReading(conns, lambda rows: _temperature_samples(path, names, wanted, unique, conns, rows))


def _temperature_samples(path: str | os.PathLike[str], names: Sequence[str], wanted: list[str], unique: list[str],
                         conns: list["Connection"], rows: Iterable[tuple[int, int, bytes]]) -> list[TemperatureSamples]:
    """Each sensor's temperatures (its topic in ``wanted``, of the distinct ``unique``) from the connections' rows."""
    index = {c.id: unique.index(c.topic) for c in conns}
    stamps: list[list[int]] = [[] for _ in unique]
    values: list[list[float]] = [[] for _ in unique]
    for cid, bag_time, data in rows:
        try:
            stamp, celsius = decode_temperature(data, bag_time)
        except InputError as exc:
            raise InputError(f"{path}: {unique[index[cid]]}: {exc}") from None
        stamps[index[cid]].append(stamp)
        values[index[cid]].append(celsius)
    kept = []
    for t, st, v in zip(unique, stamps, values):
        check_temperatures(np.array(v), f"{path}: {t}")
        kept.append(side.accepted_samples(side.TEMPERATURE.check, st, v))
    return [TemperatureSamples(n, np.array(kept[unique.index(t)][0], np.int64), np.array(kept[unique.index(t)][1]),
                               kept[unique.index(t)][2]) for n, t in zip(names, wanted)]


def read_imu_stream(reader: "Reader", path: str | os.PathLike[str], topic: str, frame: str = "enu") -> ImuStream:
    """Every sample of the ``sensor_msgs/msg/Imu`` topic ``topic``: header stamp (the bag time when zero),
    orientation (none where orientation_covariance[0] is -1; ``frame="ned"``: an orientation to NED,
    turned into ENU) and angular velocity (none where its covariance[0] is -1). :class:`InputError` naming a
    missing or mistyped topic or a message that does not decode."""
    return imu_reading(reader, path, topic, frame).read(reader)


def imu_reading(reader: "Reader", path: str | os.PathLike[str], topic: str, frame: str = "enu") -> SideReading:
    """The IMU topic ``topic`` as a :class:`SideReading` (as :func:`read_imu_stream` reads it);
    :class:`InputError` naming a missing or mistyped topic."""
    wanted = topic_names.absolute(topic)
    conns = typed_connections(reader, path, [wanted], (IMU,), "IMU", "orientation, rad/s")
    return SideReading(conns, lambda rows: _imu_stream(path, wanted, frame, rows))


def _imu_stream(path: str | os.PathLike[str], wanted: str, frame: str,
                rows: Iterable[tuple[int, int, bytes]]) -> ImuStream:
    """The IMU samples of the topic ``wanted`` from its connections' rows."""
    stamps: list[int] = []
    q: list[tuple[float, ...]] = []
    w: list[tuple[float, ...]] = []
    frame_id = ""
    for _, bag_time, data in rows:
        try:
            stamp, quat, rate, frame_id = decode_imu(data, bag_time)
        except InputError as exc:
            raise InputError(f"{path}: {wanted}: {exc}") from None
        stamps.append(stamp)
        q.append(quat)
        w.append(rate)
    orientation = np.array(q, dtype=float).reshape(-1, 4)
    if frame == "ned":
        orientation = ned_to_enu(orientation)
    rate = np.array(w, dtype=float).reshape(-1, 3)
    samples = list(zip(orientation.tolist(), rate.tolist()))
    side.refuse_units(side.IMU, samples, f"{path}: {wanted}")
    kept_t, kept, counts = side.accepted_samples(side.IMU.check, stamps, samples)
    q_kept, w_kept = side.usable_imu(kept)
    try:
        return ImuStream(np.array(kept_t, np.int64), q_kept, w_kept, frame_id, counts)
    except InputError as exc:
        raise InputError(f"{path}: {wanted}: {exc}") from None


# --------------------------------------------------------------------------- reading


def read_bag_sets(
    path: str | os.PathLike[str],
    names: Sequence[str] | None = None,
    topics: Sequence[str] | None = None,
    tolerance: float = DEFAULT_SYNC_TOLERANCE,
    nonfinite: NonFinite = "drop",
    progress: Progress | None = None,
    sync_mode: str = DEFAULT_SYNC_MODE,
    max_gap: float = DEFAULT_MAX_GAP,
    time_offsets: dict[str, float] | None = None,
) -> tuple[Recording, SyncStats]:
    """Synchronized raw sets of a bag and the synchronisation counters.

    ``names``: sensors (topics ``/<name>/raw``; default all ``*/raw`` MagneticField
    topics, sorted); ``topics``: explicit topic per sensor instead. ``tolerance`` (s):
    largest header stamp difference within a set (exact matching); ``sync_mode``,
    ``max_gap`` (s) and ``time_offsets`` (s by sensor name) as
    :func:`~magcal_ros.core.sync.stream_synchronizer` takes them. Stamps of the recording
    are the sets' stamps in integer nanoseconds; vectors are in Tesla, sensor axes.
    """
    with open_bag(path) as reader:
        names_t, conns = resolve_sensor_topics(reader, path, names, topics)
        sets = SetReader(reader, path, conns, tolerance, nonfinite, progress=progress, sync_mode=sync_mode,
                         max_gap=max_gap, time_offsets=time_offsets)
        stamps: list[NDArray[np.int64]] = []
        vectors: list[NDArray[np.float64]] = []
        for batch in sets:
            stamps.append(batch.set_stamps)
            vectors.append(batch.vectors)
        stats = sets.stats
    if not stamps:
        raise InputError(f"{path}: no complete synchronized sets of {', '.join(topic_names.absolute(topic_names.raw(n)) for n in names_t)} ({stats.describe()})")
    rec = Recording(names_t, np.concatenate(stamps), np.concatenate(vectors))
    return rec, stats


def read_bag_recording(path: str | os.PathLike[str], names: Sequence[str] | None = None, **options: Any) -> Recording:
    """Synchronized raw sets of a rosbag2 directory (sqlite3 or mcap) as a :class:`Recording`.

    Options as :func:`read_bag_sets` (which also returns how many messages were dropped).
    """
    return read_bag_sets(path, names, **options)[0]

"""Batch output of rosbag2 bags: a rosbags ``Writer`` plus whole-batch storage inserts.

Messages are written in sets: one fixed layout of messages per synchronized set (e.g.
four ``/<name>/corrected``, ``/field``, ``/gradient``), filled for many sets at once as one
(n, B) byte array. For sqlite3 a single ``INSERT .. SELECT`` slices the rows out of that
blob inside SQLite; for mcap the message records (headers included) are part of the
block and go into the open chunk with one write. Topics, metadata and the storage files
themselves are still rosbags' (``Writer.add_connection``, ``Writer.close``), so the bags
are ordinary rosbag2 bags; any other storage falls back to ``Writer.write`` per message.
"""

from __future__ import annotations

import contextlib
import functools
import os
import struct
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.imu import ImuStream
from magcal_ros.core.recording import Recording
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.io import topics
from magcal_ros.io.atomic import atomic_path, public_path, write_failure
from magcal_ros.io.bag_reader import first_line
from magcal_ros.io.cdr import (
    BATTERY_STATE,
    IMU,
    MAGNETIC_FIELD,
    TEMPERATURE,
    battery_state_message,
    imu_message,
    magnetic_field_template,
    temperature_message,
    typestore,
)

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.rosbag2 import Writer

Storage = Literal["sqlite3", "mcap"]
STORAGES: tuple[str, ...] = ("sqlite3", "mcap")
SETS_PER_WRITE = 8192
"""Sets encoded and inserted per storage call."""
BAG_FILE_SUFFIXES: tuple[str, ...] = (".db3", ".mcap", ".yaml", ".db3-shm", ".db3-wal", ".db3-journal", ".zstd")
"""Files a rosbag2 directory may hold; only such a directory is replaced by a new output."""


def check_storage(storage: str) -> Storage:
    """Validate a storage name."""
    if storage not in STORAGES:
        raise InputError(f"unknown storage {storage!r}; choose one of {', '.join(STORAGES)}")
    return storage  # type: ignore[return-value]


def _fsync_tree(path: Path) -> None:
    """Flush every file of a finished bag directory (and the directory) to disk."""
    for f in path.iterdir():
        if f.is_file():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclass(frozen=True)
class SetLayout:
    """Byte layout of the messages written for one set, in write order.

    ``block`` (B,) is the per-set template (storage record headers included); message
    ``j`` has its payload at ``offsets[j]`` with ``sizes[j]`` bytes; ``time_at`` lists byte
    positions of uint64 bag times inside the block (mcap records carry them).
    """

    connections: tuple["Connection", ...]
    block: NDArray[np.uint8]
    offsets: tuple[int, ...]
    sizes: tuple[int, ...]
    record_at: tuple[int, ...]
    time_at: tuple[int, ...]

    def new(self, n: int) -> NDArray[np.uint8]:
        """(n, B) blocks initialised from the template."""
        out = np.empty((n, len(self.block)), np.uint8)
        out[:] = self.block
        return out


F = TypeVar("F", bound=Callable[..., Any])


def output_error(path: str | os.PathLike[str], exc: BaseException) -> MagcalError:
    """One line for a failed bag write (create, write or close): the final output's name and the real cause."""
    return MagcalError(f"cannot write bag {public_path(path)}: {write_failure(exc) or first_line(exc)}")


def _output_errors(method: F) -> F:
    """Report any storage failure while writing as one :class:`MagcalError` line."""

    @functools.wraps(method)
    def wrapper(self: "BagSink", *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, *args, **kwargs)
        except MagcalError:
            raise
        except Exception as exc:
            raise output_error(self.writer.path, exc) from None

    return wrapper  # type: ignore[return-value]


MCAP_CHUNK_CRC_AT: int = 1 + 8 + 8 + 8 + 8
"""Offset of a Chunk record's ``uncompressed_crc`` from the record's opcode: opcode (1), record
length (8), message start time (8), message end time (8), uncompressed size (8)."""


def _write_chunk_crcs(storage: Any) -> None:
    """Make rosbags' MCAP storage writer fill in each chunk's CRC-32 of its uncompressed records
    (it writes 0, "not computed", so a reader cannot detect a corrupted chunk): the chunk is
    closed by rosbags, then its CRC field is written in place."""
    close = getattr(storage, "close_chunk", None)
    if close is None or not hasattr(storage, "chunk") or not hasattr(storage, "bio"):
        return

    def close_chunk() -> None:
        crc = zlib.crc32(storage.chunk.bio.getbuffer())
        start = storage.bio.tell()
        close()
        end = storage.bio.tell()
        storage.bio.seek(start + MCAP_CHUNK_CRC_AT)
        storage.bio.write(struct.pack("<I", crc))
        storage.bio.seek(end)

    storage.close_chunk = close_chunk


class BagSink:
    """A rosbags ``Writer`` plus batch insertion for the sqlite3 and mcap storages."""

    MCAP_RECORD_HEADER = 31
    """op (1) + record length (8) + channel (2) + sequence (4) + log time (8) + publish time (8)."""
    MCAP_CHUNK_BYTES = 1 << 20

    def __init__(self, writer: "Writer", storage: Storage) -> None:
        self.writer = writer
        self.storage = storage
        self._fast = self._detect_fast()
        if storage == "mcap":
            _write_chunk_crcs(writer.storage)
        self._sqlite_order: bool | None = None
        if self._fast == "sqlite3":
            # The bag is written in a temporary directory, fsynced and renamed when complete:
            # SQLite's own journal and syncs buy nothing here.
            conn = writer.storage.conn
            conn.execute("PRAGMA journal_mode=OFF")
            conn.execute("PRAGMA synchronous=OFF")

    @classmethod
    @contextlib.contextmanager
    def create(cls, path: str | os.PathLike[str], storage: Storage) -> Iterator["BagSink"]:
        """A sink writing a new bag at ``path`` (which must not exist); closed on exit."""
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if check_storage(storage) == "mcap" else StoragePlugin.SQLITE3
        try:
            writer = Writer(Path(path), version=9, storage_plugin=plugin)
            writer.open()
        except Exception as exc:
            raise output_error(path, exc) from None
        sink = cls(writer, storage)
        try:
            yield sink
        except BaseException:
            with contextlib.suppress(Exception):
                writer.abort()
            raise
        try:
            writer.close()
            _fsync_tree(Path(path))
        except Exception as exc:
            raise output_error(path, exc) from None

    def _detect_fast(self) -> str | None:
        st = self.writer.storage
        if self.storage == "sqlite3" and hasattr(st, "cursor") and hasattr(st, "conn"):
            return "sqlite3"
        if self.storage == "mcap" and all(hasattr(st, a) for a in ("chunk", "close_chunk", "channel_stats")):
            return "mcap"
        return None

    @_output_errors
    def add_topic(self, topic: str, msgtype: str) -> "Connection":
        """Register ``topic`` of a Jazzy standard ``msgtype``."""
        return self.writer.add_connection(topic, msgtype, typestore=typestore())

    @_output_errors
    def add_copy_of(self, conn: "Connection") -> "Connection":
        """Register a topic with the same type, definition and QoS as an input connection."""
        from rosbags.interfaces import ConnectionExtRosbag2

        ext = conn.ext
        kw: dict[str, Any] = {}
        if isinstance(ext, ConnectionExtRosbag2):
            kw = {"serialization_format": ext.serialization_format, "offered_qos_profiles": ext.offered_qos_profiles}
        if conn.msgdef.data and conn.digest:
            return self.writer.add_connection(conn.topic, conn.msgtype, msgdef=conn.msgdef.data, rihs01=conn.digest, **kw)
        return self.writer.add_connection(conn.topic, conn.msgtype, typestore=typestore(), **kw)

    def layout(self, parts: Sequence[tuple["Connection", NDArray[np.uint8]]]) -> SetLayout:
        """The per-set layout of messages ``(connection, payload template)`` in write order."""
        pieces: list[NDArray[np.uint8]] = []
        offsets, sizes, records, times = [], [], [], []
        pos = 0
        for conn, payload in parts:
            records.append(pos)
            if self._fast == "mcap":
                head = np.zeros(self.MCAP_RECORD_HEADER, np.uint8)
                head[0] = 0x05
                head[1:9] = np.frombuffer((22 + len(payload)).to_bytes(8, "little"), np.uint8)
                head[9:11] = np.frombuffer(int(conn.id).to_bytes(2, "little"), np.uint8)
                times += [pos + 15, pos + 23]
                pieces.append(head)
                pos += len(head)
            offsets.append(pos)
            sizes.append(len(payload))
            pieces.append(payload)
            pos += len(payload)
        return SetLayout(tuple(c for c, _ in parts), np.concatenate(pieces), tuple(offsets), tuple(sizes), tuple(records), tuple(times))

    def _account(self, conn: "Connection", count: int, tmin: int, tmax: int) -> None:
        w = self.writer
        w.counts[conn.id] += count
        w.min_timestamp = min(w.min_timestamp, tmin)
        w.max_timestamp = max(w.max_timestamp, tmax)

    @_output_errors
    def write_sets(self, layout: SetLayout, blocks: NDArray[np.uint8], times: NDArray[np.int64]) -> None:
        """Write n filled set blocks (n, B); every message of set i gets bag time ``times[i]`` (ns)."""
        n = len(blocks)
        if n == 0:
            return
        times = np.asarray(times, dtype=np.int64)
        if self._fast == "sqlite3":
            self._sqlite_sets(layout, blocks, times)
        elif self._fast == "mcap":
            self._mcap_sets(layout, blocks, times)
        else:
            data = blocks.tobytes()
            width = blocks.shape[1]
            for i, t in enumerate(times.tolist()):
                for conn, off, size in zip(layout.connections, layout.offsets, layout.sizes):
                    base = i * width + off
                    self.writer.write(conn, t, data[base : base + size])

    def _sqlite_sets(self, layout: SetLayout, blocks: NDArray[np.uint8], times: NDArray[np.int64]) -> None:
        """One INSERT .. SELECT per batch: SQLite slices the messages out of one blob.

        The CROSS JOIN makes the sets the outer loop (documented SQLite behaviour), so rows
        go in set order, messages of a set in layout order. That is verified on the first
        batch; should it ever not hold, the statement gains an ORDER BY (slower, same bytes).
        """
        width = blocks.shape[1]
        cur = self.writer.storage.cursor
        values = ",".join(f"({j},{c.id},{o},{s})" for j, (c, o, s) in enumerate(zip(layout.connections, layout.offsets, layout.sizes)))
        sql = (
            "INSERT INTO messages (topic_id, timestamp, data) "
            f"SELECT lay.column2, s.value, substr(?1, s.key * {width} + lay.column3 + 1, lay.column4) "
            f"FROM json_each(?2) AS s CROSS JOIN (VALUES {values}) AS lay"
        )
        if self._sqlite_order is True:
            sql += " ORDER BY s.key, lay.column1"
        stamps = "[" + ",".join(map(str, times.tolist())) + "]"
        first_row = cur.execute("SELECT coalesce(max(id), 0) FROM messages").fetchone()[0] if self._sqlite_order is None else 0
        cur.execute(sql, (blocks.tobytes(), stamps))
        if self._sqlite_order is None:
            got = [r[0] for r in cur.execute("SELECT topic_id FROM messages WHERE id > ? ORDER BY id", (first_row,))]
            expected = [c.id for c in layout.connections] * len(times)
            self._sqlite_order = False
            if got != expected:  # pragma: no cover - SQLite changed its join order
                cur.execute("DELETE FROM messages WHERE id > ?", (first_row,))
                self._sqlite_order = True
                cur.execute(sql + " ORDER BY s.key, lay.column1", (blocks.tobytes(), stamps))
        tmin, tmax = int(times.min()), int(times.max())
        for conn in layout.connections:
            self._account(conn, len(times), tmin, tmax)

    def _mcap_sets(self, layout: SetLayout, blocks: NDArray[np.uint8], times: NDArray[np.int64]) -> None:
        st = self.writer.storage
        width = blocks.shape[1]
        t8 = times.astype("<u8").view(np.uint8).reshape(len(times), 8)
        for at in layout.time_at:
            blocks[:, at : at + 8] = t8
        per_chunk = max(1, self.MCAP_CHUNK_BYTES // width)
        for a in range(0, len(blocks), per_chunk):
            piece, tp = blocks[a : a + per_chunk], times[a : a + per_chunk]
            chunk = st.chunk
            base = chunk.bio.tell()
            chunk.bio.write(piece.tobytes())
            tlist = tp.tolist()
            starts = base + np.arange(len(piece), dtype=np.int64) * width
            tmin, tmax = int(tp.min()), int(tp.max())
            for conn, rec in zip(layout.connections, layout.record_at):
                chunk.msgs[conn.id].extend(zip(tlist, (starts + rec).tolist()))
                st.channel_stats[conn.id] += len(piece)
                self._account(conn, len(piece), tmin, tmax)
            chunk.message_start_time = min(chunk.message_start_time, tmin)
            chunk.message_end_time = max(chunk.message_end_time, tmax)
            st.message_start_time = min(st.message_start_time, tmin)
            st.message_end_time = max(st.message_end_time, tmax)
            if chunk.bio.tell() > self.MCAP_CHUNK_BYTES:
                st.close_chunk()

    @_output_errors
    def write_messages(self, items: Sequence[tuple["Connection", int, bytes]]) -> None:
        """Write already serialized messages ``(output connection, bag time ns, bytes)``."""
        if self._fast == "sqlite3" and items:
            self.writer.storage.cursor.executemany(
                "INSERT INTO messages (topic_id, timestamp, data) VALUES(?, ?, ?)", [(c.id, t, d) for c, t, d in items]
            )
            for c, t, _ in items:
                self._account(c, 1, t, t)
            return
        for c, t, d in items:
            self.writer.write(c, t, d)


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


def storage_of(path: Path) -> Storage:
    """Storage of an input bag (for ``storage=None`` outputs): ``mcap`` or ``sqlite3``."""
    if path.suffix == ".mcap" or (path.is_dir() and any(path.glob("*.mcap"))):
        return "mcap"
    return "sqlite3"


def write_recording_bag(
    path: str | os.PathLike[str],
    recording: Recording,
    storage: Storage = "sqlite3",
    frame_ids: Sequence[str] | None = None,
    imu_stream: ImuStream | None = None,
    imu_topic: str = "/imu",
) -> None:
    """Write ``recording`` as a rosbag2 directory with topics ``/<name>/raw``.

    One ``sensor_msgs/msg/MagneticField`` per sensor and set: header stamp = the set's
    stamp, ``frame_id`` = the sensor name (or ``frame_ids``), field in T, covariance zero;
    bag time = the stamp. The recording's current channels become one
    ``sensor_msgs/msg/BatteryState`` topic each (``/<channel>``, ``current`` in A, header
    stamp and bag time = the set's stamp); its temperatures one ``sensor_msgs/msg/Temperature``
    topic per sensor (``/<name>/temperature``, deg C, at the set's stamp); its IMU the
    ``sensor_msgs/msg/Imu`` topic ``imu_topic`` at the set's stamp, or every sample of
    ``imu_stream`` at its own stamps (an IMU at its own rate). Atomic: written to a temporary
    directory, renamed at the end.
    """
    check_storage(storage)
    names = recording.names
    frames = list(frame_ids) if frame_ids is not None else list(names)
    if len(frames) != len(names):
        raise InputError(f"{len(frames)} frame ids for {len(names)} sensors")
    check_bag_output(path)
    stamps = recording.stamps
    templates = [magnetic_field_template(f) for f in frames]
    with atomic_path(path) as tmp, BagSink.create(tmp, storage) as sink:
        conns = [sink.add_topic(topics.absolute(topics.raw(n)), MAGNETIC_FIELD) for n in names]
        currents = [sink.add_topic(topics.current_topic(c), BATTERY_STATE) for c in recording.channels]
        _write_side_topics(sink, recording, imu_stream, imu_topic)
        layout = sink.layout([(c, t.template) for c, t in zip(conns, templates)])
        for a in range(0, len(recording), SETS_PER_WRITE):
            ts = stamps[a : a + SETS_PER_WRITE]
            blocks = layout.new(len(ts))
            for k, tmpl in enumerate(templates):
                tmpl.fill(blocks, layout.offsets[k], ts, recording.vectors[a : a + SETS_PER_WRITE, k])
            sink.write_sets(layout, blocks, ts)
            if currents:
                sink.write_messages([
                    (conn, t, bytes(typestore().serialize_cdr(battery_state_message(t, i), BATTERY_STATE)))
                    for t, row in zip(ts.tolist(), recording.currents[a : a + SETS_PER_WRITE].tolist())  # type: ignore[index]
                    for conn, i in zip(currents, row)
                ])


def write_stream_bag(
    path: str | os.PathLike[str],
    names: Sequence[str],
    stamps: Sequence[NDArray[np.int64]],
    vectors: Sequence[NDArray[np.float64]],
    bag_times: Sequence[NDArray[np.int64]],
    storage: Storage = "sqlite3",
) -> None:
    """Write per-sensor streams as a rosbag2 directory: topic ``/<name>/raw`` per sensor, one
    ``sensor_msgs/msg/MagneticField`` per sample (header stamp ``stamps[k]`` ns, field
    ``vectors[k]`` (n_k, 3) T, ``frame_id`` the sensor name) at bag time ``bag_times[k]`` ns: each
    sensor's messages in its own order, all of them in bag time order (as a recorder receives
    them; stamps may jump or go back, bag time does not). Atomic like
    :func:`write_recording_bag`."""
    check_storage(storage)
    if not (len(names) == len(stamps) == len(vectors) == len(bag_times)):
        raise InputError("need stamps, vectors and bag times for every sensor")
    check_bag_output(path)
    with atomic_path(path) as tmp, BagSink.create(tmp, storage) as sink:
        conns = [sink.add_topic(topics.absolute(topics.raw(n)), MAGNETIC_FIELD) for n in names]
        encoded, events = [], []
        for k, name in enumerate(names):
            s = np.asarray(stamps[k], dtype=np.int64)
            t = np.asarray(bag_times[k], dtype=np.int64)
            if len(t) != len(s) or np.any(np.diff(t) < 0):
                raise InputError(f"{name}: bag times must be one per message and never go back")
            encoded.append(magnetic_field_template(name).encode(s, np.asarray(vectors[k], dtype=float).reshape(-1, 3)))
            events += [(bt, k, i) for i, bt in enumerate(t.tolist())]
        events.sort()
        for a in range(0, len(events), 8 * SETS_PER_WRITE):
            sink.write_messages([(conns[k], bt, bytes(encoded[k][i])) for bt, k, i in events[a : a + 8 * SETS_PER_WRITE]])


def _write_side_topics(sink: BagSink, recording: Recording, imu_stream: ImuStream | None, imu_topic: str) -> None:
    """The recording's temperatures (``/<name>/temperature``) and IMU (``imu_topic``, or ``imu_stream``)."""
    store = typestore()
    if recording.temperatures is not None:
        conns = [sink.add_topic(topics.absolute(topics.temperature(n)), TEMPERATURE) for n in recording.names]
        sink.write_messages([
            (conn, t, bytes(store.serialize_cdr(temperature_message(t, celsius, name), TEMPERATURE)))
            for t, row in zip(recording.stamps.tolist(), recording.temperatures.tolist())
            for conn, name, celsius in zip(conns, recording.names, row)
        ])
    if imu_stream is None and recording.imu is not None:
        imu = recording.imu
        imu_stream = ImuStream(recording.stamps, imu.orientation, imu.angular_velocity, imu.frame_id)
    if imu_stream is not None:
        conn = sink.add_topic(topics.absolute(imu_topic), IMU)
        sink.write_messages([
            (conn, t, bytes(store.serialize_cdr(imu_message(t, q, w, imu_stream.frame_id), IMU)))
            for t, q, w in zip(imu_stream.stamps.tolist(), imu_stream.orientation, imu_stream.angular_velocity)
        ])

"""Open a recording from a path: a CSV file or a rosbag2 directory (sqlite3 or mcap), with the
currents of its interference channels, the sensors' temperatures and the IMU (CSV columns, or
bag topics matched to the sets by the rule of :mod:`magcal_ros.core.matching`)."""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.imu import DEFAULT_IMU_TOLERANCE, ImuStats, imu_frame, match_imu
from magcal_ros.core.interference import (
    DEFAULT_CURRENT_TOLERANCE,
    CurrentStats,
    match_currents,
    tolerance_of,
)
from magcal_ros.core.matching import MatchStats, match_latest
from magcal_ros.core.recording import Recording
from magcal_ros.core.side_streams import SideCounts
from magcal_ros.core.sync import (
    DEFAULT_MAX_GAP,
    DEFAULT_SYNC_MODE,
    DEFAULT_SYNC_TOLERANCE,
    SyncStats,
    stream_synchronizer,
    synchronise_streams,
)
from magcal_ros.core.temperature import DEFAULT_TEMPERATURE_TOLERANCE, TemperatureStats
from magcal_ros.errors import InputError
from magcal_ros.io.csv_recording import read_csv, read_csv_names

if TYPE_CHECKING:
    from rosbags.rosbag2 import Reader

    from magcal_ros.io.bag_reader import SideReading


def is_csv(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` names a CSV recording (by its ``.csv`` ending)."""
    return str(path).lower().endswith(".csv")


def recording_sensors(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """Sensor names a recording holds, without reading its data.

    A CSV's column stems (header order); a bag's ``/<name>/raw`` MagneticField topics (sorted).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p} does not exist")
    if is_csv(p):
        return read_csv_names(p)
    from magcal_ros.io.bag_reader import open_bag, sensor_names_of

    if p.is_file() and p.suffix not in (".db3", ".mcap"):
        raise InputError(f"{p}: not a recording: give a rosbag2 directory or a .csv file")
    with open_bag(p) as reader:
        return sensor_names_of(reader)


def read_recording(path: str | os.PathLike[str], **options: object) -> Recording:
    """Synchronized raw sets from ``path`` (options as :func:`open_recording`)."""
    return open_recording(path, **options)[0]  # type: ignore[arg-type]


def open_recording(
    path: str | os.PathLike[str],
    names: tuple[str, ...] | None = None,
    start_ns: int | None = None,
    end_ns: int | None = None,
    tolerance: float | None = None,
    nonfinite: Literal["drop", "error"] = "drop",
    progress: Callable[[int], None] | None = None,
    sync_mode: str = DEFAULT_SYNC_MODE,
    max_gap: float = DEFAULT_MAX_GAP,
    time_offsets: dict[str, float] | None = None,
    imu_orientation_frame: str = "enu",
) -> tuple[Recording, SyncStats]:
    """Synchronized raw sets from ``path``, restricted to sensors ``names`` and a stamp window.

    CSV rows are sets already; bag topics ``/<name>/raw`` are synchronised by the rule of
    :mod:`magcal_ros.core.sync` (``sync_mode``: ``auto``, ``exact`` within ``tolerance``
    seconds (default :data:`~magcal_ros.core.sync.DEFAULT_SYNC_TOLERANCE`) or
    ``interpolate`` never across more than ``max_gap`` s, 0 automatic). Both go through the
    same acceptance rule: repeated, out-of-order and (bags) zero stamps are dropped and
    counted; NaN readings are dropped (``nonfinite="drop"``) or refused (``"error"``). Also
    returns those counts. A CSV's temperature and IMU columns come with its sets
    (``imu_orientation_frame``: the world frame of its ``imu.q*`` columns, ``enu`` or ``ned``);
    a bag's side topics are added by :func:`with_bag_temperatures` and :func:`with_bag_imu`.

    ``time_offsets`` (s by sensor name): a sensor's reading stamped ``t`` is the field at
    ``t - offset``; its stamps are shifted and its readings interpolated to the reference
    sensor's instants (a CSV's columns as much as a bag's topics). The stamp window applies
    to the sets' stamps.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p} does not exist")
    tol = DEFAULT_SYNC_TOLERANCE if tolerance is None else tolerance
    if is_csv(p):
        if p.is_dir():
            raise InputError(f"{p} is a directory, not a CSV file")
        try:
            rec, stats = read_csv(p, nonfinite, imu_orientation_frame)
        except InputError as exc:
            raise (exc if str(p) in str(exc) else InputError(f"{p}: {exc}")) from None
        if names:
            rec = rec.select(tuple(names))
        stream_synchronizer(rec.names, tol, sync_mode, max_gap, time_offsets)  # the settings, checked
        if time_offsets and any(time_offsets.values()):
            rec, stats = _shifted_rows(p, rec, stats, max_gap, time_offsets)
    else:
        from magcal_ros.io.bag_reader import read_bag_sets

        if p.is_file() and p.suffix not in (".db3", ".mcap"):
            raise InputError(f"{p}: not a recording: give a rosbag2 directory or a .csv file")
        rec, stats = read_bag_sets(p, names, tolerance=tol, nonfinite=nonfinite, progress=progress,
                                   sync_mode=sync_mode, max_gap=max_gap, time_offsets=time_offsets)
    why = stats.disorder()
    if why:
        raise InputError(f"{p}: {why}")
    rec = rec.window(start_ns, end_ns)
    if len(rec) == 0:
        raise InputError(f"{p}: no synchronized sets in the selected time window")
    return rec, stats


def _shifted_rows(path: Path, rec: Recording, stats: SyncStats, max_gap: float,
                  time_offsets: dict[str, float]) -> tuple[Recording, SyncStats]:
    """A CSV's rows with each sensor's column shifted by its time offset, resampled at the first
    sensor's instants; each set keeps the currents, temperatures and IMU of the row nearest it."""
    streams = [(rec.stamps, rec.vectors[:, k]) for k in range(len(rec.names))]
    batch, moved, _ = synchronise_streams(streams, [time_offsets.get(n, 0.0) for n in rec.names], "interpolate",
                                          max_gap, names=rec.names, reject_zero=False)
    if len(batch) == 0:
        raise InputError(f"{path}: no sets left after shifting by the time offsets ({moved.describe()})")
    merged = SyncStats(**{k: v for k, v in stats.as_dict().items()})
    merged.sets = moved.sets
    for name in ("unmatched", "gap", "glitch"):
        setattr(merged, name, getattr(merged, name) + getattr(moved, name))
    at = np.clip(np.searchsorted(rec.stamps, batch.set_stamps), 1, max(len(rec) - 1, 1))
    nearer = np.where(batch.set_stamps - rec.stamps[at - 1] <= rec.stamps[at] - batch.set_stamps, at - 1, at)
    side = rec.take(nearer)
    return replace(side, stamps=batch.set_stamps, vectors=batch.vectors), merged


# --------------------------------------------------------------------------- a bag's side topics


@dataclass(frozen=True)
class SideTopicKind:
    """What differs between a bag's currents, temperatures and IMU when they are read with its sets: one
    table row per kind (:data:`CURRENTS`, :data:`TEMPERATURES`, :data:`IMU_TOPIC`) instead of one function each.
    The range check of each kind's values is :mod:`magcal_ros.core.side_streams`' (the bag readers apply it).
    """

    what: str
    """The kind in messages (``the current tolerance``) and :func:`~magcal_ros.core.interference.tolerance_of`."""
    csv_refusal: str
    """Why a CSV path is refused: where a CSV gives this kind instead."""
    stamps: str
    """Whose stamps to check when no set is left (``the topics'``)."""
    stats: type[MatchStats]
    """The counts of the sets dropped (:class:`CurrentStats`, :class:`TemperatureStats`, :class:`ImuStats`)."""
    reading: Callable[[Reader, Path, Recording, SideTopics], SideReading | None]
    """The kind's topics in the open bag (None: the bag has none and none were named)."""
    match: Callable[[NDArray[np.int64], Any, int], tuple[Any, NDArray[np.bool_]]]
    """The matching rule: (set stamps, samples, tolerance ns) to (values, fresh (N, m))."""
    streams: Callable[[Recording, SideTopics, Any], tuple[str, ...]]
    """The streams the stats count (channels, sensors, the IMU topic)."""
    counts: Callable[[Any], list[SideCounts]]
    """What each stream's samples came to."""
    attach: Callable[[Recording, tuple[str, ...], Any], Recording]
    """The recording with the matched values."""
    options: Callable[[SideTopics], object] = lambda request: None
    """Checks the request's kind-specific options (:class:`InputError`), before the bag is opened."""

    def refuse_csv(self, path: Path) -> None:
        """:class:`InputError` for a CSV path: its topics are a bag's."""
        if is_csv(path):
            raise InputError(f"{path}: {self.csv_refusal}")

    def checked(self, path: Path, request: SideTopics) -> int:
        """The request's tolerance in ns, once the path and the options are checked (:class:`InputError` for a
        CSV path, a bad option, a tolerance that is not a finite number >= 0)."""
        self.refuse_csv(path)
        self.options(request)
        return tolerance_of(request.tolerance, self.what)

    def matched(self, path: Path, recording: Recording, request: SideTopics, samples: Any,
                tol: int) -> tuple[Recording, MatchStats]:
        """``recording`` with the samples matched to its sets, the sets without a value dropped and counted;
        :class:`InputError` when none is left."""
        values, fresh = self.match(recording.stamps, samples, tol)
        streams = self.streams(recording, request, samples)
        stats = self.stats(streams, tol, self.counts(samples))
        keep = stats.keep(fresh)
        if not np.any(keep):
            raise InputError(f"{path}: {stats.describe()}: no set left; check {self.stamps} stamps or widen the "
                             "tolerance")
        return self.attach(recording, streams, values).take(keep), stats


@dataclass(frozen=True)
class SideTopics:
    """A request to read one kind of side topic of a bag with its sets."""

    kind: SideTopicKind
    topics: tuple[str, ...] | None = None
    """The topics (a sensor's temperatures: one per sensor or one for all; None: ``/<name>/temperature``
    when the bag has them); the IMU: one topic."""
    tolerance: float = 0.0
    """How much older than a set (s) its value may be (the IMU: also newer, to interpolate)."""
    frame: str = "enu"
    """The IMU's orientation frame (``enu`` or ``ned``, turned into ENU)."""


def _current_reading(reader: Reader, path: Path, recording: Recording, request: SideTopics) -> SideReading:
    from magcal_ros.io.bag_reader import current_reading

    return current_reading(reader, path, request.topics or ())


def _temperature_reading(reader: Reader, path: Path, recording: Recording, request: SideTopics) -> SideReading | None:
    from magcal_ros.io.bag_reader import temperature_reading, temperature_topics

    found = list(request.topics) if request.topics else temperature_topics(reader, recording.names)
    return None if found is None else temperature_reading(reader, path, recording.names, found)


def _imu_reading(reader: Reader, path: Path, recording: Recording, request: SideTopics) -> SideReading:
    from magcal_ros.io.bag_reader import imu_reading

    return imu_reading(reader, path, (request.topics or ("",))[0], imu_frame(request.frame))


CURRENTS = SideTopicKind(
    what="current",
    csv_refusal="current topics are for bags; a CSV recording gives its currents as current.<channel> columns",
    stamps="the topics'", stats=CurrentStats, reading=_current_reading, match=match_currents,
    streams=lambda rec, req, samples: tuple(s.channel for s in samples),
    counts=lambda samples: [s.counts for s in samples if s.counts],
    attach=lambda rec, channels, currents: rec.with_currents(channels, currents),
)
"""Current channels: each set takes each channel's latest value not newer than it, at most the tolerance older."""
TEMPERATURES = SideTopicKind(
    what="temperature",
    csv_refusal="temperature topics are for bags; a CSV recording gives them as temperature.<name> columns",
    stamps="the topics'", stats=TemperatureStats, reading=_temperature_reading, match=match_latest,
    streams=lambda rec, req, samples: rec.names,
    counts=lambda samples: [s.counts for s in samples if s.counts],
    attach=lambda rec, names, values: rec.with_temperatures(values),
)
"""The sensors' temperatures: each set takes each sensor's latest value not newer than it, at most the tolerance
older."""
IMU_TOPIC = SideTopicKind(
    what="IMU",
    csv_refusal="IMU topics are for bags; a CSV recording gives them as imu.qx,...,imu.wz columns",
    stamps="the topic's", stats=ImuStats, reading=_imu_reading,
    match=lambda stamps, stream, tol: _fresh_columns(match_imu(stamps, stream, tol)),
    streams=lambda rec, req, stream: (req.topics or ("",))[0:1],
    counts=lambda stream: [stream.counts] if stream.counts else [],
    attach=lambda rec, topics, imu: rec.with_imu(imu),
    options=lambda request: imu_frame(request.frame),
)
"""The IMU: interpolated to each set's instant, or the latest sample propagated
(:func:`~magcal_ros.core.imu.match_imu`)."""


def _fresh_columns(matched: tuple[Any, NDArray[np.bool_]]) -> tuple[Any, NDArray[np.bool_]]:
    """A single stream's ``fresh`` (N,) as the (N, 1) of the stats."""
    return matched[0], matched[1][:, None]


def with_bag_side_streams(
    path: str | os.PathLike[str],
    recording: Recording,
    requests: Sequence[SideTopics],
    each: Callable[[SideTopics, MatchStats | None, Recording], None] | None = None,
) -> tuple[Recording, list[MatchStats | None]]:
    """``recording`` (read from the bag ``path``) with the side topics of every request at its sets, the bag
    opened and its side topics read once.

    The requests are checked (a CSV path, the options, the tolerances) and their topics found in the bag in
    their order; one pass reads every message of them all; then each kind is decoded and matched, in the
    requests' order, to the sets the previous ones left, by its own rule (:class:`SideTopicKind`): the same
    recording, counts and errors as :func:`with_bag_currents`, :func:`with_bag_temperatures` and
    :func:`with_bag_imu` one after the other (except that a missing or mistyped topic of any request is
    refused before any is read).
    Returns the recording and each request's stats (None: a temperature request the bag has no topics for,
    the recording unchanged). ``each(request, stats, recording)`` is called after each kind is matched.
    """
    from magcal_ros.io.bag_reader import open_bag, read_side_rows

    p = Path(path)
    tolerances = [request.kind.checked(p, request) for request in requests]
    with open_bag(p) as reader:
        readings = [r.kind.reading(reader, p, recording, r) for r in requests]
        rows = read_side_rows(reader, [r for r in readings if r is not None])
    out: list[MatchStats | None] = []
    taken = iter(rows)
    for request, reading, tol in zip(requests, readings, tolerances):
        stats = None
        if reading is not None:
            samples = reading.decode(next(taken))
            recording, stats = request.kind.matched(p, recording, request, samples, tol)
        out.append(stats)
        if each is not None:
            each(request, stats, recording)
    return recording, out


def with_bag_currents(
    path: str | os.PathLike[str],
    recording: Recording,
    topics: Sequence[str],
    tolerance: float = DEFAULT_CURRENT_TOLERANCE,
) -> tuple[Recording, CurrentStats]:
    """``recording`` (read from the bag ``path``) with the currents of ``topics`` at its sets.

    Each channel's current at a set is its latest value not newer than the set's stamp
    and at most ``tolerance`` s older (:func:`~magcal_ros.core.interference.match_currents`);
    sets without such a value of every channel are dropped and counted. Channel names are
    the topics without their leading ``/``. Raises :class:`InputError` for a CSV path, a
    missing or mistyped topic, or when no set keeps a current of every channel.
    """
    rec, (stats,) = with_bag_side_streams(path, recording, [SideTopics(CURRENTS, tuple(topics), tolerance)])
    return rec, stats  # type: ignore[return-value]


def with_bag_temperatures(
    path: str | os.PathLike[str],
    recording: Recording,
    topics: Sequence[str] | None = None,
    tolerance: float = DEFAULT_TEMPERATURE_TOLERANCE,
) -> tuple[Recording, TemperatureStats | None]:
    """``recording`` (read from the bag ``path``) with each sensor's temperature (deg C) at its sets.

    ``topics``: one ``sensor_msgs/msg/Temperature`` topic per sensor (or one for all); None: the
    bag's ``/<name>/temperature`` topics when it has them (the recording returned unchanged, and
    no stats, when it has none). Each sensor's temperature at a set is its latest value not
    newer than the set's stamp and at most ``tolerance`` s older; sets without one of every
    sensor are dropped and counted. :class:`InputError` for a CSV path, a missing or mistyped
    topic, or when no set keeps a temperature of every sensor.
    """
    request = SideTopics(TEMPERATURES, tuple(topics) if topics else None, tolerance)
    rec, (stats,) = with_bag_side_streams(path, recording, [request])
    return rec, stats  # type: ignore[return-value]


def with_bag_imu(
    path: str | os.PathLike[str],
    recording: Recording,
    topic: str,
    tolerance: float = DEFAULT_IMU_TOLERANCE,
    orientation_frame: str = "enu",
) -> tuple[Recording, ImuStats]:
    """``recording`` (read from the bag ``path``) with the IMU of the ``sensor_msgs/msg/Imu`` topic
    ``topic`` at its sets (:func:`~magcal_ros.core.imu.match_imu`: interpolated to the set instant when
    samples bracket it within ``tolerance`` s, else the latest sample at most ``tolerance`` s older,
    propagated with its angular velocity). Sets without an IMU sample are dropped and counted.
    ``orientation_frame``: ``ned`` when the IMU gives its orientation to north-east-down (turned
    into ENU). :class:`InputError` for a CSV path, a missing or mistyped topic, or no set left.
    """
    request = SideTopics(IMU_TOPIC, (topic,), tolerance, orientation_frame)
    rec, (stats,) = with_bag_side_streams(path, recording, [request])
    return rec, stats  # type: ignore[return-value]

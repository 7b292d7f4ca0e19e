"""Open a recording from a path: a CSV file or a rosbag2 directory (sqlite3 or mcap), with the
currents of its interference channels, the sensors' temperatures and the IMU (CSV columns, or
bag topics matched to the sets by the rule of :mod:`magcal_ros.core.matching`)."""

from __future__ import annotations

import os
from dataclasses import replace
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from magcal_ros.core.imu import DEFAULT_IMU_TOLERANCE, ImuStats, imu_frame, match_imu
from magcal_ros.core.interference import (
    DEFAULT_CURRENT_TOLERANCE,
    CurrentStats,
    match_currents,
    tolerance_of,
)
from magcal_ros.core.matching import match_latest
from magcal_ros.core.recording import Recording
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
    from magcal_ros.io.bag_reader import open_bag, read_current_samples

    p = Path(path)
    if is_csv(p):
        raise InputError(f"{p}: current topics are for bags; a CSV recording gives its currents as "
                         "current.<channel> columns")
    tol = tolerance_of(tolerance)
    with open_bag(p) as reader:
        samples = read_current_samples(reader, p, topics)
    currents, fresh = match_currents(recording.stamps, samples, tol)
    stats = CurrentStats(tuple(s.channel for s in samples), tol, [s.counts for s in samples if s.counts])
    keep = stats.keep(fresh)
    if not np.any(keep):
        raise InputError(f"{p}: {stats.describe()}: no set left; check the topics' stamps or widen the tolerance")
    out = recording.with_currents(stats.channels, currents).take(keep)
    return out, stats


def _bag_only(path: Path, what: str, columns: str) -> None:
    if is_csv(path):
        raise InputError(f"{path}: {what} topics are for bags; a CSV recording gives them as {columns} columns")


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
    from magcal_ros.io.bag_reader import open_bag, read_temperature_samples, temperature_topics

    p = Path(path)
    _bag_only(p, "temperature", "temperature.<name>")
    tol = tolerance_of(tolerance, "temperature")
    with open_bag(p) as reader:
        found = list(topics) if topics else temperature_topics(reader, recording.names)
        if found is None:
            return recording, None
        samples = read_temperature_samples(reader, p, recording.names, found)
    values, fresh = match_latest(recording.stamps, samples, tol)
    stats = TemperatureStats(recording.names, tol, [s.counts for s in samples if s.counts])
    keep = stats.keep(fresh)
    if not np.any(keep):
        raise InputError(f"{p}: {stats.describe()}: no set left; check the topics' stamps or widen the tolerance")
    return recording.with_temperatures(values).take(keep), stats


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
    from magcal_ros.io.bag_reader import open_bag, read_imu_stream

    p = Path(path)
    _bag_only(p, "IMU", "imu.qx,...,imu.wz")
    frame = imu_frame(orientation_frame)
    tol = tolerance_of(tolerance, "IMU")
    with open_bag(p) as reader:
        stream = read_imu_stream(reader, p, topic, frame)
    imu, fresh = match_imu(recording.stamps, stream, tol)
    stats = ImuStats((topic,), tol, [stream.counts] if stream.counts else [])
    keep = stats.keep(fresh[:, None])
    if not np.any(keep):
        raise InputError(f"{p}: {stats.describe()}: no set left; check the topic's stamps or widen the tolerance")
    return recording.with_imu(imu).take(keep), stats

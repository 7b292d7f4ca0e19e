"""Offline correction (``magcal correct``): a calibration applied to every set of a recording.

Bag to bag streams in chunks through :class:`~magcal_ros.io.bag_reader.SetReader` and
:class:`~magcal_ros.io.bag_writer.BagSink` (memory stays flat); anything involving CSV
goes through an in-memory :class:`~magcal_ros.core.recording.Recording`. Outputs carry the
same topics and types as the live correction node, every stamp exactly the input's.

A calibration with interference channels subtracts ``interference @ u`` per sensor, ``u``
the channels' currents at each set: from a CSV's ``current.<channel>`` columns, or from
bag topics (:func:`~magcal_ros.io.bag_reader.read_current_samples`) matched to each set
by time (:func:`~magcal_ros.core.interference.match_currents`); sets without a fresh
current of every channel are dropped and counted. A calibration with temperature terms
needs each sensor's temperature the same way: a CSV's ``temperature.<name>`` (or
``temperature``) columns, or a bag's ``/<name>/temperature`` topics (or the topics given),
``sensor_msgs/msg/Temperature``. A calibration that records the temperatures it was made at
(``<name>.calibration_temperatures``) has the sets' temperatures, where the recording has them,
compared with those: sets more than :data:`~magcal_ros.core.temperature.TEMPERATURE_MARGIN` outside
are counted per sensor and said in a note (:class:`~magcal_ros.core.temperature.SpanExcursions`); no
set is dropped or waits for a temperature it does not need. A calibration with an output frame writes
its ``frame_id`` unless another is given.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.calibration import ArrayCalibration, CorrectedSets
from magcal_ros.core.interference import (
    DEFAULT_CURRENT_TOLERANCE,
    CurrentStats,
    match_currents,
    tolerance_of,
)
from magcal_ros.core.matching import match_latest
from magcal_ros.core.recording import Recording
from magcal_ros.core.sync import DEFAULT_MAX_GAP, DEFAULT_SYNC_MODE, DEFAULT_SYNC_TOLERANCE, SetBatch, SyncStats
from magcal_ros.core.tensor import gradient, method_for
from magcal_ros.core.temperature import DEFAULT_TEMPERATURE_TOLERANCE, SpanExcursions, TemperatureStats
from magcal_ros.core.units import check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.atomic import atomic_path
from magcal_ros.io.bag_reader import (
    NonFinite,
    Progress,
    SetReader,
    open_bag,
    read_current_samples,
    read_temperature_samples,
    resolve_sensor_topics,
    sensor_names_of,
    temperature_topics,
)
from magcal_ros.io.bag_writer import (
    SETS_PER_WRITE,
    BagSink,
    SetLayout,
    Storage,
    check_bag_output,
    check_storage,
    storage_of,
)
from magcal_ros.io.cdr import (
    FLOAT64_MULTI_ARRAY,
    MAGNETIC_FIELD,
    VECTOR3_STAMPED,
    gradient_template,
    magnetic_field_template,
    vector3_stamped_template,
)
from magcal_ros.io.csv_recording import write_corrected_csv

if TYPE_CHECKING:
    from rosbags.interfaces import Connection

DEFAULT_FRAME_ID = topics.DEFAULT_FRAME_ID


@dataclass(frozen=True)
class CorrectionOutput:
    """Topics and templates of corrected output for ``names`` and the array's gradient kind."""

    layout: SetLayout
    sensor_template: Any
    gradient_template: Any
    baseline_template: Any
    sensors: int
    kind: str
    """``tensor`` (writes /gradient), ``baseline`` (/baseline_gradient) or ``none``."""
    withheld: bool = False
    """Only the corrected vectors: /field and the gradient withheld (a sensor is left raw)."""

    def encode(self, batch: SetBatch, sets: CorrectedSets) -> NDArray[np.uint8]:
        """Filled blocks for ``batch``: corrected vectors, centre field and the gradient per set."""
        blocks = self.layout.new(len(batch))
        off = self.layout.offsets
        for k in range(self.sensors):
            self.sensor_template.fill(blocks, off[k], batch.stamps[:, k], sets.vectors[:, k])
        if self.withheld:
            return blocks
        self.sensor_template.fill(blocks, off[self.sensors], batch.set_stamps, sets.centre)
        if self.kind == "tensor":
            self.gradient_template.fill(blocks, off[self.sensors + 1], sets.tensor)
        elif self.kind == "baseline":
            self.baseline_template.fill(blocks, off[self.sensors + 1], batch.set_stamps, sets.baseline)
        return blocks


def correction_output(sink: BagSink, names: Sequence[str], frame_id: str, kind: str = "tensor",
                      withheld: bool = False) -> CorrectionOutput:
    """Register ``/<name>/corrected``, ``/field`` and the gradient topic of ``kind`` on ``sink`` (``withheld``:
    the corrected vectors only)."""
    mf = magnetic_field_template(frame_id)
    gt = gradient_template()
    vt = vector3_stamped_template(frame_id)
    parts = [(sink.add_topic(topics.absolute(topics.corrected(n)), MAGNETIC_FIELD), mf.template) for n in names]
    if withheld:
        return CorrectionOutput(sink.layout(parts), mf, gt, vt, len(names), kind, True)
    parts.append((sink.add_topic(topics.absolute(topics.FIELD), MAGNETIC_FIELD), mf.template))
    if kind == "tensor":
        parts.append((sink.add_topic(topics.absolute(topics.GRADIENT), FLOAT64_MULTI_ARRAY), gt.template))
    elif kind == "baseline":
        parts.append((sink.add_topic(topics.absolute(topics.BASELINE_GRADIENT), VECTOR3_STAMPED), vt.template))
    return CorrectionOutput(sink.layout(parts), mf, gt, vt, len(names), kind)


def time_offsets_of(calibration: ArrayCalibration) -> dict[str, float]:
    """The calibration's non-zero time offsets (s) by sensor name (empty when there are none)."""
    return {n: float(t) for n, t in zip(calibration.geometry.names, calibration.time_offsets) if t}  # type: ignore[arg-type]


def withheld_note(raw: Sequence[str]) -> str:
    """Why a correction with sensors left raw (``--uncorrected``) writes the corrected vectors only."""
    return (f"field and gradient withheld: {', '.join(raw)} {'is' if len(raw) == 1 else 'are'} raw (--uncorrected), and "
            "a centre field or gradient with a raw sensor in it is wrong by its errors (thousands of nT/m); only "
            "the corrected vectors are written (a CSV has nan in the field and gradient columns)")


def check_sensors(
    calibration: ArrayCalibration,
    available: Sequence[str],
    recording: str | os.PathLike[str],
    calibration_file: str | os.PathLike[str],
    gradient_method: str = "difference",
) -> list[str]:
    """Match the calibration's sensors with the ``available`` sensors of a recording.

    A calibrated sensor the recording lacks is an :class:`InputError` naming it. Sensors
    of the recording the calibration lacks are an :class:`InputError` naming them when the
    calibrated sensors alone cannot give the tensor by ``gradient_method``; otherwise they
    are left out and reported in the returned notes.
    """
    names = calibration.geometry.names
    missing = [n for n in names if n not in available]
    extra = [n for n in available if n not in names]
    have = ", ".join(available) or "none"
    if missing:
        raise InputError(f"{recording} has no {', '.join(missing)} (its sensors: {have}); {calibration_file} covers {', '.join(names)}")
    if not extra:
        return []
    try:
        gradient(np.zeros((1, len(names), 3)), calibration.geometry, gradient_method)
    except InputError:
        raise InputError(
            f"{recording} has sensors {have} but {calibration_file} covers only {', '.join(names)}: "
            f"no calibration for {', '.join(extra)} (calibrate all {len(available)} sensors together)"
        ) from None
    return [f"{recording} also has {', '.join(extra)}, which {calibration_file} does not cover: left out"]


def check_channels(calibration: ArrayCalibration, given: Sequence[str], how: str) -> None:
    """:class:`InputError` unless the currents ``given`` cover the calibration's channels.

    ``how`` says where currents come from (for the message). With ``--currents`` every
    topic must be one of the calibration's channels (a surplus topic is likely a typo).
    """
    need = calibration.channels
    if not need:
        if given and how == "topics":
            raise InputError(f"--currents {','.join(given)} given, but the calibration subtracts no current "
                             "interference (it has no interference_channels)")
        return
    missing = [c for c in need if c not in given]
    if missing:
        where = ("--currents TOPIC,... (channel = topic without its leading '/')" if how == "topics"
                 else "current.<channel> columns")
        raise InputError(f"the calibration subtracts the interference of {', '.join(need)}: no current of "
                         f"{', '.join(missing)} (given: {', '.join(given) or 'none'}); give them as {where}")
    extra = [c for c in given if c not in need]
    if extra and how == "topics":
        raise InputError(f"the calibration has no interference for {', '.join(extra)} "
                         f"(its interference_channels: {', '.join(need)})")


def output_frame(calibration: ArrayCalibration, frame_id: str | None) -> str:
    """The frame of the corrected outputs: ``frame_id`` if given, else the calibration's, else the default."""
    return frame_id or calibration.frame_id or DEFAULT_FRAME_ID


def check_temperature_topics(calibration: ArrayCalibration, given: Sequence[str] | None) -> None:
    """:class:`InputError` when temperature topics are given for a calibration without temperature terms nor
    the temperatures it was made at (``calibration_temperatures``, which the sets' temperatures are compared
    with)."""
    if given and not calibration.has_temperature_terms and calibration.temperature_span is None:
        raise InputError(f"--temperature-topics {','.join(given)} given, but the calibration has no temperature terms "
                         "(no temperature_reference with offset_per_kelvin/matrix_per_kelvin) nor "
                         "calibration_temperatures")


def span_excursions(calibration: ArrayCalibration) -> SpanExcursions | None:
    """A counter of the sets corrected beyond the temperatures ``calibration`` was made at (None: unknown)."""
    span = calibration.temperature_span
    return None if span is None else SpanExcursions(calibration.geometry.names, span)


def temperature_span_notes(calibration: ArrayCalibration, recording: Recording, bag: str | os.PathLike[str] | None = None,
                           given: Sequence[str] | None = None,
                           tolerance: float = DEFAULT_TEMPERATURE_TOLERANCE) -> list[str]:
    """The notes on the sets of ``recording`` corrected beyond the temperatures ``calibration`` was made at
    (empty when within them, or either is unknown): its own temperatures, else those of the ``bag`` it was
    read from (the ``given`` topics, or ``/<name>/temperature`` when it has them), no set dropped."""
    watch = span_excursions(calibration)
    if watch is None:
        return []
    if recording.temperatures is not None:
        watch.add(recording.temperatures)
        return watch.notes()
    if bag is None:
        return []
    with open_bag(Path(bag)) as reader:
        found = _SpanWatch.of(reader, Path(bag), calibration, given, tolerance_of(tolerance, "temperature"))
    found.add(recording.stamps, None)
    return [] if found.excursions is None else found.excursions.notes()


@dataclass(frozen=True)
class CorrectionReport:
    """What :func:`correct_bag` did."""

    stats: SyncStats
    input_messages: int
    copied_messages: int
    output: str
    storage: str
    notes: tuple[str, ...] = ()
    """Sensors of the input left out (see :func:`check_sensors`)."""
    currents: CurrentStats | None = None
    """Sets dropped for lack of a fresh current (None: the calibration has no channels)."""
    temperatures: TemperatureStats | None = None
    """Sets dropped for lack of a fresh temperature (None: the calibration has no temperature terms)."""
    span: SpanExcursions | None = None
    """Sets beyond the temperatures the calibration was made at (None: those or the bag's temperatures
    unknown); :meth:`~magcal_ros.core.temperature.SpanExcursions.notes` says them."""


def _window(batch: SetBatch, start_ns: int | None, end_ns: int | None) -> SetBatch:
    if start_ns is None and end_ns is None:
        return batch
    t = batch.set_stamps
    keep = np.ones(len(t), bool)
    if start_ns is not None:
        keep &= t >= start_ns
    if end_ns is not None:
        keep &= t <= end_ns
    return batch.take(keep)


def correct_bag(
    in_path: str | os.PathLike[str],
    calibration: ArrayCalibration,
    out_path: str | os.PathLike[str],
    storage: Storage | None = None,
    copy_topics: Sequence[str] | Literal["all"] = (),
    progress: Progress | None = None,
    frame_id: str | None = None,
    gradient_method: str | None = "difference",
    tolerance: float = DEFAULT_SYNC_TOLERANCE,
    nonfinite: NonFinite = "drop",
    start_ns: int | None = None,
    end_ns: int | None = None,
    calibration_name: str = "the calibration",
    currents: Sequence[str] = (),
    current_tolerance: float = DEFAULT_CURRENT_TOLERANCE,
    sync_mode: str = DEFAULT_SYNC_MODE,
    max_gap: float = DEFAULT_MAX_GAP,
    temperature_topics: Sequence[str] | None = None,
    temperature_tolerance: float = DEFAULT_TEMPERATURE_TOLERANCE,
    raw_sensors: Sequence[str] = (),
) -> CorrectionReport:
    """Correct every synchronized set of ``in_path`` and write a new bag at ``out_path``.

    Writes ``/<name>/corrected`` (MagneticField, T, frame ``frame_id``, each sensor's own
    header stamp), ``/field`` (centre field, stamped with the set's stamp) and what the
    positions determine: ``/gradient`` (Float64MultiArray 3x3 row-major, T/m) for three or
    more sensors, ``/baseline_gradient`` (Vector3Stamped, dB/ds, T/m) for a collinear array,
    nothing for one sensor; all at bag time = the set's stamp; plus the
    input topics in ``copy_topics`` (``"all"``: every topic) unchanged with their bag
    times. ``storage`` defaults to the input's. ``start_ns``/``end_ns`` bound the set
    stamps. The bag's sensors are matched with the calibration's first (:func:`check_sensors`,
    ``calibration_name`` names the calibration in messages) and the readings must be in
    Tesla. ``currents``: the topics of the calibration's interference channels, each set's current the
    latest value at most ``current_tolerance`` s older than the set (sets without one are
    dropped and counted). Sets are formed by ``sync_mode`` (``auto``, ``exact`` within
    ``tolerance`` s, ``interpolate`` never across more than ``max_gap`` s) with the
    calibration's time offsets: a sensor whose ``time_offset`` is not zero is shifted and
    interpolated to the reference sensor's instants, and every output of a set is stamped
    with the set's instant. A calibration with temperature terms takes each sensor's temperature
    from ``temperature_topics`` (one per sensor or one for all; default ``/<name>/temperature``),
    the latest at most ``temperature_tolerance`` s older than the set (sets without one of every
    sensor are dropped and counted). ``frame_id``: the outputs' frame (default the calibration's,
    else ``magcal_array``). ``gradient_method`` None: the difference formula when the bag holds sensors
    the calibration lacks, else :func:`~magcal_ros.core.tensor.method_for` the calibration's geometry
    (decided here, so the bag is opened once). ``raw_sensors``: sensors left raw on purpose (their
    calibration is the identity, ``--uncorrected``): only the corrected vectors are written, ``/field``
    and the gradient withheld (:func:`withheld_note`). Streaming and atomic: nothing is left at
    ``out_path`` on failure.
    """
    names = calibration.geometry.names
    inp = Path(in_path)
    out_storage = check_storage(storage) if storage else storage_of(inp)
    check_bag_output(out_path, inp)
    check_channels(calibration, [topics.current_channel(t) for t in currents], "topics")
    check_temperature_topics(calibration, temperature_topics)
    tol = tolerance_of(current_tolerance)
    temp_tol = tolerance_of(temperature_tolerance, "temperature")
    frame_id = output_frame(calibration, frame_id)
    with open_bag(inp) as reader:
        available = sensor_names_of(reader)
        if gradient_method is None:
            gradient_method = "difference" if set(available) - set(names) else method_for(calibration.geometry)
        notes = check_sensors(calibration, available, inp, calibration_name, gradient_method)
        _, conns = resolve_sensor_topics(reader, inp, names)
        samples = read_current_samples(reader, inp, currents) if calibration.channels else []
        samples = sorted(samples, key=lambda c: calibration.channels.index(c.channel))
        current_stats = (CurrentStats(calibration.channels, tol, [c.counts for c in samples if c.counts])
                         if calibration.channels else None)
        temperatures, temperature_stats = [], None
        if calibration.has_temperature_terms:
            found = list(temperature_topics) if temperature_topics else _bag_temperature_topics(reader, inp, names)
            temperatures = read_temperature_samples(reader, inp, names, found)
            temperature_stats = TemperatureStats(names, temp_tol, [t.counts for t in temperatures if t.counts])
        span_watch = _SpanWatch.of(reader, inp, calibration, temperature_topics, temp_tol)
        extra = _copied(reader, inp, copy_topics, names)
        with atomic_path(out_path) as tmp, BagSink.create(tmp, out_storage) as sink:
            out = correction_output(sink, names, frame_id, calibration.geometry.gradient_kind, bool(raw_sensors))
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

            sets = SetReader(reader, inp, conns, tolerance, nonfinite, extra=extra, on_extra=on_extra, progress=progress,
                             sync_mode=sync_mode, max_gap=max_gap, time_offsets=time_offsets_of(calibration))
            n_in = 0
            checked = False
            for batch in sets:
                if not checked and len(batch):
                    check_tesla(batch.vectors, names, str(inp))  # before anything is written
                    checked = True
                batch = _window(batch, start_ns, end_ns)
                u = None
                if current_stats is not None:
                    u, fresh = match_currents(batch.set_stamps, samples, tol)
                    keep = current_stats.keep(fresh)
                    batch, u = batch.take(keep), u[keep]
                temps = None
                if temperature_stats is not None:
                    temps, fresh = match_latest(batch.set_stamps, temperatures, temp_tol)
                    keep = temperature_stats.keep(fresh)
                    batch, temps, u = batch.take(keep), temps[keep], None if u is None else u[keep]
                span_watch.add(batch.set_stamps, temps)
                for a in range(0, len(batch), SETS_PER_WRITE):
                    part = SetBatch(batch.stamps[a : a + SETS_PER_WRITE], batch.vectors[a : a + SETS_PER_WRITE])
                    part_u = None if u is None else u[a : a + SETS_PER_WRITE]
                    part_t = None if temps is None else temps[a : a + SETS_PER_WRITE]
                    sets_out = calibration.outputs(part.vectors, gradient_method, part_u, part_t)
                    sink.write_sets(out.layout, out.encode(part, sets_out), part.set_stamps)
                n_in += len(batch)
            _check_sets_written(inp, names, sets.stats, n_in, current_stats, temperature_stats)
    return CorrectionReport(sets.stats, n_in, copied[0], str(out_path), out_storage, tuple(notes), current_stats,
                            temperature_stats, span_watch.excursions)


@dataclass
class _SpanWatch:
    """The sets' temperatures compared with those a calibration was made at, chunk by chunk of a bag."""

    excursions: SpanExcursions | None = None
    samples: Sequence[Any] = ()
    """The sensors' temperature samples, when the calibration has no temperature terms (else the sets'
    own temperatures are compared)."""
    tolerance_ns: int = 0

    @classmethod
    def of(cls, reader: Any, path: Path, calibration: ArrayCalibration, given: Sequence[str] | None,
           tolerance_ns: int) -> _SpanWatch:
        """The watch of ``calibration`` on the bag open in ``reader`` (nothing watched when the calibration
        does not record its temperatures, or the bag has no temperature topics)."""
        watch = span_excursions(calibration)
        if watch is None or calibration.has_temperature_terms:
            return cls(watch)
        names = calibration.geometry.names
        found = list(given) if given else temperature_topics(reader, names)
        if not found:
            return cls()
        return cls(watch, read_temperature_samples(reader, path, names, found), tolerance_ns)

    def add(self, stamps: Any, temperatures: Any) -> None:
        """Count the sets stamped ``stamps`` (ns) at ``temperatures`` (N, S) deg C (None: matched here)."""
        if self.excursions is None:
            return
        if temperatures is not None:
            self.excursions.add(temperatures)
        elif self.samples:
            values, fresh = match_latest(stamps, self.samples, self.tolerance_ns)
            self.excursions.add(values, fresh)


def _check_sets_written(inp: Path, names: Sequence[str], stats: SyncStats, written: int,
                        current_stats: CurrentStats | None, temperature_stats: TemperatureStats | None) -> None:
    """:class:`InputError` naming why a correction wrote no set (or met stamps out of order)."""
    why = stats.disorder()
    if why:
        raise InputError(f"{inp}: {why}")
    if stats.sets == 0:
        raise InputError(f"{inp}: no complete synchronized sets of {', '.join(topics.absolute(topics.raw(n)) for n in names)} "
                         f"({stats.describe()})")
    if written == 0 and current_stats is not None and current_stats.dropped:
        raise InputError(f"{inp}: {current_stats.describe()}: no set left; check the topics' stamps or "
                         "widen --current-tolerance")
    if written == 0 and temperature_stats is not None and temperature_stats.dropped:
        raise InputError(f"{inp}: {temperature_stats.describe()}: no set left; check the topics' stamps or "
                         "widen --temperature-tolerance")
    if written == 0:
        raise InputError(f"{inp}: no synchronized sets in the selected time window")


def _copied(reader: Any, inp: Path, copy_topics: Sequence[str] | Literal["all"], names: Sequence[str]) -> list[Any]:
    """The input connections to copy unchanged (``"all"``, or the topics named); :class:`InputError` for a
    topic the bag lacks or one the corrected output writes itself."""
    outputs = {topics.absolute(t) for t in [*map(topics.corrected, names), topics.FIELD, topics.GRADIENT,
                                            topics.BASELINE_GRADIENT]}
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
    return extra


def _bag_temperature_topics(reader: Any, path: Path, names: Sequence[str]) -> list[str]:
    """The bag's ``/<name>/temperature`` topics, which a calibration with temperature terms needs."""
    found = temperature_topics(reader, names)
    if found is None:
        raise InputError(f"{path}: the calibration corrects for temperature, but the bag has no "
                         f"{', '.join(topics.absolute(topics.temperature(n)) for n in names)} "
                         "(sensor_msgs/msg/Temperature): name the temperature topics with --temperature-topics")
    return found


def write_corrected_bag(
    path: str | os.PathLike[str],
    recording: Recording,
    calibration: ArrayCalibration,
    storage: Storage = "sqlite3",
    frame_id: str | None = None,
    gradient_method: str = "difference",
    raw_sensors: Sequence[str] = (),
) -> None:
    """Corrected output of an in-memory ``recording`` (e.g. from CSV) as a bag; see :func:`correct_bag`
    (``raw_sensors`` as there).

    The recording must carry the currents of the calibration's channels and, for temperature
    terms, the sensors' temperatures (:func:`corrected_input`)."""
    check_bag_output(path)
    rec = corrected_input(recording, calibration)
    stamps = rec.stamps
    with atomic_path(path) as tmp, BagSink.create(tmp, check_storage(storage)) as sink:
        out = correction_output(sink, rec.names, output_frame(calibration, frame_id), calibration.geometry.gradient_kind,
                                bool(raw_sensors))
        for a in range(0, len(rec), SETS_PER_WRITE):
            ts = stamps[a : a + SETS_PER_WRITE]
            part = SetBatch(np.repeat(ts[:, None], len(rec.names), axis=1), rec.vectors[a : a + SETS_PER_WRITE])
            u = rec.currents[a : a + SETS_PER_WRITE] if rec.channels else None  # type: ignore[index]
            t = None if rec.temperatures is None else rec.temperatures[a : a + SETS_PER_WRITE]
            sink.write_sets(out.layout, out.encode(part, calibration.outputs(part.vectors, gradient_method, u, t)), ts)


def correct_recording_csv(
    path: str | os.PathLike[str],
    recording: Recording,
    calibration: ArrayCalibration,
    gradient_method: str = "difference",
    raw_sensors: Sequence[str] = (),
) -> int:
    """Correct an in-memory ``recording`` and write it atomically as CSV; returns the set count
    (``raw_sensors`` as :func:`correct_bag`'s: nan in the field and gradient columns).

    The recording must carry the currents of the calibration's channels and, for temperature
    terms, the sensors' temperatures (:func:`corrected_input`)."""
    rec = corrected_input(recording, calibration)
    sets = calibration.outputs(rec.vectors, gradient_method, rec.currents if rec.channels else None, rec.temperatures)
    write_corrected_csv(path, rec.stamps, rec.names, sets, withheld=bool(raw_sensors))
    return len(rec)


def corrected_input(recording: Recording, calibration: ArrayCalibration) -> Recording:
    """``recording`` restricted to the calibration's sensors and current channels, in its order.

    :class:`InputError` when a channel's currents are missing (:func:`check_channels`), or the
    temperatures a calibration with temperature terms needs.
    """
    check_channels(calibration, recording.channels, "columns")
    if calibration.has_temperature_terms and recording.temperatures is None:
        raise InputError("the calibration corrects for temperature: the recording has no temperatures (CSV: "
                         "temperature.<name> columns or one temperature column; bag: /<name>/temperature topics)")
    return recording.select(calibration.geometry.names).select_channels(calibration.channels)

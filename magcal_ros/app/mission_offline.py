"""The mission soak's mission processed offline, as on shore: recorded, corrected, recalibrated after each change.

The mission of :mod:`magcal_ros.app.soak` (receipt stamps, a driver restart, a silent sensor, the thermocline, the
IMU, a payload switched on, the hull's hard iron jumping) is written to a rosbag2 as a recorder would have
received it (bag time = arrival, header stamps as the drivers stamped them). Then, with the ``magcal`` command:

1. ``magcal correct`` with the starting calibration (the true one, as the soak's correction node starts with;
   without the payload's interference when :attr:`~magcal_ros.app.soak.SoakPlan.payload_known` is off);
2. after each change (the payload switched on when its interference is unknown, the hull change), ``magcal
   calibrate --prior`` over ``window`` s of the mission from ``settle`` s after it, with the IMU and the payload's
   current, the previous calibration as the prior; each span of the mission is then corrected with the latest
   calibration made before it (as a crew would: the stretch after a change, recalibrated from that stretch).

Per block of the mission, for both (the starting calibration throughout, and recalibrated), against the
simulator's truth: the tensor RMS over the floor ``sqrt(2) noise / baseline``, the TMI over the noise, with the
IMU the centre field's error in the IMU frame over ``noise / 2`` and the output frame's angle.
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.app.soak import (
    CHANNEL,
    INTENSITY,
    NOISE,
    Block,
    MissionSource,
    SoakPlan,
    field_floor,
    floor,
    fold_outputs,
    output_errors,
    write_start_calibration,
)
from magcal_ros.core.stamps import format_seconds, parse_seconds_column
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.io.cdr import (
    BATTERY_STATE,
    IMU,
    MAGNETIC_FIELD,
    TEMPERATURE,
    battery_state_message,
    imu_message,
    magnetic_field_message,
    temperature_message,
    typestore,
)
from magcal_ros.sim.imu import DEFAULT_IMU_FRAME_ID

Array = NDArray[np.float64]
START_NS = 1_700_000_000 * NS_PER_S
"""The mission's first instant (ns since the epoch) in the bag."""
IMU_TOPIC = "/imu"


@dataclass(frozen=True)
class OfflinePlan:
    """The mission and how the crew recalibrates it on shore."""

    mission: SoakPlan
    window: float = 300.0
    """s of the mission each recalibration uses."""
    settle: float = 30.0
    """s after a change before its recalibration window starts."""


@dataclass
class Recalibration:
    """One ``magcal calibrate --prior`` run after a change."""

    what: str
    start: float
    """Mission s of its first set."""
    end: float
    path: Path
    seconds: float
    """Wall s the command took."""
    summary: str


@dataclass
class OfflineOutcome:
    """What the offline run measured: blocks with the starting calibration throughout, and recalibrated."""

    plan: OfflinePlan
    start_blocks: dict[int, Block] = field(default_factory=dict)
    recal_blocks: dict[int, Block] = field(default_factory=dict)
    recalibrations: list[Recalibration] = field(default_factory=list)
    messages: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    """What ``magcal correct`` said (its warnings and notes), per span."""


def _message(store: Any, kind: int, index: int, stamp: int, value: Any, names: tuple[str, ...]) -> tuple[int, bytes]:
    """(connection key, serialized message) of one mission item (kinds as :meth:`MissionSource.stretch`)."""
    if kind == 0:
        sec, nsec = divmod(stamp, NS_PER_S)
        return index, bytes(store.serialize_cdr(magnetic_field_message(sec, nsec, names[index], value), MAGNETIC_FIELD))
    if kind == 1:
        return -1, bytes(store.serialize_cdr(battery_state_message(stamp, value), BATTERY_STATE))
    if kind == 2:
        return 100 + index, bytes(store.serialize_cdr(temperature_message(stamp, value, names[index]), TEMPERATURE))
    q, w = value
    return -2, bytes(store.serialize_cdr(imu_message(stamp, q, w, DEFAULT_IMU_FRAME_ID), IMU))


def write_mission_bag(source: MissionSource, path: Path, say: Callable[[str], None] = print) -> int:
    """Write the whole mission to the rosbag2 ``path`` in arrival order (bag time = arrival); how many messages."""
    from magcal_ros.io import topics
    from magcal_ros.io.atomic import atomic_path
    from magcal_ros.io.bag_writer import BagSink

    p, names, store = source.plan, source.names, typestore()
    count, shown = 0, time.monotonic()
    with atomic_path(path) as tmp, BagSink.create(tmp, "sqlite3") as sink:
        conns: dict[int, Any] = {i: sink.add_topic(topics.absolute(topics.raw(n)), MAGNETIC_FIELD)
                                 for i, n in enumerate(names)}
        conns[-1] = sink.add_topic(topics.current_topic(CHANNEL), BATTERY_STATE)
        conns.update({100 + i: sink.add_topic(topics.absolute(topics.temperature(n)), TEMPERATURE)
                      for i, n in enumerate(names)})
        if source.imu is not None:
            conns[-2] = sink.add_topic(IMU_TOPIC, IMU)
        t0, last = 0.0, -1
        while t0 < p.duration:
            t1 = min(t0 + p.chunk, p.duration)
            when, items = source.stretch(t0, t1)
            rows = []
            for arrival, (kind, index, stamp, value) in zip(when.tolist(), items):
                key, data = _message(store, kind, index, stamp, value, names)
                last = max(source.start_ns + int(round(arrival * NS_PER_S)), last + 1)  # never back
                rows.append((conns[key], last, data))
            sink.write_messages(rows)
            count += len(rows)
            t0 = t1
            if time.monotonic() - shown > 10.0:
                shown = time.monotonic()
                say(f"  writing the mission: {t0 / 60:.0f} of {p.duration / 60:.0f} min, {count:,} messages")
    return count


def _magcal(args: list[str]) -> tuple[int, str]:
    """Run the ``magcal`` command in this process: (exit code, what it printed on stdout and stderr)."""
    from magcal_ros.app.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        code = main(args)
    return code, out.getvalue()


def _seconds(source: MissionSource, mission: float) -> str:
    """The header stamp (s since the epoch) of mission time ``mission`` (s), for ``--start`` / ``--end``."""
    return format_seconds(source.start_ns + round(mission * NS_PER_S))


def read_outputs(path: Path) -> tuple[NDArray[np.int64], Array, Array]:
    """A corrected CSV's set stamps (ns), centre fields (n, 3) T and tensors (n, 3, 3) T/m (output frame)."""
    with open(path, encoding="utf-8") as fh:
        header = fh.readline().strip().split(",")
        rows = [line.strip().split(",") for line in fh if line.strip()]
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
    stamps = parse_seconds_column([r[0] for r in rows])
    values = np.array([r[1:] for r in rows], dtype=float)
    col = {name: k - 1 for k, name in enumerate(header)}
    fields = values[:, [col[f"field.{a}"] for a in "xyz"]]
    tensors = values[:, [col[f"gradient.{i}{j}"] for i in "xyz" for j in "xyz"]].reshape(-1, 3, 3)
    return stamps, fields, tensors


def correct_span(source: MissionSource, bag: Path, calibration: Path, span: tuple[float, float], out: Path,
                 blocks: dict[int, Block], with_current: bool) -> list[str]:
    """``magcal correct`` of the mission's ``span`` (mission s) with ``calibration``, folded into ``blocks``
    against the truth; the command's notes (lines that are not progress)."""
    args = [str(bag), "-c", str(calibration), "-o", str(out), "-q", "--start", _seconds(source, span[0]),
            "--end", _seconds(source, span[1])]
    if with_current:
        args += ["--currents", "/" + CHANNEL]
    code, text = _magcal(["correct", *args])
    if code != 0:
        raise RuntimeError(f"magcal correct failed ({code}):\n{text}")
    stamps, fields, tensors = read_outputs(out)
    keep = (stamps >= source.start_ns + span[0] * NS_PER_S) & (stamps < source.start_ns + span[1] * NS_PER_S)
    stamps, fields, tensors = stamps[keep], fields[keep], tensors[keep]
    if len(stamps):
        tensor_ss, tmi, field_err = output_errors(source, stamps, tensors, fields)
        fold_outputs(blocks, source.plan.block, (stamps - source.start_ns) / NS_PER_S, fields, tensor_ss, tmi,
                     field_err)
    return [line for line in text.splitlines() if line.strip()]


def recalibrate(source: MissionSource, bag: Path, prior: Path, what: str, span: tuple[float, float],
                out: Path) -> Recalibration:
    """``magcal calibrate --prior`` over the mission's ``span`` (s) with the IMU and the payload's current."""
    args = [str(bag), "-o", str(out), "--prior", str(prior), "--reference-field", f"{INTENSITY:.6g}", "-q",
            "--currents", "/" + CHANNEL, "--start", _seconds(source, span[0]), "--end", _seconds(source, span[1])]
    if source.imu is not None:
        args += ["--imu", IMU_TOPIC]
    w0 = time.monotonic()
    code, text = _magcal(["calibrate", *args])
    if code != 0:
        raise RuntimeError(f"magcal calibrate --prior after the {what} failed ({code}):\n{text}")
    return Recalibration(what, span[0], span[1], out, time.monotonic() - w0, text.strip())


def _changes(plan: SoakPlan) -> list[tuple[str, float]]:
    """The changes a crew recalibrates after (name, mission s), in order."""
    out = [] if plan.payload_known else [("payload switched on", plan.at(plan.current_at))]
    out.append(("hull change", plan.at(plan.hull_at)))
    return sorted(out, key=lambda c: c[1])


def run_offline(plan: OfflinePlan, workdir: Path, say: Callable[[str], None] = print) -> OfflineOutcome:
    """The mission written, corrected with the starting calibration, recalibrated after each change and corrected
    span by span with the latest calibration (see the module docstring)."""
    source = MissionSource(plan.mission, START_NS)
    outcome = OfflineOutcome(plan)
    bag, start_cal = workdir / "mission_bag", workdir / "start.yaml"
    w0 = time.monotonic()
    outcome.messages = write_mission_bag(source, bag, say)
    outcome.timings["write the bag"] = time.monotonic() - w0
    write_start_calibration(source, start_cal)
    p = plan.mission
    w0 = time.monotonic()
    say("correcting the whole mission with the starting calibration")
    outcome.notes += correct_span(source, bag, start_cal, (0.0, p.duration), workdir / "start.csv",
                                  outcome.start_blocks, p.payload_known)
    outcome.timings["correct with the starting calibration"] = time.monotonic() - w0
    spans: list[tuple[float, Path, bool]] = [(0.0, start_cal, p.payload_known)]
    for k, (what, at) in enumerate(_changes(p)):
        window = (at + plan.settle, min(at + plan.settle + plan.window, p.duration))
        say(f"recalibrating after the {what} from mission {window[0] / 60:.1f}-{window[1] / 60:.1f} min")
        rec = recalibrate(source, bag, spans[-1][1], what, window, workdir / f"recal{k + 1}.yaml")
        outcome.recalibrations.append(rec)
        spans.append((at, rec.path, True))
    w0 = time.monotonic()
    for k, (begin, cal, current) in enumerate(spans):
        end = spans[k + 1][0] if k + 1 < len(spans) else p.duration
        say(f"correcting mission {begin / 60:.1f}-{end / 60:.1f} min with {cal.name}")
        outcome.notes += correct_span(source, bag, cal, (begin, end), workdir / f"span{k}.csv", outcome.recal_blocks,
                                      current)
    outcome.timings["correct span by span"] = time.monotonic() - w0
    for k in range(int(math.ceil(p.duration / p.block))):  # offered sets per block, for both tables
        n = len(source.instants(0, k * p.block, min((k + 1) * p.block, p.duration)))
        for blocks in (outcome.start_blocks, outcome.recal_blocks):
            blocks.setdefault(k, Block()).sent = n
    return outcome


def offline_table(outcome: OfflineOutcome) -> list[str]:
    """Per block: the starting calibration throughout, and recalibrated after each change; then the recalibrations."""
    p = outcome.plan.mission
    fl = floor()
    imu = p.imu
    part = f"{'out':>7} {'tensor/fl':>9} {'TMI/noise':>9}" + (f" {'IMU/fl':>7} {'mdeg':>6}" if imu else "")
    lines = [f"{'':>12} {'':>7} | {'starting calibration throughout':^{len(part)}} | "
             f"{'recalibrated after each change':^{len(part)}}",
             f"{'block (min)':>12} {'sets':>7} | {part} | {part}"]

    def cells(b: Block) -> str:
        out = f"{b.outputs:7d} {b.tensor() / fl:9.2f} {b.tmi() / NOISE:9.2f}"
        return out + (f" {b.field_error() / field_floor():7.2f} {b.frame_error() * 1e3:6.2f}" if imu else "")

    for k in sorted(outcome.start_blocks):
        lo, hi = k * p.block / 60, min((k + 1) * p.block, p.duration) / 60
        a, b = outcome.start_blocks[k], outcome.recal_blocks.get(k, Block())
        lines.append(f"{lo:5.0f}-{hi:<6.0f} {a.sent:7d} | {cells(a)} | {cells(b)}")
    lines.append(f"events (mission min): restart of mag{p.restart_sensor + 1} {p.at(p.restart_at) / 60:.1f}, "
                 f"mag{p.silent_sensor + 1} silent {p.at(p.silent_at) / 60:.1f}-"
                 f"{(p.at(p.silent_at) + p.silent_for) / 60:.1f}, payload current on {p.at(p.current_at) / 60:.1f}"
                 f"{'' if p.payload_known else ' (its interference not in the starting calibration)'}, "
                 f"hull change {p.at(p.hull_at) / 60:.1f}")
    for r in outcome.recalibrations:
        first = r.summary.splitlines()[0] if r.summary else ""
        lines.append(f"recalibrated after the {r.what} from mission {r.start / 60:.1f}-{r.end / 60:.1f} min "
                     f"({r.seconds:.1f} s): {first[:160]}")
    lines.append("wall: " + ", ".join(f"{k} {v:.1f} s" for k, v in outcome.timings.items()) +
                 f"; {outcome.messages:,} messages")
    if imu:
        lines.append(f"IMU/fl: RMS per axis of the centre field's error in the IMU frame over noise / 2 = "
                     f"{field_floor() / NT:.2f} nT; mdeg: the output frame's angle off the IMU's")
    return lines

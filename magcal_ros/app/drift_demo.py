"""The demo's mission: a drift mid-run, seen and fixed, over DDS (used by the demo, a test and a benchmark).

With both nodes running and the correction node calibrated, a survey mission at ``RATE`` sets/s
is replayed into them (with the thrusters' currents, when there are thrusters): yaw turns
with +-5 deg of wobble, a magnetic target passed in the clean phase (the calibration health
must stay OK), then the hard iron of every sensor jumps by 300-800 nT. The demo waits for the
correction node's ``<node>: calibration`` status on ``/diagnostics`` to name the drift, for
the calibration node (``auto_recalibrate`` false) to advise what to fly while leaving the
calibration untouched, then sets ``auto_recalibrate`` true and waits for the recalibration
to be pushed; finally it replays fresh turns and measures the live tensor against the floor. A test
gives its own jump (one sensor's) and runs the calibration node with ``auto_recalibrate`` from the
start: the push is then awaited right after the drift is named.

Mission time is the sets' stamps; ``speed`` > 1 replays it faster than real time (the nodes
judge by stamps, so only the wall-clock waits shrink).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np

from magcal_ros.core.metrics import tensor_floor, tensor_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import parse_seconds
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.sim.mission import Leg, Target, mission
from magcal_ros.sim.simulator import ArraySimulation, hard_iron_moved

RATE = 100.0
"""Sets per second of the mission."""
YAW_RATE = 6.0
"""deg/s of the yaw turns."""
CHUNK = 5.0
"""Seconds of mission replayed between two looks at the statuses."""
TARGET = Target(15.0, 4.0, (0.0, 0.0, 80.0))
"""A dipole of 80 A m^2 passed 4 m below the track (about 250 nT at the array)."""


@dataclass
class DriftOutcome:
    """What the mission showed (times in mission seconds, tensor figures in T/m)."""

    clean_levels: list[int] = field(default_factory=list)
    """Levels of the calibration status judged during the clean phase."""
    named_after: float | None = None
    """Seconds of sets after the jump that the health had judged when it named the drift."""
    named: str = ""
    advice: str = ""
    untouched: bool = False
    """The correction node's calibration was the same after the advice as before the jump."""
    recalibrated_after: float | None = None
    """Seconds after auto_recalibrate was set true (or, when it was from the start, after the drift was named) at
    which the push was seen."""
    recalibrated: str = ""
    attempts: int = 0
    """Recalibrations the calibration node had tried when the push was seen (its status' ``attempts``)."""
    named_sensors: str = ""
    """The health's ``drifted_sensors`` when it named the drift."""
    tensor_drifted: float = float("nan")
    tensor_recalibrated: float = float("nan")
    floor: float = float("nan")
    final_health: str = ""


def _values(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values} if status is not None else {}


def _calibration_values(driver: Any, node: str, names: tuple[str, ...]) -> dict[str, Any]:
    wanted = [f"{n}.{k}" for n in names for k in ("matrix", "offset")]
    return driver.get_parameters(node, wanted)


def run_drift_mission(driver: Any, sim: ArraySimulation, rng: np.random.Generator, say: Callable[[str], None],
                      speed: float = 1.0, clean: float = 40.0, longest: float = 400.0, target_at: float = 15.0,
                      correction: str = "/magcal_correction", calibration: str = "/magcal_calibration",
                      max_current: float = 20.0, fresh: float = 40.0, patience: float = 120.0,
                      target_depth: float | None = None, moved: ArraySimulation | None = None,
                      advise: bool = True) -> DriftOutcome:
    """The mission (see the module docstring); ``clean`` s before the jump (the target passed at
    ``target_at`` s), at most ``longest`` s after it. Times are taken from the stamps the nodes judged
    (the health's ``newest_stamp``), so a node that lags the replay does not change them; ``patience``
    (s of wall time) is how long to wait for a node to catch up at the end of the clean phase;
    ``target_depth`` m below the track (default the demo's target's). ``moved``: the array after the
    jump (default every sensor's hard iron moved by 300-800 nT); ``advise`` false: the calibration node
    runs with ``auto_recalibrate`` true from the start, and the mission waits for the push right after
    the drift is named."""
    out = DriftOutcome(floor=tensor_floor(sim.noise, 0.4))
    driver.watch_diagnostics()
    health_name, recal_name = correction + ": calibration", calibration + ": recalibration"
    m = len(sim.thrusters)
    seconds = clean + longest
    count = int(seconds * RATE)
    currents = rng.uniform(0.0, max_current, (count, m)) if m else None
    jump = "the hard iron of " + ", ".join(n for n, a, b in zip(sim.geometry.names, sim.sensors, moved.sensors)
                                           if not np.array_equal(a.hard_iron, b.hard_iron)) + " jumps" if moved else \
        "every sensor's hard iron jumps by 300-800 nT"
    moved = moved or hard_iron_moved(sim, rng)
    target = replace(TARGET, seconds=target_at, distance=target_depth or TARGET.distance)
    # The mission starts a health window after whatever the correction node saw last (the driver's probe
    # sets, stamped now, all sensors reading one constant vector): judged by stamps, they are out of it.
    window = float(driver.get_parameters(correction, ["health_window"]).get("health_window") or 60.0)
    rec, _ = mission(sim, [Leg(seconds, YAW_RATE)], rng, rate=RATE, targets=[target], step=moved, step_at=clean,
                     start=time.time() + window + 1.0, currents=currents)
    jump_ns = int(rec.stamps[0]) + int(clean * NS_PER_S)
    say(f"mission: yaw turns at {YAW_RATE:g} deg/s with +-5 deg wobble, {RATE:g} sets/s, replayed at {speed:g}x real "
        f"time; a target ({np.linalg.norm(target.moment):.0f} A m^2, {target.distance:g} m below) passed at "
        f"{target.seconds:g} s; {jump} at {clean:g} s")
    before = _calibration_values(driver, correction, sim.geometry.names)

    def judged() -> tuple[Any, dict[str, str], float]:
        """The health status, its values and the mission time (s since the jump) of the newest set it judged."""
        status = driver.status(health_name)
        values = _values(status)
        newest = values.get("newest_stamp")
        return status, values, (parse_seconds(newest) - jump_ns) / NS_PER_S if newest else float("-inf")

    k = 0
    phase = "clean"
    auto_at: float | None = None
    patient = True  # false once a node did not catch up within patience: the replay then goes on regardless
    drifted_stamps: list[int] = []
    chunk = int(CHUNK * RATE)
    last_clean = int(np.searchsorted(rec.stamps, jump_ns))  # the replay stops there until the clean sets are judged
    while k < len(rec):
        part = rec.take(np.arange(k, min(k + chunk, last_clean if k < last_clean else len(rec))))
        _replay(driver, part, speed)
        k += len(part)
        t = (int(part.stamps[-1]) - jump_ns) / NS_PER_S  # mission time since the jump, as published
        health, hv, seen = judged()
        if phase == "clean":
            if k >= last_clean:  # let the node judge the clean phase before a drifted set reaches it
                out.clean_levels = _judge_clean(driver, health_name, jump_ns, clean, patience, say)
                phase = "drifting"
        elif phase == "drifting":
            drifted_stamps.extend(int(s) for s in part.stamps if int(s) > jump_ns)
            if hv.get("drifted") == "true" and seen >= 0:
                out.named_after, out.named, out.named_sensors = seen, health.message, hv.get("drifted_sensors", "")
                say(f"{seen:.0f} s after the jump (of sets judged) /diagnostics says: {health.message}")
                phase, auto_at = ("advising", None) if advise else ("recalibrating", t)
        elif phase == "advising":
            drifted_stamps.extend(int(s) for s in part.stamps)
            rv = _values(driver.status(recal_name))
            if rv.get("advice"):
                out.advice = rv["advice"]
                out.untouched = _calibration_values(driver, correction, sim.geometry.names) == before
                say(f"auto_recalibrate false: the calibration node advises: {out.advice}; the running calibration "
                    f"{'is untouched' if out.untouched else 'CHANGED'}")
                (ok, reason), = driver.set_parameters(calibration, {"auto_recalibrate": True})
                if not ok:
                    raise RuntimeError(f"the calibration node refused auto_recalibrate: {reason}")
                auto_at = t
                say("set auto_recalibrate true")
                phase = "recalibrating"
        elif phase == "recalibrating":  # the calibration node may lag: at most a chunk of sets behind the replay
            patient = patient and _wait(partial(_caught_up, driver, recal_name, int(part.stamps[0])), patience)
            if _pushed(_values(driver.status(recal_name)), out):
                out.recalibrated_after = t - (auto_at or t)
                say(f"{out.recalibrated_after:.0f} s later: {out.recalibrated}")
                break
    if phase == "recalibrating" and not out.recalibrated:  # the replay ended: the node may still be at it
        _await_push(driver, recal_name, patience, out, say)
    if drifted_stamps:  # a node (or this driver) that lags delivers them late: wait for them
        driver.wait_for_outputs(drifted_stamps, timeout=60.0, settle=5.0)
        g = driver.gradients(drifted_stamps)
        out.tensor_drifted = tensor_rms(np.stack(list(g.values()))) if g else float("nan")
    if not out.recalibrated:
        return out
    _fresh_turns(driver, moved, rng, (int(rec.stamps[k - 1]) + NS_PER_S) / NS_PER_S, speed, fresh, max_current,
                 health_name, out, say)
    return out


def _pushed(values: dict[str, str], out: DriftOutcome) -> bool:
    """Whether the recalibration status's ``values`` count a push; if so, it and the attempts go into ``out``."""
    if int(values.get("recalibrations", "0") or 0) < 1:
        return False
    out.recalibrated, out.attempts = values.get("last_recalibration", ""), int(values.get("attempts", "0") or 0)
    return True


def _await_push(driver: Any, recal_name: str, patience: float, out: DriftOutcome, say: Callable[[str], None]) -> None:
    """After the replay: wait up to ``patience`` s for the calibration node's push, into ``out``."""
    if _wait(lambda: _pushed(_values(driver.status(recal_name)), out), patience):
        say(f"after the replay: {out.recalibrated}")
    else:
        say(f"no recalibration by the end of the replay: {_values(driver.status(recal_name))}")


def _level(status: Any) -> int:
    """A diagnostic status's level as a number."""
    return int(status.level[0]) if isinstance(status.level, bytes) else int(status.level)


def _caught_up(driver: Any, name: str, stamp: int) -> bool:
    """Whether a node's status ``name`` says it has seen the sets up to ``stamp`` (ns)."""
    newest = _values(driver.status(name)).get("newest_stamp")
    return bool(newest) and parse_seconds(newest) >= stamp


def _judge_clean(driver: Any, health_name: str, jump_ns: int, clean: float, patience: float,
                 say: Callable[[str], None]) -> list[int]:
    """The replay held at the jump: wait up to ``patience`` s for a judgement of the clean phase's last
    ``CHUNK`` s (so that a node that lags judges clean sets at all), then the levels of every clean judgement."""
    recent = jump_ns - int(CHUNK * NS_PER_S)
    _wait(lambda: bool(_clean_judgements(driver, health_name, jump_ns, clean, None, since=recent)), patience)
    return _clean_judgements(driver, health_name, jump_ns, clean, say)


def _wait(ready: Callable[[], bool], patience: float) -> bool:
    """Poll ``ready`` until it holds (True) or ``patience`` s of wall time passed (False)."""
    deadline = time.monotonic() + patience
    while not ready():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.2)
    return True


def _clean_judgements(driver: Any, health_name: str, jump_ns: int, clean: float, say: Callable[[str], None] | None,
                      since: int = 0) -> list[int]:
    """The levels of every judgement of clean sets only (stamped before ``jump_ns``, the newest at or after
    ``since`` ns), as received: polling alone misses some when a node lags."""
    judged_all = [(st, _values(st)) for st in driver.statuses_of(health_name)]
    clean_statuses = [st for st, v in judged_all if v.get("figure") and v.get("newest_stamp")
                      and since <= parse_seconds(v["newest_stamp"]) < jump_ns]
    levels = [_level(st) for st in clean_statuses]
    shown = clean_statuses[-1].message if clean_statuses else "no judgement of clean sets"
    if say is not None:
        say(f"clean phase over ({clean:g} s, target passed): {len(clean_statuses)} judgements of clean sets, "
            f"levels {sorted(set(levels))}, the last: {shown}")
    return levels


def _fresh_turns(driver: Any, moved: ArraySimulation, rng: np.random.Generator, start: float, speed: float,
                 fresh: float, max_current: float, health_name: str, out: DriftOutcome,
                 say: Callable[[str], None]) -> None:
    """Fresh turns (``fresh`` s from ``start`` s) with the new calibration: the live tensor against the floor
    and the final health, into ``out``."""
    count = int(fresh * RATE)
    m = len(moved.thrusters)
    check, _ = mission(moved, [Leg(fresh, YAW_RATE)], rng, rate=RATE, start=start,
                       currents=rng.uniform(0.0, max_current, (count, m)) if m else None)
    driver.clear_outputs()
    _replay(driver, check, speed)
    stamps = [int(s) for s in check.stamps]
    driver.wait_for_outputs(stamps, timeout=60.0)
    g = driver.gradients(stamps[int(RATE):])  # the first second may still meet the push
    out.tensor_recalibrated = tensor_rms(np.stack(list(g.values()))) if g else float("nan")
    health = driver.status(health_name)
    out.final_health = health.message if health is not None else ""
    say(f"{len(g)} fresh sets after the recalibration: tensor RMS {out.tensor_recalibrated / NT:.2f} nT/m "
        f"({out.tensor_recalibrated / out.floor:.2f}x the floor); calibration health: {out.final_health}")


def _replay(driver: Any, rec: Recording, speed: float) -> None:
    """Publish ``rec`` with its own stamps at ``speed`` times its rate (with its currents)."""
    from magcal_ros.app.ros_driver import recording_messages

    messages = recording_messages(rec.names, rec.stamps, rec.vectors)
    driver.replay(messages, rate=RATE * speed, restamp=False,
                  currents=rec.currents if rec.channels else None)

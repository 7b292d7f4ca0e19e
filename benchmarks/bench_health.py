"""Calibration health and recalibration during the mission: cost, false alarms, detection delay.

    .venv/bin/python benchmarks/bench_health.py            # in-process figures (a minute or two)
    .venv/bin/python benchmarks/bench_health.py --dds      # plus the real-time 100 Hz mission over DDS (~4 min)

Prints:
- the cost of :class:`~magcal_ros.core.calibration_health.CalibrationHealth`: ``add`` per set
  (the correction node's hot path) and ``assess`` per status period (4 sensors, 60 blocks);
- on clean missions (yaw turns, a straight leg, slow turns, strong targets passed; true
  calibration running) the largest figure reported, in noise units (WARN at 10);
- for hard-iron steps of 50, 100 and 300 nT per axis on every sensor during yaw turns, the
  delay (s of sets) until the drift is named, and its level;
- with ``--dds``: the demo's mission through both nodes in real time at 100 sets/s (drift named
  after ..., advice, recalibration pushed, live tensor against the floor).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np


from magcal_ros.core.calibration_health import CalibrationHealth  # noqa: E402
from magcal_ros.core.field import earth_field  # noqa: E402
from magcal_ros.core.geometry import ArrayGeometry  # noqa: E402
from magcal_ros.core.units import NS_PER_S, NT  # noqa: E402
from magcal_ros.sim.mission import Leg, Target, mission  # noqa: E402
from magcal_ros.sim.simulator import ArraySimulation, hard_iron_moved, random_sensor_errors  # noqa: E402

F = 51_500 * NT
NOISE = 1.0 * NT
TARGETS = (Target(25.0, 4.0, (0.0, 0.0, 80.0)), Target(75.0, 3.0, (30.0, 0.0, 60.0)),
           Target(140.0, 4.0, (0.0, 40.0, 60.0)))


def array(seed: int) -> tuple[ArraySimulation, np.random.Generator]:
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross()
    return ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(F, 60.0, 5.0),
                           noise=NOISE), rng


def reports(sim: ArraySimulation, rec, rate: float) -> list[tuple[float, object]]:  # type: ignore[no-untyped-def]
    health = CalibrationHealth(sim.geometry, np.full(4, NOISE), F)
    corrected = sim.true_calibration().apply(rec.vectors)
    out = []
    t0 = int(rec.stamps[0])
    per = int(rate)
    for k, (stamp, v) in enumerate(zip(rec.stamps.tolist(), corrected)):
        health.add(stamp, v)
        if (k + 1) % per == 0:
            out.append(((stamp - t0) / NS_PER_S, health.assess()))
    return out


def cost() -> None:
    sim, rng = array(1)
    for rate in (100.0, 500.0, 1000.0):
        rec, _ = mission(sim, [Leg(81.0, 6.0)], rng, rate=rate)
        corrected = sim.true_calibration().apply(rec.vectors)
        rows = list(zip(rec.stamps.tolist(), corrected))
        first = int(61 * rate)
        health = CalibrationHealth(sim.geometry, np.full(4, NOISE), F)
        t0 = time.perf_counter()
        for stamp, v in rows[:first]:
            health.add(stamp, v)
        add_us = (time.perf_counter() - t0) / first * 1e6
        health.assess()
        per = int(rate)
        judge = []
        for k in range(first, len(rows) - per, per):  # one more second of sets, then the status period's judgement
            for stamp, v in rows[k:k + per]:
                health.add(stamp, v)
            t0 = time.perf_counter()
            health.assess()
            judge.append(time.perf_counter() - t0)
        print(f"  {rate:6.0f} sets/s: add {add_us:.2f} us/set; assess once per second (a block closed: block sums "
              f"of its {per} sets, then the fits of 60 blocks x 4 sensors) median {np.median(judge) * 1e3:.1f} ms")


def clean(seeds: range) -> None:
    worst = []
    alarms = judged = 0
    for seed in seeds:
        sim, rng = array(seed)
        rec, _ = mission(sim, [Leg(50.0, 6.0), Leg(60.0, 0.0), Leg(70.0, 2.0)], rng, rate=50.0, targets=TARGETS)
        rs = [r for _, r in reports(sim, rec, 50.0) if r.sensors]  # type: ignore[attr-defined]
        judged += len(rs)
        alarms += sum(r.drifted for r in rs)  # type: ignore[attr-defined]
        worst.append(max(float(r.values["figure"]) for r in rs))  # type: ignore[attr-defined]
    print(f"  {len(seeds)} clean missions of 180 s (turns, straight, slow turns, 3 targets of 250-400 nT): "
          f"{alarms} alarms in {judged} reports; largest figure per mission {np.round(worst, 2).tolist()} "
          f"(noise units; WARN at 10)")


def detection(seeds: range) -> None:
    for step in (50.0, 100.0, 300.0):
        delays, levels = [], []
        for seed in seeds:
            sim, rng = array(100 + seed)
            moved = hard_iron_moved(sim, rng, step * NT, step * NT)
            rec, _ = mission(sim, [Leg(160.0, 6.0)], rng, rate=50.0, targets=TARGETS[:1], step=moved, step_at=80.0)
            rs = reports(sim, rec, 50.0)
            named = [(t, r) for t, r in rs if t >= 80.0 and r.drifted]  # type: ignore[attr-defined]
            delays.append(named[0][0] - 80.0 if named else float("nan"))
            levels.append(rs[-1][1].level)  # type: ignore[attr-defined]
        print(f"  hard iron +-{step:.0f} nT per axis on every sensor during yaw turns: named after "
              f"{np.nanmin(delays):.0f}-{np.nanmax(delays):.0f} s of sets; level at the end "
              f"{sorted(set(levels))} (1 WARN, 2 ERROR)")


def dds() -> None:
    import tempfile
    from dataclasses import replace

    from magcal_ros.app.drift_demo import run_drift_mission
    from magcal_ros.app.ros_driver import ArrayDriver, NodeProcess, pick_domain_id, ros_args, ros_environment
    from magcal_ros.io import calibration_file as calfile

    sim, rng = array(3)
    work = Path(tempfile.mkdtemp(prefix="magcal_bench_health_"))
    calfile.write(work / "cal.yaml", replace(sim.true_calibration(), metadata={"noise": [NOISE] * 4, "intensity": F}))
    domain = pick_domain_id()
    env = ros_environment(domain)
    nodes = [NodeProcess("correction_node", ros_args(params_files=[work / "cal.yaml"]), env, work / "correction.log"),
             NodeProcess("calibration_node", ros_args(params={"reference_field": F, "calibration_file":
                                                              str(work / "cal.yaml")}), env, work / "calibration.log")]
    driver = ArrayDriver(sim.geometry.names, domain, node_name="magcal_bench_health")
    t0 = time.monotonic()
    try:
        if not (driver.wait_for_subscribers(2, 60.0) and driver.wait_for_output_publishers(60.0) and driver.prime(60.0)):
            raise RuntimeError("nodes not discovered")
        out = run_drift_mission(driver, sim, rng, lambda s: print(f"  [{time.monotonic() - t0:5.0f} s] {s}"))
    finally:
        driver.close()
        for p in nodes:
            p.stop()
    print(f"  real time, 100 sets/s, default parameters: drift named {out.named_after:.0f} s after the jump; "
          f"recalibrated {out.recalibrated_after:.0f} s after auto_recalibrate was set; live tensor "
          f"{out.tensor_recalibrated / out.floor:.2f}x the floor (drifted: {out.tensor_drifted / out.floor:.0f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dds", action="store_true", help="also the real-time mission over DDS (about 4 minutes)")
    args = parser.parse_args()
    print("cost:")
    cost()
    print("false alarms:")
    clean(range(1, 7))
    print("detection:")
    detection(range(4))
    if args.dds:
        print("over DDS:")
        dds()


if __name__ == "__main__":
    main()

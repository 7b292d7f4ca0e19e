"""End-to-end demo: simulate a rotation manoeuvre, calibrate it live over ROS 2, show the gain.

    python -m magcal_ros.app.demo [--sets 1200] [--rate 400] [--relative] [--no-thrusters] [--no-drift]
                                  [--speed 1] [--no-imu] [--keep DIR]

1. simulates a four-fluxgate cross (0.4 m) with realistic per-sensor errors, 1 nT noise,
   turning through random attitudes in a uniform 51 500 nT field, with two thrusters 0.7 m
   behind the array drawing random currents of 0-20 A while it turns (the survey runs them
   too), and writes the manoeuvre as a rosbag2 (``/magN/raw``, ``/thrusterN/battery``);
2. starts ``correction_node`` and ``calibration_node`` as separate processes, with localhost
   discovery only, on the ``ROS_DOMAIN_ID`` you set (it says so), else on a domain it picks
   that nothing on this machine uses (no DDS participant on it, no other run holding it);
   the calibration node collects the thrusters' currents (``sensor_msgs/BatteryState``)
   with the sets;
3. replays fresh survey sets (thrusters running) through the uncalibrated correction node
   (before), replays the manoeuvre into the calibration node, calls ``~/start`` and
   ``~/calibrate`` (calibration and the thrusters' interference solved jointly), replays
   the survey again with the correction node subtracting the live currents (after), and
   once more with the subtraction switched off, and prints the tensor and TMI residuals
   against the noise floor;
4. (unless ``--no-drift``) flies a survey mission at 100 sets/s in real time (``--speed``
   replays it faster) with the thrusters running: a target passed, then every sensor's hard
   iron jumps by 300-800 nT during yaw turns; the correction node's calibration health names
   the drift on ``/diagnostics``, the calibration node (``auto_recalibrate`` false) advises
   what to fly and changes nothing, then (set true) recalibrates from the sets flown since,
   and the live tensor on fresh turns is compared with the floor
   (:mod:`magcal_ros.app.drift_demo`; about 3 minutes in real time);
5. (unless ``--no-imu``) calibrates a tumble over a pier with the vehicle's IMU, offline
   (:mod:`magcal_ros.app.imu_demo`): the array-to-IMU rotation and the pier's gradient with
   their 1-sigma, and fresh attitudes corrected into the IMU's frame against the truth.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tensor_floor, tensor_rms, tmi_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.units import NT
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation, Thruster, random_sensor_errors

INTENSITY = 51_500 * NT
NOISE = 1.0 * NT
THRUSTERS: tuple[Thruster, ...] = (
    Thruster("thruster1/battery", np.array([-0.7, 0.25, 0.1]), np.array([0.06, 0.0, 0.04])),
    Thruster("thruster2/battery", np.array([-0.7, -0.25, 0.1]), np.array([0.0, -0.06, 0.04])),
)
"""Two thrusters 0.7 m behind the array (platform frame, m; dipole moment per ampere, A m^2/A)."""
MAX_CURRENT = 20.0
"""The thrusters draw random currents of 0..MAX_CURRENT A."""
BATTERY_STATE = "sensor_msgs/msg/BatteryState"


class Clock:
    """Prints progress lines with the elapsed time."""

    def __init__(self) -> None:
        self.start = time.monotonic()

    def say(self, text: str) -> None:
        """One progress line."""
        print(f"[demo {time.monotonic() - self.start:5.1f} s] {text}", flush=True)


def simulate(sets: int, fresh: int, seed: int, thrusters: bool = True) -> tuple[ArraySimulation, Recording, Recording]:
    """The array, a calibration manoeuvre and a separate survey of fresh attitudes (thrusters running in both)."""
    rng = np.random.default_rng(seed)
    geometry = ArrayGeometry.cross()
    sensors = tuple(random_sensor_errors(rng) for _ in geometry.names)
    sim = ArraySimulation(geometry, sensors, earth_field(INTENSITY, 60.0, 5.0), noise=NOISE,
                          thrusters=THRUSTERS if thrusters else ())
    m = len(sim.thrusters)
    manoeuvre, _ = sim.run(uniform_random(sets, rng), rng, rate=50.0, currents=rng.uniform(0, MAX_CURRENT, (sets, m)))
    check, _ = sim.run(uniform_random(fresh, rng), rng, rate=50.0, start=1000.0,
                       currents=rng.uniform(0, MAX_CURRENT, (fresh, m)))
    return sim, manoeuvre, check


def measure(driver, check: Recording, rate: float) -> tuple[float, float, int]:  # type: ignore[no-untyped-def]
    """Replay ``check`` (and its currents) into the correction node; tensor RMS (T/m), worst TMI RMS (T),
    sets received."""
    from magcal_ros.app.ros_driver import recording_messages

    driver.clear_outputs()
    mapping = driver.replay(recording_messages(check.names, check.stamps, check.vectors), rate=rate,
                            currents=check.currents if check.channels else None)
    stamps = list(mapping.values())
    driver.wait_for_outputs(stamps, timeout=180.0, settle=60.0)  # a busy machine delays, never loses
    gradients = driver.gradients(stamps)
    corrected = driver.corrected(stamps)
    if not gradients or not corrected:
        raise RuntimeError("the correction node published nothing; see its log")
    g = np.stack(list(gradients.values()))
    b = np.stack(list(corrected.values()))
    return tensor_rms(g), float(np.max(tmi_rms(b, INTENSITY))), len(gradients)


LOSSLESS = {"raw_reliability": "reliable", "qos_depth": 10000}
"""Reliable raw subscriptions with deep queues: on a busy machine the nodes fall behind and catch up, they
never drop the replayed sets."""
Row = tuple[str, float, float]
"""A line of the demo's table: label, tensor RMS (T/m), worst TMI RMS (T; NaN: not measured)."""


def start_nodes(nodes: list[Any], names: Sequence[str], channels: Sequence[str], calibration_file: Path,
                env: dict[str, str], work: Path, relative: bool) -> None:
    """Start ``correction_node`` (uncalibrated at first, on purpose: the "before" figures) and
    ``calibration_node`` (collecting the thrusters' currents with the sets) as processes in ``env``, logs in
    ``work``, each appended to ``nodes`` as soon as it runs (so that a failure stops those started)."""
    from magcal_ros.app.ros_driver import NodeProcess, ros_args

    raw = {"uncorrected_sensors": list(names), **LOSSLESS}
    nodes.append(NodeProcess("correction_node", ros_args(params=raw), env, work / "correction_node.log"))
    cal_params: dict[str, object] = {"calibration_file": str(calibration_file),
                                     "reference_field": 0.0 if relative else INTENSITY,
                                     "assess_period": 2.0, **LOSSLESS}
    if channels:
        cal_params["interference_channels"] = list(channels)  # currents on /thrusterN/battery, collected with the sets
    nodes.append(NodeProcess("calibration_node", ros_args(params=cal_params), env, work / "calibration_node.log"))


def calibrate_live(driver, bag: Path, manoeuvre: Recording, channels: Sequence[str], rate: float,  # type: ignore[no-untyped-def]
                   say: Any) -> bool:
    """``~/start``, the manoeuvre's bag replayed (with its currents), ``~/calibrate``; whether it succeeded."""
    from magcal_ros.app.ros_driver import bag_messages, wait_for_samples

    ok, message = driver.trigger("/magcal_calibration/start")
    say(f"~/start -> {message}")
    messages = bag_messages(bag)
    sent = driver.replay(messages, rate=rate, currents=manoeuvre.currents if channels else None)
    progress = wait_for_samples(driver, "magcal_calibration", len(sent), timeout=180.0)
    say(f"replayed {len(messages)} bag messages{' with the thruster currents' if channels else ''}; the "
        f"calibration node holds {progress.get('samples', '?')} sets, coverage "
        f"{float(progress.get('coverage', 0)):.0%}, ready={progress.get('ready', '?')}")
    ok, message = driver.trigger("/magcal_calibration/calibrate")
    say(f"~/calibrate -> success={ok}: {message}")
    return bool(ok)


def thruster_rows(driver, check: Recording, channels: Sequence[str], rate: float,  # type: ignore[no-untyped-def]
                  after: tuple[float, float], say: Any) -> list[Row]:
    """The calibrated rows: with thrusters, the survey again with their subtraction switched off."""
    if not channels:
        return [("after calibration", *after)]
    (ok, reason), = driver.set_parameters("magcal_correction", {"interference_channels": []})
    if not ok:
        raise RuntimeError(f"the correction node refused to stop subtracting: {reason}")
    t_off, tmi_off, n = measure(driver, check, rate)
    say(f"the same {n} survey sets with the thrusters' interference NOT subtracted")
    return [("calibrated, thrusters not compensated", t_off, tmi_off), ("calibrated, thrusters compensated", *after)]


def drift_rows(driver, sim: ArraySimulation, channels: Sequence[str], args: argparse.Namespace,  # type: ignore[no-untyped-def]
               say: Any) -> tuple[list[Row], Any]:
    """The drift mission (:mod:`magcal_ros.app.drift_demo`) with the thrusters subtracted again: its rows
    and outcome; RuntimeError when the drift was not named and fixed."""
    if channels:
        (ok, reason), = driver.set_parameters("magcal_correction", {"interference_channels": list(channels)})
        if not ok:
            raise RuntimeError(f"the correction node refused to subtract the thrusters again: {reason}")
    from magcal_ros.app.drift_demo import run_drift_mission

    drift = run_drift_mission(driver, sim, np.random.default_rng(args.seed + 1), say, speed=args.speed,
                              max_current=MAX_CURRENT)
    if drift.named_after is None or not drift.recalibrated:
        raise RuntimeError("the drift was not named and fixed; see the lines above and the node logs")
    return [("hard iron moved: drifted calibration", drift.tensor_drifted, float("nan")),
            ("recalibrated during the mission", drift.tensor_recalibrated, float("nan"))], drift


def print_table(rows: Sequence[Row], channels: Sequence[str], drift: Any, calibration_file: Path,
                keep: str | None) -> None:
    """The residuals against the noise floor, the drift's timings and where the calibration file is."""
    floor = tensor_floor(NOISE, 0.4)
    print()
    print(f"  {'fresh survey sets' + (' (thrusters running)' if channels else ''):44}{'tensor RMS':>12}"
          f"{'worst TMI RMS':>15}")
    for label, tensor, tmi in rows:
        tmi_text = f"{tmi / NT:10.2f} nT" if np.isfinite(tmi) else ""
        print(f"  {label:44}{tensor / NT:9.2f} nT/m{tmi_text}")
    print(f"  {'noise floor':44}{floor / NT:9.2f} nT/m{NOISE / NT:10.2f} nT")
    kept = "" if keep else " (removed at exit; --keep DIR keeps it)"
    if drift is not None:
        print(f"  drift named {drift.named_after:.0f} s after the jump (of sets judged); recalibrated "
              f"{drift.recalibrated_after:.0f} s after auto_recalibrate was set true")
    print(f"  calibration file: {calibration_file}{kept}")
    print()


def show_logs(nodes: Sequence[Any]) -> None:
    """The last lines of each node's log, on stderr (after a failure)."""
    for p in nodes:
        tail = "\n    ".join(p.log().splitlines()[-8:])
        print(f"--- last lines of {p.log_path.name}:\n    {tail}", file=sys.stderr)


MAX_DOMAIN_ID = 232
"""The largest ROS domain id (the RTPS ports of a larger one would pass 65535)."""


def demo_domain() -> tuple[int, str]:
    """The ROS domain of the demo and how it was chosen: the ``ROS_DOMAIN_ID`` the user set, else a free
    one leased by :func:`~magcal_ros.app.ros_driver.pick_domain_id`. RuntimeError (one line) for a
    ``ROS_DOMAIN_ID`` that is not a domain id."""
    import os

    from magcal_ros.app.ros_driver import domain_in_use, pick_domain_id

    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return pick_domain_id(), "a free one picked: no ROS_DOMAIN_ID set"
    try:
        domain = int(text)
    except ValueError:
        domain = -1
    if not 0 <= domain <= MAX_DOMAIN_ID:
        raise RuntimeError(f"ROS_DOMAIN_ID={text!r} is not a ROS domain id (0..{MAX_DOMAIN_ID}); unset it to let "
                           "the demo pick a free one")
    how = "your ROS_DOMAIN_ID"
    if domain_in_use(domain):
        how += ("; NOTE: DDS participants are already on it on this machine, the demo's nodes and topics join "
                "theirs (unset ROS_DOMAIN_ID to let the demo pick a free domain)")
    return domain, how


def run(args: argparse.Namespace) -> int:
    """The demo; returns the exit code."""
    from magcal_ros.app.ros_driver import ArrayDriver, ros_environment
    from magcal_ros.io.bag_writer import write_recording_bag

    clock = Clock()
    domain, how = demo_domain()
    env = ros_environment(domain)
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="magcal_demo_"))
    work.mkdir(parents=True, exist_ok=True)
    sim, manoeuvre, check = simulate(args.sets, args.fresh, args.seed, thrusters=not args.no_thrusters)
    channels = list(sim.channels)
    bag = work / "manoeuvre_bag"
    if bag.exists():
        shutil.rmtree(bag)
    write_recording_bag(bag, manoeuvre, storage=args.storage)
    running = f", thrusters {', '.join(channels)} at 0-{MAX_CURRENT:g} A" if channels else ""
    clock.say(f"simulated {len(manoeuvre)} sets of a rotation manoeuvre (random attitudes, 1 nT noise, "
              f"{INTENSITY / NT:.0f} nT field{running}) -> {bag} ({args.storage})")
    calibration_file = work / "calibration.yaml"
    nodes: list[Any] = []
    driver = None
    try:
        start_nodes(nodes, sim.geometry.names, channels, calibration_file, env, work, args.relative)
        clock.say(f"started correction_node (pid {nodes[0].pid}) and calibration_node (pid {nodes[1].pid}) "
                  f"on ROS_DOMAIN_ID={domain} ({how}), localhost discovery")
        driver = ArrayDriver(sim.geometry.names, domain, node_name="magcal_demo",
                             currents=[(c, BATTERY_STATE) for c in channels])
        if not (driver.wait_for_subscribers(2, 30.0) and driver.wait_for_output_publishers(30.0)
                and driver.prime(30.0)):
            raise RuntimeError("the nodes were not discovered within 30 s")
        clock.say("nodes discovered")

        t_before, tmi_before, n = measure(driver, check, args.rate)
        clock.say(f"before calibration: {n} fresh survey sets through the correction node")
        if not calibrate_live(driver, bag, manoeuvre, channels, args.rate, clock.say):
            return 1
        t_after, tmi_after, n = measure(driver, check, args.rate)
        clock.say(f"after calibration: {n} fresh survey sets (not used for the calibration) through the correction "
                  f"node{', subtracting the live thruster currents' if channels else ''}")
        rows = [("before calibration", t_before, tmi_before)]
        rows += thruster_rows(driver, check, channels, args.rate, (t_after, tmi_after), clock.say)
        drift = None
        if not args.no_drift:
            more, drift = drift_rows(driver, sim, channels, args, clock.say)
            rows += more
        print_table(rows, channels, drift, calibration_file, args.keep)
        if not args.no_imu:
            from magcal_ros.app.imu_demo import imu_step

            print("\n".join(imu_step(args.seed)))
            print()
        return 0
    except BaseException:
        show_logs(nodes)
        raise
    finally:
        if driver is not None:
            driver.close()
        codes = [p.stop() for p in nodes]
        if nodes:
            where = f"; bag, calibration file and logs in {work}" if args.keep else ""
            clock.say(f"nodes stopped (exit codes {', '.join(map(str, codes))}){where}")
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m magcal_ros.app.demo``."""
    parser = argparse.ArgumentParser(prog="python -m magcal_ros.app.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=1200, help="sets in the manoeuvre (default 1200)")
    parser.add_argument("--fresh", type=int, default=500, help="fresh sets replayed before and after (default 500)")
    parser.add_argument("--rate", type=float, default=400.0, help="replay rate, sets per second (default 400)")
    parser.add_argument("--relative", action="store_true", help="calibrate without the reference field")
    parser.add_argument("--no-thrusters", action="store_true",
                        help="no thrusters (by default two run at 0-20 A during the manoeuvre and the survey)")
    parser.add_argument("--no-drift", action="store_true",
                        help="skip the mission with a hard-iron jump, seen and fixed (about 3 minutes in real time)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="replay the mission this many times faster than real time (default 1: 100 sets/s)")
    parser.add_argument("--no-imu", action="store_true",
                        help="skip the IMU step (a tumble over a pier calibrated with the vehicle's IMU, offline: "
                        "outputs in the IMU frame, the pier's gradient fitted)")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default="mcap", help="bag storage (default mcap)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--keep", metavar="DIR", help="keep the bag, calibration file and node logs in DIR")
    args = parser.parse_args(argv)
    try:
        return run(args)
    except (RuntimeError, TimeoutError, FileNotFoundError) as exc:
        print(f"demo failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())

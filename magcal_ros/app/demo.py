"""End-to-end demo: simulate a rotation manoeuvre, calibrate it live over ROS 2, show the gain.

    python -m magcal_ros.app.demo [--sets 1200] [--rate 400] [--relative] [--keep DIR]

1. simulates a four-fluxgate cross (0.4 m) with realistic per-sensor errors, 1 nT noise,
   turning through random attitudes in a uniform 51 500 nT field, and writes the
   manoeuvre as a rosbag2 (``/magN/raw``);
2. starts ``correction_node`` and ``calibration_node`` as separate processes on a private
   ROS domain (localhost discovery only);
3. replays fresh sets through the uncalibrated correction node (before), replays the bag
   into the calibration node, calls ``~/start`` and ``~/calibrate``, replays fresh sets
   again (after), and prints the tensor and TMI residuals against the noise floor.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tensor_floor, tensor_rms, tmi_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.units import NT
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

INTENSITY = 51_500 * NT
NOISE = 1.0 * NT


class Clock:
    """Prints progress lines with the elapsed time."""

    def __init__(self) -> None:
        self.start = time.monotonic()

    def say(self, text: str) -> None:
        """One progress line."""
        print(f"[demo {time.monotonic() - self.start:5.1f} s] {text}", flush=True)


def simulate(sets: int, fresh: int, seed: int) -> tuple[ArraySimulation, Recording, Recording]:
    """The array, a calibration manoeuvre and a separate set of fresh attitudes."""
    rng = np.random.default_rng(seed)
    geometry = ArrayGeometry.cross()
    sensors = tuple(random_sensor_errors(rng) for _ in geometry.names)
    sim = ArraySimulation(geometry, sensors, earth_field(INTENSITY, 60.0, 5.0), noise=NOISE)
    manoeuvre, _ = sim.run(uniform_random(sets, rng), rng, rate=50.0)
    check, _ = sim.run(uniform_random(fresh, rng), rng, rate=50.0, start=1000.0)
    return sim, manoeuvre, check


def measure(driver, check: Recording, rate: float) -> tuple[float, float, int]:  # type: ignore[no-untyped-def]
    """Replay ``check`` into the correction node; tensor RMS (T/m), worst TMI RMS (T), sets received."""
    from magcal_ros.app.ros_driver import recording_messages

    driver.clear_outputs()
    mapping = driver.replay(recording_messages(check.names, check.stamps, check.vectors), rate=rate)
    stamps = list(mapping.values())
    driver.wait_for_outputs(stamps, timeout=60.0)
    gradients = driver.gradients(stamps)
    corrected = driver.corrected(stamps)
    if not gradients or not corrected:
        raise RuntimeError("the correction node published nothing; see its log")
    g = np.stack(list(gradients.values()))
    b = np.stack(list(corrected.values()))
    return tensor_rms(g), float(np.max(tmi_rms(b, INTENSITY))), len(gradients)


def run(args: argparse.Namespace) -> int:
    """The demo; returns the exit code."""
    from magcal_ros.app.ros_driver import (
        ArrayDriver,
        NodeProcess,
        bag_messages,
        pick_domain_id,
        ros_args,
        ros_environment,
        wait_for_samples,
    )
    from magcal_ros.io.bag_writer import write_recording_bag

    clock = Clock()
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="magcal_demo_"))
    work.mkdir(parents=True, exist_ok=True)
    domain = pick_domain_id()
    env = ros_environment(domain)
    sim, manoeuvre, check = simulate(args.sets, args.fresh, args.seed)
    bag = work / "manoeuvre_bag"
    if bag.exists():
        shutil.rmtree(bag)
    write_recording_bag(bag, manoeuvre, storage=args.storage)
    clock.say(f"simulated {len(manoeuvre)} sets of a rotation manoeuvre (random attitudes, 1 nT noise, "
              f"{INTENSITY / NT:.0f} nT field) -> {bag} ({args.storage})")
    calibration_file = work / "calibration.yaml"
    nodes: list[NodeProcess] = []
    driver = None
    try:
        # Uncalibrated at first, on purpose (the "before" figures): raw readings for every sensor.
        raw = {"uncorrected_sensors": list(sim.geometry.names)}
        nodes.append(NodeProcess("correction_node", ros_args(params=raw), env, work / "correction_node.log"))
        cal_params = {"calibration_file": str(calibration_file),
                      "reference_field": 0.0 if args.relative else INTENSITY}
        nodes.append(NodeProcess("calibration_node", ros_args(params=cal_params), env, work / "calibration_node.log"))
        clock.say(f"started correction_node (pid {nodes[0].pid}) and calibration_node (pid {nodes[1].pid}) "
                  f"on ROS_DOMAIN_ID={domain}, localhost discovery")
        driver = ArrayDriver(sim.geometry.names, domain, node_name="magcal_demo")
        if not (driver.wait_for_subscribers(2, 30.0) and driver.wait_for_output_publishers(30.0)
                and driver.prime(30.0)):
            raise RuntimeError("the nodes were not discovered within 30 s")
        clock.say("nodes discovered")

        t_before, tmi_before, n = measure(driver, check, args.rate)
        clock.say(f"before calibration: {n} fresh sets through the correction node")
        ok, message = driver.trigger("/magcal_calibration/start")
        clock.say(f"~/start -> {message}")
        messages = bag_messages(bag)
        sent = driver.replay(messages, rate=args.rate)
        progress = wait_for_samples(driver, "magcal_calibration", len(sent), timeout=15.0)
        clock.say(f"replayed {len(messages)} bag messages; the calibration node holds {progress.get('samples', '?')} "
                  f"sets, coverage {float(progress.get('coverage', 0)):.0%}, ready={progress.get('ready', '?')}")
        ok, message = driver.trigger("/magcal_calibration/calibrate")
        clock.say(f"~/calibrate -> success={ok}: {message}")
        if not ok:
            return 1
        t_after, tmi_after, n = measure(driver, check, args.rate)
        clock.say(f"after calibration: {n} fresh sets (not used for the calibration) through the correction node")
        floor = tensor_floor(NOISE, 0.4)
        print()
        print(f"  {'':24}{'before':>12}{'after':>12}{'noise floor':>14}")
        print(f"  {'tensor RMS (nT/m)':24}{t_before / NT:12.1f}{t_after / NT:12.2f}{floor / NT:14.2f}")
        print(f"  {'worst TMI RMS (nT)':24}{tmi_before / NT:12.1f}{tmi_after / NT:12.2f}{NOISE / NT:14.2f}")
        kept = "" if args.keep else " (removed at exit; --keep DIR keeps it)"
        print(f"  calibration file: {calibration_file}{kept}")
        print()
        return 0
    except BaseException:
        for p in nodes:
            tail = "\n    ".join(p.log().splitlines()[-8:])
            print(f"--- last lines of {p.log_path.name}:\n    {tail}", file=sys.stderr)
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

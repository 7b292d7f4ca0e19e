"""A mission soak: both nodes through hours of simulated mission over DDS, faster than real time.

    .venv/bin/python benchmarks/bench_mission_soak.py                    # 2 h of mission at 10x (~13 min)
    .venv/bin/python benchmarks/bench_mission_soak.py --hours 0.25 --block-minutes 2   # a quick look

The correction node starts with the true calibration (temperature terms, a payload current's
interference), the calibration node with ``auto_recalibrate`` on; a 4-sensor cross turning while it
dives through a thermocline, each sensor stamped on receipt (delay and jitter), one driver restarting
(its stamps jump back), one sensor silent for minutes, a payload current switched on, the hull's hard
iron jumping (see :mod:`magcal_ros.app.soak`); with ``--payload-unknown`` the payload's interference is not in
the starting calibration (it was off during the manoeuvre) and must be named and learnt when it comes on; with
``--imu`` the vehicle's IMU (mounted a few degrees off the array, 50 Hz) is published to the calibration node too
(a recalibration during the mission solves with it: the output rotation is fitted again), the outputs are in the
IMU frame (the starting calibration's ``output_rotation``; ``--running-frame-error`` turns it off the mounting)
and the table gets the centre field's error in it (RMS per axis over noise / 2) and the output frame's error
(mdeg). Prints progress while it runs, then per block of
mission the sets offered and output, the tensor RMS error over the floor sqrt(2) noise / baseline,
the TMI error over the noise and each process's RSS (min-max, MiB); every status change of the
correction node on /diagnostics; every recalibration pushed and its latency from the hull change;
whether a node hung.
"""

from __future__ import annotations

import argparse
import time

import _first  # noqa: F401  (this checkout; one BLAS thread, as the nodes run)

from magcal_ros.app.soak import SoakPlan, run_soak, table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=2.0, help="mission duration (h, default 2)")
    parser.add_argument("--speed", type=float, default=10.0, help="times real time (default 10)")
    parser.add_argument("--rate", type=float, default=20.0, help="samples per second of each sensor (default 20)")
    parser.add_argument("--block-minutes", type=float, default=10.0, help="minutes of mission per table row")
    parser.add_argument("--silent-minutes", type=float, default=3.0, help="how long one sensor is silent")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--tempco", action="store_true",
                        help="sensors that follow the temperature, a calibration with temperature terms")
    parser.add_argument("--payload-unknown", action="store_true",
                        help="the payload was off during the manoeuvre: the running calibration does not know its "
                        "interference and the correction node watches its current (named and learnt when it comes on)")
    parser.add_argument("--imu", action="store_true",
                        help="publish the vehicle's IMU (sensor_msgs/Imu, 50 Hz, mounted a few degrees off the array) "
                        "to the calibration node; the outputs are in the IMU frame and the table gets the centre "
                        "field's error and the output frame's error in it")
    parser.add_argument("--running-frame-error", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                        metavar=("ROLL", "PITCH", "YAW"),
                        help="with --imu: deg by which the starting calibration's output rotation is off the "
                        "mounting (a recalibration during the mission puts it right)")
    args = parser.parse_args()
    roll, pitch, yaw = (float(a) for a in args.running_frame_error)
    plan = SoakPlan(duration=args.hours * 3600.0, speed=args.speed, rate=args.rate, block=args.block_minutes * 60.0,
                    silent_for=args.silent_minutes * 60.0, seed=args.seed, tempco=args.tempco,
                    payload_known=not args.payload_unknown, imu=args.imu,
                    running_frame_error=(roll, pitch, yaw))
    t0 = time.monotonic()
    out = run_soak(plan, lambda s: print(s, flush=True))
    print(f"\nmission soak: {args.hours:g} h of mission at {args.speed:g}x, {args.rate:g} Hz per sensor, "
          f"{time.monotonic() - t0:.0f} s wall")
    for line in table(out):
        print(line)


if __name__ == "__main__":
    main()

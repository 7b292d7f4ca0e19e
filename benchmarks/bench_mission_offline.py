"""Benchmark (not a test): the mission soak's mission processed offline with the ``magcal`` command.

    .venv/bin/python benchmarks/bench_mission_offline.py                       # 2 h of mission, IMU, payload unknown
    .venv/bin/python benchmarks/bench_mission_offline.py --hours 0.5 --block-minutes 5

The mission of ``bench_mission_soak.py`` (receipt stamps, a driver restart, a silent sensor, the thermocline, the
IMU mounted a few degrees off the array, a payload switched on, the hull's hard iron jumping) is written to a
rosbag2 as a recorder receives it; ``magcal correct`` corrects it with the starting calibration, ``magcal calibrate
--prior`` recalibrates after each change from ``--window`` s of the mission starting ``--settle`` s after it, and
each span is corrected with the latest calibration (see :mod:`magcal_ros.app.mission_offline`). Prints per block the
tensor over the floor sqrt(2) noise / baseline, the TMI over the noise and the centre field's error in the IMU frame
over noise / 2, for the starting calibration throughout and recalibrated, with the recalibrations and wall times.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import _first  # noqa: F401  (this checkout; one BLAS thread, as the command runs)

from magcal_ros.app.mission_offline import OfflinePlan, offline_table, run_offline
from magcal_ros.app.soak import SoakPlan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=2.0, help="mission duration (h, default 2)")
    parser.add_argument("--rate", type=float, default=20.0, help="samples per second of each sensor (default 20)")
    parser.add_argument("--block-minutes", type=float, default=10.0, help="minutes of mission per table row")
    parser.add_argument("--window", type=float, default=300.0, help="s of mission each recalibration uses")
    parser.add_argument("--settle", type=float, default=30.0, help="s after a change before its window starts")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--payload-known", action="store_true",
                        help="the starting calibration knows the payload's interference (default: it does not)")
    parser.add_argument("--no-imu", action="store_true", help="no IMU (outputs in the array frame)")
    parser.add_argument("--tempco", action="store_true", help="the sensors follow their temperature")
    args = parser.parse_args()
    mission = SoakPlan(duration=args.hours * 3600.0, rate=args.rate, block=args.block_minutes * 60.0,
                       seed=args.seed, payload_known=args.payload_known, imu=not args.no_imu, tempco=args.tempco)
    plan = OfflinePlan(mission, window=args.window, settle=args.settle)
    with tempfile.TemporaryDirectory(prefix="magcal_offline_") as tmp:
        outcome = run_offline(plan, Path(tmp))
    print("\n".join(offline_table(outcome)))


if __name__ == "__main__":
    main()

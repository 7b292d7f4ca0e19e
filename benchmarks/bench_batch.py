"""``magcal batch`` on a local Dask cluster: 8 recordings with ``--workers 1`` and ``--workers 2``.

Not a test. Simulates one raw recording (``--sets`` sets of 4 sensors, sqlite3 by default)
and its true calibration, copies it to 8 recordings in a campaign directory, then runs, each
as a user would (``python -m magcal_ros.app.cli batch``, wall time from process start to exit,
cluster start-up included):

- ``magcal batch CAMPAIGN -c CAL -o OUT1 --workers 1``
- ``magcal batch CAMPAIGN -c CAL -o OUT2 --workers 2``

and prints both wall times and the speed-up (target on a 2-core machine: at least 1.6x).
Then it runs ``magcal correct`` on each recording alone and checks that both batch outputs
hold the same messages (topic, type, bag time and bytes, in order) as those runs.

    python benchmarks/bench_batch.py                  # 8 x 150,000 sets
    python benchmarks/bench_batch.py --sets 50000 --storage mcap
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

RECORDINGS = 8
INTENSITY = 5.5e-5


def make_recording(path: Path, sets: int, storage: str, cal_path: Path) -> float:
    """Simulated raw bag of ``sets`` x 4 messages and its true calibration; returns seconds."""
    import numpy as np

    from magcal_ros.io import calibration_file as calfile
    from magcal_ros.io.bag_writer import write_recording_bag
    from magcal_ros.sim.attitudes import uniform_random
    from magcal_ros.sim.spec import SimulationSpec, build

    t0 = time.perf_counter()
    sim, _ = build(SimulationSpec(count=1, intensity=INTENSITY))
    rng = np.random.default_rng(1)
    rec, truth = sim.run(uniform_random(sets, rng), rng, rate=200.0, start=1.7e9)
    write_recording_bag(path, rec, storage)  # type: ignore[arg-type]
    calfile.write(cal_path, truth.calibration)
    return time.perf_counter() - t0


def magcal(*args: object) -> float:
    """Run ``magcal ARGS`` in a child process; its wall time (s). Exits on failure."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "magcal_ros.app.cli", *map(str, args)], env=env,
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"magcal {' '.join(map(str, args))} failed ({proc.returncode}): {proc.stderr.strip()}")
    return wall


def messages(bag: Path) -> list[tuple[str, str, int, bytes]]:
    """Every message of a bag in order (topic, type, bag time, bytes)."""
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        return [(c.topic, c.msgtype, t, bytes(d)) for c, t, d in reader.messages()]


def task_seconds(report: Path) -> float:
    with open(report, newline="") as fh:
        return sum(float(r["seconds"]) for r in csv.DictReader(fh))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", type=int, default=150_000, help="sets per recording (default 150,000 = 600,000 messages)")
    ap.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap"])
    ap.add_argument("--repeat", type=int, default=1, help="runs of each worker count; the fastest counts (default 1)")
    ap.add_argument("--workdir", help="where to put the recordings (default: a temporary directory)")
    ap.add_argument("--_make", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._make:
        make_recording(Path(args._make[0]), int(args._make[1]), args.storage, Path(args._make[2]))
        return 0
    work = Path(args.workdir or tempfile.mkdtemp(prefix="magcal_bench_batch_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        campaign, cal = work / "campaign", work / "cal.yaml"
        first = campaign / "rec0_bag"
        if not first.exists():
            t0 = time.perf_counter()
            subprocess.run([sys.executable, __file__, "--storage", args.storage, "--_make", str(first), str(args.sets),
                            str(cal)], check=True)
            print(f"simulated {args.sets} sets x 4 sensors ({4 * args.sets} messages, {args.storage}) in "
                  f"{time.perf_counter() - t0:.1f} s")
        for i in range(1, RECORDINGS):
            if not (campaign / f"rec{i}_bag").exists():
                shutil.copytree(first, campaign / f"rec{i}_bag")
        os.sync()
        print(f"{RECORDINGS} recordings of {4 * args.sets} messages; {os.cpu_count()} cores")
        walls: dict[int, float] = {1: float("inf"), 2: float("inf")}
        tasks: dict[int, float] = {}
        loads: dict[int, float] = {}
        for _ in range(args.repeat):  # alternate, so a change of the machine's load hits both alike
            for workers in (1, 2):
                out = work / f"out_w{workers}"
                shutil.rmtree(out, ignore_errors=True)
                before = os.getloadavg()[0]
                wall = magcal("batch", campaign, "-c", cal, "-o", out, "--workers", workers,
                              "--reference-field", INTENSITY, "--quiet")
                if wall < walls[workers]:
                    walls[workers], loads[workers] = wall, before
                    tasks[workers] = task_seconds(out / "report.csv")
        print(f"{'run':<28} {'wall s':>8} {'sum of task s':>14} {'recordings/min':>15} {'load before':>12}")
        for workers in (1, 2):
            print(f"{'magcal batch --workers ' + str(workers):<28} {walls[workers]:>8.2f} {tasks[workers]:>14.2f} "
                  f"{60 * RECORDINGS / walls[workers]:>15.1f} {loads[workers]:>12.1f}")
        if max(loads.values()) > 0.5:
            print("note: other processes were running (1-minute load average above); the speed-up of two "
                  "workers needs the two cores free")
        speedup = walls[1] / walls[2]
        print(f"speed-up --workers 2 / --workers 1: {speedup:.2f}x (target >= 1.6x) "
              f"{'PASS' if speedup >= 1.6 else 'BELOW TARGET'}")
        same = 0
        for i in range(RECORDINGS):
            name = f"rec{i}_bag"
            alone = work / "alone" / name
            shutil.rmtree(alone, ignore_errors=True)
            magcal("correct", campaign / name, "-c", cal, "-o", alone, "--quiet")
            want = messages(alone)
            for workers in (1, 2):
                if messages(work / f"out_w{workers}" / name) != want:
                    raise SystemExit(f"{name}: the --workers {workers} output differs from magcal correct alone")
            same += 1
        print(f"outputs identical to magcal correct alone, message for message: {same}/{RECORDINGS} recordings "
              f"({len(want)} messages each) for both worker counts")
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

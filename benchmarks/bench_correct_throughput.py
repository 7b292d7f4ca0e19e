"""Throughput of ``magcal correct`` against a plain rosbags deserialize/serialize loop.

Not a test. Builds a simulated recording of ``--messages`` raw messages (4 sensors, so
messages/4 sets), then, each in its own process so peak RSS is per run:

- ``fast``: ``python -m magcal_ros.app.cli correct`` (batch CDR decoding/encoding, batch
  storage inserts);
- ``plain``: the straightforward path: ``Reader.messages`` -> ``deserialize_cdr`` per
  message -> sets matched by stamp -> the same numpy correction, in batches of 1024 sets ->
  one message object per output -> ``serialize_cdr`` -> ``Writer.write``.

Prints messages per second (input messages / wall time, process start-up included for
both), the speed-up, and peak RSS of the fast path for two recording sizes (the second a
quarter of the first) to show memory does not grow with the recording.

    python benchmarks/bench_correct_throughput.py                 # 1,000,000 messages
    python benchmarks/bench_correct_throughput.py --messages 200000 --storage mcap
"""

from __future__ import annotations

import argparse
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


def make_recording(path: Path, sets: int, storage: str, cal_path: Path) -> float:
    """Simulated raw bag of ``sets`` x 4 messages and its true calibration; returns seconds."""
    import numpy as np

    from magcal_ros.io import calibration_file as calfile
    from magcal_ros.io.bag_writer import write_recording_bag
    from magcal_ros.sim.attitudes import uniform_random
    from magcal_ros.sim.spec import SimulationSpec, build

    t0 = time.perf_counter()
    sim, _ = build(SimulationSpec(count=1))
    rng = np.random.default_rng(1)
    rec, truth = sim.run(uniform_random(sets, rng), rng, rate=200.0, start=1.7e9)
    write_recording_bag(path, rec, storage)  # type: ignore[arg-type]
    calfile.write(cal_path, truth.calibration)
    return time.perf_counter() - t0


def plain_correct(in_path: str, cal_path: str, out_path: str, storage: str) -> None:
    """The plain per-message rosbags path (see module docstring)."""
    import numpy as np
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    from magcal_ros.io import calibration_file as calfile
    from magcal_ros.io.cdr import FLOAT64_MULTI_ARRAY, MAGNETIC_FIELD, typestore

    ts = typestore()
    t = ts.types
    mf_t, hdr_t, time_t, vec_t = t[MAGNETIC_FIELD], t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"], t["geometry_msgs/msg/Vector3"]
    arr_t, lay_t, dim_t = t[FLOAT64_MULTI_ARRAY], t["std_msgs/msg/MultiArrayLayout"], t["std_msgs/msg/MultiArrayDimension"]
    cal = calfile.read(cal_path)
    names = cal.geometry.names
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Reader(in_path) as reader, Writer(out_path, version=9, storage_plugin=plugin) as writer:
        raw = {c.id: names.index(c.topic.strip("/").split("/")[0]) for c in reader.connections if c.topic.endswith("/raw")}
        out_c = [writer.add_connection(f"/{n}/corrected", MAGNETIC_FIELD, typestore=ts) for n in names]
        field_c = writer.add_connection("/field", MAGNETIC_FIELD, typestore=ts)
        grad_c = writer.add_connection("/gradient", FLOAT64_MULTI_ARRAY, typestore=ts)
        pending: dict[tuple[int, int], list] = {}
        ready: list[tuple[tuple[int, int], list]] = []

        def flush() -> None:
            vecs = np.array([[v for v in s] for _, s in ready])
            b, centre, g = cal.field_and_gradient(vecs)
            for i, ((sec, nsec), _) in enumerate(ready):
                stamp_ns = sec * 1_000_000_000 + nsec
                for k in range(len(names)):
                    msg = mf_t(header=hdr_t(stamp=time_t(sec=sec, nanosec=nsec), frame_id="magcal_array"),
                               magnetic_field=vec_t(x=b[i, k, 0], y=b[i, k, 1], z=b[i, k, 2]),
                               magnetic_field_covariance=np.zeros(9))
                    writer.write(out_c[k], stamp_ns, ts.serialize_cdr(msg, MAGNETIC_FIELD))
                msg = mf_t(header=hdr_t(stamp=time_t(sec=sec, nanosec=nsec), frame_id="magcal_array"),
                           magnetic_field=vec_t(x=centre[i, 0], y=centre[i, 1], z=centre[i, 2]),
                           magnetic_field_covariance=np.zeros(9))
                writer.write(field_c, stamp_ns, ts.serialize_cdr(msg, MAGNETIC_FIELD))
                msg = arr_t(layout=lay_t(dim=[dim_t(label="row", size=3, stride=9), dim_t(label="col", size=3, stride=3)],
                                         data_offset=0), data=g[i].reshape(9))
                writer.write(grad_c, stamp_ns, ts.serialize_cdr(msg, FLOAT64_MULTI_ARRAY))
            ready.clear()

        conns = [c for c in reader.connections if c.id in raw]
        for conn, _, data in reader.messages(connections=conns):
            m = ts.deserialize_cdr(data, MAGNETIC_FIELD)
            key = (m.header.stamp.sec, m.header.stamp.nanosec)
            slot = pending.setdefault(key, [None] * len(names))
            slot[raw[conn.id]] = (m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z)
            if all(v is not None for v in slot):
                ready.append((key, pending.pop(key)))
                if len(ready) >= 1024:
                    flush()
        if ready:
            flush()


def timed(cmd: list[str]) -> tuple[float, float]:
    """Run ``cmd``; wall seconds and the child's peak RSS in MiB."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err.strip()}")
    return wall, usage.ru_maxrss / 1024.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--messages", type=int, default=1_000_000, help="raw messages in the recording (default 1,000,000)")
    ap.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap"])
    ap.add_argument("--skip-plain", action="store_true", help="only the fast path")
    ap.add_argument("--workdir", help="where to put the bags (default: a temporary directory)")
    ap.add_argument("--_plain", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--_make", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._plain:
        plain_correct(*args._plain, storage=args.storage)
        return 0
    if args._make:
        secs = make_recording(Path(args._make[0]), int(args._make[1]), args.storage, Path(args._make[2]))
        print(f"  wrote {Path(args._make[0]).name} in {secs:.1f} s")
        return 0

    work = Path(args.workdir or tempfile.mkdtemp(prefix="magcal_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    try:
        sets = args.messages // 4
        rows = []
        print(f"recording: {sets} sets x 4 sensors = {4 * sets} messages, storage {args.storage}")
        sizes = [sets, max(1, sets // 4)]
        results = {}
        for n in sizes:
            bag, cal = work / f"raw_{args.storage}_{n}", work / f"cal_{n}.yaml"
            if not bag.exists():
                # In a child process: the parent stays small, so the children's peak RSS
                # (which on Linux includes the forked parent's pages) measures the child.
                subprocess.run([py, __file__, "--storage", args.storage, "--_make", str(bag), str(n), str(cal)], check=True)
            os.sync()
            out = work / f"fast_{n}"
            shutil.rmtree(out, ignore_errors=True)
            wall, rss = timed([py, "-m", "magcal_ros.app.cli", "correct", str(bag), "-c", str(cal), "-o", str(out),
                               "--storage", args.storage, "--quiet"])
            results[n] = (wall, rss)
            rows.append((f"fast  magcal correct, {4 * n} msgs", 4 * n / wall, wall, rss))
        if not args.skip_plain:
            bag, cal, out = work / f"raw_{args.storage}_{sets}", work / f"cal_{sets}.yaml", work / "plain"
            shutil.rmtree(out, ignore_errors=True)
            os.sync()
            wall, rss = timed([py, __file__, "--storage", args.storage, "--_plain", str(bag), str(cal), str(out)])
            rows.append((f"plain rosbags deserialize/serialize, {4 * sets} msgs", 4 * sets / wall, wall, rss))
        print(f"{'path':<50} {'msg/s':>10} {'wall s':>8} {'peak RSS MiB':>13}")
        for label, rate, wall, rss in rows:
            print(f"{label:<50} {rate:>10,.0f} {wall:>8.2f} {rss:>13.1f}")
        if not args.skip_plain:
            print(f"speed-up fast/plain: {rows[0][1] / rows[-1][1]:.1f}x (target >= 4x)")
        big, small = results[sizes[0]][1], results[sizes[1]][1]
        print(f"peak RSS of the fast path: {small:.1f} MiB at {4 * sizes[1]} msgs, {big:.1f} MiB at {4 * sizes[0]} msgs "
              f"(x{big / small:.2f} for x{sizes[0] / sizes[1]:.0f} messages)")
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Throughput of ``magcal correct`` against the storage limit, sqlite3 and mcap; flat memory.

Not a test. Builds a simulated recording of ``--messages`` raw messages (4 sensors, so
messages/4 sets) in both storages, then runs, each in its own process (wall time from process
start, interpreter start-up included; peak RSS per run), interleaved, best of ``--reps``:

- ``correct``: ``python -m magcal_ros.app.cli correct`` on the sqlite3 and on the mcap bag;
- ``limit``, plain SQLite reading every raw row and writing 1.5x as many (the corrected output
  has 6 messages per set of 4): one cursor reads every row of the sqlite3 bag into Python (apsw,
  as the reader does), then one ``executemany`` writes each row and every second row again into
  a new rosbag2 ``messages`` table (timestamp index, journal and syncs off, as the writer runs);
  no decoding, no synchronising, no maths;
- ``SQLite alone``: the same rows copied by SQLite itself (``INSERT .. SELECT`` from the
  attached input, no Python per row): the floor no Python program reaches.

Prints messages per second and each ``correct`` run against both (``correct / limit``), and
peak RSS of ``correct`` for two recording sizes (the second a quarter of the first) to show
memory does not grow with the recording. ``--rosbags`` adds the plain per-message rosbags
path (``Reader.messages`` -> ``deserialize_cdr`` -> numpy -> ``serialize_cdr`` ->
``Writer.write``, about 45,000 msg/s).

    python benchmarks/bench_correct_throughput.py                 # 1,000,000 messages
    python benchmarks/bench_correct_throughput.py --messages 200000 --reps 3
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


def plain_sqlite_limit(in_path: str, out_path: str) -> None:
    """Read every row of the sqlite3 bag ``in_path`` into Python; write each, and every second one
    again (1.5x), into a new rosbag2 messages table at ``out_path`` (see the module docstring)."""
    import glob
    import sqlite3

    import apsw

    Path(out_path).mkdir(parents=True)
    rows = []
    for f in sorted(glob.glob(f"{in_path}/*.db3")):
        db = apsw.Connection(f"file:{f}?immutable=1", flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI)
        rows += db.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp").fetchall()
        db.close()
    out = sqlite3.connect(Path(out_path) / "out.db3")
    out.executescript(LIMIT_SCHEMA)

    def doubled():  # type: ignore[no-untyped-def]
        again = False
        for row in rows:
            yield row
            if again:
                yield row
            again = not again

    out.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", doubled())
    out.commit()
    out.close()


def sqlite_alone(in_path: str, out_path: str) -> None:
    """The same 1.5x rows copied by SQLite itself (no Python per row)."""
    import glob
    import sqlite3

    Path(out_path).mkdir(parents=True)
    out = sqlite3.connect(f"file:{Path(out_path) / 'out.db3'}", uri=True)  # URI: the input attached immutable
    out.executescript(LIMIT_SCHEMA)
    for f in sorted(glob.glob(f"{in_path}/*.db3")):
        out.execute("ATTACH ? AS src", (f"file:{f}?immutable=1",))
        out.execute("INSERT INTO messages (topic_id, timestamp, data) SELECT m.topic_id, m.timestamp, m.data "
                    "FROM src.messages AS m CROSS JOIN (SELECT 0 AS k UNION ALL SELECT 1) AS twice "
                    "WHERE twice.k = 0 OR m.id % 2 = 0 ORDER BY m.timestamp")
        out.commit()
        out.execute("DETACH src")
    out.close()


LIMIT_SCHEMA = """PRAGMA journal_mode=OFF; PRAGMA synchronous=OFF;
CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL,
                      data BLOB NOT NULL);
CREATE INDEX timestamp_idx ON messages (timestamp ASC);"""


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
    ap.add_argument("--reps", type=int, default=2, help="interleaved runs of each; the best counts (default 2)")
    ap.add_argument("--rosbags", action="store_true", help="also the plain per-message rosbags path (slow)")
    ap.add_argument("--workdir", help="where to put the bags (default: a temporary directory; kept when given)")
    ap.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap"], help=argparse.SUPPRESS)
    ap.add_argument("--_plain", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--_make", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--_limit", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--_alone", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._plain:
        plain_correct(*args._plain, storage=args.storage)
        return 0
    if args._make:
        secs = make_recording(Path(args._make[0]), int(args._make[1]), args.storage, Path(args._make[2]))
        print(f"  wrote {Path(args._make[0]).name} in {secs:.1f} s")
        return 0
    if args._limit:
        plain_sqlite_limit(*args._limit)
        return 0
    if args._alone:
        sqlite_alone(*args._alone)
        return 0

    work = Path(args.workdir or tempfile.mkdtemp(prefix="magcal_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    try:
        sets = args.messages // 4
        sizes = [sets, max(1, sets // 4)]
        print(f"recording: {sets} sets x 4 sensors = {4 * sets} messages; {os.cpu_count()} CPUs; wall time from "
              f"process start; best of {args.reps} interleaved runs")
        for n in sizes:
            for storage in ("sqlite3", "mcap"):
                bag, cal = work / f"raw_{storage}_{n}", work / f"cal_{n}.yaml"
                if not bag.exists():
                    # In a child process: the parent stays small, so the children's peak RSS
                    # (which on Linux includes the forked parent's pages) measures the child.
                    subprocess.run([py, __file__, "--storage", storage, "--_make", str(bag), str(n), str(cal)],
                                   check=True)
        raw = {st: work / f"raw_{st}_{sets}" for st in ("sqlite3", "mcap")}
        cal = work / f"cal_{sets}.yaml"

        def correct(storage: str, n: int = sets) -> tuple[float, float]:
            out = work / f"out_{storage}_{n}"
            shutil.rmtree(out, ignore_errors=True)
            os.sync()
            return timed([py, "-m", "magcal_ros.app.cli", "correct", str(work / f"raw_{storage}_{n}"), "-c",
                          str(work / f"cal_{n}.yaml"), "-o", str(out), "--quiet"])

        def child(flag: str) -> tuple[float, float]:
            out = work / f"out{flag}"
            shutil.rmtree(out, ignore_errors=True)
            os.sync()
            return timed([py, __file__, flag, str(raw["sqlite3"]), str(out)])

        runs: dict[str, list[tuple[float, float]]] = {}
        for _ in range(args.reps):
            for label, run in (("limit", lambda: child("--_limit")), ("correct sqlite3", lambda: correct("sqlite3")),
                               ("SQLite alone", lambda: child("--_alone")), ("correct mcap", lambda: correct("mcap"))):
                runs.setdefault(label, []).append(run())
        if args.rosbags:
            out = work / "plain"
            shutil.rmtree(out, ignore_errors=True)
            runs["rosbags per message"] = [timed([py, __file__, "--storage", "sqlite3", "--_plain", str(raw["sqlite3"]),
                                                  str(cal), str(out)])]
        best = {k: min(v) for k, v in runs.items()}
        msgs = 4 * sets
        print(f"{'path':<44} {'msg/s':>10} {'wall s':>8} {'runs s':>16} {'peak RSS MiB':>13}")
        for label, (wall, rss) in best.items():
            every = ", ".join(f"{w:.2f}" for w, _ in runs[label])
            print(f"{label:<44} {msgs / wall:>10,.0f} {wall:>8.2f} {every:>16} {rss:>13.1f}")
        for storage in ("sqlite3", "mcap"):
            w = best[f"correct {storage}"][0]
            print(f"correct {storage}: {best['limit'][0] / w:.2f} of the plain-SQLite limit, "
                  f"{best['SQLite alone'][0] / w:.2f} of SQLite alone")
        small = {st: correct(st, sizes[1])[1] for st in ("sqlite3", "mcap")}
        for st in ("sqlite3", "mcap"):
            big = best[f"correct {st}"][1]
            print(f"peak RSS of correct {st}: {small[st]:.1f} MiB at {4 * sizes[1]} msgs, {big:.1f} MiB at "
                  f"{msgs} msgs (x{big / small[st]:.2f} for x{sizes[0] / sizes[1]:.0f} messages)")
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

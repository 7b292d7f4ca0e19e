"""Benchmark real sensor streams through the set synchroniser (not a test; prints its figures).

Run: ``python benchmarks/bench_streams.py [--seconds 30] [--seeds 3]`` from the repository root.

For each stamp pattern of :data:`magcal_ros.sim.streams.PATTERNS` (four 100 Hz fluxgates on the
0.4 m cross, 1 nT noise, a uniform 51,500 nT field, the vehicle turning about y at 0.2 rad/s,
10,000 nT/s, or 1 rad/s for the lag): the sets kept, of the reference sensor's samples, offline
(a rosbag2 written as a recorder receives the messages, read back through the bag reader) and
live (every message in arrival order through the synchroniser a node runs, with the bag times as
its clock), the mode chosen, whether both paths gave the same sets, and the RMS of the tensor
with the TRUE calibration over the floor ``sqrt(2) sigma / d`` (3.5 nT/m). The lag is shown with
and without its time offset. Also the synchroniser's time per message.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np


from magcal_ros.core.field import earth_field  # noqa: E402
from magcal_ros.core.geometry import ArrayGeometry  # noqa: E402
from magcal_ros.core.metrics import tensor_floor  # noqa: E402
from magcal_ros.core.sync import stream_synchronizer  # noqa: E402
from magcal_ros.core.units import NT  # noqa: E402
from magcal_ros.io.bag_reader import read_bag_sets  # noqa: E402
from magcal_ros.io.bag_writer import write_stream_bag  # noqa: E402
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors  # noqa: E402
from magcal_ros.sim.streams import PATTERNS, StreamRecording, simulate_streams, turn  # noqa: E402

FLOOR = tensor_floor(1 * NT, 0.4)


def simulate(pattern: str, seconds: float, seed: int) -> StreamRecording:
    spec, rate = PATTERNS[pattern]
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross(0.4)
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                          earth_field(51_500 * NT, 60.0, 5.0), noise=1 * NT)
    attitudes, steps = turn(rate, seconds + 1.0)
    return simulate_streams(sim, attitudes, steps, spec, seconds, rng)


def offsets(rec: StreamRecording, applied: bool) -> dict[str, float] | None:
    return {n: float(t) for n, t in zip(rec.names, rec.calibration.time_offsets) if t} if applied else None


def offline(rec: StreamRecording, folder: Path, applied: bool) -> tuple[np.ndarray, np.ndarray]:
    bag = folder / f"bag{time.perf_counter_ns()}"
    write_stream_bag(bag, rec.names, [s.stamps for s in rec.streams], [s.vectors for s in rec.streams],
                     [s.receipts for s in rec.streams])
    got, _ = read_bag_sets(bag, time_offsets=offsets(rec, applied))
    return got.stamps, got.vectors


def live(rec: StreamRecording, applied: bool) -> tuple[np.ndarray, np.ndarray, str, float]:
    sync = stream_synchronizer(rec.names, time_offsets=offsets(rec, applied))
    messages = rec.messages()
    rows = [(k, int(rec.streams[k].stamps[i]), *rec.streams[k].vectors[i].tolist(), bag) for bag, k, i in messages]
    sets = []
    start = time.perf_counter()
    for k, stamp, x, y, z, bag in rows:
        sets += sync.add(k, stamp, x, y, z, bag)
    per_message = (time.perf_counter() - start) / len(rows)
    return (np.array([s.stamp for s in sets], dtype=np.int64), np.array([s.values for s in sets]),
            str(sync.mode), per_message)


def tensor(rec: StreamRecording, vectors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(rec.calibration.outputs(vectors).tensor ** 2)) / FLOOR)  # type: ignore[operator]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    print(f"{args.seconds:g} s of four 100 Hz sensors, {args.seeds} seeds; sets kept of the reference's samples, "
          f"tensor RMS with the true calibration / floor {FLOOR / NT:.2f} nT/m (worst seed)")
    print(f"{'pattern':34s} {'mode':12s} {'offline':>8s} {'live':>8s} {'same':>5s} {'tensor':>7s} {'us/msg':>7s}")
    rows = [(p, True) for p in PATTERNS] + [("5 ms lag at 1 rad/s", False)]
    with tempfile.TemporaryDirectory() as tmp:
        for pattern, applied in rows:
            kept_off, kept_live, ratio, cost, same, modes = [], [], [], [], True, set()
            for seed in range(args.seeds):
                rec = simulate(pattern, args.seconds, seed)
                ref = len(rec.streams[0])
                stamps, vectors = offline(rec, Path(tmp), applied)
                lstamps, lvectors, mode, per = live(rec, applied)
                n = len(lstamps)
                same &= bool(np.array_equal(stamps[:n], lstamps) and np.array_equal(vectors[:n], lvectors))
                kept_off.append(len(stamps) / ref)
                kept_live.append(n / ref)
                ratio.append(tensor(rec, vectors))
                cost.append(per)
                modes.add(mode)
            label = pattern if applied else f"{pattern}, no time offset"
            print(f"{label:34s} {'/'.join(sorted(modes)):12s} {min(kept_off):8.2%} {min(kept_live):8.2%} "
                  f"{'yes' if same else 'NO':>5s} {max(ratio):6.2f}x {np.mean(cost) * 1e6:7.1f}")


if __name__ == "__main__":
    main()

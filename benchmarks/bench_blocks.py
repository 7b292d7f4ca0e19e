"""Benchmark (not a test): calibration cost of each combination of the model's blocks against the set count.

    python benchmarks/bench_blocks.py                        # 20,000 and 200,000 sets, every combination
    python benchmarks/bench_blocks.py --sizes 20000 --combos sensor imu all

A four-sensor cross tumbling smoothly at 50 sets/s (1 nT noise, 55 uT) with, as a combination asks, the sets'
stamps (lags: the lag block fits every sensor's lag behind the first; simulated at zero, the cost is the
same), a temperature ramp 5 -> 25 C with offset and gain tempcos,
one current channel (a payload's dipole, 0-20 A at random) and the vehicle's IMU (orientation 0.02 deg,
gyro, mounted 2-3 deg off). Each case is simulated once and written to a file; ``calibrate_array`` then runs
on it in its own process (so that its peak memory, VmHWM, is its own): CPU and wall seconds, peak MB, and
the TMI and tensor residuals on the sets fitted against the noise and the floor sqrt(2) sigma / d; then
again in the same process ("again": the median of five calls, what a long-lived caller such as the calibration
node pays, without the first call's imports). The table gives each combination's CPU time against the sensor block alone at the same size
(first call, and again), and each
size's CPU time (first call, and again) and wall time against the smallest's (the pass over every set runs its
chunks on the spare cores: its wall time is less than its CPU time; the first call's time includes a fixed
cost the second does not pay, so its growth with the set count is the smaller).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np

from magcal_ros.core.metrics import tensor_floor
from magcal_ros.core.units import NT

NOISE = 1 * NT
AGAIN = 5
F = 5.5e-5
COMBOS: dict[str, tuple[str, ...]] = {
    "sensor": (),
    "lags": ("lags",),
    "temperature": ("temperature",),
    "currents": ("currents",),
    "imu": ("imu",),
    "imu+lags": ("imu", "lags"),
    "all": ("imu", "lags", "temperature", "currents"),
}


def simulate(n: int, blocks: tuple[str, ...], path: Path) -> None:
    """Write the recording of one case to ``path`` (npz)."""
    from magcal_ros.sim.spec import SimulationSpec, run

    kw: dict[str, object] = dict(count=n, schedule="tumble", seed=3, noise=NOISE, rate=50.0, intensity=F)
    if "imu" in blocks:
        kw.update(imu=True, imu_mounting=(2.0, -1.5, 3.0), imu_orientation_noise=0.02)
    if "temperature" in blocks:
        kw.update(temperature_ramp=(5.0, 25.0), tempco_offset=0.5e-9, tempco_gain=30e-6)
    if "currents" in blocks:
        kw.update(thrusters=((-0.7, 0.25, 0.1, 0.0, 0.0, 0.05),))
    rec, _, sim = run(SimulationSpec(**kw))  # type: ignore[arg-type]
    out: dict[str, object] = {"raw": rec.vectors, "positions": sim.geometry.positions,
                              "names": np.array(sim.geometry.names)}
    if "lags" in blocks or "imu" in blocks:
        out["stamps"] = rec.stamps
    if "temperature" in blocks:
        out["temperatures"] = rec.temperatures
    if "currents" in blocks:
        out["currents"], out["channels"] = rec.currents, np.array(rec.channels)
    if "imu" in blocks:
        out["q"], out["w"] = rec.imu.orientation, rec.imu.angular_velocity
    np.savez(path, **out)


def solve(path: str) -> dict[str, float]:
    """Calibrate one case (in this process); the figures as a dict."""
    import resource

    from magcal_ros.core.geometry import ArrayGeometry
    from magcal_ros.core.metrics import rms
    from magcal_ros.core.recording import ImuSamples
    from magcal_ros.methods.pipeline import calibrate_array

    d = np.load(path)
    geo = ArrayGeometry(tuple(str(x) for x in d["names"]), d["positions"])
    kwargs: dict[str, object] = {}
    if "stamps" in d:
        kwargs["stamps"] = d["stamps"]
    if "temperatures" in d:
        kwargs["temperatures"] = d["temperatures"]
    if "currents" in d:
        kwargs.update(currents=d["currents"], channels=tuple(str(c) for c in d["channels"]))
    if "q" in d:
        kwargs["imu"] = ImuSamples(d["q"], d["w"], "imu_link")
    c0, w0 = time.process_time(), time.perf_counter()
    result = calibrate_array(d["raw"], geo, F, **kwargs)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    peak = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) / 1024.0
    again = []  # again in the same process: what a long-lived caller pays (the median of AGAIN calls)
    for _ in range(AGAIN):
        c0 = time.process_time()
        calibrate_array(d["raw"], geo, F, **kwargs)
        again.append(time.process_time() - c0)
    return {"cpu": cpu, "wall": wall, "again": float(np.median(again)), "peak_mb": peak, "tmi": float(np.max(result.tmi_after)) / NOISE,
            "tensor": float(result.tensor_after) / tensor_floor(NOISE, 0.4), "sets": float(len(d["raw"])),
            "tmi_rms": float(rms(result.tmi_after)) / NOISE}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[20_000, 200_000])
    ap.add_argument("--combos", nargs="+", default=list(COMBOS), choices=list(COMBOS))
    ap.add_argument("--solve", help=argparse.SUPPRESS)  # the child: calibrate one case file
    args = ap.parse_args()
    if args.solve:
        print(json.dumps(solve(args.solve)))
        return 0
    rows: dict[tuple[str, int], dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            for name in args.combos:
                path = Path(tmp) / f"{name}_{n}.npz"
                t0 = time.perf_counter()
                simulate(n, COMBOS[name], path)
                made = time.perf_counter() - t0
                proc = subprocess.run([sys.executable, __file__, "--solve", str(path)], capture_output=True, text=True)
                if proc.returncode:
                    print(f"{name} {n}: failed\n{proc.stderr[-2000:]}", flush=True)
                    continue
                rows[name, n] = json.loads(proc.stdout.strip().splitlines()[-1])
                r = rows[name, n]
                print(f"  {name:12s} {n:8d} sets: {r['cpu']:6.2f} s CPU ({r['again']:.2f} again), {r['wall']:6.2f} s wall, "
                      f"{r['peak_mb']:6.0f} MB, "
                      f"TMI {r['tmi']:.2f}x noise, tensor {r['tensor']:.2f}x floor (simulated in {made:.0f} s)",
                      flush=True)
    print()
    head = f"{'blocks':12s} " + " ".join(f"{f'{n} sets: CPU s (x sensor)':>28s} {'again (x sensor)':>17s} {'MB':>5s}"
                                         for n in args.sizes)
    if len(args.sizes) > 1:
        more = str(args.sizes[-1] // args.sizes[0])
        head += f" {'CPU x ' + more + ' sets':>16s} {'again x ' + more:>12s} {'wall x ' + more + ' sets':>16s}"
    print(head)
    for name in args.combos:
        cells = []
        for n in args.sizes:
            r, base = rows.get((name, n)), rows.get(("sensor", n))
            if r is None:
                cells.append(f"{'failed':>28s} {'':>17s} {'':>5s}")
                continue
            ratio = f"(x{r['cpu'] / base['cpu']:.1f})" if base else ""
            again = f"(x{r['again'] / base['again']:.1f})" if base else ""
            cells.append(f"{r['cpu']:20.2f} {ratio:>7s} {r['again']:9.2f} {again:>7s} {r['peak_mb']:5.0f}")
        line = f"{name:12s} " + " ".join(cells)
        small, large = rows.get((name, args.sizes[0])), rows.get((name, args.sizes[-1]))
        if len(args.sizes) > 1 and small and large:
            line += (f" {large['cpu'] / small['cpu']:16.1f} {large['again'] / small['again']:12.1f}"
                     f" {large['wall'] / small['wall']:16.1f}")
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

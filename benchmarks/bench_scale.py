"""Benchmark (not a test): calibration cost against the recording's length, and small jobs.

    python benchmarks/bench_scale.py                 # 20k, 200k, 500k sets; single sensor 20k
    python benchmarks/bench_scale.py --sizes 20000 200000 --no-magyc
    python benchmarks/bench_scale.py --single-only --single-csv compass.csv   # and on a real recording

For each size, a four-sensor array tumbling smoothly at 50 sets/s is written as CSV and
``magcal calibrate`` runs on it as a user would (its own process, best of two runs): wall time, CPU time and
peak memory (RSS, VmHWM read by the process as it exits) of that process, and the ratios to the smallest size. The calibration is
then checked on fresh attitudes against the simulator's truth: TMI RMS against the noise
and tensor RMS against the floor sqrt(2) sigma / d. At the smallest size the solve with every
set in every stage (``--max-solve-sets 0``) runs too: what the reduction costs in accuracy.

Single sensor: ``calibrate_array`` on 20,000 sets of one sensor against MAGYC's closed-form
ellipsoid fit (Fang et al., 2011) on the same readings, in turns (two of magcal's, five of MAGYC's,
30 times: a shared host's slow spells weigh on both alike), the best of each; MAGYC run in a separate
virtual environment (``magyc`` pins numpy < 2, so it never shares the package's). The
environment is made on first use (needs the package index); ``--no-magyc`` skips it.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np
from scipy.spatial.transform import Rotation

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tensor_rms, tmi_rms
from magcal_ros.core.units import NT
from magcal_ros.io.calibration_file import read as read_calibration
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

F = 50_000 * NT
NOISE = 1 * NT
MAGYC_VENV = Path(os.environ.get("MAGYC_VENV", Path(__file__).resolve().parent / ".magyc-venv"))


def array(sensors: int, seed: int = 5) -> ArraySimulation:
    """Percent gains, degree angles, 100 nT hard and 1 % soft iron, 1 nT noise."""
    rng = np.random.default_rng(seed)
    geometry = ArrayGeometry.cross() if sensors == 4 else ArrayGeometry.single()
    errors = tuple(random_sensor_errors(rng, hard_iron_sd=100 * NT, soft_iron_sd=0.01) for _ in range(sensors))
    return ArraySimulation(geometry, errors, earth_field(F, 60.0, -5.0), noise=NOISE)


def smooth_tumble(count: int, seed: int) -> np.ndarray:
    """(N, 3, 3) a smooth random tumble (rotation vector wandering by about 1 deg per set)."""
    gen = np.random.default_rng(seed)
    steps = gen.normal(size=(count, 3))
    kernel = np.ones(25) / 25
    smooth = np.stack([np.convolve(steps[:, k], kernel, mode="same") for k in range(3)], axis=1)
    rotvec = np.cumsum(smooth * np.radians(1.0) / np.sqrt(np.mean(np.sum(smooth**2, axis=1))), axis=0)
    return Rotation.from_rotvec(rotvec).as_matrix()


CHILD = """
import atexit, sys
def _peak():
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM"):
                sys.stderr.write("\\nMAGCAL_BENCH_PEAK_KB " + line.split()[1] + "\\n")
atexit.register(_peak)
from magcal_ros.app.cli import main
main()
"""
"""``magcal`` with its own peak memory reported at exit: the peak of the process after it started
(``ru_maxrss`` of a child also counts the parent's memory at the moment it was started)."""


def run_cli(args: list[str]) -> tuple[float, float, float, str]:
    """``magcal`` in its own process: wall s, CPU s, peak RSS MB, last lines of its output."""
    cmd = [sys.executable, "-c", CHILD, *args]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = proc.stdout.read() if proc.stdout else ""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"magcal {' '.join(args)} failed:\n{out}")
    peaks = [int(line.split()[1]) for line in out.splitlines() if line.startswith("MAGCAL_BENCH_PEAK_KB ")]
    peak_mb = peaks[-1] / 1024 if peaks else usage.ru_maxrss / 1024
    return wall, usage.ru_utime + usage.ru_stime, peak_mb, out


def fresh_errors(sim: ArraySimulation, path: Path) -> tuple[float, float]:
    """TMI RMS (nT) and tensor RMS (nT/m) of a calibration file on 2000 fresh attitudes."""
    cal = read_calibration(path)
    rec, _ = sim.run(uniform_random(2000, 77), rng=78)
    out = cal.field_and_gradient(rec.vectors)
    corrected = cal.apply(rec.vectors)
    return float(np.max(tmi_rms(corrected, F)) / NT), float(tensor_rms(out[2]) / NT)


def scale(sizes: list[int]) -> None:
    sim = array(4)
    floor = np.sqrt(2.0) * NOISE / 0.4 / NT  # the default cross: 0.4 m baseline
    print(f"four-sensor array, 1 nT noise, tensor floor {floor:.2f} nT/m (on fresh attitudes)")
    print(f"{'sets':>8} {'wall s':>8} {'CPU s':>8} {'peak MB':>8} {'x time':>7} {'x CPU':>6}   "
          f"{'TMI nT':>7} {'tensor':>7}  summary")
    base = None
    with tempfile.TemporaryDirectory() as tmp:
        for k, n in enumerate(sizes):
            csv = Path(tmp) / f"rec{n}.csv"
            rec, _ = sim.run(smooth_tumble(n, 3 + k), rng=4 + k, rate=50.0, continuous=True)
            write_csv(csv, rec)
            del rec
            out_yaml = Path(tmp) / f"cal{n}.yaml"
            runs = [run_cli(["calibrate", str(csv), "-o", str(out_yaml), "-q", "--reference-field", str(F)])
                    for _ in range(2)]  # best of two: a shared machine's neighbours come and go
            wall, cpu, mb, text = min(runs, key=lambda r: r[0])
            tmi, tensor = fresh_errors(sim, out_yaml)
            base = base or (wall, cpu)
            solved = next((p.strip() for p in text.split(",") if "solved on" in p), "every set")
            print(f"{n:>8} {wall:8.2f} {cpu:8.2f} {mb:8.0f} {wall / base[0]:7.2f} {cpu / base[1]:6.2f}   "
                  f"{tmi:7.3f} {tensor / floor:6.2f}x  {solved}")
            if k == 0:
                wall0, cpu0, mb0, _ = run_cli(["calibrate", str(csv), "-o", str(out_yaml), "-q", "--reference-field", str(F),
                                               "--max-solve-sets", "0"])
                tmi0, tensor0 = fresh_errors(sim, out_yaml)
                print(f"{n:>8} {wall0:8.2f} {cpu0:8.2f} {mb0:8.0f} {'':>7} {'':>6}   {tmi0:7.3f} "
                      f"{tensor0 / floor:6.2f}x  every set in every stage (--max-solve-sets 0)")
            csv.unlink()


def magyc_python() -> Path | None:
    """The interpreter of a virtual environment with MAGYC (made on first use), or None."""
    py = MAGYC_VENV / "bin" / "python"
    if not py.exists():
        print(f"  making {MAGYC_VENV} with magyc (once) ...", flush=True)
        if subprocess.run([sys.executable, "-m", "venv", str(MAGYC_VENV)]).returncode != 0:
            return None
        if subprocess.run([str(py), "-m", "pip", "install", "-q", "magyc"]).returncode != 0:
            return None
    return py


FANG = """
import sys, time, numpy as np, magyc
x = np.load(sys.argv[1])
magyc.ellipsoid_fit_fang(x)
print("ready", flush=True)
for line in sys.stdin:  # a few fits back to back per line (warm, as in a loop), the best time answered
    best = 1e9
    for _ in range(int(line)):
        t0 = time.perf_counter(); magyc.ellipsoid_fit_fang(x); best = min(best, time.perf_counter() - t0)
    print(best, flush=True)
"""
REPEATS = 30
"""Rounds of the single-sensor comparison: each runs magcal's solve twice and MAGYC's fit five times, back
to back (warm), so that a shared host's slow spells weigh on both alike; the best of each counts."""


def fang_workers(py: Path, path: Path) -> dict[str, subprocess.Popen]:
    """MAGYC's Fang fit ready in two processes: its own BLAS threads ("default") and one ("1")."""
    workers = {}
    for threads in ("default", "1"):  # MAGYC at its best: its own BLAS threads, or one as magcal runs
        env = dict(os.environ)
        env.pop("OPENBLAS_NUM_THREADS", None)
        env.pop("OMP_NUM_THREADS", None)
        if threads == "1":
            env["OPENBLAS_NUM_THREADS"] = env["OMP_NUM_THREADS"] = "1"
        workers[threads] = subprocess.Popen([str(py), "-c", FANG, str(path)], stdin=subprocess.PIPE,
                                            stdout=subprocess.PIPE, text=True, env=env)
        if workers[threads].stdout.readline().strip() != "ready":
            raise RuntimeError("MAGYC's fit did not start")
    return workers


def single(use_magyc: bool, count: int = 20_000, csv: Path | None = None) -> None:
    """magcal's one-sensor solve against MAGYC's Fang fit: on ``count`` simulated sets (F given), or on the
    recording ``csv`` (one sensor, no reference field: as ``magcal calibrate`` runs it without one)."""
    if csv is None:
        sim = array(1)
        rec, _ = sim.run(smooth_tumble(count, 9), rng=10, rate=50.0, continuous=True)
        geometry, field, what = sim.geometry, F, f"{count} sets"
    else:
        from magcal_ros.io.csv_recording import read_csv

        rec, _ = read_csv(csv)
        if rec.vectors.shape[1] != 1:
            raise SystemExit(f"{csv}: {rec.vectors.shape[1]} sensors; the comparison is for one")
        geometry, field, what = ArrayGeometry.single(rec.names[0]), None, f"{len(rec.vectors)} sets of {csv.name}"
    calibrate_array(rec.vectors[:2000], geometry, field)  # warm-up (imports, caches)
    py = magyc_python() if use_magyc else None
    if use_magyc and py is None:
        print("  MAGYC not available (no package index?)")
    best, res = np.inf, None
    fang = {"default": np.inf, "1": np.inf}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.npy"
        np.save(path, rec.vectors[:, 0] / NT)
        workers = fang_workers(py, path) if py is not None else {}
        try:
            for _ in range(REPEATS):
                for _ in range(2):
                    t0 = time.perf_counter()
                    res = calibrate_array(rec.vectors, geometry, field, stamps=rec.stamps)
                    best = min(best, time.perf_counter() - t0)
                for threads, proc in workers.items():
                    proc.stdin.write("5\n")
                    proc.stdin.flush()
                    fang[threads] = min(fang[threads], float(proc.stdout.readline()))
        finally:
            for proc in workers.values():
                proc.stdin.close()
                proc.wait()
    print(f"\nsingle sensor, {what}: magcal {best:.4f} s, best of {2 * REPEATS} "
          f"({re.search(r'TMI RMS [^,]*', res.summary()).group(0)})")
    if workers:
        least = min(fang.values())
        print(f"  MAGYC Fang ellipsoid fit {least:.4f} s, best of {5 * REPEATS} in turns with magcal's (BLAS threads default "
              f"{fang['default']:.4f} s, one {fang['1']:.4f} s): magcal takes {best / least:.1f}x (target <= 20x)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[20_000, 200_000, 500_000])
    p.add_argument("--no-magyc", action="store_true", help="skip the MAGYC comparison")
    p.add_argument("--single-csv", type=Path, metavar="CSV", help="also compare on this one-sensor recording "
                   "(magcal's CSV: stamp, <name>.x, <name>.y, <name>.z in T)")
    p.add_argument("--single-only", action="store_true", help="only the single-sensor comparisons")
    a = p.parse_args()
    if not a.single_only:
        scale(a.sizes)
    single(not a.no_magyc)
    if a.single_csv is not None:
        single(not a.no_magyc, csv=a.single_csv)


if __name__ == "__main__":
    main()

"""Benchmark calibration at sea and on real data (not a test; prints its figures).

Run: ``python benchmarks/bench_field.py`` from the repository root.

- outliers: 5 % and 20 % of readings spiked by 500-5000 nT; TMI and tensor on fresh data over
  what the clean-data calibration gives, readings excluded against readings spiked;
- envelopes: sea manoeuvres (full yaw, pitch and roll swinging +-P/+-R deg), the envelope
  reported, the predicted and measured whole-sphere TMI ratio (to the true calibration),
  averaged over seeds, and the ratio inside the flown envelope;
- partial recalibration: hard iron moved 300-800 nT per axis on every sensor, a yaw circle
  with +-3 deg wobble, with and without the previous calibration as the prior;
- correlated noise: 30-run Monte Carlo, reported 1-sigma over the actual spread;
- the real hand-held recording: residual over noise, uncertainty widening, block scatter;
- solve time for 2,000 sets of four sensors.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np


from magcal_ros.core.geometry import ArrayGeometry  # noqa: E402
from magcal_ros.errors import MagcalError  # noqa: E402
from magcal_ros.io.csv_recording import read_csv  # noqa: E402
from magcal_ros.methods.pipeline import calibrate_array  # noqa: E402
from magcal_ros.sim.attitudes import sea_manoeuvre, tumble, uniform_random  # noqa: E402
from magcal_ros.sim.scenarios import field_trial_array  # noqa: E402
from magcal_ros.sim.simulator import (  # noqa: E402
    ArraySimulation,
    hard_iron_moved,
)

NT = 1e-9
F = 51_500 * NT
# The real hand-held QMC5883L recording in the repository (data/real/, MIT-licensed; see its README);
# MAGCAL_REAL_RECORDING names another.
REAL = Path(os.environ.get("MAGCAL_REAL_RECORDING", Path(__file__).resolve().parents[1] / "data" / "real"
                           / "qmc5883l_handheld.csv"))


def ratios(cal: object, sim: ArraySimulation, seed: int = 99, attitudes: np.ndarray | None = None) -> tuple[float, float]:
    """(TMI, tensor rows x and y) RMS over the true calibration's on fresh data."""
    rng = np.random.default_rng(seed)
    fresh, _ = sim.run(uniform_random(3000, rng) if attitudes is None else attitudes, rng)
    out = []
    for c in (cal, sim.true_calibration()):
        b = c.apply(fresh.vectors)  # type: ignore[attr-defined]
        tmi = np.sqrt(np.mean((np.linalg.norm(b, axis=-1) - F) ** 2))
        rows = np.stack([(b[:, 0] - b[:, 2]) / 0.4, (b[:, 1] - b[:, 3]) / 0.4], axis=1)
        out.append((tmi, np.sqrt(np.mean(rows**2))))
    return out[0][0] / out[1][0], out[0][1] / out[1][1]


def outliers() -> None:
    print("outliers (1000 random sets; ratios to the clean-data calibration on fresh data)")
    for fraction in (0.05, 0.2):
        sim = field_trial_array(2, NT)
        rng = np.random.default_rng(2)
        rec, _ = sim.run(uniform_random(1000, rng), rng)
        clean = ratios(calibrate_array(rec.vectors, sim.geometry, F).calibration, sim)
        v = rec.vectors.copy()
        hit = rng.random(v.shape[:2]) < fraction
        d = rng.normal(size=v.shape)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        v[hit] += (d * rng.uniform(500, 5000, v.shape[:2])[..., None] * NT)[hit]
        t0 = time.perf_counter()
        res = calibrate_array(v, sim.geometry, F)
        got = ratios(res.calibration, sim)
        print(f"  {fraction:4.0%} spiked: TMI {got[0] / clean[0]:.3f}, tensor {got[1] / clean[1]:.3f}; excluded "
              f"{int(res.outliers.sum())} of {int(hit.sum())} spiked readings; {time.perf_counter() - t0:.2f} s")


def envelopes(seeds: int = 4) -> None:
    print("envelopes (600 sets, sea manoeuvre; predicted / measured whole-sphere TMI ratio, mean of squares)")
    for pitch, roll in ((30, 15), (15, 5), (5, 2)):
        env, pred, meas, inside, refused = [], [], [], [], 0
        for seed in range(seeds):
            sim = field_trial_array(10 + seed, NT)
            rng = np.random.default_rng(seed)
            rec, _ = sim.run(sea_manoeuvre(600, pitch, roll, turns=2, rng=rng), rng)
            try:
                res = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps)
            except MagcalError:
                refused += 1
                continue
            env.append((res.envelope.pitch_deg, res.envelope.roll_deg))
            pred.append(res.envelope.ratio_sphere**2)
            meas.append(ratios(res.calibration, sim, seed)[0] ** 2)
            inside.append(ratios(res.calibration, sim, seed, sea_manoeuvre(2000, pitch, roll, 3, rng=seed))[0])
        if env:
            print(f"  +-{pitch}/+-{roll} deg: envelopes {env}; whole sphere predicted {np.sqrt(np.mean(pred)):.2f} "
                  f"measured {np.sqrt(np.mean(meas)):.2f}; inside the flown envelope {np.mean(inside):.3f}"
                  + (f"; {refused} refused" if refused else ""))
        else:
            print(f"  +-{pitch}/+-{roll} deg: refused in all {seeds} seeds (undetermined without a prior)")


def partial_recalibration() -> None:
    print("partial recalibration (hard iron moved 300-800 nT per axis; yaw circle, +-3 deg wobble, 600 sets)")
    sim = field_trial_array(4, NT)
    rng = np.random.default_rng(4)
    rec, _ = sim.run(uniform_random(1000, rng), rng)
    first = calibrate_array(rec.vectors, sim.geometry, F).calibration
    new = hard_iron_moved(sim, rng)
    yaw, _ = new.run(sea_manoeuvre(600, 0, 0, turns=2, wobble_deg=3, rng=rng), rng)
    old = ratios(first, new)
    print(f"  previous calibration on the changed hull: TMI {old[0]:.1f}x, tensor {old[1]:.1f}x the true one")
    try:
        calibrate_array(yaw.vectors, sim.geometry, F, stamps=yaw.stamps)
        print("  without the prior: accepted (unexpected)")
    except MagcalError as exc:
        print(f"  without the prior: refused ({str(exc)[:110]}...)")
    res = calibrate_array(yaw.vectors, sim.geometry, F, prior=first, stamps=yaw.stamps)
    got = ratios(res.calibration, new)
    print(f"  with the prior: whole sphere TMI {got[0]:.3f}x, tensor {got[1]:.3f}x the true new calibration; "
          f"{res.envelope.describe()}")


def correlated(runs: int = 30) -> None:
    print(f"honest uncertainty ({runs}-run Monte Carlo, smooth tumble of 800 sets): reported 1-sigma / actual spread")
    for rho in (0.0, 0.9, 0.98):
        sim = field_trial_array(7, NT, noise_correlation=rho)
        rng = np.random.default_rng(7)
        att = tumble(800, 3.0, rng)
        vals, sigs = [], []
        for _ in range(runs):
            rec, _ = sim.run(att, rng, rate=20)
            res = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps)
            vals.append([q.value for q in res.identifiability.quantities])
            sigs.append([q.sigma for q in res.identifiability.quantities])
        r = np.mean(sigs, axis=0) / np.std(vals, axis=0, ddof=1)
        print(f"  AR(1) {rho:4.2f}: median {np.median(r):.2f}, range {r.min():.2f} .. {r.max():.2f}")


def real() -> None:
    if not REAL.exists():
        print(f"real recording: {REAL} not found (data/real/ in the repository, or MAGCAL_REAL_RECORDING)")
        return
    rec, _ = read_csv(REAL)
    geo = ArrayGeometry.single("mag1")
    t0 = time.perf_counter()
    res = calibrate_array(rec.vectors, geo, None, stamps=rec.stamps)
    seconds = time.perf_counter() - t0
    sigma = np.array([q.sigma for q in res.identifiability.quantities])
    blocks = np.array_split(np.arange(len(rec)), 4)
    vals = np.array([[q.value for q in calibrate_array(rec.vectors[b], geo, None, stamps=rec.stamps[b])
                      .identifiability.quantities] for b in blocks])
    r = sigma / (vals.std(axis=0, ddof=1) / 2.0)
    print(f"real QMC5883L hand-held ({len(rec)} sets): residual {res.tmi_after[0] / NT:.0f} nT for a white noise "
          f"of {res.noise[0] / NT:.0f} nT per axis, uncertainty widened {np.sqrt(res.inflation):.1f}x, stated 1-sigma "
          f"/ block scatter median {np.median(r):.2f} ({r.min():.2f} .. {r.max():.2f}); {seconds:.1f} s")


def solve_time(repeats: int = 5) -> None:
    sim = field_trial_array(1, NT)
    rng = np.random.default_rng(1)
    rec, _ = sim.run(uniform_random(2000, rng), rng)
    best = min(_timed(lambda: calibrate_array(rec.vectors, sim.geometry, F)) for _ in range(repeats))
    print(f"solve time, 4 sensors x 2000 sets (method ml, everything included): {best:.3f} s (best of {repeats})")


def _timed(fn: object) -> float:
    t0 = time.perf_counter()
    fn()  # type: ignore[operator]
    return time.perf_counter() - t0


if __name__ == "__main__":
    for part in (solve_time, outliers, envelopes, partial_recalibration, correlated, real):
        part()

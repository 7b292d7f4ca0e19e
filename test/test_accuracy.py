"""Held-out accuracy of every method against the simulator's truth, with bounds a 10 % regression breaks.

Each method calibrates on one simulated manoeuvre (800 random attitudes) and is judged on
1000 FRESH attitudes with fresh noise. Everything it is compared with comes from the
simulator and is computed here with :mod:`truth_tools` (plain numpy), never with the
package's own ``apply`` / ``gradient``:

- the gradient (tensor rows x and y on a cross, ``dB/ds`` on a baseline) in the uniform
  field of the manoeuvre is pure noise; its RMS with the estimate over its RMS with the
  TRUE calibration on the same fresh readings is the ratio to the realized floor (1.0:
  perfect). That floor itself is checked against ``sqrt(2) sigma / d``;
- the TMI residual ``|B| - F`` per sensor, over the true calibration's on the same data;
- the relative alignment: the rotation between each sensor's corrected frame and sensor
  1's, against the truth (rotation-invariant checks such as Li et al.'s (2018) Table 1
  cannot see it).

``ml`` is also judged where it differs most from the papers: a partial recalibration at sea
with the previous calibration as the prior (at the end).

Bounds come from the spread over 20 seeds of this exact procedure (``PYTHONPATH=. python
test/test_accuracy.py`` prints it; the figures are in the comment above ``BOUNDS``). Each ratio bound
lies 8 sd above the measured mean and below 1.1 x that mean, so a method whose tensor or
TMI accuracy degrades by 10 % fails; the angle bounds (7-14 urad) are far below the 5e-5
rad of an aligner that is off by that much.
"""

from __future__ import annotations

import functools
import sys
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np
import pytest
import truth_tools as tt

from magcal_ros.core.units import NT
from magcal_ros.methods.pipeline import SolveOptions, calibrate_array
from magcal_ros.sim import scenarios as sc
from magcal_ros.sim.attitudes import sea_manoeuvre, uniform_random
from magcal_ros.sim.simulator import ArraySimulation

CAL_SETS = 800
FRESH_SETS = 1000
PSO_BUDGET = SolveOptions(pso_particles=30, pso_iterations=300)
"""A small swarm budget that still reaches the ML optimum on 800 sets (30 x 150 does not)."""


@dataclass(frozen=True)
class Case:
    """A method on the scenario of its paper (or of the papers it is compared with)."""

    scenario: Callable[[], ArraySimulation]
    intensity: float
    reference: bool
    """Give the method F (False: relative, F estimated)."""
    raw_noise: bool
    """Noise added to the raw reading (True) or to the orthogonal output (Li et al. 2018)."""
    options: SolveOptions | None = None


def _gradiometer_intensity() -> float:
    return float(np.linalg.norm(sc.GRADIOMETER_FIELD_NT * NT))


CASES: dict[str, Case] = {
    # Li et al. (2018)'s cross, sensor errors and noise (sigma = 1 nT on the orthogonal output).
    "ml": Case(sc.li2018_simulation, sc.LI2018_F, True, False),
    "linear": Case(sc.li2018_simulation, sc.LI2018_F, True, False),
    "pso": Case(sc.li2018_simulation, sc.LI2018_F, True, False, PSO_BUDGET),
    "paired": Case(sc.li2018_simulation, sc.LI2018_F, False, False),  # Wu et al. (2013): no reference
    # The JNWPU 2022 coaxial calibration's cross (0.5 m, F 48750 nT, raw noise 1 nT).
    "reference": Case(sc.coaxial2022_simulation, sc.COAXIAL2022_F, True, True),
    # The two-fluxgate gradiometer paper: two sensors 0.5 m apart, raw noise 1 nT.
    "regression": Case(sc.gradiometer_simulation, _gradiometer_intensity(), True, True),
}

SIGMA = 1 * NT  # every scenario above simulates 1 nT per axis

# Measured over seeds 0..19 with `python test/test_accuracy.py` (mean / sd / max); a bound is the
# mean + 8 sd rounded up (ratios to 0.005, angles to 1 urad), always below 1.1 x the mean:
#   method      gradient ratio          TMI ratio (worst sensor)  relative angle, urad (worst)
#   ml          1.0023 / 0.0012 / 1.0044  1.0063 / 0.0027 / 1.0121  2.07 / 0.51 / 3.21
#   linear      1.0055 / 0.0023 / 1.0092  1.0097 / 0.0044 / 1.0200  3.39 / 0.86 / 5.66
#   pso         1.0045 / 0.0018 / 1.0085  1.0097 / 0.0044 / 1.0200  2.07 / 0.51 / 3.19
#   paired      1.0099 / 0.0028 / 1.0165  1.0195 / 0.0084 / 1.0461  2.09 / 0.52 / 3.24
#   reference   1.0056 / 0.0027 / 1.0108  1.0099 / 0.0044 / 1.0206  4.18 / 1.22 / 6.46
#   regression  1.0024 / 0.0017 / 1.0064  1.0079 / 0.0049 / 1.0202  1.77 / 0.61 / 3.06
# The realized floor over sqrt(2) sigma / d (raw noise: over the floor the true matrices give)
# was 1.0046 / 0.0071 / 1.0204 (cross) and 1.0052 / 0.0100 / 1.0234 (baseline).
URAD = 1e-6
BOUNDS: dict[str, tuple[float, float, float]] = {
    "ml": (1.015, 1.03, 7 * URAD),
    "linear": (1.025, 1.045, 11 * URAD),
    "pso": (1.02, 1.045, 7 * URAD),
    "paired": (1.035, 1.09, 7 * URAD),
    "reference": (1.03, 1.045, 14 * URAD),
    "regression": (1.02, 1.05, 7 * URAD),
}
"""method -> (gradient ratio, TMI ratio, relative angle in rad) on fresh data."""


@functools.lru_cache(maxsize=None)
def evaluate(method: str, seed: int = 0) -> dict[str, Any]:
    """Calibrate ``method`` on its scenario and measure it on fresh data against the truth."""
    case = CASES[method]
    sim = case.scenario()
    rec, _ = sim.run(uniform_random(CAL_SETS, 1000 + seed), rng=2000 + seed)
    res = calibrate_array(rec.vectors, sim.geometry, case.intensity if case.reference else None,
                          method=method, options=case.options)
    scale = case.intensity / res.intensity  # relative calibration: in units of the estimated F
    m_est, o_est = res.calibration.matrices * scale, res.calibration.offsets
    fresh, _ = sim.run(uniform_random(FRESH_SETS, 3000 + seed), rng=4000 + seed)
    m_true, o_true = tt.true_correction(sim)
    b_est = tt.correct(m_est, o_est, fresh.vectors)
    b_true = tt.correct(m_true, o_true, fresh.vectors)
    pos = sim.geometry.positions
    if sim.geometry.size == 2:
        g_est, g_true = tt.baseline_slope(b_est, pos), tt.baseline_slope(b_true, pos)
        pairs, d = [(1, 0)], float(np.linalg.norm(pos[1] - pos[0]))
    else:
        g_est, g_true = tt.cross_rows(b_est, pos), tt.cross_rows(b_true, pos)
        (px, mx), (py, my), d = tt.cross_pairs(pos)
        pairs = [(px, mx), (py, my)]
    expected = (tt.raw_noise_floor(m_true, pairs, SIGMA, d) if case.raw_noise else tt.difference_floor(SIGMA, d))
    tmi_est = tt.rms(np.linalg.norm(b_est, axis=2) - case.intensity, axis=0)
    tmi_true = tt.rms(np.linalg.norm(b_true, axis=2) - case.intensity, axis=0)
    return {
        "gradient": float(tt.rms(g_est) / tt.rms(g_true)),
        "floor": float(tt.rms(g_true) / expected),
        "formula": float(tt.rms(g_true) / tt.difference_floor(SIGMA, d)),
        "tmi": float(np.max(tmi_est / tmi_true)),
        "angle": float(np.max(tt.relative_angles(m_est, tt.true_forward(sim)))),
        "seconds": res.seconds,
    }


@pytest.mark.parametrize("method", list(CASES))
def test_realized_floor_is_the_simulated_noise(method: str) -> None:
    """The truth the ratios divide by: the true calibration's gradient noise on the fresh sets is
    ``sqrt(2) sigma / d`` (raw noise: carried by the true matrices) to the sampling error of
    1000 sets x 6 components (sd 0.9 %; measured 20 seeds: within 2.5 %)."""
    assert abs(evaluate(method)["floor"] - 1.0) < 0.04


@pytest.mark.parametrize("method", list(CASES))
def test_gradient_on_fresh_data(method: str) -> None:
    assert evaluate(method)["gradient"] < BOUNDS[method][0]


@pytest.mark.parametrize("method", list(CASES))
def test_tmi_on_fresh_data(method: str) -> None:
    assert evaluate(method)["tmi"] < BOUNDS[method][1]


@pytest.mark.parametrize("method", list(CASES))
def test_relative_alignment_against_truth(method: str) -> None:
    """Sensor-to-sensor rotations, which Li et al.'s (2018) Table 1 parameters do not contain."""
    assert evaluate(method)["angle"] < BOUNDS[method][2]


# --------------------------------------------------------------------------------------
# ml with a prior: the partial recalibration at sea. A full calibration ashore, then the hull's
# hard iron moves (every offset by 300 nT sd) and the vehicle flies what it flies at sea (yaw
# circles, pitch +-5, roll +-2 deg: 600 sets in time order); the old calibration is the prior.
# Judged on a fresh sea manoeuvre (inside the validity envelope the result reports) against the
# drifted truth. Measured over 10 seeds (mean / sd / max): gradient 1.0030 / 0.0022 / 1.0068,
# worst TMI 1.011 / 0.007 / 1.029; the old calibration gives 310x and 390x. Bounds mean + 8 sd.
PRIOR_BOUNDS = (1.02, 1.07)


@functools.lru_cache(maxsize=None)
def evaluate_recalibration(seed: int = 0) -> dict[str, float]:
    sim = sc.coaxial2022_simulation()
    rec, _ = sim.run(uniform_random(CAL_SETS, 1000 + seed), rng=2000 + seed)
    ashore = calibrate_array(rec.vectors, sim.geometry, sc.COAXIAL2022_F).calibration
    rng = np.random.default_rng(seed)
    drifted = replace(sim, sensors=tuple(replace(s, offset=s.offset + rng.normal(0.0, 300 * NT, 3))
                                         for s in sim.sensors))
    sea, _ = drifted.run(sea_manoeuvre(600, rng=3000 + seed), rng=4000 + seed)
    res = calibrate_array(sea.vectors, sim.geometry, sc.COAXIAL2022_F, prior=ashore, stamps=sea.stamps)
    fresh, _ = drifted.run(sea_manoeuvre(1000, rng=7000 + seed), rng=6000 + seed)
    b = tt.correct(res.calibration.matrices, res.calibration.offsets, fresh.vectors)
    b_true = tt.correct(*tt.true_correction(drifted), fresh.vectors)
    pos = sim.geometry.positions
    tmi = tt.rms(np.linalg.norm(b, axis=2) - sc.COAXIAL2022_F, axis=0)
    tmi_true = tt.rms(np.linalg.norm(b_true, axis=2) - sc.COAXIAL2022_F, axis=0)
    return {"gradient": float(tt.rms(tt.cross_rows(b, pos)) / tt.rms(tt.cross_rows(b_true, pos))),
            "tmi": float(np.max(tmi / tmi_true)),
            "offsets_updated": float({"offset x", "offset y", "offset z"} <= {q.name for q in res.identifiability.updated()})}


def test_partial_recalibration_at_sea_on_fresh_data() -> None:
    r = evaluate_recalibration()
    assert r["offsets_updated"], "the offsets are what a sea manoeuvre must update"
    assert r["gradient"] < PRIOR_BOUNDS[0]
    assert r["tmi"] < PRIOR_BOUNDS[1]


def _spread(seeds: int, methods: list[str]) -> None:
    """Print mean / sd / max of every metric over ``seeds`` seeds (the figures above ``BOUNDS``)."""
    for method in methods:
        rows = [evaluate_recalibration(s) if method == "prior" else evaluate(method, s) for s in range(seeds)]
        parts = []
        for key, unit in (("gradient", 1), ("tmi", 1), ("angle", 1e6), ("floor", 1), ("seconds", 1)):
            if key not in rows[0]:
                continue
            v = np.array([r[key] for r in rows]) * unit
            sd = v.std(ddof=1) if len(v) > 1 else 0.0
            parts.append(f"{key} {v.mean():.4f}/{sd:.4f}/{v.max():.4f}")
        print(f"{method:10s} " + "  ".join(parts), flush=True)


if __name__ == "__main__":  # PYTHONPATH=. python test/test_accuracy.py [SEEDS [METHOD ... | prior]]
    _spread(int(sys.argv[1]) if len(sys.argv) > 1 else 20, sys.argv[2:] or list(CASES))

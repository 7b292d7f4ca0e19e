"""Scenarios of :func:`~magcal_ros.methods.pipeline.calibrate_array` whose outputs are recorded as a reference.

Each scenario is a small, seeded simulation that takes one path through the pipeline (a plain rotation,
a subset refined on every set, a method without the joint fit, a prior on a yaw-only manoeuvre, current
channels one of which is undetermined, temperatures, lags, the IMU's blocks, a collapsed start retried
from spheres, refusals). :func:`record` turns an outcome (a result, or the error raised) into plain
JSON data; :func:`differences` compares two records (numbers to a relative 1e-9, texts exactly).

``python test/pipeline_scenarios.py`` writes the reference ``test/data/pipeline_reference.json``
(run it on the pipeline the reference is to hold; ``test_pipeline_stages.py`` compares against it).
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.units import NT
from magcal_ros.errors import MagcalError
from magcal_ros.methods.pipeline import CalibrationResult, SolveOptions, calibrate_array
from magcal_ros.sim.attitudes import sea_manoeuvre, tumble, uniform_random
from magcal_ros.sim.scenarios import field_trial_array
from magcal_ros.sim.simulator import (
    ArraySimulation,
    hard_iron_moved,
    random_sensor_errors,
)
from magcal_ros.sim.spec import SimulationSpec, run
from magcal_ros.sim.temperature import draw_tempcos, temperature_profile

REFERENCE = Path(__file__).resolve().parent / "data" / "pipeline_reference.json"
F = 51_500 * NT
RTOL = 1e-6
"""Numbers agree to this relative part (of themselves, or of the largest number of the array they are in): what
the pipeline computes moves by up to a few 1e-8 between builds of numpy and its BLAS (an ill-conditioned
covariance), and entries at round-off (1e-16 in a matrix of ones) by their whole size; a change of the method
moves them far more."""
ATOL = 1e-300  # numbers that are exactly 0 stay 0
THRUSTERS = ((-0.7, 0.25, 0.1, 0.06, 0.0, 0.04), (-0.7, -0.25, 0.1, 0.0, -0.06, 0.04))
CHANNELS = ("thruster1/battery", "thruster2/battery")

Call = tuple[tuple[Any, ...], dict[str, Any]]
"""Positional and keyword arguments of :func:`calibrate_array`."""


def _rotation() -> Call:
    """Four fluxgates, random attitudes, stamps in no time order of motion (no lag block)."""
    sim = field_trial_array(1)
    rng = np.random.default_rng(1)
    rec, _ = sim.run(uniform_random(300, rng), rng)
    return (rec.vectors, sim.geometry, F), {"stamps": rec.stamps}


def _subset_refined() -> Call:
    """A tumble longer than the solve budget: solved on a subset, refined on every set (jackknifed)."""
    sim = field_trial_array(2)
    rng = np.random.default_rng(2)
    rec, _ = sim.run(tumble(700, 3.0, rng), rng, rate=10)
    return (rec.vectors, sim.geometry, F), {"stamps": rec.stamps,
                                            "options": SolveOptions(max_solve_sets=450)}


def _relative() -> Call:
    """No reference intensity: the relative path (the sensors' mean gain 1)."""
    sim = field_trial_array(3)
    rng = np.random.default_rng(3)
    rec, _ = sim.run(uniform_random(300, rng), rng)
    return (rec.vectors, sim.geometry, None), {}


def _linear_method() -> Call:
    """A method without the joint fit (Li et al. 2018): its own solution, evaluated."""
    sim = field_trial_array(4)
    rng = np.random.default_rng(4)
    rec, _ = sim.run(uniform_random(300, rng), rng)
    return (rec.vectors, sim.geometry, F, "linear"), {}


def _paired_method_no_joint() -> Call:
    """Method ml with the joint fit switched off, relative."""
    sim = field_trial_array(5)
    rng = np.random.default_rng(5)
    rec, _ = sim.run(uniform_random(300, rng), rng)
    return (rec.vectors, sim.geometry, None, "ml", SolveOptions(joint=False)), {}


def _prior_parts(intensity_prior: bool) -> tuple[Any, Any, Any]:
    sim = field_trial_array(6)
    rng = np.random.default_rng(6)
    rec, _ = sim.run(uniform_random(400, rng), rng)
    first = calibrate_array(rec.vectors, sim.geometry, F).calibration
    if not intensity_prior:
        first = replace(first, metadata={k: v for k, v in first.metadata.items() if k != "intensity"})
    new = hard_iron_moved(sim, rng)
    yaw, _ = new.run(sea_manoeuvre(400, 0.0, 0.0, turns=2, wobble_deg=3.0, rng=rng), rng)
    return first, yaw, sim


def _prior_yaw() -> Call:
    """A yaw-only manoeuvre with a prior: the offsets updated, what yaw cannot determine kept."""
    first, yaw, sim = _prior_parts(True)
    return (yaw.vectors, sim.geometry, F), {"prior": first, "stamps": yaw.stamps}


def _prior_yaw_no_reference() -> Call:
    """The same without a reference field: the prior's intensity is used (and said)."""
    first, yaw, sim = _prior_parts(True)
    return (yaw.vectors, sim.geometry, None), {"prior": first}


def _prior_yaw_wrong_reference() -> Call:
    """A prior with a reference 4 % off the field: refused, or the intensity the data imply said."""
    first, yaw, sim = _prior_parts(False)
    return (yaw.vectors, sim.geometry, 1.04 * F), {"prior": first}


def _current_manoeuvre() -> tuple[Any, Any, Any]:
    return run(SimulationSpec(count=500, seed=5, noise=NT, thrusters=THRUSTERS, thruster_current="random:20"))


def _currents() -> Call:
    """Two thrusters drawing random currents: their interference solved jointly."""
    rec, _, sim = _current_manoeuvre()
    return (rec.vectors, sim.geometry, 5.5e-5), {"currents": rec.currents, "channels": CHANNELS}


def _currents_one_undetermined() -> Call:
    """The second channel never varies: not solved (the recursion without it), a warning names it."""
    rec, truth, sim = _current_manoeuvre()
    constant = np.column_stack([rec.currents[:, 0], np.full(len(rec), 10.0)])
    data = sim.run(truth.attitudes, 3, currents=constant)[0]
    return (data.vectors, sim.geometry, 5.5e-5), {"currents": constant, "channels": CHANNELS}


def _currents_lockstep() -> Call:
    """Both channels in lockstep: not solved, and the field left is not uniform: refused naming both."""
    rec, truth, sim = _current_manoeuvre()
    lockstep = np.column_stack([rec.currents[:, 0], rec.currents[:, 0]])
    data = sim.run(truth.attitudes, 3, currents=lockstep)[0]
    return (data.vectors, sim.geometry, 5.5e-5), {"currents": lockstep, "channels": CHANNELS}


def _thermal_array(seed: int) -> ArraySimulation:
    rng = np.random.default_rng(seed)
    sensors = tuple(random_sensor_errors(rng, hard_iron_sd=100 * NT, soft_iron_sd=0.01) for _ in range(4))
    a, g = draw_tempcos(np.random.default_rng(seed + 100), 4, 0.5 * NT, 30e-6)
    return ArraySimulation(ArrayGeometry.cross(), sensors, earth_field(5e-5, 60.0, -5.0), noise=NT,
                           offset_tempco=a, gain_tempco=g, temperature_reference=15.0)


def _temperatures() -> Call:
    """Tumbles at 5, 15 and 25 C: the temperature terms fitted (and the lag block on)."""
    sim = _thermal_array(1)
    temps = temperature_profile("steps", [5, 15, 25], 600)
    rec, _ = sim.run(tumble(600, rng=1), 2, temperatures=temps, rate=7.5)
    return (rec.vectors, sim.geometry, 5e-5), {"stamps": rec.stamps, "temperatures": rec.temperatures}


def _temperatures_held() -> Call:
    """The temperature changes only while still: gains per kelvin undetermined, held at zero."""
    sim = _thermal_array(4)
    turning = tumble(450, rng=4)
    att = np.concatenate([turning, np.repeat(turning[-1:], 150, axis=0)])
    temps = np.concatenate([np.full(450, 15.0), np.linspace(15.0, 25.0, 150)])
    rec, _ = sim.run(att, 5, temperatures=temps, rate=7.5)
    return (rec.vectors, sim.geometry, 5e-5), {"stamps": rec.stamps, "temperatures": rec.temperatures}


def _lag() -> Call:
    """A smooth tumble in time order with stamps: the lag block (each sensor's lag fitted)."""
    sim = field_trial_array(8)
    rng = np.random.default_rng(8)
    rec, _ = sim.run(tumble(600, 2.0, rng), rng, rate=20)
    return (rec.vectors, sim.geometry, F), {"stamps": rec.stamps}


def _imu() -> Call:
    """A tumble with the IMU's orientation: outputs in its frame."""
    spec = SimulationSpec(count=300, schedule="tumble", seed=11, noise=NT, imu=True, imu_mounting=(2.0, -2.5, 3.0),
                          imu_orientation_noise=0.02)
    rec, _, sim = run(spec)
    return (rec.vectors, sim.geometry, spec.intensity), {"stamps": rec.stamps, "imu": rec.imu}


def _compass(seed: int, wobble: float | None) -> tuple[ArraySimulation, Any]:
    rng = np.random.default_rng(seed)
    sensor = random_sensor_errors(rng, scale_sd=0.05, offset_sd=0.5 * 5e-5)
    sim = ArraySimulation(ArrayGeometry.single("mag1"), (sensor,), earth_field(5e-5, 60, 5), noise=0.005 * 5e-5)
    motion = tumble(400, 3.0, rng) if wobble is None else sea_manoeuvre(1200, 0, 0, turns=3, wobble_deg=wobble,
                                                                         rng=rng)
    return sim, sim.run(motion, rng, rate=50)[0]


def _sphere_retry() -> Call:
    """A noisy consumer sensor, quantised, yaw circles with 20 deg of wobble: the closed-form start
    collapses and the fit starts again from a sphere (a subset, refined on every set)."""
    sim, rec = _compass(46, 20.0)
    q = 1e-4 / 12000
    return (np.round(rec.vectors / q) * q, sim.geometry, 5e-5), {"stamps": rec.stamps,
                                                                 "options": SolveOptions(max_solve_sets=800)}


def _single_mounting() -> Call:
    """One sensor with a given mounting rotation."""
    sim, rec = _compass(48, None)
    c, s = math.cos(0.1), math.sin(0.1)
    mounting = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (rec.vectors, sim.geometry, 5e-5), {"options": SolveOptions(mounting=mounting)}


def _refused_yaw_only() -> Call:
    """A yaw-only manoeuvre without a prior: refused, naming the rotation that would determine it."""
    _, yaw, sim = _prior_parts(True)
    return (yaw.vectors, sim.geometry, F), {}


def _refused_yaw_linear() -> Call:
    """A yaw-only manoeuvre with method linear: its start fails (or the result is refused)."""
    _, yaw, sim = _prior_parts(True)
    return (yaw.vectors, sim.geometry, F, "linear"), {}


def _start_failed_flat_yaw() -> Call:
    """Method linear on flat yaw circles: its closed-form start fails (not an ellipsoid), the crude start
    and then spheres are tried, and the manoeuvre is refused."""
    sim = field_trial_array(6)
    rng = np.random.default_rng(12)
    yaw, _ = sim.run(sea_manoeuvre(400, 0.0, 0.0, turns=2, wobble_deg=0.0, rng=rng), rng)
    return (yaw.vectors, sim.geometry, F, "linear"), {}


def _refused_few_sets() -> Call:
    """Too few sets."""
    sim = field_trial_array(9)
    rng = np.random.default_rng(9)
    rec, _ = sim.run(uniform_random(11, rng), rng)
    return (rec.vectors, sim.geometry, F), {}


def _refused_gradient() -> Call:
    """A constant gradient of about 300 nT/m across the array: refused as not uniform."""
    base = field_trial_array(10)
    g = 300 * NT * np.array([[1.0, 0.5, 0.0], [0.5, -0.5, 0.3], [0.0, 0.3, -0.5]])
    sim = ArraySimulation(base.geometry, base.sensors, base.earth, noise=base.noise, world_gradient=g)
    rng = np.random.default_rng(10)
    rec, _ = sim.run(uniform_random(300, rng), rng)
    return (rec.vectors, sim.geometry, F), {}


def _refused_bad_input() -> Call:
    """A reference field in nT, not T."""
    sim = field_trial_array(1)
    rng = np.random.default_rng(1)
    rec, _ = sim.run(uniform_random(60, rng), rng)
    return (rec.vectors, sim.geometry, 51_500.0), {}


def _prior_wrong_reference_refused() -> Call:
    """A prior with a reference 8 % off: refused, the intensity the data imply said (a second solve)."""
    first, yaw, sim = _prior_parts(False)
    return (yaw.vectors, sim.geometry, 1.08 * F), {"prior": first}


def _sea(wobble: float) -> Call:
    """Yaw circles with pitch and roll of +-5 deg and ``wobble`` deg: weak quantities, a narrow envelope."""
    sim = field_trial_array(6)
    rng = np.random.default_rng(13)
    rec, _ = sim.run(sea_manoeuvre(300, 5.0, 5.0, turns=2, wobble_deg=wobble, rng=rng), rng)
    return (rec.vectors, sim.geometry, F), {}


def _sphere_retry_relative() -> Call:
    """The collapsed start retried from spheres without a reference (the sphere start's mean gain 1)."""
    args, kwargs = _sphere_retry()
    return (args[0], args[1], None), kwargs


def _linear_sea() -> Call:
    """Method linear on a narrow sea manoeuvre."""
    args, kwargs = _sea(20.0)
    return args + ("linear",), kwargs


def _linear_compass_yaw() -> Call:
    """Method linear on one noisy sensor turned in yaw with wobble (its closed form fails or collapses)."""
    args, kwargs = _sphere_retry()
    return args + ("linear",), kwargs


def _small_input(**change: Any) -> Call:
    sim = field_trial_array(1)
    rng = np.random.default_rng(1)
    rec, _ = sim.run(uniform_random(60, rng), rng)
    call: dict[str, Any] = {"raw": rec.vectors, "geometry": sim.geometry, "reference_field": F}
    call.update(change)
    return (), call


def _still() -> Call:
    sim = field_trial_array(1)
    rng = np.random.default_rng(1)
    rec, _ = sim.run(uniform_random(1, rng), rng)
    return _small_input(raw=np.repeat(rec.vectors, 60, axis=0) + rng.normal(size=(60, 4, 3)) * 0.1 * NT)


def _clipped() -> Call:
    sim, rec = _compass(48, None)
    full_scale = 0.85 * np.abs(rec.vectors).max()
    return (np.clip(rec.vectors, -full_scale, full_scale), sim.geometry, 5e-5), {}


def _skewed_mounting() -> Call:
    sim, rec = _compass(48, None)
    return (rec.vectors, sim.geometry, 5e-5), {"options": SolveOptions(mounting=np.eye(3) * 1.1)}


REFUSED_INPUTS: dict[str, Callable[[], Call]] = {
    "refused_unknown_method": lambda: _small_input(method="nonsense"),
    "refused_bad_currents": lambda: _small_input(currents=np.ones((60, 2)), channels=("a",)),
    "refused_channels_with_linear": lambda: _small_input(method="linear", channels=("a",), currents=np.ones((60, 1))),
    "refused_linear_without_reference": lambda: _small_input(method="linear", reference_field=None),
    "refused_barely_changes": _still,
    "refused_temperatures_with_linear": lambda: _small_input(method="linear", temperatures=np.linspace(0, 20, 60)),
    "refused_mounting_on_array": lambda: _small_input(options=SolveOptions(mounting=np.eye(3))),
    "refused_stamps_shape": lambda: _small_input(stamps=np.arange(59)),
    "refused_saturated": _clipped,
    "refused_mounting_not_rotation": _skewed_mounting,
}
"""Input the pipeline refuses (most before any fit)."""


SCENARIOS: dict[str, Callable[[], Call]] = {
    "rotation": _rotation,
    "subset_refined": _subset_refined,
    "relative": _relative,
    "linear_method": _linear_method,
    "ml_without_joint": _paired_method_no_joint,
    "prior_yaw": _prior_yaw,
    "prior_yaw_no_reference": _prior_yaw_no_reference,
    "prior_yaw_wrong_reference": _prior_yaw_wrong_reference,
    "currents": _currents,
    "currents_one_undetermined": _currents_one_undetermined,
    "currents_lockstep": _currents_lockstep,
    "temperatures": _temperatures,
    "temperatures_held": _temperatures_held,
    "lag": _lag,
    "imu": _imu,
    "sphere_retry": _sphere_retry,
    "single_mounting": _single_mounting,
    "refused_yaw_only": _refused_yaw_only,
    "refused_yaw_linear": _refused_yaw_linear,
    "start_failed_flat_yaw": _start_failed_flat_yaw,
    "refused_few_sets": _refused_few_sets,
    "refused_gradient": _refused_gradient,
    "refused_bad_input": _refused_bad_input,
    "prior_wrong_reference_refused": _prior_wrong_reference_refused,
    "sea_weak": lambda: _sea(5.0),
    "sea_envelope": lambda: _sea(10.0),
    "sphere_retry_relative": _sphere_retry_relative,
    "linear_sea": _linear_sea,
    "linear_compass_yaw": _linear_compass_yaw,
    **REFUSED_INPUTS,
}


def _plain(x: Any) -> Any:
    """Numbers, strings, lists and dicts only (arrays as nested lists, None kept)."""
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def _result_record(res: CalibrationResult, stages: list[str]) -> dict[str, Any]:
    cal, ana, env = res.calibration, res.identifiability, res.envelope
    return _plain({
        "kind": "result",
        "matrices": cal.matrices, "offsets": cal.offsets, "covariances": cal.covariances,
        "channels": list(cal.channels), "interference": cal.interference, "time_offsets": cal.time_offsets,
        "temperature_reference": cal.temperature_reference, "offset_tempco": cal.offset_tempco,
        "matrix_tempco": cal.matrix_tempco, "output_rotation": cal.output_rotation, "frame_id": cal.frame_id,
        "method": res.method, "samples": res.samples, "intensity": res.intensity, "relative": res.relative,
        "tmi_before": res.tmi_before, "tmi_after": res.tmi_after, "tensor_before": res.tensor_before,
        "tensor_after": res.tensor_after, "noise": res.noise, "outliers": res.outliers, "prior": res.prior,
        "inflation": res.inflation, "coverage": res.excitation.coverage,
        "quantities": [[q.sensor, q.name, q.unit, q.value, q.sigma, q.effect, q.status, q.prior_sigma]
                       for q in ana.quantities],
        "envelope": [env.pitch_deg, env.roll_deg, env.ratio_sphere, env.describe()],
        "warnings": res.warnings, "summary": res.summary(), "frame_note": res.frame_note(),
        "extras": {k: v for k, v in res.extras.items() if k in ("mounting", "bandwidth", "temperature_range",
                                                                "temperature_stored", "block_notes", "drift",
                                                                "solved_on")},
        "metadata": {k: v for k, v in cal.metadata.items() if k != "created"},
        "stages": stages,
    })


def record(name: str) -> dict[str, Any]:
    """The outcome of scenario ``name``: its result's numbers and texts, or the error's type and message."""
    args, kwargs = SCENARIOS[name]()
    stages: list[str] = []
    options = kwargs.get("options") or (args[4] if len(args) > 4 else None) or SolveOptions()
    options = replace(options, progress=stages.append)
    if len(args) > 4:
        args = args[:4] + (options,) + args[5:]
    else:
        kwargs = {**kwargs, "options": options}
    try:
        res = calibrate_array(*args, **kwargs)
    except MagcalError as exc:
        return {"kind": "error", "type": type(exc).__name__, "message": str(exc), "stages": stages}
    return _result_record(res, stages)


def _largest(value: Any) -> float:
    """The largest finite magnitude among the numbers of a (nested) list; 0 for anything else."""
    if isinstance(value, list):
        return max((_largest(v) for v in value), default=0.0)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return abs(float(value))
    return 0.0


def differences(got: Any, want: Any, path: str = "", scale: float = 0.0) -> list[str]:
    """Where ``got`` differs from ``want``: numbers beyond :data:`RTOL` (of themselves or of ``scale``, the
    largest of the top array they are in), anything else unequal."""
    if isinstance(want, dict) and isinstance(got, dict):
        if set(got) != set(want):
            return [f"{path}: keys {sorted(set(got) ^ set(want))} differ"]
        return [d for k in want for d in differences(got[k], want[k], f"{path}.{k}")]
    if isinstance(want, list) and isinstance(got, list):
        if len(got) != len(want):
            return [f"{path}: length {len(got)} != {len(want)}"]
        scale = scale or _largest(want)
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in differences(g, w, f"{path}[{i}]", scale)]
    numbers = (int, float)
    if isinstance(want, numbers) and isinstance(got, numbers) and not isinstance(want, bool):
        if math.isnan(want) and math.isnan(got):
            return []
        if got == want or abs(got - want) <= RTOL * max(abs(got), abs(want), scale) + ATOL:
            return []
        return [f"{path}: {got!r} != {want!r}"]
    return [] if got == want else [f"{path}: {got!r} != {want!r}"]


def main() -> int:
    """Write the reference of every scenario (or of those named on the command line)."""
    names = sys.argv[1:] or list(SCENARIOS)
    out = json.loads(REFERENCE.read_text()) if REFERENCE.exists() and sys.argv[1:] else {}
    for name in names:
        out[name] = record(name)
        kind = out[name]["kind"]
        print(f"{name}: {kind}" + (f" {out[name]['type']}: {out[name]['message'][:150]}" if kind == "error" else
                                   f" {out[name]['summary'][:150]}"), flush=True)
    REFERENCE.parent.mkdir(exist_ok=True)
    REFERENCE.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

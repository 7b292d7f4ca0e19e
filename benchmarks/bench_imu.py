"""Benchmark the IMU's blocks of the forward model (not a test; prints its figures).

Run: ``python benchmarks/bench_imu.py`` from the repository root.

- yaw manoeuvre with +-5 deg wobble (1200 sets, 2 yaw circles, no pitch or roll swing, IMU
  mounted 2, -2.5, 3 deg off the array): the envelope and the predicted whole-sphere TMI
  error (ratio to the noise) without the IMU, with its gyro alone, with its orientation;
  and the measured TMI and corrected-vector error (IMU frame) on fresh random attitudes;
- a tumble over a site with a 30 nT/m-scale world gradient, tested where the field is
  uniform: tensor and TMI with the IMU (the gradient a block of the model) and without it
  (accepted with --max-residual: the gradient becomes calibration error).
"""

from __future__ import annotations

import time

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np


from magcal_ros.core.metrics import rms, tensor_floor, tensor_rms, tmi_rms  # noqa: E402
from magcal_ros.core.recording import ImuSamples  # noqa: E402
from magcal_ros.errors import MagcalError  # noqa: E402
from magcal_ros.methods.pipeline import SolveOptions, calibrate_array  # noqa: E402
from magcal_ros.sim.spec import SimulationSpec, run  # noqa: E402

NT = 1e-9
NOISE = 1 * NT
MOUNTING = (2.0, -2.5, 3.0)


def _fresh(seed: int):
    rec, truth, sim = run(SimulationSpec(count=800, schedule="random", seed=seed, noise=NOISE, imu=True,
                                         imu_mounting=MOUNTING))
    return rec, truth, sim


def _line(name: str, result, fresh, truth, sim, seconds: float) -> str:
    env = result.envelope
    out = result.calibration.outputs(fresh.vectors)
    vectors = "vectors in the array frame (no IMU: no truth to compare)"
    if result.calibration.rotated:
        err = rms(out.vectors - np.einsum("ab,nsb->nsa", sim.imu.mounting, truth.field)) / NT
        vectors = f"vectors {err:7.2f} nT/axis from the truth (IMU frame)"
    return (f"  {name:<12} {env.describe():<40} sphere {env.ratio_sphere:7.2f}x noise | fresh: TMI "
            f"{np.max(tmi_rms(out.vectors, result.intensity)) / NT:7.2f} nT, {vectors}, {seconds:5.1f} s")


def yaw_wobble(seed: int = 7) -> None:
    spec = SimulationSpec(count=1200, schedule="sea", pitch=0.0, roll=0.0, wobble=5.0, turns=2.0, seed=seed,
                          noise=NOISE, imu=True, imu_mounting=MOUNTING, imu_gyro_noise=1e-4,
                          imu_orientation_noise=0.02)
    rec, _, sim = run(spec)
    fresh, ftruth, _ = _fresh(seed)
    gyro = ImuSamples(np.full((len(rec), 4), np.nan), rec.imu.angular_velocity, rec.imu.frame_id)
    print(f"yaw circles with +-5 deg wobble, {len(rec)} sets, 1 nT noise, IMU {MOUNTING} deg off "
          "(gyro 1e-4 rad/s, orientation 0.02 deg):")
    for name, imu in (("without IMU", None), ("gyro only", gyro), ("orientation", rec.imu)):
        t0 = time.perf_counter()
        try:
            result = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=imu)
        except MagcalError as exc:
            print(f"  {name:<12} refused: {str(exc)[:120]}")
            continue
        print(_line(name, result, fresh, ftruth, sim, time.perf_counter() - t0))
        if result.extras.get("imu") is not None:
            print("               " + result.extras["imu"].notes()[0])


def site_gradient(seed: int = 5) -> None:
    spec = SimulationSpec(count=1000, schedule="tumble", seed=seed, noise=NOISE, imu=True, imu_mounting=MOUNTING,
                          imu_orientation_noise=0.02, world_gradient=(30e-9, 10e-9, -15e-9, -20e-9, 5e-9))
    rec, _, sim = run(spec)
    fresh, ftruth, _ = _fresh(seed)
    floor = tensor_floor(NOISE, spec.baseline)
    print(f"tumble over a site gradient (NED xx 30, xy 10, xz -15, yy -20, yz 5 nT/m), tested in a uniform "
          f"field; tensor floor {floor / NT:.2f} nT/m:")
    for name, imu, opts in (("without IMU", None, SolveOptions(max_residual=100 * NT)),
                            ("orientation", rec.imu, None)):
        t0 = time.perf_counter()
        result = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=imu, options=opts)
        out = result.calibration.outputs(fresh.vectors)
        print(f"  {name:<12} tensor {tensor_rms(out.tensor) / floor:5.2f}x floor, TMI "
              f"{np.max(tmi_rms(out.vectors, spec.intensity)) / NOISE:5.2f}x noise, {time.perf_counter() - t0:5.1f} s")
        if result.extras.get("imu") is not None:
            print("               " + result.extras["imu"].notes()[-1])


if __name__ == "__main__":
    yaw_wobble()
    site_gradient()

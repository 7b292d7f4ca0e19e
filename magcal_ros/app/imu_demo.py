"""The demo's IMU step: a tumble with the vehicle's IMU, calibrated with it, outputs in the IMU frame.

Offline (the core pipeline, as ``magcal calibrate --imu`` runs it): four fluxgates on the
0.4 m cross with 1 nT noise tumble over a pier whose gradient is 30-50 nT/m, the IMU mounted
2, -1.5, 3 deg (roll, pitch, yaw) off the array with 0.02 deg of orientation error; the
calibration fits the array-to-IMU rotation and the site gradient with the sensors, and fresh
attitudes in a uniform field are corrected into the IMU's frame and compared with the truth.
"""

from __future__ import annotations

import numpy as np

from magcal_ros.core.metrics import rms, tensor_floor, tensor_rms, tmi_rms
from magcal_ros.core.units import NT
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.sim.spec import SimulationSpec, run

MOUNTING = (2.0, -1.5, 3.0)
PIER_GRADIENT = (30e-9, 10e-9, -15e-9, -20e-9, 5e-9)
"""T/m, world NED: xx, xy, xz, yy, yz."""


def imu_step(seed: int, sets: int = 600, fresh: int = 300) -> list[str]:
    """Lines for the demo's output (see the module docstring)."""
    spec = SimulationSpec(count=sets, schedule="tumble", seed=seed, noise=1 * NT, imu=True, imu_mounting=MOUNTING,
                          imu_orientation_noise=0.02, world_gradient=PIER_GRADIENT)
    rec, _, sim = run(spec)
    result = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=rec.imu)
    check, truth, _ = run(SimulationSpec(count=fresh, schedule="random", seed=seed, noise=1 * NT))
    out = result.calibration.outputs(check.vectors)
    error = rms(out.vectors - np.einsum("ab,nsb->nsa", sim.imu.mounting, truth.field))
    report = result.extras["imu"]
    lines = [f"IMU: {sets} sets of a tumble over a pier ({', '.join(f'{g / NT:g}' for g in PIER_GRADIENT)} nT/m, "
             f"NED), IMU mounted {MOUNTING} deg (roll, pitch, yaw) off the array"]
    lines += [f"  {note}" for note in report.notes()]
    lines.append("  (the angles are from the array frame the calibration reports, its virtual centre sensor's axes: "
                 "they differ from the mechanical mounting by that frame's own small rotation)")
    lines.append(f"  fresh attitudes in a uniform field, outputs in {result.calibration.frame_id}: vectors "
                 f"{error / NT:.2f} nT/axis from the truth, worst TMI RMS "
                 f"{np.max(tmi_rms(out.vectors, spec.intensity)) / NT:.2f} nT, tensor RMS "
                 f"{tensor_rms(out.tensor) / NT:.2f} nT/m (floor {tensor_floor(1 * NT, spec.baseline) / NT:.2f})")
    return lines

"""Side streams: how well the IMU is matched to the sets, and what temperature terms cost per set.

1. A hand tumble (~30 deg/s) sampled at 10 sets/s, its IMU on its own clock at 50, 100 and
   200 Hz: the orientation error at the sets with the interpolation of ``core.imu.match_imu``
   against the latest sample alone (the currents' rule), against the simulator's truth.
2. ``ArrayCalibration.outputs`` of one set (the correction node's per-set call): plain, with
   temperature terms, with an output rotation.

Prints its figures; decides nothing (timings depend on the machine).

    .venv/bin/python benchmarks/bench_side_streams.py
"""

from __future__ import annotations

import timeit

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np
from scipy.spatial.transform import Rotation

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import match_imu
from magcal_ros.core.matching import latest_before
from magcal_ros.sim.spec import SimulationSpec, run

S = 1_000_000_000


def imu_matching() -> None:
    print("IMU at the set instants, hand tumble at 10 sets/s (orientation error, deg: median / max)")
    for rate in (50.0, 100.0, 200.0):
        rec, truth, _ = run(SimulationSpec(schedule="tumble", count=1200, seed=1, noise=0.0, imu=True, imu_rate=rate))
        stream = truth.imu_stream
        imu, fresh = match_imu(rec.stamps, stream, S // 10)
        at, fresh_latest = latest_before(stream.stamps, rec.stamps, S // 10)
        ok = fresh & fresh_latest
        want = Rotation.from_quat(truth.imu_orientation[ok])
        interp = np.degrees((Rotation.from_quat(imu.orientation[ok]).inv() * want).magnitude())
        latest = np.degrees((Rotation.from_quat(stream.orientation[at[ok]]).inv() * want).magnitude())
        turn = np.degrees(np.median(np.linalg.norm(truth.imu_angular_velocity, axis=1)))
        print(f"  IMU {rate:5.0f} Hz (turn rate median {turn:.0f} deg/s): interpolated {np.median(interp):.4f} / "
              f"{interp.max():.4f}, latest sample {np.median(latest):.4f} / {latest.max():.4f}")


def per_set_cost() -> None:
    geo = ArrayGeometry.cross()
    m, o = np.tile(np.eye(3), (4, 1, 1)), np.zeros((4, 3))
    rot = Rotation.from_euler("xyz", [2, -1.5, 3], degrees=True).as_matrix()
    cases = {
        "plain": (ArrayCalibration(geo, m, o), None),
        "temperature terms": (ArrayCalibration(geo, m, o, temperature_reference=20.0,
                                               offset_tempco=np.full((4, 3), 1e-10)), np.full((1, 4), 21.0)),
        "output rotation": (ArrayCalibration(geo, m, o, output_rotation=rot), None),
    }
    raw = np.full((1, 4, 3), 2e-5)
    print("ArrayCalibration.outputs of one set (best of 20 x 2000 calls)")
    for name, (cal, temps) in cases.items():
        best = min(timeit.repeat(lambda cal=cal, temps=temps: cal.outputs(raw, "difference", None, temps), number=2000, repeat=20)) / 2000
        print(f"  {name:<18} {best * 1e6:6.1f} us")


if __name__ == "__main__":
    imu_matching()
    per_set_cost()

"""Simulated recordings on disk: the recording and its ground truth, as ``magcal simulate`` writes them.

Files for an output ``OUT`` (a rosbag2 directory, or a CSV file when it ends in .csv):

- ``OUT``: the raw recording, topics ``/<name>/raw`` (or CSV columns ``<name>.x,...``),
  plus one ``sensor_msgs/msg/BatteryState`` topic ``/<channel>`` per thruster (or CSV
  columns ``current.<channel>``, A); with a temperature profile ``/<name>/temperature``
  (``sensor_msgs/msg/Temperature``, deg C; CSV ``temperature.<name>``); with an IMU ``/imu``
  (``sensor_msgs/msg/Imu`` at the IMU's rate or each set's stamp; CSV ``imu.qx..imu.qw`` and,
  for schedules flown in time, ``imu.wx..imu.wz``).
- ``OUT.truth.yaml``: the true calibration as a calibration file (``magcal_correction``
  block, loadable by ``magcal correct --calibration`` and the correction node; with
  thrusters its ``interference_channels`` and per-sensor ``interference``, the thrusters'
  field per ampere at each sensor, T/A, platform frame) plus a ``magcal_simulation`` block
  with every simulation parameter.
- ``OUT.truth.npz``: per-set truth, platform frame: ``stamps`` (N,) int64 ns, ``field``
  (N, S, 3) T at each sensor (without the thrusters' field), ``centre`` (N, 3) T,
  ``gradient`` (N, 3, 3) T/m at the centre (``G[i, j] = dB_j/dx_i``), ``attitudes``
  (N, 3, 3) platform to world, ``names`` (S,), ``positions`` (S, 3) m, ``earth`` (3,) T
  world NED, ``currents`` (N, m) A and ``channels`` (m,) of the thrusters; with a
  temperature profile ``temperatures`` (N, S) deg C, the sensors' true temperatures (the
  recording's carry ``temperature_noise``); with an IMU ``imu_orientation`` (N, 4) the true
  orientation IMU frame -> world ENU (x, y, z, w), ``imu_angular_velocity`` (N, 3) the true
  rate (rad/s, IMU frame; NaN for schedules not flown in time) and ``output_rotation`` (3, 3)
  the mounting, array frame -> IMU frame (the true calibration's outputs are
  ``output_rotation @ field``); with a world gradient ``world_gradient`` (3, 3) T/m NED and
  ``world_gradient_enu`` (3, 3) T/m ENU (``gradient`` includes it, platform frame).

The YAML's ``magcal_simulation`` block holds, besides the spec, each sensor's
``offset_tempco`` (T/K, raw axes) and ``gain_tempco`` (1/K) when the sensors follow their
temperature, ``imu_mounting_matrix`` (9, row-major) with an IMU and ``world_gradient_ned`` /
``world_gradient_enu`` (9, T/m) with a world gradient; the ``magcal_correction`` block is
the true calibration, its temperature terms and output rotation included.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magcal_ros.core.imu import NED_TO_ENU
from magcal_ros.core.metrics import tensor_floor
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io.atomic import atomic_path
from magcal_ros.io.bag_writer import check_storage, write_recording_bag
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.io.recordings import is_csv
from magcal_ros.sim.simulator import ArraySimulation, Truth
from magcal_ros.sim.spec import SimulationSpec, run

SIMULATION_NODE = "magcal_simulation"


def truth_paths(out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``OUT.truth.yaml`` and ``OUT.truth.npz`` beside the recording ``OUT``."""
    base = str(out).rstrip("/\\")
    return Path(base + ".truth.yaml"), Path(base + ".truth.npz")


def truth_yaml(spec: SimulationSpec, truth: Truth, sim: ArraySimulation) -> str:
    """The calibration file of the true calibration plus the simulation parameters."""
    cal = truth.calibration
    params: dict[str, Any] = {k: v for k, v in asdict(spec).items()
                              if k not in ("dipoles", "names", "position", "thrusters")
                              and not (isinstance(v, tuple) and not v)}  # ROS parameter files hold no empty lists
    params.update(
        {
            "sets": int(len(truth.centre)),
            "names": list(spec.names),
            "position": [float(v) for v in spec.position],
            "dipole_count": len(spec.dipoles),
            "earth_field": [float(v) for v in sim.earth],
            "tensor_noise_floor": tensor_floor(spec.noise, spec.baseline),
        }
    )
    if spec.dipoles:  # ROS parameter files cannot hold empty lists
        params["dipoles"] = [float(v) for d in spec.dipoles for v in d]
    if spec.thrusters:  # x, y, z (m), mx, my, mz (A m^2 / A) per thruster, platform frame
        params["thrusters"] = [float(v) for d in spec.thrusters for v in d]
        params["thruster_channels"] = list(spec.channels)
    for name, s in zip(spec.names, sim.sensors):
        params[name] = {
            "scale": [float(v) for v in s.scale],
            "angles_rad": [float(v) for v in s.angles],
            "offset": [float(v) for v in s.offset],
            "misalignment_rad": [float(v) for v in s.misalignment],
            "hard_iron": [float(v) for v in s.hard_iron],
            "soft_iron": [float(v) for v in s.soft_iron.reshape(-1)],
        }
    if sim.temperature_dependent:
        for i, name in enumerate(spec.names):
            params[name]["offset_tempco"] = [float(v) for v in sim._tempcos()[0][i]]
            params[name]["gain_tempco"] = [float(v) for v in sim._tempcos()[1][i]]
    if sim.imu is not None:
        params["imu_mounting_matrix"] = [float(v) for v in sim.imu.mounting.reshape(-1)]
    if sim.world_gradient is not None:
        params["world_gradient_ned"] = [float(v) for v in sim.world_gradient.reshape(-1)]
        params["world_gradient_enu"] = [float(v) for v in (NED_TO_ENU @ sim.world_gradient @ NED_TO_ENU.T).reshape(-1)]
    text = calfile.dumps(cal)
    text += "# Simulation parameters (SI units, spreads as 1-sigma, angles in degrees unless _rad):\n"
    text += yaml.safe_dump({SIMULATION_NODE: {"ros__parameters": params}}, sort_keys=False, default_flow_style=None, width=1000)
    return text


def write_simulation(out: str | os.PathLike[str], spec: SimulationSpec, storage: str = "sqlite3") -> tuple[Truth, Path, Path]:
    """Simulate and write the recording and both truth files, all atomically."""
    rec, truth, sim = run(spec)
    ypath, npath = truth_paths(out)
    csv = is_csv(out)
    if not csv:
        check_storage(storage)
    extra: dict[str, Any] = {}
    if truth.temperatures is not None:
        extra["temperatures"] = truth.temperatures
    if sim.imu is not None:
        extra.update(imu_orientation=truth.imu_orientation, imu_angular_velocity=truth.imu_angular_velocity,
                     output_rotation=sim.imu.mounting)
    if sim.world_gradient is not None:
        extra.update(world_gradient=sim.world_gradient, world_gradient_enu=NED_TO_ENU @ sim.world_gradient @ NED_TO_ENU.T)
    with atomic_path(out) as t_out, atomic_path(ypath) as t_yaml, atomic_path(npath) as t_npz:
        with open(t_npz, "wb") as fh:
            np.savez_compressed(
                fh, stamps=rec.stamps, field=truth.field, centre=truth.centre, gradient=truth.gradient,
                attitudes=truth.attitudes, names=np.array(rec.names), positions=sim.geometry.positions, earth=sim.earth,
                currents=truth.currents, channels=np.array(rec.channels, dtype=str), **extra,
            )
        t_yaml.write_text(truth_yaml(spec, truth, sim))
        if csv:
            write_csv(t_out, rec)
        else:
            write_recording_bag(t_out, rec, storage, imu_stream=truth.imu_stream)  # type: ignore[arg-type]
    return truth, ypath, npath


def load_truth(out: str | os.PathLike[str]) -> dict[str, Any]:
    """The per-set truth arrays of a simulated recording ``OUT`` (see module docstring)."""
    _, npath = truth_paths(out)
    with np.load(npath) as data:
        return {k: data[k] for k in data.files}

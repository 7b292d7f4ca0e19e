"""Simulated recordings on disk: the recording and its ground truth, as ``magcal simulate`` writes them.

Files for an output ``OUT`` (a rosbag2 directory, or a CSV file when it ends in .csv):

- ``OUT``: the raw recording, topics ``/<name>/raw`` (or CSV columns ``<name>.x,...``),
  plus one ``sensor_msgs/msg/BatteryState`` topic ``/<channel>`` per thruster (or CSV
  columns ``current.<channel>``, A).
- ``OUT.truth.yaml``: the true calibration as a calibration file (``magcal_correction``
  block, loadable by ``magcal correct --calibration`` and the correction node; with
  thrusters its ``interference_channels`` and per-sensor ``interference``, the thrusters'
  field per ampere at each sensor, T/A, platform frame) plus a ``magcal_simulation`` block
  with every simulation parameter.
- ``OUT.truth.npz``: per-set truth, platform frame: ``stamps`` (N,) int64 ns, ``field``
  (N, S, 3) T at each sensor (without the thrusters' field), ``centre`` (N, 3) T,
  ``gradient`` (N, 3, 3) T/m at the centre (``G[i, j] = dB_j/dx_i``), ``attitudes``
  (N, 3, 3) platform to world, ``names`` (S,), ``positions`` (S, 3) m, ``earth`` (3,) T
  world NED, ``currents`` (N, m) A and ``channels`` (m,) of the thrusters.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magcal_ros.core.metrics import tensor_floor
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io.atomic import atomic_path
from magcal_ros.io.bag_writer import check_storage, write_recording_bag
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.io.recordings import is_csv
from magcal_ros.sim.simulator import ArraySimulation, Truth
from magcal_ros.sim.spec import SimulationSpec, run

SIMULATION_NODE = "magcal_simulation"


def simulation_parameters(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``magcal_simulation`` parameters of a truth file (``intensity`` T, ``noise`` T, ...);
    ``{}`` for any other file, or one that cannot be read."""
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}
    block = doc.get(SIMULATION_NODE) if isinstance(doc, dict) else None
    params = block.get("ros__parameters") if isinstance(block, dict) else None
    return params if isinstance(params, dict) else {}


def truth_paths(out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``OUT.truth.yaml`` and ``OUT.truth.npz`` beside the recording ``OUT``."""
    base = str(out).rstrip("/\\")
    return Path(base + ".truth.yaml"), Path(base + ".truth.npz")


def truth_yaml(spec: SimulationSpec, truth: Truth, sim: ArraySimulation) -> str:
    """The calibration file of the true calibration plus the simulation parameters."""
    cal = truth.calibration
    params: dict[str, Any] = {k: v for k, v in asdict(spec).items()
                              if k not in ("dipoles", "names", "position", "thrusters")}
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
    with atomic_path(out) as t_out, atomic_path(ypath) as t_yaml, atomic_path(npath) as t_npz:
        with open(t_npz, "wb") as fh:
            np.savez_compressed(
                fh, stamps=rec.stamps, field=truth.field, centre=truth.centre, gradient=truth.gradient,
                attitudes=truth.attitudes, names=np.array(rec.names), positions=sim.geometry.positions, earth=sim.earth,
                currents=truth.currents, channels=np.array(rec.channels, dtype=str),
            )
        t_yaml.write_text(truth_yaml(spec, truth, sim))
        if csv:
            write_csv(t_out, rec)
        else:
            write_recording_bag(t_out, rec, storage)  # type: ignore[arg-type]
    return truth, ypath, npath


def load_truth(out: str | os.PathLike[str]) -> dict[str, Any]:
    """The per-set truth arrays of a simulated recording ``OUT`` (see module docstring)."""
    _, npath = truth_paths(out)
    with np.load(npath) as data:
        return {k: data[k] for k in data.files}

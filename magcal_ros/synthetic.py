"""Synthetic rotation recordings with ground truth, as written by ``magcal simulate``.

Files for an output ``OUT`` (a rosbag2 directory, or a CSV file when it ends in .csv):

- ``OUT``: the raw recording, topics ``/<name>/raw`` (or CSV columns ``<name>.x,...``).
- ``OUT.truth.yaml``: the true calibration as a calibration file (``magcal_correction``
  block, loadable by ``magcal correct --calibration`` and the correction node) plus a
  ``magcal_simulation`` block with every simulation parameter.
- ``OUT.truth.npz``: per-set truth, platform frame: ``stamps`` (N,) s, ``field``
  (N, S, 3) T at each sensor, ``centre`` (N, 3) T, ``gradient`` (N, 3, 3) T/m at the
  centre (``G[i, j] = dB_j/dx_i``), ``attitudes`` (N, 3, 3) platform to world,
  ``names`` (S,), ``positions`` (S, 3) m, ``earth`` (3,) T world NED.

Sensor errors depend only on the seed and the error spreads, so two recordings made with
the same ``seed`` share the same sensors: calibrate one, correct the other.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magcal_ros import attitudes, calfile
from magcal_ros.atomic import atomic_path
from magcal_ros.errors import InputError
from magcal_ros.field import Dipole, earth_field
from magcal_ros.geometry import DEFAULT_NAMES, ArrayGeometry
from magcal_ros.metrics import tensor_floor
from magcal_ros.recording import Recording, write_csv
from magcal_ros.simulate import ArraySimulation, Truth, random_sensor_errors
from magcal_ros.units import NT

SIMULATION_NODE = "magcal_simulation"
SCHEDULE_NAMES: tuple[str, ...] = ("single-axis", "paper000", "paper004", "three-axes", "random")


@dataclass(frozen=True)
class SimulationSpec:
    """Everything ``magcal simulate`` varies (SI units, angles in degrees)."""

    schedule: str = "random"
    count: int = 1000
    axis: str = "z"
    intensity: float = 5.5e-5
    inclination: float = 60.0
    declination: float = 5.0
    scale_sd: float = 0.02
    angle_sd: float = 1.0
    offset_sd: float = 200 * NT
    misalignment_sd: float = 2.0
    hard_iron_sd: float = 0.0
    soft_iron_sd: float = 0.0
    noise: float = 1.0 * NT
    noise_kind: str = "gaussian"
    noise_domain: str = "raw"
    dipoles: tuple[tuple[float, ...], ...] = ()
    """Each ``(x, y, z, mx, my, mz)``: world position (m, NED) and moment (A m^2)."""
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Array centre in the world frame (m)."""
    rate: float = 10.0
    start_time: float = 1.7e9
    seed: int = 0
    baseline: float = 0.4
    names: tuple[str, ...] = field(default=DEFAULT_NAMES)

    def check(self) -> None:
        """Raise :class:`InputError` for values no simulation can use."""
        if self.schedule not in SCHEDULE_NAMES:
            raise InputError(f"unknown schedule {self.schedule!r}; choose one of {', '.join(SCHEDULE_NAMES)}")
        if self.axis not in ("x", "y", "z"):
            raise InputError("--axis must be x, y or z")
        if self.count < 1:
            raise InputError("--count must be at least 1")
        if not (self.rate > 0 and np.isfinite(self.rate)):
            raise InputError("--rate must be a positive number of sets per second")
        if not (0 < self.intensity < 1e-2):
            raise InputError(f"--intensity {self.intensity} T is not a magnetic field intensity in Tesla")
        if not self.baseline > 0:
            raise InputError("--baseline must be positive (m)")
        spreads = (self.scale_sd, self.angle_sd, self.offset_sd, self.misalignment_sd, self.hard_iron_sd, self.soft_iron_sd, self.noise)
        if any(not (np.isfinite(v) and v >= 0) for v in spreads):
            raise InputError("error spreads and noise must be finite and >= 0")
        for d in self.dipoles:
            if len(d) != 6 or not np.all(np.isfinite(d)):
                raise InputError("--dipole needs 6 numbers: x,y,z (m) and mx,my,mz (A m^2)")


def build(spec: SimulationSpec) -> tuple[ArraySimulation, np.ndarray]:
    """The simulated array and its attitude schedule (N, 3, 3)."""
    spec.check()
    geometry = ArrayGeometry.cross(spec.baseline, tuple(spec.names))
    err_rng = np.random.default_rng([spec.seed, 0])
    sensors = tuple(
        random_sensor_errors(err_rng, spec.scale_sd, spec.angle_sd, spec.offset_sd, spec.misalignment_sd,
                             spec.hard_iron_sd, spec.soft_iron_sd)
        for _ in geometry.names
    )
    sim = ArraySimulation(
        geometry=geometry,
        sensors=sensors,
        earth=earth_field(spec.intensity, spec.inclination, spec.declination),
        noise=spec.noise,
        noise_kind=spec.noise_kind,  # type: ignore[arg-type]
        noise_domain=spec.noise_domain,  # type: ignore[arg-type]
        dipoles=tuple(Dipole(np.asarray(d[:3], float), np.asarray(d[3:], float)) for d in spec.dipoles),
        position=np.asarray(spec.position, dtype=float),
    )
    att_rng = np.random.default_rng([spec.seed, 1])
    if spec.schedule == "single-axis":
        rot = attitudes.single_axis(spec.axis, spec.count)
    else:
        rot = attitudes.SCHEDULES[spec.schedule](spec.count, att_rng)
    for d in sim.dipoles:
        if np.min(np.linalg.norm(sim.position + np.einsum("nij,sj->nsi", rot, geometry.positions) - d.position, axis=-1)) < 1e-3:
            raise InputError("a dipole lies on a sensor position: move it away (--dipole x,y,z in m)")
    return sim, rot


def run(spec: SimulationSpec) -> tuple[Recording, Truth, ArraySimulation]:
    """Simulate: ``(recording, truth, simulation)``."""
    sim, rot = build(spec)
    rec, truth = sim.run(rot, np.random.default_rng([spec.seed, 2]), rate=spec.rate, start=spec.start_time)
    return rec, truth, sim


def truth_paths(out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``OUT.truth.yaml`` and ``OUT.truth.npz`` beside the recording ``OUT``."""
    base = str(out).rstrip("/\\")
    return Path(base + ".truth.yaml"), Path(base + ".truth.npz")


def truth_yaml(spec: SimulationSpec, truth: Truth, sim: ArraySimulation) -> str:
    """The calibration file of the true calibration plus the simulation parameters."""
    cal = truth.calibration
    params: dict[str, Any] = {k: v for k, v in asdict(spec).items() if k not in ("dipoles", "names", "position")}
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


def write(out: str | os.PathLike[str], spec: SimulationSpec, storage: str = "sqlite3") -> tuple[Truth, Path, Path]:
    """Simulate and write the recording and both truth files, all atomically."""
    from magcal_ros.bagio import check_storage, write_recording_bag
    from magcal_ros.sources import is_csv

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

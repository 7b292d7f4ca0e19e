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

Sensor streams (:func:`write_stream_simulation`): the bag holds each sensor's messages at
their own sample instants, stamped on receipt; the truth YAML's calibration carries each
sensor's lag as ``time_offset``, the NPZ per-sensor arrays instead of per-set ones.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.imu import NED_TO_ENU
from magcal_ros.core.metrics import gradient_floor
from magcal_ros.io import calibration_file as calfile
from magcal_ros.errors import InputError
from magcal_ros.io.atomic import atomic_path
from magcal_ros.io.bag_writer import check_storage, write_recording_bag, write_stream_bag
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.io.recordings import is_csv
from magcal_ros.sim.simulator import ArraySimulation, Truth
from magcal_ros.sim.spec import SimulationSpec, build, run
from magcal_ros.sim.streams import StreamRecording, StreamSpec, simulate_streams

SIMULATION_NODE = "magcal_simulation"


def read_simulation_parameters(path: str | os.PathLike[str]) -> dict[str, Any]:
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


def simulation_parameters(spec: SimulationSpec, sim: ArraySimulation, sets: int) -> dict[str, Any]:
    """The ``magcal_simulation`` block: every simulation parameter and each sensor's true errors."""
    params: dict[str, Any] = {k: v for k, v in asdict(spec).items()
                              if k not in ("dipoles", "names", "position", "thrusters")
                              and not (isinstance(v, tuple) and not v)}  # ROS parameter files hold no empty lists
    params.update(
        {
            "sets": int(sets),
            "names": list(spec.names),
            "position": [float(v) for v in spec.position],
            "dipole_count": len(spec.dipoles),
            "earth_field": [float(v) for v in sim.earth],
        }
    )
    floor = gradient_floor(spec.noise, sim.geometry)
    if floor is not None:  # T/m: the tensor's six measured components, or dB/ds along a line of sensors
        params["tensor_noise_floor"] = floor
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
    return params


def _yaml(cal: ArrayCalibration, params: dict[str, Any]) -> str:
    text = calfile.dumps(cal)
    text += "# Simulation parameters (SI units, spreads as 1-sigma, angles in degrees unless _rad):\n"
    text += yaml.safe_dump({SIMULATION_NODE: {"ros__parameters": params}}, sort_keys=False, default_flow_style=None, width=1000)
    return text


def truth_yaml(spec: SimulationSpec, truth: Truth, sim: ArraySimulation) -> str:
    """The calibration file of the true calibration plus the simulation parameters."""
    return _yaml(truth.calibration, simulation_parameters(spec, sim, len(truth.centre)))


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


def stream_parameters(streams: StreamSpec, names: tuple[str, ...]) -> dict[str, Any]:
    """The stream settings as ROS-safe values (per-sensor lists, glitches and restarts as text)."""
    size = len(names)
    out: dict[str, Any] = {
        "sensor_rate": streams.per_sensor(streams.rate, size, "rate").tolist(),
        "phases": streams.per_sensor(streams.phases, size, "phases").tolist(),
        "receipt_delay": streams.per_sensor(streams.delay, size, "delay").tolist(),
        "receipt_jitter": float(streams.jitter), "jitter_kind": streams.jitter_kind,
        "clock_ppm": streams.per_sensor(streams.clock_ppm, size, "clock_ppm").tolist(),
        "loss": float(streams.loss), "lags": streams.per_sensor(streams.lags, size, "lags").tolist(),
    }
    if streams.glitches:
        out["glitches"] = [f"{names[k]},{t:g},{shift:g}" for k, t, shift in streams.glitches]
    if streams.restarts:
        out["restarts"] = [",".join([f"{t:g}", f"{jump:g}", *(names[k] for k in which)])
                           for t, jump, which in streams.restarts]
    return out


def write_stream_simulation(out: str | os.PathLike[str], spec: SimulationSpec, streams: StreamSpec,
                            storage: str = "sqlite3") -> tuple[StreamRecording, Path, Path]:
    """Simulate per-sensor streams (:mod:`magcal_ros.sim.streams`: the schedule's attitudes at ``spec.rate``
    as a continuous turn, each sensor sampling and stamped as ``streams`` says) and write the bag and both
    truth files atomically. The truth YAML's calibration carries each sensor's lag as its
    ``time_offset``; the NPZ holds per sensor ``stamps_<name>``, ``instants_<name>`` (true sample
    instants, ns), ``receipts_<name>`` (bag times, ns) and ``field_<name>`` (n, 3) T platform frame,
    plus ``names``, ``positions`` and ``earth``."""
    if is_csv(out):
        raise InputError("sensor stream options write a rosbag2 directory (CSV rows are sets, one stamp each)")
    if spec.thrusters:
        raise InputError("sensor stream options do not simulate thrusters: leave out --thruster")
    check_storage(storage)
    sim, rot = build(spec)
    lags = streams.per_sensor(streams.lags, sim.geometry.size, "lags")
    duration = (len(rot) - 1) / spec.rate - max(0.0, -float(lags.min()))
    rec = simulate_streams(sim, rot, spec.rate, streams, duration, np.random.default_rng([spec.seed, 2]),
                           start=spec.start_time)
    ypath, npath = truth_paths(out)
    params = simulation_parameters(spec, sim, len(rec.streams[0]))
    params.update(stream_parameters(streams, rec.names))
    arrays: dict[str, Any] = {"names": np.array(rec.names), "positions": sim.geometry.positions, "earth": sim.earth}
    for s in rec.streams:
        arrays.update({f"stamps_{s.name}": s.stamps, f"instants_{s.name}": s.instants,
                       f"receipts_{s.name}": s.receipts, f"field_{s.name}": s.field})
    with atomic_path(out) as t_out, atomic_path(ypath) as t_yaml, atomic_path(npath) as t_npz:
        with open(t_npz, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        t_yaml.write_text(_yaml(rec.calibration, params))
        write_stream_bag(t_out, rec.names, [s.stamps for s in rec.streams], [s.vectors for s in rec.streams],
                         [s.receipts for s in rec.streams], storage)  # type: ignore[arg-type]
    return rec, ypath, npath


def load_truth(out: str | os.PathLike[str]) -> dict[str, Any]:
    """The per-set truth arrays of a simulated recording ``OUT`` (see module docstring)."""
    _, npath = truth_paths(out)
    with np.load(npath) as data:
        return {k: data[k] for k in data.files}

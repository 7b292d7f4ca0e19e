"""Any array through the command line: one sensor, two, four or N sensors in any geometry.

Calibrate with ``magcal calibrate`` on simulated recordings (CSV), then judge the written
calibration on FRESH attitudes and noise against the simulator's truth. Floors come from the
truth (the true calibration applied with plain numpy here) or from ``sqrt(2) sigma / d``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from test_offline import magcal, ok

from magcal_ros.core.field import Dipole, earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.recording import Recording
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.sim import scenarios as sc
from magcal_ros.sim.attitudes import three_rotations, uniform_random
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors
from magcal_ros.sim.spec import SimulationSpec

NT = 1e-9


def corrected(matrices: np.ndarray, offsets: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """``M (r - o)`` per sensor with plain numpy (independent of the package's apply)."""
    return np.einsum("sij,nsj->nsi", matrices, raw - offsets)


def tmi_rms(b: np.ndarray, f: float) -> float:
    return float(np.sqrt(np.mean((np.linalg.norm(b, axis=-1) - f) ** 2)))


def true_correction(sim: ArraySimulation) -> tuple[np.ndarray, np.ndarray]:
    """The true ``(M, o)`` straight from the simulated sensors' forward model ``r = K B + o``."""
    pairs = [s.forward() for s in sim.sensors]
    return np.stack([np.linalg.inv(k) for k, _ in pairs]), np.stack([o for _, o in pairs])


def calibrate_csv(tmp: Path, rec: Recording, *args: object) -> tuple[object, str]:
    path = tmp / "rec.csv"
    write_csv(path, rec)
    out = tmp / "cal.yaml"
    proc = ok(magcal("calibrate", path, "-o", out, *args))
    return calfile.read(out), proc.stdout


@pytest.mark.parametrize("table", [1, 2])
def test_one_sensor_at_the_tmi_floor_of_the_true_calibration(tmp_path: Path, table: int) -> None:
    """Ding (2024) Tables 1 and 2, 300 random attitudes, 2 and 10 nT peak-to-peak noise, no positions."""
    for peak in (2 * NT, 10 * NT):
        sim = ArraySimulation(ArrayGeometry.single("mag1"), (sc.ding2024_sensor(table),),
                              earth_field(sc.DING2024_F, 52.0, -7.0), noise=peak / np.sqrt(12), noise_kind="uniform")
        rng = np.random.default_rng(table)
        rec, _ = sim.run(uniform_random(300, rng), rng)
        plot = tmp_path / f"one_{peak / NT:g}.png"
        cal, out = calibrate_csv(tmp_path, rec, "--reference-field", sc.DING2024_F, *(["--plot", plot] if table == 1 else []))
        assert "calibrated 1 sensor" in out and "sensor axes made orthogonal" in out
        assert table != 1 or plot.read_bytes().startswith(b"\x89PNG")  # a figure without a gradient row
        assert cal.geometry.gradient_kind == "none"
        fresh, _ = sim.run(uniform_random(4000, rng), rng)
        m_true, o_true = true_correction(sim)
        ratio = tmi_rms(corrected(cal.matrices, cal.offsets, fresh.vectors), sc.DING2024_F) / tmi_rms(
            corrected(m_true, o_true, fresh.vectors), sc.DING2024_F)
        assert ratio < 1.03, f"table {table}, {peak / NT:g} nT p-p: TMI {ratio:.3f}x the true calibration"


def test_one_sensor_at_strong_noise_without_a_reference(tmp_path: Path) -> None:
    """Wu et al. (2013): noise sd 1e-2 of the field unit, no offset, no reference intensity."""
    s = sc.wu2013_sensor()
    sim = ArraySimulation(ArrayGeometry.single("s1"), (s,), np.array([1.0, 1.0, np.sqrt(2.0)]) * sc.WU2013_UNIT,
                          noise=1e-2 * sc.WU2013_UNIT)
    rng = np.random.default_rng(3)
    rec, _ = sim.run(uniform_random(720, rng), rng)
    cal, _ = calibrate_csv(tmp_path, rec)
    # Relative calibration: the matrix up to its scale; compare normalised shapes with the truth.
    m_true = np.linalg.inv(s.forward()[0])
    est = cal.matrices[0].T @ cal.matrices[0]
    truth = m_true.T @ m_true
    est, truth = est / np.trace(est), truth / np.trace(truth)
    assert np.max(np.abs(est - truth)) < 5e-3


def test_two_sensor_gradiometer_baseline_gradient_at_its_floor(tmp_path: Path) -> None:
    """The two-fluxgate gradiometer paper: 0.5 m apart, three turns of 10 points; the gradient along
    the baseline within 10 % of sqrt(2) sigma / d on fresh data."""
    sim = sc.gradiometer_simulation()
    f = float(np.linalg.norm(sim.earth))
    rng = np.random.default_rng(1)
    rec, _ = sim.run(np.concatenate([three_rotations(40), uniform_random(400, rng)]), rng)
    cal, out = calibrate_csv(tmp_path, rec, "--reference-field", f, "--positions", "0,0,0,0.5,0,0",
                             "--plot", tmp_path / "two.png")
    assert "baseline gradient RMS" in out and "nan" not in out
    assert (tmp_path / "two.png").read_bytes().startswith(b"\x89PNG")  # dB/ds drawn
    fresh, _ = sim.run(uniform_random(4000, rng), rng)
    b = corrected(cal.matrices, cal.offsets, fresh.vectors)
    slope = (b[:, 1] - b[:, 0]) / 0.5  # uniform field: the true dB/ds is 0
    floor = np.sqrt(2.0) * sim.noise / 0.5
    assert float(np.sqrt(np.mean(slope**2))) < 1.10 * floor


def test_six_sensors_in_three_dimensions_give_the_tensor_at_its_floor(tmp_path: Path) -> None:
    """A non-cross 3-D array of six sensors, a dipole 1.5 m away: the least-squares tensor on fresh
    data within 15 % of what the true calibration gives, against the simulator's true gradient."""
    pos = np.array([[0.3, 0, 0], [-0.2, 0.25, 0], [-0.1, -0.3, 0.05], [0, 0, 0.3], [0.15, 0.1, -0.25], [-0.2, 0, -0.2]])
    names = tuple(f"m{i}" for i in range(6))
    geo = ArrayGeometry(names, pos)
    rng = np.random.default_rng(6)
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in names), earth_field(51500 * NT, 60, 5))
    rec, _ = sim.run(uniform_random(1500, rng), rng)
    positions = ",".join(f"{v:g}" for v in pos.reshape(-1))
    cal, out = calibrate_csv(tmp_path, rec, "--reference-field", 51500 * NT, "--positions", positions,
                             "--gradient-method", "least_squares", "--plot", tmp_path / "six.png")
    assert "tensor RMS" in out and (tmp_path / "six.png").read_bytes().startswith(b"\x89PNG")
    survey = ArraySimulation(geo, sim.sensors, sim.earth,
                             dipoles=(Dipole(np.array([1.5, 0.3, 0.4]), np.array([0.0, 0.5, 1.0])),))
    fresh, truth = survey.run(uniform_random(3000, rng), rng)
    # Least-squares tensor with our own design: B_i = B0 + G^T p_i, G symmetric traceless.
    rel = pos - pos.mean(axis=0)
    basis = np.zeros((5, 3, 3))
    basis[0, 0, 0], basis[0, 2, 2], basis[1, 1, 1], basis[1, 2, 2] = 1, -1, 1, -1
    for k, (i, j) in enumerate([(0, 1), (0, 2), (1, 2)], start=2):
        basis[k, i, j] = basis[k, j, i] = 1
    design = np.vstack([np.hstack([np.eye(3), np.einsum("kij,i->jk", basis, p)]) for p in rel])
    op = np.linalg.pinv(design)

    def tensor(b: np.ndarray) -> np.ndarray:
        return np.einsum("nk,kij->nij", (b.reshape(len(b), -1) @ op.T)[:, 3:], basis)

    m_true, o_true = true_correction(sim)
    err_est = tensor(corrected(cal.matrices, cal.offsets, fresh.vectors)) - truth.gradient
    err_true = tensor(corrected(m_true, o_true, fresh.vectors)) - truth.gradient
    ratio = float(np.sqrt(np.mean(err_est**2) / np.mean(err_true**2)))
    assert ratio < 1.15, f"tensor {ratio:.3f}x the true calibration's"


def test_positions_that_determine_no_tensor_are_named(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    geo = ArrayGeometry(("a", "b", "c"), [[0, 0, 0], [0.2, 0, 0], [0.5, 0, 0]])
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in range(3)), earth_field(50000 * NT, 60, 5))
    rec, _ = sim.run(uniform_random(300, rng), rng)
    path = tmp_path / "line.csv"
    write_csv(path, rec)
    out = tmp_path / "line.yaml"
    ok(magcal("calibrate", path, "-o", out, "--positions", "0,0,0,0.2,0,0,0.5,0,0"))  # a line: baseline gradient
    bad = magcal("calibrate", path, "-o", tmp_path / "x.yaml", "--positions", "0,0,0,0.2,0,0,0.5,0,0",
                 "--gradient-method", "least_squares")
    assert bad.returncode == 0  # the gradient method only matters for a tensor
    proc = magcal("calibrate", path, "-o", tmp_path / "y.yaml", "--positions", "0,0,0,0.2,0,0")
    assert proc.returncode == 2 and "positions" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    doc = yaml.safe_load(out.read_text())
    assert doc["magcal_correction"]["ros__parameters"]["sensor_names"] == ["a", "b", "c"]


def test_one_sensor_correction_writes_no_gradient(tmp_path: Path) -> None:
    spec = SimulationSpec()
    sim = ArraySimulation(ArrayGeometry.single("mag1"), (random_sensor_errors(1),), earth_field(spec.intensity, 60, 5))
    rec, _ = sim.run(uniform_random(200, 1), 1)
    cal, _ = calibrate_csv(tmp_path, rec, "--reference-field", spec.intensity)
    out = tmp_path / "out.csv"
    ok(magcal("correct", tmp_path / "rec.csv", "-c", tmp_path / "cal.yaml", "-o", out))
    header = out.read_text().splitlines()[0].split(",")
    assert header == ["stamp", "mag1.x", "mag1.y", "mag1.z", "field.x", "field.y", "field.z"]
    bag = tmp_path / "out_bag"
    ok(magcal("correct", tmp_path / "rec.csv", "-c", tmp_path / "cal.yaml", "-o", bag))
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        assert sorted(c.topic for c in reader.connections) == ["/field", "/mag1/corrected"]

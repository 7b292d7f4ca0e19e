"""IMU samples are data with outliers like readings: a glitch is left out and counted, an IMU that does not
describe the readings is refused naming it, a value no IMU gives is no value, and nothing ends in a
traceback. Against the simulator's truth: the same manoeuvre with a clean IMU."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_offline import magcal, ok

from magcal_ros.io import calibration_file as calfile

SETS = 900


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    d = tmp_path_factory.mktemp("imu_faults")
    csv = d / "cal.csv"
    ok(magcal("simulate", csv, "--schedule", "tumble", "--count", SETS, "--imu", "--imu-orientation-noise", "0.05",
              "--temperature-ramp", "5,25", "--tempco-offset", "0.5e-9", "--seed", 4, "-q"))
    good = d / "good.yaml"
    ok(magcal("calibrate", csv, "-o", good))
    lines = csv.read_text().splitlines()
    return {"dir": d, "lines": lines, "good": calfile.read(good), "q": lines[0].split(",").index("imu.qx")}


def _with(rec: dict[str, object], name: str, rows: dict[int, list[float]], first: int) -> Path:
    lines = list(rec["lines"])  # type: ignore[arg-type]
    for row, values in rows.items():
        cells = lines[row].split(",")
        cells[first:first + len(values)] = [repr(float(v)) for v in values]
        lines[row] = ",".join(cells)
    path = rec["dir"] / name  # type: ignore[operator]
    path.write_text("\n".join(lines) + "\n")
    return path


def _quaternion(rec: dict[str, object], row: int) -> np.ndarray:
    q0 = int(rec["q"])  # type: ignore[arg-type]
    return np.array([float(c) for c in rec["lines"][row].split(",")[q0:q0 + 4]])  # type: ignore[index]


@pytest.mark.parametrize("kind", ["120 deg off", "5 deg off", "inverse"])
def test_one_wrong_attitude_in_the_manoeuvre_is_left_out_and_counted(recording: dict[str, object], kind: str) -> None:
    """One wrong IMU quaternion in 900 sets (a valid rotation, so no range check sees it): the calibration is
    the clean one's (corrections equal to half the noise), with the temperature terms, and the
    summary and file say one attitude was left out (it took TMI from 1.0 to 9.5 nT and dropped the
    temperature terms, the warnings blaming temperature and the manoeuvre)."""
    row = 400
    q = _quaternion(recording, row)
    wrong = {"120 deg off": (Rotation.from_quat(q) * Rotation.from_rotvec(np.radians(120) * np.ones(3) / np.sqrt(3))),
             "5 deg off": Rotation.from_quat(q) * Rotation.from_euler("z", 5, degrees=True),
             "inverse": Rotation.from_quat(q).inv()}[kind].as_quat()
    path = _with(recording, f"bad_{kind.replace(' ', '_')}.csv", {row: list(wrong)}, int(recording["q"]))  # type: ignore[arg-type]
    out = path.with_suffix(".yaml")
    proc = ok(magcal("calibrate", path, "-o", out))
    assert "1 attitude far off the field left out" in proc.stdout
    assert "temperature terms fitted" in proc.stdout
    cal, good = calfile.read(out), recording["good"]
    raw = np.random.default_rng(1).normal(0, 5e-5, (200, 4, 3))
    temps = np.full((200, 4), 15.0)
    diff = cal.apply(raw, temperatures=temps) - good.apply(raw, temperatures=temps)  # type: ignore[attr-defined]
    assert np.abs(diff).max() < 0.5e-9  # half the noise: the statistical spread of one set fewer
    assert cal.metadata["imu"]["attitudes_excluded"] == 1


def test_an_imu_that_does_not_describe_the_readings_is_refused_naming_it(recording: dict[str, object]) -> None:
    """Every attitude shuffled among the sets (another vehicle's topic, a clock far off): the fit made a
    calibration with a 64 deg attitude error and outputs "in the IMU frame"; now a refusal naming the IMU and
    what to check, nothing written."""
    lines = list(recording["lines"])  # type: ignore[arg-type]
    q0 = int(recording["q"])  # type: ignore[arg-type]
    rows = [ln.split(",") for ln in lines[1:]]
    imu = [r[q0:q0 + 7] for r in rows]
    for r, k in zip(rows, np.random.default_rng(1).permutation(len(rows))):
        r[q0:q0 + 7] = imu[k]
    path = recording["dir"] / "shuffled.csv"  # type: ignore[operator]
    path.write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    out = path.with_suffix(".yaml")
    proc = magcal("calibrate", path, "-o", out)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "the IMU's attitudes disagree with the field throughout" in proc.stderr and not out.exists()


@pytest.mark.parametrize("value", ["1e300", "nan", "-1e300"])
def test_a_gyro_value_no_imu_gives_is_no_value_not_a_traceback(recording: dict[str, object], value: str) -> None:
    """A gyro value of 1e300 rad/s ended in a traceback: it is beyond any gyro (35 rad/s), so that sample has
    no angular velocity, and the calibration is the clean one's."""
    w0 = int(recording["q"]) + 4  # type: ignore[arg-type]
    path = _with(recording, f"gyro_{value}.csv", {300: [float(value), 0.0, 0.0]}, w0)
    out = path.with_suffix(".yaml")
    proc = magcal("calibrate", path, "-o", out)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    raw, temps = np.random.default_rng(1).normal(0, 5e-5, (50, 4, 3)), np.full((50, 4), 15.0)
    got = calfile.read(out).apply(raw, temperatures=temps)
    assert np.abs(got - recording["good"].apply(raw, temperatures=temps)).max() < 0.5e-9  # type: ignore[attr-defined]

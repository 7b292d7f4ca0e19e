"""The ``magcal`` command end to end: simulate -> calibrate -> correct, over sqlite3, mcap and CSV.

Every command runs as ``python -m magcal_ros.app.cli`` in a subprocess, as a user would.
"""

from __future__ import annotations

import csv
import io
import os
import pty
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import truth_tools as tt
import yaml
from rosbags.rosbag2 import Reader

from magcal_ros.app.progress import ProgressBar
from magcal_ros.core.metrics import tensor_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import format_seconds, parse_seconds
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import cdr
from magcal_ros.io.bag_writer import write_recording_bag
from ros_harness import realistic_stamps
from magcal_ros.io.recordings import read_recording
from magcal_ros.io.truth_file import load_truth, truth_paths

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("mag1", "mag2", "mag3", "mag4")
F = 5.5e-5  # simulate's default intensity (T)
NOISE = 1e-9
SETS = 600
SEED = 11


def magcal(*args: object, stderr: int | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``python -m magcal_ros.app.cli ARGS`` (works installed or from the source tree)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-m", "magcal_ros.app.cli", *map(str, args)],
        capture_output=stderr is None, stderr=stderr, text=True, env=env, timeout=300,
    )


def ok(proc: subprocess.CompletedProcess[str]) -> subprocess.CompletedProcess[str]:
    assert proc.returncode == 0, proc.stderr
    return proc


def bag_messages(path: Path) -> list[tuple[str, str, int, object]]:
    ts = cdr.typestore()
    with Reader(path) as reader:
        return [(c.topic, c.msgtype, t, ts.deserialize_cdr(d, c.msgtype)) for c, t, d in reader.messages()]


def stamp_ns(msg: object) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec  # type: ignore[attr-defined]


def vec(msg: object) -> list[float]:
    m = msg.magnetic_field  # type: ignore[attr-defined]
    return [m.x, m.y, m.z]


def read_corrected(path: Path) -> dict[str, np.ndarray]:
    """Corrected output (bag or CSV) as arrays: stamps ns, sensors (N,S,3), field (N,3), gradient (N,3,3)."""
    if str(path).endswith(".csv"):
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        header, data = rows[0], np.array([r[1:] for r in rows[1:]], dtype=float)
        expected = ["stamp"] + [f"{n}.{a}" for n in NAMES for a in "xyz"] + [f"field.{a}" for a in "xyz"]
        expected += [f"gradient.{i}{j}" for i in "xyz" for j in "xyz"]
        assert header == expected
        return {
            "stamps": np.array([parse_seconds(r[0]) for r in rows[1:]], dtype=np.int64),
            "sensors": data[:, 0:12].reshape(-1, 4, 3),
            "field": data[:, 12:15],
            "gradient": data[:, 15:24].reshape(-1, 3, 3),
        }
    msgs = bag_messages(path)
    with Reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert types == {**{f"/{n}/corrected": cdr.MAGNETIC_FIELD for n in NAMES}, "/field": cdr.MAGNETIC_FIELD,
                     "/gradient": cdr.FLOAT64_MULTI_ARRAY}
    n = counts["/gradient"]
    assert set(counts.values()) == {n}
    order = [f"/{x}/corrected" for x in NAMES] + ["/field", "/gradient"]
    assert [m[0] for m in msgs] == order * n, "per set: sensors, then field, then gradient"
    for topic, _, t, m in msgs:
        if topic != "/gradient":
            assert m.header.frame_id == "magcal_array"  # type: ignore[attr-defined]
        if topic == "/field":
            assert stamp_ns(m) == t, "bag time = header stamp = the set's stamp"
    sensor_stamps = np.array([stamp_ns(m[3]) for m in msgs if m[0].endswith("/corrected")]).reshape(-1, 4)
    set_times = np.array([m[2] for m in msgs if m[0] == "/field"])
    assert np.array_equal(np.array([m[2] for m in msgs if m[0].endswith("/corrected")]).reshape(-1, 4),
                          np.repeat(set_times[:, None], 4, axis=1)), "a sensor's bag time is its set's stamp"
    g = [m for m in msgs if m[0] == "/gradient"]
    assert all([(d.label, d.size, d.stride) for d in m[3].layout.dim] == [("row", 3, 9), ("col", 3, 3)] for m in g)
    return {
        "stamps": np.array([m[2] for m in msgs if m[0] == "/field"]),
        "sensors": np.array([vec(m[3]) for m in msgs if m[0].endswith("/corrected")]).reshape(-1, 4, 3),
        "field": np.array([vec(m[3]) for m in msgs if m[0] == "/field"]),
        "gradient": np.array([m[3].data for m in g]).reshape(-1, 3, 3),
        "bagtimes": np.array([m[2] for m in g]),
        "sensor_stamps": sensor_stamps,  # (N, S): each /<name>/corrected header stamp, the sensor's own
    }


def out_name(tmp: Path, stem: str, storage: str) -> Path:
    return tmp / (f"{stem}.csv" if storage == "csv" else f"{stem}_{storage}")


def simulate(out: Path, storage: str, *extra: object) -> Path:
    """``magcal simulate``; a bag is then given the stamps of a real recording (per-sensor header
    stamps that differ within the sync tolerance, bag time after the header stamp, jitter)."""
    args: list[object] = ["simulate", out, "--count", SETS, "--seed", SEED, "--noise", NOISE]
    if storage != "csv":
        args += ["--storage", storage]
    ok(magcal(*args, *extra))
    if storage != "csv":
        realistic_stamps(out, SEED)
    return out


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("offline")


@pytest.fixture(scope="module")
def calibrated(work: Path) -> tuple[Path, Path]:
    """A uniform-field rotation bag (sqlite3) and the calibration solved from it."""
    bag = simulate(work / "rotation_ref", "sqlite3")
    cal = work / "rotation_ref.yaml"
    ok(magcal("calibrate", bag, "-o", cal, "--reference-field", F))
    return bag, cal


@pytest.mark.parametrize("storage", ["sqlite3", "mcap", "csv"])
def test_simulate_calibrate_correct(tmp_path: Path, storage: str) -> None:
    raw = simulate(out_name(tmp_path, "rotation", storage), storage)
    ypath, npath = truth_paths(raw)
    assert ypath.is_file() and npath.is_file()
    truth = load_truth(raw)
    assert truth["gradient"].shape == (SETS, 3, 3) and not np.any(truth["gradient"])  # uniform field
    true_cal = calfile.read(ypath)
    assert true_cal.geometry.names == NAMES

    if storage != "csv":
        msgs = bag_messages(raw)
        with Reader(raw) as reader:
            assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == {
                f"/{n}/raw": (cdr.MAGNETIC_FIELD, SETS) for n in NAMES
            }
            assert any(p.suffix == (".mcap" if storage == "mcap" else ".db3") for p in raw.iterdir())
        first = [m for m in msgs if m[0] == f"/{NAMES[0]}/raw"]  # the first sensor's stamps are the sets'
        assert [stamp_ns(m[3]) for m in first] == truth["stamps"].tolist()
        assert all(m[3].header.frame_id == m[0].split("/")[1] for m in msgs)

    cal = tmp_path / "cal.yaml"
    args = ["calibrate", raw, "-o", cal, "--plot", tmp_path / "cal.png"]
    if storage != "csv":
        args += ["--reference-field", F]  # CSV: relative calibration, F estimated
    proc = ok(magcal(*args))
    assert f"from {SETS} sets" in proc.stdout
    assert cal.is_file() and (tmp_path / "cal.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    out = out_name(tmp_path, "corrected", storage)
    proc = ok(magcal("correct", raw, "--calibration", cal, "-o", out))
    assert f"corrected {SETS} sets" in proc.stdout
    res = read_corrected(out)
    assert res["gradient"].shape == (SETS, 3, 3)
    np.testing.assert_array_equal(res["stamps"], read_recording(raw).stamps)

    # The tensor is at the noise floor: what the TRUE calibration gives on the same data (the
    # tests' own numpy), itself sigma sqrt(|M_a[j]|^2 + |M_b[j]|^2) / d for raw noise.
    # Measured in-process over 20 seeds (mean / sd / min / max), the same for both paths once
    # the relative (CSV) calibration is put in units of its estimated F: tensor over the floor
    # 0.9963 / 0.0013 / 0.9934 / 0.9984 (fit data: 9 parameters per sensor absorb some noise),
    # TMI over the true calibration's 0.9954 / 0.0024 / 0.9905 / 0.9995; the estimated F is
    # off by -0.001 / 0.0055 / -0.015 / 0.009 (the sensors' mean gain is not observable).
    rec = read_recording(raw)
    pos = true_cal.geometry.positions
    ideal = tt.correct(true_cal.matrices, true_cal.offsets, rec.vectors)
    floor = tt.rms(tt.cross_rows(ideal, pos))
    (px, mx), (py, my), d = tt.cross_pairs(pos)
    assert floor == pytest.approx(tt.raw_noise_floor(true_cal.matrices, [(px, mx), (py, my)], NOISE, d), rel=0.04)
    assert floor == pytest.approx(tt.difference_floor(NOISE, d), rel=0.15)  # gains of 2 % sd
    intensity = F if storage != "csv" else calfile.read(cal).metadata["intensity"]
    assert abs(intensity / F - 1.0) < 0.03
    units = F / intensity
    assert 0.98 < tt.rms(res["gradient"][:, :2]) * units / floor < 1.01
    # And the corrected vectors have |B| = F (the estimated F for CSV) to the noise.
    tmi = tt.rms(np.linalg.norm(res["sensors"], axis=-1) - intensity) * units
    assert tmi < 1.01 * tt.rms(np.linalg.norm(ideal, axis=-1) - F)


def procrustes(measured: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Rotation Q with measured ~ Q true (rows are vectors)."""
    u, _, vt = np.linalg.svd(measured.T @ true)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


@pytest.mark.parametrize("storage", ["mcap"])
def test_dipole_tensor_after_calibrating_elsewhere(tmp_path: Path, calibrated: tuple[Path, Path], storage: str) -> None:
    _, cal = calibrated
    survey = simulate(tmp_path / "survey", storage, "--dipole", "3,2,1.5,180,-120,240", "--position", "0,0,0")
    out = tmp_path / "survey_corrected"
    ok(magcal("correct", survey, "-c", cal, "-o", out))
    res = read_corrected(out)
    truth = load_truth(survey)
    true_cal = calfile.read(truth_paths(survey)[0])
    geometry = true_cal.geometry

    # The solved platform frame differs from the true one by a rotation no uniform-field
    # manoeuvre can observe: B' = Q B, so G' = G Q^T with rows along the true sensor axes.
    q = procrustes(res["field"], truth["centre"])
    assert np.degrees(np.arccos(np.clip((np.trace(q) - 1) / 2, -1, 1))) < 10
    g_aligned = res["gradient"] @ q

    # Everything it is compared with from the truth, with the tests' own numpy: the difference
    # formula on the noise-free fields (its truncation), and on the true calibration's output
    # (the noise). Noise and truncation add in quadrature. Measured in-process over 10 seeds
    # (mean / sd / max): sqrt(err^2 - truncation^2) / noise 0.998 / 0.005 / 1.004; the part
    # the calibration adds, RMS(estimate - true calibration) / noise, 0.085 / 0.015 / 0.115.
    pos = geometry.positions
    diff_true = tt.cross_difference(truth["field"], pos)
    truncation = tensor_rms(diff_true, truth["gradient"])
    raw = read_recording(survey)
    g_true_cal = tt.cross_difference(tt.correct(true_cal.matrices, true_cal.offsets, raw.vectors), pos)
    noise_floor = tensor_rms(g_true_cal, diff_true)
    signal = tensor_rms(truth["gradient"])
    assert signal > 10 * (noise_floor + truncation), "the dipole must stand far above the floor"
    err = tensor_rms(g_aligned, truth["gradient"])
    assert err <= np.hypot(1.03 * noise_floor, truncation), (err, noise_floor, truncation)
    assert tensor_rms(g_aligned, g_true_cal) < 0.2 * noise_floor
    # Rotation-free check too: Frobenius norms of the measured rows agree with the truth.
    rows = np.linalg.norm(res["gradient"][:, :2, :], axis=-1)
    rows_true = np.linalg.norm(truth["gradient"][:, :2, :], axis=-1)
    assert np.sqrt(np.mean((rows - rows_true) ** 2)) <= 1.1 * noise_floor + truncation


def test_correct_bag_to_csv_and_csv_to_bag(tmp_path: Path, calibrated: tuple[Path, Path]) -> None:
    bag, cal = calibrated
    ok(magcal("correct", bag, "-c", cal, "-o", tmp_path / "c.csv"))
    from_bag = read_corrected(tmp_path / "c.csv")
    raw_csv = tmp_path / "raw.csv"
    ok(magcal("simulate", raw_csv, "--count", SETS, "--seed", SEED, "--noise", NOISE))
    ok(magcal("correct", raw_csv, "-c", cal, "-o", tmp_path / "c_bag", "--storage", "mcap"))
    from_csv = read_corrected(tmp_path / "c_bag")
    # Same seed: same recording, so CSV and bag paths agree (CSV keeps 17 digits).
    np.testing.assert_allclose(from_csv["gradient"], from_bag["gradient"], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(from_csv["bagtimes"], from_csv["stamps"])


def test_windows_and_sensor_selection(tmp_path: Path, calibrated: tuple[Path, Path]) -> None:
    bag, cal = calibrated
    t0 = int(read_recording(bag).stamps[0])
    at = {s: format_seconds(t0 + round(s * 1e9)) for s in (10, 49.95, 19.95)}
    proc = ok(magcal("calibrate", bag, "-o", tmp_path / "w.yaml", "--start", at[10], "--end", at[49.95]))
    assert "from 400 sets" in proc.stdout
    out = tmp_path / "w_bag"
    ok(magcal("correct", bag, "-c", cal, "-o", out, "--start", at[10], "--end", at[19.95], "--storage", "mcap"))
    assert len(read_corrected(out)["gradient"]) == 100
    proc = magcal("calibrate", bag, "-o", tmp_path / "s.yaml", "--sensors", "mag1,mag2,mag3")
    assert proc.returncode == 2 and "--positions" in proc.stderr


def test_copy_topics(tmp_path: Path, calibrated: tuple[Path, Path]) -> None:
    bag, cal = calibrated
    out = tmp_path / "copy"
    ok(magcal("correct", bag, "-c", cal, "-o", out, "--copy-topics", "/mag1/raw,/mag3/raw"))
    with Reader(out) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts["/mag1/raw"] == counts["/mag3/raw"] == counts["/gradient"] == SETS and "/mag2/raw" not in counts
    ok(magcal("correct", bag, "-c", cal, "-o", tmp_path / "all", "--copy-all"))
    with Reader(tmp_path / "all") as reader:
        assert len(reader.connections) == 10


def test_nonfinite_readings_in_a_bag(tmp_path: Path, calibrated: tuple[Path, Path]) -> None:
    _, cal = calibrated
    rec = read_recording(calibrated[0])
    v = rec.vectors.copy()
    v[[5, 77], 2, 1] = np.nan
    bag = tmp_path / "nan_bag"
    write_recording_bag(bag, Recording(rec.names, rec.stamps, v))
    proc = magcal("correct", bag, "-c", cal, "-o", tmp_path / "out")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "NaN" in proc.stderr
    assert not (tmp_path / "out").exists()
    proc = ok(magcal("correct", bag, "-c", cal, "-o", tmp_path / "out", "--drop-nonfinite"))
    assert "2 messages with NaN/inf readings dropped" in proc.stderr
    assert len(read_corrected(tmp_path / "out")["gradient"]) == SETS - 2


# --------------------------------------------------------------------------- bad input


def _truncate(path: Path) -> None:
    data = next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2])


@pytest.fixture(scope="module")
def broken(work: Path, calibrated: tuple[Path, Path]) -> dict[str, Path]:
    """Inputs that must be refused."""
    bag, cal = calibrated
    d = work / "broken"
    d.mkdir()
    rec = read_recording(bag)
    paths = {"bag": bag, "cal": cal}
    for storage in ("sqlite3", "mcap"):
        p = d / f"truncated_{storage}"
        write_recording_bag(p, rec, storage)  # type: ignore[arg-type]
        _truncate(p)
        paths[f"truncated_{storage}"] = p
    header = "stamp," + ",".join(f"{n}.{a}" for n in NAMES for a in "xyz")
    rows = [",".join([format_seconds(t)] + [f"{x:.17g}" for x in v.reshape(-1)]) for t, v in zip(rec.stamps[:50], rec.vectors[:50])]
    (d / "nan.csv").write_text(header + "\n" + "\n".join(rows[:20] + [rows[20].replace(rows[20].split(",")[3], "nan")] + rows[21:]) + "\n")
    (d / "columns.csv").write_text("stamp,mag1.x,mag1.y\n1,2,3\n")
    (d / "bad.yaml").write_text("magcal_correction:\n  ros__parameters:\n    sensor_names: [mag1, mag2\n")
    (d / "shape.yaml").write_text(calfile.dumps(calfile.read(cal)).replace("matrix: [1", "matrix: [9, 1", 1).replace(
        "offset: [", "offset: [0.0, ", 1))
    (d / "notabag").mkdir()
    (d / "notabag" / "x.txt").write_text("hello")
    paths.update({k: d / v for k, v in {"nan_csv": "nan.csv", "columns_csv": "columns.csv", "bad_yaml": "bad.yaml",
                                        "shape_yaml": "shape.yaml", "notabag": "notabag"}.items()})
    return paths


BAD_CASES = {
    "truncated sqlite3 bag": ("calibrate", "{truncated_sqlite3}", "-o", "{out}.yaml"),
    "truncated mcap bag": ("correct", "{truncated_mcap}", "-c", "{cal}", "-o", "{out}"),
    "missing topic": ("calibrate", "{bag}", "-o", "{out}.yaml", "--sensors", "mag1,mag2,mag3,mag9"),
    "csv with NaN row": ("calibrate", "{nan_csv}", "-o", "{out}.yaml"),
    "csv with wrong columns": ("correct", "{columns_csv}", "-c", "{cal}", "-o", "{out}.csv"),
    "malformed calibration yaml": ("correct", "{bag}", "-c", "{bad_yaml}", "-o", "{out}"),
    "calibration with wrong shapes": ("correct", "{bag}", "-c", "{shape_yaml}", "-o", "{out}"),
    "missing calibration file": ("correct", "{bag}", "-c", "{out}_nothing.yaml", "-o", "{out}"),
    "directory that is not a bag": ("calibrate", "{notabag}", "-o", "{out}.yaml"),
    "input does not exist": ("correct", "{out}_nothing", "-c", "{cal}", "-o", "{out}"),
    "output is a non-bag directory": ("correct", "{bag}", "-c", "{cal}", "-o", "{notabag}"),
    "copy of a missing topic": ("correct", "{bag}", "-c", "{cal}", "-o", "{out}", "--copy-topics", "/imu"),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_one_line_no_output(tmp_path: Path, broken: dict[str, Path], case: str) -> None:
    out = tmp_path / "result"
    args = [a.format(out=out, **broken) for a in BAD_CASES[case]]
    before = sorted(p.name for p in tmp_path.iterdir())
    proc = magcal(*args)
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"magcal {args[0]}: error: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == before, "no output and no temporary files"
    assert (broken["notabag"] / "x.txt").read_text() == "hello"


def test_single_axis_rotation_is_refused_clearly(tmp_path: Path) -> None:
    bag = tmp_path / "single"
    ok(magcal("simulate", bag, "--schedule", "single-axis", "--axis", "x", "--count", 120))
    proc = magcal("calibrate", bag, "-o", tmp_path / "cal.yaml")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "cal.yaml").exists()


def test_simulate_options(tmp_path: Path) -> None:
    out = tmp_path / "grid.csv"
    proc = ok(magcal("simulate", out, "--schedule", "coaxial2022", "--hard-iron-sd", "1e-7", "--soft-iron-sd", "0.01",
                     "--noise-kind", "uniform", "--intensity", "4.8e-5", "--inclination", "-30", "--declination", "12",
                     "--rate", "50", "--baseline", "0.5", "--scale-sd", "0.01", "--angle-sd", "0.5",
                     "--offset-sd", "1e-7", "--misalignment-sd", "1"))
    assert "144 sets" in proc.stdout
    truth = load_truth(out)
    assert np.all(np.diff(truth["stamps"]) == 20_000_000)
    np.testing.assert_allclose(np.linalg.norm(truth["earth"]), 4.8e-5)
    np.testing.assert_allclose(np.abs(truth["positions"]).max(), 0.25)
    sim = yaml.safe_load(truth_paths(out)[0].read_text())["magcal_simulation"]["ros__parameters"]
    assert sim["schedule"] == "coaxial2022" and sim["noise_kind"] == "uniform" and sim["hard_iron_sd"] == 1e-7
    bad = magcal("simulate", tmp_path / "x", "--dipole", "1,2,3")
    assert bad.returncode == 2 and "--dipole" in bad.stderr and not (tmp_path / "x").exists()


def test_first_release_schedule_names_resolve(tmp_path: Path) -> None:
    out = tmp_path / "grid.csv"
    proc = ok(magcal("simulate", out, "--schedule", "paper004"))
    assert "schedule coaxial2022" in proc.stdout and "paper004" not in proc.stdout
    sim = yaml.safe_load(truth_paths(out)[0].read_text())["magcal_simulation"]["ros__parameters"]
    assert sim["schedule"] == "coaxial2022"
    bad = magcal("simulate", tmp_path / "x.csv", "--schedule", "bogus")
    assert bad.returncode == 2 and "unknown schedule 'bogus'" in bad.stderr.strip().splitlines()[-1]
    assert "li2018" in bad.stderr and "paper000" not in bad.stderr and not (tmp_path / "x.csv").exists()


def test_a_closed_stdout_pipe_stops_quietly(tmp_path: Path) -> None:
    """``magcal ... | head``: the reader leaves first; no traceback, no error line, the shell's 141."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    read, write = os.pipe()
    os.close(read)  # nobody will read what magcal prints
    with os.fdopen(write, "w") as stdout:
        proc = subprocess.run([sys.executable, "-m", "magcal_ros.app.cli", "simulate", str(tmp_path / "a.csv"),
                               "--count", "30"], stdout=stdout, stderr=subprocess.PIPE, text=True, env=env, timeout=120)
    assert proc.returncode == 141 and proc.stderr == ""
    assert load_truth(tmp_path / "a.csv")["stamps"].size > 0


@pytest.mark.parametrize("command", [None, "simulate", "calibrate", "correct"])
def test_help_has_examples(command: str | None) -> None:
    proc = ok(magcal(*([command] if command else []), "--help"))
    assert "examples:" in proc.stdout


# --------------------------------------------------------------------------- progress


def test_progress_bar_draws_only_on_a_terminal() -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty = Tty()
    with ProgressBar(1000, "correct", stream=tty) as bar:
        for _ in range(10):
            bar(100)
    text = tty.getvalue()
    assert "correct [" in text and "msg/s" in text and "left" in text and "1.0k/1.0k" in text and text.endswith("\n")
    pipe = io.StringIO()
    with ProgressBar(1000, stream=pipe) as bar:
        bar(500)
    assert pipe.getvalue() == ""
    quiet = Tty()
    with ProgressBar(1000, stream=quiet, enabled=False) as bar:
        bar(500)
    assert quiet.getvalue() == ""


def test_cli_progress_on_a_tty_and_quiet(tmp_path: Path, calibrated: tuple[Path, Path]) -> None:
    bag, cal = calibrated
    for quiet, expect in ((False, True), (True, False)):
        master, slave = pty.openpty()
        try:
            proc = magcal("correct", bag, "-c", cal, "-o", tmp_path / f"p{quiet}", *(["--quiet"] if quiet else []), stderr=slave)
            os.close(slave)
            chunks = []
            while True:
                try:
                    chunk = os.read(master, 4096)
                except OSError:
                    break
                if not chunk:
                    break
                chunks.append(chunk)
        finally:
            os.close(master)
        assert proc.returncode == 0
        drawn = b"".join(chunks).decode(errors="replace")
        assert ("msg/s" in drawn) is expect, drawn

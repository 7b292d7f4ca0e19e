"""``magcal batch`` without a cluster: which recordings, their names, vehicles and calibrations, what
counts as done, and the statistics of its report (bounded-memory quantiles and set-to-set noise)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcal_ros.app import campaign as cp
from magcal_ros.app.batch import plan
from magcal_ros.app.cli import build_parser
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.streaming_stats import LogHistogram, StepNoise
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile

ROOT = Path(__file__).resolve().parents[1]


def bag(path: Path) -> Path:
    """A directory that looks like a rosbag2 recording (planning reads no data)."""
    path.mkdir(parents=True)
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    return path


def csv_file(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("stamp,mag1.x,mag1.y,mag1.z\n1,0,0,5e-5\n")
    return path


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    """campaign/{auv1/{m1_bag, m2.csv, notes.txt, .hidden.csv}, auv2/2025-05-01/m1_bag, glider7/m1_bag}, a
    calibration file per vehicle and a default one."""
    camp = tmp_path / "campaign"
    bag(camp / "auv1" / "m1_bag")
    csv_file(camp / "auv1" / "m2.csv")
    (camp / "auv1" / "notes.txt").write_text("not a recording")
    csv_file(camp / "auv1" / ".hidden.csv")
    bag(camp / "auv2" / "2025-05-01" / "m1_bag")
    bag(camp / "glider7" / "m1_bag")
    broken = camp / "glider7" / "storage_only_bag"
    broken.mkdir()
    (broken / "x_0.db3").write_bytes(b"")
    cal = ArrayCalibration(ArrayGeometry.single("mag1"), np.eye(3)[None], np.zeros((1, 3)))
    for name in ("cal_auv1.yaml", "cal_default.yaml", "cal_glider.yaml"):
        calfile.write(tmp_path / "cals" / name, cal)
    return tmp_path


def args_of(*argv: object) -> object:
    return build_parser().parse_args(["batch", *map(str, argv)])


def test_walked_directories_keep_relative_names_and_skip_the_output(tree: Path) -> None:
    out = tree / "campaign" / "corrected"   # OUTDIR inside the walked tree: left out of the walk
    bag(out / "auv1" / "m1_bag")
    jobs, notes, others = plan(args_of(tree / "campaign", "-c", tree / "cals" / "cal_default.yaml", "-o", out))
    assert [j.name for j in jobs] == ["auv1/m1_bag", "auv1/m2.csv", "auv2/2025-05-01/m1_bag", "glider7/m1_bag"]
    assert [j.output for j in jobs] == [str(out.absolute() / j.name) for j in jobs]
    assert [j.vehicle for j in jobs] == ["auv1", "auv1", "2025-05-01", "glider7"], "the parent directory"
    assert all(j.calibration == str((tree / "cals" / "cal_default.yaml").absolute()) for j in jobs)
    assert all(j.record == str(out.absolute() / ".magcal_batch" / (j.name + ".json")) for j in jobs)
    assert not any(j.problem for j in jobs) and notes == []
    # A folder is a bag only by its metadata.yaml: the folder with a lone .db3 is walked, and what is not a
    # recording is listed as skipped (never run), hidden files left out.
    assert [(o.name, o.status, o.other, o.vehicle) for o in others] == [
        ("auv1/notes.txt", "skipped", True, "auv1"), ("glider7/storage_only_bag/x_0.db3", "skipped", True,
                                                     "storage_only_bag")]
    assert others[0].reason == "not a recording: neither a .csv file nor a rosbag2 directory"
    assert others[1].reason.startswith("not a recording: a rosbag2 storage file without the bag's metadata.yaml")


def test_a_stray_storage_file_does_not_turn_a_folder_of_recordings_into_a_bag(tree: Path) -> None:
    """A .db3 left in a campaign folder made the folder one failed "bag": its CSV recordings were never
    tried nor listed."""
    folder = tree / "campaign" / "auv1"
    (folder / "stray_0.db3").write_bytes(b"SQLite format 3\x00" + bytes(100))
    assert not cp.is_bag_dir(folder)
    jobs, _, others = plan(args_of(folder, "-c", tree / "cals" / "cal_default.yaml", "-o", tree / "out"))
    assert [j.name for j in jobs] == ["m1_bag", "m2.csv"] and not any(j.problem for j in jobs)
    assert [o.name for o in others] == ["notes.txt", "stray_0.db3"]
    with pytest.raises(InputError, match=r"no recordings in .*storage_only_bag .*; 1 other file\)"):
        plan(args_of(tree / "campaign" / "glider7" / "storage_only_bag", "-c", tree / "cals" / "cal_default.yaml",
                     "-o", tree / "out"))


def test_two_recordings_of_one_name_are_refused_before_anything_runs(tree: Path) -> None:
    camp = tree / "campaign"
    with pytest.raises(InputError, match="would both write m1_bag.*parent directory"):
        plan(args_of(camp / "auv1" / "m1_bag", camp / "glider7" / "m1_bag", "-c", tree / "cals" / "cal_default.yaml",
                     "-o", tree / "out"))


def test_list_files_and_missing_recordings(tree: Path) -> None:
    camp = tree / "campaign"
    listing = tree / "lists" / "missions.txt"
    listing.parent.mkdir()
    listing.write_text("# May\n\n../campaign/glider7\n  ../campaign/auv1/notes.txt \n")
    more = tree / "lists" / "more.txt"
    more.write_text(f"{camp / 'auv1' / 'm2.csv'}\n{camp / 'missing_bag'}\n")
    jobs, _, _ = plan(args_of(f"@{listing}", "--list", more, "-c", tree / "cals" / "cal_default.yaml", "-o", tree / "out"))
    by_name = {j.name: j for j in jobs}
    # A listed directory is walked (names relative to it); a listed recording goes by its own name.
    assert list(by_name) == ["m1_bag", "notes.txt", "m2.csv", "missing_bag"]
    assert by_name["m1_bag"].input == str((tree / "lists" / "../campaign/glider7/m1_bag").absolute())
    assert by_name["notes.txt"].problem.endswith("notes.txt: not a recording: give a rosbag2 directory or a .csv file")
    assert by_name["missing_bag"].problem == f"{camp / 'missing_bag'} does not exist"
    assert not by_name["m2.csv"].problem


def test_a_mapping_file_picks_each_recordings_calibration(tree: Path) -> None:
    mapping = tree / "cals" / "campaign.yaml"
    mapping.write_text(
        "magcal_batch:\n"
        "  calibrations:\n"
        "    - {vehicle: auv1, calibration: cal_auv1.yaml}\n"
        "    - {match: 'glider*/*', calibration: cal_glider.yaml}\n"
        "    - {vehicle: 'nothing*', match: '*', calibration: missing.yaml}\n"
    )
    jobs, _, _ = plan(args_of(tree / "campaign", "-c", mapping, "-o", tree / "out", "--vehicle-pattern",
                           r"campaign/(?P<vehicle>[^/]+)/"))
    cal = {j.name: Path(j.calibration).name if j.calibration else "" for j in jobs}
    assert cal == {"auv1/m1_bag": "cal_auv1.yaml", "auv1/m2.csv": "cal_auv1.yaml", "auv2/2025-05-01/m1_bag": "",
                   "glider7/m1_bag": "cal_glider.yaml"}
    (auv2,) = [j for j in jobs if j.name.startswith("auv2")]
    assert auv2.vehicle == "auv2", "the pattern's group"
    assert auv2.problem == f"no entry of {mapping} covers auv2/2025-05-01/m1_bag (vehicle auv2)"
    # A default entry covers the rest.
    mapping.write_text(mapping.read_text() + "    - {calibration: cal_default.yaml}\n")
    jobs, _, _ = plan(args_of(tree / "campaign", "-c", mapping, "-o", tree / "out", "--vehicle-pattern",
                           r"campaign/([^/]+)/"))
    assert {Path(j.calibration).name for j in jobs if j.vehicle == "auv2"} == {"cal_default.yaml"}
    assert {Path(j.calibration).name for j in jobs if j.vehicle == "auv1"} == {"cal_auv1.yaml"}, "the first match wins"
    assert not any(j.problem for j in jobs)


@pytest.mark.parametrize(("text", "message"), [
    ("magcal_batch: {calibrations: []}\n", "needs 'calibrations:'"),
    ("magcal_batch:\n  calibrations:\n    - {vehicle: auv1}\n", "entry 1 needs 'calibration: FILE'"),
    ("magcal_batch:\n  calibrations:\n    - {vehicel: auv1, calibration: a.yaml}\n", "unknown key vehicel"),
])
def test_a_bad_mapping_is_refused_with_its_reason(tree: Path, text: str, message: str) -> None:
    mapping = tree / "cals" / "bad.yaml"
    mapping.write_text(text)
    with pytest.raises(InputError, match=message):
        plan(args_of(tree / "campaign", "-c", mapping, "-o", tree / "out"))


def test_an_unreadable_calibration_refuses_the_batch(tree: Path) -> None:
    bad = tree / "cals" / "broken.yaml"
    bad.write_text("magcal_correction:\n  ros__parameters:\n    sensor_names: [mag1\n")
    with pytest.raises(InputError, match="broken.yaml"):
        plan(args_of(tree / "campaign", "-c", bad, "-o", tree / "out"))
    with pytest.raises(InputError, match="inside the output directory"):
        plan(args_of(tree / "campaign" / "auv1", "-c", tree / "cals" / "cal_default.yaml", "-o", tree / "campaign"))


def test_done_means_unchanged_input_output_calibration_and_options(tree: Path) -> None:
    jobs, _, _ = plan(args_of(tree / "campaign" / "auv1" / "m2.csv", "-c", tree / "cals" / "cal_default.yaml",
                           "-o", tree / "out"))
    (job,) = jobs
    assert cp.finished(job, "abc") is None, "no record yet"
    Path(job.output).parent.mkdir(parents=True)
    shutil.copy2(job.input, job.output)
    os.utime(job.output, ns=(Path(job.input).stat().st_mtime_ns + 10**9,) * 2)
    outcome = job.outcome("corrected", sets=1)
    cp.write_record(job, "abc", outcome)
    assert cp.finished(job, "abc") == outcome
    assert json.loads(Path(job.record).read_text())["files"]["input"][0][0] == "m2.csv"
    assert cp.finished(job, "other calibration") is None
    assert cp.finished(replace(job, correct_args=("--drop-nonfinite",)), "abc") is None, "other options"
    st = Path(job.input).stat()
    os.utime(job.input, ns=(st.st_atime_ns, st.st_mtime_ns + 5 * 10**9))
    assert cp.finished(job, "abc") is None, "input newer than the record"
    os.utime(job.input, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert cp.finished(job, "abc") == outcome
    Path(job.output).write_text(Path(job.output).read_text() + "\n")
    assert cp.finished(job, "abc") is None, "output changed"
    Path(job.record).write_text("{not json")
    assert cp.finished(job, "abc") is None


def test_log_histogram_quantiles_are_the_inverted_cdf_within_its_resolution() -> None:
    rng = np.random.default_rng(3)
    values = np.abs(rng.normal(0, 1e-9, 20001))
    values[:7] = 0.0
    h = LogHistogram()
    for part in np.array_split(values, 7):
        h.add(part)
    h.add([np.nan])
    assert h.count == len(values)
    for q in (0.01, 0.5, 0.95, 0.999):
        want = np.quantile(values, q, method="inverted_cdf")
        assert h.quantile(q) == pytest.approx(want, rel=6e-4)
    assert LogHistogram().quantile(0.5) is None
    assert h.quantile(0.0001) == pytest.approx(1e-15, rel=1e-3), "zeros count in the lowest bin"


def test_step_noise_is_white_noise_sigma_across_chunks() -> None:
    rng = np.random.default_rng(4)
    sigma = 3.5e-9
    rows = 1e-7 * np.linspace(0, 1, 50000)[:, None] + rng.normal(0, sigma, (50000, 6))  # a slow ramp plus noise
    s = StepNoise()
    for part in np.array_split(rows, 9):
        s.add(part)
    d = np.diff(rows, axis=0)
    assert s.value() == pytest.approx(np.sqrt(np.mean(d * d) / 2), rel=1e-12)
    assert s.value() == pytest.approx(sigma, rel=0.02)
    assert StepNoise().value() is None


def test_other_commands_do_not_import_dask() -> None:
    code = ("import sys; from magcal_ros.app.cli import build_parser; p = build_parser(); "
            "p.parse_args(['correct', 'a', '-c', 'b', '-o', 'c']); p.parse_args(['batch', 'a', '-c', 'b', '-o', 'c']); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "[]"


def test_the_reports_reference_comes_from_the_calibration_or_a_truth_file(tmp_path: Path) -> None:
    from magcal_ros.app.batch_task import reference_of
    from magcal_ros.io.truth_file import write_simulation
    from magcal_ros.sim.spec import SimulationSpec

    _, truth_yaml, _ = write_simulation(tmp_path / "sim.csv", SimulationSpec(count=20, intensity=4.8e-5, noise=2e-9))
    assert reference_of(str(truth_yaml), calfile.read(truth_yaml)) == (4.8e-5, 2e-9)
    cal = ArrayCalibration(ArrayGeometry.single("mag1"), np.eye(3)[None], np.zeros((1, 3)),
                           {"intensity": 5.1e-5, "noise": [1e-9, 3e-9]})
    calfile.write(tmp_path / "cal.yaml", cal)
    assert reference_of(str(tmp_path / "cal.yaml"), calfile.read(tmp_path / "cal.yaml")) == \
        pytest.approx((5.1e-5, np.sqrt(5e-18)), rel=1e-12)
    plain = ArrayCalibration(ArrayGeometry.single("mag1"), np.eye(3)[None], np.zeros((1, 3)))
    calfile.write(tmp_path / "plain.yaml", plain)
    assert reference_of(str(tmp_path / "plain.yaml"), calfile.read(tmp_path / "plain.yaml")) == (None, None)


def test_local_workers_are_bounded_by_the_machine_and_connect_timeout_goes_with_scheduler(
        tree: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from magcal_ros.app import batch

    cal = tree / "cals" / "cal_default.yaml"
    monkeypatch.setattr(batch, "default_workers", lambda: 2)
    monkeypatch.setattr(batch, "available_memory", lambda: 64 * 2**30)
    assert batch.max_workers() == (8, "4 per core on its 2 cores")
    plan(args_of(tree / "campaign", "-c", cal, "-o", tree / "out", "--workers", 8))
    with pytest.raises(InputError, match=r"^--workers 9: this machine runs at most 8 local worker processes \(4 per "
                       r"core on its 2 cores\); give at most 8$"):
        plan(args_of(tree / "campaign", "-c", cal, "-o", tree / "out", "--workers", 9))
    monkeypatch.setattr(batch, "available_memory", lambda: 5 * batch.WORKER_MEMORY + 1)  # memory holds 5
    assert batch.max_workers()[0] == 5
    monkeypatch.setattr(batch, "available_memory", lambda: batch.WORKER_MEMORY)  # never fewer than the cores
    assert batch.max_workers()[0] == 2
    with pytest.raises(InputError, match="^--connect-timeout applies to --scheduler$"):
        plan(args_of(tree / "campaign", "-c", cal, "-o", tree / "out", "--connect-timeout", 5))

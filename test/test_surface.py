"""What a new user meets first: `magcal --version`, the licence, the install requirements, the help
texts, and `magcal simulate` for any array (one, two, N sensors, or any positions)."""

from __future__ import annotations

import ast
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import truth_tools as tt
import yaml

from magcal_ros.app.cli import _attach_negative_values, _value_options, build_parser
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import gradient_floor
from magcal_ros.io.csv_recording import read_csv

ROOT = Path(__file__).resolve().parents[1]


def run_magcal(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "magcal_ros.app.cli", *args], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def _setup_call() -> dict[str, ast.expr]:
    """The keyword arguments of setup.py's setup() call, as syntax (the file is not run)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    return {k.arg: k.value for k in call.keywords if k.arg}


def _requirement_name(text: str) -> str:
    return re.split(r"[\[<>=!~; ]", text.strip(), maxsplit=1)[0].lower()


def test_version_matches_package_xml_and_setup() -> None:
    proc = run_magcal("--version")
    assert proc.returncode == 0, proc.stderr
    xml = re.search(r"<version>([^<]+)</version>", (ROOT / "package.xml").read_text()).group(1)  # type: ignore[union-attr]
    assert proc.stdout.strip() == f"magcal {xml} (magcal_ros)"
    assert ast.literal_eval(_setup_call()["version"]) == xml


def test_licence_file_is_the_apache_text_that_package_xml_and_setup_name() -> None:
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "TERMS AND CONDITIONS FOR USE, REPRODUCTION, AND DISTRIBUTION" in text and len(text.splitlines()) > 150
    assert "<license>Apache-2.0</license>" in (ROOT / "package.xml").read_text()
    kw = _setup_call()
    assert ast.literal_eval(kw["license"]) == "Apache-2.0" and ast.literal_eval(kw["license_files"]) == ["LICENSE"]


def test_every_runtime_requirement_is_an_install_requirement() -> None:
    """`pip install .` installs what `magcal` imports: requirements.txt less the ROS wheels (colcon users
    have them from ROS). Dask was missing, so `magcal batch` ended in a ModuleNotFoundError."""
    wanted = {_requirement_name(line) for line in (ROOT / "requirements.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#") and not line.startswith("ros-jazzy-")}
    installed = {_requirement_name(r) for r in ast.literal_eval(_setup_call()["install_requires"])}
    assert "dask" in wanted and wanted <= installed, wanted - installed


def _help(*command: str) -> str:
    proc = run_magcal(*command, "--help")
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


@pytest.mark.parametrize("command", [(), ("simulate",), ("calibrate",), ("correct",), ("batch",), ("plot",)])
def test_help_speaks_of_any_array_and_keeps_its_examples_on_their_lines(command: tuple[str, ...]) -> None:
    """No help says the product is four fluxgates; every example that continues on the next line (a
    trailing backslash) does so, and each example parses with the command's own parser."""
    text = _help(*command)
    assert "four fluxgates" not in text
    lines = text.splitlines()
    parser = build_parser()
    options = _value_options(parser)
    examples: list[str] = []
    for k, line in enumerate(lines):
        if line.lstrip().startswith("magcal "):
            assert len(line) <= 120, f"an example of {len(line)} characters (lost line breaks?): {line!r}"
        if line.rstrip().endswith("\\"):
            assert lines[k + 1].startswith("      "), (line, lines[k + 1])
        if line.lstrip().startswith("magcal ") and (k == 0 or not lines[k - 1].rstrip().endswith("\\")):
            example, j = line.split("#")[0].strip(), k
            while example.endswith("\\"):
                j += 1
                example = example[:-1] + " " + lines[j].split("#")[0].strip()
            examples.append(example)
    assert examples or not command or command == ("plot",) and "magcal plot" in text
    for example in examples:
        words = shlex.split(example)[1:]
        if "..." in words or "&&" in words or words[-1:] == ["--help"]:
            continue
        parser.parse_args(_attach_negative_values(words, options))  # SystemExit(2) on an example that is wrong


def test_simulate_epilogue_keeps_its_line_breaks() -> None:
    text = _help("simulate")
    assert re.search(r"--count 3142 --rate 100 \\\n +--phases 0,0\.0025", text)
    assert re.search(r"--temperatures 5,15,25 \\\n +--tempco-offset", text)
    assert re.search(r"--imu-mounting 2,-1\.5,3 \\\n +--imu-rate 100", text)


@pytest.mark.parametrize(
    ("options", "positions"),
    [
        (["--sensors", "1"], [[0.0, 0.0, 0.0]]),
        (["--sensors", "2", "--baseline", "0.5"], [[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0]]),
        (["--sensors", "3"], [[0.2, 0.0, 0.0], [-0.1, 0.2 * np.sqrt(0.75), 0.0], [-0.1, -0.2 * np.sqrt(0.75), 0.0]]),
        (["--sensors", "4"], [[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]]),
        (["--positions", "0,0,0,0.3,0.1,0,0,0.4,0.2,-0.5,0,0.1,0,-0.2,0"],
         [[0, 0, 0], [0.3, 0.1, 0], [0, 0.4, 0.2], [-0.5, 0, 0.1], [0, -0.2, 0]]),
    ],
)
def test_simulate_makes_any_array_and_its_truth(tmp_path: Path, options: list[str], positions: list[list[float]]) -> None:
    """The recording has one sensor per position; the truth's calibration, applied by the tests' own
    numpy to the raw readings, gives the truth's field at each sensor to the noise (1 nT per axis), so
    the recording is what the truth says it is; the truth YAML's gradient floor is the geometry's."""
    out = tmp_path / "array.csv"
    proc = run_magcal("simulate", str(out), "--count", "300", "--seed", "3", *options)
    assert proc.returncode == 0, proc.stderr
    truth = yaml.safe_load(Path(f"{out}.truth.yaml").read_text())
    params = truth["magcal_correction"]["ros__parameters"]
    count = len(positions)
    assert params["sensor_names"] == [f"mag{i + 1}" for i in range(count)]
    assert np.allclose(np.reshape(params["positions"], (-1, 3)), positions, atol=1e-12)
    rec, _ = read_csv(out)
    assert rec.vectors.shape == (300, count, 3)
    npz = np.load(f"{out}.truth.npz")
    m = np.stack([np.reshape(params[n]["matrix"], (3, 3)) for n in params["sensor_names"]])
    o = np.stack([params[n]["offset"] for n in params["sensor_names"]])
    err = tt.correct(m, o, rec.vectors) - npz["field"]
    assert 0.8e-9 < tt.rms(err) < 1.2e-9  # the noise, nothing else
    floor = truth["magcal_simulation"]["ros__parameters"].get("tensor_noise_floor")
    assert (floor is None) == (count == 1)
    if count == 4:
        assert floor == pytest.approx(tt.difference_floor(1e-9, 0.4), rel=1e-12)
    assert f"{count} sensor" in proc.stdout


@pytest.mark.parametrize("geometry", [ArrayGeometry.ring(2), ArrayGeometry.ring(3), ArrayGeometry.ring(6, 1.0),
                                      ArrayGeometry(("a", "b", "c", "d"), [0, 0, 0, 0.3, 0, 0, 0, 0.4, 0, 0.1, 0.1, 0.3])])
def test_gradient_floor_is_the_spread_of_pure_noise(geometry: ArrayGeometry) -> None:
    """The floor a geometry states is the RMS of the gradient its estimator makes of white noise alone
    (20,000 sets of 1 nT per axis), within 2 %."""
    rng = np.random.default_rng(5)
    noise = rng.normal(0.0, 1e-9, (20_000, geometry.size, 3))
    if geometry.gradient_kind == "baseline":
        measured = tt.rms(tt.baseline_slope(noise, geometry.positions)) if geometry.size == 2 else None
    else:
        measured = tt.rms(tt.least_squares_tensor(noise, geometry.positions)[:, :2, :])
    assert measured is not None
    assert gradient_floor(1e-9, geometry) == pytest.approx(float(measured), rel=0.02)


@pytest.mark.parametrize("options", [["--sensors", "0"], ["--sensors", "65"], ["--positions", "1,2"],
                                     ["--positions", "0,0,x"], ["--sensors", "2", "--positions", "0,0,0"],
                                     ["--positions", "0,0,0,0,0,nan"]])
def test_simulate_refuses_an_array_it_cannot_make_in_one_line(tmp_path: Path, options: list[str]) -> None:
    proc = run_magcal("simulate", str(tmp_path / "x.csv"), *options)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "--sensors" in proc.stderr or "--positions" in proc.stderr
    assert not list(tmp_path.iterdir())


PLOTTED = re.compile(r"plotted (?P<sets>\d+) sets of (?P<sensors>\d+) sensors? -> \S+, TMI median (?P<tmi>[\d.]+) nT"
                     r"(?: \(F (?P<F>[\d.]+) nT\))?, gradient set-to-set noise (?P<noise>[\d.]+) nT/m"
                     r"(?: against the noise floor (?P<floor>[\d.]+) nT/m)?")


@pytest.mark.parametrize("array", [[], ["--sensors", "3", "--baseline", "0.6"]])
def test_plot_draws_a_corrected_recording_with_its_noise_floor(tmp_path: Path, array: list[str]) -> None:
    """`magcal plot` of a corrected survey in a uniform field: the printed gradient set-to-set noise is the
    truth's noise floor within 8 %, the floor drawn (from the calibration's stored noise and the
    array's own estimator) within 5 % of it, the centre TMI's median F within 1 nT; a raw recording with
    -c gives the very same line; the PNG has one panel row per series (3 here). Planted: the floor as
    sqrt(2) sigma / 0.4 m whatever the array fails the 3-sensor case."""
    sim = ["--seed", "4", "--count", "1500", *array]
    assert run_magcal("simulate", str(tmp_path / "rot.csv"), *sim).returncode == 0
    assert run_magcal("simulate", str(tmp_path / "survey.csv"), *sim[:2], "--count", "2000", *array,
                      "--schedule", "tumble").returncode == 0
    truth = yaml.safe_load(Path(f"{tmp_path / 'rot.csv'}.truth.yaml").read_text())
    positions = ",".join(str(v) for v in truth["magcal_correction"]["ros__parameters"]["positions"])
    floor = truth["magcal_simulation"]["ros__parameters"]["tensor_noise_floor"]
    cal = tmp_path / "cal.yaml"
    proc = run_magcal("calibrate", str(tmp_path / "rot.csv"), "-o", str(cal), "--reference-field", "5.5e-5",
                      "--positions", positions)
    assert proc.returncode == 0 and "warning" not in proc.stdout, proc.stdout + proc.stderr
    assert run_magcal("correct", str(tmp_path / "survey.csv"), "-c", str(cal), "-o", str(tmp_path / "out.csv")).returncode == 0
    lines = []
    for source in ("out.csv", "survey.csv"):
        proc = run_magcal("plot", str(tmp_path / source), "-c", str(cal), "-o", str(tmp_path / f"{source}.png"))
        assert proc.returncode == 0, proc.stderr
        lines.append(proc.stdout.split(" -> ")[1].split(", ", 1)[1])
        found = PLOTTED.search(proc.stdout)
        assert found, proc.stdout
        assert int(found["sets"]) == 2000 and float(found["F"]) == 55000.0
        assert abs(float(found["tmi"]) - 55000.0) < 1.0
        assert float(found["floor"]) == pytest.approx(floor * 1e9, rel=0.05)
        assert float(found["noise"]) == pytest.approx(floor * 1e9, rel=0.08)
    assert lines[0] == lines[1]
    from matplotlib.image import imread

    image = imread(tmp_path / "out.csv.png")
    assert image.shape[0] == pytest.approx(90 * (3 * 3.6 + 0.6), abs=2) and np.mean(image[..., :3] < 0.5) > 0.005


def test_plot_refuses_a_raw_recording_without_its_calibration(tmp_path: Path) -> None:
    assert run_magcal("simulate", str(tmp_path / "raw.csv"), "--count", "50").returncode == 0
    proc = run_magcal("plot", str(tmp_path / "raw.csv"), "-o", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and "is a raw recording" in proc.stderr and "-c CALIBRATION.yaml" in proc.stderr
    proc = run_magcal("plot", str(tmp_path / "raw.csv"), "-o", str(tmp_path / "x.pdf"))
    assert proc.returncode == 2 and "PNG" in proc.stderr
    assert not (tmp_path / "x.png").exists()

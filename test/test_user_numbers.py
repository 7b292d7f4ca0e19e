"""What a user reads, against simulated truth, with units: the printed summary and per-sensor
lines of ``magcal calibrate``, the quantities it reports (nT, ppm, deg) and the calibration
file's provenance (T, nT, ppm, deg), each number recomputed from the recording and the
simulator's true calibration with plain numpy (test/truth_tools.py).

A quantity reported in the wrong unit (an offset of 1.7e-16 nT), a residual of the wrong
sensor or a stale summary fails here even when the calibration itself is right.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from test_offline import magcal, ok
from truth_tools import correct, cross_rows, quantities, rms, sensor_errors, summary_numbers

NT = 1e-9
F = 5.5e-5  # simulate's default intensity (T)
NOISE = 1e-9
SETS = 600


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """``magcal simulate`` (CSV, its truth beside it) then ``magcal calibrate``: what it printed,
    the file it wrote, the raw readings and the true calibration."""
    work = tmp_path_factory.mktemp("numbers")
    rec = work / "rotation.csv"
    ok(magcal("simulate", rec, "--count", SETS, "--seed", 3, "--noise", NOISE))
    out = work / "cal.yaml"
    printed = ok(magcal("calibrate", rec, "-o", out, "--reference-field", F)).stdout
    rows = np.loadtxt(rec, delimiter=",", skiprows=1, dtype=str)
    raw = rows[:, 1:].astype(float).reshape(len(rows), 4, 3)
    truth = yaml.safe_load(Path(f"{rec}.truth.yaml").read_text())["magcal_correction"]["ros__parameters"]
    names = truth["sensor_names"]
    m = np.stack([np.reshape(truth[n]["matrix"], (3, 3)) for n in names])
    o = np.stack([truth[n]["offset"] for n in names])
    return {"printed": printed, "file": yaml.safe_load(out.read_text()), "raw": raw, "names": names,
            "positions": np.reshape(truth["positions"], (-1, 3)), "matrices": m, "offsets": o}


def _floors(run: dict[str, Any]) -> dict[str, Any]:
    """What the raw readings and the true calibration give on the same sets (T, T/m)."""
    raw, pos = run["raw"], run["positions"]
    true_b = correct(run["matrices"], run["offsets"], raw)
    return {
        "tmi_before": rms(np.linalg.norm(raw, axis=-1) - F, axis=0),
        "tmi_truth": rms(np.linalg.norm(true_b, axis=-1) - F, axis=0),
        "tensor_before": float(rms(cross_rows(raw, pos))),
        "tensor_truth": float(rms(cross_rows(true_b, pos))),
    }


def test_the_printed_summary_reads_true_numbers_in_nT(cli_run: dict[str, Any]) -> None:
    got = summary_numbers(cli_run["printed"])
    floors = _floors(cli_run)
    assert got["sensors"] == 4 and got["sets"] == SETS and got["method"] == "ml"
    assert got["F"] == pytest.approx(F / NT, abs=0.05)
    assert got["tmi_before"] == pytest.approx(np.max(floors["tmi_before"]) / NT, abs=0.006)  # worst sensor, raw
    assert got["gradient_before"] == pytest.approx(floors["tensor_before"] / NT, abs=0.06)
    # After: at the true calibration's level on the same sets (a fit leaves slightly less).
    assert 0.9 < got["tmi_after"] / (np.max(floors["tmi_truth"]) / NT) < 1.05, (got, floors)
    assert 0.9 < got["gradient_after"] / (floors["tensor_truth"] / NT) < 1.05, (got, floors)


def test_the_printed_sensor_lines_read_true_numbers_in_nT(cli_run: dict[str, Any]) -> None:
    floors = _floors(cli_run)
    for i, name in enumerate(cli_run["names"]):
        line = re.search(rf"  {name}: TMI RMS +([\d.]+) -> +([\d.]+) nT, noise ([\d.]+) nT", cli_run["printed"])
        assert line, cli_run["printed"]
        before, after, noise = map(float, line.groups())
        assert before == pytest.approx(floors["tmi_before"][i] / NT, abs=0.006)
        assert 0.9 < after / (floors["tmi_truth"][i] / NT) < 1.05
        assert 0.9 < noise / (NOISE / NT) < 1.1  # the simulated noise, per axis


def test_the_printed_quantities_have_their_units(cli_run: dict[str, Any]) -> None:
    """``mag3 non-orthogonality x-z -0.9257 +- 0.00013 deg (0.12 nT effect)``: the value is the true
    angle within its 1-sigma, and the effect is the 1-sigma times F in nT."""
    line = next(x for x in cli_run["printed"].splitlines() if "least determined:" in x)
    shown = quantities(line)
    effects = [float(e) for e in re.findall(r"\(([\d.e+-]+) nT effect\)", line)]
    assert len(shown) == 3 and len(effects) == 3, line
    for q, effect in zip(shown, effects):
        per_unit = {"nT": 1.0, "ppm": 1e-6 * F / NT, "deg": np.radians(1.0) * F / NT}[q["unit"]]  # type: ignore[index]
        assert effect == pytest.approx(float(q["sigma"]) * per_unit, rel=0.06), (q, effect)
        i = cli_run["names"].index(q["sensor"])
        k = np.linalg.inv(cli_run["matrices"][i])
        errors = sensor_errors(k)
        name = str(q["name"])
        if name.startswith("offset"):
            true = cli_run["offsets"][i]["xyz".index(name[-1])] / NT
        elif name.startswith("scale"):
            true = errors["scale"]["xyz".index(name[-1])]
        elif name.startswith("non-orthogonality"):
            true = np.degrees(errors["angles"][("x-z", "x-y", "y-z").index(name.split()[-1])])
        else:
            continue  # misalignment: relative to the array's own frame
        value, sigma = float(q["value"]), float(q["sigma"]) * (1e-6 if q["unit"] == "ppm" else 1.0)
        assert abs(value - true) < 5 * sigma + 1e-4 * abs(true), (q, true)


def test_the_files_provenance_reads_true_numbers_in_si_and_its_uncertainty_in_nT(cli_run: dict[str, Any]) -> None:
    meta = cli_run["file"]["magcal_provenance"]["ros__parameters"]
    cal = cli_run["file"]["magcal_correction"]["ros__parameters"]
    floors = _floors(cli_run)
    assert meta["samples"] == SETS and meta["intensity"] == pytest.approx(F, rel=1e-12)
    assert meta["reference_field"] == pytest.approx(F, rel=1e-12)
    np.testing.assert_allclose(meta["tmi_rms_before"], floors["tmi_before"], rtol=1e-9)  # T
    assert meta["tensor_rms_before"] == pytest.approx(floors["tensor_before"], rel=1e-9)  # T/m
    ratio = np.array(meta["tmi_rms_after"]) / floors["tmi_truth"]
    assert np.all((ratio > 0.9) & (ratio < 1.05)), ratio
    assert 0.9 < meta["tensor_rms_after"] / floors["tensor_truth"] < 1.05
    assert np.all(np.abs(np.array(meta["noise"]) / NOISE - 1) < 0.1), meta["noise"]  # T
    assert meta["summary"].replace("\u00a0", " ") in cli_run["printed"]  # the file keeps rclpy from re-reading ": " as YAML
    # Offsets (nT): each 1-sigma between the floor of averaging N readings of one axis and a few
    # times it, and the fitted offsets off the truth by about their 1-sigma (z-scores RMS ~ 1).
    floor = NOISE / NT / np.sqrt(SETS)
    z = []
    for i, name in enumerate(cli_run["names"]):
        u = meta["uncertainty"][name]
        for a, axis in enumerate("xyz"):
            sigma = u[f"offset_{axis}_nT"]
            assert floor < sigma < 4 * floor, (name, axis, sigma, floor)
            z.append((cal[name]["offset"][a] - cli_run["offsets"][i][a]) / NT / sigma)
            # gains (ppm) and angles (deg): at least the floor noise / (F sqrt(N)), at most a few times it
            rel = NOISE / (F * np.sqrt(SETS))
            assert rel * 1e6 < u[f"scale_{axis}_ppm"] < 6 * rel * 1e6, (name, u)
        for pair in ("xz", "xy", "yz"):
            assert np.degrees(rel) < u[f"nonorthogonality_{pair}_deg"] < 6 * np.degrees(rel), (name, u)
    assert 0.4 < float(rms(np.array(z))) < 2.5, np.round(z, 2)


def test_every_quantity_describes_itself_in_its_unit_against_the_truth() -> None:
    """In process, every quantity of a calibration (offsets nT, gains with ppm, angles deg) as
    ``describe()`` prints it, against the simulator's sensor errors."""
    from magcal_ros.methods.pipeline import calibrate_array
    from magcal_ros.sim.attitudes import uniform_random
    from magcal_ros.sim.scenarios import field_trial_array

    sim = field_trial_array(31)
    rng = np.random.default_rng(31)
    rec, _ = sim.run(uniform_random(800, rng), rng)
    res = calibrate_array(rec.vectors, sim.geometry, 51_500 * NT)
    printed = "; ".join(q.describe() for q in res.identifiability.quantities)
    shown = {(q["sensor"], q["name"]): q for q in quantities(printed)}
    exact = {(q.sensor, q.name): q for q in res.identifiability.quantities}
    assert len(shown) == 48, printed
    z = []
    for i, sensor in enumerate(sim.sensors):
        k, offset = sensor.forward()
        errors = sensor_errors(k)
        name = sim.geometry.names[i]
        for a, axis in enumerate("xyz"):
            q = shown[(name, f"offset {axis}")]
            assert q["unit"] == "nT"
            z.append((float(q["value"]) - offset[a] / NT) / float(q["sigma"]))
            s = shown[(name, f"scale {axis}")]
            assert s["unit"] == "ppm" and abs(float(s["value"]) - exact[(name, f"scale {axis}")].value * 1e-6) <= 5e-6
            gain = exact[(name, f"scale {axis}")].value * 1e-6  # printed to 1e-5, finer than its 1-sigma
            z.append((gain - errors["scale"][a]) / (float(s["sigma"]) * 1e-6))
        for j, pair in enumerate(("x-z", "x-y", "y-z")):
            q = shown[(name, f"non-orthogonality {pair}")]
            assert q["unit"] == "deg"
            z.append((float(q["value"]) - np.degrees(errors["angles"][j])) / float(q["sigma"]))
    z_arr = np.array(z)
    assert np.max(np.abs(z_arr)) < 5 and 0.4 < float(rms(z_arr)) < 2.0, np.round(z_arr, 2)

"""Both nodes with any array, over DDS, nodes as separate processes (issue: one, two or N sensors).

One private domain holds three arrays, each in its own namespace:

- ``/one``: one sensor ``mag1`` with no positions, both nodes: raw in, corrected out (the
  calibration applied in numpy), ``field`` only (no gradient topic exists), ``~/calibrate``
  on a simulated rotation reaching the noise floor on fresh data;
- ``/two``: two sensors 0.5 m apart, both nodes: ``baseline_gradient`` (dB/ds) instead of
  the tensor topics, calibrated over DDS to its floor ``sqrt(2) sigma / d``;
- ``/six``: six sensors in no cross (``gradient_method: least_squares``): the tensor as the
  core computes it; ``difference`` is refused at start-up with the reason.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ros_harness as h

from magcal_ros.app.ros_driver import (
    ArrayDriver,
    NodeProcess,
    recording_messages,
    ros_args,
    wait_for_samples,
)
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.recording import Recording
from magcal_ros.core.tensor import baseline_gradient, gradient
from magcal_ros.io import calibration_file as calfile
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

ONE = ArrayGeometry.single("mag1")
TWO = ArrayGeometry(("fore", "aft"), np.array([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0]]))
SIX = ArrayGeometry(tuple(f"m{i}" for i in range(1, 7)), np.array([
    [0.3, 0.0, 0.0], [0.1, 0.25, 0.0], [-0.2, 0.2, 0.05], [-0.3, -0.05, 0.0], [0.0, -0.25, -0.05], [0.15, -0.1, 0.1],
]))


def simulate(geometry: ArrayGeometry, seed: int) -> ArraySimulation:
    rng = np.random.default_rng(seed)
    return ArraySimulation(geometry, tuple(random_sensor_errors(rng) for _ in geometry.names),
                           earth_field(h.INTENSITY, 60.0, 5.0), noise=h.NOISE)


@dataclass
class Array:
    sim: ArraySimulation
    namespace: str
    driver: ArrayDriver
    manoeuvre: Recording
    fresh: Recording

    @property
    def correction(self) -> str:
        return f"/{self.namespace}/{h.CORRECTION}"

    @property
    def calibration(self) -> str:
        return f"/{self.namespace}/{h.CALIBRATION}"


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Any:
    workdir = tmp_path_factory.mktemp("arrays")
    run = h.RosRun(workdir, domain_id=h.pick_domain_id(seed=os.getpid() + 37))
    arrays: dict[str, Array] = {}
    try:
        for key, geo, kind in (("one", ONE, "none"), ("two", TWO, "baseline")):
            sim = simulate(geo, {"one": 1, "two": 2}[key])
            rng = np.random.default_rng(10)
            manoeuvre, _ = sim.run(uniform_random(600, rng), rng, rate=50.0)
            fresh, _ = sim.run(uniform_random(300, rng), rng, rate=50.0, start=1000.0)
            params: dict[str, Any] = {"sensor_names": list(geo.names), "uncorrected_sensors": list(geo.names),
                                      **h.LOSSLESS}
            if key == "two":
                params["positions"] = [float(x) for x in geo.positions.reshape(-1)]
            run.start("correction_node", params=params, namespace=key, log_name=f"{key}_correction")
            cal = {"sensor_names": list(geo.names), "reference_field": h.INTENSITY, "prior": "none", **h.LOSSLESS,
                   "calibration_file": str(workdir / f"{key}.yaml"), "service_timeout": h.SERVICE_TIMEOUT, "progress_period": 0.5}
            if key == "two":
                cal["positions"] = params["positions"]
            run.start("calibration_node", params=cal, namespace=key, log_name=f"{key}_calibration")
            driver = run.driver(geo.names, namespace=key, kind=kind)
            h.wait_discovered(driver, subscribers=2)
            arrays[key] = Array(sim, key, driver, manoeuvre, fresh)
        yield run, arrays
    finally:
        codes = run.close()
        assert codes and all(c == 0 for c in codes.values()), codes


def _replay(array: Array, rec: Recording) -> tuple[dict[int, int], list[int]]:
    mapping = array.driver.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE)
    published = [mapping[int(t)] for t in rec.stamps]
    array.driver.wait_for_outputs(published, timeout=h.OUTPUT_TIMEOUT, settle=h.OUTPUT_SETTLE)
    return mapping, published


def _live_calibration(driver: ArrayDriver, node: str, geometry: ArrayGeometry) -> ArrayCalibration:
    names = ["sensor_names", "positions"] + [f"{n}.{s}" for n in geometry.names for s in ("matrix", "offset")]
    p = driver.get_parameters(node, names)
    nested: dict[str, Any] = {"sensor_names": p["sensor_names"], "positions": p["positions"]}
    for n in geometry.names:
        nested[n] = {"matrix": p[f"{n}.matrix"], "offset": p[f"{n}.offset"]}
    return ArrayCalibration.from_parameters(nested)


def _calibrate(array: Array) -> str:
    d = array.driver
    ok, message = d.trigger(f"{array.calibration}/start")
    assert ok, message
    rec = array.manoeuvre
    sent = d.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE)
    progress = wait_for_samples(d, array.calibration.strip("/"), len(sent), timeout=h.SAMPLES_TIMEOUT)
    assert int(progress.get("samples", 0)) >= 0.97 * len(rec), progress  # a busy machine may lose a few
    ok, message = d.trigger(f"{array.calibration}/calibrate")
    assert ok, message
    return message


# --------------------------------------------------------------------------- one sensor


def test_one_sensor_without_positions_publishes_field_and_no_gradient_topic(world: Any) -> None:
    run, arrays = world
    one = arrays["one"]
    log = next(p for p in run.processes if p.log_path.stem == "one_correction").log()
    assert "correcting mag1 -> <name>/corrected, field (one sensor position: no gradient)" in log
    d = one.driver
    for topic in ("gradient", "gradient_stamped", "baseline_gradient"):
        assert d.node.get_publishers_info_by_topic(f"/one/{topic}") == [], topic
    assert d.node.get_publishers_info_by_topic("/one/field")
    # Raw in, corrected out: the node's calibration applied, and the field is the one sensor's corrected vector.
    # Started uncorrected (the vector is the raw reading itself), unless the calibration test ran first.
    calibrated = len(d.get_parameters(one.correction, ["mag1.matrix"])["mag1.matrix"]) > 0
    live = _live_calibration(d, one.correction, ONE) if calibrated else None
    rec = one.fresh.window(None, one.fresh.stamps[49])
    mapping, published = _replay(one, rec)
    corrected = d.corrected(published)
    fields = d.fields(published)
    assert len(corrected) >= 48 and set(corrected) == set(fields)
    raw = {mapping[int(t)]: v for t, v in zip(rec.stamps, rec.vectors)}
    for t, v in corrected.items():
        expected = raw[t] if live is None else live.apply(raw[t][None])[0]
        np.testing.assert_allclose(v, expected, rtol=1e-12, atol=1e-20)
        assert np.array_equal(fields[t], v[0]) and (live is not None or np.array_equal(v, raw[t]))


def test_one_sensor_calibrates_over_dds_to_the_noise_floor(world: Any) -> None:
    """~/calibrate on a simulated rotation of one sensor; then fresh sets: the corrected vectors are
    the pushed calibration applied in numpy, and their TMI is at the noise (the true calibration's)."""
    _, arrays = world
    one = arrays["one"]
    message = _calibrate(one)
    assert message.startswith("calibrated 1 sensor from") and "frame: sensor axes made orthogonal" in message
    assert "valid over the whole sphere" in message and "tensor" not in message
    assert "no outlying readings excluded" in message and "prior: none (prior: none)" in message
    live = _live_calibration(one.driver, one.correction, ONE)
    mapping, published = _replay(one, one.fresh)
    corrected = one.driver.corrected(published)
    assert len(corrected) == len(one.fresh)
    raw = {mapping[int(t)]: v for t, v in zip(one.fresh.stamps, one.fresh.vectors)}
    got = np.stack([corrected[t][0] for t in sorted(corrected)])
    expected = live.apply(np.stack([raw[t] for t in sorted(corrected)]))[:, 0]
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-20)
    truth = one.sim.true_calibration().apply(np.stack([raw[t] for t in sorted(corrected)]))[:, 0]
    tmi = np.sqrt(np.mean((np.linalg.norm(got, axis=1) - h.INTENSITY) ** 2))
    tmi_truth = np.sqrt(np.mean((np.linalg.norm(truth, axis=1) - h.INTENSITY) ** 2))
    assert tmi <= 1.1 * tmi_truth, (tmi / 1e-9, tmi_truth / 1e-9)
    file = calfile.read(world[0].workdir / "one.yaml")
    assert file.geometry.names == ("mag1",) and np.array_equal(file.matrices, live.matrices)


# --------------------------------------------------------------------------- two sensors


def test_two_sensors_publish_the_baseline_gradient_at_its_floor(world: Any) -> None:
    _, arrays = world
    two = arrays["two"]
    d = two.driver
    for topic in ("gradient", "gradient_stamped"):
        assert d.node.get_publishers_info_by_topic(f"/two/{topic}") == [], topic
    message = _calibrate(two)
    assert message.startswith("calibrated 2 sensors") and "baseline gradient RMS" in message and "nan" not in message
    live = _live_calibration(d, two.correction, TWO)
    mapping, published = _replay(two, two.fresh)
    base = d.baselines(published)
    assert len(base) == len(two.fresh) and d.outputs.baseline_frames == {"magcal_array"}
    raw = {mapping[int(t)]: v for t, v in zip(two.fresh.stamps, two.fresh.vectors)}
    stamps = sorted(base)
    got = np.stack([base[t] for t in stamps])
    expected = baseline_gradient(live.apply(np.stack([raw[t] for t in stamps])), TWO)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-18)
    floor = np.sqrt(2) * h.NOISE / 0.5  # uniform field: the true baseline gradient is 0
    error = float(np.sqrt(np.mean(got**2)))
    assert error <= 1.1 * floor, (error / 1e-9, floor / 1e-9)


# --------------------------------------------------------------------------- six sensors, any geometry


def test_six_sensors_in_any_geometry_give_the_least_squares_tensor(world: Any, tmp_path: Path) -> None:
    run, _ = world
    sim = simulate(SIX, 6)
    true = sim.true_calibration()
    path = tmp_path / "six.yaml"
    path.write_text(calfile.dumps(true, node_name="/six/magcal_correction"))
    # The difference formula needs a cross: refused at start-up with the reason, exit code 1.
    bad = NodeProcess("correction_node", ros_args(params_files=[path], namespace="six"), run.env,
                      run.workdir / "six_refused.log")
    assert bad.wait(30.0) == 1
    assert "the difference formula needs a planar cross; use gradient_method least_squares" in bad.log()
    run.start("correction_node", params={"gradient_method": "least_squares"}, params_files=[path], namespace="six",
              log_name="six_correction")
    d = run.driver(SIX.names, namespace="six")
    h.wait_discovered(d, subscribers=1)
    rng = np.random.default_rng(6)
    rec, truth = sim.run(uniform_random(200, rng), rng, rate=50.0)
    mapping = d.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE)
    published = [mapping[int(t)] for t in rec.stamps]
    d.wait_for_outputs(published, timeout=h.OUTPUT_TIMEOUT, settle=h.OUTPUT_SETTLE)
    g = d.gradients(published)
    assert len(g) == len(rec)
    index = {mapping[int(t)]: k for k, t in enumerate(rec.stamps)}
    rows = [index[t] for t in sorted(g)]
    got = np.stack([g[t] for t in sorted(g)])
    np.testing.assert_allclose(got, gradient(true.apply(rec.vectors[rows]), SIX, "least_squares"), rtol=1e-9,
                               atol=1e-18)
    assert np.allclose(got, np.swapaxes(got, 1, 2), atol=1e-18) and np.allclose(np.trace(got, axis1=1, axis2=2), 0,
                                                                                  atol=1e-18)


def test_positions_are_required_beyond_one_sensor(world: Any) -> None:
    run, _ = world
    bad = NodeProcess("correction_node", ros_args(params={"sensor_names": ["fore", "aft"]}, namespace="nopos"),
                      run.env, run.workdir / "nopos.log")
    assert bad.wait(30.0) == 1
    assert "positions needs 3 numbers per sensor (m, platform frame): 6 for 2 sensors, none given" in bad.log()

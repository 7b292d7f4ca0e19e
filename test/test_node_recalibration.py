"""Calibration health and recalibration during a mission, through both nodes over DDS.

The mission of the demo (:mod:`magcal_ros.app.drift_demo`) at 100 sets/s of stamps, replayed
four times faster than real time: the nodes judge by the sets' stamps, so what is asserted
(seconds of mission, figures against the floor) does not depend on the replay speed or on
spare CPU; only how long the test waits does. The correction node runs the true calibration
and judges it over 30 s of sets (the default 60 s is the demo's, at real time); the
calibration node recalibrates from 20 s of sets.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

import ros_harness as h
from magcal_ros.app.drift_demo import run_drift_mission
from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.io import calibration_file as calfile
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

SPEED = 4.0


def test_a_drift_mid_mission_is_named_advised_then_fixed(tmp_path: Path) -> None:
    rng = np.random.default_rng(31)
    geo = ArrayGeometry.cross(h.BASELINE)
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                          earth_field(h.INTENSITY, 60.0, 5.0), noise=h.NOISE)
    cal_path = tmp_path / "calibration.yaml"
    truth = replace(sim.true_calibration(), metadata={"noise": [h.NOISE] * 4, "intensity": h.INTENSITY})
    calfile.write(cal_path, truth)
    before_text = cal_path.read_text()
    block = yaml.safe_load(before_text)["magcal_correction"]["ros__parameters"]  # what the health compares with
    assert block["calibration_intensity"] == pytest.approx(h.INTENSITY) and block["mag3"]["noise"] == pytest.approx(h.NOISE)
    qos = h.LOSSLESS
    run = h.RosRun(tmp_path)
    lines: list[str] = []
    t0 = time.monotonic()

    def say(text: str) -> None:
        lines.append(f"[{time.monotonic() - t0:5.1f} s] {text}")

    try:
        run.start("correction_node", params={**qos, "health_window": 30.0}, params_files=[cal_path],
                  log_name="correction")
        run.start("calibration_node", params={**qos, "reference_field": h.INTENSITY, "calibration_file": str(cal_path),
                                              "recalibrate_window": 20.0, "assess_period": 1.0},
                  log_name="calibration")
        driver = run.driver(geo.names)
        h.wait_discovered(driver, subscribers=2)
        out = run_drift_mission(driver, sim, rng, say, speed=SPEED, clean=24.0, longest=600.0,
                                target_at=12.0, fresh=20.0)
        log = run.processes[1].log()
    finally:
        codes = run.close()
    assert codes == {"correction": 0, "calibration": 0}, codes
    story = "\n".join(lines)
    # the clean phase, a target passed: judged and OK throughout
    assert out.clean_levels and set(out.clean_levels) == {0}, story
    # the drift named on /diagnostics within a minute of sets (half the 30 s window), naming sensors and the noise
    assert out.named_after is not None and 0.0 <= out.named_after <= 30.0, story
    assert "calibration drifted: TMI residual" in out.named and out.named.endswith(": recalibrate")
    # auto_recalibrate false: advice, and the calibration untouched (node and file)
    assert out.advice.startswith("what is being flown determines what changed"), story
    assert out.untouched
    # auto_recalibrate true: pushed, said on /diagnostics and in the log, saved with a backup
    assert out.recalibrated.startswith("recalibrated /magcal_correction during the mission from "), story
    assert "offsets moved: mag1 " in out.recalibrated and "held-out sets: TMI RMS" in out.recalibrated
    assert "recalibrated /magcal_correction during the mission" in log
    saved = calfile.read(cal_path)
    assert len(calfile.backups(cal_path)) == 1 and calfile.backups(cal_path)[0].read_text() == before_text
    assert not np.allclose(saved.offsets, truth.offsets)
    # on fresh attitudes afterwards: the live tensor within 1.2x the floor (the drifted one: far above)
    assert out.tensor_recalibrated <= 1.2 * out.floor, story
    assert out.tensor_drifted > 50 * out.floor
    assert out.final_health.startswith(("calibration fits", "collecting")), story


def test_one_sensors_jump_is_fixed_on_the_first_window_over_dds(tmp_path: Path) -> None:
    """auto_recalibrate from the start, mag2's hard iron jumps by 500 nT during the demo's turns: the health
    names mag2 and only it, the calibration node pushes on its first attempt (it counts them), the other three
    sensors keep their calibration to the bit in the file it saved, and the live tensor on fresh turns is
    within 1.2x the floor sqrt(2) sigma / d."""
    rng = np.random.default_rng(32)
    geo = ArrayGeometry.cross(h.BASELINE)
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                          earth_field(h.INTENSITY, 60.0, 5.0), noise=h.NOISE)
    sensors = list(sim.sensors)
    sensors[1] = replace(sensors[1], hard_iron=sensors[1].hard_iron + np.array([300.0, -250.0, 300.0]) * 1e-9)
    moved = replace(sim, sensors=tuple(sensors))
    cal_path = tmp_path / "calibration.yaml"
    truth = replace(sim.true_calibration(), metadata={"noise": [h.NOISE] * 4, "intensity": h.INTENSITY})
    calfile.write(cal_path, truth)
    run = h.RosRun(tmp_path)
    lines: list[str] = []
    try:
        run.start("correction_node", params={**h.LOSSLESS, "health_window": 30.0}, params_files=[cal_path],
                  log_name="correction")
        run.start("calibration_node", params={**h.LOSSLESS, "reference_field": h.INTENSITY,
                                              "calibration_file": str(cal_path), "recalibrate_window": 20.0,
                                              "assess_period": 1.0, "auto_recalibrate": True},
                  log_name="calibration")
        driver = run.driver(geo.names)
        h.wait_discovered(driver, subscribers=2)
        out = run_drift_mission(driver, sim, rng, lines.append, speed=SPEED, clean=24.0, longest=600.0,
                                target_at=12.0, fresh=20.0, moved=moved, advise=False)
        log = run.processes[1].log()
    finally:
        codes = run.close()
    assert codes == {"correction": 0, "calibration": 0}, codes
    story = "\n".join(lines)
    assert out.named.startswith("mag2 calibration drifted: ") and out.named_sensors == "mag2", story
    assert len(out.named) <= 128 and out.named.endswith(": recalibrate")
    assert out.attempts == 1 and out.recalibrated.startswith("recalibrated /magcal_correction during the mission"), \
        story + log
    assert "the hard iron of mag2 jumps at 24 s" in story
    assert "(mag1, mag3, mag4 kept as running)" in out.recalibrated, out.recalibrated
    saved = calfile.read(cal_path)
    kept = [0, 2, 3]
    np.testing.assert_array_equal(saved.offsets[kept], truth.offsets[kept])
    np.testing.assert_array_equal(saved.matrices[kept], truth.matrices[kept])
    assert not np.allclose(saved.offsets[1], truth.offsets[1])
    assert out.tensor_recalibrated <= 1.2 * out.floor < 50 * out.floor < out.tensor_drifted, story


@pytest.mark.parametrize("uncorrected", [True])
def test_the_health_is_not_assessed_without_a_calibration(tmp_path: Path, uncorrected: bool) -> None:
    """Raw readings on purpose: the calibration status says so (OK), and says nothing about drift."""
    run = h.RosRun(tmp_path)
    try:
        run.start("correction_node", params=h.UNCORRECTED, log_name="correction")
        driver = run.driver(h.NAMES)
        status = driver.diagnostics(f"/{h.CORRECTION}: calibration", timeout=h.DISCOVERY_TIMEOUT)
    finally:
        run.close()
    assert status is not None
    assert status.message == "not assessed: mag1, mag2, mag3, mag4 not calibrated"
    assert {kv.key: kv.value for kv in status.values}["drifted"] == "false"

"""The nodes with the sensors' temperatures and the vehicle's IMU, over DDS, against simulated truth.

``warm``: a correction node loaded with a true calibration that has temperature terms and an
output rotation (an IMU mounted 2-3 deg off the array): every set it publishes is the truth's
correction at that set's temperature, in the IMU's frame; a set without a fresh temperature is
withheld and counted. ``col``: a calibration node collecting the temperatures and the IMU with
the sets, and a correction node whose temperature terms and rotation the new calibration clears.
Waits are on counts with generous deadlines, raw topics reliable: no timing decides a test.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import ros_harness as h
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import MagneticField

from magcal_ros.app.ros_driver import ArrayDriver, recording_messages, status_values, wait_for_samples
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.recording import Recording
from magcal_ros.io import calibration_file as calfile
from magcal_ros.sim.spec import SimulationSpec, build, run

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

WARM = "/warm/magcal_correction"
COL = "/col/magcal_correction"
COL_CAL = "/col/magcal_calibration"
MOUNTING_DEG = (2.0, -1.5, 3.0)
F = 5.5e-5
LEAD = 50
"""Sets by which the temperatures and the IMU lead the raw sets in a replay (they are there first)."""


@dataclass
class Warm:
    rec: Recording
    field: np.ndarray
    """(N, S, 3) true field, platform frame."""
    true: ArrayCalibration


@dataclass
class Col:
    rec: Recording


@pytest.fixture(scope="module")
def warm_data() -> Warm:
    spec = SimulationSpec(count=300, seed=8, noise=h.NOISE, temperatures=(4.0, 27.0), tempco_offset=0.5e-9,
                          tempco_gain=40e-6, imu=True, imu_mounting=MOUNTING_DEG)
    sim, attitudes = build(spec)
    blocks = np.where(np.arange(len(attitudes)) < len(attitudes) // 2, 4.0, 27.0)
    temps = blocks[:, None] + np.array([0.0, 1.5, 3.0, -2.0])  # each sensor at its own temperature
    rec, truth = sim.run(attitudes, np.random.default_rng(81), rate=50.0, start=100.0, temperatures=temps)
    return Warm(rec, truth.field, truth.calibration)


@pytest.fixture(scope="module")
def col_data() -> Col:
    spec = SimulationSpec(schedule="tumble", count=800, seed=9, noise=h.NOISE, temperatures=(10.0, 20.0), imu=True,
                          imu_mounting=MOUNTING_DEG)
    rec, _, _ = run(spec)
    return Col(rec)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, warm_data: Warm) -> Any:
    workdir = tmp_path_factory.mktemp("temperature")
    runner = h.RosRun(workdir, domain_id=h.pick_domain_id(seed=os.getpid() + 73))
    fast = {"status_period": 0.25, "sensor_timeout": 0.5, "output_timeout": 1.5}
    reliable = h.LOSSLESS  # a history deeper than any replay: a reliable reader whose history fills loses sets for good
    try:
        for ns, key in (("warm", WARM), ("col", COL)):
            path = workdir / f"{ns}.yaml"
            path.write_text(calfile.dumps(warm_data.true, node_name=key))
            runner.start("correction_node", params=dict(fast, **reliable), params_files=[path], namespace=ns,
                         log_name=f"{ns}_correction")
        runner.start("calibration_node", namespace="col", log_name="col_calibration", params=dict(reliable, **{
            "reference_field": F, "prior": "none", "calibration_file": str(workdir / "col_out.yaml"),
            "service_timeout": 10.0, "progress_period": 0.5}))
        yield runner
    finally:
        codes = runner.close()
        assert codes and all(c == 0 for c in codes.values()), codes


def _discovered(d: ArrayDriver, subscribers: int, extra: list[Any]) -> None:
    assert d.wait_for_subscribers(subscribers, h.DISCOVERY_TIMEOUT) and d.wait_for_output_publishers(h.DISCOVERY_TIMEOUT)
    deadline = time.monotonic() + h.DISCOVERY_TIMEOUT
    while not all(p.get_subscription_count() >= 1 for p in extra):
        assert time.monotonic() < deadline, "temperature or IMU topics not matched"
        time.sleep(0.05)


def _replay(d: ArrayDriver, rec: Recording, temperatures: np.ndarray | None, imu: bool = False) -> dict[int, int]:
    return d.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE, current_lead=LEAD,
                    temperatures=temperatures,
                    imu=(rec.imu.orientation, rec.imu.angular_velocity) if imu and rec.imu is not None else None)


@pytest.fixture(scope="module")
def warm(world: h.RosRun, warm_data: Warm) -> ArrayDriver:
    d = world.driver(warm_data.rec.names, namespace="warm", temperatures=True)
    _discovered(d, 1, list(d.temperature_publishers))
    rec = warm_data.rec.take(np.arange(10))
    deadline = time.monotonic() + h.DISCOVERY_TIMEOUT
    while True:  # every topic discovered both ways: a few sets come back
        d.clear_outputs()
        mapping = _replay(d, rec, rec.temperatures)
        if d.wait_for_outputs([mapping[int(t)] for t in rec.stamps], timeout=2.0, settle=0.5) >= len(rec):
            break
        assert time.monotonic() < deadline, "no corrected sets came back"
    d.clear_outputs()
    return d


def test_the_correction_node_corrects_for_temperature_in_the_imu_frame(warm: ArrayDriver, warm_data: Warm) -> None:
    """Each set is the truth's correction at its own temperature (4 or 27 C), turned into the IMU frame:
    the true field there within the noise; without the temperature terms tens of nT off."""
    rec, true = warm_data.rec, warm_data.true
    frames: list[str] = []
    sub = warm.node.create_subscription(MagneticField, warm.topic("field"), lambda m: frames.append(m.header.frame_id),
                                        100)
    try:
        warm.clear_outputs()
        mapping = _replay(warm, rec, rec.temperatures)
        warm.wait_for_outputs([mapping[int(t)] for t in rec.stamps], timeout=60.0)
        back = {mapping[int(t)]: k for k, t in enumerate(rec.stamps)}
        c = warm.corrected(back)
    finally:
        warm.node.destroy_subscription(sub)
    rows = np.array([back[t] for t in sorted(c)])
    assert len(rows) >= 0.95 * len(rec)
    b = np.stack([c[t] for t in sorted(c)])
    expected = true.apply(rec.vectors[rows], temperatures=rec.temperatures[rows])
    own_sensor = np.all(np.isclose(b, expected, rtol=1e-9, atol=1e-18), axis=2)  # (sets, sensors)
    own = own_sensor.all(axis=1)
    # A set formed before a sensor's own temperature arrived (a loaded machine delays one topic more
    # than another; each sensor's temperature is a topic of its own) takes that sensor's latest
    # temperature received, an earlier set's: exactly that sensor's correction, and rarely.
    for i, k in zip(*np.nonzero(~own_sensor)):
        r = int(rows[i])
        earlier = true.apply(np.repeat(rec.vectors[r : r + 1], r, axis=0), temperatures=rec.temperatures[:r])[:, k]
        assert np.any(np.all(np.isclose(b[i, k], earlier, rtol=1e-9, atol=1e-18), axis=1)), (r, k, b[i, k],
                                                                                             expected[i, k])
    assert own.sum() >= 0.95 * len(rows), f"{(~own).sum()} of {len(rows)} sets with an earlier set's temperature"
    rot = true.output_rotation
    err = b - warm_data.field[rows] @ rot.T
    assert np.sqrt(np.mean(err**2)) < 1.5 * h.NOISE  # the true field, in the IMU frame, within the noise
    untempered = ArrayCalibration(true.geometry, true.matrices, true.offsets, output_rotation=rot)
    assert np.max(np.abs(untempered.apply(rec.vectors[rows]) - warm_data.field[rows] @ rot.T)) > 10e-9
    assert set(frames) == {"imu_link"}


def test_a_stale_temperature_withholds_the_set_and_names_the_sensor(warm: ArrayDriver, warm_data: Warm) -> None:
    """mag3's temperature stops (NaN is no value) for longer than temperature_tolerance: its sets are not
    published, counted as mag3.stale_temperature, and /diagnostics warns naming mag3 only."""
    before = status_values(warm.diagnostics(WARM, None, 30.0))
    rec = warm_data.rec.take(np.arange(60))
    temps = rec.temperatures.copy()
    temps[:, 2] = np.nan
    # Stamped 11 s ahead of the wall clock: mag3's last temperature (from the sets before) is older than the
    # 10 s tolerance, the others' come with the sets.
    key = "mag3.stale_temperature"
    sent = _replay_ahead(warm, rec, temps, ahead_s=11.0)

    def counted(s: DiagnosticStatus) -> bool:
        return int(status_values(s)[key]) - int(before[key]) >= len(rec)

    status = warm.diagnostics(WARM, counted, 60.0)
    assert status is not None, "the stale sets were not counted"
    values = status_values(status)
    assert int(values[key]) - int(before[key]) == len(rec)
    for other in ("mag1", "mag2", "mag4"):
        assert values[f"{other}.stale_temperature"] == before[f"{other}.stale_temperature"]
    assert int(values["mag1.temperature_received"]) > int(before["mag1.temperature_received"])
    assert status.level[0] >= 1 and "stale temperature" in status.message, status.message
    assert "mag3 on /warm/mag3/temperature" in status.message and "mag1 on" not in status.message
    with warm._lock:
        assert not any(t in warm.outputs.field for t in sent), "a set used a stale temperature"


def _replay_ahead(d: ArrayDriver, rec: Recording, temps: np.ndarray, ahead_s: float) -> list[int]:
    """Publish the sets (and their temperatures, LEAD sets ahead) stamped ``ahead_s`` s after now; the stamps."""
    spacing = int(1e9 / h.REPLAY_RATE)
    base = time.time_ns() + int(ahead_s * 1e9)
    stamps = [base + k * spacing for k in range(len(rec))]
    period = 1.0 / h.REPLAY_RATE
    for k in range(len(rec) + LEAD):
        if k < len(rec):
            for j, c in enumerate(temps[k]):
                d.publish_temperature(j, stamps[k], float(c))
        if k >= LEAD:
            i = k - LEAD
            for name, v in zip(rec.names, rec.vectors[i]):
                d.publish(h.RawMessage(name, stamps[i], (float(v[0]), float(v[1]), float(v[2]))))
        time.sleep(period)
    return stamps


def test_the_calibration_node_collects_temperatures_and_imu_and_clears_old_terms(
    world: h.RosRun, col_data: Col, warm_data: Warm
) -> None:
    """The calibration node hears the temperatures and the IMU and collects them with every set (none
    stale); the calibration it pushes has no temperature terms and the IMU's rotation, so the correction
    node's earlier terms (loaded from a file) are cleared: its sets need no temperature any more."""
    rec = col_data.rec
    d = world.driver(rec.names, namespace="col", temperatures=True, imu_topic="imu")
    _discovered(d, 2, [*d.temperature_publishers, d.imu_publisher])
    ok, message = d.trigger(f"{COL_CAL}/start")
    assert ok, message
    sent = _replay(d, rec, rec.temperatures, imu=True)
    progress = wait_for_samples(d, COL_CAL.strip("/"), len(sent), timeout=h.SAMPLES_TIMEOUT)

    def heard(s: DiagnosticStatus) -> bool:
        v = status_values(s)
        return int(v.get("imu.received", 0)) >= len(rec) and int(v.get("mag4.temperature_received", 0)) >= len(rec)

    status = d.diagnostics(COL_CAL, heard, 60.0)
    assert status is not None, "the IMU and the temperatures were not heard"
    values = status_values(status)
    assert values["imu.stale"] == "0" and all(values[f"{n}.stale_temperature"] == "0" for n in rec.names)
    # none stale, so every set is collected: the last one too (it waited for an IMU sample newer than itself,
    # which never comes at the end of a stream, until it waited the IMU tolerance)
    assert int(progress.get("samples", 0)) == len(rec), str(progress)
    ok, message = d.trigger(f"{COL_CAL}/calibrate", timeout=180.0)
    assert ok, message
    got = d.get_parameters(COL, ["mag1.offset_per_kelvin", "mag2.matrix_per_kelvin", "output_rotation"])
    assert got["mag1.offset_per_kelvin"] == [0.0] * 3 and got["mag2.matrix_per_kelvin"] == [0.0] * 9
    # calibrated with the IMU: the outputs are in its frame (the fitted array-to-IMU rotation, a few deg)
    rot = np.reshape(got["output_rotation"], (3, 3))
    assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) and 0.5 < np.degrees(np.arccos((np.trace(rot) - 1) / 2)) < 10
    # sets without any temperature now come back from the correction node
    part = rec.take(np.arange(40))
    d.clear_outputs()
    mapping = d.replay(recording_messages(part.names, part.stamps, part.vectors), rate=h.REPLAY_RATE)
    assert d.wait_for_outputs([mapping[int(t)] for t in part.stamps], timeout=60.0) >= 0.95 * len(part)


def test_temperature_and_imu_parameters_are_checked(world: h.RosRun, warm: ArrayDriver) -> None:
    cases = [
        (WARM, {"temperature_reference": 400.0}, "not a temperature in deg C"),
        (WARM, {"mag1.offset_per_kelvin": [1e-3, 0.0, 0.0]}, "units must be T/K"),
        (WARM, {"output_rotation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]}, "must be a rotation matrix"),
        (COL_CAL, {"imu_topic": "bad topic"}, "imu_topic"),
    ]
    for node, values, reason in cases:
        (ok, why), = warm.set_parameters(node, values)
        assert not ok and reason in why, (values, why)
    described = warm.describe_parameters(WARM, ["temperature_tolerance"])["temperature_tolerance"]
    assert described.floating_point_range[0].to_value == 3600.0

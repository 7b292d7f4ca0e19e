"""The ROS 2 nodes, tested as a user runs them: separate processes talking over DDS.

Synthetic rotation recordings are written as rosbag2 with rosbags, replayed message by
message into ``correction_node`` and ``calibration_node`` (installed executables,
``--ros-args``, a private ROS domain, localhost discovery), and the services are called
through a real rclpy client. Outputs are checked against the simulation's truth on sets
that were not part of the calibration.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ros_harness as h  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402

from magcal_ros.app.ros_driver import (  # noqa: E402
    bag_messages,
    status_values,
    wait_for_samples,
    write_messages_bag,
)
from magcal_ros.core.calibration import ArrayCalibration  # noqa: E402
from magcal_ros.core.metrics import rms, tensor_floor, tmi_rms  # noqa: E402
from magcal_ros.core.sync import DEFAULT_SYNC_MODE  # noqa: E402
from magcal_ros.io import calibration_file as calfile  # noqa: E402
from magcal_ros.io.bag_writer import write_recording_bag  # noqa: E402

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

CALIBRATION_PARAMS = ["sensor_names", "positions"] + [
    f"mag{i}.{s}" for i in range(1, 5) for s in ("matrix", "offset")
]


@pytest.fixture(scope="module")
def data() -> h.Data:
    return h.make_data()


@pytest.fixture(scope="module")
def bags(data: h.Data, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The recordings as rosbag2 directories (sqlite3 and mcap)."""
    root = tmp_path_factory.mktemp("bags")
    out = {"manoeuvre": root / "manoeuvre", "single_axis": root / "single_axis", "faulty": root / "faulty"}
    write_recording_bag(out["manoeuvre"], data.manoeuvre, storage="mcap")
    write_recording_bag(out["single_axis"], data.single_axis, storage="sqlite3")
    write_messages_bag(out["faulty"], data.faulty, storage="sqlite3")
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """Both nodes running as processes on a private domain, and a driver node."""
    workdir = tmp_path_factory.mktemp("ros")
    r = h.RosRun(workdir)
    calibration_file = workdir / "calibration.yaml"
    try:
        r.start("correction_node", params=h.UNCORRECTED, log_name="correction")
        r.start(
            "calibration_node",
            params={"reference_field": h.INTENSITY, "calibration_file": str(calibration_file), "service_timeout": h.SERVICE_TIMEOUT},
            log_name="calibration",
        )
        r.calibration_file = calibration_file
        yield r
    finally:
        codes = r.close()
        # Both nodes must still be alive at the end and stop cleanly on Ctrl-C.
        assert codes == {"correction": 0, "calibration": 0}, codes


@pytest.fixture(scope="module")
def driver(run: h.RosRun, data: h.Data) -> Any:
    d = run.driver(data.names)
    h.wait_discovered(d, subscribers=2)
    return d


@pytest.fixture(scope="module")
def calibrated(run: h.RosRun, driver: Any, data: h.Data, bags: dict[str, Path]) -> dict[str, Any]:
    """Calibrate over DDS from the manoeuvre bag; then replay the fresh sets."""
    ok, message = driver.trigger(f"/{h.CALIBRATION}/start")
    assert ok, message
    messages = bag_messages(bags["manoeuvre"])
    sent = driver.replay(messages, rate=h.REPLAY_RATE)
    progress = wait_for_samples(driver, h.CALIBRATION, len(sent), timeout=h.SAMPLES_TIMEOUT)
    ok, message = driver.trigger(f"/{h.CALIBRATION}/calibrate")
    assert ok, f"calibration failed: {message}\n{run.processes[1].log()}"
    params = driver.get_parameters(h.CORRECTION, CALIBRATION_PARAMS)
    stamps = h.original_stamps(data.check)
    mapping = h.replay_recording(driver, data.check)
    gradients, corrected = h.outputs_by_original(driver, mapping, stamps)
    return {"message": message, "progress": progress, "params": params, "gradients": gradients,
            "corrected": corrected, "stamps": stamps, "file_text": run.calibration_file.read_text()}


def _calibration_from(params: dict[str, Any]) -> ArrayCalibration:
    nested: dict[str, Any] = {"sensor_names": params["sensor_names"], "positions": params["positions"]}
    for name in params["sensor_names"]:
        nested[name] = {"matrix": params[f"{name}.matrix"], "offset": params[f"{name}.offset"]}
    return ArrayCalibration.from_parameters(nested)


def test_calibration_over_dds_reaches_the_noise_floor(calibrated: dict[str, Any], data: h.Data) -> None:
    assert calibrated["message"].startswith("calibrated 4 sensors")
    assert "applied to /magcal_correction" in calibrated["message"]
    assert calibrated["progress"].get("ready") == "true"
    stamps = calibrated["stamps"]
    got = [t for t in stamps if t in calibrated["gradients"] and t in calibrated["corrected"]]
    assert len(got) == len(stamps), f"only {len(got)} of {len(stamps)} fresh sets came back"
    index = {t: k for k, t in enumerate(stamps)}
    rows = [index[t] for t in got]
    g = np.stack([calibrated["gradients"][t] for t in got])
    b = np.stack([calibrated["corrected"][t] for t in got])
    truth = data.check_truth.gradient[rows]
    floor = tensor_floor(h.NOISE, h.BASELINE)
    tensor_error = float(rms((g - truth)[:, :2, :]))  # the six measured components
    tmi_error = float(rms(np.linalg.norm(b, axis=-1) - h.INTENSITY))
    assert tensor_error <= 1.15 * floor, f"tensor RMSE {tensor_error / 1e-9:.3f} nT/m vs floor {floor / 1e-9:.3f}"
    assert tmi_error <= 1.15 * h.NOISE, f"TMI RMS {tmi_error / 1e-9:.3f} nT vs noise {h.NOISE / 1e-9:.3f}"
    assert np.max(tmi_rms(b, h.INTENSITY)) <= 1.3 * h.NOISE


def test_the_service_answer_reads_true_numbers_in_nT(calibrated: dict[str, Any], data: h.Data) -> None:
    """``~/calibrate``'s answer, as a user reads it: sets, F, TMI and tensor RMS before (from the raw
    manoeuvre, recomputed here) and after (at the level the true calibration reaches on it)."""
    from truth_tools import correct, cross_rows, summary_numbers, true_correction

    got = summary_numbers(calibrated["message"])
    raw = data.manoeuvre.vectors
    pos = data.sim.geometry.positions
    true_b = correct(*true_correction(data.sim), raw)
    assert got["sensors"] == 4 and got["sets"] == len(data.manoeuvre) == int(calibrated["progress"]["samples"])
    assert got["F"] == pytest.approx(h.INTENSITY / 1e-9, abs=0.05)
    assert got["tmi_before"] == pytest.approx(np.max(tmi_rms(raw, h.INTENSITY)) / 1e-9, abs=0.006)
    assert got["gradient_before"] == pytest.approx(float(rms(cross_rows(raw, pos))) / 1e-9, abs=0.06)
    assert 0.9 < got["tmi_after"] / (np.max(tmi_rms(true_b, h.INTENSITY)) / 1e-9) < 1.05, got
    assert 0.9 < got["gradient_after"] / (float(rms(cross_rows(true_b, pos))) / 1e-9) < 1.05, got


def test_outputs_follow_the_contract(calibrated: dict[str, Any], driver: Any) -> None:
    """Gradient layout dims and the corrected vectors' relation to the live parameters."""
    assert driver.outputs.gradient_layouts[0] == (("row", 3, 9), ("col", 3, 3))
    cal = _calibration_from(calibrated["params"])
    t = calibrated["stamps"][0]
    b = calibrated["corrected"][t]
    # The tensor is what the core computes from the corrected vectors (difference formula).
    from magcal_ros.core.tensor import gradient

    assert np.allclose(gradient(b[None], cal.geometry)[0], calibrated["gradients"][t], rtol=1e-9, atol=1e-18)


def test_calibration_file_reloads_into_a_fresh_node(calibrated: dict[str, Any], data: h.Data, tmp_path: Path) -> None:
    """The file written by ~/calibrate, loaded with --params-file, gives the same output."""
    text = calibrated["file_text"]
    loaded = calfile.loads(text)
    live = _calibration_from(calibrated["params"])
    assert np.array_equal(loaded.matrices, live.matrices) and np.array_equal(loaded.offsets, live.offsets)
    path = tmp_path / "calibration.yaml"
    path.write_text(text)
    fresh = h.RosRun(tmp_path, domain_id=h.pick_domain_id(seed=os.getpid() + 50))
    try:
        fresh.start("correction_node", params_files=[path], log_name="fresh_correction")
        assert "calibrated sensors: mag1, mag2, mag3, mag4" in fresh.processes[0].log()
        d = fresh.driver(data.names)
        h.wait_discovered(d, subscribers=1)
        stamps = calibrated["stamps"][:100]
        mapping = h.replay_recording(d, data.check.window(None, data.check.stamps[99]))
        gradients, _ = h.outputs_by_original(d, mapping, stamps)
        common = [t for t in stamps if t in gradients and t in calibrated["gradients"]]
        assert len(common) == len(stamps)
        for t in common:
            assert np.allclose(gradients[t], calibrated["gradients"][t], rtol=1e-12, atol=1e-20)
    finally:
        assert fresh.close() == {"fresh_correction": 0}


def test_single_axis_rotation_is_refused_and_nothing_changes(
    calibrated: dict[str, Any], run: h.RosRun, driver: Any, data: h.Data, bags: dict[str, Path]
) -> None:
    """Without a prior (prior: none); with the running calibration as the prior it would be a
    partial recalibration (tests in test_node_field.py)."""
    (ok, reason), = driver.set_parameters(h.CALIBRATION, {"prior": "none"})
    assert ok, reason
    ok, message = driver.trigger(f"/{h.CALIBRATION}/start")
    assert ok, message
    sent = driver.replay(bag_messages(bags["single_axis"]), rate=h.REPLAY_RATE)
    progress = wait_for_samples(driver, h.CALIBRATION, len(sent), timeout=h.SAMPLES_TIMEOUT)
    assert progress.get("ready") == "false" and "one axis" in progress.get("problem", "")
    ok, message = driver.trigger(f"/{h.CALIBRATION}/calibrate")
    assert not ok
    assert "one axis" in message and "nothing was changed" in message
    assert driver.get_parameters(h.CORRECTION, CALIBRATION_PARAMS) == calibrated["params"]
    assert run.calibration_file.read_text() == calibrated["file_text"]
    # The correction node still gives exactly the same output for the same raw sets.
    stamps = calibrated["stamps"][:50]
    mapping = h.replay_recording(driver, data.check.window(None, data.check.stamps[49]))
    gradients, _ = h.outputs_by_original(driver, mapping, stamps)
    assert len(gradients) == len(stamps)
    for t, g in gradients.items():
        assert np.array_equal(g, calibrated["gradients"][t])
    ok, _ = driver.trigger(f"/{h.CALIBRATION}/reset")
    assert ok
    assert driver.set_parameters(h.CALIBRATION, {"prior": "running"})[0][0]


def test_bad_samples_are_dropped_and_good_sets_corrected(
    calibrated: dict[str, Any], run: h.RosRun, driver: Any, data: h.Data, bags: dict[str, Path]
) -> None:
    """NaN and infinite readings, a silent sensor, a repeat and a stale stamp: nodes survive."""
    ok, _ = driver.trigger(f"/{h.CALIBRATION}/start")
    assert ok
    messages = bag_messages(bags["faulty"])
    assert any(not math.isfinite(m.vector[1]) for m in messages)
    mapping = driver.replay(messages, rate=h.REPLAY_RATE)
    # Sets come out in order, so once the good ones are in, a wrongly published bad one would be too.
    gradients, _ = h.outputs_by_original(driver, mapping, sorted(mapping), wait_for=data.faulty_good)
    assert set(gradients) <= set(data.faulty_good), "a bad or incomplete set was published"
    assert len(gradients) == len(data.faulty_good)
    cal = _calibration_from(calibrated["params"])
    raw = {m.stamp_ns: {} for m in messages}
    for m in messages:
        raw[m.stamp_ns].setdefault(m.name, m.vector)
    for t, g in gradients.items():
        vectors = np.array([[raw[t][n] for n in data.names]])
        _, _, expected = cal.field_and_gradient(vectors)
        assert np.allclose(g, expected[0], rtol=1e-9, atol=1e-18)
    progress = wait_for_samples(driver, h.CALIBRATION, len(gradients), timeout=h.SAMPLES_TIMEOUT)
    assert int(progress["samples"]) == len(data.faulty_good)
    status = driver.wait_for_message(
        DiagnosticStatus, f"/{h.CORRECTION}/status", lambda m: int(status_values(m)["nonfinite"]) >= 20, 30.0
    )
    assert status is not None, "the correction node's ~/status never counted the bad samples"
    counters = status_values(status)
    assert int(counters["nonfinite"]) >= 20 and int(counters["unmatched"]) >= 60
    assert int(counters["duplicate"]) >= 1 and int(counters["out_of_order"]) >= 1
    assert all(p.alive() for p in run.processes)
    assert run.processes[0].wait_for_log("dropped since last report", 15.0)
    ok, _ = driver.trigger(f"/{h.CALIBRATION}/reset")
    assert ok


INVALID_UPDATES: list[tuple[dict[str, Any], str]] = [
    ({"mag1.matrix": [1.0] * 8}, "9 numbers"),
    ({"mag1.matrix": [float("nan")] + [0.0] * 8}, "finite"),
    ({"mag1.matrix": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]}, "singular"),
    ({"mag2.matrix": [50.0, 0.0, 0.0, 0.0, 50.0, 0.0, 0.0, 0.0, 50.0]}, "gains"),
    ({"mag2.offset": [1.0, 0.0, 0.0]}, "Tesla"),
    ({"mag3.offset": [0.0, 0.0]}, "3 numbers"),
    ({"mag3.offset": ["a", "b", "c"]}, "list of numbers"),
    ({"gradient_method": "bogus"}, "gradient_method"),
    ({"positions": [0.2] * 11}, "positions"),
    ({"positions": [0.2, 0, 0, 0.1, 0.3, 0, -0.2, 0, 0, 0, -0.2, 0]}, "least_squares"),
    ({"sensor_names": ["mag1", "mag2", "mag3"]}, "positions"),
    ({"sync_tolerance": -1.0}, "sync_tolerance"),
    ({"frame_id": ""}, "frame_id"),
    ({"mag9.matrix": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}, "unknown parameter"),
    ({"mag1.matrix": [2.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 2.0], "mag4.offset": [1.0, 1.0, 1.0]}, "mag4"),
]


@pytest.mark.parametrize("atomic", [True, False], ids=["atomically", "set_parameters"])
def test_invalid_parameter_updates_are_rejected_with_a_reason(
    calibrated: dict[str, Any], driver: Any, atomic: bool
) -> None:
    for update, why in INVALID_UPDATES:
        results = driver.set_parameters(h.CORRECTION, {k: [float(x) if isinstance(x, int) else x for x in v]
                                                        if isinstance(v, list) else v for k, v in update.items()},
                                        atomic=atomic)
        if atomic or len(update) == 1:
            assert not any(ok for ok, _ in results), f"{update} was accepted"
            reasons = " ".join(r for _, r in results)
            assert why in reasons, f"{update}: reason {reasons!r} does not mention {why!r}"
        else:
            # Non-atomic: each parameter on its own; the valid one may pass, the bad one may not.
            assert not all(ok for ok, _ in results), f"{update} was accepted"
            driver.set_parameters(h.CORRECTION, {"mag1.matrix": calibrated["params"]["mag1.matrix"]})
    assert driver.get_parameters(h.CORRECTION, CALIBRATION_PARAMS) == calibrated["params"]
    # A valid update is accepted and can be undone.
    assert driver.set_parameters(h.CORRECTION, {"gradient_method": "least_squares"}, atomic=atomic)[0][0]
    assert driver.set_parameters(h.CORRECTION, {"gradient_method": "difference"}, atomic=atomic)[0][0]


def test_calibration_with_unreachable_correction_node_changes_nothing(
    calibrated: dict[str, Any], run: h.RosRun, driver: Any, bags: dict[str, Path]
) -> None:
    assert driver.set_parameters(h.CALIBRATION, {"correction_node": "no_such_node", "service_timeout": 1.0})[0][0]
    try:
        ok, _ = driver.trigger(f"/{h.CALIBRATION}/start")
        assert ok
        sent = driver.replay(bag_messages(bags["manoeuvre"]), rate=h.REPLAY_RATE)
        wait_for_samples(driver, h.CALIBRATION, len(sent), timeout=h.SAMPLES_TIMEOUT)
        ok, message = driver.trigger(f"/{h.CALIBRATION}/calibrate")
        assert not ok
        assert "not reachable" in message and "nothing was changed" in message
        assert run.calibration_file.read_text() == calibrated["file_text"]
        assert driver.get_parameters(h.CORRECTION, CALIBRATION_PARAMS) == calibrated["params"]
    finally:
        driver.set_parameters(h.CALIBRATION, {"correction_node": h.CORRECTION, "service_timeout": h.SERVICE_TIMEOUT})
        driver.trigger(f"/{h.CALIBRATION}/reset")


def test_calibrate_without_samples_explains_what_to_do(calibrated: dict[str, Any], driver: Any) -> None:
    ok, _ = driver.trigger(f"/{h.CALIBRATION}/reset")
    assert ok
    ok, message = driver.trigger(f"/{h.CALIBRATION}/calibrate")
    assert not ok
    assert "no synchronized sets" in message and "~/start" in message


def test_calibration_node_rejects_invalid_parameters(driver: Any) -> None:
    for update, why in [
        ({"method": "bogus"}, "unknown method"),
        ({"reference_field": 1.0}, "out of range"),
        ({"reference_field": 1e-9}, "Earth-like"),
        ({"reference_field": "a lot"}, "must be a number"),
        ({"max_samples": 3}, "out of range"),
        ({"positions": [0.2, 0.0, 0.0]}, "positions"),
    ]:
        (ok, reason), = driver.set_parameters(h.CALIBRATION, update)
        assert not ok and why in reason, (update, reason)


def test_relative_calibration_without_reference_field(
    calibrated: dict[str, Any], run: h.RosRun, driver: Any, data: h.Data, bags: dict[str, Path], tmp_path: Path
) -> None:
    """reference_field 0: F is estimated; the tensor still reaches the floor. Restores the state after."""
    other_file = tmp_path / "relative.yaml"
    assert driver.set_parameters(h.CALIBRATION, {"reference_field": 0.0, "calibration_file": str(other_file)})[0][0]
    try:
        assert driver.trigger(f"/{h.CALIBRATION}/start")[0]
        sent = driver.replay(bag_messages(bags["manoeuvre"]), rate=h.REPLAY_RATE)
        wait_for_samples(driver, h.CALIBRATION, len(sent), timeout=h.SAMPLES_TIMEOUT)
        ok, message = driver.trigger(f"/{h.CALIBRATION}/calibrate")
        assert ok and "relative: no reference, F taken as" in message, message
        assert calfile.read(other_file).metadata["reference_field"] == 0.0
        stamps = calibrated["stamps"][:200]
        mapping = h.replay_recording(driver, data.check.window(None, data.check.stamps[199]))
        gradients, _ = h.outputs_by_original(driver, mapping, stamps)
        g = np.stack([gradients[t] for t in stamps if t in gradients])
        error = float(rms(g[:, :2, :]))
        assert error <= 1.15 * tensor_floor(h.NOISE, h.BASELINE)
    finally:
        restore = {"reference_field": h.INTENSITY, "calibration_file": str(run.calibration_file)}
        driver.set_parameters(h.CALIBRATION, restore)
        driver.trigger(f"/{h.CALIBRATION}/reset")
        (ok, reason), = driver.set_parameters(h.CORRECTION, calibrated["params"])
        assert ok, reason


def test_each_corrected_vector_carries_its_sensors_own_stamp(calibrated: dict[str, Any], driver: Any,
                                                              data: h.Data) -> None:
    """Sensors stamp their own readings: here each a different 0.1-0.7 ms after the first (inside the
    1 ms sync tolerance). ``/<name>/corrected`` keeps each sensor's stamp, ``field`` and
    ``gradient_stamped`` the set's (the first sensor's). Matching exactly, as this test's premise (with mode
    ``auto`` the node's choice depends on the replays before: after one whose sensors stamped alike, these
    offsets end exact matching and the interpolated sets carry the set's stamp)."""
    (ok, reason), = driver.set_parameters(h.CORRECTION, {"sync_mode": "exact"})
    assert ok, reason
    try:
        _each_sensors_own_stamp(driver, data)
    finally:
        (ok, reason), = driver.set_parameters(h.CORRECTION, {"sync_mode": DEFAULT_SYNC_MODE})
        assert ok, reason


def _each_sensors_own_stamp(driver: Any, data: h.Data) -> None:
    rng = np.random.default_rng(5)
    rec = data.check.window(None, data.check.stamps[59])
    start = 1_900_000_000 * 10**9 + 123_457  # odd nanoseconds, far from every other replay's stamps
    messages, own = [], {n: [] for n in data.names}
    for k, vectors in enumerate(rec.vectors):
        t0 = start + k * 20_000_000
        for i, (name, v) in enumerate(zip(data.names, vectors)):
            t = t0 + (i * h.SENSOR_SKEW_NS + int(rng.integers(-h.STAMP_JITTER_NS, h.STAMP_JITTER_NS)) if i else 0)
            own[name].append(t)
            messages.append(h.RawMessage(name, t, (float(v[0]), float(v[1]), float(v[2]))))
    driver.clear_outputs()
    driver.replay(messages, rate=h.REPLAY_RATE, restamp=False)
    sets = own[data.names[0]]
    assert driver.wait_for_outputs(sets, timeout=h.OUTPUT_TIMEOUT, settle=h.OUTPUT_SETTLE) == len(sets)
    with driver._lock:
        for name in data.names:
            got = sorted(driver.outputs.corrected[name])
            assert got == own[name], f"{name}/corrected is not stamped with {name}'s own stamps"
        assert sorted(driver.outputs.field) == sets and sorted(driver.outputs.stamped) == sets

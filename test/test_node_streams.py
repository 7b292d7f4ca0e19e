"""Real sensor streams through the correction node over DDS: each sensor on its own clock, stamped on
receipt, with glitches, restarts and a lag, published message by message in arrival order into the
installed node (own process, private domain, reliable QoS so that nothing is lost on a busy
machine). What the node published is compared with the same synchroniser run offline on the same
messages, and with the noise floor (uniform field, true calibration); counts come from what the
node reports on ~/status."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ros_harness as h  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402

from magcal_ros.app.ros_driver import ArrayDriver, RawMessage, status_values  # noqa: E402
from magcal_ros.core.metrics import tensor_floor  # noqa: E402
from magcal_ros.core.sync import DROP_FIELDS, synchronise_streams  # noqa: E402
from magcal_ros.core.units import NT  # noqa: E402
from magcal_ros.io import calibration_file as calfile  # noqa: E402
from magcal_ros.sim.streams import PATTERNS, StreamRecording, simulate_streams, turn  # noqa: E402
from test_streams import array  # noqa: E402

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

FLOOR = tensor_floor(1 * NT, 0.4)
DURATION = 8.0
SPEED = 2.0
"""Messages are published at twice their pace: a loaded machine still keeps up on average."""
FAST = {"status_period": 0.25, "raw_reliability": "reliable", "qos_depth": 10000}
CASES = {  # namespace: (pattern, time offsets given to the node)
    "phased": "phased + 0.5 ms jitter",
    "restart_all": "restart of all",
    "restart_one": "restart of one",
    "glitch": "glitch 2 s early + late",
    "lag": "5 ms lag at 1 rad/s",
}


def recording(pattern: str) -> StreamRecording:
    spec, rate = PATTERNS[pattern]
    if spec.glitches:  # within the shorter run
        spec = type(spec)(**{**spec.__dict__, "glitches": ((1, 3.0, -2.0), (2, 5.0, 2.0))})
    if spec.restarts:
        spec = type(spec)(**{**spec.__dict__, "restarts": ((4.0, 60.0, spec.restarts[0][2]),)})
    attitudes, steps = turn(rate, DURATION + 1.0)
    return simulate_streams(array(3), attitudes, steps, spec, DURATION, np.random.default_rng(33))


@pytest.fixture(scope="module")
def recordings() -> dict[str, StreamRecording]:
    return {ns: recording(p) for ns, p in CASES.items()}


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, StreamRecording]) -> Any:
    workdir: Path = tmp_path_factory.mktemp("streams")
    run = h.RosRun(workdir, domain_id=h.pick_domain_id(seed=os.getpid() + 71))
    try:
        for ns, rec in recordings.items():
            truth = workdir / f"{ns}.yaml"
            cal = rec.calibration
            if ns == "lag":  # the node starts without the lag; the test sets it at runtime
                cal = type(cal)(cal.geometry, cal.matrices, cal.offsets, {}, None)
            truth.write_text(calfile.dumps(cal, node_name=f"/{ns}/{h.CORRECTION}"))
            run.start("correction_node", params=FAST, params_files=[truth], namespace=ns, log_name=ns)
        yield run
    finally:
        codes = run.close()
        assert codes and all(c == 0 for c in codes.values()), codes


def replay(driver: ArrayDriver, rec: StreamRecording) -> None:
    """Every message in bag-time order, paced at SPEED times its own pace."""
    start, first = time.monotonic(), None
    for bag_time, k, i in rec.messages():
        first = bag_time if first is None else first
        delay = start + (bag_time - first) / 1e9 / SPEED - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        s = rec.streams[k]
        driver.publish(RawMessage(s.name, int(s.stamps[i]), tuple(s.vectors[i].tolist())))  # type: ignore[arg-type]


def status(driver: ArrayDriver, ns: str, settled: int) -> dict[str, str]:
    """The node's ~/status once it has counted ``settled`` messages and they are all decided."""
    seen: dict[str, str] = {}

    def done(msg: Any) -> bool:
        seen.clear()
        seen.update(status_values(msg))
        received = sum(int(v) for k, v in seen.items() if k.endswith(".received"))
        return received >= settled and int(seen.get("pending", "0")) < 40
    driver.wait_for_message(DiagnosticStatus, f"/{ns}/{h.CORRECTION}/status", done, 120.0)
    return dict(seen)


def run_case(world: h.RosRun, rec: StreamRecording, ns: str, offsets: bool = True) -> tuple[dict, dict, Any]:
    """Replay ``rec`` into the node of ``ns``; (its status, gradients by stamp it published, the offline sets)."""
    driver = world.driver(rec.names, namespace=ns)
    assert driver.wait_for_subscribers(1, h.DISCOVERY_TIMEOUT) and driver.wait_for_output_publishers(h.DISCOVERY_TIMEOUT)
    time.sleep(1.0)  # the node's readers of this driver's raw topics, and this driver's of its outputs
    replay(driver, rec)
    total = sum(len(s) for s in rec.streams)
    values = status(driver, ns, total)
    lags = list(rec.calibration.time_offsets) if offsets else None  # type: ignore[arg-type]
    batch, _, _ = synchronise_streams([(s.stamps, s.vectors) for s in rec.streams], lags,
                                      receipts=[s.receipts for s in rec.streams], names=rec.names)
    return values, stamped_gradients(driver, batch.set_stamps.tolist()), batch


def stamped_gradients(driver: ArrayDriver, stamps: list[int], timeout: float = 60.0) -> dict[int, np.ndarray]:
    """The gradient_stamped outputs (by their header stamp) of ``stamps``, once they stop coming."""
    wanted = set(stamps)
    deadline, last, since = time.monotonic() + timeout, -1, time.monotonic()
    while time.monotonic() < deadline:
        with driver._lock:
            got = {t: g for t, g in driver.outputs.stamped.items() if t in wanted}
        if len(got) == len(wanted) or (len(got) == last and time.monotonic() - since > 5.0):
            return got
        if len(got) != last:
            last, since = len(got), time.monotonic()
        time.sleep(0.05)
    return got


def check_counts(values: dict[str, str], rec: StreamRecording, keep: float) -> None:
    """At least ``keep`` of the reference's samples published; every message counted once."""
    published = int(values["published"])
    assert published >= keep * len(rec.streams[0]), values
    received = sum(int(values[f"{n}.received"]) for n in rec.names)
    assert received == sum(len(s) for s in rec.streams)
    counted = int(values["used"]) + sum(int(values[k]) for k in DROP_FIELDS) + int(values["pending"])
    assert counted == received, values


def check_outputs(rec: StreamRecording, gradients: dict[int, np.ndarray], batch: Any, factor: float = 1.3,
                  same: bool = True) -> None:
    """The published tensors: at the floor with the true calibration, and (``same``) those of the offline sets.
    (Counts come from the node's status: this driver's own subscription, matched last, may miss the first
    outputs on a busy machine.)"""
    assert len(gradients) >= 0.5 * len(batch)
    g = np.array(list(gradients.values()))
    assert np.sqrt(np.mean(g**2)) / FLOOR < factor
    if same:
        expected = rec.calibration.outputs(batch.vectors).tensor
        index = {t: i for i, t in enumerate(batch.set_stamps.tolist())}
        off = {t: float(np.max(np.abs(got - expected[index[t]]))) for t, got in gradients.items()}  # type: ignore[index]
        bad = sorted(t for t, d in off.items() if d > 1e-15 + 1e-9 * np.max(np.abs(expected[index[t]])))
        first = int(batch.set_stamps[0])
        assert not bad, (f"{len(bad)} of {len(gradients)} published tensors differ from the offline sets' "
                         f"(at {[round((t - first) / 1e9, 4) for t in bad[:12]]} s into the run, worst "
                         f"{max(off[t] for t in bad) / NT:.3g} nT/m)")


def test_sensors_sampled_apart_and_stamped_on_receipt(world: h.RosRun, recordings: dict[str, StreamRecording]) -> None:
    """2.5 ms apart, 0.5 ms of receipt jitter: auto interpolates, >= 99 % of the sets published, each the
    offline set, the tensor at the floor."""
    rec = recordings["phased"]
    values, gradients, batch = run_case(world, rec, "phased")
    assert values["sync_mode"] == "interpolate"
    check_counts(values, rec, 0.99)
    check_outputs(rec, gradients, batch)
    assert world.processes[list(CASES).index("phased")].wait_for_log("sets: mag1's sample instants", 10.0)


@pytest.mark.parametrize("ns", ["restart_all", "glitch"])
def test_restarts_and_glitches_lose_only_what_they_touch(world: h.RosRun, recordings: dict[str, StreamRecording],
                                                         ns: str) -> None:
    rec = recordings[ns]
    values, gradients, batch = run_case(world, rec, ns)
    check_counts(values, rec, 0.98)
    if ns == "glitch":
        assert int(values["glitch"]) == 2
    else:
        assert int(values["restarts"]) == 1
    check_outputs(rec, gradients, batch)


def test_one_sensor_restarting_alone_keeps_the_sets(world: h.RosRun, recordings: dict[str, StreamRecording]) -> None:
    """mag3's stamps jump 60 s back: placed by its arrival (the node's clock), the sets go on (their
    timing is as good as that arrival on a busy machine, so only the counts are checked)."""
    rec = recordings["restart_one"]
    values, _, _ = run_case(world, rec, "restart_one")
    check_counts(values, rec, 0.98)
    assert int(values["restarts"]) == 1


def test_a_lag_set_at_runtime_is_applied(world: h.RosRun, recordings: dict[str, StreamRecording]) -> None:
    """mag3 reads 5 ms late at 1 rad/s: <name>.time_offset set through the parameter service (a bad value
    or exact matching refused with the reason), then the published tensor is at the floor."""
    rec = recordings["lag"]
    driver = world.driver(rec.names, namespace="lag")
    node = f"lag/{h.CORRECTION}"
    (ok, why), = driver.set_parameters(node, {"mag3.time_offset": 0.7})
    assert not ok and "mag3.time_offset" in why
    (ok, why), = driver.set_parameters(node, {"mag3.time_offset": 0.005, "sync_mode": "exact"})
    assert not ok and "interpolate" in why
    (ok, why), = driver.set_parameters(node, {"mag3.time_offset": 0.005})
    assert ok, why
    assert driver.get_parameters(node, ["mag3.time_offset"]) == {"mag3.time_offset": 0.005}
    values, gradients, batch = run_case(world, rec, "lag")
    assert values["sync_mode"] == "interpolate"
    check_counts(values, rec, 0.99)
    check_outputs(rec, gradients, batch)

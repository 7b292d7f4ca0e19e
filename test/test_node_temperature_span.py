"""The correction node and the temperatures its calibration was made at, over DDS.

``span``: a correction node loaded with a calibration made at the surface (18.2..19.0 C, no temperature
terms) that records them (``<name>.calibration_temperatures``): it hears ``<name>/temperature`` without
making any set wait, and when mag2 dives 16 K colder counts mag2's sets on ``/diagnostics``
(``mag2.temperature_beyond_calibration``), warns in that status period naming mag2, and logs one WARN
line, not one per set. ``old``: the same calibration from a file without the key: no key, nothing said.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np
import pytest
import ros_harness as h
from diagnostic_msgs.msg import DiagnosticStatus

from magcal_ros.app.ros_driver import ArrayDriver, recording_messages, status_values
from magcal_ros.core.recording import Recording
from magcal_ros.io import calibration_file as calfile
from magcal_ros.sim.spec import SimulationSpec, run

pytestmark = pytest.mark.dds

SPAN = "/span/magcal_correction"
OLD = "/old/magcal_correction"
SURFACE = (18.2, 19.0)
LEAD = 50
"""Sets by which the temperatures lead the raw sets in a replay."""


@pytest.fixture(scope="module")
def data() -> tuple[Recording, Any]:
    rec, truth, _ = run(SimulationSpec(count=120, seed=8, noise=h.NOISE))
    span = np.tile(SURFACE, (len(rec.names), 1))
    cal = type(truth.calibration)(truth.calibration.geometry, truth.calibration.matrices, truth.calibration.offsets,
                                  temperature_span=span)
    return rec, cal


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, data: tuple[Recording, Any]) -> Any:
    workdir = tmp_path_factory.mktemp("span")
    runner = h.RosRun(workdir, domain_id=h.pick_domain_id(seed=os.getpid() + 97))
    fast = {"status_period": 0.25, "sensor_timeout": 0.5, "output_timeout": 1.5}
    _, cal = data
    try:
        for ns, key in (("span", SPAN), ("old", OLD)):
            text = calfile.dumps(cal, node_name=key)
            if ns == "old":  # a file from before the key existed
                text = "\n".join(line for line in text.splitlines() if "calibration_temperatures" not in line) + "\n"
            path = workdir / f"{ns}.yaml"
            path.write_text(text)
            runner.start("correction_node", params=dict(fast, **h.LOSSLESS), params_files=[path], namespace=ns,
                         log_name=f"{ns}_correction")
        yield runner
    finally:
        codes = runner.close()
        assert codes and all(c == 0 for c in codes.values()), codes


def _replay(d: ArrayDriver, rec: Recording, temperatures: np.ndarray) -> dict[int, int]:
    return d.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE, current_lead=LEAD,
                    temperatures=temperatures)


def _driver(world: h.RosRun, rec: Recording, namespace: str) -> ArrayDriver:
    d = world.driver(rec.names, namespace=namespace, temperatures=True)
    assert d.wait_for_subscribers(1, h.DISCOVERY_TIMEOUT) and d.wait_for_output_publishers(h.DISCOVERY_TIMEOUT)
    deadline = time.monotonic() + h.DISCOVERY_TIMEOUT
    while not all(p.get_subscription_count() >= 1 for p in d.temperature_publishers):
        assert time.monotonic() < deadline, "temperature topics not matched"
        time.sleep(0.05)
    return d


def test_the_node_counts_and_warns_once_when_a_sensor_leaves_the_calibrated_temperatures(
        world: h.RosRun, data: tuple[Recording, Any]) -> None:
    rec, _ = data
    d = _driver(world, rec, "span")
    warm_rec, cold_rec = rec.take(np.arange(60)), rec.take(np.arange(60, 120))
    warm = np.full((60, 4), 18.6)
    mapping = _replay(d, warm_rec, warm)
    assert d.wait_for_outputs([mapping[int(t)] for t in warm_rec.stamps], timeout=60.0) >= 55  # no set waits
    status = d.diagnostics(SPAN, lambda s: "mag1.temperature_beyond_calibration" in status_values(s), 30.0)
    assert status is not None, "no calibration temperature keys on /diagnostics"
    values = status_values(status)
    assert values["mag1.calibration_temperatures_C"] == "18.2..19.0"
    assert all(values[f"{n}.temperature_beyond_calibration"] == "0" for n in rec.names)

    cold = warm.copy()
    cold[:, 1] = SURFACE[0] - 16.0  # mag2 16 K below
    _replay(d, cold_rec, cold)
    key = "mag2.temperature_beyond_calibration"

    def counted(s: DiagnosticStatus) -> bool:
        return int(status_values(s).get(key, 0)) >= 55

    status = d.diagnostics(SPAN, counted, 60.0)
    assert status is not None, "mag2's sets beyond the calibrated temperatures were not counted"
    values = status_values(status)
    assert int(values[key]) <= 60
    assert float(values["mag2.temperature_beyond_calibration_K"]) == pytest.approx(16.0, abs=0.01)
    assert all(values[f"{n}.temperature_beyond_calibration"] == "0" for n in ("mag1", "mag3", "mag4"))
    log = next(p for p in world.processes if p.log_path.stem == "span_correction").log()
    assert log.count("beyond the temperatures the calibration was made at") == 1, log
    assert "mag2 at 2.2 C (calibrated at 18.2..19.0 C)" in log


def test_a_file_without_the_key_says_nothing(world: h.RosRun, data: tuple[Recording, Any]) -> None:
    rec, _ = data
    d = _driver_without_temperatures(world, rec)
    mapping = d.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE)
    assert d.wait_for_outputs([mapping[int(t)] for t in rec.stamps], timeout=60.0) >= 0.9 * len(rec)
    status = d.diagnostics(OLD, lambda s: int(status_values(s).get("published", 0)) >= 0.9 * len(rec), 30.0)
    assert status is not None
    assert not any("calibration" in k and "temperature" in k for k in status_values(status)), status_values(status)
    log = next(p for p in world.processes if p.log_path.stem == "old_correction").log()
    assert "beyond the temperatures" not in log


def _driver_without_temperatures(world: h.RosRun, rec: Recording) -> ArrayDriver:
    d = world.driver(rec.names, namespace="old")
    assert d.wait_for_subscribers(1, h.DISCOVERY_TIMEOUT) and d.wait_for_output_publishers(h.DISCOVERY_TIMEOUT)
    return d

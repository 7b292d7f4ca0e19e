"""The calibration node through a mission's worth of use: ~/start, a prior change and ~/calibrate, again and
again, with the sensors streaming all the while and two busy loops on the machine.

Both nodes run as processes on a private domain. Each cycle asserts progress: the collection restarted,
the prior taken, an analysis of this collection with this prior reported on ``~/progress`` by the analysis
process (its count going up on ``/diagnostics``, never restarted), a calibration solved, applied and written,
and a second ``~/calibrate`` at once answered ``unchanged`` although sets kept coming. CI runs
:data:`CYCLES` cycles; ``MAGCAL_CYCLES=100`` runs the benchmark (the time is printed: ``pytest -s``).

The same world also holds the tests of the calibration node's answers in a mission: "TMI before" with a
running prior, one hardware_id for both nodes, a prior file that does not exist, a parameter it does not have.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ros_harness as h
from diagnostic_msgs.msg import DiagnosticStatus

from magcal_ros.api import save_calibration
from magcal_ros.app.ros_driver import ArrayDriver, RawMessage, status_values
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tmi_rms

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

CYCLES = int(os.environ.get("MAGCAL_CYCLES", "4"))
"""Cycles of start / prior / calibrate (the benchmark: MAGCAL_CYCLES=100)."""
RATE = 100.0
"""Sets per second the sensors stream."""
MIN_SETS = 150
"""Sets each collection holds before ~/calibrate."""
CALIBRATION = f"/{h.CALIBRATION}"
CORRECTION = f"/{h.CORRECTION}"
ANALYSIS = f"{CALIBRATION}: analysis"
NAMES = h.NAMES


class Stream:
    """The sensors: sets of a manoeuvre (random attitudes, cycling) at :data:`RATE`, stamped from now on, from a
    thread of their own until :meth:`stop`."""

    def __init__(self, driver: ArrayDriver, vectors: np.ndarray) -> None:
        self.driver, self.vectors = driver, vectors
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sensors", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        start, period = time.time_ns(), int(1e9 / RATE)
        began = time.monotonic()
        while not self._stop.is_set():
            k = self.sent
            for name, v in zip(NAMES, self.vectors[k % len(self.vectors)]):
                self.driver.publish(RawMessage(name, start + k * period, (float(v[0]), float(v[1]), float(v[2]))))
            self.sent += 1
            lag = began + self.sent / RATE - time.monotonic()
            if lag > 0:
                time.sleep(lag)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(30.0)


@contextlib.contextmanager
def busy_loops(count: int = 2) -> Iterator[list[int]]:
    """``( while :; do :; done ) &`` ``count`` times: processes that take a whole core each; killed after."""
    procs = [subprocess.Popen(["bash", "-c", "while :; do :; done"]) for _ in range(count)]
    try:
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            p.kill()
            p.wait(10.0)


@pytest.fixture(scope="module")
def data() -> h.Data:
    return h.make_data()


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, data: h.Data) -> Iterator[dict[str, Any]]:
    workdir = tmp_path_factory.mktemp("cycles")
    run = h.RosRun(workdir, domain_id=h.pick_domain_id(seed=os.getpid() + 61))
    output = workdir / "calibration.yaml"
    stream = None
    try:
        run.start("correction_node", params={**h.UNCORRECTED, "status_period": 0.25}, log_name="correction")
        run.start("calibration_node", log_name="calibration", params={
            "reference_field": h.INTENSITY, "calibration_file": str(output), "service_timeout": h.SERVICE_TIMEOUT,
            "max_samples": 300, "progress_period": 0.25, "assess_period": 0.25, "analysis_timeout": 600.0,
            "prior": "none"})
        driver = run.driver(NAMES)
        h.wait_discovered(driver, subscribers=2)
        driver.watch_diagnostics()
        stream = Stream(driver, data.manoeuvre.vectors)
        yield {"run": run, "driver": driver, "output": output, "stream": stream, "workdir": workdir}
    finally:
        if stream is not None:
            stream.stop()
        logs = {p.log_path.stem: p.log() for p in run.processes}
        codes = run.close()
        assert codes == {"correction": 0, "calibration": 0}, codes
        assert not any("Traceback" in text for text in logs.values()), logs


def _progress(driver: ArrayDriver, predicate: Any, timeout: float = h.SAMPLES_TIMEOUT) -> dict[str, str]:
    seen: dict[str, str] = {}

    def check(msg: DiagnosticStatus) -> bool:
        seen.clear()
        seen.update(status_values(msg))
        return bool(predicate(seen))

    got = driver.wait_for_message(DiagnosticStatus, f"{CALIBRATION}/progress", check, timeout)
    assert got is not None, f"~/progress never satisfied the condition within {timeout} s: {seen}"
    return seen


def _analysis(driver: ArrayDriver, predicate: Any = None, timeout: float = 120.0) -> dict[str, str]:
    status = driver.diagnostics(ANALYSIS, predicate, timeout)
    assert status is not None, f"no {ANALYSIS} status on /diagnostics within {timeout} s"
    return status_values(status)


def _collect(driver: ArrayDriver, prior: str) -> dict[str, str]:
    """~/start, set ``prior``, and wait for an analysis of this collection with it over at least MIN_SETS sets."""
    ok, message = driver.trigger(f"{CALIBRATION}/start")
    assert ok, message
    (ok, reason), = driver.set_parameters(CALIBRATION, {"prior": prior})
    assert ok, reason
    expected = "none" if prior == "none" else "the running calibration"

    def analysed(v: dict[str, str]) -> bool:
        return int(v.get("assessed", "0")) >= MIN_SETS and v.get("prior", "").startswith(expected)

    return _progress(driver, analysed)


def test_start_prior_change_and_calibrate_again_and_again_beside_two_busy_loops(world: dict[str, Any]) -> None:
    driver: ArrayDriver = world["driver"]
    output: Path = world["output"]
    durations: list[float] = []
    with busy_loops(2):
        began = time.monotonic()
        for cycle in range(CYCLES):
            t0 = time.monotonic()
            before = _analysis(driver)
            prior = "none" if cycle % 2 == 0 else "running"
            progress = _collect(driver, prior)
            sent = world["stream"].sent
            ok, message = driver.trigger(f"{CALIBRATION}/calibrate")
            assert ok and message.startswith("calibrated 4 sensors"), (cycle, message)
            text = output.read_text()
            ok, again = driver.trigger(f"{CALIBRATION}/calibrate")
            assert ok and again.startswith("unchanged"), (cycle, again)
            assert output.read_text() == text
            assert world["stream"].sent > sent, "the sensors stopped streaming"
            after = _analysis(driver, lambda s, n=int(before["analyses"]): int(status_values(s)["analyses"]) > n)
            assert after["restarts"] == "0" and after["timeouts"] == "0", after
            assert int(progress["samples"]) >= MIN_SETS
            durations.append(time.monotonic() - t0)
        total = time.monotonic() - began
    print(f"\n{CYCLES} cycles of start / prior change / calibrate in {total:.1f} s (per cycle: min "
          f"{min(durations):.1f}, median {float(np.median(durations)):.1f}, max {max(durations):.1f} s)")
    assert all(p.alive() for p in world["run"].processes)


def test_a_second_calibrate_while_the_sensors_stream_answers_unchanged(world: dict[str, Any]) -> None:
    """Sets keep coming while the first ~/calibrate solves: they are not part of the calibration in force, so
    the second call finds the same sets and settings and neither solves, applies nor writes anything."""
    driver: ArrayDriver = world["driver"]
    _collect(driver, "none")
    seen = _progress(driver, lambda v: True)
    ok, message = driver.trigger(f"{CALIBRATION}/calibrate")
    assert ok, message
    text, solves = world["output"].read_text(), _log(world, "calibration").count("solving from")
    during = _progress(driver, lambda v: True)
    assert int(during["offered"]) > int(seen["offered"]), "no set arrived during the solve: nothing was tested"
    ok, again = driver.trigger(f"{CALIBRATION}/calibrate")
    assert ok and again.startswith("unchanged"), again
    assert world["output"].read_text() == text
    assert _log(world, "calibration").count("solving from") == solves


def _log(world: dict[str, Any], name: str) -> str:
    return next(p for p in world["run"].processes if p.log_path.stem == name).log()


def _running(driver: ArrayDriver) -> ArrayCalibration:
    names = ["sensor_names", "positions"] + [f"{n}.{s}" for n in NAMES for s in ("matrix", "offset")]
    params = driver.get_parameters(CORRECTION, names)
    nested: dict[str, Any] = {"sensor_names": params["sensor_names"], "positions": params["positions"]}
    for name in NAMES:
        nested[name] = {"matrix": params[f"{name}.matrix"], "offset": params[f"{name}.offset"]}
    return ArrayCalibration.from_parameters(nested)


def test_tmi_before_with_a_running_prior_is_the_running_calibrations(world: dict[str, Any], data: h.Data) -> None:
    """With the running calibration as the prior, "TMI RMS before -> after" starts from what that calibration
    gives on the collected sets (about the 1 nT noise here), not from the raw readings (thousands of nT)."""
    from truth_tools import summary_numbers

    driver: ArrayDriver = world["driver"]
    _collect(driver, "none")
    ok, message = driver.trigger(f"{CALIBRATION}/calibrate")
    assert ok, message
    running = _running(driver)
    _collect(driver, "running")
    ok, message = driver.trigger(f"{CALIBRATION}/calibrate")
    assert ok and "prior: the running calibration of /magcal_correction" in message, message
    got = summary_numbers(message)
    raw = data.manoeuvre.vectors
    expected = float(np.max(tmi_rms(running.apply(raw), h.INTENSITY))) / 1e-9
    assert got["tmi_before"] == pytest.approx(expected, rel=0.25), (got, expected)
    assert got["tmi_before"] < 0.01 * float(np.max(tmi_rms(raw, h.INTENSITY))) / 1e-9


def test_every_status_of_both_nodes_carries_the_arrays_hardware_id(world: dict[str, Any]) -> None:
    """rqt_robot_monitor groups by hardware_id: every status both nodes put on /diagnostics names the same array,
    its sensors as resolved (so another namespace's array stays apart)."""
    driver: ArrayDriver = world["driver"]
    names = [CORRECTION, f"{CORRECTION}: calibration", CALIBRATION, f"{CALIBRATION}: recalibration", ANALYSIS]
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline and not all(driver.status(n) is not None for n in names):
        time.sleep(0.1)
    ids = {n: driver.status(n).hardware_id for n in names if driver.status(n) is not None}
    assert set(ids) == set(names) and set(ids.values()) == {"/mag1,/mag2,/mag3,/mag4"}, ids


def test_a_prior_file_that_cannot_be_read_is_refused_when_set(world: dict[str, Any]) -> None:
    driver: ArrayDriver = world["driver"]
    missing = world["workdir"] / "no_such_calibration.yaml"
    (ok, reason), = driver.set_parameters(CALIBRATION, {"prior": str(missing)})
    assert not ok and f"prior '{missing}'" in reason and "does not exist" in reason, reason
    own = world["workdir"] / "prior_calibration.yaml"  # (not the node's output: no test before need have written it)
    save_calibration(own, ArrayCalibration.identity(ArrayGeometry.cross(h.BASELINE)))
    (ok, reason), = driver.set_parameters(CALIBRATION, {"prior": str(own)})  # a calibration file: fine
    assert ok, reason
    assert driver.get_parameters(CALIBRATION, ["prior"])["prior"] == str(own)
    assert driver.set_parameters(CALIBRATION, {"prior": "none"})[0][0]


def test_a_parameter_the_calibration_node_does_not_have_is_named_in_the_refusal(world: dict[str, Any]) -> None:
    driver: ArrayDriver = world["driver"]
    for atomic in (True, False):
        (ok, reason), = driver.set_parameters(CALIBRATION, {"max_sampels": 300}, atomic=atomic)
        assert not ok and "unknown parameter 'max_sampels'" in reason and CALIBRATION in reason, reason

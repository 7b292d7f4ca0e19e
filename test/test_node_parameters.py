"""The nodes' parameters as the ROS tools use them: ``ros2 param dump``, ``load``, ``get``, ``describe``
and ``set``, ``--params-file`` with a dump or a saved calibration, and names that are not ROS names.

There is no ``ros2`` command here, so each test does what the command does (ros2param's own
steps): list_parameters, then get_parameters of every name in one request, printed with
``yaml.dump`` (dump); rclpy's ``parameter_dict_from_yaml_file`` of the whole file, then
set_parameters (load); rcl's parser (``--params-file``). The nodes run in this process, their
parameter services reached through rclpy's parameter client over a private ROS domain.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rcl_interfaces.msg import ParameterType
from test_offline import magcal, ok

from magcal_ros.app.ros_driver import isolate_this_process, pick_domain_id
from magcal_ros.io import calibration_file as calfile

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

NAMES = ["mag1", "mag2", "mag3", "mag4"]


class InProcess:
    """A private ROS context in this process: nodes spun by a background executor, a parameter client."""

    def __init__(self, args: list[str]) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor

        domain = pick_domain_id(os.getpid() + 41)
        isolate_this_process(domain)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain, args=["test", "--ros-args", *args])
        self.client_node = rclpy.create_node("param_tool", context=self.context)
        self.executor = MultiThreadedExecutor(context=self.context)
        self.executor.add_node(self.client_node)
        self.nodes: list[Any] = []
        self._clients: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        with contextlib.suppress(Exception):
            self.executor.spin()

    def add(self, node: Any) -> Any:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def client(self, target: str) -> Any:
        from rclpy.parameter_client import AsyncParameterClient

        if target not in self._clients:
            self._clients[target] = AsyncParameterClient(self.client_node, target)
        client = self._clients[target]
        assert client.wait_for_services(timeout_sec=60.0), f"{target}'s parameter services not found"
        return client

    @staticmethod
    def wait(future: Any, timeout: float = 120.0) -> Any:
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(timeout), "no answer from the parameter service"
        return future.result()

    def close(self) -> None:
        import rclpy

        for node in self.nodes:
            if hasattr(node, "close"):
                node.close()
        self.executor.shutdown(timeout_sec=5.0)
        for node in self.nodes:
            node.destroy_node()
        self.client_node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@contextlib.contextmanager
def in_process(*args: str) -> Iterator[InProcess]:
    run = InProcess(list(args))
    try:
        yield run
    finally:
        run.close()


def dump(run: InProcess, target: str) -> dict[str, Any]:
    """What ``ros2 param dump TARGET`` prints, parsed: names listed, then all values in one request."""
    from rclpy.parameter import parameter_value_to_python

    client = run.client(target)
    names = sorted(run.wait(client.list_parameters()).result.names)
    values = run.wait(client.get_parameters(names)).values
    assert len(values) == len(names), "get_parameters of every listed name failed as a whole"
    params: dict[str, Any] = {}
    for name, value in zip(names, values):
        assert value.type != ParameterType.PARAMETER_NOT_SET, f"{name} has no value"
        node = params
        parts = name.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = parameter_value_to_python(value)
    return {target: {"ros__parameters": params}}


def load(run: InProcess, target: str, path: Path) -> list[tuple[str, bool, str]]:
    """What ``ros2 param load TARGET FILE`` does: every block of the file, set one by one."""
    from rclpy.parameter import parameter_dict_from_yaml_file

    params = list(parameter_dict_from_yaml_file(str(path), False).values())
    results = run.wait(run.client(target).set_parameters(params)).results
    return [(p.name, r.successful, r.reason) for p, r in zip(params, results)]


def flat(block: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in block.items():
        if isinstance(value, dict):
            out.update(flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _make(kind: str, run: InProcess, **kwargs: Any) -> Any:
    from magcal_ros.nodes.calibration_node import CalibrationNode
    from magcal_ros.nodes.correction_node import CorrectionNode

    node = CorrectionNode(context=run.context, **kwargs) if kind == "correction" else \
        CalibrationNode(context=run.context, **kwargs)
    return run.add(node)


@pytest.mark.parametrize("kind", ["correction", "calibration"])
def test_dump_has_every_parameter_and_round_trips_through_load_and_params_file(kind: str, tmp_path: Path) -> None:
    target = "/magcal_correction" if kind == "correction" else "/magcal_calibration"
    # (not date: rclpy re-reads a YYYY-MM-DD string as a date object and ros2 param load fails on it)
    extra = ["-p", "site:=[43.2, 5.4]", "-p", "max_residual:=5e-09"] if kind == "calibration" else \
        ["-p", "mag1.offset:=[5e-08, -1e-07, 2e-05]", "-p", "mag1.matrix:=[1.0,0.0,0.0,0.0,1.0,0.0,0.0,0.0,1.0]"]
    with in_process(*extra) as run:
        node = _make(kind, run)
        listed = set(node.list_parameters([], 0).names)
        first = dump(run, target)
        values = flat(first[target]["ros__parameters"])
        assert set(values) == listed
        for name in ("interference_channels", "interference_topics", "interference_types"):
            assert values[name] == []
        if kind == "correction":
            assert values["uncorrected_sensors"] == [] and values["mag2.interference"] == []
        else:
            assert values["site"] == [43.2, 5.4]
        described = run.wait(run.client(target).describe_parameters(sorted(listed))).descriptors
        assert len(described) == len(listed) and all(d.description for d in described if d.name != "use_sim_time"
                                                      and d.name != "start_type_description_service")
        path = tmp_path / "dump.yaml"
        path.write_text(yaml.dump(first, default_flow_style=False))  # as ros2 param dump prints it
        results = load(run, target, path)
        refused = [(n, why) for n, good, why in results if not good]
        read_only = {d.name for d in described if d.read_only}
        assert all(n in read_only and "read-only" in why for n, why in refused), refused
        assert dump(run, target) == first
    with in_process("--params-file", str(path)) as run:  # a fresh node from the dump
        _make(kind, run)
        again = flat(dump(run, target)[target]["ros__parameters"])
        assert again == values


def test_a_saved_calibration_loads_with_ros2_param_load_and_params_file(tmp_path: Path) -> None:
    """Real provenance strings (created, summary, warnings) are read a second time as YAML by rclpy."""
    rec, cal = tmp_path / "rot.csv", tmp_path / "cal.yaml"
    ok(magcal("simulate", rec, "--count", 300, "--seed", 3, "-q"))
    ok(magcal("calibrate", rec, "-o", cal, "--reference-field", 5.15e-5, "-q"))
    saved = calfile.read(cal)
    prov = yaml.safe_load(cal.read_text())["magcal_provenance"]["ros__parameters"]
    assert ": " in prov["summary"].replace("\u00a0", " ") and prov["created"].startswith("20")
    from rclpy.parameter import parameter_dict_from_yaml_file, parameter_value_to_python

    every = parameter_dict_from_yaml_file(str(cal), False)  # what ros2 param load reads
    for key in ("created", "summary", "method", "source"):
        assert parameter_value_to_python(every[key].value) == prov[key]  # the same text as PyYAML reads
    with in_process() as run:
        node = _make("correction", run)
        results = load(run, "/magcal_correction", cal)
        mine = {n for n in every if n in ("sensor_names", "positions", "calibration_intensity") or n.split(".")[0] in NAMES}
        assert all(good for n, good, _ in results if n in mine), results
        bad = [(n, why) for n, good, why in results if n not in mine and "magcal_provenance" not in why]
        assert not bad, bad
        state = node._state
        assert state.missing == ()
        np.testing.assert_array_equal(state.calibration.matrices, saved.matrices)
        np.testing.assert_array_equal(state.calibration.offsets, saved.offsets)
    with in_process("--params-file", str(cal)) as run:
        node = _make("correction", run)
        np.testing.assert_array_equal(node._state.calibration.matrices, saved.matrices)
        assert node._state.missing == ()


@pytest.mark.parametrize("bad", [["mag 1", "mag2", "mag3", "mag4"], ["../x", "mag2", "mag3", "mag4"],
                                 ["mag1", "mag2", "mag3", "/abs"]])
def test_sensor_names_that_are_not_ros_names_are_refused_and_the_node_keeps_its_state(bad: list[str]) -> None:
    from rclpy.parameter import Parameter

    with in_process("-p", f"uncorrected_sensors:={NAMES}") as run:
        correction, calibration = _make("correction", run), _make("calibration", run)
        for node in (correction, calibration):
            result = node.set_parameters([Parameter("sensor_names", value=bad)])[0]
            assert not result.successful and "is not a valid relative ROS name" in result.reason
            assert node.get_parameter("sensor_names").value == NAMES
        assert [s.topic_name for s in correction._subs] == [f"/{n}/raw" for n in NAMES]
        for name in ("bad name", "../x", "1abc"):
            result = calibration.set_parameters([Parameter("correction_node", value=name)])[0]
            assert not result.successful and "is not a valid ROS node name" in result.reason, result.reason
        assert calibration.get_parameter("correction_node").value == "magcal_correction"
        assert calibration._target_name() == "/magcal_correction"


def test_a_node_started_with_a_bad_name_says_why_in_one_line() -> None:
    from magcal_ros.errors import InputError

    with in_process("-p", "correction_node:=bad name") as run, pytest.raises(InputError, match="not a valid ROS node"):
        _make("calibration", run)
    with in_process("-p", "sensor_names:=[mag 1]") as run, pytest.raises(InputError, match="not a valid relative ROS"):
        _make("correction", run)


def test_the_correction_nodes_outputs_carry_no_qos_event_handlers_and_its_inputs_keep_theirs() -> None:
    """The executor polls every QoS event handler of the node each time it wakes (thousands of times a
    second at 4 x 1000 Hz): the outputs have none (a subscriber asking for more than they offer is warned
    by its own handler); the raw subscriptions keep rclpy's defaults (incompatible QoS and type)."""
    with in_process("-p", "uncorrected_sensors:=[mag1, mag2, mag3, mag4]") as run:
        node = _make("correction", run)
        ours = [p for p in node.publishers if p.topic_name not in ("/parameter_events", "/rosout")]
        names = {p.topic_name for p in ours}
        assert {"/mag1/corrected", "/mag4/corrected", "/field", "/gradient", "/gradient_stamped",
                "/magcal_correction/status", "/diagnostics"} <= names, names
        assert all(len(p.event_handlers) == 0 for p in ours), [(p.topic_name, len(p.event_handlers)) for p in ours]
        raw = [s for s in node.subscriptions if s.topic_name.endswith("/raw")]
        assert len(raw) == 4 and all(len(s.event_handlers) >= 2 for s in raw)


def test_health_factors_out_of_order_are_refused_at_start_and_at_param_set(tmp_path: Path) -> None:
    """A WARN above the ERROR it should come before: refused with the reason at start (the node does not start)
    and by ``ros2 param set`` (the factors are settable while the node runs: the health judges afresh with new
    ones, the window kept)."""
    from rclpy.parameter import Parameter

    from magcal_ros.errors import InputError

    args = ("-p", f"uncorrected_sensors:={NAMES}", "-p", "health_warn_factor:=40", "-p", "health_error_factor:=20.0")
    with in_process(*args) as run, pytest.raises(InputError, match="health_warn_factor 40 is above "
                                                                   "health_error_factor 20: a WARN must come"):
        _make("correction", run)
    from dataclasses import replace

    from magcal_ros.core.field import earth_field
    from magcal_ros.core.geometry import ArrayGeometry
    from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

    rng = np.random.default_rng(3)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(5.15e-5, 60.0, 5.0),
                          noise=1e-9)
    cal = tmp_path / "calibration.yaml"
    calfile.write(cal, replace(sim.true_calibration(), metadata={"noise": [1e-9] * 4, "intensity": 5.15e-5}))
    with in_process("--params-file", str(cal)) as run:
        node = _make("correction", run)
        client = run.client("/magcal_correction")
        health = node._health_cal
        assert health is not None and (health.thresholds.warn_factor, health.thresholds.error_factor) == (10.0, 30.0)
        for params, reason in (([Parameter("health_warn_factor", value=50.0)], "health_warn_factor 50 is above "
                                "health_error_factor 30"),
                               ([Parameter("health_error_factor", value=5)], "health_warn_factor 10 is above "
                                "health_error_factor 5"),
                               ([Parameter("health_warn_factor", value=0)], "health_warn_factor must be 1 .. 1e+06")):
            result = run.wait(client.set_parameters(params)).results[0]
            assert not result.successful and result.reason.startswith(reason), result.reason
        assert node.get_parameter("health_warn_factor").value == 10.0 and health.thresholds.warn_factor == 10.0
        for name, value in (("health_error_factor", 60.0), ("health_warn_factor", 50.0)):  # ros2 param set, twice
            result = run.wait(client.set_parameters([Parameter(name, value=value)])).results[0]
            assert result.successful, result.reason
        assert node._health_cal is health  # the same window
        assert (health.thresholds.warn_factor, health.thresholds.error_factor) == (50.0, 60.0)
        result = run.wait(client.set_parameters_atomically([Parameter("health_warn_factor", value=70.0),
                                                            Parameter("health_error_factor", value=80.0)])).result
        assert result.successful, result.reason  # both at once: judged together
        assert (node._drift_thresholds.warn_factor, health.thresholds.error_factor) == (70.0, 80.0)

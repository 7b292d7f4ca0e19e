"""Calibration service node: collect a rotation manoeuvre, solve, hand the result over.

Subscribes ``<name>/raw`` (sensor_msgs/MagneticField, T) like the correction node and,
while collecting, keeps up to ``max_samples`` synchronized sets spread over the
attitudes. Services (std_srvs/srv/Trigger):

- ``~/start``: forget collected sets and start collecting;
- ``~/calibrate``: solve with the core (:func:`magcal_ros.methods.pipeline.calibrate_array`),
  set the result on the running correction node through its
  ``set_parameters_atomically`` service (all or nothing), then write the calibration
  file (atomic, previous file kept as ``.bak``); answers the one-line summary, or
  ``success: false`` with the reason and what to do, having changed nothing;
- ``~/reset``: drop collected sets (and stop collecting).

``~/progress`` (diagnostic_msgs/DiagnosticStatus, every ``progress_period`` s): level OK
when a solve would pass the observability checks, WARN when not yet (message says why),
values ``collecting``, ``samples``, ``max_samples``, ``offered``, ``coverage`` (fraction
of 42 sphere cells), ``thickness`` (thinnest/widest spread, ~0 for one rotation axis),
``ready`` and ``problem``.

Usage::

    ros2 run magcal_ros calibration_node --ros-args -p reference_field:=5.15e-5
    ros2 service call /magcal_calibration/start std_srvs/srv/Trigger
    # ... rotate the array about at least two axes ...
    ros2 service call /magcal_calibration/calibrate std_srvs/srv/Trigger
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rcl_interfaces.srv import GetParameters, SetParametersAtomically
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.task import Future
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger

from magcal_ros.core import sync
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.observability import excitation
from magcal_ros.core.sync import SetSynchronizer
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import topics
from magcal_ros.methods.pipeline import (
    DEFAULT_METHOD,
    METHODS,
    CalibrationResult,
    SolveOptions,
    calibrate_array,
)
from magcal_ros.nodes import common
from magcal_ros.nodes.buffer import SetBuffer

NODE_NAME = "magcal_calibration"
DEFAULT_CALIBRATION_FILE = "~/.ros/magcal_calibration.yaml"
WHAT_TO_DO = "call ~/start, turn the array through large angles about at least two axes, then call ~/calibrate"


class CallFailed(Exception):
    """A service call to the correction node did not complete."""


class CalibrationNode(Node):
    """Collects synchronized raw sets and solves the array calibration on request."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.Lock()
        self._solve_lock = threading.Lock()
        self._declare_parameters()
        try:
            self._geometry = self._read_geometry({})
        except (TypeError, ValueError) as exc:
            raise InputError(f"invalid parameter: {exc}") from None
        self._collecting = bool(self.get_parameter("autostart").value)
        depth = int(self.get_parameter("qos_depth").value)
        self._raw_qos = common.raw_qos(str(self.get_parameter("raw_reliability").value), depth)
        self._calibrate_group = ReentrantCallbackGroup()
        self._wake = self.create_guard_condition(lambda: None)
        self._subs: list[Any] = []
        self._connect(self._geometry)
        self._progress_pub = self.create_publisher(DiagnosticStatus, "~/progress", 10)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/calibrate", self._on_calibrate, callback_group=self._calibrate_group)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self._target_clients: dict[str, tuple[Any, Any]] = {}
        self._service_clients()
        self._drops = common.DropReporter(self.get_logger())
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self.create_timer(max(float(self.get_parameter("progress_period").value), 0.05), self._publish_progress)
        self.get_logger().info(
            f"listening to {', '.join(topics.raw(n) for n in self._geometry.names)}; "
            f"{'collecting' if self._collecting else 'idle: call ~/start to collect'}; "
            f"method {self.get_parameter('method').value}, results go to "
            f"/{self._target().lstrip('/')} and {self._calibration_path() or '(no file)'}"
        )

    # -- parameters -----------------------------------------------------------------
    def _declare_parameters(self) -> None:
        d = common.describe
        self.declare_parameter("sensor_names", common.DEFAULT_SENSOR_NAMES, d(common.SENSOR_NAMES_DOC))
        self.declare_parameter("positions", common.DEFAULT_POSITIONS, d(common.POSITIONS_DOC, numbers=True))
        self.declare_parameter(
            "reference_field", 0.0,
            d("total field intensity during the manoeuvre (T); 0 = unknown: relative calibration "
              "(methods ml and paired only)", numbers=True),
        )
        self.declare_parameter(
            "method", DEFAULT_METHOD,
            d("calibration method: " + "; ".join(f"{m.name} ({m.source})" for m in METHODS.values()),
              constraints=" | ".join(METHODS)),
        )
        self.declare_parameter(
            "calibration_file", DEFAULT_CALIBRATION_FILE,
            d("calibration file written on success (ROS 2 params file for the correction node; "
              "previous one kept as .bak); empty = do not write"),
        )
        self.declare_parameter(
            "correction_node", "magcal_correction",
            d("name of the running correction node that receives the calibration"),
        )
        self.declare_parameter(
            "max_samples", 2000,
            d("most synchronized sets kept; when full, sets of the most visited attitudes are replaced"),
        )
        self.declare_parameter(
            "sync_tolerance", sync.DEFAULT_SYNC_TOLERANCE,
            d("largest spread (s) of header stamps within one set", numbers=True),
        )
        self.declare_parameter("autostart", False, d("collect from start-up without calling ~/start", read_only=True))
        self.declare_parameter(
            "service_timeout", 5.0, d("how long (s) to wait for the correction node's services", numbers=True)
        )
        self.declare_parameter("progress_period", 1.0, d("period (s) of ~/progress", read_only=True))
        self.declare_parameter("raw_reliability", "best_effort", d(common.RELIABILITY_DOC, read_only=True))
        self.declare_parameter("qos_depth", 100, d("history depth of the raw subscriptions", read_only=True))

    def _value(self, name: str, updates: dict[str, Any]) -> Any:
        return updates[name] if name in updates else self.get_parameter(name).value

    def _number(self, name: str, updates: dict[str, Any]) -> float:
        value = self._value(name, updates)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{name} must be a number, got {value!r}")
        return float(value)

    def _read_geometry(self, updates: dict[str, Any]) -> ArrayGeometry:
        """Validate the combined parameter state; return the array geometry."""
        geo = common.geometry(self._value("sensor_names", updates), self._value("positions", updates))
        method = self._value("method", updates)
        if method not in METHODS:
            raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        ref = self._number("reference_field", updates)
        if not (ref == 0.0 or 1e-7 <= ref <= 1e-3):
            raise InputError(f"reference_field {ref} T is not Earth-like (1e-7 .. 1e-3 T, or 0 for relative)")
        if int(self._value("max_samples", updates)) < 20:
            raise InputError("max_samples must be at least 20")
        common.tolerance_ns(self._number("sync_tolerance", updates))
        if self._number("service_timeout", updates) <= 0:
            raise InputError("service_timeout must be > 0 s")
        if not str(self._value("correction_node", updates)).strip("/"):
            raise InputError("correction_node must name a node")
        return geo

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for p in params:
            why = common.check_number_array(p) if p.name == "positions" else None
            if why:
                return SetParametersResult(successful=False, reason=why)
        try:
            self._read_geometry({p.name: p.value for p in params})
        except (InputError, TypeError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        names = {p.name for p in params}
        if "correction_node" in names:
            self._service_clients()
        if names & {"sensor_names", "positions", "max_samples", "sync_tolerance"}:
            with self._lock:
                self._disconnect()
                self._geometry = self._read_geometry({})
                self._connect(self._geometry)
            self._drops.reset()
            self.get_logger().info(f"reconfigured ({', '.join(sorted(names))}): collected sets dropped")

    # -- collecting -----------------------------------------------------------------
    def _connect(self, geo: ArrayGeometry) -> None:
        self._sync = SetSynchronizer(geo.size, common.tolerance_ns(self.get_parameter("sync_tolerance").value))
        self._buffer = SetBuffer(int(self.get_parameter("max_samples").value), geo.size)
        self._subs = [
            self.create_subscription(
                MagneticField, topics.raw(n), self._raw_callback(i), self._raw_qos
            )
            for i, n in enumerate(geo.names)
        ]

    def _disconnect(self) -> None:
        for s in self._subs:
            self.destroy_subscription(s)
        self._subs = []

    def _raw_callback(self, index: int) -> Any:
        def callback(msg: MagneticField) -> None:
            st = msg.header.stamp
            f = msg.magnetic_field
            with self._lock:
                synced = self._sync.add(index, common.stamp_ns(st), f.x, f.y, f.z)
                if synced is not None and self._collecting:
                    self._buffer.add(synced.stamp, synced.values)

        return callback

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self._buffer.clear()
            self._collecting = True
        response.success = True
        response.message = (
            f"collecting up to {self._buffer.capacity} sets from {', '.join(self._geometry.names)}: "
            "turn the array through large angles about at least two axes, then call ~/calibrate"
        )
        self.get_logger().info(response.message)
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            dropped = len(self._buffer)
            self._buffer.clear()
            self._collecting = False
        response.success = True
        response.message = f"dropped {dropped} collected sets; call ~/start to collect again"
        self.get_logger().info(response.message)
        return response

    def _publish_progress(self) -> None:
        with self._lock:
            _, raw = self._buffer.snapshot()
            collecting, offered, capacity = self._collecting, self._buffer.offered, self._buffer.capacity
            stats = self._sync.stats.as_dict()
        self._drops.update(stats, f"{stats['sets']} complete sets")
        exc = excitation(raw.mean(axis=1)) if len(raw) else excitation(np.zeros((0, 3)))
        problem = exc.problem()
        values = {
            "collecting": str(collecting).lower(),
            "samples": str(len(raw)),
            "max_samples": str(capacity),
            "offered": str(offered),
            "coverage": f"{exc.coverage:.3f}",
            "thickness": f"{exc.thickness:.3f}",
            "ready": str(problem is None).lower(),
            "problem": problem or "",
            "unmatched": str(stats["unmatched"]),
            "bad_samples": str(stats["nonfinite"] + stats["out_of_order"] + stats["duplicate"] + stats["zero_stamp"]),
        }
        if problem is None:
            message = f"ready: {len(raw)} sets, coverage {exc.coverage:.0%}; call ~/calibrate"
        elif not collecting and not len(raw):
            message = "idle: call ~/start to collect"
        else:
            message = problem
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK if problem is None else DiagnosticStatus.WARN,
            name=self.get_fully_qualified_name(),
            message=message,
            hardware_id=",".join(self._geometry.names),
            values=[KeyValue(key=k, value=v) for k, v in values.items()],
        )
        self._progress_pub.publish(status)

    # -- calibrating ----------------------------------------------------------------
    async def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Solve and hand over in a worker thread; the executor keeps serving meanwhile."""
        if not self._solve_lock.acquire(blocking=False):
            response.success = False
            response.message = "a calibration is already running; wait for its answer"
            return response
        done: Future = Future()

        def work() -> None:
            try:
                outcome = self._calibrate()
            except Exception as exc:  # noqa: BLE001 - the service must answer, whatever happened
                outcome = (False, f"calibration failed unexpectedly ({type(exc).__name__}: {exc}); "
                                  "nothing was changed")
                self.get_logger().error(outcome[1])
            done.set_result(outcome)
            self._wake.trigger()

        threading.Thread(target=work, name="magcal-calibrate", daemon=True).start()
        try:
            response.success, response.message = await done
        finally:
            self._solve_lock.release()
        return response

    def _calibrate(self) -> tuple[bool, str]:
        with self._lock:
            _, raw = self._buffer.snapshot()
            geo = self._geometry
        if len(raw) == 0:
            return self._fail("no synchronized sets collected" + ("" if self._collecting else " (not collecting)")
                              + f"; {WHAT_TO_DO}")
        method = str(self.get_parameter("method").value)
        reference = float(self.get_parameter("reference_field").value) or None
        self.get_logger().info(f"solving from {len(raw)} sets (method {method})")
        try:
            result = calibrate_array(raw, geo, reference, method, SolveOptions())
        except MagcalError as exc:
            return self._fail(f"calibration not possible: {exc}; nothing was changed")
        path = self._calibration_path()
        if path:
            try:
                _check_writable(path)
            except OSError as exc:
                return self._fail(f"solved but cannot write {path}: {exc}; set calibration_file; nothing was changed")
        try:
            previous = self._get_target_parameters(result.calibration.geometry.names)
            self._push(result.calibration.to_parameters())
        except CallFailed as exc:
            return self._fail(f"solved but not applied: {exc}; nothing was changed")
        if path:
            try:
                calfile.write(path, result.calibration, node_name=self._file_key())
            except (OSError, MagcalError) as exc:
                rollback = "restored the previous calibration there"
                try:
                    self._push(previous, raw_messages=True)
                except CallFailed as again:
                    rollback = f"could NOT restore the previous calibration there ({again})"
                return self._fail(f"applied to {self._target()} but writing {path} failed ({exc}); {rollback}")
        with self._lock:
            self._collecting = False
        message = self._success_message(result, path)
        self.get_logger().info(message)
        return True, message

    def _success_message(self, result: CalibrationResult, path: str) -> str:
        where = f"applied to /{self._target().lstrip('/')}" + (f", written {path}" if path else ", no file written")
        return f"{result.summary()}; {where}"

    def _fail(self, message: str) -> tuple[bool, str]:
        self.get_logger().warn(message)
        return False, message

    def _calibration_path(self) -> str:
        text = str(self.get_parameter("calibration_file").value).strip()
        return os.path.expanduser(text) if text else ""

    def _target(self) -> str:
        return str(self.get_parameter("correction_node").value).strip()

    def _file_key(self) -> str:
        """Node key of the calibration file: the correction node's name, with its namespace if any."""
        target = self._target()
        if target.startswith("/") or self.get_namespace() == "/":
            return target
        return f"{self.get_namespace()}/{target}"

    def _service_clients(self) -> tuple[Any, Any]:
        target = self._target()
        if target not in self._target_clients:
            self._target_clients[target] = (
                self.create_client(SetParametersAtomically, f"{target}/set_parameters_atomically"),
                self.create_client(GetParameters, f"{target}/get_parameters"),
            )
        return self._target_clients[target]

    def _call(self, client: Any, request: Any) -> Any:
        """Call a service from the worker thread; the executor thread delivers the answer."""
        timeout = float(self.get_parameter("service_timeout").value)
        if not client.wait_for_service(timeout_sec=timeout):
            raise CallFailed(
                f"the correction node is not reachable ({client.srv_name} not available after {timeout:g} s); "
                f"start it (ros2 run magcal_ros correction_node) or set correction_node"
            )
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout) or future.result() is None:
            future.cancel()
            raise CallFailed(f"{client.srv_name} did not answer within {timeout:g} s")
        return future.result()

    def _get_target_parameters(self, names: Sequence[str]) -> list[ParameterMsg]:
        """The correction node's current calibration parameters, to restore if needed."""
        _, getter = self._service_clients()
        wanted = ["sensor_names", "positions"] + [f"{n}.{s}" for n in names for s in ("matrix", "offset")]
        reply = self._call(getter, GetParameters.Request(names=wanted))
        return [ParameterMsg(name=n, value=v) for n, v in zip(wanted, reply.values)
                if v.type != ParameterType.PARAMETER_NOT_SET]

    def _push(self, params: Any, raw_messages: bool = False) -> None:
        """Set the calibration on the correction node, all parameters at once."""
        setter, _ = self._service_clients()
        if raw_messages:
            msgs = list(params)
        else:
            msgs = [common.parameter_message(k, v) for k, v in common.flatten_parameters(params).items()]
        reply = self._call(setter, SetParametersAtomically.Request(parameters=msgs))
        if not reply.result.successful:
            raise CallFailed(f"{self._target()} rejected the calibration: {reply.result.reason}")


def _check_writable(path: str) -> None:
    """Raise OSError unless ``path``'s directory exists (or can be made) and is writable."""
    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
    if not os.access(parent, os.W_OK):
        raise PermissionError(f"directory {parent} is not writable")
    if os.path.isdir(path):
        raise IsADirectoryError(f"{path} is a directory")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ``ros2 run magcal_ros calibration_node``."""
    return common.run_node(CalibrationNode, SingleThreadedExecutor, args)


if __name__ == "__main__":
    raise SystemExit(main())

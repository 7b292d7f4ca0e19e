"""Calibration service node: collect a rotation manoeuvre, solve, hand the result over.

Subscribes ``<name>/raw`` (sensor_msgs/MagneticField, T) like the correction node and,
while collecting, keeps up to ``max_samples`` synchronized sets spread over the
attitudes. Services (std_srvs/srv/Trigger):

- ``~/start``: forget collected sets and start collecting;
- ``~/calibrate``: solve with the core (:func:`magcal_ros.methods.pipeline.calibrate_array`),
  write the calibration file (atomic; the previous file kept as a timestamped backup,
  the last ``backups``), then set the result on the running correction node through its
  ``set_parameters_atomically`` service (all or nothing); if that fails the previous
  file is put back, so the file and the running node never disagree and no set is ever
  corrected with a calibration that is then withdrawn. Answers the one-line summary, or
  ``success: false`` with the reason and what to do, having changed nothing. Called again
  on the same collected sets and settings it does not solve again and changes nothing
  (the answer says so);
- ``~/reset``: drop collected sets (and stop collecting).

``correction_node`` is a node name resolved like a topic: relative names live in this
node's namespace. The file's node key is the correction node's fully qualified name.

``~/progress`` (diagnostic_msgs/DiagnosticStatus, every ``progress_period`` s): level OK
when a solve would pass the observability checks, WARN when not yet (message says why),
values ``collecting``, ``samples``, ``max_samples``, ``offered``, ``coverage`` (fraction
of 42 sphere cells), ``thickness`` (thinnest/widest spread, ~0 for one rotation axis),
``ready`` and ``problem``. ``/diagnostics`` (DiagnosticArray, same period): the health of
the raw streams (silent or late sensors, drops, sets lost before the node, no complete
set for ``output_timeout``), as the correction node reports it.

Usage::

    ros2 run magcal_ros calibration_node --ros-args -p reference_field:=5.15e-5
    ros2 service call /magcal_calibration/start std_srvs/srv/Trigger
    # ... rotate the array about at least two axes ...
    ros2 service call /magcal_calibration/calibrate std_srvs/srv/Trigger
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
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
from magcal_ros.nodes.health import ArrayHealth

NODE_NAME = "magcal_calibration"
DEFAULT_CALIBRATION_FILE = "~/.ros/magcal_calibration.yaml"
WHAT_TO_DO = "call ~/start, turn the array through large angles about at least two axes, then call ~/calibrate"


class CallFailed(Exception):
    """A service call to the correction node did not complete."""

    def __init__(self, message: str, unknown_outcome: bool = False) -> None:
        super().__init__(message)
        self.unknown_outcome = unknown_outcome
        """The request went out but no answer came: the correction node may have applied it."""


class Stopping(CallFailed):
    """The node is shutting down: the calibration is abandoned."""

    def __init__(self) -> None:
        super().__init__("the calibration node is shutting down")


class CalibrationNode(Node):
    """Collects synchronized raw sets and solves the array calibration on request."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.Lock()
        self._solve_lock = threading.Lock()
        self._stopping = threading.Event()
        self._worker: threading.Thread | None = None
        self._last_solved: tuple[str, str] | None = None
        """(fingerprint of the sets and settings, answer) of the last successful calibration."""
        self._declare_parameters()
        self._limits = common.declare_health(self)
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
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, common.DIAGNOSTICS_TOPIC, 10)
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
            f"{self._target_name()} and {self._calibration_path() or '(no file)'}"
        )

    # -- parameters -----------------------------------------------------------------
    def _declare_parameters(self) -> None:
        d = common.describe
        self.declare_parameter("sensor_names", common.DEFAULT_SENSOR_NAMES, d(common.SENSOR_NAMES_DOC))
        self.declare_parameter("positions", common.DEFAULT_POSITIONS, d(common.POSITIONS_DOC, numbers=True))
        self.declare_parameter(
            "reference_field", 0.0,
            d("total field intensity during the manoeuvre (T); 0 = unknown: relative calibration "
              "(methods ml and paired only)", constraints="0, or 1e-7 .. 1e-3 T", numbers=True,
              floats=(0.0, 1e-3)),
        )
        self.declare_parameter(
            "method", DEFAULT_METHOD,
            d("calibration method: " + "; ".join(f"{m.name} ({m.source})" for m in METHODS.values()),
              constraints=" | ".join(METHODS)),
        )
        self.declare_parameter(
            "calibration_file", DEFAULT_CALIBRATION_FILE,
            d("calibration file written on success (ROS 2 params file for the correction node; previous "
              "files kept as <file>.<UTC time>.bak); empty = do not write"),
        )
        self.declare_parameter(
            "backups", calfile.DEFAULT_BACKUPS,
            d("previous calibration files kept beside calibration_file (newest first)", ints=(0, 100)),
        )
        self.declare_parameter(
            "correction_node", "magcal_correction",
            d("the running correction node that receives the calibration; a relative name is resolved in "
              "this node's namespace"),
        )
        self.declare_parameter(
            "max_samples", 2000,
            d("most synchronized sets kept; when full, sets of the most visited attitudes are replaced",
              ints=(20, 1_000_000)),
        )
        self.declare_parameter(
            "sync_tolerance", sync.DEFAULT_SYNC_TOLERANCE,
            d("largest spread (s) of header stamps within one set; capped at half the sample period",
              constraints="0 < t < 1", numbers=True, floats=common.TOLERANCE_RANGE),
        )
        self.declare_parameter("autostart", False, d("collect from start-up without calling ~/start", read_only=True))
        self.declare_parameter(
            "service_timeout", 5.0, d("how long (s) to wait for the correction node's services", numbers=True,
                                      floats=(0.01, 3600.0))
        )
        self.declare_parameter("progress_period", 1.0, d("period (s) of ~/progress and /diagnostics",
                                                         read_only=True, numbers=True, floats=common.PERIOD_RANGE))
        self.declare_parameter("raw_reliability", "best_effort", d(common.RELIABILITY_DOC, read_only=True))
        self.declare_parameter("qos_depth", 100, d("history depth of the raw subscriptions", read_only=True,
                                                   ints=common.QOS_DEPTH_RANGE))

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
                self._last_solved = None
            self._drops.reset()
            self.get_logger().info(f"reconfigured ({', '.join(sorted(names))}): collected sets dropped")

    # -- collecting -----------------------------------------------------------------
    def _connect(self, geo: ArrayGeometry) -> None:
        self._sync = SetSynchronizer(geo.size, common.tolerance_ns(self.get_parameter("sync_tolerance").value))
        self._health = ArrayHealth(geo.names, self._sync, self._limits, common.now_ns(self))
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
            stamp = common.stamp_ns(st)
            with self._lock:
                self._health.seen(index, stamp)
                synced = self._sync.add(index, stamp, f.x, f.y, f.z)
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
        now = common.now_ns(self)
        with self._lock:
            _, raw = self._buffer.snapshot()
            collecting, offered, capacity = self._collecting, self._buffer.offered, self._buffer.capacity
            stats = self._sync.stats.as_dict()
            stats["pending"] = self._sync.pending
            self._health.output(stats["sets"], now)
            health = self._health.assess(now, stats, "complete sets")
        self._drops.update(stats, f"{stats['sets']} complete sets")
        for line in health.notices:
            self.get_logger().warn(line)
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
        health.values.update(collecting=values["collecting"], samples=values["samples"])
        sensors = ",".join(self._geometry.names)
        self._diagnostics_pub.publish(common.diagnostic_array(
            self, [common.diagnostic_status(self.get_fully_qualified_name(), sensors, health)]))

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
            except Stopping:
                return  # shutting down: nothing changed, nobody to answer
            except Exception as exc:  # noqa: BLE001 - the service must answer, whatever happened
                if self._stopping.is_set():
                    return
                outcome = (False, f"calibration failed unexpectedly ({type(exc).__name__}: {exc}); "
                                  "nothing was changed")
                self.get_logger().error(outcome[1])
            if self._stopping.is_set():
                return
            done.set_result(outcome)
            with contextlib.suppress(Exception):  # the node may be going down
                self._wake.trigger()

        self._worker = threading.Thread(target=work, name="magcal-calibrate", daemon=True)
        self._worker.start()
        try:
            response.success, response.message = await done
        finally:
            self._solve_lock.release()
        return response

    def close(self) -> None:
        """Before destruction: abandon a running calibration (it changes nothing), wait for it briefly."""
        self._stopping.set()
        worker = self._worker
        if worker is not None and worker.is_alive():
            self.get_logger().info("shutting down during a calibration: it is abandoned, nothing is changed")
            worker.join(2.0)

    def _check_stop(self) -> None:
        if self._stopping.is_set():
            raise Stopping()

    def _fingerprint(self, raw: np.ndarray, geo: ArrayGeometry, method: str, reference: float | None) -> str:
        """Identifies a calibration: the collected sets, geometry, method settings and where it goes."""
        h = hashlib.sha256(np.ascontiguousarray(raw).tobytes())
        where = (self._target_name(), self._calibration_path())
        h.update(repr((geo.names, geo.positions.tolist(), method, reference, where)).encode())
        return h.hexdigest()

    def _calibrate(self) -> tuple[bool, str]:
        with self._lock:
            _, raw = self._buffer.snapshot()
            geo = self._geometry
        if len(raw) == 0:
            return self._fail("no synchronized sets collected" + ("" if self._collecting else " (not collecting)")
                              + f"; {WHAT_TO_DO}")
        method = str(self.get_parameter("method").value)
        reference = float(self.get_parameter("reference_field").value) or None
        fingerprint = self._fingerprint(raw, geo, method, reference)
        if self._last_solved is not None and self._last_solved[0] == fingerprint:
            message = (f"unchanged: these {len(raw)} sets and settings gave the calibration already in force, "
                       f"so nothing was solved, applied or written again; call ~/start to collect new sets "
                       f"(last result: {self._last_solved[1]})")
            self.get_logger().info(message)
            return True, message
        self.get_logger().info(f"solving from {len(raw)} sets (method {method})")
        try:
            result = calibrate_array(raw, geo, reference, method, SolveOptions())
        except MagcalError as exc:
            return self._fail(f"calibration not possible: {exc}; nothing was changed")
        self._check_stop()
        cal = result.calibration
        try:
            previous = self._get_target_parameters(cal.geometry.names)
        except CallFailed as exc:
            return self._fail(f"solved but not applied: {exc}; nothing was changed")
        path = self._calibration_path()
        params = calfile.parameters(cal)
        for name in cal.geometry.names:  # replace any covariance the node holds from an earlier calibration
            params[name].setdefault("covariance", list(common.UNKNOWN_COVARIANCE))
        keep = int(self.get_parameter("backups").value)
        staged = calfile.replace(path, cal, self._target_name(), keep) if path else contextlib.nullcontext()
        try:
            with staged:
                self._check_stop()
                self._push(params)
        except OSError as exc:
            why = f"{exc.strerror} ({exc.filename})" if exc.strerror and exc.filename else str(exc)
            if isinstance(exc.__context__, CallFailed):  # the push failed, then putting the old file back did
                return self._fail(f"solved but not applied: {exc.__context__}; and the previous {path} could NOT be "
                                  f"put back ({why}): the file holds a calibration the correction node does not run")
            return self._fail(f"solved but cannot write {path}: {why}; set calibration_file; nothing was changed")
        except CallFailed as exc:
            if isinstance(exc, Stopping):
                raise
            undo = "the file was left as it was" if path else "no file was written"
            if exc.unknown_outcome:
                try:
                    self._push(previous, raw_messages=True)
                    undo += "; the previous calibration was set again on the correction node"
                except CallFailed as again:
                    undo += f"; could NOT set the previous calibration again on the correction node ({again})"
            return self._fail(f"solved but not applied: {exc}; {undo}")
        with self._lock:
            self._collecting = False
        message = self._success_message(result, path)
        self._last_solved = (fingerprint, message)
        self.get_logger().info(message)
        return True, message

    def _success_message(self, result: CalibrationResult, path: str) -> str:
        where = f"applied to {self._target_name()}" + (f", written {path}" if path else ", no file written")
        return f"{result.summary()}; {where}"

    def _fail(self, message: str) -> tuple[bool, str]:
        self.get_logger().warn(message)
        return False, message

    def _calibration_path(self) -> str:
        text = str(self.get_parameter("calibration_file").value).strip()
        return os.path.expanduser(text) if text else ""

    def _target(self) -> str:
        return str(self.get_parameter("correction_node").value).strip()

    def _target_name(self) -> str:
        """The correction node's fully qualified name (relative names in this node's namespace)."""
        return self.resolve_service_name(self._target())

    def _service_clients(self) -> tuple[Any, Any]:
        target = self._target()
        if target not in self._target_clients:
            self._target_clients[target] = (
                self.create_client(SetParametersAtomically, f"{target}/set_parameters_atomically"),
                self.create_client(GetParameters, f"{target}/get_parameters"),
            )
        return self._target_clients[target]

    def _wait(self, ready: Any, timeout: float) -> bool:
        """Wait up to ``timeout`` s for ``ready(slice)``; :class:`Stopping` if the node shuts down."""
        deadline = time.monotonic() + timeout
        while True:
            self._check_stop()
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if ready(min(left, 0.1)):
                return True

    def _call(self, client: Any, request: Any) -> Any:
        """Call a service from the worker thread; the executor thread delivers the answer."""
        timeout = float(self.get_parameter("service_timeout").value)
        if not self._wait(lambda t: client.wait_for_service(timeout_sec=t), timeout):
            raise CallFailed(
                f"the correction node is not reachable ({client.srv_name} not available after {timeout:g} s); "
                f"start it (ros2 run magcal_ros correction_node) or set correction_node"
            )
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not self._wait(done.wait, timeout) or future.result() is None:
            future.cancel()
            raise CallFailed(f"{client.srv_name} did not answer within {timeout:g} s", unknown_outcome=True)
        return future.result()

    def _get_target_parameters(self, names: Sequence[str]) -> list[ParameterMsg]:
        """The correction node's current calibration parameters, to restore if needed."""
        _, getter = self._service_clients()
        wanted = ["sensor_names", "positions"] + [f"{n}.{s}" for n in names for s in ("matrix", "offset", "covariance")]
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
            raise CallFailed(f"{self._target_name()} rejected the calibration: {reply.result.reason}")


def main(args: Sequence[str] | None = None, stop: threading.Event | None = None) -> int:
    """Run the node (``ros2 run magcal_ros calibration_node`` goes through :mod:`magcal_ros.nodes.entry`)."""
    return common.run_node(lambda argv: CalibrationNode(), SingleThreadedExecutor, args, stop)


if __name__ == "__main__":
    raise SystemExit(main())

"""The calibration node's link to the correction node: its calibration fetched, a new one set (all or nothing)."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters, SetParametersAtomically
from rclpy.parameter import parameter_value_to_python

from magcal_ros.nodes import common


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


class CorrectionLink:
    """The calibration node's part that talks to the correction node's parameter services (a mixin of
    :class:`~magcal_ros.nodes.calibration_node.CalibrationNode`)."""

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

    @staticmethod
    def _wanted(names: Sequence[str]) -> list[str]:
        """The correction node's parameters that make up its calibration for sensors ``names``."""
        per_sensor = [f"{n}.{s}" for n in names
                      for s in ("matrix", "offset", "covariance", "interference", "noise", *common.TEMPERATURE_SUFFIXES)]
        return ["sensor_names", "positions", *common.INTERFERENCE_PARAMETERS[:3], *common.WATCH_PARAMETERS,
                *common.CALIBRATION_FRAME_PARAMETERS,
                "frame_id", "calibration_intensity"] + per_sensor

    def _fetch(self, names: Sequence[str]) -> dict[str, Any]:
        """ParameterValue messages of the correction node's parameters ``names`` that are set.

        rclpy answers a request naming an unset parameter with no values at all: then each
        name is asked on its own.
        """
        _, getter = self._service_clients()
        reply = self._call(getter, GetParameters.Request(names=list(names)))
        if len(reply.values) != len(names):
            values = []
            for name in names:
                one = self._call(getter, GetParameters.Request(names=[name])).values
                values.append(one[0] if one else None)
        else:
            values = list(reply.values)
        return {n: v for n, v in zip(names, values) if v is not None and v.type != ParameterType.PARAMETER_NOT_SET}

    def _get_target_parameters(self, names: Sequence[str]) -> list[ParameterMsg]:
        """The correction node's current calibration parameters, to restore if needed."""
        found = self._fetch(self._wanted(names))
        out = [ParameterMsg(name=n, value=v) for n, v in found.items()]
        for name in (*common.INTERFERENCE_PARAMETERS[:3], *common.WATCH_PARAMETERS):  # none before: none again
            if name not in found:
                out.append(common.parameter_message(name, []))
        neutral = neutral_terms({}, names)  # no temperature terms or rotation before: none again
        for name, value in common.flatten_parameters(neutral).items():
            if name not in found:
                out.append(common.parameter_message(name, value))
        return out

    def _target_values(self, names: Sequence[str]) -> dict[str, Any]:
        """The correction node's calibration parameters for ``names`` as Python values (unset ones left out)."""
        found = self._fetch(self._wanted(names) + ["uncorrected_sensors"])
        return {n: parameter_value_to_python(v) for n, v in found.items()}

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


def neutral_terms(params: dict[str, Any], names: Sequence[str]) -> dict[str, Any]:
    """Zero temperature terms, no calibration temperatures and an identity output rotation where ``params``
    (nested) has none: pushed with a calibration, so terms of an earlier one never outlive it on the correction
    node."""
    out: dict[str, Any] = {}
    for name in names:
        block = dict(params.get(name) or {})
        block.setdefault("offset_per_kelvin", [0.0] * 3)
        block.setdefault("matrix_per_kelvin", [0.0] * 9)
        block.setdefault("calibration_temperatures", [])  # unknown: nor an earlier calibration's span
        out[name] = block
    if "output_rotation" not in params:
        out["output_rotation"] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    return out


def channel_parameters(inputs: common.CurrentInputs, solved: Sequence[str]) -> dict[str, list[str]]:
    """The channels of a calibration with the topics and types they were read from (the correction node
    is to read the same currents; channels a calibration left unsolved are left out of them and watched:
    ``watch_*``, so that the calibration health names one when it starts to vary)."""
    keep = [inputs.channels.index(c) for c in solved]
    unsolved = [j for j, c in enumerate(inputs.channels) if c not in solved]
    return {"interference_channels": list(solved), "interference_topics": [inputs.topics[j] for j in keep],
            "interference_types": [inputs.types[j] for j in keep],
            "watch_channels": [inputs.channels[j] for j in unsolved],
            "watch_topics": [inputs.topics[j] for j in unsolved],
            "watch_types": [inputs.types[j] for j in unsolved]}

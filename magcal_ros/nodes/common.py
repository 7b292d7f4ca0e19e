"""Helpers shared by the magcal ROS 2 nodes: parameters, QoS, stamps, the main loop."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from magcal_ros.core import sync
from magcal_ros.core.geometry import DEFAULT_NAMES, ArrayGeometry
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

DEFAULT_SENSOR_NAMES: list[str] = list(DEFAULT_NAMES)
DEFAULT_POSITIONS: list[float] = [float(x) for x in ArrayGeometry.cross().positions.reshape(-1)]
IDENTITY: list[float] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
ZEROS: list[float] = [0.0, 0.0, 0.0]
RELIABILITIES: tuple[str, ...] = ("best_effort", "reliable")

SENSOR_NAMES_DOC = "sensor names; each subscribes <name>/raw (sensor_msgs/MagneticField, T)"
POSITIONS_DOC = "sensor positions, 3 per sensor in sensor_names order (m, platform frame)"
RELIABILITY_DOC = (
    "QoS reliability of the <name>/raw subscriptions: best_effort (matches every publisher) "
    "or reliable (lossless, needs a reliable publisher)"
)


def describe(text: str, read_only: bool = False, constraints: str = "", numbers: bool = False) -> ParameterDescriptor:
    """A parameter descriptor with a description (and optional constraints text).

    ``numbers``: a number or list of numbers that may come as integers from a hand-written
    YAML file (``0``, ``[0, 0, 0]``): dynamically typed, the node checks the value itself.
    """
    return ParameterDescriptor(
        description=text, read_only=read_only, additional_constraints=constraints, dynamic_typing=numbers
    )


NUMBER_ARRAYS = (Parameter.Type.DOUBLE_ARRAY, Parameter.Type.INTEGER_ARRAY)


def check_number_array(param: Parameter) -> str | None:
    """Why ``param`` is not a list of numbers, or None if it is."""
    if param.type_ not in NUMBER_ARRAYS:
        return f"{param.name} must be a list of numbers, got {param.type_.name.lower()}"
    return None


def raw_qos(reliability: str, depth: int) -> QoSProfile:
    """QoS of the raw subscriptions."""
    if reliability not in RELIABILITIES:
        raise InputError(f"raw_reliability must be one of {', '.join(RELIABILITIES)}, got {reliability!r}")
    if depth < 1:
        raise InputError(f"qos_depth must be >= 1, got {depth}")
    policy = ReliabilityPolicy.BEST_EFFORT if reliability == "best_effort" else ReliabilityPolicy.RELIABLE
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=policy)


def output_qos(depth: int) -> QoSProfile:
    """QoS of published outputs: reliable, keep last ``depth`` (matches any subscriber)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return stamp.sec * NS_PER_S + stamp.nanosec


def set_stamp(stamp: Any, ns: int) -> None:
    """Write integer nanoseconds into a builtin_interfaces/Time in place."""
    stamp.sec, stamp.nanosec = divmod(ns, NS_PER_S)


def tolerance_ns(seconds_value: Any) -> int:
    """A synchronization tolerance (s) as nanoseconds; :class:`InputError` unless 0 < t < 1 s."""
    try:
        t = float(seconds_value)
    except (TypeError, ValueError):
        raise InputError(f"sync_tolerance must be a number of seconds, got {seconds_value!r}") from None
    if not (0.0 < t < 1.0):
        raise InputError(f"sync_tolerance must be between 0 and 1 s (less than half the sample period), got {t}")
    return sync.tolerance_ns(t)


def geometry(names: Sequence[str], positions: Sequence[float]) -> ArrayGeometry:
    """The array geometry from parameter values (:class:`InputError` if inconsistent)."""
    return ArrayGeometry(tuple(str(n) for n in names), list(positions))


def parameter_message(name: str, value: Any) -> Any:
    """An rcl_interfaces/Parameter message for a Python value (lists of str or float)."""
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
        return Parameter(name, Parameter.Type.STRING_ARRAY, list(value)).to_parameter_msg()
    if isinstance(value, (list, tuple)):
        return Parameter(name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in value]).to_parameter_msg()
    return Parameter(name, value=value).to_parameter_msg()


def flatten_parameters(params: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested parameter dicts (as in a params file) to dotted names."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten_parameters(value, name + "."))
        else:
            out[name] = value
    return out


DROP_COUNTERS: tuple[str, ...] = tuple(k for k in sync.SyncStats().as_dict() if k != "sets")
LOG_PERIOD: float = 5.0
"""Shortest interval (s) between two drop reports in the log."""


class DropReporter:
    """Logs what the synchronizer dropped, at most every :data:`LOG_PERIOD` seconds."""

    def __init__(self, logger: Any) -> None:
        self.logger = logger
        self._last_status: dict[str, int] = {}
        self._last_log: dict[str, int] = {}
        self._last_time = -float("inf")

    def reset(self) -> None:
        """Start counting afresh (new synchronizer)."""
        self._last_status, self._last_log = {}, {}

    def update(self, counters: dict[str, int], what: str) -> dict[str, int]:
        """Log the drops since the last log line if due; return the drops since the last call."""
        recent = drops_since(counters, self._last_status)
        self._last_status = dict(counters)
        now = time.monotonic()
        if now - self._last_time >= LOG_PERIOD:
            since = drops_since(counters, self._last_log)
            if since:
                self.logger.warn(
                    "dropped since last report: "
                    + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in since.items())
                    + f" ({what})"
                )
                self._last_log, self._last_time = dict(counters), now
        return recent


def drops_since(counters: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    """Drop counters that grew since ``before``."""
    out = {k: counters.get(k, 0) - before.get(k, 0) for k in DROP_COUNTERS}
    return {k: v for k, v in out.items() if v > 0}


def run_node(make_node: Callable[[], Any], make_executor: Callable[[], Any], args: Sequence[str] | None = None) -> int:
    """Initialise rclpy, spin the node until shutdown (Ctrl-C, SIGTERM) and clean up.

    A node that cannot start (invalid parameters) logs one clear line and gives exit code 1.
    """
    import rclpy
    from rclpy.exceptions import (
        InvalidParameterTypeException,
        InvalidParameterValueException,
    )
    from rclpy.executors import ExternalShutdownException

    logger = rclpy.logging.get_logger("magcal")
    try:
        rclpy.init(args=list(args) if args is not None else sys.argv)
    except Exception as exc:  # rcl refuses bad --ros-args or an unparsable params file
        logger.fatal(f"cannot start: {str(exc).strip().splitlines()[0] if str(exc).strip() else exc!r}")
        return 1
    node = None
    try:
        try:
            node = make_node()
        except (InputError, InvalidParameterTypeException, InvalidParameterValueException) as exc:
            logger.fatal(f"cannot start: {exc}")
            return 1
        executor = make_executor()
        executor.add_node(node)
        try:
            executor.spin()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()

"""Helpers shared by the magcal ROS 2 nodes: parameters, QoS, stamps, diagnostics, the main loop."""

from __future__ import annotations

import faulthandler
import math
import re
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.parameter import Parameter
from rclpy.parameter_service import ParameterService
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from magcal_ros.core import sync
from magcal_ros.core.geometry import DEFAULT_NAMES, ArrayGeometry
from magcal_ros.core.interference import (
    DEFAULT_CURRENT_TOLERANCE,
    LatestCurrents,
    tolerance_of,
)
from magcal_ros.core.matching import LatestValues
from magcal_ros.core.temperature import DEFAULT_TEMPERATURE_TOLERANCE
from magcal_ros.core.units import MAX_READING, NS_PER_S
from magcal_ros.errors import InputError
from magcal_ros.nodes.entry import StopFlag, quiet_signals
from magcal_ros.nodes.health import Assessment, HealthLimits

DEFAULT_SENSOR_NAMES: list[str] = list(DEFAULT_NAMES)
DEFAULT_POSITIONS: list[float] = [float(x) for x in ArrayGeometry.cross().positions.reshape(-1)]
IDENTITY: list[float] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
ZEROS: list[float] = [0.0, 0.0, 0.0]
RELIABILITIES: tuple[str, ...] = ("best_effort", "reliable")
UNKNOWN_COVARIANCE: list[float] = [-1.0] + [0.0] * 8
"""ROS convention for an unknown covariance: -1 in element 0, zeros elsewhere."""

SENSOR_NAMES_DOC = "sensor names; each subscribes <name>/raw (sensor_msgs/MagneticField, T)"
POSITIONS_DOC = (
    "sensor positions, 3 per sensor in sensor_names order (m, platform frame); default: the 0.4 m cross for "
    "4 sensors, the origin for 1 sensor, none (must be given) otherwise"
)
RELIABILITY_DOC = (
    "QoS reliability of the <name>/raw and current subscriptions: best_effort (matches every publisher) "
    "or reliable (lossless, needs a reliable publisher)"
)


def describe(
    text: str,
    read_only: bool = False,
    constraints: str = "",
    numbers: bool = False,
    floats: tuple[float, float] | None = None,
    ints: tuple[int, int] | None = None,
) -> ParameterDescriptor:
    """A parameter descriptor with a description (and optional constraints text and range).

    ``numbers``: a number or list of numbers that may come as integers from a hand-written
    YAML file (``0``, ``[0, 0, 0]``): dynamically typed, the node checks the value itself.
    ``floats`` / ``ints``: the inclusive range rclpy enforces and ``ros2 param describe``
    shows (the node may check stricter bounds itself, said in ``constraints``).
    """
    d = ParameterDescriptor(
        description=text, read_only=read_only, additional_constraints=constraints, dynamic_typing=numbers
    )
    if floats is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(floats[0]), to_value=float(floats[1]), step=0.0)]
    if ints is not None:
        d.integer_range = [IntegerRange(from_value=int(ints[0]), to_value=int(ints[1]), step=1)]
    return d


TOLERANCE_RANGE: tuple[float, float] = (0.0, 1.0)
"""sync_tolerance (s): rclpy's inclusive range; the node requires 0 < t < 1."""
QOS_DEPTH_RANGE: tuple[int, int] = (1, 10_000)
PERIOD_RANGE: tuple[float, float] = (0.05, 3600.0)
"""Reporting periods and timeouts (s)."""


def declare_health(node: Any) -> HealthLimits:
    """Declare the diagnostics parameters shared by both nodes; the limits they give."""
    d = describe
    silent = node.declare_parameter(
        "sensor_timeout", 1.0,
        d("a sensor with no message for this long (s), or whose stamps lag the array's newest by this "
          "much, is reported silent or late on /diagnostics (WARN)", read_only=True, numbers=True,
          floats=PERIOD_RANGE)).value
    stale = node.declare_parameter(
        "output_timeout", 3.0,
        d("no output for this long (s) is an ERROR on /diagnostics", read_only=True, numbers=True,
          floats=PERIOD_RANGE)).value
    fraction = node.declare_parameter(
        "max_drop_fraction", 0.01,
        d("more than this fraction of the raw messages of one status period dropped or lost is a WARN "
          "on /diagnostics", read_only=True, numbers=True, floats=(0.0, 1.0))).value
    return HealthLimits(int(float(silent) * NS_PER_S), int(float(stale) * NS_PER_S), float(fraction))


DIAGNOSTICS_TOPIC = "/diagnostics"
"""Where diagnostic aggregators and rqt_robot_monitor listen (absolute, by convention)."""


def diagnostic_status(name: str, hardware_id: str, assessment: Assessment) -> DiagnosticStatus:
    """A diagnostic_msgs/DiagnosticStatus from a health assessment."""
    return DiagnosticStatus(
        level=bytes([assessment.level]),
        name=name,
        message=assessment.message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value=v) for k, v in assessment.values.items()],
    )


def hardware_id(node: Any, names: Sequence[str]) -> str:
    """The ``hardware_id`` of every status both nodes put on ``/diagnostics`` for the array of sensors ``names``:
    their names as the nodes resolve them (``/array1/mag1,/array1/mag2,...``), so that rqt_robot_monitor groups
    the correction and the calibration node of one array together, and apart from another array's."""
    return ",".join(node.resolve_topic_name(n) for n in names)


QUIET_CHECK: float = 0.5
"""How often (s) a node asks its synchroniser for the sets that messages held for a quiet sensor complete
(:meth:`~magcal_ros.core.sync.StreamSynchronizer.release_quiet`)."""


def steady_timer(node: Any, period: float, callback: Callable[[], None]) -> Any:
    """A timer on the steady clock: reports and supervision go on whatever the node clock does (with
    ``use_sim_time`` and no ``/clock`` the node clock stands still, and a timer on it never fires)."""
    from rclpy.clock import Clock
    from rclpy.clock_type import ClockType

    return node.create_timer(period, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


class SimTimeWatch:
    """With ``use_sim_time``: whether ``/clock`` drives the node clock. :meth:`problem` says when no ``/clock``
    arrived or it stopped for ``patience`` s of wall time (a WARN for ``/diagnostics``), and logs the change
    once each way."""

    def __init__(self, logger: Any, patience: float = 3.0) -> None:
        self.logger = logger
        self.patience = float(patience)
        self._clock = -1
        self._moved = time.monotonic()
        self._warned = False

    def problem(self, use_sim_time: bool, clock_ns: int) -> str | None:
        """The problem with simulated time now (``clock_ns``: the node clock, ns), or None."""
        wall = time.monotonic()
        if clock_ns != self._clock or not use_sim_time:
            self._clock, self._moved = clock_ns, wall
        text = None
        if use_sim_time and wall - self._moved >= self.patience:
            if clock_ns == 0:
                text = (f"use_sim_time is true and no /clock arrived in {wall - self._moved:.0f} s: the node clock "
                        "stands at 0 (play a bag with --clock, or set use_sim_time false)")
            else:
                text = (f"use_sim_time is true and /clock stopped {wall - self._moved:.0f} s ago at "
                        f"{clock_ns / NS_PER_S:.3f} s (bag paused or ended?)")
        if text and not self._warned:
            self.logger.warn(text)
        elif not text and self._warned:
            self.logger.info("simulated time runs again (/clock)")
        self._warned = text is not None
        return text


def out_of_range(node: Any, params: Sequence[Parameter]) -> str | None:
    """Why a number among ``params`` is outside its parameter's declared range, or None. rclpy checks the
    floating-point range of a dynamically typed parameter only for a double: an integer (``2**63 - 1`` for
    a tolerance in seconds) would pass."""
    for p in params:
        if p.type_ not in (Parameter.Type.INTEGER, Parameter.Type.DOUBLE) or not node.has_parameter(p.name):
            continue
        d = node.describe_parameter(p.name)
        value = p.value
        for r in (*d.floating_point_range, *d.integer_range):
            if not (math.isfinite(value) and r.from_value <= value <= r.to_value):
                return f"{p.name} {value!r} is out of range: {r.from_value:g} .. {r.to_value:g}"
    return None


def check_ranges(node: Any) -> None:
    """:class:`InputError` naming a declared parameter whose number lies outside its range (at start-up)."""
    names = node.list_parameters([], 0).names
    why = out_of_range(node, [node.get_parameter(n) for n in names])
    if why:
        raise InputError(why)


def unknown_parameters(node: Any, names: Sequence[str]) -> str:
    """The reason a request naming parameters the node does not have is refused (names given)."""
    return (f"unknown parameter{'s' if len(names) > 1 else ''} {', '.join(repr(n) for n in names)}: not a parameter "
            f"of {node.get_fully_qualified_name()} (ros2 param list shows its parameters)")


class RequestParameterService(ParameterService):
    """rclpy's parameter services, except that a ``~/set_parameters`` request (``ros2 param set``, ``ros2 param
    load``) goes to the node's ``set_request(parameters)`` as a whole, which answers one result per parameter:
    rclpy applies such a request one parameter at a time."""

    def _set_parameters_callback(self, request: Any, response: Any) -> Any:
        node = self._get_node()
        response.results = node.set_request([Parameter.from_parameter_msg(p) for p in request.parameters])
        return response


def diagnostic_array(node: Any, statuses: Sequence[DiagnosticStatus]) -> DiagnosticArray:
    """The statuses as one DiagnosticArray stamped with the node clock."""
    msg = DiagnosticArray(status=list(statuses))
    msg.header.stamp = node.get_clock().now().to_msg()
    return msg


def now_ns(node: Any) -> int:
    """The node clock (simulated time with use_sim_time) in integer nanoseconds."""
    return int(node.get_clock().now().nanoseconds)


def clock_reader(node: Any) -> Callable[[], int]:
    """A fast reader of the node clock (ns) for the hot path: without use_sim_time the ROS clock is
    the system clock, read directly; with it, the node clock. Call again when use_sim_time changes."""
    if node.get_parameter("use_sim_time").value:
        return lambda: now_ns(node)
    return time.time_ns


def arrival_reader(node: Any) -> Callable[[Any], int]:
    """When a message arrived (ns), from the message info a subscription callback gets: the middleware's
    reception time (system clock), not the moment the callback runs, which on a busy machine can be
    seconds later for a whole queue of messages; the node clock when the middleware gives none, or with
    use_sim_time (the reception time is system time). Call again when use_sim_time changes."""
    clock = clock_reader(node)
    if node.get_parameter("use_sim_time").value:
        return lambda info: clock()
    return lambda info: info.get("received_timestamp") or clock()


NUMBER_ARRAYS = (Parameter.Type.DOUBLE_ARRAY, Parameter.Type.INTEGER_ARRAY)


def is_empty_list(param: Parameter) -> bool:
    """An empty list of any element type: how ``[]`` comes from a params file or ``ros2 param load``
    (which give it no element type, or booleans)."""
    return param.type_.name.endswith("_ARRAY") and len(param.value) == 0


def check_number_array(param: Parameter) -> str | None:
    """Why ``param`` is not a list of numbers (an empty list of any type counts), or None if it is."""
    if param.type_ not in NUMBER_ARRAYS and not is_empty_list(param):
        return f"{param.name} must be a list of numbers, got {param.type_.name.lower()}"
    return None


def declare_list(node: Any, name: str, kind: Parameter.Type, descriptor: ParameterDescriptor) -> Any:
    """Declare a list parameter whose "none" is the empty list, so that it always has a value
    (``ros2 param get`` and ``dump`` fail on a parameter without one). Dynamically typed: an empty
    list comes back from a params file without an element type (rcl) or as booleans (``ros2 param
    load``); the node reads an empty list of any type as none."""
    descriptor.dynamic_typing = True
    node.declare_parameter(name, None, descriptor)
    if node.get_parameter(name).type_ == Parameter.Type.NOT_SET:
        node.set_parameters([Parameter(name, kind, [])])  # before the nodes add their set callbacks
    return node.get_parameter(name).value


def number_text(text: str) -> float | list[float] | None:
    """A number or list of numbers that ``ros2 param load`` passed on as text, or None.

    rclpy re-reads each value of a params file with YAML 1.1, to which ``5e-08`` (no decimal
    point) is a string: ``[5e-08, 1.0]`` arrives as the string ``"[5e-08, 1.0]"``, and
    ``[5e-08, 1e-07]`` as a list of strings."""
    body = text.strip()
    try:
        if body.startswith("[") and body.endswith("]"):
            inner = body[1:-1].strip()
            return [float(t) for t in inner.split(",")] if inner else []
        return float(body)
    except ValueError:
        return None


def numbers_from_text(numeric: Callable[[str], bool]) -> Callable[[list[Parameter]], list[Parameter]]:
    """A pre-set parameters callback: a string value of a parameter that holds numbers (``numeric(name)``)
    that reads as numbers is turned into them (see :func:`number_text`); everything else passes as it is."""
    def convert(params: list[Parameter]) -> list[Parameter]:
        out = []
        for p in params:
            value = None
            if p.type_ == Parameter.Type.STRING and numeric(p.name):
                value = number_text(p.value)
            elif p.type_ == Parameter.Type.STRING_ARRAY and p.value and numeric(p.name):
                value = number_text("[" + ",".join(p.value) + "]")
            if isinstance(value, list):
                p = Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, value)
            elif value is not None:
                p = Parameter(p.name, Parameter.Type.DOUBLE, value)
            out.append(p)
        return out

    return convert


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


SYNC_MODE_DOC = (
    "how raw messages become sets: exact (header stamps that coincide within sync_tolerance: sensors sampled "
    "together and stamped alike), interpolate (at each sample instant of the first sensor, the others "
    "interpolated between their samples: sensors sampled apart or stamped on receipt), auto (chosen from the "
    "first stamps of every sensor)"
)
MAX_GAP_DOC = (
    "interpolation: a set whose neighbouring samples of a sensor are further apart (s) is dropped and counted "
    "(gap); 0 = 3.5 sample periods of that sensor (two lost samples in a row are bridged)"
)
MAX_GAP_RANGE: tuple[float, float] = (0.0, 60.0)


def declare_sync(node: Any) -> None:
    """Declare ``sync_mode`` and ``max_gap``, shared by both nodes (``sync_tolerance`` is declared beside)."""
    node.declare_parameter("sync_mode", sync.DEFAULT_SYNC_MODE,
                           describe(SYNC_MODE_DOC, constraints=" | ".join(sync.SYNC_MODES)))
    node.declare_parameter("max_gap", sync.DEFAULT_MAX_GAP,
                           describe(MAX_GAP_DOC, constraints="0 <= t < 60", numbers=True, floats=MAX_GAP_RANGE))


def sync_settings(values: dict[str, Any]) -> tuple[str, int]:
    """``sync_mode`` and ``max_gap`` (ns) from parameter values; :class:`InputError` naming a bad one."""
    mode = values.get("sync_mode", sync.DEFAULT_SYNC_MODE)
    if mode not in sync.SYNC_MODES:
        raise InputError(f"sync_mode must be one of {', '.join(sync.SYNC_MODES)}, got {mode!r}")
    gap = values.get("max_gap", sync.DEFAULT_MAX_GAP)
    if isinstance(gap, bool) or not isinstance(gap, (int, float)):
        raise InputError(f"max_gap must be a number of seconds, got {gap!r}")
    try:
        return str(mode), sync.max_gap_ns(gap)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def synchronizer(names: Sequence[str], tolerance: int, mode: str, max_gap: int,
                 time_offsets: Sequence[float] | None = None,
                 stats: sync.SyncStats | None = None) -> sync.StreamSynchronizer:
    """The set synchroniser of a node: ``tolerance`` and ``max_gap`` in ns, ``time_offsets`` in s per
    sensor (None: zeros); ``stats`` to keep counting into (a reconfiguration). Live readings beyond
    :data:`~magcal_ros.core.units.MAX_READING` are dropped and counted (``out_of_range``)."""
    offsets = {n: float(t) for n, t in zip(names, time_offsets if time_offsets is not None else []) if t}
    return sync.stream_synchronizer(list(names), tolerance / NS_PER_S, mode, max_gap / NS_PER_S, offsets,
                                    stats=stats, max_reading=MAX_READING)


def default_positions(count: int) -> list[float] | None:
    """The positions a node assumes for ``count`` sensors: the default cross for 4, the origin for
    1, none otherwise (they must be given)."""
    return {4: DEFAULT_POSITIONS, 1: [0.0, 0.0, 0.0]}.get(count)


def check_unique(names: Sequence[Any]) -> tuple[str, ...]:
    """``names`` as strings; :class:`InputError` naming any listed more than once."""
    out = tuple(str(n) for n in names)
    twice = sorted({n for n in out if out.count(n) > 1})
    if twice:
        raise InputError(f"sensor_names lists {', '.join(twice)} more than once: each sensor needs a name of its own")
    return out


def declare_geometry(node: Any) -> list[str]:
    """Declare ``sensor_names`` and ``positions`` (default by the sensor count); the names (:class:`InputError`
    for a name listed twice, before anything is declared per sensor)."""
    names = node.declare_parameter("sensor_names", DEFAULT_SENSOR_NAMES, describe(SENSOR_NAMES_DOC)).value
    check_unique(names)
    node.declare_parameter("positions", default_positions(len(names)), describe(POSITIONS_DOC, numbers=True))
    return list(names)


def check_node_name(parameter: str, name: str) -> None:
    """:class:`InputError` unless ``name`` is a valid ROS node name, optionally with a namespace
    (``magcal_correction``, ``array1/magcal_correction``, ``/array1/magcal_correction``)."""
    from rclpy.exceptions import InvalidNamespaceException, InvalidNodeNameException
    from rclpy.validate_namespace import validate_namespace
    from rclpy.validate_node_name import validate_node_name

    namespace, _, base = name.rpartition("/")
    try:
        validate_node_name(base)
        if namespace:
            validate_namespace("/" + namespace.lstrip("/"))
    except (InvalidNodeNameException, InvalidNamespaceException) as exc:
        reason = str(exc).strip().splitlines()[0].rstrip(": ")
        raise InputError(f"{parameter} {name!r} is not a valid ROS node name ({reason})") from None


def geometry(names: Sequence[str], positions: Sequence[float] | None) -> ArrayGeometry:
    """The array geometry from parameter values (:class:`InputError` if inconsistent).

    ``positions`` None or empty (an empty list in a params file is no value) is the origin
    for one sensor and an error naming what to give otherwise.
    """
    names = check_unique(names)
    if not positions:
        if len(names) != 1:
            raise InputError(f"positions needs 3 numbers per sensor (m, platform frame): {3 * len(names)} for "
                             f"{len(names)} sensors, none given")
        positions = [0.0, 0.0, 0.0]
    return ArrayGeometry(names, list(positions))


# -- current interference channels (both nodes) ----------------------------------------------------
BATTERY_STATE = "sensor_msgs/msg/BatteryState"
FLOAT64 = "std_msgs/msg/Float64"
CURRENT_TYPES: tuple[str, ...] = (BATTERY_STATE, FLOAT64)
"""Message types of a current channel: BatteryState (its ``current``, A, at its header stamp, or on
receipt when the header stamp is zero) or
Float64 (``data``, A, stamped on receipt with the node clock: it has no header)."""


@dataclass(frozen=True)
class CurrentInputs:
    """Where each interference channel's current comes from."""

    channels: tuple[str, ...] = ()
    topics: tuple[str, ...] = ()
    """Topic per channel (relative names resolve in the node's namespace)."""
    types: tuple[str, ...] = ()
    """One of :data:`CURRENT_TYPES` per channel."""
    tolerance_ns: int = tolerance_of(DEFAULT_CURRENT_TOLERANCE)
    """Largest age of a channel's value at a set's stamp."""

    def sources(self) -> tuple[tuple[str, str, str], ...]:
        """(channel, topic, type) of every channel: what the subscriptions depend on."""
        return tuple(zip(self.channels, self.topics, self.types))


def _strings(name: str, value: Any) -> list[str]:
    if value is None:
        return []
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise InputError(f"{name} must be a list of strings")
    return [v.strip() for v in value]


def current_inputs(values: dict[str, Any], prefix: str = "interference") -> CurrentInputs:
    """The current channels from parameter values (dotted names): ``interference_channels``,
    ``interference_topics`` (default: each channel's name, relative), ``interference_types``
    (default BatteryState) and ``current_tolerance`` (s); with ``prefix`` ``watch``, those of
    ``watch_channels``, ``watch_topics`` and ``watch_types``. :class:`InputError` naming what is wrong."""
    from rclpy.exceptions import InvalidTopicNameException
    from rclpy.validate_topic_name import validate_topic_name

    channels = _strings(f"{prefix}_channels", values.get(f"{prefix}_channels"))
    if len(set(channels)) != len(channels) or not all(channels):
        raise InputError(f"{prefix}_channels must be unique, non-empty names, got {channels}")
    tolerance = values.get("current_tolerance", DEFAULT_CURRENT_TOLERANCE)
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not tolerance > 0:
        raise InputError(f"current_tolerance must be a positive number of seconds, got {tolerance!r}")
    if not channels:  # no interference: the topics and types of earlier channels do not matter
        return CurrentInputs((), (), (), tolerance_of(float(tolerance)))
    topics_ = _strings(f"{prefix}_topics", values.get(f"{prefix}_topics")) or list(channels)
    types = _strings(f"{prefix}_types", values.get(f"{prefix}_types")) or [BATTERY_STATE] * len(channels)
    for name, given in ((f"{prefix}_topics", topics_), (f"{prefix}_types", types)):
        if len(given) != len(channels):
            raise InputError(f"{name} needs one entry per {prefix} channel ({len(channels)}: "
                             f"{', '.join(channels) or 'none'}), got {len(given)}")
    for topic in topics_:
        try:
            validate_topic_name(topic)
        except InvalidTopicNameException as exc:
            raise InputError(f"{prefix}_topics: {str(exc).splitlines()[0]}: {topic!r}") from None
    bad = [t for t in types if t not in CURRENT_TYPES]
    if bad:
        raise InputError(f"{prefix}_types {bad[0]!r} is not supported; use {' or '.join(CURRENT_TYPES)}")
    return CurrentInputs(tuple(channels), tuple(topics_), tuple(types), tolerance_of(float(tolerance)))


INTERFERENCE_PARAMETERS: tuple[str, ...] = (
    "interference_channels", "interference_topics", "interference_types", "current_tolerance",
)


def declare_currents(node: Any) -> None:
    """Declare the interference channel parameters both nodes share (no channels by default)."""
    d = describe
    strings = Parameter.Type.STRING_ARRAY
    declare_list(
        node, "interference_channels", strings,
        d("current channels whose interference is subtracted (correction node) or estimated (calibration node), "
          "e.g. [thruster1/battery]; [] = no current interference"))
    declare_list(
        node, "interference_topics", strings,
        d("topic of each channel's current, in interference_channels order; [] = the channel names (relative)"))
    declare_list(
        node, "interference_types", strings,
        d(f"message type of each channel's topic: {BATTERY_STATE} (current, A, header stamp, or receipt time when "
          f"it is zero; default) or "
          f"{FLOAT64} (data, A, stamped on receipt)", constraints=" | ".join(CURRENT_TYPES)))
    node.declare_parameter(
        "current_tolerance", DEFAULT_CURRENT_TOLERANCE,
        d("a channel's latest current stamped more than this (s) before a set is stale: the set is not used",
          numbers=True, floats=(0.0, 3600.0)))


WATCH_PARAMETERS: tuple[str, ...] = ("watch_channels", "watch_topics", "watch_types")
"""The correction node's current channels whose interference its calibration does not know (watched, not
applied): the calibration node sets them with every calibration it pushes."""


def declare_watched(node: Any) -> None:
    """Declare the correction node's watched current channels (none by default)."""
    d = describe
    strings = Parameter.Type.STRING_ARRAY
    declare_list(
        node, "watch_channels", strings,
        d("current channels whose interference the calibration does not know (its manoeuvre left them "
          "undetermined, or they are new): read, not applied; the calibration health names one as soon as its "
          "current varies beyond its reading noise (a recalibration then learns it). The calibration node sets "
          "them with every calibration it pushes: the channels of its interference_channels left unsolved"))
    declare_list(node, "watch_topics", strings,
                 d("topic of each watched channel's current, in watch_channels order; [] = the channel names"))
    declare_list(node, "watch_types", strings,
                 d(f"message type of each watched channel's topic: {BATTERY_STATE} (default) or {FLOAT64}",
                   constraints=" | ".join(CURRENT_TYPES)))


def subscribe_currents(node: Any, inputs: CurrentInputs, store: LatestCurrents | Any, qos: QoSProfile,
                       clock: Callable[[], int]) -> list[Any]:
    """Subscribe every channel's topic, feeding its values into ``store`` (``add(channel index, stamp ns,
    value A)``: a :class:`LatestCurrents`, or a watch) (BatteryState at its
    header stamp, or at ``clock()`` ns on receipt when that is zero; Float64 on receipt)."""
    from sensor_msgs.msg import BatteryState
    from std_msgs.msg import Float64

    subs = []
    for j, (topic, kind) in enumerate(zip(inputs.topics, inputs.types)):
        if kind == BATTERY_STATE:
            def on_battery(msg: Any, j: int = j) -> None:
                # Many battery drivers leave the header empty: an unstamped value counts from its receipt.
                store.add(j, stamp_ns(msg.header.stamp) or clock(), float(msg.current))

            subs.append(node.create_subscription(BatteryState, topic, on_battery, qos))
        else:
            def on_float(msg: Any, j: int = j) -> None:
                store.add(j, clock(), float(msg.data))

            subs.append(node.create_subscription(Float64, topic, on_float, qos))
    return subs


# -- the sensors' temperatures and the output frame (both nodes) -----------------------------------
TEMPERATURE = "sensor_msgs/msg/Temperature"
TEMPERATURE_SUFFIXES: tuple[str, ...] = ("offset_per_kelvin", "matrix_per_kelvin", "calibration_temperatures")
"""Per-sensor temperature terms of a calibration (``<name>.offset_per_kelvin``: 3 T/K, ``<name>.matrix_per_kelvin``:
9 1/K row-major) and the temperatures it was made at (``<name>.calibration_temperatures``: [min, max] deg C)."""
CALIBRATION_FRAME_PARAMETERS: tuple[str, ...] = ("temperature_reference", "output_rotation")
"""Array-wide calibration parameters of the temperature terms and the output frame."""


def declare_temperature_tolerance(node: Any) -> None:
    """Declare ``temperature_tolerance`` (s): how old a sensor's latest temperature may be at a set."""
    node.declare_parameter(
        "temperature_tolerance", DEFAULT_TEMPERATURE_TOLERANCE,
        describe("a sensor's latest temperature (<name>/temperature) stamped more than this (s) before a set is "
                 "stale: the set is not used (temperatures change slowly; their sensors publish at 0.1-10 Hz)",
                 numbers=True, floats=(0.0, 3600.0)))


def temperature_tolerance_ns(value: Any) -> int:
    """``temperature_tolerance`` (s) as ns; :class:`InputError` unless a positive number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise InputError(f"temperature_tolerance must be a positive number of seconds, got {value!r}")
    return tolerance_of(float(value), "temperature")


def subscribe_temperatures(node: Any, names: Sequence[str], store: LatestValues, qos: QoSProfile,
                           clock: Callable[[], int]) -> list[Any]:
    """Subscribe ``<name>/temperature`` (sensor_msgs/Temperature, deg C) of every sensor, feeding ``store``
    (stream ``i`` = sensor ``i``) at the header stamp, or at ``clock()`` ns on receipt when that is zero."""
    from sensor_msgs.msg import Temperature

    from magcal_ros.io import topics

    subs = []
    for i, name in enumerate(names):
        def on_temperature(msg: Any, i: int = i) -> None:
            store.add(i, stamp_ns(msg.header.stamp) or clock(), float(msg.temperature))

        subs.append(node.create_subscription(Temperature, topics.temperature(name), on_temperature, qos))
    return subs


def running_calibration(values: dict[str, Any], geometry: ArrayGeometry) -> tuple[Any, str]:
    """The calibration a correction node runs for ``geometry``'s sensors, from its parameter values
    (Python values by dotted name, unset ones absent), or ``(None, why not)``.

    A sensor it does not have, or holds without a matrix or offset (``[]``: never calibrated, e.g.
    listed in ``uncorrected_sensors``), means it runs no calibration to start from; an identity and
    zeros given are a calibration like any other.
    """
    from magcal_ros.core.calibration import ArrayCalibration

    names = geometry.names
    theirs = list(values.get("sensor_names") or [])
    absent = [n for n in names if n not in theirs]
    if absent:
        return None, f"it has no sensor {', '.join(absent)} (its sensors: {', '.join(theirs) or 'none'})"
    blank = [n for n in names if not values.get(f"{n}.matrix") or not values.get(f"{n}.offset")]
    if blank:
        raw = [n for n in blank if n in list(values.get("uncorrected_sensors") or [])]
        why = f"; {', '.join(raw)} uncorrected on purpose" if raw else ""
        return None, f"{', '.join(blank)} without a matrix and offset (never calibrated{why})"
    channels = list(values.get("interference_channels") or [])
    params: dict[str, Any] = {"sensor_names": list(names), "positions": list(geometry.positions.reshape(-1)),
                              "interference_channels": channels}
    for n in names:
        params[n] = {"matrix": list(values[f"{n}.matrix"]), "offset": list(values[f"{n}.offset"])}
        if channels and f"{n}.interference" in values:
            params[n]["interference"] = list(values[f"{n}.interference"])
        for suffix in TEMPERATURE_SUFFIXES:  # temperature terms and output frame, when it runs them
            if f"{n}.{suffix}" in values:
                params[n][suffix] = list(values[f"{n}.{suffix}"])
    for key in CALIBRATION_FRAME_PARAMETERS:
        if key in values:
            params[key] = values[key]
    if "output_rotation" in values and "frame_id" in values:  # the frame the running calibration outputs in
        params["frame_id"] = values["frame_id"]
    try:
        return ArrayCalibration.from_parameters(params), ""
    except InputError as exc:
        return None, f"its calibration is unusable ({exc})"


STRING_LISTS: frozenset[str] = frozenset({"sensor_names", "uncorrected_sensors", *INTERFERENCE_PARAMETERS[:3],
                                          *WATCH_PARAMETERS})
"""Parameters that are lists of strings, also when empty."""


def parameter_message(name: str, value: Any) -> Any:
    """An rcl_interfaces/Parameter message for a Python value (lists of str or float)."""
    if isinstance(value, (list, tuple)) and (name in STRING_LISTS or value and all(isinstance(v, str) for v in value)):
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


DROP_COUNTERS: tuple[str, ...] = (*sync.DROP_FIELDS, "restarts")
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


def params_files(argv: Sequence[str]) -> list[str]:
    """The ``--params-file`` paths among the ROS arguments of a command line."""
    files: list[str] = []
    ros = False
    it = iter(argv)
    for arg in it:
        if arg == "--ros-args":
            ros = True
        elif arg == "--":
            ros = False
        elif ros and arg == "--params-file":
            files.append(next(it, ""))
    return [f for f in files if f]


def _node_blocks(doc: Any, prefix: str = "") -> list[tuple[str, dict[str, Any]]]:
    """(node key, ros__parameters) of a params file, nested namespace blocks joined with '/'."""
    out: list[tuple[str, dict[str, Any]]] = []
    if not isinstance(doc, dict):
        return out
    for key, value in doc.items():
        if not isinstance(value, dict):
            continue
        name = f"{prefix}/{str(key).strip('/')}" if prefix else str(key)
        if isinstance(value.get("ros__parameters"), dict):
            out.append((name, value["ros__parameters"]))
        else:
            out.extend(_node_blocks(value, name))
    return out


def key_matches(key: str, fully_qualified_name: str) -> bool:
    """Whether a params-file node key applies to the node, as rcl decides (``/**``, ``*``, namespaces)."""
    rx = ""
    for part in key.strip("/").split("/"):
        rx += r"(?:/[^/]+)*" if part == "**" else "/" + re.escape(part).replace(r"\*", "[^/]*")
    return re.fullmatch(rx, fully_qualified_name) is not None


def _has_sensor_calibration(params: dict[str, Any]) -> bool:
    flat = flatten_parameters(params)
    return any(k.endswith((".matrix", ".offset")) for k in flat)


def unmatched_calibrations(files: Sequence[str], fully_qualified_name: str) -> list[tuple[str, str]]:
    """(file, key) of each params-file block with per-sensor calibration that does not apply to the node."""
    out = []
    for path in files:
        try:
            with open(path, encoding="utf-8") as fh:
                doc = yaml.safe_load(fh)
        except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError):
            continue  # rcl already refused or read it; nothing to compare
        for key, params in _node_blocks(doc):
            if _has_sensor_calibration(params) and not key_matches(key, fully_qualified_name):
                out.append((path, key))
    return out


def run_node(
    make_node: Callable[[list[str]], Any],
    make_executor: Callable[[], Any],
    args: Sequence[str] | None = None,
    stop: StopFlag | None = None,
) -> int:
    """Initialise rclpy, spin the node until shutdown (Ctrl-C, SIGTERM) and clean up; exit code.

    ``make_node(argv)`` builds the node. A node that cannot start (invalid parameters) logs
    one clear line and gives exit code 1; a signal at any moment gives a quiet exit 0.
    ``stop``: the event of :func:`~magcal_ros.nodes.entry.quiet_signals` if already installed.
    The node's ``close()`` (if any) runs before ``destroy_node``. SIGUSR1 prints every thread's
    stack to stderr (a node that seems stuck), and the node carries on.
    """
    if stop is None:
        stop = quiet_signals()
    if hasattr(signal, "SIGUSR1"):  # kill -USR1 <pid>: every thread's stack to stderr, the node runs on
        faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)
    import rclpy
    from rclpy.exceptions import (
        InvalidParameterTypeException,
        InvalidParameterValueException,
    )
    from rclpy.executors import ExternalShutdownException

    logger = rclpy.logging.get_logger("magcal")
    argv = list(args) if args is not None else list(sys.argv)
    try:
        rclpy.init(args=argv)
    except Exception as exc:  # rcl refuses bad --ros-args or an unparsable params file
        logger.fatal(f"cannot start: {str(exc).strip().splitlines()[0] if str(exc).strip() else exc!r}")
        return 1
    node = None
    try:
        if stop.is_set():
            return 0
        try:
            node = make_node(argv)
        except (InputError, InvalidParameterTypeException, InvalidParameterValueException) as exc:
            logger.fatal(f"cannot start: {exc}")
            return 1
        except Exception:
            if stop.is_set() or not rclpy.ok():
                return 0  # interrupted while starting
            raise
        try:
            executor = make_executor()
            executor.add_node(node)
            # spin until rclpy's handler shuts the context down, or the stop flag is seen: the wait wakes
            # within STOP_POLL of wall time even when nothing else wakes it (a node on a simulated clock
            # that stopped), so a stop signal rclpy's handler missed still ends the spin
            while rclpy.ok(context=executor.context) and not stop.is_set():
                executor.spin_once(timeout_sec=STOP_POLL)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:
            if stop.is_set() or not rclpy.ok():
                return 0  # interrupted before spinning: the context is already shut down
            raise
        return 0
    finally:
        _clean_up(node, rclpy)


STOP_POLL: float = 0.5
"""Longest wait (s, wall time) of the node's executor before it looks at the stop flag again."""
CLEANUP_TIMEOUT: float = 15.0
"""Seconds the clean-up after the spin (the node's ``close``, ``destroy_node``, rclpy shutdown) may
take before the process prints every thread's stack and exits with code 1 instead of hanging."""


def _clean_up(node: Any, rclpy: Any) -> None:
    """Close and destroy ``node`` (None: not built) and shut rclpy down, deaf to further signals.

    A terminal's Ctrl-C or a launch file's stop may come again and again while the node shuts
    down: from here on they are ignored at the process level (rclpy's handler would act on a
    context being torn down, and the interpreter's own teardown resets Python handlers to the
    default: killed by SIGINT, exit -2). A clean-up stuck in the middleware ends after
    :data:`CLEANUP_TIMEOUT` with the stacks in the output rather than never: Fast DDS 2.14 can
    deadlock destroying the participant while another node's endpoints disappear (two nodes
    stopped at once; about once in 300 such stops on a busy machine).
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    faulthandler.dump_traceback_later(CLEANUP_TIMEOUT, exit=True)
    try:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    finally:
        faulthandler.cancel_dump_traceback_later()
        # rclpy's shutdown put back the handlers it found: ignored signals stay ignored
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)

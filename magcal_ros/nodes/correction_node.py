"""Live correction node: raw sensor vectors in, corrected vectors, centre field and gradient out.

Subscribes ``<name>/raw`` (sensor_msgs/MagneticField, T) for every name in
``sensor_names``, groups the messages into sets (:mod:`magcal_ros.core.sync`, ``sync_mode``:
stamps that coincide, or every sensor interpolated at the first sensor's sample instants,
with each sensor's ``<name>.time_offset``) and, per set, publishes ``<name>/corrected`` (``matrix @ (raw - offset) - interference @ u``,
platform frame, with ``<name>.covariance``), ``field`` (centre field, T, covariance of the
mean) and the gradient the positions determine:

- three or more sensors spread in a plane or in space: ``gradient``
  (std_msgs/Float64MultiArray, 3x3 row-major, ``G[i][j] = dB_j/dx_i`` in T/m) and
  ``gradient_stamped`` (sensor_msgs/JointState: the same nine components in ``position``,
  named ``gradient.xx`` ... ``gradient.zz``, stamped with the set's stamp and ``frame_id``);
- sensors on one line (two sensors): ``baseline_gradient`` (geometry_msgs/Vector3Stamped,
  ``dB/ds`` in T/m along the line from the first sensor towards the last);
- one sensor: no gradient topic at all (its ``positions`` may be left out).

Topics the sensor count does not support are not created. All are relative names: a
namespace or a remap moves them. The calibration comes from parameters
(``<name>.matrix``, ``<name>.offset``, ``<name>.covariance``, ``positions``,
``interference_channels`` and ``<name>.interference``) and can be replaced at runtime
through the standard parameter services; a replacement is validated as a whole and
swapped in between two sets, an invalid one is rejected with a reason.

Current interference: with ``interference_channels`` the node subscribes each channel's
topic (``interference_topics``, default the channel name; ``interference_types``
BatteryState or Float64), keeps the values of the last seconds and subtracts
``interference @ u`` from every set, ``u`` each channel's latest current stamped at most
``current_tolerance`` before the set (the rule of ``magcal correct``). A set without such
a current of every channel is not published (counted per channel as ``stale_current``,
a WARN on ``/diagnostics`` naming the channel), never corrected with a stale current.

Temperature: a calibration with temperature terms (``temperature_reference``,
``<name>.offset_per_kelvin``, ``<name>.matrix_per_kelvin``) makes the node subscribe every
``<name>/temperature`` (sensor_msgs/Temperature, deg C) and correct each set with each
sensor's latest temperature stamped at most ``temperature_tolerance`` before it; a set
without one is withheld like a set without a current (``<name>.stale_temperature``). Without
temperature terms nothing is subscribed for them and no set waits for a temperature. A calibration
that records the temperatures it was made at (``<name>.calibration_temperatures``, [min, max] deg C)
has every ``<name>/temperature`` heard (sets never wait for it) and compared with them: sets more than
2 K outside are counted per sensor on ``/diagnostics`` (``<name>.temperature_beyond_calibration``,
``<name>.temperature_beyond_calibration_K``, ``<name>.calibration_temperatures_C``), a WARN status
in the period it happens and one WARN log line when a sensor first leaves them. An
``output_rotation`` turns every output into the calibration's frame (``frame_id``, e.g. the
IMU's).

A sensor whose matrix or offset is ``[]`` (never given: the default, or set to ``[]``) is not
calibrated: the node warns, naming it, and publishes neither ``field`` nor the tensor (nor
that sensor's corrected vector) until it is, unless the sensor is listed in
``uncorrected_sensors`` (its raw reading is then used on purpose). An identity matrix and a
zero offset given are a calibration like any other (``magcal correct`` takes them alike).

Every ``status_period`` s: ``~/status`` (diagnostic_msgs/DiagnosticStatus) and the same
status on ``/diagnostics`` (DiagnosticArray): level, message (what is wrong, naming
sensors) and values: per sensor ``received``, ``lost`` (estimated from gaps in its stamp
sequence: lost before reaching the node), ``gaps``, ``period_ms``; the synchroniser's
counters (``sets``, ``unmatched``, ``nonfinite``, ``duplicate``, ``out_of_order``,
``zero_stamp``, ``malformed``, ``restarts``, ``glitch``, ``gap``, ``used``), ``published``,
``withheld`` (sets not published for want of a calibration), ``pending``, ``sync_mode``,
``sync_window_ms`` and, when sets were
published, ``age_ms_p50/p99/max``: node clock at publication minus the set's stamp (a
latency when the sensors stamp with the same clock; simulated time with use_sim_time).

The calibration health (:mod:`magcal_ros.core.calibration_health`) goes on ``/diagnostics`` as
its own status, ``<node>: calibration``, in the same array: whether the running calibration
still fits, judged from the corrected sets over ``health_window`` s against the noise the
calibration stored (``<name>.noise``, ``calibration_intensity``); WARN or ERROR naming the
drifted sensors above ``health_warn_factor`` / ``health_error_factor`` times that noise.

Usage::

    ros2 run magcal_ros correction_node --ros-args --params-file calibration.yaml
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState, MagneticField
from std_msgs.msg import Float64MultiArray

from magcal_ros.core import side_streams as side
from magcal_ros.core import sync
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.calibration_health import CalibrationHealth, with_unknown_currents
from magcal_ros.core.interference import CurrentWatch, LatestCurrents
from magcal_ros.core.matching import KEEP_NS, LatestValues
from magcal_ros.core.sync import StreamSynchronizer, SyncedSet
from magcal_ros.core.tensor import GRADIENT_METHODS, gradient
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.cdr import decode_magnetic_field
from magcal_ros.nodes import common, drift
from magcal_ros.nodes.entry import StopFlag
from magcal_ros.nodes.health import (
    ArrayHealth,
    CurrentHealth,
    TemperatureHealth,
    TemperatureSpanHealth,
)
from magcal_ros.nodes.live_outputs import Listeners, SetOutputs

NODE_NAME = "magcal_correction"
WAIT_CHECK: float = 0.02
"""How often (s) the node looks whether a set waiting for a current or temperature may go."""
CORE_PARAMETERS: tuple[str, ...] = (
    "sensor_names", "positions", "frame_id", "sync_tolerance", "sync_mode", "max_gap", "gradient_method",
    "uncorrected_sensors", *common.INTERFERENCE_PARAMETERS, *common.WATCH_PARAMETERS, *common.CALIBRATION_FRAME_PARAMETERS,
    "temperature_tolerance", drift.INTENSITY,
)
SENSOR_SUFFIXES: tuple[str, ...] = ("matrix", "offset", "covariance", "interference", "time_offset",
                                    *common.TEMPERATURE_SUFFIXES)
ARRAY_SUFFIXES: tuple[str, ...] = ("matrix", "offset", "covariance", "interference", *common.TEMPERATURE_SUFFIXES)
"""Per-sensor parameters that are lists of numbers (``time_offset`` is one number)."""
NUMERIC_PARAMETERS: frozenset[str] = frozenset({"positions", "sync_tolerance", "current_tolerance", "max_gap",
                                                "temperature_reference", "output_rotation", "temperature_tolerance"})
"""Parameters that hold numbers besides the per-sensor ones (text that reads as numbers is taken as them)."""
GRADIENT_TOPICS: dict[str, tuple[str, ...]] = {
    "tensor": (topics.GRADIENT, topics.GRADIENT_STAMPED), "baseline": (topics.BASELINE_GRADIENT,), "none": (),
}
"""The gradient topics published for each kind of array geometry."""
UNKNOWN_COVARIANCE = common.UNKNOWN_COVARIANCE
PROVENANCE_IGNORED = ("ignored: not a parameter of {node}; with a calibration, a calibration file's magcal_provenance "
                      "block (what made it: kept in the file, not set on the node)")
"""The answer to a name a ``ros2 param load`` of a calibration file offers that is not this node's."""


def no_events() -> PublisherEventCallbacks:
    """No QoS event handlers for an output publisher. The executor polls every handler of every entity
    each time it wakes (thousands of times a second at 4 x 1000 Hz): the outputs' handlers (incompatible
    QoS and type, two per publisher) were most of that work. A subscriber that asks for more than an
    output offers is still told, by its own handler; the raw subscriptions keep theirs."""
    return PublisherEventCallbacks(use_default_callbacks=False)


@dataclass(frozen=True)
class CorrectionState:
    """Everything a set needs, swapped as one reference when parameters change."""

    calibration: ArrayCalibration
    gradient_method: str
    frame_id: str
    tolerance_ns: int
    missing: tuple[str, ...] = ()
    """Sensors without a calibration and not listed in uncorrected_sensors: no field, no tensor."""
    covariances: tuple[tuple[float, ...], ...] = ()
    """Per sensor, 9 numbers row-major (T^2), or :data:`UNKNOWN_COVARIANCE`."""
    field_covariance: tuple[float, ...] = tuple(UNKNOWN_COVARIANCE)
    """Covariance of the centre field (the mean of the sensors): sum / S^2, or unknown."""
    currents: common.CurrentInputs = common.CurrentInputs()
    """The interference channels' current topics (the calibration's ``channels``)."""
    noise: tuple[float, ...] = ()
    """Per sensor, the noise per axis at calibration (T; 0 unknown): the calibration health's reference."""
    intensity: float = 0.0
    """The intensity (T) the calibration maps ``|B|`` to (0 unknown)."""
    sync_mode: str = sync.DEFAULT_SYNC_MODE
    max_gap_ns: int = 0
    temperature_tolerance_ns: int = 0
    """Largest age of a sensor's temperature at a set (used when the calibration has temperature terms)."""
    calibrated: tuple[str, ...] = ()
    """Sensors with a calibration (matrix and offset given), in set order."""
    watched: common.CurrentInputs = common.CurrentInputs()
    """The current channels whose interference the calibration does not know (``watch_channels``): read, not
    applied; the calibration health names one that varies."""

    def sync_settings(self) -> tuple[Any, ...]:
        """What the set synchroniser is built from (a change rebuilds it)."""
        return (self.names, self.sync_mode, self.max_gap_ns, tuple(self.calibration.time_offsets.tolist()))  # type: ignore[union-attr]

    @property
    def temperatures(self) -> bool:
        """True when every set needs the sensors' temperatures (the calibration has temperature terms)."""
        return self.calibration.has_temperature_terms

    @property
    def heard_temperatures(self) -> bool:
        """True when the sensors' temperatures are subscribed: for temperature terms, or to compare them with
        the temperatures the calibration was made at (then no set waits for them)."""
        return self.temperatures or self.calibration.temperature_span is not None

    @property
    def names(self) -> tuple[str, ...]:
        """Sensor names, in set order."""
        return self.calibration.geometry.names

    @property
    def gradient_kind(self) -> str:
        """``tensor``, ``baseline`` or ``none``: what the positions determine."""
        return self.calibration.geometry.gradient_kind


def _covariances(values: dict[str, Any], cal: ArrayCalibration) -> tuple[tuple[tuple[float, ...], ...], tuple[float, ...]]:
    """Per-sensor covariances (unknown marker where not given) and the centre field's."""
    names = cal.geometry.names
    known: list[np.ndarray | None] = []
    for name in names:
        value = values.get(f"{name}.covariance")
        if value is None:
            known.append(None)
            continue
        c = np.asarray(value, dtype=float).reshape(-1)
        if c.size != 9:
            raise InputError(f"{name}.covariance needs 9 numbers (row-major 3x3, T^2), or -1.0 first for unknown")
        known.append(None if c[0] == -1.0 else c.reshape(3, 3))
    if any(c is not None for c in known):  # validated where the calibration validates covariances
        ArrayCalibration(cal.geometry, cal.matrices, cal.offsets,
                         covariances=np.stack([np.zeros((3, 3)) if c is None else c for c in known]))
    per_sensor = tuple(tuple(UNKNOWN_COVARIANCE) if c is None else tuple(c.reshape(9).tolist()) for c in known)
    if any(c is None for c in known) or not known:
        return per_sensor, tuple(UNKNOWN_COVARIANCE)
    mean = sum(known) / len(known) ** 2  # type: ignore[operator]
    return per_sensor, tuple(np.asarray(mean).reshape(9).tolist())


def calibrated(values: dict[str, Any], name: str) -> bool:
    """Whether sensor ``name`` has a calibration among parameter ``values``: a matrix and an offset, neither
    ``[]`` (the default: not calibrated). An identity and zeros given count."""
    return bool(values.get(f"{name}.matrix")) and bool(values.get(f"{name}.offset"))


def _watched(values: dict[str, Any], currents: common.CurrentInputs) -> common.CurrentInputs:
    """The watched current channels (``watch_*``); :class:`InputError` for one that is also applied."""
    watched = common.current_inputs(values, "watch")
    both = sorted(set(watched.channels) & set(currents.channels))
    if both:
        raise InputError(f"{', '.join(both)} in both interference_channels and watch_channels: a channel's "
                         "interference is either known (applied) or watched")
    return watched


def build_state(values: dict[str, Any]) -> CorrectionState:
    """Validate a complete parameter state (dotted names) and build the correction from it.

    A sensor without a calibration (:func:`calibrated`) is corrected with identity and zero, and is
    ``missing`` unless listed in ``uncorrected_sensors``. Raises :class:`InputError`
    naming what is wrong: sensor names or positions, a matrix, offset or covariance, the
    gradient method, the tolerance, ``sync_mode``, ``max_gap``, a ``time_offset``, the frame or
    ``uncorrected_sensors``.
    """
    names = values.get("sensor_names")
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise InputError("sensor_names must be a list of strings")
    geo = common.geometry(names, values.get("positions"))
    uncorrected = values.get("uncorrected_sensors") or []
    if not isinstance(uncorrected, (list, tuple)) or not all(isinstance(n, str) for n in uncorrected):
        raise InputError("uncorrected_sensors must be a list of sensor names")
    strangers = sorted(set(uncorrected) - set(geo.names))
    if strangers:
        raise InputError(f"uncorrected_sensors names {', '.join(strangers)}, not in sensor_names")
    currents = common.current_inputs(values)
    watched = _watched(values, currents)
    params: dict[str, Any] = {"sensor_names": list(geo.names), "positions": list(geo.positions.reshape(-1)),
                              "interference_channels": list(currents.channels)}
    for name in geo.names:
        params[name] = {
            "matrix": values.get(f"{name}.matrix") or common.IDENTITY,
            "offset": values.get(f"{name}.offset") or common.ZEROS,
            "time_offset": values.get(f"{name}.time_offset") or 0.0,
        }
        if currents.channels:
            gains = values.get(f"{name}.interference") or None  # [] is none
            if gains is None and name not in uncorrected:
                raise InputError(f"interference_channels is set ({', '.join(currents.channels)}) but {name}.interference "
                                 f"is not: give 3 x {len(currents.channels)} numbers (row-major, T/A) for every sensor")
            if gains is not None:
                params[name]["interference"] = list(gains)
        for suffix in common.TEMPERATURE_SUFFIXES:
            if values.get(f"{name}.{suffix}") is not None:
                params[name][suffix] = list(values[f"{name}.{suffix}"])
    for key in common.CALIBRATION_FRAME_PARAMETERS:
        params[key] = values.get(key)
    temperature_tolerance = common.temperature_tolerance_ns(values.get("temperature_tolerance"))
    cal = ArrayCalibration.from_parameters(params)
    done = tuple(n for n in geo.names if calibrated(values, n))
    missing = tuple(n for n in geo.names if n not in done and n not in uncorrected)
    covariances, field_covariance = _covariances(values, cal)
    method = values.get("gradient_method")
    if method not in GRADIENT_METHODS:
        raise InputError(f"unknown gradient_method {method!r}; choose one of {', '.join(GRADIENT_METHODS)}")
    if geo.gradient_kind == "tensor":
        gradient(np.zeros((1, geo.size, 3)), geo, method)  # raises if the geometry does not suit the method
    frame = values.get("frame_id")
    if not isinstance(frame, str) or not frame.strip():
        raise InputError("frame_id must be a non-empty string")
    tolerance = common.tolerance_ns(values.get("sync_tolerance"))
    mode, gap = common.sync_settings(values)
    if mode == "exact" and np.any(cal.time_offsets):  # type: ignore[arg-type]
        lagging = ", ".join(f"{n}.time_offset" for n, t in zip(geo.names, cal.time_offsets) if t)  # type: ignore[arg-type]
        verb = "needs" if lagging.count(",") == 0 else "need"
        raise InputError(f"{lagging} {verb} sync_mode interpolate or auto: exact matching pairs stamps as they are")
    noise, intensity = drift.reference(values, geo.names)
    return CorrectionState(cal, method, frame, tolerance, missing, covariances, field_covariance, currents, noise,
                           intensity, mode, gap, temperature_tolerance, done, watched)


def sync_mode_line(synchronizer: StreamSynchronizer) -> str:
    """How the sets are formed, in words (for the log)."""
    if synchronizer.mode == "interpolate":
        return (f"{synchronizer.names[0]}'s sample instants, the other sensors interpolated (sync_mode "
                f"{synchronizer.requested}: {synchronizer.reason})")
    return f"exact matching of the header stamps (sync_mode {synchronizer.requested}: {synchronizer.reason})"


class CorrectionNode(Node):
    """Applies the array calibration to synchronized raw sets and publishes field and gradient."""

    def __init__(self, node_name: str = NODE_NAME, argv: Sequence[str] = (), **kwargs: Any) -> None:
        services = kwargs.pop("start_parameter_services", True)
        super().__init__(node_name, allow_undeclared_parameters=True, start_parameter_services=False, **kwargs)
        if services:  # rclpy's, but a set_parameters request is applied as a whole (set_request)
            self._parameter_service = common.RequestParameterService(self)
        self._declare_parameters()
        common.check_ranges(self)
        self._state = build_state(self._current_values())
        self._pending: CorrectionState | None = None
        self._subs: list[Any] = []
        self._corrected_pubs: list[Any] = []
        self._gradient_pubs: dict[str, Any] = {}
        self._current_subs: list[Any] = []
        self._watch_subs: list[Any] = []
        self._temperature_subs: list[Any] = []
        self._out: SetOutputs | None = None
        self._out_state: CorrectionState | None = None
        self._listeners = Listeners([])
        depth = int(self.get_parameter("qos_depth").value)
        self._raw_qos = common.raw_qos(str(self.get_parameter("raw_reliability").value), depth)
        self._out_qos = common.output_qos(depth)
        self._limits = common.declare_health(self)
        self._field_pub = self.create_publisher(MagneticField, topics.FIELD, self._out_qos, event_callbacks=no_events())
        self._status_pub = self.create_publisher(DiagnosticStatus, "~/status", 10, event_callbacks=no_events())
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, common.DIAGNOSTICS_TOPIC, 10,
                                                      event_callbacks=no_events())
        self._now = common.clock_reader(self)
        self._arrival = common.arrival_reader(self)
        self._published = 0
        self._withheld = 0
        self._waiting = side.WaitingSets()
        """Sets held while a current or temperature stamped at or before them is due (core/side_streams)."""
        self._ages: list[int] = []
        self._drops = common.DropReporter(self.get_logger())
        self._drift_thresholds = drift.declare_thresholds(self)
        self._calibration_health(self._state)
        self._connect(self._state)
        self._gradient_outputs(self._state.gradient_kind)
        self._connect_currents(self._state.currents)
        self._connect_watched(self._state.watched)
        self.add_pre_set_parameters_callback(common.numbers_from_text(self._numeric))
        self._connect_temperatures(self._state)
        self._outputs_for(self._state)  # now, not at the first set (the first build loads the CDR templates)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        period = float(self.get_parameter("status_period").value)
        self._sim_time = common.SimTimeWatch(self.get_logger())
        common.steady_timer(self, max(period, 0.05), self._report)  # reports go on without /clock (use_sim_time)
        self.create_timer(WAIT_CHECK, self._release_waiting)
        common.steady_timer(self, common.QUIET_CHECK, self._release_quiet)
        self.get_logger().info(
            f"correcting {', '.join(self._state.names)} -> {self._outputs_text(self._state)} in "
            f"{self.get_namespace()}, frame {self._state.frame_id}, sync_mode {self._state.sync_mode}, sync "
            f"tolerance {self._state.tolerance_ns / 1e6:g} ms; {self._describe(self._state)}"
        )
        self._warn_missing(self._state)
        self._warn_unmatched_files(argv)

    # -- parameters -----------------------------------------------------------------
    def _declare_parameters(self) -> None:
        d = common.describe
        names = common.declare_geometry(self)
        for name in names:
            common.declare_list(
                self, f"{name}.matrix", Parameter.Type.DOUBLE_ARRAY,
                d(f"correction matrix of {name}, 9 numbers row-major: raw sensor axes to platform frame "
                  "(B = matrix (raw - offset)); [] = not calibrated (an identity given is a calibration)",
                  constraints="finite, gains 0.1..10, condition < 100", numbers=True),
            )
            common.declare_list(
                self, f"{name}.offset", Parameter.Type.DOUBLE_ARRAY,
                d(f"raw offset of {name}, 3 numbers (T, sensor axes); [] = not calibrated (zeros given are a "
                  "calibration)", constraints="finite, |offset| <= 1e-3 T", numbers=True),
            )
            self.declare_parameter(
                f"{name}.covariance", UNKNOWN_COVARIANCE,
                d(f"covariance of {name}'s corrected vector, 9 numbers row-major (T^2, platform frame), "
                  "published in its magnetic_field_covariance; -1.0 first = unknown",
                  constraints="symmetric positive semi-definite, or -1.0 first", numbers=True),
            )
            common.declare_list(
                self, f"{name}.interference", Parameter.Type.DOUBLE_ARRAY,
                d(f"current interference of {name}: 3 x m numbers row-major (T/A, platform frame), one column per "
                  "channel of interference_channels; B = matrix (raw - offset) - interference @ u; [] = none",
                  constraints="finite; needed for every sensor when interference_channels is set", numbers=True),
            )
            self.declare_parameter(
                f"{name}.time_offset", 0.0,
                d(f"lag of {name} (s): its reading stamped t is the field at t - time_offset (positive: it reads "
                  "late); its stamps are shifted and it is interpolated to the sets' instants (sync_mode "
                  "interpolate or auto)", constraints=f"finite, |t| <= {sync.MAX_TIME_OFFSET:g}", numbers=True,
                  floats=(-sync.MAX_TIME_OFFSET, sync.MAX_TIME_OFFSET)),
            )
            common.declare_list(
                self, f"{name}.offset_per_kelvin", Parameter.Type.DOUBLE_ARRAY,
                d(f"offset temperature coefficient of {name}, 3 numbers (T/K, sensor axes): the offset at temperature T "
                  "is offset + (T - temperature_reference) offset_per_kelvin; [] = 0",
                  constraints="finite, |value| <= 1e-6 T/K", numbers=True),
            )
            common.declare_list(
                self, f"{name}.calibration_temperatures", Parameter.Type.DOUBLE_ARRAY,
                d(f"temperatures of {name} (deg C) the calibration was made at, [min, max]: sets more than 2 K "
                  "outside are counted on /diagnostics and warned of once; [] = unknown",
                  constraints="finite, min <= max, -60 .. 150 deg C, or []", numbers=True),
            )
            common.declare_list(
                self, f"{name}.matrix_per_kelvin", Parameter.Type.DOUBLE_ARRAY,
                d(f"matrix temperature coefficient of {name}, 9 numbers row-major (1/K): the matrix at temperature T is "
                  "matrix + (T - temperature_reference) matrix_per_kelvin; [] = 0",
                  constraints="finite, |value| <= 1e-2 per K", numbers=True),
            )
        common.declare_list(
            self, "temperature_reference", Parameter.Type.DOUBLE_ARRAY,
            d("temperature (deg C) at which matrix and offset hold; with non-zero <name>.offset_per_kelvin or "
              "<name>.matrix_per_kelvin the node subscribes <name>/temperature (sensor_msgs/Temperature) and corrects "
              "every set for each sensor's temperature; [] = no temperature terms",
              constraints="-60 .. 150 deg C, or [] for none", numbers=True),
        )
        common.declare_temperature_tolerance(self)
        common.declare_list(
            self, "output_rotation", Parameter.Type.DOUBLE_ARRAY,
            d("rotation from the array frame to the output frame (frame_id; e.g. the IMU's), 9 numbers row-major: "
              "vectors and field R v, tensor R G R^T, baseline gradient R g; [] = identity",
              constraints="a rotation matrix (orthonormal, determinant +1), or []", numbers=True),
        )
        common.declare_list(
            self, "uncorrected_sensors", Parameter.Type.STRING_ARRAY,
            d("sensors used without a calibration on purpose (raw readings); any other sensor without "
              "matrix and offset stops field and gradient output; [] = none"),
        )
        common.declare_currents(self)
        common.declare_watched(self)
        drift.declare_reference(self, names)
        self.declare_parameter("frame_id", topics.DEFAULT_FRAME_ID,
                               d("frame of all outputs: the platform (array) frame, or the frame output_rotation "
                                 "turns them into (a calibration file made with an IMU sets it to the IMU's)"))
        self.declare_parameter(
            "sync_tolerance", sync.DEFAULT_SYNC_TOLERANCE,
            d("exact matching: largest spread (s) of header stamps within one synchronized set; capped at half "
              "the sample period", constraints="0 < t < 1", numbers=True, floats=common.TOLERANCE_RANGE),
        )
        common.declare_sync(self)
        self.declare_parameter(
            "gradient_method", "difference",
            d("tensor formula: difference (planar cross) or least_squares (any geometry with 3 or more sensors "
              "not on one line)", constraints=" | ".join(GRADIENT_METHODS)),
        )
        self.declare_parameter("raw_reliability", "best_effort", d(common.RELIABILITY_DOC, read_only=True))
        self.declare_parameter("qos_depth", 100, d("history depth of the raw subscriptions and the outputs",
                                                   read_only=True, ints=common.QOS_DEPTH_RANGE))
        self.declare_parameter("status_period", 1.0, d("period (s) of ~/status, /diagnostics and the drop report",
                                                       read_only=True, numbers=True, floats=common.PERIOD_RANGE))

    def _current_values(self) -> dict[str, Any]:
        names = self.list_parameters([], 0).names
        return {n: self.get_parameter_or(n).value for n in names}  # unset parameters: None

    def _numeric(self, name: str) -> bool:
        """Whether parameter ``name`` holds numbers (a known one, or a per-sensor calibration value)."""
        if name in NUMERIC_PARAMETERS or name.endswith(tuple(f".{s}" for s in SENSOR_SUFFIXES)):
            return True
        return self.has_parameter(name) and self.get_parameter(name).type_ in (
            Parameter.Type.DOUBLE, Parameter.Type.INTEGER, *common.NUMBER_ARRAYS)

    def _known(self, name: str, names: Sequence[str]) -> bool:
        if name in CORE_PARAMETERS:
            return True
        stem, _, suffix = name.rpartition(".")
        return suffix in (*SENSOR_SUFFIXES, drift.SENSOR_SUFFIX) and stem in names

    def set_request(self, params: list[Parameter]) -> list[SetParametersResult]:
        """One ``~/set_parameters`` request (``ros2 param set``, ``ros2 param load``), one result per parameter.

        Its calibration parameters (sensors, per-sensor terms, frame, synchronisation: :meth:`_known`) are
        validated and applied together, as one update between two sets: ``ros2 param load`` of a calibration
        file otherwise swaps it in one parameter at a time, and sets in between are corrected with half a new
        calibration. If they do not make a valid state, none is applied and each says why. With a calibration,
        names that are neither this node's nor a sensor's (a calibration file's ``magcal_provenance`` block,
        which ``ros2 param load`` offers with it) are answered ``ignored``. Every other parameter on its own."""
        new_names = next((p.value for p in params if p.name == "sensor_names"), self._state.names)
        names = list(new_names) if isinstance(new_names, (list, tuple)) else []
        group = [i for i, p in enumerate(params) if self._known(p.name, names)]
        calibration = any(params[i].name.rpartition(".")[2] in ("matrix", "offset") for i in group)
        results: list[SetParametersResult | None] = [None] * len(params)
        if len(group) > 1:
            together = self.set_parameters_atomically([params[i] for i in group])
            if not together.successful:
                together = SetParametersResult(successful=False, reason=f"{together.reason} (applied together with "
                                               f"the request's other calibration parameters: none was set)")
            for i in group:
                results[i] = together
        for i, p in enumerate(params):
            if results[i] is None and calibration and i not in group and not self.has_parameter(p.name) \
                    and p.name.split(".")[0] not in names:
                results[i] = SetParametersResult(successful=True, reason=PROVENANCE_IGNORED.format(
                    node=self.get_fully_qualified_name()))
            elif results[i] is None:
                results[i] = self.set_parameters_atomically([p])
        return [r for r in results if r is not None]

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate the combined new state; stash it for :meth:`_after_set_parameters`."""
        values = self._current_values()
        updates = {p.name: p.value for p in params}
        try:
            drift.factors(updates, self._drift_thresholds)
        except InputError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        why = common.out_of_range(self, params)  # what the node's own checks leave (an integer out of range)
        if why:
            return SetParametersResult(successful=False, reason=why)
        values.update(updates)
        new_names = values.get("sensor_names") or []
        for p in params:
            known = self._known(p.name, new_names if isinstance(new_names, (list, tuple)) else [])
            if p.type_ == Parameter.Type.NOT_SET and (known or self.has_parameter(p.name)):
                return SetParametersResult(successful=False, reason=f"{p.name} cannot be unset")
            if not known and not self.has_parameter(p.name):
                return SetParametersResult(
                    successful=False,
                    reason=f"unknown parameter {p.name!r}: per-sensor parameters are <name>.matrix, "
                    f"<name>.offset, <name>.covariance, <name>.interference, <name>.time_offset, "
                    f"<name>.offset_per_kelvin, <name>.matrix_per_kelvin and <name>.calibration_temperatures for a name in "
                    f"sensor_names (ros2 param "
                    f"load also offers a calibration file's magcal_provenance block, which is not for this node: "
                    f"ignored)",
                )
            if known and p.name.endswith(".time_offset") and p.type_ not in (Parameter.Type.DOUBLE,
                                                                             Parameter.Type.INTEGER):
                return SetParametersResult(successful=False,
                                           reason=f"{p.name} must be a number of seconds, got {p.type_.name.lower()}")
            if known and (p.name in ("positions", "output_rotation") or p.name.rpartition(".")[2] in ARRAY_SUFFIXES):
                why = common.check_number_array(p)
                if why:
                    return SetParametersResult(successful=False, reason=why)
        if not any(self._known(n, new_names) for n in updates):
            self._pending = None
            return SetParametersResult(successful=True)
        try:
            self._pending = build_state(values)
        except (InputError, TypeError, ValueError, ArithmeticError) as exc:  # a value of any type may come
            self._pending = None
            reason = str(exc) if isinstance(exc, InputError) else f"invalid value ({exc})"
            self.get_logger().warn(f"rejected parameter update ({', '.join(updates)}): {reason}")
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        """Swap in the validated state (runs between two sets: single-threaded executor)."""
        if any(p.name == "use_sim_time" for p in params):
            self._now = common.clock_reader(self)
            self._arrival = common.arrival_reader(self)
        if any(p.name in drift.FACTORS for p in params):
            self._drift_thresholds = drift.factors({p.name: p.value for p in params}, self._drift_thresholds)
            if self._health_cal is not None:
                self._health_cal.set_factors(self._drift_thresholds.warn_factor, self._drift_thresholds.error_factor)
        new, self._pending = self._pending, None
        if new is None:
            return
        old = self._state
        if new.names != old.names:
            self._disconnect()
            self._state = new
            self._connect(new)
        else:
            self._state = new
            if new.tolerance_ns != old.tolerance_ns:
                self._sync.tolerance_ns = new.tolerance_ns
            if new.sync_settings() != old.sync_settings():
                self._resync(new)
        if new.gradient_kind != old.gradient_kind:
            self._gradient_outputs(new.gradient_kind)
        if new.currents.sources() != old.currents.sources():
            self._connect_currents(new.currents)
        elif new.currents.tolerance_ns != old.currents.tolerance_ns:
            self._currents.tolerance_ns = new.currents.tolerance_ns
            self._current_health.tolerance_ns = new.currents.tolerance_ns
        if new.watched.sources() != old.watched.sources():
            self._connect_watched(new.watched)
        if (new.names, new.heard_temperatures, new.temperature_tolerance_ns) != \
                (old.names, old.heard_temperatures, old.temperature_tolerance_ns):
            self._connect_temperatures(new)
        self.get_logger().info(
            f"parameters updated ({', '.join(p.name for p in params)}): {self._describe(new)}"
            + (f"; now publishing {self._outputs_text(new)}" if new.gradient_kind != old.gradient_kind else "")
        )
        if new.missing != old.missing:
            self._warn_missing(new)
        self._calibration_health(new)

    def _calibration_health(self, state: CorrectionState) -> None:
        """Judge the calibration of ``state`` afresh (its sets only), or say why it is not judged."""
        self._drifted = False
        self._current_watch = CurrentWatch(state.watched.channels)
        """The watched channels' latest readings and which varied (a new calibration: a new watch)."""
        self._span_health = TemperatureSpanHealth(state.names, state.calibration.temperature_span)
        uncalibrated = [n for n in state.names if n not in state.calibrated]
        if uncalibrated:
            self._health_cal: CalibrationHealth | None = None
            self._not_judged = drift.not_assessed(f"{', '.join(uncalibrated)} not calibrated")
            return
        noise = [v if v > 0 else float("nan") for v in state.noise]
        self._health_cal = CalibrationHealth(state.calibration.geometry, noise, state.intensity or None,
                                             self._drift_thresholds)

    @staticmethod
    def _outputs_text(state: CorrectionState) -> str:
        gradients = GRADIENT_TOPICS[state.gradient_kind]
        what = {"tensor": "", "baseline": f" ({state.names[0]} to {state.names[-1]}: sensors on one line)",
                "none": " (one sensor position: no gradient)"}[state.gradient_kind]
        method = f" ({state.gradient_method})" if state.gradient_kind == "tensor" else ""
        return ", ".join(["<name>/corrected", topics.FIELD, *gradients]) + method + what

    def _describe(self, state: CorrectionState) -> str:
        names = state.names
        done = state.calibrated
        raw = [n for n in names if n not in done and n not in state.missing]
        parts = [f"calibrated sensors: {', '.join(done)}" if done else "no calibration loaded"]
        if raw:
            parts.append(f"uncorrected on purpose: {', '.join(raw)}")
        lags = [f"{n} {t * 1e3:g} ms" for n, t in zip(names, state.calibration.time_offsets) if t]  # type: ignore[arg-type]
        if lags:
            parts.append("time offsets " + ", ".join(lags))
        if state.currents.channels:
            parts.append("subtracting current interference of " + ", ".join(
                f"{c} ({t}, {k.rsplit('/', 1)[-1]})" for c, t, k in state.currents.sources()))
        if state.watched.channels:
            parts.append("watching the currents of " + ", ".join(
                f"{c} ({t})" for c, t, _ in state.watched.sources()) + " (interference unknown: named when they vary)")
        cal = state.calibration
        if state.temperatures:
            parts.append(f"correcting for temperature about {cal.temperature_reference:g} deg C "
                         f"(<name>/temperature within {state.temperature_tolerance_ns / 1e9:g} s)")
        if cal.temperature_span is not None:
            parts.append("comparing <name>/temperature with the temperatures the calibration was made at "
                         "(<name>.calibration_temperatures)")
        if cal.rotated:
            parts.append(f"outputs turned by output_rotation into {state.frame_id}")
        return "; ".join(parts)

    def _warn_missing(self, state: CorrectionState) -> None:
        if state.missing:
            names = [topics.FIELD, *GRADIENT_TOPICS[state.gradient_kind]]
            outputs = " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)
            verb = "are" if len(names) > 1 else "is"
            self.get_logger().warn(
                f"no calibration (matrix and offset) for {', '.join(state.missing)}: {outputs} {verb} NOT published, "
                f"nor the corrected vectors of these sensors; load a calibration file with every sensor, call the "
                f"calibration node's ~/calibrate, or list the sensors in uncorrected_sensors to use their raw "
                f"readings on purpose"
            )
        else:
            self.get_logger().info("every sensor calibrated or uncorrected on purpose: publishing field and gradient")

    def _warn_unmatched_files(self, argv: Sequence[str]) -> None:
        """Warn about a params file whose calibration block is keyed for another node (so not loaded)."""
        me = self.get_fully_qualified_name()
        for path, key in common.unmatched_calibrations(common.params_files(argv), me):
            self.get_logger().warn(
                f"params file {path}: the calibration under '{key}' does not apply to this node ({me}) and was "
                f"NOT loaded; key it '{me}' (or '/**/{self.get_name()}') to load it here"
            )

    # -- topics ---------------------------------------------------------------------
    def _synchronizer(self, state: CorrectionState, stats: sync.SyncStats | None = None) -> StreamSynchronizer:
        return common.synchronizer(state.names, state.tolerance_ns, state.sync_mode, state.max_gap_ns,
                                   state.calibration.time_offsets.tolist(), stats)  # type: ignore[union-attr]

    def _resync(self, state: CorrectionState) -> None:
        """A new synchroniser for changed sync settings or time offsets (what was queued is dropped, counted)."""
        old = self._sync
        placed = old.placements() if list(old.names) == list(state.names) else None
        old.reset()
        self._sync = self._synchronizer(state, old.stats)
        self._sync.keep_placements(placed)  # a sensor that restarted stays where its stamps were placed
        self._sync.set_pause(self._limits.silent_after_ns)
        self._health.sync = self._sync
        self._sync_reason = ""
        self.get_logger().info("set synchroniser restarted for the new sync settings or time offsets")

    def _connect(self, state: CorrectionState) -> None:
        self._sync = self._synchronizer(state)
        self._sync_reason = ""
        self._health = ArrayHealth(state.names, self._sync, self._limits, common.now_ns(self))
        self._drops.reset()
        self._corrected_pubs = [
            self.create_publisher(MagneticField, topics.corrected(n), self._out_qos, event_callbacks=no_events())
            for n in state.names
        ]
        self._out_state = None
        self._subs = [
            self.create_subscription(
                MagneticField, topics.raw(n), self._raw_callback(i), self._raw_qos, raw=True
            )
            for i, n in enumerate(state.names)
        ]

    def _disconnect(self) -> None:
        for s in self._subs:
            self.destroy_subscription(s)
        for p in self._corrected_pubs:
            self.destroy_publisher(p)
        self._subs, self._corrected_pubs = [], []

    def _gradient_outputs(self, kind: str) -> None:
        """Advertise the gradient topics of ``kind`` (and no other)."""
        for pub in self._gradient_pubs.values():
            self.destroy_publisher(pub)
        types = {topics.GRADIENT: Float64MultiArray, topics.GRADIENT_STAMPED: JointState,
                 topics.BASELINE_GRADIENT: Vector3Stamped}
        self._gradient_pubs = {t: self.create_publisher(types[t], t, self._out_qos, event_callbacks=no_events())
                               for t in GRADIENT_TOPICS[kind]}
        self._out_state = None

    def _connect_currents(self, inputs: common.CurrentInputs) -> None:
        """Subscribe the current channels afresh (their values so far are dropped)."""
        for s in self._current_subs:
            self.destroy_subscription(s)
        self._currents = LatestCurrents(len(inputs.channels), inputs.tolerance_ns, check=side.CURRENT.check)
        self._current_health = CurrentHealth(inputs.channels, tuple(self.resolve_topic_name(t) for t in inputs.topics),
                                             inputs.tolerance_ns)
        self._current_subs = common.subscribe_currents(self, inputs, self._currents, self._raw_qos,
                                                       lambda: self._now())

    def _connect_watched(self, inputs: common.CurrentInputs) -> None:
        """Subscribe the watched channels afresh: their readings go to the calibration health's current watch."""
        for s in self._watch_subs:
            self.destroy_subscription(s)
        node = self

        class Forward:
            """The subscriptions' store: the node's current watch of the moment."""

            @staticmethod
            def add(index: int, stamp: int, value: float) -> None:
                node._current_watch.add(index, stamp, value)

        self._watch_subs = common.subscribe_currents(self, inputs, Forward(), self._raw_qos, lambda: self._now())

    def _connect_temperatures(self, state: CorrectionState) -> None:
        """Subscribe every ``<name>/temperature`` afresh when the calibration has temperature terms (else none)."""
        for s in self._temperature_subs:
            self.destroy_subscription(s)
        names = state.names if state.heard_temperatures else ()
        self._temperatures = LatestValues(len(names), state.temperature_tolerance_ns, check=side.TEMPERATURE.check,
                                          keep_ns=max(2 * state.temperature_tolerance_ns, KEEP_NS))
        self._temperature_health = TemperatureHealth(
            names, tuple(self.resolve_topic_name(topics.temperature(n)) for n in names), state.temperature_tolerance_ns)
        self._temperature_subs = common.subscribe_temperatures(self, names, self._temperatures, self._raw_qos,
                                                               lambda: self._now())

    def _raw_callback(self, index: int) -> Any:
        decode, publish = decode_magnetic_field, self._publish

        def callback(data: bytes, info: dict[str, Any]) -> None:
            try:
                stamp, x, y, z = decode(data)
            except (InputError, struct.error):
                self._sync.stats.malformed += 1
                return
            self._health.seen(index, stamp)
            for synced in self._sync.add(index, stamp, x, y, z, self._arrival(info)):
                publish(synced)

        return callback

    def _outputs_for(self, state: CorrectionState) -> SetOutputs:
        """The packers and correction map of ``state`` (rebuilt when the state or the publishers change)."""
        self._out = SetOutputs(state.calibration, state.gradient_method, state.frame_id, state.covariances,
                               state.field_covariance)
        self._out_state = state
        self._listeners = Listeners([*self._corrected_pubs, self._field_pub, *self._gradient_pubs.values()])
        return self._out

    def _publish(self, synced: SyncedSet) -> None:
        """Correct one set now, or once the currents and temperatures due at its stamp came (at most
        :data:`~magcal_ros.core.side_streams.MAX_WAIT` later; the sets in the order they formed)."""
        state = self._state
        if not (state.currents.channels or state.temperatures) and not self._waiting:
            self._correct(synced)
            return
        self._waiting.add(synced.stamp, self._now(), synced)
        self._release_waiting()

    def _release_quiet(self) -> None:
        """Publish the sets completed by messages held for a sensor that fell quiet (the synchroniser decides
        them as at the end of its stream once it has been quiet for its hold, on the arrivals' clock)."""
        for synced in self._sync.release_quiet(self._now()):
            self._publish(synced)

    def _release_waiting(self) -> None:
        """Correct the held sets nothing is due for any more (or that waited long enough)."""
        if self._waiting:
            for synced in self._waiting.release(self._now(), self._side_due):
                self._correct(synced)

    def _side_due(self, stamp: int) -> bool:
        """Whether a current or temperature stamped at or before ``stamp`` (ns) is due and has not come."""
        state = self._state
        return bool((state.currents.channels and self._currents.due(stamp))
                    or (state.temperatures and self._temperatures.due(stamp)))

    def _correct(self, synced: SyncedSet) -> None:
        """Correct one set; publish corrected vectors, then field and the gradient topics (each only when
        somebody subscribes it)."""
        state = self._state
        out = self._out if self._out_state is state else self._outputs_for(state)
        currents = temperatures = None
        stale = False
        if state.currents.channels:
            currents, fresh = self._currents.at(synced.stamp)
            stale = not self._current_health.count(fresh)
        if state.temperatures:
            temperatures, fresh = self._temperatures.at(synced.stamp)
            stale = not self._temperature_health.count(fresh) or stale
        if stale:
            self._withheld += 1  # never corrected with a stale current or temperature
            return
        if self._span_health.watch is not None:
            self._watch_temperatures(synced.stamp, temperatures)
        listeners = self._listeners
        listeners.tick()
        health = self._health_cal
        if listeners.any or health is not None:
            cal = state.calibration
            y = out.values(cal, state.gradient_method, synced.values, currents, temperatures)
            s3 = 3 * out.sensors
            if health is not None:  # judged in the array frame, where the positions are
                vectors = y[:s3].reshape(-1, 3)
                health.add(synced.stamp, vectors if cal.output_rotation is None else vectors @ cal.output_rotation)
            if listeners.any:
                self._send(state, out, synced, y.tolist(), listeners.listening)
        if state.missing:
            self._withheld += 1
            return
        self._published += 1
        self._ages.append(self._now() - synced.stamp)

    def _watch_temperatures(self, stamp: int, temperatures: list[float] | None) -> None:
        """Compare the sensors' temperatures at a set (those it is corrected with, else the latest heard) with
        those the calibration was made at; one WARN line when a sensor first leaves them."""
        fresh = [True] * len(self._state.names)
        if temperatures is None:
            temperatures, fresh = self._temperatures.at(stamp)
        first = self._span_health.count(temperatures, fresh)
        watch = self._span_health.watch
        if not first or watch is None:
            return
        where = []
        for name in first:
            i = watch.names.index(name)
            where.append(f"{name} at {temperatures[i]:.1f} C (calibrated at {watch.span[i][0]:.1f}..{watch.span[i][1]:.1f} C)")
        self.get_logger().warn(
            f"beyond the temperatures the calibration was made at (more than {watch.margin:g} K): {', '.join(where)}; "
            "the calibration is applied where it extrapolates (counted per sensor as "
            "<name>.temperature_beyond_calibration on /diagnostics; said once per sensor)")

    def _send(self, state: CorrectionState, out: SetOutputs, synced: SyncedSet, y: list[float],
              listening: list[bool]) -> None:
        """Pack and publish the outputs of one set somebody listens to (``y``: :meth:`SetOutputs.values`)."""
        missing = state.missing
        s = out.sensors
        for k, (stamp, packer, pub) in enumerate(zip(synced.stamps, out.corrected, self._corrected_pubs)):
            if listening[k] and not (missing and state.names[k] in missing):
                pub.publish(packer.pack(stamp, y[3 * k], y[3 * k + 1], y[3 * k + 2]))
        if missing:
            return
        stamp, c = synced.stamp, 3 * s
        if listening[s]:
            self._field_pub.publish(out.field.pack(stamp, y[c], y[c + 1], y[c + 2]))
        if out.gradient is not None and out.stamped is not None:
            components = y[c + 3 : c + 12]
            if listening[s + 1]:
                self._gradient_pubs[topics.GRADIENT].publish(out.gradient.pack(components))
            if listening[s + 2]:
                self._gradient_pubs[topics.GRADIENT_STAMPED].publish(out.stamped.pack(stamp, components))
        elif out.baseline is not None and listening[s + 1]:
            self._gradient_pubs[topics.BASELINE_GRADIENT].publish(out.baseline.pack(stamp, y[c + 3], y[c + 4], y[c + 5]))

    # -- reporting ------------------------------------------------------------------
    def _counters(self) -> dict[str, int]:
        c = self._sync.stats.as_dict()
        c["published"] = self._published
        c["withheld"] = self._withheld
        c["pending"] = self._sync.pending
        return c

    def _report(self) -> None:
        """Publish ~/status and /diagnostics; log (throttled) what was dropped."""
        if self._sync.reason and self._sync.reason != self._sync_reason:
            self._sync_reason = self._sync.reason
            self.get_logger().info(f"sets: {sync_mode_line(self._sync)}")
        counters = self._counters()
        self._drops.update(counters, f"{counters['published']} sets published in total")
        now = common.now_ns(self)
        self._health.output(self._published, now)
        state = self._state
        extras = [f"not calibrated: {', '.join(state.missing)} (see uncorrected_sensors)"] if state.missing else []
        stale, current_values = self._current_health.assess(self._currents, "withheld")
        if stale:
            extras.append(stale)
        stale, temperature_values = self._temperature_health.assess(self._temperatures, "withheld")
        beyond, span_values = self._span_health.assess()
        temperature_values.update(span_values)
        extras += [beyond] if beyond else []
        clock = self._sim_time.problem(bool(self.get_parameter("use_sim_time").value), now)
        extras += [x for x in (stale, clock) if x]
        assessment = self._health.assess(now, counters, "sets published", "; ".join(extras) or None)
        assessment.values.update(current_values)
        assessment.values.update(temperature_values)
        for line in assessment.notices:
            self.get_logger().warn(line)
        ages, self._ages = self._ages, []
        if ages:
            p50, p99, pmax = np.percentile(np.asarray(ages, dtype=float) / 1e6, [50.0, 99.0, 100.0])
            assessment.values.update(age_ms_p50=f"{p50:.3f}", age_ms_p99=f"{p99:.3f}", age_ms_max=f"{pmax:.3f}")
        status = common.diagnostic_status(self.get_fully_qualified_name(), common.hardware_id(self, state.names),
                                          assessment)
        self._status_pub.publish(status)
        calibration = self._report_calibration(state)
        self._diagnostics_pub.publish(common.diagnostic_array(self, [status, calibration]))

    def _report_calibration(self, state: CorrectionState) -> DiagnosticStatus:
        """The calibration health's status; a drift (and its end) is logged once."""
        report = self._health_cal.assess() if self._health_cal is not None else self._not_judged
        if self._health_cal is not None:
            for name in self._current_watch.judge():
                self.get_logger().warn(f"{self._current_watch.named[name]}, and the calibration does not know its "
                                       "interference: the corrected outputs carry its field; recalibrate (the "
                                       "calibration node with it among its interference_channels learns it)")
            report = with_unknown_currents(report, self._current_watch.named)
        if report.drifted != self._drifted:
            self._drifted = report.drifted
            if report.drifted:
                self.get_logger().warn(report.message)
            else:
                self.get_logger().info(f"calibration health back to normal: {report.message}")
        return drift.status(self.get_fully_qualified_name(), common.hardware_id(self, state.names), report)


def main(args: Sequence[str] | None = None, stop: StopFlag | None = None) -> int:
    """Run the node (``ros2 run magcal_ros correction_node`` goes through :mod:`magcal_ros.nodes.entry`)."""
    return common.run_node(lambda argv: CorrectionNode(argv=argv), SingleThreadedExecutor, args, stop)


if __name__ == "__main__":
    raise SystemExit(main())

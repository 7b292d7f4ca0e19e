"""Live correction node: raw sensor vectors in, corrected vectors, centre field and tensor out.

Subscribes ``<name>/raw`` (sensor_msgs/MagneticField, T) for every name in
``sensor_names``, groups the messages into synchronized sets by header stamp and, per
set, publishes ``<name>/corrected`` (``matrix @ (raw - offset)``, platform frame, with
``<name>.covariance``), ``field`` (centre field, T, covariance of the mean),
``gradient`` (std_msgs/Float64MultiArray, 3x3 row-major, ``G[i][j] = dB_j/dx_i`` in T/m)
and ``gradient_stamped`` (sensor_msgs/JointState: the same nine components in
``position``, named ``gradient.xx`` ... ``gradient.zz``, stamped with the set's stamp and
``frame_id``). All are relative names: a namespace or a remap moves them. The
calibration comes from parameters (``<name>.matrix``, ``<name>.offset``,
``<name>.covariance``, ``positions``) and can be replaced at runtime through the standard
parameter services; a replacement is validated as a whole and swapped in between two
sets, an invalid one is rejected with a reason.

A sensor whose matrix and offset were never given (params file, ``-p`` or a parameter
update) is not calibrated: the node warns, naming it, and publishes neither ``field`` nor
the tensor (nor that sensor's corrected vector) until it is, unless the sensor is listed
in ``uncorrected_sensors`` (its raw reading is then used on purpose).

Every ``status_period`` s: ``~/status`` (diagnostic_msgs/DiagnosticStatus) and the same
status on ``/diagnostics`` (DiagnosticArray): level, message (what is wrong, naming
sensors) and values: per sensor ``received``, ``lost`` (estimated from gaps in its stamp
sequence: lost before reaching the node), ``gaps``, ``period_ms``; the synchroniser's
counters (``sets``, ``unmatched``, ``nonfinite``, ``duplicate``, ``out_of_order``,
``zero_stamp``, ``malformed``, ``restarts``), ``published``, ``withheld`` (sets not
published for want of a calibration), ``pending``, ``sync_window_ms`` and, when sets were
published, ``age_ms_p50/p99/max``: node clock at publication minus the set's stamp (a
latency when the sensors stamp with the same clock; simulated time with use_sim_time).

Usage::

    ros2 run magcal_ros correction_node --ros-args --params-file calibration.yaml
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState, MagneticField
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from magcal_ros.core import sync
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.sync import SetSynchronizer, SyncedSet
from magcal_ros.core.tensor import GRADIENT_METHODS, gradient
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.cdr import decode_magnetic_field
from magcal_ros.io.csv_recording import TENSOR_COLUMNS
from magcal_ros.nodes import common
from magcal_ros.nodes.health import ArrayHealth

NODE_NAME = "magcal_correction"
CORE_PARAMETERS: tuple[str, ...] = (
    "sensor_names", "positions", "frame_id", "sync_tolerance", "gradient_method", "uncorrected_sensors",
)
SENSOR_SUFFIXES: tuple[str, ...] = ("matrix", "offset", "covariance")
UNKNOWN_COVARIANCE = common.UNKNOWN_COVARIANCE


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

    @property
    def names(self) -> tuple[str, ...]:
        """Sensor names, in set order."""
        return self.calibration.geometry.names


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


def build_state(values: dict[str, Any], given: frozenset[str] | set[str] | None = None) -> CorrectionState:
    """Validate a complete parameter state (dotted names) and build the correction from it.

    ``given``: names of the parameters set from outside (params file, ``-p``, updates);
    None means every per-sensor value counts as given. Raises :class:`InputError`
    naming what is wrong: sensor names or positions, a matrix, offset or covariance, the
    gradient method, the tolerance, the frame or ``uncorrected_sensors``.
    """
    names = values.get("sensor_names")
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise InputError("sensor_names must be a list of strings")
    geo = common.geometry(names, values.get("positions", []))
    uncorrected = values.get("uncorrected_sensors") or []
    if not all(isinstance(n, str) for n in uncorrected):
        raise InputError("uncorrected_sensors must be a list of sensor names")
    strangers = sorted(set(uncorrected) - set(geo.names))
    if strangers:
        raise InputError(f"uncorrected_sensors names {', '.join(strangers)}, not in sensor_names")
    params: dict[str, Any] = {"sensor_names": list(geo.names), "positions": list(geo.positions.reshape(-1))}
    for name in geo.names:
        params[name] = {
            "matrix": values.get(f"{name}.matrix", common.IDENTITY),
            "offset": values.get(f"{name}.offset", common.ZEROS),
        }
    cal = ArrayCalibration.from_parameters(params)
    missing = tuple(
        n for n in geo.names
        if given is not None and not {f"{n}.matrix", f"{n}.offset"} <= set(given) and n not in uncorrected
    )
    covariances, field_covariance = _covariances(values, cal)
    method = values.get("gradient_method")
    if method not in GRADIENT_METHODS:
        raise InputError(f"unknown gradient_method {method!r}; choose one of {', '.join(GRADIENT_METHODS)}")
    gradient(np.zeros((1, geo.size, 3)), geo, method)  # raises if the geometry does not suit the method
    frame = values.get("frame_id")
    if not isinstance(frame, str) or not frame.strip():
        raise InputError("frame_id must be a non-empty string")
    return CorrectionState(cal, method, frame, common.tolerance_ns(values.get("sync_tolerance")), missing,
                           covariances, field_covariance)


def _gradient_message() -> Float64MultiArray:
    """A gradient message with the contract's 3x3 row-major layout (dims row, col)."""
    msg = Float64MultiArray()
    msg.layout.dim = [
        MultiArrayDimension(label="row", size=3, stride=9),
        MultiArrayDimension(label="col", size=3, stride=3),
    ]
    msg.layout.data_offset = 0
    msg.data = [0.0] * 9
    return msg


class CorrectionNode(Node):
    """Applies the array calibration to synchronized raw sets and publishes the tensor."""

    def __init__(self, node_name: str = NODE_NAME, argv: Sequence[str] = (), **kwargs: Any) -> None:
        super().__init__(node_name, allow_undeclared_parameters=True, **kwargs)
        self._declare_parameters()
        self._given: set[str] = set(self._parameter_overrides)
        self._state = build_state(self._current_values(), self._given)
        self._pending: CorrectionState | None = None
        self._pending_names: set[str] = set()
        self._subs: list[Any] = []
        self._corrected_pubs: list[Any] = []
        self._corrected_msgs: list[MagneticField] = []
        self._msg_state: CorrectionState | None = None
        depth = int(self.get_parameter("qos_depth").value)
        self._raw_qos = common.raw_qos(str(self.get_parameter("raw_reliability").value), depth)
        self._out_qos = common.output_qos(depth)
        self._limits = common.declare_health(self)
        self._field_pub = self.create_publisher(MagneticField, topics.FIELD, self._out_qos)
        self._gradient_pub = self.create_publisher(Float64MultiArray, topics.GRADIENT, self._out_qos)
        self._stamped_pub = self.create_publisher(JointState, topics.GRADIENT_STAMPED, self._out_qos)
        self._status_pub = self.create_publisher(DiagnosticStatus, "~/status", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, common.DIAGNOSTICS_TOPIC, 10)
        self._field_msg = MagneticField()
        self._gradient_msg = _gradient_message()
        self._stamped_msg = JointState(name=list(TENSOR_COLUMNS))
        self._now = common.clock_reader(self)
        self._published = 0
        self._withheld = 0
        self._ages: list[int] = []
        self._drops = common.DropReporter(self.get_logger())
        self._connect(self._state)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        period = float(self.get_parameter("status_period").value)
        self.create_timer(max(period, 0.05), self._report)
        self.get_logger().info(
            f"correcting {', '.join(self._state.names)} -> <name>/corrected, field, gradient, gradient_stamped "
            f"({self._state.gradient_method}) in {self.get_namespace()}, frame {self._state.frame_id}, "
            f"sync tolerance {self._state.tolerance_ns / 1e6:g} ms; {self._describe(self._state)}"
        )
        self._warn_missing(self._state)
        self._warn_unmatched_files(argv)

    # -- parameters -----------------------------------------------------------------
    def _declare_parameters(self) -> None:
        d = common.describe
        names = self.declare_parameter(
            "sensor_names", common.DEFAULT_SENSOR_NAMES, d(common.SENSOR_NAMES_DOC)
        ).value
        self.declare_parameter("positions", common.DEFAULT_POSITIONS, d(common.POSITIONS_DOC, numbers=True))
        for name in names:
            self.declare_parameter(
                f"{name}.matrix", common.IDENTITY,
                d(f"correction matrix of {name}, 9 numbers row-major: raw sensor axes to platform frame "
                  "(B = matrix (raw - offset)); not given = not calibrated",
                  constraints="finite, gains 0.1..10, condition < 100", numbers=True),
            )
            self.declare_parameter(
                f"{name}.offset", common.ZEROS,
                d(f"raw offset of {name}, 3 numbers (T, sensor axes); not given = not calibrated",
                  constraints="finite, |offset| <= 1e-3 T", numbers=True),
            )
            self.declare_parameter(
                f"{name}.covariance", UNKNOWN_COVARIANCE,
                d(f"covariance of {name}'s corrected vector, 9 numbers row-major (T^2, platform frame), "
                  "published in its magnetic_field_covariance; -1.0 first = unknown",
                  constraints="symmetric positive semi-definite, or -1.0 first", numbers=True),
            )
        self.declare_parameter(
            "uncorrected_sensors", Parameter.Type.STRING_ARRAY,
            d("sensors used without a calibration on purpose (raw readings); any other sensor without "
              "matrix and offset stops field and tensor output"),
        )
        self.declare_parameter("frame_id", topics.DEFAULT_FRAME_ID, d("frame of all outputs (platform frame)"))
        self.declare_parameter(
            "sync_tolerance", sync.DEFAULT_SYNC_TOLERANCE,
            d("largest spread (s) of header stamps within one synchronized set; capped at half the sample "
              "period", constraints="0 < t < 1", numbers=True, floats=common.TOLERANCE_RANGE),
        )
        self.declare_parameter(
            "gradient_method", "difference",
            d("tensor formula: difference (planar cross) or least_squares (any geometry)",
              constraints=" | ".join(GRADIENT_METHODS)),
        )
        self.declare_parameter("raw_reliability", "best_effort", d(common.RELIABILITY_DOC, read_only=True))
        self.declare_parameter("qos_depth", 100, d("history depth of the raw subscriptions and the outputs",
                                                   read_only=True, ints=common.QOS_DEPTH_RANGE))
        self.declare_parameter("status_period", 1.0, d("period (s) of ~/status, /diagnostics and the drop report",
                                                       read_only=True, numbers=True, floats=common.PERIOD_RANGE))

    def _current_values(self) -> dict[str, Any]:
        names = self.list_parameters([], 0).names
        return {n: self.get_parameter_or(n).value for n in names}  # uncorrected_sensors may be unset: None

    def _known(self, name: str, names: Sequence[str]) -> bool:
        if name in CORE_PARAMETERS:
            return True
        stem, _, suffix = name.rpartition(".")
        return suffix in SENSOR_SUFFIXES and stem in names

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate the combined new state; stash it for :meth:`_after_set_parameters`."""
        values = self._current_values()
        updates = {p.name: p.value for p in params}
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
                    f"<name>.offset and <name>.covariance for a name in sensor_names",
                )
            if known and (p.name == "positions" or p.name.endswith(SENSOR_SUFFIXES)):
                why = common.check_number_array(p)
                if why:
                    return SetParametersResult(successful=False, reason=why)
        if not any(self._known(n, new_names) for n in updates):
            self._pending = None
            return SetParametersResult(successful=True)
        try:
            self._pending = build_state(values, self._given | set(updates))
            self._pending_names = set(updates)
        except InputError as exc:
            self._pending = None
            self.get_logger().warn(f"rejected parameter update ({', '.join(updates)}): {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        """Swap in the validated state (runs between two sets: single-threaded executor)."""
        if any(p.name == "use_sim_time" for p in params):
            self._now = common.clock_reader(self)
        new, self._pending = self._pending, None
        if new is None:
            return
        self._given |= self._pending_names
        old = self._state
        if new.names != old.names:
            self._disconnect()
            self._state = new
            self._connect(new)
        else:
            self._state = new
            if new.tolerance_ns != old.tolerance_ns:
                self._sync.tolerance_ns = new.tolerance_ns
        self.get_logger().info(
            f"parameters updated ({', '.join(p.name for p in params)}): {self._describe(new)}"
        )
        if new.missing != old.missing:
            self._warn_missing(new)

    def _describe(self, state: CorrectionState) -> str:
        names = state.names
        calibrated = [n for n in names if {f"{n}.matrix", f"{n}.offset"} <= self._given]
        raw = [n for n in names if n not in calibrated and n not in state.missing]
        parts = [f"calibrated sensors: {', '.join(calibrated)}" if calibrated else "no calibration loaded"]
        if raw:
            parts.append(f"uncorrected on purpose: {', '.join(raw)}")
        return "; ".join(parts)

    def _warn_missing(self, state: CorrectionState) -> None:
        if state.missing:
            self.get_logger().warn(
                f"no calibration (matrix and offset) for {', '.join(state.missing)}: field, gradient and "
                f"gradient_stamped are NOT published, nor the corrected vectors of these sensors; load a "
                f"calibration file with every sensor, call the calibration node's ~/calibrate, or list the "
                f"sensors in uncorrected_sensors to use their raw readings on purpose"
            )
        else:
            self.get_logger().info("every sensor calibrated or uncorrected on purpose: publishing field and tensor")

    def _warn_unmatched_files(self, argv: Sequence[str]) -> None:
        """Warn about a params file whose calibration block is keyed for another node (so not loaded)."""
        me = self.get_fully_qualified_name()
        for path, key in common.unmatched_calibrations(common.params_files(argv), me):
            self.get_logger().warn(
                f"params file {path}: the calibration under '{key}' does not apply to this node ({me}) and was "
                f"NOT loaded; key it '{me}' (or '/**/{self.get_name()}') to load it here"
            )

    # -- topics ---------------------------------------------------------------------
    def _connect(self, state: CorrectionState) -> None:
        self._sync = SetSynchronizer(len(state.names), state.tolerance_ns)
        self._health = ArrayHealth(state.names, self._sync, self._limits, common.now_ns(self))
        self._drops.reset()
        self._corrected_pubs = [
            self.create_publisher(MagneticField, topics.corrected(n), self._out_qos) for n in state.names
        ]
        self._corrected_msgs = [MagneticField() for _ in state.names]
        self._msg_state = None
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

    def _raw_callback(self, index: int) -> Any:
        add, decode, seen = self._sync.add, decode_magnetic_field, self._health.seen

        def callback(data: bytes) -> None:
            try:
                sample = decode(data)
            except (InputError, struct.error):
                self._sync.stats.malformed += 1
                return
            seen(index, sample[0])
            synced = add(index, *sample)
            if synced is not None:
                self._publish(synced)

        return callback

    def _apply_covariances(self, state: CorrectionState) -> None:
        """Put the state's covariances into the reused output messages."""
        for msg, cov in zip(self._corrected_msgs, state.covariances):
            msg.magnetic_field_covariance = list(cov)
        self._field_msg.magnetic_field_covariance = list(state.field_covariance)
        self._msg_state = state

    def _publish(self, synced: SyncedSet) -> None:
        """Correct one set; publish corrected vectors, then field, gradient and gradient_stamped."""
        state = self._state
        if state is not self._msg_state:
            self._apply_covariances(state)
        raw = np.array(synced.values, dtype=float).reshape(1, -1, 3)
        vectors, centre, tensor = state.calibration.field_and_gradient(raw, state.gradient_method)
        frame = state.frame_id
        missing = state.missing
        for name, msg, pub, stamp, v in zip(state.names, self._corrected_msgs, self._corrected_pubs, synced.stamps,
                                            vectors[0].tolist()):
            if missing and name in missing:
                continue
            common.set_stamp(msg.header.stamp, stamp)
            msg.header.frame_id = frame
            f = msg.magnetic_field
            f.x, f.y, f.z = v
            pub.publish(msg)
        if missing:
            self._withheld += 1
            return
        msg = self._field_msg
        common.set_stamp(msg.header.stamp, synced.stamp)
        msg.header.frame_id = frame
        f = msg.magnetic_field
        f.x, f.y, f.z = centre[0].tolist()
        self._field_pub.publish(msg)
        components = tensor[0].reshape(9).tolist()
        self._gradient_msg.data = components
        self._gradient_pub.publish(self._gradient_msg)
        stamped = self._stamped_msg
        common.set_stamp(stamped.header.stamp, synced.stamp)
        stamped.header.frame_id = frame
        stamped.position = components
        self._stamped_pub.publish(stamped)
        self._published += 1
        self._ages.append(self._now() - synced.stamp)

    # -- reporting ------------------------------------------------------------------
    def _counters(self) -> dict[str, int]:
        c = self._sync.stats.as_dict()
        c["published"] = self._published
        c["withheld"] = self._withheld
        c["pending"] = self._sync.pending
        return c

    def _report(self) -> None:
        """Publish ~/status and /diagnostics; log (throttled) what was dropped."""
        counters = self._counters()
        self._drops.update(counters, f"{counters['published']} sets published in total")
        now = common.now_ns(self)
        self._health.output(self._published, now)
        state = self._state
        extra = f"not calibrated: {', '.join(state.missing)} (see uncorrected_sensors)" if state.missing else None
        assessment = self._health.assess(now, counters, "sets published", extra)
        for line in assessment.notices:
            self.get_logger().warn(line)
        ages, self._ages = self._ages, []
        if ages:
            p50, p99, pmax = np.percentile(np.asarray(ages, dtype=float) / 1e6, [50.0, 99.0, 100.0])
            assessment.values.update(age_ms_p50=f"{p50:.3f}", age_ms_p99=f"{p99:.3f}", age_ms_max=f"{pmax:.3f}")
        status = common.diagnostic_status(self.get_fully_qualified_name(), state.frame_id, assessment)
        self._status_pub.publish(status)
        self._diagnostics_pub.publish(common.diagnostic_array(self, [status]))


def main(args: Sequence[str] | None = None, stop: threading.Event | None = None) -> int:
    """Run the node (``ros2 run magcal_ros correction_node`` goes through :mod:`magcal_ros.nodes.entry`)."""
    return common.run_node(lambda argv: CorrectionNode(argv=argv), SingleThreadedExecutor, args, stop)


if __name__ == "__main__":
    raise SystemExit(main())

"""Live correction node: raw sensor vectors in, corrected vectors, centre field and tensor out.

Subscribes ``<name>/raw`` (sensor_msgs/MagneticField, T) for every name in
``sensor_names``, groups the messages into synchronized sets by header stamp and, per
set, publishes ``<name>/corrected`` (``matrix @ (raw - offset)``, platform frame),
``field`` (centre field, T) and ``gradient`` (std_msgs/Float64MultiArray, 3x3 row-major,
``G[i][j] = dB_j/dx_i`` in T/m). The calibration comes from parameters
(``<name>.matrix``, ``<name>.offset``, ``positions``) and can be replaced at runtime
through the standard parameter services; a replacement is validated as a whole and
swapped in between two sets, an invalid one is rejected with a reason.

``~/status`` (diagnostic_msgs/DiagnosticStatus, every ``status_period`` s): level WARN
while samples are being dropped; values ``published`` (sets), ``incomplete`` (sets
dropped for a missing or bad sample), ``bad_value`` (NaN/inf samples), ``out_of_order``
and ``duplicate`` (samples with a stale or repeated stamp), ``time_jumps`` (stamps went
back more than 1 s: synchronizer reset), ``pending`` (open sets) and, when sets were
published, ``age_ms_p50/p99/max``: wall clock at publication minus the set's stamp
(a latency when the sensors stamp with the wall clock).

Usage::

    ros2 run magcal_ros correction_node --ros-args --params-file calibration.yaml
"""

from __future__ import annotations

import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import MagneticField
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from magcal_ros.core import sync
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.sync import SetSynchronizer, SyncedSet
from magcal_ros.core.tensor import GRADIENT_METHODS, gradient
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.cdr import decode_magnetic_field
from magcal_ros.nodes import common

NODE_NAME = "magcal_correction"
CORE_PARAMETERS: tuple[str, ...] = ("sensor_names", "positions", "frame_id", "sync_tolerance", "gradient_method")
SENSOR_SUFFIXES: tuple[str, ...] = ("matrix", "offset")


@dataclass(frozen=True)
class CorrectionState:
    """Everything a set needs, swapped as one reference when parameters change."""

    calibration: ArrayCalibration
    gradient_method: str
    frame_id: str
    tolerance_ns: int

    @property
    def names(self) -> tuple[str, ...]:
        """Sensor names, in set order."""
        return self.calibration.geometry.names


def build_state(values: dict[str, Any]) -> CorrectionState:
    """Validate a complete parameter state (dotted names) and build the correction from it.

    Raises :class:`InputError` naming what is wrong: sensor names or positions,
    a matrix or offset (check_sensor), the gradient method, the tolerance or the frame.
    """
    names = values.get("sensor_names")
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise InputError("sensor_names must be a list of strings")
    geo = common.geometry(names, values.get("positions", []))
    params: dict[str, Any] = {"sensor_names": list(geo.names), "positions": list(geo.positions.reshape(-1))}
    for name in geo.names:
        params[name] = {
            "matrix": values.get(f"{name}.matrix", common.IDENTITY),
            "offset": values.get(f"{name}.offset", common.ZEROS),
        }
    cal = ArrayCalibration.from_parameters(params)
    method = values.get("gradient_method")
    if method not in GRADIENT_METHODS:
        raise InputError(f"unknown gradient_method {method!r}; choose one of {', '.join(GRADIENT_METHODS)}")
    gradient(np.zeros((1, geo.size, 3)), geo, method)  # raises if the geometry does not suit the method
    frame = values.get("frame_id")
    if not isinstance(frame, str) or not frame.strip():
        raise InputError("frame_id must be a non-empty string")
    return CorrectionState(cal, method, frame, common.tolerance_ns(values.get("sync_tolerance")))


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

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, allow_undeclared_parameters=True, **kwargs)
        self._declare_parameters()
        self._state = build_state(self._current_values())
        self._pending: CorrectionState | None = None
        self._subs: list[Any] = []
        self._corrected_pubs: list[Any] = []
        self._corrected_msgs: list[MagneticField] = []
        depth = int(self.get_parameter("qos_depth").value)
        self._raw_qos = common.raw_qos(str(self.get_parameter("raw_reliability").value), depth)
        self._out_qos = common.output_qos(depth)
        self._field_pub = self.create_publisher(MagneticField, topics.FIELD, self._out_qos)
        self._gradient_pub = self.create_publisher(Float64MultiArray, topics.GRADIENT, self._out_qos)
        self._status_pub = self.create_publisher(DiagnosticStatus, "~/status", 10)
        self._field_msg = MagneticField()
        self._gradient_msg = _gradient_message()
        self._published = 0
        self._ages: list[int] = []
        self._drops = common.DropReporter(self.get_logger())
        self._connect(self._state)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        period = float(self.get_parameter("status_period").value)
        self.create_timer(max(period, 0.05), self._report)
        self.get_logger().info(
            f"correcting {', '.join(self._state.names)} -> <name>/corrected, field, gradient "
            f"({self._state.gradient_method}), frame {self._state.frame_id}, "
            f"sync tolerance {self._state.tolerance_ns / 1e6:g} ms; {self._describe(self._state.calibration)}"
        )

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
                  "(B = matrix (raw - offset))", constraints="finite, gains 0.1..10, condition < 100", numbers=True),
            )
            self.declare_parameter(
                f"{name}.offset", common.ZEROS,
                d(f"raw offset of {name}, 3 numbers (T, sensor axes)", constraints="finite, |offset| <= 1e-3 T",
                  numbers=True),
            )
        self.declare_parameter("frame_id", "magcal_array", d("frame of all outputs (platform frame)"))
        self.declare_parameter(
            "sync_tolerance", sync.DEFAULT_SYNC_TOLERANCE,
            d("largest spread (s) of header stamps within one synchronized set; keep it below half the "
              "sample period", numbers=True),
        )
        self.declare_parameter(
            "gradient_method", "difference",
            d("tensor formula: difference (planar cross) or least_squares (any geometry)",
              constraints=" | ".join(GRADIENT_METHODS)),
        )
        self.declare_parameter("raw_reliability", "best_effort", d(common.RELIABILITY_DOC, read_only=True))
        self.declare_parameter("qos_depth", 100, d("history depth of the raw subscriptions and the outputs",
                                                   read_only=True))
        self.declare_parameter("status_period", 1.0, d("period (s) of ~/status and of the drop report",
                                                       read_only=True))

    def _current_values(self) -> dict[str, Any]:
        names = self.list_parameters([], 0).names
        return {p.name: p.value for p in self.get_parameters(names)}

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
                    reason=f"unknown parameter {p.name!r}: per-sensor parameters are <name>.matrix and "
                    f"<name>.offset for a name in sensor_names",
                )
            if known and (p.name == "positions" or p.name.endswith(SENSOR_SUFFIXES)):
                why = common.check_number_array(p)
                if why:
                    return SetParametersResult(successful=False, reason=why)
        if not any(self._known(n, new_names) for n in updates):
            self._pending = None
            return SetParametersResult(successful=True)
        try:
            self._pending = build_state(values)
        except InputError as exc:
            self._pending = None
            self.get_logger().warn(f"rejected parameter update ({', '.join(updates)}): {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        """Swap in the validated state (runs between two sets: single-threaded executor)."""
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
        self.get_logger().info(
            f"parameters updated ({', '.join(p.name for p in params)}): {self._describe(new.calibration)}"
        )

    @staticmethod
    def _describe(cal: ArrayCalibration) -> str:
        eye = np.eye(3)
        changed = [
            n for n, m, o in zip(cal.geometry.names, cal.matrices, cal.offsets)
            if not (np.array_equal(m, eye) and not np.any(o))
        ]
        return f"calibrated sensors: {', '.join(changed)}" if changed else "no calibration (identity)"

    # -- topics ---------------------------------------------------------------------
    def _connect(self, state: CorrectionState) -> None:
        self._sync = SetSynchronizer(len(state.names), state.tolerance_ns)
        self._drops.reset()
        self._corrected_pubs = [
            self.create_publisher(MagneticField, topics.corrected(n), self._out_qos) for n in state.names
        ]
        self._corrected_msgs = [MagneticField() for _ in state.names]
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
        add, decode = self._sync.add, decode_magnetic_field

        def callback(data: bytes) -> None:
            try:
                sample = decode(data)
            except (InputError, struct.error):
                self._sync.stats.malformed += 1
                return
            synced = add(index, *sample)
            if synced is not None:
                self._publish(synced)

        return callback

    def _publish(self, synced: SyncedSet) -> None:
        """Correct one set and publish corrected vectors, then field, then gradient."""
        state = self._state
        raw = np.array(synced.values, dtype=float).reshape(1, -1, 3)
        vectors, centre, tensor = state.calibration.field_and_gradient(raw, state.gradient_method)
        frame = state.frame_id
        for msg, pub, stamp, v in zip(self._corrected_msgs, self._corrected_pubs, synced.stamps, vectors[0].tolist()):
            common.set_stamp(msg.header.stamp, stamp)
            msg.header.frame_id = frame
            f = msg.magnetic_field
            f.x, f.y, f.z = v
            pub.publish(msg)
        msg = self._field_msg
        common.set_stamp(msg.header.stamp, synced.stamp)
        msg.header.frame_id = frame
        f = msg.magnetic_field
        f.x, f.y, f.z = centre[0].tolist()
        self._field_pub.publish(msg)
        self._gradient_msg.data = tensor[0].reshape(9).tolist()
        self._gradient_pub.publish(self._gradient_msg)
        self._published += 1
        self._ages.append(time.time_ns() - synced.stamp)

    # -- reporting ------------------------------------------------------------------
    def _counters(self) -> dict[str, int]:
        c = self._sync.stats.as_dict()
        c["published"] = self._published
        c["pending"] = self._sync.pending
        return c

    def _report(self) -> None:
        """Publish ~/status and log (throttled) what was dropped."""
        counters = self._counters()
        recent = self._drops.update(counters, f"{counters['published']} sets published in total")
        ages, self._ages = self._ages, []
        values = {k: str(v) for k, v in counters.items()}
        if ages:
            p50, p99, pmax = np.percentile(np.asarray(ages, dtype=float) / 1e6, [50.0, 99.0, 100.0])
            values.update(age_ms_p50=f"{p50:.3f}", age_ms_p99=f"{p99:.3f}", age_ms_max=f"{pmax:.3f}")
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if recent else DiagnosticStatus.OK,
            name=self.get_fully_qualified_name(),
            message=("dropping: " + ", ".join(recent)) if recent else "ok",
            hardware_id=self._state.frame_id,
            values=[KeyValue(key=k, value=v) for k, v in values.items()],
        )
        self._status_pub.publish(status)


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ``ros2 run magcal_ros correction_node``."""
    return common.run_node(CorrectionNode, SingleThreadedExecutor, args)


if __name__ == "__main__":
    raise SystemExit(main())

"""The correction node's outputs of one set, built as CDR bytes for ``publish(bytes)``.

Per set the node publishes up to seven messages (``<name>/corrected`` per sensor, ``field``,
``gradient`` and ``gradient_stamped``, or ``baseline_gradient``). Filling message objects and
letting rclpy convert and serialize them costs more than the correction itself, so each output
is packed straight into its bytes (:mod:`magcal_ros.io.cdr` packers: frame, covariance, names and
layout fixed per calibration state, stamp and values per set); each packer is checked once, when
built, by deserializing its bytes with rclpy. The correction is the calibration's
:meth:`~magcal_ros.core.calibration.ArrayCalibration.affine_outputs` map (one matrix product per
set); with temperature terms, :meth:`~magcal_ros.core.calibration.ArrayCalibration.outputs`.

An output nobody subscribes costs nothing: :class:`Listeners` keeps, per publisher, whether it has
subscribers (an output without them looked at every set, one with them every :data:`REFRESH_SETS`
sets; matched events would add a waitable per publisher to every executor cycle, which costs more),
and nothing is computed or packed for an output without one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState, MagneticField
from std_msgs.msg import Float64MultiArray

from magcal_ros.core.calibration import AffineOutputs, ArrayCalibration
from magcal_ros.io.cdr import (
    GradientPacker,
    StampedNinePacker,
    StampedVectorPacker,
    gradient_template,
    magnetic_field_template,
    vector3_stamped_template,
)
from magcal_ros.io.csv_recording import TENSOR_COLUMNS

REFRESH_SETS: int = 8
"""Sets between two looks at the subscription counts of the outputs that have subscribers (about 2 us
a publisher); an output without one is looked at every set, so a new subscriber is served from the next
set on, as DDS itself would."""
_PROBE_NS = 1_700_000_123_456_789_012
_PROBE = (1.25e-5, -3.5e-5, 4.0625e-5)


class Listeners:
    """Whether each of ``publishers`` has subscribers: those without are looked at every set, those with
    every :data:`REFRESH_SETS` sets (a subscriber that left is noticed a few sets late: harmless)."""

    __slots__ = ("publishers", "listening", "any", "_countdown", "_idle")

    def __init__(self, publishers: Sequence[Any]) -> None:
        self.publishers = list(publishers)
        self.listening: list[bool] = [False] * len(self.publishers)
        self.any = False
        self._countdown = 0
        self._idle: list[Any] = []
        """(index, publisher) of the outputs without subscribers at the last full look."""

    def tick(self) -> None:
        """Before a set: bring the listening flags up to date."""
        self._countdown -= 1
        if self._countdown <= 0:
            self._countdown = REFRESH_SETS
            self.listening = [p.get_subscription_count() > 0 for p in self.publishers]
            self._idle = [(k, p) for k, p in enumerate(self.publishers) if not self.listening[k]]
            self.any = len(self._idle) < len(self.publishers)
            return
        if self._idle:
            found = [(k, p) for k, p in self._idle if p.get_subscription_count() > 0]
            if found:
                for k, _ in found:
                    self.listening[k] = True
                self._idle = [(k, p) for k, p in self._idle if not self.listening[k]]
                self.any = True


def _check(data: bytes, kind: type, expected: Callable[[Any], bool], what: str) -> None:
    """Raise unless ``data`` deserializes (rclpy) to a message ``expected`` accepts."""
    if not expected(deserialize_message(data, kind)):  # pragma: no cover - guards a change of the CDR layout
        raise RuntimeError(f"the packed {what} message does not deserialize to what was packed")


def _stamp_ok(msg: Any, frame_id: str) -> bool:
    return bool(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == _PROBE_NS
                and msg.header.frame_id == frame_id)


class SetOutputs:
    """The packers and the correction map of one calibration state (see the module docstring)."""

    def __init__(self, calibration: ArrayCalibration, gradient_method: str, frame_id: str,
                 covariances: Sequence[Sequence[float]], field_covariance: Sequence[float]) -> None:
        self.affine: AffineOutputs | None = calibration.affine_outputs(gradient_method)
        self.sensors = calibration.geometry.size
        self.kind = calibration.geometry.gradient_kind
        mf = magnetic_field_template(frame_id)
        self.corrected = [StampedVectorPacker(mf, c) for c in covariances]
        self.field = StampedVectorPacker(mf, field_covariance)
        self.gradient = GradientPacker(gradient_template()) if self.kind == "tensor" else None
        self.stamped = StampedNinePacker(frame_id, TENSOR_COLUMNS) if self.kind == "tensor" else None
        self.baseline = StampedVectorPacker(vector3_stamped_template(frame_id)) if self.kind == "baseline" else None
        self._check(frame_id, [*covariances, field_covariance])

    def _check(self, frame_id: str, covariances: Sequence[Sequence[float]]) -> None:
        for packer, cov in zip([*self.corrected, self.field], covariances):
            _check(packer.pack(_PROBE_NS, *_PROBE), MagneticField,
                   lambda m, cov=cov: _stamp_ok(m, frame_id) and tuple(m.magnetic_field_covariance) == tuple(cov)
                   and (m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z) == _PROBE, "MagneticField")
        nine = [float(i) - 3.5 for i in range(9)]
        if self.gradient is not None:
            _check(self.gradient.pack(nine), Float64MultiArray,
                   lambda m: list(m.data) == nine and [(d.label, d.size, d.stride) for d in m.layout.dim]
                   == [("row", 3, 9), ("col", 3, 3)] and m.layout.data_offset == 0, "Float64MultiArray")
        if self.stamped is not None:
            _check(self.stamped.pack(_PROBE_NS, nine), JointState,
                   lambda m: _stamp_ok(m, frame_id) and list(m.position) == nine and list(m.name) == list(TENSOR_COLUMNS)
                   and not len(m.velocity) and not len(m.effort), "JointState")
        if self.baseline is not None:
            _check(self.baseline.pack(_PROBE_NS, *_PROBE), Vector3Stamped,
                   lambda m: _stamp_ok(m, frame_id) and (m.vector.x, m.vector.y, m.vector.z) == _PROBE,
                   "Vector3Stamped")

    def values(self, calibration: ArrayCalibration, gradient_method: str, vectors: Sequence[Sequence[float]],
               currents: Sequence[float] | None, temperatures: Sequence[float] | None) -> np.ndarray:
        """The set's outputs as one flat array (layout of :class:`AffineOutputs`): corrected vectors,
        centre field, then the tensor or baseline gradient."""
        if self.affine is not None:
            x = [c for v in vectors for c in v]
            if currents is not None:
                x += currents
            return self.affine.matrix @ x + self.affine.offset  # type: ignore[no-any-return]
        out = calibration.outputs(np.array(vectors, dtype=float).reshape(1, -1, 3), gradient_method,
                                  None if currents is None else np.array([currents], dtype=float),
                                  None if temperatures is None else np.array([temperatures], dtype=float))
        parts = [out.vectors.reshape(-1), out.centre.reshape(-1)]
        if out.tensor is not None:
            parts.append(out.tensor.reshape(-1))
        elif out.baseline is not None:
            parts.append(out.baseline.reshape(-1))
        return np.concatenate(parts)

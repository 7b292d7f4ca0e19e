"""The correction node's hot path: the correction as one affine map, outputs packed into CDR bytes, and
the outputs nobody subscribes left alone."""

from __future__ import annotations

import numpy as np
import pytest

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry

rclpy = pytest.importorskip("rclpy")


def _rotation(axis: list[float], angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def _calibration(geometry: ArrayGeometry, rng: np.random.Generator, channels: int = 0,
                 rotated: bool = False) -> ArrayCalibration:
    s = geometry.size
    matrices = np.eye(3) + 0.05 * rng.standard_normal((s, 3, 3))
    offsets = 2e-6 * rng.standard_normal((s, 3))
    kw: dict = {}
    if channels:
        kw = {"channels": tuple(f"c{j}" for j in range(channels)),
              "interference": 1e-7 * rng.standard_normal((s, 3, channels))}
    if rotated:
        kw["output_rotation"] = _rotation([0.3, -1.0, 0.4], 0.7)
    return ArrayCalibration(geometry, matrices, offsets, **kw)


GEOMETRIES = {
    "cross": ArrayGeometry.cross(0.2),
    "spread": ArrayGeometry(("a", "b", "c", "d", "e"), np.array(
        [[0.2, 0.0, 0.0], [0.0, 0.25, 0.0], [-0.2, 0.05, 0.0], [0.0, -0.2, 0.1], [0.1, 0.1, -0.15]])),
    "line": ArrayGeometry(("a", "b"), np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])),
    "one": ArrayGeometry.single("m"),
}


@pytest.mark.parametrize("name", sorted(GEOMETRIES))
@pytest.mark.parametrize(("channels", "rotated"), [(0, False), (2, True)])
def test_the_affine_map_is_the_calibrations_outputs(name: str, channels: int, rotated: bool) -> None:
    """Corrected vectors, centre field and tensor (or baseline gradient) of 200 sets of Earth-field
    readings: the precomputed map gives what ``outputs`` gives, to rounding (1e-12 of the field, and of
    the field over the baseline for gradients), with currents and an output rotation."""
    rng = np.random.default_rng(3)
    geo = GEOMETRIES[name]
    cal = _calibration(geo, rng, channels, rotated)
    method = "least_squares" if name == "spread" else "difference"
    raw = 5e-5 * rng.standard_normal((200, geo.size, 3))
    u = 20.0 * rng.standard_normal((200, channels)) if channels else None
    want = cal.outputs(raw, method, u)
    affine = cal.affine_outputs(method)
    assert affine is not None and affine.kind == geo.gradient_kind and affine.sensors == geo.size
    x = raw.reshape(200, -1) if u is None else np.hstack([raw.reshape(200, -1), u])
    y = x @ affine.matrix.T + affine.offset
    s3 = 3 * geo.size
    np.testing.assert_allclose(y[:, :s3], want.vectors.reshape(200, -1), rtol=0, atol=1e-12 * 5e-5)
    np.testing.assert_allclose(y[:, s3 : s3 + 3], want.centre, rtol=0, atol=1e-12 * 5e-5)
    rest = {"tensor": want.tensor, "baseline": want.baseline, "none": None}[geo.gradient_kind]
    if rest is None:
        assert y.shape[1] == s3 + 3
    else:
        np.testing.assert_allclose(y[:, s3 + 3 :], rest.reshape(200, -1), rtol=0, atol=1e-12 * 5e-5 / 0.2)


def test_temperature_terms_have_no_affine_map() -> None:
    geo = GEOMETRIES["cross"]
    s = geo.size
    cal = ArrayCalibration(geo, np.tile(np.eye(3), (s, 1, 1)), np.zeros((s, 3)), temperature_reference=20.0,
                           offset_tempco=np.full((s, 3), 1e-9), matrix_tempco=np.zeros((s, 3, 3)))
    assert cal.affine_outputs() is None


@pytest.mark.parametrize("frame", ["magcal_array", "a", "ab", "abc", "abcd", "imu_link_12345"])
def test_packed_outputs_deserialize_to_the_messages(frame: str) -> None:
    """Every packer, for frame ids of every length modulo 8 (CDR padding): rclpy reads back the stamp,
    frame, values, covariance, names and layout that were packed."""
    from geometry_msgs.msg import Vector3Stamped
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState, MagneticField
    from std_msgs.msg import Float64MultiArray

    from magcal_ros.io.cdr import (
        GradientPacker,
        StampedNinePacker,
        StampedVectorPacker,
        gradient_template,
        magnetic_field_template,
        vector3_stamped_template,
    )
    from magcal_ros.io.csv_recording import TENSOR_COLUMNS

    stamp = 1_731_234_567_000_000_123
    cov = [1e-18 * (i + 1) for i in range(9)]
    m = deserialize_message(StampedVectorPacker(magnetic_field_template(frame), cov).pack(stamp, 1.5e-5, -2e-5, 3.25e-5),
                            MagneticField)
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (1_731_234_567, 123, frame)
    assert (m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z) == (1.5e-5, -2e-5, 3.25e-5)
    assert list(m.magnetic_field_covariance) == cov
    v = deserialize_message(StampedVectorPacker(vector3_stamped_template(frame)).pack(stamp, 1.0, 2.0, -3.0),
                            Vector3Stamped)
    assert (v.header.stamp.sec, v.header.stamp.nanosec, v.header.frame_id) == (1_731_234_567, 123, frame)
    assert (v.vector.x, v.vector.y, v.vector.z) == (1.0, 2.0, -3.0)
    nine = [1e-9 * (i - 4) for i in range(9)]
    g = deserialize_message(GradientPacker(gradient_template()).pack(nine), Float64MultiArray)
    assert list(g.data) == nine and g.layout.data_offset == 0
    assert [(d.label, d.size, d.stride) for d in g.layout.dim] == [("row", 3, 9), ("col", 3, 3)]
    j = deserialize_message(StampedNinePacker(frame, TENSOR_COLUMNS).pack(stamp, nine), JointState)
    assert (j.header.stamp.sec, j.header.stamp.nanosec, j.header.frame_id) == (1_731_234_567, 123, frame)
    assert list(j.position) == nine and list(j.name) == list(TENSOR_COLUMNS)
    assert len(j.velocity) == 0 and len(j.effort) == 0


class _Publisher:
    def __init__(self, subscribers: int) -> None:
        self.subscribers = subscribers
        self.looked = 0

    def get_subscription_count(self) -> int:
        self.looked += 1
        return self.subscribers


def test_outputs_without_subscribers_are_looked_at_every_set_the_others_now_and_then() -> None:
    from magcal_ros.nodes.live_outputs import REFRESH_SETS, Listeners

    pubs = [_Publisher(1), _Publisher(0), _Publisher(0)]
    listeners = Listeners(pubs)
    listeners.tick()
    assert listeners.listening == [True, False, False] and listeners.any
    pubs[1].subscribers = 1  # a subscriber arrives: served from the next set
    listeners.tick()
    assert listeners.listening == [True, True, False]
    for _ in range(3 * REFRESH_SETS):
        listeners.tick()
    assert pubs[2].looked == 3 * REFRESH_SETS + 2  # every set
    assert pubs[0].looked <= 4  # now and then
    pubs[0].subscribers = pubs[1].subscribers = 0  # everybody leaves: noticed within REFRESH_SETS sets
    for _ in range(REFRESH_SETS):
        listeners.tick()
    assert listeners.listening == [False, False, False] and not listeners.any

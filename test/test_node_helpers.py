"""What only the nodes use: the bounded sample buffer and the one-message MagneticField decoder."""

from __future__ import annotations

import numpy as np

from magcal_ros.nodes.buffer import CELLS, SetBuffer


def test_buffer_is_bounded_and_keeps_rare_attitudes() -> None:
    rng = np.random.default_rng(0)
    buf = SetBuffer(capacity=200, sensors=2, seed=1)
    up = (0.0, 0.0, 5e-5)
    for k in range(5000):  # a long stationary stretch ...
        buf.add(k, (up, up))
    dirs = rng.normal(size=(150, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for k, d in enumerate(dirs):  # ... then a short tumble
        v = tuple(5e-5 * d)
        buf.add(10_000 + k, (v, v))
    stamps, raw = buf.snapshot()
    assert len(buf) == 200 and raw.shape == (200, 2, 3)
    assert np.all(np.diff(stamps) >= 0)
    assert np.sum(stamps >= 10_000) >= 140, "the rare attitudes were pushed out"
    assert buf.cells_visited > CELLS // 2


def test_raw_magnetic_field_decoding_matches_rclpy_and_rosbags() -> None:
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import MagneticField

    from magcal_ros.io.cdr import (
        MAGNETIC_FIELD,
        decode_magnetic_field,
        magnetic_field_message,
        typestore,
    )

    for frame in ("", "a", "mag1", "abcdefg", "x" * 13):
        msg = MagneticField()
        msg.header.frame_id = frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000, 123_456_789
        msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = 1.5e-5, -2.25e-5, 4.125e-5
        expected = (1_700_000_000_123_456_789, 1.5e-5, -2.25e-5, 4.125e-5)
        assert decode_magnetic_field(serialize_message(msg)) == expected
        rb = magnetic_field_message(1_700_000_000, 123_456_789, frame, (1.5e-5, -2.25e-5, 4.125e-5))
        big = bytes(typestore().serialize_cdr(rb, MAGNETIC_FIELD, little_endian=False))
        assert big[1] == 0 and decode_magnetic_field(big) == expected

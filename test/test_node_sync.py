"""The live nodes' set synchronizer and bounded sample buffer (pure Python, no ROS)."""

from __future__ import annotations

import numpy as np

from magcal_ros.nodes.buffer import CELLS, SetBuffer
from magcal_ros.nodes.sync import SetSynchronizer

MS = 1_000_000


def feed(sync: SetSynchronizer, items: list[tuple[int, int, float]]) -> list[tuple[int, ...]]:
    out = []
    for index, stamp, value in items:
        s = sync.add(index, stamp, value, 0.0, 0.0)
        if s is not None:
            out.append(s.stamps)
    return out


def test_sets_form_from_any_arrival_order_and_jitter() -> None:
    sync = SetSynchronizer(3, tolerance_ns=MS)
    items = [(0, 10 * MS, 1.0), (2, 10 * MS + 300_000, 1.0), (1, 10 * MS - 400_000, 1.0),
             (1, 20 * MS, 2.0), (0, 20 * MS, 2.0), (2, 20 * MS, 2.0)]
    assert feed(sync, items) == [(10 * MS, 10 * MS - 400_000, 10 * MS + 300_000), (20 * MS,) * 3]
    assert sync.stats.complete == 2 and sync.pending == 0


def test_nearest_set_wins_when_tolerance_exceeds_the_period() -> None:
    sync = SetSynchronizer(2, tolerance_ns=MS)
    items = [(0, 0, 0.0), (0, MS, 1.0), (1, 0, 0.0), (1, MS, 1.0)]
    assert feed(sync, items) == [(0, 0), (MS, MS)]


def test_bad_values_missing_sensors_and_stale_stamps_are_dropped_and_counted() -> None:
    sync = SetSynchronizer(2, tolerance_ns=MS)
    nan = float("nan")
    items = [
        (0, 10 * MS, 1.0), (1, 10 * MS, nan),       # NaN: set 10 incomplete
        (0, 20 * MS, 1.0),                          # sensor 1 silent at 20
        (0, 30 * MS, 1.0), (1, 30 * MS, 1.0),       # complete
        (1, 30 * MS, 1.0),                          # repeat
        (0, 25 * MS, 1.0),                          # older than sensor 0's last
        (0, 40 * MS, 1.0), (1, 40 * MS, float("inf")),
        (0, 50 * MS, 1.0), (1, 50 * MS, 1.0),
    ]
    assert feed(sync, items) == [(30 * MS, 30 * MS), (50 * MS, 50 * MS)]
    st = sync.stats
    assert (st.bad_value, st.duplicate, st.out_of_order) == (2, 1, 1)
    assert st.incomplete == 3 and sync.pending == 0


def test_a_silent_sensor_cannot_grow_the_pending_sets_without_bound() -> None:
    sync = SetSynchronizer(2, tolerance_ns=MS, max_pending=10)
    for k in range(1000):
        assert sync.add(0, k * 10 * MS, 1.0, 0.0, 0.0) is None
    assert sync.pending <= 10 and sync.stats.incomplete >= 990


def test_a_source_restart_resets_instead_of_dropping_everything() -> None:
    sync = SetSynchronizer(2, tolerance_ns=MS)
    base = 100 * 10**9
    assert feed(sync, [(0, base, 1.0), (1, base, 1.0)]) == [(base, base)]
    assert feed(sync, [(0, 5 * MS, 1.0), (1, 5 * MS, 1.0)]) == [(5 * MS, 5 * MS)]
    assert sync.stats.time_jumps == 1


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

    from magcal_ros.cdr import MAGNETIC_FIELD, magnetic_field_message, typestore
    from magcal_ros.nodes.common import decode_magnetic_field

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

"""What a live node keeps while one sensor is silent for minutes: bounded, counted entry by entry.

A sensor that stops (a cable, a driver) while the others go on at 100 Hz: every message of the
others is given up after the lag (``unmatched``), and nothing of it may stay behind. Memory is
judged by counting what the synchroniser (and the correction node around it) holds, element by
element of every container it owns, never by the process's resident size.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from magcal_ros.core.sync_rules import SyncStats
from magcal_ros.nodes import common

NAMES = ("mag1", "mag2", "mag3", "mag4")
RATE_NS = 10_000_000
"""100 Hz."""
START = 1_700_000_000 * 10**9
MINUTE = 6000
"""Sets in a minute at 100 Hz."""


def retained(obj: Any, seen: set[int] | None = None) -> int:
    """Elements held by ``obj``: every list, tuple, deque, set and dict entry (and array element) reachable
    through the attributes of magcal objects, each container counted once. Numbers and strings count 0."""
    seen = set() if seen is None else seen
    if id(obj) in seen or isinstance(obj, (int, float, str, bytes, bool, type(None), SyncStats)):
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return int(obj.size)
    if isinstance(obj, dict):
        return len(obj) + sum(retained(v, seen) for v in obj.values())
    if isinstance(obj, (list, tuple, deque, set, frozenset)):
        return len(obj) + sum(retained(v, seen) for v in obj)
    module = type(obj).__module__ or ""
    if not module.startswith("magcal_ros"):
        return 0
    fields = dict(getattr(obj, "__dict__", {}))
    for slot in getattr(type(obj), "__slots__", ()):
        if hasattr(obj, slot):
            fields[slot] = getattr(obj, slot)
    return sum(retained(v, seen) for v in fields.values())


def silent_run(sync: Any, silent: int, minutes: float, every: int = 500) -> Iterator[tuple[int, int]]:
    """Feed 10 s of every sensor, then ``minutes`` with sensor ``silent`` quiet; yields (sets sent, retained)
    every ``every`` sets of the silence."""
    k = 0
    vector = (1.8e-5, 2.1e-6, 4.7e-5)
    for k in range(1000):
        t = START + k * RATE_NS
        for i in range(len(NAMES)):
            sync.add(i, t, *vector, t + 1000)
    for n in range(int(minutes * MINUTE)):
        t = START + (1000 + n) * RATE_NS
        for i in range(len(NAMES)):
            if i != silent:
                sync.add(i, t, *vector, t + 1000)
        if n % every == every - 1:
            yield n + 1, retained(sync)


@pytest.mark.parametrize("mode", ["exact", "interpolate", "auto"])
@pytest.mark.parametrize("silent", [0, 3], ids=["reference_silent", "other_silent"])
def test_a_silent_sensor_leaves_nothing_behind_for_three_minutes(mode: str, silent: int) -> None:
    """Three minutes of one silent sensor, the others at 100 Hz (54,000 messages given up): what the
    synchroniser keeps stays within what the first minute needed (consumed messages are forgotten in
    blocks, so it saws up and down). Before the fix exact matching kept every given-up message (330 B each,
    98 kB/s in the node) and interpolation with a silent reference every sample of the others."""
    sync = common.synchronizer(list(NAMES), 1_000_000, mode, 0)
    samples = list(silent_run(sync, silent, minutes=3.0))
    first = max(r for n, r in samples if n <= MINUTE)
    later = max(r for n, r in samples if n > 2 * MINUTE)
    assert later <= first, f"kept {first} entries after one minute, {later} in the third"
    # and in absolute terms: the lag's worth of messages waiting plus one compaction block per sensor
    per_message = 5  # stamp, header stamp, window cap, value tuple (3 numbers) or their equivalents
    bound = (3 * (5 * 100 + 4096 + 64)) * per_message * 2
    assert later < bound, (later, bound)
    stats = sync.stats
    assert stats.unmatched >= 3 * (3 * MINUTE - 600), stats.as_dict()  # given up and counted, not kept


def test_the_correction_nodes_state_stays_bounded_with_a_silent_sensor() -> None:
    """The correction node's raw callback path (decoding, health, synchroniser) over three minutes of mag4
    silent: the node's synchroniser and stream health keep no more in the third minute than in the first."""
    import rclpy
    from rclpy.context import Context
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import MagneticField

    from magcal_ros.app.ros_driver import isolate_this_process, pick_domain_id
    from magcal_ros.nodes.correction_node import CorrectionNode

    domain = pick_domain_id()
    isolate_this_process(domain)
    context = Context()
    rclpy.init(context=context, domain_id=domain, args=["test", "--ros-args", "-p",
                                                          f"uncorrected_sensors:={list(NAMES)}"])
    node = CorrectionNode(context=context)
    try:
        callbacks = [node._raw_callback(i) for i in range(len(NAMES))]
        msg = MagneticField()
        msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = 1.8e-5, 2.1e-6, 4.7e-5

        def send(i: int, t: int) -> None:
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 10**9)
            callbacks[i](serialize_message(msg), {"received_timestamp": t + 1000})

        for k in range(1000):
            for i in range(4):
                send(i, START + k * RATE_NS)
        samples = []
        for n in range(3 * MINUTE):
            for i in range(3):
                send(i, START + (1000 + n) * RATE_NS)
            if n % 500 == 499:
                samples.append((n + 1, retained(node._sync) + retained(node._health)))
        first = max(r for n, r in samples if n <= MINUTE)
        later = max(r for n, r in samples if n > 2 * MINUTE)
        assert later <= first, f"kept {first} entries after one minute, {later} in the third"
        assert node._sync.stats.unmatched >= 3 * (3 * MINUTE - 600)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)

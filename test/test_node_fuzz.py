"""Nothing kills a node: 1,000 random parameter updates and 10,000 random messages (finite, NaN,
infinite, huge, tiny, zero and negative stamps, out of order, undecodable bytes), and every message
is published or counted.

The nodes run in this process and their callbacks are driven directly, one message after another
(no timing decides anything): a parameter update goes through ``set_parameters_atomically`` exactly
as the parameter service calls it (which answers ParameterNotDeclaredException with a refusal and
lets anything else escape into the executor, killing the node), a message through the
subscription's own callback.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest
from test_node_parameters import NAMES, _make, in_process

from magcal_ros.core.sync import DROP_FIELDS
from magcal_ros.core.units import NS_PER_S

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

UPDATES = 1000
MESSAGES = 10_000


def _random_value(rng: np.random.Generator) -> Any:
    """A value of any parameter type, valid or not."""
    numbers = [0.0, -1.0, 1e-3, 0.5, 5e-5, 1e300, -1e300, math.nan, math.inf, 3.0, 1e-9, 100.0]
    words = ["mag1", "mag 1", "../x", "", "none", "running", "difference", "least_squares", "reliable",
             "sensor_msgs/msg/BatteryState", "std_msgs/msg/Int32", "thruster1/battery", "~/x", "2026-11-23", "ml"]
    kind = rng.integers(0, 9)
    if kind == 0:
        return bool(rng.integers(0, 2))
    if kind == 1:
        return int(rng.choice([0, 1, -5, 20, 100, 10**9]))
    if kind == 2:
        return float(rng.choice(numbers))
    if kind == 3:
        return str(rng.choice(words))
    n = int(rng.choice([0, 1, 2, 3, 4, 8, 9, 12, 13]))
    if kind in (4, 5):
        return [float(rng.choice(numbers)) if rng.random() < 0.2 else float(rng.normal(0, 0.3)) for _ in range(n)]
    if kind == 6:
        return [int(v) for v in rng.integers(-3, 3, n)]
    if kind == 7:
        if rng.random() < 0.3:  # four names, one of them perhaps not a ROS name: the cross's positions fit
            return [str(rng.choice(words)) if rng.random() < 0.3 else name for name in NAMES]
        return [str(rng.choice(words)) for _ in range(n)] if rng.random() < 0.5 else list(NAMES[: max(n, 1)])
    return [bool(v) for v in rng.integers(0, 2, n)]


def _update(node: Any, rng: np.random.Generator) -> bool:
    """One random update, as the set_parameters service applies it; whether it was accepted."""
    from rclpy.exceptions import ParameterNotDeclaredException
    from rclpy.parameter import Parameter

    declared = node.list_parameters([], 0).names
    extra = ["mag9.matrix", "mag1.matrix", "mag1.offset", "mag1.interference", "bogus", "mag1.covariance"]
    names = list(declared) + extra
    count = int(rng.integers(1, 4))
    params = []
    for _ in range(count):
        name = str(rng.choice(names))
        value = _random_value(rng)
        params.append(Parameter(name, value=value))
    try:
        return bool(node.set_parameters_atomically(params).successful)
    except ParameterNotDeclaredException:
        return False


def _messages(rng: np.random.Generator, count: int, sensors: int) -> list[tuple[int, int, int, tuple[float, ...]]]:
    """(sensor, sec, nanosec, vector) of random messages: mostly a good stream, with every fault."""
    out = []
    last: dict[int, int] = {}
    t = 1_700_000_000 * NS_PER_S
    for k in range(count):
        if k % sensors == 0:  # a new set: the sensors sample together, 20 ms apart
            t += 20_000_000
            order = rng.permutation(sensors)
        stamp = t + int(rng.integers(0, 100_000))
        fault = rng.random()
        if fault < 0.03:
            stamp = 0
        elif fault < 0.06:
            stamp = -5 * NS_PER_S + int(rng.integers(0, NS_PER_S))
        elif fault < 0.09:
            stamp = t - int(rng.integers(0, 3 * NS_PER_S))  # repeat, late or a restart
        elif fault < 0.10:
            stamp = (2**31 - 1) * NS_PER_S
        elif fault < 0.12:
            stamp = last.get(int(order[k % sensors]), stamp)  # a repeat of that sensor's previous stamp
        vector = tuple(float(v) for v in rng.normal(0.0, 3e-5, 3))
        bad = rng.random()
        if bad < 0.03:
            vector = (math.nan, vector[1], vector[2])
        elif bad < 0.06:
            vector = (math.inf, -math.inf, 0.0)
        elif bad < 0.09:
            vector = (1e30, 0.0, 0.0)
        elif bad < 0.10:
            vector = (-1e300, 1e300, 5e-324)
        elif bad < 0.11:
            vector = (0.0, 0.0, 0.0)
        sec, nanosec = divmod(stamp, NS_PER_S)
        index = int(order[k % sensors]) if rng.random() < 0.95 else int(rng.integers(0, sensors))
        last[index] = stamp
        out.append((index, sec, nanosec, vector))
    return out


def _message(sec: int, nanosec: int, vector: tuple[float, ...]) -> Any:
    from sensor_msgs.msg import MagneticField

    msg = MagneticField()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.header.frame_id = "mag"
    msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = vector
    return msg


def _accounted(stats: dict[str, int], pending: int, sensors: int) -> int:
    """Messages the synchronizer accounts for: in sets (``used``), dropped for any reason, or still queued."""
    dropped = sum(stats[k] for k in DROP_FIELDS)
    return stats["used"] + dropped + pending


@pytest.mark.parametrize("kind", ["correction", "calibration"])
def test_nodes_survive_random_parameter_updates_and_keep_a_valid_state(kind: str) -> None:
    rng = np.random.default_rng(21 if kind == "correction" else 22)
    with in_process("-p", f"uncorrected_sensors:={list(NAMES)}") as run:
        node = _make(kind, run)
        accepted = sum(_update(node, rng) for _ in range(UPDATES))
        assert 0 < accepted < UPDATES  # some of each: the fuzz reached the validation
        # whatever was accepted is a state the node can run: set a known array and feed a good set
        from rclpy.parameter import Parameter

        good = [Parameter("sensor_names", value=list(NAMES)), Parameter("positions", value=[0.2, 0.0, 0.0, 0.0, 0.2,
                0.0, -0.2, 0.0, 0.0, 0.0, -0.2, 0.0]), Parameter("sync_tolerance", value=0.001),
                Parameter("interference_channels", value=["x"]), Parameter("interference_channels", value=[])]
        for p in good:
            node.set_parameters_atomically([p])
        assert node.get_parameter("sensor_names").value == list(NAMES)


@pytest.mark.parametrize("kind", ["correction", "calibration"])
def test_every_random_message_is_published_or_counted(kind: str) -> None:
    from rclpy.serialization import serialize_message

    rng = np.random.default_rng(31 if kind == "correction" else 32)
    sensors = len(NAMES)
    with in_process("-p", f"uncorrected_sensors:={list(NAMES)}", "-p", "autostart:=true") as run:
        node = _make(kind, run)
        callbacks = [sub.callback for sub in node._subs[:sensors]]
        # a clock of the test's own, whatever this machine's speed: arrivals 0.5 ms apart, a replay ten times
        # faster than the stamps (whose arrivals then do not keep their time: the stamps alone decide)
        clock = [time.time_ns()]
        node._arrival = lambda info: info.get("received_timestamp") or clock[0]
        offered = 0
        for index, sec, nanosec, vector in _messages(rng, MESSAGES, sensors):
            msg = _message(sec, nanosec, vector)
            clock[0] += 500_000
            # the middleware's reception time, or none (0: the node's clock stands in)
            info = {"source_timestamp": 0,
                    "received_timestamp": clock[0] + int(rng.integers(0, 20_000)) if rng.random() < 0.9 else 0}
            if kind == "correction":
                data = serialize_message(msg)
                if rng.random() < 0.01:
                    data = bytes(rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8))  # undecodable
                callbacks[index](data, info)
            else:
                callbacks[index](msg, info)
            offered += 1
        stats = node._sync.stats.as_dict()
        assert _accounted(stats, node._sync.pending, sensors) == offered
        for name in ("nonfinite", "out_of_range", "zero_stamp", "negative_stamp", "duplicate", "out_of_order"):
            assert stats[name] > 0, name
        assert stats["sets"] > 100
        if kind == "correction":
            assert stats["malformed"] > 0
            assert node._published + node._withheld == stats["sets"] and node._published > 100
        else:
            assert node._buffer.offered == stats["sets"]


def test_a_sensor_restarting_alone_is_placed_by_when_its_messages_arrived_not_when_the_node_read_them() -> None:
    """mag3's clock jumps 60 s back mid-stream while the node reads a backlog, each topic's queue in turn,
    after a second without CPU (a busy machine): its new segment is placed by the middleware's reception
    times (the message info), so the sets go on; the moment the callbacks ran would put it a second
    ahead of the other sensors, and a second of sets would be lost."""
    from rclpy.serialization import serialize_message

    with in_process("-p", f"uncorrected_sensors:={list(NAMES)}", "-p", "sync_mode:=exact") as run:
        node = _make("correction", run)
        callbacks = [sub.callback for sub in node._subs[:len(NAMES)]]
        t0, arrived0 = 1_700_000_000 * NS_PER_S, time.time_ns() - 60 * NS_PER_S
        sets, period = 1500, 10_000_000  # 100 sets/s, mag3 restarts at set 500
        for block in range(0, sets, 50):  # the executor serves each topic's queue in turn: 50 of mag1, of mag2 ...
            if block == 500:
                time.sleep(1.0)  # and the node got no CPU for a second just before mag3's restart
            for i in range(len(NAMES)):
                for k in range(block, block + 50):
                    stamp = t0 + k * period - (60 * NS_PER_S if i == 2 and k >= 500 else 0)
                    msg = _message(stamp // NS_PER_S, stamp % NS_PER_S, (2e-5, 1e-5, 4e-5))
                    info = {"source_timestamp": 0, "received_timestamp": arrived0 + k * period + 200_000}
                    callbacks[i](serialize_message(msg), info)
        stats = node._sync.stats.as_dict()
        assert stats["restarts"] == 1, stats
        assert node._published >= 0.98 * sets, (node._published, stats)

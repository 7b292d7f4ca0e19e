"""What only the nodes use: the bounded sample buffer and the one-message MagneticField decoder."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

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


def test_buffer_keeps_the_currents_with_their_sets() -> None:
    buf = SetBuffer(capacity=3, sensors=1, seed=0, channels=2)
    for k, v in enumerate(((1e-5, 0, 0), (0, 1e-5, 0), (0, 0, 1e-5), (-1e-5, 0, 0))):
        buf.add(100 - k, (v,), (float(k), 10.0 + k))
    stamps, raw, currents = buf.snapshot_all()
    assert len(stamps) == 3 and np.all(np.diff(stamps) > 0)
    for t, r, u in zip(stamps, raw, currents):  # each set kept its own currents
        k = 100 - int(t)
        assert u.tolist() == [float(k), 10.0 + k] and np.isclose(np.abs(r).sum(), 1e-5)


def test_node_geometry_defaults_by_sensor_count() -> None:
    import pytest

    from magcal_ros.errors import InputError
    from magcal_ros.nodes import common

    assert common.geometry(["mag1"], None).positions.tolist() == [[0.0, 0.0, 0.0]]
    assert common.geometry(["mag1"], []).gradient_kind == "none"
    assert common.default_positions(4) == common.DEFAULT_POSITIONS and common.default_positions(1) == [0.0] * 3
    assert common.default_positions(2) is None
    with pytest.raises(InputError, match="positions needs 3 numbers per sensor .*: 6 for 2 sensors, none given"):
        common.geometry(["a", "b"], None)
    assert common.geometry(["a", "b"], [0.2, 0, 0, -0.2, 0, 0]).gradient_kind == "baseline"


def test_current_inputs_default_to_the_channel_names_and_battery_state() -> None:
    import pytest

    from magcal_ros.errors import InputError
    from magcal_ros.nodes import common

    inputs = common.current_inputs({"interference_channels": ["thruster1/battery", "pump"], "current_tolerance": 0.25})
    assert inputs.topics == ("thruster1/battery", "pump") and inputs.types == (common.BATTERY_STATE,) * 2
    assert inputs.tolerance_ns == 250_000_000
    assert common.current_inputs({}) == common.CurrentInputs()
    for values, why in [
        ({"interference_channels": ["a", "a"]}, "unique"),
        ({"interference_channels": ["a"], "interference_topics": ["x", "y"]}, "one entry per interference channel"),
        ({"interference_channels": ["a"], "interference_types": ["std_msgs/msg/Int32"]}, "not supported"),
        ({"interference_channels": ["a"], "interference_topics": ["no spaces"]}, "interference_topics: Invalid"),
        ({"interference_channels": ["a"], "current_tolerance": -1.0}, "positive number"),
        ({"interference_channels": "a"}, "list of strings"),
    ]:
        with pytest.raises(InputError, match=why):
            common.current_inputs(values)


def test_the_running_calibration_is_a_prior_only_when_calibrated() -> None:
    from magcal_ros.core.geometry import ArrayGeometry
    from magcal_ros.nodes import common

    geo = ArrayGeometry.cross()
    values = {"sensor_names": list(geo.names), "interference_channels": ["t1"]}
    for k, n in enumerate(geo.names):
        values[f"{n}.matrix"] = [1.01, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        values[f"{n}.offset"] = [1e-7 * (k + 1), 0.0, 0.0]
        values[f"{n}.interference"] = [1e-9, 2e-9, 3e-9]
    cal, why = common.running_calibration(values, geo)
    assert why == "" and cal.channels == ("t1",) and np.allclose(cal.offsets[2], [3e-7, 0, 0])
    assert np.allclose(cal.interference[1, :, 0], [1e-9, 2e-9, 3e-9])
    blank = dict(values, **{"mag3.matrix": [], "mag3.offset": [], "uncorrected_sensors": ["mag3"]})
    assert common.running_calibration(blank, geo) == (
        None, "mag3 without a matrix and offset (never calibrated; mag3 uncorrected on purpose)")
    # an identity given on purpose is a calibration, and so a prior
    on_purpose = dict(values, **{"mag3.matrix": common.IDENTITY, "mag3.offset": common.ZEROS})
    cal, why = common.running_calibration(on_purpose, geo)
    assert why == "" and np.array_equal(cal.matrices[2], np.eye(3)) and not cal.offsets[2].any()
    cal, why = common.running_calibration(dict(values, sensor_names=["mag1"]), geo)
    assert cal is None and why.startswith("it has no sensor mag2, mag3, mag4")
    cal, why = common.running_calibration(dict(values, **{"mag2.offset": [1.0, 0.0, 0.0]}), geo)
    assert cal is None and "unusable" in why and "Tesla" in why


def test_empty_string_lists_go_out_as_string_arrays() -> None:
    from rcl_interfaces.msg import ParameterType

    from magcal_ros.nodes import common

    assert common.parameter_message("interference_channels", []).value.type == ParameterType.PARAMETER_STRING_ARRAY
    assert common.parameter_message("positions", [0, 1]).value.type == ParameterType.PARAMETER_DOUBLE_ARRAY


def test_unstamped_currents_count_from_their_arrival() -> None:
    """A BatteryState with a zero header stamp (many battery drivers) is stamped on receipt like a
    Float64, live, and at its bag time offline; a stamped one keeps its stamp."""
    from sensor_msgs.msg import BatteryState
    from std_msgs.msg import Float64

    from magcal_ros.core.interference import LatestCurrents
    from magcal_ros.io import cdr
    from magcal_ros.nodes import common

    class Subscriber:
        def __init__(self) -> None:
            self.callbacks: list = []

        def create_subscription(self, kind, topic, callback, qos):  # noqa: ANN001, ANN202
            self.callbacks.append((kind, callback))

    inputs = common.current_inputs({"interference_channels": ["a", "b"],
                                    "interference_types": [common.BATTERY_STATE, common.FLOAT64]})
    store = LatestCurrents(2, inputs.tolerance_ns)
    node, arrival = Subscriber(), 1_700_000_000_123_456_789
    common.subscribe_currents(node, inputs, store, common.output_qos(10), clock=lambda: arrival)
    (battery_type, on_battery), (float_type, on_float) = node.callbacks
    assert (battery_type, float_type) == (BatteryState, Float64)
    on_battery(BatteryState(current=3.5))  # header stamp 0
    on_float(Float64(data=7.0))
    assert store.at(arrival) == ([3.5, 7.0], [True, True])  # both fresh
    stamped = BatteryState(current=4.0)
    stamped.header.stamp.sec, stamped.header.stamp.nanosec = 1_700_000_000, 200_000_000
    on_battery(stamped)
    assert store.at(1_700_000_000_200_000_000) == ([4.0, 7.0], [True, True])

    ts = cdr.typestore()
    zero = bytes(ts.serialize_cdr(cdr.battery_state_message(0, 2.0), cdr.BATTERY_STATE))
    assert cdr.decode_current(cdr.BATTERY_STATE, zero, 42) == (42, 2.0)
    given = bytes(ts.serialize_cdr(cdr.battery_state_message(1_000_000_007, 2.0), cdr.BATTERY_STATE))
    assert cdr.decode_current(cdr.BATTERY_STATE, given, 42) == (1_000_000_007, 2.0)


def test_the_calibration_health_reference_is_validated_with_the_calibration() -> None:
    """<name>.noise and calibration_intensity come with a calibration; a bad one is refused with the reason."""
    from magcal_ros.errors import InputError
    from magcal_ros.nodes.drift import reference

    names = ("mag1", "mag2")
    assert reference({}, names) == ((0.0, 0.0), 0.0)  # unknown: the live noise is used
    assert reference({"mag2.noise": 1e-9, "calibration_intensity": 5.15e-5}, names) == ((0.0, 1e-9), 5.15e-5)
    for values, why in (({"mag1.noise": -1e-9}, "mag1.noise must be 0 (unknown) or a noise in T"),
                        ({"mag1.noise": "x"}, "mag1.noise must be a finite number"),
                        ({"calibration_intensity": 51500.0}, "calibration_intensity 51500 T is not Earth-like")):
        try:
            reference(values, names)
        except InputError as exc:
            assert str(exc).startswith(why), exc
        else:
            raise AssertionError(f"{values} accepted")


@pytest.mark.dds
def test_a_run_loads_its_fast_dds_profile_and_keeps_a_users_own(tmp_path: Path) -> None:
    """Every process of a run gets the profile in which reliable writers announce every 0.1 s (lost
    messages come back within a fraction of a second on a busy machine); Fast DDS parses it without an
    error; a profile the user names is kept."""
    import os
    import subprocess
    import sys

    from magcal_ros.app.ros_driver import ros_environment

    base = {k: v for k, v in os.environ.items() if "PROFILES_FILE" not in k}
    env = ros_environment(97, base)
    text = Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"]).read_text()
    assert "<heartbeatPeriod><sec>0</sec><nanosec>100000000</nanosec></heartbeatPeriod>" in text
    code = ("import rclpy\nfrom rclpy.qos import QoSProfile, ReliabilityPolicy\nfrom std_msgs.msg import Float64\n"
            "rclpy.init()\nnode = rclpy.create_node('profile_check')\n"
            "node.create_publisher(Float64, 'x', QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))\n"
            "node.destroy_node()\nrclpy.shutdown()\nprint('created')\n")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "created" in done.stdout, done.stderr
    assert "XMLPARSER" not in done.stdout + done.stderr and "Error" not in done.stderr, done.stdout + done.stderr
    mine = tmp_path / "mine.xml"
    for key in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        kept = ros_environment(97, {**base, key: str(mine)})
        assert kept[key] == str(mine) and kept.get("FASTRTPS_DEFAULT_PROFILES_FILE", str(mine)) == str(mine)


@pytest.mark.dds
def test_the_test_driver_hears_on_after_a_callback_raises() -> None:
    """A test's predicate that raises reaches the test; a callback that raises is recorded and the driver's
    thread goes on (once it ended silently: every later wait of the module timed out with "none")."""
    import os
    import threading
    import time

    from sensor_msgs.msg import MagneticField

    from magcal_ros.app.ros_driver import ArrayDriver, pick_domain_id

    driver = ArrayDriver(("m",), pick_domain_id(os.getpid() + 7), node_name="raising_driver", listen=False)
    try:
        topic = driver.topic("m/raw")

        def publish_until(found: list[object]) -> None:
            for k in range(600):
                if found:
                    return
                msg = MagneticField()
                msg.header.stamp.sec = k + 1
                driver.publishers["m"].publish(msg)
                time.sleep(0.05)

        def raising(msg: object) -> bool:
            raise KeyError("a value the message lacks")

        found: list[object] = []
        feeder = threading.Thread(target=publish_until, args=(found,), daemon=True)
        feeder.start()
        with pytest.raises(KeyError, match="a value the message lacks"):
            driver.wait_for_message(MagneticField, topic, raising, timeout=60.0)
        found.append(True)
        feeder.join()

        def broken(msg: object) -> None:
            raise RuntimeError("broken callback")

        driver.node.create_subscription(MagneticField, topic, broken, 10)
        found = []
        feeder = threading.Thread(target=publish_until, args=(found,), daemon=True)
        feeder.start()
        got = driver.wait_for_message(MagneticField, topic, lambda m: bool(driver.spin_errors), timeout=60.0)
        found.append(True)
        feeder.join()
        assert got is not None and driver._thread.is_alive()
        assert driver.spin_errors and driver.spin_errors[0] == "RuntimeError: broken callback"
    finally:
        driver.close()


@pytest.mark.dds
def test_the_driver_credits_each_unstamped_gradient_to_its_own_set() -> None:
    """The ``gradient`` topic has no stamp; the driver once paired it with ``field`` in arrival order, so
    a message lost or cleared on one topic only shifted every later pair (after a busy replay, 0 of 1,900
    fresh sets came back). Now each is credited to the ``gradient_stamped`` with the same numbers: a field
    missing, gradients cleared in flight and an arrival order mixed across topics leave every pair right."""
    import os
    from types import SimpleNamespace

    from magcal_ros.app.ros_driver import ArrayDriver, pick_domain_id

    def stamp(t: int) -> SimpleNamespace:
        return SimpleNamespace(stamp=SimpleNamespace(sec=t // 10**9, nanosec=t % 10**9), frame_id="magcal_array")

    def field(t: int) -> SimpleNamespace:
        return SimpleNamespace(header=stamp(t), magnetic_field=SimpleNamespace(x=1.0, y=2.0, z=3.0),
                               magnetic_field_covariance=[0.0] * 9)

    def gradient(g: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(data=g.reshape(-1).tolist(), layout=SimpleNamespace(dim=[]))

    def stamped(t: int, g: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(header=stamp(t), position=g.reshape(-1).tolist(), name=[f"g{k}" for k in range(9)])

    driver = ArrayDriver(("m",), pick_domain_id(os.getpid() + 11), node_name="pairing_driver", listen=False)
    try:
        rng = np.random.default_rng(3)
        stamps = [10**18 + k * 10**7 for k in range(40)]
        tensors = {t: rng.normal(size=(3, 3)) * 1e-8 for t in stamps}
        tensors[stamps[7]] = tensors[stamps[6]].copy()  # two sets with equal tensors
        for t in stamps[:10]:  # gradients first, their stamped twins later, one field lost
            driver._on_gradient(gradient(tensors[t]))
            if t != stamps[3]:
                driver._on_field(field(t))
        for t in stamps[:10]:
            driver._on_stamped(stamped(t, tensors[t]))
        for t in stamps[10:20]:  # outputs cleared while the gradients are in flight
            driver._on_field(field(t))
        driver.clear_outputs()
        for t in stamps[10:20]:
            driver._on_gradient(gradient(tensors[t]))
            driver._on_stamped(stamped(t, tensors[t]))
        for t in stamps[20:]:  # then in order
            driver._on_field(field(t))
            driver._on_stamped(stamped(t, tensors[t]))
            driver._on_gradient(gradient(tensors[t]))
        got = driver.gradients(stamps)
        assert set(got) == set(stamps[10:])
        for t, g in got.items():
            np.testing.assert_array_equal(g, tensors[t])
    finally:
        driver.close()


_CLEAN_UP_SCRIPT = """
import os, signal, sys, time
from magcal_ros.nodes import common
common.CLEANUP_TIMEOUT = float(sys.argv[2])
class Node:
    def destroy_node(self):
        print("destroying", flush=True)
        time.sleep(float(sys.argv[1]))
class Rclpy:
    @staticmethod
    def try_shutdown():
        print("shut down", flush=True)
common._clean_up(Node(), Rclpy)
print("cleaned up", flush=True)
"""


def _clean_up_process(destroy_seconds: float, timeout: float) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", _CLEAN_UP_SCRIPT, str(destroy_seconds), str(timeout)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "destroying"  # inside the clean-up now
    return proc


def test_ctrl_c_again_and_again_during_the_clean_up_is_ignored() -> None:
    """A terminal or launch file signals again while the node shuts down: the clean-up finishes, exit 0."""
    proc = _clean_up_process(destroy_seconds=1.5, timeout=60.0)
    for _ in range(20):
        if proc.poll() is not None:
            break
        proc.send_signal(signal.SIGINT)
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.02)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, out
    assert "shut down" in out and "cleaned up" in out and "Traceback" not in out


def test_a_clean_up_stuck_in_the_middleware_ends_with_its_stack_instead_of_hanging() -> None:
    """``destroy_node`` that never returns (seen once in a few hundred shutdowns): after the clean-up
    timeout the process prints where it was stuck and exits 1 rather than hanging until killed."""
    started = time.monotonic()
    proc = _clean_up_process(destroy_seconds=1000.0, timeout=1.0)
    try:
        out, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 1, out
    assert "destroy_node" in out and "cleaned up" not in out
    assert time.monotonic() - started < 100.0


def test_runs_side_by_side_never_share_a_ros_domain() -> None:
    """Parallel test workers (or a demo beside the tests) pick domain ids from the same seeds: a held id
    is skipped by every other process until it is given back."""
    from magcal_ros.app.ros_driver import pick_domain_id, release_domain_id

    child = [sys.executable, "-c", "from magcal_ros.app.ros_driver import pick_domain_id; print(pick_domain_id(seed=41))"]
    held = pick_domain_id(seed=41)
    try:
        second = pick_domain_id(seed=41)  # this process skips its own lease too
        assert second != held
        release_domain_id(second)
        other = int(subprocess.run(child, capture_output=True, text=True, check=True, timeout=60).stdout)
        assert other != held and 1 <= other <= 100
    finally:
        release_domain_id(held)
    again = int(subprocess.run(child, capture_output=True, text=True, check=True, timeout=60).stdout)
    assert again == held



_PARTICIPANT_SCRIPT = """
import sys, time
import rclpy
rclpy.init()
node = rclpy.create_node("somebody_elses_node")
print("up", flush=True)
sys.stdin.read()  # until the test closes our stdin
node.destroy_node()
rclpy.try_shutdown()
"""


def test_a_domain_with_a_participant_on_it_is_never_leased(monkeypatch: pytest.MonkeyPatch) -> None:
    """A DDS participant the picker did not start (an rclpy node of another process) on the very domain
    a seed points at: the picker skips it, reading the socket tables or, where they cannot be read, by
    binding the domain's ports."""
    from magcal_ros.app import ros_driver as rd

    seed = os.getpid() + 131
    domain = rd.pick_domain_id(seed=seed)  # leased while the participant starts: no run of ours takes it
    assert not rd.domain_in_use(domain), "the picker leased a domain in use"
    child = subprocess.Popen([sys.executable, "-c", _PARTICIPANT_SCRIPT], env=rd.ros_environment(domain),
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "up", child.stdout.read()
        rd.release_domain_id(domain)  # from here only the participant keeps it
        assert rd.domain_in_use(domain)
        picked = rd.pick_domain_id(seed=seed)
        rd.release_domain_id(picked)
        assert picked != domain, f"domain {domain} leased with a participant on it"
        monkeypatch.setattr(rd, "bound_udp_ports", lambda: None)  # no /proc/net/udp: bind each port instead
        assert rd.domain_in_use(domain)
        picked = rd.pick_domain_id(seed=seed)
        rd.release_domain_id(picked)
        assert picked != domain, f"domain {domain} leased with a participant on it (no socket tables)"
    finally:
        rd.release_domain_id(domain)
        child.communicate(timeout=60)


_ENVIRONMENT_PICKS = """
import json, os, subprocess, sys
from magcal_ros.app.ros_driver import isolate_this_process, pick_domain_id, release_domain_id, ros_environment

def picks():
    out = []
    for seed in range(300):
        d = pick_domain_id(seed=seed)
        release_domain_id(d)
        out.append(d)
    return out

if sys.argv[1] == "child":
    print(json.dumps(picks()))
    raise SystemExit
before = picks()
own = pick_domain_id()
isolate_this_process(own)  # what a test driver does: this process's ROS_DOMAIN_ID is now its leased one
after = picks()
grandchild = subprocess.run([sys.executable, "-c", sys.argv[2], "child"], env=ros_environment(own),
                            capture_output=True, text=True, check=True).stdout
print(json.dumps({"before": before, "after": after, "grandchild": json.loads(grandchild)}))
"""


def test_the_environments_ros_domain_id_is_never_leased() -> None:
    """With ROS_DOMAIN_ID=N set (the vehicle's live domain), the tests' picker never returns N, from any
    seed (each domain is some seed's first choice), not even once a run replaced this process's
    ROS_DOMAIN_ID with its own lease, nor in a process that run starts."""
    user = 1 + (os.getpid() + 53) % 100
    env = dict(os.environ, ROS_DOMAIN_ID=str(user))
    env.pop("MAGCAL_USER_ROS_DOMAIN_ID", None)
    done = subprocess.run([sys.executable, "-c", _ENVIRONMENT_PICKS, "parent", _ENVIRONMENT_PICKS], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    picks = __import__("json").loads(done.stdout)
    for when, domains in picks.items():
        assert len(domains) == 300 and all(1 <= d <= 100 for d in domains), when
        assert user not in domains, f"ROS_DOMAIN_ID={user} leased {when}"
    assert len(set(picks["before"])) > 50, "most domains are some seed's choice (others may be leased meanwhile)"


_FLOOD_SCRIPT = """
import sys, time
from magcal_ros.nodes.entry import quiet_signals
stop = quiet_signals()
print("ready", flush=True)
end = time.monotonic() + 1.5
while time.monotonic() < end:
    pass
print("done" if stop.is_set() else "no signal seen", flush=True)
"""


def test_a_flood_of_stop_signals_neither_deadlocks_nor_recurses_the_quiet_handler() -> None:
    """The nodes' Ctrl-C handler runs again inside itself when signals come faster than it returns: one
    that took a lock (``threading.Event.set``) deadlocked on itself (seen: a calibration node stuck in
    its handler after a SIGINT flood) or recursed until RecursionError. SIGINT as fast as ``kill`` can
    send it for a second: the process finishes its work, exit 0."""
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, "-c", _FLOOD_SCRIPT], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        end = time.monotonic() + 1.0
        while time.monotonic() < end and proc.poll() is None:
            os.kill(proc.pid, signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=60)
        finally:
            proc.kill()
        assert proc.returncode == 0 and "done" in out, out[-2000:]


def test_a_node_stops_on_its_stop_flag_when_nothing_wakes_its_executor() -> None:
    """A stop that rclpy's own signal handler did not turn into a shutdown (seen once under load: a node
    on a simulated clock that no longer advanced waited for ever) still ends the spin: the executor's
    wait wakes within ``STOP_POLL`` of wall time and reads the flag. Here the flag is set with no signal
    at all, on a node with nothing to wake it (no timers, no traffic)."""
    from magcal_ros.app.ros_driver import pick_domain_id, ros_environment

    code = (
        "import threading, time\n"
        "from rclpy.executors import SingleThreadedExecutor\n"
        "from rclpy.node import Node\n"
        "from magcal_ros.nodes import common\n"
        "from magcal_ros.nodes.entry import StopFlag\n"
        "stop = StopFlag()\n"
        "threading.Timer(1.0, lambda: stop(0, None)).start()\n"
        "t0 = time.monotonic()\n"
        "code = common.run_node(lambda argv: Node('idle_node'), SingleThreadedExecutor, [], stop)\n"
        "print('stopped', code, round(time.monotonic() - t0, 1))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], env=ros_environment(pick_domain_id()), capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0 and "stopped 0" in done.stdout, done.stdout + done.stderr

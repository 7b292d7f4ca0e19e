"""Drive the magcal nodes from outside, over DDS: start them, feed them, listen to them.

Used by the demo, the node tests and the benchmark. :class:`NodeProcess` runs an
installed node executable as a separate process with ``--ros-args``; :class:`ArrayDriver`
is an rclpy node (own context, spun in a background thread) that publishes raw sets or
replays a rosbag2 message by message, collects the correction node's outputs by stamp
and calls the Trigger and parameter services. :func:`ros_environment` isolates a run:
its own ``ROS_DOMAIN_ID`` and localhost-only discovery.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, MutableMapping, Sequence
from dataclasses import dataclass
from dataclasses import field as default
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.units import NS_PER_S

# --------------------------------------------------------------------------- environment


SERVICE_SETTLE: float = 1.0
"""Seconds a new service client waits after the service is ready before its first call (see
:meth:`ArrayDriver._call`)."""
OTHER_OUTPUTS_SETTLE: float = 5.0
"""Once every set's gradient is in, seconds without progress after which the other topics' outputs of
the same sets are no longer waited for (see :meth:`ArrayDriver.wait_for_outputs`)."""


_LEASES: dict[int, Any] = {}
"""Domain ids this process holds (id -> its locked file), see :func:`pick_domain_id`."""
DOMAIN_IDS = range(1, 101)
"""The domain ids runs lease (:func:`pick_domain_id`)."""
USER_DOMAIN_VARIABLE = "MAGCAL_USER_ROS_DOMAIN_ID"
"""Environment variable that keeps the user's own ``ROS_DOMAIN_ID`` once a run replaced it (see
:func:`ros_environment`): processes started from there still never lease it."""
RTPS_PORT_BASE, RTPS_DOMAIN_GAIN = 7400, 250
"""The RTPS well-known ports (DDSI-RTPS 2.x, 9.6.1.1): every participant of domain ``d`` binds UDP ports
in ``[7400 + 250 d, 7400 + 250 (d + 1))`` (discovery and user traffic, unicast and multicast), whatever
the DDS vendor and however it discovers."""


def environment_domain_ids(env: Mapping[str, str] | None = None) -> set[int]:
    """Domain ids the environment names (``ROS_DOMAIN_ID`` and :data:`USER_DOMAIN_VARIABLE`): never leased."""
    env = os.environ if env is None else env
    out = set()
    for key in ("ROS_DOMAIN_ID", USER_DOMAIN_VARIABLE):
        try:
            out.add(int(env.get(key, "").strip()))
        except ValueError:
            continue
    return out


def rtps_ports(domain: int) -> range:
    """The UDP ports of ``domain``'s participants (see :data:`RTPS_PORT_BASE`)."""
    return range(RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * domain, RTPS_PORT_BASE + RTPS_DOMAIN_GAIN * (domain + 1))


def bound_udp_ports(tables: Sequence[str] = ("/proc/net/udp", "/proc/net/udp6")) -> set[int] | None:
    """Local ports of every UDP socket of this machine's network namespace (``/proc/net/udp*``); None
    when no table can be read."""
    ports: set[int] = set()
    read = False
    for table in tables:
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        read = True
        for line in lines:
            fields = line.split()
            if len(fields) > 1 and ":" in fields[1]:
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports if read else None


def _port_taken(port: int) -> bool:
    """Whether binding UDP ``port`` on every interface fails because a socket holds it."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return True
    return False


def domain_in_use(domain: int, ports: set[int] | None = None) -> bool:
    """Whether a DDS participant of this machine is on ``domain`` (ours or anybody's): a UDP port of its
    RTPS range is bound (:func:`rtps_ports`). Read from ``ports`` (default :func:`bound_udp_ports`), or
    where the socket tables cannot be read by binding each port in turn. Takes no time and joins nothing:
    a graph query would have to join the domain and wait for discovery, and miss a participant that is
    slow to answer or has no node."""
    ports = bound_udp_ports() if ports is None else ports
    if ports is None:
        return any(_port_taken(p) for p in rtps_ports(domain))
    return any(p in ports for p in rtps_ports(domain))


def pick_domain_id(seed: int | None = None) -> int:
    """A ROS domain id in :data:`DOMAIN_IDS`, tried from the one ``seed`` (default: this process id) points
    at, that nothing else uses: never one the environment names (:func:`environment_domain_ids`, the user's
    own), never one another run of this machine holds, never one with a DDS participant on it
    (:func:`domain_in_use`: somebody's nodes, a vehicle's stack). Each id picked is leased through a lock on
    a file in the temporary directory, held until :func:`release_domain_id` or the end of the process, so
    runs side by side (parallel test workers, a demo beside the tests) never share a domain.
    RuntimeError when none is free."""
    start = os.getpid() if seed is None else seed
    avoid = environment_domain_ids()
    for k in range(len(DOMAIN_IDS)):
        domain = DOMAIN_IDS[(start + k) % len(DOMAIN_IDS)]
        if domain in _LEASES or domain in avoid:
            continue
        lock = open(Path(tempfile.gettempdir()) / f"magcal_ros_domain_{domain}.lock", "a")  # noqa: SIM115
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            continue
        if domain_in_use(domain):  # checked under the lease: no other run of ours starts on it meanwhile
            lock.close()
            continue
        _LEASES[domain] = lock
        return domain
    raise RuntimeError(f"no free ROS domain id in {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1}: each is leased by "
                       "another run, has DDS participants on this machine or is the environment's ROS_DOMAIN_ID")


def release_domain_id(domain: int) -> None:
    """Give back a domain id leased by :func:`pick_domain_id` (nothing if this process does not hold it)."""
    lock = _LEASES.pop(domain, None)
    if lock is not None:
        lock.close()


FASTDDS_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="magcal_run_writer" is_default_profile="true">
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>100000000</nanosec></heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""
"""Fast DDS profile of a run's processes: reliable writers announce what they sent every 0.1 s instead
of every 3 s, so that a message the transport dropped on a busy machine is sent again within a
fraction of a second (a reader learns that it misses one only from a later message or from such an
announcement: a replay's last messages would otherwise wait seconds)."""


def fastdds_profile() -> str:
    """Path of a file holding :data:`FASTDDS_PROFILE` (written once, in the temporary directory)."""
    digest = hashlib.sha1(FASTDDS_PROFILE.encode()).hexdigest()[:12]
    path = Path(tempfile.gettempdir()) / f"magcal_fastdds_{digest}.xml"
    if not path.exists():
        tmp = path.with_name(f"{path.name}.{os.getpid()}")
        tmp.write_text(FASTDDS_PROFILE)
        os.replace(tmp, path)
    return str(path)


def use_fastdds_profile(env: MutableMapping[str, str]) -> None:
    """Point ``env`` at :data:`FASTDDS_PROFILE` unless it names a Fast DDS profile of its own."""
    if not env.get("FASTRTPS_DEFAULT_PROFILES_FILE") and not env.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = fastdds_profile()


def ros_environment(domain_id: int, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for a run isolated on ``domain_id`` with localhost-only discovery (and
    :data:`FASTDDS_PROFILE`, see :func:`use_fastdds_profile`); a ``ROS_DOMAIN_ID`` it replaces is kept
    in :data:`USER_DOMAIN_VARIABLE` (unless that is set already), so that :func:`pick_domain_id` in the
    run's processes still avoids it."""
    env = dict(os.environ if base is None else base)
    use_fastdds_profile(env)
    outer = env.get("ROS_DOMAIN_ID", "").strip()
    if outer and outer != str(domain_id):
        env.setdefault(USER_DOMAIN_VARIABLE, outer)  # the user's own id, still avoided by what runs in env
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    env.pop("ROS_STATIC_PEERS", None)
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    return env


def isolate_this_process(domain_id: int) -> None:
    """Apply :func:`ros_environment` to this process (before its first ``rclpy.init``)."""
    os.environ.update(ros_environment(domain_id))


def find_executable(name: str) -> str:
    """Path of an installed node executable: a path as given, PATH, this interpreter's bin, or lib/magcal_ros."""
    if os.sep in name:
        if os.path.isfile(name) and os.access(name, os.X_OK):
            return name
        raise FileNotFoundError(f"{name} is not an executable file")
    candidates = [shutil.which(name), str(Path(sys.executable).parent / name)]
    prefix = Path(sys.prefix)
    candidates.append(str(prefix / "lib" / "magcal_ros" / name))
    for c in candidates:
        if c and os.path.isfile(c) and os.access(c, os.X_OK):
            return c
    raise FileNotFoundError(f"executable {name!r} not found; install the package (pip install . or colcon build)")


def ros_args(
    node_name: str | None = None,
    params: Mapping[str, Any] | None = None,
    params_files: Sequence[str | os.PathLike[str]] = (),
    log_level: str | None = None,
    namespace: str | None = None,
) -> list[str]:
    """``--ros-args`` for a node: rename, namespace, ``-p name:=value`` (YAML values), params files."""
    out = ["--ros-args"]
    if node_name:
        out += ["-r", f"__node:={node_name}"]
    if namespace:
        out += ["-r", f"__ns:=/{namespace.strip('/')}"]
    for f in params_files:
        out += ["--params-file", str(f)]
    for k, v in (params or {}).items():
        out += ["-p", f"{k}:={_yaml_value(v)}"]
    if log_level:
        out += ["--log-level", log_level]
    return out


def _yaml_value(value: Any) -> str:
    """A parameter value as ``-p`` YAML: floats always with a decimal point."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        text = repr(value)
        if "." not in text and "e" in text:
            mant, exp = text.split("e")
            text = f"{mant}.0e{exp}"
        return text
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return str(value)


class NodeProcess:
    """One node executable running as a child process, its output captured to a log file."""

    def __init__(
        self,
        executable: str,
        args: Sequence[str],
        env: Mapping[str, str],
        log_path: str | os.PathLike[str],
        process_group: int | None = None,
    ) -> None:
        """``executable``: a name (found by :func:`find_executable`) or a path. The process leads a
        new session, or with ``process_group`` joins that process group of this session (0: a new
        group led by the process), as the processes of one terminal command do."""
        self.executable = find_executable(executable)
        self.args = list(args)
        self.log_path = Path(log_path)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "w", encoding="utf-8")
        group: dict[str, Any] = {"start_new_session": True} if process_group is None else {"process_group": process_group}
        self.process = subprocess.Popen(
            [self.executable, *self.args], env=dict(env), stdout=self._log, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, **group,
        )

    @property
    def pid(self) -> int:
        """Process id."""
        return self.process.pid

    def alive(self) -> bool:
        """True while the process runs."""
        return self.process.poll() is None

    def log(self) -> str:
        """Everything the node printed so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def wait_for_log(self, text: str, timeout: float = 30.0) -> bool:
        """Wait until ``text`` appears in the log (or the process ends)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.log():
                return True
            if not self.alive():
                return text in self.log()
            time.sleep(0.05)
        return False

    def stop(self, timeout: float = 20.0) -> int:
        """Ctrl-C the node, wait for a clean exit, kill it if it hangs; returns the exit code. The wait outlasts the
        node's own limit on its clean-up (15 s, then it prints its stacks and exits with 1): on a loaded machine
        destroying a node's endpoints took longer than the 10 s waited before, and the node was killed (-9) while
        it was still closing."""
        if self.alive():
            self.process.send_signal(signal.SIGINT)
        return self.wait(timeout)

    def wait(self, timeout: float = 10.0) -> int:
        """Wait for the process to end (killed if it is still there after ``timeout``); the exit code."""
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            # A hung node: ask it where it is (SIGUSR1 prints every thread's stack into its log)
            # before killing it, so the log says why it did not exit.
            if hasattr(signal, "SIGUSR1"):
                with contextlib.suppress(ProcessLookupError):
                    self.process.send_signal(signal.SIGUSR1)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.process.wait(2.0)
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait(5.0)
        self._log.close()
        return int(self.process.returncode)


# --------------------------------------------------------------------------- raw messages


@dataclass(frozen=True)
class RawMessage:
    """One raw reading to publish: sensor name, header stamp (ns), vector (T)."""

    name: str
    stamp_ns: int
    vector: tuple[float, float, float]


def recording_messages(
    names: Sequence[str], stamps_ns: NDArray[np.int64], vectors: NDArray[np.float64]
) -> list[RawMessage]:
    """Messages of complete sets (stamps (N,) int ns, vectors (N, S, 3) T), sensor order per set."""
    ns = np.asarray(stamps_ns, dtype=np.int64)
    out = []
    for t, sets in zip(ns.tolist(), np.asarray(vectors, dtype=float).tolist()):
        for name, v in zip(names, sets):
            out.append(RawMessage(name, t, (v[0], v[1], v[2])))
    return out


def serialized_sets(
    names: Sequence[str], stamps_ns: NDArray[np.int64], vectors: NDArray[np.float64]
) -> list[list[bytes]]:
    """CDR bytes of complete sets (stamps (N,) ns, vectors (N, S, 3) T): per set, one message per sensor."""
    from magcal_ros.io.cdr import magnetic_field_template

    columns = [
        magnetic_field_template(n).encode(np.asarray(stamps_ns, dtype=np.int64), np.asarray(vectors)[:, k])
        for k, n in enumerate(names)
    ]
    return [[bytes(col[i]) for col in columns] for i in range(len(stamps_ns))]


def bag_messages(path: str | os.PathLike[str], names: Sequence[str] | None = None) -> list[RawMessage]:
    """Every ``/<name>/raw`` message of a rosbag2 directory, in bag order, as recorded."""
    from magcal_ros.io.bag_reader import open_bag, resolve_sensor_topics
    from magcal_ros.io.cdr import decode_magnetic_fields

    with open_bag(path) as reader:
        found, conns = resolve_sensor_topics(reader, path, names)
        by_id = {c.id: n for n, cs in zip(found, conns) for c in cs}
        out = []
        for conn, _, data in reader.messages(connections=[c for cs in conns for c in cs]):
            stamps, vectors = decode_magnetic_fields([bytes(data)], str(path))
            v = vectors[0]
            out.append(RawMessage(by_id[conn.id], int(stamps[0]), (float(v[0]), float(v[1]), float(v[2]))))
    return out


def write_messages_bag(path: str | os.PathLike[str], messages: Iterable[RawMessage], storage: str = "sqlite3") -> None:
    """Write raw messages as they are (gaps, NaN and all) to a rosbag2 directory.

    Bag time is the header stamp, but never earlier than the previous message's bag time
    (+1 ns), so a reader returns the messages in the given order, late ones included.
    """
    from magcal_ros.io import topics
    from magcal_ros.io.atomic import atomic_path
    from magcal_ros.io.bag_writer import BagSink
    from magcal_ros.io.cdr import MAGNETIC_FIELD, magnetic_field_message, typestore

    store = typestore()
    msgs = list(messages)
    with atomic_path(path) as tmp, BagSink.create(tmp, storage) as sink:  # type: ignore[arg-type]
        conns: dict[str, Any] = {}
        items = []
        bag_time = -1
        for m in msgs:
            if m.name not in conns:
                conns[m.name] = sink.add_topic(topics.absolute(topics.raw(m.name)), MAGNETIC_FIELD)
            sec, nsec = divmod(m.stamp_ns, NS_PER_S)
            data = store.serialize_cdr(magnetic_field_message(sec, nsec, m.name, m.vector), MAGNETIC_FIELD)
            bag_time = max(m.stamp_ns, bag_time + 1)
            items.append((conns[m.name], bag_time, bytes(data)))
        sink.write_messages(items)


# --------------------------------------------------------------------------- driver node


@dataclass
class Outputs:
    """What the correction node published, by set stamp (ns)."""

    gradient: dict[int, NDArray[np.float64]] = default(default_factory=dict)
    """Gradient (3, 3) T/m by the field message's stamp (the gradient follows its field)."""
    field: dict[int, NDArray[np.float64]] = default(default_factory=dict)
    corrected: dict[str, dict[int, NDArray[np.float64]]] = default(default_factory=dict)
    latency: list[float] = default(default_factory=list)
    """Receipt wall time minus stamp (s) of each gradient, when stamps are wall times."""
    gradient_layouts: list[tuple[tuple[str, int, int], ...]] = default(default_factory=list)
    stamped: dict[int, NDArray[np.float64]] = default(default_factory=dict)
    """Gradient (3, 3) T/m from gradient_stamped, by its header stamp."""
    stamped_frames: set[str] = default(default_factory=set)
    stamped_names: list[tuple[str, ...]] = default(default_factory=list)
    covariances: dict[str, NDArray[np.float64]] = default(default_factory=dict)
    """Last magnetic_field_covariance (9,) received on field and each <name>/corrected, by topic name."""
    field_covariance: dict[int, NDArray[np.float64]] = default(default_factory=dict)
    """magnetic_field_covariance (9,) of each field message, by its header stamp (a message that comes
    late from an earlier replay cannot pass for a new one)."""
    baseline: dict[int, NDArray[np.float64]] = default(default_factory=dict)
    """Baseline gradient dB/ds (3,) T/m by its header stamp (a collinear array)."""
    baseline_frames: set[str] = default(default_factory=set)


def _wait_until(due: float) -> None:
    """Sleep until the monotonic clock reads ``due`` (s); at once when it is past."""
    delay = due - time.monotonic()
    if delay > 0:
        time.sleep(delay)


class _SideStreams:
    """The side sensors of a replay (currents, temperatures, the IMU): each set's values published with
    the set's stamp, in order, up to a given count of sets (see :meth:`ArrayDriver.replay`)."""

    def __init__(self, driver: ArrayDriver, stamps: Sequence[int], currents: NDArray[np.float64] | None,
                 temperatures: NDArray[np.float64] | None,
                 imu: tuple[NDArray[np.float64], NDArray[np.float64]] | None) -> None:
        self.driver, self.stamps = driver, stamps
        self.currents, self.temperatures, self.imu = currents, temperatures, imu
        self.sent = 0

    def send(self, upto: int) -> None:
        """Publish the side values of the sets before ``upto`` not sent yet (none without side streams)."""
        while self.sent < min(upto, len(self.stamps)):
            k, d = self.sent, self.driver
            if self.currents is not None:
                for j, amperes in enumerate(self.currents[k]):
                    d.publish_current(j, self.stamps[k], float(amperes))
            if self.temperatures is not None:
                for j, celsius in enumerate(self.temperatures[k]):
                    d.publish_temperature(j, self.stamps[k], float(celsius))
            if self.imu is not None:
                d.publish_imu(self.stamps[k], self.imu[0][k], self.imu[1][k])
            self.sent += 1


class ArrayDriver:
    """An rclpy node in its own context and thread that feeds and watches the magcal nodes."""

    def __init__(
        self,
        names: Sequence[str],
        domain_id: int,
        node_name: str = "magcal_driver",
        collect_corrected: bool = True,
        publish_depth: int = 10000,
        namespace: str = "",
        listen: bool = True,
        kind: str = "tensor",
        currents: Sequence[tuple[str, str]] = (),
        temperatures: bool = False,
        imu_topic: str | None = None,
    ) -> None:
        """``namespace``: the nodes' namespace; raw topics are published and outputs read in it.
        ``listen=False``: publish only (no subscriptions to the outputs). ``kind``: the gradient
        the correction node publishes for this array (``tensor``: ``gradient`` and
        ``gradient_stamped``; ``baseline``: ``baseline_gradient``; ``none``: only ``field``).
        ``currents``: (topic, type) of each current channel to publish (type
        ``sensor_msgs/msg/BatteryState`` or ``std_msgs/msg/Float64``). ``temperatures``: publish
        ``<name>/temperature`` (sensor_msgs/Temperature) per sensor; ``imu_topic``: publish the IMU
        (sensor_msgs/Imu) there."""
        import rclpy
        from geometry_msgs.msg import Vector3Stamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import BatteryState, Imu, JointState, MagneticField, Temperature
        from std_msgs.msg import Float64, Float64MultiArray

        self._rclpy = rclpy
        isolate_this_process(domain_id)
        self.names = tuple(names)
        self.prefix = f"/{namespace.strip('/')}" if namespace.strip("/") else ""
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(node_name, context=self.context)
        self._msg_type = MagneticField
        reliable = QoSProfile(depth=publish_depth, reliability=ReliabilityPolicy.RELIABLE)
        self.publishers = {
            n: self.node.create_publisher(MagneticField, self.topic(f"{n}/raw"), reliable) for n in self.names
        }
        if kind not in ("tensor", "baseline", "none"):
            raise ValueError(f"kind must be tensor, baseline or none, got {kind!r}")
        self.kind = kind
        self._current_types = {"sensor_msgs/msg/BatteryState": BatteryState, "std_msgs/msg/Float64": Float64}
        self.current_publishers = [
            (self.node.create_publisher(self._current_types[t], self.topic(topic), reliable), t)
            for topic, t in currents
        ]
        self._temperature_type, self._imu_type = Temperature, Imu
        self.temperature_publishers = [
            self.node.create_publisher(Temperature, self.topic(f"{n}/temperature"), reliable) for n in self.names
        ] if temperatures else []
        self.imu_publisher = self.node.create_publisher(Imu, self.topic(imu_topic), reliable) if imu_topic else None
        self.outputs = Outputs()
        self._lock = threading.Lock()
        self._retired: list[Any] = []
        """Subscriptions and clients to destroy in the spinning thread (:meth:`_retire`)."""
        # The ``gradient`` topic has no stamp: each is credited to the set whose ``gradient_stamped`` carries
        # the same nine numbers (robust to a message lost or cleared on one topic only, which pairing in
        # arrival order is not: one lost message shifted every later pair).
        self._tensors: dict[bytes, deque[tuple[int, NDArray[np.float64]]]] = {}
        self._stamps_of: dict[bytes, deque[int]] = {}
        out_qos = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)  # a busy reader catches up
        self.subscriptions = [
            self.node.create_subscription(MagneticField, self.topic("field"), self._on_field, out_qos),
        ] if listen else []
        if listen and kind == "tensor":
            self.subscriptions += [
                self.node.create_subscription(Float64MultiArray, self.topic("gradient"), self._on_gradient, out_qos),
                self.node.create_subscription(JointState, self.topic("gradient_stamped"), self._on_stamped, out_qos),
            ]
        if listen and kind == "baseline":
            self.subscriptions.append(self.node.create_subscription(
                Vector3Stamped, self.topic("baseline_gradient"), self._on_baseline, out_qos))
        if collect_corrected and listen:
            for n in self.names:
                self.outputs.corrected[n] = {}
                self.subscriptions.append(self.node.create_subscription(
                    MagneticField, self.topic(f"{n}/corrected"), self._corrected_cb(n), out_qos))
        self._clock_pub: Any = None
        self.statuses: dict[str, Any] = {}
        self._clients: dict[tuple[Any, str], Any] = {}
        """Service clients by (type, name), kept between calls (see :meth:`_call`)."""
        self.status_history: dict[str, deque[Any]] = {}
        """Every status received per name (see :meth:`statuses_of`)."""
        self.spin_errors: list[str] = []
        """What callbacks raised in the driver's thread (see :meth:`_spin`)."""
        self._closing = threading.Event()
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name="magcal-driver", daemon=True)
        self._thread.start()

    def topic(self, relative: str) -> str:
        """The absolute name of a node topic in the driver's namespace."""
        return f"{self.prefix}/{relative.lstrip('/')}"

    def _spin(self) -> None:
        """Run the callbacks until :meth:`close`. A callback that raises is reported on stderr and kept in
        :attr:`spin_errors`, and the spinning goes on: a driver whose thread ended would hear nothing more
        for the rest of its life (every later wait times out, far from the cause)."""
        while not self._closing.is_set() and self.context.ok():
            try:
                self._executor.spin_once(timeout_sec=0.2)
                self._destroy_retired()
            except Exception as exc:  # noqa: BLE001 - see the docstring
                if self._closing.is_set() or not self.context.ok():
                    return
                self.spin_errors.append(f"{type(exc).__name__}: {exc}")
                print(f"magcal driver: a callback raised (the driver carries on):\n{traceback.format_exc()}",
                      file=sys.stderr, flush=True)

    def _retire(self, entity: Any) -> None:
        """Have the spinning thread destroy a subscription or client between two waits: destroyed from another
        thread while the executor builds its wait set, it makes that wait raise (``InvalidHandle``)."""
        with self._lock:
            self._retired.append(entity)

    def _destroy_retired(self) -> None:
        with self._lock:
            retired, self._retired = self._retired, []
        from rclpy.client import Client

        for entity in retired:
            if isinstance(entity, Client):
                self.node.destroy_client(entity)
            else:
                self.node.destroy_subscription(entity)

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self._closing.set()
        self._executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)
        self._thread.join(5.0)

    def __enter__(self) -> ArrayDriver:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- outputs ----------------------------------------------------------------------
    def _on_field(self, msg: Any) -> None:
        t = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        f = msg.magnetic_field
        with self._lock:
            self.outputs.field[t] = np.array([f.x, f.y, f.z])
            self.outputs.covariances["field"] = np.array(msg.magnetic_field_covariance, dtype=float)
            self.outputs.field_covariance[t] = self.outputs.covariances["field"]

    def _on_gradient(self, msg: Any) -> None:
        now = time.time_ns()
        g = np.array(msg.data, dtype=float).reshape(3, 3)
        with self._lock:
            key = g.tobytes()
            self._tensors.setdefault(key, deque()).append((now, g))
            if not self.outputs.gradient_layouts:
                self.outputs.gradient_layouts.append(
                    tuple((d.label, int(d.size), int(d.stride)) for d in msg.layout.dim)
                )
            self._pair(key)

    def _on_stamped(self, msg: Any) -> None:
        t = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        g = np.array(msg.position, dtype=float).reshape(3, 3)
        with self._lock:
            self.outputs.stamped[t] = g
            self.outputs.stamped_frames.add(msg.header.frame_id)
            if not self.outputs.stamped_names:
                self.outputs.stamped_names.append(tuple(msg.name))
            key = g.tobytes()
            self._stamps_of.setdefault(key, deque()).append(t)
            self._pair(key)

    def _on_baseline(self, msg: Any) -> None:
        t = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        v = msg.vector
        with self._lock:
            self.outputs.baseline[t] = np.array([v.x, v.y, v.z])
            self.outputs.baseline_frames.add(msg.header.frame_id)

    def _received(self) -> dict[int, Any]:
        """What marks a set as come back, by stamp: its gradient, baseline gradient, or field (one sensor).
        Call with the lock held."""
        return {"tensor": self.outputs.gradient, "baseline": self.outputs.baseline, "none": self.outputs.field}[self.kind]

    def _pair(self, key: bytes) -> None:
        """Credit the unstamped gradients with the nine numbers ``key`` to the sets whose stamped gradient
        carries them (in order, for sets with equal tensors). Call with the lock held."""
        tensors, stamps = self._tensors.get(key), self._stamps_of.get(key)
        while tensors and stamps:
            t = stamps.popleft()
            received, g = tensors.popleft()
            self.outputs.gradient[t] = g
            self.outputs.latency.append((received - t) / NS_PER_S)
        for store in (self._tensors, self._stamps_of):
            if key in store and not store[key]:
                del store[key]

    def _corrected_cb(self, name: str) -> Any:
        def cb(msg: Any) -> None:
            t = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
            f = msg.magnetic_field
            with self._lock:
                self.outputs.corrected[name][t] = np.array([f.x, f.y, f.z])
                self.outputs.covariances[name] = np.array(msg.magnetic_field_covariance, dtype=float)

        return cb

    def clear_outputs(self) -> None:
        """Forget everything received so far."""
        with self._lock:
            self.outputs.gradient.clear()
            self.outputs.field.clear()
            for d in self.outputs.corrected.values():
                d.clear()
            self.outputs.latency.clear()
            self.outputs.stamped.clear()
            self.outputs.covariances.clear()
            self.outputs.field_covariance.clear()
            self.outputs.baseline.clear()
            self._tensors.clear()
            self._stamps_of.clear()

    def gradients(self, stamps: Iterable[int]) -> dict[int, NDArray[np.float64]]:
        """Received gradients for the given set stamps (missing ones left out)."""
        with self._lock:
            return {t: self.outputs.gradient[t] for t in stamps if t in self.outputs.gradient}

    def corrected(self, stamps: Iterable[int]) -> dict[int, NDArray[np.float64]]:
        """Corrected vectors (S, 3) for the given set stamps where every sensor's arrived."""
        out = {}
        with self._lock:
            for t in stamps:
                rows = [self.outputs.corrected[n].get(t) for n in self.names]
                if all(r is not None for r in rows):
                    out[t] = np.stack(rows)  # type: ignore[arg-type]
        return out

    def fields(self, stamps: Iterable[int]) -> dict[int, NDArray[np.float64]]:
        """Received centre fields (3,) T for the given set stamps (missing ones left out)."""
        with self._lock:
            return {t: self.outputs.field[t] for t in stamps if t in self.outputs.field}

    def baselines(self, stamps: Iterable[int]) -> dict[int, NDArray[np.float64]]:
        """Received baseline gradients (3,) T/m for the given set stamps (missing ones left out)."""
        with self._lock:
            return {t: self.outputs.baseline[t] for t in stamps if t in self.outputs.baseline}

    def wait_for_outputs(self, stamps: Sequence[int], timeout: float = 60.0, settle: float = 5.0,
                         expected: Callable[[], int | None] | None = None) -> int:
        """Wait until the outputs of all ``stamps`` arrived (gradients; baseline gradients, or fields for
        one sensor, see ``kind``), or none arrived for ``settle`` s; then until the other topics' outputs
        of those sets are in too (at most :data:`OTHER_OUTPUTS_SETTLE` s without progress).

        ``expected()``: how many of these sets the node says it published, once it has judged them all
        (None before): the wait ends when those arrived, without waiting ``settle`` for sets it withheld.
        Returns how many arrived. Never fails on time: the caller checks what it got.
        """
        wanted = set(stamps)
        deadline = time.monotonic() + timeout
        last_count, last_change = -1, time.monotonic()
        while time.monotonic() < deadline:
            with self._lock:
                received = self._received()
                count = sum(1 for t in wanted if t in received)
            published = expected() if expected is not None else None
            if count == len(wanted) or (published is not None and count >= published):
                self._wait_for_the_other_outputs(settle=min(settle, OTHER_OUTPUTS_SETTLE))
                return count
            if count != last_count:
                last_count, last_change = count, time.monotonic()
            elif time.monotonic() - last_change > settle and count > 0:
                return count
            time.sleep(0.02)
        return max(last_count, 0)

    def _behind(self) -> int:
        """How many outputs of the other topics (field, stamped gradient, every sensor's corrected) are still
        missing against the sets come back (see :meth:`_received`). Call with the lock held."""
        done = len(self._received())
        stores = [self.outputs.field, *self.outputs.corrected.values()]
        if self.kind == "tensor":
            stores.append(self.outputs.stamped)
        return sum(max(done - len(d), 0) for d in stores)

    def _wait_for_the_other_outputs(self, settle: float) -> None:
        """Let the other topics' callbacks catch up with the sets come back: this reader serves its topics in
        turn, and on a busy machine a set's corrected vectors can still be queued when its gradient is in.
        Returns when none is missing or nothing changed for ``settle`` s (an output the node does not send)."""
        last, since = -1, time.monotonic()
        while True:
            with self._lock:
                behind = self._behind()
            if behind == 0:
                return
            if behind != last:
                last, since = behind, time.monotonic()
            elif time.monotonic() - since > settle:
                return
            time.sleep(0.02)

    # -- discovery --------------------------------------------------------------------
    def wait_for_subscribers(self, count: int = 1, timeout: float = 30.0) -> bool:
        """Wait until every raw publisher is matched by at least ``count`` subscriptions."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(p.get_subscription_count() >= count for p in self.publishers.values()):
                return True
            time.sleep(0.02)
        return False

    def wait_for_output_publishers(self, timeout: float = 30.0) -> bool:
        """Wait until /field, /gradient (and /<name>/corrected) have a publisher matched."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(s.get_publisher_count() >= 1 for s in self.subscriptions):
                return True
            time.sleep(0.02)
        return False

    def prime(self, timeout: float = 30.0) -> bool:
        """Publish probe sets until both ``field`` and the gradient (see ``kind``) come back, then forget them.

        Discovery is not symmetric: this side may see the node's writers before they see
        this side's readers, and early messages of one topic can be lost while the other's
        arrive. Once both topics have delivered, delivery is reliable and gradients pair
        with fields one to one. Returns False if nothing came back within ``timeout``.
        """
        deadline = time.monotonic() + timeout
        probe = (2.0e-5, 1.0e-6, 4.5e-5)
        ok = False
        while time.monotonic() < deadline:
            stamp = time.time_ns()
            for n in self.names:
                self.publish(RawMessage(n, stamp, probe))
            time.sleep(0.2)
            with self._lock:
                gradient = {"tensor": bool(self.outputs.gradient) or bool(self._tensors),
                            "baseline": bool(self.outputs.baseline), "none": True}[self.kind]
                ok = bool(self.outputs.field) and gradient
            if ok:
                break
        time.sleep(0.3)
        self.clear_outputs()
        return ok

    # -- publishing -------------------------------------------------------------------
    def publish(self, message: RawMessage) -> None:
        """Publish one raw reading with its stamp."""
        msg = self._msg_type()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(message.stamp_ns, NS_PER_S)
        msg.header.frame_id = message.name
        msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = message.vector
        self.publishers[message.name].publish(msg)

    def publish_current(self, channel: int, stamp_ns: int, amperes: float) -> None:
        """Publish one current (A) on channel ``channel``'s topic: a BatteryState stamped ``stamp_ns``,
        or a Float64 (no stamp: the receiver stamps it on arrival)."""
        pub, kind = self.current_publishers[channel]
        msg = self._current_types[kind]()
        if kind.endswith("BatteryState"):
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), NS_PER_S)
            msg.current = float(amperes)
        else:
            msg.data = float(amperes)
        pub.publish(msg)

    def publish_temperature(self, sensor: int, stamp_ns: int, celsius: float) -> None:
        """Publish one temperature (deg C) of sensor ``sensor`` (index into ``names``) stamped ``stamp_ns``."""
        msg = self._temperature_type()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), NS_PER_S)
        msg.header.frame_id = self.names[sensor]
        msg.temperature = float(celsius)
        self.temperature_publishers[sensor].publish(msg)

    def publish_imu(self, stamp_ns: int, orientation: Sequence[float], angular_velocity: Sequence[float],
                    frame_id: str = "imu_link") -> None:
        """Publish one IMU sample: quaternion x, y, z, w (IMU frame -> ENU; NaN: unknown, sent as covariance[0]
        = -1) and angular velocity rad/s (NaN: unknown), stamped ``stamp_ns``."""
        msg = self._imu_type()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), NS_PER_S)
        msg.header.frame_id = frame_id
        q = [float(v) for v in orientation]
        w = [float(v) for v in angular_velocity]
        if all(math.isfinite(v) for v in q):
            msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = q
        else:
            msg.orientation_covariance[0] = -1.0
        if all(math.isfinite(v) for v in w):
            msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = w
        else:
            msg.angular_velocity_covariance[0] = -1.0
        msg.linear_acceleration_covariance[0] = -1.0
        self.imu_publisher.publish(msg)  # type: ignore[union-attr]

    def replay(
        self,
        messages: Sequence[RawMessage],
        rate: float = 200.0,
        restamp: bool = True,
        progress: Any = None,
        currents: NDArray[np.float64] | None = None,
        current_lead: int | None = None,
        temperatures: NDArray[np.float64] | None = None,
        imu: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    ) -> dict[int, int]:
        """Publish ``messages`` in order, ``rate`` sets (distinct stamps) per second.

        With ``restamp`` set ``k`` is stamped with the wall time at which it is due (start
        + k / rate), like a live sensor sampling at ``rate``: stamps keep their spacing even
        when publishing lags, and latency is measured from the sampling instant. Returns
        ``{original stamp: published stamp}``.

        ``currents`` (sets, m) A: the channels' currents of each set (in order of the sets'
        first messages), published on the :attr:`current_publishers` with the set's stamp
        ``current_lead`` sets ahead of the set itself (default: one second of sets; the first sets
        start that much later; the side messages go out at the sets' pace from the start, never in
        a burst), so that a receiver has them whatever the order in which its topics are served and
        however late a lost message is sent again (a receiver keeps 2 s of values and takes the
        latest stamped not after the set: a current that came late would be the previous one). ``temperatures``
        (sets, S) deg C and ``imu`` (orientation (sets, 4), angular velocity (sets, 3)) go out the
        same way, with each set's stamp.
        """
        mapping: dict[int, int] = {}
        period = 1.0 / rate if rate > 0 else 0.0
        spacing = int(period * NS_PER_S) if period else 10_000_000
        sides = currents is not None or temperatures is not None or imu is not None
        if current_lead is None:
            current_lead = max(1, int(round(rate))) if rate > 0 else 25
        lead = current_lead if sides else 0  # the side sensors started that much earlier
        start = time.monotonic() + lead * period
        start_ns = time.time_ns() + lead * spacing
        originals = list(dict.fromkeys(m.stamp_ns for m in messages)) if sides else []
        stamps = [start_ns + k * spacing for k in range(len(originals))] if restamp else originals
        side = _SideStreams(self, stamps, currents, temperatures, imu)
        ahead = start - lead * period
        for j in range(min(lead, len(originals))):  # paced like the sets: a burst can overflow the transport
            _wait_until(ahead + j * period)
            side.send(j + 1)
        for m in messages:
            stamp = mapping.get(m.stamp_ns)
            if stamp is None:
                k = len(mapping)
                if period:
                    _wait_until(start + k * period)
                side.send(k + 1 + lead)
                stamp = start_ns + k * spacing if restamp else m.stamp_ns
                mapping[m.stamp_ns] = stamp
                if progress is not None and (k + 1) % 500 == 0:
                    progress(k + 1)
            self.publish(RawMessage(m.name, stamp, m.vector))
        return mapping

    def replay_serialized(self, frames: Sequence[Sequence[bytes]], rate: float) -> tuple[int, float]:
        """Publish pre-serialized sets (per set, one CDR message per sensor in ``names`` order) at ``rate``.

        The fast path for high rates: no message objects, no serialization while publishing.
        Returns (sets published, seconds taken).
        """
        pubs = [self.publishers[n] for n in self.names]
        period = 1.0 / rate
        start = time.monotonic()
        for k, frame in enumerate(frames):
            delay = start + k * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            for pub, data in zip(pubs, frame):
                pub.publish(data)
        return len(frames), time.monotonic() - start

    # -- services ---------------------------------------------------------------------
    def _call(self, srv_type: Any, name: str, request: Any, timeout: float) -> Any:
        """One call; the client is kept for the next calls of the same service. A new client waits for the
        service and then :data:`SERVICE_SETTLE` s more: the service is "ready" once it hears requests, but
        its answer is lost when it has not yet discovered the client's reply reader (a busy machine
        discovers slowly), and a kept client is discovered once."""
        key = (srv_type, name)
        with self._lock:
            client = self._clients.get(key)
        new = client is None
        if new:
            client = self.node.create_client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            if new:
                self._retire(client)
            raise TimeoutError(f"service {name} not available after {timeout:g} s")
        if new:
            time.sleep(SERVICE_SETTLE)
            with self._lock:
                self._clients[key] = client
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout) or future.result() is None:
            raise TimeoutError(f"service {name} did not answer within {timeout:g} s")
        return future.result()

    def trigger(self, name: str, timeout: float = 300.0) -> tuple[bool, str]:
        """Call a std_srvs/Trigger service; returns (success, message)."""
        from std_srvs.srv import Trigger

        reply = self._call(Trigger, name, Trigger.Request(), timeout)
        return bool(reply.success), str(reply.message)

    def set_parameters(self, node: str, values: Mapping[str, Any], atomic: bool = True,
                       timeout: float = 120.0) -> list[tuple[bool, str]]:
        """Set parameters of ``node`` through its parameter service; (successful, reason) each."""
        from rcl_interfaces.srv import SetParameters, SetParametersAtomically

        from magcal_ros.nodes.common import parameter_message

        msgs = [parameter_message(k, v) for k, v in values.items()]
        if atomic:
            reply = self._call(SetParametersAtomically, f"/{node.strip('/')}/set_parameters_atomically",
                               SetParametersAtomically.Request(parameters=msgs), timeout)
            return [(bool(reply.result.successful), str(reply.result.reason))]
        reply = self._call(SetParameters, f"/{node.strip('/')}/set_parameters",
                           SetParameters.Request(parameters=msgs), timeout)
        return [(bool(r.successful), str(r.reason)) for r in reply.results]

    def get_parameters(self, node: str, names: Sequence[str], timeout: float = 120.0) -> dict[str, Any]:
        """Values of parameters of ``node`` (None for unset ones)."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        request = GetParameters.Request(names=list(names))
        reply = self._call(GetParameters, f"/{node.strip('/')}/get_parameters", request, timeout)
        out = {}
        for n, v in zip(names, reply.values):
            value = parameter_value_to_python(v)
            out[n] = list(value) if isinstance(value, (list, tuple)) or hasattr(value, "tolist") else value
        return out

    def describe_parameters(self, node: str, names: Sequence[str], timeout: float = 120.0) -> dict[str, Any]:
        """rcl_interfaces/ParameterDescriptor of parameters of ``node``, by name."""
        from rcl_interfaces.srv import DescribeParameters

        reply = self._call(DescribeParameters, f"/{node.strip('/')}/describe_parameters",
                           DescribeParameters.Request(names=list(names)), timeout)
        return {d.name: d for d in reply.descriptors}

    def publish_clock(self, stamp_ns: int) -> None:
        """Publish ``stamp_ns`` on /clock (rosgraph_msgs/Clock), as a bag player with --clock does."""
        from rosgraph_msgs.msg import Clock

        if self._clock_pub is None:
            self._clock_pub = self.node.create_publisher(Clock, "/clock", 10)
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(stamp_ns), NS_PER_S)
        self._clock_pub.publish(msg)

    def diagnostics(self, node: str, predicate: Any = None, timeout: float = 30.0) -> Any:
        """The first status of ``node`` (fully qualified name) on /diagnostics satisfying ``predicate``."""
        from diagnostic_msgs.msg import DiagnosticArray

        found: list[Any] = []

        def match(msg: Any) -> bool:
            for status in msg.status:
                if status.name == node and (predicate is None or predicate(status)):
                    found.append(status)
                    return True
            return False

        self.wait_for_message(DiagnosticArray, "/diagnostics", match, timeout)
        return found[0] if found else None

    def watch_diagnostics(self) -> None:
        """Keep the latest status of every name seen on /diagnostics (see :meth:`status`)."""
        from diagnostic_msgs.msg import DiagnosticArray

        if getattr(self, "_diagnostics_sub", None) is not None:
            return

        def keep(msg: Any) -> None:
            with self._lock:
                for status in msg.status:
                    self.statuses[status.name] = status
                    self.status_history.setdefault(status.name, deque(maxlen=100_000)).append(status)

        self._diagnostics_sub = self.node.create_subscription(DiagnosticArray, "/diagnostics", keep, 100)

    def statuses_of(self, name: str) -> list[Any]:
        """Every status named ``name`` received since :meth:`watch_diagnostics`, oldest first (a reader that
        polls :meth:`status` on a busy machine may miss some)."""
        with self._lock:
            return list(self.status_history.get(name, ()))

    def status(self, name: str) -> Any:
        """The latest status named ``name`` on /diagnostics (after :meth:`watch_diagnostics`), or None."""
        with self._lock:
            return self.statuses.get(name)

    def wait_for_message(self, msg_type: Any, topic: str, predicate: Any = None, timeout: float = 30.0) -> Any:
        """The first message on ``topic`` satisfying ``predicate`` (None on timeout). What ``predicate``
        raises (it runs in the driver's thread) is raised here."""
        got: list[Any] = []
        raised: list[BaseException] = []
        done = threading.Event()

        def cb(msg: Any) -> None:
            if done.is_set():
                return
            try:
                if predicate is None or predicate(msg):
                    got.append(msg)
                    done.set()
            except Exception as exc:  # noqa: BLE001 - handed to the caller
                raised.append(exc)
                done.set()

        sub = self.node.create_subscription(msg_type, topic, cb, 10)
        try:
            done.wait(timeout)
        finally:
            self._retire(sub)
        if raised:
            raise raised[0]
        return got[0] if got else None


def wait_for_samples(driver: ArrayDriver, node: str, count: int, timeout: float = 20.0) -> dict[str, str]:
    """Wait until the calibration node's ``~/progress`` reports at least ``count`` samples.

    Returns the last progress values seen (empty if none arrived).
    """
    from diagnostic_msgs.msg import DiagnosticStatus

    seen: dict[str, str] = {}

    def enough(msg: Any) -> bool:
        seen.clear()
        seen.update(status_values(msg))
        return int(seen.get("samples", "0")) >= count

    driver.wait_for_message(DiagnosticStatus, f"/{node.strip('/')}/progress", enough, timeout)
    return seen


def status_values(msg: Any) -> dict[str, str]:
    """The key/value pairs of a diagnostic_msgs/DiagnosticStatus."""
    return {kv.key: kv.value for kv in msg.values}


def chunks(items: Sequence[Any], size: int) -> Iterator[Sequence[Any]]:
    """Consecutive slices of ``items`` of length ``size``."""
    for a in range(0, len(items), size):
        yield items[a : a + size]


def is_finite(vector: Sequence[float]) -> bool:
    """True when every component is finite."""
    return all(math.isfinite(v) for v in vector)

"""Test harness for the node tests: node processes, a private ROS domain, synthetic data.

The nodes under test always run as separate processes started from their installed
executables with ``--ros-args``; the test talks to them only over DDS through
:class:`magcal_ros.app.ros_driver.ArrayDriver` (publishers, subscriptions, service
clients). Waits are on discovery and on data, with generous timeouts.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magcal_ros.app.ros_driver import (
    ArrayDriver,
    NodeProcess,
    RawMessage,
    pick_domain_id,
    recording_messages,
    release_domain_id,
    ros_args,
    ros_environment,
    use_fastdds_profile,
)
from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.recording import Recording
from magcal_ros.core.units import NT
from magcal_ros.sim.attitudes import single_axis, uniform_random
from magcal_ros.sim.simulator import ArraySimulation, Truth, random_sensor_errors

# before this process's first DDS participant (Fast DDS reads the profile once): the test driver's
# writers are the ones whose lost messages must come back quickly (see ros_driver.FASTDDS_PROFILE)
use_fastdds_profile(os.environ)

INTENSITY = 51_500 * NT
NOISE = 1.0 * NT
BASELINE = 0.4
STARTUP_TIMEOUT = 180.0
DISCOVERY_TIMEOUT = 180.0
REPLAY_RATE = 400.0
CORRECTION = "magcal_correction"
CALIBRATION = "magcal_calibration"
NAMES = ("mag1", "mag2", "mag3", "mag4")
UNCORRECTED = {"uncorrected_sensors": list(NAMES)}
"""Correction node parameters to run without a calibration (raw readings on purpose)."""
LOSSLESS = {"raw_reliability": "reliable", "qos_depth": 10000}
"""Node parameters that deliver every message the test publishes however busy the machine is:
reliable raw (and current) subscriptions and 10,000-deep queues (25 s of a 400 Hz replay), so a
node that falls behind catches up instead of dropping. :meth:`RosRun.start` adds them unless a
test sets these parameters itself (or passes ``lossless=False``)."""
SAMPLES_TIMEOUT = 180.0
"""Generous deadline (s) for a node to count what was sent: never reached unless it is lost."""
OUTPUT_TIMEOUT = 180.0
"""Generous deadline (s) for the outputs of what was sent."""
SERVICE_TIMEOUT = 120.0
"""The calibration node's ``service_timeout`` in the tests: the correction node answers, only late."""
OUTPUT_SETTLE = 60.0
"""Give up waiting for outputs only after this long (s) without a new one."""


@dataclass
class Data:
    """Synthetic recordings of one simulated array (uniform field, so the true tensor is 0)."""

    sim: ArraySimulation
    manoeuvre: Recording
    """Random attitudes for the calibration."""
    check: Recording
    """Fresh attitudes and noise, never used for a calibration."""
    check_truth: Truth
    single_axis: Recording
    """A rotation about z only: a calibration must refuse it."""
    faulty: list[RawMessage]
    faulty_good: list[int]
    """Original stamps (ns) of the faulty replay's sets that are complete and finite."""

    @property
    def names(self) -> tuple[str, ...]:
        return self.sim.geometry.names


def make_data(seed: int = 11, sets: int = 800, check_sets: int = 400) -> Data:
    """Simulate the recordings used by the node tests."""
    rng = np.random.default_rng(seed)
    geometry = ArrayGeometry.cross(BASELINE)
    sensors = tuple(random_sensor_errors(rng) for _ in geometry.names)
    sim = ArraySimulation(geometry, sensors, earth_field(INTENSITY, 60.0, 5.0), noise=NOISE)
    manoeuvre, _ = sim.run(uniform_random(sets, rng), rng, rate=50.0)
    check, check_truth = sim.run(uniform_random(check_sets, rng), rng, rate=50.0, start=1000.0)
    axis, _ = sim.run(single_axis("z", 360), rng, rate=50.0, start=2000.0)
    faulty_rec, _ = sim.run(uniform_random(200, rng), rng, rate=50.0, start=3000.0)
    faulty, good = faulty_messages(faulty_rec)
    return Data(sim, manoeuvre, check, check_truth, axis, faulty, good)


def faulty_messages(rec: Recording) -> tuple[list[RawMessage], list[int]]:
    """Raw messages with NaN and infinite readings, a silent sensor, a repeat and a stale stamp.

    Sets 20-29: mag2 has a NaN; 50-59: mag3 reads +inf; 100-139: mag4 is silent; set 150
    repeats mag1's message; after set 160 a stale mag1 message (set 155's stamp) arrives.
    Returns the messages and the original stamps of the sets that should come through.
    """
    msgs = recording_messages(rec.names, rec.stamps, rec.vectors)
    out: list[RawMessage] = []
    good: list[int] = []
    per_set = len(rec.names)
    for k in range(len(rec)):
        bad_set = False
        for m in msgs[k * per_set : (k + 1) * per_set]:
            v = m.vector
            if 20 <= k < 30 and m.name == "mag2":
                v, bad_set = (v[0], float("nan"), v[2]), True
            if 50 <= k < 60 and m.name == "mag3":
                v, bad_set = (float("inf"), v[1], v[2]), True
            if 100 <= k < 140 and m.name == "mag4":
                bad_set = True
                continue
            out.append(RawMessage(m.name, m.stamp_ns, v))
            if k == 150 and m.name == "mag1":
                out.append(RawMessage(m.name, m.stamp_ns, v))
        if k == 160:
            stale = msgs[155 * per_set]
            out.append(stale)
        if not bad_set:
            good.append(msgs[k * per_set].stamp_ns)
    return out, good


@dataclass
class RosRun:
    """A private ROS domain with node processes and a driver node talking to them."""

    workdir: Path
    domain_id: int = field(default_factory=pick_domain_id)
    processes: list[NodeProcess] = field(default_factory=list)
    drivers: list[ArrayDriver] = field(default_factory=list)

    @property
    def env(self) -> dict[str, str]:
        return ros_environment(self.domain_id)

    def start(
        self,
        executable: str,
        params: Mapping[str, Any] | None = None,
        params_files: Sequence[str | os.PathLike[str]] = (),
        log_name: str | None = None,
        ready_text: str | None = None,
        namespace: str | None = None,
        process_group: int | None = None,
        lossless: bool = True,
    ) -> NodeProcess:
        """Start an installed node executable (name or path) and wait for its start-up log line.

        ``lossless``: a magcal node gets :data:`LOSSLESS` (for the keys ``params`` does not set)."""
        log = self.workdir / f"{log_name or executable}.log"
        if lossless and Path(executable).name in ("correction_node", "calibration_node"):
            params = {**LOSSLESS, **(params or {})}
        args = ros_args(params=params, params_files=params_files, namespace=namespace)
        proc = NodeProcess(executable, args, self.env, log, process_group=process_group)
        self.processes.append(proc)
        text = ready_text or ("correcting" if executable.endswith("correction_node") else "listening to")
        if not proc.wait_for_log(text, STARTUP_TIMEOUT):
            raise AssertionError(f"{executable} did not start:\n{proc.log()}")
        return proc

    def driver(self, names: Sequence[str], namespace: str = "", kind: str = "tensor",
               currents: Sequence[tuple[str, str]] = (), temperatures: bool = False,
               imu_topic: str | None = None) -> ArrayDriver:
        """A driver node on this domain (publishing and listening in ``namespace``; ``kind``,
        ``currents``, ``temperatures`` and ``imu_topic`` as :class:`ArrayDriver` takes them)."""
        d = ArrayDriver(names, self.domain_id, node_name=f"magcal_test_driver_{len(self.drivers)}",
                        namespace=namespace, kind=kind, currents=currents, temperatures=temperatures,
                        imu_topic=imu_topic)
        self.drivers.append(d)
        return d

    def close(self) -> dict[str, int]:
        """Close drivers, stop processes (Ctrl-C); exit codes by log name. What the drivers' callbacks
        raised goes to stderr (pytest shows it with a failure)."""
        for d in self.drivers:
            name = d.node.get_name()
            d.close()
            for error in d.spin_errors:
                print(f"driver {name}: a callback raised {error}", file=sys.stderr)
        self.drivers.clear()
        codes = {p.log_path.stem: p.stop() for p in self.processes}
        self.processes.clear()
        release_domain_id(self.domain_id)
        return codes


def wait_discovered(driver: ArrayDriver, subscribers: int) -> None:
    """Every raw topic matched by ``subscribers`` nodes and every output topic by a publisher."""
    assert driver.wait_for_subscribers(subscribers, DISCOVERY_TIMEOUT), "raw topics not matched by the nodes"
    assert driver.wait_for_output_publishers(DISCOVERY_TIMEOUT), "output topics not matched"
    assert driver.prime(DISCOVERY_TIMEOUT), "the correction node does not answer probe sets"


def replay_recording(driver: ArrayDriver, rec: Recording, rate: float = REPLAY_RATE) -> dict[int, int]:
    """Replay complete sets; returns {original stamp ns: published stamp ns}."""
    return driver.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=rate)


def original_stamps(rec: Recording) -> list[int]:
    """Set stamps of a recording in ns, as the driver keys them."""
    return [int(t) for t in rec.stamps]


def outputs_by_original(
    driver: ArrayDriver,
    mapping: dict[int, int],
    stamps: Sequence[int],
    wait_for: Sequence[int] | None = None,
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Gradients and corrected vectors received for ``stamps`` (original ns), keyed by original stamp.

    Waits for the outputs of ``wait_for`` (original stamps; default ``stamps``) first.
    """
    waited = [mapping[t] for t in (stamps if wait_for is None else wait_for) if t in mapping]
    driver.wait_for_outputs(waited, timeout=OUTPUT_TIMEOUT, settle=OUTPUT_SETTLE)
    published = [mapping[t] for t in stamps if t in mapping]
    back = {mapping[t]: t for t in stamps if t in mapping}
    g = {back[t]: v for t, v in driver.gradients(published).items()}
    c = {back[t]: v for t, v in driver.corrected(published).items()}
    return g, c


def chunked(values: Sequence[Any], n: int) -> Iterator[Sequence[Any]]:
    """Slices of ``n``."""
    for a in range(0, len(values), n):
        yield values[a : a + n]


# -- bags with the stamps a real recording has ------------------------------------------------------
SENSOR_SKEW_NS = 200_000
"""Each sensor after the first stamps this much later than the one before it (ns): four sensors
span 0.6 ms (+ jitter), inside the default 1 ms sync tolerance."""
STAMP_JITTER_NS = 100_000
"""Header stamps of the sensors after the first jitter by up to this much (ns), uniformly."""
BAG_DELAY_NS = (2_000_000, 6_000_000)
"""A message reaches the recorder (its bag time) this long after its header stamp (ns)."""
CURRENT_LEAD_NS = 300_000
"""A current is sampled (header stamp) this much before the set it belongs to (ns)."""


def realistic_stamps(path: str | os.PathLike[str], seed: int = 0) -> dict[str, np.ndarray]:
    """Rewrite a rosbag2 directory in place with the stamps of a real recording; returns each
    ``/<name>/raw`` topic's new header stamps (ns) by sensor name, in bag order.

    The bag's sensors (topics ``/<name>/raw``, names sorted) keep their sets, but sensor ``k``
    stamps ``k`` x :data:`SENSOR_SKEW_NS` plus up to :data:`STAMP_JITTER_NS` of jitter later than
    the first (whose stamps, the sets' stamps, stay as they were); ``BatteryState`` currents are
    stamped :data:`CURRENT_LEAD_NS` before their set; every message's bag time is its header stamp
    plus 2-6 ms (a ``Float64``, which has no header, arrives that much after its old bag time).
    Anything that reads bag time for a header stamp, or the set's stamp for a sensor's own, is
    off by a set then. Values are unchanged.
    """
    from rosbags.rosbag2 import Reader

    from magcal_ros.io.atomic import atomic_path
    from magcal_ros.io.bag_writer import BagSink, storage_of
    from magcal_ros.io.cdr import BATTERY_STATE, MAGNETIC_FIELD, typestore

    src = Path(path)
    rng = np.random.default_rng(seed)
    store = typestore()
    with Reader(src) as reader:
        conns = list(reader.connections)
        raw_topics = sorted(c.topic for c in conns if c.msgtype == MAGNETIC_FIELD and c.topic.endswith("/raw"))
        items = [(c, t, bytes(d)) for c, t, d in reader.messages()]
    skew = {topic: k for k, topic in enumerate(raw_topics)}
    stamps: dict[str, list[int]] = {topic.strip("/")[: -len("/raw")]: [] for topic in raw_topics}
    out = []
    for conn, bag_time, data in items:
        delay = int(rng.integers(*BAG_DELAY_NS))
        if conn.msgtype in (MAGNETIC_FIELD, BATTERY_STATE):
            msg = store.deserialize_cdr(data, conn.msgtype)
            t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            if conn.msgtype == MAGNETIC_FIELD and conn.topic in skew:
                k = skew[conn.topic]
                t += k * SENSOR_SKEW_NS + (int(rng.integers(-STAMP_JITTER_NS, STAMP_JITTER_NS + 1)) if k else 0)
                stamps[conn.topic.strip("/")[: -len("/raw")]].append(t)
            elif conn.msgtype == BATTERY_STATE and t:
                t -= CURRENT_LEAD_NS
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
            data = bytes(store.serialize_cdr(msg, conn.msgtype))
            bag_time = (t if t else bag_time) + delay
        else:
            bag_time += delay
        out.append((conn, bag_time, data))
    storage = storage_of(src)
    tmp_out = src.with_name(src.name + ".realistic")
    with atomic_path(tmp_out) as tmp, BagSink.create(tmp, storage) as sink:  # type: ignore[arg-type]
        new = {c.id: sink.add_copy_of(c) for c in conns}
        sink.write_messages([(new[c.id], t, d) for c, t, d in sorted(out, key=lambda x: x[1])])
    import shutil

    shutil.rmtree(src)
    tmp_out.rename(src)
    return {name: np.array(v, dtype=np.int64) for name, v in stamps.items()}

"""Benchmark of the live nodes over DDS (not a test): CPU against a bare node, throughput, latency, memory.

    python benchmarks/bench_correction_node.py                  # all three parts (about 15 min)
    python benchmarks/bench_correction_node.py --compare-only   # CPU against the bare node only (about 3 min)
    python benchmarks/bench_correction_node.py --rates 500 --minutes 0

CPU against a bare node (``--compare-only``, first part of a full run): ``correction_node`` and
a bare rclpy node (this file, ``--bare``: the same four raw subscriptions and the same seven
publications, ``<name>/corrected`` x 4, ``field``, ``gradient``, ``gradient_stamped``, filled
with the received messages and constants, no maths; rclpy's default QoS event handlers, as a plain
node has them, where the correction node's outputs have none) run side by side as their own processes,
fed by one publisher process at each rate, so both see the same traffic and the same machine
load. For each rate and each set of listeners, in repeated runs: CPU seconds per wall second of
each node process (user + system, from psutil, over the publishing window plus 0.5 s to drain),
and the ratio. Listeners: ``all`` (a receiver process subscribes every output of both nodes, so
every output is published) and ``gradient`` (only ``gradient``: the correction node computes
and builds nothing nobody listens to; the bare node publishes everything regardless, as a
node that does not look does). The receiver counts each node's ``gradient`` messages: both
must deliver every set.

Throughput: ``correction_node`` runs as its own process (installed executable); four
sensors publish from another process at each rate, every set stamped with the wall time
at which it is published. This process receives ``field`` and ``gradient`` and reports
delivered sets/s, dropped sets (published minus corrected, and the node's own counters),
latency p50/p99/max from the set's stamp to receipt of its gradient, and the node's
CPU (% of one core) and RSS (psutil).

Memory flatness: both nodes run for ``--minutes`` at 4 x 200 Hz of a tumbling array while
the calibration node collects (bounded by ``max_samples``); RSS of both is sampled and
its growth after the first minute reported. Targets: no drops and p99 < 5 ms at 4 x 500 Hz.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _first  # noqa: F401  (this checkout; before numpy: one BLAS thread, as the command and nodes run)
import numpy as np

NS_PER_S = 1_000_000_000
NAMES = ("mag1", "mag2", "mag3", "mag4")


# --------------------------------------------------------------------------- publisher process


def publish(rate: float, seconds: float, domain: int, wait_subscribers: int) -> None:
    """Publisher process: four MagneticField topics at ``rate``, stamp = publish wall time."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import MagneticField

    rclpy.init(domain_id=domain)
    node = rclpy.create_node("magcal_bench_publisher")
    qos = QoSProfile(depth=COMPARE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
    pubs = [node.create_publisher(MagneticField, f"/{n}/raw", qos) for n in NAMES]
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and min(p.get_subscription_count() for p in pubs) < wait_subscribers:
        time.sleep(0.01)
    time.sleep(0.5)
    # A tumbling array in a 51 500 nT field: the direction turns about a tilted axis.
    k = np.arange(2000)
    a, b = 0.01 * k, 0.003 * k
    dirs = np.column_stack([np.cos(a) * np.cos(b), np.sin(a), np.cos(a) * np.sin(b)])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    fields = (5.15e-5 * dirs).tolist()
    offsets = [(1e-7 * (i + 1), -2e-7, 3e-8 * i) for i in range(len(NAMES))]
    from magcal_ros.io.cdr import StampedVectorPacker, magnetic_field_template

    packers = [StampedVectorPacker(magnetic_field_template(n)) for n in NAMES]  # bytes: a cheap publisher
    period = 1.0 / rate
    start = time.monotonic()
    print("START", flush=True)
    sent, last = 0, 0
    while True:
        due = start + sent * period
        now = time.monotonic()
        if now - start >= seconds:
            break
        if due > now:
            time.sleep(due - now)
        stamp = max(time.time_ns(), last + 1)
        last = stamp
        f = fields[sent % len(fields)]
        for packer, p, o in zip(packers, pubs, offsets):
            p.publish(packer.pack(stamp, f[0] + o[0], f[1] + o[1], f[2] + o[2]))
        sent += 1
    print(f"SENT {sent} {time.monotonic() - start:.3f}", flush=True)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.try_shutdown()


def start_publisher(
    rate: float, seconds: float, domain: int, env: dict[str, str], wait_subscribers: int
) -> subprocess.Popen:
    """The publisher as a separate process (this file with --publish)."""
    return subprocess.Popen(
        [sys.executable, __file__, "--publish", str(rate), str(seconds), "--domain", str(domain),
         "--wait-subscribers", str(wait_subscribers)],
        env=env, stdout=subprocess.PIPE, text=True,
    )


def publisher_result(proc: subprocess.Popen, timeout: float) -> tuple[int, float]:
    """(sets sent, seconds) printed by the publisher process."""
    out, _ = proc.communicate(timeout=timeout)
    for line in out.splitlines():
        if line.startswith("SENT"):
            _, n, secs = line.split()
            return int(n), float(secs)
    raise RuntimeError(f"publisher failed:\n{out}")


# --------------------------------------------------------------------------- bare node and receiver

BARE_NAMESPACE = "bare"
COMPARE_DEPTH = 1000
"""Raw QoS of both nodes in the comparison: reliable, this deep, so that neither loses messages when the
machine is busy (a node that drops sets would look cheaper)."""
OUTPUTS_ALL = tuple(f"{n}/corrected" for n in NAMES) + ("field", "gradient", "gradient_stamped")


def bare_node(domain: int, count_file: str) -> None:
    """The bare node process: the correction node's subscriptions and publications, no maths.

    On each set (the last sensor's message; the publisher sends the sensors in order) it publishes
    the four received messages as ``<name>/corrected``, the last one's header on ``field`` and
    ``gradient_stamped`` with constant values, and a constant ``gradient``: what any node with these
    topics pays in rclpy and DDS. Writes its set count to ``count_file`` every second."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState, MagneticField
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension

    from magcal_ros.io.csv_recording import TENSOR_COLUMNS
    from magcal_ros.nodes.common import output_qos, raw_qos

    rclpy.init(domain_id=domain)
    node = rclpy.create_node("magcal_bare", namespace=f"/{BARE_NAMESPACE}")
    qin, qout = raw_qos("reliable", COMPARE_DEPTH), output_qos(COMPARE_DEPTH)
    corrected = [node.create_publisher(MagneticField, f"{n}/corrected", qout) for n in NAMES]
    field_pub = node.create_publisher(MagneticField, "field", qout)
    gradient_pub = node.create_publisher(Float64MultiArray, "gradient", qout)
    stamped_pub = node.create_publisher(JointState, "gradient_stamped", qout)
    field = MagneticField()
    grad = Float64MultiArray()
    grad.layout.dim = [MultiArrayDimension(label="row", size=3, stride=9),
                       MultiArrayDimension(label="col", size=3, stride=3)]
    grad.data = [1e-9] * 9
    stamped = JointState(name=list(TENSOR_COLUMNS), position=[1e-9] * 9)
    latest: list = [None] * len(NAMES)
    last = len(NAMES) - 1
    sets = [0]

    def callback(k: int):  # type: ignore[no-untyped-def]
        def cb(msg: MagneticField) -> None:
            latest[k] = msg
            if k != last:
                return
            for pub, m in zip(corrected, latest):
                if m is not None:
                    pub.publish(m)
            field.header = msg.header
            field.magnetic_field = msg.magnetic_field
            field_pub.publish(field)
            gradient_pub.publish(grad)
            stamped.header = msg.header
            stamped_pub.publish(stamped)
            sets[0] += 1
        return cb

    subs = [node.create_subscription(MagneticField, f"/{n}/raw", callback(k), qin) for k, n in enumerate(NAMES)]
    assert subs
    node.create_timer(1.0, lambda: Path(count_file).write_text(f"{sets[0]}\n"))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print("READY", flush=True)
    try:
        executor.spin()
    except (KeyboardInterrupt, Exception):
        pass
    finally:
        rclpy.try_shutdown()


def listener(domain: int, listen: str) -> None:
    """Listener process: subscriptions to every output of both nodes (``all``) or only their ``gradient``,
    best effort with a history of one and never spun, so that the nodes see subscribers and DDS delivers,
    while this process spends no Python per message (it would starve the nodes of a small machine)."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState, MagneticField
    from std_msgs.msg import Float64MultiArray

    rclpy.init(domain_id=domain)
    node = rclpy.create_node("magcal_bench_listener")
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    types = {"field": MagneticField, "gradient": Float64MultiArray, "gradient_stamped": JointState}
    subs = [node.create_subscription(types.get(out, MagneticField), f"{prefix}/{out}", lambda _: None, qos, raw=True)
            for prefix in ("", f"/{BARE_NAMESPACE}") for out in (OUTPUTS_ALL if listen == "all" else ("gradient",))]
    assert subs
    print("READY", flush=True)
    try:
        while rclpy.ok():  # SIGINT shuts the context down
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass


def _count(path: Path) -> int:
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0


def compare(rates: list[float], seconds: float, reps: int, workdir: Path, domain: int) -> list[tuple]:
    """Correction node and bare node side by side: CPU seconds per wall second at each rate and listener set."""
    import signal as sig

    import psutil
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from magcal_ros.app.ros_driver import NodeProcess, ros_args, ros_environment, status_values

    env = ros_environment(domain)
    params = {"uncorrected_sensors": list(NAMES), "raw_reliability": "reliable", "qos_depth": COMPARE_DEPTH}
    node = NodeProcess("correction_node", ros_args(params=params), env, workdir / "cmp_correction.log")
    bare_count = workdir / "bare_count"
    bare = subprocess.Popen([sys.executable, __file__, "--bare", str(bare_count), "--domain", str(domain)], env=env,
                            stdout=subprocess.PIPE, text=True)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    watcher = rclpy.create_node("magcal_bench_watcher", context=context)
    published = [0]
    status: dict[str, str] = {}

    def on_status(msg: DiagnosticStatus) -> None:
        status.update(status_values(msg))
        published[0] = int(status.get("published", 0))

    watcher.create_subscription(DiagnosticStatus, "/magcal_correction/status", on_status, 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(watcher)
    import threading

    threading.Thread(target=executor.spin, daemon=True).start()
    rows = []
    try:
        assert bare.stdout is not None
        bare.stdout.readline()
        if not node.wait_for_log("correcting", 60.0):
            raise RuntimeError(f"correction node did not start:\n{node.log()}")
        procs = {"magcal": psutil.Process(node.pid), "bare": psutil.Process(bare.pid)}
        print(f"\nCPU against a bare rclpy node (same subscriptions and publications, no maths), side by side, "
              f"{seconds:g} s per run, {os.cpu_count()} CPUs; CPU = (user + system) s per wall s of the node process; "
              "sets: published by each node in the run; age: set stamp to publication in the correction node, "
              "median of its last second (a node that falls behind the traffic is starved, not cheap); us: CPU "
              "microseconds per set published (the fair figure when a busy machine starves a node)")
        print(f"{'rate':>10} {'listeners':>9} {'run':>4} {'bare CPU %':>11} {'magcal CPU %':>13} {'magcal/bare':>12}"
              f" {'sets sent':>10} {'magcal':>7} {'bare':>7} {'age p50 ms':>12} {'magcal us':>10} {'bare us':>8}"
              f" {'ratio':>8}")
        for listen in ("all", "gradient"):
            rec = subprocess.Popen([sys.executable, __file__, "--listen", listen, "--domain", str(domain)], env=env,
                                   stdout=subprocess.PIPE, text=True)
            try:
                assert rec.stdout is not None
                rec.stdout.readline()
                time.sleep(3.0)  # discovery; the node looks at who listens
                pub = start_publisher(200.0, 2.0, domain, env, wait_subscribers=2)  # warm-up, discarded
                publisher_result(pub, 120.0)
                time.sleep(1.5)
                for rate in rates:
                    for rep in range(reps):
                        before = (published[0], _count(bare_count))
                        pub = start_publisher(rate, seconds, domain, env, wait_subscribers=2)
                        assert pub.stdout is not None
                        pub.stdout.readline()  # START
                        t0 = time.monotonic()
                        c0 = {k: p.cpu_times() for k, p in procs.items()}
                        sent, secs = publisher_result(pub, seconds + 120.0)
                        time.sleep(0.5)
                        c1 = {k: p.cpu_times() for k, p in procs.items()}
                        wall = time.monotonic() - t0
                        time.sleep(1.6)  # both counts written
                        got = (published[0] - before[0], _count(bare_count) - before[1])
                        cpu = {k: (c1[k].user + c1[k].system - c0[k].user - c0[k].system) / wall for k in procs}
                        rows.append((rate, listen, rep + 1, cpu["bare"], cpu["magcal"], sent, *got))
                        per_set = [1e6 * cpu[k] * wall / max(n, 1) for k, n in (("magcal", got[0]), ("bare", got[1]))]
                        print(f"{4:>3} x {rate:<4g} {listen:>9} {rep + 1:>4} {100 * cpu['bare']:>11.1f} "
                              f"{100 * cpu['magcal']:>13.1f} {cpu['magcal'] / cpu['bare']:>12.3f} {sent:>10} {got[0]:>7}"
                              f" {got[1]:>7} {status.get('age_ms_p50', '-'):>12} {per_set[0]:>10.0f} {per_set[1]:>8.0f}"
                              f" {per_set[0] / per_set[1]:>8.3f}", flush=True)
                        rows[-1] += (per_set[0], per_set[1])
            finally:
                rec.send_signal(sig.SIGINT)
                rec.wait(10)
        print("summary (median over runs; a run where a node published fewer sets than were sent was starved "
              "by the machine, not cheaper):")
        for rate in rates:
            for listen in ("all", "gradient"):
                r = [x for x in rows if x[0] == rate and x[1] == listen]
                ratio = float(np.median([x[4] / x[3] for x in r]))
                per_set = float(np.median([x[8] / x[9] for x in r]))
                print(f"  4 x {rate:g} Hz, {listen:>8} listened: magcal {100 * np.median([x[4] for x in r]):.1f} % "
                      f"of a core, bare {100 * np.median([x[3] for x in r]):.1f} %, magcal/bare {ratio:.3f}; per set "
                      f"published {np.median([x[8] for x in r]):.0f} us against {np.median([x[9] for x in r]):.0f} us, "
                      f"{per_set:.3f}")
    finally:
        node.stop()
        bare.send_signal(sig.SIGINT)
        try:
            bare.wait(10)
        except subprocess.TimeoutExpired:
            bare.kill()
        executor.shutdown()
        rclpy.try_shutdown(context=context)
    return rows


# --------------------------------------------------------------------------- measurements


def node_counters(driver, node: str) -> dict[str, int]:  # type: ignore[no-untyped-def]
    """The correction node's ~/status counters (next message)."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from magcal_ros.app.ros_driver import status_values

    msg = driver.wait_for_message(DiagnosticStatus, f"/{node}/status", None, 10.0)
    if msg is None:
        return {}
    return {k: int(v) for k, v in status_values(msg).items() if v.lstrip("-").isdigit()}


def throughput(rates: list[float], seconds: float, workdir: Path, domain: int) -> None:
    """Correction node at each rate: sets/s, drops, latency, CPU, RSS."""
    import psutil

    from magcal_ros.app.ros_driver import (
        ArrayDriver,
        NodeProcess,
        ros_args,
        ros_environment,
    )

    env = ros_environment(domain)
    node = NodeProcess("correction_node", ros_args(params={"uncorrected_sensors": list(NAMES)}), env,
                       workdir / "correction_node.log")
    proc = psutil.Process(node.pid)
    driver = ArrayDriver(NAMES, domain, node_name="magcal_bench_receiver", collect_corrected=False)
    try:
        if not (node.wait_for_log("correcting", 60.0) and driver.wait_for_output_publishers(60.0)
                and driver.prime(60.0)):
            raise RuntimeError(f"correction node not discovered:\n{node.log()}")
        print(f"correction_node pid {node.pid}, ROS_DOMAIN_ID={domain}, {seconds:g} s per rate after a 3 s "
              f"warm-up, {os.cpu_count()} CPUs")
        from diagnostic_msgs.msg import DiagnosticStatus

        from magcal_ros.app.ros_driver import status_values

        ages: list[dict[str, str]] = []
        driver.node.create_subscription(
            DiagnosticStatus, "/magcal_correction/status", lambda m: ages.append(status_values(m)), 10)
        print("latency: set stamp (publish wall time) to receipt of its gradient here; 'node p99': stamp to "
              "publication inside the node, worst 1-s window")
        print(f"{'rate (Hz)':>10}{'sent':>8}{'corrected':>10}{'received':>10}{'sets/s':>9}{'dropped':>9}"
              f"{'p50 ms':>8}{'p99 ms':>8}{'max ms':>8}{'node p99':>9}{'CPU %':>7}{'RSS MB':>8}")
        # Warm-up (discarded): the first seconds of high-rate traffic stall this receiving process
        # once (DDS reader buffers growing), which is not the node's latency.
        pub = start_publisher(500.0, 3.0, domain, env, wait_subscribers=1)
        publisher_result(pub, 120.0)
        time.sleep(1.0)
        for rate in rates:
            before = node_counters(driver, "magcal_correction")
            driver.clear_outputs()
            ages.clear()
            pub = start_publisher(rate, seconds, domain, env, wait_subscribers=1)
            assert pub.stdout is not None
            pub.stdout.readline()  # START
            proc.cpu_percent(None)
            sent, secs = publisher_result(pub, seconds + 120.0)
            cpu = proc.cpu_percent(None)
            time.sleep(1.0)
            after = node_counters(driver, "magcal_correction")
            corrected = after.get("published", 0) - before.get("published", 0)
            incomplete = after.get("incomplete", 0) - before.get("incomplete", 0)
            received = len(driver.outputs.gradient)
            lat = np.array(driver.outputs.latency) * 1e3
            p50, p99, pmax = (np.percentile(lat, 50), np.percentile(lat, 99), lat.max()) if len(lat) else (np.nan,) * 3
            rss = proc.memory_info().rss / 2**20
            node_p99 = max((float(a["age_ms_p99"]) for a in ages if "age_ms_p99" in a), default=float("nan"))
            print(f"{4:>3} x {rate:<4g}{sent:>8}{corrected:>10}{received:>10}{received / secs:>9.1f}"
                  f"{sent - corrected:>9}{p50:>8.2f}{p99:>8.2f}{pmax:>8.2f}{node_p99:>9.2f}{cpu:>7.1f}{rss:>8.1f}"
                  + (f"   (node counted {incomplete} incomplete sets)" if incomplete else ""), flush=True)
    finally:
        driver.close()
        node.stop()


def memory(minutes: float, rate: float, max_samples: int, workdir: Path, domain: int) -> None:
    """Both nodes for ``minutes`` at 4 x ``rate`` Hz with the calibration node collecting."""
    import psutil

    from magcal_ros.app.ros_driver import (
        ArrayDriver,
        NodeProcess,
        ros_args,
        ros_environment,
        wait_for_samples,
    )

    env = ros_environment(domain)
    nodes = {
        "correction_node": NodeProcess("correction_node", ros_args(params={"uncorrected_sensors": list(NAMES)}), env,
                                       workdir / "mem_correction.log"),
        "calibration_node": NodeProcess(
            "calibration_node", ros_args(params={"max_samples": max_samples, "calibration_file": ""}), env,
            workdir / "mem_calibration.log"),
    }
    procs = {k: psutil.Process(p.pid) for k, p in nodes.items()}
    driver = ArrayDriver(NAMES, domain, node_name="magcal_bench_memory", collect_corrected=False)
    try:
        if not driver.wait_for_subscribers(2, 60.0):
            raise RuntimeError("nodes not discovered")
        ok, msg = driver.trigger("/magcal_calibration/start")
        assert ok, msg
        seconds = minutes * 60.0
        print(f"\nmemory run: {minutes:g} min at 4 x {rate:g} Hz, calibration node collecting (max_samples "
              f"{max_samples}); RSS in MB")
        pub = start_publisher(rate, seconds, domain, env, wait_subscribers=2)
        assert pub.stdout is not None
        pub.stdout.readline()
        t0 = time.monotonic()
        samples: dict[str, list[tuple[float, float]]] = {k: [] for k in procs}
        step = max(5.0, seconds / 24)
        next_print = 0.0
        while pub.poll() is None:
            t = time.monotonic() - t0
            for k, p in procs.items():
                samples[k].append((t, p.memory_info().rss / 2**20))
            if t >= next_print:
                print(f"  t={t:6.0f} s  " + "  ".join(f"{k} {samples[k][-1][1]:6.1f}" for k in procs), flush=True)
                next_print += step
            time.sleep(1.0)
        sent, _ = publisher_result(pub, 60.0)
        progress = wait_for_samples(driver, "magcal_calibration", 0, 10.0)
        print(f"  sent {sent} sets; calibration node holds {progress.get('samples')} sets "
              f"(max_samples {max_samples}), {progress.get('offered')} offered")
        for k, s in samples.items():
            arr = np.array(s)
            warm = arr[arr[:, 0] >= min(60.0, arr[-1, 0] / 2)]
            slope = np.polyfit(warm[:, 0] / 60.0, warm[:, 1], 1)[0] if len(warm) > 2 else float("nan")
            print(f"  {k:17} RSS start {arr[0, 1]:6.1f}  after warm-up {warm[0, 1]:6.1f}  end {arr[-1, 1]:6.1f}  "
                  f"max {arr[:, 1].max():6.1f}  trend after warm-up {slope:+.3f} MB/min")
        for k, p in nodes.items():
            if not p.alive():
                print(f"  {k} died:\n{p.log()[-2000:]}")
    finally:
        driver.close()
        for p in nodes.values():
            p.stop()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", type=float, nargs="*", default=[100.0, 500.0, 1000.0], help="Hz per sensor")
    parser.add_argument("--seconds", type=float, default=10.0, help="duration per rate (s)")
    parser.add_argument("--minutes", type=float, default=10.0, help="memory run length (min); 0 skips it")
    parser.add_argument("--memory-rate", type=float, default=200.0, help="Hz per sensor in the memory run")
    parser.add_argument("--max-samples", type=int, default=2000, help="calibration node buffer in the memory run")
    parser.add_argument("--compare-only", action="store_true", help="only CPU against the bare node")
    parser.add_argument("--compare-rates", type=float, nargs="*", default=[500.0, 1000.0],
                        help="Hz per sensor of the comparison with the bare node")
    parser.add_argument("--compare-seconds", type=float, default=8.0, help="duration of each comparison run (s)")
    parser.add_argument("--reps", type=int, default=2, help="comparison runs per rate and listener set")
    parser.add_argument("--publish", type=float, nargs=2, metavar=("RATE", "SECONDS"), help=argparse.SUPPRESS)
    parser.add_argument("--bare", help=argparse.SUPPRESS)
    parser.add_argument("--listen", help=argparse.SUPPRESS)
    parser.add_argument("--domain", type=int, help="ROS domain id (default: one in 215..232, away from test runs)")
    parser.add_argument("--wait-subscribers", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        publish(args.publish[0], args.publish[1], args.domain, args.wait_subscribers)
        return 0
    if args.bare:
        bare_node(args.domain, args.bare)
        return 0
    if args.listen:
        listener(args.domain, args.listen)
        return 0
    # Outside 1..100, where test runs pick theirs (pick_domain_id): another run's traffic on the same
    # domain would mix into the nodes here (and this benchmark's into that run).
    domain = args.domain if args.domain is not None else 215 + os.getpid() % 18
    with tempfile.TemporaryDirectory(prefix="magcal_bench_") as tmp:
        if args.compare_rates:
            compare(args.compare_rates, args.compare_seconds, args.reps, Path(tmp), domain)
        if args.compare_only:
            return 0
        if args.rates:
            throughput(args.rates, args.seconds, Path(tmp), domain)
        if args.minutes > 0:
            memory(args.minutes, args.memory_rate, args.max_samples, Path(tmp), domain)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

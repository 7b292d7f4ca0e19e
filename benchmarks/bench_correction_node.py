"""Benchmark of the live nodes over DDS (not a test): throughput, latency, CPU, memory.

    python benchmarks/bench_correction_node.py                  # 10 s at 100/500/1000 Hz, 10 min memory run
    python benchmarks/bench_correction_node.py --seconds 10 --minutes 2
    python benchmarks/bench_correction_node.py --rates 500 --minutes 0

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
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
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
    msgs = [MagneticField() for _ in NAMES]
    for m, n in zip(msgs, NAMES):
        m.header.frame_id = n
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
        sec, nsec = divmod(stamp, NS_PER_S)
        f = fields[sent % len(fields)]
        for m, p, o in zip(msgs, pubs, offsets):
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
            m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z = f[0] + o[0], f[1] + o[1], f[2] + o[2]
            p.publish(m)
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
    parser.add_argument("--publish", type=float, nargs=2, metavar=("RATE", "SECONDS"), help=argparse.SUPPRESS)
    parser.add_argument("--domain", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--wait-subscribers", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        publish(args.publish[0], args.publish[1], args.domain, args.wait_subscribers)
        return 0
    from magcal_ros.app.ros_driver import pick_domain_id

    domain = pick_domain_id()
    with tempfile.TemporaryDirectory(prefix="magcal_bench_") as tmp:
        if args.rates:
            throughput(args.rates, args.seconds, Path(tmp), domain)
        if args.minutes > 0:
            memory(args.minutes, args.memory_rate, args.max_samples, Path(tmp), domain)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark of the burst case (not a test): 4 x 2000 Hz for 10 s into the correction node, every message accounted for.

    python benchmarks/bench_burst.py                 # 4 x 2000 Hz, 10 s
    python benchmarks/bench_burst.py --rate 1000 --seconds 5

``correction_node`` runs as its own process (installed executable, default parameters:
best-effort raw subscriptions of depth 100, sync_tolerance 1 ms, which the node caps at
0.25 ms at 2 kHz). Another process publishes four ``/magN/raw`` topics from pre-serialized
CDR messages (no message objects while publishing), stamps exactly ``1 / rate`` apart:

1. a slow warm-up until the node has heard every sensor (its ``/diagnostics`` counters are
   then the baseline);
2. the burst: ``rate`` sets per second for ``seconds``;
3. a slow tail of 40 sets, so that a loss at the end of the burst is a gap in each
   sensor's stamp sequence like any other.

After the tail the node's ``/diagnostics`` counters give, per message offered after the
baseline: published in a set (4 per set), dropped by the synchroniser (by cause), lost
before reaching the node (gaps in a sensor's stamps: DDS queue overflow) or still pending.
The script prints them and checks that they add up to what was offered.
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
NODE = "/magcal_correction"
TAIL = 40
CAUSES = ("unmatched", "nonfinite", "duplicate", "out_of_order", "zero_stamp", "malformed")


def _frames(count: int, first: int, start_ns: int, period_ns: int) -> list[list[bytes]]:
    """Pre-serialized sets ``first .. first + count`` of a tumbling array in a 51 500 nT field."""
    from magcal_ros.app.ros_driver import serialized_sets

    k = np.arange(first, first + count)
    a, b = 0.01 * k, 0.003 * k
    dirs = np.column_stack([np.cos(a) * np.cos(b), np.sin(a), np.cos(a) * np.sin(b)])
    field = 5.15e-5 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    offsets = np.array([[1e-7 * (i + 1), -2e-7, 3e-8 * i] for i in range(len(NAMES))])
    vectors = field[:, None, :] + offsets[None]
    return serialized_sets(NAMES, start_ns + k * period_ns, vectors)


def publisher(rate: float, seconds: float, domain: int) -> None:
    """Publisher process: warm-up, (wait for GO on stdin), burst, tail; prints counts."""
    from magcal_ros.app.ros_driver import ArrayDriver

    period_ns = int(round(NS_PER_S / rate))
    start_ns = time.time_ns()
    burst = int(rate * seconds)
    driver = ArrayDriver(NAMES, domain, node_name="magcal_bench_burst_publisher", listen=False)
    try:
        if not driver.wait_for_subscribers(1, 60.0):
            raise RuntimeError("the correction node's raw subscriptions were not discovered")
        time.sleep(1.0)
        warm = _frames(40, 0, start_ns, period_ns)
        driver.replay_serialized(warm, rate=20.0)
        print(f"WARM {len(warm)}", flush=True)
        sys.stdin.readline()
        frames = _frames(burst, len(warm), start_ns, period_ns)  # built before the clock starts
        sent, secs = driver.replay_serialized(frames, rate=rate)
        print(f"SENT {sent} {secs:.3f}", flush=True)
        tail = _frames(TAIL, len(warm) + burst, start_ns, period_ns)
        driver.replay_serialized(tail, rate=20.0)
        print(f"DONE {len(tail)}", flush=True)
        time.sleep(1.0)
    finally:
        driver.close()


def _status(driver, settle: float = 0.0) -> tuple[dict[str, int], dict[str, str]]:  # type: ignore[no-untyped-def]
    """The node's /diagnostics counters and all its values (the next status after ``settle`` s)."""
    from magcal_ros.app.ros_driver import status_values

    time.sleep(settle)
    status = driver.diagnostics(NODE, None, 10.0)
    if status is None:
        raise RuntimeError("no /diagnostics from the correction node")
    values = status_values(status)
    values["message"] = status.message
    return {k: int(v) for k, v in values.items() if v.lstrip("-").isdigit()}, values


def run(rate: float, seconds: float, workdir: Path) -> int:
    from magcal_ros.app.ros_driver import (
        ArrayDriver,
        NodeProcess,
        pick_domain_id,
        ros_args,
        ros_environment,
    )

    domain = pick_domain_id()
    env = ros_environment(domain)
    params = {"uncorrected_sensors": list(NAMES)}
    node = NodeProcess("correction_node", ros_args(params=params), env, workdir / "correction_node.log")
    listener = ArrayDriver(NAMES, domain, node_name="magcal_bench_burst_listener", listen=False)
    pub = None
    try:
        if not node.wait_for_log("correcting", 60.0):
            raise RuntimeError(f"correction node did not start:\n{node.log()}")
        pub = subprocess.Popen(
            [sys.executable, __file__, "--publish", "--rate", str(rate), "--seconds", str(seconds),
             "--domain", str(domain)],
            env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )
        assert pub.stdin is not None and pub.stdout is not None
        line = pub.stdout.readline()
        if not line.startswith("WARM"):
            raise RuntimeError(f"publisher failed: {line}")
        before, _ = _status(listener, settle=1.5)
        if any(before.get(f"{n}.received", 0) == 0 for n in NAMES):
            raise RuntimeError(f"the node did not hear every sensor during the warm-up: {before}")
        pub.stdin.write("GO\n")
        pub.stdin.flush()
        sent, secs = pub.stdout.readline().split()[1:]
        tail = int(pub.stdout.readline().split()[1])
        pub.wait(60.0)
        after, values = _status(listener, settle=2.0)
    finally:
        if pub is not None and pub.poll() is None:
            pub.kill()
        listener.close()
        code = node.stop()
    sets = int(sent) + tail
    offered = len(NAMES) * sets
    d = {k: after.get(k, 0) - before.get(k, 0) for k in after}
    published = d["published"]
    dropped = {c: d.get(c, 0) for c in CAUSES}
    lost = {n: d.get(f"{n}.lost", 0) for n in NAMES}
    received = {n: d.get(f"{n}.received", 0) for n in NAMES}
    pending = after.get("pending", 0) - before.get("pending", 0)
    total = len(NAMES) * published + sum(dropped.values()) + sum(lost.values()) + pending
    print(f"correction_node, ROS_DOMAIN_ID={domain}, {os.cpu_count()} CPUs; exit code {code}")
    print(f"offered: {int(sent)} sets in {float(secs):.2f} s ({int(sent) / float(secs):.0f} sets/s, "
          f"{len(NAMES) * int(sent) / float(secs):.0f} msg/s) + {tail} tail sets = {sets} sets, {offered} messages")
    print(f"sync window: {values.get('sync_window_ms', '?')} ms (sync_tolerance {values.get('sync_tolerance_ms')} ms); "
          f"/diagnostics: {values['message']}")
    capped = [line for line in node.log().splitlines() if "capped" in line]
    print(f"node log on the cap ({len(capped)} line): {capped[0].split(']: ')[-1] if capped else 'none'}")
    print(f"published: {published} sets ({len(NAMES) * published} messages)")
    print("dropped by the synchroniser (messages): "
          + ", ".join(f"{c} {v}" for c, v in dropped.items()) + f"; pending {pending}")
    print("lost before the node (gaps in each sensor's stamps): "
          + ", ".join(f"{n} {lost[n]} ({d.get(f'{n}.gaps', 0)} gaps)" for n in NAMES))
    print("per sensor received + lost = offered: "
          + ", ".join(f"{n} {received[n]} + {lost[n]} = {received[n] + lost[n]}" for n in NAMES) + f" (of {sets})")
    ok = total == offered and all(received[n] + lost[n] == sets for n in NAMES)
    print(f"check: 4 x published + dropped + lost + pending = {len(NAMES)} x {published} + "
          f"{sum(dropped.values())} + {sum(lost.values())} + {pending} = {total} "
          f"{'==' if total == offered else '!='} {offered} offered: {'OK' if ok else 'MISMATCH'}")
    return 0 if ok else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=2000.0, help="sets per second per sensor (default 2000)")
    parser.add_argument("--seconds", type=float, default=10.0, help="burst length (default 10 s)")
    parser.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--domain", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.publish:
        publisher(args.rate, args.seconds, args.domain)
        return 0
    with tempfile.TemporaryDirectory(prefix="magcal_burst_") as tmp:
        return run(args.rate, args.seconds, Path(tmp))


if __name__ == "__main__":
    raise SystemExit(main())

"""Both speed figures in one run (not a test): ``magcal correct`` against the storage limit, and the
correction node's CPU against a bare rclpy node at 4 x 500 and 4 x 1000 Hz.

    python benchmarks/bench_speed.py                      # about 5 min
    python benchmarks/bench_speed.py --messages 400000 --seconds 5

Runs ``bench_correct_throughput.py`` (sqlite3 and mcap, interleaved, best of two) and
``bench_correction_node.py --compare-only`` (side by side, every output listened and only the
gradient, two runs each); see those files for what is measured.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--messages", type=int, default=1_000_000, help="raw messages of the correct run")
    ap.add_argument("--seconds", type=float, default=8.0, help="seconds of each node run")
    ap.add_argument("--reps", type=int, default=2, help="runs of each")
    args = ap.parse_args()
    print("== magcal correct against the storage limit", flush=True)
    subprocess.run([sys.executable, str(HERE / "bench_correct_throughput.py"), "--messages", str(args.messages),
                    "--reps", str(args.reps)], check=True)
    print("\n== correction_node against a bare rclpy node", flush=True)
    subprocess.run([sys.executable, str(HERE / "bench_correction_node.py"), "--compare-only", "--compare-seconds",
                    str(args.seconds), "--reps", str(args.reps)], check=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

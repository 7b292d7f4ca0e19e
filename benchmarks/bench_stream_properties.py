"""A longer run of the generated stream tests (test/test_stream_properties.py): examples tried, sets
checked against the truth oracle, faults drawn, time.

    .venv/bin/python benchmarks/bench_stream_properties.py [--examples 2000] [--seed 0]

Each example is a recording of one to four sensors on their own clocks with faults drawn at random
(steps of any size, glitches, repeats, pauses, stalls with and without restamped backlogs, bad readings),
synchronised offline and live; every published set's members must stand for one true instant, every
message must be counted, the clean reference samples must make sets, and live must equal offline. The
side-stream part draws temperature streams with swaps, pauses, values out of range and stamps far off; the
last parts, a fifth as many recordings each: one sensor steps forward while the receiver is blocked
(``hidden_steps``); one sensor's stamps step either way while it is silent (``silent_steps``); general
recordings where topics are taken late for a while, the stamps right (``late_topics``); hidden steps with each
sensor at a rate of its own (``hidden_steps(mixed=True)``).
Unlike the suite (a fixed number of derandomised examples), this draws fresh examples from ``--seed``.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from collections.abc import Callable
from pathlib import Path

import _first  # noqa: F401  (this checkout's magcal_ros, not an installed copy)
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, seed, settings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
import test_stream_properties as props  # noqa: E402


def first_line(exc: BaseException) -> str:
    """A failure's first line (an assertion without a message: its type)."""
    lines = str(exc).splitlines()
    return (lines[0] if lines else f"{type(exc).__name__} without a message")[:200]


def main() -> int:
    # the draws without the code's constants: two versions of the code are compared on the same recordings
    props.leave_out_local_constants(pytest.MonkeyPatch())
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=2000, help="recordings to draw (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help="the draw (default 0)")
    parser.add_argument("--keep", help="pickle the plans of failing recordings into this file")
    args = parser.parse_args()
    tally: collections.Counter[str] = collections.Counter()
    failures: list[str] = []
    cases: list[props.Case] = []

    @seed(args.seed)
    @settings(max_examples=args.examples, database=None, deadline=None, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(props.cases())
    def sets(case: props.Case) -> None:
        streams = props.streams_of(case)
        batch, stats, mode = props.offline(streams)
        tally["examples"] += 1
        tally["sensors"] += len(streams)
        tally["messages"] += sum(len(s.stamps) for s in streams)
        tally["sets checked"] += len(batch)
        tally[f"mode {mode}"] += 1
        for p in case.plans:
            for kind in ("steps", "glitches", "duplicates", "silences", "stalls", "bad"):
                tally[f"fault: {kind}"] += len(getattr(p, kind))
        try:
            props.test_every_published_set_stands_for_one_true_instant.hypothesis.inner_test(case)
        except AssertionError as exc:
            failures.append(first_line(exc))
            cases.append(case)

    @seed(args.seed)
    @settings(max_examples=4 * args.examples, database=None, deadline=None, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(props.side_streams())
    def side(stream: tuple) -> None:  # type: ignore[type-arg]
        tally["side streams"] += 1
        tally["side samples"] += len(stream[0])
        try:
            props.test_a_side_stream_gives_each_set_its_latest_true_value_live_and_offline.hypothesis.inner_test(stream)
        except AssertionError as exc:
            failures.append("side: " + first_line(exc))

    def family(strategy: object, key: str, label: str) -> Callable[[], None]:
        """A fifth as many recordings of one family (``strategy``), each checked whole; tallied under ``key``."""

        @seed(args.seed)
        @settings(max_examples=max(1, args.examples // 5), database=None, deadline=None, phases=[Phase.generate],
                  suppress_health_check=list(HealthCheck))
        @given(strategy)
        def run(case: props.Case) -> None:
            tally[key] += 1
            try:
                props.check_case(case)
            except AssertionError as exc:
                tally[f"{key} failures"] += 1
                failures.append(f"{label}: " + first_line(exc))
                cases.append(case)

        return run

    hidden = family(props.hidden_steps(), "hidden", "hidden step")
    silent = family(props.silent_steps(), "silent", "silent step")
    late = family(props.late_topics(), "late", "late topic")
    mixed = family(props.hidden_steps(mixed=True), "mixed", "hidden step, mixed rates")

    t0 = time.perf_counter()
    sets()
    t1 = time.perf_counter()
    side()
    t2 = time.perf_counter()
    hidden()
    t3 = time.perf_counter()
    silent()
    t4 = time.perf_counter()
    late()
    t5 = time.perf_counter()
    mixed()
    t6 = time.perf_counter()
    print(f"recordings: {tally['examples']} examples, {tally['sensors']} sensors, {tally['messages']:,} messages, "
          f"{tally['sets checked']:,} sets checked (offline and live), {t1 - t0:.1f} s "
          f"({(t1 - t0) / max(tally['examples'], 1) * 1e3:.0f} ms each)")
    print("  modes: " + ", ".join(f"{k[5:]} {v}" for k, v in sorted(tally.items()) if k.startswith("mode ")))
    print("  faults drawn: " + ", ".join(f"{k[7:]} {v}" for k, v in sorted(tally.items()) if k.startswith("fault")))
    print(f"side streams: {tally['side streams']} examples, {tally['side samples']:,} samples, 200 sets each, "
          f"{t2 - t1:.1f} s")
    print(f"steps a blocked receiver's queue hides: {tally['hidden']} examples, {tally['hidden failures']} failing, "
          f"{t3 - t2:.1f} s")
    print(f"steps inside a sensor's silence: {tally['silent']} examples, {tally['silent failures']} failing, "
          f"{t4 - t3:.1f} s")
    print(f"topics taken late for a while: {tally['late']} examples, {tally['late failures']} failing, "
          f"{t5 - t4:.1f} s")
    print(f"hidden steps with the sensors at rates of their own: {tally['mixed']} examples, "
          f"{tally['mixed failures']} failing, {t6 - t5:.1f} s")
    print(f"failures: {len(failures)}")
    for line in failures[:10]:
        print("  " + line)
    if cases and args.keep:
        import pickle

        Path(args.keep).write_bytes(pickle.dumps(cases))
        print(f"failing recordings' plans kept in {args.keep}")
    return 1 if failures else 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())

"""A short mission soak through both nodes over DDS (:mod:`magcal_ros.app.soak`; the long one is
``benchmarks/bench_mission_soak.py``).

Seven minutes of mission at 20 samples/s per sensor, published ten times faster than real time:
receipt-stamped sensors, mag3's driver restarting (its stamps 30 s back), mag4 silent for 20 s, the
payload current switched on, the hull's hard iron jumping on every sensor. What is asserted are counts
and mission-time figures (the nodes judge by stamps), with generous bounds: never a wall-clock timing.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import ros_harness  # noqa: F401  (the run's Fast DDS profile, before this process's first participant)

from magcal_ros.app.soak import SoakPlan, floor, run_soak, table

pytestmark = pytest.mark.dds

PLAN = SoakPlan(duration=420.0, speed=10.0, rate=20.0, block=60.0, restart_at=0.08, silent_at=0.15, silent_for=20.0,
                current_at=0.22, hull_at=0.3, health_window=30.0, recalibrate_window=60.0, hang=120.0)
"""Hull change at 126 s: named within half a health window or so, recalibrated from the next 60 s of sets,
and two minutes or more of mission left after the push."""


def test_a_short_mission_soak(tmp_path: Path) -> None:
    lines: list[str] = []
    out = run_soak(PLAN, lines.append, tmp_path)
    story = "\n".join(lines + table(out))
    assert out.exit_codes == {"correction": 0, "calibration": 0}, story
    assert not out.hung, story
    sent = sum(b.sent for b in out.blocks.values())
    got = sum(b.outputs for b in out.blocks.values())
    silent = PLAN.silent_for * PLAN.rate
    assert got >= 0.8 * (sent - silent), story  # outputs for most sets, the restart and the silence included
    counted = out.counters  # the correction node's own counts: the restart seen, most sets published
    assert int(counted.get("restarts", "0")) >= 1 and int(counted.get("published", "0")) >= 0.8 * (sent - silent), story
    # before the hull change (restart, silence and current on): at the floor
    assert out.tensor_before_hull() <= 2.0 * floor(), story
    # the hull change named by the health (mission time of the sets it judged) within a minute
    hull = PLAN.at(PLAN.hull_at)
    assert out.named_at is not None and hull <= out.named_at <= hull + 60.0, story
    # recalibrated by auto_recalibrate, and the tensor from a minute after the push within a few times the floor
    assert out.pushed_at is not None and out.pushes, story
    assert out.after_push_sets >= 500 and out.tensor_after_push() <= 3.0 * floor(), story
    # memory: no growth beyond a generous bound after the first block (the calibration node solves once)
    for process in ("correction", "calibration"):
        assert out.rss_growth(process) < 64.0, story


def test_outputs_go_on_after_a_time_offset_is_set_following_a_driver_restart(tmp_path: Path) -> None:
    """Found by the 2 h soak: a time offset set after a driver restart (as a recalibration that fitted time
    offsets pushes it) rebuilt the correction node's synchroniser, which forgot where the restarted sensor's
    stamps lie: every later set was withheld (stale current) for the rest of the mission."""
    plan = replace(PLAN, duration=180.0, restart_at=0.1, silent_at=2.0, current_at=0.15, hull_at=2.0, offset_at=0.4)
    lines: list[str] = []
    out = run_soak(plan, lines.append, tmp_path)
    story = "\n".join(lines + table(out))
    sent = sum(b.sent for b in out.blocks.values())
    got = sum(b.outputs for b in out.blocks.values())
    assert got >= 0.8 * sent, story

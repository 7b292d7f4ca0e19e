"""The README's demo, run as a user runs it: its table must show the calibration at the floor.

``python -m magcal_ros.app.demo`` starts both nodes as processes on a private domain, replays a
simulated manoeuvre with two thrusters running and prints before/after residuals on fresh survey
sets. The floor is ``sqrt(2) sigma / d`` for the simulator's 1 nT noise on the 0.4 m cross; the
before-figure comes from the simulator's errors, so an uncalibrated array is far above it.
"""

from __future__ import annotations

import math
import os
import re
import socket
import subprocess
import sys

import pytest

from magcal_ros.app.demo import demo_domain
from magcal_ros.app.ros_driver import pick_domain_id, release_domain_id, rtps_ports

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

FLOOR_TENSOR = math.sqrt(2) * 1.0 / 0.4  # nT/m
FLOOR_TMI = 1.0  # nT
ROW = re.compile(r"^\s{2}(?P<label>[a-z][a-z ,]+?)\s+(?P<tensor>[\d.]+) nT/m\s+(?P<tmi>[\d.]+) nT$")


def _table(stdout: str) -> dict[str, tuple[float, float]]:
    rows = {}
    for line in stdout.splitlines():
        m = ROW.match(line)
        if m:
            rows[m["label"]] = (float(m["tensor"]), float(m["tmi"]))
    return rows


def test_demo_reaches_the_floor_and_shows_what_the_thrusters_cost() -> None:
    # The demo takes a ROS_DOMAIN_ID it is given: one leased here, never the environment's (a vehicle's live domain).
    domain = pick_domain_id()
    try:
        run = subprocess.run([sys.executable, "-m", "magcal_ros.app.demo", "--sets", "800", "--fresh", "300",
                              "--no-drift"], env=dict(os.environ, ROS_DOMAIN_ID=str(domain)),
                             capture_output=True, text=True, timeout=1200)  # a generous deadline: a busy machine only slows it
    finally:
        release_domain_id(domain)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert f"on ROS_DOMAIN_ID={domain} (your ROS_DOMAIN_ID), localhost discovery" in run.stdout, run.stdout[:3000]
    rows = _table(run.stdout)
    before = rows["before calibration"]
    off = rows["calibrated, thrusters not compensated"]
    on = rows["calibrated, thrusters compensated"]
    floor = rows["noise floor"]
    assert floor == pytest.approx((FLOOR_TENSOR, FLOOR_TMI), abs=0.01)
    assert before[0] > 100 * FLOOR_TENSOR and before[1] > 100 * FLOOR_TMI
    assert on[0] < 1.15 * FLOOR_TENSOR and on[1] < 1.3 * FLOOR_TMI, run.stdout[-4000:]
    assert off[0] > 10 * on[0] and off[1] > 10 * on[1], run.stdout[-4000:]  # the interference is real and removed
    assert "removed at exit" in run.stdout


def test_the_demo_takes_the_users_ros_domain_id_and_says_so_else_a_free_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """ROS_DOMAIN_ID set: the demo uses it, says so, and warns when DDS participants are on it already; unset:
    a domain nothing uses, leased; not a domain id: one line."""
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    picked, how = demo_domain()
    try:
        assert 1 <= picked <= 100 and how == "a free one picked: no ROS_DOMAIN_ID set"
        monkeypatch.setenv("ROS_DOMAIN_ID", str(picked))
        assert demo_domain() == (picked, "your ROS_DOMAIN_ID")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as participant:  # a participant's discovery port
            participant.bind(("127.0.0.1", rtps_ports(picked)[10]))
            domain, how = demo_domain()
        assert domain == picked and how.startswith("your ROS_DOMAIN_ID; NOTE: DDS participants are already on it")
    finally:
        release_domain_id(picked)
    for bad in ("abc", "233", "-1"):
        monkeypatch.setenv("ROS_DOMAIN_ID", bad)
        with pytest.raises(RuntimeError, match=f"ROS_DOMAIN_ID='{bad}' is not a ROS domain id"):
            demo_domain()

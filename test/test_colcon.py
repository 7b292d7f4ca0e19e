"""``colcon build`` of the package in a scratch workspace installs a ROS 2 package layout.

Checks what ``ros2 run magcal_ros correction_node`` and ``ros2 launch magcal_ros
magcal.launch.py`` rely on: executables in ``lib/magcal_ros``, config, launch and the
ament index entry in ``share``; then runs the colcon-installed executable after
sourcing ``install/setup.bash``.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).parent / "colcon"
IGNORE = shutil.ignore_patterns(
    ".venv", ".git", "build", "install", "log", "__pycache__", "*.egg-info", ".pytest_cache"
)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A colcon workspace with a copy of this package, built."""
    assert COLCON.exists(), f"colcon is required (requirements-test.txt); not found at {COLCON}"
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(ROOT, ws / "src" / "magcal_ros", ignore=IGNORE)
    env = dict(os.environ, PATH=f"{COLCON.parent}{os.pathsep}{os.environ.get('PATH', '')}")
    proc = subprocess.run(
        [str(COLCON), "build", "--event-handlers", "console_direct-"],
        cwd=ws, env=env, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return ws


def test_executables_are_installed_where_ros2_run_looks(workspace: Path) -> None:
    lib = workspace / "install" / "magcal_ros" / "lib" / "magcal_ros"
    for name in ("correction_node", "calibration_node", "magcal"):
        exe = lib / name
        assert exe.is_file() and os.access(exe, os.X_OK), f"{exe} missing"


def test_share_files_are_installed(workspace: Path) -> None:
    share = workspace / "install" / "magcal_ros" / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "magcal_ros").is_file()
    for rel in ("package.xml", "config/magcal.yaml", "config/example_calibration.yaml", "launch/magcal.launch.py"):
        assert (share / "magcal_ros" / rel).is_file(), rel


def test_colcon_installed_node_starts_after_sourcing(workspace: Path, tmp_path: Path) -> None:
    """``source install/setup.bash`` then the installed executable runs and stops on Ctrl-C."""
    from magcal_ros.app.ros_driver import pick_domain_id, release_domain_id, ros_environment

    log = tmp_path / "node.log"
    domain = pick_domain_id()  # a domain nothing uses, never the environment's
    env = ros_environment(domain)
    script = (
        "source install/setup.bash && exec install/magcal_ros/lib/magcal_ros/correction_node --ros-args "
        "--params-file install/magcal_ros/share/magcal_ros/config/magcal.yaml "
        "--params-file install/magcal_ros/share/magcal_ros/config/example_calibration.yaml"
    )
    with open(log, "w") as out:
        proc = subprocess.Popen(["bash", "-c", script], cwd=workspace, env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and proc.poll() is None and "correcting" not in log.read_text():
            time.sleep(0.1)
        text = log.read_text()
        assert "calibrated sensors: mag1, mag2, mag3, mag4" in text, text
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        release_domain_id(domain)
    assert proc.returncode == 0, log.read_text()

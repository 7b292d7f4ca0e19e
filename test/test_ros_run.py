"""``ros2 run`` after the README's pip install, and Ctrl-C in a terminal, as a ROS user meets them.

``ros2 run magcal_ros <exe>`` resolves ``get_package_prefix('magcal_ros')`` through the
ament index (``AMENT_PREFIX_PATH``) and runs ``<prefix>/lib/magcal_ros/<exe>``; there is no
ros2cli on PyPI, so the test does exactly that lookup with ``ament_index_python`` in a
shell that has only sourced the venv's ``activate``, then runs what it found. A terminal's
Ctrl-C (and ``ros2 launch``) signals the whole process group: both nodes run in one group
and get SIGINT while a calibration is being solved, then again and again while they shut
down; both must exit 0 without a traceback, and the abandoned calibration must change
nothing.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import ros_harness as h

from magcal_ros.app.ros_driver import bag_messages, wait_for_samples
from magcal_ros.io.bag_writer import write_recording_bag

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

VENV = Path(sys.prefix)
EXECUTABLES = ("correction_node", "calibration_node", "magcal")
TRACEBACK_MARKERS = ("Traceback", "KeyboardInterrupt", "ExternalShutdownException", "Exception in thread")


def _lookup() -> dict[str, str]:
    """Paths ``ros2 run`` would run, found after sourcing the venv's activate only."""
    code = (
        "import os\n"
        "from ament_index_python.packages import get_package_prefix\n"
        "prefix = get_package_prefix('magcal_ros')\n"
        f"for exe in {EXECUTABLES!r}:\n"
        "    path = os.path.join(prefix, 'lib', 'magcal_ros', exe)\n"
        "    if os.path.isfile(path) and os.access(path, os.X_OK):\n"
        "        print(exe, path)\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("AMENT_PREFIX_PATH", "VIRTUAL_ENV")}
    script = f'. "{VENV}/bin/activate" && exec python -c "$0"'
    proc = subprocess.run(["bash", "-c", script, code], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return dict(line.split(" ", 1) for line in proc.stdout.splitlines())


@pytest.fixture(scope="module")
def found() -> dict[str, str]:
    if not (VENV / "bin" / "activate").is_file():
        pytest.skip("not running from a virtual environment made by scripts/setup_env.sh")
    return _lookup()


def test_ros2_run_finds_every_executable_after_the_pip_install(found: dict[str, str]) -> None:
    assert set(found) == set(EXECUTABLES), found
    for path in found.values():
        assert Path(path).parent == VENV / "lib" / "magcal_ros"
    proc = subprocess.run([found["magcal"], "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "usage: magcal" in proc.stdout, proc.stderr


def test_sigint_to_the_process_group_stops_both_nodes_cleanly(
    found: dict[str, str], tmp_path: Path
) -> None:
    """Both nodes found as ros2 run finds them, one process group, SIGINT during a solve and during shutdown."""
    data = h.make_data(seed=5, sets=800, check_sets=10)
    bag = tmp_path / "manoeuvre"
    write_recording_bag(bag, data.manoeuvre, storage="sqlite3")
    calibration_file = tmp_path / "calibration.yaml"
    run = h.RosRun(tmp_path, domain_id=h.pick_domain_id(seed=os.getpid() + 61))
    try:
        correction = run.start(found["correction_node"], params=h.UNCORRECTED, log_name="correction", process_group=0)
        calibration = run.start(
            found["calibration_node"], log_name="calibration", process_group=correction.pid,
            params={"reference_field": h.INTENSITY, "calibration_file": str(calibration_file), "method": "pso",
                    "service_timeout": h.SERVICE_TIMEOUT},
        )
        assert os.getpgid(calibration.pid) == os.getpgid(correction.pid) == correction.pid
        driver = run.driver(data.names)
        h.wait_discovered(driver, subscribers=2)
        assert driver.trigger(f"/{h.CALIBRATION}/start")[0]
        sent = driver.replay(bag_messages(bag), rate=h.REPLAY_RATE)
        assert int(wait_for_samples(driver, h.CALIBRATION, len(sent), timeout=h.SAMPLES_TIMEOUT).get("samples", 0)) >= 0.97 * len(sent)
        answer: list[object] = []
        caller = threading.Thread(target=lambda: answer.append(_try_calibrate(driver)), daemon=True)
        caller.start()
        assert calibration.wait_for_log("solving from", 30.0), calibration.log()
        time.sleep(0.2)  # inside the particle swarm (seconds long)
        os.killpg(correction.pid, signal.SIGINT)
        # Ctrl-C again and again while the nodes shut down (destroy_node, rclpy shutdown).
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline and (correction.alive() or calibration.alive()):
            try:
                os.killpg(correction.pid, signal.SIGINT)
            except ProcessLookupError:
                break
            time.sleep(0.01)
        codes = {"correction": correction.wait(20.0), "calibration": calibration.wait(20.0)}
    finally:
        run.close()
    logs = {name: p.log() for name, p in (("correction", correction), ("calibration", calibration))}
    assert codes == {"correction": 0, "calibration": 0}, (codes, logs)
    for name, text in logs.items():
        assert not any(m in text for m in TRACEBACK_MARKERS), f"{name}:\n{text}"
    # The abandoned solve wrote nothing and applied nothing.
    assert not calibration_file.exists() and not list(tmp_path.glob("calibration.yaml*"))
    assert "applied to" not in logs["calibration"]
    assert "parameters updated" not in logs["correction"]


def _try_calibrate(driver: object) -> object:
    try:
        return driver.trigger(f"/{h.CALIBRATION}/calibrate", timeout=30.0)  # type: ignore[attr-defined]
    except Exception as exc:  # noqa: BLE001 - the node is stopped under it; the answer does not matter
        return exc


def test_sigusr1_prints_every_threads_stack_and_the_node_carries_on(found: dict[str, str], tmp_path: Path) -> None:
    """A node that seems stuck can be asked where it is: ``kill -USR1 <pid>`` prints every thread's stack
    into its output (the spinning executor among them) and the node keeps running and exits cleanly."""
    run = h.RosRun(tmp_path, domain_id=h.pick_domain_id(seed=os.getpid() + 67))
    try:
        node = run.start(found["correction_node"], params=h.UNCORRECTED, log_name="correction")
        # A signal that comes while the node is still being built prints that one thread only; ask again
        # (every few seconds, up to a generous deadline) until the stack shows the executor spinning.
        deadline = time.monotonic() + 90.0
        while time.monotonic() < deadline and "in spin" not in node.log() and node.alive():
            os.kill(node.pid, signal.SIGUSR1)
            node.wait_for_log("in spin", 5.0)
        assert "in spin" in node.log(), node.log()
        assert node.alive()
    finally:
        codes = run.close()
    text = node.log()
    assert "thread 0x" in text.lower() and "most recent call first" in text and "in spin" in text, text
    assert codes == {"correction": 0}, (codes, text)

"""Console entry points of the two nodes: Ctrl-C is made quiet before anything heavy is imported.

A terminal's Ctrl-C (or ``ros2 launch`` stopping a node that is still starting) may come
while Python imports rclpy and numpy, which takes most of a second; the handler is
therefore installed first, and the node then exits 0 as soon as rclpy is up.
"""

from __future__ import annotations

import signal
import threading
from typing import Any


def quiet_signals() -> threading.Event:
    """SIGINT and SIGTERM set the returned event instead of raising KeyboardInterrupt or killing the process.

    Installed before ``rclpy.init``: rclpy's own handler (installed by init) shuts the
    context down, which ends the spin, and then calls this one, so a Ctrl-C anywhere,
    also a second one during clean-up, never raises a traceback.
    """
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return stop


def correction_node() -> int:
    """``correction_node`` (``ros2 run magcal_ros correction_node``)."""
    stop = quiet_signals()
    from magcal_ros.nodes.correction_node import main

    return main(stop=stop)


def calibration_node() -> int:
    """``calibration_node`` (``ros2 run magcal_ros calibration_node``)."""
    stop = quiet_signals()
    from magcal_ros.nodes.calibration_node import main

    return main(stop=stop)

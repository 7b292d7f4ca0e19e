"""Console entry points of the two nodes: Ctrl-C is made quiet before anything heavy is imported.

A terminal's Ctrl-C (or ``ros2 launch`` stopping a node that is still starting) may come
while Python imports rclpy and numpy, which takes most of a second; the handler is
therefore installed first, and the node then exits 0 as soon as rclpy is up.
"""

from __future__ import annotations

import signal
from typing import Any


class StopFlag:
    """Set by a stop signal (it is the signal handler itself); read with :meth:`is_set`.

    No lock and one line of Python: a handler runs again inside itself when the next signal
    comes between two of its bytecodes (a terminal or launch file signalling again and again),
    and one that takes a lock, such as ``threading.Event.set``, then waits for itself for ever
    (or, under a flood, recurses until the interpreter gives up)."""

    def __init__(self) -> None:
        self._set = False

    def __call__(self, signum: int, frame: Any) -> None:
        self._set = True

    def is_set(self) -> bool:
        return self._set


def quiet_signals() -> StopFlag:
    """SIGINT and SIGTERM set the returned flag instead of raising KeyboardInterrupt or killing the process.

    Installed before ``rclpy.init``: rclpy's own handler (installed by init) shuts the
    context down, which ends the spin, and then calls this one, so a Ctrl-C anywhere,
    also a second one during clean-up, never raises a traceback.
    """
    stop = StopFlag()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop)
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

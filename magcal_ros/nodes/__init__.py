"""The ROS 2 nodes (rclpy): ``correction_node`` and ``calibration_node``, thin over the core.

Parameters, synchronisation, solving and files live in the lower layers and are tested
without a middleware; these modules wire them to topics, services and parameters.
"""

from __future__ import annotations

from magcal_ros._lazy import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "CalibrationNode": "magcal_ros.nodes.calibration_node",
        "CorrectionNode": "magcal_ros.nodes.correction_node",
    },
)

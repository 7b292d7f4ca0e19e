"""What users run: the ``magcal`` command, offline correction, plots, progress bars, the demo,
and the replay driver that feeds the nodes over DDS (demo, tests, benchmarks)."""

from __future__ import annotations

from magcal_ros._lazy import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "correct_bag": "magcal_ros.app.correct",
        "main": "magcal_ros.app.cli",
    },
)

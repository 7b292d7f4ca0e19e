"""Calibration methods: one pipeline (:mod:`.pipeline`), each method a set of strategies
(:mod:`.strategies`), the papers' own solvers (particle swarm, paired norms), and the
progress analysis of a manoeuvre being collected (:mod:`.progress`)."""

from __future__ import annotations

from magcal_ros._lazy import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "CalibrationResult": "magcal_ros.methods.pipeline",
        "DEFAULT_METHOD": "magcal_ros.methods.strategies",
        "METHODS": "magcal_ros.methods.strategies",
        "Method": "magcal_ros.methods.strategies",
        "SolveOptions": "magcal_ros.methods.pipeline",
        "calibrate_array": "magcal_ros.methods.pipeline",
        "calibrate_interference": "magcal_ros.methods.interference",
        "Assessment": "magcal_ros.methods.progress",
        "assess": "magcal_ros.methods.progress",
        "paired_fit": "magcal_ros.methods.paired",
        "pso_fit": "magcal_ros.methods.pso",
    },
)

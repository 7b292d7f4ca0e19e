"""Simulated arrays with known truth: sensors with errors on a turning platform in the Earth's
field (plus dipoles), manoeuvre schedules, the papers' scenarios, ``magcal simulate``'s spec, and per-sensor
streams as real drivers produce them (own clocks, receipt stamps, glitches, restarts, lags)."""

from __future__ import annotations

from magcal_ros._lazy import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "ArraySimulation": "magcal_ros.sim.simulator",
        "AttitudePath": "magcal_ros.sim.attitudes",
        "ImuModel": "magcal_ros.sim.imu",
        "SimulationSpec": "magcal_ros.sim.spec",
        "StreamSpec": "magcal_ros.sim.streams",
        "Thruster": "magcal_ros.sim.simulator",
        "Truth": "magcal_ros.sim.simulator",
        "random_sensor_errors": "magcal_ros.sim.simulator",
        "run": "magcal_ros.sim.spec",
        "simulate_streams": "magcal_ros.sim.streams",
        "simulate_imu": "magcal_ros.sim.imu",
        "temperature_profile": "magcal_ros.sim.temperature",
    },
)

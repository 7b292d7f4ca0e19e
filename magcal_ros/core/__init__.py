"""The calibration math on numpy arrays: no file or message I/O, no ROS, no simulation.

Units are SI everywhere (Tesla, metres, T/m), stamps integer nanoseconds. Frames: each
sensor's raw axes, and the platform frame all corrected vectors and tensors are in.
"""

from __future__ import annotations

from magcal_ros._lazy import lazy_exports

__all__, __getattr__ = lazy_exports(
    __name__,
    {
        "ArrayCalibration": "magcal_ros.core.calibration",
        "ArrayGeometry": "magcal_ros.core.geometry",
        "CurrentSamples": "magcal_ros.core.interference",
        "Dipole": "magcal_ros.core.field",
        "Excitation": "magcal_ros.core.observability",
        "ImuSamples": "magcal_ros.core.recording",
        "ImuStream": "magcal_ros.core.imu",
        "LatestValues": "magcal_ros.core.matching",
        "NS_PER_S": "magcal_ros.core.units",
        "NT": "magcal_ros.core.units",
        "Recording": "magcal_ros.core.recording",
        "ScalarFit": "magcal_ros.core.scalar_fit",
        "SampleClock": "magcal_ros.core.sample_clock",
        "SensorErrors": "magcal_ros.core.sensor_model",
        "SetBatch": "magcal_ros.core.sync",
        "SetSynchronizer": "magcal_ros.core.sync",
        "SiteField": "magcal_ros.core.geomagnetic",
        "StreamSynchronizer": "magcal_ros.core.sync",
        "SyncStats": "magcal_ros.core.sync",
        "SyncedSet": "magcal_ros.core.sync",
        "TemperatureSamples": "magcal_ros.core.temperature",
        "algebraic_fit": "magcal_ros.core.scalar_fit",
        "centre_field": "magcal_ros.core.tensor",
        "earth_field": "magcal_ros.core.field",
        "estimate_interference": "magcal_ros.core.interference",
        "excitation": "magcal_ros.core.observability",
        "gradient": "magcal_ros.core.tensor",
        "invariants": "magcal_ros.core.tensor",
        "match_currents": "magcal_ros.core.interference",
        "match_imu": "magcal_ros.core.imu",
        "match_latest": "magcal_ros.core.matching",
        "ml_fit": "magcal_ros.core.scalar_fit",
        "procrustes": "magcal_ros.core.rotation",
        "site_field": "magcal_ros.core.geomagnetic",
        "stream_synchronizer": "magcal_ros.core.sync",
        "synchronise_streams": "magcal_ros.core.sync",
        "tensor_floor": "magcal_ros.core.metrics",
        "tensor_rms": "magcal_ros.core.metrics",
        "tmi_rms": "magcal_ros.core.metrics",
        "undetermined_channels": "magcal_ros.core.interference",
    },
)

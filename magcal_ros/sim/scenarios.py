"""The five papers' simulations with their own parameters (tests and benchmarks share them).

Each builder returns an :class:`ArraySimulation` (SI units) and documents where its
numbers come from; ``REPORTED`` holds the numbers the papers print (nT, nT/m, deg).
Parameters a paper does not give (noted per builder) are chosen here and say so.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.sensor_model import SensorErrors
from magcal_ros.core.units import NT
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

Array = NDArray[np.float64]

# Li et al. (2018) (Li et al. 2018): Table 1 sensor errors, Table 3 misalignments, sections 5.1-5.2.
LI2018_F: float = 60_000 * NT
LI2018_BASELINE: float = 0.4
LI2018_ANGLES_DEG: Array = np.array(  # (phi, theta, psi) per sensor
    [[3.56, -1.85, 2.27], [-2.74, 3.11, 1.66], [1.86, -2.95, 3.02], [-3.28, 2.44, -1.88]]
)
LI2018_SCALE: Array = np.array(
    [[1.253, 1.175, 0.859], [0.951, 1.202, 1.105], [1.110, 0.799, 1.308], [0.853, 1.235, 1.186]]
)
LI2018_OFFSET_NT: Array = np.array([[357, 160, -213], [-253, 183, 97], [169, -364, 245], [256, 169, -166]], float)
LI2018_MISALIGNMENT_RAD: Array = np.array(  # (alpha, beta, gamma), Table 3 in rad
    [
        [-0.383449, 0.224798, 0.238063],
        [0.218341, -0.069115, 0.373850],
        [-0.205425, 0.130202, -0.227416],
        [0.212407, 0.233700, 0.168250],
    ]
)

# Ding (2024) (Ding 2024): Tables 1 and 2, F 51500 nT, D -7 deg, I 52 deg.
DING2024_F: float = 51_500 * NT
DING2024_TABLES: dict[int, dict[str, Array]] = {
    1: {
        "offset_nt": np.array([75.5, 57.3, -42.6]),
        "scale": np.array([1.031, 0.988, 0.982]),
        "angles_deg": np.array([-1.01, -0.83, 1.20]),
        "hard_iron_nt": np.array([212.0, -367.0, 398.0]),
        "soft_iron": np.array([[0.11, 0.09, -0.13], [0.13, -0.06, 0.14], [-0.06, 0.13, 0.11]]),
    },
    2: {
        "offset_nt": np.array([52.65, -35.5, 72.4]),
        "scale": np.array([1.00002, 0.99997, 1.00005]),
        "angles_deg": np.array([0.08, 0.03, -0.02]),
        "hard_iron_nt": np.array([100.0, -200.0, 100.0]),
        "soft_iron": np.array([[0.09, 0.05, 0.09], [0.15, -0.04, 0.10], [-0.04, 0.09, 0.15]]),
    },
}
DING2024_NOISE_PP_NT: tuple[float, ...] = (0.0, 2.0, 5.0, 10.0)
"""Peak-to-peak uniform noise amplitudes of Ding (2024) (sd = a / sqrt(12))."""

# Wu et al. (2013) (Wu et al. 2013): (theta, phi, psi) rad and gains k'xz, k'yz relative to z.
WU2013_TRUTH: Array = np.array([0.06, 0.08, -0.04, 0.95, 1.05])
WU2013_UNIT: float = 1e4 * NT
"""Wu et al. (2013)'s field unit: the field is (1, 1, sqrt 2) units and noise sd is quoted in units."""

# The two-fluxgate gradiometer paper: field vector as printed (x, y, z) nT, Tables 1-2 (non-orthogonality P, sensitivity K, offset E).
GRADIOMETER_FIELD_NT: Array = np.array([31653.3, -1968.8, 41810.1])
GRADIOMETER_P: tuple[Array, Array] = (
    np.array([[0.9994, 0.0140, 0.0], [0.0, 0.9998, 0.0], [0.0349, -0.0175, 1.0]]),
    np.array([[0.9988, 0.0331, -0.0209], [-0.0349, 0.9985, -0.0007], [0.0349, -0.0436, 0.9998]]),
)
GRADIOMETER_K: tuple[Array, Array] = (np.diag([0.9870, 1.0460, 1.0120]), np.diag([0.9910, 0.9890, 1.0120]))
GRADIOMETER_E_NT: tuple[Array, Array] = (np.array([-30.0, 60.0, 110.0]), np.array([600.0, -70.0, 20.0]))

COAXIAL2022_F: float = 48_750 * NT

REPORTED: dict[str, dict[str, tuple[float, ...]]] = {
    "000": {
        "tmi_before": (8994.31, 6714.99, 9041.56, 8723.06),
        "tmi_after": (0.9803, 0.9941, 1.0192, 0.9835),
        "tensor_before": (52171, 28115, 42346, 53898, 21816, 30940),
        "tensor_scalar_only": (34764, 24375, 13835, 36119, 15338, 21053),
        "tensor_after": (3.7537, 3.4655, 3.8518, 3.9604, 3.5570, 3.5281),
    },
    "001": {"tmi_ptp_before": (3138.6, 2633.0), "tmi_ptp_after": (4.6, 4.1),
            "diff_ptp_before": (2831.5, 5801.9, 2218.8), "diff_ptp_after": (5.4, 5.6, 5.9)},
    "002": {"table1_improved": (7.05e-12, 0.58, 1.42, 2.84), "table1_plain": (7.28e-6, 8.35, 87.70, 162.26),
            "table2_improved": (1.672e-10, 0.532, 1.329, 2.659)},
    "004": {"axis_angle_after_deg": (0.01,)},
}


def li2018_sensors() -> tuple[SensorErrors, ...]:
    """Li et al. (2018)'s four sensors: Table 1 errors and Table 3 misalignments."""
    return tuple(
        SensorErrors(
            scale=LI2018_SCALE[i],
            angles=np.radians(LI2018_ANGLES_DEG[i]),
            offset=LI2018_OFFSET_NT[i] * NT,
            misalignment=LI2018_MISALIGNMENT_RAD[i],
        )
        for i in range(4)
    )


def li2018_simulation(noise: float = 1 * NT) -> ArraySimulation:
    """Li et al. (2018): cross of 0.4 m, F 60000 nT, I 57, D -5 deg, Gaussian noise on the
    misaligned orthogonal output (before scale and non-orthogonality)."""
    return ArraySimulation(
        ArrayGeometry.cross(LI2018_BASELINE),
        li2018_sensors(),
        earth_field(LI2018_F, 57.0, -5.0),
        noise=noise,
        noise_domain="sensor",
    )


def ding2024_sensor(table: int, misalignment_deg: ArrayLike | None = None) -> SensorErrors:
    """Ding (2024) Table 1 or 2 sensor with hull hard and soft iron."""
    t = DING2024_TABLES[table]
    return SensorErrors(
        scale=t["scale"],
        angles=np.radians(t["angles_deg"]),
        offset=t["offset_nt"] * NT,
        hard_iron=t["hard_iron_nt"] * NT,
        soft_iron=t["soft_iron"],
        misalignment=np.radians(misalignment_deg) if misalignment_deg is not None else np.zeros(3),
    )


def ding2024_simulation(table: int, peak_to_peak: float, seed: int = 0) -> ArraySimulation:
    """A cross array of Ding (2024) sensors: Table ``table`` errors on every sensor plus a
    random 2-deg misalignment each (the paper has one sensor and no array), uniform noise
    of ``peak_to_peak`` (T) on the raw output."""
    rng = np.random.default_rng(seed)
    sensors = tuple(ding2024_sensor(table, rng.normal(0.0, 2.0, 3)) for _ in range(4))
    return ArraySimulation(
        ArrayGeometry.cross(),
        sensors,
        earth_field(DING2024_F, 52.0, -7.0),
        noise=peak_to_peak / np.sqrt(12.0),
        noise_kind="uniform",
        noise_domain="raw",
    )


def wu2013_sensor() -> SensorErrors:
    """Wu et al. (2013)'s sensor: ``Gamma = diag(1/k'xz, 1/k'yz, 1) A(theta, phi, psi)``.

    Wu et al. (2013)'s theta (elevation) and phi (azimuth) are this package's phi and theta.
    """
    theta, phi, psi, kxz, kyz = WU2013_TRUTH
    return SensorErrors(scale=[1.0 / kxz, 1.0 / kyz, 1.0], angles=[theta, phi, psi])


def wu2013_simulation(sd_units: float) -> ArraySimulation:
    """Wu et al. (2013): field (1, 1, sqrt 2) x 1e4 nT, Gaussian raw noise of ``sd_units`` x 1e4 nT,
    no offset. Two identical sensors (an array needs two); use sensor 0."""
    s = wu2013_sensor()
    return ArraySimulation(
        ArrayGeometry(("s1", "s2"), [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]),
        (s, s),
        np.array([1.0, 1.0, np.sqrt(2.0)]) * WU2013_UNIT,
        noise=sd_units * WU2013_UNIT,
    )


def gradiometer_sensors() -> tuple[SensorErrors, SensorErrors]:
    """The two-fluxgate gradiometer paper's two sensors, ``r = K P^-1 B + E`` (the composition that fits its eq. 8)."""
    s1, s2 = (
        SensorErrors.from_forward(k @ np.linalg.inv(p), e * NT)
        for p, k, e in zip(GRADIOMETER_P, GRADIOMETER_K, GRADIOMETER_E_NT)
    )
    return s1, s2


def gradiometer_simulation(noise: float = 1 * NT) -> ArraySimulation:
    """The two-fluxgate gradiometer paper: two sensors 0.5 m apart in the printed field vector (F = its norm,
    52477.5 nT), Gaussian raw noise (sd 1 nT fits the paper's results)."""
    return ArraySimulation(
        ArrayGeometry(("s1", "s2"), [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]),
        gradiometer_sensors(),
        GRADIOMETER_FIELD_NT * NT,
        noise=noise,
    )


def coaxial2022_simulation(seed: int = 4, noise: float = 1 * NT) -> ArraySimulation:
    """The JNWPU 2022 coaxial calibration paper: cross of 0.5 m, F 48750 nT. Not given by the paper and chosen here:
    field direction (I 60, D -5 deg), errors of a typical fluxgate
    (:func:`random_sensor_errors`, 1-deg misalignments: its axis angles before calibration
    are about 1-2 deg), Gaussian raw noise 1 nT."""
    rng = np.random.default_rng(seed)
    sensors = tuple(random_sensor_errors(rng, misalignment_sd_deg=1.0) for _ in range(4))
    return ArraySimulation(ArrayGeometry.cross(0.5), sensors, earth_field(COAXIAL2022_F, 60.0, -5.0), noise=noise)


FIELD_TRIAL_F: float = 51_500 * NT
"""Intensity of the field-trial arrays (T): mid-latitude, inclination 60 deg."""


def field_trial_array(seed: int, noise: float = 1 * NT, **options: float) -> ArraySimulation:
    """The 0.4 m cross of typical fluxgates (:func:`random_sensor_errors` from ``seed``) in a
    51 500 nT field of inclination 60 deg: the array of the at-sea and real-data scenarios.

    ``options`` go to :class:`ArraySimulation` (e.g. ``noise_correlation``).
    """
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross()
    return ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                           earth_field(FIELD_TRIAL_F, 60.0, 5.0), noise=noise, **options)  # type: ignore[arg-type]

"""A simulated IMU on the array's vehicle: orientation (ENU, as ``sensor_msgs/Imu`` gives it) and gyro.

The IMU is mounted with ``mounting`` (3, 3), the rotation from the array (platform) frame
to the IMU frame (``v_imu = mounting v_array``): a few degrees off in practice. With the
platform's attitude ``R`` (platform to the simulator's world frame, NED), the IMU's true
orientation is ``R_imu = NED_TO_ENU R mounting^T`` (IMU frame to world ENU) and its true
angular velocity ``mounting w`` (``w`` the platform's, platform frame). Measured values add
a small random rotation of ``orientation_noise`` rad (1-sigma per axis) to the orientation
and ``gyro_bias`` plus white noise of ``gyro_noise`` rad/s to the gyro. Only a path flown
in time has an angular velocity (:class:`~magcal_ros.sim.attitudes.AttitudePath`); without
one the IMU gives its orientation only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core.imu import NED_TO_ENU, ImuStream, matrix_to_quat, quat_exp, quat_multiply
from magcal_ros.core.recording import ImuSamples
from magcal_ros.core.stamps import seconds_to_ns
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError
from magcal_ros.sim.attitudes import AttitudePath

Array = NDArray[np.float64]

DEFAULT_IMU_FRAME_ID = "imu_link"


@dataclass(frozen=True)
class ImuModel:
    """A simulated IMU (see the module docstring). Angles in rad, rates in rad/s."""

    mounting: Array = field(default_factory=lambda: np.eye(3))
    """(3, 3) rotation array (platform) frame -> IMU frame."""
    orientation_noise: float = 0.0
    """1-sigma per axis (rad) of the measured orientation's error, a small rotation per sample."""
    gyro_noise: float = 0.0
    """1-sigma per axis (rad/s) of the gyro's white noise."""
    gyro_bias: Array = field(default_factory=lambda: np.zeros(3))
    """(3,) rad/s, IMU frame: the gyro's constant bias."""
    rate: float = 0.0
    """Samples per second of the IMU's own stream (0: one sample at each set's stamp)."""
    frame_id: str = DEFAULT_IMU_FRAME_ID
    array_lag: float = 0.0
    """s: how late the array's stamps are on the IMU's clock (drivers that stamp on receipt): a set stamped
    ``t`` was sampled at ``t - array_lag`` on the IMU's clock, where the IMU's own samples are stamped when
    they are taken. Needs attitudes flown in time."""

    def __post_init__(self) -> None:
        m = np.asarray(self.mounting, dtype=float).reshape(3, 3)
        if not np.all(np.isfinite(m)) or np.max(np.abs(m @ m.T - np.eye(3))) > 1e-9 or np.linalg.det(m) <= 0:
            raise InputError("the IMU mounting must be a rotation matrix")
        bias = np.asarray(self.gyro_bias, dtype=float).reshape(3)
        if not (np.isfinite(self.array_lag) and abs(self.array_lag) <= 0.5):
            raise InputError("the array's lag behind the IMU must be a finite number of seconds within +-0.5 s")
        for name, v in (("orientation noise", self.orientation_noise), ("gyro noise", self.gyro_noise),
                        ("IMU rate", self.rate)):
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0")
        if not np.all(np.isfinite(bias)):
            raise InputError("the gyro bias must be finite")
        object.__setattr__(self, "mounting", m)
        object.__setattr__(self, "gyro_bias", bias)

    def true_orientation(self, attitudes: ArrayLike) -> Array:
        """(N, 4) quaternions IMU frame -> world ENU of platform-to-NED ``attitudes`` (N, 3, 3)."""
        r = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
        return matrix_to_quat(np.einsum("ij,njk,lk->nil", NED_TO_ENU, r, self.mounting))

    def true_angular_velocity(self, platform_rates: ArrayLike) -> Array:
        """(N, 3) rad/s in the IMU frame of the platform's angular velocity (N, 3) rad/s, platform frame."""
        return np.asarray(platform_rates, dtype=float).reshape(-1, 3) @ self.mounting.T

    def measure(self, orientation: Array, angular_velocity: Array, rng: np.random.Generator) -> tuple[Array, Array]:
        """Measured orientation (N, 4) and angular velocity (N, 3) of true ones (NaN rows stay NaN)."""
        q = orientation
        if self.orientation_noise > 0:
            q = quat_multiply(q, quat_exp(rng.normal(0.0, self.orientation_noise, (len(q), 3))))
        w = angular_velocity + self.gyro_bias
        if self.gyro_noise > 0:
            w = w + rng.normal(0.0, self.gyro_noise, w.shape)
        return q, w


@dataclass(frozen=True)
class ImuOutput:
    """What the simulated IMU gives for a recording."""

    measured: ImuSamples
    """At each set's stamp, measured (what a CSV row holds)."""
    true_orientation: Array
    """(N, 4) at each set, IMU frame -> world ENU."""
    true_angular_velocity: Array
    """(N, 3) rad/s at each set, IMU frame; NaN without a path in time."""
    stream: ImuStream
    """The IMU's own stream, measured (at ``rate``, or at the set stamps)."""


def simulate_imu(model: ImuModel, attitudes: ArrayLike, stamps: NDArray[np.int64], path: AttitudePath | None,
                 rng: np.random.Generator) -> ImuOutput:
    """The IMU for sets at ``stamps`` (ns) with platform-to-NED ``attitudes``; ``path``: the continuous
    attitude the sets sample (times in s from the first stamp), None when the attitudes are not a path
    in time (then no angular velocity, and no stream at its own rate). With the model's ``array_lag`` the
    IMU at a set's stamp is the path ``array_lag`` after the set's sample; the true values are at the
    samples."""
    rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
    q_true = model.true_orientation(rot)
    t_sets = (np.asarray(stamps, np.int64) - stamps[0]) / NS_PER_S
    lag = model.array_lag
    if path is None:
        if model.rate > 0 or lag:
            raise InputError("an IMU at its own rate, or an array lagging the IMU, needs attitudes flown in time (a "
                             "schedule of single-axis, sea or tumble)")
        w_true = np.full((len(rot), 3), np.nan)
    else:
        w_true = model.true_angular_velocity(path.angular_velocity(t_sets))
    if lag:  # what the IMU says at the sets' stamps: the path lag later
        q, w = model.measure(model.true_orientation(path.attitude(t_sets + lag)),
                             model.true_angular_velocity(path.angular_velocity(t_sets + lag)), rng)
    else:
        q, w = model.measure(q_true, w_true, rng)
    measured = ImuSamples(q, w, model.frame_id)
    if model.rate > 0 and path is not None:
        span = t_sets[-1]
        phase = 0.37 / model.rate  # the IMU's clock is not the magnetometers': no sample falls on a set
        t_imu = phase + np.arange(int(np.floor((span - phase) * model.rate)) + 1) / model.rate
        t_imu = t_imu[t_imu <= span]
        sq, sw = model.measure(model.true_orientation(path.attitude(t_imu)),
                               model.true_angular_velocity(path.angular_velocity(t_imu)), rng)
        stream = ImuStream(stamps[0] + seconds_to_ns(t_imu - lag), sq, sw, model.frame_id)  # taken at t_imu
    else:
        stream = ImuStream(np.asarray(stamps, np.int64), q, w, model.frame_id)  # at the stamps: what it says there
    return ImuOutput(measured, q_true, w_true, stream)

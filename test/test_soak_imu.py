"""The mission soak's IMU (:mod:`magcal_ros.app.soak`, ``SoakPlan.imu``) without DDS: what MissionSource
publishes is the simulator's convention (orientation IMU frame -> world ENU, angular velocity rad/s in the IMU
frame), the gyro agrees with the orientations, the default mission publishes none, and the frame error of a
block finds a rotation of the outputs."""

from __future__ import annotations

import numpy as np

from magcal_ros.app.soak import IMU_RATE, Block, MissionSource, SoakPlan
from magcal_ros.core.imu import NED_TO_ENU, quat_exp, quat_multiply, quat_to_matrix
from magcal_ros.sim.attitudes import yaw_pitch_roll

START = 10**18


def test_the_imu_is_the_attitude_turned_by_the_mounting_and_its_gyro_follows_it() -> None:
    src = MissionSource(SoakPlan(duration=120.0, imu=True), START)
    assert src.imu is not None and src.sim.true_calibration().output_rotation is not None
    np.testing.assert_allclose(src.sim.true_calibration().output_rotation, src.imu.mounting)
    t = src.imu_instants(10.0, 14.0)
    assert len(t) == 4 * IMU_RATE and np.all(np.diff(t) > 0)
    q, w = src.imu_samples(t)
    # the IMU-frame field turned by the orientation is the Earth's field in ENU, whatever the attitude
    b_imu = src.truth_field(t) @ src.imu.mounting.T
    np.testing.assert_allclose(np.einsum("nij,nj->ni", quat_to_matrix(q), b_imu),
                               np.broadcast_to(NED_TO_ENU @ src.sim.earth, b_imu.shape), atol=1e-12)
    # integrating the gyro over one IMU period gives the next orientation (dR/dt = R [w]x, IMU frame)
    step = quat_multiply(q[:-1], quat_exp(0.5 * (w[:-1] + w[1:]) / IMU_RATE))
    assert np.max(np.abs(quat_to_matrix(step) - quat_to_matrix(q[1:]))) < 1e-6
    assert 5.0 < np.degrees(np.median(np.linalg.norm(w, axis=1))) < 10.0  # the 6 deg/s turn and the wobble


def test_imu_messages_only_when_asked_and_sets_placed_on_the_first_sensors_grid() -> None:
    plain = MissionSource(SoakPlan(duration=120.0), START)
    assert plain.imu is None and not plain.sim.true_calibration().rotated
    assert {kind for kind, *_ in plain.stretch(0.0, 5.0)[1]} == {0, 1, 2}
    src = MissionSource(SoakPlan(duration=120.0, imu=True), START)
    when, items = src.stretch(0.0, 5.0)
    assert np.all(np.diff(when) >= 0)
    imu = [it for it in items if it[0] == 3]
    assert len(imu) == 5 * IMU_RATE
    first = np.array([it[2] for it in items if it[0] == 0 and it[1] == 0], dtype=np.int64)
    np.testing.assert_allclose(src.sample_instants(first), src.instants(0, 0.0, 5.0), atol=1e-9)


def test_the_frame_error_of_a_block_is_the_rotation_of_its_outputs() -> None:
    src = MissionSource(SoakPlan(duration=120.0, imu=True), START)
    t = np.arange(0.0, 60.0, 0.05)
    truth = src.truth_field(t)
    turned = truth @ yaw_pitch_roll(0.002, 0.0, 0.0)[0].T  # 2 mdeg about z
    b = Block(outputs=len(t))
    b.field_ss = float(np.sum((turned - truth) ** 2))
    b.field_cross += np.einsum("ni,nj->ij", turned, truth)
    assert abs(b.frame_error() - 0.002) < 1e-6
    assert b.field_error() > 0.0 and np.isnan(Block().frame_error())

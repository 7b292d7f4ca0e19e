"""The IMU's blocks of the forward model against simulated truth: the array-to-IMU rotation, the
field direction, a world-frame site gradient, the gyro's relative rotations; outputs in the IMU frame.

Floors come from the simulator: 1 nT noise per axis, the tensor floor sqrt(2) sigma / d of the
0.4 m cross; the mounting 2-3 deg off the array. The array frame is fixed by the gauge of
:mod:`magcal_ros.core.uncertainty` (the virtual centre sensor's matrix upper triangular), so the
true array-to-IMU rotation is the simulated mounting expressed in that frame.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg

from magcal_ros.core import attitude_blocks as ab
from magcal_ros.core.imu import NED_TO_ENU, matrix_to_quat
from magcal_ros.core.metrics import rms, tensor_floor, tensor_rms, tmi_rms
from magcal_ros.core.recording import ImuSamples
from magcal_ros.core.units import NT
from magcal_ros.errors import ObservabilityError
from magcal_ros.methods.pipeline import SolveOptions, calibrate_array
from magcal_ros.sim.spec import SimulationSpec, run

NOISE = 1 * NT
FLOOR = tensor_floor(NOISE, 0.4)
MOUNTING = (2.0, -2.5, 3.0)  # roll, pitch, yaw (deg): array frame -> IMU frame
GRADIENT_NED = (30e-9, 10e-9, -15e-9, -20e-9, 5e-9)  # xx, xy, xz, yy, yz (T/m): ||G|| about 50 nT/m


def _fresh(seed: int):
    """The same sensors (same seed) in a uniform field at other attitudes."""
    rec, truth, sim = run(SimulationSpec(count=600, schedule="random", seed=seed, noise=NOISE, imu=True,
                                         imu_mounting=MOUNTING))
    return rec, truth, sim


def _gauge_mounting(truth_cal, mounting: np.ndarray) -> np.ndarray:
    """The true array-to-IMU rotation in the reported array frame (mean(K_i) upper triangular)."""
    upper, q = scipy.linalg.rq(np.linalg.inv(truth_cal.matrices).mean(axis=0))
    q = np.sign(np.diag(upper))[:, None] * q
    return mounting @ q.T


@pytest.fixture(scope="module")
def tumble():
    """A tumble with the IMU's orientation (0.02 deg error) and a fresh recording of the same sensors."""
    spec = SimulationSpec(count=380, schedule="tumble", seed=11, noise=NOISE, imu=True, imu_mounting=MOUNTING,
                          imu_orientation_noise=0.02)
    rec, truth, sim = run(spec)
    result = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=rec.imu)
    return spec, rec, truth, sim, result


def test_orientation_outputs_in_the_imu_frame_on_fresh_attitudes(tumble):
    spec, _, _, sim, result = tumble
    cal = result.calibration
    assert cal.frame_id == "imu_link" and cal.rotated
    rec, truth, _ = _fresh(spec.seed)
    out = cal.outputs(rec.vectors)
    true_imu = np.einsum("ab,nsb->nsa", sim.imu.mounting, truth.field)
    per_axis = rms(out.vectors - true_imu)
    assert per_axis < 2 * NT, per_axis / NT
    assert np.max(tmi_rms(out.vectors, spec.intensity)) < 1.2 * NOISE
    assert tensor_rms(out.tensor) < 1.2 * FLOOR
    # the file stores the rotation and the frame
    params = cal.to_parameters()
    assert np.allclose(np.reshape(params["output_rotation"], (3, 3)), cal.output_rotation)
    assert params["frame_id"] == "imu_link"


def test_the_frame_note_says_whether_this_solve_fitted_the_rotation(tumble):
    """With the IMU in the solve the note says output_rotation was fitted from its orientations; a rotation carried
    over from a running or prior calibration (a recalibration without the IMU) is said to be kept, not fitted."""
    import dataclasses

    result = tumble[-1]
    assert "was fitted from its orientations" in result.frame_note()
    kept = dataclasses.replace(result, extras={k: v for k, v in result.extras.items() if k != "imu"})
    assert "is kept from the running or prior calibration" in kept.frame_note()
    assert "fitted" not in kept.frame_note()


def test_without_a_lag_none_is_applied(tumble):
    """The tumble's IMU stamps its samples when the array does: the array lag block finds nothing significant
    and the calibration carries no time offsets (sets formed as the sensors stamp them)."""
    _, _, _, _, result = tumble
    lag = result.extras["imu"].by_name("array lag behind the IMU")
    assert abs(lag.value) < 3 * lag.sigma and lag.sigma < 0.1
    assert not np.any(result.calibration.time_offsets)
    assert any(n.startswith("array lag behind the IMU: ") and n.endswith("not significant; none applied")
               for n in result.extras["block_notes"])


def test_the_array_lag_behind_the_imu_is_fitted_and_applied_offline(tmp_path):
    """Magnetometer drivers that stamp 10 ms late on the IMU's clock (an IMU at 100 Hz, tumbling): the
    calibration finds the lag, adds it to every sensor's time offset, and ``magcal correct`` stamps the
    outputs at the IMU's instants, where the centre field in the IMU frame matches the truth at the IMU's
    instant within 2 nT RMS per axis (the same bound as without a lag); stamped as the array stamps, the
    field is 100 nT and more off the truth at those stamps."""
    import yaml
    from test_offline import magcal, ok, read_corrected

    from magcal_ros.io import calibration_file as calfile
    from magcal_ros.io.recordings import read_recording
    from magcal_ros.io.truth_file import load_truth

    bag, lag = tmp_path / "bag", 0.010
    ok(magcal("simulate", bag, "--schedule", "tumble", "--count", 600, "--seed", 11, "--imu", "--imu-rate", 100,
              "--imu-orientation-noise", 0.02, "--imu-mounting", "2,-2.5,3", "--imu-array-lag", lag))
    proc = ok(magcal("calibrate", bag, "-o", tmp_path / "cal.yaml", "--imu", "/imu", "--reference-field", 5.5e-5))
    cal = calfile.read(tmp_path / "cal.yaml")
    fitted = float(cal.time_offsets[0])
    assert np.all(cal.time_offsets == fitted) and abs(fitted - lag) < 2e-4, cal.time_offsets
    imu = cal.metadata["imu"]
    assert imu["values"]["array_lag_behind_the_imu_ms"] == pytest.approx(fitted * 1e3)
    assert 0 < imu["sigma"]["array_lag_behind_the_imu_ms"] < 0.1
    assert "array lag behind the IMU: 9.9" in proc.stdout + proc.stderr
    ok(magcal("correct", bag, "-c", tmp_path / "cal.yaml", "-o", tmp_path / "out.csv"))
    out = read_corrected(tmp_path / "out.csv")
    rec = read_recording(bag)
    rec = rec[0] if isinstance(rec, tuple) else rec
    assert np.array_equal(rec.stamps - out["stamps"], np.full(len(rec.stamps), round(fitted * 1e9)))
    # the truth: the centre field in the IMU frame at each sample; sample k (path time t_k) is stamped
    # s_0 + t_k by the array and taken at s_0 + t_k - lag on the IMU's clock
    truth = load_truth(bag)
    mounting = np.reshape(yaml.safe_load((tmp_path / "bag.truth.yaml").read_text())["magcal_simulation"]
                          ["ros__parameters"]["imu_mounting_matrix"], (3, 3))
    centre = truth["field"].mean(axis=1) @ mounting.T
    t = (rec.stamps - rec.stamps[0]) / 1e9

    def truth_at(imu_stamps):
        path = (imu_stamps - rec.stamps[0]) / 1e9 + lag
        return np.stack([np.interp(path, t, centre[:, a]) for a in range(3)], axis=1)

    inner = slice(5, -5)
    at_outputs = np.sqrt(np.mean((out["field"] - truth_at(out["stamps"]))[inner] ** 2, axis=0))
    assert np.all(at_outputs < 2 * NT), at_outputs / NT
    as_stamped = np.sqrt(np.mean((out["field"] - truth_at(rec.stamps))[inner] ** 2, axis=0))
    assert np.all(as_stamped > 100 * NT), as_stamped / NT


def test_mounting_and_field_direction_within_three_sigma_of_truth(tumble):
    spec, _, truth, sim, result = tumble
    report = result.extras["imu"]
    true_rpy = ab.roll_pitch_yaw(_gauge_mounting(truth.calibration, sim.imu.mounting))
    for name, value in zip(("roll", "pitch", "yaw"), true_rpy):
        q = report.by_name(f"array to IMU {name}")
        assert 0 < q.sigma < 0.01, q
        assert abs(q.value - value) < 3 * q.sigma + 1e-4, (q, value)
    # declination and inclination of the simulated Earth field (ENU world of the IMU)
    for name, value in (("declination", spec.declination), ("inclination", spec.inclination)):
        q = report.by_name(f"field {name}")
        assert abs(q.value - value) < 3 * q.sigma + 1e-4, (q, value)
    assert "array to IMU: roll" in result.summary()
    assert result.calibration.metadata["imu"]["sigma"]["array_to_imu_roll_deg"] == pytest.approx(
        report.by_name("array to IMU roll").sigma)
    # the sensors' own analysis is unchanged in kind: still whole-sphere
    assert result.envelope.whole_sphere


def test_site_gradient_is_modelled_not_calibration_error():
    spec = SimulationSpec(count=380, schedule="tumble", seed=12, noise=NOISE, imu=True, imu_mounting=MOUNTING,
                          imu_orientation_noise=0.02, world_gradient=GRADIENT_NED)
    rec, truth, sim = run(spec)
    result = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=rec.imu)
    fresh, _, _ = run(SimulationSpec(count=600, schedule="random", seed=spec.seed, noise=NOISE))
    out = result.calibration.outputs(fresh.vectors)
    assert np.max(tmi_rms(out.vectors, spec.intensity)) < 1.2 * NOISE
    assert tensor_rms(out.tensor) < 1.2 * FLOOR
    g = NED_TO_ENU @ sim.world_gradient @ NED_TO_ENU.T
    report = result.extras["imu"]
    for name, value in zip(ab.GRADIENT_NAMES, ab.gradient_params(g) / NT):
        q = report.by_name(f"site gradient {name}")
        assert abs(q.value - value) < max(3 * q.sigma, 0.05), (q, value)
        assert q.sigma < 1.0
    # Without the IMU the same recording cannot separate the gradient from the calibration:
    # accepted anyway, it becomes calibration error on the fresh attitudes.
    plain = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps,
                            options=SolveOptions(max_residual=100 * NT))
    worse = plain.calibration.outputs(fresh.vectors)
    assert tensor_rms(worse.tensor) > 1.5 * FLOOR


def test_near_iron_the_cli_fits_the_site_gradient_and_holds_away_from_it(tmp_path):
    """Issue 37 item 5 through ``magcal``: 2,000 sets of a smooth 10 Hz tumble 4 m from a magnetic object (a
    ~40 nT/m site gradient), orientation and gyro columns: accepted with the gradient fitted (each entry within
    3 sigma of the truth), and on fresh attitudes of the same sensors in a uniform field the corrected tensor is
    within 1.2x the floor sqrt(2) sigma / d and the TMI within 1.2x the noise."""
    from test_offline import magcal, ok, read_corrected

    from magcal_ros.io import calibration_file as calfile
    from magcal_ros.io.truth_file import load_truth

    near, fresh = tmp_path / "near.csv", tmp_path / "fresh.csv"
    ok(magcal("simulate", near, "--schedule", "tumble", "--count", 2000, "--rate", 10, "--seed", 5, "--imu",
              "--imu-mounting", "2,-1.5,3", "--imu-orientation-noise", 0.02, "--world-gradient",
              ",".join(str(g) for g in GRADIENT_NED)))
    proc = ok(magcal("calibrate", near, "-o", tmp_path / "cal.yaml", "--reference-field", 5.5e-5))
    assert "not uniform" not in proc.stdout + proc.stderr
    values, sigma = (calfile.read(tmp_path / "cal.yaml").metadata["imu"][k] for k in ("values", "sigma"))
    g = np.array([[30, 10, -15], [10, -20, 5], [-15, 5, -10]], dtype=float)  # nT/m NED
    want = ab.gradient_params(NED_TO_ENU @ g @ NED_TO_ENU.T)
    for name, value in zip(ab.GRADIENT_NAMES, want):
        key = f"site_gradient_{name}_nT_per_m"
        assert abs(values[key] - value) < max(3 * sigma[key], 0.05), (name, values[key], value, sigma[key])
    ok(magcal("simulate", fresh, "--count", 600, "--seed", 5))  # the same sensors, random attitudes, uniform
    ok(magcal("correct", fresh, "-c", tmp_path / "cal.yaml", "-o", tmp_path / "out.csv"))
    out, truth = read_corrected(tmp_path / "out.csv"), load_truth(fresh)
    floor = tensor_floor(float(truth["noise"]) if "noise" in truth else NOISE, 0.4)
    assert tensor_rms(out["gradient"]) < 1.2 * floor, tensor_rms(out["gradient"]) / floor
    assert rms(np.linalg.norm(out["field"], axis=1) - 5.5e-5) < 1.2 * NOISE / 2


@pytest.mark.parametrize("source", ["orientation", "gyro"])
def test_a_long_recording_with_the_imu_is_solved_on_a_subset(source):
    """6,000 tumbling sets at 50 Hz with the IMU: the expensive stages run on a subset as without it (the
    gyro's attitudes integrated over every set, then the subset's taken), and on fresh attitudes the
    outputs in the IMU frame are at the noise: vectors within 2 nT per axis of the truth, TMI within 1.2x the
    noise, tensor within 1.2x the floor."""
    spec = SimulationSpec(count=6000, schedule="tumble", seed=13, noise=NOISE, rate=50.0, imu=True,
                          imu_mounting=MOUNTING, imu_orientation_noise=0.02)
    rec, _, sim = run(spec)
    imu = rec.imu if source == "orientation" else ImuSamples(np.full((6000, 4), np.nan), rec.imu.angular_velocity,
                                                                rec.imu.frame_id)
    result = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=imu)
    assert "solved on 4000 of 6000 sets" in result.summary()
    assert result.extras["imu"].source == source
    fresh, truth, _ = _fresh(spec.seed)
    out = result.calibration.outputs(fresh.vectors)
    per_axis = rms(out.vectors - np.einsum("ab,nsb->nsa", sim.imu.mounting, truth.field))
    # the gyro alone (its integrated error, 0.18 deg here) gives the mounting to 0.02 deg (1-sigma), 20 nT at 55 uT;
    # with every set instead of the subset it is the same (19 nT)
    assert per_axis < (2 * NT if source == "orientation" else 40 * NT), per_axis / NT
    assert np.max(tmi_rms(out.vectors, spec.intensity)) < 1.2 * NOISE
    assert tensor_rms(out.tensor) < 1.2 * FLOOR


def test_gyro_alone_turns_a_refused_yaw_manoeuvre_into_a_calibration():
    """Yaw circles with +-5 deg of wobble, gyro only (no orientation): without the IMU scale z and
    offset z are undetermined (refused); the gyro's relative rotations tie the sets' directions
    together and the calibration holds within an envelope wider than the wobble."""
    spec = SimulationSpec(count=390, schedule="sea", pitch=0.0, roll=0.0, wobble=5.0, turns=2.0, seed=13,
                          noise=NOISE, imu=True, imu_mounting=MOUNTING, imu_gyro_noise=1e-4)
    rec, truth, sim = run(spec)
    with pytest.raises(ObservabilityError, match="scale z"):
        calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps)
    gyro = ImuSamples(np.full((len(rec), 4), np.nan), rec.imu.angular_velocity, rec.imu.frame_id)
    with_gyro = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=gyro)
    report = with_gyro.extras["imu"]
    assert report.source == "gyro" and report.segments == 1
    assert with_gyro.envelope.pitch_deg > 5.0 and with_gyro.envelope.roll_deg > 5.0
    assert with_gyro.envelope.ratio_sphere < 30.0
    true_rpy = ab.roll_pitch_yaw(_gauge_mounting(truth.calibration, sim.imu.mounting))
    for name, value in zip(("roll", "pitch", "yaw"), true_rpy):
        q = report.by_name(f"array to IMU {name}")
        # the gyro's integrated error wanders: the stated 1-sigma is a lower bound, 0.01 deg beside it
        assert abs(q.value - value) < 3 * q.sigma + 0.01, (q, value)
    assert with_gyro.calibration.frame_id == "imu_link"


def test_without_an_imu_nothing_changes(tumble):
    spec, rec, _, sim, _ = tumble
    plain = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps)
    blind = calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps,
                            imu=ImuSamples.unknown(len(rec), "imu_link"))
    for res in (plain, blind):
        assert not res.calibration.rotated and res.calibration.frame_id is None
        assert "imu" not in res.calibration.metadata and "array to IMU" not in res.summary()
    assert np.array_equal(plain.calibration.matrices, blind.calibration.matrices)
    assert np.array_equal(plain.calibration.offsets, blind.calibration.offsets)


# -- the blocks' pieces -------------------------------------------------------------------------------
def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.stack([ab.rotation_of(v) for v in rng.normal(0, 1.5, (n, 3))])


def test_closed_form_start_recovers_mounting_and_field_from_exact_directions():
    rng = np.random.default_rng(1)
    q = _random_rotations(rng, 50)
    a = ab.rotation_of(np.radians([2.0, -1.0, 93.0]))  # far from the identity: an IMU mounted sideways
    f = np.array([0.1, 0.5, -0.86])
    f /= np.linalg.norm(f)
    d = np.einsum("ba,ncb,c->na", a, q, f)  # A^T Q^T f
    att = ab.AttitudeInputs(q, np.zeros(50, np.int64), 1, True)
    state = ab.initial_state(att, d)
    assert np.allclose(state.mounting, a, atol=1e-9)
    assert np.allclose(state.fields[0], f, atol=1e-9)
    assert np.allclose(ab.attitude_residuals(att, state, d), 0.0, atol=1e-9)


def test_gyro_integration_follows_a_constant_turn():
    w = np.array([0.05, -0.02, 0.3])  # rad/s, IMU frame
    t = np.arange(40) * 0.1
    rot, groups, count = ab.gyro_attitudes(np.tile(w, (40, 1)), t)
    assert count == 1 and np.all(groups == 0)
    for k in (1, 17, 39):
        assert np.allclose(rot[k], ab.rotation_of(w * t[k]), atol=1e-12)
    # a gap splits the integration: two segments, each from its own first set
    t2 = np.concatenate([t[:20], t[20:] + 5.0])
    _, groups2, count2 = ab.gyro_attitudes(np.tile(w, (40, 1)), t2)
    assert count2 == 2 and np.all(groups2[:20] == 0) and np.all(groups2[20:] == 1)


def _finite_difference(fun, state: ab.GlobalState, model, size: int) -> np.ndarray:
    cols = []
    for j in range(size):
        step = np.zeros(size)
        step[j] = 1e-7
        cols.append((fun(state.moved(step, model)) - fun(state.moved(-step, model))) / 2e-7)
    return np.stack(cols, axis=-1)


def test_jacobians_of_the_global_blocks_match_finite_differences():
    rng = np.random.default_rng(2)
    n = 6
    q = _random_rotations(rng, n)
    positions = rng.normal(0, 0.2, (4, 3))
    att = ab.AttitudeInputs(q, np.array([0, 0, 0, 0, -1, 0]), 1, True, positions)
    model = att.model(4)
    state = ab.GlobalState(ab.rotation_of([0.03, -0.04, 1.2]), np.array([[0.2, 0.6, -0.77]]) / 1.0016,
                           ab.gradient_matrix([3e-4, 1e-4, -2e-4, 5e-4, 1e-4]))
    state = ab.GlobalState(state.mounting, state.fields / np.linalg.norm(state.fields), state.gradient)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = model.global_size
    num = _finite_difference(lambda s: ab.attitude_residuals(att, s, d), state, model, g)
    assert np.allclose(ab.attitude_jacobian(att, state, model), num, atol=1e-6)
    num_h = _finite_difference(lambda s: ab.gradient_field(att, s), state, model, g)
    assert np.allclose(ab.gradient_jacobian(att, state, model), num_h, atol=1e-9)
    assert np.all(ab.gradient_field(att, state)[4] == 0)  # a set without attitude sees none


def test_the_array_lag_turns_the_attitude_back_and_its_jacobian_matches_finite_differences():
    """With the IMU's angular velocity the attitude at a set's stamp ``t`` is turned back to ``t - lag``:
    ``Q(t - lag)^T f`` for a constant rate is exactly ``exp(lag [w]x) Q(t)^T f``; every global block's
    Jacobian (mounting, field, gradient, lag) matches finite differences at a non-zero lag."""
    rng = np.random.default_rng(5)
    n = 7
    q = _random_rotations(rng, n)
    rates = rng.normal(0.0, 0.8, (n, 3))
    rates[5] = 0.0  # a set without a rate: the lag does not move it
    att = ab.AttitudeInputs(q, np.array([0, 0, 0, 0, -1, 0, 0]), 1, True, rng.normal(0, 0.2, (4, 3)), rates=rates)
    model = att.model(4)
    assert model.array_lag and model.global_blocks[-1] == "array lag" and model.array_lag_index == model.global_size - 1
    fields = np.array([[0.2, 0.6, -0.77]])
    state = ab.GlobalState(ab.rotation_of([0.03, -0.04, 1.2]), fields / np.linalg.norm(fields),
                           ab.gradient_matrix([3e-4, 1e-4, -2e-4, 5e-4, 1e-4]), lag=0.012)
    # the truth: the IMU turning at w from Q(t - lag): Q(t) = Q(t - lag) exp(lag [w]x)
    earlier = np.einsum("nab,nbc->nac", q, np.stack([ab.rotation_of(-0.012 * w) for w in rates]))
    u_true = np.einsum("nji,j->ni", earlier, state.fields[0])
    u = ab.reference_field(att, state)
    known = att.known
    assert np.allclose(u[known], u_true[known], atol=1e-12) and np.all(u[~known] == 0)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = model.global_size
    num = _finite_difference(lambda s: ab.attitude_residuals(att, s, d), state, model, g)
    assert np.allclose(ab.attitude_jacobian(att, state, model), num, atol=1e-6)
    assert np.abs(num[:, :, -1]).max() > 0.1  # the lag column is not zero
    num_h = _finite_difference(lambda s: ab.gradient_field(att, s), state, model, g)
    assert np.allclose(ab.gradient_jacobian(att, state, model), num_h, atol=1e-9)


def test_site_gradient_field_is_the_world_gradient_at_each_sensor():
    """``R^T G R p`` is the world field change ``G^T (R p)`` seen in the array frame (``G[i, j] = dB_j/dx_i``)."""
    rng = np.random.default_rng(3)
    q = _random_rotations(rng, 3)
    a = ab.rotation_of([0.02, 0.01, -0.03])
    gw = ab.gradient_matrix([3e-4, 1e-4, -2e-4, 5e-4, 1e-4])
    p = rng.normal(0, 0.2, (4, 3))
    att = ab.AttitudeInputs(q, np.zeros(3, np.int64), 1, True, p)
    h = ab.gradient_field(att, ab.GlobalState(a, np.array([[0.0, 1.0, 0.0]]), gw))
    for k in range(3):
        ra = q[k] @ a  # array -> world
        world = (ra @ p.T).T @ gw  # B_j = sum_i x_i G_ij at x = R p
        assert np.allclose(h[k], world @ ra, atol=1e-15)  # back into the array frame: R^T B


def test_quaternion_orientation_enters_as_imu_to_world():
    """The IMU's quaternion is IMU -> world ENU: the blocks see ``Q = R(q)`` (not its transpose)."""
    rng = np.random.default_rng(4)
    q = _random_rotations(rng, 20)
    att = ab.attitude_inputs(matrix_to_quat(q), np.full((20, 3), np.nan), np.arange(20) * 10**8, None, False)
    assert att is not None and att.world
    assert np.allclose(att.rotations, q, atol=1e-12)


def test_an_imu_that_does_not_turn_with_the_readings_is_refused_in_words(tumble):
    """Every orientation the identity (a frozen IMU, or another vehicle's) while the readings tumble: the
    solve ended in "solution rejected: covariances must be positive semi-definite"; now the refusal
    says what is wrong. The IMU of the same tumble (turning with it) still calibrates (the fixture)."""
    from magcal_ros.errors import InputError

    spec, rec, _, sim, result = tumble
    assert result.calibration.rotated
    still = ImuSamples(np.tile([0.0, 0.0, 0.0, 1.0], (len(rec.imu), 1)), rec.imu.angular_velocity, "imu_link")
    with pytest.raises(InputError, match=r"the IMU's orientation turns by 0\.0 deg at most while the readings turn by "
                                         r"\d+ deg: the IMU does not follow the array"):
        calibrate_array(rec.vectors, sim.geometry, spec.intensity, stamps=rec.stamps, imu=still)


LEAVE_OUT_CASES = {
    "tumble, orientation": SimulationSpec(count=2400, schedule="tumble", seed=5, noise=NOISE, rate=50.0, imu=True,
                                          imu_mounting=MOUNTING, imu_orientation_noise=0.02),
    "yaw circles, gyro": SimulationSpec(count=2400, schedule="sea", pitch=0.0, roll=0.0, wobble=5.0, turns=2.0, seed=5,
                                        noise=NOISE, rate=50.0, imu=True, imu_mounting=MOUNTING, imu_gyro_noise=1e-4),
}


def _jackknife_variance(estimates: np.ndarray) -> np.ndarray:
    """Delete-one-block jackknife variance of each parameter from the K blocks' estimates (K, P)."""
    k = len(estimates)
    return (k - 1) / k * np.sum((estimates - estimates.mean(axis=0)) ** 2, axis=0)


@pytest.mark.parametrize("case", list(LEAVE_OUT_CASES))
def test_the_leave_out_step_with_the_imu_gives_the_jackknife_of_full_refits(case):
    """The block jackknife's one-step refits with the IMU's global blocks (the sensors' and the global
    parameters stepped together from the solution) against full refits without each of eight time blocks,
    with slowly correlated noise (AR(1) 0.99, 3 nT) beside the white 1 nT. What the calibration uses is each
    parameter's jackknife variance: per parameter the one-step's over the refits' is 0.99-1.0 in the median
    and above 0.7 for nine in ten (stepping the sensors' parameters alone, the globals held: 0.80 and 0.10
    on the yaw circles, whose vertical axis only the gyro determines)."""
    from magcal_ros.core.array_fit import fit_array, fix_rotation_gauge, leave_out_estimates
    from magcal_ros.core.uncertainty import centre_gauge_constraints

    spec = LEAVE_OUT_CASES[case]
    rec, truth, _ = run(spec)
    rng = np.random.default_rng(5)
    drift = np.zeros(rec.vectors.shape)
    kicks = rng.normal(size=rec.vectors.shape) * 3 * NT * np.sqrt(1 - 0.99**2)
    for k in range(1, len(drift)):
        drift[k] = 0.99 * drift[k - 1] + kicks[k]
    raw = rec.vectors + drift
    q = rec.imu.orientation if spec.schedule == "tumble" else np.full((len(raw), 4), np.nan)
    att = ab.attitude_inputs(q, rec.imu.angular_velocity, rec.stamps, None, False)
    assert att is not None and att.world == (spec.schedule == "tumble")
    sol = fix_rotation_gauge(fit_array(raw, truth.calibration.matrices, truth.calibration.offsets, spec.intensity,
                                       attitude=att))
    parts = np.array_split(np.arange(len(raw)), 8)
    one_step = leave_out_estimates(sol, raw, parts, gauge=centre_gauge_constraints(sol.w, sol.model.size))
    refits = []
    for part in parts:
        keep = np.setdiff1d(np.arange(len(raw)), part)
        refits.append(fix_rotation_gauge(fit_array(
            raw[keep], sol.matrices, sol.offsets, sol.intensity, None, None, None, sol.weights[keep], robust=False,
            start=sol.theta, attitude=att.take(keep), attitude_start=sol.globals)).theta.reshape(-1))
    full = _jackknife_variance(np.array(refits))
    free = full > 0  # the lag gauge and the frame's gauge do not scatter
    ratio = _jackknife_variance(one_step)[free] / full[free]
    assert 0.85 < np.median(ratio) < 1.15 and np.percentile(ratio, 10) > 0.5, \
        (np.median(ratio), np.percentile(ratio, [10, 90]))


@pytest.mark.parametrize("with_imu", [True, False])
def test_the_parts_shares_the_fit_keeps_are_each_parts_own_evaluation(with_imu):
    """A fit given the jackknife's parts keeps each part's share of the normal equations from its last
    evaluation (every set's); each is what an evaluation of the part's sets alone gives (the solution's
    attitudes' weights included), the shares add up to the whole, the rotation gauge maps them, and the
    leave-out estimates from them are those computed afresh (without the shares), to rounding."""
    from dataclasses import replace

    from magcal_ros.core import array_fit as af
    from magcal_ros.core.uncertainty import centre_gauge_constraints

    spec = LEAVE_OUT_CASES["tumble, orientation"]
    rec, truth, _ = run(spec)
    att = ab.attitude_inputs(rec.imu.orientation, rec.imu.angular_velocity, rec.stamps, None, False) \
        if with_imu else None
    parts = [np.sort(p) for p in np.array_split(np.random.default_rng(2).permutation(len(rec.vectors)), 8)]
    sol = af.fit_array(rec.vectors, truth.calibration.matrices, truth.calibration.offsets, spec.intensity,
                       attitude=att, parts=parts)
    sums = sol.part_sums
    assert sums is not None and sums.matches(parts) and not sums.matches(parts[::-1])
    whole = sol.information if att is None else sol.full_information
    scale = np.abs(whole).max()
    assert np.abs(sums.information.sum(axis=0) - whole).max() < 1e-9 * scale
    glob = af._solution_globals(sol)
    f = sol.intensity
    # the whole information (summed from the parts where they hold every set once) is an evaluation of every set;
    # parts that leave a set out leave it in the whole
    every = af._Eval(sol.model, sol.theta, sol.directions, rec.vectors / f, af.SetInputs(np.zeros((len(rec.vectors), 0))),
                     None, sol.weights, sol.sigma / f, glob).information()
    assert np.abs(whole - every).max() < 1e-9 * scale
    short = af.fit_array(rec.vectors, truth.calibration.matrices, truth.calibration.offsets, spec.intensity,
                         attitude=att, parts=parts[1:])
    short_whole = short.information if att is None else short.full_information
    assert np.abs(short_whole - whole).max() < 1e-6 * scale
    for idx in (parts[0], parts[5]):
        ev = af._Eval(sol.model, sol.theta, sol.directions[idx], rec.vectors[idx] / f, af.SetInputs(np.zeros((len(idx), 0))),
                      None, sol.weights[idx], sol.sigma / f, None if glob is None else glob.take(idx))
        k = next(i for i, p in enumerate(parts) if p is idx)
        assert np.abs(sums.information[k] - ev.information()).max() < 1e-9 * scale
        assert np.allclose(sums.scores[k], ev.scores().sum(axis=0), rtol=1e-7, atol=1e-9 * np.abs(sums.scores).max())
    turned = af.fix_rotation_gauge(sol)
    gauge = centre_gauge_constraints(turned.w, turned.model.size)
    kept = af.leave_out_estimates(turned, rec.vectors, parts, gauge=gauge)
    fresh = af.leave_out_estimates(replace(turned, part_sums=None), rec.vectors, parts, gauge=gauge)
    moved = np.abs(kept - turned.theta.reshape(-1)).max()  # what leaving a part out moves the parameters by
    assert np.abs(kept - fresh).max() < 1e-4 * moved, (np.abs(kept - fresh).max(), moved)


def test_an_imu_about_as_good_as_the_sensors_leaves_every_noise_estimate_unbiased():
    """An IMU whose attitude error (0.0005 deg per axis, 8.7e-6 rad) is of the order of the four sensors' direction
    noise (1 nT in 55,000 nT, 1.8e-5 rad each): each set's direction is then fitted partly from the attitude, and
    the attitude residuals keep only their share of the degrees of freedom. Read for 2 dof, the attitude's error
    came out small, the IMU was trusted more, down to the floor (5.7e-5 deg), and the sensors' noise absorbed its
    error (1.16 nT against 1)."""
    truth_deg = 0.0005
    rec, _, sim = run(SimulationSpec(count=3000, schedule="tumble", seed=5, noise=NT, rate=50.0, intensity=5.5e-5,
                                     imu=True, imu_mounting=(2.0, -1.5, 3.0), imu_orientation_noise=truth_deg))
    res = calibrate_array(rec.vectors, sim.geometry, 5.5e-5, stamps=rec.stamps,
                          imu=ImuSamples(rec.imu.orientation, rec.imu.angular_velocity, "imu_link"))
    noise = np.asarray(res.noise) / NT
    assert np.all(np.abs(noise - 1.0) < 0.05), noise
    attitude = res.extras["imu"].attitude_sigma_deg
    assert 0.7 * truth_deg < attitude < 1.5 * truth_deg, attitude


YAW_MOUNTING = (2.0, -2.5, 3.0)
"""deg: the array-to-IMU rotation of the one-yaw-turn recalibrations."""


def _tumble_calibration():
    """The calibration a tumble with the IMU gives (0.002 deg attitudes; the rotation to 0.06 mdeg)."""
    rich = SimulationSpec(count=2400, schedule="tumble", seed=21, noise=NOISE, imu=True, imu_mounting=YAW_MOUNTING,
                          imu_orientation_noise=0.002, rate=50.0)
    rec, _, sim = run(rich)
    return calibrate_array(rec.vectors, sim.geometry, rich.intensity, stamps=rec.stamps, imu=rec.imu).calibration


def _one_yaw_turn(orientation_noise: float = 0.002):
    """(spec, recording, simulation) of a minute of one yaw turn (+-5 deg of wobble) at 20 Hz with the IMU."""
    turn = SimulationSpec(count=1200, schedule="sea", pitch=0.0, roll=0.0, wobble=5.0, turns=1.0, seed=21, noise=NOISE,
                          imu=True, imu_mounting=YAW_MOUNTING, imu_orientation_noise=orientation_noise, rate=20.0)
    rec, _, sim = run(turn)
    return turn, rec, sim


def _imu_frame_error(calibration) -> float:
    """RMS per axis (T) of the centre field's error in the IMU frame on fresh random attitudes against the truth."""
    fresh, truth, sim = run(SimulationSpec(count=600, schedule="random", seed=21, noise=NOISE, imu=True,
                                           imu_mounting=YAW_MOUNTING))
    true_centre = np.einsum("ab,nsb->nsa", sim.imu.mounting, truth.field).mean(axis=1)
    return float(rms(calibration.outputs(fresh.vectors).vectors.mean(axis=1) - true_centre))


def test_a_recalibration_from_a_short_yaw_turn_keeps_the_running_calibrations_mounting():
    """A minute of one yaw turn (+-5 deg of wobble) leaves the array-to-IMU rotation's yaw nearly free (it trades
    with the field's declination): recalibrated from it with the weak prior on the mounting, the centre field in the
    IMU frame was 1.5x its floor on fresh attitudes. The mount is rigid: the running calibration's rotation (from a
    tumble with the IMU, 0.06 mdeg) is the mounting's prior, and the field stays at the floor."""
    running = _tumble_calibration()
    assert running.metadata["imu"]["sigma"]["array_to_imu_yaw_deg"] < 1e-4
    turn, rec, sim = _one_yaw_turn()
    recal = calibrate_array(rec.vectors, sim.geometry, turn.intensity, stamps=rec.stamps, imu=rec.imu,
                            prior=running).calibration
    error = _imu_frame_error(recal)
    assert error < 1.15 * NOISE / 2, error / (NOISE / 2)  # the mean of four sensors' 1 nT noise: 0.5 nT per axis


def _smooth_attitude_error(count: int, mdeg: float, seed: int) -> np.ndarray:
    """(count, 3, 3) rotations of a random walk smoothed over 200 sets (10 s at 20 Hz), ``mdeg`` RMS per axis: an
    IMU's slowly wandering attitude error."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(size=(count, 3)), axis=0)
    smooth = np.column_stack([np.convolve(walk[:, i] - walk[:, i].mean(), np.ones(200) / 200, mode="same")
                              for i in range(3)])
    smooth *= np.radians(mdeg * 1e-3) / smooth.std()
    return np.stack([ab.rotation_of(v) for v in smooth])


def test_an_imu_whose_error_is_smooth_in_time_does_not_outweigh_what_else_is_known():
    """An IMU's attitude error is smooth in time (its slow wander; a sample interpolated between the IMU's): here
    1 mdeg RMS, correlated over about 10 s. Weighed as independent, a minute of it outweighed the running
    calibration's mounting and what the sensors say: recalibrated from one yaw turn, the centre field in the IMU
    frame came out 2.8-5.4x its floor on fresh attitudes (the mount moved 0.02-0.07 mdeg, the rest of the error
    went into the other blocks). Each attitude is weighed by the information the residuals' time correlation
    leaves (their long-run variance over their variance): 1.05-1.11x."""
    from magcal_ros.core.imu import quat_to_matrix

    running = _tumble_calibration()
    turn, rec, sim = _one_yaw_turn(orientation_noise=0.0)
    wander = _smooth_attitude_error(len(rec.imu.orientation), 1.0, 21)
    imu = replace(rec.imu, orientation=matrix_to_quat(quat_to_matrix(rec.imu.orientation) @ wander))
    recal = calibrate_array(rec.vectors, sim.geometry, turn.intensity, stamps=rec.stamps, imu=imu, prior=running)
    error = _imu_frame_error(recal.calibration)
    assert error < 1.2 * NOISE / 2, error / (NOISE / 2)  # the mean of four sensors' 1 nT noise: 0.5 nT per axis


def test_the_running_calibration_lends_its_files_mounting_sigma_to_the_recalibration(tmp_path):
    """A correction node's parameters carry the array-to-IMU rotation but not how well it is known: the calibration
    node's `prior: running` had the weak prior on the mounting (one yaw turn after a tumble's calibration: the
    centre field in the IMU frame 1.5x its floor). The calibration file the node saved (or started from) holds the
    running rotation's 1-sigma: taken when its rotation is the running one, the recalibration keeps the mount
    (1.05x); a file of another rotation lends nothing."""
    from magcal_ros.io import calibration_file as calfile
    from magcal_ros.methods.attitude import MOUNTING_KEYS, with_saved_imu
    from magcal_ros.nodes import common

    tumble = _tumble_calibration()
    path = tmp_path / "calibration.yaml"
    calfile.write(path, tumble)
    values: dict = {}
    for key, value in tumble.to_parameters().items():  # as the correction node holds them: dotted names
        values.update({f"{key}.{k}": v for k, v in value.items()} if isinstance(value, dict) else {key: value})
    running, why = common.running_calibration(values, tumble.geometry)
    assert why == "" and "imu" not in running.metadata
    lent = with_saved_imu(running, calfile.read(path))
    assert lent.metadata["imu"]["sigma"] == tumble.metadata["imu"]["sigma"]
    assert max(lent.metadata["imu"]["sigma"][k] for k in MOUNTING_KEYS) < 1e-4  # deg: 0.06 mdeg
    turned = replace(tumble, output_rotation=ab.rotation_of(np.array([0.0, 0.0, 1e-4])) @ tumble.output_rotation)
    assert "imu" not in with_saved_imu(running, turned).metadata
    turn, rec, sim = _one_yaw_turn()
    recal = calibrate_array(rec.vectors, sim.geometry, turn.intensity, stamps=rec.stamps, imu=rec.imu,
                            prior=lent).calibration
    error = _imu_frame_error(recal)
    assert error < 1.15 * NOISE / 2, error / (NOISE / 2)


def test_the_first_robust_round_does_not_lean_on_the_imu_for_what_the_start_left_unmodelled(monkeypatch):
    """20,000 sets of a tumble with the IMU and a temperature ramp (the start, without temperature terms, leaves 3-11 nT):
    against that the IMU's attitudes would take several per cent of each set's direction in the first robust
    round and pull the directions toward the IMU's 0.02 deg error, leaving residuals 1.2x the noise. With
    their share held to 1 % there, the first round's noise estimate is within 10 % of the true 1 nT and the
    next round starts from the right weights (planted: no cap, 1.22 nT)."""
    from magcal_ros.core import array_fit

    rec, _, sim = run(SimulationSpec(count=20000, schedule="tumble", seed=3, noise=1 * NT, rate=50.0,
                                     intensity=55_000 * NT, imu=True, imu_mounting=(2.0, -1.5, 3.0),
                                     imu_orientation_noise=0.02, temperature_ramp=(5.0, 25.0),
                                     tempco_offset=0.5e-9, tempco_gain=30e-6))
    seen: list[tuple[int, np.ndarray]] = []
    robust_sigma = array_fit._robust_sigma

    def recorded(e, weights, dof):  # type: ignore[no-untyped-def]
        out = robust_sigma(e, weights, dof)
        seen.append((len(e), out * 55_000 * NT))
        return out

    monkeypatch.setattr(array_fit, "_robust_sigma", recorded)
    res = calibrate_array(rec.vectors, sim.geometry, 55_000 * NT, stamps=rec.stamps, temperatures=rec.temperatures,
                          imu=ImuSamples(rec.imu.orientation, rec.imu.angular_velocity, "imu_link"))
    start, first = [sigma for n, sigma in seen if n == seen[0][0]][:2]  # the robust fit's start, its first round
    assert np.all(start > 3 * NT)  # what the start left unmodelled
    assert np.all(first < 1.1 * NT), first / NT
    assert np.max(res.tmi_after) < 1.05 * NT


def test_the_first_robust_round_weighs_anew_once_its_first_step_took_up_what_the_start_left_unmodelled(monkeypatch):
    """The same tumble with a payload's current too (the start's residuals 14-28 nT against 1 nT of noise): the
    first step of the first robust round takes up the temperature and the current, the round then goes on at
    the noise its residuals show there (the sensors alike, the IMU by its own residuals) and the fit needs no
    second round: three evaluations of the model in all (the start's, the re-weighed point's, the final one),
    the noise found within 5 % of the true 1 nT, the TMI at the noise. Planted: no re-weighing inside the
    round, a second round and four evaluations."""
    from magcal_ros.core import array_fit

    rec, _, sim = run(SimulationSpec(count=20000, schedule="tumble", seed=3, noise=1 * NT, rate=50.0,
                                     intensity=55_000 * NT, imu=True, imu_mounting=(2.0, -1.5, 3.0),
                                     imu_orientation_noise=0.02, temperature_ramp=(5.0, 25.0),
                                     tempco_offset=0.5e-9, tempco_gain=30e-6,
                                     thrusters=((-0.7, 0.25, 0.1, 0.0, 0.0, 0.05),)))
    evaluations: list[int] = []
    evaluation = array_fit._Eval.__init__

    def counted(self, model, theta, d, x, *args, **kwargs):  # type: ignore[no-untyped-def]
        evaluations.append(len(x))
        evaluation(self, model, theta, d, x, *args, **kwargs)

    monkeypatch.setattr(array_fit._Eval, "__init__", counted)
    res = calibrate_array(rec.vectors, sim.geometry, 55_000 * NT, stamps=rec.stamps, temperatures=rec.temperatures,
                          currents=rec.currents, channels=rec.channels,
                          imu=ImuSamples(rec.imu.orientation, rec.imu.angular_velocity, "imu_link"))
    assert evaluations == [evaluations[0]] * 3, evaluations  # one fit on the subset, no pass over every set
    assert np.all(np.abs(res.noise / NT - 1.0) < 0.05), res.noise / NT
    assert np.max(res.tmi_after) < 1.05 * NT, res.tmi_after / NT

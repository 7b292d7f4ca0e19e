"""The sensors' temperatures and the vehicle's IMU: inputs, matching, application and simulation, against truth.

Every expected value comes from the simulator's truth or from a few lines of the test's own
numpy (the correction formula, a rotation at constant angular velocity), never from the code
under test run on the same data.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_offline import bag_messages, magcal, ok, read_corrected

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import (
    NED_TO_ENU,
    ImuStats,
    ImuStream,
    LatestImu,
    match_imu,
    ned_to_enu,
    quat_to_matrix,
)
from magcal_ros.core.interference import CurrentSamples, match_currents
from magcal_ros.core.side_streams import TEMPERATURE
from magcal_ros.core.matching import accept_streams, LatestValues, MatchStats, match_latest
from magcal_ros.core.recording import ImuSamples, Recording
from magcal_ros.core.temperature import TemperatureSamples, TemperatureStats
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import cdr
from magcal_ros.io.bag_writer import BagSink
from magcal_ros.io.csv_recording import parse_columns, read_csv, write_csv
from magcal_ros.io.recordings import open_recording, with_bag_imu, with_bag_temperatures
from magcal_ros.io.truth_file import load_truth
from magcal_ros.nodes.buffer import SetBuffer, collected_recording
from magcal_ros.sim.spec import SimulationSpec, run

MS = 1_000_000
S = 1_000_000_000
NAMES = ("mag1", "mag2", "mag3", "mag4")
MOUNTING_DEG = (2.0, -1.5, 3.0)  # roll, pitch, yaw of the IMU off the array


def angle_deg(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Angle (deg) between rotations given as quaternions x, y, z, w (the test's own scipy)."""
    return np.degrees((Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude())


def mounting_matrix() -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll) of MOUNTING_DEG (scipy's intrinsic ZYX)."""
    roll, pitch, yaw = MOUNTING_DEG
    return Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()


def expected_correction(cal: ArrayCalibration, raw: np.ndarray, temps: np.ndarray, currents: np.ndarray | None = None,
                        ) -> np.ndarray:
    """The contract's formula written out: R [(M + dT Mt)(r - o - dT ot) - D u], sensor by sensor."""
    out = np.empty_like(raw)
    for k in range(raw.shape[0]):
        for i in range(raw.shape[1]):
            dt = temps[k, i] - cal.temperature_reference
            b = (cal.matrices[i] + dt * cal.matrix_tempco[i]) @ (raw[k, i] - cal.offsets[i] - dt * cal.offset_tempco[i])
            if currents is not None:
                b = b - cal.interference[i] @ currents[k]
            out[k, i] = cal.output_rotation @ b
    return out


# -- Recording -----------------------------------------------------------------------------------
def test_recording_keeps_temperatures_and_imu_with_their_sets() -> None:
    n = 6
    rng = np.random.default_rng(0)
    q = Rotation.random(n, random_state=1).as_quat()
    q[2] = np.nan  # orientation unknown at set 2
    w = rng.normal(size=(n, 3))
    temps = np.arange(n * 4, dtype=float).reshape(n, 4)
    rec = Recording(NAMES, np.arange(1, n + 1) * S, rng.normal(0, 3e-5, (n, 4, 3)), ("pump",), np.arange(n.__float__()),
                    temps, ImuSamples(q, w, "imu_link"))
    part = rec.window(2 * S, 5 * S).select(("mag3", "mag1")).take([1, 2])  # sets 2 and 3 (stamps 3, 4 s)
    np.testing.assert_array_equal(part.temperatures, temps[[2, 3]][:, [2, 0]])
    np.testing.assert_array_equal(part.imu.orientation[1], q[3])
    assert np.all(np.isnan(part.imu.orientation[0])) and part.imu.frame_id == "imu_link"
    np.testing.assert_array_equal(part.imu.angular_velocity, w[[2, 3]])
    swapped = rec.with_currents(("a",), np.ones((n, 1)))
    assert swapped.temperatures is rec.temperatures and swapped.imu is rec.imu
    assert rec.select_channels(()).imu is rec.imu
    with pytest.raises(InputError, match="finite temperatures"):
        Recording(NAMES, np.arange(n), np.zeros((n, 4, 3)), temperatures=np.zeros((n, 3)))
    with pytest.raises(InputError, match="not a unit quaternion"):
        ImuSamples(np.tile([0.0, 0.0, 0.0, 2.0], (2, 1)), np.zeros((2, 3)))


# -- the one matching rule -----------------------------------------------------------------------
def test_every_side_stream_follows_the_currents_rule() -> None:
    sets = np.array([1000, 1100, 1200, 1300, 2500]) * MS
    stamps, values = np.array([900, 1000, 1150, 1150, 1250, 1400]) * MS, np.array([1.0, 2.0, 3.0, 4.0, np.nan, 6.0])
    u, fresh_u = match_currents(sets, [CurrentSamples("a", stamps, values)], 500 * MS)
    t, fresh_t = match_latest(sets, [TemperatureSamples("mag1", stamps, values)], 500 * MS)
    np.testing.assert_array_equal(u, t)
    np.testing.assert_array_equal(fresh_u, fresh_t)
    np.testing.assert_array_equal(t[:4, 0], [2.0, 2.0, 4.0, 4.0])  # latest not newer, equal stamps: the later
    np.testing.assert_array_equal(fresh_t[:, 0], [True, True, True, True, False])
    stats = TemperatureStats(("mag1", "mag2"), 10 * S)
    keep = stats.keep(np.array([[True, True], [True, False], [False, False]]))
    np.testing.assert_array_equal(keep, [True, False, False])
    assert stats.describe() == ("2 of 3 sets dropped without a temperature of every sensor within 10 s before the set "
                                "(mag1: 1, mag2: 2)")
    imu_stats = ImuStats(("/imu",), 100 * MS)
    imu_stats.keep(np.array([[True], [False]]))
    assert imu_stats.describe() == "1 of 2 sets dropped without an IMU sample within 0.1 s before the set (/imu: 1)"
    assert isinstance(stats, MatchStats) and isinstance(imu_stats, MatchStats)


def test_live_temperatures_follow_the_offline_rule_whatever_the_stream_holds() -> None:
    """A temperature stream with neighbours swapped, a sample stamped three years ahead and values out of
    range: live (one sample at a time) and offline (the recorded stream) give every set the same value,
    and the sample far ahead costs itself only (later values are used)."""
    rng = np.random.default_rng(4)
    stamps = np.sort(rng.choice(100, 80, replace=False)) * S
    values = rng.uniform(0, 30, 80)
    order = np.arange(80)
    for k in range(0, 78, 7):  # a few neighbours delivered the other way round
        order[[k, k + 1]] = order[[k + 1, k]]
    stamps, values = stamps[order], values[order]
    stamps[40] += 3 * 365 * 86_400 * S  # stamped three years ahead
    values[[10, 60]] = [-300.0, 1e30]
    store = LatestValues(1, 10 * S, keep_ns=1000 * S, check=TEMPERATURE.check)
    for t, v in zip(stamps, values):
        store.add(0, int(t), float(v))
    accepted, counts = accept_streams([TemperatureSamples("a", stamps, values)], TEMPERATURE.check)
    assert store.counts[0] == counts[0]
    assert (counts[0].glitch, counts[0].out_of_range, counts[0].accepted) == (1, 2, 77)
    sets = rng.integers(0, 120, 40) * S + 123
    offline, fresh = match_latest(sets, accepted, 10 * S)
    for t, v, f in zip(sets, offline[:, 0], fresh[:, 0]):
        got, ok_ = store.at(int(t))
        assert ok_ == [bool(f)] and (not f or got[0] == v)
    assert fresh[sets > stamps[41]].any()  # values after the glitch are used


# -- the IMU -------------------------------------------------------------------------------------
def constant_rate_motion(times_s: np.ndarray, w: np.ndarray, r0: Rotation) -> Rotation:
    """R(t) = R0 exp([w t]x): a constant body-frame angular velocity ``w`` (rad/s)."""
    return r0 * Rotation.from_rotvec(np.outer(times_s, w))


def test_imu_is_interpolated_to_the_set_instant_and_propagated_at_the_end() -> None:
    w = np.array([0.3, -0.4, 0.5])  # ~0.7 rad/s, 40 deg/s
    r0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True)
    t_imu = np.arange(0.0, 1.0, 0.01)  # 100 Hz
    stream = ImuStream((t_imu * S).round().astype(np.int64), constant_rate_motion(t_imu, w, r0).as_quat(),
                       np.tile(w, (len(t_imu), 1)), "imu_link")
    t_sets = np.array([0.0031, 0.5, 0.5057, 0.9951, 1.05, 1.2, -0.01])  # inside, on a sample, after the end, stale
    imu, fresh = match_imu((t_sets * S).round().astype(np.int64), stream, 100 * MS)
    np.testing.assert_array_equal(fresh, [True, True, True, True, True, False, False])
    truth = constant_rate_motion(t_sets[:5], w, r0).as_quat()
    # slerp is exact for a constant rate; so is propagation by the angular velocity after the last sample
    assert np.max(angle_deg(imu.orientation[:5], truth)) < 1e-9
    np.testing.assert_allclose(imu.angular_velocity[:5], np.tile(w, (5, 1)), atol=1e-12)
    assert np.all(np.isnan(imu.orientation[5:])) and np.all(np.isnan(imu.angular_velocity[5:]))
    # the latest sample alone would lag by up to one sample interval: 0.4 deg here
    latest = constant_rate_motion(np.floor(t_sets[:4] * 100) / 100, w, r0).as_quat()
    assert np.max(angle_deg(latest, truth[:4])) > 0.2
    # gyro unknown: orientation interpolated between samples, the last one held after them
    no_gyro = ImuStream(stream.stamps, stream.orientation, np.full((len(t_imu), 3), np.nan))
    imu2, _ = match_imu((t_sets[:5] * S).round().astype(np.int64), no_gyro, 100 * MS)
    assert np.max(angle_deg(imu2.orientation[:3], truth[:3])) < 1e-9 and np.all(np.isnan(imu2.angular_velocity))
    assert np.max(angle_deg(imu2.orientation[3:5], constant_rate_motion(t_imu[-1:], w, r0).as_quat())) < 1e-9


def test_live_imu_matches_the_offline_rule_in_any_order_a_topic_delivers() -> None:
    rng = np.random.default_rng(7)
    t_imu = np.sort(rng.uniform(0, 5, 300))
    stream = ImuStream((t_imu * S).astype(np.int64), Rotation.random(300, random_state=2).as_quat(),
                       rng.normal(size=(300, 3)))
    live = LatestImu(50 * MS, keep_ns=100 * S)
    arrival = np.argsort(t_imu + rng.normal(0, 0.03, 300))  # neighbours delivered out of order now and then
    for k in arrival:
        live.add(int(stream.stamps[k]), stream.orientation[k], stream.angular_velocity[k])
    sets = (rng.uniform(-0.2, 5.2, 60) * S).astype(np.int64)
    offline, fresh = match_imu(sets, stream, 50 * MS)
    for k, t in enumerate(sets):
        q, w, f = live.at(int(t))
        assert f == fresh[k]
        if f:
            assert angle_deg(q, offline.orientation[k]) < 1e-9 and np.allclose(w, offline.angular_velocity[k])
    assert live.ready(int(sets[0]), 0) == (live.newest > sets[0])  # waits for the sample after the set
    assert LatestImu(50 * MS).ready(10 * S, 10 * S + 51 * MS)  # or until the tolerance has passed
    # a stream's last set (its IMU sample has its own stamp, nothing newer comes): matched once it waited the
    # tolerance since it arrived, not only when a newer set comes
    last = LatestImu(50 * MS)
    last.add(10 * S, [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.1])
    assert not last.ready(10 * S, 10 * S, waited_ns=49 * MS) and last.ready(10 * S, 10 * S, waited_ns=51 * MS)
    assert last.at(10 * S)[2]


def test_ned_orientation_becomes_enu() -> None:
    # A vehicle level and heading east: in NED (FRD body) its attitude is a yaw of +90 deg; its nose (body x)
    # points east, which is +x in ENU.
    q_ned = Rotation.from_euler("z", 90, degrees=True).as_quat()
    r_enu = quat_to_matrix(ned_to_enu(q_ned))
    np.testing.assert_allclose(r_enu @ [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(r_enu @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], atol=1e-15)  # body down is world down
    np.testing.assert_allclose(NED_TO_ENU @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])  # north is ENU y


# -- application -----------------------------------------------------------------------------------
def thermal_imu_spec(**kw: object) -> SimulationSpec:
    """Four sensors with tempcos, hull iron, an IMU 2-3 deg off the array and a world gradient; no noise."""
    base = dict(schedule="tumble", count=400, seed=3, noise=0.0, temperatures=(2.0, 14.0, 28.0), tempco_offset=0.5e-9,
                tempco_gain=40e-6, hard_iron_sd=300e-9, soft_iron_sd=0.01, imu=True, imu_mounting=MOUNTING_DEG,
                world_gradient=(30e-9, 10e-9, -5e-9, -15e-9, 8e-9), thrusters=((-0.7, 0.25, 0.1, 0.06, 0.0, 0.04),))
    base.update(kw)
    return SimulationSpec(**base)  # type: ignore[arg-type]


def test_the_true_temperature_terms_and_rotation_give_the_true_field() -> None:
    rec, truth, sim = run(thermal_imu_spec())
    cal = truth.calibration
    assert cal.has_temperature_terms and cal.rotated and cal.frame_id == "imu_link"
    np.testing.assert_allclose(cal.output_rotation, mounting_matrix(), atol=1e-15)
    # the formula, written out by the test, applied with the truth's terms gives the true field in the IMU frame
    want = np.einsum("ij,nsj->nsi", mounting_matrix(), truth.field)
    formula = expected_correction(cal, rec.vectors, rec.temperatures, rec.currents)
    assert np.max(np.abs(formula - want)) < 1e-12 * np.max(np.abs(want))
    out = cal.outputs(rec.vectors, "difference", rec.currents, rec.temperatures)
    assert np.max(np.abs(out.vectors - want)) < 1e-12 * np.max(np.abs(want))
    np.testing.assert_allclose(out.centre, want.mean(axis=1), rtol=0, atol=1e-12 * np.max(np.abs(want)))
    # the tensor is formed in the array frame and turned: R G R^T of the truth (a constant world gradient)
    g_want = np.einsum("ij,njk,lk->nil", mounting_matrix(), truth.gradient, mounting_matrix())
    assert np.max(np.abs(out.tensor - g_want)) < 1e-6 * np.max(np.abs(g_want))
    # the temperature terms matter: tens of nT at 28 C without them
    plain = ArrayCalibration(sim.geometry, cal.matrices, cal.offsets, channels=cal.channels,
                             interference=cal.interference, output_rotation=cal.output_rotation)
    assert np.max(np.abs(plain.apply(rec.vectors, rec.currents) - want)) > 5e-9
    with pytest.raises(InputError, match="give the temperatures"):
        cal.apply(rec.vectors, rec.currents)


def test_a_collinear_array_turns_its_baseline_gradient() -> None:
    geo = ArrayGeometry(("a", "b"), np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]))
    rot = mounting_matrix()
    cal = ArrayCalibration(geo, np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)), output_rotation=rot)
    raw = np.array([[[1e-5, 2e-5, 3e-5], [1.1e-5, 2.2e-5, 3.3e-5]]])
    out = cal.outputs(raw)
    np.testing.assert_allclose(out.baseline[0], rot @ ((raw[0, 1] - raw[0, 0]) / 0.5), rtol=1e-14)
    np.testing.assert_allclose(out.vectors[0], raw[0] @ rot.T, rtol=1e-14)


def test_calibration_file_carries_the_terms_and_an_old_file_loads_unchanged(tmp_path: Path) -> None:
    _, truth, _ = run(thermal_imu_spec(count=20))
    cal = truth.calibration
    path = tmp_path / "cal.yaml"
    calfile.write(path, cal)
    text = path.read_text()
    block = calfile.yaml.safe_load(text)["magcal_correction"]["ros__parameters"]
    assert block["temperature_reference"] == 20.0 and block["frame_id"] == "imu_link"
    assert len(block["output_rotation"]) == 9 and len(block["mag2"]["offset_per_kelvin"]) == 3
    assert len(block["mag2"]["matrix_per_kelvin"]) == 9 and "matrix_per_kelvin" in text.splitlines()[0]
    back = calfile.read(path)
    for name in ("matrices", "offsets", "offset_tempco", "matrix_tempco", "output_rotation", "interference"):
        np.testing.assert_allclose(getattr(back, name), getattr(cal, name), rtol=1e-15, atol=0)
    assert back.temperature_reference == 20.0 and back.frame_id == "imu_link"
    # a file without any of the new keys: no temperature terms, no rotation, the old correction exactly
    old = ArrayCalibration(cal.geometry, cal.matrices, cal.offsets)
    calfile.write(tmp_path / "old.yaml", old)
    assert not {"temperature_reference", "output_rotation", "frame_id"} & set((tmp_path / "old.yaml").read_text().split())
    loaded = calfile.read(tmp_path / "old.yaml")
    assert not loaded.has_temperature_terms and not loaded.rotated and loaded.frame_id is None
    raw = np.random.default_rng(1).normal(0, 3e-5, (5, 4, 3))
    np.testing.assert_array_equal(loaded.apply(raw), np.einsum("sij,nsj->nsi", loaded.matrices, raw - loaded.offsets))


@pytest.mark.parametrize("change, message", [
    ({"temperature_reference": None}, "need temperature_reference"),
    ({"offset_tempco": np.full((4, 3), 1e-3)}, "units must be T/K"),
    ({"matrix_tempco": np.full((4, 3, 3), 1.0)}, "units must be 1/K"),
    ({"output_rotation": np.diag([1.0, 1.0, -1.0])}, "must be a rotation matrix"),
    ({"temperature_reference": 300.0}, "not a temperature in deg C"),
])
def test_bad_temperature_terms_or_rotation_are_one_line(change: dict[str, object], message: str) -> None:
    geo = ArrayGeometry.cross()
    kw: dict[str, object] = {"temperature_reference": 20.0, "offset_tempco": np.full((4, 3), 1e-10)}
    kw.update(change)
    with pytest.raises(InputError, match=message) as exc:
        ArrayCalibration(geo, np.tile(np.eye(3), (4, 1, 1)), np.zeros((4, 3)), **kw)  # type: ignore[arg-type]
    assert "\n" not in str(exc.value)


# -- CSV -------------------------------------------------------------------------------------------
def _shuffle_columns(path: Path, order: list[str]) -> None:
    """Rewrite a CSV with its extra columns (after the sensor columns) in ``order``."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0][: 1 + 12]
    idx = [rows[0].index(c) for c in head + order]
    with open(path, "w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows([[r[i] for i in idx] for r in rows])


def test_csv_round_trip_with_temperature_and_imu_columns_in_any_order(tmp_path: Path) -> None:
    rec, truth, _ = run(thermal_imu_spec(count=30))
    rec = rec.with_temperatures(rec.temperatures + np.array([0.0, 0.5, 1.0, 1.5]))  # each sensor its own
    path = tmp_path / "rec.csv"
    write_csv(path, rec)
    header = path.read_text().splitlines()[0].split(",")
    extra = header[13:]
    assert extra == (["current.thruster1/battery"] + [f"temperature.{n}" for n in NAMES]
                     + ["imu.qx", "imu.qy", "imu.qz", "imu.qw", "imu.wx", "imu.wy", "imu.wz"])
    order = list(np.random.default_rng(2).permutation(extra))
    _shuffle_columns(path, order)
    back, stats = read_csv(path)
    assert stats.dropped() == 0
    np.testing.assert_array_equal(back.vectors, rec.vectors)
    np.testing.assert_array_equal(back.temperatures, rec.temperatures)
    np.testing.assert_array_equal(back.currents, rec.currents)
    np.testing.assert_allclose(back.imu.orientation, rec.imu.orientation, rtol=0, atol=1e-16)
    np.testing.assert_array_equal(back.imu.angular_velocity, rec.imu.angular_velocity)
    # the recorded IMU is the truth's (no noise): IMU frame -> ENU of the attitudes and mounting
    assert np.max(angle_deg(back.imu.orientation, truth.imu_orientation)) < 1e-9
    want = NED_TO_ENU @ truth.attitudes[7] @ mounting_matrix().T
    np.testing.assert_allclose(quat_to_matrix(back.imu.orientation[7]), want, atol=1e-12)


def test_a_long_csv_is_read_a_chunk_at_a_time_with_the_same_result(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A recording read in chunks of a few lines and formed into sets a few rows at a time (a long one is
    read 4 MB and 65,536 rows at a time, so memory stays bounded) gives exactly what one pass gives, with IMU cells left empty or not; a bad line in a later
    chunk is still named by its line number."""
    from magcal_ros.io import csv_recording

    rec, _, _ = run(thermal_imu_spec(count=60))
    plain = Recording(rec.names, rec.stamps, rec.vectors)
    for name, r in (("imu", rec), ("plain", plain)):
        path = tmp_path / f"{name}.csv"
        write_csv(path, r)
        if name == "imu":  # one row's orientation unknown: the optional-cell parser
            lines = path.read_text().splitlines()
            cells = lines[9].split(",")
            header = lines[0].split(",")
            for c in ("imu.qx", "imu.qy", "imu.qz", "imu.qw"):
                cells[header.index(c)] = ""
            lines[9] = ",".join(cells)
            path.write_text("\n".join(lines) + "\n")
        whole, _ = read_csv(path)
        monkeypatch.setattr(csv_recording, "CHUNK_CHARS", 700)  # a few lines per chunk
        monkeypatch.setattr(csv_recording, "SYNC_ROWS", 7)  # and sets formed a few rows at a time
        chunked, _ = read_csv(path)
        monkeypatch.undo()
        assert len(whole) == len(r) and np.array_equal(chunked.stamps, whole.stamps)
        np.testing.assert_array_equal(chunked.vectors, whole.vectors)
        np.testing.assert_array_equal(chunked.vectors, r.vectors)
        if name == "imu":
            np.testing.assert_array_equal(chunked.temperatures, whole.temperatures)
            np.testing.assert_array_equal(chunked.imu.orientation, whole.imu.orientation)
            assert np.all(np.isnan(chunked.imu.orientation[8]))
        lines = path.read_text().splitlines()
        lines[50] = lines[50] + ",1.0"  # a ragged line far into the file
        path.write_text("\n".join(lines) + "\n")
        monkeypatch.setattr(csv_recording, "CHUNK_CHARS", 700)
        with pytest.raises(InputError, match="line 51: "):
            read_csv(path)
        monkeypatch.undo()


HALVES_SCRIPT = """
import json, os, sys
import numpy as np
from magcal_ros.core import parallel
from magcal_ros.errors import InputError
from magcal_ros.io import csv_recording
csv_recording.CHUNK_CHARS, csv_recording.PARALLEL_CHARS = 700, 2000  # a few lines a chunk; halves from 2 kB
forked = []
def counted(nbytes, fill):
    handle = parallel.fill_in_child(nbytes, fill)
    forked.append(handle is not None)
    return handle
csv_recording.fill_in_child = counted
out = {}
for workers in ("1", "2"):
    os.environ["MAGCAL_WORKERS"] = workers
    try:
        rec, stats = csv_recording.read_csv(sys.argv[1])
        np.save(sys.argv[2] + workers + ".npy", np.concatenate([rec.stamps[:, None].astype(float), rec.vectors.reshape(len(rec), -1),
                                                              rec.temperatures], axis=1))
        out[workers] = stats.sets
    except InputError as exc:
        out[workers] = str(exc)
if len(sys.argv) > 3:  # interrupted while the child parses: the parent's half raises
    parent, real = os.getpid(), csv_recording._fast_chunk
    def failing(*args):
        if os.getpid() == parent:
            raise KeyboardInterrupt
        return real(*args)
    csv_recording._fast_chunk = failing
    try:
        csv_recording.read_csv(sys.argv[1])
    except KeyboardInterrupt:
        out["interrupted"] = True
    try:
        os.waitpid(-1, os.WNOHANG)
        out["left"] = "a child"
    except ChildProcessError:
        out["left"] = "none"
print(json.dumps({"out": out, "forked": forked}))
"""


@pytest.mark.parametrize("bad_line", [None, 7, 55, "interrupted"])
def test_a_long_csv_parsed_in_two_halves_side_by_side_gives_the_one_process_result(tmp_path: Path,
                                                                                   bad_line: int | str | None) -> None:
    """With a second core a long CSV's second half is parsed in a forked child meanwhile (the ``magcal``
    command runs one thread, so a fork copies no held lock): exactly the values, stamps and temperatures
    one process reads, and a bad line in either half is still named by its line number; interrupted
    (Ctrl-C) while the child parses, the child is stopped and reaped. Run in a fresh interpreter, as the
    command runs."""
    import json
    import subprocess
    import sys

    rec, _, _ = run(thermal_imu_spec(count=60))
    path = tmp_path / "long.csv"
    write_csv(path, Recording(rec.names, rec.stamps, rec.vectors, temperatures=rec.temperatures))
    if isinstance(bad_line, int):  # a ragged line in the parent's half (7) or in the child's (55)
        lines = path.read_text().splitlines()
        lines[bad_line - 1] += ",1.0"
        path.write_text("\n".join(lines) + "\n")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    extra = ["interrupt"] if bad_line == "interrupted" else []
    done = subprocess.run([sys.executable, "-c", HALVES_SCRIPT, str(path), str(tmp_path / "v"), *extra], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["forked"][:2] == [False, True]  # one worker: no child; two: the second half in a child
    if bad_line == "interrupted":
        assert report["forked"] == [False, True, True]
        assert report["out"]["interrupted"] is True and report["out"]["left"] == "none"
    elif bad_line is None:
        assert report["out"] == {"1": len(rec), "2": len(rec)}
        one, two = np.load(tmp_path / "v1.npy"), np.load(tmp_path / "v2.npy")
        np.testing.assert_array_equal(two, one)
        np.testing.assert_array_equal(two[:, 1:13], rec.vectors.reshape(len(rec), -1))
    else:
        assert report["out"]["1"] == report["out"]["2"] and f"line {bad_line}: " in report["out"]["2"]


def test_csv_single_temperature_column_unknown_imu_cells_and_ned(tmp_path: Path) -> None:
    q_ned = Rotation.random(4, random_state=5).as_quat()
    lines = ["stamp,a.x,a.y,a.z,imu.wx,imu.wy,imu.wz,temperature,imu.qx,imu.qy,imu.qz,imu.qw"]
    for k in range(4):
        q = [repr(float(v)) for v in q_ned[k]]
        if k == 1:
            q = ["", "", "", ""]  # orientation unknown at this set: kept, NaN
        w = ["0.1", "0.2", "0.3"] if k != 2 else ["nan", "nan", "nan"]
        temp = "12.5" if k != 3 else "nan"  # no temperature: the row goes, as a NaN current's would
        lines.append(",".join([f"{k + 1}.0", "2e-5", "1e-5", "4e-5", *w, temp, *q]))
    path = tmp_path / "ned.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 5: NaN"):
        read_csv(path)
    rec, stats = read_csv(path, nonfinite="drop", imu_orientation_frame="ned")
    assert len(rec) == 3 and stats.nonfinite == 1 and rec.temperatures.shape == (3, 1)
    assert np.all(rec.temperatures == 12.5)
    assert np.all(np.isnan(rec.imu.orientation[1])) and np.all(np.isnan(rec.imu.angular_velocity[2]))
    for k in (0, 2):
        np.testing.assert_allclose(quat_to_matrix(rec.imu.orientation[k]),
                                   NED_TO_ENU @ Rotation.from_quat(q_ned[k]).as_matrix(), atol=1e-12)
    enu, _ = read_csv(path, nonfinite="drop")
    np.testing.assert_allclose(quat_to_matrix(enu.imu.orientation[0]), Rotation.from_quat(q_ned[0]).as_matrix(),
                               atol=1e-12)
    # the same through open_recording, as the CLI reads it
    rec2, _ = open_recording(path, nonfinite="drop", imu_orientation_frame="ned")
    np.testing.assert_array_equal(rec2.imu.orientation, rec.imu.orientation)


@pytest.mark.parametrize("extra, message", [
    (["temperature.b"], "CSV column temperature.b: no sensor b"),
    (["temperature", "temperature.a"], "give one or the other"),
    (["imu.qx", "imu.qy", "imu.qz"], "the IMU needs all of imu.qx,imu.qy,imu.qz,imu.qw"),
    (["imu.wx", "imu.wy", "imu.wz", "imu.wy"], "names an IMU column twice"),
    (["temperature.a", "pressure"], "column 'pressure' after the temperature columns"),
    (["imu.wx", "imu.wy", "imu.wz", "c.x", "c.y", "c.z"], "column 'c.x' after the IMU columns"),
])
def test_malformed_extra_columns_are_one_line(extra: list[str], message: str) -> None:
    with pytest.raises(InputError, match=message) as exc:
        parse_columns(["stamp", "a.x", "a.y", "a.z", *extra])
    assert "\n" not in str(exc.value)


def test_csv_with_two_sensors_needs_every_temperature() -> None:
    with pytest.raises(InputError, match="temperature of a but not of b"):
        parse_columns(["stamp", "a.x", "a.y", "a.z", "b.x", "b.y", "b.z", "temperature.a", "current.p"])
    layout = parse_columns(["stamp", "a.x", "a.y", "a.z", "b.x", "b.y", "b.z", "temperature.b", "current.p",
                            "temperature.a"])
    assert layout.names == ("a", "b") and layout.channels == ("p",) and layout.temperatures == ("b", "a")
    # a sensor may be named like a prefix: its three columns are a sensor
    assert parse_columns(["stamp", "imu.x", "imu.y", "imu.z", "temperature.imu"]).names == ("imu",)


# -- bags ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def imu_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tumble at 10 Hz with temperatures and an IMU at 100 Hz (its own clock), no noise."""
    out = tmp_path_factory.mktemp("imu") / "tumble_bag"
    ok(magcal("simulate", out, "--schedule", "tumble", "--count", 600, "--seed", 4, "--noise", 0,
              "--temperature-ramp", "5,25", "--tempco-offset", "0.5e-9", "--tempco-gain", "30e-6", "--imu",
              "--imu-mounting", ",".join(map(str, MOUNTING_DEG)), "--imu-rate", 100))
    return out


def test_bag_temperatures_and_imu_match_the_truth(imu_bag: Path) -> None:
    truth = load_truth(imu_bag)
    rec, _ = open_recording(imu_bag)
    rec, tstats = with_bag_temperatures(imu_bag, rec)  # found automatically
    assert tstats is not None and tstats.dropped == 0
    np.testing.assert_array_equal(rec.temperatures, truth["temperatures"])
    with_imu, istats = with_bag_imu(imu_bag, rec, "/imu")
    assert istats.dropped == 1  # the IMU's first sample comes 3.7 ms after the first set
    k = np.searchsorted(truth["stamps"], with_imu.stamps)
    err = angle_deg(with_imu.imu.orientation, truth["imu_orientation"][k])
    # a hand tumble turns ~30 deg/s: the latest sample alone is up to 0.3 deg off, the interpolation a few mdeg
    assert np.max(err) < 0.02 and with_imu.imu.frame_id == "imu_link"
    rate = np.linalg.norm(truth["imu_angular_velocity"], axis=1)
    assert np.median(np.degrees(rate)) > 20
    assert np.max(np.abs(with_imu.imu.angular_velocity - truth["imu_angular_velocity"][k])) < 0.05 * rate.max()
    # output_rotation in the truth is the mounting
    np.testing.assert_allclose(truth["output_rotation"], mounting_matrix(), atol=1e-15)


def _write_bag(path: Path, rec: Recording, temperature_stamps: dict[str, np.ndarray], imu: list[tuple] | None = None,
               storage: str = "sqlite3") -> None:
    """Raw sets of ``rec`` plus ``/<name>/temperature`` messages at the given stamps (value: 10 + seconds) and
    optional ``/imu`` messages ``(stamp, q, w)``."""
    ts = cdr.typestore()
    with BagSink.create(path, storage) as sink:  # type: ignore[arg-type]
        items = []
        raw = [sink.add_topic(f"/{n}/raw", cdr.MAGNETIC_FIELD) for n in rec.names]
        for t, sets in zip(rec.stamps.tolist(), rec.vectors):
            for conn, name, v in zip(raw, rec.names, sets):
                msg = cdr.magnetic_field_message(t // S, t % S, name, v)
                items.append((conn, t, bytes(ts.serialize_cdr(msg, cdr.MAGNETIC_FIELD))))
        for name, stamps in temperature_stamps.items():
            conn = sink.add_topic(f"/{name}/temperature", cdr.TEMPERATURE)
            items += [(conn, int(t), bytes(ts.serialize_cdr(cdr.temperature_message(int(t), 10 + t / S),
                                                           cdr.TEMPERATURE))) for t in stamps]
        if imu is not None:
            conn = sink.add_topic("/imu", cdr.IMU)
            items += [(conn, int(t), bytes(ts.serialize_cdr(cdr.imu_message(int(t), q, w, "base_imu"), cdr.IMU)))
                      for t, q, w in imu]
        sink.write_messages(sorted(items, key=lambda i: i[1]))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_stale_temperatures_and_imu_are_dropped_and_counted(tmp_path: Path, storage: str) -> None:
    n = 100  # sets at 1 Hz
    rng = np.random.default_rng(9)
    rec = Recording(NAMES, (np.arange(n) + 1) * S, rng.normal(0, 3e-5, (n, 4, 3)))
    every_2s = np.arange(0, n + 2, 2) * S
    temps = {name: every_2s for name in NAMES}
    temps["mag3"] = every_2s[(every_2s < 40 * S) | (every_2s > 60 * S)]  # silent from 40 to 60 s
    q = Rotation.random(3, random_state=1).as_quat()
    imu = [(10 * S, q[0], [0.0, 0.0, 0.0]), (10 * S + 500 * MS, [np.nan] * 4, [0.1, 0.0, 0.0]),
           (50 * S, q[2], [np.nan] * 3)]
    path = tmp_path / f"stale_{storage}"
    _write_bag(path, rec, temps, imu, storage)
    got, stats = with_bag_temperatures(path, rec, tolerance=5.0)
    # mag3's last value before the gap is at 38 s: sets from 44 s to 61 s are more than 5 s after it
    stale = [t for t in range(1, n + 1) if 43 < t < 62]
    assert stats.dropped == len(stale) and stats.stale == [0, 0, len(stale), 0]
    assert [int(t // S) for t in got.stamps] == [t for t in range(1, n + 1) if t not in stale]
    np.testing.assert_array_equal(got.temperatures[:, 0], 10 + 2 * (got.stamps // S // 2))  # latest, not newer
    # one topic for every sensor
    one, _ = with_bag_temperatures(path, rec, ["/mag1/temperature"], tolerance=5.0)
    np.testing.assert_array_equal(one.temperatures, np.repeat(one.temperatures[:, :1], 4, axis=1))
    # IMU: a set needs a sample at most 2 s before it; orientation unknown where the message says so
    got, istats = with_bag_imu(path, rec, "/imu", tolerance=2.0)
    assert [int(t // S) for t in got.stamps] == [10, 11, 12, 50, 51, 52] and istats.dropped == n - 6
    assert got.imu.frame_id == "base_imu"
    # 10 s: on the first sample; 11, 12 s: after the sample at 10.5 s, which has no orientation: propagated
    # from... none, so unknown, with its angular velocity
    assert angle_deg(got.imu.orientation[0], q[0]) < 1e-12
    assert np.all(np.isnan(got.imu.orientation[1:3])) and np.allclose(got.imu.angular_velocity[1:3], [0.1, 0, 0])
    assert angle_deg(got.imu.orientation[3], q[2]) < 1e-12 and np.all(np.isnan(got.imu.angular_velocity[3:]))


def test_bag_topic_errors_are_one_line(tmp_path: Path, imu_bag: Path) -> None:
    rec, _ = open_recording(imu_bag)
    with pytest.raises(InputError, match="no IMU topic /gyro") as exc:
        with_bag_imu(imu_bag, rec, "/gyro")
    assert "Imu topics: /imu" in str(exc.value)
    with pytest.raises(InputError, match="topic /mag1/raw has type sensor_msgs/msg/MagneticField, expected "
                                         "sensor_msgs/msg/Imu"):
        with_bag_imu(imu_bag, rec, "/mag1/raw")
    with pytest.raises(InputError, match="2 temperature topics for 4 sensors"):
        with_bag_temperatures(imu_bag, rec, ["/mag1/temperature", "/mag2/temperature"])
    partial = tmp_path / "partial_bag"
    _write_bag(partial, rec.take(np.arange(10)), {"mag1": rec.stamps[:10], "mag2": rec.stamps[:10]})
    with pytest.raises(InputError, match="has /mag1/temperature, /mag2/temperature but not /mag3/temperature"):
        with_bag_temperatures(partial, rec.take(np.arange(10)))
    csv_path = tmp_path / "x.csv"
    write_csv(csv_path, rec.take(np.arange(5)))
    with pytest.raises(InputError, match="temperature topics are for bags"):
        with_bag_temperatures(csv_path, rec)


# -- magcal simulate / correct ---------------------------------------------------------------------
def test_simulate_writes_what_the_truth_file_says(tmp_path: Path) -> None:
    out = tmp_path / "dive.csv"
    ok(magcal("simulate", out, "--schedule", "sea", "--count", 800, "--seed", 2, "--noise", 0, "--thermocline",
              "25,4,2", "--tempco-offset", "0.5e-9", "--tempco-gain", "30e-6", "--imu", "--imu-mounting",
              ",".join(map(str, MOUNTING_DEG)), "--world-gradient", "30e-9,0,0,-15e-9,0"))
    truth = load_truth(out)
    rec, _ = open_recording(out)
    np.testing.assert_array_equal(rec.temperatures, truth["temperatures"])
    temp = truth["temperatures"][:, 0]
    assert temp.max() == pytest.approx(25.0) and temp.min() == pytest.approx(4.0, abs=0.01)
    crossings = np.sum(np.diff(np.sign(temp - 14.5)) != 0)
    assert crossings == 4, "two dives cross the thermocline twice each"
    # the IMU: orientation = ENU of attitude and mounting; gyro = the attitude's rate in the IMU frame
    want = NED_TO_ENU @ truth["attitudes"] @ mounting_matrix().T
    assert np.max(np.abs(quat_to_matrix(rec.imu.orientation) - want)) < 1e-12
    dt = 0.1
    r = truth["attitudes"]
    # finite difference of the recorded attitudes (body rate, platform frame), turned into the IMU frame
    rel = Rotation.from_matrix(np.einsum("nji,njk->nik", r[:-2], r[2:])).as_rotvec() / (2 * dt)
    fd = rel @ mounting_matrix().T
    w = rec.imu.angular_velocity[1:-1]
    assert np.median(np.linalg.norm(w - fd, axis=1) / np.linalg.norm(w, axis=1)) < 0.02
    np.testing.assert_array_equal(truth["imu_angular_velocity"], rec.imu.angular_velocity)
    # the world gradient is in the truth's tensor (platform frame): R^T G R
    g = np.array([[30, 0, 0], [0, -15, 0], [0, 0, -15]]) * 1e-9
    np.testing.assert_allclose(truth["gradient"], np.einsum("nki,kl,nlj->nij", r, g, r), atol=1e-18)
    np.testing.assert_allclose(truth["world_gradient_enu"], NED_TO_ENU @ g @ NED_TO_ENU.T)
    # and the true calibration corrects the recording to the truth in the IMU frame
    cal = calfile.read(str(out) + ".truth.yaml")
    b = cal.apply(rec.vectors, temperatures=rec.temperatures)
    assert np.max(np.abs(b - truth["field"] @ mounting_matrix().T)) < 1e-12 * np.max(np.abs(truth["field"]))


def test_random_attitudes_have_orientation_but_no_gyro(tmp_path: Path) -> None:
    out = tmp_path / "random.csv"
    ok(magcal("simulate", out, "--count", 50, "--imu"))
    header = out.read_text().splitlines()[0]
    assert header.endswith("imu.qx,imu.qy,imu.qz,imu.qw") and "imu.wx" not in header
    assert np.all(np.isnan(load_truth(out)["imu_angular_velocity"]))
    bad = magcal("simulate", tmp_path / "b.csv", "--count", 50, "--imu", "--imu-rate", 100)
    assert bad.returncode == 2 and "--imu-rate needs a schedule flown in time" in bad.stderr


@pytest.mark.parametrize("args, message", [
    (["--tempco-offset", "1e-9"], "need a temperature profile"),
    (["--imu-mounting", "1,2,3"], "the --imu-* options need --imu"),
    (["--temperatures", "5,15", "--thermocline", "25,4"], "give one temperature profile"),
    (["--temperature-ramp", "5"], "--temperature-ramp needs two temperatures"),
    (["--world-gradient", "1e-9,2e-9"], "--world-gradient needs 5 numbers"),
    (["--temperatures", "5,300"], "temperatures must lie in"),
])
def test_simulate_temperature_and_imu_options_are_checked(tmp_path: Path, args: list[str], message: str) -> None:
    proc = magcal("simulate", tmp_path / "x.csv", "--count", 10, *args)
    assert proc.returncode == 2 and message in proc.stderr and proc.stderr.count("\n") == 1
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.parametrize("fmt", ["csv", "sqlite3", "mcap"])
def test_magcal_correct_applies_temperature_terms_and_the_output_frame(tmp_path: Path, fmt: str) -> None:
    out = tmp_path / ("warm.csv" if fmt == "csv" else f"warm_{fmt}")
    extra = [] if fmt == "csv" else ["--storage", fmt]
    ok(magcal("simulate", out, "--schedule", "tumble", "--count", 300, "--seed", 6, "--noise", 0, "--temperatures",
              "2,15,28", "--tempco-offset", "0.5e-9", "--tempco-gain", "30e-6", "--imu", "--imu-mounting",
              ",".join(map(str, MOUNTING_DEG)), *extra))
    truth = load_truth(out)
    cal = Path(str(out) + ".truth.yaml")
    want = truth["field"] @ mounting_matrix().T
    tol = 1e-12 * np.max(np.abs(want))
    targets = [tmp_path / "corrected.csv"] + ([] if fmt == "csv" else [tmp_path / "corrected_bag"])
    for target in targets:
        proc = ok(magcal("correct", out, "-c", cal, "-o", target))
        assert "corrected 300 sets" in proc.stdout
        if target.suffix == ".csv":
            got = read_corrected(target)
        else:  # the streaming bag path: every output in the calibration's frame
            msgs = bag_messages(target)
            assert {m[3].header.frame_id for m in msgs if m[1] == cdr.MAGNETIC_FIELD} == {"imu_link"}
            got = {"sensors": np.array([[m[3].magnetic_field.x, m[3].magnetic_field.y, m[3].magnetic_field.z]
                                        for m in msgs if m[0].endswith("/corrected")]).reshape(-1, 4, 3)}
        assert np.max(np.abs(got["sensors"] - want)) < tol
    # another frame name on request
    if fmt != "csv":
        ok(magcal("correct", out, "-c", cal, "-o", tmp_path / "named_bag", "--frame-id", "nav"))
        assert {m[3].header.frame_id for m in bag_messages(tmp_path / "named_bag") if m[0] == "/field"} == {"nav"}


def test_magcal_correct_refuses_what_the_temperature_terms_need(tmp_path: Path, imu_bag: Path) -> None:
    cal = Path(str(imu_bag) + ".truth.yaml")
    plain = tmp_path / "plain_bag"
    ok(magcal("simulate", plain, "--count", 20, "--seed", 4))
    for target in ("o_bag", "o.csv"):
        proc = magcal("correct", plain, "-c", cal, "-o", tmp_path / target)
        assert proc.returncode == 2 and "corrects for temperature" in proc.stderr and "--temperature-topics" in proc.stderr
    plain_csv = tmp_path / "plain.csv"
    ok(magcal("simulate", plain_csv, "--count", 20, "--seed", 4))
    proc = magcal("correct", plain_csv, "-c", cal, "-o", tmp_path / "o2.csv")
    assert proc.returncode == 2 and "temperature.<name> columns" in proc.stderr
    # one topic for every sensor
    ok(magcal("correct", imu_bag, "-c", cal, "-o", tmp_path / "one.csv", "--temperature-topics", "/mag2/temperature"))
    # topics for a calibration without temperature terms: refused, like --currents
    plain_cal = tmp_path / "plain.yaml"
    true_cal = calfile.read(cal)
    calfile.write(plain_cal, ArrayCalibration(true_cal.geometry, true_cal.matrices, true_cal.offsets))
    proc = magcal("correct", imu_bag, "-c", plain_cal, "-o", tmp_path / "o3_bag", "--temperature-topics", "/mag1/t")
    assert proc.returncode == 2 and "no temperature terms" in proc.stderr
    # a stale stretch is dropped with a note
    proc = ok(magcal("correct", imu_bag, "-c", cal, "-o", tmp_path / "tight_bag", "--temperature-tolerance", "0"))
    assert "note:" not in proc.stderr  # the temperatures are stamped with the sets


def test_magcal_calibrate_reads_the_temperatures_and_the_imu(tmp_path: Path, imu_bag: Path) -> None:
    proc = magcal("calibrate", imu_bag, "-o", tmp_path / "c.yaml", "--imu", "/imu")
    assert "1 of 600 sets dropped without an IMU sample within 0.1 s before the set (/imu: 1)" in proc.stderr
    bad = magcal("calibrate", imu_bag, "-o", tmp_path / "c.yaml", "--imu", "/nope")
    assert bad.returncode == 2 and "no IMU topic /nope" in bad.stderr
    csv_path = tmp_path / "r.csv"
    ok(magcal("simulate", csv_path, "--count", 30))
    bad = magcal("calibrate", csv_path, "-o", tmp_path / "c.yaml", "--imu", "/imu")
    assert bad.returncode == 2 and "imu.qx" in bad.stderr


# -- the calibration node's buffer -------------------------------------------------------------------
def test_collected_sets_carry_temperatures_and_imu_once_heard() -> None:
    buf = SetBuffer(capacity=10, sensors=2, channels=0)
    vec = ((1e-5, 2e-5, 3e-5), (1e-5, 2e-5, 3e-5))
    buf.add(1, vec)  # before the first temperature
    buf.add(2, vec, (), [10.0, 11.0])
    buf.add(3, vec, (), [12.0, 13.0], [0.0, 0.0, 0.0, 1.0, 0.1, 0.2, 0.3])
    buf.add(4, vec, (), [14.0, 15.0], [np.nan] * 4 + [0.4, 0.5, 0.6])
    rec, notes = collected_recording(("a", "b"), (), *buf.collected(), "imu_link")
    assert list(rec.stamps) == [3, 4] and rec.temperatures.tolist() == [[12.0, 13.0], [14.0, 15.0]]
    assert rec.imu.frame_id == "imu_link" and np.all(np.isnan(rec.imu.orientation[1]))
    np.testing.assert_array_equal(rec.imu.angular_velocity, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    assert notes == ["1 sets collected before every sensor's temperature arrived left out",
                     "1 sets collected before the IMU arrived left out"]
    plain = SetBuffer(capacity=3, sensors=2)
    plain.add(1, vec)
    rec, notes = collected_recording(("a", "b"), (), *plain.collected())
    assert rec.temperatures is None and rec.imu is None and notes == []


def test_a_still_run_keeps_the_held_temperature_terms_and_frame() -> None:
    """Thrusters stepped on a still vehicle while the sensors warm from 5 to 25 C: with the held calibration's
    temperature terms the gains are the truth's, and the result keeps those terms and the output frame."""
    from dataclasses import replace

    from magcal_ros.methods.interference import calibrate_interference

    rec, truth, sim = run(thermal_imu_spec(schedule="random", still=True, count=480, noise=1e-9,
                                          temperature_ramp=(5.0, 25.0), temperatures=(),
                                          thruster_current="steps:0,5,10,20", step_sets=30))
    held = replace(truth.calibration, channels=(), interference=None)
    result = calibrate_interference(rec.vectors, rec.currents, rec.channels, held, rec.temperatures)
    cal = result.calibration
    err = np.linalg.norm(cal.interference - sim.interference(), axis=1) / np.linalg.norm(sim.interference(), axis=1)
    assert np.all(err < 0.01), err
    assert cal.temperature_reference == held.temperature_reference and cal.frame_id == "imu_link"
    np.testing.assert_array_equal(cal.matrix_tempco, held.matrix_tempco)
    np.testing.assert_array_equal(cal.output_rotation, held.output_rotation)
    with pytest.raises(InputError, match="give the temperatures"):
        calibrate_interference(rec.vectors, rec.currents, rec.channels, held)


def test_side_topics_recorded_without_a_message_are_no_temperatures_not_a_traceback(tmp_path: Path) -> None:
    """A recorder that subscribed to ``/<name>/temperature`` (and ``/imu``) but got no message: the default
    temperature topics count as absent (the sets are kept, none dropped); naming an empty topic is refused
    in one line, as any topic without a usable sample is (it raised a reshape ValueError from the matching)."""
    n = 50
    rng = np.random.default_rng(4)
    rec = Recording(NAMES, (np.arange(n) + 1) * S, rng.normal(0, 3e-5, (n, 4, 3)))
    bag = tmp_path / "empty_side_bag"
    _write_bag(bag, rec, {name: np.zeros(0, np.int64) for name in NAMES}, imu=[])
    opened, _ = open_recording(bag)
    same, stats = with_bag_temperatures(bag, opened)
    assert stats is None and same.temperatures is None and len(same) == n
    with pytest.raises(InputError, match="no set left"):
        with_bag_temperatures(bag, opened, ["/mag1/temperature"])
    with pytest.raises(InputError):
        with_bag_imu(bag, opened, "/imu")

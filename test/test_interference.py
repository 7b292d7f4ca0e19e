"""Thruster and payload current interference: matched, estimated and subtracted, against simulated truth.

Two thrusters 0.7 m behind the 0.4 m cross, 0-20 A: tens to ~1,000 nT at the sensors. The
noise floor of the tensor is computed from its formula, ``sqrt(2) sigma / d``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from test_offline import magcal, ok, read_corrected

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.interference import (
    CurrentSamples,
    CurrentStats,
    LatestCurrents,
    estimate_interference,
    match_currents,
    undetermined_channels,
)
from magcal_ros.core.metrics import tensor_rms, tmi_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.tensor import gradient_difference
from magcal_ros.errors import CalibrationFailed, InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import cdr
from magcal_ros.io.bag_writer import write_recording_bag
from ros_harness import realistic_stamps
from magcal_ros.io.csv_recording import parse_header, read_csv, write_csv
from magcal_ros.io.recordings import read_recording
from magcal_ros.io.truth_file import load_truth, truth_paths
from magcal_ros.methods.interference import calibrate_interference
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation
from magcal_ros.sim.spec import SimulationSpec, build, current_schedule, run

F = 5.5e-5  # simulate's default intensity (T)
NOISE = 1e-9
BASELINE = 0.4
FLOOR = np.sqrt(2.0) * NOISE / BASELINE  # tensor noise floor (T/m) of the cross difference formula
THRUSTERS = ((-0.7, 0.25, 0.1, 0.06, 0.0, 0.04), (-0.7, -0.25, 0.1, 0.0, -0.06, 0.04))
THRUSTER_ARGS = [a for t in THRUSTERS for a in ("--thruster", ",".join(map(str, t)))]  # values start with '-' 
CHANNELS = ("thruster1/battery", "thruster2/battery")
SEED = 5
SETS = 1500
IMAX = 20.0


def fresh_run(sim: ArraySimulation, count: int, seed: int) -> tuple[Recording, object]:
    """Fresh attitudes and fresh random currents 0-20 A for the same sensors and thrusters."""
    currents = np.random.default_rng([seed, 9]).uniform(0.0, IMAX, (count, len(sim.thrusters)))
    return sim.run(uniform_random(count, seed), seed + 1, start=1.7e9, currents=currents)


def in_true_frame(cal: ArrayCalibration, truth_cal: ArrayCalibration) -> np.ndarray:
    """The interference of ``cal`` in the truth's platform frame: the solved frame differs from the true
    one by a rotation a uniform field cannot show, so compare what each sensor sees (M_true M^-1 D)."""
    return np.einsum("sab,sbc,scm->sam", truth_cal.matrices, np.linalg.inv(cal.matrices), cal.interference)


def relative_gain_error(cal: ArrayCalibration, truth_cal: ArrayCalibration) -> np.ndarray:
    """(S, m) |D - D_true| / |D_true| per sensor and channel, in the true frame."""
    d_true = truth_cal.interference
    return np.linalg.norm(in_true_frame(cal, truth_cal) - d_true, axis=1) / np.linalg.norm(d_true, axis=1)


@pytest.fixture(scope="module")
def manoeuvre() -> tuple[Recording, object, ArraySimulation]:
    """A 1,500-set random manoeuvre with both thrusters drawing random currents 0-20 A."""
    return run(SimulationSpec(count=SETS, seed=SEED, noise=NOISE, thrusters=THRUSTERS,
                              thruster_current=f"random:{IMAX:g}"))


def test_simulated_interference_is_tens_to_a_thousand_nt(manoeuvre) -> None:
    _, truth, sim = manoeuvre
    gains = np.linalg.norm(sim.interference(), axis=1)  # (S, m) T/A
    assert 10e-9 < IMAX * gains.min() and 0.8e-6 < IMAX * gains.max() < 1.5e-6
    # the truth file's interference is the dipole field per ampere at each sensor
    np.testing.assert_array_equal(truth.calibration.interference, sim.interference())
    assert truth.calibration.channels == CHANNELS
    assert truth.currents.shape == (SETS, 2) and 0 <= truth.currents.min() and truth.currents.max() <= IMAX


def test_joint_calibration_subtracts_interference_on_fresh_data(manoeuvre) -> None:
    rec, truth, sim = manoeuvre
    result = calibrate_array(rec.vectors, sim.geometry, F, currents=rec.currents, channels=rec.channels)
    cal = result.calibration
    assert cal.channels == CHANNELS and not result.warnings
    assert np.all(relative_gain_error(cal, truth.calibration) < 0.01)

    fresh, fresh_truth = fresh_run(sim, 3000, 77)
    true_b = fresh_truth.calibration.apply(fresh.vectors, fresh.currents)
    b = cal.apply(fresh.vectors, fresh.currents)
    assert np.all(tmi_rms(b, F) < 1.1 * tmi_rms(true_b, F))
    g_true = tensor_rms(gradient_difference(true_b, sim.geometry))
    assert g_true == pytest.approx(FLOOR, rel=0.1)
    assert tensor_rms(gradient_difference(b, sim.geometry)) < 1.1 * g_true

    # Without compensation even the true calibration leaves the tensor far above the floor.
    uncompensated = ArrayCalibration(sim.geometry, fresh_truth.calibration.matrices, fresh_truth.calibration.offsets)
    b0 = uncompensated.apply(fresh.vectors)
    assert tensor_rms(gradient_difference(b0, sim.geometry)) > 100 * FLOOR
    assert np.all(tmi_rms(b0, F) > 30 * NOISE)


def test_match_currents_takes_the_latest_value_not_newer_than_the_set() -> None:
    ms = 1_000_000
    sets = np.array([1000, 1100, 1200, 1300, 2500]) * ms
    a = CurrentSamples("a", np.array([900, 1000, 1150, 1150, 1250, 1400]) * ms, np.array([1.0, 2.0, 3.0, 4.0, np.nan, 6.0]))
    b = CurrentSamples("b", np.array([1300, 100]) * ms, np.array([7.0, 8.0]))  # out of order in the bag
    u, fresh = match_currents(sets, [a, b], 500 * ms)
    np.testing.assert_array_equal(fresh[:, 0], [True, True, True, True, False])  # 1400 is > 0.5 s before 2500
    np.testing.assert_array_equal(u[:4, 0], [2.0, 2.0, 4.0, 4.0])  # equal stamps: the later; NaN: no value
    np.testing.assert_array_equal(fresh[:, 1], [False, False, False, True, False])  # 100 ms is too old
    assert u[3, 1] == 7.0
    stats = CurrentStats(("a", "b"), 500 * ms)
    np.testing.assert_array_equal(stats.keep(fresh), [False, False, False, True, False])
    assert (stats.dropped, stats.stale) == (4, [1, 4])
    assert stats.describe() == "4 of 5 sets dropped without a current of every channel within 0.5 s before the set (a: 1, b: 4)"


@pytest.mark.parametrize("seed", range(3))
def test_live_currents_follow_the_offline_rule_whatever_the_arrival_order(seed: int) -> None:
    """The correction node's store (values arriving live, in any order, before or after the set) gives
    every set the same currents and staleness as the offline matching of the same values."""
    rng = np.random.default_rng(seed)
    ms = 1_000_000
    tol = 300 * ms
    samples = []
    for channel in ("a", "b"):
        t = np.sort(rng.choice(np.arange(0, 20_000, 7), 400, replace=False)) * ms
        t[50:53] = t[50]  # repeated stamps: the one received last counts
        v = rng.uniform(0, 20, len(t))
        v[rng.random(len(t)) < 0.05] = np.nan  # no value
        samples.append(CurrentSamples(channel, t, v))
    sets = np.sort(rng.integers(0, 20_000, 300)) * ms
    expected_u, expected_fresh = match_currents(sets, samples, tol)
    store = LatestCurrents(2, tol, keep_ns=60_000 * ms)
    events = [(t, j, k) for j, s in enumerate(samples) for k, t in enumerate(s.stamps)]
    jitter = rng.normal(0, 200 * ms, len(events))  # arrival order: stamp plus up to ~0.5 s of jitter,
    jitter[[e for e, (t, j, _) in enumerate(events) if t == samples[j].stamps[50]]] = 0.0  # equal stamps in order
    arrivals = sorted(range(len(events)), key=lambda e: (events[e][0] + jitter[e], events[e][2]))
    for e in arrivals:
        t, j, k = events[e]
        store.add(j, int(t), float(samples[j].values[k]))
    for i, t in enumerate(sets):
        u, fresh = store.at(int(t))
        np.testing.assert_array_equal(fresh, expected_fresh[i])
        np.testing.assert_array_equal(np.where(fresh, u, 0.0), expected_u[i])
    assert store.received == [int(np.isfinite(s.values).sum()) for s in samples]


def test_live_currents_forget_old_values() -> None:
    ms = 1_000_000
    store = LatestCurrents(1, 500 * ms, keep_ns=2000 * ms)
    for k in range(100):
        store.add(0, k * 100 * ms, float(k))
    assert store.at(9_900 * ms) == ([99.0], [True])
    assert store.at(9_000 * ms) == ([90.0], [True])
    assert store.at(7_000 * ms) == ([0.0], [False])  # older than the 2 s kept: forgotten, stale
    assert store.latest(0) == 99.0 and LatestCurrents(1, 0).latest(0) is None


def test_csv_current_columns_round_trip_with_dropped_rows(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    vectors = rng.normal(0, 3e-5, (6, 2, 3))
    stamps = np.array([1, 2, 2, 3, 4, 5]) * 1_000_000_000  # the repeated stamp's row is dropped
    currents = np.arange(12.0).reshape(6, 2)
    currents[4, 1] = np.nan  # a NaN current drops its row
    path = tmp_path / "rec.csv"
    write_csv(path, Recording(("a", "b"), stamps, vectors, ("pump", "thruster1/battery"), currents))
    assert path.read_text().splitlines()[0] == "stamp,a.x,a.y,a.z,b.x,b.y,b.z,current.pump,current.thruster1/battery"
    rec, stats = read_csv(path, nonfinite="drop")
    kept = [0, 1, 3, 5]
    assert rec.channels == ("pump", "thruster1/battery") and (stats.duplicate, stats.nonfinite) == (2, 2)
    np.testing.assert_array_equal(rec.stamps, stamps[kept])
    np.testing.assert_array_equal(rec.vectors, vectors[kept])
    np.testing.assert_array_equal(rec.currents, currents[kept])
    with pytest.raises(InputError, match="line 6: NaN"):
        read_csv(path)
    # window, take and select keep the currents with their sets
    part = rec.window(2_000_000_000, 3_000_000_000).select(("b",)).select_channels(("thruster1/battery",))
    np.testing.assert_array_equal(part.currents, currents[[1, 3], 1:])
    # a sensor named like the prefix is still a sensor
    assert parse_header(["stamp", "current.x", "current.y", "current.z", "current.x"]) == (("current",), ("x",))


@pytest.mark.parametrize("header, message", [
    (["stamp", "a.x", "a.y", "a.z", "current."], "column 'current.'"),
    (["stamp", "a.x", "a.y", "a.z", "current.p", "b.x", "b.y", "b.z"], "column 'b.x' after the current columns"),
    (["stamp", "a.x", "a.y", "a.z", "current.p", "current.p"], "names a current channel twice"),
    (["stamp", "current.p"], "3 columns per sensor"),
])
def test_malformed_current_columns_are_one_line(header: list[str], message: str) -> None:
    with pytest.raises(InputError, match=message) as exc:
        parse_header(header)
    assert "\n" not in str(exc.value)


def test_undetermined_channels() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.uniform(0, 20, (2, 600))
    cases = {
        "independent": (np.column_stack([a, b]), [False, False]),
        "constant": (np.column_stack([a, np.full(600, 12.0)]), [False, True]),
        "never on": (np.column_stack([a, np.zeros(600)]), [False, True]),
        "lockstep": (np.column_stack([a, 0.5 * a + 2.0, b]), [True, True, False]),
        "barely varies": (np.column_stack([a, 12.0 + 1e-3 * b]), [False, True]),  # 12 A +- 0.6 mA
    }
    for name, (u, expected) in cases.items():
        np.testing.assert_array_equal(undetermined_channels(u), expected, err_msg=name)
    # a current that follows the attitude is undetermined in a manoeuvre
    direction = rng.normal(size=(600, 3))
    np.testing.assert_array_equal(undetermined_channels(np.column_stack([a, 3 + direction[:, 0]]), direction), [False, True])


@pytest.fixture(scope="module")
def rotation_calibration() -> tuple[ArrayCalibration, ArraySimulation]:
    """A rotation calibration without currents (thrusters off), and the simulated array."""
    rec, _, _ = run(SimulationSpec(count=800, seed=SEED, noise=NOISE))
    sim, _ = build(SimulationSpec(count=1, seed=SEED, noise=NOISE, thrusters=THRUSTERS))
    return calibrate_array(rec.vectors, sim.geometry, F).calibration, sim


def still_run(sim: ArraySimulation, currents: np.ndarray, seed: int = 2) -> Recording:
    attitude = uniform_random(1, seed)
    return sim.run(np.repeat(attitude, len(currents), axis=0), seed, currents=currents)[0]


def test_still_run_with_a_channel_that_never_varies(rotation_calibration) -> None:
    held, sim = rotation_calibration
    steps = current_schedule("steps:0,5,10,20", 400, 1, 25, np.random.default_rng(0))[:, 0]
    u = np.column_stack([steps, np.full(400, 8.0)])
    rec = still_run(sim, u)
    est = estimate_interference(rec.vectors, u, held)
    np.testing.assert_array_equal(est.undetermined, [False, True])
    assert np.all(est.gains[:, :, 1] == 0) and np.all(np.isinf(est.sigma[:, :, 1]))
    result = calibrate_interference(rec.vectors, u, CHANNELS, held)
    assert result.calibration.channels == CHANNELS[:1]
    assert "thruster2/battery (8 A) never varied" in result.warnings[0]
    truth = ArrayCalibration(sim.geometry, sim.true_calibration().matrices, sim.true_calibration().offsets, {}, None,
                             CHANNELS[:1], sim.interference()[:, :, :1])
    assert np.all(relative_gain_error(result.calibration, truth) < 0.02)
    assert result.calibration.metadata["interference_undetermined"] == ["thruster2/battery"]


def test_still_run_with_channels_in_lockstep_is_not_solved(rotation_calibration) -> None:
    held, sim = rotation_calibration
    steps = current_schedule("steps:0,5,10,20", 400, 1, 25, np.random.default_rng(0))[:, 0]
    u = np.column_stack([steps, steps])
    rec = still_run(sim, u)
    with pytest.raises(CalibrationFailed, match="thruster1/battery, thruster2/battery varied in lockstep"):
        calibrate_interference(rec.vectors, u, CHANNELS, held)


def test_joint_path_drops_undetermined_channels_and_warns(manoeuvre) -> None:
    rec, truth, sim = manoeuvre
    constant = np.column_stack([rec.currents[:, 0], np.full(len(rec), 10.0)])
    data = sim.run(truth.attitudes, 3, currents=constant)[0]
    result = calibrate_array(data.vectors, sim.geometry, F, currents=constant, channels=CHANNELS)
    assert result.calibration.channels == CHANNELS[:1]
    assert result.warnings[0].startswith("interference not solved (undetermined): thruster2/battery (10 A) never varied")
    assert result.calibration.metadata["interference_undetermined"] == ["thruster2/battery"]
    # the constant current's field went into the offsets: valid at that current
    b = result.calibration.apply(data.vectors, constant[:, :1])
    assert np.all(tmi_rms(b, F) < 1.1 * tmi_rms(truth.calibration.apply(data.vectors, constant), F))

    lockstep = np.column_stack([rec.currents[:, 0], rec.currents[:, 0]])
    data = sim.run(truth.attitudes, 3, currents=lockstep)[0]
    # Without the channels the thrusters' varying field makes the field over the array far from
    # uniform (hundreds of nT/m): refused, naming both causes (it used to be accepted, corrupted).
    with pytest.raises(CalibrationFailed) as err:
        calibrate_array(data.vectors, sim.geometry, F, currents=lockstep, channels=CHANNELS)
    assert "thruster1/battery, thruster2/battery varied in lockstep" in str(err.value)
    assert "the field is not uniform where you calibrate" in str(err.value) and "currents near the array" in str(err.value)


# -- through the command line: bags with BatteryState and Float64 channels, CSV ----------------
def with_float64_channel(src: Path, dst: Path, storage: str, lead_ns: int, skip_every: int = 0) -> None:
    """Copy a bag, turning /thruster2/battery (BatteryState) into /thruster2/current (Float64, no
    header: stamped by its bag time, ``lead_ns`` before the set it belongs to); with
    ``skip_every`` k, every k-th of those messages is lost."""
    ts = cdr.typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=plugin) as writer:
        out = {}
        for c in reader.connections:
            if c.topic == "/thruster2/battery":
                out[c.id] = writer.add_connection("/thruster2/current", cdr.FLOAT64, typestore=ts)
            else:
                out[c.id] = writer.add_connection(c.topic, c.msgtype, typestore=ts)
        count = 0
        for c, t, data in reader.messages():
            if c.topic == "/thruster2/battery":
                count += 1
                if skip_every and count % skip_every == 0:
                    continue
                msg = ts.deserialize_cdr(data, c.msgtype)
                data = ts.serialize_cdr(ts.types[cdr.FLOAT64](data=float(msg.current)), cdr.FLOAT64)
                t -= lead_ns
            writer.write(out[c.id], t, data)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bags_with_battery_state_and_float64_channels_via_the_cli(tmp_path: Path, storage: str) -> None:
    sim_bag = tmp_path / "rotation_sim"
    ok(magcal("simulate", sim_bag, "--count", SETS, "--seed", SEED, "--noise", NOISE, "--storage", storage,
              *THRUSTER_ARGS, "--thruster-current", f"random:{IMAX:g}"))
    realistic_stamps(sim_bag, SEED)  # currents: header stamp 0.3 ms before the set, bag time 2-6 ms after it
    with Reader(sim_bag) as reader:
        types = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
    assert types["/thruster1/battery"] == (cdr.BATTERY_STATE, SETS)
    true_cal = calfile.read(truth_paths(sim_bag)[0])
    assert true_cal.channels == CHANNELS
    bag = tmp_path / "rotation"
    with_float64_channel(sim_bag, bag, storage, lead_ns=30_000_000)
    currents = "/thruster1/battery,/thruster2/current"
    cal_path = tmp_path / "cal.yaml"
    proc = ok(magcal("calibrate", bag, "-o", cal_path, "--reference-field", F, "--currents", currents,
                     "--plot", tmp_path / "cal.png"))
    assert "interference of thruster1/battery, thruster2/current estimated" in proc.stdout
    assert (tmp_path / "cal.png").read_bytes()[:4] == b"\x89PNG"
    cal = calfile.read(cal_path)
    assert cal.channels == ("thruster1/battery", "thruster2/current")
    truth = ArrayCalibration(true_cal.geometry, true_cal.matrices, true_cal.offsets, {}, None, cal.channels,
                             true_cal.interference)
    assert np.all(relative_gain_error(cal, truth) < 0.01)

    # fresh attitudes and currents of the same sensors, as a bag with the same two channel types
    sim, _ = build(SimulationSpec(count=1, seed=SEED, noise=NOISE, thrusters=THRUSTERS))
    fresh, fresh_truth = fresh_run(sim, 1000, 31)
    write_recording_bag(tmp_path / "survey_sim", fresh, storage)  # type: ignore[arg-type]
    sensor_stamps = realistic_stamps(tmp_path / "survey_sim", SEED + 1)
    survey = tmp_path / "survey"
    with_float64_channel(tmp_path / "survey_sim", survey, storage, lead_ns=30_000_000)
    out = tmp_path / "corrected"
    proc = ok(magcal("correct", survey, "-c", cal_path, "-o", out, "--currents", currents))
    assert "corrected 1000 sets" in proc.stdout
    res = read_corrected(out)
    np.testing.assert_array_equal(res["stamps"], fresh.stamps)
    np.testing.assert_array_equal(res["sensor_stamps"], np.stack([sensor_stamps[n] for n in fresh.names], axis=1))
    true_b = fresh_truth.calibration.apply(fresh.vectors, fresh.currents)
    assert np.all(tmi_rms(res["sensors"], F) < 1.1 * tmi_rms(true_b, F))
    g_true = tensor_rms(gradient_difference(true_b, sim.geometry))
    assert tensor_rms(res["gradient"]) < 1.1 * g_true
    # bag in, CSV out: the same numbers
    ok(magcal("correct", survey, "-c", cal_path, "-o", tmp_path / "corrected.csv", "--currents", currents))
    np.testing.assert_allclose(read_corrected(tmp_path / "corrected.csv")["gradient"], res["gradient"], atol=1e-15)

    # Lost Float64 values: with a 50 ms tolerance their sets are dropped and counted (the previous
    # value is 130 ms old), the others corrected as before.
    lossy = tmp_path / "lossy"
    with_float64_channel(tmp_path / "survey_sim", lossy, storage, lead_ns=30_000_000, skip_every=10)
    proc = ok(magcal("correct", lossy, "-c", cal_path, "-o", tmp_path / "lossy.csv", "--currents", currents,
                     "--current-tolerance", "0.05"))
    assert "corrected 900 sets" in proc.stdout
    assert ("note: 100 of 1000 sets dropped without a current of every channel within 0.05 s before the set "
            "(thruster2/current: 100)") in proc.stderr
    kept = np.arange(1000) % 10 != 9
    np.testing.assert_allclose(read_corrected(tmp_path / "lossy.csv")["gradient"], res["gradient"][kept], atol=1e-15)
    # values 30 ms old with a 10 ms tolerance: no set left, one line, no output
    proc = magcal("correct", survey, "-c", cal_path, "-o", tmp_path / "strict", "--currents", currents,
                  "--current-tolerance", "0.01")
    assert proc.returncode == 2 and "1000 of 1000 sets dropped" in proc.stderr and "no set left" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "strict").exists()


def test_correct_needs_the_calibrations_channels(tmp_path: Path) -> None:
    sim, _ = build(SimulationSpec(count=1, seed=SEED, noise=NOISE, thrusters=THRUSTERS))
    fresh, truth = fresh_run(sim, 50, 3)
    cal_path = tmp_path / "truth.yaml"
    calfile.write(cal_path, truth.calibration)
    bag, csv = tmp_path / "survey", tmp_path / "survey.csv"
    write_recording_bag(bag, fresh)
    write_csv(csv, fresh)
    write_csv(tmp_path / "no_currents.csv", Recording(fresh.names, fresh.stamps, fresh.vectors))
    cases = [
        (bag, [], "subtracts the interference of thruster1/battery, thruster2/battery: no current of thruster1/battery, "
                  "thruster2/battery (given: none); give them as --currents"),
        (bag, ["--currents", "/thruster1/battery"], "no current of thruster2/battery (given: thruster1/battery)"),
        (bag, ["--currents", "/thruster1/battery,/thruster2/battery,/pump"], "has no interference for pump"),
        (csv, ["--currents", "/thruster1/battery"], "--currents names bag topics"),
        (tmp_path / "no_currents.csv", [], "give them as current.<channel> columns"),
    ]
    for source, extra, message in cases:
        out = tmp_path / "out.csv"
        proc = magcal("correct", source, "-c", cal_path, "-o", out, *extra)
        assert proc.returncode == 2 and message in proc.stderr, (extra, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1 and not out.exists()
    # CSV with its current columns: corrected with the truth to the noise
    ok(magcal("correct", csv, "-c", cal_path, "-o", tmp_path / "ok.csv"))
    res = read_corrected(tmp_path / "ok.csv")
    np.testing.assert_allclose(res["sensors"], truth.calibration.apply(fresh.vectors, fresh.currents), atol=1e-15)
    # A calibration without channels ignores current columns
    plain = ArrayCalibration(sim.geometry, truth.calibration.matrices, truth.calibration.offsets)
    calfile.write(tmp_path / "plain.yaml", plain)
    ok(magcal("correct", csv, "-c", tmp_path / "plain.yaml", "-o", tmp_path / "plain.csv"))
    np.testing.assert_allclose(read_corrected(tmp_path / "plain.csv")["sensors"], plain.apply(fresh.vectors), atol=1e-15)


def test_stepped_thrusters_on_a_still_vehicle_after_a_rotation_calibration(tmp_path: Path) -> None:
    """Rotation calibration without currents, then a still run with stepped thrusters (CLI, CSV)."""
    rotation, steps = tmp_path / "rotation.csv", tmp_path / "steps.csv"
    ok(magcal("simulate", rotation, "--count", 800, "--seed", SEED, "--noise", NOISE))
    ok(magcal("calibrate", rotation, "-o", tmp_path / "cal.yaml", "--reference-field", F))
    proc = ok(magcal("simulate", steps, "--count", 480, "--seed", SEED, "--noise", NOISE, "--still", *THRUSTER_ARGS,
                     "--thruster-current", "steps:0,5,10,20", "--step-sets", 30))
    assert "still" in proc.stdout
    truth = load_truth(steps)
    assert np.ptp(truth["attitudes"], axis=0).max() == 0 and truth["channels"].tolist() == list(CHANNELS)
    assert len({tuple(u) for u in truth["currents"]}) == 16  # every pair of levels
    proc = ok(magcal("calibrate", steps, "-o", tmp_path / "with_thrusters.yaml", "--interference-only",
                     tmp_path / "cal.yaml"))
    assert "interference of 2 channels from a still run of 480 sets" in proc.stdout
    held = calfile.read(tmp_path / "cal.yaml")
    cal = calfile.read(tmp_path / "with_thrusters.yaml")
    np.testing.assert_array_equal(cal.matrices, held.matrices)
    np.testing.assert_array_equal(cal.offsets, held.offsets)
    true_cal = calfile.read(truth_paths(steps)[0])
    assert np.all(relative_gain_error(cal, true_cal) < 0.02)
    # and the result corrects a fresh manoeuvre with random currents to the floor
    sim, _ = build(SimulationSpec(count=1, seed=SEED, noise=NOISE, thrusters=THRUSTERS))
    fresh, fresh_truth = fresh_run(sim, 2000, 41)
    b = cal.apply(fresh.vectors, fresh.currents)
    true_b = fresh_truth.calibration.apply(fresh.vectors, fresh.currents)
    assert tensor_rms(gradient_difference(b, sim.geometry)) < 1.1 * tensor_rms(gradient_difference(true_b, sim.geometry))
    # without the currents it cannot run
    proc = magcal("calibrate", rotation, "-o", tmp_path / "x.yaml", "--interference-only", tmp_path / "cal.yaml")
    assert proc.returncode == 2 and "--interference-only needs the currents" in proc.stderr


def test_simulate_thruster_options_are_checked(tmp_path: Path) -> None:
    for extra, message in [
        (["--thruster", "1,2,3"], "--thruster must be 6"),
        (["--thruster=0.2,0,0,1,0,0"], "thruster thruster1/battery lies on a sensor"),
        ([*THRUSTER_ARGS, "--thruster-current", "sometimes:5"], "--thruster-current must be random:IMAX (IMAX >= 0) or steps"),
        ([*THRUSTER_ARGS, "--thruster-current", "steps:1,2", "--step-sets", "0"], "--step-sets must be at least 1"),
    ]:
        proc = magcal("simulate", tmp_path / "x.csv", "--count", 10, *extra)
        assert proc.returncode == 2 and message in proc.stderr, proc.stderr
        assert not (tmp_path / "x.csv").exists()
    rec = read_recording(ok_path(tmp_path / "r.csv", "--count", 10, *THRUSTER_ARGS, "--thruster-current", "steps:1,2",
                                 "--step-sets", 2))
    np.testing.assert_array_equal(rec.currents[:, 0], [1, 1, 2, 2, 1, 1, 2, 2, 1, 1])
    np.testing.assert_array_equal(rec.currents[:, 1], [1, 1, 1, 1, 2, 2, 2, 2, 1, 1])


def ok_path(path: Path, *args: object) -> Path:
    ok(magcal("simulate", path, *args))
    return path


PAYLOADS = ((-0.7, 0.25, 0.1, 0.0, 0.0, 0.07), (-0.7, -0.25, 0.1, 0.0, 0.0, 0.07))
"""Two payloads behind the cross, 9-40 nT/A at the sensors (about 20 nT/A on average)."""
PAYLOAD_CHANNELS = ("payload1", "payload2")
PAYLOAD_NOISE = 0.01  # A, 1 sigma: the current monitors' reading noise


def test_a_current_within_its_reading_noise_is_undetermined() -> None:
    """payload1 steps 1 <-> 3 A every 25 sets; payload2 is off: its monitor reads N(0, 0.01 A) only. The
    first is determined and its gains recovered within their uncertainty; the second is undetermined
    (its interference not applied), whereas the old rule (variation above 1 mA) estimated it."""
    sim, _ = build(SimulationSpec(count=1, seed=SEED, noise=NOISE, thrusters=PAYLOADS))
    assert 15e-9 < np.linalg.norm(sim.interference(), axis=1).mean() < 25e-9
    n = SETS
    k = np.arange(n)
    true = np.column_stack([np.where((k // 25) % 2, 3.0, 1.0), np.zeros(n)])
    rec, truth = sim.run(uniform_random(n, SEED), SEED + 1, currents=true)
    read = true + np.random.default_rng([SEED, 3]).normal(0.0, PAYLOAD_NOISE, (n, 2))
    np.testing.assert_array_equal(undetermined_channels(read), [False, True])

    result = calibrate_array(rec.vectors, sim.geometry, F, currents=read, channels=PAYLOAD_CHANNELS)
    cal = result.calibration
    assert cal.channels == ("payload1",)
    assert cal.metadata["interference_undetermined"] == ["payload2"]
    assert result.warnings[0].startswith("interference not solved (undetermined): payload2 (")
    assert "varied only within its reading noise" in result.warnings[0]
    truth_cal = ArrayCalibration(sim.geometry, truth.calibration.matrices, truth.calibration.offsets, {}, None,
                                 ("payload1",), truth.calibration.interference[:, :, :1])
    error = (in_true_frame(cal, truth_cal) - truth_cal.interference)[:, :, 0]  # (S, 3) T/A
    sigma = np.array([next(q.sigma for q in result.identifiability.quantities
                            if q.sensor == name and q.name == f"interference payload1 {axis}")
                      for name in sim.geometry.names for axis in "xyz"]).reshape(-1, 3) * 1e-9  # nT/A -> T/A
    assert np.all(np.abs(error) < 4.0 * sigma), (error / sigma)

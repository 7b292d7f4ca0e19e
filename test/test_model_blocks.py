"""The forward model's temperature and lag blocks against simulated truth, and drift named as drift.

The references are the simulator's own: its temperature coefficients (offset per kelvin in raw axes,
gain per kelvin of each raw axis), each sensor's lag, and the noise floor ``sqrt(2) sigma / d``. A
corrected vector is ``(M + dT M1) (r - o - dT c)`` written out here in numpy (``M1 = -M diag(g)``).
"""

from __future__ import annotations

import numpy as np
import pytest
import truth_tools as tt

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.sync import synchronise_streams
from magcal_ros.core.units import NT
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.sim.attitudes import tumble, uniform_random, yaw_pitch_roll
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors
from magcal_ros.sim.streams import StreamSpec, simulate_streams
from magcal_ros.sim.temperature import draw_tempcos, temperature_profile

F = 50_000 * NT
NOISE = 1 * NT
GEO = ArrayGeometry.cross()
FLOOR = tt.difference_floor(NOISE, 0.4)


def thermal_array(seed: int, offset_sd: float = 0.5 * NT, gain_sd: float = 30e-6) -> ArraySimulation:
    """Four fluxgates whose offsets and gains follow their temperature (reference 15 C)."""
    rng = np.random.default_rng(seed)
    sensors = tuple(random_sensor_errors(rng, hard_iron_sd=100 * NT, soft_iron_sd=0.01) for _ in range(4))
    a, g = draw_tempcos(np.random.default_rng(seed + 100), 4, offset_sd, gain_sd)
    return ArraySimulation(GEO, sensors, earth_field(F, 60.0, -5.0), noise=NOISE, offset_tempco=a, gain_tempco=g,
                           temperature_reference=15.0)


def corrected(cal_matrices: np.ndarray, offsets: np.ndarray, m1: np.ndarray, c: np.ndarray, ref: float,
              raw: np.ndarray, temps: np.ndarray) -> np.ndarray:
    """``(M + dT M1)(r - o - dT c)`` per sensor and set, written out."""
    dt = temps - ref
    out = np.empty_like(raw)
    for i in range(raw.shape[1]):
        m = cal_matrices[i][None] + dt[:, i, None, None] * m1[i][None]
        out[:, i] = np.einsum("nab,nb->na", m, raw[:, i] - offsets[i] - dt[:, i, None] * c[i])
    return out


def fresh_scores(sim: ArraySimulation, m: np.ndarray, o: np.ndarray, m1: np.ndarray, c: np.ndarray,
                 ref: float) -> tuple[float, float]:
    """(worst sensor's TMI RMS, tensor RMS) in T and T/m on 2,000 fresh attitudes at 2-28 C."""
    temps = np.random.default_rng(8).uniform(2.0, 28.0, 2000)
    rec, _ = sim.run(uniform_random(2000, 7), 9, temperatures=temps)
    b = corrected(m, o, m1, c, ref, rec.vectors, rec.temperatures)
    tmi = float(np.max(tt.rms(np.linalg.norm(b, axis=2) - F, axis=0)))
    return tmi, float(tt.rms(tt.cross_difference(b, GEO.positions)))


def three_temperature_tumble(sim: ArraySimulation, seed: int, sets: int = 1500):
    """Tumbles at 5, 15 and 25 C, one after the other (in time order, 7.5 sets/s)."""
    temps = temperature_profile("steps", [5, 15, 25], sets)
    return sim.run(tumble(sets, rng=seed), seed + 1, temperatures=temps, rate=7.5)


def test_tumbles_at_three_temperatures_give_the_temperature_terms_and_reach_the_true_calibration() -> None:
    """Tumbles at 5, 15 and 25 C (1,500 sets); on fresh attitudes at 2-28 C TMI and tensor within 1.1x of
    the true temperature-aware calibration (measured 1.00x / 1.00x), where the same calibration without
    temperature terms is 10x / 8x. Each coefficient within 4 of its stated 1-sigma of the truth."""
    sim = thermal_array(1)
    rec, _ = three_temperature_tumble(sim, 1)
    res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps, temperatures=rec.temperatures)
    cal = res.calibration
    assert cal.has_temperature_terms and cal.temperature_reference == pytest.approx(15.0)
    true_m, true_o = tt.true_correction(sim)
    a, g = sim.offset_tempco, sim.gain_tempco
    true_m1 = -true_m * g[:, None, :]
    truth = fresh_scores(sim, true_m, true_o, true_m1, a, sim.temperature_reference)
    got = fresh_scores(sim, cal.matrices, cal.offsets, cal.matrix_tempco, cal.offset_tempco, cal.temperature_reference)
    assert truth[0] < 1.2 * NOISE and truth[1] < 1.1 * FLOOR  # the reference itself at the floor
    assert got[0] < 1.1 * truth[0] and got[1] < 1.1 * truth[1], (got, truth)
    plain = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps).calibration
    zeros = np.zeros_like(true_m1)
    without = fresh_scores(sim, plain.matrices, plain.offsets, zeros, np.zeros((4, 3)), 15.0)
    assert without[0] > 3 * truth[0] and without[1] > 3 * truth[1]  # the terms matter here
    # the coefficients themselves, in the units users read
    for i, name in enumerate(GEO.names):
        for k, axis in enumerate("xyz"):
            qo = res.identifiability.by_name(name, f"offset tempco {axis}")
            qg = res.identifiability.by_name(name, f"gain tempco {axis}")
            assert qo.unit == "nT/K" and abs(qo.value - a[i, k] / NT) < 4 * qo.sigma, (qo, a[i, k] / NT)
            assert qg.unit == "ppm/K" and abs(qg.value - g[i, k] * 1e6) < 4 * qg.sigma, (qg, g[i, k] * 1e6)
            assert 0.001 < qo.sigma < 0.05 and 0.01 < qg.sigma < 2  # nT/K, ppm/K: about sigma / (sqrt(N) rms dT)
    assert "temperature terms fitted over 5.0..25.0 C (reference 15.0 C)" in res.summary()
    assert cal.metadata["temperature_range"] == [5.0, 25.0]


def test_the_stated_sigma_of_the_temperature_coefficients_matches_their_spread() -> None:
    """Monte Carlo, 10 runs of the same three-temperature tumble (900 sets): each coefficient's stated
    1-sigma over its actual spread, median within 1/1.5 .. 1.5."""
    sim = thermal_array(3)
    rng = np.random.default_rng(5)
    att = tumble(900, rng=5)
    temps = temperature_profile("steps", [5, 15, 25], 900)
    values, sigmas = [], []
    for _ in range(10):
        rec, _ = sim.run(att, rng, temperatures=temps, rate=7.5)
        res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps, temperatures=rec.temperatures)
        qs = [q for q in res.identifiability.quantities if "tempco" in q.name]
        values.append([q.value for q in qs])
        sigmas.append([q.sigma for q in qs])
    ratio = np.mean(sigmas, axis=0) / np.std(values, axis=0, ddof=1)
    assert len(ratio) == 24
    assert 1 / 1.5 < np.median(ratio) < 1.5, np.round(ratio, 2)


def test_temperatures_that_barely_change_fit_no_temperature_terms_and_say_why() -> None:
    sim = thermal_array(2)
    rec, _ = sim.run(tumble(900, rng=2), 3, temperatures=np.full(900, 15.3), rate=7.5)
    res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps, temperatures=rec.temperatures)
    assert not res.calibration.has_temperature_terms
    assert "temperature span 0.0 K: too small to determine temperature coefficients" in res.summary()


def test_a_temperature_change_not_crossed_with_attitude_holds_the_gains_at_zero_and_names_them() -> None:
    """The temperature changes only while the vehicle sits still: the offsets per kelvin are determined
    (the readings move with temperature), the gains per kelvin are not (no attitude to scale): held at 0."""
    sim = thermal_array(4)
    turning = tumble(900, rng=4)
    still = np.repeat(turning[-1:], 300, axis=0)
    att = np.concatenate([turning, still])
    temps = np.concatenate([np.full(900, 15.0), np.linspace(15.0, 25.0, 300)])
    rec, _ = sim.run(att, 5, temperatures=temps, rate=7.5)
    res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps, temperatures=rec.temperatures)
    held = {(q.sensor, q.name) for q in res.identifiability.held()}
    assert any(name.startswith("gain tempco") for _, name in held)
    assert "not determined, held at zero" in res.summary()
    assert res.calibration.metadata["held"]


def smooth_turns(duration: float, seed: int, hz: float = 200.0) -> np.ndarray:
    """A smooth manoeuvre: 1 rad/s of yaw with pitch and roll swinging +-50 deg and more."""
    t = np.arange(int(duration * hz) + 3) / hz
    ph = np.random.default_rng(seed).uniform(0, 2 * np.pi, 4)
    pitch = 40 * np.sin(2 * np.pi * 0.05 * t + ph[0]) + 15 * np.sin(2 * np.pi * 0.13 * t + ph[1])
    roll = 50 * np.sin(2 * np.pi * 0.037 * t + ph[2]) + 20 * np.sin(2 * np.pi * 0.11 * t + ph[3])
    return yaw_pitch_roll(np.degrees(t), pitch, roll)


def test_a_sensor_reading_5_ms_late_is_found_and_applied_keeps_the_tensor_at_the_floor() -> None:
    """mag3's readings lag its stamps by 5 ms, the vehicle turning at 1 rad/s (60 s at 100 Hz): the lag
    is found to 0.05 ms with an honest 1-sigma, said in words and stored; with it applied to fresh
    streams the tensor is within 1.3x the floor (measured 0.94x), where ignoring it leaves 40x."""
    rng = np.random.default_rng(11)
    sensors = tuple(random_sensor_errors(rng, hard_iron_sd=100 * NT, soft_iron_sd=0.01) for _ in range(4))
    sim = ArraySimulation(GEO, sensors, earth_field(F, 60.0, -5.0), noise=NOISE)
    lags = (0.0, 0.0, 0.005, 0.0)

    def sets(seconds: float, seed: int, offsets: list[float] | None):
        streams = simulate_streams(sim, smooth_turns(seconds, seed), 200.0, StreamSpec(rate=100.0, lags=lags),
                                   seconds, rng=seed + 1)
        batch, _, _ = synchronise_streams([(s.stamps, s.vectors) for s in streams.streams], offsets,
                                          mode="exact" if offsets is None else "interpolate", names=streams.names)
        return batch

    batch = sets(60.0, 1, None)
    res = calibrate_array(batch.vectors, GEO, F, stamps=batch.set_stamps)
    q = res.identifiability.by_name("mag3", "time offset")
    assert q.unit == "ms" and abs(q.value - 5.0) < max(4 * q.sigma, 0.05), q
    assert 1e-4 < q.sigma < 0.05
    others = [res.identifiability.by_name(n, "time offset") for n in ("mag2", "mag4")]
    assert all(abs(o.value) < max(4 * o.sigma, 0.02) for o in others)
    assert res.calibration.time_offsets[2] == pytest.approx(0.005, abs=5e-5)
    assert "mag3 reads 5.00 +- " in res.summary() and " ms late" in res.summary()
    assert res.calibration.metadata["lags"][0].startswith("mag3 reads 5.00")
    fresh = sets(30.0, 50, list(res.calibration.time_offsets))
    tensor = tt.rms(tt.cross_difference(res.calibration.apply(fresh.vectors), GEO.positions))
    assert tensor < 1.3 * FLOOR, tensor / FLOOR
    stale = sets(30.0, 50, None)
    assert tt.rms(tt.cross_difference(res.calibration.apply(stale.vectors), GEO.positions)) > 10 * FLOOR


def test_random_attitudes_switch_on_no_lag_or_temperature_block() -> None:
    """Sets in no time order (independent attitudes) cannot show a lag: the model is the sensor block only."""
    rng = np.random.default_rng(3)
    sensors = tuple(random_sensor_errors(rng, hard_iron_sd=100 * NT, soft_iron_sd=0.01) for _ in range(4))
    sim = ArraySimulation(GEO, sensors, earth_field(F, 60.0, -5.0), noise=NOISE)
    rec, _ = sim.run(uniform_random(600, 4), 5)
    res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps)
    assert not any(q.name == "time offset" for q in res.identifiability.quantities)
    assert not np.any(res.calibration.time_offsets)


def test_offsets_that_wander_with_an_unrecorded_temperature_are_named_as_drift() -> None:
    """The sensors warm by 20 K during one continuous tumble and no temperature is recorded: the output
    says the offsets drift with time (and what to do), not that the noise is correlated."""
    sim = thermal_array(1)
    temps = temperature_profile("ramp", [5, 25], 1500)
    rec, _ = sim.run(tumble(1500, rng=1), 2, temperatures=temps, rate=7.5)
    res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps)
    text = res.summary()
    assert "offsets drift with time" in text and "record the sensors' temperature" in text
    assert any("drift with time: about" in w for w in res.warnings)
    assert not any("time-correlated noise" in w for w in res.warnings)
    assert res.calibration.metadata["drift"]


def test_a_clean_tumble_names_no_drift() -> None:
    sim = thermal_array(1, offset_sd=0.0, gain_sd=0.0)
    rec, _ = sim.run(tumble(1500, rng=1), 2, rate=7.5)
    res = calibrate_array(rec.vectors, GEO, F, stamps=rec.stamps)
    assert "drift" not in res.summary() and not any("drift" in w for w in res.warnings)


def test_direction_rates_match_the_motion_and_do_not_depend_on_the_block_size(monkeypatch: pytest.MonkeyPatch) -> None:
    """The lag block's field-direction rates: a steady turn at 0.5 rad/s about z (a gap splits it) gives
    0.5 rad/s perpendicular to the direction away from the gap; computed a block of sets at a time (memory
    bounded on long recordings), exactly what one block gives."""
    from magcal_ros.core import array_fit

    t = np.concatenate([np.arange(300) * 0.02, 10.0 + np.arange(200) * 0.02])
    angle = 0.5 * t
    d = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(t)], axis=1)
    whole = array_fit.direction_rates(d, t)
    speed = np.linalg.norm(whole, axis=1)
    assert np.allclose(speed[5:290], 0.5, rtol=1e-3) and np.allclose(speed[305:495], 0.5, rtol=1e-3)
    assert np.allclose(np.sum(whole * d, axis=1), 0.0, atol=1e-12)
    monkeypatch.setattr(array_fit, "RATE_BLOCK", 7)
    np.testing.assert_array_equal(array_fit.direction_rates(d, t), whole)
    shuffled = np.random.default_rng(3).permutation(len(t))  # sets in any order: each its own rate
    np.testing.assert_array_equal(array_fit.direction_rates(d[shuffled], t[shuffled]), whole[shuffled])
    lone = np.concatenate([t[:300], [8.0], t[300:]])  # a set with no neighbour in reach: no rate
    d_lone = np.concatenate([d[:300], [[0.0, 0.0, 1.0]], d[300:]])
    rates = array_fit.direction_rates(d_lone, lone)
    assert np.all(rates[300] == 0.0) and np.allclose(np.linalg.norm(rates[5:290], axis=1), 0.5, rtol=1e-3)

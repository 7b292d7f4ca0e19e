"""The progress analysis of a manoeuvre being collected (:func:`magcal_ros.methods.progress.assess`),
against the calibration itself and simulated truth: it is ready exactly when a calibration of
the same sets would pass, its envelope contains what was flown, and flying its advice gets a
manoeuvre that was not enough to one that is.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from test_field import moved_hard_iron  # noqa: F401 - the fixture: hard iron moved, then a yaw circle

from magcal_ros.core import identifiability as ident
from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.errors import MagcalError
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.methods.progress import MAX_SETS, assess
from magcal_ros.sim.attitudes import (
    sea_manoeuvre,
    single_axis,
    uniform_random,
    yaw_pitch_roll,
)
from magcal_ros.sim.simulator import ArraySimulation, Thruster, random_sensor_errors

NT = 1e-9
F = 51_500 * NT
TILT_ADVICE = re.compile(r"^(pitch nose down|pitch nose up|roll to port|roll to starboard) 15 deg and keep turning$")


def array(seed: int, geometry: ArrayGeometry | None = None, **kw: object) -> ArraySimulation:
    rng = np.random.default_rng(seed)
    geo = geometry or ArrayGeometry.cross()
    return ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(F, 60.0, 5.0),
                           noise=1 * NT, **kw)  # type: ignore[arg-type]


def calibrates(raw: np.ndarray, sim: ArraySimulation, stamps: np.ndarray, **kw: object) -> bool:
    try:
        calibrate_array(raw, sim.geometry, F, stamps=stamps, **kw)  # type: ignore[arg-type]
        return True
    except MagcalError:
        return False


MANOEUVRES = {
    "tumble": lambda rng: uniform_random(400, rng),
    "yaw only": lambda rng: sea_manoeuvre(600, 0, 0, turns=2, wobble_deg=3, rng=rng),
    "glider 5/2": lambda rng: sea_manoeuvre(600, 5, 2, turns=2, rng=rng),
    "sea 10/4": lambda rng: sea_manoeuvre(900, 10, 4, turns=2, wobble_deg=2, rng=rng),
    "sea 15/5": lambda rng: sea_manoeuvre(600, 15, 5, turns=2, rng=rng),
    "single axis": lambda rng: single_axis("z", 360),
}


@pytest.mark.parametrize("name", list(MANOEUVRES))
def test_ready_exactly_when_the_calibration_of_the_same_sets_passes(name: str) -> None:
    decisions = []
    for seed in range(2):
        sim = array(seed)
        rng = np.random.default_rng(100 + seed)
        rec, _ = sim.run(MANOEUVRES[name](rng), rng)
        a = assess(rec.vectors, sim.geometry, F, stamps=rec.stamps)
        ok = calibrates(rec.vectors, sim, rec.stamps)
        decisions.append((a.ready, ok))
        assert a.ready == ok, (name, seed, a)
        assert a.samples == len(rec) <= MAX_SETS
        if ok:
            assert not a.undetermined and a.advice.startswith("enough for a calibration")
        else:
            assert a.undetermined and TILT_ADVICE.match(a.advice), a.advice
    if name in ("tumble", "sea 15/5", "glider 5/2"):
        assert decisions == [(True, True)] * 2
    if name in ("yaw only", "single axis"):
        assert decisions == [(False, False)] * 2
    if name == "glider 5/2":  # weak: ready, with the tilt that widens the envelope
        assert re.fullmatch(r"enough for a calibration valid near the attitudes flown: call ~/calibrate; to widen its "
                            r"envelope, (pitch nose (down|up)|roll to (port|starboard)) 15 deg and keep turning",
                            a.advice), a.advice


def test_the_envelope_so_far_contains_what_was_flown_and_matches_the_calibration() -> None:
    sim = array(3)
    rng = np.random.default_rng(3)
    rec, _ = sim.run(sea_manoeuvre(600, 30, 15, turns=2, rng=rng), rng)
    a = assess(rec.vectors, sim.geometry, F, stamps=rec.stamps)
    res = calibrate_array(rec.vectors, sim.geometry, F, stamps=rec.stamps)
    assert a.envelope is not None and not a.envelope.whole_sphere
    assert a.envelope.pitch_deg >= 30 and a.envelope.roll_deg >= 15
    assert abs(a.envelope.pitch_deg - res.envelope.pitch_deg) <= 2 and abs(a.envelope.roll_deg - res.envelope.roll_deg) <= 2
    assert re.fullmatch(r"valid within pitch \+-\d+ deg, roll \+-\d+ deg", a.envelope_text())
    tumble = assess(*sim.run(uniform_random(300, rng), rng)[0].vectors[None], sim.geometry, F)
    assert tumble.envelope is not None and tumble.envelope_text() == "valid over the whole sphere"


def test_following_the_advice_turns_a_yaw_circle_into_a_calibration() -> None:
    """A yaw circle is not enough; each round flies the advised tilt through another circle (with
    a few degrees of wobble) until the analysis says enough; then the calibration passes, its
    envelope takes in the tilts flown, and inside it the TMI error is at the noise."""
    sim = array(5)
    rng = np.random.default_rng(5)
    rec, _ = sim.run(sea_manoeuvre(300, 0, 0, turns=1, wobble_deg=3, rng=rng), rng)
    raw, stamps = rec.vectors, rec.stamps
    advised = []
    for step in range(6):
        a = assess(raw, sim.geometry, F, stamps=stamps)
        if a.ready:
            break
        assert TILT_ADVICE.match(a.advice), a.advice
        advised.append(a.advice)
        words = a.advice.split(" 15 deg")[0]
        pitch, roll = next((p, r) for w, p, r in ident.CANDIDATES if w == words)
        yaw = np.linspace(0, 360, 300) + rng.uniform(0, 360)
        wobble = 3 * np.sin(np.linspace(0, 20, 300))
        more, _ = sim.run(yaw_pitch_roll(yaw, pitch + wobble, roll + wobble[::-1]), rng, start=100.0 * (step + 1))
        raw, stamps = np.concatenate([raw, more.vectors]), np.concatenate([stamps, more.stamps])
    assert a.ready and a.advice.startswith("enough"), advised
    assert 1 <= len(advised) <= 4, advised
    res = calibrate_array(raw, sim.geometry, F, stamps=stamps)
    env = res.envelope
    assert env.pitch_deg >= 5 and env.roll_deg >= 5, env  # the yaw circle alone: valid at no attitude
    assert abs(a.envelope.pitch_deg - env.pitch_deg) <= 2 and abs(a.envelope.roll_deg - env.roll_deg) <= 2  # type: ignore[union-attr]
    inside = yaw_pitch_roll(rng.uniform(0, 360, 2000), rng.uniform(-env.pitch_deg, env.pitch_deg, 2000),
                            rng.uniform(-env.roll_deg, env.roll_deg, 2000))
    fresh, _ = sim.run(inside, rng)
    b = res.calibration.apply(fresh.vectors)
    tmi = np.sqrt(np.mean((np.linalg.norm(b, axis=-1) - F) ** 2))
    assert tmi < 1.3 * NT, tmi / NT  # 1 nT noise: at the floor inside the envelope


def test_with_a_prior_a_yaw_circle_is_enough_and_says_what_the_prior_keeps(moved_hard_iron: dict) -> None:  # noqa: F811
    """The hull's hard iron moved after a full calibration; a yaw circle (test_field's scenario)."""
    first, new, yaw = moved_hard_iron["first"], moved_hard_iron["new"], moved_hard_iron["yaw"]
    without = assess(yaw.vectors, new.geometry, F, stamps=yaw.stamps)
    assert not without.ready and "scale z" in without.undetermined and TILT_ADVICE.match(without.advice)
    a = assess(yaw.vectors, new.geometry, F, first, yaw.stamps)
    assert a.ready and "scale z" in a.undetermined and "offset z" not in a.undetermined
    assert a.advice.startswith("enough to recalibrate from the prior") and "keeps" in a.advice and "scale z" in a.advice
    assert a.envelope is not None and a.envelope.pitch_deg >= 15
    assert calibrates(yaw.vectors, new, yaw.stamps, prior=first)


def test_too_few_sets_say_how_many_more() -> None:
    sim = array(6)
    rec, _ = sim.run(uniform_random(5, 6), 6)
    a = assess(rec.vectors, sim.geometry, F)
    assert not a.ready and a.envelope is None and "collect at least 12 sets" in a.advice
    assert a.envelope_text() == "no envelope yet (too few sets)"


def test_one_sensor_and_more_sets_than_the_analysis_uses() -> None:
    sim = array(7, ArrayGeometry.single("mag1"))
    rng = np.random.default_rng(7)
    rec, _ = sim.run(uniform_random(2500, rng), rng)
    a = assess(rec.vectors, sim.geometry, F, stamps=rec.stamps)
    assert a.ready and a.samples == MAX_SETS and a.envelope is not None and a.envelope.whole_sphere
    yaw, _ = sim.run(sea_manoeuvre(600, 0, 0, turns=2, wobble_deg=3, rng=rng), rng)
    b = assess(yaw.vectors, sim.geometry, F, stamps=yaw.stamps)
    assert not b.ready and "scale z" in b.undetermined


def test_thruster_currents_are_fitted_not_taken_for_noise() -> None:
    """Thrusters at 0-20 A add hundreds of nT: given the currents the analysis is ready and the
    envelope covers the sphere; a current that never varies does not block it (the calibration
    leaves such a channel out) but is named."""
    thrusters = (Thruster("t1", np.array([-0.7, 0.1, 0.0]), np.array([0.0, 0.0, 0.5])),
                 Thruster("t2", np.array([-0.7, -0.1, 0.0]), np.array([0.0, 0.3, 0.3])))
    sim = array(8, thrusters=thrusters)
    rng = np.random.default_rng(8)
    u = rng.uniform(0, 20, (800, 2))
    rec, _ = sim.run(uniform_random(800, rng), rng, currents=u)
    a = assess(rec.vectors, sim.geometry, F, stamps=rec.stamps, currents=u, channels=sim.channels)
    assert a.ready and a.envelope is not None and a.envelope.whole_sphere and not a.undetermined
    u[:, 1] = 7.0
    rec, _ = sim.run(uniform_random(800, rng), rng, currents=u)
    b = assess(rec.vectors, sim.geometry, F, stamps=rec.stamps, currents=u, channels=sim.channels)
    assert b.ready and any(q.startswith("interference t2") for q in b.undetermined), b.undetermined

"""The nodes in the field, over DDS, nodes as separate processes: a reference field from the
site, outliers, partial recalibration at sea from the running calibration, progress advice
while collecting, and thruster current interference subtracted live and solved.

One private domain holds two set-ups, each in its own namespace:

- ``/sea``: both nodes; the calibration node takes F from the World Magnetic Model at its
  ``site`` on its ``date``. A full calibration (with spikes) first; then the hull's hard iron
  moves 300-800 nT per axis on every sensor and a yaw-only manoeuvre is replayed: refused
  without a prior (naming the missing pitch and roll), and with the running calibration as the
  prior it recalibrates the offsets and keeps the scale z, to the truth's accuracy over the
  whole sphere;
- ``/thrusters``: two thrusters 0.7 m behind the cross at 0-20 A; currents on BatteryState
  (and Float64) topics. The correction node, loaded with the true interference, subtracts
  the latest currents from every set; a stale current withholds the set; the calibration
  node solves the interference with the calibration.
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass, replace
from datetime import date
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ros_harness as h
from diagnostic_msgs.msg import DiagnosticStatus

from magcal_ros.app.ros_driver import (
    ArrayDriver,
    recording_messages,
    status_values,
    wait_for_samples,
)
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geomagnetic import site_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import rms, tensor_floor
from magcal_ros.core.recording import Recording
from magcal_ros.io import calibration_file as calfile
from magcal_ros.sim.attitudes import sea_manoeuvre, uniform_random
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors
from magcal_ros.sim.spec import SimulationSpec, build

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

NT = 1e-9
SITE = [43.2, 5.4, 0.0]
DATE = "2026-06-01"
FIELD = site_field(*SITE, date(2026, 6, 1))
SEA = "/sea/magcal_calibration"
SEA_CORRECTION = "/sea/magcal_correction"
THR = "/thrusters/magcal_calibration"
THR_CORRECTION = "/thrusters/magcal_correction"
BATTERY = "sensor_msgs/msg/BatteryState"
FLOAT64 = "std_msgs/msg/Float64"
THRUSTERS = ((-0.7, 0.25, 0.1, 0.06, 0.0, 0.04), (-0.7, -0.25, 0.1, 0.0, -0.06, 0.04))
CHANNELS = ("thruster1/battery", "thruster2/battery")
F_THR = 5.5e-5
FLOOR = tensor_floor(h.NOISE, h.BASELINE)
TILT_ADVICE = re.compile(r"^(pitch nose down|pitch nose up|roll to port|roll to starboard) 15 deg and keep turning$")
ENVELOPE = re.compile(r"^(valid within pitch \+-\d+ deg, roll \+-\d+ deg|valid over the whole sphere)$")
CAL_PARAMS = ["sensor_names", "positions"] + [f"mag{i}.{s}" for i in range(1, 5) for s in ("matrix", "offset")]


@dataclass
class Sea:
    sim: ArraySimulation
    manoeuvre: Recording
    spiked: int
    """Readings hit by a spike in the manoeuvre."""
    moved: ArraySimulation
    """The same array after the hard iron moved."""
    yaw: Recording
    file: Path


@dataclass
class Thrusters:
    sim: ArraySimulation
    manoeuvre: Recording
    check: Recording
    true: ArrayCalibration


@pytest.fixture(scope="module")
def sea_data(tmp_path_factory: pytest.TempPathFactory) -> Sea:
    rng = np.random.default_rng(21)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), FIELD.vector, noise=h.NOISE)
    rec, _ = sim.run(uniform_random(1000, rng), rng, rate=50.0)
    vectors = rec.vectors.copy()
    hit = rng.random(vectors.shape[:2]) < 0.02  # 2 % of the readings: spikes of 500-5000 nT
    d = rng.normal(size=vectors.shape)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    vectors[hit] += (d * rng.uniform(500, 5000, vectors.shape[:2])[..., None] * NT)[hit]
    moved = ArraySimulation(geo, tuple(replace(s, hard_iron=s.hard_iron + rng.choice([-1, 1], 3)
                                               * rng.uniform(300, 800, 3) * NT) for s in sim.sensors),
                            sim.earth, noise=sim.noise)
    yaw, _ = moved.run(sea_manoeuvre(600, 0.0, 0.0, turns=2, wobble_deg=3.0, rng=rng), rng, rate=50.0, start=500.0)
    return Sea(sim, Recording(rec.names, rec.stamps, vectors), int(hit.sum()), moved, yaw,
               tmp_path_factory.mktemp("sea") / "calibration.yaml")


@pytest.fixture(scope="module")
def thruster_data() -> Thrusters:
    spec = SimulationSpec(count=1500, seed=5, noise=h.NOISE, intensity=F_THR, thrusters=THRUSTERS,
                          thruster_current="random:20")
    sim, attitudes = build(spec)
    rng = np.random.default_rng(55)
    manoeuvre, _ = sim.run(attitudes, rng, rate=50.0, currents=rng.uniform(0, 20, (1500, 2)))
    check, _ = sim.run(uniform_random(400, rng), rng, rate=50.0, start=2000.0, currents=rng.uniform(0, 20, (400, 2)))
    return Thrusters(sim, manoeuvre, check, sim.true_calibration())


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, sea_data: Sea, thruster_data: Thrusters) -> Any:
    workdir = tmp_path_factory.mktemp("field")
    run = h.RosRun(workdir, domain_id=h.pick_domain_id(seed=os.getpid() + 61))
    fast = {"status_period": 0.25, "sensor_timeout": 0.5, "output_timeout": 1.5}
    reliable = h.LOSSLESS  # a history deeper than any replay: a reliable reader whose history fills loses sets for good
    try:
        run.start("correction_node", params=dict(fast, **h.UNCORRECTED, **reliable), namespace="sea",
                  log_name="sea_correction")
        run.start("calibration_node", namespace="sea", log_name="sea_calibration", params={
            "site": SITE, "date": DATE, "calibration_file": str(sea_data.file), "service_timeout": h.SERVICE_TIMEOUT,
            "progress_period": 0.5, "assess_period": 1.0, **reliable})
        truth = workdir / "thrusters.yaml"
        truth.write_text(calfile.dumps(thruster_data.true, node_name=THR_CORRECTION))
        run.start("correction_node", params=dict(fast, **reliable), params_files=[truth], namespace="thrusters",
                  log_name="thr_correction")
        run.start("calibration_node", namespace="thrusters", log_name="thr_calibration", params=dict(reliable, **{
            "reference_field": F_THR, "interference_channels": list(CHANNELS), "prior": "none",
            "calibration_file": str(workdir / "thr_out.yaml"), "service_timeout": h.SERVICE_TIMEOUT, "progress_period": 0.5}))
        yield run
    finally:
        codes = run.close()
        assert codes and all(c == 0 for c in codes.values()), codes


@pytest.fixture(scope="module")
def sea(world: h.RosRun, sea_data: Sea) -> ArrayDriver:
    d = world.driver(sea_data.sim.geometry.names, namespace="sea")
    h.wait_discovered(d, subscribers=2)
    return d


@pytest.fixture(scope="module")
def thr(world: h.RosRun, thruster_data: Thrusters) -> ArrayDriver:
    d = world.driver(thruster_data.sim.geometry.names, namespace="thrusters",
                     currents=[(c, BATTERY) for c in CHANNELS])
    assert d.wait_for_subscribers(2, h.DISCOVERY_TIMEOUT) and d.wait_for_output_publishers(h.DISCOVERY_TIMEOUT)
    deadline = time.monotonic() + h.DISCOVERY_TIMEOUT
    while not all(p.get_subscription_count() >= 2 for p, _ in d.current_publishers):
        assert time.monotonic() < deadline, "current topics not matched by both nodes"
        time.sleep(0.05)
    _prime(d, thruster_data)
    return d


def _prime(d: ArrayDriver, data: Thrusters) -> None:
    """Replay a few sets with their currents until they come back (every topic discovered both ways)."""
    rec = data.check.window(None, data.check.stamps[9])
    deadline = time.monotonic() + h.DISCOVERY_TIMEOUT
    while True:
        d.clear_outputs()
        mapping = d.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE,
                           currents=rec.currents, current_lead=5)  # a Float64 sent far ahead would be stale
        time.sleep(0.5)
        # (a Float64 current is stamped on arrival, after the first set: that one is stale)
        if d.wait_for_outputs([mapping[int(t)] for t in rec.stamps], timeout=2.0, settle=0.5) >= len(rec) - 1:
            break
        assert time.monotonic() < deadline, "no corrected sets with currents came back"
    d.clear_outputs()


def _log(run: h.RosRun, name: str) -> str:
    return next(p for p in run.processes if p.log_path.stem == name).log()


def _progress(driver: ArrayDriver, node: str, predicate: Any, timeout: float = 180.0) -> dict[str, str]:
    seen: dict[str, str] = {}

    def check(msg: DiagnosticStatus) -> bool:
        seen.clear()
        seen.update(status_values(msg))
        return bool(predicate(seen))

    driver.wait_for_message(DiagnosticStatus, f"{node}/progress", check, timeout)
    assert predicate(seen), f"no ~/progress of {node} satisfied the condition: {seen}"
    return dict(seen)


CURRENT_LEAD = 400
"""Currents go out this many sets (1 s at 400 Hz) ahead of their sets: a node keeps 2 s of them, and
on a busy machine the current topics may be served well after the raw ones (a set whose current has
not arrived yet is withheld, by design)."""


def _collect(driver: ArrayDriver, node: str, rec: Recording, currents: np.ndarray | None = None) -> None:
    ok, message = driver.trigger(f"{node}/start")
    assert ok, message
    before = _counts(driver, node)
    sent = driver.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE,
                         currents=currents, current_lead=CURRENT_LEAD)
    # Every set judged (a set is collected or withheld as it forms): what was collected is final.
    judged = driver.diagnostics(node, lambda s: int(status_values(s)["sets"]) - int(before["sets"]) >= len(sent),
                                h.SAMPLES_TIMEOUT)
    assert judged is not None, f"the calibration node did not form the {len(sent)} sets sent"
    progress = wait_for_samples(driver, node.strip("/"), 0, timeout=h.SAMPLES_TIMEOUT)
    # all but a few: on a busy machine a set whose current comes late is withheld (by design, counted)
    assert int(progress.get("samples", 0)) >= 0.97 * len(rec), progress


def _counts(driver: ArrayDriver, node: str) -> dict[str, str]:
    """A node's counters now (its next status on /diagnostics)."""
    status = driver.diagnostics(node, None, 60.0)
    assert status is not None, f"no status of {node}"
    return status_values(status)


def _replay(driver: ArrayDriver, rec: Recording, currents: np.ndarray | None = None,
            lead: int = CURRENT_LEAD, before: dict[str, str] | None = None) -> dict[int, int]:
    """Replay ``rec`` and wait for the outputs of the sets the correction node published (once it counted
    every set as published or withheld, the sets it withheld are not waited for); ``before``: its counters
    before the replay, if the caller has them."""
    node = f"{driver.prefix}/magcal_correction"
    driver.watch_diagnostics()
    before = before or _counts(driver, node)

    def published() -> int | None:
        status = driver.status(node)
        if status is None:
            return None
        now = status_values(status)
        judged = sum(int(now[k]) - int(before[k]) for k in ("published", "withheld"))
        return int(now["published"]) - int(before["published"]) if judged >= len(rec) else None

    mapping = driver.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE,
                            currents=currents, current_lead=lead)
    driver.wait_for_outputs([mapping[int(t)] for t in rec.stamps], timeout=h.OUTPUT_TIMEOUT, settle=h.OUTPUT_SETTLE,
                            expected=published)
    return mapping


def _fresh_outputs(driver: ArrayDriver, rec: Recording, currents: np.ndarray | None = None,
                   lead: int = CURRENT_LEAD, before: dict[str, str] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(rows of ``rec`` that came back, corrected vectors, tensors, their currents; ``lead``: how many
    sets ahead the currents go out; ``before`` as :func:`_replay` takes it)."""
    driver.clear_outputs()
    mapping = _replay(driver, rec, currents, lead, before)
    return _come_back(driver, rec, mapping, currents)


def _come_back(driver: ArrayDriver, rec: Recording, mapping: dict[int, int], currents: np.ndarray | None,
               published: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The sets of ``rec`` whose gradient and every corrected vector are in (see :func:`_fresh_outputs`), once
    at least ``published`` of them are or :data:`ros_harness.OUTPUT_TIMEOUT` passed (a loaded reader can
    still be serving the last sets' other topics when their gradients are in)."""
    back = {p: k for k, p in enumerate(mapping[int(t)] for t in rec.stamps)}
    deadline = time.monotonic() + h.OUTPUT_TIMEOUT
    while True:
        g, c = driver.gradients(back), driver.corrected(back)
        stamps = sorted(t for t in g if t in c)
        if len(stamps) >= published or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    rows = np.array([back[t] for t in stamps], dtype=int)
    s = len(rec.names)
    return rows, np.stack([c[t] for t in stamps]) if stamps else np.empty((0, s, 3)), \
        np.stack([g[t] for t in stamps]) if stamps else np.empty((0, 3, 3)), \
        None if currents is None else currents[rows]


def _set_counts(status: DiagnosticStatus | None) -> tuple[int, int]:
    """(published, withheld) sets in a correction node's status."""
    assert status is not None, "no status of the correction node"
    values = status_values(status)
    return int(values["published"]), int(values["withheld"])


def _fresh_with_currents(driver: ArrayDriver, rec: Recording,
                         currents: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`_fresh_outputs` of the thruster set-up, checked against what the correction node counted: every
    set came back or was withheld for a current that had not yet arrived (by design: on a busy machine a
    current can come after its set however far ahead it is sent), and most came back."""
    counters = _counts(driver, THR_CORRECTION)
    before = int(counters["published"]), int(counters["withheld"])
    driver.clear_outputs()
    mapping = _replay(driver, rec, currents, CURRENT_LEAD, counters)

    def counted(s: DiagnosticStatus) -> bool:
        return sum(_set_counts(s)) - sum(before) >= len(rec)

    status = driver.diagnostics(THR_CORRECTION, counted, h.SAMPLES_TIMEOUT)
    published, withheld = (n - b for n, b in zip(_set_counts(status), before))
    rows, b, g, used = _come_back(driver, rec, mapping, currents, published)
    assert len(rows) + withheld == len(rec) and len(rows) >= 0.75 * len(rec), \
        f"{len(rows)} sets back, {withheld} withheld: {status_values(status)}"
    return rows, b, g, used


def _ratios(rows: np.ndarray, b: np.ndarray, g: np.ndarray, rec: Recording, truth: ArrayCalibration,
            intensity: float, currents: np.ndarray | None = None) -> tuple[float, float]:
    """(TMI, tensor) RMS of the node's outputs over the true calibration's on the same raw sets (uniform
    field: the true tensor is 0; rows x and y of the cross's difference tensor)."""
    true = truth.outputs(rec.vectors[rows], "difference", currents)
    tmi = rms(np.linalg.norm(b, axis=-1) - intensity) / rms(np.linalg.norm(true.vectors, axis=-1) - intensity)
    tensor = rms(g[:, :2, :]) / rms(true.tensor[:, :2, :])  # type: ignore[index]
    return float(tmi), float(tensor)


def _float32(currents: np.ndarray | None) -> np.ndarray:
    """Currents as a BatteryState carries them (its ``current`` is a float32)."""
    assert currents is not None
    return currents.astype(np.float32).astype(float)


# --------------------------------------------------------------------------- parameters


def test_site_date_max_residual_and_prior_parameters_are_checked_with_reasons(world: h.RosRun, sea: ArrayDriver,
                                                                             thr: ArrayDriver) -> None:
    for node, driver, update, why in [
        (SEA, sea, {"reference_field": 5e-5}, "either reference_field or site, not both"),
        (SEA, sea, {"site": [100.0, 5.0]}, "latitude 100 deg is outside -90 .. 90 deg"),
        (SEA, sea, {"site": [43.2]}, "a site is latitude, longitude (deg) and optionally altitude (m)"),
        (SEA, sea, {"site": [43.2, 5.4, -5000.0]}, "altitude -5000 m is outside"),
        (SEA, sea, {"date": "2040-01-01"}, "outside the World Magnetic Model's validity"),
        (SEA, sea, {"date": "1 June"}, "is not a calendar date YYYY-MM-DD"),
        (SEA, sea, {"max_residual": -1e-9}, "out of range"),
        (SEA, sea, {"prior": " "}, "prior must be running, none or the path of a calibration file"),
        (THR, thr, {"interference_types": ["std_msgs/msg/String", FLOAT64]}, "is not supported"),
        (THR, thr, {"interference_topics": ["a"]}, "needs one entry per interference channel (2"),
        (THR, thr, {"current_tolerance": 0.0}, "current_tolerance must be a positive number"),
        (THR_CORRECTION, thr, {"interference_topics": ["bad topic", "x"]}, "interference_topics"),
        (THR_CORRECTION, thr, {"mag2.interference": [1e-9] * 5}, "mag2.interference needs 6 numbers"),
        (THR_CORRECTION, thr, {"interference_channels": ["a", "b", "c"], "interference_topics": ["a", "b", "c"],
                               "interference_types": [BATTERY] * 3}, "mag1.interference needs 9 numbers"),
    ]:
        (ok, reason), = driver.set_parameters(node, update)
        assert not ok and why in reason, (update, reason)
    d = sea.describe_parameters(SEA, ["site", "date", "max_residual", "prior", "assess_period"])
    assert all(d[n].description for n in d) and d["max_residual"].floating_point_range[0].to_value == 1e-3
    assert sea.get_parameters(SEA, ["site", "date"]) == {"site": SITE, "date": DATE}
    # An empty list clears the site (ros2 param set NODE site "[]"); then it can be given again.
    assert sea.set_parameters(SEA, {"site": [], "date": ""})[0][0]
    try:
        (ok, reason), = sea.set_parameters(SEA, {"date": DATE})
        assert not ok and "date needs site" in reason, reason
    finally:
        assert sea.set_parameters(SEA, {"site": SITE, "date": DATE})[0][0]
    assert sea.get_parameters(SEA, ["site", "date"]) == {"site": SITE, "date": DATE}


# --------------------------------------------------------------------------- at sea


@pytest.fixture(scope="module")
def first(world: h.RosRun, sea: ArrayDriver, sea_data: Sea) -> dict[str, Any]:
    """The full calibration: a random manoeuvre with 2 % spikes, F from the site."""
    _collect(sea, SEA, sea_data.manoeuvre)
    progress = _progress(sea, SEA, lambda v: int(v.get("assessed") or 0) >= len(sea_data.manoeuvre))
    ok, message = sea.trigger(f"{SEA}/calibrate")
    assert ok, message
    return {"message": message, "progress": progress, "params": sea.get_parameters(SEA_CORRECTION, CAL_PARAMS),
            "file": sea_data.file.read_text()}


def test_a_full_calibration_takes_f_from_the_site_and_says_how_many_outliers_it_excluded(
    first: dict[str, Any], sea_data: Sea
) -> None:
    message = first["message"]
    assert f"F {FIELD.intensity / NT:.1f} nT" in message
    assert "reference F from WMM-2025 at 43.2N 5.4E 0 m on 2026-06-01" in message
    assert f"prior: none ({SEA_CORRECTION} is not calibrated" in message and "valid over the whole sphere" in message
    excluded = int(re.search(r"(\d+) outlying readings excluded", message).group(1))  # type: ignore[union-attr]
    assert 0.9 * sea_data.spiked <= excluded <= 1.1 * sea_data.spiked, (excluded, sea_data.spiked)
    meta = calfile.loads(first["file"]).metadata  # (as written then: a later test may recalibrate)
    assert meta["outliers_excluded"]["total"] == excluded
    assert meta["reference_source"] == "WMM-2025 at 43.2N 5.4E 0 m on 2026-06-01"
    assert meta["reference_model_intensity"] == pytest.approx(FIELD.intensity, rel=1e-9)
    progress = first["progress"]
    assert progress["ready"] == "true" and progress["envelope"] == "valid over the whole sphere"
    assert progress["advice"].startswith("enough for a calibration") and progress["prior"].startswith("none")


def test_max_residual_below_the_noise_refuses_and_changes_nothing(first: dict[str, Any], sea: ArrayDriver,
                                                                  sea_data: Sea) -> None:
    before, text = sea.get_parameters(SEA_CORRECTION, CAL_PARAMS), sea_data.file.read_text()  # (whatever ran before)
    assert sea.set_parameters(SEA, {"max_residual": 0.3e-9})[0][0]
    try:
        _collect(sea, SEA, sea_data.manoeuvre.window(None, sea_data.manoeuvre.stamps[399]))
        ok, message = sea.trigger(f"{SEA}/calibrate")
        assert not ok and "max residual 0.3 nT" in message and "nothing was changed" in message, message
        assert "max_residual parameter" in message
        assert sea.get_parameters(SEA_CORRECTION, CAL_PARAMS) == before
        assert sea_data.file.read_text() == text
    finally:
        assert sea.set_parameters(SEA, {"max_residual": 0.0})[0][0]


def test_at_sea_a_yaw_circle_recalibrates_from_the_running_calibration(
    world: h.RosRun, first: dict[str, Any], sea: ArrayDriver, sea_data: Sea
) -> None:
    """Refused without a prior (naming pitch and roll, nothing changes); with the running calibration
    as the prior the offsets are updated and scale z kept, and over the whole sphere TMI and tensor
    are within 1.2x of the true new calibration. ~/progress says so while collecting."""
    yaw = sea_data.yaw
    assert sea.set_parameters(SEA, {"prior": "none"})[0][0]
    _collect(sea, SEA, yaw)
    progress = _progress(sea, SEA, lambda v: int(v.get("assessed") or 0) >= len(yaw)
                         and v.get("prior", "").startswith("none"))
    assert progress["ready"] == "false" and "scale z" in progress["undetermined"]
    assert TILT_ADVICE.match(progress["advice"]), progress["advice"]
    assert progress["envelope"] == "not valid at any attitude yet" and "pitch or roll" in progress["problem"]
    ok, message = sea.trigger(f"{SEA}/calibrate")
    assert not ok and "pitch and roll" in message and "nothing was changed" in message, message
    assert sea.get_parameters(SEA_CORRECTION, CAL_PARAMS) == first["params"]
    assert sea_data.file.read_text() == first["file"]

    assert sea.set_parameters(SEA, {"prior": "running"})[0][0]  # the same collected sets
    progress = _progress(sea, SEA, lambda v: int(v.get("assessed") or 0) >= len(yaw)
                         and v.get("prior", "").startswith("the running calibration"))
    assert progress["prior"] == f"the running calibration of {SEA_CORRECTION}"
    assert progress["ready"] == "true" and ENVELOPE.match(progress["envelope"]), progress
    assert progress["advice"].startswith("enough to recalibrate from the prior") and "scale z" in progress["advice"]
    ok, message = sea.trigger(f"{SEA}/calibrate")
    assert ok, message
    found = re.search(r", (valid [^,]*(?:, roll [^,]*)?), updated \((.*?)\), kept from the prior \((.*?)\), "
                      r"(?:\d+ outlying|coverage)", message)
    assert found, message
    envelope, updated, kept = found.groups()
    assert ENVELOPE.match(envelope), envelope

    def per_sensor(text: str) -> dict[str, set[str]]:  # "every sensor: a, b; mag2: c" -> {quantity: sensors}
        out: dict[str, set[str]] = {}
        for group in ([] if text == "nothing" else text.split("; ")):
            who, _, names = group.partition(": ")
            for name in names.split(", "):
                out.setdefault(name, set()).update(["every sensor"] if who == "every sensor" else who.split(", "))
        return out

    updated_by, kept_by = per_sensor(updated), per_sensor(kept)
    assert all(updated_by.get(f"offset {a}") == {"every sensor"} for a in "xyz"), updated
    assert kept_by.get("scale z") == {"every sensor"} and "scale z" not in updated_by, (updated, kept)
    assert f"prior: the running calibration of {SEA_CORRECTION}" in message
    assert "kept from the prior" in _log(world, "sea_calibration")
    rng = np.random.default_rng(77)
    fresh, _ = sea_data.moved.run(uniform_random(400, rng), rng, rate=50.0, start=3000.0)
    rows, b, g, _ = _fresh_outputs(sea, fresh)
    assert len(rows) == len(fresh), str(status_values(sea.diagnostics(SEA_CORRECTION, None, 30.0)))
    tmi, tensor = _ratios(rows, b, g, fresh, sea_data.moved.true_calibration(), FIELD.intensity)
    assert tmi < 1.2 and tensor < 1.2, (tmi, tensor)


# --------------------------------------------------------------------------- thrusters


def test_the_correction_node_subtracts_the_latest_currents(world: h.RosRun, thr: ArrayDriver,
                                                           thruster_data: Thrusters) -> None:
    """Loaded with the true interference: each set is the truth applied in numpy with its currents (tensor
    at the floor); without the subtraction the tensor is more than 100x the floor."""
    check = thruster_data.check
    true = thruster_data.true
    u = check.currents
    rows, b, g, used = _fresh_with_currents(thr, check, u)
    expected = true.outputs(check.vectors[rows], "difference", _float32(used))
    np.testing.assert_allclose(b, expected.vectors, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(g, expected.tensor, rtol=1e-9, atol=1e-15)
    tmi, tensor = _ratios(rows, b, g, check, true, F_THR, used)
    assert tmi <= 1.1 and tensor <= 1.1, (tmi, tensor)
    assert rms(g[:, :2, :]) <= 1.15 * FLOOR
    (ok, reason), = thr.set_parameters(THR_CORRECTION, {"interference_channels": []})
    assert ok, reason
    try:
        rows, _, g, _ = _fresh_outputs(thr, check, u)
        assert len(rows) == len(check)
        assert rms(g[:, :2, :]) > 100 * FLOOR, rms(g[:, :2, :]) / FLOOR
    finally:
        params = {"interference_channels": list(CHANNELS)}
        params.update({f"{n}.interference": [float(x) for x in true.interference[i].reshape(-1)]  # type: ignore[index]
                       for i, n in enumerate(true.geometry.names)})
        (ok, reason), = thr.set_parameters(THR_CORRECTION, params)
        assert ok, reason


def test_a_stale_current_withholds_the_set_and_names_the_channel(world: h.RosRun, thr: ArrayDriver,
                                                                 thruster_data: Thrusters) -> None:
    """thruster2's current stops (its messages carry NaN, which is no value): no set is corrected with
    a stale current; /diagnostics warns naming thruster2 only and counts the sets."""
    before = status_values(thr.diagnostics(THR_CORRECTION, None, 30.0))
    time.sleep(1.0)  # the last currents are older than current_tolerance by now
    rec = thruster_data.check.window(None, thruster_data.check.stamps[59])
    u = rec.currents.copy()
    u[:, 1] = np.nan
    thr.clear_outputs()
    mapping = thr.replay(recording_messages(rec.names, rec.stamps, rec.vectors), rate=h.REPLAY_RATE, currents=u)
    key = "thruster2/battery.stale_current"

    def counted(s: DiagnosticStatus) -> bool:
        return int(status_values(s)[key]) - int(before[key]) >= len(rec)

    status = thr.diagnostics(THR_CORRECTION, counted, 30.0)
    assert status is not None, "the stale sets were not counted"
    values = status_values(status)
    assert int(values[key]) - int(before[key]) == len(rec)
    assert values["thruster1/battery.stale_current"] == before["thruster1/battery.stale_current"]
    # The status of the period in which the last of them was counted names the channel.
    assert status.level[0] >= 1 and "stale current" in status.message, status.message
    assert "thruster2/battery on /thrusters/thruster2/battery" in status.message and "thruster1" not in status.message
    with thr._lock:
        assert not any(mapping[int(t)] in thr.outputs.field for t in rec.stamps), "a set used a stale current"


def test_float64_currents_are_stamped_on_arrival(world: h.RosRun, thr: ArrayDriver,
                                                 thruster_data: Thrusters) -> None:
    """thruster2 on a std_msgs/Float64 topic (no header: the node stamps it on arrival), held steady."""
    (ok, reason), = thr.set_parameters(THR_CORRECTION, {"interference_topics": ["thruster1/battery", "thruster2/current"],
                                                        "interference_types": [BATTERY, FLOAT64]})
    assert ok, reason
    d = world.driver(thruster_data.sim.geometry.names, namespace="thrusters",
                     currents=[("thruster1/battery", BATTERY), ("thruster2/current", FLOAT64)])
    try:
        assert d.wait_for_subscribers(2, h.DISCOVERY_TIMEOUT) and d.wait_for_output_publishers(h.DISCOVERY_TIMEOUT)
        deadline = time.monotonic() + h.DISCOVERY_TIMEOUT
        while d.current_publishers[1][0].get_subscription_count() < 1:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        rec = thruster_data.check.window(None, thruster_data.check.stamps[99])
        u = rec.currents.copy()
        u[:, 1] = 12.5
        _prime(d, replace(thruster_data, check=Recording(rec.names, rec.stamps, rec.vectors, rec.channels, u)))
        # A Float64 is stamped when it arrives: sent CURRENT_LEAD (1 s) ahead it would be stale
        # (older than the 0.5 s current tolerance) at its set; 0.3 s ahead (120 sets at 400 sets/s) it is
        # within it and held steady, so it is the set's. (5 sets ahead, the first sets were withheld
        # whenever the node took the first Float64 more than 12 ms after it was sent: 64 of 100 on CI.)
        rows, b, _, used = _fresh_outputs(d, rec, u, lead=int(0.3 * h.REPLAY_RATE))
        # Every set from the first Float64's arrival on; on a busy machine it may arrive after the first
        # sets' stamps, which are then withheld (no current yet, by design): only a leading stretch.
        assert len(rows) >= 0.5 * len(rec) and np.array_equal(rows, np.arange(len(rec) - len(rows), len(rec))), rows
        expected = thruster_data.true.apply(rec.vectors[rows], _float32(used))
        np.testing.assert_allclose(b, expected, rtol=1e-9, atol=1e-18)
    finally:
        (ok, reason), = thr.set_parameters(THR_CORRECTION, {"interference_topics": list(CHANNELS),
                                                            "interference_types": [BATTERY, BATTERY]})
        assert ok, reason


def test_the_calibration_node_solves_the_interference_with_the_calibration(
    world: h.RosRun, thr: ArrayDriver, thruster_data: Thrusters
) -> None:
    """A 1,500-set manoeuvre with both thrusters at random 0-20 A, currents collected with the sets, no
    prior: the pushed calibration carries the interference (gains within 2 % of the truth), and with
    the live currents fresh sets are within 1.1x of the true calibration in TMI and tensor. The correction
    node's calibration is put back after (the other thruster tests expect the true one)."""
    names = thruster_data.sim.geometry.names
    kept = thr.get_parameters(THR_CORRECTION, CAL_PARAMS + [f"{n}.interference" for n in names])
    try:
        _solve_the_interference(thr, thruster_data)
    finally:
        (ok, reason), = thr.set_parameters(THR_CORRECTION, kept)
        assert ok, reason


def _solve_the_interference(thr: ArrayDriver, thruster_data: Thrusters) -> None:
    before = sum(_set_counts(thr.diagnostics(THR_CORRECTION, None, 60.0)))
    _collect(thr, THR, thruster_data.manoeuvre, thruster_data.manoeuvre.currents)
    # the correction node saw the manoeuvre too: its sets judged before the check's counters are taken (the new
    # segment of a replay sent at 8x is held up to HOLD_NS and may be decided after the calibration node's)
    count = 0.97 * len(thruster_data.manoeuvre)  # (as _collect: all but a few)
    judged = thr.diagnostics(THR_CORRECTION, lambda st: sum(_set_counts(st)) - before >= count, h.SAMPLES_TIMEOUT)
    assert judged is not None, "the correction node did not judge the manoeuvre's sets"
    ok, message = thr.trigger(f"{THR}/calibrate")
    assert ok, message
    assert "interference of thruster1/battery, thruster2/battery solved" in message
    names = thruster_data.sim.geometry.names
    p = thr.get_parameters(THR_CORRECTION, CAL_PARAMS + ["interference_channels", "interference_topics",
                                                         "interference_types"] + [f"{n}.interference" for n in names])
    assert p["interference_channels"] == p["interference_topics"] == list(CHANNELS)
    assert p["interference_types"] == [BATTERY, BATTERY]
    nested: dict[str, Any] = {"sensor_names": p["sensor_names"], "positions": p["positions"],
                              "interference_channels": p["interference_channels"]}
    for n in names:
        nested[n] = {"matrix": p[f"{n}.matrix"], "offset": p[f"{n}.offset"], "interference": p[f"{n}.interference"]}
    live = ArrayCalibration.from_parameters(nested)
    true = thruster_data.true
    seen = np.einsum("sab,sbc,scm->sam", true.matrices, np.linalg.inv(live.matrices), live.interference)
    error = np.linalg.norm(seen - true.interference, axis=1) / np.linalg.norm(true.interference, axis=1)
    assert np.max(error) < 0.02, np.round(error, 4)
    check = thruster_data.check
    rows, b, g, used = _fresh_with_currents(thr, check, check.currents)
    tmi, tensor = _ratios(rows, b, g, check, true, F_THR, used)
    assert tmi <= 1.1 and tensor <= 1.1, (tmi, tensor)

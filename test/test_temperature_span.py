"""The temperatures a calibration was made at, recorded in its file and watched where it is applied.

A glider's manoeuvre at the surface spans 0.8 K (18.2..19.0 C): too little for temperature terms, so
none is stored, yet its dives are 16 K colder. The calibration file records per sensor the span
(``<name>.calibration_temperatures``); ``magcal correct`` says, per sensor, how many sets were more than
:data:`~magcal_ros.core.temperature.TEMPERATURE_MARGIN` outside it and how far; a file without the key
(written before it existed) says nothing. The correction node counts the same with
:class:`~magcal_ros.core.temperature.SpanExcursions`.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_model_blocks import GEO, F, thermal_array
from test_offline import magcal, ok

from magcal_ros.core import calibration_bounds as bounds
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.temperature import (
    span_with_prior,
    TEMPERATURE_MARGIN,
    SpanExcursions,
    temperature_span,
)
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.sim.attitudes import uniform_random

SURFACE = (18.2, 19.0)  # deg C: the manoeuvre at the surface
COLD = 16.0  # K colder at depth


class Surface:
    """A calibration at the surface (no temperature terms) and fresh dives 16 K colder."""

    def __init__(self) -> None:
        self.sim = thermal_array(1)
        temps = np.random.default_rng(3).uniform(*SURFACE, 1500)
        self.manoeuvre, _ = self.sim.run(uniform_random(1500, 4), 5, temperatures=temps, rate=10.0)
        self.result = calibrate_array(self.manoeuvre.vectors, GEO, F, stamps=self.manoeuvre.stamps,
                                      temperatures=self.manoeuvre.temperatures)
        cold = np.random.default_rng(6).uniform(SURFACE[0] - COLD - 0.5, SURFACE[0] - COLD + 0.5, 600)
        self.dive, _ = self.sim.run(uniform_random(600, 7), 8, temperatures=cold, rate=10.0, start=1000.0)
        surface = np.random.default_rng(9).uniform(*SURFACE, 300)
        self.warm, _ = self.sim.run(uniform_random(300, 10), 11, temperatures=surface, rate=10.0, start=2000.0)


@pytest.fixture(scope="module")
def surface() -> Surface:
    return Surface()


def test_the_file_records_the_temperatures_the_calibration_was_made_at(surface: Surface, tmp_path: Path) -> None:
    cal = surface.result.calibration
    assert not cal.has_temperature_terms  # 0.8 K: no term stored
    t = surface.manoeuvre.temperatures
    np.testing.assert_array_equal(cal.temperature_span, np.column_stack([t.min(axis=0), t.max(axis=0)]))
    path = tmp_path / "cal.yaml"
    calfile.write(path, cal)
    text = path.read_text()
    assert text.count("calibration_temperatures: [") == 4
    back = calfile.read(path)
    np.testing.assert_array_equal(back.temperature_span, cal.temperature_span)
    # without temperatures nothing is recorded
    blind = calibrate_array(surface.manoeuvre.vectors, GEO, F).calibration
    assert blind.temperature_span is None and "calibration_temperatures" not in calfile.dumps(blind)


@pytest.mark.parametrize("value, message", [
    ([19.0, 18.2], "minimum above its maximum"),
    ([18.2, float("nan")], "two finite numbers"),
    ([291.4, 292.2], "not a span of temperatures in deg C"),
    ([18.2], "two finite numbers"),
    ("warm", "must be \\[min, max\\]"),
])
def test_a_bad_span_is_refused_when_read(surface: Surface, value: object, message: str) -> None:
    params = surface.result.calibration.to_parameters()
    params["mag2"]["calibration_temperatures"] = value
    with pytest.raises(InputError, match=f"mag2.calibration_temperatures.*{message}"):
        ArrayCalibration.from_parameters(params)
    assert bounds.check_temperature_span("x", [-2.0, 30.0]).tolist() == [-2.0, 30.0]


def test_magcal_correct_names_the_sensors_and_sets_beyond_the_span(surface: Surface, tmp_path: Path) -> None:
    cal_path = tmp_path / "cal.yaml"
    calfile.write(cal_path, surface.result.calibration)
    dive_csv, warm_csv = tmp_path / "dive.csv", tmp_path / "warm.csv"
    write_csv(dive_csv, surface.dive)
    write_csv(warm_csv, surface.warm)
    proc = ok(magcal("correct", dive_csv, "-c", cal_path, "-o", tmp_path / "out.csv"))
    lo, hi = surface.result.calibration.temperature_span[1]
    far = lo - surface.dive.temperatures[:, 1].min()
    for name in GEO.names:
        assert re.search(rf"note: {name}: 600 sets up to [0-9.]+ K below the calibrated temperatures", proc.stderr), \
            proc.stderr
    assert f"mag2: 600 sets up to {far:.1f} K below the calibrated temperatures {lo:.1f}..{hi:.1f} C" in proc.stderr
    assert f"more than {TEMPERATURE_MARGIN:g} K outside" in proc.stderr
    # at the surface: nothing said
    proc = ok(magcal("correct", warm_csv, "-c", cal_path, "-o", tmp_path / "warm_out.csv"))
    assert "calibrated temperatures" not in proc.stderr, proc.stderr
    # a file without the key (written before it existed): the same correction, nothing said
    old = tmp_path / "old.yaml"
    old.write_text("\n".join(line for line in cal_path.read_text().splitlines()
                             if "calibration_temperatures" not in line) + "\n")
    assert calfile.read(old).temperature_span is None
    proc = ok(magcal("correct", dive_csv, "-c", old, "-o", tmp_path / "old_out.csv"))
    assert "calibrated temperatures" not in proc.stderr, proc.stderr
    assert (tmp_path / "old_out.csv").read_text() == (tmp_path / "out.csv").read_text()


def test_span_excursions_count_per_sensor_once_each(surface: Surface) -> None:
    """What the correction node counts, set by set: the first excursion of a sensor is named once."""
    span = surface.result.calibration.temperature_span
    watch = SpanExcursions(GEO.names, span)
    t = surface.dive.temperatures
    assert watch.add(surface.warm.temperatures) == []
    first = watch.add(t[:1])
    assert first == list(GEO.names)
    assert watch.add(t[1:]) == []  # already named
    fresh = np.ones_like(t, bool)
    fresh[:, 3] = False  # mag4's temperature stale: not counted
    watch.add(t, fresh)
    np.testing.assert_array_equal(watch.counts, [1200, 1200, 1200, 600])
    np.testing.assert_allclose(watch.below, span[:, 0] - t.min(axis=0))
    assert np.all(watch.above == 0)
    assert len(watch.notes()) == 4 and watch.notes()[0].startswith("mag1: 1,200 sets up to ")
    # unknown for one sensor (a NaN row), or none given: nothing counted for it
    span2 = span.copy()
    span2[0] = np.nan
    other = SpanExcursions(GEO.names, span2)
    other.add(t)
    assert other.counts[0] == 0 and other.counts[1] == 600
    assert temperature_span(None, 4) is None


def test_bag_to_bag_correct_notes_a_dive_below_the_surface_calibration(tmp_path: Path) -> None:
    """The user's path: a surface manoeuvre bag at 18.6 C calibrated, a dive bag at 2.6 C corrected; the
    bags' /<name>/temperature are read for the check only (no temperature terms, no set dropped)."""
    ok(magcal("simulate", tmp_path / "surface", "--count", 1500, "--seed", 4, "--temperatures", 18.6,
              "--temperature-noise", 0.2))
    ok(magcal("calibrate", tmp_path / "surface", "-o", tmp_path / "cal.yaml", "--reference-field", F))
    cal = calfile.read(tmp_path / "cal.yaml")
    assert not cal.has_temperature_terms and cal.temperature_span is not None
    assert np.all(np.abs(cal.temperature_span - 18.6) < 1.5)
    ok(magcal("simulate", tmp_path / "dive", "--count", 300, "--seed", 4, "--temperatures", 2.6,
              "--temperature-noise", 0.2))
    proc = ok(magcal("correct", tmp_path / "dive", "-c", tmp_path / "cal.yaml", "-o", tmp_path / "out"))
    assert "corrected 300 sets" in proc.stdout
    for name in GEO.names:
        assert re.search(rf"note: {name}: 300 sets up to 1[5-7]\.\d K below the calibrated temperatures", proc.stderr), \
            proc.stderr


def test_the_node_health_warns_in_the_period_sets_go_beyond_and_shows_the_counts() -> None:
    """:class:`~magcal_ros.nodes.health.TemperatureSpanHealth`, what the correction node reports: per sensor keys
    when its span is known, a WARN text in the period sets went beyond (naming the sensor), none after."""
    from magcal_ros.nodes.health import TemperatureSpanHealth

    span = np.array([[18.2, 19.0], [18.2, 19.0], [np.nan, np.nan]])
    health = TemperatureSpanHealth(("mag1", "mag2", "mag3"), span)
    assert health.count([18.5, 18.6, 2.0], [True, True, True]) == []  # mag3's span unknown: not counted
    text, values = health.assess()
    assert text is None and values["mag2.temperature_beyond_calibration"] == "0"
    assert values["mag1.calibration_temperatures_C"] == "18.2..19.0" and not any(k.startswith("mag3") for k in values)
    assert health.count([18.5, 2.1, 2.0], [True, True, True]) == ["mag2"]
    assert health.count([18.5, 2.2, 2.0], [True, True, True]) == []  # named once
    assert health.count([30.0, 2.2, 2.0], [False, True, True]) == []  # a stale temperature is not counted
    text, values = health.assess()
    assert text is not None and "mag2: 3 sets up to 16.1 K below the calibrated temperatures 18.2..19.0 C" in text
    assert "mag1" not in text
    assert values["mag2.temperature_beyond_calibration"] == "3" and values["mag2.temperature_beyond_calibration_K"] == "16.1"
    assert health.assess()[0] is None  # nothing new this period
    old = TemperatureSpanHealth(("mag1",), None)  # a calibration without the key
    assert old.count([2.0], [True]) == [] and old.assess() == (None, {})


def test_a_recalibration_holds_over_what_its_prior_held_over_too() -> None:
    """A recalibration from a short window (20.5..21.7 C) with a prior made over 5..15 C holds over 5..21.7 C
    (what the window does not determine, the prior's temperature dependence with it, is kept); with a prior
    whose span is unknown, unknown (not the window's alone: a mission's dives would be called beyond it);
    without a prior, the window's."""
    geo = ArrayGeometry.cross()
    window = np.column_stack([np.full(4, 20.5), np.full(4, 21.7)])
    prior = replace(ArrayCalibration.identity(geo), temperature_span=np.tile([5.0, 15.0], (4, 1)))
    assert np.array_equal(span_with_prior(window, geo.names, prior), np.tile([5.0, 21.7], (4, 1)))
    assert span_with_prior(window, geo.names, ArrayCalibration.identity(geo)) is None
    assert span_with_prior(window, geo.names, None) is window
    partly = np.tile([5.0, 15.0], (4, 1))
    partly[2] = np.nan  # mag3's unknown in the prior
    both = span_with_prior(window, geo.names, replace(prior, temperature_span=partly))
    assert np.all(np.isnan(both[2])) and np.array_equal(both[[0, 1, 3]], np.tile([5.0, 21.7], (3, 1)))

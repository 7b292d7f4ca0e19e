"""Reference field from the site: the World Magnetic Model offline, and `magcal calibrate --site`."""

from __future__ import annotations

import builtins
import socket
from datetime import date, datetime, timezone
from pathlib import Path

import numpy as np
import pytest
import yaml

from magcal_ros.app.cli import main
from magcal_ros.core.field import earth_field
from magcal_ros.core.geomagnetic import decimal_year, parse_date, site_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.units import NT
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.sim.attitudes import uniform_random
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

# Published test values, copied by hand (X, Y, Z, F in nT rounded to 0.1 nT; I, D in deg
# rounded to 0.01 deg): NOAA NCEI / BGS, "WMM2025 test values" (WMM2025_TEST_VALUES.txt,
# December 2024) and "WMM2020 test values" (WMM2020testvalues.pdf, December 2019).
# Columns: model, decimal year, height km, lat, lon, X, Y, Z, F, I, D.
PUBLISHED = [
    ("WMM-2025", 2025.0, 0.0, 80.0, 0.0, 6521.6, 145.9, 54791.5, 55178.5, 83.21, 1.28),
    ("WMM-2025", 2027.5, 0.0, 0.0, 120.0, 39701.6, -167.4, -10381.8, 41036.9, -14.65, -0.24),
    ("WMM-2025", 2027.5, 100.0, -80.0, 240.0, 5984.0, 14760.1, -49317.7, 51825.7, -72.10, 67.93),
    ("WMM-2020", 2022.5, 0.0, 0.0, 120.0, 39684.7, -42.2, -10809.5, 41130.5, -15.24, -0.06),
]
NT_ROUNDING = 0.05 + 1e-6  # half of the published 0.1 nT
DEG_ROUNDING = 0.005 + 1e-6  # half of the published 0.01 deg


def _when(year: float) -> datetime:
    """The UTC instant of a decimal year ``YYYY.0`` or ``YYYY.5`` (non-leap years: 2 July 12:00)."""
    whole = int(year)
    return datetime(whole, 1, 1) if year == whole else datetime(whole, 7, 2, 12)


@pytest.mark.parametrize("row", PUBLISHED, ids=lambda r: f"{r[0]}-{r[1]}-{r[2]:g}km-{r[3]:g}N-{r[4]:g}E")
def test_field_agrees_with_the_published_test_values(row) -> None:
    model, year, height_km, lat, lon, x, y, z, f, inc, dec = row
    assert decimal_year(_when(year)) == year
    site = site_field(lat, lon, height_km * 1000.0, _when(year))
    assert site.model == model
    np.testing.assert_allclose(site.vector / NT, [x, y, z], rtol=0, atol=NT_ROUNDING)
    assert abs(site.intensity / NT - f) <= NT_ROUNDING
    assert abs(site.inclination_deg - inc) <= DEG_ROUNDING
    assert abs(site.declination_deg - dec) <= DEG_ROUNDING
    np.testing.assert_allclose(earth_field(site.intensity, site.inclination_deg, site.declination_deg), site.vector,
                               rtol=0, atol=1e-6 * NT)


def test_model_error_is_the_documented_one_and_longitudes_wrap() -> None:
    now = site_field(43.2, 5.4, 0.0, date(2026, 11, 23))
    assert now.model == "WMM-2025" and now.epoch == 2025.0
    assert now.intensity_error == pytest.approx(138 * NT)  # NOAA's WMM2025 error model, F
    assert site_field(0.0, 120.0, 0.0, date(2022, 7, 2)).intensity_error == pytest.approx(148 * NT)  # WMM2020
    assert now.describe() == "WMM-2025 at 43.2N 5.4E 0 m on 2026-11-23"
    east, west = site_field(-80.0, 240.0, -50.0, date(2026, 1, 1)), site_field(-80.0, -120.0, -50.0, date(2026, 1, 1))
    np.testing.assert_array_equal(east.vector, west.vector)
    assert east.describe() == "WMM-2025 at 80S 120W -50 m on 2026-01-01"
    assert set(now.provenance()) >= {"reference_source", "reference_model_intensity",
                                     "reference_model_inclination_deg", "reference_model_declination_deg"}


def test_works_offline_without_reading_any_file(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the model must not open files or sockets")

    monkeypatch.setattr(socket, "socket", refuse)
    monkeypatch.setattr(builtins, "open", refuse)
    assert site_field(43.2, 5.4, 0.0, date(2026, 11, 23)).intensity == pytest.approx(46838.3 * NT, abs=0.1 * NT)


@pytest.mark.parametrize(
    ("args", "says"),
    [
        ((90.5, 0.0, 0.0, date(2026, 1, 1)), "latitude 90.5 deg is outside -90 .. 90 deg"),
        ((0.0, -180.5, 0.0, date(2026, 1, 1)), "longitude -180.5 deg is outside -180 .. 360 deg"),
        ((0.0, 360.5, 0.0, date(2026, 1, 1)), "outside -180 .. 360 deg"),
        ((0.0, 0.0, -1500.0, date(2026, 1, 1)), "altitude -1500 m is outside -1000 .. 850000 m"),
        ((0.0, 0.0, 9e5, date(2026, 1, 1)), "outside -1000 .. 850000 m"),
        ((float("nan"), 0.0, 0.0, date(2026, 1, 1)), "latitude nan"),
        ((0.0, 0.0, 0.0, date(2030, 1, 1)), "date 2030-01-01 is outside the World Magnetic Model's validity (2015-01-01 .. 2029-12-31"),
        ((0.0, 0.0, 0.0, date(2014, 12, 31)), "(2015-01-01 .. 2029-12-31"),
    ],
)
def test_out_of_range_inputs_name_the_valid_range(args, says) -> None:
    with pytest.raises(InputError) as err:
        site_field(*args)
    assert says in str(err.value) and "\n" not in str(err.value)


def test_date_text() -> None:
    assert parse_date("2026-11-23") == date(2026, 11, 23)
    before = datetime.now(timezone.utc).date()
    assert parse_date("") in {before, datetime.now(timezone.utc).date()}  # today, UTC
    assert parse_date(None) in {before, datetime.now(timezone.utc).date()}
    with pytest.raises(InputError, match="not a calendar date YYYY-MM-DD"):
        parse_date("2026-02-30")


# --- magcal calibrate --site ---------------------------------------------------------------

SITE, DAY = "43.2,5.4,-10", "2026-11-23"


@pytest.fixture(scope="module")
def rotation(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, ArraySimulation, float]:
    """A recording made in the model's field at SITE on DAY (CSV), its simulation and F (T)."""
    site = site_field(43.2, 5.4, -10.0, date(2026, 11, 23))
    rng = np.random.default_rng(11)
    sim = ArraySimulation(ArrayGeometry.cross(), tuple(random_sensor_errors(rng) for _ in range(4)), site.vector)
    path = tmp_path_factory.mktemp("site") / "rotation.csv"
    write_csv(path, sim.run(uniform_random(300, 5), 6)[0])
    return path, sim, site.intensity


def test_site_gives_the_calibration_of_the_model_intensity_and_records_it(tmp_path, rotation, capsys) -> None:
    path, sim, f_model = rotation
    by_site, by_hand = tmp_path / "site.yaml", tmp_path / "hand.yaml"
    assert main(["calibrate", str(path), "-o", str(by_site), "--site", SITE, "--date", DAY, "-q"]) == 0
    out = capsys.readouterr().out
    assert f"F {f_model / NT:.1f} nT" in out and "sets the absolute scale only" in out and "138 nT" in out
    assert main(["calibrate", str(path), "-o", str(by_hand), "--reference-field", repr(f_model), "-q"]) == 0
    site_cal, hand_cal = calfile.read(by_site), calfile.read(by_hand)
    np.testing.assert_array_equal(site_cal.matrices, hand_cal.matrices)
    np.testing.assert_array_equal(site_cal.offsets, hand_cal.offsets)
    prov = yaml.safe_load(by_site.read_text())["magcal_provenance"]["ros__parameters"]
    assert prov["reference_source"] == "WMM-2025 at 43.2N 5.4E -10 m on 2026-11-23"
    assert prov["reference_field"] == prov["reference_model_intensity"] == f_model
    model = site_field(43.2, 5.4, -10.0, date(2026, 11, 23))
    assert prov["reference_model_inclination_deg"] == model.inclination_deg
    assert prov["reference_model_declination_deg"] == model.declination_deg
    assert prov["reference_model_error"] == pytest.approx(138 * NT)
    # the model's F is the field the data were made in: corrected fresh data sit on it
    fresh, truth = sim.run(uniform_random(500, 7), 8)
    norms = np.linalg.norm(site_cal.apply(fresh.vectors), axis=-1)
    assert abs(np.mean(norms) - f_model) < 1 * NT


def test_a_southern_site_needs_no_equals_sign(tmp_path, rotation, capsys) -> None:
    out = tmp_path / "south.yaml"
    assert main(["calibrate", str(rotation[0]), "-o", str(out), "--site", "-33.87,151.21", "--date", DAY, "-q"]) == 0
    prov = yaml.safe_load(out.read_text())["magcal_provenance"]["ros__parameters"]
    assert prov["reference_source"] == "WMM-2025 at 33.87S 151.21E 0 m on 2026-11-23"


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--site", SITE, "--reference-field", "5e-5"], "give either --reference-field or --site, not both"),
        (["--date", DAY], "--date needs --site"),
        (["--site", "43.2"], "latitude, longitude (deg) and optionally altitude (m): got 1 numbers"),
        (["--site", "43.2,5.4,0,1"], "got 4 numbers"),
        (["--site", "north,east"], "the site must be LAT,LON[,ALT_M]"),
        (["--site", "91,5.4"], "latitude 91 deg is outside -90 .. 90 deg"),
        (["--site", "43.2,5.4,-3000"], "altitude -3000 m is outside -1000 .. 850000 m"),
        (["--site", SITE, "--date", "2031-06-01"], "outside the World Magnetic Model's validity"),
        (["--site", SITE, "--date", "23/11/2026"], "not a calendar date YYYY-MM-DD"),
    ],
)
def test_bad_site_or_date_one_line_exit_2_no_output(tmp_path, rotation, capsys, extra, says) -> None:
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(rotation[0]), "-o", str(out), "-q", *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err, err
    assert not out.exists()

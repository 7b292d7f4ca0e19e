"""The Earth's main field at a site from the World Magnetic Model (WMM), offline.

Evaluated by ``pygeomag`` (a pure-Python port of NOAA's WMM code) with the spherical
harmonic coefficients it ships as Python data: no file is read and no network is used.
The model is chosen by date: WMM-2015v2 (2015.0-2020.0), WMM-2020 (2020.0-2025.0) and
WMM-2025 (2025.0-2030.0, the current one).

Frames and units: the vector is in the local geodetic NED frame (x north, y east, z down,
as ``core.field.earth_field``), in Tesla; angles in degrees, inclination positive down,
declination positive east of true north. The model describes the main (core) field only:
crustal anomalies and external disturbances add to it, and its documented 1-sigma error
in F is 138 nT for WMM-2025 (148 nT WMM-2020, 152 nT WMM-2015), i.e. about 0.3 % of F.
That error is larger than a fluxgate's noise: a reference intensity from the model fixes
the absolute scale of a calibration, not its precision.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import date, datetime, time, timezone
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pygeomag import GeoMag
from pygeomag.wmm.wmm_2015v2 import WMM_2015v2
from pygeomag.wmm.wmm_2020 import WMM_2020
from pygeomag.wmm.wmm_2025 import WMM_2025

from magcal_ros.core.units import NT
from magcal_ros.errors import InputError

Array = NDArray[np.float64]

ALTITUDE_RANGE_M: tuple[float, float] = (-1_000.0, 850_000.0)
"""Heights (m above the WGS 84 ellipsoid, about mean sea level) the WMM is specified for."""
LATITUDE_RANGE_DEG: tuple[float, float] = (-90.0, 90.0)
LONGITUDE_RANGE_DEG: tuple[float, float] = (-180.0, 360.0)
"""Accepted longitudes (deg east); 180..360 is the same as -180..0."""

# (epoch, coefficients as pygeomag ships them in Python modules), newest first.
_MODELS: tuple[tuple[float, tuple[Any, ...]], ...] = ((2025.0, WMM_2025), (2020.0, WMM_2020), (2015.0, WMM_2015v2))
_LIFESPAN_YEARS = 5.0
VALID_YEARS: tuple[float, float] = (_MODELS[-1][0], _MODELS[0][0] + _LIFESPAN_YEARS)
"""Decimal years covered by the shipped models: [2015.0, 2030.0)."""


@dataclass(frozen=True)
class SiteField:
    """The model's main field at one site and time (SI units, NED frame)."""

    latitude_deg: float
    """Geodetic latitude, deg north."""
    longitude_deg: float
    """Longitude, deg east, in [-180, 180)."""
    altitude_m: float
    """Height above the WGS 84 ellipsoid (m; negative below sea level)."""
    when: datetime
    """The time evaluated (UTC)."""
    decimal_year: float
    model: str
    """Model name and edition, e.g. ``WMM-2025``."""
    epoch: float
    """First decimal year of the model's validity (it ends 5 years later)."""
    vector: Array
    """(3,) field in T, NED: north, east, down."""
    intensity: float
    """Total intensity F (T)."""
    inclination_deg: float
    declination_deg: float
    intensity_error: float
    """The model's documented 1-sigma error in F (T), NOAA's error model for this edition."""

    def describe(self) -> str:
        """Where the reference came from, e.g. ``WMM-2025 at 43.2N 5.4E 0 m on 2026-11-23``."""
        midnight = self.when.time() == time(0, 0)
        when = self.when.date().isoformat() if midnight else self.when.strftime("%Y-%m-%dT%H:%M:%SZ")
        return (
            f"{self.model} at {_angle(self.latitude_deg, 'N', 'S')} {_angle(self.longitude_deg, 'E', 'W')} "
            f"{self.altitude_m:g} m on {when}"
        )

    def provenance(self) -> dict[str, Any]:
        """Calibration-file provenance keys (T and deg) describing this reference."""
        return {
            "reference_source": self.describe(),
            "reference_model_intensity": self.intensity,
            "reference_model_inclination_deg": self.inclination_deg,
            "reference_model_declination_deg": self.declination_deg,
            "reference_model_error": self.intensity_error,
        }


def _angle(value: float, positive: str, negative: str) -> str:
    """``43.2N`` style: up to 5 decimals, trailing zeros dropped."""
    text = f"{abs(value):.5f}".rstrip("0").rstrip(".")
    return f"{text}{positive if value >= 0 else negative}"


def decimal_year(when: date | datetime) -> float:
    """Year plus the elapsed fraction of it (a date is taken at 00:00 UTC; naive times are UTC)."""
    t = _utc(when)
    start = datetime(t.year, 1, 1, tzinfo=timezone.utc)
    end = datetime(t.year + 1, 1, 1, tzinfo=timezone.utc)
    return t.year + (t - start).total_seconds() / (end - start).total_seconds()


def _utc(when: date | datetime) -> datetime:
    if isinstance(when, datetime):
        return when.replace(tzinfo=timezone.utc) if when.tzinfo is None else when.astimezone(timezone.utc)
    if isinstance(when, date):
        return datetime(when.year, when.month, when.day, tzinfo=timezone.utc)
    raise InputError(f"date must be a date or datetime, got {type(when).__name__}")


def parse_date(text: str | None) -> date:
    """``YYYY-MM-DD`` to a date; empty or None: today (UTC). :class:`InputError` otherwise."""
    if text is None or not text.strip():
        return datetime.now(timezone.utc).date()
    try:
        return date.fromisoformat(text.strip())
    except ValueError:
        raise InputError(f"date {text!r} is not a calendar date YYYY-MM-DD (e.g. 2026-11-23)") from None


def parse_site(values: Sequence[float]) -> tuple[float, float, float]:
    """``[lat_deg, lon_deg]`` or ``[lat_deg, lon_deg, alt_m]`` to (lat, lon, alt); altitude 0 if absent."""
    site = [float(v) for v in values]
    if len(site) not in (2, 3):
        raise InputError(f"a site is latitude, longitude (deg) and optionally altitude (m): got {len(site)} numbers")
    return site[0], site[1], site[2] if len(site) == 3 else 0.0


def _check_site(lat: float, lon: float, alt_m: float) -> None:
    for name, value, (lo, hi), unit in (
        ("latitude", lat, LATITUDE_RANGE_DEG, "deg"),
        ("longitude", lon, LONGITUDE_RANGE_DEG, "deg"),
        ("altitude", alt_m, ALTITUDE_RANGE_M, "m"),
    ):
        if not (math.isfinite(value) and lo <= value <= hi):
            where = " above the WGS 84 ellipsoid, the World Magnetic Model's range" if name == "altitude" else ""
            raise InputError(f"{name} {value:g} {unit} is outside {lo:g} .. {hi:g} {unit}{where}")


def _model_for(year: float, when: datetime) -> tuple[float, tuple[Any, ...]]:
    """(epoch, pygeomag coefficient data) of the model valid at ``year``."""
    lo, hi = VALID_YEARS
    if not lo <= year < hi:
        raise InputError(
            f"date {when.date().isoformat()} is outside the World Magnetic Model's validity "
            f"({int(lo)}-01-01 .. {int(hi) - 1}-12-31, editions WMM-2015v2, WMM-2020, WMM-2025): "
            "give a date inside it or the intensity by hand"
        )
    return next(m for m in _MODELS if m[0] <= year)


def site_field(latitude_deg: float, longitude_deg: float, altitude_m: float, when: date | datetime) -> SiteField:
    """The WMM main field at a site and time.

    ``latitude_deg`` -90..90 (geodetic, north positive), ``longitude_deg`` -180..360 (east
    positive), ``altitude_m`` -1000..850000 m above the WGS 84 ellipsoid (negative under
    water), ``when`` a date (00:00 UTC) or datetime (naive = UTC) in 2015-01-01 ..
    2029-12-31. Raises :class:`InputError` naming the valid range otherwise.
    """
    lat, lon, alt = float(latitude_deg), float(longitude_deg), float(altitude_m)
    _check_site(lat, lon, alt)
    lon = (lon + 180.0) % 360.0 - 180.0
    t = _utc(when)
    year = decimal_year(t)
    epoch, coefficients = _model_for(year, t)
    model = GeoMag(coefficients_data=coefficients)
    result = model.calculate(glat=lat, glon=lon, alt=alt / 1000.0, time=year)
    return SiteField(
        latitude_deg=lat, longitude_deg=lon, altitude_m=alt, when=t, decimal_year=year, model=model.model,
        epoch=epoch, vector=np.array([result.x, result.y, result.z]) * NT, intensity=float(result.f) * NT,
        inclination_deg=float(result.i), declination_deg=float(result.d),
        intensity_error=round(float(result.calculate_uncertainty().f) * NT, 15),
    )

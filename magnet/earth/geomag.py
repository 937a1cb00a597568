"""The Earth's magnetic field at a place and date, from the World Magnetic Model WMM2025 (through ``pygeomag``).

Declination is positive east (true heading = magnetic heading + declination, seed 001 eq. 1); inclination (dip) is
positive when the field points below the horizon (northern hemisphere). Field components are in microtesla in the
local north-east-down frame: north_ut, east_ut, down_ut (WMM's X, Y, Z).

WMM2025 is valid from 2025.0 to 2030.0; a date outside that span is refused with a ValueError, since an extrapolated
declination can be wrong by degrees.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import math
import threading
from typing import Any

COEFFICIENTS_FILE = "wmm/WMM_2025.COF"
MODEL_START_YEAR = 2025.0
MODEL_END_YEAR = 2030.0
UT_PER_NT = 0.001

DateLike = _dt.date | str | float | int | None


@dataclasses.dataclass(frozen=True)
class EarthField:
    """The main field at one place and date.

    Attributes (degrees and microtesla):
        declination_deg: angle from true north to the horizontal field, positive east.
        inclination_deg: dip below the horizon, positive down.
        total_ut, horizontal_ut: field magnitude and its horizontal part.
        north_ut, east_ut, down_ut: NED components.
        blackout: the horizontal field is under 2000 nT (near the magnetic poles): a compass is unreliable there.
        caution: the horizontal field is under 6000 nT: heading is degraded.
    """

    declination_deg: float
    inclination_deg: float
    total_ut: float
    horizontal_ut: float
    north_ut: float
    east_ut: float
    down_ut: float
    blackout: bool = False
    caution: bool = False

    @property
    def ned_ut(self) -> tuple[float, float, float]:
        """The field vector (north, east, down) in uT."""
        return (self.north_ut, self.east_ut, self.down_ut)


def decimal_year(date: DateLike = None) -> float:
    """A date as a decimal year: ``datetime.date``/``datetime``, ``"YYYY-MM-DD"``, a number (already a decimal year),
    or None for today. Raises ValueError for anything else."""
    if date is None:
        date = _dt.date.today()
    if isinstance(date, bool):
        raise ValueError(f"date must be a date, 'YYYY-MM-DD' or a decimal year, got {date!r}")
    if isinstance(date, (int, float)):
        year = float(date)
        if not math.isfinite(year):
            raise ValueError(f"decimal year must be finite, got {date!r}")
        return year
    if isinstance(date, str):
        try:
            text = date.strip()
            date = _dt.date.fromisoformat(text)
        except ValueError:
            try:
                return decimal_year(float(text))
            except ValueError:
                raise ValueError(f"date {date!r} is neither 'YYYY-MM-DD' nor a decimal year such as 2026.5") from None
    if isinstance(date, _dt.datetime):
        date = date.date()
    if not isinstance(date, _dt.date):
        raise ValueError(f"date must be a date, 'YYYY-MM-DD' or a decimal year, got {date!r}")
    start = _dt.date(date.year, 1, 1)
    days_in_year = (_dt.date(date.year + 1, 1, 1) - start).days
    return date.year + (date - start).days / days_in_year


@functools.lru_cache(maxsize=1)
def _model() -> Any:
    from pygeomag import GeoMag  # imported lazily: pure Python, no network or bus

    return GeoMag(coefficients_file=COEFFICIENTS_FILE)


_MODEL_LOCK = threading.Lock()  # GeoMag keeps scratch state between calls; guard it when services share it


def _check_location(lat_deg: float, lon_deg: float, alt_m: float) -> None:
    for name, value in (("latitude", lat_deg), ("longitude", lon_deg), ("altitude", alt_m)):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"latitude must be within -90..90 degrees, got {lat_deg}")
    if not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"longitude must be within -180..180 (or 0..360) degrees, got {lon_deg}")
    if not -1000.0 <= alt_m <= 850_000.0:
        raise ValueError(f"altitude must be within -1 km..850 km (WMM validity), got {alt_m} m")


@functools.lru_cache(maxsize=4096)
def _earth_field_cached(lat_deg: float, lon_deg: float, alt_m: float, year: float) -> EarthField:
    with _MODEL_LOCK:
        result = _model().calculate(lat_deg, lon_deg, alt_m / 1000.0, year)
    horizontal_nt = math.hypot(result.x, result.y)
    return EarthField(
        declination_deg=float(result.d),
        inclination_deg=float(result.i),
        total_ut=float(result.f) * UT_PER_NT,
        horizontal_ut=horizontal_nt * UT_PER_NT,
        north_ut=float(result.x) * UT_PER_NT,
        east_ut=float(result.y) * UT_PER_NT,
        down_ut=float(result.z) * UT_PER_NT,
        blackout=horizontal_nt < 2000.0,
        caution=horizontal_nt < 6000.0,
    )


def earth_field(lat_deg: float, lon_deg: float, alt_m: float = 0.0, date: DateLike = None) -> EarthField:
    """The WMM2025 field at geodetic latitude/longitude (degrees), altitude above the ellipsoid (metres) and date.

    ``date``: ``datetime.date``, ``"YYYY-MM-DD"``, decimal year, or None for today. Raises ValueError for an invalid
    place or a date outside 2025.0..2030.0. Results are cached per (place, date).
    """
    lat, lon, alt = float(lat_deg), float(lon_deg), float(alt_m)
    _check_location(lat, lon, alt)
    year = decimal_year(date)
    if not MODEL_START_YEAR <= year <= MODEL_END_YEAR:
        raise ValueError(
            f"date {year:.3f} is outside WMM2025's life span ({MODEL_START_YEAR:.0f}.0 to {MODEL_END_YEAR:.0f}.0): "
            "give a date in that span"
        )
    return _earth_field_cached(lat, lon, alt, year)

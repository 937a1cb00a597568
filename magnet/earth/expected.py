"""What the compass expects where a device is: ``Earth`` (declination, |B|, dip) from the World Magnetic Model.

One lookup, ``earth_at(location, date)``: the caller says which day (the compass derives it from the clock it is
given, or takes ``--date``), so nothing here reads the clock; places that round to the same ~1 km
(``Location.rounded``) share one model evaluation per date.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools

from magnet.earth.geomag import DateLike, EarthField, earth_field
from magnet.earth.location import Location


@dataclasses.dataclass(frozen=True)
class Earth:
    """What the compass expects at a place: declination (deg, east +), |B| (uT), dip (deg); None = unknown."""

    declination_deg: float = 0.0
    total_ut: float | None = None
    inclination_deg: float | None = None

    @classmethod
    def of(cls, field: EarthField) -> Earth:
        return cls(field.declination_deg, field.total_ut, field.inclination_deg)


@functools.lru_cache(maxsize=4096)
def _earth(rounded: tuple[float, float, float], date: _dt.date | str | float) -> Earth:
    return Earth.of(earth_field(*rounded, date))


def earth_at(location: Location | None, date: DateLike) -> Earth:
    """What the WMM expects at ``location`` (rounded to about 1 km) on ``date`` (``datetime.date``, ``YYYY-MM-DD`` or
    a decimal year); ``Earth()`` (nothing known) without a location. ValueError for a date outside the model's life.
    ``date`` None means today as ``magnet.earth.geomag`` reads it (not cached here: a long-running caller passes its
    own)."""
    if location is None:
        return Earth()
    if date is None:
        return Earth.of(earth_field(*location.rounded(), None))
    return _earth(location.rounded(), date)


def utc_date(now_ns: int) -> _dt.date:
    """The UTC calendar day of a wall-clock time in ns since the epoch (the compass's "today", from its step)."""
    return (_dt.datetime(1970, 1, 1, tzinfo=_dt.UTC) + _dt.timedelta(microseconds=now_ns // 1000)).date()

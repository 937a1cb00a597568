"""Where a device is: ``Location`` (latitude, longitude in degrees, altitude in metres), checked in one place.

On the wire a raw message may carry ``location: [lat_deg, lon_deg, alt_m]`` (optional); in a places file or on the
command line it is ``"LAT,LON[,ALT_M]"`` or ``[lat, lon(, alt)]``. The one location type and parser of the project
(every ``--location`` goes through ``Location.parse``, once per service). Pure: no wire, no files.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

#: altitude limits (m): the World Magnetic Model's validity, from 1 km below the ellipsoid to 850 km above
MIN_ALT_M, MAX_ALT_M = -1_000.0, 850_000.0
#: places that round to the same ROUND_DIGITS decimals of a degree (0.01 deg: about 1 km) and ROUND_ALT_M metres
#: share one model lookup
ROUND_DIGITS, ROUND_ALT_M = 2, 100.0


@dataclasses.dataclass(frozen=True)
class Location:
    """lat_deg in [-90, 90], lon_deg in [-180, 180], alt_m in [-1 km, 850 km] (WMM validity); all finite."""

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lat_deg", "lon_deg", "alt_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"location {name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if not -90.0 <= self.lat_deg <= 90.0:
            raise ValueError(f"latitude must be within -90..90 degrees, got {self.lat_deg}")
        if not -180.0 <= self.lon_deg <= 180.0:
            raise ValueError(f"longitude must be within -180..180 degrees, got {self.lon_deg}")
        if not MIN_ALT_M <= self.alt_m <= MAX_ALT_M:
            raise ValueError(f"altitude must be within -1 km..850 km (WMM validity), got {self.alt_m} m")

    @classmethod
    def parse(cls, value: Any) -> Location:
        """From ``"LAT,LON[,ALT_M]"``, ``[lat, lon(, alt)]`` or ``{lat_deg, lon_deg(, alt_m)}``; ValueError saying the
        expected form otherwise."""
        if isinstance(value, Location):
            return value
        if isinstance(value, str):
            parts = [p.strip() for p in value.split(",")]
            try:
                numbers: list[Any] = [float(p) for p in parts]
            except ValueError:
                raise ValueError(f"location {value!r} must be LAT,LON[,ALT_M] (e.g. 50.45,30.52,180)") from None
        elif isinstance(value, dict):
            numbers = [value.get("lat_deg"), value.get("lon_deg"), value.get("alt_m", 0.0)]
        elif isinstance(value, (list, tuple)):
            numbers = list(value)
        else:
            raise ValueError(f"location must be LAT,LON[,ALT_M] or [lat, lon, alt_m], got {type(value).__name__}")
        if len(numbers) not in (2, 3):
            raise ValueError(f"location {value!r} must hold 2 or 3 numbers: LAT,LON[,ALT_M]")
        return cls(*numbers)

    def as_tuple(self) -> tuple[float, float, float]:
        """``(lat_deg, lon_deg, alt_m)``, as ``magnet.earth.geomag.earth_field`` takes them."""
        return (self.lat_deg, self.lon_deg, self.alt_m)

    def to_wire(self) -> list[float]:
        """``[lat_deg, lon_deg, alt_m]``."""
        return [self.lat_deg, self.lon_deg, self.alt_m]

    def rounded(self) -> tuple[float, float, float]:
        """The model lookup key: lat and lon to ROUND_DIGITS decimals, alt to ROUND_ALT_M."""
        return (
            round(self.lat_deg, ROUND_DIGITS),
            round(self.lon_deg, ROUND_DIGITS),
            float(round(self.alt_m / ROUND_ALT_M) * ROUND_ALT_M),
        )

    def __str__(self) -> str:
        return f"{self.lat_deg:g},{self.lon_deg:g},{self.alt_m:g}"

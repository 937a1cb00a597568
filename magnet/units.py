"""Units of magnetic field and their conversion to microtesla (uT), the library's unit.

1 gauss = 100 uT; 1 milligauss = 0.1 uT; 1 nT (= 1 gamma) = 0.001 uT. ``counts`` are raw sensor codes with no known
scale.
"""

from __future__ import annotations

import enum

#: the weakest and strongest total field the Earth has at its surface (uT, WMM)
EARTH_MIN_UT, EARTH_MAX_UT = 22.0, 67.0


class FieldUnit(enum.Enum):
    """Unit of a raw magnetometer column."""

    UT = "ut"
    GAUSS = "gauss"
    MGAUSS = "mgauss"
    NT = "nt"
    COUNTS = "counts"

    @classmethod
    def parse(cls, name: str) -> FieldUnit:
        try:
            return cls(name.strip().lower())
        except ValueError:
            choices = ", ".join(u.value for u in cls)
            raise ValueError(f"unknown field unit {name!r}: use one of {choices}") from None


UT_PER_GAUSS = 100.0
UT_PER_MGAUSS = 0.1
#: microtesla per one unit; None where the scale is unknown (raw counts).
UT_PER_UNIT: dict[FieldUnit, float | None] = {
    FieldUnit.UT: 1.0,
    FieldUnit.GAUSS: UT_PER_GAUSS,
    FieldUnit.MGAUSS: UT_PER_MGAUSS,
    FieldUnit.NT: 0.001,
    FieldUnit.COUNTS: None,
}

STANDARD_GRAVITY_MS2 = 9.80665

_UNIT_ALIASES = {"gamma": "nt", "g": "gauss", "microtesla": "ut", "µt": "ut", "mg": "mgauss", "milligauss": "mgauss"}


def ut_per_unit(unit: str) -> float | None:
    """uT per one raw unit, or None when the unit has no known scale (``counts``, free words)."""
    name = unit.strip().lower()
    try:
        return UT_PER_UNIT[FieldUnit(_UNIT_ALIASES.get(name, name))]
    except ValueError:
        return None

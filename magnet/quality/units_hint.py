"""Advice for a fit made in the wrong unit: which unit the data are probably in.

A fit's radius is the field's strength in the unit the data were declared in. When that strength is far from the
expected field by a factor that one unit's scale explains, the advice names that unit. Let ``r_raw`` be the radius
in the declared unit; read with a unit of ``s`` uT per unit it would be ``r_raw * s`` uT. A unit explains the radius
when that value lands within the gate's radius tolerance of the expected field (the WMM's, when the place is known),
or, with no place, within the range of the Earth's field at the surface (22 to 67 uT).

The candidate units are those ``--unit`` accepts (gauss: 100 uT; mgauss: 0.1 uT; nT: 0.001 uT) and raw counts at the
gains of the chips in ``magnet.drivers`` (counts per uT = LSB per gauss / 100), for which the advice is ``--unit
counts`` (or converting with the chip's gain).
"""

from __future__ import annotations

import math

from magnet.units import EARTH_MAX_UT, EARTH_MIN_UT

UNIT_SCALES_UT = (("gauss", 100.0), ("mgauss", 0.1), ("nt", 0.001), ("ut", 1.0))


def chip_count_scales() -> list[tuple[str, float]]:
    """(chip and gain, uT per count) of every magnetometer driver's gain settings."""
    from magnet.drivers.ak09918c import UT_PER_COUNT as AK_UT_PER_COUNT
    from magnet.drivers.lsm9ds1 import MAG_RANGES as LSM9_RANGES
    from magnet.drivers.lsm303dlh import LSB_PER_GAUSS as LSM303_LSB_PER_GAUSS
    from magnet.drivers.qmc5883l import RANGES as QMC_RANGES
    from magnet.drivers.selftest import LSB_PER_GAUSS as HMC_LSB_PER_GAUSS

    out = [(f"hmc5883l gain {gn}", 100.0 / lsb) for gn, lsb in enumerate(HMC_LSB_PER_GAUSS)]
    out += [(f"lsm303dlh gain {code}", 100.0 / lsb[0]) for code, lsb in sorted(LSM303_LSB_PER_GAUSS.items())]
    out += [(f"qmc5883l {fs} gauss", 100.0 / lsb) for fs, (_, lsb) in sorted(QMC_RANGES.items())]
    out += [(f"lsm9ds1 {fs} gauss", mg / 10.0) for fs, (_, mg) in sorted(LSM9_RANGES.items())]
    out += [("ak09918c/icm20948", AK_UT_PER_COUNT)]
    return out


def unit_hint(
    radius: float,
    declared_ut_per_unit: float | None,
    expected_field_ut: float | None,
    tolerance_pct: float = 15.0,
) -> str | None:
    """The advice when the fitted ``radius`` (in the declared unit, whose scale is ``declared_ut_per_unit`` uT per
    unit; None: counts) is implausible for the expected field (uT; None: the Earth's range) and another unit explains
    it; None when the radius is plausible or nothing explains it."""
    if not math.isfinite(radius) or radius <= 0 or declared_ut_per_unit is None:
        return None
    if expected_field_ut is not None and expected_field_ut > 0:
        low, high = expected_field_ut * (1 - tolerance_pct / 100), expected_field_ut * (1 + tolerance_pct / 100)
        against = f"the expected {expected_field_ut:.1f} uT"
    else:
        low, high, against = EARTH_MIN_UT, EARTH_MAX_UT, f"the Earth's field ({EARTH_MIN_UT:g}-{EARTH_MAX_UT:g} uT)"
    radius_ut = radius * declared_ut_per_unit
    if low <= radius_ut <= high:
        return None
    units = [name for name, scale in UNIT_SCALES_UT if low <= radius * scale <= high and scale != declared_ut_per_unit]
    chips = [name for name, scale in chip_count_scales() if low <= radius * scale <= high]
    if not units and not chips:
        return None
    ratio = radius_ut / (expected_field_ut or math.sqrt(EARTH_MIN_UT * EARTH_MAX_UT))
    options = [f"--unit {name}" for name in units]
    if chips:
        shown = ", ".join(chips[:4]) + (" ..." if len(chips) > 4 else "")
        options.append(f"--unit counts (raw counts of a {shown})")
    return (
        f"the fitted radius {radius_ut:.4g} uT is {ratio:.3g} x {against}: the data are probably not in the unit "
        f"given: try {' or '.join(options)}"
    )


def earth_range_refusal(radius: float, declared_ut_per_unit: float | None) -> str | None:
    """Why a fitted field strength ``radius`` (in the declared unit, ``declared_ut_per_unit`` uT per unit; None:
    counts, not judged) can be no Earth field when no expected field is known: the total field at the surface lies in
    EARTH_MIN_UT..EARTH_MAX_UT everywhere, so a radius outside it is a wrong unit (gauss read as uT: 0.5 "uT"). The
    refusal names the unit to try where one explains the radius (``unit_hint``); None when the radius is plausible."""
    if declared_ut_per_unit is None or not math.isfinite(radius) or radius <= 0:
        return None
    radius_ut = radius * declared_ut_per_unit
    if EARTH_MIN_UT <= radius_ut <= EARTH_MAX_UT:
        return None
    return unit_hint(radius, declared_ut_per_unit, None) or (
        f"fitted radius {radius_ut:.3g} uT is no Earth field ({EARTH_MIN_UT:g}-{EARTH_MAX_UT:g} uT anywhere at the "
        "surface): the samples are in another unit than declared (--unit)"
    )

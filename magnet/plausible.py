"""Whether a calibration record is one a real sensor could have (``check_plausible``): the entry check of every
record from outside, called by ``magnet.model.Calibration.from_dict`` (and re-exported there).

It reads only arrays and units (``Correction``: any record with ``matrix``, ``offset``, ``unit`` and
``output_unit``), so it depends on no record module and ``magnet.model`` can import it without a circle."""

from __future__ import annotations

import math
from typing import Protocol, TypeVar

import numpy as np

from magnet.units import ut_per_unit


class Correction(Protocol):
    """What the check reads of a calibration: ``matrix`` (3,3) output units per raw unit, ``offset`` (3,) raw
    units, the raw ``unit`` and the ``output_unit``."""

    @property
    def matrix(self) -> np.ndarray: ...

    @property
    def offset(self) -> np.ndarray: ...

    @property
    def unit(self) -> str: ...

    @property
    def output_unit(self) -> str: ...


C = TypeVar("C", bound=Correction)

#: A correction matrix whose largest / smallest singular value exceeds this is not a sensor's (the gate refuses
#: fits beyond 5; this entry check refuses what no fit of a real sensor gives).
MAX_CONDITION = 10.0
#: Largest plausible |offset| component: in uT where the raw unit converts to uT (a +-50 gauss range), else in raw
#: units (a 24-bit converter).
MAX_OFFSET_UT = 5_000.0
MAX_OFFSET_RAW = float(2**24)
#: Largest plausible gain of the correction either way (its singular values, in output units per raw unit, over the
#: units' ratio): a real correction rescales the field by a few per cent to a factor of a few (the gate refuses axis
#: ratios beyond 5), never by 10. Where a unit's scale is unknown (counts), only UNKNOWN_SCALE_GAIN bounds it.
MAX_GAIN = 10.0
UNKNOWN_SCALE_GAIN = 1e6
#: No plausible correction has an entry this large (MAX_GAIN times the largest ratio of units, gauss to nT, is 1e6):
#: beyond it a record is refused before any matrix arithmetic, which would overflow.
MAX_MATRIX_ENTRY = 1e9


def check_plausible(calibration: C) -> C:
    """``calibration`` if a real sensor could have it, else ValueError naming what is wrong and what to do.

    Checks, each before the arithmetic that needs the one before: every matrix entry within MAX_MATRIX_ENTRY (no
    overflow below), the matrix's condition number (largest / smallest singular value) <= MAX_CONDITION, its gain
    within MAX_GAIN either way (``_check_gain``: a vanishing matrix such as 1e-300 times the identity is refused here,
    as implausible), its determinant's sign > 0 (no reflection: it would mirror every heading), and each offset
    component within MAX_OFFSET_UT (uT, where the raw unit converts to uT) or MAX_OFFSET_RAW (raw units otherwise)."""
    largest = float(np.abs(calibration.matrix).max())
    if largest > MAX_MATRIX_ENTRY:
        raise ValueError(
            f"calibration matrix holds an entry of {largest:.3g}, beyond {MAX_MATRIX_ENTRY:g}: no sensor needs "
            "that; check the record's units and fit again"
        )
    singular = np.linalg.svd(calibration.matrix, compute_uv=False)
    condition = singular[0] / singular[-1] if singular[-1] > 0 else math.inf
    if not condition <= MAX_CONDITION:
        raise ValueError(
            f"calibration matrix condition number {condition:.3g} exceeds {MAX_CONDITION:g}: it is "
            "singular or absurdly anisotropic; fit again from data covering all attitudes"
        )
    _check_gain(singular, calibration)
    sign, _ = np.linalg.slogdet(calibration.matrix)  # the sign alone: a determinant of 1e-900 does not underflow
    if sign <= 0:
        raise ValueError(
            "calibration matrix has a negative determinant (a reflection, which mirrors headings): "
            "check the axis signs and fit again"
        )
    to_ut = ut_per_unit(calibration.unit)
    limit, unit = (MAX_OFFSET_UT / to_ut, calibration.unit) if to_ut else (MAX_OFFSET_RAW, calibration.unit)
    worst = float(np.abs(calibration.offset).max())
    if worst > limit:
        raise ValueError(
            f"calibration offset {worst:.4g} {unit} exceeds {limit:.4g} {unit}: no sensor reads that; "
            "check the record's unit and fit again"
        )
    return calibration


def _check_gain(singular: np.ndarray, calibration: Correction) -> None:
    """ValueError when the correction's gain (singular values, descending) is beyond what a sensor needs."""
    raw_ut, out_ut = ut_per_unit(calibration.unit), ut_per_unit(calibration.output_unit)
    if raw_ut and out_ut:
        gain, limit = singular / (raw_ut / out_ut), MAX_GAIN
    else:
        gain, limit = singular, UNKNOWN_SCALE_GAIN
    if not (gain[0] <= limit and gain[-1] >= 1 / limit):
        raise ValueError(
            f"calibration matrix scales the field by {gain[-1]:.3g} to {gain[0]:.3g} "
            f"({calibration.unit} to {calibration.output_unit}), beyond 1/{limit:g} to {limit:g}: no "
            "sensor needs that; check the record's units and fit again"
        )

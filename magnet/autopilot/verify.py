"""After ``magnet export --apply``: does the vehicle now correct its compass as the record says? (docs/mavlink.md)

ArduPilot sends the field it has corrected (SCALED_IMU, RAW_IMU: its offsets, matrix and scale applied,
``magnet.autopilot.params``): f = W (s (R r + o)) in milligauss, r the sensor's reading in its own axes. The record
was fitted on what the vehicle sent *before* the parameters changed, u = W_o (s_o (R_o r + o_o)), and says two
things of the field the vehicle will send:

1. its size is the Earth's field the record was scaled to (``field_strength``) at every attitude: the RMS of
   |f| - F must be within ``AGREE_UT`` or ``AGREE_FRACTION`` of F. This is what a vehicle that did not take the
   values (or whose compass is another sensor) fails: its field's size follows the attitude.
2. its direction is the record's B = A (u - b): from each f the reading r is recovered with the new parameters, u
   with the old ones, and B with the record; the RMS of f - B must be within the same limit. With old parameters
   at their defaults this holds by construction of the export; it fails when the record was fitted on a field the
   vehicle had corrected with an older calibration, which the written values replace rather than add to.

A vehicle that does not turn during the check tests 1 at one attitude only; the summary says how far its field
turned.

The motors' compensation is left out of both sides (samples at high current differ by what it adds). Pure: numbers in,
a verdict out.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.autopilot.params import in_microtesla
from magnet.frames import rotation_matrix
from magnet.model import Calibration
from magnet.units import UT_PER_MGAUSS

#: the vehicle agrees when the RMS of (its field - the record's) is within the larger of these
AGREE_UT = 1.0
AGREE_FRACTION = 0.02
#: fewer samples than this say nothing
MIN_SAMPLES = 50
#: ArduPilot applies COMPASS_SCALE only within this range (else 1)
SCALE_RANGE = (0.85, 1.4)


@dataclasses.dataclass(frozen=True)
class Correction:
    """ArduPilot's correction of one compass: W (3, 3), offsets o (3,) mGauss, scale s, orientation R (3, 3)."""

    matrix: np.ndarray
    offsets_mg: np.ndarray
    scale: float
    rotation: np.ndarray

    def field(self, reading_mg: np.ndarray) -> np.ndarray:
        """(N, 3) mGauss the vehicle sends for sensor readings (N, 3) mGauss in the sensor's axes."""
        return self.scale * (reading_mg @ self.rotation.T + self.offsets_mg) @ self.matrix.T

    def reading(self, field_mg: np.ndarray) -> np.ndarray:
        """The sensor's readings (N, 3) mGauss behind fields (N, 3) mGauss the vehicle sent."""
        body = np.linalg.solve(self.matrix, (field_mg / self.scale).T).T - self.offsets_mg
        return body @ self.rotation

    @property
    def identity(self) -> bool:
        """No correction (offsets zero, matrix and scale one): the vehicle sends the reading, rotated."""
        return bool(np.allclose(self.matrix, np.eye(3)) and not self.offsets_mg.any() and self.scale == 1.0)


def ardupilot_correction(params: Mapping[str, float], instance: int, orientation: int) -> Correction:
    """The correction ArduPilot's parameters (``COMPASS_OFS``.., missing ones at their defaults) make for compass
    ``instance``; ``orientation`` the COMPASS_ORIENTn in force when ``params`` holds none."""
    n = "" if instance == 0 else str(instance + 1)

    def value(name: str, default: float) -> float:
        return float(params.get(name, default))

    diagonal = [value(f"COMPASS_DIA{n}_{a}", 0.0) for a in "XYZ"]
    off = [value(f"COMPASS_ODI{n}_{a}", 0.0) for a in "XYZ"]
    matrix = np.eye(3)
    if any(diagonal):  # all-zero diagonals mean identity (docs/autopilots.md)
        matrix = np.array([[diagonal[0], off[0], off[1]], [off[0], diagonal[1], off[2]], [off[1], off[2], diagonal[2]]])
    scale = value(f"COMPASS_SCALE{n}", 0.0)
    scale = scale if SCALE_RANGE[0] <= scale <= SCALE_RANGE[1] else 1.0
    offsets = np.array([value(f"COMPASS_OFS{n}_{a}", 0.0) for a in "XYZ"])
    rotation = rotation_matrix(round(value(f"COMPASS_ORIENT{n}", orientation)))
    return Correction(matrix, offsets, scale, rotation)


@dataclasses.dataclass(frozen=True)
class AfterApply:
    """The check's verdict: samples compared, RMS of (vehicle - record) in uT, RMS of its field's size less the
    record's (uT), the record's field size (uT), how far the vehicle's field turned (deg), whether it agrees (None:
    too few samples), and why in words."""

    samples: int
    rms_ut: float | None
    size_rms_ut: float | None
    field_ut: float | None
    turned_deg: float | None
    agrees: bool | None
    summary: str

    def to_dict(self) -> dict[str, Any]:
        def rounded(x: float | None) -> float | None:
            return None if x is None else round(x, 3)

        return {
            "samples": self.samples,
            "rms_ut": rounded(self.rms_ut),
            "size_rms_ut": rounded(self.size_rms_ut),
            "field_ut": rounded(self.field_ut),
            "turned_deg": rounded(self.turned_deg),
            "agrees": self.agrees,
            "summary": self.summary,
        }


def check_after_apply(
    calibration: Calibration,
    before: Mapping[str, float],
    after: Mapping[str, float],
    instance: int,
    sent_mg: np.ndarray,
    rotation_in_force: int = 0,
) -> AfterApply:
    """Compare what the vehicle sends after the apply (``sent_mg`` (N, 3), its compass ``instance``'s field in
    mGauss, body frame) with what ``calibration`` predicts (module docstring); ``before`` the parameters' values read
    before the writes, ``after`` those written (names ArduPilot's)."""
    sent_mg = np.asarray(sent_mg, dtype=float).reshape(-1, 3)
    sent_mg = sent_mg[np.isfinite(sent_mg).all(axis=1) & sent_mg.any(axis=1)]
    if len(sent_mg) < MIN_SAMPLES:
        text = f"{len(sent_mg)} samples of compass {instance} after the apply, fewer than {MIN_SAMPLES}: not checked"
        return AfterApply(len(sent_mg), None, None, None, None, None, text)
    old = ardupilot_correction(before, instance, rotation_in_force)
    new = ardupilot_correction({**before, **after}, instance, rotation_in_force)
    offset_ut, matrix = in_microtesla(calibration)
    u_ut = old.field(new.reading(sent_mg)) * UT_PER_MGAUSS
    predicted = (u_ut - offset_ut) @ matrix.T
    sent_ut = sent_mg * UT_PER_MGAUSS
    rms = float(np.sqrt(np.mean(np.sum((sent_ut - predicted) ** 2, axis=1))))
    field = calibration.field_strength or float(np.median(np.linalg.norm(predicted, axis=1)))
    size_rms = float(np.sqrt(np.mean((np.linalg.norm(sent_ut, axis=1) - field) ** 2)))
    turned = _turned_deg(sent_ut)
    limit = max(AGREE_UT, AGREE_FRACTION * field)
    agrees = rms <= limit and size_rms <= limit
    said = (
        f"over {len(sent_mg)} samples of compass {instance} (its field turned {turned:.0f} deg): its size is "
        f"{size_rms:.2f} uT RMS from the record's {field:.1f} uT, its direction {rms:.2f} uT RMS from the record's "
        f"(limit {limit:.2f} uT)"
    )
    if agrees:
        return AfterApply(len(sent_mg), rms, size_rms, field, turned, True, f"agrees {said}")
    why = ""
    if size_rms > limit:
        why += "; its field's size follows the attitude: the vehicle does not apply the values (not taken, not yet "
        why += "in force, or another sensor behind this compass)"
    if rms > limit and not old.identity:
        why += "; the vehicle held a calibration before (its old offsets or matrix were not the defaults): if the "
        why += "record was fitted on the field it corrected with it, the values written replace that correction "
        why += "instead of adding to it: calibrate again on what the vehicle sends now"
    return AfterApply(len(sent_mg), rms, size_rms, field, turned, False, f"DISAGREES {said}{why}")


def _turned_deg(field_ut: np.ndarray) -> float:
    """How far (deg) the field's direction got from its first sample's: 0 for a vehicle that stays put."""
    unit = field_ut / np.linalg.norm(field_ut, axis=1)[:, None]
    return float(np.degrees(np.arccos(np.clip(unit @ unit[0], -1.0, 1.0))).max())

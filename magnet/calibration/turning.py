"""The field's turn against the gyroscope's: how well a correction's field turns with the body
(docs/field-calibration.md, "The field's turn against the gyroscope's").

The Earth's field is constant in the Earth frame while the body turns (Kok and Schon 2016): over a window from sample
s to sample e, a right correction gives b(e) = P^T b(s), P the turn the gyroscope measured. An offset error d across
the turns leaves (I - P^T) d in every window, whatever a tilt filter makes of the accelerometer, so over windows of a
few seconds (a boat's or a car's turn of 10-90 deg) the residual tells a good correction from one a few uT off, where
the field's 1-s windows of the ladder's gyroscope block turn too little to. The gyroscope's bias beta (a phone's
reaches 0.5 deg/s) turns the measured P away from the true one by about M beta, M = Q_e^T sum_k Q_k dt (the bias
integrated in the axes the body had along the window, Q_k sample k's axes in the window's first): for a body that
turns a quarter turn within the window, M is far from dt I about the horizontal axes. It is fitted by least squares
for each correction, so that a correction is not blamed for the bias.

``turn_residual_ut``: the RMS residual (uT) after the bias, over windows that turned ``MIN_ANGLE_DEG`` to
``WINDOW_ANGLE_DEG`` within ``WINDOW_S``, both ends among the rows used. Pure numpy.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.calibration.field_input import FieldInput
from magnet.calibration.gyro_ellipsoid import gyro_attitudes, kept_windows, skew
from magnet.calibration.gyro_ellipsoid import windows as gyro_windows
from magnet.frames import rotation_vector_to_matrix
from magnet.model import Calibration
from magnet.quality import GateThresholds, for_travel, gate

#: a window ends once the gyroscope has turned this far since its start ...
WINDOW_ANGLE_DEG = 90.0
#: ... or after this long (s): a boat turning at 8-15 deg/s turns 50-90 deg in it; the bias is fitted
WINDOW_S = 6.0
#: windows that turned less than this are left out (the field's change is then mostly the sensor's noise)
MIN_ANGLE_DEG = 10.0
#: at most this many windows (starts spread evenly)
MAX_WINDOWS = 2000
#: fewer windows than this give no figure
MIN_WINDOWS = 30


@dataclasses.dataclass(frozen=True)
class Turns:
    """The gyroscope's windows: starts (M,) and ends (M,) sample indices, back (M, 3, 3) = P^T (a vector's body-s
    coordinates -> body-e), bias_gain (M, 3, 3) = M (rad of turn error per rad/s of bias, in body-e axes)."""

    starts: np.ndarray
    ends: np.ndarray
    back: np.ndarray
    bias_gain: np.ndarray


def turns(gyr_rads: np.ndarray, period_s: float, rows: np.ndarray | None = None) -> Turns | None:
    """The windows of the body rates gyr_rads (N, 3) sampled every period_s, both ends in rows (N,) bool (None:
    all); None when fewer than MIN_WINDOWS."""
    gyr = np.asarray(gyr_rads, dtype=float)
    count = len(gyr)
    if count < 3 or not period_s > 0:
        return None
    starts, ends = gyro_windows(gyr, period_s, WINDOW_ANGLE_DEG, WINDOW_S, MIN_ANGLE_DEG, every=1)
    starts, ends = kept_windows(starts, ends, rows, MAX_WINDOWS)
    if len(starts) < MIN_WINDOWS:
        return None
    axes = gyro_attitudes(rotation_vector_to_matrix(gyr * period_s))
    to_end = np.transpose(axes[ends], (0, 2, 1))
    summed = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(axes[:-1], axis=0) * period_s])
    return Turns(starts, ends, to_end @ axes[starts], to_end @ (summed[ends] - summed[starts]))


def turn_residual_ut(windows: Turns, field_ut: np.ndarray) -> float:
    """The RMS of b(e) - P^T b(s) + [w]x M beta over the windows (uT), w = P^T b(s), beta the gyroscope's bias
    fitted by least squares; field_ut (N, 3) a correction's field in uT, in body axes."""
    field = np.asarray(field_ut, dtype=float)
    w = np.einsum("nij,nj->ni", windows.back, field[windows.starts])
    residual = field[windows.ends] - w
    design = (skew(w) @ windows.bias_gain).reshape(-1, 3)
    bias, *_ = np.linalg.lstsq(design, -residual.reshape(-1), rcond=None)
    left = residual.reshape(-1) + design @ bias
    return float(np.sqrt(np.mean(left**2)))


def vehicle_turns(inp: FieldInput, planar: bool, keep: np.ndarray | None) -> Turns | None:
    """The windows (``turns``) of a field fit's input when it is a travelling planar device (its samples carry a
    velocity: a boat, a car), both ends among the kept rows (None: all); None for any other device, without a
    gyroscope or with too few turns. Such a vehicle's turns lean its unaided tilt, and the held-out heading
    consistency with it, so its candidates are chosen by how their field turns with the gyroscope
    (``candidates.best``). Measured on the bench's live path (tuning seeds): boats better; walks and robots, which
    send no velocity, moved both ways (docs/field-calibration.md, "The field's turn against the gyroscope's"), so
    theirs are chosen as before."""
    if inp.gyr is None or inp.period_s is None or inp.vel_ned_ms is None or not planar:
        return None
    return turns(np.asarray(inp.gyr, dtype=float), inp.period_s, keep)


def with_turn_residual(record: Calibration, windows: Turns | None, raw: np.ndarray) -> Calibration:
    """The record with quality ``turn_residual_ut`` (``turn_residual_ut`` of its field from the raw samples (N, 3));
    as it is without windows or when it does not correct to uT."""
    if windows is None or record.output_unit != "ut":
        return record
    turned = turn_residual_ut(windows, record.apply(raw))
    return record.replace(quality=record.quality.with_extra(turn_residual_ut=turned))


#: a refresh of a travelling level device (a record in force) must make its field turn with the gyroscope better than
#: the record in force's by this fraction (the candidates' choice asks as much: ``candidates.TURN_GAIN``)
REFRESH_TURN_GAIN = 0.05
#: what such a refresh's record says it was judged by (quality ``judged_by``)
JUDGED_BY = "the field's turn against the gyroscope's"


def judged_by_turns(
    record: Calibration,
    windows: Turns | None,
    raw: np.ndarray,
    reference: Calibration | None,
    thresholds: GateThresholds | None = None,
) -> Calibration:
    """A travelling level device's refresh (``windows`` from ``vehicle_turns``, ``reference`` the record in force
    correcting to uT) that the held-out heading consistency refused, judged again by its field's turn against the
    gyroscope's: accepted when every other check of the gate passes and its ``turn_residual_ut`` is lower than the
    record in force's on the same windows (raw (N, 3) the samples) by REFRESH_TURN_GAIN; quality
    ``reference_turn_residual_ut``, ``turn_gain_pct`` and ``judged_by`` say so. The record as it is when it was
    accepted, or for any other device. Why: the held-out consistency is measured with the filter's attitude, which a
    vehicle's turns lean, so it refused every boat refresh that took the partial arc's error out of the first record
    (boats 38, 40, 43, 51: 2.4-3.2 -> 0.7-1.2 deg in the field against the truth, within its margin of the record in
    force); the turn residual ranked those pairs as the truth did (docs/field-calibration.md, "A vehicle's refresh
    judged by its turns")."""
    mine = record.quality.get("turn_residual_ut")
    if windows is None or mine is None or reference is None or record.accepted:
        return record
    if reference.output_unit != "ut" or record.output_unit != "ut":
        return record
    theirs = turn_residual_ut(windows, reference.apply(raw))
    gain = 1.0 - float(mine) / theirs
    figures = {key: value for key, value in record.quality.to_dict().items() if key != "holdout_consistency_deg"}
    accepted, reason = gate(figures, for_travel(thresholds))
    figures_turned = f"{float(mine):.3f} against {theirs:.3f} uT RMS"
    if accepted and gain < REFRESH_TURN_GAIN:
        accepted, reason = (
            False,
            (
                f"its field turns with the gyroscope only {100 * gain:.1f} % better than the calibration in force's "
                f"({figures_turned}; a refresh must gain {100 * REFRESH_TURN_GAIN:g} %)"
            ),
        )
    elif accepted:
        better = f"its field turns with the gyroscope {100 * gain:.0f} % better than the calibration in force's"
        reason = f"{reason}; {better} ({figures_turned})"
    quality = record.quality.with_extra(
        reference_turn_residual_ut=theirs, turn_gain_pct=100.0 * gain, judged_by=JUDGED_BY
    )
    return record.replace(quality=quality, accepted=accepted, reason=f"{reason}; {record.quality.get('why', '')}")

"""Judging a calibration with data collected in motion (docs/design.md, "Heading in motion").

A moving accelerometer measures gravity plus linear acceleration, so the dip check (angle between field and gravity)
cannot use every sample. The gravity direction comes from:

- with a gyroscope: the gyroscope + accelerometer filter (``magnet.attitude.fusion``, offline, no magnetometer, so it
  does not depend on the calibration being judged): its attitude gives gravity in every sample, in motion too;
- without: the quasi-static samples only, whose specific force is within ``QUASI_STATIC_TOL`` of g (the median
  magnitude, so any unit works). A linear acceleration a tilts the measured gravity by up to a / g rad; the
  magnitude test sees its component along gravity, which for the random accelerations of a hand or a vehicle is
  as large as the rest most of the time.

A gyroscope also lets a fit check itself: the calibrated field, rotated into the earth frame by that same attitude,
must be constant in direction (constant dip, constant horizontal direction). ``direction_spread_deg`` is the RMS angle
between each sample's earth-frame field direction and their mean direction. The attitude's heading is the
gyroscope's, so it drifts slowly; the drift is the same for every calibration compared on the same samples, but it
adds noise to their difference, so the comparisons of the gate take the mean direction over stretches of
``STRETCH_S`` seconds (12 deg of drift over 2 minutes leaves 0.12 deg instead of 1.4).
Without a gyroscope the dip spread on the quasi-static samples stands in for it.

The rule (``check_consistency``): on the held-out samples (fitted without them), the candidate must make the field
more constant than the reference (the calibration in force, or none) by more than chance, and than the raw field by
at least ``MIN_GAIN_OVER_NONE`` of it: a calibration never makes heading worse. A factory-calibrated sensor in a
non-uniform local field is the case it catches: an ellipsoid fit there soaks up the field's variation with position
and bends the headings; and one whose maker's calibration is already as good as the fit, whose field a fit can only
move by its own noise.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet import frames
from magnet.attitude.mag_delay import advance_field
from magnet.frames import quaternion_to_matrix
from magnet.model import IDENTITY, Calibration, Quality
from magnet.quality import chance
from magnet.quality.stats import median, take_rows

#: |specific force| within this fraction of g (a few % of g: a cheap accelerometer's scale error is about 1 %)
QUASI_STATIC_TOL = 0.03
#: fewest quasi-static samples for a dip spread that means something
MIN_QUASI_STATIC = 30
#: runs of held-out samples whose spread gives the uncertainty of a comparison (``chance.CHUNKS``)
MARGIN_CHUNKS = chance.CHUNKS
#: the field's earth-frame direction is compared with its mean over stretches of this many seconds, not over the
#: whole recording: the gyroscope filter's heading drifts slowly (its bias about the vertical is unknown), and that
#: drift, the same for every calibration compared, would otherwise swamp their difference
STRETCH_S = 10.0
#: against no calibration a fit must also make the held-out field this fraction more constant: a maker-calibrated
#: sensor's raw field is at the noise floor, where a gain of a per cent is the fit's own noise (chance passes two
#: standard errors one time in forty). Simulated wand, tuning seeds 1-99 (docs/field-calibration.md): the one fit
#: accepted on less (1.1 %) made causal heading 12 % worse than vqf raw; the 98 others gained 5.7 % or more.
MIN_GAIN_OVER_NONE = 0.03


@dataclasses.dataclass(frozen=True)
class MotionEvidence:
    """What the samples say about attitude, for N samples.

    down: (N, 3) unit down direction in body axes (NaN rows where unknown); attitude: (N, 4) body -> earth quats from
    the gyroscope filter, or None without a gyroscope; source: "fused gravity" or "quasi-static samples";
    period_s: the sample period with a gyroscope (None: the direction is judged over every row at once);
    gyr_rads: (N, 3) the gyroscope's rates, or None.
    """

    down: np.ndarray
    attitude: np.ndarray | None
    source: str
    period_s: float | None = None
    gyr_rads: np.ndarray | None = None

    def applied(self, calibration: Calibration, raw: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """The field as the compass's filter gets it from ``calibration`` for raw samples (K, 3): corrected, and
        turned forward over the magnetometer's delay the record carries (``magnet.attitude.mag_delay``) where the rates
        are known. rows: (N,) bool, which of the evidence's rows ``raw`` holds (None: all of them)."""
        return self.turned(calibration, _corrected(calibration, raw), rows)

    def turned(self, calibration: Calibration, field: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """A field (K, 3) corrected by ``calibration`` turned forward over the delay its record carries (the same
        array when it carries none); rows as in ``applied``."""
        lag = calibration.mag_lag_s
        if not lag or self.gyr_rads is None:
            return field
        return advance_field(field, self.gyr_rads if rows is None else take_rows(self.gyr_rads, rows), lag)

    @property
    def known(self) -> np.ndarray:
        return finite_rows(self.down)

    def rows(self, keep: np.ndarray) -> MotionEvidence:
        """This evidence on the rows (N,) bool only (the filter ran over every sample, in time order; the figures
        are then taken on these rows, e.g. the undisturbed ones)."""
        attitude = None if self.attitude is None else take_rows(self.attitude, keep)
        gyr = None if self.gyr_rads is None else take_rows(self.gyr_rads, keep)
        return dataclasses.replace(self, down=take_rows(self.down, keep), attitude=attitude, gyr_rads=gyr)


def finite_rows(rows: np.ndarray) -> np.ndarray:
    """(N,) bool: the rows of an (N, 3) array whose three values are finite (``np.all(np.isfinite(rows), axis=1)``,
    several times faster: a reduction along rows of three is slow in numpy)."""
    finite = np.isfinite(rows)
    return finite[:, 0] & finite[:, 1] & finite[:, 2]


def row_norms(rows: np.ndarray) -> np.ndarray:
    """(N,) Euclidean lengths of the rows of an (N, 3) array, bit for bit ``np.linalg.norm(rows, axis=1)`` (the
    same squares summed in the same order), several times faster."""
    x, y, z = rows[:, 0], rows[:, 1], rows[:, 2]
    return np.sqrt(x * x + y * y + z * z)


def quasi_static(acc: np.ndarray, tol: float = QUASI_STATIC_TOL) -> np.ndarray:
    """(N,) bool: samples whose specific force (N, 3) is within ``tol`` of g (the median magnitude)."""
    acc = np.asarray(acc, dtype=float)
    return _near_g(np.sqrt(np.einsum("ij,ij->i", acc, acc)), tol)


def _near_g(norm: np.ndarray, tol: float) -> np.ndarray:
    """``quasi_static`` from the magnitudes (N,) of the specific force."""
    g = median(norm) if len(norm) else 0.0
    if g <= 0:
        return np.zeros(len(norm), dtype=bool)
    return np.abs(norm / g - 1.0) <= tol


#: the evidence's source when the velocity freed the accelerometer of the device's own acceleration
AIDED_SOURCE = "velocity-aided gravity"


@dataclasses.dataclass(frozen=True)
class Aiding:
    """What frees a moving device's accelerometer of its own acceleration: sample times t_s (N,) s, the velocity
    over the ground vel_ned_ms (N, 3) m/s magnetic NED (NaN rows where unknown) and the field (N, 3) uT corrected by
    a calibration (the calibration in force, or a first fit), whose heading turns the velocity's acceleration into
    the body frame."""

    t_s: np.ndarray
    vel_ned_ms: np.ndarray
    field_ut: np.ndarray


def evidence(
    acc: np.ndarray, gyr_rads: np.ndarray | None = None, period_s: float | None = None, aiding: Aiding | None = None
) -> MotionEvidence:
    """Gravity (and attitude, with a gyroscope) for samples with specific force acc (N, 3) and rates gyr (N, 3).
    With ``aiding`` (and a gyroscope) the filter is fed the accelerometer less the linear acceleration the velocity
    implies (``magnet.attitude.fusion.acc_less_velocity``): a car's or a boat's sustained accelerations then do not
    tilt it (source "velocity-aided gravity")."""
    acc = np.asarray(acc, dtype=float)
    if gyr_rads is not None:
        if period_s is None:
            raise ValueError("a gyroscope needs the sample period (t_s or a rate) to be fused")
        from magnet.attitude import fusion  # vqf's wrapper: only where a gyroscope's attitudes are needed

        source, acc_ms2 = "fused gravity", fusion.acc_in_ms2(acc)
        if aiding is not None and np.isfinite(aiding.vel_ned_ms).all(axis=1).any():
            source = AIDED_SOURCE
            acc_ms2 = fusion.acc_less_velocity(
                gyr_rads, acc_ms2, aiding.field_ut, period_s, aiding.t_s, aiding.vel_ned_ms
            )
        fused = fusion.fuse_offline(gyr_rads, acc_ms2, None, period_s)
        down = frames.down_in_body(fused.quat_wxyz)
        return MotionEvidence(down, fused.quat_wxyz, source, period_s, np.asarray(gyr_rads, dtype=float))
    norm = np.sqrt(np.einsum("ij,ij->i", acc, acc))
    down = -acc / norm[:, None]
    down[~_near_g(norm, QUASI_STATIC_TOL)] = np.nan
    return MotionEvidence(down, None, "quasi-static samples")


def dip_spread_deg(field: np.ndarray, down: np.ndarray) -> float | None:
    """Standard deviation (deg) of the dip (angle of the field below the horizon) over the rows where ``down`` is
    known; None with fewer than MIN_QUASI_STATIC of them."""
    norm = np.sqrt(np.einsum("ij,ij->i", field, field))
    along = np.einsum("ij,ij->i", field, down)  # NaN where down is unknown
    keep = np.isfinite(along) & (norm > 0)
    if np.count_nonzero(keep) < MIN_QUASI_STATIC:
        return None
    if not keep.all():
        along, norm = along[keep], norm[keep]
    dip = np.degrees(np.arcsin(np.clip(along / norm, -1.0, 1.0)))
    return float(dip.std())


def _direction_errors_deg(field: np.ndarray, attitude: np.ndarray, stretch: np.ndarray | None = None) -> np.ndarray:
    """Angle (N,) deg between each earth-frame field direction and the mean direction of its stretch (``stretch``
    (N,) int labels; None: one stretch)."""
    earth = np.einsum("nij,nj->ni", quaternion_to_matrix(attitude), field)
    unit = earth / row_norms(earth)[:, None]
    labels = np.zeros(len(unit), dtype=int) if stretch is None else np.unique(stretch, return_inverse=True)[1]
    sums = np.column_stack([np.bincount(labels, weights=unit[:, k]) for k in range(3)])
    mean = sums[labels] / row_norms(sums[labels])[:, None]
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", unit, mean), -1.0, 1.0)))


def _heading_errors_deg(field: np.ndarray, attitude: np.ndarray, stretch: np.ndarray | None = None) -> np.ndarray:
    """Angle (N,) deg about the vertical between each earth-frame field's horizontal direction and the circular mean
    of its stretch (labels as ``_direction_errors_deg``): the heading a compass takes from it, less the stretch's.
    Used to choose between accepted candidates (``holdout_heading_consistency_deg``): the 3D angle weighs a heading
    error by cos(dip) (0.38 at 67 deg) and a dip error that bends no heading in full, and so ranked a plain sphere
    fit with a far-off vertical offset (2.7 deg, headings 1.5 deg RMS) behind a planar fit (1.3 deg, headings 3.4)."""
    earth = np.einsum("nij,nj->ni", quaternion_to_matrix(attitude), field)
    angle = np.arctan2(earth[:, 1], earth[:, 0])
    labels = np.zeros(len(angle), dtype=int) if stretch is None else np.unique(stretch, return_inverse=True)[1]
    mean = np.arctan2(np.bincount(labels, weights=np.sin(angle)), np.bincount(labels, weights=np.cos(angle)))
    return np.degrees(np.angle(np.exp(1j * (angle - mean[labels]))))


def heading_consistency_deg(field: np.ndarray, ev: MotionEvidence, rows: np.ndarray) -> float | None:
    """RMS (deg) of ``_heading_errors_deg`` of field (M, 3) on the rows (N,) bool (M = rows.sum()) over stretches
    of ``STRETCH_S``; None without an attitude or rows."""
    if ev.attitude is None or not rows.any():
        return None
    index = np.flatnonzero(rows)
    stretch = None if ev.period_s is None else (index * ev.period_s // STRETCH_S).astype(int)
    return _rms(_heading_errors_deg(field, take_rows(ev.attitude, rows), stretch))


def direction_spread_deg(field: np.ndarray, attitude: np.ndarray) -> float | None:
    """RMS angle (deg) between the earth-frame field directions (field (N, 3) body, attitude (N, 4) body -> earth)
    and their mean direction; None without samples."""
    if len(field) == 0:
        return None
    return float(np.sqrt(np.mean(_direction_errors_deg(field, attitude) ** 2)))


def _errors_deg(field: np.ndarray, ev: MotionEvidence, rows: np.ndarray | None) -> np.ndarray | None:
    """Per-sample departures (deg) from a field constant in the earth frame over the selected rows (None: every
    row): the angle to the mean direction with an attitude, else the dip's departure from its mean on the rows where
    down is known."""
    return _departures_deg(field if rows is None else take_rows(field, rows), ev, rows)


def _departures_deg(chosen: np.ndarray, ev: MotionEvidence, rows: np.ndarray | None) -> np.ndarray | None:
    """``_errors_deg`` from the field on the selected rows only, chosen (M, 3) (M = rows.sum(), or N)."""
    if ev.attitude is not None:
        if rows is not None and not rows.any():
            return None
        index = np.arange(len(chosen)) if rows is None else np.flatnonzero(rows)
        stretch = None if ev.period_s is None else (index * ev.period_s // STRETCH_S).astype(int)
        return _direction_errors_deg(chosen, ev.attitude if rows is None else take_rows(ev.attitude, rows), stretch)
    down = ev.down if rows is None else take_rows(ev.down, rows)
    norm = row_norms(chosen)
    keep = finite_rows(down) & (norm > 0)
    if np.count_nonzero(keep) < MIN_QUASI_STATIC:
        return None
    if not keep.all():
        chosen, down, norm = take_rows(chosen, keep), take_rows(down, keep), norm[keep]
    unit = chosen / norm[:, None]
    dip = np.degrees(np.arcsin(np.clip(np.einsum("ij,ij->i", unit, down), -1.0, 1.0)))
    return dip - dip.mean()


def _rms(errors: np.ndarray | None) -> float | None:
    return None if errors is None else float(np.sqrt(np.mean(errors**2)))


def consistency_deg(field: np.ndarray, ev: MotionEvidence, rows: np.ndarray | None = None) -> float | None:
    """How far the field is from constant in the earth frame (deg; smaller is better) over the selected rows (None:
    every row): direction spread with an attitude, else dip spread on the quasi-static rows."""
    return _rms(_errors_deg(field, ev, rows))


def margin_deg(field: np.ndarray, other: np.ndarray, ev: MotionEvidence, rows: np.ndarray) -> float | None:
    """How much better than ``other`` (deg of consistency) ``field`` must be on the rows for the difference to be
    more than chance (``chance.difference_margin``); None when there are too few rows."""
    return chance.margin(_errors_deg(field, ev, rows), _errors_deg(other, ev, rows))


def motion_figures(
    raw: np.ndarray,
    candidate: Calibration,
    ev: MotionEvidence,
    test: np.ndarray,
    train_candidate: Calibration | None,
    reference: Calibration,
    reference_name: str,
    field: np.ndarray | None = None,
    level_turns: bool = False,
) -> dict[str, Any]:
    """Quality figures for data in motion: raw (N, 3) samples, test (N,) bool the held-out rows (train_candidate was
    fitted without them; None when that fit failed), reference the calibration to beat, reference_name how the
    reasons name it ("the calibration in force", "no calibration"). With a calibration in force the fit must also
    beat no calibration (``none_*`` figures); each comparison with its margin (``margin_deg``). field: candidate's
    corrected field (N, 3) when the caller has it (None: computed here); level_turns: a level device in an undisturbed
    field, whose comparison with no calibration may stand on its turns (``chance.margin``)."""
    raw = np.asarray(raw, dtype=float)
    field = ev.turned(candidate, candidate.apply(raw) if field is None else field)
    ref_field = ev.applied(reference, raw)
    dip_spread = dip_spread_deg(field, ev.down)
    figures: dict[str, Any] = {
        "dip_spread_deg": dip_spread,
        "dip_source": ev.source,
        "dip_samples": int(ev.known.sum()),
        "consistency": "direction" if ev.attitude is not None else "dip",
        # without an attitude the consistency over every row is that same dip spread
        "consistency_deg": consistency_deg(field, ev) if ev.attitude is not None else dip_spread,
        "reference": reference_name,
        "reference_consistency_deg": consistency_deg(ref_field, ev),
        "holdout_consistency_deg": None,
        "reference_holdout_consistency_deg": None,
    }
    if train_candidate is not None and test.any():
        test_raw = take_rows(raw, test)  # each field on the held-out rows only, its departures once for both
        held_field = ev.applied(train_candidate, test_raw, test)
        held = _departures_deg(held_field, ev, test)
        figures["holdout_heading_consistency_deg"] = heading_consistency_deg(held_field, ev, test)
        reference_held = _departures_deg(take_rows(ref_field, test), ev, test)
        figures["holdout_consistency_deg"] = _rms(held)
        figures["reference_holdout_consistency_deg"] = _rms(reference_held)
        if reference_name == "no calibration":  # a first record: a level device's turns, for ``chance.margin``
            turned = chance.turns(ev.attitude, test, ev.period_s, STRETCH_S) if level_turns else None
            figures["holdout_margin_deg"] = chance.margin(held, reference_held, turned)
        else:
            figures["holdout_margin_deg"] = chance.margin(held, reference_held)
            none_held = _departures_deg(test_raw, ev, test)
            figures["none_holdout_consistency_deg"] = _rms(none_held)
            figures["none_holdout_margin_deg"] = chance.margin(held, none_held)
    return figures


def with_motion_figures(
    quality: Quality,
    raw: np.ndarray,
    candidate: Calibration,
    ev: MotionEvidence,
    test: np.ndarray,
    holdout: tuple[np.ndarray, Calibration] | None,
    reference: Calibration | None,
    field: np.ndarray | None = None,
    level_turns: bool = False,
) -> Quality:
    """``quality`` with the figures of ``motion_figures`` (its dip spread in its own field), judged against
    ``reference`` (the calibration in force; None: no calibration); ``holdout`` the held-out fit, if any; level_turns
    as ``motion_figures``."""
    figures = motion_figures(
        raw,
        candidate,
        ev,
        test,
        holdout[1] if holdout else None,
        reference or IDENTITY,
        "the calibration in force" if reference else "no calibration",
        field,
        level_turns,
    )
    return dataclasses.replace(quality, dip_spread_deg=figures.pop("dip_spread_deg")).with_extra(**figures)


def _corrected(calibration: Calibration, raw: np.ndarray) -> np.ndarray:
    """``calibration.apply(raw)``, without the product for the identity (no calibration: the same numbers)."""
    if not calibration.offset.any() and np.array_equal(calibration.matrix, np.eye(3)):
        return raw
    return calibration.apply(raw)


def _number(quality: Quality | Mapping[str, Any], key: str) -> float | None:
    value = quality.get(key)
    return None if value is None or not math.isfinite(float(value)) else float(value)


def _refusal(quality: Quality | Mapping[str, Any], prefix: str, reference: str) -> str | None:
    """The refusal when the held-out consistency is not better than ``prefix``'s by more than its margin."""
    held, ref = _number(quality, "holdout_consistency_deg"), _number(quality, f"{prefix}holdout_consistency_deg")
    margin = _number(quality, f"{prefix.replace('reference_', '')}holdout_margin_deg") or 0.0
    least = MIN_GAIN_OVER_NONE * ref if ref is not None and reference == "no calibration" else 0.0
    if held is None or ref is None or held < ref - max(margin, least):
        return None
    what = {"direction": "direction spread in the earth frame", "dip": "dip spread"}.get(
        str(quality.get("consistency")), "spread"
    )
    if held < ref - margin:  # more than chance, less than the least gain over the raw field
        return (
            f"the fit makes the field only {100 * (1 - held / ref):.1f} % more constant than no calibration on "
            f"held-out data ({what} {held:.3f} deg vs {ref:.3f} deg; a fit must gain {100 * MIN_GAIN_OVER_NONE:g} % "
            "over the raw field): the sensor is calibrated well enough already, and a calibration never makes "
            "heading worse"
        )
    return (
        f"the fit does not make the field more constant than {reference} by more than chance ({what} on held-out "
        f"data {held:.2f} deg vs {ref:.2f} deg, margin {margin:.2f} deg), and a calibration never makes heading "
        "worse: the sensor may be calibrated well enough already, or the fit soaked up a non-uniform local field "
        "(calibrate away from iron and other devices)"
    )


def check_consistency(quality: Quality | Mapping[str, Any], thresholds: Any = None) -> str | None:
    """The gate's check: refuse a fit whose held-out field is not more constant than the reference's (and than no
    calibration's, when a calibration is in force) by more than the comparison's margin, and against no calibration
    by at least ``MIN_GAIN_OVER_NONE`` of its figure too (None: passes or not measured)."""
    reference = str(quality.get("reference") or "no calibration")
    return _refusal(quality, "reference_", reference) or _refusal(quality, "none_", "no calibration")

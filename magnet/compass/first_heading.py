"""The first heading not taken from a disturbed field (``FirstHeading``; docs/compass.md, "Disturbances").

When a filter starts, or a new record restarts its magnetic side, vqf takes its heading from the field as a running
mean of the first tauMag seconds of samples (its ``kMagInit``: gain 1/N, whatever its own disturbance detection
says), and the field's watch (``magnet.attitude.field_watch``) judges nothing before it has learnt its levels. A door,
a parked car or a desk's steel near the device in those seconds is then taken whole: on a simulated walk past doors
that starts by one (hand, tuning seed 8), the heading was 116 deg off after 2 s and still 22 deg off after 9 s, and
came back only at tauMag's pace.

What the record in force knows is the strength of the field it corrects to (``Calibration.field_strength``, else
the World Magnetic Model's at the place): a sample more than ``TOL_PCT`` % away from it in those seconds is not the
Earth's field, and is left out (a zero row, which vqf skips; flagged disturbed) once the field has shown that
strength (a field never near it is no door: vqf's take stays as it was). Where the first such sample came within
``EARLY_S`` of the start, the take starts again (once) after ``CALM_S`` back within the strength: the door's fringe,
within the tolerance but bent, leaves the mean too. When more than half of the samples judged so far are away (after
``MIN_JUDGED_S``), the strength is in question rather than the field (another place, another scale), and nothing
more is left out until the next start. A few numbers a device, stepped by one compiled call a batch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from magnet import _kernels
from magnet.model import Calibration
from magnet.units import ut_per_unit
from magnet.wire import DeviceCalibration

if TYPE_CHECKING:
    from magnet.attitude.fusion import Fusion

#: |B| further than this from the expected strength (%) is not the Earth's field while the first heading is taken
TOL_PCT = 15.0
#: the share of the judged samples away from the strength beyond which the strength, not the field, is in question
MAX_SHARE = 0.5
#: the samples judged before that share counts (s)
MIN_JUDGED_S = 3.0
#: the take starts again once the field has been back within the strength this long (s) after a sample away from it,
#: where the first away came within EARLY_S of the take's start: a take begun again lags a drifting gyroscope as a
#: new one does (its bias x half its window), which is worth paying only while most of the heading was the door's
CALM_S = 1.0
EARLY_S = 3.0


#: FirstHeading.state's items (magnet/_kernels.c's FT_*): samples of the take left and in all, judged, away, the calm
#: run's length, whether one was away early, whether the field has shown the strength, the calm run needed, the take's
#: early samples (EARLY_S), the period (s)
LEFT, SIZE, JUDGED, AWAY, CALM, SEEN_AWAY, SEEN_STRENGTH, CALM_NEEDED, EARLY, PERIOD, STATE_SIZE = range(11)
LOW2, HIGH2 = (1.0 - TOL_PCT / 100.0) ** 2, (1.0 + TOL_PCT / 100.0) ** 2


class FirstHeading:
    """The gate of one device's filter: ``start`` at each (re)start of its magnetic side, ``judge`` on the samples
    fed to it. Its numbers are ``state`` (STATE_SIZE,) float64, stepped by one compiled call a batch
    (``magnet._kernels.first_take``, the maths of this module's docstring)."""

    def __init__(self) -> None:
        self.state = np.zeros(STATE_SIZE)
        self.state[CALM_NEEDED] = self.state[EARLY] = 1.0

    def start(self, fusion: Fusion, again: bool = False) -> None:
        """A (re)start of the filter's magnetic side: the next tauMag seconds of samples are judged, where vqf takes
        its first heading from them (not where a record's heading came from the device's history: its ``kMagInit``
        is off then, ``magnet.attitude.causal_drift``); ``again``: the take begun again after a door (once only)."""
        period_s = fusion.period_s
        taking = float(fusion._filter.state["kMagInit"]) != 0.0
        size = max(1, round(fusion.figures().tau_mag_s / period_s)) if taking else 0
        self.state[:] = 0.0
        self.state[[LEFT, SIZE, PERIOD]] = size, size, period_s
        self.state[CALM_NEEDED] = max(1, round(CALM_S / period_s))
        self.state[EARLY] = 0 if again else round(EARLY_S / period_s)

    def judge(
        self, fields: np.ndarray, expected_ut: np.ndarray, lo: int, hi: int
    ) -> tuple[np.ndarray | None, int | None]:
        """(left out, restart) for samples lo .. hi of fields (S, 3) uT, C-contiguous (zero rows: no field) against
        expected_ut (S,) uT (NaN or 0 where unknown; one device's samples of one step, so one value: the first's is
        taken): those (n = hi - lo,) bool away from the strength, their rows zeroed in ``fields`` (in place), or None
        when none is (the usual case: the take is over); and the index (from lo) where the take starts again (the
        filter's magnetic side restarted there, the rest judged after ``start``), or None."""
        left = self.state[LEFT]
        if left <= 0 or hi <= lo:
            return None, None
        strength = float(expected_ut[lo])
        if not strength > 0.0:  # NaN or 0: no strength to judge by
            self.state[LEFT] = max(0.0, left - (hi - lo))
            return None, None
        out = np.empty(hi - lo, dtype=bool)
        square = strength * strength
        restart, left_out = _kernels.first_take(
            fields[lo:hi], LOW2 * square, HIGH2 * square, MIN_JUDGED_S, MAX_SHARE, self.state, out
        )
        return (out if left_out else None), (None if restart < 0 else restart)


def expected_columns(
    records: Sequence[DeviceCalibration | None], counts: Sequence[int] | np.ndarray, earth_ut: np.ndarray
) -> np.ndarray:
    """(S,) uT: the |B| a field corrected by each batch's record (B, one per batch, None: uncalibrated) shows
    undisturbed, S = sum(counts): the record's own strength where it states one in a unit that converts to uT, else
    the World Magnetic Model's earth_ut (S,) uT; NaN for uncalibrated samples (their field is no Earth's)."""
    strengths = [_strength_ut(r.calibration if r is not None else None) for r in records]
    per_sample = np.repeat(np.asarray(strengths, dtype=float), np.asarray(counts, dtype=np.int64))
    calibrated = np.repeat(np.asarray([r is not None for r in records]), np.asarray(counts, dtype=np.int64))
    return np.where(np.isfinite(per_sample), per_sample, np.where(calibrated, earth_ut, np.nan))


def _strength_ut(calibration: Calibration | None) -> float:
    """The record's stated strength in uT, NaN where none (or none in a unit that converts)."""
    if calibration is None or calibration.field_strength <= 0:
        return math.nan
    to_ut = ut_per_unit(calibration.output_unit)
    return math.nan if to_ut is None else float(calibration.field_strength) * to_ut

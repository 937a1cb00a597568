"""The record's offset error learnt in service against the gyroscope (``OffsetLearner``; docs/field-calibration.md,
"The record's offset error learnt against the gyroscope").

A record corrects the field as B = A (u - b). Its offset b is fitted from the samples the calibrator saw, and is off
by about 1 uT (on ``magnet bench field``'s walks: 0.5-3 uT). An error e (body axes) of the corrected field turns its
heading by g . R e (``drift_bias.offset_columns``): about e / H_horizontal (3 deg at 19 uT), and by a different
amount on each course, so a walk's legs each carry their own heading error. Where the gyroscope drifts little, that
is more than what the gyroscope alone would have done over the walk.

The gyroscope tells the two apart (Kok and Schon 2016). In vqf's 6D frame (gyroscope and accelerometer only) the
corrected field's angle about the vertical is

    psi(t) = c + D(t) . (b_gyro - b_0) + G(t) e + noise,

D(t) the integral of the up axis in body axes (the 6D frame's drift under a bias error, ``drift_bias``), G(t) the
offset columns. vqf's own bias estimate moves after the record (the bias loop of ``heading_bias``); what it moved
(the integral of up . (b_est(t) - b_0)) is known and added back to psi, so that one constant b_gyro - b_0 remains.
Over the minutes after a record with a few turns the drift (a slow ramp) and the offset error (a sinusoid in
heading) separate: ``drift_bias.fit_drift`` fits both, the offset error with a zero-mean prior of
``OFFSET_SIGMA_UT`` an axis, its Huber weights and the median |B| and dip screen (``field_angle_rad``) against
objects passed, and rows the compass flagged as disturbed never enter. Its estimate (the posterior mean: shrunk to
zero where the turns leave it unidentified, and never along an axis the walk does not turn) is then taken off the
field the filter gets, and vqf's ``delta`` moved by the change of the field's angle over its recent rows (as
``refresh_shift`` does for a refresh), so the bias loop does not read the change as a drift.

Per device, from each record on (``start``), not where aided; one row every ``ROW_S`` over the last ``WINDOW_S``.
Plain Python and numpy; vqf's frames (body FLU, earth ENU) throughout.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magnet.attitude.drift_bias import field_angle_rad, fit_drift, learnt_at_rest, offset_columns
from magnet.attitude.drift_bias import up_in_body as up_rows
from magnet.attitude.heading_bias import up_in_body
from magnet.frames import quaternion_to_matrix

#: the rows fitted: those of the last this many seconds (s), one every ``ROW_S`` at most
WINDOW_S = 120.0
ROW_S = 1.0
#: the first fit comes once the rows span this long (s), then one every ``REFIT_S``
MIN_SPAN_S = 30.0
REFIT_S = 10.0
#: the offset error's prior, one sigma per body axis (uT; ``causal_drift.OFFSET_SIGMA_UT``)
OFFSET_SIGMA_UT = 1.0
#: the bias's prior about b_0 (deg/s), and the field heading's correlation time (s), as ``causal_drift``'s fit
PRIOR_DPS = 0.3
CORRELATION_S = 4.0
#: vqf's delta is moved by the change's mean over the rows of this many tauMag before now
SHIFT_TAUS = 3.0
#: whether the compass learns it (``start``), and whether the rows begin with the seconds before the record
ENABLED = True
SEED = True
#: the filter's first seconds are not among them (its tilt settling: vqf's tauAcc is 3 s)
SEED_AFTER_S = 3.0


class OffsetLearner:
    """The module docstring's estimate for one vqf filter (``filter_``, a ``vqf.VQF``) and the record's ``correct``ion
    (raw field, gyroscope (N, 3) vqf's frame -> corrected field (N, 3)). ``offset_ut`` (3,): the error taken off the
    corrected field now (body FLU, uT)."""

    def __init__(self, filter_: Any, correct: Any) -> None:
        self.filter = filter_
        self.correct = correct
        self.offset_ut = np.zeros(3)
        self.bias0 = np.asarray(filter_.getBiasEstimate()[0], dtype=float).copy()
        #: rows: time (s), 6D attitude (4), raw field (3), gyroscope (3), the known drift (rad), usable (1/0)
        self.rows: list[list[float]] = []
        self.known_rad = 0.0
        self.last_fit_s = -math.inf
        self.shifted_rad = 0.0

    def note(self, t_s: float, raw_vqf: Any, gyr_vqf: Any, disturbed: bool) -> bool:
        """One fused batch's last sample at ``t_s`` (s since the filter's start); True when the offset changed (refit
        every ``REFIT_S``)."""
        quat = np.asarray(self.filter.getQuat6D(), dtype=float)
        if self.rows:
            last = self.rows[-1]
            if t_s < last[0]:  # the filter restarted: its attitude is another
                self.rows = []
            elif t_s - last[0] < ROW_S:
                last[-1] = 0.0 if disturbed else last[-1]  # a flagged batch spoils the row it joins
                return False
            else:
                bias = np.asarray(self.filter.getBiasEstimate()[0], dtype=float)
                self.known_rad += float(up_in_body(quat) @ (bias - self.bias0)) * (t_s - last[0])
        raw, gyr = np.asarray(raw_vqf, dtype=float).ravel(), np.asarray(gyr_vqf, dtype=float).ravel()
        self.rows.append([t_s, *quat.tolist(), *raw.tolist(), *gyr.tolist(), self.known_rad, 0.0 if disturbed else 1.0])
        while t_s - self.rows[0][0] > WINDOW_S:
            self.rows.pop(0)
        if t_s - self.rows[0][0] < MIN_SPAN_S or t_s - self.last_fit_s < REFIT_S:
            return False
        self.last_fit_s = t_s
        found = self.fit()
        if found is None:
            return False
        self.shifted_rad = self.move_to(found)
        return True

    def fit(self) -> np.ndarray | None:
        """The offset error (3,) uT from the rows (module docstring), or None (too few rows, vqf learnt its bias)."""
        if learnt_at_rest(float(self.filter.getBiasEstimate()[1])):
            return None
        rows = np.array(self.rows)
        quat = rows[:, 1:5]
        field = self.correct(np.ascontiguousarray(rows[:, 5:8]), np.ascontiguousarray(rows[:, 8:11]))
        angle = field_angle_rad(quat, field) + rows[:, 11]
        angle[rows[:, 12] < 0.5] = np.nan
        steps = np.diff(rows[:, 0], prepend=rows[0, 0] - ROW_S)
        columns = offset_columns(quat, field)
        found = fit_drift(
            angle,
            up_rows(quat),
            float(np.median(steps)),
            steps,
            MIN_SPAN_S,
            nuisance=columns,
            nuisance_sigma=OFFSET_SIGMA_UT,
            prior_dps=PRIOR_DPS,
            correlation_s=CORRELATION_S,
        )
        if found is None or found.nuisance is None:
            return None
        return np.asarray(found.nuisance, dtype=float)

    def move_to(self, offset_ut: np.ndarray) -> float:
        """Take ``offset_ut`` off the field from now on, vqf's delta moved by what that changes in the field's angle
        over the last ``SHIFT_TAUS`` tauMag of rows (weighted as vqf's loop weighs them); that move returned (rad)."""
        change = offset_ut - self.offset_ut
        self.offset_ut = offset_ut.copy()
        state = self.filter.state
        if state["kMagInit"] != 0.0 or not self.rows:
            return 0.0  # vqf has not taken its heading yet: it takes it from the field as it now is
        rows = np.array(self.rows)
        tau_s = max(float(self.filter.params["tauMag"]), 1e-3)
        rows = rows[rows[:, 0] >= rows[-1, 0] - SHIFT_TAUS * tau_s]
        field = self.correct(np.ascontiguousarray(rows[:, 5:8]), np.ascontiguousarray(rows[:, 8:11]))
        earth = np.einsum("nij,nj->ni", quaternion_to_matrix(rows[:, 1:5]), field)
        moved = earth - np.einsum("nij,j->ni", quaternion_to_matrix(rows[:, 1:5]), change)
        turn = np.arctan2(moved[:, 0], moved[:, 1]) - np.arctan2(earth[:, 0], earth[:, 1])
        turn = np.remainder(turn + np.pi, 2.0 * np.pi) - np.pi
        weights = np.exp(-(rows[-1, 0] - rows[:, 0]) / tau_s) * (rows[:, 12] > 0.5)
        if weights.sum() <= 0.0:
            return 0.0
        shift = float(weights @ turn / weights.sum())
        state["delta"] = math.remainder(float(state["delta"]) + shift, 2.0 * math.pi)
        self.filter.state = state
        return shift


def start(state: Any, correct: Any, history: list[list[float]] | None = None, bias_before: Any = None) -> None:
    """A record with its ``correct``ion was put in force on the device ``state``'s (a ``DeviceFilter``) unaided filter
    (``causal_drift.take_drift``, after the bias handed over): its learner from now on (``state.offset``), its rows
    begun with the seconds before (``history``: ``CausalDrift``'s rows, time, 6D attitude, raw field, gyroscope;
    ``bias_before`` vqf's bias estimate over them), fitted at once where they span enough."""
    fusion = state.filter
    ok = ENABLED and correct is not None and fusion is not None and not fusion.aided
    state.offset = found = OffsetLearner(fusion._filter, correct) if ok else None
    if found is None or not history or bias_before is None or not SEED:
        return
    before = np.asarray(bias_before, dtype=float) - found.bias0
    for row in history:
        if row[0] < SEED_AFTER_S or (found.rows and row[0] - found.rows[-1][0] < ROW_S):
            continue
        if found.rows:
            found.known_rad += float(up_in_body(np.asarray(row[1:5])) @ before) * (row[0] - found.rows[-1][0])
        found.rows.append([*row[:11], found.known_rad, 1.0])
    if found.rows and found.rows[-1][0] - found.rows[0][0] >= MIN_SPAN_S:
        found.last_fit_s = found.rows[-1][0]
        fitted = found.fit()
        if fitted is not None:
            delta_moved = found.move_to(fitted)
            found.shifted_rad = delta_moved


def learner(state: Any) -> OffsetLearner | None:
    """The device ``state``'s learner, dropped where its filter was replaced or is aided."""
    found, fusion = getattr(state, "offset", None), state.filter
    if found is not None and (fusion is None or fusion.aided or found.filter is not fusion._filter):
        state.offset = found = None
    return found


def take_off(state: Any, field_vqf: np.ndarray, lo: int, hi: int) -> None:
    """The learnt offset error taken off rows ``lo .. hi`` of ``field_vqf`` (S, 3) in place (rows with no field, all
    zeros, left as they are), before the device ``state``'s filter fuses them."""
    found = learner(state)
    if found is None or not found.offset_ut.any():
        return
    rows = field_vqf[lo:hi]
    present = np.any(rows != 0.0, axis=1).reshape(-1, 1)
    rows -= np.where(present, found.offset_ut, 0.0)


def refresh(state: Any, correct: Any) -> float:
    """An in-service refresh replaced the record (``correct``: its correction, or None): the rows fitted again with
    the new correction at once and that estimate taken off instead (none where they do not yet span enough), vqf's
    delta moved by what that changes (returned, rad; the record's own change is ``refresh_shift``'s); the learner
    dropped without a correction."""
    found = learner(state)
    if found is None:
        return 0.0
    if correct is None:
        state.offset = None
        return found.move_to(np.zeros(3))
    found.correct = correct
    fitted = found.fit() if found.rows and found.rows[-1][0] - found.rows[0][0] >= MIN_SPAN_S else None
    return found.move_to(np.zeros(3) if fitted is None else fitted)

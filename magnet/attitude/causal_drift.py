"""The gyroscope's bias about the vertical for the causal filter, found as each record is put in force
(``CausalDrift``; docs/field-calibration.md, "The gyroscope's bias about the vertical, in service"): the drift fit of
``magnet.attitude.drift_bias`` on the last seconds before the record, their raw field corrected with it.

numpy; vqf's frames (body FLU, earth ENU) throughout.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.attitude.drift_bias import DriftBias, field_angle_rad, fit_drift, learnt_at_rest, up_in_body
from magnet.frames import quaternion_to_matrix

#: a record's correction: raw field (N, 3) and gyroscope (N, 3) -> field (N, 3), vqf's frames
Correct = Callable[[np.ndarray, np.ndarray], np.ndarray]


#: the history kept before a record (s): one row per fused batch (vqf's 6D attitude, the raw field, the gyroscope)
HISTORY_S = 30.0
#: it is fitted from this many seconds of it, the filter's first seconds left out (its tilt settling: vqf's tauAcc is
#: 3 s)
HISTORY_MIN_S = 8.0
HISTORY_AFTER_S = 3.0
#: a bias is taken only when its one-sigma uncertainty is below this (deg/s)
HISTORY_MAX_SIGMA_DPS = 0.25
#: nor when it is larger than this (deg/s): no phone's gyroscope is that far off once vqf started
MAX_DPS = 2.0
#: the fit's prior on the bias (one sigma, deg/s, zero mean): a phone's gyroscope left with up to 0.5 deg/s per axis
#: after its factory calibration (uniform: 0.29 one sigma); vqf's own 0.5 (``drift_bias.PRIOR_DPS``) let a short
#: history's noise through whole
PRIOR_DPS = 0.3
#: the record's offset error (one sigma per body axis, uT) fitted with the bias: it turns the field's heading by up
#: to offset / horizontal field (1 uT: 3 deg at 19 uT), and by a different amount on each leg of a walk, so that a
#: corner in a short history looks like a drift
OFFSET_SIGMA_UT = 1.0
#: the field's heading errors in a walk are correlated over this long (s): a corner's tilt fades with vqf's tauAcc
#: (3 s) and the gait's stride comes back within a second or so; ``drift_bias.CORRELATION_S`` (2 s) took a short
#: history for surer than it was
CORRELATION_S = 4.0


class CausalDrift:
    """The gyroscope's bias about the vertical for the compass's causal filter, found as a record is put in force.

    vqf's heading lags a bias about the vertical it has not learnt by bias x tauMag (a phone's 0.5 deg/s: 4.5 deg),
    which every walk's absolute heading carries. Once a record is known, the field it corrects is constant in the
    Earth frame, so its angle in vqf's 6D frame drifts at that bias (``magnet.attitude.drift_bias``). The compass
    keeps, per batch fused, vqf's 6D attitude and the raw field of its last sample (``note``, the last
    ``HISTORY_S``); when a record comes the raw field is corrected with it, the drift fitted (``fit_drift``) and the
    bias along the mean up axis handed to vqf (``from_history``) as its magnetic side restarts: the heading is taken
    afresh there anyway, so the change costs no step in it (a bias learnt later moves vqf's standing lag, a step of
    the heading). Not where vqf learnt the bias itself (``drift_bias.learnt_at_rest``: it rested), nor
    where the velocity aids the filter. Memory: the history's rows, one a batch. ``filter_``: the ``vqf.VQF``."""

    def __init__(self, filter_: Any) -> None:
        self.filter = filter_
        self.found: DriftBias | None = None
        #: one row per fused batch: time (s), vqf's 6D attitude (4), raw field (3) and gyroscope (3), vqf's frames
        self.history: list[list[float]] = []

    def note(self, t_s: float, raw_vqf: Any, gyr_vqf: Any, quat6d_vqf: np.ndarray | None = None) -> None:
        """One row of the history (the last sample of a fused batch, at ``t_s`` since the filter's start; the 6D
        attitude vqf's now unless given); rows older than ``HISTORY_S`` dropped, all of them when the time went back
        (the filter restarted: its attitude was lost)."""
        if self.history and t_s < float(self.history[-1][0]):
            self.history = []
        quat = self.filter.getQuat6D() if quat6d_vqf is None else quat6d_vqf
        self.history.append([t_s, *_floats(quat), *_floats(raw_vqf), *_floats(gyr_vqf)])  # a list: once a batch
        while t_s - float(self.history[0][0]) > HISTORY_S:
            self.history.pop(0)

    def from_history(self, correct: Correct) -> bool:
        """A new record's ``correct``ion put on the history's raw field, the drift fitted there and its bias added to
        vqf's estimate. True when a bias was taken. The fit (``fit_drift``) has the bias's prior (``PRIOR_DPS``) and
        the record's offset error (``OFFSET_SIGMA_UT``, ``offset_columns``) in it, so that its estimate is shrunk
        towards zero by as much as the history leaves it uncertain, and a corner's step of the field's angle that a
        wrong offset makes is not read as a drift; taken where its uncertainty is below ``HISTORY_MAX_SIGMA_DPS``."""
        rows = np.array(self.history).reshape(-1, 11)
        rows = rows[rows[:, 0] >= HISTORY_AFTER_S]
        if len(rows) < 3:
            return False
        field = correct(np.ascontiguousarray(rows[:, 5:8]), np.ascontiguousarray(rows[:, 8:11]))
        steps = np.diff(rows[:, 0], prepend=rows[0, 0])
        quat = rows[:, 1:5]
        found = fit_drift(
            field_angle_rad(quat, field),
            up_in_body(quat),
            float(np.median(steps[1:])),
            steps,
            HISTORY_MIN_S,
            nuisance=offset_columns(quat, field),
            nuisance_sigma=OFFSET_SIGMA_UT,
            prior_dps=PRIOR_DPS,
            correlation_s=CORRELATION_S,
        )
        bias, sigma = self.filter.getBiasEstimate()
        if (
            found is None
            or learnt_at_rest(float(sigma))
            or found.sigma_rads > math.radians(HISTORY_MAX_SIGMA_DPS)
            or abs(found.along_up_rads) > math.radians(MAX_DPS)
        ):
            return False
        self.found = found
        self.filter.setBiasEstimate(np.asarray(bias, dtype=float) + found.bias_rads)
        self.history = []  # integrated with the bias before: another drift
        return True


def offset_columns(quat_vqf: np.ndarray, field_vqf: np.ndarray) -> np.ndarray:
    """(N, 3) rad per uT: how an offset error (body FLU, uT) of the corrected field turns its angle about the up axis
    in the frame of vqf quaternions (N, 4) wxyz body -> ENU, at the field (N, 3) body FLU: d(angle) = g . R d(offset),
    g = (-e_y, e_x, 0) / (e_x^2 + e_y^2), e = R field the field in that frame (zero where it has no horizontal
    part)."""
    rotation = quaternion_to_matrix(np.asarray(quat_vqf, dtype=float).reshape(-1, 4))
    earth = np.einsum("nij,nj->ni", rotation, np.asarray(field_vqf, dtype=float).reshape(-1, 3))
    horizontal = earth[:, 0] ** 2 + earth[:, 1] ** 2
    scale = np.where(horizontal > 0.0, 1.0 / np.maximum(horizontal, 1e-300), 0.0)
    towards = np.column_stack([-earth[:, 1], earth[:, 0], np.zeros(len(earth))]) * scale[:, None]
    return np.einsum("ni,nij->nj", towards, rotation)


def _floats(values: Any) -> list[float]:
    """``values`` (any shape) as a flat list of Python floats."""
    return np.asarray(values, dtype=float).ravel().tolist()


def note_batch(state: Any, drain: Any, row: int) -> None:
    """The compass's device ``state`` (a ``magnet.compass.filters.DeviceFilter``) fed its drain's rows up to ``row``
    (permuted): that row's raw field (``drain.raw_source``: uT sensor axes and the permutation; None: nothing) and
    gyroscope noted in the device's ``CausalDrift`` (made on first use, kept as ``state.drift``); not where aided."""
    fusion = state.filter
    if drain.raw_source is None or fusion is None or fusion.aided:
        return
    drift = getattr(state, "drift", None)
    if drift is None or drift.filter is not fusion._filter:
        drift = state.drift = CausalDrift(fusion._filter)
    raw_ut, order = drain.raw_source
    index = row if order is None else int(order[row])
    x, y, z = raw_ut[index].tolist()
    drift.note(fusion.samples * fusion.period_s, (x, -y, -z), drain.inputs[0][row])  # FRD -> FLU (``frd_flu``)


def take_drift(state: Any, correct: Correct | None) -> None:
    """A record with its ``correct``ion was put in force on the device ``state``'s filter (after its
    ``restart_magnetometer``): ``CausalDrift.from_history`` (not where aided, nor without a correction)."""
    drift = getattr(state, "drift", None)
    if correct is not None and drift is not None and state.filter is not None and not state.filter.aided:
        drift.from_history(correct)

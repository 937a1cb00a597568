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

from magnet.attitude import bias_walk, offset_learn
from magnet.attitude.drift_bias import (
    DriftBias,
    field_angle_rad,
    fit_drift,
    learnt_at_rest,
    offset_columns,
    up_in_body,
)
from magnet.attitude.heading_bias import HeadingBias, step_batch
from magnet.attitude.mag_gain import note_gain, start_gain
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
#: a new record's heading is taken from this many seconds of the history (``heading_from_history``), from at least
#: this many rows, those within these of the history's median |B| (fraction) and dip (deg)
HEADING_S = 6.0
HEADING_MIN_ROWS = 6
NORM_TOL = 0.08
DIP_TOL_DEG = 10.0
#: where set (``HEADING_FROM_HISTORY``)
HEADING_FROM_HISTORY = True
#: after it, vqf's first-heading average (its gain 1/N) goes on as if this many seconds of samples had been fed, as
#: a tauMag of this plus the time since, up to vqf's own: its rejections and the gates meanwhile on (``kMagInit`` 0)
HEADING_WORTH_S = 3.0
#: the fit's prior on the bias (one sigma, deg/s, zero mean): a phone's gyroscope left with up to 0.5 deg/s per axis
#: after its factory calibration (uniform: 0.29 one sigma); vqf's own 0.5 (``drift_bias.PRIOR_DPS``) let a short
#: history's noise through whole
PRIOR_DPS = 0.3
#: the record's offset error (one sigma per body axis, uT) fitted with the bias: it turns the field's heading by up
#: to offset / horizontal field (1 uT: 3 deg at 19 uT), and by a different amount on each leg of a walk, so that a
#: corner in a short history looks like a drift
OFFSET_SIGMA_UT = 1.0
#: from a record on, the bias about the vertical is also learnt from vqf's magnetic corrections (``HeadingBias``, the
#: loop's integral term): what the history's fit left of it (0.1-0.3 deg/s on walks) lags vqf's heading by bias x
#: tauMag, a standing error the constant offset hides and a user sees (docs/field-calibration.md, "The walks' absolute
#: heading")
HEADING_LOOP = True
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
        #: after a heading from the history: (time it was taken, vqf's own tauMag), tauMag growing back to it
        self.ramp: tuple[float, float] | None = None

    def note(self, t_s: float, raw_vqf: Any, gyr_vqf: Any, quat6d_vqf: np.ndarray | None = None) -> None:
        """One row of the history (the last sample of a fused batch, at ``t_s`` since the filter's start; the 6D
        attitude vqf's now unless given); rows older than ``HISTORY_S`` dropped, all of them when the time went back
        (the filter restarted: its attitude was lost)."""
        if self.history and t_s < float(self.history[-1][0]):
            self.history = []
        if self.ramp is not None:
            start, base = self.ramp
            tau = HEADING_WORTH_S + t_s - start
            if t_s < start or tau >= base:
                tau, self.ramp = base, None
            self.filter.setTauMag(tau)
        quat = self.filter.getQuat6D() if quat6d_vqf is None else quat6d_vqf
        self.history.append([t_s, *_floats(quat), *_floats(raw_vqf), *_floats(gyr_vqf)])  # a list: once a batch
        while t_s - float(self.history[0][0]) > HISTORY_S:
            self.history.pop(0)

    def _corrected(self, correct: Correct) -> tuple[np.ndarray, np.ndarray]:
        """The history's rows (M, 11) from ``HISTORY_AFTER_S`` on (the filter's first seconds left out) and their raw
        field corrected with a record's ``correct``ion (M, 3), vqf's frames."""
        rows = np.array(self.history).reshape(-1, 11)
        rows = rows[rows[:, 0] >= HISTORY_AFTER_S]
        if not len(rows):
            return rows, np.zeros((0, 3))
        return rows, correct(np.ascontiguousarray(rows[:, 5:8]), np.ascontiguousarray(rows[:, 8:11]))

    def heading_from_history(self, correct: Correct) -> bool:
        """A new record's ``correct``ion put on the history's raw field, vqf's magnetic heading offset (``delta``) and
        its field reference (|B| and dip) set from the last ``HEADING_S`` of it, its rows that agree with the whole
        history's median |B| and dip (``NORM_TOL``, ``DIP_TOL_DEG``): the heading taken from seconds of field before the
        record rather than from the samples after it, which an object passed then would bend. True when set: vqf's
        first-heading gain is then off (``kMagInit`` 0: it overrides vqf's rejection, and the heading gate stands aside
        for it), and its average goes on as a tauMag of ``HEADING_WORTH_S`` plus the time since (``note``)."""
        rows, field = self._corrected(correct)
        if len(rows) < HEADING_MIN_ROWS:
            return False
        earth = np.einsum("nij,nj->ni", quaternion_to_matrix(rows[:, 1:5]), field)
        norm = np.linalg.norm(earth, axis=1)
        if not np.all(norm > 0.0):
            return False
        dip = np.arcsin(np.clip(-earth[:, 2] / norm, -1.0, 1.0))  # vqf's: positive where the field points down
        norm_ref, dip_ref = float(np.median(norm)), float(np.median(dip))
        agree = (np.abs(norm / norm_ref - 1.0) <= NORM_TOL) & (np.abs(dip - dip_ref) <= math.radians(DIP_TOL_DEG))
        agree &= rows[:, 0] >= rows[-1, 0] - HEADING_S
        if int(agree.sum()) < HEADING_MIN_ROWS:
            return False
        angle = np.arctan2(earth[agree, 0], earth[agree, 1])  # vqf's delta: the field's angle from north, clockwise
        centre = math.atan2(float(np.sin(angle).mean()), float(np.cos(angle).mean()))
        offset = float(np.median(np.remainder(angle - centre + np.pi, 2.0 * np.pi) - np.pi))
        state = self.filter.state
        state["delta"] = math.remainder(centre + offset, 2.0 * math.pi)
        state["kMagInit"] = 0.0
        for key, value in (("magRefNorm", norm_ref), ("magCandidateNorm", norm_ref)):
            state[key] = value
        for key, value in (("magRefDip", dip_ref), ("magCandidateDip", dip_ref)):
            state[key] = value
        state["magDistDetected"] = False
        state["magRejectT"] = 0.0
        self.filter.state = state
        if HEADING_WORTH_S > 0.0:
            self.ramp = (float(rows[-1, 0]), float(self.filter.params["tauMag"]))
            self.filter.setTauMag(min(HEADING_WORTH_S, self.ramp[1]))
        return True

    def from_history(self, correct: Correct) -> bool:
        """A new record's ``correct``ion put on the history's raw field, the drift fitted there and its bias added to
        vqf's estimate. True when a bias was taken. The fit (``fit_drift``) has the bias's prior (``PRIOR_DPS``) and
        the record's offset error (``OFFSET_SIGMA_UT``, ``offset_columns``) in it, so that its estimate is shrunk
        towards zero by as much as the history leaves it uncertain, and a corner's step of the field's angle that a
        wrong offset makes is not read as a drift; taken where its uncertainty is below ``HISTORY_MAX_SIGMA_DPS``."""
        rows, field = self._corrected(correct)
        if len(rows) < 3:
            return False
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


def _floats(values: Any) -> list[float]:
    """``values`` (any shape) as a flat list of Python floats."""
    return np.asarray(values, dtype=float).ravel().tolist()


def note_batch(state: Any, drain: Any, row: int, disturbed: bool = False) -> None:
    """The compass's device ``state`` (a ``magnet.compass.filters.DeviceFilter``) fed its drain's rows up to ``row``
    (permuted; ``disturbed``: whether any of those just fused was flagged): that row's raw field
    (``drain.raw_source``: uT sensor axes and the permutation; None: nothing) and gyroscope noted in the device's
    ``CausalDrift`` (made on first use, kept as ``state.drift``), and its bias loop stepped (``note_loop``); not
    where aided."""
    fusion = state.filter
    if fusion is not None and not fusion.aided:
        note_loop(state, disturbed)
    if drain.raw_source is None or fusion is None or fusion.aided:
        return
    drift = getattr(state, "drift", None)
    if drift is None or drift.filter is not fusion._filter:
        drift = state.drift = CausalDrift(fusion._filter)
    raw_ut, order = drain.raw_source
    index = row if order is None else int(order[row])
    x, y, z = raw_ut[index].tolist()
    t_s, gyr = fusion.samples * fusion.period_s, drain.inputs[0][row]
    drift.note(t_s, (x, -y, -z), gyr)  # FRD -> FLU (``frd_flu``)
    learner = offset_learn.learner(state)  # the record's offset error against the gyroscope (``offset_learn``)
    if learner is not None and learner.note(t_s, (x, -y, -z), gyr, disturbed):
        delta_moved(state, learner.shifted_rad)
    note_gain(state)  # the magnetic gain from the drift, once a record is in force (``magnet.attitude.mag_gain``)


def take_drift(state: Any, correct: Correct | None) -> None:
    """A record with its ``correct``ion was put in force on the device ``state``'s filter (after its
    ``restart_magnetometer``): its magnetic gain started again (``magnet.attitude.mag_gain.start_gain``), then
    ``CausalDrift.heading_from_history`` and ``from_history`` (not where aided, nor without a correction), and from
    now on the bias loop (``HEADING_LOOP``: ``magnet.attitude.heading_bias``, where the filter has none yet), its gains
    and tauMag from the bias's uncertainty (``bias_walk``, where on: the magnetic gain then stopped)."""
    start_gain(state)
    state.offset = None  # the learnt offset error was the old record's
    fusion = state.filter
    if correct is None or fusion is None or fusion.aided:
        return
    drift = getattr(state, "drift", None)
    history, bias = None, None
    if drift is not None and drift.filter is fusion._filter:
        history, bias = list(drift.history), np.array(fusion._filter.getBiasEstimate()[0], dtype=float)
    if drift is not None:
        if HEADING_FROM_HISTORY:
            drift.heading_from_history(correct)
        drift.from_history(correct)
    if HEADING_LOOP and fusion.heading_bias is None:
        heading = HeadingBias(fusion.period_s, fusion._taus[1])
        if bias_walk.ENABLED:  # its gains and tauMag from the bias's uncertainty, not the gain from delta's drift
            heading.walk, state.gain = bias_walk.BiasWalk(), None
        state.loop = (fusion._filter, fusion.samples, heading)
    offset_learn.start(state, correct, history, bias)
    if state.offset is not None and state.offset.shifted_rad:
        delta_moved(state, state.offset.shifted_rad)


def note_loop(state: Any, disturbed: bool) -> None:
    """The device ``state``'s bias loop (``state.loop``: the vqf filter it runs on, that filter's sample count at its
    last step, the ``HeadingBias``; started by ``take_drift``) stepped over the samples fused since
    (``heading_bias.step_batch``), once a fused batch: the compass's compiled path stays whole. Dropped where the
    filter was replaced; started again where it restarted (its sample count went back)."""
    loop = getattr(state, "loop", None)
    fusion = state.filter
    if loop is None or fusion is None:
        return
    filter_, seen, heading = loop
    if filter_ is not fusion._filter:
        state.loop = None
        return
    if fusion.samples < seen:
        heading.reset()
        seen = 0
    step_batch(heading, filter_, fusion.samples - seen, disturbed)
    state.loop = (filter_, fusion.samples, heading)


def delta_moved(state: Any, change_rad: float) -> None:
    """vqf's ``delta`` on the device ``state`` was moved by ``change_rad`` at once (``refresh_shift``: a refresh's
    new correction): the bias loop's last delta moved with it, so that the step is not read as a drift."""
    loop = getattr(state, "loop", None)
    if loop is not None and loop[2].delta is not None:
        loop[2].delta = math.remainder(loop[2].delta + change_rad, 2.0 * math.pi)

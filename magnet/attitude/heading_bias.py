"""The gyroscope's bias about the vertical, learnt from the magnetometer's heading corrections (``HeadingBias``), for
the causal filter without velocity aiding (``magnet.attitude.fusion.Fusion``).

vqf learns its gyroscope's bias at rest and, in motion, from the accelerometer, which sees the two horizontal axes
only: about the vertical a walking phone's bias is never learnt (a phone carried the same way keeps the same body
axis up). Its 6D attitude then drifts in heading at the bias's rate, and its magnetic correction ``delta`` (the turn
from 6D to 9D) follows that drift through a proportional loop of time constant tauMag, lagging by rate x tauMag: a
phone's 0.5 deg/s bias leaves a standing heading error of 4.5 deg, the constant offset of the walks in
``magnet bench field`` (with the simulator's true calibration and true gyroscope, 1.1 deg; with its gyroscope bias,
up to 4.4). This adds the loop's integral term (as ``aided_fusion.VerticalBias`` does for the aided filter): every
change of delta over a piece of samples, divided by T_i = ``INTEGRAL_TAUS`` tauMag, goes into vqf's own bias
estimate along the body's up axis, where the drift comes from. With T_i = 4 tauMag the loop is critically damped
(damping sqrt(T_i / tauMag) / 2 = 1): slower than the aided filter's 2 tauMag, and less moved by the heading's
short errors.

Those short errors come from the tilt. A walker's corner (90 deg at 70-120 deg/s, 1.4-2.4 s) puts a centripetal
acceleration of v x rate (about 2 m/s^2 walking, 4 running) on the accelerometer, which tilts vqf's attitude by a
degree or more for a few seconds, and a tilt error turns the field's heading by tilt x tan(dip). So the loop does not
learn while the body turns about the vertical faster than ``TURN_RATE_DPS`` (vqf's 6D attitude's turn about the
vertical over the last two pieces, 1 s: a stride or so, over which the gait's own sway cancels), nor for
``AFTER_TURN_S`` after, nor while the field is disturbed (vqf's flag or the field's watch), nor before
``SETTLE_TAUS`` tauMag since the filter's magnetic side (re)started (vqf's first convergence, or a new calibration,
is not a drift).

Nor does it learn where vqf has learnt the bias itself: a device that rested (vqf's rest detection learns all three
axes to a few 0.01 deg/s) keeps vqf's estimate, which the loop could only make noisier (BROAD's trials start still:
with the loop on them causal heading went 1.082 -> 1.132 and 0.819 -> 0.842 deg). The loop runs while vqf's own
uncertainty of its bias exceeds ``MIN_SIGMA_DPS`` (it starts at 0.5 deg/s and, in motion, stays there:
the accelerometer cannot see that axis). vqf's own bound on its bias's uncertainty is the largest over its axes, the
vertical's in motion; it costs nothing to ask.

Pieces are cut at fixed sample counts from the filter's start (``PIECE_S``), so the answers do not depend on how the
samples come in batches.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magnet.attitude.bias_walk import BiasWalk

#: the loop's integral time in units of vqf's magnetic time constant tauMag (critical damping at 4)
INTEGRAL_TAUS = 4.0
#: the loop starts this many tauMag after the filter's magnetic side (re)started
SETTLE_TAUS = 1.0
#: the length of a piece of samples between two steps of the loop (s)
PIECE_S = 0.5
#: pieces whose rate about the vertical, over the last two, exceeds this (deg/s) are a turn: not learnt from
TURN_RATE_DPS = 20.0
#: nor the pieces this long after a turn (s): the tilt it caused takes vqf's accelerometer time constant to fade
AFTER_TURN_S = 4.0
#: the loop runs only while vqf's uncertainty (one sigma) of its bias about the vertical exceeds this (deg/s)
MIN_SIGMA_DPS = 0.2


def up_in_body(quat_vqf: Any) -> np.ndarray:
    """The earth's up axis (3,) in body axes from a vqf quaternion (4,) wxyz body -> ENU (vqf's frames)."""
    w, x, y, z = (float(v) for v in np.asarray(quat_vqf, dtype=float).reshape(4))
    return np.array([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)])


def vqf_flags_count(recalibrated: bool, filter_: Any) -> bool:
    """Whether a vqf filter's disturbance flags stop the loop. vqf flags every field until it has accepted a
    reference, which after a restart of its magnetic side takes 5 s of turns faster than 20 deg/s (a phone held to the
    ear or for texting waits tens of seconds, corrected at half vqf's gain meanwhile). After a new calibration was
    put in force (``recalibrated``: ``Fusion.restart_magnetometer``) those flags do not stop the loop while vqf has
    no reference: the record was judged against the Earth's field, and the watch looks for what passes by. Before
    any (the raw field, or a log fused with its record from the start) they do."""
    return not (recalibrated and float(filter_.getMagRefNorm()) == 0.0)


def vertical_turn_rad(previous_vqf: np.ndarray, now_vqf: np.ndarray) -> float:
    """The turn (rad) about the earth's vertical from one vqf quaternion (4,) wxyz body -> ENU to another: the twist
    about z of now * conj(previous), which is defined at any attitude (an upright phone too)."""
    pw, px, py, pz = (float(v) for v in previous_vqf)
    nw, nx, ny, nz = (float(v) for v in now_vqf)
    w = nw * pw + nx * px + ny * py + nz * pz
    z = -nw * pz - nx * py + ny * px + nz * pw
    return math.remainder(2.0 * math.atan2(z, w), math.tau)


class HeadingBias:
    """The loop of the module docstring for one filter. ``period_s``: the sample period (s); ``tau_mag_s``: vqf's
    tauMag (s). ``piece_samples`` samples make one piece; ``observe`` counts each batch's samples in it and ``step``
    is called at the end of each piece."""

    def __init__(self, period_s: float, tau_mag_s: float) -> None:
        self.period_s = float(period_s)
        self.piece_samples = max(1, round(PIECE_S / self.period_s))
        self.integral_s = INTEGRAL_TAUS * float(tau_mag_s)
        self.settle_s = SETTLE_TAUS * float(tau_mag_s)
        #: where set (the compass, ``causal_drift.take_drift``): the gains and tauMag from the bias's uncertainty
        self.walk: BiasWalk | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the loop's state (its delta, the settling time and the turn), not the bias it gave vqf."""
        self.delta: float | None = None
        self.quat: np.ndarray | None = None  # vqf's 6D attitude at the last step
        self.fed_s = 0.0
        self.since_turn_s = math.inf
        self.turns: list[float] = []  # the turns (rad) about the vertical over the last two pieces
        self.count = 0
        self.disturbed = False
        self.learnt = False  # whether the last step learnt
        if self.walk is not None:
            self.walk = BiasWalk()

    def remaining(self) -> int:
        """Samples still to come in the current piece."""
        return self.piece_samples - self.count

    def observe(self, count: int, disturbed: bool) -> None:
        """``count`` more samples of the current piece fed, and whether any of them had its field disturbed."""
        self.count += count
        self.disturbed = self.disturbed or disturbed

    def step(self, delta: float, quat6d_vqf: np.ndarray, sigma_rads: float) -> np.ndarray:
        """At the end of a piece: vqf's delta (rad) and 6D attitude (4,) (body -> ENU) now, and vqf's bound on the
        uncertainty of its gyroscope bias (rad/s, one sigma: ``getBiasEstimate``'s, the largest over its axes, which
        in motion is the vertical's: the accelerometer cannot see it). Returns the change (3,) rad/s to vqf's bias
        estimate (zeros while the loop does not learn)."""
        seconds = self.count * self.period_s
        quat = np.asarray(quat6d_vqf, dtype=float).reshape(4)
        turn = 0.0 if self.quat is None else vertical_turn_rad(self.quat, quat)
        self.turns = [*self.turns[-1:], turn]
        rate = abs(sum(self.turns)) / max(len(self.turns) * seconds, 1e-9)
        self.since_turn_s = 0.0 if rate > math.radians(TURN_RATE_DPS) else self.since_turn_s + seconds
        self.fed_s += seconds
        up = up_in_body(quat)
        learn = (
            self.delta is not None
            and not self.disturbed
            and self.fed_s >= self.settle_s
            and self.since_turn_s >= AFTER_TURN_S
            and sigma_rads > math.radians(MIN_SIGMA_DPS)
        )
        step = math.remainder(delta - self.delta, math.tau) if learn and self.delta is not None else 0.0
        self.learnt = bool(learn)
        self.delta, self.quat = delta, quat
        self.count, self.disturbed = 0, False
        return -step / self.integral_s * up


def run_pieces(
    filter_: Any,
    loop: HeadingBias,
    inputs: tuple[np.ndarray, np.ndarray, np.ndarray],
    watched: np.ndarray,
    recalibrated: bool,
) -> dict[str, Any]:
    """vqf's ``updateBatch`` on one batch of (gyroscope, accelerometer, field) (N, 3) each, vqf frames, cut where the
    loop's pieces end, the loop stepped there (its change added to vqf's bias estimate). ``watched`` (N,): the samples
    the field's watch left out; ``recalibrated``: as ``vqf_flags_count``. Returns vqf's outputs (quat6D, quat9D,
    restDetected, magDistDetected) for the whole batch."""
    gyr, acc, field = inputs

    def disturbed(out: dict[str, Any], lo: int, hi: int) -> bool:
        flagged = bool(out["magDistDetected"].any()) and vqf_flags_count(recalibrated, filter_)
        return flagged or bool(watched[lo:hi].any())

    if loop.remaining() > len(gyr):  # the whole batch within one piece (the usual case: no copies)
        out = filter_.updateBatch(gyr, acc, field)
        loop.observe(len(gyr), disturbed(out, 0, len(gyr)))
        return out
    parts = []
    start = 0
    while start < len(gyr):
        stop = min(start + loop.remaining(), len(gyr))
        out = filter_.updateBatch(gyr[start:stop], acc[start:stop], field[start:stop])
        loop.observe(stop - start, disturbed(out, start, stop))
        if loop.remaining() == 0:
            sigma = float(filter_.getBiasEstimate()[1])
            change = loop.step(float(filter_.getDelta()), filter_.getQuat6D(), sigma)
            if change.any():
                filter_.setBiasEstimate(np.asarray(filter_.getBiasEstimate()[0], dtype=float) + change)
        parts.append(out)
        start = stop
    if len(parts) == 1:
        return dict(parts[0])
    keys = ("quat6D", "quat9D", "restDetected", "magDistDetected")
    return {key: np.concatenate([np.asarray(part[key]) for part in parts]) for key in keys}


def step_batch(loop: HeadingBias, filter_: Any, count: int, disturbed: bool) -> None:
    """The loop stepped once over ``count`` samples just fed to the ``vqf.VQF`` ``filter_`` (a piece as long as the
    batch: the compass's, after a record; ``disturbed``: any of them flagged by vqf or the watch), its change added
    to vqf's bias estimate. vqf's flags are not counted while it has no field reference (``vqf_flags_count``). With
    the loop's ``walk`` (``bias_walk``) the change and vqf's tauMag come from the bias's uncertainty instead of the
    fixed integral time."""
    if count <= 0:
        return
    loop.observe(count, disturbed and vqf_flags_count(True, filter_))
    sigma = float(filter_.getBiasEstimate()[1])
    walk, seconds, previous = loop.walk, loop.count * loop.period_s, loop.delta
    delta, quat = float(filter_.getDelta()), filter_.getQuat6D()
    change = loop.step(delta, quat, sigma)
    if walk is not None:
        walk.predict(seconds)
        change = np.zeros(3)
        if loop.learnt and previous is not None:
            moved = math.remainder(delta - previous, math.tau)
            along_up, tau = walk.learn(seconds, moved, float(filter_.params["tauMag"]))
            change = along_up * up_in_body(quat)
            filter_.setTauMag(tau)
    if change.any():
        filter_.setBiasEstimate(np.asarray(filter_.getBiasEstimate()[0], dtype=float) + change)

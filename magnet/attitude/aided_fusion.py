"""The gyroscope-aided filter fed with velocity: vqf run a little behind the newest sample (design: docs/design.md,
"Heading in motion", velocity aiding; the acceleration itself: ``magnet.attitude.aiding``).

The linear acceleration at time t is known only once a velocity fix after t + h has arrived (a few tenths of a
second later). So the filter (vqf, in its own frames: z-up body, ENU with magnetic north) is fed a sample only when
its acceleration is known, or when it is ``max_lag_s`` old (a receiver that went quiet: fed as it is). Each sample
is fed as acc - R^T a_enu, R the latest attitude this filter gave that sample (carried forward, below). The attitude
of a sample not yet fed is the filter's latest attitude carried forward by the gyroscope (less the filter's bias
estimate) over the samples in between: q_i = q_filter * prod_j exp((w_j - b) dt / 2), a fraction of a second of
integration, so the newest sample is answered at once (causal, no delay on the output).

After each piece fed (docs/aiding.md): vqf's rest detection is off while the fixes say the vehicle moves, and
travel counts towards a new reference field (``travelled``); where the velocity explains the accelerometer (a
vehicle: ``magnet.attitude.gyro_bias.Explained``) vqf's accelerometer time constant is the aided vehicle's
(``magnet.attitude.aiding.vehicle_tau_acc_s``) and a Kalman filter of the heading's drift
(``magnet.attitude.gyro_bias.HeadingDrift``) gives vqf its gyroscope bias and heading correction; elsewhere
``VerticalBias`` adds an integral term to vqf's heading correction (docs/gyro-calibration.md).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import vqf

from magnet.attitude.aiding import VEHICLE_RESIDUAL_MS2, VelocityFixes, vehicle_tau_acc_s
from magnet.attitude.gyro_bias import Explained, HeadingDrift, PieceField
from magnet.compiled import kernels as _kernels
from magnet.units import STANDARD_GRAVITY_MS2

#: the longest piece of samples answered from one filter state when no fix comes (s)
CHUNK_S = 0.1
#: the longest a sample waits for its acceleration before it is fed as it is (s)
MAX_LAG_S = 1.0
#: the vertical bias loop's integral time, in units of vqf's magnetic time constant tauMag (``VerticalBias``)
BIAS_INTEGRAL_TAUS = 2.0
#: the loop starts once this many tauMag of samples were fed (vqf's first magnetic convergence is not a drift)
BIAS_SETTLE_TAUS = 1.0


def _in_body(quat_vqf: np.ndarray, a_ned: np.ndarray) -> np.ndarray:
    """Accelerations (N, 3) magnetic NED in vqf's body frame (N, 3), by vqf quaternions (N, 4) body -> ENU."""
    out = np.empty((len(quat_vqf), 3))
    _kernels.into_body(quat_vqf, a_ned, out)
    return out


def body_acceleration(quat_vqf: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray) -> np.ndarray:
    """The linear acceleration (N, 3) of a whole log in vqf's body frame: the velocity's (magnetic NED, held rows,
    NaN where unknown) with every fix known, turned by the attitudes ``quat_vqf`` (N, 4)."""
    fixes = VelocityFixes(max_fixes=max(len(t_s), 2))
    fixes.observe(np.asarray(t_s, dtype=float), vel_ned_ms)
    return _in_body(np.asarray(quat_vqf, dtype=float), fixes.acceleration(np.asarray(t_s, dtype=float)))


def carry_forward(start: np.ndarray, gyr: np.ndarray, bias: np.ndarray, period_s: float) -> np.ndarray:
    """Quaternions (N, 4) from ``start`` (4,) turned by each body rate (N, 3) rad/s less ``bias`` (3,) over one
    period in turn (right products: body-frame rates), as vqf integrates them."""
    out = np.empty((len(gyr), 4))
    _kernels.carry_forward(np.asarray(start, dtype=float), np.asarray(gyr, dtype=float), bias, period_s, out)
    return out


def travelled(filter_: Any, seconds: float) -> None:
    """Count ``seconds`` of travel towards vqf's acceptance of a new reference field, as vqf counts time turning
    faster than magNewMinGyr: a local disturbance (a magnet, steel nearby) changes as the vehicle moves past it, so a
    field that kept its norm and dip while the vehicle travelled is the earth's as surely as one that kept them while
    it turned. Only while the newest field agrees with the candidate (vqf's own test)."""
    if not filter_.getMagDistDetected():  # no candidate field to count towards (without reading the whole state)
        return
    state, params = filter_.state, filter_.params
    norm, dip = (float(v) for v in np.asarray(state["magNormDip"], dtype=float).reshape(-1)[:2])
    cand_norm, cand_dip = float(state["magCandidateNorm"]), float(state["magCandidateDip"])
    if not state["magDistDetected"] or cand_norm <= 0.0:
        return
    agrees = abs(norm - cand_norm) < params["magNormTh"] * cand_norm
    if agrees and abs(dip - cand_dip) < math.radians(params["magDipTh"]):
        state["magCandidateT"] = float(state["magCandidateT"]) + seconds
        filter_.state = state


def horizontal_bias_sigma(state: dict[str, Any], up: np.ndarray) -> float:
    """vqf's uncertainty (rad/s, one sigma per axis) of its gyroscope bias about the two horizontal axes, from the
    bias covariance of its state (``VQF.state``: body axes, in (0.01 deg/s)^2) and the earth's up axis in body axes
    (3,)."""
    cov = np.asarray(state["biasP"], dtype=float).reshape(3, 3)
    variance = max(float(np.trace(cov) - up @ cov @ up), 0.0) / 2.0
    return math.radians(math.sqrt(variance) / 100.0)


class VerticalBias:
    """The integral term for vqf's heading: the gyroscope's bias about the vertical is learnt by vqf only slowly in
    motion (its accelerometer cannot see it, tilts reveal it over a minute or so) while vqf's 6D attitude drifts in
    heading at its rate; vqf's magnetic correction delta (the heading turn from 6D to 9D) follows that drift,
    lagging by rate x tauMag (0.4 deg/s of bias: 3.7 deg). That is a proportional loop; this adds the integral:
    every change of delta (rad), divided by T_i = ``BIAS_INTEGRAL_TAUS`` tauMag, goes into vqf's own bias estimate
    along the body's up axis, where the drift comes from (one estimate, which vqf's own learning carries on). The
    loop's damping is then sqrt(T_i / tauMag) / 2 = 0.71. Changes while vqf reports a magnetic disturbance, or
    before ``BIAS_SETTLE_TAUS`` tauMag of samples, are not used."""

    def __init__(self, params: dict[str, Any], period_s: float) -> None:
        tau = float(params.get("tauMag", vqf.VQF(period_s).params["tauMag"]))
        self.integral_s, self.settle_s = BIAS_INTEGRAL_TAUS * tau, BIAS_SETTLE_TAUS * tau
        self.fed_s = 0.0
        self.delta: float | None = None

    def correction(self, delta: float, up_body: np.ndarray, seconds: float, disturbed: bool) -> np.ndarray:
        """The change (3,) rad/s to vqf's bias estimate after ``seconds`` more of samples fed: vqf's delta (rad)
        then, the earth's up axis in body axes (3,) (vqf frames), and whether the field was disturbed."""
        self.fed_s += seconds
        step = 0.0
        if self.delta is not None and not disturbed and self.fed_s >= self.settle_s:
            step = math.remainder(delta - self.delta, math.tau)
        self.delta = delta
        return -step / self.integral_s * np.asarray(up_body, dtype=float)


_T, _GYR, _ACC, _FIELD, _GIVEN, _TURN = (
    slice(0, 1),
    slice(1, 4),
    slice(4, 7),
    slice(7, 10),
    slice(10, 14),
    slice(14, 18),
)
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


class AidedFilter:
    """vqf with velocity aiding for one device (see the module docstring). Inputs in vqf's frames; velocities in
    magnetic NED m/s; times in seconds. ``pending`` (n, 18): the samples not yet fed, each with its time, gyroscope,
    accelerometer, field, the attitude last given to it and its turn since the filter's state (the gyroscope's
    product from the first pending sample to it)."""

    def __init__(
        self,
        period_s: float,
        params: dict[str, Any],
        start: Any = None,
        max_lag_s: float = MAX_LAG_S,
        fed: bool = False,
    ) -> None:
        """``start``: a vqf filter to carry on from (the device's filter before its first velocity), else a new one;
        ``fed``: whether that filter has taken samples already (else its attitude is no attitude yet)."""
        self.period_s, self.params, self.max_lag_s = period_s, params, max_lag_s
        self.filter = start if start is not None else vqf.VQF(period_s, **params)
        self.fed = fed and start is not None
        self.fixes = VelocityFixes()
        self.pending = np.zeros((0, 18))
        self.disturbed = False
        self.vertical = VerticalBias(params, period_s)
        defaults = vqf.VQF(period_s).params
        self.rest_enabled = bool(params.get("restBiasEstEnabled", True))
        self.tau_acc_s = float(params.get("tauAcc", defaults["tauAcc"]))
        bias_sigma = math.radians(float(params.get("biasSigmaInit", defaults["biasSigmaInit"])))
        self.bias_sigma = bias_sigma
        self.vehicle_tau_s = min(vehicle_tau_acc_s(VEHICLE_RESIDUAL_MS2, bias_sigma), self.tau_acc_s)
        self.drift = HeadingDrift(self.tau_acc_s, bias_sigma)
        self.explained = Explained()

    def restart(self) -> None:
        self.release()
        self.filter.resetState()
        self.fed = False
        self.fixes, self.pending, self.disturbed = VelocityFixes(), np.zeros((0, 18)), False
        self.vertical = VerticalBias(self.params, self.period_s)
        self.drift = HeadingDrift(self.drift.tau_s, self.drift.bias_sigma)
        self.explained = Explained()

    def release(self) -> None:
        """Give the filter back its own settings (rest detection, tauAcc), for samples fed without aiding."""
        self.filter.setRestBiasEstEnabled(self.rest_enabled)
        self.filter.setTauAcc(self.tau_acc_s)

    def update(
        self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One batch (N samples, vqf frame, C-contiguous float64): (vqf quaternions (N, 4) body -> ENU, magnetic
        disturbance flags (N,)) for its samples. Taken in pieces that start where a fix arrives or a ``CHUNK_S`` tick
        of time begins, so that the answers do not depend on how the samples were cut into batches."""
        rows = np.column_stack([t_s, gyr, acc, field, np.zeros((len(t_s), 8))])
        tick = np.floor(np.asarray(t_s, dtype=float) / CHUNK_S)
        cuts = np.flatnonzero(self.fixes.arrivals(vel_ned_ms)[1:] | (tick[1:] != tick[:-1])) + 1
        bounds = [0, *cuts.tolist(), len(rows)]
        parts = [self._chunk(rows[a:b], vel_ned_ms[a:b]) for a, b in itertools.pairwise(bounds) if b > a]
        if not parts:
            return np.zeros((0, 4)), np.zeros(0, dtype=bool)
        return np.vstack([q for q, _ in parts]), np.concatenate([d for _, d in parts])

    def _chunk(self, rows: np.ndarray, vel_ned_ms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One piece of a batch: rows (n, 18) with time, gyroscope, accelerometer and field filled in."""
        self.fixes.observe(rows[:, 0], vel_ned_ms)
        bias = np.asarray(self.filter.getBiasEstimate()[0], dtype=float)
        before = self.pending[-1, _TURN] if len(self.pending) else _IDENTITY
        _kernels.carry_forward(before, rows[:, _GYR], bias, self.period_s, rows[:, _TURN])
        self.pending = np.concatenate((self.pending, rows))
        self._give()
        if not self.fed:  # a filter that has taken no sample has no attitude to carry forward: fed at once
            quat = self._feed(float(rows[0, 0]), keep=0, at_once=True)
            return quat[-len(rows) :], np.full(len(rows), self.disturbed)
        self._feed(float(rows[0, 0]), keep=len(rows))
        self._give()
        return self.pending[-len(rows) :, _GIVEN].copy(), np.full(len(rows), self.disturbed)

    def _give(self) -> None:
        """The attitude of every pending sample: the filter's, turned by the sample's turn."""
        start = np.asarray(self.filter.getQuat9D(), dtype=float).reshape(1, 4)
        _kernels.quaternion_product(start, self.pending[:, _TURN], self.pending[:, _GIVEN])

    def _feed(self, now_s: float, keep: int, at_once: bool = False) -> np.ndarray:
        """Feed the pending samples whose acceleration is known (or that waited ``max_lag_s``; all of them
        ``at_once``), in order, but not the last ``keep`` (the ones being answered); then count the turns of the
        others from the new filter state. Returns vqf's quaternions (n, 4) of the samples fed.

        At once: a filter that has taken no sample yet answers from no attitude at all (the identity: magnetic east
        at level), which the gyroscope would carry forward for up to ``max_lag_s`` after every restart (a gap, a new
        calibration); so its first samples are fed without waiting for their acceleration."""
        table = self.pending
        ready = (table[:, 0] <= self.fixes.known_until_s) | (table[:, 0] < now_s - self.max_lag_s) | at_once
        count = min(int(np.argmin(ready)) if not ready.all() else len(table), len(table) - keep)
        if count == 0:
            return np.zeros((0, 4))
        self.fed = True
        fed, self.pending = table[:count], table[count:].copy()
        acc = fed[:, _ACC] - _in_body(fed[:, _GIVEN], self.fixes.acceleration(fed[:, 0]))
        gyr, field = np.ascontiguousarray(fed[:, _GYR]), np.ascontiguousarray(fed[:, _FIELD])
        standing = self.fixes.standing(float(fed[0, 0]), float(fed[-1, 0]))
        self.filter.setRestBiasEstEnabled(self.rest_enabled and standing is not False)
        out = self.filter.updateBatch(gyr, np.ascontiguousarray(acc), field)
        if standing is False:
            travelled(self.filter, count * self.period_s)
        self.disturbed = bool(np.asarray(out["magDistDetected"]).reshape(-1)[-1])
        self._heading_loop(fed[:, 0], acc, field, out)
        # the turns from the new state: conj(last fed) turn, normalised (rounding would compound)
        if len(self.pending):
            _kernels.quaternion_product(fed[-1:, _TURN], self.pending[:, _TURN], self.pending[:, _TURN], True, True)
        return np.asarray(out["quat9D"], dtype=float).reshape(-1, 4)

    def _heading_loop(self, t_s: np.ndarray, acc: np.ndarray, field: np.ndarray, out: dict[str, Any]) -> None:
        """After a piece was fed (times (n,) s, the accelerometer fed (n, 3) and the field (n, 3), vqf frames, vqf's
        outputs): where the velocity explains the accelerometer (``Explained``: a vehicle), vqf's accelerometer time
        constant for a vehicle and the Kalman filter of its heading's drift (``HeadingDrift``: the bias it learns goes
        into vqf's, its heading offset into vqf's delta); elsewhere vqf's own tauAcc and the integral term of
        ``VerticalBias``."""
        quat6d = np.asarray(out["quat6D"], dtype=float).reshape(-1, 4)
        *up_xyz, heading, horizontal, vertical, left = _kernels.piece_figures(quat6d, field, acc, STANDARD_GRAVITY_MS2)
        disturbed, up, seconds = (
            bool(np.asarray(out["magDistDetected"]).any()),
            np.array(up_xyz),
            len(t_s) * self.period_s,
        )
        bias = np.asarray(self.filter.getBiasEstimate()[0], dtype=float)
        residual = self.explained.update(left, seconds)
        vehicle = vehicle_tau_acc_s(residual, self.bias_sigma) < self.tau_acc_s
        tau = self.vehicle_tau_s if vehicle else self.tau_acc_s
        self.filter.setTauAcc(tau)
        self.drift.tau_s = tau
        if not vehicle:
            if self.drift.p is not None:  # starts afresh when it is needed again
                self.drift = HeadingDrift(self.drift.tau_s, self.drift.bias_sigma)
            more = self.vertical.correction(float(self.filter.getDelta()), up, seconds, disturbed)
            self.filter.setBiasEstimate(bias + more)
            return
        self.vertical.delta = None  # vqf's delta is set here: not a drift for the integral term
        figures = PieceField(float(np.mean(t_s)), len(t_s), heading, horizontal, vertical)
        state = self.filter.state  # read once (a dict of vqf's whole state: microseconds), written back at most once
        learnt = self.drift.update(figures, disturbed, up, horizontal_bias_sigma(state, up) * self.drift.tau_s)
        if self.drift.p is not None and not disturbed:  # the bias (rad/s, as setBiasEstimate sets it) and the delta
            state["bias"], state["delta"] = (bias + learnt).tolist(), float(self.drift.x[0])
            self.filter.state = state
        else:
            self.filter.setBiasEstimate(bias + learnt)

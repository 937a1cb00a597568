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

import functools
import math
import sys
from typing import Any

import numpy as np
import vqf

from magnet.attitude.aiding import (
    DELAY_S,
    HALF_WINDOW_S,
    MAX_FIXES,
    STANDING_SPEED_MS,
    VEHICLE_RESIDUAL_MS2,
    VelocityFixes,
    vehicle_tau_acc_s,
)
from magnet.attitude.gyro_bias import DRIFT_FIGURES, EXPLAINED_TIME_S, Explained, HeadingDrift
from magnet.compiled import kernels as _kernels
from magnet.units import STANDARD_GRAVITY_MS2

#: the longest piece of samples answered from one filter state when no fix comes (s)
CHUNK_S = 0.1
#: the longest a sample waits for its acceleration before it is fed as it is (s)
MAX_LAG_S = 1.0
#: vqf options for the offline pass of a vehicle with a velocity: it counts time towards accepting a field at any body
#: rate (vqf's ``magNewMinGyr`` default, 20 deg/s, is a hand's turn; a boat never reaches it and its whole field was
#: rejected; docs/design.md, "Velocity aiding")
OFFLINE_VQF_OPTIONS: dict[str, float] = {"magNewMinGyr": 0.0}
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
    it turned. Only while the newest field agrees with the candidate (vqf's own test: its norm within magNormTh of
    the candidate's, its dip within magDipTh), and while vqf has a candidate (magDistDetected). Compiled
    (``magnet._kernels.vqf_travelled``, on the vqf object's own state)."""
    _bind()
    _kernels.vqf_travelled(filter_, float(seconds))


def horizontal_bias_sigma(state: dict[str, Any], up: np.ndarray) -> float:
    """vqf's uncertainty (rad/s, one sigma per axis) of its gyroscope bias about the two horizontal axes, from the
    bias covariance of its state (``VQF.state``: body axes, in (0.01 deg/s)^2) and the earth's up axis in body axes
    (3,): sqrt(max(trace(P) - up^T P up, 0) / 2), in rad/s."""
    cov = np.asarray(state["biasP"], dtype=float).reshape(9)
    return _kernels.horizontal_bias_sigma(cov, np.asarray(up, dtype=float))


class VerticalBias:
    """The integral term for vqf's heading: the gyroscope's bias about the vertical is learnt by vqf only slowly in
    motion (its accelerometer cannot see it, tilts reveal it over a minute or so) while vqf's 6D attitude drifts in
    heading at its rate; vqf's magnetic correction delta (the heading turn from 6D to 9D) follows that drift,
    lagging by rate x tauMag (0.4 deg/s of bias: 3.7 deg). That is a proportional loop; this adds the integral:
    every change of delta (rad), divided by T_i = ``BIAS_INTEGRAL_TAUS`` tauMag, goes into vqf's own bias estimate
    along the body's up axis, where the drift comes from (one estimate, which vqf's own learning carries on). The
    loop's damping is then sqrt(T_i / tauMag) / 2 = 0.71. Changes while vqf reports a magnetic disturbance, or
    before ``BIAS_SETTLE_TAUS`` tauMag of samples, are not used.

    Its numbers live in ``store`` (5,): seconds fed, whether a delta is held, that delta, T_i and the settling time
    (a view into the aided filter's state, whose compiled loop runs the same ``magnet._kernels.vertical_correction``;
    a new array when alone)."""

    def __init__(self, params: dict[str, Any], period_s: float, store: np.ndarray | None = None) -> None:
        tau = float(params.get("tauMag", vqf.VQF(period_s).params["tauMag"]))
        self.store = np.zeros(5) if store is None else store
        self.store[:] = [0.0, 0.0, 0.0, BIAS_INTEGRAL_TAUS * tau, BIAS_SETTLE_TAUS * tau]

    @property
    def integral_s(self) -> float:
        return float(self.store[3])

    @property
    def settle_s(self) -> float:
        return float(self.store[4])

    @property
    def fed_s(self) -> float:
        return float(self.store[0])

    @property
    def delta(self) -> float | None:
        return float(self.store[2]) if self.store[1] else None

    def correction(self, delta: float, up_body: np.ndarray, seconds: float, disturbed: bool) -> np.ndarray:
        """The change (3,) rad/s to vqf's bias estimate after ``seconds`` more of samples fed: vqf's delta (rad)
        then, the earth's up axis in body axes (3,) (vqf frames), and whether the field was disturbed."""
        more = _kernels.vertical_correction(
            self.store, float(delta), np.asarray(up_body, dtype=float), float(seconds), bool(disturbed)
        )
        return np.array(more)


#: whether an aided vehicle's heading drift is learnt (``HeadingDrift``); off only to compare without it
DRIFT_LEARNING = True
#: the layout of the aided filter's numbers (``magnet._kernels.aided_layout``: the indices the compiled loop uses)
_LAYOUT = _kernels.aided_layout()
#: a pending row: time, gyroscope, accelerometer, field, the attitude last given, the turn since the filter's state
ROW_SIZE = 18


@functools.cache
def _bind() -> None:
    """Find vqf's compiled filter (its C++ class, in vqf's own extension module) for the compiled loop."""
    _kernels.vqf_bind(str(sys.modules[vqf.VQF.__module__].__file__))


class AidedFilter:
    """vqf with velocity aiding for one device (see the module docstring). Inputs in vqf's frames; velocities in
    magnetic NED m/s; times in seconds.

    The loop over a batch is compiled (``magnet._kernels.aided_update``, docs/cost.md): it drives ``filter``, this
    Python ``vqf.VQF`` itself (the C++ object inside it, through the functions vqf's module exports), and keeps the
    aided filter's own numbers in ``state`` (float64; ``fixes``, ``explained``, ``vertical`` and ``drift`` are views
    into it, the same classes a test or another user runs alone) and the samples not yet fed in ``pending`` (n, 18):
    each with its time, gyroscope, accelerometer, field, the attitude last given to it and its turn since the
    filter's state (the gyroscope's product from the first pending sample to it)."""

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
        _bind()
        self.period_s, self.params, self.max_lag_s = period_s, params, max_lag_s
        self.filter = start if start is not None else vqf.VQF(period_s, **params)
        defaults = vqf.VQF(period_s).params
        self.rest_enabled = bool(params.get("restBiasEstEnabled", True))
        self.tau_acc_s = float(params.get("tauAcc", defaults["tauAcc"]))
        self.bias_sigma = math.radians(float(params.get("biasSigmaInit", defaults["biasSigmaInit"])))
        self.vehicle_tau_s = min(vehicle_tau_acc_s(VEHICLE_RESIDUAL_MS2, self.bias_sigma), self.tau_acc_s)
        self.settings = np.zeros(_LAYOUT["settings"])
        figures = _LAYOUT["figures"]
        self.settings[:figures] = [
            period_s,
            max_lag_s,
            DELAY_S,
            HALF_WINDOW_S,
            MAX_FIXES,
            self.rest_enabled,
            self.tau_acc_s,
            self.vehicle_tau_s,
            STANDARD_GRAVITY_MS2,
            STANDING_SPEED_MS,
            CHUNK_S,
            EXPLAINED_TIME_S,
            DRIFT_LEARNING,
        ]
        self.settings[figures:] = DRIFT_FIGURES
        self.state = np.zeros(_LAYOUT["state"])
        self._fresh()
        self.state[0] = float(fed and start is not None)

    def _fresh(self) -> None:
        """The aided filter's own numbers as new (vqf's state is the caller's)."""
        at, size = _LAYOUT, _LAYOUT
        self.state[:] = 0.0
        self.fixes = VelocityFixes(meta=self.state[at["fixes"] : at["fixes"] + size["fixes_size"]])
        self.explained = Explained(self.state[at["explained"] : at["explained"] + size["explained_size"]])
        self.vertical = VerticalBias(
            self.params, self.period_s, self.state[at["vertical"] : at["vertical"] + size["vertical_size"]]
        )
        self.drift = HeadingDrift(
            self.tau_acc_s, self.bias_sigma, self.state[at["drift"] : at["drift"] + size["drift_size"]]
        )
        self._pending = np.zeros((0, ROW_SIZE))

    @property
    def fed(self) -> bool:
        """Whether the filter has taken samples (else its attitude is no attitude yet)."""
        return bool(self.state[0])

    @property
    def disturbed(self) -> bool:
        """vqf's magnetic disturbance flag after the last piece fed."""
        return bool(self.state[1])

    @property
    def pending(self) -> np.ndarray:
        """The samples not yet fed (n, 18) (see the class docstring; a view)."""
        return self._pending[: int(self.state[2])]

    def sigma_figures(self) -> tuple[float, VelocityFixes]:
        """For the heading's uncertainty (``magnet.attitude.uncertainty``): the accelerometer time constant in use
        (s: an aided vehicle's, else vqf's own) and the velocity fixes (their acceleration, how far it is known)."""
        return self.drift.tau_s, self.fixes

    def restart(
        self, keep_fixes: bool = False, quat_vqf: np.ndarray | None = None, before: dict[str, Any] | None = None
    ) -> AidedFilter:
        """Back to a new filter (itself, returned); ``keep_fixes``: the velocity's fixes kept (they say nothing of
        the attitude), so that the accelerometer is freed of the acceleration from the first samples the new filter
        takes (a new record while the car accelerates: docs/field-calibration.md); ``quat_vqf`` (4,): the attitude
        (body -> ENU) it starts from, as if fed (``magnet.compass.replay.start_attitude``), else none; with it the
        gyroscope's bias and its uncertainty of vqf's state ``before`` (the sensor's, not the record's) are kept."""
        self.release()
        self.filter.resetState()
        kept = (self.fixes.meta.copy(), self.fixes.buffer_times.copy(), self.fixes.buffer_values.copy())
        self._fresh()
        if keep_fixes:
            self.fixes.meta[:], self.fixes.buffer_times[:], self.fixes.buffer_values[:] = kept
        if quat_vqf is not None:
            state = self.filter.state
            state["accQuat"] = np.asarray(quat_vqf, dtype=float)
            if before is not None:
                state["bias"], state["biasP"] = before["bias"], before["biasP"]
            self.filter.state = state
            self.state[0] = 1.0
        return self

    def release(self) -> None:
        """Give the filter back its own settings (rest detection, tauAcc), for samples fed without aiding."""
        self.filter.setRestBiasEstEnabled(self.rest_enabled)
        self.filter.setTauAcc(self.tau_acc_s)

    def update(
        self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray, t_s: np.ndarray, vel_ned_ms: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One batch (N samples, vqf frame, float64): (vqf quaternions (N, 4) body -> ENU, magnetic disturbance
        flags (N,)) for its samples. Taken in pieces that start where a fix arrives or a ``CHUNK_S`` tick of time
        begins, so that the answers do not depend on how the samples were cut into batches. Each piece: its fixes
        observed; its turns carried forward from the last pending sample's (``carry_forward``, less vqf's bias
        estimate); the pending samples whose acceleration is known (or that waited ``max_lag_s``; all of them
        while the filter has taken none) fed to vqf as acc - R^T a (``magnet.attitude.aiding``), vqf's rest
        detection off while the fixes say the vehicle moves and ``travelled`` counted; after each feed the heading
        loop (``Explained``, then ``HeadingDrift`` for a vehicle or ``VerticalBias`` elsewhere, module docstring);
        the piece's samples answered from the filter's state carried forward."""
        count = len(t_s)
        held = int(self.state[2])
        if len(self._pending) < held + count:
            grown = np.zeros((max(held + count, 2 * len(self._pending)), ROW_SIZE))
            grown[:held] = self._pending[:held]
            self._pending = grown
        quat = np.empty((count, 4))
        disturbed = np.zeros(count, dtype=bool)
        vel = np.ascontiguousarray(vel_ned_ms, dtype=float)
        _kernels.aided_update(
            self.filter,
            self.settings,
            self.state,
            self.fixes.buffer_times,
            self.fixes.buffer_values,
            self._pending,
            np.asarray(t_s, dtype=float),
            gyr,
            acc,
            field,
            vel,
            quat,
            disturbed,
        )
        return quat, disturbed

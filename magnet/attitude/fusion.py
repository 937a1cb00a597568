"""Gyroscope-aided attitude and heading: a thin wrapper around the ``vqf`` orientation filter.

Design: docs/design.md, "Heading in motion".

vqf (Laidig and Seel 2023, MIT) fuses gyroscope, accelerometer and magnetometer. Its frames are ROS's, not the
project's: body FLU (x forward, y left, z up) and earth ENU with y along magnetic north. The inputs are turned into
FLU here (``magnet.frames.frd_flu``) and its quaternions back into body FRD -> NED (magnetic)
(``magnet.frames.ned_enu_attitude``), once, at the boundary; the frames and the Euler angles are those of
``magnet.frames`` (docs/frames.md).

Inputs: gyroscope (N, 3) rad/s, accelerometer (N, 3) m/s^2 (specific force: a level still device reads (0, 0, -g)),
magnetometer (N, 3) calibrated field (uT; any unit works, vqf uses directions and relative norms), all in the project
body frame and sampled together at one fixed period (seconds). ``Fusion`` is causal and keeps its state across
batches (the live compass, one per device); ``fuse_offline`` may look ahead (``offlineVQF``, forward-backward), the
best estimate for a log.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import vqf

from magnet.attitude.field_watch import FieldWatch
from magnet.attitude.fused import Fused
from magnet.attitude.heading_bias import HeadingBias, run_pieces
from magnet.attitude.heading_gate import HeadingGate
from magnet.attitude.turn_gate import TurnGate, fuse_rows, run_gated
from magnet.attitude.uncertainty import FilterFigures
from magnet.frames import frd_flu
from magnet.order_stats import median
from magnet.units import STANDARD_GRAVITY_MS2

if TYPE_CHECKING:  # the aided filter and the offline bias are imported where used: `magnet heading` needs neither
    from magnet.attitude.aided_fusion import AidedFilter

#: sample periods a filter accepts, seconds (10 kHz .. 0.5 Hz)
MIN_PERIOD_S = 1e-4
MAX_PERIOD_S = 2.0


def acc_in_ms2(acc: np.ndarray) -> np.ndarray:
    """Accelerometer readings (N, 3) in m/s^2, or in g (recognised by a median magnitude of 0.5 .. 2), as m/s^2: the
    filter's rest detection works in m/s^2; logs in g are common (``magnet heading`` takes either)."""
    arr = np.asarray(acc, dtype=float)
    typical = median(np.ravel(np.linalg.norm(arr, axis=-1))) if arr.size else 0.0
    return arr * STANDARD_GRAVITY_MS2 if 0.5 <= typical <= 2.0 else arr


def sample_period_s(t: np.ndarray, scale: float = 1.0) -> float:
    """Fixed sample period (seconds) of time stamps ``t`` (N,) in seconds (``scale`` 1) or ns (``scale`` 1e-9): the
    median step, so a few dropped or jittered samples do not matter. ValueError when the stamps do not go forward or
    give a period outside 0.1 ms .. 2 s."""
    stamps = np.asarray(t, dtype=float)
    if stamps.ndim != 1 or stamps.size < 2:
        raise ValueError("need at least two time stamps to know the sample period")
    if not np.all(np.isfinite(stamps)):
        raise ValueError("time stamps hold NaN or infinite values")
    period = median(np.diff(stamps) * scale)
    if not MIN_PERIOD_S <= period <= MAX_PERIOD_S:
        raise ValueError(
            f"median time step {period:.6g} s is not a usable sample period "
            f"({MIN_PERIOD_S:g} .. {MAX_PERIOD_S:g} s): are the times in seconds, and increasing?"
        )
    return period


def _check_period(period_s: float) -> float:
    period = float(period_s)
    if not (math.isfinite(period) and MIN_PERIOD_S <= period <= MAX_PERIOD_S):
        raise ValueError(f"sample period {period_s!r} s is outside {MIN_PERIOD_S:g} .. {MAX_PERIOD_S:g} s")
    return period


def to_vqf_frame(vectors: np.ndarray) -> np.ndarray:
    """Body vectors (..., 3) (x forward, y right, z down) in vqf's z-up body frame, C-contiguous float64."""
    return np.ascontiguousarray(frd_flu(vectors))


def _to_vqf(vectors: np.ndarray, name: str, count: int | None = None) -> np.ndarray:
    """(N, 3) body vectors -> C-contiguous float64 in vqf's z-up body frame; ValueError on bad shape or values."""
    arr = np.asarray(vectors, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3 or (count is not None and len(arr) != count):
        want = f"({count}, 3)" if count is not None else "(N, 3)"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds NaN or infinite values: drop those samples before fusing")
    return np.ascontiguousarray(frd_flu(arr))


#: vqf's state that belongs to the magnetometer (``Fusion.restart_magnetometer``)
_MAGNETIC_STATE = (
    "delta", "kMagInit", "lastMagDisAngle", "lastMagCorrAngularRate", "magCandidateDip", "magCandidateNorm",
    "magCandidateT", "magDistDetected", "magNormDip", "magNormDipLpState", "magRefDip", "magRefNorm", "magRejectT",
    "magUndisturbedT",
)  # fmt: skip


class Fusion:
    """Causal gyroscope + accelerometer (+ magnetometer) filter for one device; state carries across batches.

    ``period_s``: the fixed sample period in seconds. ``params``: vqf parameters by name (its defaults otherwise).
    ``update`` takes one batch of aligned samples; ``restart`` forgets everything (a gap, a device restart).
    With ``heading_bias`` (off by default: docs/gyro-calibration.md) the gyroscope's bias about the vertical is learnt
    from vqf's magnetic corrections where no velocity aids the filter (``magnet.attitude.heading_bias``).
    """

    def __init__(
        self,
        period_s: float,
        params: Mapping[str, Any] | None = None,
        watch: bool = True,
        heading_bias: bool = False,
        turn_gate: bool = True,
        heading_gate: bool = True,
    ) -> None:
        self.period_s = _check_period(period_s)
        self.params = dict(params or {})
        self._filter = vqf.VQF(self.period_s, **self.params)
        #: vqf's own accelerometer and magnetic time constants (s), for ``figures``
        self._taus = (float(self._filter.params["tauAcc"]), float(self._filter.params["tauMag"]))
        self._figures: FilterFigures | None = None  # the last ``figures`` without aiding
        #: from the first batch with a velocity on (``magnet.attitude.aided_fusion``)
        self._aided: AidedFilter | None = None
        #: with ``watch`` (the default), the field's disturbances are left out and the gyroscope holds the heading
        #: (docs/compass.md, "Disturbances"); compiled, it costs about a quarter of vqf itself (docs/cost.md)
        self.watch = FieldWatch(self.period_s) if watch else None
        self.heading_bias = HeadingBias(self.period_s, self._filter.params["tauMag"]) if heading_bias else None
        #: with ``turn_gate`` (the default), in a gait (a walker's or runner's steps) the accelerometer is fed a window
        #: late and left out where the course turned (in a swinging hand levelled), its centripetal acceleration not
        #: taken for gravity (``magnet.attitude.turn_gate``; docs/compass.md, "Turns of the course")
        #: with ``heading_gate`` too (the default), field samples at odds with vqf's heading while the device did not
        #: turn are left out: a slow turn of the field (a parked car) the watch does not see (``magnet.attitude.
        #: heading_gate``, judged in the turn gate's blocks; docs/compass.md, "Disturbances")
        self.turn_gate = TurnGate(self.period_s, filter_params=self.params) if turn_gate else None
        if self.turn_gate is not None and heading_gate:
            self.turn_gate.heading = HeadingGate(self.period_s)
        self._recalibrated = False  # a calibration was put in force since the start (``restart_magnetometer``)
        self.samples = 0

    @property
    def aided(self) -> bool:
        """Whether the velocity-aided filter runs (from the first batch with a velocity on, until ``restart``): its
        samples must then all come with their times, the velocity NaN where unknown (``update_vqf_frame``)."""
        return self._aided is not None

    def restart(self) -> None:
        """Back to the initial state: attitude, gyro bias and magnetic reference forgotten."""
        if self._aided is not None:
            self._aided.release()
        self._filter.resetState()
        self._aided = None
        if self.watch is not None:
            self.watch.reset()
        if self.heading_bias is not None:
            self.heading_bias.reset()
        if self.turn_gate is not None:
            self.turn_gate.reset()
        self._recalibrated = False
        self.samples = 0

    def restart_magnetometer(self, keep_fixes: bool = True, quat_vqf: np.ndarray | None = None) -> None:
        """Forget the magnetic side only (a new calibration put in force): the heading taken again from the next field
        sample, the tilt and the gyroscope's bias kept (a whole restart takes 10 s and more to find a swinging hand's
        tilt). Aided: a whole restart (``AidedFilter.restart``'s options; docs/field-calibration.md)."""
        if (aided := self._aided) is not None:
            before = self._filter.state  # (a copy) its gyroscope bias is kept where an attitude is given
            self.restart()
            self._aided = aided.restart(keep_fixes, quat_vqf, before)
            return
        fresh = vqf.VQF(self.period_s, **self.params).state
        state = self._filter.state
        for key in _MAGNETIC_STATE:
            state[key] = fresh[key]
        self._filter.state = state
        if self.watch is not None:
            self.watch.reset()
        if self.heading_bias is not None:  # the bias it learnt is kept, its loop starts again with the new delta
            self.heading_bias.reset()
        self._recalibrated = True

    def update(
        self,
        gyr_rads: np.ndarray,
        acc_ms2: np.ndarray,
        mag: np.ndarray | None = None,
        t_s: np.ndarray | None = None,
        vel_ned_ms: np.ndarray | None = None,
    ) -> Fused:
        """Feed one batch: gyr (N, 3) rad/s, acc (N, 3) m/s^2, mag (N, 3) calibrated field or None; body frame.
        With the field, ``t_s`` (N,) s and ``vel_ned_ms`` (N, 3) m/s in magnetic NED (NaN rows where unknown):
        velocity aiding (``magnet.attitude.aiding``)."""
        gyr = _to_vqf(gyr_rads, "gyr_rads")
        if len(gyr) == 0:
            return Fused.empty()
        acc = _to_vqf(acc_ms2, "acc_ms2", len(gyr))
        field = None if mag is None else _to_vqf(mag, "mag", len(gyr))
        if field is not None and t_s is not None and vel_ned_ms is not None:
            quat, disturbed = self.update_vqf_frame(gyr, acc, field, np.asarray(t_s, float), vel_ned_ms)
            return Fused.from_vqf({"quat9D": quat, "magDistDetected": disturbed, "restDetected": disturbed * 0}, True)
        watched = self._watched(field, gyr)
        if field is not None and watched.any():
            field = np.ascontiguousarray(np.where(watched[:, None], 0.0, field))
        out = self._vqf(gyr, acc, field, watched)
        self.samples += len(gyr)
        if field is not None:
            out["magDistDetected"] = np.asarray(out["magDistDetected"], dtype=bool).reshape(-1) | watched
        return Fused.from_vqf(out, field is not None)

    def update_vqf_frame(
        self,
        gyr: np.ndarray,
        acc: np.ndarray,
        field: np.ndarray,
        t_s: np.ndarray | None = None,
        vel_ned_ms: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The fast path for many small batches: inputs (N, 3) already in vqf's frame (``to_vqf_frame``), finite,
        C-contiguous float64; returns vqf's own quaternions (N, 4) (``frames.ned_enu_attitude`` converts them) and
        its magnetic disturbance flags (N,). With times (N,) s and velocities (N, 3) m/s magnetic NED of which one is
        known (or after such a batch, until ``restart``): the velocity-aided filter. Samples the watch finds disturbed
        (``magnet.attitude.field_watch``) reach vqf without their field (a zero vector, which vqf skips: the gyroscope
        holds the heading) and are flagged disturbed."""
        self.samples += len(gyr)
        watched = self._watched(field, gyr)
        if watched.any():
            field = np.ascontiguousarray(np.where(watched[:, None], 0.0, field))
        quat, disturbed = self._vqf_frame(gyr, acc, field, t_s, vel_ned_ms, watched)
        return quat, np.asarray(disturbed, dtype=bool) | watched

    def update_rows(self, inputs: tuple[np.ndarray, ...], lo: int, hi: int, quat: Any, disturbed: Any) -> None:
        """``update_vqf_frame`` without a velocity on rows lo .. hi of a drain's gyroscope, accelerometer and field
        (S, 3) each, written into those rows of ``quat`` (S, 4) and ``disturbed`` (S,) bool. Where only the watch, the
        turn gate and vqf run (not aided, no bias loop, the gate's companion done): one compiled call, the same code
        (``turn_gate.fuse_rows``)."""
        gate = self.turn_gate
        if (
            gate is not None
            and self._aided is None
            and self.heading_bias is None
            and (gate.alone is None or gate.alone.done)
        ):
            self.samples += hi - lo
            fuse_rows(gate, self._filter, self.watch, inputs, lo, hi, quat, disturbed)
        else:
            quat[lo:hi], disturbed[lo:hi] = self.update_vqf_frame(*(x[lo:hi] for x in inputs))

    def figures(self) -> FilterFigures:
        """What the heading's uncertainty needs of this filter's state now (``magnet.attitude.uncertainty``): vqf's
        accelerometer time constant in use and its magnetic one (s), its gyroscope bias uncertainty (rad/s), and
        where velocity aids it, the velocity's acceleration (magnetic NED) and how far it is known."""
        bias_sigma = float(self._filter.getBiasEstimate()[1])
        aided = self._aided
        if aided is None:
            figures = self._figures  # kept while the bias uncertainty holds (a frozen dataclass costs 1.6 us to make)
            if figures is None or figures.bias_sigma_rads != bias_sigma:
                figures = self._figures = FilterFigures(self._taus[0], self._taus[1], bias_sigma)
            return figures
        tau_acc_s, fixes = aided.sigma_figures()
        return FilterFigures(tau_acc_s, self._taus[1], bias_sigma, fixes.acceleration, fixes.known_until_s)

    def _watched(self, field: np.ndarray | None, gyr: np.ndarray) -> np.ndarray:
        """(N,) bool: the samples the watch finds disturbed (none without a field or a watch)."""
        if field is None or self.watch is None:
            return np.zeros(len(gyr), dtype=bool)
        return self.watch.update(field, gyr)

    def _vqf_frame(
        self,
        gyr: np.ndarray,
        acc: np.ndarray,
        field: np.ndarray,
        t_s: np.ndarray | None,
        vel_ned_ms: np.ndarray | None,
        watched: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """vqf (or the aided filter) on one batch, as ``update_vqf_frame`` (``watched`` (N,): the watch's flags)."""
        if self._aided is None and t_s is not None and vel_ned_ms is not None and np.isfinite(vel_ned_ms).any():
            had = self.samples > len(gyr)  # carries on from its state, an attitude once it took samples
            from magnet.attitude.aided_fusion import AidedFilter

            self._aided = AidedFilter(self.period_s, self.params, self._filter, fed=had)
        if self._aided is not None and t_s is not None:
            vel = np.full((len(gyr), 3), np.nan) if vel_ned_ms is None else vel_ned_ms
            return self._aided.update(gyr, acc, field, t_s, vel)
        if self._aided is not None:  # a batch without times after aided ones: vqf with its own settings
            self._aided.release()
        out = self._vqf(gyr, acc, field, watched)
        return out["quat9D"], out["magDistDetected"]

    def _vqf(self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray | None, watched: np.ndarray) -> dict[str, Any]:
        """vqf's ``updateBatch`` on one batch (vqf frames; ``watched`` (N,) the samples the watch left out), with the
        turn gate (in pieces cut at its blocks, ``TurnGate.left_in_block``, vqf's attitude and bias read at each one's
        start; one compiled call without a bias loop) and the bias loop where they run: vqf's outputs for the batch."""
        if self.turn_gate is None:
            return self._vqf_piece(gyr, acc, field, watched)
        alone = self.heading_bias is None or field is None or self._aided is not None  # no bias loop: vqf's batch
        return run_gated(self.turn_gate, self._filter, None if alone else self._vqf_piece, (gyr, acc, field), watched)

    def _vqf_piece(
        self, gyr: np.ndarray, acc: np.ndarray, field: np.ndarray | None, watched: np.ndarray
    ) -> dict[str, Any]:
        """vqf's ``updateBatch`` on one piece, with the bias loop where it runs (``heading_bias.run_pieces``)."""
        loop = self.heading_bias
        if loop is None or field is None or self._aided is not None:
            return self._filter.updateBatch(gyr, acc, field)
        return run_pieces(self._filter, loop, (gyr, acc, field), watched, self._recalibrated)


def fuse_offline(
    gyr_rads: np.ndarray,
    acc_ms2: np.ndarray,
    mag: np.ndarray | None,
    period_s: float,
    params: Mapping[str, Any] | None = None,
    t_s: np.ndarray | None = None,
    vel_ned_ms: np.ndarray | None = None,
    watch: bool = False,
    vertical_bias: bool = True,
) -> Fused:
    """Best estimate for a whole log (vqf's ``offlineVQF``: looks ahead, forward and backward). Shapes as ``Fusion``.
    With ``t_s`` and ``vel_ned_ms`` (magnetic NED) the accelerometer is first freed of the linear acceleration the
    velocity implies (every fix known at once), turned into the body frame by the causal aided attitude, and vqf
    counts time towards accepting the field at any body rate (``aided_fusion.OFFLINE_VQF_OPTIONS``). With ``watch``
    the samples the field's watch flags (``FieldWatch``, as the causal filter runs it) reach ``offlineVQF`` without
    their field and are flagged disturbed; off by default: offlineVQF rejects on its own, and the watch's few flags
    on BROAD make it worse (0.809 -> 0.888, 0.530 -> 0.536 deg; docs/compass.md, "Disturbances"). With
    ``vertical_bias`` (the default) and the field, where vqf cannot learn the gyroscope's bias about the vertical (it
    never rests), that bias is first found from the field's heading drift over the log and taken off, and without a
    velocity vqf trusts the field longer (``magnet.attitude.drift_bias.offline_correction``)."""
    from magnet.attitude import aided_fusion, drift_bias

    period = _check_period(period_s)
    gyr = _to_vqf(gyr_rads, "gyr_rads")
    if len(gyr) == 0:
        return Fused.empty()
    acc = _to_vqf(acc_ms2, "acc_ms2", len(gyr))
    field = None if mag is None else _to_vqf(mag, "mag", len(gyr))
    aided = False
    if field is not None and t_s is not None and vel_ned_ms is not None and np.isfinite(vel_ned_ms).any():
        aided = True
        causal = Fusion(period, params)
        quat, _ = causal.update_vqf_frame(gyr, acc, field, np.asarray(t_s, dtype=float), vel_ned_ms)
        acc = np.ascontiguousarray(acc - aided_fusion.body_acceleration(quat, t_s, vel_ned_ms))
    watched = FieldWatch(period).update(field, gyr) if field is not None and watch else np.zeros(len(gyr), bool)
    if field is not None and watched.any():
        field = np.ascontiguousarray(np.where(watched[:, None], 0.0, field))
    options = {**(aided_fusion.OFFLINE_VQF_OPTIONS if aided else {}), **(params or {})}
    out = dict(vqf.offlineVQF(gyr, acc, field, period, options or None))
    if field is not None and vertical_bias:  # again, with the bias about the vertical its 6D attitude shows
        gyr, options, found = drift_bias.offline_correction(gyr, field, period, options, out, lengthen=not aided)
        if found:
            out = dict(vqf.offlineVQF(gyr, acc, field, period, options or None))
    if field is not None:
        out["magDistDetected"] = np.asarray(out["magDistDetected"], dtype=bool).reshape(-1) | watched
    return Fused.from_vqf(out, field is not None)


def acc_less_velocity(
    gyr_rads: np.ndarray,
    acc_ms2: np.ndarray,
    mag: np.ndarray,
    period_s: float,
    t_s: np.ndarray,
    vel_ned_ms: np.ndarray,
) -> np.ndarray:
    """The accelerometer (N, 3) m/s^2 body FRD less the linear acceleration the velocity implies (every fix known at
    once, ``magnet.attitude.aiding``), turned into the body frame by the causal velocity-aided attitude with the
    field ``mag`` (N, 3), calibrated (its heading turns the velocity's acceleration into the body; a heading a few
    degrees off leaves a few % of it). What is left is gravity, for a filter without the magnetometer whose tilt a
    vehicle's own accelerations should not bend. ``vel_ned_ms`` (N, 3) magnetic NED, NaN rows where unknown (their
    samples are returned as they are)."""
    from magnet.attitude.aided_fusion import body_acceleration

    period = _check_period(period_s)
    gyr = _to_vqf(gyr_rads, "gyr_rads")
    acc = _to_vqf(acc_in_ms2(acc_ms2), "acc_ms2", len(gyr))
    field = _to_vqf(mag, "mag", len(gyr))
    t = np.asarray(t_s, dtype=float)
    quat, _ = Fusion(period).update_vqf_frame(gyr, acc, field, t, vel_ned_ms)
    return frd_flu(acc - body_acceleration(quat, t, vel_ned_ms))


def fuse_causal(
    gyr_rads: np.ndarray,
    acc_ms2: np.ndarray,
    mag: np.ndarray | None,
    period_s: float,
    params: Mapping[str, Any] | None = None,
    t_s: np.ndarray | None = None,
    vel_ned_ms: np.ndarray | None = None,
    watch: bool = True,
    heading_gate: bool = True,
) -> Fused:
    """A whole log through a fresh causal filter, as the live compass would see it. Shapes as ``Fusion``; ``watch``
    and ``heading_gate`` as there."""
    return Fusion(period_s, params, watch, heading_gate=heading_gate).update(gyr_rads, acc_ms2, mag, t_s, vel_ned_ms)

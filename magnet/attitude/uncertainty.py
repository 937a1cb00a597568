"""A heading's uncertainty: one sigma in degrees on every sample (``heading_sigma_deg``), from physics.

The model, stated once here (docs/vehicles.md, "Heading uncertainty", says it in words). A heading is the direction
of the horizontal field B_h in a frame the attitude's tilt sets. Four independent sources of error; sigma is the root
of the sum of their squares (radians, given in degrees, at most 180):

1. **The calibration.** A field error of r uT across the horizontal field turns the heading by r / |B_h| rad; r is
   the calibration's residual RMS (uT, ``Quality.residual_rms_ut``), or ``UNCALIBRATED_FRACTION`` of |B| without a
   calibration. A heading from the accelerometer's tilt takes each sample as it comes: r / |B_h|. The gyroscope-aided
   filter turns its heading towards the field's with its magnetic time constant tau_mag (vqf's tauMag), so errors
   that change from sample to sample (period T) average down to r / |B_h| sqrt(T / (2 tau_mag)).
2. **The tilt.** A tilt error e about magnetic north lets the vertical field into the horizontal plane: the heading
   turns by e B_v / B_h = e tan(dip). The filter's tilt follows its accelerometer's low-pass (vqf: second order, time
   constant tauAcc; here two first-order stages of tauAcc / sqrt(2), the same fall-off) of what no one explains: the
   linear acceleration, less the velocity's where a velocity aids the filter, over g, a horizontal vector in the
   (magnetic) earth frame. The heading sees it through its own magnetic correction (first order, tau_mag), so the
   tilt's share is |LP_mag(LP_acc(a_h / g) tan(dip))| / sqrt(2) (the two horizontal axes alike). A heading from the
   accelerometer's tilt has no low-pass: e = | |acc| - g | / g (the linear acceleration along gravity, the only part
   an accelerometer alone shows); a sample without accelerometer assumes the device level within ``UNLEVEL_DEG``.
3. **The filter's state.** While the field is not trusted (a disturbance vqf or the field's watch rejects: the
   FIELD_DISTURBED flag of a fused sample), the gyroscope alone carries the heading: its bias uncertainty b (rad/s,
   vqf's ``biasSigma``) over the time t since the last trusted field sample gives b t.
4. **A disturbance** in a heading taken from the field directly (not fused) and flagged FIELD_DISTURBED or
   DIP_DISTURBED: the disturbing field is at least | |B| - B_expected | (uT), which turns the heading by up to that over
   |B_h|.

Shapes: S samples of many batches (``bounds``), vectors (S, 3) in the body frame (x forward, y right, z down),
attitudes (S, 4) body -> magnetic NED. Per-device state (the low-passes, the last trusted time) is kept across steps
for at most ``max_devices`` devices. Pure (numpy, and the per-sample maths compiled: ``_direct``); times are the
samples' own.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from magnet import _kernels
from magnet.attitude import heading as hd
from magnet.bounded import Recent
from magnet.frames import quaternion_to_matrix
from magnet.units import STANDARD_GRAVITY_MS2

#: without a calibration, the field's error taken as this fraction of |B| (a factory calibration's hard iron left)
UNCALIBRATED_FRACTION = 0.1
#: a sample without accelerometer: the device taken as level within this (deg, one sigma)
UNLEVEL_DEG = 10.0
#: the dip beyond which tan(dip) is held (deg): near the magnetic poles a heading has no meaning anyway
MAX_DIP_DEG = 85.0
#: a gap between a device's samples beyond which its state starts again (s; the filter restarts after 0.5 s)
RESTART_GAP_S = 1.0
#: batches of a device that wait for their velocity's acceleration at most
MAX_WAITING = 200
#: the least tilt sigma said (deg): an accelerometer's own alignment to its board is seldom better
MIN_TILT_DEG = 0.1
#: the largest sigma (deg): no heading at all
MAX_SIGMA_DEG = 180.0
#: vqf's defaults (s) where no filter's figures are given
DEFAULT_TAU_ACC_S, DEFAULT_TAU_MAG_S = 3.0, 9.0
_ONE = np.array([1.0, 0.0, 0.0, 0.0])
_DISTURBED = int(hd.HeadingFlag.FIELD_DISTURBED | hd.HeadingFlag.DIP_DISTURBED)


@dataclasses.dataclass(frozen=True)
class FilterFigures:
    """What the model needs of a device's gyroscope-aided filter after a batch: its accelerometer and magnetic time
    constants (s, in use: an aided vehicle's tauAcc is shorter), its gyroscope bias uncertainty (rad/s, one sigma),
    and where a velocity aids it, the acceleration the velocity explains (``explained``: times (n,) s -> (n, 3) m/s^2
    magnetic NED), known up to ``known_until_s`` (s; the samples after it wait, as the filter's do)."""

    tau_acc_s: float = DEFAULT_TAU_ACC_S
    tau_mag_s: float = DEFAULT_TAU_MAG_S
    bias_sigma_rads: float = 0.0
    explained: Callable[[np.ndarray], np.ndarray] | None = None
    known_until_s: float = math.inf


class Sigmas(NamedTuple):
    """One sigma per sample (S,), deg: of the heading, and of the tilt about each horizontal axis (the module's 2:
    the filter's low-passed unexplained acceleration over g, or the accelerometer's alone; at least
    ``MIN_TILT_DEG``)."""

    heading_deg: np.ndarray
    tilt_deg: np.ndarray


@dataclasses.dataclass
class _Device:
    """One device's state: the two accelerometer stages and the magnetic stage, (north, east) each; the last
    sample's time and the last trusted field sample's (ns); the time (s) the stages last took; and its batches
    waiting for their velocity's acceleration, as (mean time s, mean north, mean east force in g)."""

    last_ns: int
    trusted_ns: int
    acc1: tuple[float, float] = (0.0, 0.0)
    acc2: tuple[float, float] = (0.0, 0.0)
    mag: tuple[float, float] = (0.0, 0.0)
    fed_s: float | None = None
    waiting: list[tuple[float, float, float]] = dataclasses.field(default_factory=list)


class _Batches(NamedTuple):
    """Per batch (B,) of one step, as Python lists: fused samples, mean tan(dip) over them, the samples whose
    horizontal force is known, their mean time (s) and mean force (north, east; g), whether a fused sample is not
    trusted, the first and last time (ns)."""

    fused: list[float]
    tan_dip: list[float]
    known: list[float]
    t_s: list[float]
    north: list[float]
    east: list[float]
    untrusted: list[bool]
    first_ns: list[int]
    last_ns: list[int]

    @classmethod
    def of(
        cls,
        bounds: Sequence[int],
        t_ns: np.ndarray,
        fused: np.ndarray,
        trusted: np.ndarray,
        tan_dip: np.ndarray,
        horizontal: np.ndarray,
    ) -> _Batches:
        edges = np.asarray(bounds, dtype=np.int64)
        figures = np.empty((len(edges) - 1, 7))  # one compiled pass: the sums along each batch, numpy's reduceat's
        _kernels.batch_figures(edges, t_ns, fused, trusted, tan_dip, np.ascontiguousarray(horizontal), figures)
        last = np.maximum(edges[1:] - 1, 0)
        first = np.minimum(edges[:-1], max(len(t_ns) - 1, 0))
        times = t_ns if len(t_ns) else np.zeros(1, dtype=np.int64)
        fused_n, tan_mean, known, t_s, north, east, untrusted = figures.T.tolist()
        return cls(
            fused_n,
            tan_mean,
            known,
            t_s,
            north,
            east,
            [u > 0 for u in untrusted],
            times[first].tolist(),
            times[last].tolist(),
        )


class HeadingUncertainty:
    """The model of the module for the compass: ``step`` gives every sample's sigmas (deg), keeping per device the
    state the filter's part needs (a few floats: the per-batch work is done for all batches at once)."""

    def __init__(self, max_devices: int = 100_000) -> None:
        self.devices: Recent[str, _Device] = Recent(max_devices)

    @property
    def evicted(self) -> int:
        return self.devices.evicted

    def step(
        self,
        devices: Sequence[str],
        bounds: Sequence[int],
        t_ns: np.ndarray,
        acc_ms2: np.ndarray,
        field_ut: np.ndarray,
        flags: np.ndarray,
        quat_wxyz: np.ndarray | None,
        expected_ut: np.ndarray,
        residuals_ut: Sequence[float | None],
        figures: Sequence[FilterFigures | None],
        rotation: np.ndarray | None = None,
    ) -> Sigmas:
        """The sigmas (``Sigmas``, (S,) deg each) of S samples. t_ns (S,) int; acc_ms2 and field_ut (S, 3) (the
        corrected field; NaN acc rows: no accelerometer); flags (S,) ``HeadingFlag`` bits (FUSED, FIELD_DISTURBED,
        ...); quat_wxyz (S, 4) body -> magnetic NED where fused (NaN rows elsewhere), None when nothing is fused;
        expected_ut (S,) the field expected at the place (NaN: unknown); per batch the calibration's residual RMS
        (uT, None: not calibrated) and the filter's figures (None: not fused). ``rotation`` (S, 3, 3): the matrices
        of ``quat_wxyz`` where fused and the identity elsewhere, when the caller has them already (the compass:
        ``FusedColumns.rotation``); None: made here."""
        flags = np.asarray(flags, dtype=np.int64)
        fused = (flags & int(hd.HeadingFlag.FUSED)) != 0
        if quat_wxyz is None or not fused.any():
            rotation = None
        elif rotation is None:
            rotation = quaternion_to_matrix(
                np.where(fused[:, None] & hd.rows_finite(quat_wxyz)[:, None], quat_wxyz, _ONE)
            )
        counts = np.diff(np.asarray(bounds, dtype=np.int64)).tolist()
        residual = np.repeat([math.nan if r is None else float(r) for r in residuals_ut], counts)
        tan_dip, field_rad, tilt, variance = _direct(field_ut, acc_ms2, rotation, fused, flags, expected_ut, residual)
        if rotation is not None:
            trusted = fused & ((flags & int(hd.HeadingFlag.FIELD_DISTURBED)) == 0)
            batches = _Batches.of(bounds, t_ns, fused, trusted, tan_dip, _horizontal_force_g(acc_ms2, rotation))
            per_batch = self._filtered(devices, batches, figures)
            filtered = np.repeat(per_batch[:, 0], counts) * field_rad**2 + np.repeat(per_batch[:, 1], counts)
            drift = self._drift(devices, bounds, t_ns, trusted, batches, figures)
            use = fused & np.repeat(per_batch[:, 3] > 0, counts)
            variance = np.where(use, filtered + drift**2, variance)
            tilt = np.where(use, np.repeat(per_batch[:, 2], counts), tilt)
        heading, tilt_deg = np.empty(len(variance)), np.empty(len(variance))
        _kernels.sigma_degrees(variance, tilt, MAX_SIGMA_DEG, UNLEVEL_DEG, MIN_TILT_DEG, heading, tilt_deg)
        return Sigmas(heading, tilt_deg)

    def _filtered(
        self, devices: Sequence[str], batches: _Batches, figures: Sequence[FilterFigures | None]
    ) -> np.ndarray:
        """(B, 4) per batch with fused samples and figures: the factor of the residual's variance (T / (2 tau_mag)),
        the tilt's share of the heading's variance (rad^2), the filter's tilt per horizontal axis (rad), and 1 (0 for
        the other batches): the module's 1 and 2, advancing each device's state over the batch."""
        out = np.zeros((len(devices), 4))
        for b, (device, figure) in enumerate(zip(devices, figures)):
            if figure is None or not batches.fused[b]:
                continue
            first, last = batches.first_ns[b], batches.last_ns[b]
            state = self.devices.get(device)
            if state is not None:
                self.devices.touch(device)
            if state is None or not 0 < (first - state.last_ns) * 1e-9 <= RESTART_GAP_S:
                self.devices[device] = state = _Device(first, first)
            seconds = max((last - state.last_ns) * 1e-9, 0.0)
            period_s = seconds / batches.fused[b] if seconds > 0 else 0.01
            state.last_ns = last
            if batches.known[b]:
                _take(state, (batches.t_s[b], batches.north[b], batches.east[b]), batches.tan_dip[b], figure)
            tilt_heading = math.hypot(*state.mag) / math.sqrt(2.0)
            out[b] = (period_s / (2.0 * figure.tau_mag_s), tilt_heading**2, math.hypot(*state.acc2) / math.sqrt(2.0), 1)
        return out

    def _drift(
        self,
        devices: Sequence[str],
        bounds: Sequence[int],
        t_ns: np.ndarray,
        trusted: np.ndarray,
        batches: _Batches,
        figures: Sequence[FilterFigures | None],
    ) -> np.ndarray:
        """(S,) rad: the module's 3, the bias uncertainty times the time since the last trusted field sample (zero in
        batches whose fused samples are all trusted), each device's last trusted time carried on from batch to batch
        and drain to drain: in a batch with an untrusted sample, the running maximum of the trusted samples' times and
        (where a sample is not trusted) the device's last trusted time before the batch. One compiled pass over the
        batches in order (``magnet._kernels.bias_drift``), the devices' times in and out."""
        drift = np.zeros(len(t_ns))
        slot_of: dict[str, int] = {}
        kept: list[_Device] = []
        slot, bias = [-1] * len(devices), [0.0] * len(devices)
        for b, (device, figure) in enumerate(zip(devices, figures)):
            state = self.devices.get(device) if batches.fused[b] else None
            if state is None or figure is None:
                continue
            slot[b], bias[b] = slot_of.setdefault(device, len(kept)), figure.bias_sigma_rads
            if slot[b] == len(kept):
                kept.append(state)
        if not kept:
            return drift
        times = np.array([s.trusted_ns for s in kept], dtype=np.int64)
        _kernels.bias_drift(
            np.asarray(t_ns, dtype=np.int64), trusted, np.asarray(bounds, dtype=np.int64), np.array(slot, np.int64),
            np.array(batches.untrusted, dtype=bool), np.array(bias), times, drift,
        )  # fmt: skip
        for state, carried in zip(kept, times.tolist()):
            state.trusted_ns = carried
        return drift


def _take(state: _Device, batch: tuple[float, float, float], tan_dip: float, figures: FilterFigures) -> None:
    """Queue a batch's (mean time s, mean north, mean east horizontal specific force in g) and run the low-passes
    over the queued batches whose unexplained acceleration is known (at once without a velocity; ``MAX_WAITING``
    batches at most wait)."""
    if figures.explained is None:
        ready = [batch]
    else:
        state.waiting.append(batch)
        del state.waiting[:-MAX_WAITING]
        count = sum(1 for t, _, _ in state.waiting if t <= figures.known_until_s)
        ready, state.waiting = state.waiting[:count], state.waiting[count:]
        if ready:
            explained = figures.explained(np.array([t for t, _, _ in ready])) / STANDARD_GRAVITY_MS2
            ready = [(t, n - a[0], e - a[1]) for (t, n, e), a in zip(ready, explained.tolist())]
    for t, north, east in ready:
        seconds = 0.0 if state.fed_s is None else max(t - state.fed_s, 0.0)
        state.fed_s = t
        _advance(state, seconds, north, east, tan_dip, figures)


def _advance(state: _Device, seconds: float, north: float, east: float, tan_dip: float, figures: FilterFigures) -> None:
    """The low-passes over ``seconds`` towards the unexplained horizontal acceleration (north, east; g) and
    tan(dip): two stages of tauAcc / sqrt(2), then the magnetic stage of tau_mag on the tilt times tan(dip)."""
    keep = math.exp(-seconds * math.sqrt(2.0) / max(figures.tau_acc_s, 1e-3))
    a1 = (north + (state.acc1[0] - north) * keep, east + (state.acc1[1] - east) * keep)
    a2 = (a1[0] + (state.acc2[0] - a1[0]) * keep, a1[1] + (state.acc2[1] - a1[1]) * keep)
    keep_mag = math.exp(-seconds / max(figures.tau_mag_s, 1e-3))
    m = state.mag
    state.acc1, state.acc2 = a1, a2
    state.mag = (
        a2[0] * tan_dip + (m[0] - a2[0] * tan_dip) * keep_mag,
        a2[1] * tan_dip + (m[1] - a2[1] * tan_dip) * keep_mag,
    )


def _horizontal_force_g(acc_ms2: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(S, 2) the horizontal (north, east) specific force in the magnetic earth frame, in g (NaN rows: unknown)."""
    out = np.empty((len(acc_ms2), 2))  # numpy's einsum("sij,sj->si", rotation[:, :2], acc_ms2) / g to the bit
    _kernels.horizontal_force(np.ascontiguousarray(rotation).reshape(-1, 9), acc_ms2, STANDARD_GRAVITY_MS2, out)
    return out


def _direct(
    field_ut: np.ndarray,
    acc_ms2: np.ndarray,
    rotation: np.ndarray | None,
    fused: np.ndarray,
    flags: np.ndarray,
    expected_ut: np.ndarray,
    residual_ut: np.ndarray,
) -> np.ndarray:
    """(4, S): per sample |tan(dip)| (the dip against the fused down where ``rotation`` (S, 3, 3) is given and the
    sample ``fused``, else against the accelerometer's, else level; held at ``MAX_DIP_DEG``), the calibration's
    share r / |B_h| (rad; r the ``residual_ut`` (S,), NaN: ``UNCALIBRATED_FRACTION`` of |B|), the tilt error of an
    attitude from the accelerometer alone (rad: | |acc| - g | / g, ``UNLEVEL_DEG`` without one) and the variance
    (rad^2) of a heading taken from the field directly: the module's 1, 2 and 4 (a flagged disturbance:
    (| |B| - expected | / |B_h|)^2). One compiled pass (``magnet._kernels.sigma_direct``)."""
    count = len(field_ut)
    out = np.empty((4, count))
    down, where = (acc_ms2, np.zeros(count, dtype=bool)) if rotation is None else (rotation[:, 2, :], fused)
    expected = np.asarray(expected_ut, dtype=float)
    expected = expected if expected.shape == (count,) else np.broadcast_to(expected, (count,))
    _kernels.sigma_direct(
        np.asarray(field_ut, dtype=float), np.asarray(acc_ms2, dtype=float), down, where, flags, expected,
        residual_ut, _DISTURBED, math.radians(MAX_DIP_DEG), UNCALIBRATED_FRACTION, math.radians(UNLEVEL_DEG),
        STANDARD_GRAVITY_MS2, *out,
    )  # fmt: skip
    return out

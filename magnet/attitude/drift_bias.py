"""The gyroscope's bias about the vertical, from the drift of the field's heading under the gyroscope's attitude, for
the offline filter (``magnet.attitude.fusion.fuse_offline``, ``magnet heading --offline``; issue 26,
docs/field-calibration.md, "The heading filter of a walk").

vqf learns its gyroscope's bias at rest and, in motion, from the accelerometer, which sees the two horizontal axes
only: a phone carried by a walker keeps the same body axis up and never rests, so the bias about the vertical (up to
0.5 deg/s on a phone) is never learnt. Its 6D attitude then drifts in heading at that rate, and the magnetometer's
correction has to follow the drift through a proportional loop of time constant tauMag. That loop also passes on
the magnetometer's heading errors in walking, and these are large: a walker's corners and gait tilt the filter by a
degree or more, and a tilt error turns the field's heading by tilt x tan(dip) (2.4 at 67 deg dip). With the
simulator's true calibration on ``magnet bench field``'s walks (seeds 2026-2030), vqf's offline heading is 0.99 deg
RMS after the offset; 0.83 with the true gyroscope bias taken off, 0.46 with it taken off and tauMag 18 s instead of
9: once the drift is known, the field can be trusted over a longer time, over which its tilt errors average out.

The drift is linear in the bias: with the 6D attitude R(t) (body -> earth) integrated with a bias error b, the field's
angle about the vertical in the earth frame grows as the integral of up(t) . b, up(t) the earth's up axis in body
axes. So over the log

    psi(t) = c + D(t) . b + e(t),   D(t) = integral of up(t) dt,

psi the unwrapped angle of the field in the 6D earth frame, is a linear least-squares problem in (c, b) (the gyroscope
identification of the field's constancy, as in Kok and Schon 2016, with the calibration known). The tilt's heading
errors e(t) are zero-mean over a walk and correlated over a corner (``CORRELATION_S``); the fit is made robust (Huber
weights) against a disturbed stretch, and held near zero by vqf's own prior on the bias (``PRIOR_DPS``). Only the
bias's component along the mean up axis is used: the others are the accelerometer's to see, and a walk barely
identifies them (taken whole, they made two walks' headings 5 and 11 deg worse). On the walks the bias about the
vertical is found within 0.01-0.06 deg/s of the truth.

Not in the causal filter: there the estimate comes only after tens of seconds and keeps moving, and every change of
it moves the heading's standing lag (bias x tauMag), which is scatter after the constant offset (tuning seeds 1-9, true
calibration: 1.45 deg without it, 1.65 with it, 1.34 even with the true bias given at 40 s).

numpy and vqf; vqf's frames (body FLU, earth ENU) throughout.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import vqf

from magnet.frames import quaternion_to_matrix

#: vqf's own prior on its bias (biasSigmaInit), deg/s: the estimate is held near zero by it
PRIOR_DPS = 0.5
#: the field heading's errors from the tilt are correlated over about this long (s: a corner, a few strides), so
#: that many seconds of samples count as one in the fit's uncertainty
CORRELATION_S = 2.0
#: the bias is estimated only where vqf's own uncertainty of its bias (one sigma, rad/s as vqf gives it, converted)
#: exceeds this (deg/s): a device that rested has its bias from vqf's rest detection, on every axis
MIN_SIGMA_DPS = 0.2
#: with the bias about the vertical estimated, vqf's magnetic time constant tauMag is this many times its own
TAU_MAG_FACTOR = 2.0
#: Huber's threshold, in robust standard deviations of the residual
HUBER_K = 2.5
#: field samples whose strength is further than this fraction from the log's median, or whose dip is further than
#: this from its median (deg), are left out as disturbed (vqf's magNormTh and magDipTh)
NORM_TH = 0.1
DIP_TH_DEG = 10.0
#: the fit needs at least this many seconds of field samples
MIN_SPAN_S = 20.0
#: the field's angle is unwrapped about its circular mean over this many seconds around each sample
UNWRAP_S = 20.0
#: a longer log is cut into equal parts of at most this many seconds, each with its own bias: a gyroscope's bias
#: moves with its temperature, and over a few minutes it holds
SEGMENT_S = 300.0


@dataclasses.dataclass(frozen=True)
class DriftBias:
    """The bias found: ``bias_rads`` (3,) body (vqf's FLU axes) rad/s, along ``up`` (3,) the mean earth up axis in
    body axes (unit); ``sigma_rads`` its one-sigma uncertainty (rad/s); ``residual_rad`` the robust spread of the
    field's heading about the fitted drift (rad); with ``fit_drift``'s ``nuisance`` columns, their estimate ``nuisance``
    (K,) and its covariance (K, K), in the columns' units (else None)."""

    bias_rads: np.ndarray
    up: np.ndarray
    sigma_rads: float
    residual_rad: float
    nuisance: np.ndarray | None = None
    nuisance_covariance: np.ndarray | None = None

    @property
    def along_up_rads(self) -> float:
        """The bias about the up axis, rad/s (signed)."""
        return float(self.up @ self.bias_rads)


def up_in_body(quat_vqf: np.ndarray) -> np.ndarray:
    """(N, 3): the earth's up axis in body axes from vqf quaternions (N, 4) wxyz body -> ENU."""
    return quaternion_to_matrix(np.asarray(quat_vqf, dtype=float).reshape(-1, 4))[:, 2, :]


def field_angle_rad(quat_vqf: np.ndarray, field_vqf: np.ndarray) -> np.ndarray:
    """(N,) the field's angle (rad) about the earth's up axis in the frame of vqf quaternions (N, 4) wxyz body -> ENU,
    field (N, 3) body FLU; counter-clockwise from east. NaN where the field is zero (left out) or disturbed: its
    strength more than ``NORM_TH`` from the log's median, or its dip more than ``DIP_TH_DEG`` from the median dip
    (vqf's own thresholds for a disturbance, magNormTh and magDipTh). A steel door passed turns the field's angle by
    up to a whole turn, which would leave a step of 360 deg in the unwrapped drift (walk-texting past doors, seed 2027:
    offline heading 1.5 -> 12.3 deg before this)."""
    earth = np.einsum("nij,nj->ni", quaternion_to_matrix(np.asarray(quat_vqf, dtype=float).reshape(-1, 4)), field_vqf)
    angle = np.arctan2(earth[:, 1], earth[:, 0])
    norm = np.linalg.norm(earth, axis=1)
    known = norm > 0.0
    if not known.any():
        return np.full(len(angle), np.nan)
    dip = np.degrees(np.arcsin(np.clip(-earth[:, 2] / np.where(known, norm, 1.0), -1.0, 1.0)))
    usual = known & (np.abs(norm / np.median(norm[known]) - 1.0) <= NORM_TH)
    usual &= np.abs(dip - np.median(dip[known])) <= DIP_TH_DEG
    return np.where(usual, angle, np.nan)


def unwrapped(angle_rad: np.ndarray, period_s: float) -> np.ndarray:
    """The angles (N,) rad (NaN rows left out, returned NaN) made continuous: each taken within half a turn of the
    circular mean of the ``UNWRAP_S`` around it, that mean itself unwrapped. Unwrapping sample by sample would keep
    every whole turn a passing object makes the field's angle take (a steel door, 55 uT, on walk-texting past doors,
    seed 2027: a step of 360 deg for the rest of the log); this way such a turn is a stretch of outliers."""
    known = np.isfinite(angle_rad)
    cos = np.concatenate([[0.0], np.cumsum(np.where(known, np.cos(np.where(known, angle_rad, 0.0)), 0.0))])
    sin = np.concatenate([[0.0], np.cumsum(np.where(known, np.sin(np.where(known, angle_rad, 0.0)), 0.0))])
    half = max(1, round(UNWRAP_S / period_s / 2.0))
    index = np.arange(len(angle_rad))
    lo, hi = np.clip(index - half, 0, len(angle_rad)), np.clip(index + half + 1, 0, len(angle_rad))
    local = np.arctan2(sin[hi] - sin[lo], cos[hi] - cos[lo])
    out = np.full(len(angle_rad), np.nan)
    if known.any():
        centre = np.unwrap(local[known])
        out[known] = centre + np.remainder(angle_rad[known] - centre + np.pi, 2.0 * np.pi) - np.pi
    return out


def fit_drift(
    angle_rad: np.ndarray,
    up: np.ndarray,
    period_s: float,
    step_s: np.ndarray | None = None,
    min_span_s: float = MIN_SPAN_S,
    nuisance: np.ndarray | None = None,
    nuisance_sigma: float | np.ndarray = 1.0,
    correlation_s: float = CORRELATION_S,
    prior_dps: float = PRIOR_DPS,
) -> DriftBias | None:
    """The bias (see the module docstring) from the field's angle (N,) rad in a gyroscope-only attitude (NaN rows left
    out; wrapped or not) and that attitude's up axis (N, 3) in body axes, samples ``period_s`` apart (or, with
    ``step_s`` (N,), each that many seconds after the one before: ``period_s`` then their typical step). None when
    fewer than ``min_span_s`` seconds of field samples are given. ``nuisance`` (N, K): more columns of the design,
    each with a zero-mean prior of one sigma ``nuisance_sigma`` (scalar or (K,), the columns' units), fitted with the
    bias and marginalised out of its uncertainty (``causal_drift``: the heading errors a record's offset error
    makes, which a corner turns into a step of the angle). ``correlation_s``, ``prior_dps``: ``CORRELATION_S`` and
    ``PRIOR_DPS`` unless given."""
    known = np.isfinite(angle_rad)
    steps = np.full(len(angle_rad), period_s) if step_s is None else np.asarray(step_s, dtype=float)
    if float(steps[known].sum()) < min_span_s:
        return None
    drift = np.cumsum(up * steps[:, None], axis=0)
    psi = unwrapped(angle_rad, period_s)[known]
    columns = [np.ones(len(psi)), drift[known]]
    priors = [0.0, *([1.0 / math.radians(prior_dps) ** 2] * 3)]
    if nuisance is not None:
        extra = np.asarray(nuisance, dtype=float).reshape(len(angle_rad), -1)[known]
        columns.append(extra)
        sigmas = np.broadcast_to(np.asarray(nuisance_sigma, dtype=float), (extra.shape[1],))
        priors.extend((1.0 / sigmas**2).tolist())
    design = np.column_stack(columns)
    prior = np.diag(priors)
    per_sample = max(1.0, correlation_s / period_s)  # samples that count as one
    weights = np.ones(len(psi))
    spread = math.radians(3.0)
    solution = np.zeros(design.shape[1])
    covariance = np.eye(design.shape[1])
    for _ in range(6):
        weighted = design * weights[:, None]
        information = weighted.T @ design / (spread**2 * per_sample) + prior
        covariance = np.linalg.inv(information)
        solution = covariance @ (weighted.T @ psi) / (spread**2 * per_sample)
        residual = psi - design @ solution
        spread = max(1.4826 * float(np.median(np.abs(residual))), 1e-6)
        weights = np.minimum(1.0, HUBER_K * spread / np.maximum(np.abs(residual), 1e-12))
    mean_up = np.mean(up[known], axis=0)
    mean_up = mean_up / max(float(np.linalg.norm(mean_up)), 1e-12)
    sigma = float(np.sqrt(max(float(mean_up @ covariance[1:4, 1:4] @ mean_up), 0.0)))
    along = float(mean_up @ solution[1:4])
    if nuisance is None:
        return DriftBias(along * mean_up, mean_up, sigma, spread)
    return DriftBias(along * mean_up, mean_up, sigma, spread, solution[4:].copy(), covariance[4:, 4:].copy())


def learnt_at_rest(bias_sigma_rads: np.ndarray | float) -> bool:
    """Whether vqf's own uncertainty of its bias (rad/s; per sample: their median) says it learnt the bias on every
    axis (below ``MIN_SIGMA_DPS``): then it is left to vqf."""
    return float(np.median(np.asarray(bias_sigma_rads, dtype=float))) <= math.radians(MIN_SIGMA_DPS)


def offline_correction(
    gyr_vqf: np.ndarray,
    field_vqf: np.ndarray,
    period_s: float,
    params: dict[str, Any],
    first: Mapping[str, Any],
    lengthen: bool = True,
) -> tuple[np.ndarray, dict[str, Any], list[DriftBias]]:
    """For a whole log (vqf's frames, (N, 3) each; zero field rows left out) and vqf's offline outputs on it
    (``first``: its 6D attitude and bias uncertainty, which the field does not touch): (the gyroscope (N, 3) less
    the bias about the vertical, vqf's parameters, with ``lengthen`` tauMag ``TAU_MAG_FACTOR`` times longer, the bias
    found in each of the log's equal parts of at most ``SEGMENT_S``); the inputs unchanged (and no bias) where vqf
    learnt the bias itself or the log is too short. ``lengthen`` is for a filter whose tilt the accelerations bend:
    with the velocity taken off the accelerometer (a vehicle's GNSS) the field's heading has no tilt errors to average
    out, and tauMag is vqf's (the simulated multirotor of ``magnet bench motion``, aided: 0.10 deg with it, 0.23
    lengthened)."""
    if learnt_at_rest(first["biasSigma"]):
        return gyr_vqf, params, []
    quat = np.asarray(first["quat6D"], dtype=float)
    angle, up = field_angle_rad(quat, field_vqf), up_in_body(quat)
    parts = max(1, math.ceil(len(angle) * period_s / SEGMENT_S))
    bias = np.zeros_like(gyr_vqf)
    found = []
    for rows in np.array_split(np.arange(len(angle)), parts):
        part = fit_drift(angle[rows], up[rows], period_s)
        if part is not None:
            bias[rows] = part.bias_rads
            found.append(part)
    if not found:
        return gyr_vqf, params, []
    gyr = np.ascontiguousarray(gyr_vqf - bias)
    if not lengthen:
        return gyr, params, found
    tau_mag_s = float(params.get("tauMag", vqf.VQF(period_s).params["tauMag"])) * TAU_MAG_FACTOR
    return gyr, {**params, "tauMag": tau_mag_s}, found


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

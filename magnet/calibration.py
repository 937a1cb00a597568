"""Fitting a calibration B = A (u - b) to raw magnetometer samples (docs/design.md, "The calibration model").

Every method returns the same record (``magnet.model.Calibration``): ``offset`` b in the raw unit and ``matrix`` A
mapping raw units to the output unit. Each method first finds a *shape*: an offset b, a matrix S and a radius r (raw
unit) such that |S (u - b)| ~ r for the whole sphere (or the level circle); ``_finish`` then scales S to the output
unit:

- ``field_ut`` given (3D methods): A = S * field_ut / r, output uT, |B| = field_ut;
- else the raw unit converts to uT (ut, gauss, nt): A = S * (uT per unit), output uT, |B| = r in uT;
- else (counts): A = S, output in the raw unit, |B| = r.

Methods (``Method``):

- ``minmax2d`` (seed 001, eqs. 7-8), a level turn: Xsf = max(1, (Ymax - Ymin) / (Xmax - Xmin)), Ysf likewise;
  V' = V * sf + ((max - min)/2 - max) * sf = sf * (V - (max + min)/2), so b = ((Xmax + Xmin)/2, (Ymax + Ymin)/2, 0)
  and S = diag(Xsf, Ysf, 1). z is left uncorrected (offset 0, scale 1): a level turn never changes z, so the z hard
  iron cannot be told from the vertical Earth field; subtracting the mean z would erase the vertical field that tilt
  compensation needs. Use ``minmax2d`` for level headings only. r is the mean corrected horizontal radius.
- ``minmax`` (seeds 003, 004): b = (max + min)/2 per axis; S = diag(1, Ky, Kz) with Ky = (Xmax - Xmin)/(Ymax - Ymin),
  Kz = (Xmax - Xmin)/(Zmax - Zmin) (Kx = 1); r = (Xmax - Xmin)/2. With ``robust_extremes`` the extremes follow seed
  003's spike filter: in sample order, a sample beyond the current extreme moves it to 0.2 sample + 0.8 extreme.
- ``sphere``: linear least squares |u|^2 = 2 u.c + (r^2 - |c|^2); b = c, S = I.
- ``ellipsoid``: algebraic fit of the general quadric a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y
  + 2r z = 1 (9 parameters, on centred and normalised data), refused unless the quadric is an ellipsoid (its 3x3
  part positive definite and the right side after centring positive); then Levenberg-Marquardt on the radial
  residuals e_i = |M (u_i - b)| - 1 over b (3) and symmetric M (6) with the analytic Jacobian
  de/db = -M^T n_i, de/dM_jk = n_j d_k + n_k d_j (n_i = M d_i / |M d_i|, d_i = u_i - b). Then r = det(M)^(-1/3)
  (the geometric mean of the semi-axes) and S = r M (det S = 1). Outliers (spikes) are left out twice: before
  the fit, samples farther than 3x the median distance from the median sample; after it, samples whose radial
  residual lies beyond 6 robust sigmas (1.4826 MAD), followed by one more refinement. Neither drops more than 10 %.
- ``ellipsoid+align``: the ellipsoid, then the rotation R between the magnetometer and accelerometer frames so that
  the dip is constant: with g_i the gravity directions (-acc normalised) and m_i the corrected field directions,
  g_i . (R m_i) = sin(dip) for every i. Start: linear least squares for N with g_i^T N m_i = 1, R0 = nearest
  rotation (SVD) to +-N; then Gauss-Newton on (rotation vector w, constant k): R <- R exp([w]x), residual
  g_i . (R m_i) - k, Jacobian row (m_i x R^T g_i, -1). A becomes R S. When the gravity directions do not span the
  sphere (smallest eigenvalue of their scatter < ``MIN_GRAVITY_SPREAD``) or the Jacobian is ill-conditioned, R = I
  and the note says alignment was not observable.
- ``turntable``: see ``magnet.turntable`` (needs the mounting and table angle of every sample).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Callable

import numpy as np

from magnet.model import IDENTITY, Calibration, Quality
from magnet.quality import GateThresholds, Geometry, assess, gate, motion, scatter_condition, ut_per_unit


class Method(enum.Enum):
    MINMAX2D = "minmax2d"
    MINMAX = "minmax"
    SPHERE = "sphere"
    ELLIPSOID = "ellipsoid"
    ELLIPSOID_ALIGN = "ellipsoid+align"
    TURNTABLE = "turntable"

    @classmethod
    def parse(cls, value: Method | str) -> Method:
        if isinstance(value, cls):
            return value
        try:
            return cls(str(value).strip().lower())
        except ValueError:
            choices = ", ".join(m.value for m in cls)
            raise ValueError(f"unknown calibration method {value!r}: use one of {choices}") from None


class FitError(ValueError):
    """No calibration can be computed from these samples; the message says why and what to do."""


#: fewest samples each method accepts (several times its parameter count, so that noise averages out)
MIN_SAMPLES: dict[Method, int] = {
    Method.MINMAX2D: 8,
    Method.MINMAX: 12,
    Method.SPHERE: 12,
    Method.ELLIPSOID: 30,
    Method.ELLIPSOID_ALIGN: 50,
}
#: beyond this scatter condition (widest / thinnest spread of the raw cloud) a 3D fit is refused outright
MAX_SCATTER_FOR_3D = 50.0
#: smallest eigenvalue of the scatter of gravity directions (1/3 for the whole sphere) below which R is unobservable
MIN_GRAVITY_SPREAD = 0.02
#: largest condition number of the alignment Gauss-Newton normal matrix
MAX_ALIGN_CONDITION = 1e6
#: a sample farther from the median sample than this many times the median distance is a spike (before any fit)
GROSS_OUTLIER_FACTOR = 3.0
#: after the fit, samples whose radial residual is beyond this many robust sigmas are left out and the fit refined
OUTLIER_SIGMAS = 6.0
#: outlier rejection never drops more than this fraction of the samples (beyond it the data are not "mostly good")
MAX_OUTLIER_FRACTION = 0.1
#: samples are taken in blocks of HOLDOUT_BLOCK; every HOLDOUT_EVERY-th block is held out to score the fit on data
#: it did not see (blocks, not single samples: neighbours in time are nearly the same reading)
HOLDOUT_BLOCK = 20
HOLDOUT_EVERY = 5


@dataclasses.dataclass(frozen=True)
class Shape:
    """What a method found, before scaling to the output unit: |matrix @ (u - offset)| ~ radius (raw unit)."""

    offset: np.ndarray
    matrix: np.ndarray
    radius: float
    note: str = ""


# ----------------------------------------------------------------------------------------------- input checks


def _check_samples(mag: np.ndarray, method: Method) -> np.ndarray:
    arr = np.asarray(mag, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FitError(f"samples must be an (N, 3) array of x, y, z readings, got shape {arr.shape}")
    bad = ~np.all(np.isfinite(arr), axis=1)
    if bad.any():
        raise FitError(
            f"{int(bad.sum())} sample(s) hold NaN or infinite values (first at row {int(np.argmax(bad))}):"
            " drop them (sensor overflow?) before fitting"
        )
    need = MIN_SAMPLES.get(method, 12)
    if len(arr) < need:
        raise FitError(
            f"only {len(arr)} samples: {method.value} needs at least {need}; keep sampling while you move the device"
        )
    return arr


def _check_spread_3d(mag: np.ndarray, method: Method) -> None:
    condition = scatter_condition(mag)
    if condition > MAX_SCATTER_FOR_3D:
        raise FitError(
            f"samples are coplanar or degenerate (scatter condition {condition:.3g}): {method.value} "
            "needs samples from all attitudes; tumble the device, or use minmax2d for a level turn"
        )


def _check_acc(acc: np.ndarray | None, n: int, required: bool) -> np.ndarray | None:
    if acc is None:
        if required:
            raise FitError("ellipsoid+align needs accelerometer samples (acc) beside the magnetometer samples")
        return None
    arr = np.asarray(acc, dtype=float)
    if arr.shape != (n, 3):
        raise FitError(f"acc must have the shape of the magnetometer samples ({n}, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise FitError("acc holds NaN or infinite values: drop those rows from both arrays before fitting")
    return arr


# ----------------------------------------------------------------------------------------------- the methods


def _minmax2d(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    lo, hi = _extremes(mag, robust)
    span = hi - lo
    if np.any(span[:2] <= 0):
        raise FitError("x or y never changes: turn the device a full circle while level")
    x_sf = max(1.0, span[1] / span[0])
    y_sf = max(1.0, span[0] / span[1])
    offset = np.array([(hi[0] + lo[0]) / 2, (hi[1] + lo[1]) / 2, 0.0])
    matrix = np.diag([x_sf, y_sf, 1.0])
    radius = float(np.linalg.norm(((mag - offset) @ matrix.T)[:, :2], axis=1).mean())
    return Shape(offset, matrix, radius, "z left uncorrected: a level turn cannot calibrate z")


def _minmax(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    _check_spread_3d(mag, Method.MINMAX)
    lo, hi = _extremes(mag, robust)
    span = hi - lo
    return Shape((hi + lo) / 2, np.diag(span[0] / span), float(span[0] / 2))


def _extremes(mag: np.ndarray, robust: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (min, max), shape (3,) each; robust: seed 003's pull of 0.2 new + 0.8 old on each new extreme."""
    if not robust:
        return mag.min(axis=0), mag.max(axis=0)
    lo, hi = mag[0].tolist(), mag[0].tolist()
    for row in mag[1:].tolist():
        for k in range(3):
            value = row[k]
            if value < lo[k]:
                lo[k] = 0.2 * value + 0.8 * lo[k]
            elif value > hi[k]:
                hi[k] = 0.2 * value + 0.8 * hi[k]
    return np.array(lo), np.array(hi)


def _sphere(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    _check_spread_3d(mag, Method.SPHERE)
    mean = mag.mean(axis=0)
    d = mag - mean
    design = np.column_stack([2 * d, np.ones(len(d))])
    sol, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", d, d), rcond=None)
    centre = sol[:3]
    radius_sq = sol[3] + centre @ centre
    if radius_sq <= 0:
        raise FitError("sphere fit failed (negative radius): the samples do not surround a centre; tumble the device")
    return Shape(centre + mean, np.eye(3), float(math.sqrt(radius_sq)))


def _ellipsoid(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    _check_spread_3d(mag, Method.ELLIPSOID)
    keep = _gross_inliers(mag)
    offset, shape = _algebraic_ellipsoid(mag[keep])
    offset, shape = _refine_ellipsoid(mag[keep], offset, shape)
    inliers = _radial_inliers(mag, offset, shape)
    if not np.array_equal(inliers, keep):
        offset, shape = _refine_ellipsoid(mag[inliers], offset, shape)
    dropped = int((~inliers).sum())
    radius = float(np.linalg.det(shape) ** (-1.0 / 3.0))
    note = f"{dropped} outlier sample(s) left out of the fit" if dropped else ""
    return Shape(offset, shape * radius, radius, note)


def _gross_inliers(mag: np.ndarray) -> np.ndarray:
    """(N,) bool: samples within GROSS_OUTLIER_FACTOR times the median distance from the median sample (spikes out).

    On an ellipsoid the distances from a point near its centre are all of the order of its radius, so a spike of a
    few radii stands out even before any fit. All samples are kept when more than MAX_OUTLIER_FRACTION would go.
    """
    distance = np.linalg.norm(mag - np.median(mag, axis=0), axis=1)
    keep = distance <= GROSS_OUTLIER_FACTOR * np.median(distance)
    return keep if keep.mean() >= 1 - MAX_OUTLIER_FRACTION else np.ones(len(mag), dtype=bool)


def _radial_inliers(mag: np.ndarray, offset: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(N,) bool: radial residuals within OUTLIER_SIGMAS robust sigmas (1.4826 MAD) of their median."""
    res = np.linalg.norm((mag - offset) @ shape, axis=1) - 1.0
    deviation = np.abs(res - np.median(res))
    sigma = 1.4826 * np.median(deviation)
    keep = deviation <= OUTLIER_SIGMAS * max(sigma, 1e-12)
    return keep if keep.mean() >= 1 - MAX_OUTLIER_FRACTION else np.ones(len(mag), dtype=bool)


def _algebraic_ellipsoid(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre b (3,) and symmetric M (3,3) with |M (u - b)| = 1 on the quadric fitted by linear least squares."""
    mean = mag.mean(axis=0)
    scale = float(np.sqrt(((mag - mean) ** 2).sum(axis=1).mean()))
    x, y, z = ((mag - mean) / scale).T
    design = np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z])
    p, *_ = np.linalg.lstsq(design, np.ones(len(x)), rcond=None)
    quad = np.array([[p[0], p[5], p[4]], [p[5], p[1], p[3]], [p[4], p[3], p[2]]])
    eig = np.linalg.eigvalsh(quad)
    if eig[0] <= 0:
        raise FitError(
            "the samples do not lie on an ellipsoid (the fitted quadric is a hyperboloid or paraboloid): "
            "check for a moving magnet or saturated readings, and tumble the device through all attitudes"
        )
    centre = -np.linalg.solve(quad, p[6:])
    level = 1.0 + centre @ quad @ centre
    if level <= 0:
        raise FitError("the fitted quadric is empty (not an ellipsoid): the samples are inconsistent; sample again")
    w, v = np.linalg.eigh(quad / level)
    shape = (v * np.sqrt(w)) @ v.T / scale
    return centre * scale + mean, shape


def _sym_from(params: np.ndarray) -> np.ndarray:
    a, b, c, d, e, f = params
    return np.array([[a, d, e], [d, b, f], [e, f, c]])


def _refine_ellipsoid(
    mag: np.ndarray, offset: np.ndarray, shape: np.ndarray, iterations: int = 30
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on e_i = |M (u_i - b)| - 1 over b and symmetric M (see the module docstring)."""
    params = np.concatenate([offset, shape[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]])
    cost, jac, res = _ellipsoid_system(mag, params)
    damping = 1e-3
    for _ in range(iterations):
        jtj, jtr = jac.T @ jac, jac.T @ res
        step = np.linalg.solve(jtj + damping * np.diag(np.diag(jtj)), -jtr)
        trial = params + step
        trial_cost, trial_jac, trial_res = _ellipsoid_system(mag, trial)
        if trial_cost < cost:
            converged = cost - trial_cost < 1e-12 * cost
            params, cost, jac, res = trial, trial_cost, trial_jac, trial_res
            damping = max(damping / 10, 1e-9)
            if converged:
                break
        else:
            damping *= 10
            if damping > 1e8:
                break
    matrix = _sym_from(params[3:])
    if np.linalg.eigvalsh(matrix)[0] <= 0:
        raise FitError("ellipsoid refinement diverged: the samples are too noisy or too few directions; sample again")
    return params[:3], matrix


def _ellipsoid_system(mag: np.ndarray, params: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(cost, Jacobian (N, 9), residuals (N,)) of the radial residuals at params (b (3), M upper triangle (6))."""
    d = mag - params[:3]
    v = d @ _sym_from(params[3:])  # M symmetric: rows of d @ M = (M d_i)^T
    norm = np.linalg.norm(v, axis=1)
    res = norm - 1.0
    n = v / norm[:, None]
    jac = np.empty((len(mag), 9))
    jac[:, :3] = -(n @ _sym_from(params[3:]))
    jac[:, 3:6] = n * d
    jac[:, 6] = n[:, 0] * d[:, 1] + n[:, 1] * d[:, 0]
    jac[:, 7] = n[:, 0] * d[:, 2] + n[:, 2] * d[:, 0]
    jac[:, 8] = n[:, 1] * d[:, 2] + n[:, 2] * d[:, 1]
    return float(res @ res), jac, res


def _ellipsoid_align(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    if acc is None:
        raise FitError("ellipsoid+align needs accelerometer samples (ax, ay, az) beside the field")
    base = _ellipsoid(mag, acc, robust)
    gravity = -acc / np.linalg.norm(acc, axis=1, keepdims=True)
    field = (mag - base.offset) @ base.matrix.T
    field /= np.linalg.norm(field, axis=1, keepdims=True)
    rotation, why_not = align_rotation(field, gravity)
    if rotation is None:
        return dataclasses.replace(
            base, note=_join(base.note, f"alignment not observable: {why_not}; kept the plain ellipsoid")
        )
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(rotation) - 1) / 2))))
    return dataclasses.replace(
        base,
        matrix=rotation @ base.matrix,
        note=_join(base.note, f"magnetometer-accelerometer misalignment {angle:.2f} deg corrected"),
    )


def _join(*notes: str) -> str:
    return "; ".join(note for note in notes if note)


def _gravity_spread(gravity: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(gravity.T @ gravity / len(gravity))[0])


def align_rotation(
    field_dir: np.ndarray, gravity_dir: np.ndarray, iterations: int = 20
) -> tuple[np.ndarray | None, str]:
    """Rotation R (3,3) so that gravity_dir_i . (R field_dir_i) is the same for all i (both (N,3), unit rows).

    Returns (R, "") or (None, why it is not observable).
    """
    spread = _gravity_spread(gravity_dir)
    if spread < MIN_GRAVITY_SPREAD:
        return None, (
            f"gravity directions do not span the sphere (smallest spread {spread:.3f} < "
            f"{MIN_GRAVITY_SPREAD}); tilt and roll the device through all attitudes"
        )
    rotation = _initial_rotation(field_dir, gravity_dir)
    k = float(np.mean(np.einsum("ij,ij->i", gravity_dir, field_dir @ rotation.T)))
    for _ in range(iterations):
        rotated = field_dir @ rotation.T
        res = np.einsum("ij,ij->i", gravity_dir, rotated) - k
        jac = np.column_stack([np.cross(field_dir, gravity_dir @ rotation), -np.ones(len(res))])
        normal = jac.T @ jac
        if np.linalg.cond(normal) > MAX_ALIGN_CONDITION:
            return None, "the rotation is ill-conditioned for these attitudes; tumble the device more widely"
        step = np.linalg.solve(normal, -jac.T @ res)
        rotation = rotation @ _exp_so3(step[:3])
        k += step[3]
        if np.linalg.norm(step[:3]) < 1e-10:
            break
    return rotation, ""


def _initial_rotation(field_dir: np.ndarray, gravity_dir: np.ndarray) -> np.ndarray:
    """Nearest rotation to N (or -N, the southern hemisphere) from the least squares g_i^T N m_i = 1."""
    design = np.einsum("ij,ik->ijk", gravity_dir, field_dir).reshape(len(field_dir), 9)
    n_vec, *_ = np.linalg.lstsq(design, np.ones(len(field_dir)), rcond=None)
    n_mat = n_vec.reshape(3, 3)
    if np.linalg.det(n_mat) < 0:
        n_mat = -n_mat
    u, _, vt = np.linalg.svd(n_mat)
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:  # the dip is near zero and N is noise: start from no rotation
        return np.eye(3)
    return rotation


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix exp([w]x) for a rotation vector w (rad), Rodrigues' formula."""
    theta = float(np.linalg.norm(w))
    skew = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + skew
    return np.eye(3) + math.sin(theta) / theta * skew + (1 - math.cos(theta)) / theta**2 * skew @ skew


def _turntable(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    raise FitError(
        "the turntable method needs the mounting and table angle of every sample: use magnet.turntable.fit_turntable"
    )


#: Method -> (shape function (mag, acc, robust) -> Shape, geometry the samples are judged by)
_METHODS: dict[Method, tuple[Callable[[np.ndarray, np.ndarray | None, bool], Shape], Geometry]] = {
    Method.MINMAX2D: (_minmax2d, Geometry.CIRCLE),
    Method.MINMAX: (_minmax, Geometry.SPHERE),
    Method.SPHERE: (_sphere, Geometry.SPHERE),
    Method.ELLIPSOID: (_ellipsoid, Geometry.SPHERE),
    Method.ELLIPSOID_ALIGN: (_ellipsoid_align, Geometry.SPHERE),
    Method.TURNTABLE: (_turntable, Geometry.TURNTABLE),
}


# ----------------------------------------------------------------------------------------------- the entry point


def _finish(shape: Shape, method: Method, unit: str, field_ut: float | None, count: int) -> Calibration:
    """Scale the shape to the output unit (see the module docstring) and make the record."""
    to_ut = ut_per_unit(unit)
    if field_ut is not None and method is not Method.MINMAX2D:
        factor, output_unit, strength = field_ut / shape.radius, "ut", field_ut
    elif to_ut is not None:
        factor, output_unit, strength = to_ut, "ut", shape.radius * to_ut
    else:
        factor, output_unit, strength = 1.0, unit, shape.radius
    if method is Method.MINMAX2D:
        strength = 0.0  # the horizontal radius is not |B|: the total field is unknown from a level turn
    return Calibration(
        method=method.value,
        offset=shape.offset,
        matrix=shape.matrix * factor,
        field_strength=float(strength),
        sample_count=count,
        unit=unit,
        output_unit=output_unit,
    )


def fit_shape(
    mag: np.ndarray,
    method: Method | str,
    *,
    acc: np.ndarray | None = None,
    unit: str = "ut",
    field_ut: float | None = None,
    robust_extremes: bool = False,
) -> tuple[Calibration, Shape]:
    """The fit alone, without quality or gate: (record with empty quality, the shape found). Raises FitError."""
    method = Method.parse(method)
    mag = _check_samples(mag, method)
    acc = _check_acc(acc, len(mag), method is Method.ELLIPSOID_ALIGN)
    if field_ut is not None and not (math.isfinite(field_ut) and field_ut > 0):
        raise FitError(f"expected field strength must be a positive number of uT, got {field_ut!r}")
    function, _ = _METHODS[method]
    shape = function(mag, acc, robust_extremes)
    return _finish(shape, method, unit, field_ut, len(mag)), shape


def fit(
    mag: np.ndarray,
    method: Method | str,
    *,
    acc: np.ndarray | None = None,
    unit: str = "ut",
    field_ut: float | None = None,
    gate: GateThresholds | None = None,
    robust_extremes: bool = False,
    gyr: np.ndarray | None = None,
    period_s: float | None = None,
    reference: Calibration | None = None,
) -> Calibration:
    """Fit a calibration to raw samples mag (N, 3) in ``unit``; acc (N, 3) specific force, any unit, or None.

    field_ut: the expected |B| in uT (WMM) or None (keep the fitted radius). Returns the record with ``quality``
    (``magnet.quality.assess``, including a held-out residual: every 5th block of 20 samples is left out of a
    second fit and scored) and ``accepted``/``reason`` from ``magnet.quality.gate`` (``gate=None``: default thresholds).
    With acc, the dip and the consistency figures of ``magnet.quality.motion``: gyr (N, 3) rad/s sampled every
    period_s seconds gives the fused gravity and attitude, else the quasi-static samples are used; the fit must make
    the field more constant than ``reference`` (the calibration in force; None: no calibration) on held-out data.
    Raises FitError when no calibration can be computed.
    """
    method = Method.parse(method)
    calibration, shape = fit_shape(mag, method, acc=acc, unit=unit, field_ut=field_ut, robust_extremes=robust_extremes)
    mag = np.asarray(mag, dtype=float)
    acc_arr = None if acc is None else np.asarray(acc, dtype=float)
    holdout = _holdout(mag, method, acc_arr, unit, field_ut, robust_extremes)
    to_ut = ut_per_unit(unit)
    geometry = _METHODS[method][1]
    quality = assess(
        mag,
        calibration,
        geometry=geometry,
        acc=None,
        expected_field_ut=field_ut,
        fitted_radius_ut=shape.radius * to_ut if to_ut is not None and geometry is Geometry.SPHERE else None,
        holdout=holdout,
    )
    if acc_arr is not None and geometry is Geometry.SPHERE:
        ev = _motion_evidence(acc_arr, gyr, period_s, len(mag))
        figures = motion.motion_figures(
            mag,
            calibration,
            ev,
            _holdout_mask(len(mag)),
            holdout[1] if holdout else None,
            reference or IDENTITY,
            "the calibration in force" if reference else "no calibration",
        )
        quality = dataclasses.replace(quality, dip_spread_deg=figures.pop("dip_spread_deg")).with_extra(**figures)
    if shape.note:
        quality = quality.with_extra(note=shape.note)
    accepted, reason = _gate(quality, gate)
    if shape.note:
        reason = f"{reason}; {shape.note}"
    return calibration.replace(quality=quality, accepted=accepted, reason=reason)


def _motion_evidence(acc: np.ndarray, gyr: np.ndarray | None, period_s: float | None, n: int) -> motion.MotionEvidence:
    if gyr is not None and np.shape(gyr) != (n, 3):
        raise FitError(f"gyr must have the shape of the magnetometer samples ({n}, 3), got {np.shape(gyr)}")
    try:
        return motion.evidence(acc, gyr, period_s)
    except ValueError as exc:
        raise FitError(str(exc)) from None


def _gate(quality: Quality, thresholds: GateThresholds | None) -> tuple[bool, str]:
    return gate(quality, thresholds or GateThresholds())


def _holdout_mask(count: int) -> np.ndarray:
    """(count,) bool: every HOLDOUT_EVERY-th block of HOLDOUT_BLOCK samples, the held-out test set."""
    return (np.arange(count) // HOLDOUT_BLOCK) % HOLDOUT_EVERY == HOLDOUT_EVERY - 1


def _holdout(
    mag: np.ndarray, method: Method, acc: np.ndarray | None, unit: str, field_ut: float | None, robust: bool
) -> tuple[np.ndarray, Calibration] | None:
    """(test samples, calibration fitted on the rest): every HOLDOUT_EVERY-th block of samples is the test set."""
    test = _holdout_mask(len(mag))
    try:
        train_cal, _ = fit_shape(
            mag[~test],
            method,
            acc=None if acc is None else acc[~test],
            unit=unit,
            field_ut=field_ut,
            robust_extremes=robust,
        )
    except FitError:
        return None
    return mag[test], train_cal

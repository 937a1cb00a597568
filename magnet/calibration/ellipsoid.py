"""The ``ellipsoid`` method: hard and soft iron from a tumbled device.

- ``ellipsoid``: algebraic fit of the general quadric a x^2 + b y^2 + c z^2 + 2f yz + 2g xz + 2h xy + 2p x + 2q y
  + 2r z = 1 (9 parameters, on centred and normalised data), refused unless the quadric is an ellipsoid (its 3x3
  part positive definite and the right side after centring positive); then Levenberg-Marquardt on the radial
  residuals e_i = |M (u_i - b)| - 1 over b (3) and symmetric M (6) with the analytic Jacobian
  de/db = -M^T n_i, de/dM_jk = n_j d_k + n_k d_j (n_i = M d_i / |M d_i|, d_i = u_i - b). Then r = det(M)^(-1/3)
  (the geometric mean of the semi-axes) and S = r M (det S = 1). Outliers (spikes) are left out twice: before
  the fit, samples farther than 3x the median distance from the median sample; after it, samples whose radial
  residual lies beyond 6 robust sigmas (1.4826 MAD), followed by one more refinement. Neither drops more than 10 %.
"""

from __future__ import annotations

import numpy as np

from magnet.calibration.base import FitError, Method, Shape, check_spread_3d

#: a sample farther from the median sample than this many times the median distance is a spike (before any fit)
GROSS_OUTLIER_FACTOR = 3.0
#: after the fit, samples whose radial residual is beyond this many robust sigmas are left out and the fit refined
OUTLIER_SIGMAS = 6.0
#: outlier rejection never drops more than this fraction of the samples (beyond it the data are not "mostly good")
MAX_OUTLIER_FRACTION = 0.1


def ellipsoid(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    check_spread_3d(mag, Method.ELLIPSOID)
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

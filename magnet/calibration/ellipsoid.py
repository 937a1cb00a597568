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
from magnet.quality.stats import column_medians, median, take_rows

#: a sample farther from the median sample than this many times the median distance is a spike (before any fit)
GROSS_OUTLIER_FACTOR = 3.0
#: after the fit, samples whose radial residual is beyond this many robust sigmas are left out and the fit refined
OUTLIER_SIGMAS = 6.0
#: outlier rejection never drops more than this fraction of the samples (beyond it the data are not "mostly good")
MAX_OUTLIER_FRACTION = 0.1
#: the refinement stops when a step lowers the sum of squared residuals by less than this fraction of it
TOLERANCE = 1e-12


def ellipsoid(
    mag: np.ndarray,
    acc: np.ndarray | None,
    robust: bool,
    start: Shape | None = None,
    tolerance: float = TOLERANCE,
) -> Shape:
    """The ellipsoid of mag (N, 3) (see the module docstring). ``start``: a shape found on nearly the same samples
    (the fit of all of them, for the held-out fit of most of them): Levenberg-Marquardt starts from it instead of the
    algebraic fit and finds the same minimum in fewer steps. ``tolerance``: see ``_refine_ellipsoid``."""
    check_spread_3d(mag, Method.ELLIPSOID)
    keep = _gross_inliers(mag)
    kept = mag if keep.all() else take_rows(mag, keep)
    offset, shape = _algebraic_ellipsoid(kept) if start is None else _unit_sphere_form(start)
    offset, shape = _refine_ellipsoid(kept, offset, shape, tolerance=tolerance)
    inliers = _radial_inliers(mag, offset, shape)
    if not np.array_equal(inliers, keep):
        offset, shape = _refine_ellipsoid(take_rows(mag, inliers), offset, shape, tolerance=tolerance)
    dropped = int((~inliers).sum())
    radius = float(np.linalg.det(shape) ** (-1.0 / 3.0))
    note = f"{dropped} outlier sample(s) left out of the fit" if dropped else ""
    return Shape(offset, shape * radius, radius, note)


def _unit_sphere_form(shape: Shape) -> tuple[np.ndarray, np.ndarray]:
    """(b (3,), symmetric M (3, 3)) with |M (u - b)| = 1 on the ellipsoid of ``shape`` (its matrix / radius; a
    rotation in front, as ellipsoid+align puts there, is taken off: M is the symmetric factor of the polar
    decomposition)."""
    matrix = shape.matrix / shape.radius
    w, v = np.linalg.eigh(matrix.T @ matrix)
    return np.asarray(shape.offset, dtype=float), (v * np.sqrt(np.maximum(w, 0.0))) @ v.T


def _gross_inliers(mag: np.ndarray) -> np.ndarray:
    """(N,) bool: samples within GROSS_OUTLIER_FACTOR times the median distance from the median sample (spikes out).

    On an ellipsoid the distances from a point near its centre are all of the order of its radius, so a spike of a
    few radii stands out even before any fit. All samples are kept when more than MAX_OUTLIER_FRACTION would go.
    """
    distance = _row_norms(mag - column_medians(mag))
    keep = distance <= GROSS_OUTLIER_FACTOR * median(distance)
    return keep if keep.mean() >= 1 - MAX_OUTLIER_FRACTION else np.ones(len(mag), dtype=bool)


def _row_norms(rows: np.ndarray) -> np.ndarray:
    """(N,) Euclidean lengths of the rows of an (N, 3) array (several times faster than ``np.linalg.norm``)."""
    return np.sqrt(np.einsum("ij,ij->i", rows, rows))


def _radial_inliers(mag: np.ndarray, offset: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(N,) bool: radial residuals within OUTLIER_SIGMAS robust sigmas (1.4826 MAD) of their median."""
    res = _row_norms((mag - offset) @ shape) - 1.0
    deviation = np.abs(res - median(res))
    sigma = 1.4826 * median(deviation)
    keep = deviation <= OUTLIER_SIGMAS * max(sigma, 1e-12)
    return keep if keep.mean() >= 1 - MAX_OUTLIER_FRACTION else np.ones(len(mag), dtype=bool)


def _algebraic_ellipsoid(mag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre b (3,) and symmetric M (3,3) with |M (u - b)| = 1 on the quadric fitted by linear least squares."""
    columns = np.ascontiguousarray(mag.T)  # (3, N)
    mean = columns.mean(axis=1)
    centred = columns - mean[:, None]
    scale = float(np.sqrt(np.einsum("ij,ij->", centred, centred) / len(mag)))
    x, y, z = centred / scale
    design_t = np.array([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z])  # (9, N)
    try:  # normal equations: the data are centred and scaled, so the 9x9 system is well conditioned
        p = np.linalg.solve(design_t @ design_t.T, design_t.sum(axis=1))
    except np.linalg.LinAlgError:
        p, *_ = np.linalg.lstsq(design_t.T, np.ones(len(x)), rcond=None)
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
    mag: np.ndarray, offset: np.ndarray, shape: np.ndarray, iterations: int = 30, tolerance: float = TOLERANCE
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on e_i = |M (u_i - b)| - 1 over b and symmetric M (see the module docstring), until a
    step lowers the cost by less than ``tolerance`` of it (the residuals are not zero, so Gauss-Newton converges
    linearly here: each step gains about 30x, and what is left after the last is below a thirtieth of its gain)."""
    params = np.concatenate([offset, shape[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]])
    columns = np.ascontiguousarray(mag.T)  # (3, N): every per-sample quantity below is a contiguous row
    cost, jtj, jtr = _ellipsoid_system(columns, params)
    damping = 1e-3
    for _ in range(iterations):
        step = np.linalg.solve(jtj + damping * np.diag(np.diag(jtj)), -jtr)
        trial = params + step
        trial_cost, trial_jtj, trial_jtr = _ellipsoid_system(columns, trial)
        if trial_cost < cost:
            converged = cost - trial_cost < tolerance * cost
            params, cost, jtj, jtr = trial, trial_cost, trial_jtj, trial_jtr
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


#: samples per block of the normal equations: one block (K: 9 x 16384 doubles, 1.2 MB) for the 10,000 samples of a
#: usual fit (measured: one product there is faster than blocks of 4,096), bounded memory for long recordings
SYSTEM_BLOCK = 16384


def _ellipsoid_system(columns: np.ndarray, params: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(cost, J^T J (9, 9), J^T e (9,)) of the radial residuals e at params (b (3), M upper triangle (6)) for the
    samples ``columns`` (3, N), SYSTEM_BLOCK samples at a time. J (N, 9) is the analytic Jacobian of the module
    docstring; its rows for b are -M n_i, so with K (9, N) the rows n_i and then those for M, J^T = T K for
    T = diag(-M, I_6): J^T J = T (K K^T) T^T and J^T e = T (K e), and the product M n of every sample is not formed."""
    matrix = _sym_from(params[3:])
    cost, kkt, ke = 0.0, np.zeros((9, 9)), np.zeros(9)
    k = np.empty((9, min(SYSTEM_BLOCK, columns.shape[1])))
    for start in range(0, columns.shape[1], SYSTEM_BLOCK):
        d = columns[:, start : start + SYSTEM_BLOCK] - params[:3, None]
        v = matrix @ d  # (3, n): M d_i
        norm = np.sqrt(np.einsum("ij,ij->j", v, v))
        res = norm - 1.0
        block = k[:, : d.shape[1]]
        n = np.divide(v, norm, out=block[:3])
        np.multiply(n, d, out=block[3:6])
        np.multiply(n[0], d[1], out=block[6])
        block[6] += n[1] * d[0]
        np.multiply(n[0], d[2], out=block[7])
        block[7] += n[2] * d[0]
        np.multiply(n[1], d[2], out=block[8])
        block[8] += n[2] * d[1]
        cost += float(res @ res)
        kkt += _gram(block)
        ke += block @ res
    transform = np.eye(9)
    transform[:3, :3] = -matrix
    return cost, transform @ kkt @ transform.T, transform @ ke


def _gram(rows: np.ndarray) -> np.ndarray:
    """rows @ rows.T ((k, k) of rows (k, n), k > 3) as two products: numpy hands ``a @ a.T`` to BLAS's syrk, which
    is slower than two general products for a few rows of thousands of samples (measured: 9 x 10,000, 70 vs 120 us)."""
    gram = np.empty((len(rows), len(rows)))
    np.matmul(rows[:3], rows.T, out=gram[:3])
    np.matmul(rows[3:], rows.T, out=gram[3:])
    return gram

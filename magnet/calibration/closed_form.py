"""Closed-form methods: min/max extremes and the least-squares sphere.

- ``minmax2d`` (seed 001, eqs. 7-8), a level turn: Xsf = max(1, (Ymax - Ymin) / (Xmax - Xmin)), Ysf likewise;
  V' = V * sf + ((max - min)/2 - max) * sf = sf * (V - (max + min)/2), so b = ((Xmax + Xmin)/2, (Ymax + Ymin)/2, 0)
  and S = diag(Xsf, Ysf, 1). z is left uncorrected (offset 0, scale 1): a level turn never changes z, so the z hard
  iron cannot be told from the vertical Earth field; subtracting the mean z would erase the vertical field that tilt
  compensation needs. Use ``minmax2d`` for level headings only. r is the mean corrected horizontal radius.
- ``minmax`` (seeds 003, 004): b = (max + min)/2 per axis; S = diag(1, Ky, Kz) with Ky = (Xmax - Xmin)/(Ymax - Ymin),
  Kz = (Xmax - Xmin)/(Zmax - Zmin) (Kx = 1); r = (Xmax - Xmin)/2. With ``robust_extremes`` the extremes follow seed
  003's spike filter: in sample order, a sample beyond the current extreme moves it to 0.2 sample + 0.8 extreme.
- ``sphere``: linear least squares |u|^2 = 2 u.c + (r^2 - |c|^2); b = c, S = I.
"""

from __future__ import annotations

import math

import numpy as np

from magnet.calibration.base import FitError, Method, Shape, check_spread_3d


def minmax2d(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
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


def minmax(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    check_spread_3d(mag, Method.MINMAX)
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


def sphere(mag: np.ndarray, acc: np.ndarray | None, robust: bool) -> Shape:
    check_spread_3d(mag, Method.SPHERE)
    mean = mag.mean(axis=0)
    d = mag - mean
    design = np.column_stack([2 * d, np.ones(len(d))])
    sol, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", d, d), rcond=None)
    centre = sol[:3]
    radius_sq = sol[3] + centre @ centre
    if radius_sq <= 0:
        raise FitError("sphere fit failed (negative radius): the samples do not surround a centre; tumble the device")
    return Shape(centre + mean, np.eye(3), float(math.sqrt(radius_sq)))

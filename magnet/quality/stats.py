"""Order statistics and moments the fits and figures take of thousands of samples, computed the fast way.

``median`` and ``column_medians`` (numpy's medians bit for bit, one partition each) live in
``magnet.order_stats``, which imports numpy alone, and are named here too.
``np.cov`` of an (N, 3) array copies and reduces it in its row layout; ``covariance`` works on the three contiguous
columns (the same covariance to within a few units in the last place). ``rows[mask]`` of an (N, 3) array copies
row by row through numpy's general boolean indexing, several times slower than ``np.compress`` (``take_rows``), which
copies the same rows.
"""

from __future__ import annotations

import numpy as np

from magnet.order_stats import column_medians, median

__all__ = ["column_medians", "covariance", "median", "take_rows"]


def covariance(points: np.ndarray) -> np.ndarray:
    """(d, d) sample covariance (divided by N - 1) of points (N, d), N >= 2, as ``np.cov(points, rowvar=False)``."""
    columns = np.ascontiguousarray(np.asarray(points, dtype=float).T)
    centred = columns - columns.mean(axis=1, keepdims=True)
    return (centred @ centred.T) * (1.0 / (len(points) - 1))


def take_rows(rows: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``rows[mask]`` for an array (N, ...) and a bool mask (N,): the same copy, faster (see the module docstring)."""
    return np.compress(mask, rows, axis=0)

"""Order statistics and moments the fits and figures take of thousands of samples, computed the fast way.

``np.median`` partitions at both middle ranks and at the last one (to find NaN), several times slower than one
partition; ``median`` here gives the same number (bit for bit: the middle value, or the mean of the two middle values
(a + b) / 2) from one partition at n // 2, whose lower part holds the other middle value as its largest.
``np.cov`` of an (N, 3) array copies and reduces it in its row layout; ``covariance`` works on the three contiguous
columns (the same covariance to within a few units in the last place). ``rows[mask]`` of an (N, 3) array copies
row by row through numpy's general boolean indexing, several times slower than ``np.compress`` (``take_rows``), which
copies the same rows.
"""

from __future__ import annotations

import math

import numpy as np


def median(values: np.ndarray) -> float:
    """Median of values (N,) (N >= 1), equal to ``float(np.median(values))`` (NaN when one of them is NaN)."""
    count = len(values)
    if count == 0:
        raise ValueError("the median of no values is undefined")
    if np.isnan(values).any():
        return math.nan
    half = count // 2
    part = np.partition(values, half)
    if count % 2:
        return float(part[half])
    return float((part[:half].max() + part[half]) / 2)


def column_medians(rows: np.ndarray) -> np.ndarray:
    """(3,) median of each column of rows (N, 3)."""
    return np.array([median(column) for column in np.ascontiguousarray(rows.T)])


def covariance(points: np.ndarray) -> np.ndarray:
    """(d, d) sample covariance (divided by N - 1) of points (N, d), N >= 2, as ``np.cov(points, rowvar=False)``."""
    columns = np.ascontiguousarray(np.asarray(points, dtype=float).T)
    centred = columns - columns.mean(axis=1, keepdims=True)
    return (centred @ centred.T) * (1.0 / (len(points) - 1))


def take_rows(rows: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``rows[mask]`` for an array (N, ...) and a bool mask (N,): the same copy, faster (see the module docstring)."""
    return np.compress(mask, rows, axis=0)

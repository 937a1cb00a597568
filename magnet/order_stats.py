"""Medians and quantiles the fits, figures and commands take of thousands of values: numpy's numbers bit for bit,
computed the fast way and without numpy's masked arrays.

``np.median`` partitions at both middle ranks and at the last one (to find NaN), several times slower than one
partition; ``median`` here gives the same number (bit for bit: the middle value, or the mean of the two middle values
(a + b) / 2) from one partition at n // 2, whose lower part holds the other middle value as its largest. And
``np.median``, ``np.quantile`` and ``np.unique`` (numpy 2.4) import ``numpy.ma`` on their first call, about 10 ms of
CPU: a command that takes one median pays that in its start. This module imports numpy alone, so the commands that
must start light (``magnet heading``, ``magnet fit``) use it; ``quantile`` is numpy's default (linear) method.
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


def quantile(values: np.ndarray, q: float) -> float:
    """The ``q`` quantile (0 <= q <= 1) of values (N,) (N >= 1), equal to ``float(np.quantile(values, q))`` (numpy's
    default, linear, method: the same indices, weight and interpolation), NaN when one of them is NaN. Without NaN
    ``quantile(x[~np.isnan(x)], q)`` is ``np.nanquantile(x, q)``."""
    count = len(values)
    if count == 0:
        raise ValueError("the quantile of no values is undefined")
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"quantile {q} is not within 0 .. 1")
    if np.isnan(values).any():
        return math.nan
    virtual = (count - 1) * q
    if virtual >= count - 1:  # numpy's index -1 for both, and its weight from it
        below = above = count - 1
        weight = virtual + 1.0
    else:
        below = math.floor(virtual)
        above = below + 1
        weight = virtual - below
    part = np.partition(values, [below, above] if above != below else below)
    low, high = part[below], part[above]
    step = high - low
    return float(high - step * (1.0 - weight) if weight >= 0.5 else low + step * weight)

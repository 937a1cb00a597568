"""A magnetometer held on faster rows (docs/field-calibration.md, "Sample rates"): a phone's recording merged onto
its accelerometer's and gyroscope's rows (100-200 Hz) repeats the slower magnetometer's last reading (50-100 Hz)
until a new one comes. A repeated row is no new measurement: its field is that of the attitude one or more rows
earlier, so a fit that pairs the gyroscope's turn with the field at such a row sees a field late by up to a
magnetometer period (15 ms at 50 Hz in 200 Hz rows; a swinging hand turns 4 deg in it), a delay that changes from
row to row and that no single lag takes out.

``fresh_rows`` finds the rows where the reading changed. A real magnetometer's noise (0.1-0.5 uT against a
resolution of 0.15 uT or finer) makes its three axes repeat exactly on a few rows in a thousand, so a log in which
more than ``HELD_SHARE`` of the rows repeat the row before is taken as held. Pure numpy.
"""

from __future__ import annotations

import numpy as np

#: more than this share of rows repeating the row before on all three axes: the magnetometer is held
HELD_SHARE = 0.2


def fresh_rows(mag: np.ndarray) -> np.ndarray | None:
    """(N,) bool: the rows of mag (N, 3) whose reading differs from the row before (the first row counts as fresh),
    when more than HELD_SHARE of the rows repeat; None when the magnetometer is not held (every row its own)."""
    values = np.asarray(mag, dtype=float)
    if values.ndim != 2 or len(values) < 2:
        return None
    fresh = np.ones(len(values), dtype=bool)
    fresh[1:] = np.any(values[1:] != values[:-1], axis=1)
    return fresh if float(np.mean(~fresh)) > HELD_SHARE else None


def fresh_kept(mag: np.ndarray, keep: np.ndarray | None) -> np.ndarray | None:
    """The rows (N,) bool both kept (``keep``, None: all) and fresh (``fresh_rows``); None when every row is."""
    fresh = fresh_rows(mag)
    if fresh is None:
        return keep
    return fresh if keep is None else fresh & np.asarray(keep, dtype=bool)

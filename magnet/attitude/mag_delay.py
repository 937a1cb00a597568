"""The magnetometer's delay behind the gyroscope, and the field turned forward over it (docs/broad-motion.md).

A magnetometer's output filter and its sampling make its reading describe the field a few to tens of ms before the
gyroscope's reading of the same sample (BROAD's IMU: about 12 ms, on every trial). While the device turns at rate w,
the field in the body frame turns at -w, so a reading late by tau is off by |w| tau (3.4 deg at 280 deg/s and
12 ms), and a filter that corrects its heading from it is pulled that way. The gyro-ellipsoid fit finds tau (the lag
whose rotation consistency fits best, ``magnet.calibration.gyro_ellipsoid``) and fits its matrix to the field taken
that late; its record carries it as the quality figure ``mag_lag_s``. Applying that record consistently means
turning each calibrated reading forward by the rotation the gyroscope measured over tau:

    b(t) = exp(-[w(t)]x tau) b_measured(t)

(``w(t)`` the sample's rate, over the period ending at it; the rotation over tau is this to first order in the change
of w). Only the field fed to the orientation filter is turned; the corrected field the compass publishes is not.
"""

from __future__ import annotations

import numpy as np

from magnet.compiled import kernels as _kernels
from magnet.model import Calibration


def record_lag_s(calibration: Calibration | None) -> float:
    """The delay (s) a calibration record carries (``Calibration.mag_lag_s``), 0.0 without a record."""
    return 0.0 if calibration is None else calibration.mag_lag_s


def advance_field(field: np.ndarray, gyr_rads: np.ndarray, lag_s: float | np.ndarray) -> np.ndarray:
    """The field (N, 3) turned forward by the gyroscope's rotation over ``lag_s`` (s, scalar or (N,)) at each
    sample: gyr (N, 3) rad/s, body frame. Rows whose rate is not finite, or whose lag is 0, are returned as they
    are. A new array; ``field`` is not changed."""
    field = np.asarray(field, dtype=float)
    lags = np.broadcast_to(np.asarray(lag_s, dtype=float), (len(field),))
    out = np.empty_like(field)
    _kernels.advance_field(field, np.asarray(gyr_rads, dtype=float), lags, out)  # Rodrigues' formula, row by row
    return out

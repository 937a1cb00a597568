"""Calibration methods by name, the fit error, the shape a method finds and the checks of its input."""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from magnet.quality import scatter_condition


class Method(enum.Enum):
    MINMAX2D = "minmax2d"
    MINMAX = "minmax"
    SPHERE = "sphere"
    ELLIPSOID = "ellipsoid"
    ELLIPSOID_ALIGN = "ellipsoid+align"
    TURNTABLE = "turntable"
    GYRO_ELLIPSOID = "gyro-ellipsoid"
    OFFSET = "offset"
    OFFSET_SCALE = "offset+scale"
    PLANAR = "planar"

    @classmethod
    def parse(cls, value: Method | str) -> Method:
        if isinstance(value, cls):
            return value
        try:
            return cls(str(value).strip().lower())
        except ValueError:
            choices = ", ".join(m.value for m in cls)
            raise ValueError(f"unknown calibration method {value!r}: use one of {choices}") from None

    @property
    def needs_gyroscope(self) -> bool:
        """Whether the method fits from the gyroscope's rates (``gyr=`` and ``period_s=``, consecutive samples)."""
        return self is Method.GYRO_ELLIPSOID

    @property
    def field_rung(self) -> bool:
        """Whether the method is a rung of the field ladder (``magnet.calibration.field``): fitted with the
        gyroscope when there is one, the WMM's dip and the calibration in force's matrix."""
        return self in (Method.OFFSET, Method.OFFSET_SCALE, Method.PLANAR)


class FitError(ValueError):
    """No calibration can be computed from these samples; the message says why and what to do."""


#: samples are taken in blocks of HOLDOUT_BLOCK_S seconds; every HOLDOUT_EVERY-th block is held out to score the fit
#: on data it did not see (blocks, not single samples: neighbours in time are nearly the same reading). In seconds, so
#: that the held-out rows fall at the same moments of a motion at every rate: counted as 20 samples, a 100 Hz stream
#: held out twice as often as a 50 Hz one, and a walk's corner a 50 Hz judgement never saw decided a 100 Hz one
#: (docs/field-calibration.md, "Sample rates"). HOLDOUT_BLOCK samples where the samples have no period (the
#: calibrator's sphere cells): 0.4 s at 50 Hz
HOLDOUT_BLOCK = 20
HOLDOUT_BLOCK_S = 0.4
HOLDOUT_EVERY = 5


def holdout_mask(count: int, period_s: float | None = None) -> np.ndarray:
    """(count,) bool: every HOLDOUT_EVERY-th block of HOLDOUT_BLOCK_S seconds of samples ``period_s`` apart (None:
    of HOLDOUT_BLOCK samples), the held-out test set."""
    block = HOLDOUT_BLOCK
    if period_s is not None and period_s > 0 and np.isfinite(period_s):
        block = max(1, round(HOLDOUT_BLOCK_S / period_s))
    period = np.arange(block * HOLDOUT_EVERY) // block == HOLDOUT_EVERY - 1
    return np.resize(period, count)  # the pattern repeats every HOLDOUT_EVERY blocks


#: fewest samples each method accepts (several times its parameter count, so that noise averages out)
MIN_SAMPLES: dict[Method, int] = {
    Method.MINMAX2D: 8,
    Method.MINMAX: 12,
    Method.SPHERE: 12,
    Method.ELLIPSOID: 30,
    Method.ELLIPSOID_ALIGN: 50,
    Method.GYRO_ELLIPSOID: 100,
    Method.OFFSET: 200,
    Method.OFFSET_SCALE: 200,
    Method.PLANAR: 200,
}
#: beyond this scatter condition (widest / thinnest spread of the raw cloud) a 3D fit is refused outright
MAX_SCATTER_FOR_3D = 50.0


@dataclasses.dataclass(frozen=True)
class Shape:
    """What a method found, before scaling to the output unit: |matrix @ (u - offset)| ~ radius (raw unit).
    mag_lag_s: how far the magnetometer's readings come behind the gyroscope's (s; gyro-ellipsoid finds it)."""

    offset: np.ndarray
    matrix: np.ndarray
    radius: float
    note: str = ""
    mag_lag_s: float = 0.0


def check_samples(mag: np.ndarray, method: Method) -> np.ndarray:
    arr = np.asarray(mag, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FitError(f"samples must be an (N, 3) array of x, y, z readings, got shape {arr.shape}")
    if not np.isfinite(arr).all():  # the rows only then: a reduction along rows of three is slow
        bad = ~np.all(np.isfinite(arr), axis=1)
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


def check_spread_3d(mag: np.ndarray, method: Method) -> None:
    condition = scatter_condition(mag)
    if condition > MAX_SCATTER_FOR_3D:
        raise FitError(
            f"samples are coplanar or degenerate (scatter condition {condition:.3g}): {method.value} "
            "needs samples from all attitudes; tumble the device, or use minmax2d for a level turn"
        )


def check_acc(acc: np.ndarray | None, n: int, required: bool) -> np.ndarray | None:
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


#: why gyro-ellipsoid refuses samples without a gyroscope
GYROSCOPE_NEEDED = (
    "gyro-ellipsoid needs gyroscope samples (gx, gy, gz in rad/s) and their sample period (a t_s column or a rate) "
    "beside the magnetometer samples: use ellipsoid for a magnetometer alone"
)


def check_gyr(gyr: np.ndarray | None, period_s: float | None, n: int, required: bool) -> np.ndarray | None:
    """The body rates (n, 3) rad/s as floats, or None; FitError when gyro-ellipsoid has none or they do not fit."""
    if gyr is None or period_s is None:
        if required:
            raise FitError(GYROSCOPE_NEEDED)
        return None
    arr = np.asarray(gyr, dtype=float)
    if arr.shape != (n, 3):
        raise FitError(f"gyr must have the shape of the magnetometer samples ({n}, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise FitError("gyr holds NaN or infinite values: drop those rows from every array before fitting")
    if not (np.isfinite(period_s) and period_s > 0):
        raise FitError(f"the gyroscope's sample period must be a positive number of seconds, got {period_s!r}")
    return arr

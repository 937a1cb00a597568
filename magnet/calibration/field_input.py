"""What a field fit takes (``FieldInput``), validated where it enters: one record, apart from the fit
(``magnet.calibration.field``) so that the stages the fit calls (``magnet.calibration.disturbed``) can name it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from magnet.calibration.base import FitError
from magnet.calibration.fit_input import FitInput
from magnet.earth.geomag import earth_field
from magnet.model import Calibration

#: fewest samples a field fit takes (its windows and blocks need some seconds of data)
MIN_FIELD_SAMPLES = 200


@dataclasses.dataclass(frozen=True)
class FieldInput:
    """What a field fit takes: mag (N, 3) raw in ``unit``; acc (N, 3) specific force (any unit) or None; gyr (N, 3)
    rad/s consecutive every period_s seconds, or None; field_ut (WMM |B|, uT) and dip_deg (WMM inclination, deg,
    positive down) or None; reference: the calibration in force (its matrix is kept by the lower rungs) or None;
    vel_ned_ms (N, 3) m/s geographic NED, the velocity over the ground (NaN rows where unknown) or None, with
    declination_deg (WMM, deg; None: taken as 0): the attitude the fit is judged with is then velocity aided."""

    mag: np.ndarray
    acc: np.ndarray | None = None
    gyr: np.ndarray | None = None
    period_s: float | None = None
    unit: str = "ut"
    field_ut: float | None = None
    dip_deg: float | None = None
    reference: Calibration | None = None
    vel_ned_ms: np.ndarray | None = None
    declination_deg: float | None = None
    disturbed: np.ndarray | None = None

    @classmethod
    def of(cls, data: FitInput) -> FieldInput:
        """The field fit's input from a fit's (``FitInput``): the dip (and declination) from ``data.dip_deg``
        (``data.declination_deg``), else the WMM at ``data.place`` and ``data.date`` (None without a place)."""
        dip, declination = data.dip_deg, data.declination_deg
        if (dip is None or declination is None) and data.place is not None:
            earth = earth_field(*data.place.as_tuple(), data.date)
            dip = earth.inclination_deg if dip is None else dip
            declination = earth.declination_deg if declination is None else declination
        return cls(
            data.mag,
            data.acc,
            data.gyr_rads,
            data.period_s,
            data.unit,
            data.field_ut,
            dip,
            data.reference,
            data.vel_ned_ms,
            declination,
            data.disturbed if data.drop_disturbed else None,
        )

    def __post_init__(self) -> None:
        mag = np.asarray(self.mag, dtype=float)
        if mag.ndim != 2 or mag.shape[1] != 3:
            raise FitError(f"samples must be an (N, 3) array of x, y, z readings, got shape {mag.shape}")
        if len(mag) < MIN_FIELD_SAMPLES:
            raise FitError(f"only {len(mag)} samples: a field fit needs {MIN_FIELD_SAMPLES}; keep the device moving")
        if not np.all(np.isfinite(mag)):
            raise FitError("samples hold NaN or infinite values: drop them before fitting")
        if self.disturbed is not None and np.shape(self.disturbed) != (len(mag),):
            raise FitError(f"disturbed must be one flag per sample ({len(mag)},)")
        for name in ("acc", "gyr", "vel_ned_ms"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != mag.shape:
                raise FitError(f"{name} must have the shape of the magnetometer samples {mag.shape}")
        if self.gyr is not None and not (self.period_s and math.isfinite(self.period_s) and self.period_s > 0):
            raise FitError("the gyroscope needs its sample period (t_s or a rate), a positive number of seconds")
        if self.field_ut is not None and not (math.isfinite(self.field_ut) and self.field_ut > 0):
            raise FitError(f"expected field strength must be a positive number of uT, got {self.field_ut!r}")
        object.__setattr__(self, "mag", mag)

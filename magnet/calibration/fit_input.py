"""``FitInput``: what every calibration method is fitted from, in one value (``magnet.calibration.fitting.METHODS``).

Samples, their times, the gyroscope, the accelerometer, the place, and the options of a fit (the raw unit, the field
strength to scale to, the gate, the calibration in force); a turntable's setup for the method that needs one. A
method reads what it needs and the checks of ``magnet.calibration.base`` refuse what is missing. Pure numpy.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from magnet.earth.location import Location
from magnet.model import Calibration
from magnet.quality import GateThresholds


@dataclasses.dataclass(frozen=True)
class TurntableSetup:
    """What the turntable method needs beside the samples: mounting (N,) "a"/"b" and table angle heading_deg (N,) deg
    of every sample, the known horizontal and vertical field components (in ``field_unit``, the record's output
    unit), and the variant ("closed": seed 000's closed form, "lsq": least squares over every angle)."""

    mounting: np.ndarray
    heading_deg: np.ndarray
    horizontal: float
    vertical: float
    variant: str = "closed"
    field_unit: str = "ut"


@dataclasses.dataclass(frozen=True)
class FitInput:
    """One fit's input.

    mag (N, 3): raw magnetometer samples in ``unit``; t_s (N,) s: their times, or None; acc (N, 3): specific force,
    any unit, or None; gyr_rads (N, 3) rad/s: the body rates, consecutive samples every period_s seconds (the rate
    of a sample is over the period ending at it), or None; place and date: where and when (the World Magnetic
    Model's), or None; field_ut: the expected |B| in uT (from the place, or given), None: keep the fitted radius;
    gate: the gate's thresholds (None: the defaults); robust_extremes: minmax's spike filter; reference: the
    calibration in force (None: none); turntable: the turntable method's setup; dip_deg: the expected dip (deg, positive
    down; None: the WMM's at the place, if given), the prior of the field ladder (``magnet.calibration.field``);
    vel_ned_ms (N, 3) m/s geographic NED: the velocity over the ground (NaN rows before a fix) or None, and
    declination_deg (None: the WMM's at the place, else 0): with them the field ladder's attitude is velocity aided
    (a vehicle's accelerations do not tilt it); disturbed (N,) bool: the samples no fit takes (a disturbed field,
    ``magnet.calibration.disturbed``; None: judged by the fit itself), drop_disturbed False: keep them all. The
    arrays are checked by the fit (``magnet.calibration.base``), each against what its method needs."""

    mag: np.ndarray
    unit: str = "ut"
    t_s: np.ndarray | None = None
    acc: np.ndarray | None = None
    gyr_rads: np.ndarray | None = None
    period_s: float | None = None
    place: Location | None = None
    date: str | None = None
    field_ut: float | None = None
    gate: GateThresholds | None = None
    robust_extremes: bool = False
    reference: Calibration | None = None
    turntable: TurntableSetup | None = None
    dip_deg: float | None = None
    vel_ned_ms: np.ndarray | None = None
    declination_deg: float | None = None
    disturbed: np.ndarray | None = None
    drop_disturbed: bool = True

    @property
    def has_gyroscope(self) -> bool:
        """Whether the body rates and their period are both given (what gyro-ellipsoid fits from)."""
        return self.gyr_rads is not None and self.period_s is not None

    def replace(self, **changes: Any) -> FitInput:
        """A copy with ``changes`` (field name -> value)."""
        return dataclasses.replace(self, **changes)

"""The fitting part of the calibrator: a collection fitted with its method, scaled to the field expected at the
device's place, and judged by the quality gate (``magnet.calibration.collection.Collection.fit``, ``magnet.quality``);
every fit counted. A collection for a method that needs the gyroscope (gyro-ellipsoid) is fitted on its longest run of
consecutive samples, with their rates and period (``gyr=``, ``period_s=``). What passes is signed and stored by
``magnet.calibrator.records``. No zenoh, no store inside."""

from __future__ import annotations

from collections.abc import Callable

from magnet.calibration.collection import Collection
from magnet.calibrator.settings import Settings
from magnet.model import Calibration


class Fitter:
    """Fits collections; ``field_at(device)``: the model |B| (uT) at the device's place, None when unknown (then
    the settings' ``expected_field_ut``, else the fit's own)."""

    def __init__(
        self,
        settings: Settings,
        field_at: Callable[[str], float | None],
        dip_at: Callable[[str], float | None] = lambda device: None,
        declination_at: Callable[[str], float | None] = lambda device: None,
    ) -> None:
        self.settings, self.field_at, self.dip_at = settings, field_at, dip_at
        self.declination_at = declination_at
        self.fits = self.accepted = self.rejected = 0

    def field_ut(self, device: str | None) -> float | None:
        """The field strength (uT) a fit for ``device`` is scaled to."""
        return (self.field_at(device) if device else None) or self.settings.expected_field_ut

    def fit(
        self, collection: Collection, now: float, device: str | None = None, reference: Calibration | None = None
    ) -> Calibration | None:
        """Fit ``collection`` and count it; the calibration when the gate accepts it, else None (the reason is on
        ``collection.last_reason``). ``reference``: the calibration in force, which the fit must beat (an
        in-service refresh, ``magnet.calibrator.refresh``); the dip at the device's place is the field ladder's
        prior, its declination turns the velocity a vehicle sends into magnetic north (the fit's aided attitude)."""
        dip = self.dip_at(device) if device else None
        declination = self.declination_at(device) if device else None
        result = collection.fit(self.field_ut(device), now, reference, dip, declination)
        self.fits += 1
        accepted = result is not None and result.accepted
        if accepted:
            self.accepted += 1
        else:
            self.rejected += 1
        return result if accepted else None

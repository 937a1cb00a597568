"""What the calibrator's decisions read of its settings (``Settings``): the service's ``CalibratorSettings``
(``services.calibrator.settings``, where each is an option with its flag, default and check) is one; the core reads
them and never parses or checks them."""

from __future__ import annotations

from typing import Protocol

#: devices collected at once and kept in the roster at most (``--max-devices``' default)
DEFAULT_MAX_DEVICES = 10_000


class Settings(Protocol):
    """How the calibrator collects and fits (checked where they were read: ``--method`` and the rest)."""

    @property
    def method(self) -> str:
        """The fit method of automatic calibration and of sessions that name none (a ``choose`` choice, auto too)."""
        ...

    @property
    def min_coverage(self) -> float:
        """Sphere coverage (fraction) before an automatic fit is tried."""
        ...

    @property
    def min_samples(self) -> int:
        """Kept samples before a fit."""
        ...

    @property
    def max_samples(self) -> int:
        """Kept samples per device at most."""
        ...

    @property
    def auto(self) -> bool:
        """Whether a device without a calibration in force is collected and fitted without a session."""
        ...

    @property
    def max_devices(self) -> int:
        """Devices collected at once (sessions stay) and kept in the roster at most."""
        ...

    @property
    def recalibrate(self) -> str:
        """In-service recalibration of calibrated devices: "auto", "propose" or "off" (``calibrator.refresh``)."""
        ...

    @property
    def expected_field_ut(self) -> float | None:
        """|B| (uT) a fit is scaled to when the device's place is unknown; None: the fit's own."""
        ...

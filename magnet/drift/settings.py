"""Drift thresholds (``DriftSettings``) and what a device's field should look like (``Reference``)."""

from __future__ import annotations

import dataclasses
import math

NS_PER_S = 1_000_000_000
NS_PER_DAY = 86_400 * NS_PER_S


@dataclasses.dataclass(frozen=True)
class DriftSettings:
    """Thresholds of the drift alerts (see ``magnet.drift``); every field a positive number."""

    window_s: float = 30.0
    raise_windows: int = 4
    clear_windows: int = 4
    clear_fraction: float = 0.5
    strength_tol_pct: float = 6.0
    strength_residual_factor: float = 3.0
    model_strength_tol_ut: float = 20.0
    dip_tol_deg: float = 4.0
    model_dip_tol_deg: float = 20.0
    max_age_days: float = 365.0
    min_window_samples: int = 20
    max_window_samples: int = 4096

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"drift setting {field.name} must be a positive number, got {value!r}")
        for name in ("raise_windows", "clear_windows", "min_window_samples", "max_window_samples"):
            if not isinstance(getattr(self, name), int):
                raise ValueError(f"drift setting {name} must be a whole number")
        if self.clear_fraction >= 1:
            raise ValueError(f"clear_fraction must be below 1 (hysteresis), got {self.clear_fraction}")

    @property
    def window_ns(self) -> int:
        """Window length in ns."""
        return round(self.window_s * NS_PER_S)

    @property
    def detection_bound_s(self) -> float:
        """Longest device time from the start of a sustained departure to its alert (data flowing)."""
        return (self.raise_windows + 1) * self.window_s


#: the defaults, documented in the README
DEFAULT_DRIFT = DriftSettings()


@dataclasses.dataclass(frozen=True)
class Reference:
    """What a device's field should look like: the calibration's |B| (uT; None or 0: learn it like the dip), its
    fit residual (uT), the model's |B| (uT) and inclination (deg) at the device's place (None: unknown), and the
    calibration's id and ``created_ns``."""

    strength_ut: float | None
    residual_ut: float = 0.0
    model_total_ut: float | None = None
    model_dip_deg: float | None = None
    created_ns: int = 0
    calibration_id: str = ""

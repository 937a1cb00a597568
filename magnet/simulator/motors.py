"""The motors of a simulated vehicle: a throttle profile, the battery current it draws and the field it adds.

Throttle is commanded from hover up to full and back, again and again (a triangle wave of period ``period_s``
between ``hover_throttle`` and 1); on a multirotor trajectory it also follows the thrust the flight needs (more in
banks and climbs, less in descents: the specific force in g, capped at full throttle). The current is proportional
to the throttle (``full_current_a`` at full throttle); the motors add ``ut_per_a * current`` (uT, body frame) to the
field at the sensor, before the sensor's own errors (the motors' field reaches the chip through the same soft iron
as the Earth's). So the exact correction of the sensor gives B_earth + ut_per_a * I, the model of ``magnet.motor``.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Motors:
    """ut_per_a (3,) uT per amp, body frame; full_current_a (A) at throttle 1; hover_throttle (0..1); period_s (s) of
    one hover -> full -> hover cycle."""

    ut_per_a: tuple[float, float, float] = (0.15, -0.1, 0.2)
    full_current_a: float = 40.0
    hover_throttle: float = 0.4
    period_s: float = 20.0

    def __post_init__(self) -> None:
        if len(self.ut_per_a) != 3 or not np.isfinite(self.ut_per_a).all():
            raise ValueError(f"ut_per_a must be 3 finite numbers, got {self.ut_per_a!r}")
        if not self.full_current_a > 0 or not 0 <= self.hover_throttle <= 1 or not self.period_s > 0:
            raise ValueError("full_current_a and period_s must be > 0, hover_throttle within 0..1")

    @classmethod
    def with_full_field(cls, field_ut: float, direction: tuple[float, float, float], **options: float) -> Motors:
        """Motors adding ``field_ut`` (uT, its size) along ``direction`` at full current."""
        full = options.get("full_current_a", cls.full_current_a)
        unit = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
        per_a = unit * field_ut / full
        return cls(ut_per_a=(float(per_a[0]), float(per_a[1]), float(per_a[2])), **options)

    def throttle(self, t_s: np.ndarray, thrust_g: np.ndarray | None = None) -> np.ndarray:
        """(N,) 0..1 at times t_s (s): the commanded profile, times the thrust the trajectory needs in g (N,) where
        given (a multirotor: its specific force, 1 in a hover, more in a bank or a climb), capped at 1."""
        phase = np.mod(np.asarray(t_s, dtype=float) / self.period_s, 1.0)
        triangle = 1.0 - np.abs(2.0 * phase - 1.0)  # 0 at the cycle's start and end, 1 in its middle
        command = self.hover_throttle + (1.0 - self.hover_throttle) * triangle
        return command if thrust_g is None else np.clip(command * thrust_g, 0.0, 1.0)

    def current_a(self, throttle: np.ndarray) -> np.ndarray:
        """(N,) A drawn at ``throttle`` (N,)."""
        return self.full_current_a * np.asarray(throttle, dtype=float)

    def field_ut(self, current_a: np.ndarray) -> np.ndarray:
        """(N, 3) uT the motors add in the body frame."""
        return np.asarray(current_a, dtype=float)[:, None] * np.asarray(self.ut_per_a)

"""GNSS-like velocity for the moving simulator: what a receiver on the vehicle reports (docs/design.md, "Heading in
motion", velocity aiding).

A fix k measures the vehicle's velocity (``MotionModel.velocity``, NED m/s) at t_k = k / rate_hz, with white noise
(``noise_ms`` per axis), and is reported ``delay_s`` later; between reports the last one is held, and before the first
the velocity is unknown (NaN), as ``vel_ned_ms`` travels on the wire. A fix's noise comes from a generator seeded with
(seed, k), so a run gives the same fixes whether it is drawn at once or block by block.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.simulator.motion import MotionModel


@dataclasses.dataclass(frozen=True)
class GnssSettings:
    """Fix rate (Hz), noise per axis (m/s, one sigma) and latency (s) of the simulated receiver."""

    rate_hz: float = 10.0
    noise_ms: float = 0.1
    delay_s: float = 0.1

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"GNSS rate_hz must be a positive number, got {self.rate_hz!r}")
        if not (np.isfinite(self.noise_ms) and self.noise_ms >= 0 and np.isfinite(self.delay_s) and self.delay_s >= 0):
            raise ValueError("GNSS noise_ms and delay_s must be finite and not negative")


def gnss_velocity(
    model: MotionModel, t_s: np.ndarray, seed: int, settings: GnssSettings = GnssSettings()
) -> np.ndarray:
    """The held velocity (N, 3) m/s NED a receiver reports at sample times t_s (N,), NaN before its first report."""
    t = np.asarray(t_s, dtype=float)
    fix = np.floor((t - settings.delay_s) * settings.rate_hz + 1e-9).astype(np.int64)
    out = np.full((len(t), 3), np.nan)
    known = fix >= 0
    if not known.any():
        return out
    numbers, where = np.unique(fix[known], return_inverse=True)
    values = model.velocity(numbers / settings.rate_hz)
    noise = np.array([np.random.default_rng([seed, int(k)]).standard_normal(3) for k in numbers])
    out[known] = (values + settings.noise_ms * noise)[where]
    return out

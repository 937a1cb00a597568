"""Velocity aiding: the linear acceleration a vehicle's velocity (GNSS, an autopilot) implies, known causally.

Design: docs/design.md, "Heading in motion" (velocity aiding).

An accelerometer reads gravity plus the vehicle's own acceleration; the velocity over the ground tells the second
part, a_ned = dv/dt, so the filter can be fed acc - R^T a_ned (R body -> NED) and keeps its tilt in a sustained turn
or speed change. Velocity comes slower than the inertial samples (a GNSS fix at 5-20 Hz, held between fixes on the
wire: ``vel_ned_ms`` NaN rows before the first) and late (a receiver reports a fix about 0.1 s after the instant it
measures). So:

- a fix is a change of the held value (or its first finite row); it was measured ``delay_s`` before the sample where
  it appears;
- the acceleration at time t is the centred difference (v(t + h) - v(t - h)) / 2h of the fixes joined by straight
  lines, h = ``half_window_s``: no lag, averaging the fixes' noise and the fast swings a receiver's rate cannot
  follow. h is set by the noise: a fix's 0.1 m/s becomes sqrt(2) 0.1 / 2h m/s^2 of acceleration noise, which must stay
  well under what the filter takes for a device at rest (vqf: the accelerometer within 0.5 m/s^2 of its mean), or
  the filter never finds rest and never learns the gyroscope's bias about the vertical; h = 0.5 s gives 0.14 m/s^2
  (h = 0.25 s gave 0.28 and a car whose heading drifted by 7 deg);
- it is known only once a fix at or after t + h has arrived: ``known_until_s``. The filter therefore runs that far
  behind the newest sample (``magnet.attitude.aided_fusion``), and the attitude of the newest samples is carried forward
  from it with the gyroscope.

Velocities are in magnetic NED (north is the field's, as the filter's): rotate geographic ones with
``magnet.frames.to_magnetic_ned`` first. Pure numpy; times in seconds.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.compiled import kernels as _kernels
from magnet.units import STANDARD_GRAVITY_MS2

#: a receiver's latency: a fix appears this long after the instant it measured (s)
DELAY_S = 0.1
#: half the span of the centred difference (s)
HALF_WINDOW_S = 0.5
#: fixes kept (a few seconds of them at any common rate)
MAX_FIXES = 256
#: a receiver's velocity noise per axis (m/s, one sigma): the figure the time constants below are derived from
RECEIVER_NOISE_MS = 0.1
#: what is left of a vehicle's accelerometer once the velocity's acceleration is removed (RMS of 0.1 s means, m/s^2):
#: the velocity's noise (sqrt(2) 0.1 / 2h = 0.14) and the vibration 0.1 s means leave (road, rotors); it sets the
#: accelerometer time constant of an aided vehicle (``vehicle_tau_acc_s``: 1.8 s)
VEHICLE_RESIDUAL_MS2 = 0.4
#: the speed under which a fix says the vehicle stands still (m/s): five times a receiver's noise
STANDING_SPEED_MS = 0.5


def vehicle_tau_acc_s(residual_ms2: float, bias_sigma_rads: float) -> float:
    """The accelerometer time constant (s) for a filter whose linear acceleration the velocity removes, given what
    is left of the accelerometer (RMS m/s^2 of 0.1 s means, ``magnet.attitude.gyro_bias.Explained``) and the gyroscope
    bias's uncertainty (rad/s, one axis).

    vqf low-passes the accelerometer over tauAcc (3 s) so that a vehicle's own accelerations average out. With them
    removed, what is left, sigma_a (as an angle: / g), is correlated over about the velocity's window 2h. The tilt
    then has two errors: the gyroscope's bias not yet learnt, b, turns it by b tau before the accelerometer pulls it
    back, and the residual, low-passed, leaves sigma_a^2 2h / (2 tau). Their sum is least at
    tau^3 = sigma_a^2 2h / (4 b^2). With b = vqf's biasSigmaInit (0.5 deg/s): a car (0.2 m/s^2 left: the aiding's
    noise, sqrt(2) 0.1 / 2h = 0.14, and road vibration) 1.1 s, a multirotor (0.45 m/s^2: rotor vibration, bank
    onsets the 1 s difference smooths) 1.8 s; at 0.9 m/s^2 it reaches vqf's 3 s, where aiding no longer helps the
    tilt."""
    window = 2.0 * HALF_WINDOW_S
    sigma = residual_ms2 / STANDARD_GRAVITY_MS2
    return float((sigma**2 * window / (4.0 * bias_sigma_rads**2)) ** (1.0 / 3.0))


@dataclasses.dataclass
class VelocityFixes:
    """The velocity fixes seen so far (at most ``max_fixes``, the newest): measured times (F,) s and values (F, 3)
    m/s. ``observe`` takes held velocity rows as they come; ``acceleration`` gives dv/dt where it is known."""

    delay_s: float = DELAY_S
    half_window_s: float = HALF_WINDOW_S
    times_s: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    values: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    held: np.ndarray | None = None
    max_fixes: int = MAX_FIXES

    def arrivals(self, vel_ned_ms: np.ndarray) -> np.ndarray:
        """(N,) bool: the rows of held velocities (N, 3) where a new fix appears, after those seen so far."""
        vel = np.asarray(vel_ned_ms, dtype=float)
        if len(vel) == 0:
            return np.zeros(0, dtype=bool)
        changed = np.empty(len(vel), dtype=bool)
        changed[0] = self.held is None or bool((vel[0] != self.held).any())  # nothing held: any finite row is new
        changed[1:] = (vel[1:] != vel[:-1]).any(axis=1)
        return np.isfinite(vel).all(axis=1) & changed

    def observe(self, t_s: np.ndarray, vel_ned_ms: np.ndarray) -> None:
        """Samples' times (N,) s, increasing, and their held velocity (N, 3) (NaN rows where none is known)."""
        vel = np.asarray(vel_ned_ms, dtype=float)
        if len(vel) == 0:
            return
        new = self.arrivals(vel)
        last_finite = bool(np.isfinite(vel[-1]).all())
        if not new.any():
            self.held = vel[-1] if last_finite else self.held
            return
        measured = np.asarray(t_s, dtype=float)[new] - self.delay_s
        self.times_s = np.concatenate([self.times_s, measured])[-self.max_fixes :]
        self.values = np.concatenate((self.values, vel[new]))[-self.max_fixes :]
        self.held = vel[-1] if last_finite else self.held

    @property
    def known_until_s(self) -> float:
        """The latest time whose acceleration is known (the newest fix's time minus h); -inf before two fixes."""
        return float(self.times_s[-1] - self.half_window_s) if len(self.times_s) >= 2 else -np.inf

    def standing(self, start_s: float, end_s: float, max_speed_ms: float = STANDING_SPEED_MS) -> bool | None:
        """Whether the vehicle stood still from start_s to end_s (s) by the fixes measured within h of them: True
        when every one is under ``max_speed_ms``, False when one is not, None when there is none."""
        near = (self.times_s >= start_s - self.half_window_s) & (self.times_s <= end_s + self.half_window_s)
        if not near.any():
            return None
        near_values = self.values[near]
        return bool((np.sqrt(np.add.reduce(near_values * near_values, axis=1)) < max_speed_ms).all())

    def acceleration(self, t_s: np.ndarray) -> np.ndarray:
        """dv/dt (N, 3) m/s^2 at times t_s (N,): the centred difference over the fixes; zero where the window is
        not covered by fixes (before the first, or not yet known)."""
        t = np.asarray(t_s, dtype=float)
        if len(self.times_s) < 2:
            return np.zeros((len(t), 3))
        out = np.empty((len(t), 3))
        _kernels.centred_difference(self.times_s, self.values, t, self.half_window_s, out)
        return out

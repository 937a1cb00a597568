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
    return _kernels.vehicle_tau_acc(float(residual_ms2), float(bias_sigma_rads), HALF_WINDOW_S, STANDARD_GRAVITY_MS2)


#: the numbers of a ``VelocityFixes`` besides its buffers: the first visible fix, their count, whether a value is
#: held, the held value (3,)
FIXES_SIZE = 6


class VelocityFixes:
    """The velocity fixes seen so far (at most ``max_fixes``, the newest): measured times (F,) s and values (F, 3)
    m/s. ``observe`` takes held velocity rows as they come; ``acceleration`` gives dv/dt where it is known.

    The fixes live in buffers of twice ``max_fixes`` (moved back to their start when full) and ``meta``
    (``FIXES_SIZE``,): a view into the aided filter's state, whose compiled loop runs the same kernels
    (``magnet._kernels.fixes_observe``, ``fixes_standing``, ``centred_difference``), or a new array when alone."""

    def __init__(
        self,
        delay_s: float = DELAY_S,
        half_window_s: float = HALF_WINDOW_S,
        max_fixes: int = MAX_FIXES,
        meta: np.ndarray | None = None,
    ) -> None:
        if max_fixes < 2:
            raise ValueError(f"max_fixes must be at least 2, got {max_fixes}")
        self.delay_s, self.half_window_s, self.max_fixes = float(delay_s), float(half_window_s), int(max_fixes)
        self.meta = np.zeros(FIXES_SIZE) if meta is None else meta
        self.meta[:] = 0.0
        self.buffer_times = np.zeros(2 * self.max_fixes)
        self.buffer_values = np.zeros((2 * self.max_fixes, 3))

    @property
    def times_s(self) -> np.ndarray:
        """The fixes' measured times (F,) s (a view)."""
        start, count = int(self.meta[0]), int(self.meta[1])
        return self.buffer_times[start : start + count]

    @property
    def values(self) -> np.ndarray:
        """The fixes' values (F, 3) m/s magnetic NED (a view)."""
        start, count = int(self.meta[0]), int(self.meta[1])
        return self.buffer_values[start : start + count]

    @property
    def held(self) -> np.ndarray | None:
        """The last finite velocity seen (3,), None before one."""
        return self.meta[3:6].copy() if self.meta[2] else None

    def arrivals(self, vel_ned_ms: np.ndarray) -> np.ndarray:
        """(N,) bool: the rows of held velocities (N, 3) where a new fix appears (finite and unlike the row before;
        the first row unlike the value held), after those seen so far."""
        vel = np.ascontiguousarray(vel_ned_ms, dtype=float)
        out = np.zeros(len(vel), dtype=bool)
        _kernels.fixes_arrivals(self.meta, vel.reshape(-1, 3), out)
        return out

    def observe(self, t_s: np.ndarray, vel_ned_ms: np.ndarray) -> None:
        """Samples' times (N,) s, increasing, and their held velocity (N, 3) (NaN rows where none is known): each
        new fix (``arrivals``) is kept, dated ``delay_s`` before its sample."""
        vel = np.ascontiguousarray(vel_ned_ms, dtype=float).reshape(-1, 3)
        t = np.asarray(t_s, dtype=float)
        _kernels.fixes_observe(self.meta, self.buffer_times, self.buffer_values, t, vel, self.delay_s, self.max_fixes)

    @property
    def known_until_s(self) -> float:
        """The latest time whose acceleration is known (the newest fix's time minus h); -inf before two fixes."""
        times = self.times_s
        return float(times[-1] - self.half_window_s) if len(times) >= 2 else -np.inf

    def standing(self, start_s: float, end_s: float, max_speed_ms: float = STANDING_SPEED_MS) -> bool | None:
        """Whether the vehicle stood still from start_s to end_s (s) by the fixes measured within h of them: True
        when every one is under ``max_speed_ms``, False when one is not, None when there is none."""
        verdict = _kernels.fixes_standing(
            self.meta, self.buffer_times, self.buffer_values, start_s, end_s, self.half_window_s, max_speed_ms
        )
        return None if verdict < 0 else bool(verdict)

    def acceleration(self, t_s: np.ndarray) -> np.ndarray:
        """dv/dt (N, 3) m/s^2 at times t_s (N,): the centred difference over the fixes; zero where the window is
        not covered by fixes (before the first, or not yet known)."""
        t = np.asarray(t_s, dtype=float)
        if len(self.times_s) < 2:
            return np.zeros((len(t), 3))
        out = np.empty((len(t), 3))
        _kernels.centred_difference(self.times_s, self.values, t, self.half_window_s, out)
        return out

"""The gyroscope's bias learnt from the magnetometer by a small Kalman filter, for an aided vehicle
(docs/aiding.md); and how well the velocity explains the accelerometer (``Explained``), which says when it applies.

vqf's 6D attitude (gyroscope and accelerometer) turns in heading at the rate of whatever gyroscope bias it has not
learnt about the vertical; the accelerometer cannot see that turn, the magnetometer can: the field's direction in the
6D earth frame, phi = atan2(E_east, E_north) (vqf's frames: ENU), follows it. Five states, radians and seconds:

- phi, the 6D frame's heading offset from magnetic north;
- e (3,), the gyroscope bias vqf's estimate misses, body axes (rad/s): phi turns at -up . e, up the vertical in body
  axes, so a vehicle that stays level shows the vertical part, one that tilts shows more;
- c, the error the tilt puts on the measured phi: a tilt error t moves the field's apparent heading by up to
  t tan(dip), and vqf's tilt errors last about its accelerometer time constant tau, so c is a first-order
  Gauss-Markov process (sigma: ``TILT_ERROR_DEG`` and the tilt the unlearnt horizontal bias gives, b tau, times
  tan(dip); time constant tau) rather than white noise: treated as white, slow tilt errors passed for a drift.

Each piece of samples fed to vqf gives one measurement, the circular mean of phi over its samples, z = phi + c +
white noise (the magnetometer's, ``HEADING_NOISE_DEG`` per sample, over sqrt(n)). The states evolve as
phi' = phi - up . e dt (+ the gyroscope's angle random walk), e' = e (+ a bias random walk), c' = exp(-dt/tau) c.
The estimated e is handed to vqf's own bias estimate and zeroed here (an error-state filter: one bias estimate,
vqf's, which its own learning carries on), and phi to vqf's heading correction (delta). Early on e's variance is
vqf's initial bias uncertainty, so the gain is large and the bias is learnt in seconds; later the gain falls as the
noise figures say, instead of a fixed integral time (``magnet.attitude.aided_fusion.VerticalBias``, kept where the
velocity does not explain the accelerometer).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from magnet.compiled import kernels as _kernels

#: white noise of the heading one magnetometer sample gives (deg): 0.3 uT of noise on a 20 uT horizontal field
HEADING_NOISE_DEG = 1.0
#: vqf's tilt error in motion with velocity aiding (deg, one sigma): sets the correlated heading error with tan(dip)
TILT_ERROR_DEG = 0.5
#: the gyroscope's angle random walk (rad/sqrt(s)): about 1 deg/sqrt(h), a common MEMS figure
ANGLE_RANDOM_WALK = 3e-4
#: the gyroscope bias's random walk (rad/s/sqrt(s)): a bias that wanders by 0.05 deg/s over ten minutes
BIAS_RANDOM_WALK = 3e-5
#: the steepest dip the tilt term uses (deg): near the magnetic poles heading is not measurable anyway
MAX_DIP_DEG = 80.0
#: the time over which the accelerometer's residual is averaged (s): vqf's default accelerometer time constant
EXPLAINED_TIME_S = 3.0


@dataclasses.dataclass
class Explained:
    """How well the velocity explains the accelerometer: what is left of the accelerometer once the velocity's
    acceleration is taken out, less gravity along the filter's vertical, averaged over each piece (0.1 s: vibration
    averages out), its square averaged over ``EXPLAINED_TIME_S``. A car or a multirotor leaves 0.2-0.5 m/s^2 (the
    aiding's noise, road and rotor vibration); a hand's figure 8 or a tumble off its centre 3-6 m/s^2: motion faster
    than a 10 Hz velocity with a 1 s difference can follow. ``mean_square`` (m/s^2)^2, None before the first piece."""

    mean_square: float | None = None

    def update(self, left_ms2: float, seconds: float) -> float:
        """A piece: |mean(acc - g up)| (m/s^2) over its samples (the accelerometer fed and the vertical, body axes,
        vqf's frames: ``magnet._kernels.piece_figures``) and its length in seconds. Returns the residual's RMS so
        far (m/s^2)."""
        left = float(left_ms2) ** 2
        weight = -math.expm1(-seconds / EXPLAINED_TIME_S)
        self.mean_square = left if self.mean_square is None else self.mean_square + weight * (left - self.mean_square)
        return math.sqrt(self.mean_square)


@dataclasses.dataclass(frozen=True)
class PieceField:
    """The field over one piece fed to vqf, in the 6D earth frame (ENU, any unit; ``magnet._kernels.piece_figures``
    gives these): the piece's mean time (s) and sample count, the circular mean of the field's heading
    atan2(E_east, E_north) (rad), the mean of its horizontal norm and of its up component."""

    t_s: float
    count: int
    heading_rad: float
    horizontal: float
    vertical: float


class HeadingDrift:
    """The Kalman filter of the module docstring for one device. ``tau_acc_s``: vqf's tauAcc (s);
    ``bias_sigma_rads``: the initial uncertainty of each axis of the gyroscope bias (rad/s, vqf's biasSigmaInit).
    State x (5,): phi (rad), the bias left over in body axes (3,) rad/s, c (rad); p (5, 5) its covariance."""

    def __init__(self, tau_acc_s: float, bias_sigma_rads: float) -> None:
        self.tau_s, self.bias_sigma = float(tau_acc_s), float(bias_sigma_rads)
        self.x = np.zeros(5)
        self.p: np.ndarray | None = None
        self.t_s = 0.0
        self.up = np.array([0.0, 0.0, 1.0])

    def update(self, piece: PieceField, disturbed: bool, up: np.ndarray, tilt_rad: float) -> np.ndarray:
        """One piece (``PieceField``), whether vqf found its field disturbed, the earth's up axis in body axes (3,)
        at the piece's end and the tilt's uncertainty (rad). Returns the bias (3,) rad/s learnt, body axes, to be
        added to vqf's estimate. The prediction and the update are ``magnet._kernels.drift_step``."""
        t, up, z = piece.t_s, np.asarray(up, dtype=float), piece.heading_rad
        dip = min(math.atan2(abs(piece.vertical), piece.horizontal), math.radians(MAX_DIP_DEG))
        sigma_c = math.hypot(math.radians(TILT_ERROR_DEG), tilt_rad) * math.tan(dip)
        if self.p is None:  # starts with the first piece whose field vqf trusts
            if disturbed:
                return np.zeros(3)
            self.x, self.t_s, self.up = np.array([z, 0.0, 0.0, 0.0, 0.0]), t, up
            self.p = np.diag([math.radians(HEADING_NOISE_DEG) ** 2, *[self.bias_sigma**2] * 3, sigma_c**2])
            return np.zeros(3)
        dt = max(t - self.t_s, 0.0)
        decay = math.exp(-dt / self.tau_s)
        noise = np.array([ANGLE_RANDOM_WALK**2 * dt, *[BIAS_RANDOM_WALK**2 * dt] * 3, sigma_c**2 * (1.0 - decay**2)])
        measured = math.radians(HEADING_NOISE_DEG) ** 2 / piece.count
        _kernels.drift_step(self.x, self.p, dt, self.tau_s, (up + self.up) / 2.0, noise, z, measured, not disturbed)
        self.t_s, self.up = t, up
        if disturbed:
            return np.zeros(3)
        learnt = self.x[1:4].copy()
        self.x[1:4] = 0.0
        return learnt

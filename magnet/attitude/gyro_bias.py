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


class Explained:
    """How well the velocity explains the accelerometer: what is left of the accelerometer once the velocity's
    acceleration is taken out, less gravity along the filter's vertical, averaged over each piece (0.1 s: vibration
    averages out), its square averaged over ``EXPLAINED_TIME_S``. A car or a multirotor leaves 0.2-0.5 m/s^2 (the
    aiding's noise, road and rotor vibration); a hand's figure 8 or a tumble off its centre 3-6 m/s^2: motion faster
    than a 10 Hz velocity with a 1 s difference can follow. ``mean_square`` (m/s^2)^2, None before the first piece.

    Its numbers live in ``store`` (2,): whether a mean is held, the mean square (a view into the aided filter's
    state, whose compiled loop runs the same ``magnet._kernels.explained_update``; a new array when alone)."""

    def __init__(self, store: np.ndarray | None = None) -> None:
        self.store = np.zeros(2) if store is None else store
        self.store[:] = 0.0

    @property
    def mean_square(self) -> float | None:
        return float(self.store[1]) if self.store[0] else None

    def update(self, left_ms2: float, seconds: float) -> float:
        """A piece: |mean(acc - g up)| (m/s^2) over its samples (the accelerometer fed and the vertical, body axes,
        vqf's frames: ``magnet._kernels.piece_figures``) and its length in seconds. Returns the residual's RMS so
        far (m/s^2)."""
        return _kernels.explained_update(self.store, float(left_ms2), float(seconds), EXPLAINED_TIME_S)


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


#: the drift filter's figures in the order the compiled step takes them (``magnet._kernels.drift_update``)
DRIFT_FIGURES = np.array([HEADING_NOISE_DEG, TILT_ERROR_DEG, ANGLE_RANDOM_WALK, BIAS_RANDOM_WALK, MAX_DIP_DEG])
#: the numbers of one drift filter: started, t_s, up (3), tau_s, bias_sigma, x (5), p (5 x 5)
DRIFT_SIZE = 37


class HeadingDrift:
    """The Kalman filter of the module docstring for one device. ``tau_acc_s``: vqf's tauAcc (s);
    ``bias_sigma_rads``: the initial uncertainty of each axis of the gyroscope bias (rad/s, vqf's biasSigmaInit).
    State x (5,): phi (rad), the bias left over in body axes (3,) rad/s, c (rad); p (5, 5) its covariance (None
    before the first piece whose field vqf trusts).

    Its numbers live in ``store`` (``DRIFT_SIZE``,): started, the last piece's time (s), its up axis (3), tau_s,
    bias_sigma, x, p row-major (a view into the aided filter's state, whose compiled loop runs the same
    ``magnet._kernels.drift_update``; a new array when alone)."""

    def __init__(self, tau_acc_s: float, bias_sigma_rads: float, store: np.ndarray | None = None) -> None:
        self.store = np.zeros(DRIFT_SIZE) if store is None else store
        self.store[:] = 0.0
        self.store[4] = 1.0  # up: z
        self.store[5], self.store[6] = float(tau_acc_s), float(bias_sigma_rads)

    def reset(self) -> None:
        """Forget everything but tau_s and bias_sigma (starts afresh with the next trusted piece)."""
        self.__init__(self.tau_s, self.bias_sigma, self.store)  # type: ignore[misc]

    @property
    def tau_s(self) -> float:
        return float(self.store[5])

    @tau_s.setter
    def tau_s(self, value: float) -> None:
        self.store[5] = float(value)

    @property
    def bias_sigma(self) -> float:
        return float(self.store[6])

    @property
    def t_s(self) -> float:
        return float(self.store[1])

    @property
    def up(self) -> np.ndarray:
        return self.store[2:5]

    @property
    def x(self) -> np.ndarray:
        return self.store[7:12]

    @property
    def p(self) -> np.ndarray | None:
        return self.store[12:37].reshape(5, 5) if self.store[0] else None

    def update(self, piece: PieceField, disturbed: bool, up: np.ndarray, tilt_rad: float) -> np.ndarray:
        """One piece (``PieceField``), whether vqf found its field disturbed, the earth's up axis in body axes (3,)
        at the piece's end and the tilt's uncertainty (rad). Returns the bias (3,) rad/s learnt, body axes, to be
        added to vqf's estimate.

        The first piece whose field vqf trusts starts the filter: x = (z, 0, 0, 0, 0), p diagonal (the heading's
        noise, bias_sigma^2 on each bias axis, sigma_c^2). Each later one: sigma_c = hypot(TILT_ERROR, tilt) tan(dip),
        dip the field's (at most ``MAX_DIP_DEG``); the process noise over dt from the last piece (the random walks,
        sigma_c^2 (1 - exp(-2 dt / tau))); the step ``magnet._kernels.drift_step`` with the mean of the two up axes
        and the measurement's variance HEADING_NOISE^2 / count; the bias x[1:4] learnt is handed back and zeroed
        (none while disturbed). Compiled: ``magnet._kernels.drift_update``."""
        learnt = _kernels.drift_update(
            self.store,
            DRIFT_FIGURES,
            piece.t_s,
            float(piece.count),
            piece.heading_rad,
            piece.horizontal,
            piece.vertical,
            bool(disturbed),
            np.asarray(up, dtype=float),
            float(tilt_rad),
        )
        return np.array(learnt)

"""The compass's heading and gyroscope bias about the vertical weighed by how well each is known (``BiasWalk``;
docs/compass.md, "The bias about the vertical learnt on"; docs/field-calibration.md, "The gyroscope's bias moving
after the record").

After a record, vqf's magnetic offset ``delta`` follows the field's angle in vqf's 6D frame through a loop of time
constant tauMag, and the bias loop (``heading_bias``) moves the bias about the vertical by delta's changes over an
integral time. Together they are a Kalman filter of two states, the 6D frame's heading against the field (psi) and
the bias about the vertical (b, which drifts psi), with the field's angle as the measurement. What its gains should be
follows from two figures: the field angle's error (a walker's tilt times tan(dip): ``FIELD_SIGMA_DEG``, correlated
over ``FIELD_CORRELATION_S``; as a white noise of density R = 2 sigma^2 tau_c) and how fast a gyroscope's bias moves
(a random walk of density Q = ``WALK_DPS``^2 / ``WALK_EVERY_S``: a phone's bias moves with its temperature, and an
operating system's bias-corrected gyroscope redraws its residual every few tens of seconds). The covariance P of
(psi, b) grows by Q over each piece of samples and shrinks where the loop learns (a piece with no turn and no
disturbance); the gains are then K = P (1, 0)' / (P_psi + R / dt), and

- vqf's tauMag is dt / K_psi (held within ``MIN_TAU_S`` .. ``MAX_TAU_S``): long while the bias is well known, short
  once it has had time to move (after a record, a long turn, a disturbance);
- the bias about the vertical moves by K_b times the innovation, read off delta's change over the piece
  (innovation = change x tauMag / dt, vqf's own gain undone).

At the steady state tauMag = (R / Q)^(1/4) / sqrt(2) and the integral time 2 tauMag (13 s and 26 s with the figures
here), and where a bias never moves (Q = 0) the gains fall on as 1 / t: what the magnetic gain from the drift
(``mag_gain``) did by looking at delta's slope, now from the bias's own uncertainty. It starts at a record
(``causal_drift.take_drift``) with the heading known to ``START_HEADING_DEG`` and the bias to ``START_BIAS_DPS``.

Plain Python, per device a 2 x 2 matrix; one step a fused batch.
"""

from __future__ import annotations

import math

import numpy as np

#: whether the compass weighs its bias loop and tauMag this way (else: the loop's fixed integral time, ``mag_gain``).
#: Off: the absolute heading was better on every bias reality measured, but after the constant offset the runs whose
#: bias holds still lost a few hundredths (and running, texting past doors a tenth or more on tuning seeds 1-3):
#: docs/field-calibration.md, "The gyroscope's bias moving after the record"
ENABLED = False
#: the field angle's error in a walk (deg, one sigma) and its correlation time (s)
FIELD_SIGMA_DEG = 3.0
FIELD_CORRELATION_S = 2.0
#: the gyroscope's bias about the vertical moves like a random walk of this many deg/s every this many seconds
WALK_DPS = 0.1
WALK_EVERY_S = 30.0
#: at a record: the heading (deg) and the bias left after the history's fit (deg/s), one sigma
START_HEADING_DEG = 3.0
START_BIAS_DPS = 0.1
#: the range of tauMag (s)
MIN_TAU_S = 3.0
MAX_TAU_S = 60.0


class BiasWalk:
    """The covariance of the module docstring for one filter, from a record on."""

    def __init__(self) -> None:
        self.p = np.diag([math.radians(START_HEADING_DEG) ** 2, math.radians(START_BIAS_DPS) ** 2])
        self.field_density = 2.0 * math.radians(FIELD_SIGMA_DEG) ** 2 * FIELD_CORRELATION_S  # rad^2 s
        self.walk_density = math.radians(WALK_DPS) ** 2 / WALK_EVERY_S  # rad^2 / s^3

    def predict(self, dt_s: float) -> None:
        """``dt_s`` seconds on: psi drifts by b dt, b walks."""
        move = np.array([[1.0, dt_s], [0.0, 1.0]])
        self.p = move @ self.p @ move.T + np.diag([0.0, self.walk_density * dt_s])

    def learn(self, dt_s: float, delta_change_rad: float, tau_s: float) -> tuple[float, float]:
        """A piece of ``dt_s`` seconds learnt from, over which vqf's delta moved by ``delta_change_rad`` with tauMag
        ``tau_s``: (the change of the bias about the vertical, rad/s, to add along the body's up axis; the tauMag to
        set, s). Call after ``predict``."""
        dt = max(float(dt_s), 1e-6)
        innovation = float(delta_change_rad) * float(tau_s) / dt
        gain = self.p[:, 0] / (self.p[0, 0] + self.field_density / dt)
        self.p = self.p - np.outer(gain, self.p[0, :])
        tau = min(max(dt / float(gain[0]), MIN_TAU_S), MAX_TAU_S)
        return -float(gain[1]) * innovation, tau

    @property
    def bias_sigma_dps(self) -> float:
        """How well the bias about the vertical is known now (deg/s, one sigma)."""
        return math.degrees(math.sqrt(max(float(self.p[1, 1]), 0.0)))

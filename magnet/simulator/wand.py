"""A hand-held wand: an IMU box held in a hand and turned, as in the BROAD trials (issue 26's "device-calibrated
wand"), drawn from the seed.

The box starts at rest in a pose near level (on a table: pitch and roll within +-5 deg, any heading) and goes
through a plan of eased segments (``magnet.simulator.plan``: the quintic smoothstep, so the body rate and its
derivative are continuous), each a turn by an angle about one axis fixed in the body, from the attitude the last one
left:

- rest: held still in the hand, 0.5-3 s;
- slow rotation: about one of the box's own axes (x, y or z, either sense), 45-270 deg at a peak rate of 20-90 deg/s;
- fast rotation: about one of its axes, 90-540 deg at a peak rate of 200-500 deg/s;
- tumble: about an axis in a random direction, 180-720 deg at a peak rate of 100-350 deg/s;
- back home: the one turn that brings the box back to its starting pose, at 60-150 deg/s, then a rest on the table
  (set down: no tremor).

So, as in BROAD, the box turns slowly and fast about every axis and rests between, and over two minutes its field
and gravity directions cover much of the sphere. On top, while in the hand: its tremor (+-0.1 deg at 6-10 Hz about
each axis, a few deg/s).
Its centre sits 3-10 cm from the wrist's centre of rotation (centripetal and tangential acceleration) and the hand
wanders +-2 cm at 0.1-0.4 Hz. Attitudes are rotation matrices (no gimbal lock); the linear acceleration is the second
derivative of the box's position.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.frames import euler_to_matrix, matrix_to_euler
from magnet.simulator.motion import MotionModel
from magnet.simulator.plan import Segments, Tones, plateau, smoother
from magnet.simulator.plan import random_sign as _sign

#: segment kind -> how often it comes after a turn (a rest always follows "home")
KIND_ODDS = {"rest": 0.2, "slow": 0.3, "fast": 0.2, "tumble": 0.15, "home": 0.15}
SLOW_DEG, SLOW_RATE_DEG_S = (45.0, 270.0), (20.0, 90.0)
FAST_DEG, FAST_RATE_DEG_S = (90.0, 540.0), (200.0, 500.0)
TUMBLE_DEG, TUMBLE_RATE_DEG_S = (180.0, 720.0), (100.0, 350.0)
HOME_RATE_DEG_S = (60.0, 150.0)
REST_S = (0.5, 3.0)
#: peak rate of the quintic smoothstep over an angle A in time T: 1.875 A / T
PEAK_FACTOR = 1.875


def _rodrigues(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) by angles (N,) radians about unit axes (N, 3)."""
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    zero = np.zeros_like(x)
    k = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)
    s, c = np.sin(angle_rad)[:, None, None], np.cos(angle_rad)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def _axis_angle(rotation: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit axis (3,), angle deg in [0, 180]) of one rotation (3, 3); any axis for the identity."""
    angle = float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    norm = float(np.linalg.norm(axis))
    if norm < 1e-9:  # no turn, or half a turn: the axis from the symmetric part
        if angle < 1.0:
            return np.array([1.0, 0.0, 0.0]), 0.0
        column = int(np.argmax(np.diag(rotation)))
        axis = rotation[:, column] + np.eye(3)[column]
        norm = float(np.linalg.norm(axis))
    return axis / norm, angle


class WandModel(MotionModel):
    """A box turned by hand about every axis, with rests (see the module docstring)."""

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        super().__init__(rng, declination_deg)
        self.home = euler_to_matrix(rng.uniform(0.0, 360.0), rng.uniform(-5.0, 5.0), rng.uniform(-5.0, 5.0))
        self.plan = Segments(rng.spawn(1)[0], self._draw)
        self.tremor_deg = Tones(rng, 3, 2, (6.0, 10.0), 0.1)
        self.wander_m = Tones(rng, 3, 2, (0.1, 0.4), 0.02)
        direction = rng.standard_normal(3)
        self.lever_m = direction / np.linalg.norm(direction) * rng.uniform(0.03, 0.10)

    def _draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        if last is None:
            start = self.home
        else:
            start = np.reshape([last[f"r{i}"] for i in range(9)], (3, 3))
            turn = _rodrigues(np.array([[last["ax"], last["ay"], last["az"]]]), np.radians([last["angle"]]))[0]
            start = start @ turn
        row: dict[str, Any] = {f"r{i}": float(v) for i, v in enumerate(start.ravel())}
        row.update(ax=1.0, ay=0.0, az=0.0, angle=0.0, kind=0.0, table=0.0)
        if last is None or last["kind"] == 4.0:  # at rest on the table first, and after home
            row["table"] = 1.0
            return rng.uniform(*REST_S) + (1.5 if last is None else 0.0), row
        kind = str(rng.choice(list(KIND_ODDS), p=list(KIND_ODDS.values())))
        row["kind"] = float(list(KIND_ODDS).index(kind))
        if kind == "rest":
            return rng.uniform(*REST_S), row
        if kind == "home":
            axis, angle = _axis_angle(start.T @ self.home)
            if angle < 5.0:
                row["kind"] = 0.0
                return rng.uniform(*REST_S), row
            rate = rng.uniform(*HOME_RATE_DEG_S)
        elif kind == "tumble":
            axis = rng.standard_normal(3)
            axis /= np.linalg.norm(axis)
            angle, rate = rng.uniform(*TUMBLE_DEG), rng.uniform(*TUMBLE_RATE_DEG_S)
        else:
            axis = np.eye(3)[int(rng.integers(3))]
            span, rates = (SLOW_DEG, SLOW_RATE_DEG_S) if kind == "slow" else (FAST_DEG, FAST_RATE_DEG_S)
            angle, rate = rng.uniform(*span), rng.uniform(*rates)
        angle *= _sign(rng) if kind != "home" else 1.0
        row.update(ax=float(axis[0]), ay=float(axis[1]), az=float(axis[2]), angle=float(angle))
        return PEAK_FACTOR * abs(angle) / rate, row

    def _rotation(self, t: np.ndarray) -> np.ndarray:
        """Body -> magnetic NED (N, 3, 3) at t, tremor included."""
        row, u, _ = self.plan.locate(np.asarray(t, dtype=float))
        start = np.stack([row[f"r{i}"] for i in range(9)], axis=-1).reshape(-1, 3, 3)
        axis = np.stack([row["ax"], row["ay"], row["az"]], axis=-1)
        turn = _rodrigues(axis, np.radians(row["angle"] * smoother(u)))
        tremor = self.tremor_deg(t) * (1.0 - row["table"] * plateau(u, 0.2))[:, None]  # none on the table
        return start @ turn @ euler_to_matrix(tremor[:, 0], tremor[:, 1], tremor[:, 2])

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return matrix_to_euler(self._rotation(np.asarray(t, dtype=float)))

    def _position(self, t: np.ndarray) -> np.ndarray:
        """The box's centre (N, 3) m, geographic NED, from the wrist's mean place."""
        return np.einsum("nij,j->ni", self.rotation(t), self.lever_m) + self.wander_m(t)

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        return self._second_derivative(self._position, np.asarray(t, dtype=float))

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """The box's velocity (centimetres per second: a receiver on it would read about none)."""
        return self._first_derivative(self._position, np.asarray(t, dtype=float))


#: trajectory name -> model
MODELS: dict[str, type[MotionModel]] = {"wand": WandModel}

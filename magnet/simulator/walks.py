"""A person walking or running with a phone: in a trouser pocket, in a swinging hand, held in front to read
(texting), at the ear (phoning), or in the hand while running. Gait and path from the seed.

The path (``magnet.simulator.paths``): straight legs of 4-15 s at a steady pace (walking 1.1-1.6 m/s, running
2.6-3.6 m/s) and corners: turns of 45, 90, 135 or 180 deg (90 most often, either side) at a peak course rate of
70-120 deg/s (60-100 running), so the walk's heading changes as a real one does.

The gait, at the step frequency f (walking 1.6-2.0 Hz, running 2.5-3.0 Hz; stride = two steps at f/2), in the
course frame (x forward, y right, z down), with phase phi = 2 pi f t:
- the hip bounces vertically by +-2-3.5 cm at f (+-3.5-5 cm running: about +-3 and +-12 m/s^2), surges forward by
  +-1-2 cm at f and sways sideways by +-1.5-3 cm at f/2;
- the trunk turns +-3-6 deg (yaw) and rolls +-2-4 deg at f/2, and pitches +-1-2 deg at f.
The phone, from the trunk:
- pocket: on the thigh 15-25 cm below the hip, the thigh swinging +-20-25 deg about the hip at f/2; the phone's long
  axis along the thigh (top up or down), screen facing in or out, a few degrees askew, jiggling +-3 deg at f;
- hand: the arm a pendulum from the shoulder (60-70 cm), swinging +-25-40 deg at f/2 against the leg of its side,
  the wrist lagging +-10 deg; the phone along the hand or across it, screen to the thigh or away;
- texting: held 30 cm in front of the chest, top forward, tilted up 30-45 deg (pitch), the arms halving the trunk's
  sway, the eyes' look wandering +-5 deg (yaw) and +-3 deg (pitch) over 10-20 s;
- phoning: at the ear (right or left), the long axis 50-70 deg from horizontal with the top up and back, screen to
  the head; the head turning +-8 deg slowly and nodding with the steps;
- running: in a hand at the end of a bent arm (elbow 70-100 deg), the upper arm swinging +-35-50 deg at f/2.
Attitudes are rotation matrices (no gimbal lock: a phone in a pocket stands upright), and the linear acceleration
is the path's plus the second derivative of the phone's position about the path's point.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.frames import axis_angle_matrix, euler_to_matrix, matrix_to_euler
from magnet.simulator.paths import PathModel
from magnet.simulator.plan import Tones
from magnet.simulator.plan import random_sign as _sign

#: pace -> (speed m/s, step frequency Hz, hip bounce m, course peak rate deg/s) ranges
PACES = {
    "walk": {"speed": (1.1, 1.6), "step_hz": (1.6, 2.0), "bounce": (0.02, 0.035), "turn_rate": (70.0, 120.0)},
    "run": {"speed": (2.6, 3.6), "step_hz": (2.5, 3.0), "bounce": (0.035, 0.05), "turn_rate": (60.0, 100.0)},
}
#: corners of a walk, degrees, and how often each comes
CORNERS_DEG = (45.0, 90.0, 135.0, 180.0)
CORNER_ODDS = (0.2, 0.55, 0.1, 0.15)
STRAIGHT_S = (4.0, 15.0)


def mount(x_image: Any, z_image: Any) -> np.ndarray:
    """The rotation (3, 3) body -> segment that takes the phone's x axis (its top) to ``x_image`` and its z axis (out
    of its back) to ``z_image`` (made perpendicular to x), y = z x x."""
    x = np.asarray(x_image, dtype=float)
    x = x / np.linalg.norm(x)
    z = np.asarray(z_image, dtype=float)
    z = z - (z @ x) * x
    z = z / np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z])


def _askew(rng: np.random.Generator, degrees: float) -> np.ndarray:
    """A rotation (3, 3) of up to ``degrees`` about a random axis."""
    return axis_angle_matrix(rng.standard_normal(3), rng.uniform(0.0, degrees))


def _ry(angle_deg: np.ndarray) -> np.ndarray:
    zero = np.zeros_like(angle_deg)
    return euler_to_matrix(zero, angle_deg, zero)


def _at(rotation: np.ndarray, vector: Any) -> np.ndarray:
    """rotation (N, 3, 3) @ vector (3,) -> (N, 3)."""
    return np.einsum("nij,j->ni", rotation, np.asarray(vector, dtype=float))


class WalkModel(PathModel):
    """A walker (or runner) with a phone; ``PLACEMENT`` and ``PACE`` name the subclass's (see the module
    docstring)."""

    PACE = "walk"
    PLACEMENT = "pocket"

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        pace = PACES[self.PACE]
        self.speed_ms = rng.uniform(*pace["speed"])
        self.turn_rate_deg = pace["turn_rate"]
        self.step_hz = rng.uniform(*pace["step_hz"])
        self.phase0 = rng.uniform(0.0, 2.0 * np.pi)
        self.bounce_m = rng.uniform(*pace["bounce"])
        self.surge_m, self.sway_m = rng.uniform(0.01, 0.02), rng.uniform(0.015, 0.03)
        self.trunk_deg = np.array([rng.uniform(3.0, 6.0), rng.uniform(1.0, 2.0), rng.uniform(2.0, 4.0)])
        self.side = _sign(rng)  # the phone's side: +1 right, -1 left
        self.course0_deg = rng.uniform(0.0, 360.0)
        self.tremor_deg = Tones(rng, 3, 2, (6.0, 10.0), 0.3)
        self.setup(rng)
        super().__init__(rng, declination_deg)

    def setup(self, rng: np.random.Generator) -> None:
        """Draw the placement's own parameters (a subclass's)."""

    def draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        course = self.course0_deg if last is None else last["yaw0"] + last["dyaw"]
        row = {"yaw0": course, "dyaw": 0.0, "v0": self.speed_ms, "dv": 0.0}
        if last is None or last["dyaw"]:
            return rng.uniform(*STRAIGHT_S), row
        corner = float(rng.choice(CORNERS_DEG, p=CORNER_ODDS)) + rng.uniform(-10.0, 10.0)
        row["dyaw"] = _sign(rng) * corner
        return 1.875 * corner / rng.uniform(*self.turn_rate_deg), row

    def gait(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(step phase phi (N,) rad, trunk rotation (N, 3, 3) -> course frame, hip position (N, 3) m)."""
        phi = 2.0 * np.pi * self.step_hz * t + self.phase0
        yaw, pitch, roll = self.trunk_deg
        trunk = euler_to_matrix(yaw * np.sin(phi / 2.0), pitch * np.sin(phi + 0.5), roll * np.sin(phi / 2.0 + 1.0))
        hip = np.stack(
            [self.surge_m * np.sin(phi + np.pi / 4.0), self.sway_m * np.sin(phi / 2.0), -self.bounce_m * np.cos(phi)],
            axis=-1,
        )
        return phi, trunk, hip

    def local(self, t: np.ndarray, path: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        phi, trunk, hip = self.gait(t)
        rotation, position = self.place(t, phi, trunk, hip)
        tremor = self.tremor_deg(t)
        return rotation @ euler_to_matrix(tremor[:, 0], tremor[:, 1], tremor[:, 2]), position

    def place(
        self, t: np.ndarray, phi: np.ndarray, trunk: np.ndarray, hip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - abstract
        """The phone's rotation (N, 3, 3) body -> course frame and position (N, 3) m, from the gait."""
        raise NotImplementedError


class PocketWalk(WalkModel):
    """Phone in a front trouser pocket, on the thigh."""

    PLACEMENT = "pocket"

    def setup(self, rng: np.random.Generator) -> None:
        self.thigh_m = rng.uniform(0.15, 0.25)
        self.swing_deg = rng.uniform(20.0, 25.0)
        top, back = _sign(rng), _sign(rng)
        self.mount = mount([0.0, 0.0, -top], [back, 0.0, 0.0]) @ _askew(rng, 10.0)
        self.jiggle_deg = rng.uniform(1.5, 3.0)

    def place(
        self, t: np.ndarray, phi: np.ndarray, trunk: np.ndarray, hip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        swing = self.swing_deg * np.sin(phi / 2.0 + (0.0 if self.side > 0 else np.pi))
        thigh = trunk @ _ry(swing + 5.0)
        position = hip + _at(trunk, [0.0, 0.1 * self.side, 0.0]) + _at(thigh, [0.0, 0.0, self.thigh_m])
        jiggle = euler_to_matrix(0.0 * phi, self.jiggle_deg * np.sin(phi + 1.3), self.jiggle_deg * np.cos(phi))
        return thigh @ self.mount @ jiggle, position


class HandWalk(WalkModel):
    """Phone in a hand swinging at the side."""

    PLACEMENT = "hand"
    ELBOW_DEG = (0.0, 0.0)  # a straight arm
    ARM_M = (0.6, 0.7)
    SWING_DEG = (25.0, 40.0)

    def setup(self, rng: np.random.Generator) -> None:
        self.arm_m = rng.uniform(*self.ARM_M)
        self.swing_deg = rng.uniform(*self.SWING_DEG)
        self.elbow_deg = rng.uniform(*self.ELBOW_DEG)
        along = [0.0, 0.0, 1.0] if rng.random() < 0.5 else [1.0, 0.0, 0.0]  # along the hand, or across it
        self.mount = mount(along, [0.0, _sign(rng), 0.0]) @ _askew(rng, 10.0)

    def place(
        self, t: np.ndarray, phi: np.ndarray, trunk: np.ndarray, hip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        against = np.pi if self.side > 0 else 0.0  # the arm swings against the leg of its side
        arm = trunk @ _ry(self.swing_deg * np.sin(phi / 2.0 + against))
        hand = arm @ _ry(self.elbow_deg + 10.0 * np.sin(phi / 2.0 + against - 0.6))
        shoulder = hip + _at(trunk, [0.0, 0.2 * self.side, -0.45])
        if self.elbow_deg:  # upper arm, then the forearm bent forward at the elbow
            position = shoulder + _at(arm, [0.0, 0.0, 0.28]) + _at(hand, [0.0, 0.0, self.arm_m - 0.28])
        else:
            position = shoulder + _at(arm, [0.0, 0.0, self.arm_m])
        return hand @ self.mount, position


class TextingWalk(WalkModel):
    """Phone held in front to read, tilted up 30-45 deg."""

    PLACEMENT = "texting"

    def setup(self, rng: np.random.Generator) -> None:
        self.tilt_deg = rng.uniform(30.0, 45.0)
        self.look_hz = rng.uniform(0.05, 0.1, 2)
        self.look_phase = rng.uniform(0.0, 2.0 * np.pi, 2)

    def place(
        self, t: np.ndarray, phi: np.ndarray, trunk: np.ndarray, hip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        half = euler_to_matrix(*(0.5 * np.asarray(a) for a in _euler_of(trunk)))  # the arms halve the trunk's sway
        look = 2.0 * np.pi * self.look_hz[:, None] * t[None] + self.look_phase[:, None]
        held = euler_to_matrix(5.0 * np.sin(look[0]), self.tilt_deg + 3.0 * np.sin(look[1]), 0.0 * t)
        position = hip + _at(trunk, [0.3, 0.05 * self.side, -0.25])
        return half @ held, position


class PhoningWalk(WalkModel):
    """Phone at the ear."""

    PLACEMENT = "phoning"

    def setup(self, rng: np.random.Generator) -> None:
        elevation = np.radians(rng.uniform(50.0, 70.0))
        self.mount = mount([-np.cos(elevation), 0.0, -np.sin(elevation)], [0.0, self.side, 0.0]) @ _askew(rng, 5.0)
        self.head_hz, self.head_phase = rng.uniform(0.04, 0.1), rng.uniform(0.0, 2.0 * np.pi)

    def place(
        self, t: np.ndarray, phi: np.ndarray, trunk: np.ndarray, hip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        head = euler_to_matrix(
            8.0 * np.sin(2.0 * np.pi * self.head_hz * t + self.head_phase), 1.5 * np.sin(phi + 2.0), 0.0 * t
        )
        position = hip + _at(trunk, [0.05, 0.08 * self.side, -0.65])
        return head @ self.mount, position


class RunningHand(HandWalk):
    """Running, the phone in a hand at the end of a bent arm."""

    PACE = "run"
    PLACEMENT = "running"
    ELBOW_DEG = (70.0, 100.0)
    ARM_M = (0.5, 0.6)
    SWING_DEG = (35.0, 50.0)


def _euler_of(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-Y-X angles (deg) of rotations (N, 3, 3), yaw in (-180, 180] (small rotations stay small)."""
    yaw, pitch, roll = matrix_to_euler(rotation)
    return (yaw + 180.0) % 360.0 - 180.0, pitch, roll


#: trajectory name -> walker
MODELS: dict[str, type[WalkModel]] = {
    "walk-pocket": PocketWalk,
    "walk-hand": HandWalk,
    "walk-texting": TextingWalk,
    "walk-phoning": PhoningWalk,
    "running": RunningHand,
}

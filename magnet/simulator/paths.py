"""Motions along a path on the ground or the water: a course and a speed that change in eased segments, and a motion
of the device about the path's point (a walker's gait and limbs, a boat's waves, a robot's floor).

A ``PathModel`` draws ``Segments`` whose rows hold the course at the start (``yaw0``, magnetic degrees), its change
(``dyaw``), the speed at the start (``v0``, m/s) and its change (``dv``), each eased by the quintic smoothstep, so the
course rate and the speed's derivative are continuous. From them, in closed form:

    course(t) = yaw0 + dyaw s(u),  speed(t) = v0 + dv s(u),   s the smoothstep, u in [0, 1] within the segment
    path acceleration = dspeed/dt forward + speed * dcourse/dt to the right of the course     (NED, horizontal)
    distance along the path = sum of whole segments + duration (v0 u + dv (2.5 u^4 - 3 u^5 + u^6))

A subclass gives the device's motion about the path's point in the course frame (x along the course, y right, z
down): ``local(t)`` -> (rotation (N, 3, 3) device body -> course frame, position (N, 3) m of the device). The
attitude is Rz(course) @ local rotation, and the linear acceleration the path's plus the second derivative of
Rz(course) @ local position (central differences: every local motion here is smooth).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.frames import euler_to_matrix, matrix_to_euler
from magnet.simulator.motion import MotionModel
from magnet.simulator.plan import Segments, segment_path


def course_matrix(course_deg: np.ndarray) -> np.ndarray:
    """Rz(course) (N, 3, 3): the course frame (x along the course, y right, z down) -> NED."""
    zero = np.zeros_like(course_deg)
    return euler_to_matrix(course_deg, zero, zero)


class PathModel(MotionModel):
    """A course and a speed in eased segments (``draw``, a subclass's) and the device's motion about the path's
    point (``local``, a subclass's); see the module docstring."""

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        super().__init__(rng, declination_deg)
        self.plan = Segments(rng.spawn(1)[0], self.draw)
        self._distance_starts: list[float] = [0.0]  # distance along the path at each segment's start, m

    # -------------------------------------------------------------------------------------------- for subclasses
    def draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        raise NotImplementedError  # pragma: no cover - abstract

    def local(self, t: np.ndarray, path: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(rotation (N, 3, 3) body -> course frame, position (N, 3) m in the course frame) at t; ``path`` holds
        course_deg, speed_ms, along_ms2, lateral_ms2 (N,) at t."""
        raise NotImplementedError  # pragma: no cover - abstract

    # ------------------------------------------------------------------------------------------------ the path
    def path(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """The path at t (``magnet.simulator.motion.segment_path``)."""
        return segment_path(self.plan, self._distance_starts, np.asarray(t, dtype=float))

    # ----------------------------------------------------------------------------------------- MotionModel API
    def _rotation_and_position(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body -> magnetic NED (N, 3, 3) and the device's offset from the path's point in NED (N, 3) m."""
        path = self.path(t)
        rotation, position = self.local(t, path)
        course = course_matrix(path["course_deg"])
        return course @ rotation, np.einsum("nij,nj->ni", course, position)

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rotation, _ = self._rotation_and_position(np.asarray(t, dtype=float))
        return matrix_to_euler(rotation)

    def device_offset(self, t: np.ndarray) -> np.ndarray:
        """The device's position (N, 3) m NED (geographic) from the path's point at t."""
        _, position = self._rotation_and_position(np.asarray(t, dtype=float))
        return self._geographic(position)

    def _geographic(self, vectors_ned: np.ndarray) -> np.ndarray:
        """Magnetic NED vectors (N, 3) turned to geographic NED by the declination."""
        zero = np.zeros(len(vectors_ned))
        return np.einsum("nij,nj->ni", course_matrix(zero + self.declination_deg), vectors_ned)

    def _path_vectors(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors (N, 3) geographic NED along the course and to its right."""
        course = np.radians(self.path(t)["course_deg"] + self.declination_deg)
        zero = np.zeros_like(course)
        forward = np.stack([np.cos(course), np.sin(course), zero], axis=-1)
        right = np.stack([-np.sin(course), np.cos(course), zero], axis=-1)
        return forward, right

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        path = self.path(t)
        forward, right = self._path_vectors(t)
        acc = path["along_ms2"][:, None] * forward + path["lateral_ms2"][:, None] * right
        return acc + self._second_derivative(self.device_offset, t)

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """The device's velocity: along the path plus its motion about the path's point."""
        t = np.asarray(t, dtype=float)
        forward, _ = self._path_vectors(t)
        return self.path(t)["speed_ms"][:, None] * forward + self._first_derivative(self.device_offset, t)

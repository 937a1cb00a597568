"""Planar vehicles: a boat and a ground robot. Both only yaw, with small roll and pitch (``magnet.simulator.paths``).

- BoatModel: a steady 2-6 m/s, straight legs of 5-20 s and turns of 90-360 deg (a full circle now and then) at a
  peak course rate of 8-15 deg/s; waves roll it +-2-5 deg (0.12-0.3 Hz), pitch it +-1-2.5 deg (0.15-0.35 Hz), yaw it
  +-1-2 deg and heave it +-0.3-0.6 m (0.1-0.25 Hz); it heels 2 deg outward per m/s^2 of turn; the sensor sits 1-2 m
  above the roll centre (the waves' rolling moves it sideways).
- RobotModel: a wheeled robot indoors or on a yard: stands still (1-4 s), turns in place (90-270 deg at a peak of
  30-90 deg/s), drives off to 0.3-1.2 m/s, cruises (2-8 s), drives arcs (30-120 deg at 20-45 deg/s) and stops (at
  most 0.8 m/s^2). The floor tilts it: +-1.5-2.5 deg over 5-20 m and +-0.3-0.6 deg bumps over 0.3-1 m, both
  functions of the distance driven (standing, it stays as it is), plus 0.5 deg of pitch per m/s^2 of speed change;
  the sensor sits 0.3 m above the axles, 5-20 cm ahead of the turning centre; wheel vibration (15-30 Hz) grows with
  speed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.frames import euler_to_matrix
from magnet.simulator.paths import PathModel
from magnet.simulator.plan import Tones
from magnet.simulator.plan import random_sign as _sign


class BoatModel(PathModel):
    """A boat on waves (see the module docstring)."""

    HEEL_DEG_PER_MS2 = 2.0

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        self.speed_ms = rng.uniform(2.0, 6.0)
        self.course0_deg = rng.uniform(0.0, 360.0)
        self.roll_deg = Tones(rng, 1, 2, (0.12, 0.3), rng.uniform(2.0, 5.0) / 2.0)
        self.pitch_deg = Tones(rng, 1, 2, (0.15, 0.35), rng.uniform(1.0, 2.5) / 2.0)
        self.yaw_deg = Tones(rng, 1, 2, (0.08, 0.2), rng.uniform(1.0, 2.0) / 2.0)
        self.heave_m = Tones(rng, 1, 2, (0.1, 0.25), rng.uniform(0.3, 0.6) / 2.0)
        self.mast_m = rng.uniform(1.0, 2.0)
        super().__init__(rng, declination_deg)

    def draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        course = self.course0_deg if last is None else last["yaw0"] + last["dyaw"]
        row = {"yaw0": course, "dyaw": 0.0, "v0": self.speed_ms, "dv": 0.0}
        if last is None or last["dyaw"]:
            return rng.uniform(5.0, 20.0), row
        turn = 360.0 if rng.random() < 0.2 else rng.uniform(90.0, 270.0)
        row["dyaw"] = _sign(rng) * turn
        return 1.875 * turn / rng.uniform(8.0, 15.0), row

    def local(self, t: np.ndarray, path: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        heel = -self.HEEL_DEG_PER_MS2 * path["lateral_ms2"]
        rotation = euler_to_matrix(self.yaw_deg(t)[:, 0], self.pitch_deg(t)[:, 0], self.roll_deg(t)[:, 0] + heel)
        position = np.einsum("nij,j->ni", rotation, [0.0, 0.0, -self.mast_m])
        position[:, 2] += self.heave_m(t)[:, 0]
        return rotation, position


class RobotModel(PathModel):
    """A wheeled ground robot (see the module docstring)."""

    MAX_ALONG_MS2 = 0.8
    PITCH_DEG_PER_MS2 = 0.5
    HEIGHT_M = 0.3

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        self.course0_deg = rng.uniform(0.0, 360.0)
        self.terrain_deg = Tones(rng, 2, 2, (0.05, 0.2), rng.uniform(1.5, 2.5) / 2.0)  # cycles per metre
        self.bumps_deg = Tones(rng, 2, 2, (1.0, 3.0), rng.uniform(0.3, 0.6) / 2.0)
        self.vibration_ms2 = Tones(rng, 3, 2, (15.0, 30.0), (0.15, 0.15, 0.3))
        self.mount_m = np.array([rng.uniform(0.05, 0.2), rng.uniform(-0.05, 0.05), -self.HEIGHT_M])
        super().__init__(rng, declination_deg)

    def _speed_change(self, row: dict[str, Any], target: float, rng: np.random.Generator) -> float:
        row["dv"] = target - row["v0"]
        return max(1.0, 1.875 * abs(row["dv"]) / rng.uniform(0.4, self.MAX_ALONG_MS2))

    def draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        course = self.course0_deg if last is None else last["yaw0"] + last["dyaw"]
        speed = 0.0 if last is None else last["v0"] + last["dv"]
        row = {"yaw0": course, "dyaw": 0.0, "v0": speed, "dv": 0.0}
        choice = rng.random()
        if last is None:
            return rng.uniform(1.0, 2.0), row  # stands, then drives off
        if speed < 1e-9:
            row["v0"] = 0.0
            stood = last["dyaw"] == 0.0 and last["dv"] == 0.0
            if choice < 0.5 and not stood:
                return rng.uniform(1.0, 4.0), row  # stand
            if choice < 0.75 and len(self.plan.rows) > 1:
                turn = rng.uniform(90.0, 270.0)
                row["dyaw"] = _sign(rng) * turn
                return 1.875 * turn / rng.uniform(30.0, 90.0), row  # turn in place
            return self._speed_change(row, rng.uniform(0.3, 1.2), rng), row  # drive off
        if choice < 0.35:
            return rng.uniform(2.0, 8.0), row  # cruise
        if choice < 0.7:
            turn = rng.uniform(30.0, 120.0)
            row["dyaw"] = _sign(rng) * turn
            return 1.875 * turn / rng.uniform(20.0, 45.0), row  # arc
        return self._speed_change(row, 0.0, rng), row  # stop

    def local(self, t: np.ndarray, path: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        tilt = self.terrain_deg(path["distance_m"]) + self.bumps_deg(path["distance_m"])
        pitch = tilt[:, 0] + self.PITCH_DEG_PER_MS2 * path["along_ms2"]
        rotation = euler_to_matrix(0.0 * t, pitch, tilt[:, 1])
        return rotation, np.einsum("nij,j->ni", rotation, self.mount_m)

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        scale = np.clip(self.path(t)["speed_ms"], 0.0, None)[:, None]
        vibration = np.einsum("nij,nj->ni", rotation, self.vibration_ms2(t) * scale)
        return super().linear_acceleration(t, rotation) + vibration


#: trajectory name -> planar vehicle
MODELS: dict[str, type[PathModel]] = {"boat": BoatModel, "robot": RobotModel}

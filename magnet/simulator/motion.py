"""Moving trajectories: attitude and linear acceleration as functions of time, drawn from a seed.

Every model gives, for times t (N,) in seconds, the attitude as Z-Y-X Euler angles (magnetic heading, pitch, roll in
degrees, any values: they are turned into quaternions, never wrapped) and the linear acceleration of the sensor in NED
(N, 3) m/s^2. The simulator (``magnet.simulator.run``) turns them into measurements:

    q_k = quaternion(true heading, pitch, roll at t_k)                    body -> NED, wxyz
    gyr_k = log(q(t_k - dt)* q_k) / dt                                     body frame, rad/s
    acc_k = R_k^T (a_lin,k - g_ned),  g_ned = (0, 0, +9.80665)             specific force, body frame

so integrating the gyroscope, q_k = q_{k-1} exp(gyr_k dt), gives back the attitude exactly (the rate of a sample is
the constant body rate that carries the attitude from the previous sample time to its own, as filters integrate it),
and a level device at rest reads (0, 0, -9.81).

Models (``MODELS``), all deterministic from the generator they are given:
- MultirotorModel: a flight plan of segments (hover, yaw turns of 90-180 deg, 30 deg banks in roll, pitch or both,
  banked turns at 30 deg roll), each eased in and out (quintic smoothstep: continuous angular rate and angular
  acceleration). Thrust along body -z holds altitude (plus a slow climb/descent) and drag (0.4/s times the velocity)
  opposes the motion: a bank first accelerates the craft at g tan(bank) while the accelerometer still reads only
  along z (accelerometer tilt sees a level device), then the speed settles (about 14 m/s at 30 deg) and the
  accelerometer sees the tilt again, through the drag. Vibration: small angular jitter (0.15 deg at 4-12 Hz) and
  body-frame acceleration tones (8-24 Hz).
- CarModel: straights at constant speed, speed changes (to 5-25 m/s or a stop, at most 3 m/s^2) and turns of
  45-120 deg at 5-12 m/s (peak yaw rate 15-30 deg/s, centripetal acceleration at most 3 m/s^2); the linear
  acceleration is the longitudinal dv/dt plus the centripetal v * yaw rate (to the right in a right turn), the body
  rolls outward 0.5 deg per m/s^2 of lateral acceleration and pitches 0.3 deg per m/s^2 of
  longitudinal; road vibration grows with speed (none at rest: a parked car is level and still).
- Figure8Model: a handheld device waved in a figure 8 (position +-0.3 m at 0.35-0.5 Hz, heading +-45 deg, pitch
  +-40 deg, roll +-60 deg) while the person slowly turns around (one turn in 30-50 s); hand tremor.
- FastTumbleModel: tumbling fast about every axis (roll 1-1.6 rev/s, heading 0.5-0.9 rev/s, pitch +-75 deg at
  0.8-1.2 Hz; body rates up to about 1000 deg/s) with the sensor 2-8 cm from the centre of rotation (centripetal and
  tangential acceleration).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from magnet.frames import euler_to_matrix
from magnet.simulator.plan import Segments, Tones, plateau, segment_path, smoother, smoother_rate
from magnet.simulator.plan import random_sign as _sign
from magnet.units import STANDARD_GRAVITY_MS2

G_NED = np.array([0.0, 0.0, STANDARD_GRAVITY_MS2])  # gravity (acceleration of free fall) in NED, m/s^2
BANK_DEG = 30.0
DRAG_PER_S = 0.4  # multirotor: rotor and body drag per second (30 deg bank -> about 14 m/s in about 2.5 s)
DRAG_STEP_S = 0.01
DERIVATIVE_STEP_S = 5e-4
GRID_KEPT = 512  # multirotor: drag grid points kept (5 s), so times a little in the past cost nothing


class MotionModel:
    """Base of the moving models: ``attitude(t)`` -> (magnetic heading, pitch, roll) degrees (N,) each;
    ``linear_acceleration(t, rotation)`` -> (N, 3) m/s^2 NED, ``rotation`` (N, 3, 3) the body-to-NED attitude at t.
    ``declination_deg`` turns the magnetic heading into the true one (NED is geographic)."""

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        self.declination_deg = float(declination_deg)

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def velocity(self, t: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """Velocity (N, 3) m/s NED of the point a GNSS receiver on the vehicle follows, at increasing times t."""
        raise NotImplementedError

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """Body-to-NED matrices (N, 3, 3) at t."""
        yaw, pitch, roll = self.attitude(t)
        return euler_to_matrix(yaw + self.declination_deg, pitch, roll)

    def _first_derivative(self, position: Callable[[np.ndarray], np.ndarray], t: np.ndarray) -> np.ndarray:
        """d position / dt (N, 3) by central differences."""
        h = DERIVATIVE_STEP_S
        return (position(t + h) - position(t - h)) / (2.0 * h)

    def _second_derivative(self, position: Callable[[np.ndarray], np.ndarray], t: np.ndarray) -> np.ndarray:
        """d^2 position / dt^2 (N, 3) by central differences (the positions here are smooth and small)."""
        h = DERIVATIVE_STEP_S
        return (position(t + h) - 2.0 * position(t) + position(t - h)) / (h * h)


class MultirotorModel(MotionModel):
    """Hover with vibration, yaw turns, 30 deg banks, banked turns (see the module docstring)."""

    KINDS = ("hover", "yaw", "bank", "banked_turn")

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        super().__init__(rng, declination_deg)
        self.plan = Segments(rng.spawn(1)[0], self._draw)
        self.jitter_deg = Tones(rng, 3, 2, (4.0, 12.0), 0.15)
        self.vibration_ms2 = Tones(rng, 3, 3, (8.0, 24.0), (0.3, 0.3, 0.5))
        self.climb_hz, self.climb_phase = rng.uniform(0.05, 0.1), rng.uniform(0.0, 2.0 * np.pi)
        self.yaw0_deg = rng.uniform(0.0, 360.0)
        self._grid_first, self._grid = 0, np.zeros((1, 3))  # velocity at grid points _grid_first, ...

    def _draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        yaw0 = self.yaw0_deg if last is None else last["yaw0"] + last["dyaw"]
        kind = "hover" if last is None else self.KINDS[int(rng.choice(4, p=[0.2, 0.3, 0.3, 0.2]))]
        row = {"yaw0": yaw0, "dyaw": 0.0, "roll": 0.0, "pitch": 0.0}
        if kind == "hover":
            return rng.uniform(2.0, 4.0), row
        if kind == "yaw":
            row["dyaw"] = _sign(rng) * rng.uniform(90.0, 180.0)
            return abs(row["dyaw"]) / rng.uniform(45.0, 90.0) + 0.5, row
        if kind == "bank":
            axis = int(rng.integers(3))  # roll, pitch, or both (30 deg off level along a diagonal)
            scale = BANK_DEG if axis < 2 else np.degrees(np.arctan(np.tan(np.radians(BANK_DEG)) / np.sqrt(2.0)))
            if axis in (0, 2):
                row["roll"] = _sign(rng) * scale
            if axis in (1, 2):
                row["pitch"] = _sign(rng) * scale
            return rng.uniform(3.0, 6.0), row
        row["roll"] = _sign(rng) * BANK_DEG
        row["dyaw"] = np.sign(row["roll"]) * rng.uniform(90.0, 270.0)  # turn towards the low wing
        return abs(row["dyaw"]) / rng.uniform(30.0, 60.0) + 2.0, row

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        row, u, _ = self.plan.locate(t)
        jitter = self.jitter_deg(t)
        bank = plateau(u)
        yaw = row["yaw0"] + row["dyaw"] * smoother(u) + jitter[:, 0]
        return yaw, row["pitch"] * bank + jitter[:, 1], row["roll"] * bank + jitter[:, 2]

    def _thrust(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """Thrust + gravity (N, 3) m/s^2 NED: thrust along body -z, its vertical part holding altitude (plus a slow
        climb and descent): g - thrust R22 = climb."""
        climb = 0.5 * np.sin(2.0 * np.pi * self.climb_hz * np.asarray(t, dtype=float) + self.climb_phase)
        thrust = (STANDARD_GRAVITY_MS2 - climb) / rotation[:, 2, 2]
        return G_NED - thrust[:, None] * rotation[:, :, 2]

    def _velocity(self, t: np.ndarray) -> np.ndarray:
        """Velocity (N, 3) m/s NED at times t, from rest at t = 0: v' = thrust + gravity - drag v, stepped exactly for
        the drag on a fixed grid (the forcing at each step's middle), so any split of the times into blocks gives the
        same velocities. The last ``GRID_KEPT`` grid points are kept, so block after block (and times a little in the
        past, as a GNSS fix's) costs no more."""
        h, k = DRAG_STEP_S, DRAG_PER_S
        t = np.maximum(np.asarray(t, dtype=float), 0.0)
        cell = np.floor(t / h).astype(int)
        if cell.min() < self._grid_first:  # asked for the forgotten past: start again from rest
            self._grid_first, self._grid = 0, np.zeros((1, 3))
        last = self._grid_first + len(self._grid) - 1
        middles = (last + np.arange(max(int(cell.max()) - last, 0)) + 0.5) * h
        forcing = self._thrust(middles, self.rotation(middles)) if middles.size else np.zeros((0, 3))
        decay, gain = float(np.exp(-k * h)), float(-np.expm1(-k * h) / k)
        steps, (x, y, z) = [], self._grid[-1].tolist()
        for ux, uy, uz in forcing.tolist():  # in Python floats: the same products and sums, a tenth of the time
            x, y, z = decay * x + gain * ux, decay * y + gain * uy, decay * z + gain * uz
            steps.append((x, y, z))
        grid = np.concatenate([self._grid, np.array(steps, dtype=float).reshape(-1, 3)])
        first = self._grid_first
        self._grid_first = max(first, first + len(grid) - GRID_KEPT)
        self._grid = grid[self._grid_first - first :].copy()
        rest = t - cell * h  # from each sample's grid point to the sample
        halfway = cell * h + rest / 2.0
        u = self._thrust(halfway, self.rotation(halfway))
        return np.exp(-k * rest)[:, None] * grid[cell - first] - (np.expm1(-k * rest) / k)[:, None] * u

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        vibration = np.einsum("nij,nj->ni", rotation, self.vibration_ms2(t))
        return self._thrust(t, rotation) - DRAG_PER_S * self.velocity(t) + vibration

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """The craft's velocity (vibration left out: it moves the sensor by micrometres)."""
        return self._velocity(t)


class CarModel(MotionModel):
    """Straights and turns with centripetal acceleration (see the module docstring)."""

    ROLL_DEG_PER_MS2 = 0.5
    PITCH_DEG_PER_MS2 = 0.3
    MAX_ALONG_MS2 = 3.0  # peak longitudinal acceleration of a speed change on a straight
    MAX_LATERAL_MS2 = 3.0  # peak centripetal acceleration in a turn
    TURN_SPEED_MS = (5.0, 12.0)

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        super().__init__(rng, declination_deg)
        self.plan = Segments(rng.spawn(1)[0], self._draw)
        self.jitter_deg = Tones(rng, 3, 2, (6.0, 15.0), 0.05)
        self.bumps_ms2 = Tones(rng, 1, 3, (8.0, 15.0), 0.3)
        self.yaw0_deg = rng.uniform(0.0, 360.0)
        self._distance_starts: list[float] = [0.0]

    def path(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """The road's course, speed and distance at t (``segment_path``)."""
        return segment_path(self.plan, self._distance_starts, np.asarray(t, dtype=float))

    def device_offset(self, t: np.ndarray) -> np.ndarray:
        """The sensor's offset from the path's point: none (it is the point)."""
        return np.zeros((np.asarray(t).size, 3))

    def _draw(self, rng: np.random.Generator, last: dict[str, Any] | None) -> tuple[float, dict[str, Any]]:
        yaw0 = self.yaw0_deg if last is None else last["yaw0"] + last["dyaw"]
        speed0 = 0.0 if last is None else last["v0"] + last["dv"]
        row = {"yaw0": yaw0, "dyaw": 0.0, "v0": speed0, "dv": 0.0}
        choice = rng.random()
        if last is not None and (last["dyaw"] or choice < 0.35):  # cruise (or stand) on a straight
            return rng.uniform(3.0, 10.0), row
        if last is None or choice < 0.65 or speed0 > self.TURN_SPEED_MS[1]:  # change speed (slow down to turn)
            top = self.TURN_SPEED_MS[1] if speed0 > self.TURN_SPEED_MS[1] and choice >= 0.65 else 25.0
            target = 0.0 if last is not None and rng.random() < 0.15 else rng.uniform(self.TURN_SPEED_MS[0], top)
            row["dv"] = target - speed0
            return max(2.0, 1.875 * abs(row["dv"]) / rng.uniform(1.5, self.MAX_ALONG_MS2)), row
        if speed0 < self.TURN_SPEED_MS[0]:  # too slow to turn: move off first
            row["dv"] = rng.uniform(*self.TURN_SPEED_MS) - speed0
            return max(2.0, 1.875 * abs(row["dv"]) / self.MAX_ALONG_MS2), row
        row["dyaw"] = _sign(rng) * rng.uniform(45.0, 120.0)
        rate_deg = min(rng.uniform(15.0, 30.0), np.degrees(self.MAX_LATERAL_MS2 / speed0))
        return 1.875 * abs(row["dyaw"]) / rate_deg, row  # peak yaw rate, peak lateral bounded

    def _motion(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """(magnetic heading deg, speed m/s, longitudinal and lateral acceleration m/s^2), each (N,)."""
        row, u, duration = self.plan.locate(t)
        started = np.asarray(t, dtype=float) > 0.0
        yaw = row["yaw0"] + row["dyaw"] * smoother(u)
        speed = row["v0"] + row["dv"] * smoother(u)
        yaw_rate = np.where(started, np.radians(row["dyaw"]) * smoother_rate(u) / duration, 0.0)
        along = np.where(started, row["dv"] * smoother_rate(u) / duration, 0.0)
        return yaw, speed, along, speed * yaw_rate

    def _road(self, speed: np.ndarray) -> np.ndarray:
        """Road vibration scale (N, 1): none at rest, full at 20 m/s."""
        return (speed / 20.0)[:, None]

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        yaw, speed, along, lateral = self._motion(t)
        jitter = self.jitter_deg(t) * self._road(speed)
        return (
            yaw + jitter[:, 0],
            self.PITCH_DEG_PER_MS2 * along + jitter[:, 1],
            -self.ROLL_DEG_PER_MS2 * lateral + jitter[:, 2],
        )

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """Speed along the heading (road bumps left out: millimetres per second)."""
        yaw, speed, _, _ = self._motion(t)
        heading = np.radians(yaw + self.declination_deg)
        return np.stack([speed * np.cos(heading), speed * np.sin(heading), np.zeros_like(heading)], axis=-1)

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        yaw, speed, along, lateral = self._motion(t)
        heading = np.radians(yaw + self.declination_deg)
        forward = np.stack([np.cos(heading), np.sin(heading), np.zeros_like(heading)], axis=-1)
        right = np.stack([-np.sin(heading), np.cos(heading), np.zeros_like(heading)], axis=-1)
        acc = along[:, None] * forward + lateral[:, None] * right
        acc[:, 2] += (self.bumps_ms2(t) * self._road(speed))[:, 0]
        return acc


class Figure8Model(MotionModel):
    """A handheld figure 8 while slowly turning around (see the module docstring)."""

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        super().__init__(rng, declination_deg)
        self.omega = 2.0 * np.pi * rng.uniform(0.35, 0.5)
        self.turn_deg_per_s = _sign(rng) * 360.0 / rng.uniform(30.0, 50.0)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, 5)
        self.yaw0_deg = rng.uniform(0.0, 360.0)
        self.tremor_deg = Tones(rng, 3, 2, (6.0, 10.0), 0.1)

    def _facing_deg(self, t: np.ndarray) -> np.ndarray:
        return self.yaw0_deg + self.turn_deg_per_s * t

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        w, p = self.omega, self.phase
        tremor = self.tremor_deg(t)
        return (
            self._facing_deg(t) + 45.0 * np.sin(w * t + p[0]) + tremor[:, 0],
            40.0 * np.sin(2.0 * w * t + p[1]) + tremor[:, 1],
            60.0 * np.sin(w * t + p[2]) + tremor[:, 2],
        )

    def _position(self, t: np.ndarray) -> np.ndarray:
        w, p = self.omega, self.phase
        local = np.stack(
            [0.15 * np.sin(2.0 * w * t + p[3]), 0.3 * np.sin(w * t), 0.08 * np.sin(2.0 * w * t + p[4])], axis=-1
        )
        facing = np.radians(self._facing_deg(t) + self.declination_deg)
        c, s = np.cos(facing), np.sin(facing)
        return np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], axis=-1)

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        return self._second_derivative(self._position, np.asarray(t, dtype=float))

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """The hand's velocity (a phone's receiver moves with it)."""
        return self._first_derivative(self._position, np.asarray(t, dtype=float))


class FastTumbleModel(MotionModel):
    """Fast tumbling about every axis, the sensor off the centre of rotation (see the module docstring)."""

    def __init__(self, rng: np.random.Generator, declination_deg: float = 0.0) -> None:
        super().__init__(rng, declination_deg)
        self.turns_hz = np.array([_sign(rng) * rng.uniform(0.5, 0.9), _sign(rng) * rng.uniform(1.0, 1.6)])
        self.pitch_hz = rng.uniform(0.8, 1.2)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, 3)
        direction = rng.standard_normal(3)
        self.offset_m = direction / np.linalg.norm(direction) * rng.uniform(0.02, 0.08)

    def attitude(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        yaw = 360.0 * self.turns_hz[0] * t + np.degrees(self.phase[0])
        pitch = 75.0 * np.sin(2.0 * np.pi * self.pitch_hz * t + self.phase[1])
        roll = 360.0 * self.turns_hz[1] * t + np.degrees(self.phase[2])
        return yaw, pitch, roll

    def _position(self, t: np.ndarray) -> np.ndarray:
        return np.einsum("nij,j->ni", self.rotation(t), self.offset_m)

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """Zero: the tumble turns in place, and a receiver on its rig sits at the centre of rotation."""
        return np.zeros((np.asarray(t).size, 3))

    def linear_acceleration(self, t: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        return self._second_derivative(self._position, np.asarray(t, dtype=float))


#: trajectory name -> model class
MODELS: dict[str, type[MotionModel]] = {
    "multirotor": MultirotorModel,
    "car": CarModel,
    "figure8": Figure8Model,
    "fast-tumble": FastTumbleModel,
}

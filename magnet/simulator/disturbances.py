"""Magnetic disturbances passed on the way (steel doors, parked cars) and a hard-iron change in the middle of a run.

Passing objects (``Disturbances``): along a path (a trajectory with ``path`` and ``device_offset``: the walks, the
car, the boat, the robot) an object stands every 15-40 m (``every_m``; the first within 20 m of the start, maybe
right beside it: ``first_m``), beside the path on a random side. Each is
a magnetic dipole fixed in the world, of random orientation, whose field at the point of closest approach has the
magnitude drawn for its kind:

- a steel door (or its frame, a radiator): 0.3-0.8 m from the path, 15-50 uT there;
- a parked car: 1-2.5 m from the path and 0.2-0.8 m below the device, 5-20 uT there.

The field at the device is B = k (3 (m.r) r - m) / |r|^3 (r the unit vector and |r| the distance from the object,
m its unit moment), tapered smoothly to zero beyond 12 closest distances along the path. It changes in magnitude and
direction as the device passes (a walker past a door: a few seconds; a robot that stops beside one: as long as it
stands). The device's position about the path (a swinging hand) is in r; the object is placed in the course frame
of the moment (a straight path through the few metres that matter).

A hard-iron change (``HardIronChange``): from ``t_s`` on, the sensor's hard iron is ``hard_iron_ut`` (a magnetic
case clipped on, a new battery, a phone moved in a car's holder): what in-service recalibration has to notice.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import numpy as np

from magnet.simulator.plan import smoother

#: a dipole's field is left out beyond this many closest distances along the path (it is 1/1700 of its peak there)
REACH = 12.0
TAPER = 0.3  # the last 30 % of the reach tapers the field to zero


class HasPath(Protocol):
    """A motion model the objects can stand beside (``magnet.simulator.paths.PathModel``, ``CarModel``)."""

    declination_deg: float

    def path(self, t: np.ndarray) -> dict[str, np.ndarray]: ...

    def device_offset(self, t: np.ndarray) -> np.ndarray: ...


def _range(value: Any, name: str, low: float = 0.0) -> tuple[float, float]:
    pair = tuple(float(v) for v in value)
    if len(pair) != 2 or not all(np.isfinite(pair)) or not low <= pair[0] <= pair[1]:
        raise ValueError(f"disturbances: {name} must be two finite numbers low <= high, >= {low:g}, got {value!r}")
    return pair[0], pair[1]


@dataclasses.dataclass(frozen=True)
class Disturbances:
    """Objects passed on the way (see the module docstring): spacing along the path (m) and where the first stands
    (m from the start: a walk may start beside a parked car), the share of doors, and per kind the distance from the
    path (m) and the field at closest approach (uT)."""

    every_m: tuple[float, float] = (15.0, 40.0)
    first_m: tuple[float, float] = (0.0, 20.0)
    door_share: float = 0.5
    door_m: tuple[float, float] = (0.3, 0.8)
    door_ut: tuple[float, float] = (15.0, 50.0)
    car_m: tuple[float, float] = (1.0, 2.5)
    car_ut: tuple[float, float] = (5.0, 20.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "first_m", _range(self.first_m, "first_m"))
        for name in ("every_m", "door_m", "car_m"):
            object.__setattr__(self, name, _range(getattr(self, name), name, 0.1))
        for name in ("door_ut", "car_ut"):
            object.__setattr__(self, name, _range(getattr(self, name), name))
        if not 0.0 <= float(self.door_share) <= 1.0:
            raise ValueError(f"disturbances: door_share must be within 0..1, got {self.door_share!r}")


@dataclasses.dataclass(frozen=True)
class HardIronChange:
    """From ``t_s`` (seconds from the run's start) on, the hard iron is ``hard_iron_ut`` (3,) uT (plus its
    temperature's change, ``SensorErrors.hard_iron_tempco_ut_per_k``)."""

    t_s: float
    hard_iron_ut: Any

    def __post_init__(self) -> None:
        vector = np.array(self.hard_iron_ut, dtype=float)
        if vector.shape != (3,) or not np.all(np.isfinite(vector)) or not np.isfinite(self.t_s) or self.t_s < 0:
            raise ValueError("hard-iron change: t_s must be >= 0 and hard_iron_ut three finite numbers (uT)")
        vector.setflags(write=False)
        object.__setattr__(self, "hard_iron_ut", vector)


class PassingObjects:
    """The objects along one run's path, drawn lazily (the same ones whatever blocks the run is drawn in)."""

    def __init__(self, settings: Disturbances, rng: np.random.Generator) -> None:
        self.settings, self.rng = settings, rng
        self.at_m: list[float] = []  # distance along the path of each object's closest approach
        self.offset: list[np.ndarray] = []  # (side, below): metres right of the path and below the device
        self.moment: list[np.ndarray] = []  # unit moment in the course frame
        self.strength: list[float] = []  # k, uT m^3

    def _extend(self, distance_m: float) -> None:
        s = self.settings
        while not self.at_m or self.at_m[-1] <= distance_m:
            rng = self.rng
            self.at_m.append(self.at_m[-1] + rng.uniform(*s.every_m) if self.at_m else rng.uniform(*s.first_m))
            door = rng.random() < s.door_share
            side = float(rng.choice([-1.0, 1.0])) * rng.uniform(*(s.door_m if door else s.car_m))
            below = rng.uniform(-0.3, 0.3) if door else rng.uniform(0.2, 0.8)
            peak = rng.uniform(*(s.door_ut if door else s.car_ut))
            moment = rng.standard_normal(3)
            moment /= np.linalg.norm(moment)
            offset = np.array([0.0, side, below])
            closest = -offset / np.linalg.norm(offset)  # from the object to the path's point
            shape = np.linalg.norm(3.0 * (moment @ closest) * closest - moment)
            self.offset.append(offset)
            self.moment.append(moment)
            self.strength.append(float(peak * np.linalg.norm(offset) ** 3 / shape))

    def field_ned(self, model: HasPath, t: np.ndarray) -> np.ndarray:
        """The objects' field (N, 3) uT in geographic NED at the device at times t (N,)."""
        t = np.asarray(t, dtype=float)
        path = model.path(t)
        distance = path["distance_m"]
        reach = REACH * max(self.settings.door_m[1], self.settings.car_m[1])
        self._extend(float(distance.max()) + reach)
        course = np.radians(path["course_deg"] + model.declination_deg)
        c, s, zero, one = np.cos(course), np.sin(course), np.zeros_like(course), np.ones_like(course)
        to_ned = np.stack(
            [np.stack([c, -s, zero], axis=-1), np.stack([s, c, zero], axis=-1), np.stack([zero, zero, one], axis=-1)],
            axis=-2,
        )  # course frame -> NED (N, 3, 3)
        device = np.einsum("nji,nj->ni", to_ned, model.device_offset(t))  # the device about the path, course frame
        out = np.zeros((len(t), 3))
        for at, offset, moment, k in zip(self.at_m, self.offset, self.moment, self.strength):
            along = distance - at
            near = np.abs(along) < REACH * np.linalg.norm(offset)
            if not near.any():
                continue
            r = device[near] - offset
            r[:, 0] += along[near]
            length = np.linalg.norm(r, axis=1, keepdims=True)
            unit = r / length
            field = k * (3.0 * (unit @ moment)[:, None] * unit - moment) / length**3
            taper = smoother((1.0 - np.abs(along[near]) / (REACH * np.linalg.norm(offset))) / TAPER)
            out[near] += np.einsum("nij,nj->ni", to_ned[near], field * taper[:, None])
        return out

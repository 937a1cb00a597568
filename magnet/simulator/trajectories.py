"""The attitude trajectories of the simulator by name, and the still ones (functions of the phase of a run).

Still trajectories (the device at rest at every sample: the accelerometer reads gravity only), each a periodic
function of the sample index with period ``count``:
- SPIN: level, one full clockwise turn from magnetic north.
- TURNTABLE: seed 000's two mountings, table angle K = 0, 30, ..., 360 deg (13 steps), ``count // 26`` samples per
  step, mounting a first. Mounting a: x at table angle K, z up (the device upside down: roll 180); mounting b: x at K,
  y down (roll +90). The sensor-frame field is then exactly seed 000's eqs. 2 and 5 with Bv the *up* component of the
  field (negative in the northern hemisphere): a = (Bh cos K, Bh sin K, Bv), b = (Bh cos K, -Bv, Bh sin K). Both are
  physical attitudes (the table turns clockwise seen from above, as headings do), so no sign had to be forced.
- TUMBLE: smooth "figure 8" over the whole sphere: over one run pitch = 85 sin(21 cycles), roll turns 13 times and
  heading 8 times, with phases and senses drawn from the seed. The Fibonacci counts keep the path from closing on
  itself early, so field and gravity directions cover the sphere evenly (every one of 100 equal-area cells from 1000
  samples on). The speed follows the run's length: at 3000 samples and 50 Hz pitch swings at 0.35 Hz.
- TENFACE: our reading of seed 003's ten-face procedure (its figure is not in the text): the device rests on each of
  its six faces and on four 45-degree edges (pitch +-45, roll +-45) and is turned a full circle about the vertical on
  each; it is set down on the next face between stations (no transition samples).

Moving trajectories are functions of time with linear acceleration: MULTIROTOR, CAR, FIGURE8, FAST_TUMBLE
(``magnet.simulator.motion``); the walks WALK_POCKET, WALK_HAND, WALK_TEXTING, WALK_PHONING, RUNNING
(``magnet.simulator.walks``); the planar BOAT and ROBOT (``magnet.simulator.ground``); the hand-held WAND
(``magnet.simulator.wand``).
"""

from __future__ import annotations

import enum
from typing import Any

import numpy as np

TURNTABLE_STEP_DEG = 30
TURNTABLE_ANGLES_DEG = tuple(range(0, 361, TURNTABLE_STEP_DEG))  # 0..360 inclusive, as in seed 000's table
TURNTABLE_ROLL_DEG = {"a": 180.0, "b": 90.0}  # a: z up; b: y down
TENFACE_STATIONS = (  # (pitch_deg, roll_deg): six faces, then four 45-degree edges
    (0.0, 0.0),
    (0.0, 180.0),
    (0.0, 90.0),
    (0.0, -90.0),
    (90.0, 0.0),
    (-90.0, 0.0),
    (45.0, 0.0),
    (-45.0, 0.0),
    (0.0, 45.0),
    (0.0, -45.0),
)
TUMBLE_CYCLES = (21, 13, 8)  # pitch oscillations, roll turns, heading turns over one run (Fibonacci: no short
# Lissajous repeats, so the run covers every field and gravity direction)
TUMBLE_PITCH_AMPLITUDE_DEG = 85.0
GOLDEN_RATIO_MINOR = (5**0.5 - 1) / 2  # 0.618...


class Trajectory(enum.Enum):
    SPIN = "spin"
    TURNTABLE = "turntable"
    TUMBLE = "tumble"
    TENFACE = "tenface"
    MULTIROTOR = "multirotor"
    CAR = "car"
    FIGURE8 = "figure8"
    FAST_TUMBLE = "fast-tumble"
    WALK_POCKET = "walk-pocket"
    WALK_HAND = "walk-hand"
    WALK_TEXTING = "walk-texting"
    WALK_PHONING = "walk-phoning"
    RUNNING = "running"
    BOAT = "boat"
    ROBOT = "robot"
    WAND = "wand"

    @property
    def moving(self) -> bool:
        """True for the trajectories with linear acceleration (``magnet.simulator.motion``)."""
        return self in MOVING_TRAJECTORIES


#: the vehicles and hand motions of ``magnet.simulator.motion`` (what ``magnet bench motion`` scores)
VEHICLE_TRAJECTORIES = frozenset({Trajectory.MULTIROTOR, Trajectory.CAR, Trajectory.FIGURE8, Trajectory.FAST_TUMBLE})
#: a person walking or running with a phone (``magnet.simulator.walks``)
WALKING_TRAJECTORIES = frozenset(
    {Trajectory.WALK_POCKET, Trajectory.WALK_HAND, Trajectory.WALK_TEXTING, Trajectory.WALK_PHONING, Trajectory.RUNNING}
)
#: vehicles that only yaw, with small roll and pitch (``magnet.simulator.ground``, and the car)
PLANAR_TRAJECTORIES = frozenset({Trajectory.CAR, Trajectory.BOAT, Trajectory.ROBOT})
#: an IMU box turned by hand about every axis, with rests, as in the BROAD trials (``magnet.simulator.wand``)
HAND_TRAJECTORIES = frozenset({Trajectory.WAND})
MOVING_TRAJECTORIES = VEHICLE_TRAJECTORIES | WALKING_TRAJECTORIES | PLANAR_TRAJECTORIES | HAND_TRAJECTORIES
#: the trajectories that follow a path on the ground or water, beside which objects can disturb the field
#: (``magnet.simulator.disturbances``)
PATH_TRAJECTORIES = WALKING_TRAJECTORIES | PLANAR_TRAJECTORIES

MIN_COUNT = {
    Trajectory.SPIN: 2,
    Trajectory.TURNTABLE: 2 * len(TURNTABLE_ANGLES_DEG),
    Trajectory.TUMBLE: 2,
    Trajectory.TENFACE: len(TENFACE_STATIONS),
    **dict.fromkeys(MOVING_TRAJECTORIES, 2),
}


# Still trajectories: functions of the phase s in [0, 1) of a run -> magnetic heading, pitch, roll (degrees),
# mounting and table angle.


def _spin(s: np.ndarray, params: dict[str, Any]) -> tuple[np.ndarray, ...]:
    zero = np.zeros_like(s)
    return 360.0 * s, zero, zero, np.full(s.shape, ""), np.full(s.shape, np.nan)


def _turntable(s: np.ndarray, params: dict[str, Any]) -> tuple[np.ndarray, ...]:
    steps = len(TURNTABLE_ANGLES_DEG)
    station = np.minimum((s * 2 * steps).astype(int), 2 * steps - 1)
    mounting = np.where(station < steps, "a", "b")
    table = np.asarray(TURNTABLE_ANGLES_DEG, dtype=float)[station % steps]
    roll = np.where(mounting == "a", TURNTABLE_ROLL_DEG["a"], TURNTABLE_ROLL_DEG["b"])
    return table, np.zeros_like(s), roll, mounting, table


def _tenface(s: np.ndarray, params: dict[str, Any]) -> tuple[np.ndarray, ...]:
    stations = np.asarray(TENFACE_STATIONS)
    position = s * len(stations)
    station = np.minimum(position.astype(int), len(stations) - 1)
    yaw = 360.0 * (position - station)
    return yaw, stations[station, 0], stations[station, 1], np.full(s.shape, ""), np.full(s.shape, np.nan)


def _tumble(s: np.ndarray, params: dict[str, Any]) -> tuple[np.ndarray, ...]:
    phase = 2.0 * np.pi * s
    pitch_cycles, roll_turns, yaw_turns = TUMBLE_CYCLES
    pitch = TUMBLE_PITCH_AMPLITUDE_DEG * np.sin(pitch_cycles * phase + params["phases"][0])
    roll = params["senses"][0] * 360.0 * roll_turns * s + np.degrees(params["phases"][1])
    yaw = params["senses"][1] * 360.0 * yaw_turns * s + np.degrees(params["phases"][2])
    return yaw, pitch, roll, np.full(s.shape, ""), np.full(s.shape, np.nan)


STILL_TRAJECTORIES = {
    Trajectory.SPIN: _spin,
    Trajectory.TURNTABLE: _turntable,
    Trajectory.TENFACE: _tenface,
    Trajectory.TUMBLE: _tumble,
}


def wrap_roll(roll_deg: np.ndarray) -> np.ndarray:
    """Roll wrapped to (-180, 180]."""
    return 180.0 - np.mod(180.0 - roll_deg, 360.0)

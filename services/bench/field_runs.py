"""The motions of ``magnet bench field`` and how each estimator's heading is scored against the simulator's truth.

Motions (``MOTIONS``): the walks (phone in a pocket, a swinging hand, texting, phoning, running), the planar
vehicles (car, boat, robot), walks past steel doors and parked cars (``magnet.simulator.disturbances``) and a walk
whose hard iron changes half-way (in-service recalibration). Every one of these has a phone's raw magnetometer and
IMU (``SensorErrors.phone``: hard iron 6-15 times the field, factory soft iron), both drawn from the seed. Last, a
hand-held wand (``magnet.simulator.wand``: an IMU box turned slowly and fast about every axis, with rests, as in the
BROAD trials) whose magnetometer its maker already calibrated (``SensorErrors.calibrated``: under 1 uT and 1 % left):
there the raw field is already good, and a fit must not make heading worse than vqf on it.

The heading error of an attitude estimate is the angle about the vertical between it and the truth: the yaw of
R_est R_true^T. It is defined at any attitude (a phone in a pocket stands upright, where the heading of its x axis
is not), and it is the heading error when the tilt is right. Scores are RMS over the scored samples, after one
constant offset removed (the circular mean, as on recordings whose reference has its own north) or not ("abs":
the simulator's north is north).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import vqf

from magnet import frames
from magnet.attitude import fusion
from magnet.attitude.heading import angle_difference_deg
from magnet.simulator import (
    DEFAULT_DATE,
    DEFAULT_LAT_DEG,
    DEFAULT_LON_DEG,
    Disturbances,
    HardIronChange,
    SensorErrors,
    SimulatedRun,
    SimulatorConfig,
    Trajectory,
    simulate,
)

#: the seeds the bench runs by default: not the ones its makers tuned on (``TUNING_SEEDS``; docs/field-motions.md)
DEFAULT_SEEDS = (2026, 2027, 2028)
#: the seeds the simulator's field motions, the disturbance checks and the compass's rejection were tuned on
TUNING_SEEDS = tuple(range(1, 10))


@dataclasses.dataclass(frozen=True)
class FieldMotion:
    """One motion of the bench: its trajectory, its group ("walk", "planar", "disturbed", "in service"), whether
    objects are passed on the way, whether the hard iron changes half-way, and whether the device sends its GNSS
    velocity with its samples (a car's or a boat's navigation does; the compass then aids its filter with it), and
    its sensor: "phone" (``SensorErrors.phone``, raw) or "calibrated" (``SensorErrors.calibrated``: its maker
    calibrated it)."""

    trajectory: Trajectory
    group: str
    disturbed: bool = False
    iron_change: bool = False
    gnss: bool = False
    sensor: str = "phone"


MOTIONS: dict[str, FieldMotion] = {
    "walk-pocket": FieldMotion(Trajectory.WALK_POCKET, "walk"),
    "walk-hand": FieldMotion(Trajectory.WALK_HAND, "walk"),
    "walk-texting": FieldMotion(Trajectory.WALK_TEXTING, "walk"),
    "walk-phoning": FieldMotion(Trajectory.WALK_PHONING, "walk"),
    "running": FieldMotion(Trajectory.RUNNING, "walk"),
    "car": FieldMotion(Trajectory.CAR, "planar", gnss=True),
    "boat": FieldMotion(Trajectory.BOAT, "planar", gnss=True),
    "robot": FieldMotion(Trajectory.ROBOT, "planar"),
    "walk-pocket, doors": FieldMotion(Trajectory.WALK_POCKET, "disturbed", disturbed=True),
    "walk-hand, doors": FieldMotion(Trajectory.WALK_HAND, "disturbed", disturbed=True),
    "walk-texting, doors": FieldMotion(Trajectory.WALK_TEXTING, "disturbed", disturbed=True),
    "walk-hand, iron change": FieldMotion(Trajectory.WALK_HAND, "in service", iron_change=True),
    "wand, calibrated": FieldMotion(Trajectory.WAND, "wand", sensor="calibrated"),
}


@dataclasses.dataclass(frozen=True)
class FieldSettings:
    """The bench's runs: seconds and rate (Hz) of each, seconds left out at the start (filters settling), samples per
    raw message in service, and the place and date (the simulator's)."""

    seconds: float = 120.0
    rate_hz: float = 50.0
    settle_s: float = 10.0
    batch: int = 25
    lat_deg: float = DEFAULT_LAT_DEG
    lon_deg: float = DEFAULT_LON_DEG
    date: str = DEFAULT_DATE

    @property
    def location(self) -> str:
        return f"{self.lat_deg},{self.lon_deg}"


def field_run(motion: FieldMotion, seed: int, settings: FieldSettings) -> SimulatedRun:
    """The motion's run for ``seed``: a phone's sensor drawn from the seed, objects on the way when disturbed, a new
    hard iron (another phone-like one) from half-way when the iron changes; a maker-calibrated sensor for the wand."""
    rng = np.random.default_rng([seed, 26])
    errors = SensorErrors.calibrated(rng, 50.0) if motion.sensor == "calibrated" else SensorErrors.phone(rng, 50.0)
    change = None
    if motion.iron_change:
        change = HardIronChange(settings.seconds / 2.0, SensorErrors.phone(rng, 50.0).hard_iron_ut)
    config = SimulatorConfig(
        trajectory=motion.trajectory,
        lat_deg=settings.lat_deg,
        lon_deg=settings.lon_deg,
        date=settings.date,
        rate_hz=settings.rate_hz,
        count=int(settings.seconds * settings.rate_hz),
        errors=errors,
        seed=seed,
        disturbances=Disturbances() if motion.disturbed else None,
        hard_iron_change=change,
    )
    return simulate(config)


def heading_error_deg(estimate_wxyz: np.ndarray, truth_wxyz: np.ndarray) -> np.ndarray:
    """(N,) degrees: the yaw of R_est R_true^T, both body -> NED with the same north (NaN where the estimate is)."""
    ok = np.all(np.isfinite(estimate_wxyz), axis=1)
    estimate = frames.quaternion_to_matrix(np.where(ok[:, None], estimate_wxyz, [1.0, 0.0, 0.0, 0.0]))
    error = np.einsum("nij,nkj->nik", estimate, frames.quaternion_to_matrix(truth_wxyz))
    return np.where(ok, np.degrees(np.arctan2(error[:, 1, 0], error[:, 0, 0])), np.nan)


def rms_deg(errors_deg: np.ndarray, scored: np.ndarray, offset_removed: bool = True) -> float:
    """RMS (deg) of the errors where scored (and finite), after their circular mean when ``offset_removed``; NaN
    when nothing is scored."""
    chosen = errors_deg[scored & np.isfinite(errors_deg)]
    if chosen.size == 0:
        return float("nan")
    if offset_removed:
        radians = np.radians(chosen)
        mean = np.degrees(np.arctan2(np.sin(radians).mean(), np.cos(radians).mean()))
        chosen = angle_difference_deg(chosen, mean)
    return float(np.sqrt(np.mean(chosen**2)))


def magnetic_truth(run: SimulatedRun) -> np.ndarray:
    """The run's attitude (N, 4) body -> NED with magnetic north (what vqf estimates)."""
    return frames.rotate_heading(run.quat_wxyz, -run.earth.declination_deg)


def vqf_attitude(run: SimulatedRun, field: np.ndarray | None, offline: bool) -> np.ndarray:
    """vqf 2.1.2 itself with its defaults (causal ``VQF`` or ``offlineVQF``) on the run's gyroscope, accelerometer
    and ``field`` (None: without the magnetometer, its 6D attitude): (N, 4) body -> magnetic NED."""
    gyr, acc = fusion.to_vqf_frame(run.gyr_rads), fusion.to_vqf_frame(run.acc_ms2)
    mag = None if field is None else fusion.to_vqf_frame(field)
    period = 1.0 / float(np.round(1.0 / np.median(np.diff(run.t_s)), 6))
    out = vqf.offlineVQF(gyr, acc, mag, period) if offline else vqf.VQF(period).updateBatch(gyr, acc, mag)
    quat = np.asarray(out["quat6D" if mag is None else "quat9D"], dtype=float)
    return frames.ned_enu_attitude(quat)


def sphere_fit_field(mag_ut: np.ndarray) -> np.ndarray:
    """What a user writes first: a least-squares sphere |m - c|^2 = r^2 through the raw samples (linear in c and
    r^2 - |c|^2), the field taken as m - c (vqf needs no scale)."""
    design = np.column_stack([2.0 * mag_ut, np.ones(len(mag_ut))])
    solution, *_ = np.linalg.lstsq(design, np.sum(mag_ut**2, axis=1), rcond=None)
    return mag_ut - solution[:3]

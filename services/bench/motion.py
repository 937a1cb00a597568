"""``magnet bench motion``: heading RMS in motion against truth nobody here made (docs/design.md, "Heading in motion").

BROAD trials in ``data/`` (real IMU, optical motion capture as reference). The metric: heading of the body x axis
from the estimate and from the optical reference quaternion, one constant offset per trial removed (circular mean of
the differences; the optical frame's north is arbitrary), only samples marked as movement, with a reference, and
with |reference pitch| < 60 deg (heading is ill-defined near the vertical), RMS in degrees.

BROAD's body frame is z up (a level IMU reads +g on z): y and z are negated to get the project's (x forward, y
right, z down). Its reference is IMU -> ENU, converted to body -> NED as vqf's output is (``magnet.attitude.fusion``).

Estimators, on the raw data (the sensor is factory-calibrated): accelerometer tilt (today's compass without a
gyroscope), fused causal (as the compass runs), fused offline (``magnet heading --offline``); then the same two
fused after ``magnet fit``'s ellipsoid, and after its gyro-ellipsoid, with the motion checks (the record applied when
accepted, none when refused, as the compass does). Then the moving simulator, every trajectory, against its truth:
calibrated on its own moving data (ellipsoid) when the gate accepts that, else on a still tumble; no offset removed
(the simulator's north is north); with the causal and offline filters aided by the run's GNSS-like velocity (10 Hz,
0.1 m/s noise, 0.1 s late: ``magnet.attitude.aiding``) and one more row, the causal filter fed the accelerometer without
the run's linear acceleration (what velocity aiding could give at best: the gap to "fused causal" is what linear
acceleration costs).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from magnet import frames
from magnet.attitude import fusion
from magnet.attitude import heading as hd
from magnet.attitude.mag_delay import advance_field
from magnet.calibration import FitInput, fit
from magnet.frames import quaternion_to_matrix, to_magnetic_ned
from magnet.model import Calibration
from magnet.simulator import VEHICLE_TRAJECTORIES, SensorErrors, SimulatedRun, SimulatorConfig, Trajectory, simulate

DATA_DIR = Path(__file__).resolve().parents[2] / "data"
BROAD_TRIALS = ("broad_01_undisturbed_slow_rotation_A.npz", "broad_06_undisturbed_fast_rotation_A.npz")
MAX_PITCH_DEG = 60.0


@dataclasses.dataclass(frozen=True)
class MotionLog:
    """A recording in the project's frames. t_s (N,), gyr_rads / acc_ms2 / mag_ut (N, 3) body frame, ref_quat_wxyz
    (N, 4) body -> NED (NaN rows where there is no reference), scored (N,) bool: the samples the metric uses."""

    name: str
    t_s: np.ndarray
    gyr_rads: np.ndarray
    acc_ms2: np.ndarray
    mag_ut: np.ndarray
    ref_quat_wxyz: np.ndarray
    scored: np.ndarray

    @property
    def period_s(self) -> float:
        return fusion.sample_period_s(self.t_s)

    def reference_heading_deg(self) -> np.ndarray:
        """Heading of body x from the reference, (N,), NaN where there is none."""
        ok = np.all(np.isfinite(self.ref_quat_wxyz), axis=1)
        heading, _, _ = frames.quaternion_to_euler(np.where(ok[:, None], self.ref_quat_wxyz, [1.0, 0, 0, 0]))
        return np.where(ok, heading, np.nan)

    def score(self, heading_deg: np.ndarray) -> float:
        """The motion metric (see the module docstring) of headings (N,) in degrees."""
        reference = self.reference_heading_deg()[self.scored]
        return hd.offset_removed_rms_deg(np.asarray(heading_deg)[self.scored], reference)


def load_broad(path: str | Path) -> MotionLog:
    """A BROAD trial (.npz as in data/README.md) in the project's frames, with the samples to score."""
    data = np.load(path)
    ref = data["ref_quat_wxyz"].astype(float)
    ok = np.all(np.isfinite(ref), axis=1)
    ref_ned = np.where(ok[:, None], frames.ned_enu_attitude(np.where(ok[:, None], ref, [1.0, 0, 0, 0])), np.nan)
    _, pitch, _ = frames.quaternion_to_euler(np.where(ok[:, None], ref_ned, [1.0, 0, 0, 0]))
    scored = data["movement"].astype(bool) & ok & (np.abs(pitch) < MAX_PITCH_DEG)
    body = {key: frames.frd_flu(data[key].astype(float)) for key in ("gyr_rads", "acc_ms2", "mag_ut")}
    return MotionLog(
        Path(path).stem, data["t_s"].astype(float), body["gyr_rads"], body["acc_ms2"], body["mag_ut"], ref_ned, scored
    )


def write_csv(log: MotionLog, path: str | Path) -> Path:
    """The log as a ``magnet fit`` / ``magnet heading`` CSV (t_s, mx..mz uT, ax..az m/s^2, gx..gz rad/s)."""
    table = np.column_stack([log.t_s, log.mag_ut, log.acc_ms2, log.gyr_rads])
    np.savetxt(path, table, delimiter=",", header="t_s,mx,my,mz,ax,ay,az,gx,gy,gz", comments="", fmt="%.9g")
    return Path(path)


#: estimator name -> heading (N,) deg from (log, calibrated field (N, 3))
Estimator = Callable[[MotionLog, np.ndarray], np.ndarray]
ESTIMATORS: dict[str, Estimator] = {
    "accelerometer tilt": lambda log, field: hd.tilt_compensated_heading_deg(field, log.acc_ms2),
    "fused causal": lambda log, field: fusion.fuse_causal(log.gyr_rads, log.acc_ms2, field, log.period_s).heading_deg,
    "fused offline": lambda log, field: fusion.fuse_offline(log.gyr_rads, log.acc_ms2, field, log.period_s).heading_deg,
}


def _aided(run: SimulatedRun, field: np.ndarray, offline: bool) -> np.ndarray:
    """Fused heading (N,) deg of a simulated run aided by its GNSS-like velocity (turned to magnetic north)."""
    vel = to_magnetic_ned(np.asarray(run.vel_ned_ms, dtype=float), run.earth.declination_deg)
    fuse = fusion.fuse_offline if offline else fusion.fuse_causal
    period = fusion.sample_period_s(run.t_s)
    return fuse(run.gyr_rads, run.acc_ms2, field, period, None, run.t_s, vel).heading_deg


#: the moving simulator's estimators with velocity aiding (``magnet.attitude.aiding``): name -> heading (N,) deg
AIDED_ESTIMATORS: dict[str, Callable[[SimulatedRun, np.ndarray], np.ndarray]] = {
    "fused causal, velocity aided": lambda run, field: _aided(run, field, offline=False),
    "fused offline, velocity aided": lambda run, field: _aided(run, field, offline=True),
}


def broad_rows(data_dir: Path = DATA_DIR, calibrated: bool = False) -> list[tuple[str, str, float]]:
    """(trial, estimator, RMS deg) for every BROAD trial and estimator, on the raw (factory-calibrated) field: vqf
    with its defaults. With ``calibrated`` also the fused ones after the product's fit (``product_field``)."""
    rows = []
    for name in BROAD_TRIALS:
        log = load_broad(data_dir / name)
        for estimator, function in ESTIMATORS.items():
            rows.append((log.name, estimator, log.score(function(log, log.mag_ut))))
        for method, label in (("ellipsoid", "fit"), ("gyro-ellipsoid", "gyro fit")) if calibrated else ():
            field, verdict = product_field(log, method)
            rows.extend(
                (log.name, f"{estimator}, {label} {verdict}", log.score(ESTIMATORS[estimator](log, field)))
                for estimator in ("fused causal", "fused offline")
            )
    return rows


def product_field(log: MotionLog, method: str = "ellipsoid") -> tuple[np.ndarray, str]:
    """The field (N, 3) as the compass's filter gets it after ``magnet fit --method METHOD`` with the motion checks
    on the log itself: calibrated (and turned forward over the magnetometer's delay the record carries:
    ``magnet.attitude.mag_delay``) when the gate accepts the fit, raw when it refuses it; and "accepted" or
    "refused"."""
    try:
        calibration = fit(FitInput(log.mag_ut, acc=log.acc_ms2, gyr_rads=log.gyr_rads, period_s=log.period_s), method)
    except ValueError:
        return log.mag_ut, "refused"
    if not calibration.accepted:
        return log.mag_ut, "refused"
    return advance_field(calibration.apply(log.mag_ut), log.gyr_rads, calibration.mag_lag_s), "accepted"


@dataclasses.dataclass(frozen=True)
class SimulatorSettings:
    """The moving simulator's runs: rate (Hz), seconds per run, seconds left out at the start (the filter settling),
    and one sensor with typical MEMS errors (hard iron up to the field, soft iron +-10 %, 0.3 uT noise, gyroscope
    bias about 0.5 deg/s per axis and 0.002 rad/s noise)."""

    rate_hz: float = 100.0
    seconds: float = 120.0
    settle_s: float = 10.0
    tumble_samples: int = 3000
    seed: int = 2026


def simulated_sensor(settings: SimulatorSettings, field_ut: float = 50.0) -> SensorErrors:
    """The one sensor every run of the benchmark uses (``SimulatorSettings``), drawn from its seed."""
    rng = np.random.default_rng(settings.seed)
    return SensorErrors.random(
        rng,
        field_ut,
        hard_iron_max_ratio=1.0,
        soft_iron_max=0.1,
        noise_ut=0.3,
        acc_noise_ms2=0.02,
        gyro_bias_rads=rng.uniform(-0.01, 0.01, 3),
        gyro_noise_rads=0.002,
    )


def tumble_run(errors: SensorErrors, settings: SimulatorSettings) -> SimulatedRun:
    """A still tumble of the sensor (what an operator does before a flight or a drive), no gyroscope."""
    return simulate(
        SimulatorConfig(
            trajectory=Trajectory.TUMBLE,
            rate_hz=settings.rate_hz,
            count=settings.tumble_samples,
            errors=errors,
            seed=settings.seed + 1,
        )
    )


def moving_run(trajectory: Trajectory, errors: SensorErrors, settings: SimulatorSettings) -> SimulatedRun:
    """``settings.seconds`` of a moving trajectory with the sensor, with its truth."""
    return simulate(
        SimulatorConfig(
            trajectory=trajectory,
            rate_hz=settings.rate_hz,
            count=int(settings.seconds * settings.rate_hz),
            errors=errors,
            seed=settings.seed,
        )
    )


def _simulator_calibration(
    run: SimulatedRun, errors: SensorErrors, settings: SimulatorSettings
) -> tuple[Calibration, str]:
    """The fit of the run's own samples (with its gyroscope) when the gate accepts it, else of a still tumble of
    the same sensor."""
    try:
        own = fit(
            FitInput(run.mag_ut, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=1.0 / settings.rate_hz), "ellipsoid"
        )
        if own.accepted:
            return own, "own data"
    except ValueError:
        pass
    tumble = tumble_run(errors, settings)
    return fit(FitInput(tumble.mag_ut, acc=tumble.acc_ms2), "ellipsoid"), "tumble"


def simulator_rows(
    settings: SimulatorSettings = SimulatorSettings(), trajectories: Iterable[Trajectory] = VEHICLE_TRAJECTORIES
) -> list[tuple[str, str, float]]:
    """(trajectory (calibrated on what), estimator, heading RMS deg against the true magnetic heading, no offset
    removed) for the moving trajectories, after the settling time, samples with |pitch| < 60 deg."""
    errors = simulated_sensor(settings)
    rows = []
    for trajectory in sorted(trajectories, key=lambda t: t.value):
        run = moving_run(trajectory, errors, settings)
        calibration, source = _simulator_calibration(run, errors, settings)
        field = calibration.apply(run.mag_ut)
        scored = (run.t_s >= settings.settle_s) & (np.abs(run.pitch_deg) < MAX_PITCH_DEG)
        log = MotionLog(trajectory.value, run.t_s, run.gyr_rads, run.acc_ms2, run.mag_ut, run.quat_wxyz, scored)
        bound = dataclasses.replace(log, acc_ms2=without_linear_acceleration(run))
        estimates = [*((name, function(log, field)) for name, function in ESTIMATORS.items())]
        estimates += [(name, function(run, field)) for name, function in AIDED_ESTIMATORS.items()]
        estimates.append((BOUND_ESTIMATOR, ESTIMATORS["fused causal"](bound, field)))
        for estimator, heading in estimates:
            error = hd.angle_difference_deg(heading, run.magnetic_heading_deg)[scored]
            rows.append((f"{trajectory.value} (cal: {source})", estimator, float(np.sqrt(np.mean(error**2)))))
    return rows


#: the causal filter fed the accelerometer without the run's linear acceleration (gravity and noise only): what
#: velocity aiding (GNSS, odometry) could give at best; the gap to "fused causal" is what linear acceleration costs
BOUND_ESTIMATOR = "fused causal, lin. acc. removed"


def without_linear_acceleration(run: SimulatedRun) -> np.ndarray:
    """The run's accelerometer readings (N, 3) m/s^2 with its true linear acceleration taken out, in body axes."""
    rotation = quaternion_to_matrix(np.asarray(run.quat_wxyz, dtype=float))
    return run.acc_ms2 - np.einsum("nji,nj->ni", rotation, run.lin_acc_ned_ms2)


def aided_across_seeds(
    seeds: Iterable[int], trajectories: Iterable[Trajectory] = (Trajectory.CAR, Trajectory.MULTIROTOR)
) -> str:
    """The causal velocity-aided heading RMS (deg) of the moving simulator on other seeds (each seed draws another
    sensor and other flights), one line per seed, as the bench scores its own: whether a figure holds on data the
    filter was not built on (docs/aiding.md; about 3 s per trajectory and seed):
    ``python -c "from services.bench import motion; print(motion.aided_across_seeds(range(1, 11)))"``."""
    chosen = sorted(trajectories, key=lambda t: t.value)
    lines = ["seed  " + "".join(f"{t.value:>14}" for t in chosen)]
    for seed in seeds:
        settings = SimulatorSettings(seed=seed)
        errors = simulated_sensor(settings)
        cells = []
        for trajectory in chosen:
            run = moving_run(trajectory, errors, settings)
            field = _simulator_calibration(run, errors, settings)[0].apply(run.mag_ut)
            scored = (run.t_s >= settings.settle_s) & (np.abs(run.pitch_deg) < MAX_PITCH_DEG)
            error = hd.angle_difference_deg(_aided(run, field, offline=False), run.magnetic_heading_deg)[scored]
            cells.append(f"{float(np.sqrt(np.mean(error**2))):>14.3f}")
        lines.append(f"{seed:<6}" + "".join(cells))
    return "\n".join(lines)

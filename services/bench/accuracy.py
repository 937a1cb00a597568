"""``magnet bench accuracy``: the heading error each calibration method leaves, on synthetic data with known truth.

For every method of ``magnet.calibration`` and for misalignment 0 and 5 deg between magnetometer and accelerometer:
``trials`` random sensors (hard iron up to 3x the Earth field in a random direction, symmetric positive definite soft
iron with eigenvalues within +-20 %, 0.3 uT noise; ``magnet.simulator.SensorErrors.random``) are each fitted on a
full-sphere tumble (a level spin for ``minmax2d``, a fast tumble with the gyroscope for ``gyro-ellipsoid``) with the
simulator's accelerometer, then scored on noise-free test
attitudes: every 5 deg of heading, level and tilted 30 deg (nose up, nose down, right side down, left side down),
heading from the tilt-compensated formula with the true accelerometer, error against the true magnetic heading.
Each trial gives an RMS error; the table shows the median over trials (level, tilted, all) and the worst trial.
The fit time is the median over a few fits of 10,000 tumble samples (a spin for ``minmax2d``), quality and gate
included, as ``magnet.calibration.fit`` runs in the calibrator.

Targets (docs/design.md, "Targets"): median RMS <= 0.1 deg for ``ellipsoid`` (aligned sensor) and for
``ellipsoid+align`` and ``gyro-ellipsoid`` (also with 5 deg misalignment); an ellipsoid fit of 10,000 samples well
under 50 ms.
"""

from __future__ import annotations

import dataclasses
import logging
import statistics
import time
from collections.abc import Callable, Iterable

import numpy as np

from magnet.attitude.heading import angle_difference_deg, tilt_compensated_heading_deg
from magnet.calibration import FitInput
from magnet.earth.geomag import EarthField, earth_field
from magnet.frames import ned_to_body_euler
from magnet.model import Calibration
from magnet.simulator import (
    DEFAULT_LAT_DEG,
    DEFAULT_LON_DEG,
    SensorErrors,
    SimulatedRun,
    SimulatorConfig,
    Trajectory,
    simulate,
)
from magnet.units import STANDARD_GRAVITY_MS2

log = logging.getLogger(__name__)

METHODS = ("minmax2d", "minmax", "sphere", "ellipsoid", "ellipsoid+align", "gyro-ellipsoid")
#: method -> trajectory it is fitted on
FIT_TRAJECTORY = {"minmax2d": Trajectory.SPIN, "gyro-ellipsoid": Trajectory.FAST_TUMBLE}
TARGET_RMS_DEG = {
    ("ellipsoid", 0.0): 0.1,
    ("ellipsoid+align", 0.0): 0.1,
    ("ellipsoid+align", 5.0): 0.1,
    ("gyro-ellipsoid", 0.0): 0.1,
    ("gyro-ellipsoid", 5.0): 0.1,
}

#: fit(run (its mag_ut, acc_ms2, gyr_rads, t_s), method, field_ut, truth) -> Calibration; truth for stand-ins only
Fitter = Callable[[SimulatedRun, str, float, SensorErrors], Calibration]


@dataclasses.dataclass(frozen=True)
class AccuracySettings:
    """What the benchmark does; angles in degrees, fields in uT."""

    trials: int = 20
    fit_samples: int = 3000
    spin_samples: int = 720
    noise_ut: float = 0.3
    acc_noise_ms2: float = 0.02
    hard_iron_max_ratio: float = 3.0
    soft_iron_max: float = 0.2
    misalignments_deg: tuple[float, ...] = (0.0, 5.0)
    tilt_deg: float = 30.0
    heading_step_deg: float = 5.0
    timing_samples: int = 10_000
    timing_repeats: int = 5
    fleet_seconds: float = 0.5
    lat_deg: float = DEFAULT_LAT_DEG
    lon_deg: float = DEFAULT_LON_DEG
    date: str = "2026-01-01"
    seed: int = 2025


@dataclasses.dataclass(frozen=True)
class AccuracyRow:
    """One line of the table: medians over trials of the per-trial heading RMS error (degrees)."""

    method: str
    misalignment_deg: float
    level_rms_deg: float
    tilt_rms_deg: float
    all_rms_deg: float
    worst_rms_deg: float
    trials: int
    failed: int
    rejected: int
    fit_ms: float | None = None


def scoring_attitudes(heading_step_deg: float = 5.0, tilt_deg: float = 30.0) -> dict[str, np.ndarray]:
    """Scoring attitudes: magnetic heading every ``heading_step_deg``, level and tilted by ``tilt_deg`` four ways.
    Returns arrays (M,) magnetic_heading_deg, pitch_deg, roll_deg and a boolean ``level``."""
    headings = np.arange(0.0, 360.0, heading_step_deg)
    tilts = [(0.0, 0.0), (tilt_deg, 0.0), (-tilt_deg, 0.0), (0.0, tilt_deg), (0.0, -tilt_deg)]
    pitch = np.concatenate([np.full(headings.size, p) for p, _ in tilts])
    roll = np.concatenate([np.full(headings.size, r) for _, r in tilts])
    return {
        "magnetic_heading_deg": np.tile(headings, len(tilts)),
        "pitch_deg": pitch,
        "roll_deg": roll,
        "level": (pitch == 0.0) & (roll == 0.0),
    }


def heading_errors_deg(
    calibration: Calibration, errors: SensorErrors, earth: EarthField, attitudes: dict[str, np.ndarray]
) -> np.ndarray:
    """Heading error (M,) in degrees the calibration leaves at the attitudes: the sensor's noise-free reading at
    25 C, corrected, tilt-compensated with the true accelerometer, minus the true magnetic heading."""
    heading = attitudes["magnetic_heading_deg"] + earth.declination_deg
    pitch, roll = attitudes["pitch_deg"], attitudes["roll_deg"]
    field = ned_to_body_euler(np.array(earth.ned_ut), heading, pitch, roll)
    acc = ned_to_body_euler(np.array([0.0, 0.0, -STANDARD_GRAVITY_MS2]), heading, pitch, roll)
    raw = field @ errors.distortion.T + errors.hard_iron_ut
    measured = tilt_compensated_heading_deg(calibration.apply(raw), acc)
    return angle_difference_deg(measured, attitudes["magnetic_heading_deg"])


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def real_fitter(run: SimulatedRun, method: str, field_ut: float, truth: SensorErrors) -> Calibration:
    """``magnet.calibration.fit`` (truth unused), with the gyroscope for the method that needs it."""
    from magnet.calibration import fit

    if method == "gyro-ellipsoid":
        period = float(run.t_s[1] - run.t_s[0])
        return fit(
            FitInput(run.mag_ut, acc=run.acc_ms2, field_ut=field_ut, gyr_rads=run.gyr_rads, period_s=period), method
        )
    return fit(FitInput(run.mag_ut, acc=run.acc_ms2, field_ut=field_ut), method)


def truth_fitter(run: SimulatedRun, method: str, field_ut: float, truth: SensorErrors) -> Calibration:
    """Stand-in that 'fits' the exact inverse of the true errors: scores must come out ~0."""
    return truth.true_calibration(field_ut)


def _fit_data(method: str, errors: SensorErrors, settings: AccuracySettings, seed: int, samples: int | None = None):
    trajectory = FIT_TRAJECTORY.get(method, Trajectory.TUMBLE)
    count = samples or (settings.spin_samples if trajectory is Trajectory.SPIN else settings.fit_samples)
    return simulate(
        SimulatorConfig(
            trajectory=trajectory,
            lat_deg=settings.lat_deg,
            lon_deg=settings.lon_deg,
            date=settings.date,
            count=count,
            errors=errors,
            seed=seed,
        )
    )


def _trial_errors(settings: AccuracySettings, earth: EarthField, misalignment_deg: float) -> list[SensorErrors]:
    rng = np.random.default_rng([settings.seed, round(misalignment_deg * 1000)])
    return [
        SensorErrors.random(
            rng,
            earth.total_ut,
            hard_iron_max_ratio=settings.hard_iron_max_ratio,
            soft_iron_max=settings.soft_iron_max,
            misalignment_deg=misalignment_deg,
            noise_ut=settings.noise_ut,
            acc_noise_ms2=settings.acc_noise_ms2,
        )
        for _ in range(settings.trials)
    ]


def accuracy_rows(
    fitter: Fitter = real_fitter, settings: AccuracySettings = AccuracySettings(), methods: Iterable[str] = METHODS
) -> list[AccuracyRow]:
    """The accuracy table (without fit times): one row per (method, misalignment)."""
    earth = earth_field(settings.lat_deg, settings.lon_deg, 0.0, settings.date)
    attitudes = scoring_attitudes(settings.heading_step_deg, settings.tilt_deg)
    level = attitudes["level"]
    rows = []
    for misalignment in settings.misalignments_deg:
        sensors = _trial_errors(settings, earth, misalignment)
        for method in methods:
            per_trial, failed, rejected = [], 0, 0
            for trial, errors in enumerate(sensors):
                run = _fit_data(method, errors, settings, seed=settings.seed + trial)
                try:
                    calibration = fitter(run, method, earth.total_ut, errors)
                except ValueError as exc:  # FitError is a ValueError
                    log.info("%s trial %d failed: %s", method, trial, exc)
                    failed += 1
                    continue
                rejected += not calibration.accepted
                err = heading_errors_deg(calibration, errors, earth, attitudes)
                per_trial.append((_rms(err[level]), _rms(err[~level]), _rms(err)))
            table = np.array(per_trial) if per_trial else np.full((1, 3), np.nan)
            level_rms, tilted_rms, all_rms = (float(m) for m in np.median(table, axis=0))
            rows.append(
                AccuracyRow(
                    method,
                    float(misalignment),
                    level_rms,
                    tilted_rms,
                    all_rms,
                    float(table[:, 2].max()),
                    settings.trials,
                    failed,
                    rejected,
                )
            )
    return rows


def fit_time_ms(method: str, fitter: Fitter = real_fitter, settings: AccuracySettings = AccuracySettings()) -> float:
    """Median wall time (ms) of ``fitter`` on ``timing_samples`` samples, over ``timing_repeats`` runs."""
    earth = earth_field(settings.lat_deg, settings.lon_deg, 0.0, settings.date)
    errors = _trial_errors(settings, earth, 0.0)[0]
    run = _fit_data(method, errors, settings, seed=settings.seed, samples=settings.timing_samples)
    times = []
    for _ in range(settings.timing_repeats):
        start = time.perf_counter()
        fitter(run, method, earth.total_ut, errors)
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def fleet_samples_per_s(devices: int = 1000, batch: int = 100, seconds: float = 0.5) -> float:
    """CPU-time rate (samples/s) at which ``SimulatedDevices`` generates samples for ``devices`` x ``batch`` steps."""
    from magnet.simulator import SimulatedDevices

    fleet = SimulatedDevices(devices, rate_hz=100.0, seed=1, date=AccuracySettings.date)
    fleet.step(batch)
    steps, start = 0, time.process_time()
    while time.process_time() - start < seconds:
        fleet.step(batch)
        steps += 1
    return steps * devices * batch / (time.process_time() - start)


def format_table(rows: list[AccuracyRow], settings: AccuracySettings) -> str:
    """The table as text, with the target verdicts."""
    lines = [
        (
            f"heading RMS error after calibration (deg), median of {settings.trials} random sensors: "
            f"hard iron <= {settings.hard_iron_max_ratio:g}x |B|, soft iron +-{settings.soft_iron_max:.0%}, "
            f"noise {settings.noise_ut:g} uT; fit on {settings.fit_samples} tumble samples "
            f"({settings.spin_samples} level-spin samples for minmax2d); "
            f"scored every {settings.heading_step_deg:g} deg, "
            f"level and {settings.tilt_deg:g} deg tilt"
        ),
        (
            f"{'method':<16}{'misalign':>9}{'level':>9}{'tilted':>9}{'all':>9}{'worst':>9}{'fail':>6}{'reject':>8}"
            f"{'fit ms':>9}  target"
        ),
    ]
    for row in rows:
        target = TARGET_RMS_DEG.get((row.method, row.misalignment_deg))
        verdict = "" if target is None else (f"<= {target:g}: " + ("met" if row.all_rms_deg <= target else "MISSED"))
        fit_ms = "" if row.fit_ms is None else f"{row.fit_ms:.1f}"
        lines.append(
            f"{row.method:<16}{row.misalignment_deg:>8g}d{row.level_rms_deg:>9.3f}{row.tilt_rms_deg:>9.3f}"
            f"{row.all_rms_deg:>9.3f}{row.worst_rms_deg:>9.3f}{row.failed:>6d}{row.rejected:>8d}"
            f"{fit_ms:>9}  {verdict}"
        )
    lines.append(
        f"fit ms: median of {settings.timing_repeats} fits of {settings.timing_samples} samples "
        "(quality figures and gate included); the ellipsoid target is well under 50 ms"
    )
    return "\n".join(lines)


def run_accuracy_benchmark(fitter: Fitter | None = None, settings: AccuracySettings | None = None) -> None:
    """Run the benchmark and print the table (``magnet bench accuracy``)."""
    fitter = fitter or real_fitter
    settings = settings or AccuracySettings()
    started = time.perf_counter()
    rows = accuracy_rows(fitter, settings)
    times = {method: fit_time_ms(method, fitter, settings) for method in METHODS}
    rows = [dataclasses.replace(row, fit_ms=times.get(row.method)) for row in rows]
    print(format_table(rows, settings))
    rate = fleet_samples_per_s(seconds=settings.fleet_seconds)
    print(
        f"simulator: SimulatedDevices makes {rate / 1e6:.2f} million samples/s of CPU time (1000 devices x 100); "
        f"100,000 samples/s costs {1e7 / rate:.1f} % of a core"
    )
    print(f"benchmark time {time.perf_counter() - started:.1f} s")

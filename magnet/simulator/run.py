"""One simulated device: configuration, the run of samples with its truth, ``simulate`` and ``SensorStream``.

Truth per sample: attitude from the trajectory (``magnet.simulator.trajectories`` for the still ones,
``magnet.simulator.motion`` for the moving ones) as the body-to-NED quaternion q and Z-Y-X Euler angles; the Earth's
field B_ned from the WMM; the linear acceleration a_lin (NED, zero for still trajectories); the body angular rate
w_k = log(q_{k-1}* q_k) / dt (q_{k-1} the attitude one sample period earlier), so that the gyroscope integrates to the
attitude. Measurements (``SensorErrors``):

    mag = S M^T R^T B_ned * gain(T) + h(T) + noise (+ spikes)   (R of the attitude mag_lag_s earlier, if any)
    acc = R^T (a_lin - g_ned) + noise                      g_ned = (0, 0, +9.80665): still and level reads (0, 0, -g)
    gyr = w + gyro bias(T) + noise

Noise, spikes and gyroscope noise come from separate generators, so the same samples come out whether they are drawn
at once (``simulate``) or a few at a time (``SensorStream``). Same seed, same data.
"""

from __future__ import annotations

import dataclasses
from typing import Any, cast

import numpy as np

from magnet.earth.geomag import EarthField, earth_field
from magnet.frames import (
    euler_to_quaternion,
    ned_to_body_euler,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_matrix,
    quaternion_to_rotation_vector,
)
from magnet.simulator.disturbances import Disturbances, HardIronChange, HasPath, PassingObjects
from magnet.simulator.errors import SensorErrors
from magnet.simulator.gnss import GnssSettings, gnss_velocity
from magnet.simulator.models import MODELS
from magnet.simulator.motion import G_NED
from magnet.simulator.motors import Motors
from magnet.simulator.trajectories import MIN_COUNT, PATH_TRAJECTORIES, STILL_TRAJECTORIES, Trajectory, wrap_roll

DEFAULT_LAT_DEG = 50.45  # Kyiv, where seed 000's turntable field (Bh 18964 nT, Bv -46962 nT) is typical
DEFAULT_LON_DEG = 30.52
#: the same place as ``--location`` text (the default of every command that simulates a device)
DEFAULT_LOCATION = f"{DEFAULT_LAT_DEG},{DEFAULT_LON_DEG}"
DEFAULT_DATE = "2026-01-01"


@dataclasses.dataclass(frozen=True)
class SimulatorConfig:
    """What to simulate: trajectory, place (degrees, metres) and date of the Earth's field, sample rate (Hz), number of
    samples per run (a still trajectory's period; a moving one just goes on), the sensor's errors and the seed."""

    trajectory: Trajectory = Trajectory.TUMBLE
    lat_deg: float = DEFAULT_LAT_DEG
    lon_deg: float = DEFAULT_LON_DEG
    alt_m: float = 0.0
    date: Any = DEFAULT_DATE
    rate_hz: float = 50.0
    count: int = 3000
    errors: SensorErrors = dataclasses.field(default_factory=SensorErrors)
    seed: int = 0
    motors: Motors | None = None  # the vehicle's motors (``magnet.simulator.motors``): their field, current, throttle
    gnss: GnssSettings = dataclasses.field(default_factory=GnssSettings)
    #: objects passed on the way (``magnet.simulator.disturbances``; trajectories along a path only), or None
    disturbances: Disturbances | None = None
    #: the sensor's hard iron changes mid-run (``magnet.simulator.disturbances``), or None
    hard_iron_change: HardIronChange | None = None

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "trajectory", Trajectory(self.trajectory))
        except ValueError:
            choices = ", ".join(t.value for t in Trajectory)
            raise ValueError(f"unknown trajectory {self.trajectory!r}: use one of {choices}") from None
        if not np.isfinite(self.rate_hz) or self.rate_hz <= 0:
            raise ValueError(f"rate_hz must be a positive number, got {self.rate_hz!r}")
        minimum = MIN_COUNT[self.trajectory]
        if isinstance(self.count, bool) or not isinstance(self.count, (int, np.integer)) or self.count < minimum:
            raise ValueError(
                f"count must be a whole number >= {minimum} for the {self.trajectory.value} trajectory, "
                f"got {self.count!r}"
            )
        if not isinstance(self.errors, SensorErrors):
            raise ValueError("errors must be a SensorErrors")
        if self.disturbances is not None and self.trajectory not in PATH_TRAJECTORIES:
            names = ", ".join(sorted(t.value for t in PATH_TRAJECTORIES))
            raise ValueError(f"disturbances need a trajectory along a path ({names}), not {self.trajectory.value}")


@dataclasses.dataclass(frozen=True, eq=False)
class SimulatedRun:
    """Samples (N) with their truth. Measured: mag_ut (N, 3); acc_ms2 (N, 3) specific force; gyr_rads (N, 3) body
    angular rate with bias and noise. Truth: true_field_ut (N, 3) the Earth's field in the body frame;
    true_acc_ms2 (N, 3) specific force without noise; true_gyr_rads (N, 3) body rate over the sample period ending
    at the sample; lin_acc_ned_ms2 (N, 3) linear acceleration in NED; quat_wxyz (N, 4) attitude body -> NED
    (continuous in time, not sign-normalised); vel_ned_ms (N, 3) the GNSS-like velocity of a moving run
    (``magnet.simulator.gnss``: 10 Hz, 0.1 m/s noise, 0.1 s late, held, NaN before the first fix; None for still
    runs); heading_deg (N,) true heading (from geographic north), magnetic_heading_deg (N,) from magnetic north;
    pitch_deg, roll_deg (N,); mounting (N,) "a"/"b" on the turntable else ""; table_deg (N,) the turntable angle
    (NaN elsewhere); temperature_c (N,); earth the field used; errors the sensor's errors; current_a (N,) A and
    throttle (N,) 0..1 of the motors (None without motors); disturbance_ut (N, 3) the field of the objects passed
    (``magnet.simulator.disturbances``) in the body frame, uT (zeros without them); hard_iron_ut (N, 3) the hard
    iron in force at each sample (it changes with ``SimulatorConfig.hard_iron_change``)."""

    t_s: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray
    true_field_ut: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    mounting: np.ndarray
    table_deg: np.ndarray
    magnetic_heading_deg: np.ndarray
    temperature_c: np.ndarray
    earth: EarthField
    errors: SensorErrors
    gyr_rads: np.ndarray
    true_gyr_rads: np.ndarray
    true_acc_ms2: np.ndarray
    lin_acc_ned_ms2: np.ndarray
    quat_wxyz: np.ndarray
    current_a: np.ndarray | None = None
    throttle: np.ndarray | None = None
    vel_ned_ms: np.ndarray | None = None
    disturbance_ut: np.ndarray | None = None
    hard_iron_ut: np.ndarray | None = None


class _Generator:
    """A simulation in progress: trajectory parameters and independent random streams; ``block`` gives samples
    [start, start + n) of the endless run (still trajectories repeat every ``count`` samples)."""

    def __init__(self, config: SimulatorConfig) -> None:
        self.config = config
        self.earth = earth_field(config.lat_deg, config.lon_deg, config.alt_m, config.date)
        seeds = np.random.SeedSequence(config.seed).spawn(8)
        params_rng = np.random.default_rng(seeds[0])
        self.params = {"phases": params_rng.uniform(0.0, 2.0 * np.pi, 3), "senses": params_rng.choice([-1.0, 1.0], 2)}
        self.mag_noise, self.acc_noise, self.spike_mask, self.spike_vector, self.gyr_noise = (
            np.random.default_rng(s) for s in seeds[1:6]
        )
        self.model = None
        if config.trajectory.moving:
            self.model = MODELS[config.trajectory.value](np.random.default_rng(seeds[6]), self.earth.declination_deg)
        self.b_ned = np.array(self.earth.ned_ut)
        self.objects: tuple[PassingObjects, HasPath] | None = None
        if config.disturbances is not None:  # along a path (the config checked): the model has one
            path_model = cast(HasPath, self.model)
            self.objects = (PassingObjects(config.disturbances, np.random.default_rng(seeds[7])), path_model)

    def _attitude(self, index: np.ndarray) -> tuple[np.ndarray, ...]:
        """(magnetic heading, pitch, roll, mounting, table) at sample indices (may be -1)."""
        config = self.config
        if self.model is None:
            s = np.mod(index, config.count) / config.count
            return STILL_TRAJECTORIES[config.trajectory](s, self.params)
        yaw, pitch, roll = self.model.attitude(index / config.rate_hz)
        return yaw, pitch, roll, np.full(index.shape, ""), np.full(index.shape, np.nan)

    def _motion(
        self, index: np.ndarray, heading: np.ndarray, pitch: np.ndarray, roll: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(quat_wxyz (n, 4), body rate (n, 3) rad/s, linear acceleration NED (n, 3)) at the samples."""
        quat = euler_to_quaternion(heading, pitch, roll)
        before = self._attitude(index - 1)
        quat_before = euler_to_quaternion(before[0] + self.earth.declination_deg, before[1], before[2])
        rate = quaternion_to_rotation_vector(quaternion_multiply(quaternion_conjugate(quat_before), quat))
        rate = rate * self.config.rate_hz
        if self.model is None:
            return quat, rate, np.zeros((index.size, 3))
        return quat, rate, self.model.linear_acceleration(index / self.config.rate_hz, quaternion_to_matrix(quat))

    def block(self, start: int, n: int) -> SimulatedRun:
        config, errors = self.config, self.config.errors
        index = start + np.arange(n)
        t_s = index / config.rate_hz
        magnetic, pitch, roll, mounting, table = self._attitude(index)
        heading = magnetic + self.earth.declination_deg
        quat, rate, lin_acc = self._motion(index, heading, pitch, roll)
        field = ned_to_body_euler(self.b_ned, heading, pitch, roll)
        acc = ned_to_body_euler(lin_acc - G_NED, heading, pitch, roll)
        sensed = field  # what the magnetometer reads: the field of the attitude ``mag_lag_s`` earlier
        if errors.mag_lag_s:
            late = self._attitude(index - errors.mag_lag_s * config.rate_hz)
            sensed = ned_to_body_euler(self.b_ned, late[0] + self.earth.declination_deg, late[1], late[2])
        gain = errors.gain(t_s)
        motors = self.config.motors
        throttle = current = None
        disturbance = np.zeros((n, 3))
        if self.objects is not None:
            objects, path_model = self.objects
            disturbance = ned_to_body_euler(objects.field_ned(path_model, t_s), heading, pitch, roll)
        at_sensor = sensed + disturbance
        if motors is not None:
            thrust = np.linalg.norm(acc, axis=1) / G_NED[2] if config.trajectory is Trajectory.MULTIROTOR else None
            throttle = motors.throttle(t_s, thrust)
            current = motors.current_a(throttle)
            at_sensor = sensed + motors.field_ut(current)
        hard_iron = errors.hard_iron(t_s)
        change = config.hard_iron_change
        if change is not None:
            after = t_s >= change.t_s  # the new iron, drifting with the temperature as the old one did
            hard_iron[after] = change.hard_iron_ut + (hard_iron[after] - errors.hard_iron_ut)
        mag = (at_sensor @ errors.distortion.T) * gain[:, None] + hard_iron
        mag = mag + errors.noise_ut * self.mag_noise.standard_normal((n, 3))
        acc_measured = acc + errors.acc_noise_ms2 * self.acc_noise.standard_normal((n, 3))
        spikes = self.spike_mask.random(n) < errors.spike_probability
        directions = self.spike_vector.standard_normal((n, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        mag = mag + np.where(spikes[:, None], errors.spike_ut * directions, 0.0)
        gyr = rate + errors.gyro_bias(t_s) + errors.gyro_noise_rads * self.gyr_noise.standard_normal((n, 3))
        temperature = errors.temperature_c + errors.temperature_ramp_k_per_s * t_s
        return SimulatedRun(
            t_s=t_s,
            mag_ut=mag,
            acc_ms2=acc_measured,
            true_field_ut=field,
            heading_deg=np.mod(heading, 360.0),
            pitch_deg=pitch + 0.0,
            roll_deg=wrap_roll(roll),
            mounting=mounting,
            table_deg=table,
            magnetic_heading_deg=np.mod(magnetic, 360.0),
            temperature_c=temperature,
            earth=self.earth,
            errors=errors,
            gyr_rads=gyr,
            true_gyr_rads=rate,
            true_acc_ms2=acc,
            lin_acc_ned_ms2=lin_acc,
            quat_wxyz=quat,
            current_a=current,
            throttle=throttle,
            vel_ned_ms=None if self.model is None else gnss_velocity(self.model, t_s, config.seed, config.gnss),
            disturbance_ut=disturbance,
            hard_iron_ut=hard_iron,
        )


def simulate(config: SimulatorConfig) -> SimulatedRun:
    """One run of ``config.count`` samples (see the module docstring for the models)."""
    return _Generator(config).block(0, config.count)


class SensorStream:
    """One sample at a time, endlessly (a still run repeats every ``count`` samples with fresh noise; a moving one goes
    on): the source a chip emulator reads its field, specific force and angular rate from. The first ``count``
    samples equal ``simulate(config)``."""

    BLOCK = 1024

    def __init__(self, config: SimulatorConfig) -> None:
        self.config = config
        self._generator = _Generator(config)
        self._block: SimulatedRun | None = None
        self._index = 0  # next sample
        self._block_start = 0
        self.last_truth: dict[str, Any] = {}

    @property
    def earth(self) -> EarthField:
        return self._generator.earth

    def measure(self) -> tuple[np.ndarray, np.ndarray]:
        """The next sample: (mag_ut (3,), acc_ms2 (3,)); its truth is then in ``last_truth``."""
        mag, acc, _ = self.measure_imu()
        return mag, acc

    def measure_imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The next sample with the gyroscope: (mag_ut (3,), acc_ms2 (3,), gyr_rads (3,)); truth in ``last_truth``:
        t_s, heading_deg, magnetic_heading_deg, pitch_deg, roll_deg, temperature_c, mounting, table_deg, and
        quat_wxyz (a tuple of 4 floats), vel_ned_ms (the GNSS-like velocity, 3 floats, NaN before the first fix;
        None for a still run); with motors also current_a (A) and throttle (0..1)."""
        offset = self._index - self._block_start
        if self._block is None or offset >= self._block.t_s.size:
            self._block_start = self._index
            self._block = self._generator.block(self._index, self.BLOCK)
            offset = 0
        run, i = self._block, offset
        self._index += 1
        self.last_truth = {
            "t_s": float(run.t_s[i]),
            "heading_deg": float(run.heading_deg[i]),
            "magnetic_heading_deg": float(run.magnetic_heading_deg[i]),
            "pitch_deg": float(run.pitch_deg[i]),
            "roll_deg": float(run.roll_deg[i]),
            "temperature_c": float(run.temperature_c[i]),
            "mounting": str(run.mounting[i]),
            "table_deg": float(run.table_deg[i]),
            "quat_wxyz": tuple(float(v) for v in run.quat_wxyz[i]),
            "vel_ned_ms": None if run.vel_ned_ms is None else tuple(float(v) for v in run.vel_ned_ms[i]),
        }
        if run.current_a is not None and run.throttle is not None:
            self.last_truth.update(current_a=float(run.current_a[i]), throttle=float(run.throttle[i]))
        return run.mag_ut[i].copy(), run.acc_ms2[i].copy(), run.gyr_rads[i].copy()

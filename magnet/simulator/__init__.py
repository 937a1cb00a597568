"""Physical simulator of a magnetometer + accelerometer moved through known attitudes in the Earth's field.

Truth. The Earth's field comes from WMM2025 (``magnet.geomag``) at a place and date, as a north-east-down (NED) vector
B_ned in uT. An attitude trajectory gives, per sample, the magnetic heading K of the body x axis (clockwise from
magnetic north), pitch and roll (Z-Y-X Euler angles, ``magnet.attitude``); the true heading is K + declination. The
device is still at every sample (quasi-static: the accelerometer reads gravity only):

    B_body = R^T B_ned,      f_body = R^T (0, 0, -g),      R = Rz(true heading) Ry(pitch) Rx(roll)

Sensor model (docs/design.md, "Sensors and the simulator"). M is the magnetometer's orientation in the body
(= accelerometer) frame, from the small angles ``misalignment_deg`` (roll, pitch, yaw); S the soft-iron / gain /
cross-axis matrix; h the hard iron:

    mag_measured = S @ M^T @ B_body * (1 + tempco * (T - 25 C)) + h + noise (+ occasional spikes)
    acc_measured = f_body + noise

so the exact correction (at 25 C) is B_body = M @ S^-1 @ (mag - h) (``SensorErrors.true_calibration``).

Trajectories (``Trajectory``), each a periodic function of the sample index with period ``count``:
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

Everything is deterministic from ``seed``; noise, acc noise and spikes come from separate generators, so the same
samples come out whether they are drawn at once (``simulate``) or a few at a time (``SensorStream``).
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

import numpy as np

from magnet.attitude import axis_angle_matrix, euler_to_matrix, matrix_to_euler, random_rotations
from magnet.geomag import EarthField, earth_field
from magnet.model import Calibration
from magnet.units import STANDARD_GRAVITY_MS2

DEFAULT_LAT_DEG = 50.45   # Kyiv, where seed 000's turntable field (Bh 18964 nT, Bv -46962 nT) is typical
DEFAULT_LON_DEG = 30.52
DEFAULT_DATE = "2026-01-01"
REFERENCE_TEMPERATURE_C = 25.0

TURNTABLE_STEP_DEG = 30
TURNTABLE_ANGLES_DEG = tuple(range(0, 361, TURNTABLE_STEP_DEG))  # 0..360 inclusive, as in seed 000's table
TURNTABLE_ROLL_DEG = {"a": 180.0, "b": 90.0}                     # a: z up; b: y down
TENFACE_STATIONS = (  # (pitch_deg, roll_deg): six faces, then four 45-degree edges
    (0.0, 0.0), (0.0, 180.0), (0.0, 90.0), (0.0, -90.0), (90.0, 0.0), (-90.0, 0.0),
    (45.0, 0.0), (-45.0, 0.0), (0.0, 45.0), (0.0, -45.0),
)
TUMBLE_CYCLES = (21, 13, 8)    # pitch oscillations, roll turns, heading turns over one run (Fibonacci: no short
                               # Lissajous repeats, so the run covers every field and gravity direction)
TUMBLE_PITCH_AMPLITUDE_DEG = 85.0
GOLDEN_RATIO_MINOR = (5 ** 0.5 - 1) / 2   # 0.618...


class Trajectory(enum.Enum):
    SPIN = "spin"
    TURNTABLE = "turntable"
    TUMBLE = "tumble"
    TENFACE = "tenface"


def _vector(value: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite numbers of shape {shape}, got {np.asarray(value).tolist()!r}")
    arr.setflags(write=False)
    return arr


def _non_negative(value: float, name: str) -> float:
    number = float(value)
    if not np.isfinite(number) or number < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return number


@dataclasses.dataclass(frozen=True, eq=False)
class SensorErrors:
    """The errors of one magnetometer + accelerometer pair (see the module docstring for the model).

    hard_iron_ut (3,) uT; soft_iron (3, 3) dimensionless (identity = none); misalignment_deg (3,) roll, pitch, yaw of
    the magnetometer frame in the accelerometer (body) frame; noise_ut per axis (1 sigma); acc_noise_ms2 per axis;
    spike_probability per sample and spike_ut (magnitude of a spike, random direction); gain_tempco_per_k relative gain
    change per kelvin from 25 C; temperature_c at t = 0 and temperature_ramp_k_per_s its drift.
    """

    hard_iron_ut: Any = (0.0, 0.0, 0.0)
    soft_iron: Any = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    misalignment_deg: Any = (0.0, 0.0, 0.0)
    noise_ut: float = 0.0
    acc_noise_ms2: float = 0.0
    spike_probability: float = 0.0
    spike_ut: float = 0.0
    gain_tempco_per_k: float = 0.0
    temperature_c: float = REFERENCE_TEMPERATURE_C
    temperature_ramp_k_per_s: float = 0.0

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "hard_iron_ut", _vector(self.hard_iron_ut, "hard_iron_ut", (3,)))
        set_(self, "soft_iron", _vector(self.soft_iron, "soft_iron", (3, 3)))
        set_(self, "misalignment_deg", _vector(self.misalignment_deg, "misalignment_deg", (3,)))
        if abs(np.linalg.det(self.soft_iron)) < 1e-9:
            raise ValueError("soft_iron must be an invertible 3x3 matrix")
        for name in ("noise_ut", "acc_noise_ms2", "spike_ut"):
            set_(self, name, _non_negative(getattr(self, name), name))
        probability = _non_negative(self.spike_probability, "spike_probability")
        if probability > 1:
            raise ValueError(f"spike_probability must be within 0..1, got {probability}")
        set_(self, "spike_probability", probability)
        for name in ("gain_tempco_per_k", "temperature_c", "temperature_ramp_k_per_s"):
            number = float(getattr(self, name))
            if not np.isfinite(number):
                raise ValueError(f"{name} must be a finite number, got {getattr(self, name)!r}")
            set_(self, name, number)

    @property
    def misalignment_matrix(self) -> np.ndarray:
        """M (3, 3): the magnetometer axes expressed in the body frame; field in magnetometer axes = M^T B_body."""
        roll, pitch, yaw = self.misalignment_deg
        return euler_to_matrix(yaw, pitch, roll)

    @property
    def distortion(self) -> np.ndarray:
        """S @ M^T (3, 3): measured = distortion @ B_body * gain + hard iron."""
        return self.soft_iron @ self.misalignment_matrix.T

    def gain(self, t_s: np.ndarray) -> np.ndarray:
        """Relative gain (same shape as t_s) from the temperature at time t_s (seconds from the start)."""
        temperature = self.temperature_c + self.temperature_ramp_k_per_s * np.asarray(t_s, dtype=float)
        return 1.0 + self.gain_tempco_per_k * (temperature - REFERENCE_TEMPERATURE_C)

    def true_calibration(self, field_strength_ut: float = 0.0) -> Calibration:
        """The exact correction at 25 C: B_body = M S^-1 (mag - h), as a calibration record."""
        return Calibration(method="truth", offset=self.hard_iron_ut,
                           matrix=self.misalignment_matrix @ np.linalg.inv(self.soft_iron),
                           field_strength=field_strength_ut, reason="the simulator's true errors")

    @classmethod
    def random(cls, rng: np.random.Generator, field_ut: float, *, hard_iron_max_ratio: float = 3.0,
               soft_iron_max: float = 0.2, misalignment_deg: float = 0.0, **other: Any) -> "SensorErrors":
        """Random errors: hard iron in a random direction with magnitude uniform in 0..hard_iron_max_ratio x the field;
        soft iron symmetric positive definite, eigenvalues uniform in 1 +- soft_iron_max, random axes; misalignment a
        rotation of ``misalignment_deg`` about a random axis. ``other`` sets the remaining fields (noise_ut, ...)."""
        direction = rng.standard_normal(3)
        hard = direction / np.linalg.norm(direction) * rng.uniform(0.0, hard_iron_max_ratio) * field_ut
        axes = random_rotations(1, rng)[0]
        soft = axes @ np.diag(rng.uniform(1.0 - soft_iron_max, 1.0 + soft_iron_max, 3)) @ axes.T
        misalignment = (0.0, 0.0, 0.0)
        if misalignment_deg:
            tilt = axis_angle_matrix(rng.standard_normal(3), misalignment_deg)
            yaw, pitch, roll = matrix_to_euler(tilt)
            misalignment = (float(roll), float(pitch), float((yaw + 180.0) % 360.0 - 180.0))
        return cls(hard_iron_ut=hard, soft_iron=soft, misalignment_deg=misalignment, **other)


@dataclasses.dataclass(frozen=True)
class SimulatorConfig:
    """What to simulate: trajectory, place (degrees, metres) and date of the Earth's field, sample rate (Hz), number of
    samples per run (the trajectory's period), the sensor's errors and the random seed."""

    trajectory: Trajectory = Trajectory.TUMBLE
    lat_deg: float = DEFAULT_LAT_DEG
    lon_deg: float = DEFAULT_LON_DEG
    alt_m: float = 0.0
    date: Any = DEFAULT_DATE
    rate_hz: float = 50.0
    count: int = 3000
    errors: SensorErrors = dataclasses.field(default_factory=SensorErrors)
    seed: int = 0

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "trajectory", Trajectory(self.trajectory))
        except ValueError:
            choices = ", ".join(t.value for t in Trajectory)
            raise ValueError(f"unknown trajectory {self.trajectory!r}: use one of {choices}") from None
        if not np.isfinite(self.rate_hz) or self.rate_hz <= 0:
            raise ValueError(f"rate_hz must be a positive number, got {self.rate_hz!r}")
        minimum = _MIN_COUNT[self.trajectory]
        if isinstance(self.count, bool) or not isinstance(self.count, (int, np.integer)) or self.count < minimum:
            raise ValueError(f"count must be a whole number >= {minimum} for the {self.trajectory.value} trajectory, "
                             f"got {self.count!r}")
        if not isinstance(self.errors, SensorErrors):
            raise ValueError("errors must be a SensorErrors")


_MIN_COUNT = {Trajectory.SPIN: 2, Trajectory.TURNTABLE: 2 * len(TURNTABLE_ANGLES_DEG), Trajectory.TUMBLE: 2,
              Trajectory.TENFACE: len(TENFACE_STATIONS)}


@dataclasses.dataclass(frozen=True, eq=False)
class SimulatedRun:
    """Samples (N) with their truth. mag_ut (N, 3) measured; acc_ms2 (N, 3) measured specific force; true_field_ut
    (N, 3) the Earth's field in the body frame; heading_deg (N,) true heading (from geographic north),
    magnetic_heading_deg (N,) from magnetic north; pitch_deg, roll_deg (N,); mounting (N,) "a"/"b" on the turntable
    else ""; table_deg (N,) the turntable angle (NaN elsewhere); temperature_c (N,); earth the field used."""

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


# ---------------------------------------------------------------------------------------------------------------------
# Attitude trajectories: functions of the phase s in [0, 1) of a run -> magnetic heading, pitch, roll (degrees),
# mounting and table angle.

def _spin(s: np.ndarray, params: dict) -> tuple:
    zero = np.zeros_like(s)
    return 360.0 * s, zero, zero, np.full(s.shape, ""), np.full(s.shape, np.nan)


def _turntable(s: np.ndarray, params: dict) -> tuple:
    steps = len(TURNTABLE_ANGLES_DEG)
    station = np.minimum((s * 2 * steps).astype(int), 2 * steps - 1)
    mounting = np.where(station < steps, "a", "b")
    table = np.asarray(TURNTABLE_ANGLES_DEG, dtype=float)[station % steps]
    roll = np.where(mounting == "a", TURNTABLE_ROLL_DEG["a"], TURNTABLE_ROLL_DEG["b"])
    return table, np.zeros_like(s), roll, mounting, table


def _tenface(s: np.ndarray, params: dict) -> tuple:
    stations = np.asarray(TENFACE_STATIONS)
    position = s * len(stations)
    station = np.minimum(position.astype(int), len(stations) - 1)
    yaw = 360.0 * (position - station)
    return yaw, stations[station, 0], stations[station, 1], np.full(s.shape, ""), np.full(s.shape, np.nan)


def _tumble(s: np.ndarray, params: dict) -> tuple:
    phase = 2.0 * np.pi * s
    pitch_cycles, roll_turns, yaw_turns = TUMBLE_CYCLES
    pitch = TUMBLE_PITCH_AMPLITUDE_DEG * np.sin(pitch_cycles * phase + params["phases"][0])
    roll = params["senses"][0] * 360.0 * roll_turns * s + np.degrees(params["phases"][1])
    yaw = params["senses"][1] * 360.0 * yaw_turns * s + np.degrees(params["phases"][2])
    return yaw, pitch, roll, np.full(s.shape, ""), np.full(s.shape, np.nan)


_TRAJECTORIES = {Trajectory.SPIN: _spin, Trajectory.TURNTABLE: _turntable, Trajectory.TENFACE: _tenface,
                 Trajectory.TUMBLE: _tumble}


def ned_to_body_euler(vector_ned: np.ndarray, yaw_deg: np.ndarray, pitch_deg: np.ndarray,
                      roll_deg: np.ndarray) -> np.ndarray:
    """R^T v for R = Rz(yaw) Ry(pitch) Rx(roll), without building matrices: vector (3,) or (..., 3) in NED, angles
    broadcastable, result (..., 3) in body axes. The fast path of the simulators (three elementary rotations)."""
    v = np.asarray(vector_ned, dtype=float)
    y, p, r = (np.radians(np.asarray(a, dtype=float)) for a in (yaw_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    n, e, d = v[..., 0], v[..., 1], v[..., 2]
    x1 = cy * n + sy * e            # Rz^T
    y1 = -sy * n + cy * e
    x2 = cp * x1 - sp * d           # Ry^T
    z2 = sp * x1 + cp * d
    y3 = cr * y1 + sr * z2          # Rx^T
    z3 = -sr * y1 + cr * z2
    return np.stack(np.broadcast_arrays(x2, y3, z3), axis=-1)


def _wrap_roll(roll_deg: np.ndarray) -> np.ndarray:
    """Roll wrapped to (-180, 180]."""
    return 180.0 - np.mod(180.0 - roll_deg, 360.0)


class _Generator:
    """A simulation in progress: trajectory parameters and independent random streams; ``block`` gives samples
    [start, start + n) of the endless, ``count``-periodic run."""

    def __init__(self, config: SimulatorConfig) -> None:
        self.config = config
        self.earth = earth_field(config.lat_deg, config.lon_deg, config.alt_m, config.date)
        seeds = np.random.SeedSequence(config.seed).spawn(5)
        params_rng = np.random.default_rng(seeds[0])
        self.params = {"phases": params_rng.uniform(0.0, 2.0 * np.pi, 3),
                       "senses": params_rng.choice([-1.0, 1.0], 2)}
        self.mag_noise, self.acc_noise, self.spike_mask, self.spike_vector = (
            np.random.default_rng(s) for s in seeds[1:])
        self.b_ned = np.array(self.earth.ned_ut)

    def block(self, start: int, n: int) -> SimulatedRun:
        config, errors = self.config, self.config.errors
        index = start + np.arange(n)
        t_s = index / config.rate_hz
        s = np.mod(index, config.count) / config.count
        magnetic, pitch, roll, mounting, table = _TRAJECTORIES[config.trajectory](s, self.params)
        heading = magnetic + self.earth.declination_deg
        field = ned_to_body_euler(self.b_ned, heading, pitch, roll)
        acc = ned_to_body_euler(np.array([0.0, 0.0, -STANDARD_GRAVITY_MS2]), heading, pitch, roll)
        gain = errors.gain(t_s)
        mag = (field @ errors.distortion.T) * gain[:, None] + errors.hard_iron_ut
        mag = mag + errors.noise_ut * self.mag_noise.standard_normal((n, 3))
        acc_measured = acc + errors.acc_noise_ms2 * self.acc_noise.standard_normal((n, 3))
        spikes = self.spike_mask.random(n) < errors.spike_probability
        directions = self.spike_vector.standard_normal((n, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        mag = mag + np.where(spikes[:, None], errors.spike_ut * directions, 0.0)
        temperature = errors.temperature_c + errors.temperature_ramp_k_per_s * t_s
        return SimulatedRun(
            t_s=t_s, mag_ut=mag, acc_ms2=acc_measured, true_field_ut=field,
            heading_deg=np.mod(heading, 360.0), pitch_deg=pitch + 0.0, roll_deg=_wrap_roll(roll),
            mounting=mounting, table_deg=table, magnetic_heading_deg=np.mod(magnetic, 360.0),
            temperature_c=temperature, earth=self.earth, errors=errors,
        )


def simulate(config: SimulatorConfig) -> SimulatedRun:
    """One run of ``config.count`` samples (see the module docstring for the models)."""
    return _Generator(config).block(0, config.count)


class SensorStream:
    """One sample at a time, endlessly (the run repeats every ``count`` samples with fresh noise): the source a chip
    emulator reads its field and specific force from. The first ``count`` samples equal ``simulate(config)``."""

    BLOCK = 1024

    def __init__(self, config: SimulatorConfig) -> None:
        self.config = config
        self._generator = _Generator(config)
        self._block: SimulatedRun | None = None
        self._index = 0           # next sample
        self._block_start = 0
        self.last_truth: dict[str, float] = {}

    @property
    def earth(self) -> EarthField:
        return self._generator.earth

    def measure(self) -> tuple[np.ndarray, np.ndarray]:
        """The next sample: (mag_ut (3,), acc_ms2 (3,)); its truth is then in ``last_truth``."""
        offset = self._index - self._block_start
        if self._block is None or offset >= self._block.t_s.size:
            self._block_start = self._index
            self._block = self._generator.block(self._index, self.BLOCK)
            offset = 0
        run, i = self._block, offset
        self._index += 1
        self.last_truth = {
            "t_s": float(run.t_s[i]), "heading_deg": float(run.heading_deg[i]),
            "magnetic_heading_deg": float(run.magnetic_heading_deg[i]), "pitch_deg": float(run.pitch_deg[i]),
            "roll_deg": float(run.roll_deg[i]), "temperature_c": float(run.temperature_c[i]),
            "mounting": str(run.mounting[i]), "table_deg": float(run.table_deg[i]),
        }
        return run.mag_ut[i].copy(), run.acc_ms2[i].copy()


# ---------------------------------------------------------------------------------------------------------------------
# Fleet: many devices at once, vectorized over devices and samples.

@dataclasses.dataclass(frozen=True, eq=False)
class FleetBatch:
    """One step of the fleet: t_ns (n,) from the fleet's start; mag_ut, acc_ms2 (D, n, 3) measured; heading_deg
    (D, n) true heading; pitch_deg, roll_deg (D, n)."""

    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray


class FleetSimulator:
    """D devices tumbling smoothly at one place, each with its own random hard and soft iron (``errors[d]``) and its
    own trajectory: pitch = 85 sin(2 pi f_p t + phase), roll and heading turning at f_r and f_y turns/s, random per
    device: f_p 0.15-0.25 Hz, f_r about 0.618 f_p and f_y about 0.382 f_p (golden ratios, +-2 %, random senses: the
    path never closes early, so each device covers the sphere in about two minutes). ``step(n)`` advances every device by n samples."""

    def __init__(self, n_devices: int, rate_hz: float = 100.0, seed: int = 0, lat_deg: float = DEFAULT_LAT_DEG,
                 lon_deg: float = DEFAULT_LON_DEG, date: Any = DEFAULT_DATE, noise_ut: float = 0.3, *,
                 alt_m: float = 0.0, acc_noise_ms2: float = 0.02, hard_iron_max_ratio: float = 2.0,
                 soft_iron_max: float = 0.15, misalignment_deg: float = 0.0) -> None:
        if isinstance(n_devices, bool) or not isinstance(n_devices, (int, np.integer)) or n_devices < 1:
            raise ValueError(f"n_devices must be a whole number >= 1, got {n_devices!r}")
        if not np.isfinite(rate_hz) or rate_hz <= 0:
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
        self.n_devices, self.rate_hz = int(n_devices), float(rate_hz)
        self.earth = earth_field(lat_deg, lon_deg, alt_m, date)
        seeds = np.random.SeedSequence(seed).spawn(3)
        setup = np.random.default_rng(seeds[0])
        self.errors = tuple(
            SensorErrors.random(setup, self.earth.total_ut, hard_iron_max_ratio=hard_iron_max_ratio,
                                soft_iron_max=soft_iron_max, misalignment_deg=misalignment_deg,
                                noise_ut=noise_ut, acc_noise_ms2=acc_noise_ms2)
            for _ in range(self.n_devices))
        d = self.n_devices
        pitch_hz = setup.uniform(0.15, 0.25, d)
        self._frequency_hz = np.stack([
            pitch_hz,
            pitch_hz * GOLDEN_RATIO_MINOR * setup.uniform(0.98, 1.02, d) * setup.choice([-1.0, 1.0], d),
            pitch_hz * GOLDEN_RATIO_MINOR ** 2 * setup.uniform(0.98, 1.02, d) * setup.choice([-1.0, 1.0], d),
        ], axis=1)
        self._phase = setup.uniform(0.0, 2.0 * np.pi, (d, 3))
        self._distortion = np.stack([e.distortion for e in self.errors])      # (D, 3, 3)
        self._hard_iron = np.stack([e.hard_iron_ut for e in self.errors])     # (D, 3)
        self._noise_ut, self._acc_noise = float(noise_ut), float(acc_noise_ms2)
        self._rng = np.random.default_rng(seeds[1])
        self._b_ned = np.array(self.earth.ned_ut)
        self._next = 0

    def step(self, n: int) -> FleetBatch:
        """The next n samples of every device."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"step needs a whole number of samples >= 1, got {n!r}")
        index = self._next + np.arange(n)
        self._next += n
        t_s = index / self.rate_hz
        turns = 2.0 * np.pi * self._frequency_hz[:, None, :] * t_s[None, :, None] + self._phase[:, None, :]
        pitch = TUMBLE_PITCH_AMPLITUDE_DEG * np.sin(turns[..., 0])
        roll = np.degrees(turns[..., 1])
        heading = np.degrees(turns[..., 2])
        field = ned_to_body_euler(self._b_ned, heading, pitch, roll)                              # (D, n, 3)
        acc = ned_to_body_euler(np.array([0.0, 0.0, -STANDARD_GRAVITY_MS2]), heading, pitch, roll)
        mag = np.einsum("dij,dnj->dni", self._distortion, field) + self._hard_iron[:, None, :]
        rng = self._rng
        if self._noise_ut:
            mag += self._noise_ut * rng.standard_normal(mag.shape)
        if self._acc_noise:
            acc += self._acc_noise * rng.standard_normal(acc.shape)
        t_ns = np.round(index * (1e9 / self.rate_hz)).astype(np.int64)
        return FleetBatch(t_ns=t_ns, mag_ut=mag, acc_ms2=acc, heading_deg=np.mod(heading, 360.0),
                          pitch_deg=pitch, roll_deg=_wrap_roll(roll))

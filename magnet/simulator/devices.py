"""Many simulated devices at once, vectorized over devices and samples (``SimulatedDevices``)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from magnet.earth.geomag import earth_field
from magnet.frames import (
    euler_to_quaternion,
    ned_to_body_euler,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_rotation_vector,
)
from magnet.simulator.errors import SensorErrors
from magnet.simulator.run import DEFAULT_DATE, DEFAULT_LAT_DEG, DEFAULT_LON_DEG
from magnet.simulator.trajectories import GOLDEN_RATIO_MINOR, TUMBLE_PITCH_AMPLITUDE_DEG, wrap_roll
from magnet.units import STANDARD_GRAVITY_MS2


@dataclasses.dataclass(frozen=True, eq=False)
class DevicesBatch:
    """One step of the devices: t_ns (n,) from their start; mag_ut, acc_ms2 (D, n, 3) measured; heading_deg
    (D, n) true heading; pitch_deg, roll_deg (D, n); gyr_rads (D, n, 3) body rate (rad/s, the rate that carries each
    sample's attitude from the one before, plus noise) when the devices were made with ``gyro=True``, else None."""

    t_ns: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    gyr_rads: np.ndarray | None = None


class SimulatedDevices:
    """D devices tumbling smoothly at one place, each with its own random hard and soft iron (``errors[d]``) and its
    own trajectory: pitch = 85 sin(2 pi f_p t + phase), roll and heading turning at f_r and f_y turns/s, random per
    device: f_p 0.15-0.25 Hz, f_r about 0.618 f_p and f_y about 0.382 f_p (golden ratios, +-2 %, random senses: the
    path never closes early, so each device covers the sphere in about two minutes). ``step(n)`` advances every
    device by n samples. ``gyro=True`` adds a gyroscope (noise ``gyro_noise_rads`` per axis, rad/s)."""

    def __init__(
        self,
        n_devices: int,
        rate_hz: float = 100.0,
        seed: int = 0,
        lat_deg: float = DEFAULT_LAT_DEG,
        lon_deg: float = DEFAULT_LON_DEG,
        date: Any = DEFAULT_DATE,
        noise_ut: float = 0.3,
        *,
        alt_m: float = 0.0,
        acc_noise_ms2: float = 0.02,
        hard_iron_max_ratio: float = 2.0,
        soft_iron_max: float = 0.15,
        misalignment_deg: float = 0.0,
        gyro: bool = False,
        gyro_noise_rads: float = 0.0,
    ) -> None:
        if isinstance(n_devices, bool) or not isinstance(n_devices, (int, np.integer)) or n_devices < 1:
            raise ValueError(f"n_devices must be a whole number >= 1, got {n_devices!r}")
        if not np.isfinite(rate_hz) or rate_hz <= 0:
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
        self.n_devices, self.rate_hz = int(n_devices), float(rate_hz)
        self.earth = earth_field(lat_deg, lon_deg, alt_m, date)
        seeds = np.random.SeedSequence(seed).spawn(3)
        setup = np.random.default_rng(seeds[0])
        self.errors = tuple(
            SensorErrors.random(
                setup,
                self.earth.total_ut,
                hard_iron_max_ratio=hard_iron_max_ratio,
                soft_iron_max=soft_iron_max,
                misalignment_deg=misalignment_deg,
                noise_ut=noise_ut,
                acc_noise_ms2=acc_noise_ms2,
            )
            for _ in range(self.n_devices)
        )
        d = self.n_devices
        pitch_hz = setup.uniform(0.15, 0.25, d)
        self._frequency_hz = np.stack(
            [
                pitch_hz,
                pitch_hz * GOLDEN_RATIO_MINOR * setup.uniform(0.98, 1.02, d) * setup.choice([-1.0, 1.0], d),
                pitch_hz * GOLDEN_RATIO_MINOR**2 * setup.uniform(0.98, 1.02, d) * setup.choice([-1.0, 1.0], d),
            ],
            axis=1,
        )
        self._phase = setup.uniform(0.0, 2.0 * np.pi, (d, 3))
        self._distortion = np.stack([e.distortion for e in self.errors])  # (D, 3, 3)
        self._hard_iron = np.stack([e.hard_iron_ut for e in self.errors])  # (D, 3)
        self._noise_ut, self._acc_noise = float(noise_ut), float(acc_noise_ms2)
        self._rng = np.random.default_rng(seeds[1])
        self._b_ned = np.array(self.earth.ned_ut)
        self._next = 0
        self._gyro, self._gyro_noise = bool(gyro), float(gyro_noise_rads)
        self._gyro_rng = np.random.default_rng(seeds[2])

    def change_iron(self, device: int, hard_iron_ut: Any = None, soft_iron: Any = None) -> None:
        """New iron near device ``device`` from the next sample on (a drift): hard_iron_ut (3,) uT and/or
        soft_iron (3, 3) replace its own (``errors[device]`` keeps what it was calibrated with)."""
        if hard_iron_ut is not None:
            self._hard_iron[device] = np.asarray(hard_iron_ut, dtype=float).reshape(3)
        if soft_iron is not None:
            errors = dataclasses.replace(self.errors[device], soft_iron=np.asarray(soft_iron, dtype=float))
            self._distortion[device] = errors.distortion

    def step(self, n: int) -> DevicesBatch:
        """The next n samples of every device."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"step needs a whole number of samples >= 1, got {n!r}")
        index = self._next + np.arange(n)
        self._next += n
        heading, pitch, roll = self._attitude(index)
        field = ned_to_body_euler(self._b_ned, heading, pitch, roll)  # (D, n, 3)
        acc = ned_to_body_euler(np.array([0.0, 0.0, -STANDARD_GRAVITY_MS2]), heading, pitch, roll)
        mag = np.einsum("dij,dnj->dni", self._distortion, field) + self._hard_iron[:, None, :]
        rng = self._rng
        if self._noise_ut:
            mag += self._noise_ut * rng.standard_normal(mag.shape)
        if self._acc_noise:
            acc += self._acc_noise * rng.standard_normal(acc.shape)
        t_ns = np.round(index * (1e9 / self.rate_hz)).astype(np.int64)
        return DevicesBatch(
            t_ns=t_ns,
            mag_ut=mag,
            acc_ms2=acc,
            heading_deg=np.mod(heading, 360.0),
            pitch_deg=pitch,
            roll_deg=wrap_roll(roll),
            gyr_rads=self._rates(index, heading, pitch, roll) if self._gyro else None,
        )

    def _attitude(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(heading, pitch, roll) degrees (D, n) at sample indices (n,)."""
        t_s = index / self.rate_hz
        turns = 2.0 * np.pi * self._frequency_hz[:, None, :] * t_s[None, :, None] + self._phase[:, None, :]
        return np.degrees(turns[..., 2]), TUMBLE_PITCH_AMPLITUDE_DEG * np.sin(turns[..., 0]), np.degrees(turns[..., 1])

    def _rates(self, index: np.ndarray, heading: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
        """Body rates (D, n, 3) rad/s from the attitude one sample earlier to each sample's, plus noise."""
        before = euler_to_quaternion(*self._attitude(index - 1))
        step = quaternion_multiply(quaternion_conjugate(before), euler_to_quaternion(heading, pitch, roll))
        rates = quaternion_to_rotation_vector(step) * self.rate_hz
        if self._gyro_noise:
            rates += self._gyro_noise * self._gyro_rng.standard_normal(rates.shape)
        return rates

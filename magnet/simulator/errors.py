"""The errors of one simulated magnetometer + accelerometer (+ gyroscope): hard and soft iron, misalignment, noise,
spikes, temperature drift, gyroscope bias and noise (see ``magnet.simulator`` for the measurement model)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from magnet.frames import axis_angle_matrix, euler_to_matrix, matrix_to_euler, random_rotations
from magnet.model import Calibration

REFERENCE_TEMPERATURE_C = 25.0


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
    """The errors of one magnetometer + accelerometer + gyroscope (see ``magnet.simulator`` for the model).

    hard_iron_ut (3,) uT; soft_iron (3, 3) dimensionless (identity = none); misalignment_deg (3,) roll, pitch, yaw of
    the magnetometer frame in the accelerometer (body) frame; noise_ut per axis (1 sigma); acc_noise_ms2 per axis;
    spike_probability per sample and spike_ut (magnitude of a spike, random direction); gain_tempco_per_k relative gain
    change per kelvin from 25 C; temperature_c at t = 0 and temperature_ramp_k_per_s its drift; gyro_bias_rads (3,)
    rad/s, constant, added to every gyroscope sample; gyro_noise_rads per axis per sample (1 sigma), rad/s;
    mag_lag_s the magnetometer's delay behind the gyroscope and accelerometer (its output filter and sampling): each
    magnetometer sample reads the field of the attitude that many seconds earlier; hard_iron_tempco_ut_per_k (3,)
    uT/K the hard iron's change per kelvin from 25 C (a phone's board and battery warming: several uT over minutes;
    ``simulate`` and ``SensorStream``, not ``SimulatedDevices``); gyro_bias_tempco_rads_per_k (3,) rad/s per K, the
    gyroscope's bias's change per kelvin from 25 C (a MEMS gyroscope's 0.01-0.05 deg/s/K; same runs).
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
    gyro_bias_rads: Any = (0.0, 0.0, 0.0)
    gyro_noise_rads: float = 0.0
    mag_lag_s: float = 0.0
    hard_iron_tempco_ut_per_k: Any = (0.0, 0.0, 0.0)
    gyro_bias_tempco_rads_per_k: Any = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "hard_iron_ut", _vector(self.hard_iron_ut, "hard_iron_ut", (3,)))
        set_(self, "soft_iron", _vector(self.soft_iron, "soft_iron", (3, 3)))
        set_(self, "misalignment_deg", _vector(self.misalignment_deg, "misalignment_deg", (3,)))
        set_(self, "gyro_bias_rads", _vector(self.gyro_bias_rads, "gyro_bias_rads", (3,)))
        tempco = _vector(self.hard_iron_tempco_ut_per_k, "hard_iron_tempco_ut_per_k", (3,))
        set_(self, "hard_iron_tempco_ut_per_k", tempco)
        tempco = _vector(self.gyro_bias_tempco_rads_per_k, "gyro_bias_tempco_rads_per_k", (3,))
        set_(self, "gyro_bias_tempco_rads_per_k", tempco)
        if abs(np.linalg.det(self.soft_iron)) < 1e-9:
            raise ValueError("soft_iron must be an invertible 3x3 matrix")
        for name in ("noise_ut", "acc_noise_ms2", "spike_ut", "gyro_noise_rads", "mag_lag_s"):
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

    def hard_iron(self, t_s: np.ndarray) -> np.ndarray:
        """The hard iron (N, 3) uT at times t_s (N,) s from the start: ``hard_iron_ut`` plus its temperature's
        change (``hard_iron_tempco_ut_per_k``)."""
        temperature = self.temperature_c + self.temperature_ramp_k_per_s * np.asarray(t_s, dtype=float)
        return self.hard_iron_ut + np.outer(temperature - REFERENCE_TEMPERATURE_C, self.hard_iron_tempco_ut_per_k)

    def gyro_bias(self, t_s: np.ndarray) -> np.ndarray:
        """The gyroscope's bias (N, 3) rad/s at times t_s (N,) s: ``gyro_bias_rads`` plus its temperature's change
        (``gyro_bias_tempco_rads_per_k``)."""
        temperature = self.temperature_c + self.temperature_ramp_k_per_s * np.asarray(t_s, dtype=float)
        return self.gyro_bias_rads + np.outer(temperature - REFERENCE_TEMPERATURE_C, self.gyro_bias_tempco_rads_per_k)

    def true_calibration(self, field_strength_ut: float = 0.0) -> Calibration:
        """The exact correction at 25 C: B_body = M S^-1 (mag - h), as a calibration record."""
        return Calibration(
            method="truth",
            offset=self.hard_iron_ut,
            matrix=self.misalignment_matrix @ np.linalg.inv(self.soft_iron),
            field_strength=field_strength_ut,
            reason="the simulator's true errors",
        )

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        field_ut: float,
        *,
        hard_iron_max_ratio: float = 3.0,
        soft_iron_max: float = 0.2,
        misalignment_deg: float = 0.0,
        **other: Any,
    ) -> SensorErrors:
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

    @classmethod
    def phone(cls, rng: np.random.Generator, field_ut: float, **other: Any) -> SensorErrors:
        """A phone's raw magnetometer and IMU: hard iron of 6 to 15 times the field (its speaker, its battery, its
        case) in a random direction; factory soft iron of a few percent (gains 1 +- 0.04, cross terms up to 0.015,
        symmetric); misalignment up to 1 deg; 0.5 uT noise; accelerometer noise 0.05 m/s^2; gyroscope bias up to
        0.5 deg/s per axis and noise 0.003 rad/s. ``other`` overrides any field."""
        fields: dict[str, Any] = {
            **_iron(rng, (6.0, 15.0), field_ut, 0.04, 0.015, 1.0),
            "noise_ut": 0.5,
            "acc_noise_ms2": 0.05,
            "gyro_bias_rads": rng.uniform(-1.0, 1.0, 3) * np.radians(0.5),
            "gyro_noise_rads": 0.003,
        }
        return cls(**{**fields, **other})

    @classmethod
    def calibrated(cls, rng: np.random.Generator, field_ut: float, **other: Any) -> SensorErrors:
        """A magnetometer its maker already calibrated (an IMU box, BROAD's kind): what the maker's calibration
        leaves, hard iron under 1 uT (uniform 0-1 uT, random direction) and soft iron within 1 % (gains 1 +- 0.01,
        symmetric cross terms up to 0.005), misalignment up to 0.5 deg; 0.3 uT noise; accelerometer noise
        0.03 m/s^2; gyroscope bias up to 0.3 deg/s per axis and noise 0.002 rad/s; the magnetometer 8-16 ms behind
        the gyroscope (BROAD's is 10-16 ms: docs/broad-motion.md). ``field_ut`` is unused (the residuals do not
        scale with the field); ``other`` overrides any field."""
        fields: dict[str, Any] = {
            **_iron(rng, (0.0, 1.0), 1.0, 0.01, 0.005, 0.5),
            "noise_ut": 0.3,
            "acc_noise_ms2": 0.03,
            "gyro_bias_rads": rng.uniform(-1.0, 1.0, 3) * np.radians(0.3),
            "gyro_noise_rads": 0.002,
            "mag_lag_s": rng.uniform(0.008, 0.016),
        }
        return cls(**{**fields, **other})


def _iron(
    rng: np.random.Generator,
    hard_range: tuple[float, float],
    scale_ut: float,
    gain_spread: float,
    cross_max: float,
    tilt_max_deg: float,
) -> dict[str, Any]:
    """A sensor's iron and mounting drawn from ``rng`` (in this order, which seeds' runs depend on): hard iron of
    ``scale_ut`` times a magnitude uniform in ``hard_range``, in a random direction; symmetric soft iron with gains
    1 +- ``gain_spread`` and cross terms up to ``cross_max``; a misalignment up to ``tilt_max_deg`` about a random
    axis, as roll, pitch, yaw (deg)."""
    direction = rng.standard_normal(3)
    hard = direction / np.linalg.norm(direction) * rng.uniform(*hard_range) * scale_ut
    cross = rng.uniform(-cross_max, cross_max, 3)
    soft = np.diag(rng.uniform(1.0 - gain_spread, 1.0 + gain_spread, 3))
    soft[0, 1] = soft[1, 0] = cross[0]
    soft[0, 2] = soft[2, 0] = cross[1]
    soft[1, 2] = soft[2, 1] = cross[2]
    tilt = axis_angle_matrix(rng.standard_normal(3), rng.uniform(0.0, tilt_max_deg))
    yaw, pitch, roll = matrix_to_euler(tilt)
    misalignment_deg = (float(roll), float(pitch), float((yaw + 180.0) % 360.0 - 180.0))
    return {"hard_iron_ut": hard, "soft_iron": soft, "misalignment_deg": misalignment_deg}

"""Fitting the motors' field (``magnet.motor``) from samples that carry the battery current or the throttle.

Two ways, chosen by the data (docs/mavlink.md, "Motor interference"):

- still (ArduPilot's compassmot: the vehicle held down while the throttle is raised): the calibrated field, axis by
  axis, is a straight line in the current, c_k = base_k + m_k I; least squares per axis. Used when those lines fit
  to within ``STILL_RMS_UT``.
- moving (a flight: the attitude changes, so the Earth's field in the body frame does too): only the magnitude of
  the Earth's field is constant, |c - m I| = F. Squared, |c|^2 = F^2 + 2 I (c . m) - I^2 |m|^2 is linear in
  (F^2, m, |m|^2): least squares for a start, then Gauss-Newton on |c - m I| - F. Needs the field's direction in
  the body to change while the current does (turns, banks).

``fit_with_motor`` alternates a calibration fit (raw samples with the motors' field taken out) and a motor fit (on
the calibrated field), since a motor field left in the samples would bias the hard iron.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from magnet.calibration.base import FitError
from magnet.model import Calibration
from magnet.motor import CURRENT, MotorModel, interference_pct

#: the per-axis lines of a still run fit the calibrated field within this RMS (uT); beyond, the attitude moved
STILL_RMS_UT = 2.0
#: the driver must change at least this much for a fit: amps, or throttle (0..1)
MIN_SPAN = {CURRENT: 3.0, "throttle": 0.2}
MIN_MOTOR_SAMPLES = 50
GAUSS_NEWTON_STEPS = 10
ALTERNATIONS = 2


@dataclasses.dataclass(frozen=True)
class MotorFit:
    """model; interference_pct as compassmot reports it; residual_rms_ut of the fitted model; way: still or
    moving; samples used; offset_ut (3,) uT a constant offset found in the calibrated field (moving, with offset)."""

    model: MotorModel
    interference_pct: float
    residual_rms_ut: float
    way: str
    samples: int
    offset_ut: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))


def _usable(field_ut: np.ndarray, driver: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    field_ut, driver = np.asarray(field_ut, dtype=float), np.asarray(driver, dtype=float)
    if field_ut.ndim != 2 or field_ut.shape[1] != 3 or driver.shape != field_ut.shape[:1]:
        raise FitError(f"a motor fit needs field (N, 3) and {kind} (N,), got {field_ut.shape} and {driver.shape}")
    keep = np.isfinite(field_ut).all(axis=1) & np.isfinite(driver)
    field_ut, driver = field_ut[keep], driver[keep]
    if driver.size < MIN_MOTOR_SAMPLES:
        raise FitError(f"a motor fit needs at least {MIN_MOTOR_SAMPLES} samples with a known {kind}, got {driver.size}")
    span = float(driver.max() - driver.min())
    if span < MIN_SPAN[kind]:
        raise FitError(
            f"the {kind} changed by only {span:.3g} (at least {MIN_SPAN[kind]:g} is needed): raise the throttle from "
            "idle to full during the recording"
        )
    return field_ut, driver


def _still(field_ut: np.ndarray, driver: np.ndarray) -> tuple[np.ndarray, float]:
    design = np.column_stack([np.ones_like(driver), driver])
    coef, *_ = np.linalg.lstsq(design, field_ut, rcond=None)
    residual = field_ut - design @ coef
    return coef[1], float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def _moving(
    field_ut: np.ndarray, driver: np.ndarray, earth_ut: float | None, offset: bool
) -> tuple[np.ndarray, np.ndarray, float]:
    """(m (3,), delta (3,), RMS uT) with |c - delta - m I| = F; delta (a hard iron left in the calibrated field) is
    fitted only when ``offset``, else 0."""
    ones, current = np.ones_like(driver), driver[:, None]
    columns = [ones, 2.0 * current * field_ut, -(driver**2)]
    if offset:
        columns += [2.0 * field_ut, -2.0 * driver]
    design = np.column_stack(columns)
    if np.linalg.cond(design) > 1e8:
        raise FitError(
            "the field's direction hardly changed while the current did: fly turns and banks at varying throttle, "
            "or hold the vehicle still for a compassmot-style run"
        )
    x, *_ = np.linalg.lstsq(design, np.sum(field_ut**2, axis=1), rcond=None)
    m, delta = x[1:4], (x[5:8] if offset else np.zeros(3))
    strength = float(np.sqrt(max(x[0] + delta @ delta, 1e-9))) if earth_ut is None else earth_ut
    for _ in range(GAUSS_NEWTON_STEPS):  # residual |c - delta - m I| - F over (m[, delta][, F])
        diff = field_ut - delta - current * m
        norm = np.linalg.norm(diff, axis=1)
        unit = diff / norm[:, None]
        blocks = [-current * unit] + ([-unit] if offset else []) + ([-ones[:, None]] if earth_ut is None else [])
        step, *_ = np.linalg.lstsq(np.hstack(blocks), -(norm - strength), rcond=None)
        m = m + step[:3]
        delta = delta + (step[3:6] if offset else 0.0)
        strength = strength + (step[-1] if earth_ut is None else 0.0)
    norm = np.linalg.norm(field_ut - delta - current * m, axis=1)
    return m, delta, float(np.sqrt(np.mean((norm - strength) ** 2)))


def fit_motor(
    field_ut: np.ndarray, driver: np.ndarray, kind: str, earth_ut: float | None = None, offset: bool = False
) -> MotorFit:
    """The motors' field from the calibrated field_ut (N, 3) uT and the current (A) or throttle (0..1) driver (N,)
    of each sample (``kind``: ``current`` or ``throttle``); earth_ut the Earth's field strength (uT) when known;
    ``offset``: also fit a constant offset left in the calibrated field (``MotorFit.offset_ut``, moving data only).
    FitError when the data cannot show it."""
    field_ut, driver = _usable(field_ut, driver, kind)
    coefficients, rms = _still(field_ut, driver)
    way, delta = "still", np.zeros(3)
    if rms > STILL_RMS_UT:
        coefficients, delta, rms = _moving(field_ut, driver, earth_ut, offset)
        way = "moving"
    model = MotorModel(kind, coefficients)
    strength = earth_ut or float(np.median(np.linalg.norm(field_ut - driver[:, None] * coefficients, axis=1)))
    top = float(driver.max())
    pct = interference_pct(model, strength, top, 1.0) if kind == CURRENT else interference_pct(model, strength)
    return MotorFit(model, pct, rms, way, int(driver.size), delta)


def fit_with_motor(
    mag: np.ndarray,
    driver: np.ndarray,
    kind: str,
    fit_calibration: Callable[[np.ndarray], Calibration],
    earth_ut: float | None = None,
) -> tuple[Calibration, MotorFit]:
    """A calibration of raw mag (N, 3) and the motors' field together: the calibration is fitted to the raw samples
    with the motors' field of the previous round taken out (mapped back through the inverse correction), then the
    motors' field and the offset the calibration absorbed are fitted to the calibrated samples (``ALTERNATIONS``
    rounds). Returns the calibration (offset corrected) with its motor model, and the motor fit."""
    mag, driver = np.asarray(mag, dtype=float), np.asarray(driver, dtype=float)
    known = np.where(np.isfinite(driver), driver, 0.0)
    cleaned = mag
    for _ in range(ALTERNATIONS):
        calibration = fit_calibration(cleaned)
        motor = fit_motor(calibration.apply(mag), driver, kind, earth_ut, offset=True)
        raw_per_unit = np.linalg.solve(calibration.matrix, motor.model.coefficients)
        cleaned = mag - known[:, None] * raw_per_unit
    offset = calibration.offset + np.linalg.solve(calibration.matrix, motor.offset_ut)
    return calibration.replace(offset=offset, motor=motor.model), motor

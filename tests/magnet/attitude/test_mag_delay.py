"""The magnetometer's delay behind the gyroscope (``magnet.attitude.mag_delay``): found by the gyro-ellipsoid fit,
carried by its record, and applied by the compass's step and by ``magnet heading --offline`` (the field turned forward
by the gyroscope's rotation over the delay before the filter uses it)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magnet import wire
from magnet.attitude import fusion, heading
from magnet.attitude.mag_delay import advance_field, record_lag_s
from magnet.calibration import FitInput, fit
from magnet.earth.expected import Earth
from magnet.frames import rotation_vector_to_matrix
from magnet.model import IDENTITY, Calibration
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate
from services.commands.heading import causal_headings

RATE_HZ = 100.0
LATE = 3  # samples: the magnetometer's readings come 30 ms after the gyroscope's


def test_a_late_reading_turned_forward_is_the_field_now() -> None:
    rate = np.array([0.3, -1.2, 2.0])  # rad/s, constant: the body field turns at -rate
    t = np.arange(50) * 0.01
    field_now = np.einsum("nij,j->ni", rotation_vector_to_matrix(-rate * t[:, None]), [20.0, -5.0, 40.0])
    late = np.einsum("nij,j->ni", rotation_vector_to_matrix(-rate * (t[:, None] - 0.03)), [20.0, -5.0, 40.0])
    gyr = np.tile(rate, (50, 1))
    np.testing.assert_allclose(advance_field(late, gyr, 0.03), field_now, atol=1e-9)
    gyr[7] = np.nan
    out = advance_field(late, gyr, 0.03)
    np.testing.assert_array_equal(out[7], late[7])  # no rate: left as it is
    np.testing.assert_array_equal(advance_field(late, gyr, 0.0), late)


@pytest.mark.parametrize(
    ("value", "lag"), [(None, 0.0), (0.02, 0.02), (-0.01, -0.01), (float("nan"), 0.0), (True, 0.0), (0.5, 0.0)]
)
def test_a_record_carries_its_delay_or_none(value: object, lag: float) -> None:
    quality = IDENTITY.quality if value is None else IDENTITY.quality.with_extra(mag_lag_s=value)
    assert record_lag_s(IDENTITY.replace(quality=quality)) == lag
    assert record_lag_s(None) == 0.0


@pytest.fixture(scope="module")
def late_run():
    """60 s of a fast tumble at 100 Hz whose magnetometer reads 30 ms late (hard and soft iron, gyroscope noise)."""
    rng = np.random.default_rng(11)
    errors = SensorErrors.random(
        rng, 50.0, hard_iron_max_ratio=0.5, soft_iron_max=0.05, noise_ut=0.2, gyro_noise_rads=0.002
    )
    run = simulate(
        SimulatorConfig(trajectory=Trajectory.FAST_TUMBLE, rate_hz=RATE_HZ, count=6000, errors=errors, seed=5)
    )
    late = np.vstack([np.repeat(run.mag_ut[:1], LATE, axis=0), run.mag_ut[:-LATE]])
    return run, late


def _rms(run, heading_deg: np.ndarray) -> float:
    keep = (run.t_s >= 10.0) & (np.abs(run.pitch_deg) < 60.0)
    return float(np.sqrt(np.mean(heading.angle_difference_deg(heading_deg, run.magnetic_heading_deg)[keep] ** 2)))


def _step(run, mag: np.ndarray, calibration: Calibration) -> np.ndarray:
    """The compass's step (as ``magnet heading`` runs it) on the run as one batch, with ``calibration`` in force."""
    count = len(mag)
    raw = wire.RawColumns(
        ["file"], [0], np.array([count]), 1_000_000_000 + np.arange(count, dtype=np.int64) * 10_000_000,
        mag, run.acc_ms2, run.gyr_rads, ["file"], None, np.full((count, 3), np.nan),
    )  # fmt: skip
    return causal_headings(raw, calibration, Earth(), 1, 2_000_000_000_000_000_000).headings.heading_deg


def test_the_fit_finds_the_delay_and_the_compass_applies_it(late_run) -> None:
    run, late = late_run
    record = fit(FitInput(late, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=1 / RATE_HZ), "gyro-ellipsoid")
    assert record.accepted, record.reason
    assert record_lag_s(record) == pytest.approx(LATE / RATE_HZ)
    assert record_lag_s(Calibration.from_dict(record.to_dict())) == record_lag_s(record)  # kept in the record
    without = record.replace(quality=dataclasses.replace(record.quality, extra={}))
    applied, ignored = _rms(run, _step(run, late, record)), _rms(run, _step(run, late, without))
    assert applied < 0.6 * ignored, (applied, ignored)
    field = record.apply(late)
    offline = fusion.fuse_offline(run.gyr_rads, run.acc_ms2, advance_field(field, run.gyr_rads, 0.03), 1 / RATE_HZ)
    plain = fusion.fuse_offline(run.gyr_rads, run.acc_ms2, field, 1 / RATE_HZ)
    assert _rms(run, offline.heading_deg) < 0.6 * _rms(run, plain.heading_deg)


def test_the_fit_keeps_the_lag_that_fits_best_even_past_a_bump(monkeypatch: pytest.MonkeyPatch) -> None:
    """A slow recording's misfit need not fall steadily from no lag to the true one: every lag is tried."""
    from magnet.calibration import gyro_ellipsoid

    misfit = {0: 0.5, 1: 0.6, -1: 0.7, 2: 0.1, -2: 0.8, 3: 0.3, -3: 0.9}
    monkeypatch.setattr(gyro_ellipsoid, "_fit_at", lambda *args: (np.eye(3), np.zeros(3), misfit[args[-1]]))
    lag, (_, _, ratio) = gyro_ellipsoid._best_lag(np.zeros((9, 3)), np.zeros((9, 3, 3)), (None, None), None, 3)
    assert (lag, ratio) == (2, 0.1)


@pytest.mark.parametrize(("lag_s", "rate_hz"), [(0.012, 50.0), (0.0, 50.0), (0.015, 100.0)])
def test_the_fit_finds_a_delay_between_samples(lag_s: float, rate_hz: float) -> None:
    """A magnetometer late by part of a sample (the simulator's ``mag_lag_s``: the field of the attitude that much
    earlier): the fit's delay is refined between samples, to within 2.5 ms, and a sensor without any delay keeps
    (about) none: the gyroscope is interpolated between samples, not the noisy field."""
    errors = SensorErrors.calibrated(np.random.default_rng(4), 50.0, mag_lag_s=lag_s)
    run = simulate(
        SimulatorConfig(trajectory=Trajectory.WAND, rate_hz=rate_hz, count=int(60 * rate_hz), errors=errors, seed=8)
    )
    record = fit(FitInput(run.mag_ut, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=1 / rate_hz), "gyro-ellipsoid")
    assert record_lag_s(record) == pytest.approx(lag_s, abs=0.0025)

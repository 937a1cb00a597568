"""The accuracy benchmark's scoring: exact with the true inverse, and it sees the errors it should."""

import functools

import numpy as np
import pytest

from magnet.earth.geomag import earth_field
from magnet.frames import euler_to_matrix
from magnet.simulator import SensorErrors
from services.bench import accuracy as bench

FAST = bench.AccuracySettings(
    trials=2, fit_samples=600, spin_samples=180, timing_samples=600, timing_repeats=1, fleet_seconds=0.01
)
EARTH = earth_field(FAST.lat_deg, FAST.lon_deg, 0.0, FAST.date)


def sensor(misalignment_deg=0.0):
    return SensorErrors.random(np.random.default_rng(9), EARTH.total_ut, misalignment_deg=misalignment_deg)


def test_scoring_attitudes_cover_level_and_tilt_every_5_degrees():
    att = bench.scoring_attitudes(5.0, 30.0)
    assert att["level"].sum() == 72 and (~att["level"]).sum() == 4 * 72
    assert set(np.abs(att["pitch_deg"][~att["level"]]) + np.abs(att["roll_deg"][~att["level"]])) == {30.0}


@pytest.mark.parametrize("misalignment", [0.0, 5.0])
def test_true_inverse_scores_zero(misalignment):
    errors = sensor(misalignment)
    err = bench.heading_errors_deg(errors.true_calibration(), errors, EARTH, bench.scoring_attitudes())
    assert np.abs(err).max() < 1e-9


def test_scoring_sees_a_rotation_and_an_uncorrected_sensor():
    errors = SensorErrors()
    turned = errors.true_calibration().replace(matrix=euler_to_matrix(3.0, 0.0, 0.0))  # corrected field turned 3 deg
    err = bench.heading_errors_deg(turned, errors, EARTH, bench.scoring_attitudes())
    att = bench.scoring_attitudes()
    np.testing.assert_allclose(np.abs(err[att["level"]]), 3.0, atol=1e-9)
    from magnet.model import IDENTITY

    raw = bench.heading_errors_deg(IDENTITY, sensor(), EARTH, att)
    assert np.sqrt(np.mean(raw**2)) > 10


def test_rows_with_the_stand_in_are_exact_and_complete():
    rows = bench.accuracy_rows(bench.truth_fitter, FAST)
    assert [(r.method, r.misalignment_deg) for r in rows] == [(m, a) for a in (0.0, 5.0) for m in bench.METHODS]
    for row in rows:
        assert row.all_rms_deg < 1e-9 and row.worst_rms_deg < 1e-9 and row.failed == 0


def test_failures_are_counted_not_fatal():
    def failing(run, method, field_ut, truth):
        raise ValueError("not an ellipsoid")

    rows = bench.accuracy_rows(failing, FAST, methods=["ellipsoid"])
    assert all(r.failed == FAST.trials and np.isnan(r.all_rms_deg) for r in rows)


def test_real_ellipsoid_fits_meet_the_target_on_a_small_run():
    rows = {
        (r.method, r.misalignment_deg): r
        for r in bench.accuracy_rows(
            bench.real_fitter, FAST, methods=["ellipsoid", "ellipsoid+align", "gyro-ellipsoid"]
        )
    }
    assert rows[("ellipsoid", 0.0)].all_rms_deg < 0.2
    assert rows[("ellipsoid+align", 5.0)].all_rms_deg < 0.2
    assert rows[("gyro-ellipsoid", 5.0)].all_rms_deg < 0.2 and rows[("gyro-ellipsoid", 5.0)].failed == 0
    assert rows[("ellipsoid", 5.0)].all_rms_deg > 2.0  # plain ellipsoid cannot see the misalignment


def test_benchmark_prints_a_table(capsys, monkeypatch):
    # the fleet's rate on 50 devices, not 1000: building a simulated device takes over a millisecond
    monkeypatch.setattr(bench, "fleet_samples_per_s", functools.partial(bench.fleet_samples_per_s, devices=50))
    bench.run_accuracy_benchmark(bench.truth_fitter, FAST)
    out = capsys.readouterr().out
    for method in bench.METHODS:
        assert method in out
    assert "met" in out and "MISSED" not in out and "fit ms" in out and "SimulatedDevices" in out

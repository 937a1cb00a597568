"""Advice that fits the cause: a fit whose radius is off the expected field by a unit's factor names the --unit to
try (counts at a chip's gain, gauss, milligauss, nT); a plausible radius or an unexplained one gets no such advice."""

import numpy as np
import pytest

from magnet.calibration import FitInput, fit
from magnet.quality.units_hint import chip_count_scales, unit_hint
from magnet.simulator import SimulatedDevices
from magnet.units import ut_per_unit
from services.cli import main


@pytest.fixture(scope="module")
def tumble():
    """A tumbling device's field (uT) and specific force (m/s^2), 2,000 samples."""
    batch = SimulatedDevices(1, rate_hz=5, seed=2, noise_ut=0.3).step(2000)
    return batch.mag_ut[0], batch.acc_ms2[0]


def test_counts_fitted_as_ut_say_to_give_unit_counts_and_name_the_chip(tumble, tmp_path, capsys):
    mag, acc = tumble
    counts = mag * 1090 / 100  # an HMC5883L at gain 1: 1090 LSB per gauss
    cal = fit(FitInput(counts, acc=acc), "ellipsoid")
    assert not cal.accepted
    assert cal.reason.startswith("the fitted radius") and "try --unit mgauss or --unit counts" in cal.reason
    assert "hmc5883l gain 1" in cal.reason
    csv = tmp_path / "counts.csv"
    np.savetxt(csv, counts, delimiter=",", header="mx,my,mz", comments="", fmt="%.2f")
    assert main(["fit", str(csv), "--method", "ellipsoid", "--location", "50.45,30.52", "--date", "2026-01-01"]) == 1
    err = capsys.readouterr().err
    assert "x the expected" in err and "--unit counts (raw counts of a hmc5883l gain 0, hmc5883l gain 1" in err
    assert "keep magnets and metal away" not in err.split(";")[0]


@pytest.mark.parametrize(
    "unit_of_data, factor, advice",
    [("gauss", 0.01, "--unit gauss"), ("mgauss", 10.0, "--unit mgauss"), ("nt", 1000.0, "--unit nt")],
)
def test_gauss_milligauss_and_nanotesla_fitted_as_ut_name_their_unit(tumble, unit_of_data, factor, advice):
    mag, acc = tumble
    cal = fit(FitInput(mag * factor, acc=acc, field_ut=50.5), "ellipsoid")
    assert not cal.accepted and advice in cal.reason.split(";")[0], cal.reason
    right = fit(FitInput(mag * factor, acc=acc, unit=unit_of_data, field_ut=50.5), "ellipsoid")
    assert right.accepted and "the fitted radius" not in right.reason, right.reason
    assert ut_per_unit(unit_of_data) == pytest.approx(1 / factor)


def test_no_unit_advice_for_a_plausible_or_unexplained_radius():
    assert unit_hint(50.0, 1.0, 50.5) is None and unit_hint(45.0, 1.0, None) is None
    assert unit_hint(5050.0, 1.0, 50.5) is None  # 100x: no unit or chip gives that
    assert unit_hint(500.0, None, 50.5) is None  # counts declared: no scale to judge
    assert unit_hint(50.0, 100.0, 50.5) == (
        "the fitted radius 5000 uT is 99 x the expected 50.5 uT: the data are probably not in the unit given: "
        "try --unit ut"
    )
    scales = dict(chip_count_scales())
    assert scales["hmc5883l gain 1"] == pytest.approx(100 / 1090) and scales["ak09918c/icm20948"] == 0.15


@pytest.mark.parametrize("factor", [0.01, 1e4])  # gauss read as uT (0.5 "uT"); no unit or chip explains 500,000 uT
def test_a_radius_no_earth_field_has_is_refused_without_a_location_too(tumble, factor):
    mag, acc = tumble
    cal = fit(FitInput(mag * factor, acc=acc), "ellipsoid")  # no expected field: the Earth's range judges
    assert not cal.accepted
    assert ("try --unit gauss" in cal.reason) if factor == 0.01 else ("no Earth field (22-67 uT" in cal.reason)
    assert fit(FitInput(mag, acc=acc), "ellipsoid").accepted  # the same motion in uT is accepted

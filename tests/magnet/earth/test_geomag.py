"""WMM2025 through pygeomag: published test values, units, dates, locations and refusals."""

import datetime

import numpy as np
import pytest

from magnet.earth.geomag import decimal_year, earth_field
from magnet.earth.location import Location

# NOAA/BGS WMM2025 test values (WMM2025_TestValues.txt): (decimal year, height km, lat, lon, declination deg)
OFFICIAL = [
    (2025.0, 0.0, 80.0, 0.0, 1.28),
    (2025.0, 0.0, 0.0, 120.0, -0.16),
    (2025.0, 0.0, -80.0, 240.0, 68.78),
    (2027.5, 100.0, 80.0, 0.0, 2.16),
    (2025.5, 6.0, -36.0, -137.0, 20.28),
    (2025.0, 28.0, 89.0, -121.0, -99.77),
]


@pytest.mark.parametrize("year, height_km, lat, lon, declination", OFFICIAL)
def test_declination_matches_the_official_test_values(year, height_km, lat, lon, declination):
    assert earth_field(lat, lon, height_km * 1000.0, year).declination_deg == pytest.approx(declination, abs=0.006)


def test_london_matches_noaa_calculator_and_boulder_is_about_8_east():
    # NOAA online calculator, WMM2025, London 2026-07-04: 1.16280 deg E
    assert earth_field(51.5074, -0.1278, 0.0, datetime.date(2026, 7, 4)).declination_deg == pytest.approx(
        1.1628, abs=0.005
    )
    boulder = earth_field(40.015, -105.2705, 1655.0, 2025.0)
    assert 7.5 < boulder.declination_deg < 8.1  # east; the model itself gives 7.81
    assert boulder.inclination_deg == pytest.approx(66.1, abs=0.2)


def test_components_in_microtesla_agree_with_pygeomag_directly():
    from pygeomag import GeoMag

    raw = GeoMag(coefficients_file="wmm/WMM_2025.COF").calculate(50.45, 30.52, 0.18, 2026.25)
    field = earth_field(50.45, 30.52, 180.0, 2026.25)
    np.testing.assert_allclose(
        [field.north_ut, field.east_ut, field.down_ut], np.array([raw.x, raw.y, raw.z]) / 1000.0, rtol=1e-12
    )
    assert field.total_ut == pytest.approx(raw.f / 1000.0)
    assert field.horizontal_ut == pytest.approx(np.hypot(field.north_ut, field.east_ut))
    assert field.declination_deg == pytest.approx(np.degrees(np.arctan2(field.east_ut, field.north_ut)))
    assert field.inclination_deg == pytest.approx(np.degrees(np.arctan2(field.down_ut, field.horizontal_ut)))
    assert 45.0 < field.total_ut < 56.0 and field.down_ut > 0  # Kyiv: strong, pointing down


def test_southern_hemisphere_field_points_up():
    assert earth_field(-33.87, 151.21, 0.0, 2026.0).inclination_deg < -50.0


def test_dates_in_every_form_agree():
    as_date = earth_field(10.0, 20.0, 0.0, datetime.date(2027, 7, 2))
    as_text = earth_field(10.0, 20.0, 0.0, "2027-07-02")
    as_year = earth_field(10.0, 20.0, 0.0, decimal_year(datetime.date(2027, 7, 2)))
    assert as_date == as_text == as_year
    assert decimal_year("2028-01-01") == 2028.0
    assert decimal_year(datetime.datetime(2026, 7, 2, 12, 0)) == pytest.approx(2026.5, abs=0.002)
    assert 2025.0 <= decimal_year(None) < 2100.0


@pytest.mark.parametrize("date", ["2024-12-31", 2030.5, "2031-01-01"])
def test_dates_outside_the_model_life_span_are_refused(date):
    with pytest.raises(ValueError, match="life span"):
        earth_field(0.0, 0.0, 0.0, date)


@pytest.mark.parametrize("date", ["yesterday", "2026-13-01", object(), float("nan")])
def test_bad_dates_are_refused(date):
    with pytest.raises(ValueError):
        earth_field(0.0, 0.0, 0.0, date)


@pytest.mark.parametrize(
    "lat, lon, alt", [(91.0, 0.0, 0.0), (0.0, 400.0, 0.0), (float("nan"), 0.0, 0.0), (0.0, 0.0, 1e7)]
)
def test_bad_places_are_refused(lat, lon, alt):
    with pytest.raises(ValueError):
        earth_field(lat, lon, alt, 2026.0)


def test_near_the_magnetic_pole_the_compass_is_flagged():
    assert earth_field(85.0, 140.0, 0.0, 2026.0).blackout  # north magnetic pole region: horizontal field tiny
    assert not earth_field(50.0, 30.0, 0.0, 2026.0).caution


def test_a_location_is_parsed_in_one_place():
    assert Location.parse("50.45, 30.52").as_tuple() == (50.45, 30.52, 0.0)
    assert Location.parse("-33.9,151.2,120").as_tuple() == (-33.9, 151.2, 120.0)
    for bad in ["50.45", "a,b", "1,2,3,4", "95,0", "", "50,"]:
        with pytest.raises(ValueError, match=r"LAT|latitude|location"):
            Location.parse(bad)


def test_kyiv_field_is_close_to_the_one_seed_000_used():
    # seed 000 (Kyiv, 2017): Bh = 18964 nT, Bv = -46962 nT (up component); the field drifts only slowly
    field = earth_field(50.45, 30.52, 180.0, 2026.0)
    assert field.horizontal_ut == pytest.approx(18.964, rel=0.05)
    assert -field.down_ut == pytest.approx(-46.962, rel=0.03)

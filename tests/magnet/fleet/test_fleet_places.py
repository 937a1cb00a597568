"""Per-device places: the optional raw ``location`` field (checked), the fleet file, and each device's own
declination and expected field in the compass (checked against the World Magnetic Model)."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
from compass_steps import compass_core, heading_batches

from magnet import wire
from magnet.attitude import heading as hd
from magnet.earth.expected import Earth, earth_at, utc_date
from magnet.earth.geomag import earth_field
from magnet.earth.location import Location
from magnet.fleet.places import Places, parse_places
from magnet.simulator import SimulatedDevices

KYIV, SYDNEY = Location(50.45, 30.52, 180.0), Location(-33.86, 151.21, 20.0)
DATE = "2026-06-01"


@pytest.mark.parametrize(
    "bad",
    [
        [91, 0],
        [0, 181],
        [0, -180.5],
        [0, 0, 1e7],
        [float("nan"), 0],
        [True, 0],
        [1],
        [1, 2, 3, 4],
        "north",
        "50,east",
        {"lat_deg": 1},
    ],
)
def test_a_location_outside_the_earth_or_the_model_is_refused(bad):
    with pytest.raises(ValueError):
        Location.parse(bad)


def raw_batch(device: str, location: Location | None, n: int = 5) -> wire.RawBatch:
    return wire.RawBatch(
        device,
        1,
        "sim",
        np.arange(n, dtype=np.int64),
        np.tile([20.0, 0.0, 45.0], (n, 1)),
        np.tile([0.0, 0.0, -9.81], (n, 1)),
        location=location,
    )


def test_the_location_travels_in_raw_messages_and_a_bad_one_is_dropped_with_its_cause():
    good = wire.encode_raw(raw_batch("a", KYIV))
    without = wire.encode_raw(raw_batch("b", None))
    message = msgpack.unpackb(good)
    assert message["location"] == [50.45, 30.52, 180.0]
    bad = msgpack.packb({**message, "device": "c", "location": [95.0, 0.0, 0.0]})
    not_a_list = msgpack.packb({**message, "device": "d", "location": "50,30"})
    columns, errors = wire.decode_raw_many([good, without, bad, not_a_list])
    assert columns.devices == ["a", "b"] and columns.locations == [KYIV, None]
    assert [(i, e.cause) for i, e in errors] == [(2, "bad-location"), (3, "bad-location")]
    assert wire.decode_raw(good).location == KYIV and wire.decode_raw(without).location is None
    assert wire.decode_raw_many([without])[0].locations is None
    assert [b.location for b in columns.batches()] == [KYIV, None]


def test_a_places_file_is_json5_and_a_bad_entry_names_the_device():
    fleet = parse_places("""{
        // the roof
        "mast-1": {location: "50.45,30.52,180", notes: "roof mast",},
        "buoy-7": {location: [-33.86, 151.21]},
        "spare": {notes: "in a drawer"},
    }""")
    assert fleet["mast-1"].location == KYIV and fleet["mast-1"].notes == "roof mast"
    assert fleet["buoy-7"].location == Location(-33.86, 151.21) and fleet["spare"].location is None
    for text, named in [
        ('{"a/b": {location: "1,2"}}', "a/b"),
        ('{"x": {location: "99,2"}}', "'x'"),
        ('{"y": {place: "1,2"}}', "place"),
        ("[1, 2]", "map"),
        ("{oops", "JSON5"),
    ]:
        with pytest.raises(ValueError, match=named):
            parse_places(text)


def test_a_devices_own_report_wins_over_the_places_file_which_wins_over_the_default():
    places = Places(
        parse_places('{"a": {location: "-33.86,151.21,20"}, "b": {location: "-33.86,151.21,20"}}'),
        default=KYIV,
        date=DATE,
    )
    assert places.location("a") == SYDNEY and places.location("z") == KYIV
    assert places.report("b", KYIV) and not places.report("b", KYIV)
    assert places.location("b") == KYIV
    sydney = earth_field(-33.86, 151.21, 20.0, DATE)
    assert places.earth("a").declination_deg == pytest.approx(sydney.declination_deg, abs=0.01)
    assert earth_at(None, DATE) == Earth()


def test_two_devices_far_apart_get_their_own_declination_and_expected_field():
    kyiv = earth_field(KYIV.lat_deg, KYIV.lon_deg, KYIV.alt_m, DATE)
    sydney = earth_field(SYDNEY.lat_deg, SYDNEY.lon_deg, SYDNEY.alt_m, DATE)
    assert abs(kyiv.declination_deg - sydney.declination_deg) > 3  # the places really differ
    places = Places(parse_places('{"syd": {location: "-33.86,151.21,20"}}'), date=DATE)
    compass = compass_core(places=places)
    # each device measures the true field of its own place (no iron): level, turning
    batches = []
    for device, place, seed in (("kyiv", KYIV, 1), ("syd", None, 2)):
        where = KYIV if place else SYDNEY
        sim = SimulatedDevices(
            1,
            rate_hz=10,
            seed=seed,
            noise_ut=0.0,
            lat_deg=where.lat_deg,
            lon_deg=where.lon_deg,
            alt_m=where.alt_m,
            date=DATE,
            hard_iron_max_ratio=0.0,
            soft_iron_max=0.0,
        )
        step = sim.step(20)
        batches.append(wire.RawBatch(device, 1, "sim", step.t_ns, step.mag_ut[0], step.acc_ms2[0], location=place))
    out = {h.device: h for h in heading_batches(compass, batches)}
    assert out["kyiv"].declination_deg == pytest.approx(kyiv.declination_deg, abs=0.01)
    assert out["syd"].declination_deg == pytest.approx(sydney.declination_deg, abs=0.01)
    for h in out.values():
        assert np.allclose(hd.true_heading_deg(h.heading_deg, h.declination_deg), h.true_heading_deg)
        assert not h.disturbed.any()  # each judged against its own place's |B| and dip (they differ by > 15 %)
    # the same Sydney field judged against Kyiv's expectation is disturbed
    kyiv_only = compass_core(places=Places(default=KYIV, date=DATE))
    assert heading_batches(kyiv_only, [dataclasses.replace(batches[1], location=None)])[0].disturbed.all()


def test_without_a_fixed_date_the_model_is_dated_by_the_step_clock_not_frozen():
    """No --date: each step's own day (from the clock the step is given) dates the model; a day later, a later
    declination (the secular variation), with no cache holding the first day."""
    compass = compass_core(places=Places(default=KYIV))
    batch = wire.RawBatch("k", 0, "sim", np.arange(2), np.tile([20.0, 0.0, 40.0], (2, 1)), None)
    early, late = 1_767_225_600 * 10**9, 1_893_369_600 * 10**9  # 2026-01-01, 2029-12-31 (UTC)
    assert str(utc_date(early)) == "2026-01-01" and str(utc_date(late)) == "2029-12-31"
    [first] = heading_batches(compass, [batch], early)
    [second] = heading_batches(compass, [dataclasses.replace(batch, seq=1)], late)
    for h, day in ((first, "2026-01-01"), (second, "2029-12-31")):
        expected = earth_field(KYIV.lat_deg, KYIV.lon_deg, KYIV.alt_m, day).declination_deg
        assert h.declination_deg == pytest.approx(expected, abs=0.01)
    assert abs(first.declination_deg - second.declination_deg) > 0.1

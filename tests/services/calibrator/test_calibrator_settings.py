"""``magnet calibrator``'s settings come from one declaration: the options, their defaults and checks are the
dataclasses' own, the same whether built from the command line or in code, and nothing in them can change."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from magnet.earth.geomag import earth_field
from magnet.earth.location import Location
from magnet.shard import Shard
from services.calibrator.settings import (
    CalibratorSettings,
    ServiceSettings,
    add_arguments,
    default_db_path,
    make_places,
    settings_from_args,
)


def _settings(*argv: str) -> ServiceSettings:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return settings_from_args(parser.parse_args(list(argv)))


def test_without_options_the_settings_are_the_dataclass_defaults():
    settings = _settings()
    assert settings == ServiceSettings()
    fitting = settings.fitting
    assert (fitting.method, fitting.min_coverage) == ("auto", 0.8)
    assert (fitting.min_samples, fitting.max_samples) == (150, 1500)
    assert fitting.auto and fitting.max_devices == 10_000 and fitting.expected_field_ut is None
    assert (settings.name, settings.devices, settings.shard, settings.enrol_rate, settings.max_queue) == (
        "calibrator",
        "*",
        Shard(0, 1),
        200.0,
        100_000,
    )
    assert settings.db is None and settings.db_path == default_db_path() and settings.fleet == ()


def test_every_flag_is_read_into_its_field(tmp_path):
    fleet = tmp_path / "fleet.json5"
    fleet.write_text('{"buoy": {location: "-33.86,151.21,20", notes: "Sydney"}}')
    settings = _settings(
        *("--method", "sphere", "--location", "50.45,30.52,180", "--min-coverage", "0.5"),
        *("--min-samples", "60", "--max-samples", "600", "--no-auto", "--max-devices", "7"),
        *("--db", str(tmp_path / "c.db"), "--name", "cal-2", "--devices", "mast-*", "--shard", "1/3"),
        *("--enrol-rate", "5", "--max-queue", "10", "--fleet", str(fleet), "--prefix", "site"),
        *("--signing-key", str(tmp_path / "k.key")),
    )
    fitting = settings.fitting
    assert (fitting.method, fitting.location, fitting.min_coverage) == ("sphere", Location(50.45, 30.52, 180.0), 0.5)
    assert (fitting.min_samples, fitting.max_samples, fitting.auto, fitting.max_devices) == (60, 600, False, 7)
    assert fitting.expected_field_ut == earth_field(50.45, 30.52, 180.0).total_ut
    assert settings.db_path == tmp_path / "c.db" and settings.signing_key == tmp_path / "k.key"
    assert (settings.name, settings.devices, settings.shard) == ("cal-2", "mast-*", Shard(1, 3))
    assert (settings.enrol_rate, settings.max_queue, settings.zenoh.prefix) == (5.0, 10, "site")
    [entry] = settings.fleet
    assert entry.device == "buoy" and entry.notes == "Sydney"
    places = make_places(settings.fleet, fitting.location, fitting.max_devices)
    assert places.location("buoy") == entry.location and places.location("other") == fitting.location


def test_field_ut_wins_over_the_location():
    assert _settings("--location", "50,30", "--field-ut", "48").fitting.expected_field_ut == 48.0


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--method", "vibes"], "--method must be one of"),
        (["--min-coverage", "1.5"], "--min-coverage must be a fraction in [0, 1]"),
        (["--field-ut", "5000"], "--field-ut must be a field strength in uT in [1, 1000]"),
        (["--min-samples", "10"], "--min-samples must be a whole number >= 30"),
        (["--min-samples", "500", "--max-samples", "400"], "need 30 <= --min-samples <= --max-samples"),
        (["--max-devices", "0"], "--max-devices must be a whole number >= 1"),
        (["--enrol-rate", "0"], "--enrol-rate must be a positive number"),
        (["--max-queue", "0"], "--max-queue must be a whole number >= 1"),
        (["--shard", "3/3"], "--shard:"),
        (["--location", "95,0"], "--location: latitude must be within -90..90"),
    ],
)
def test_a_bad_value_is_refused_naming_its_flag(argv, words):
    with pytest.raises(ValueError) as exc:
        _settings(*argv)
    assert words in str(exc.value)


def test_the_same_checks_hold_in_code_and_the_settings_cannot_change():
    with pytest.raises(ValueError, match="--max-queue"):
        ServiceSettings(max_queue=0)
    with pytest.raises(ValueError, match="--min-coverage"):
        CalibratorSettings(min_coverage=2.0)
    settings = _settings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.name = "other"  # type: ignore[misc]
    hash(settings)  # nothing mutable inside: the fleet file's entries are a tuple


def test_help_states_each_default_once():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    text = " ".join(parser.format_help().split())
    for default in ("(default 0.8)", "(default 150)", "(default 10000)", "(default 100000)"):
        assert text.count(default) == 1, default
    assert text.count("(default auto)") == 2  # --method and --recalibrate, once each
    assert f"(default {Path(default_db_path())})" in text and "--no-auto" in text

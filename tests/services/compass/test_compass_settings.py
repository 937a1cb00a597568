"""``magnet compass``'s settings come from one declaration: every flag and default as before, each value checked
once, nothing mutable inside."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from magnet.earth.location import Location
from magnet.fleet.places import PlaceEntry
from magnet.shard import EVERY_DEVICE, Shard
from services.compass.settings import CompassSettings, add_arguments, settings_from_args


def _settings(*argv: str) -> CompassSettings:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return settings_from_args(parser.parse_args(list(argv)))


def test_defaults_are_the_documented_ones():
    settings = _settings()
    assert (settings.window, settings.name, settings.devices, settings.max_devices) == (1, "compass", "*", 10_000)
    assert settings.location is None and settings.date is None and settings.trust == ()
    assert settings.shard == EVERY_DEVICE and settings.places == () and settings.drift is not None


def test_each_option_is_parsed_once_into_its_type(tmp_path: Path):
    places = tmp_path / "places.json5"
    places.write_text('{"mast-1": {location: "50.45,30.52,180"}}')
    settings = _settings(
        "--location=-33.86,151.21", "--date", "2026-06-01", "--window", "5", "--shard", "1/4",
        "--trust", "a.pub", "--trust", "b.pub", "--fleet", str(places), "--no-drift",
    )  # fmt: skip
    assert settings.location == Location(-33.86, 151.21) and settings.window == 5
    assert settings.shard == Shard.parse("1/4") and settings.trust == (Path("a.pub"), Path("b.pub"))
    assert settings.places == (PlaceEntry("mast-1", Location(50.45, 30.52, 180.0)),) and settings.drift is None
    assert settings.core.window == 5 and settings.core.shard == settings.shard
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.window = 2  # type: ignore[misc]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--window", "0"], "--window must be a whole number >= 1"),
        (["--max-devices", "0"], "--max-devices must be a whole number >= 1"),
        (["--location", "95,0"], "--location: latitude"),
        (["--date", "2019-01-01"], "--date is not a usable date"),
        (["--shard", "4/4"], "--shard"),
    ],
)
def test_a_bad_value_names_its_flag(argv: list[str], message: str):
    with pytest.raises(ValueError, match=message):
        _settings(*argv)

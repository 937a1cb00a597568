"""Each device's place and what the World Magnetic Model expects there.

Where a device is comes from, first to last: the ``location`` its own raw messages carry (the edge's ``--location``,
or its simulator's place), the places file (``--fleet FILE.json5``), the service's own ``--location``. From the place
come the device's declination, expected |B| and dip (``Earth``, ``magnet.earth.expected``), looked up once per place
rounded to about 1 km (``Location.rounded``) and date.

Places file (JSON5: comments and trailing commas allowed; plain JSON is JSON5)::

    {
      // device id: where it is and anything worth knowing
      "mast-1": {location: "50.45,30.52,180", notes: "roof mast, Kyiv"},
      "buoy-7": {location: [-33.86, 151.21], notes: "Sydney harbour"},
    }

Pure: parses text; the services read the file.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.bounded import Recent
from magnet.earth.expected import Earth, earth_at
from magnet.earth.geomag import DateLike
from magnet.earth.location import Location
from magnet.wire.keys import validate_device_id

#: a places file larger than this is refused before it is parsed (bytes); at most this many devices
MAX_PLACES_FILE_BYTES = 16 * 1024 * 1024
MAX_PLACES_DEVICES = 100_000
MAX_NOTES_CHARS = 1_000
#: devices whose reported place is remembered at most by default (the least recently reporting forgotten beyond)
MAX_REPORTED = 100_000


@dataclasses.dataclass(frozen=True)
class PlaceEntry:
    """One device of the places file: its location (or None) and free notes."""

    device: str
    location: Location | None = None
    notes: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"location": None if self.location is None else self.location.to_wire(), "notes": self.notes}


def parse_places(text: str, source: str = "places file") -> dict[str, PlaceEntry]:
    """device -> PlaceEntry from the text of a places file; ValueError naming the device and what is wrong."""
    if len(text.encode()) > MAX_PLACES_FILE_BYTES:
        raise ValueError(f"{source} is larger than {MAX_PLACES_FILE_BYTES} bytes")
    import json5  # only where a places file is read (the compass's start, not every command that imports this)

    try:
        data = json5.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"{source} is not JSON5: {exc}") from None
    if not isinstance(data, Mapping):
        raise ValueError(f"{source} must be a map of device id -> {{location, notes}}")
    if len(data) > MAX_PLACES_DEVICES:
        raise ValueError(f"{source} lists {len(data)} devices, more than {MAX_PLACES_DEVICES}")
    return {entry.device: entry for entry in (_entry(device, value, source) for device, value in data.items())}


def _entry(device: Any, value: Any, source: str) -> PlaceEntry:
    try:
        validate_device_id(device)
        if isinstance(value, (str, list)):
            value = {"location": value}
        if not isinstance(value, Mapping):
            raise ValueError('must be {location: "LAT,LON[,ALT_M]", notes: "..."}')
        unknown = sorted(set(value) - {"location", "notes"})
        if unknown:
            raise ValueError(f"unknown key(s) {', '.join(map(str, unknown))}: use location and notes")
        notes = value.get("notes", "")
        if not isinstance(notes, str) or len(notes) > MAX_NOTES_CHARS:
            raise ValueError(f"notes must be text of at most {MAX_NOTES_CHARS} characters")
        location = None if value.get("location") is None else Location.parse(value["location"])
    except ValueError as exc:
        raise ValueError(f"{source}: device {device!r}: {exc}") from None
    return PlaceEntry(device, location, notes)


class Places:
    """Each device's place and Earth: reported (raw messages) over the places file over the service's default.

    ``fleet``: the places file's entries; ``default``: the service's ``--location``; ``date``: its ``--date`` (None:
    the day each caller passes, else today); ``default_earth``: what to expect at the default place (or with no
    place) when the caller knows it better than the model (``magnet heading --declination``)."""

    def __init__(
        self,
        fleet: Mapping[str, PlaceEntry] | None = None,
        default: Location | None = None,
        date: DateLike = None,
        default_earth: Earth | None = None,
        max_reported: int = MAX_REPORTED,
    ) -> None:
        self.fleet = dict(fleet or {})
        self.default, self.date, self.default_earth = default, date, default_earth
        #: places the devices reported, for at most ``max_reported`` devices (the least recently reporting forgotten)
        self.reported: Recent[str, Location] = Recent(max_reported)

    def report(self, device: str, location: Location | None) -> bool:
        """A device said where it is; True when that changes its place."""
        if location is None:
            return False
        if self.reported.get(device) == location:
            self.reported.touch(device)
            return False
        self.reported[device] = location
        return True

    def location(self, device: str) -> Location | None:
        reported = self.reported.get(device)
        if reported is not None:
            return reported
        entry = self.fleet.get(device)
        return entry.location if entry is not None and entry.location is not None else self.default

    def earth(self, device: str, date: DateLike = None) -> Earth:
        """What to expect at the device's place on ``--date``, else on ``date`` (the caller's today)."""
        location = self.location(device)
        when = self.date if self.date is not None else date
        if location is None or location == self.default:
            return self.default_earth if self.default_earth is not None else earth_at(self.default, when)
        return earth_at(location, when)

    def notes(self, device: str) -> str:
        entry = self.fleet.get(device)
        return entry.notes if entry is not None else ""


@dataclasses.dataclass(frozen=True, eq=False)
class EarthColumns:
    """Per-sample expectations: declination_deg, total_ut and inclination_deg (S,), NaN where unknown."""

    declination_deg: np.ndarray
    total_ut: np.ndarray
    inclination_deg: np.ndarray

    @classmethod
    def of(cls, earths: list[Earth], counts: np.ndarray) -> EarthColumns:
        """One Earth per batch, repeated over each batch's ``counts`` samples."""
        table = np.array(
            [
                [
                    e.declination_deg,
                    np.nan if e.total_ut is None else e.total_ut,
                    np.nan if e.inclination_deg is None else e.inclination_deg,
                ]
                for e in earths
            ],
            dtype=float,
        ).reshape(-1, 3)
        per_sample = np.repeat(table, counts, axis=0)
        return cls(per_sample[:, 0], per_sample[:, 1], per_sample[:, 2])

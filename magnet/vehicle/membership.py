"""Which vehicle a device belongs to: the one its raw batches name (``vehicle``, set by ``magnet edge --vehicle
NAME``), else by its name. The MAVLink edge names each compass ``<prefix><SYSID>-mag<N>``
(``magnet.autopilot.mavlink_stream``): the compasses of one system id are one vehicle, ``<prefix><SYSID>``, and N is
the autopilot's compass instance (0 the first: ArduPilot's ``COMPASS_ORIENT``, PX4's ``CAL_MAG0_ROT``)."""

from __future__ import annotations

import re

_DEVICE = re.compile(r"^(?P<vehicle>.+)-mag(?P<instance>\d{1,2})$")


def vehicle_of(device: str, declared: str = "") -> str | None:
    """The vehicle a batch names (``declared``: ``magnet edge --vehicle``), else that of a device named
    ``<vehicle>-mag<N>``, else None (a device on its own)."""
    if declared:
        return declared
    match = _DEVICE.match(device)
    return match.group("vehicle") if match else None


def instance_of(device: str) -> int | None:
    """N of a device named ``<vehicle>-mag<N>``, else None."""
    match = _DEVICE.match(device)
    return int(match.group("instance")) if match else None

"""The compasses of one vehicle compared with each other (docs/vehicles.md): which one disagrees, why, and the
autopilot parameter that fixes it. Pure numpy.

- ``membership``: which vehicle a device belongs to (MAVLink: ``<prefix><SYSID>-mag<N>`` -> ``<prefix><SYSID>``).
- ``window``: the recent samples of each vehicle's compasses, decimated and bounded (fed by the compass).
- ``consistency``: the comparison in the body frame and its verdicts (mounting rotation, motor interference, a
  calibration that no longer fits, a local anomaly).
"""

import importlib
from typing import TYPE_CHECKING, Any

from magnet.vehicle.membership import instance_of, vehicle_of
from magnet.vehicle.window import VehicleWindows

if TYPE_CHECKING:
    from magnet.vehicle.consistency import CompassVerdict, Series, VehicleReport, Verdict, judge

#: the comparison, loaded on first use (PEP 562): the compass's core keeps the windows on every step but judges a
#: vehicle only when asked, and ``magnet heading`` never does (its five dataclasses and enum are a few ms of a start)
_LAZY = frozenset({"CompassVerdict", "Series", "VehicleReport", "Verdict", "judge"})


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'magnet.vehicle' has no attribute {name!r}")
    value = getattr(importlib.import_module("magnet.vehicle.consistency"), name)
    globals()[name] = value
    return value


__all__ = [
    "CompassVerdict",
    "Series",
    "VehicleReport",
    "VehicleWindows",
    "Verdict",
    "instance_of",
    "judge",
    "vehicle_of",
]

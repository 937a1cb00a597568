"""The compasses of one vehicle compared with each other (docs/vehicles.md): which one disagrees, why, and the
autopilot parameter that fixes it. Pure numpy.

- ``membership``: which vehicle a device belongs to (MAVLink: ``<prefix><SYSID>-mag<N>`` -> ``<prefix><SYSID>``).
- ``window``: the recent samples of each vehicle's compasses, decimated and bounded (fed by the compass).
- ``consistency``: the comparison in the body frame and its verdicts (mounting rotation, motor interference, a
  calibration that no longer fits, a local anomaly).
"""

from magnet.vehicle.consistency import CompassVerdict, Series, VehicleReport, Verdict, judge
from magnet.vehicle.membership import instance_of, vehicle_of
from magnet.vehicle.window import VehicleWindows

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

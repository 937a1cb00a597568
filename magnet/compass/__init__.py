"""The compass's pure logic in one place, and one object with one step (``CompassCore.step``).

- ``earth``: what the World Magnetic Model expects at a place on a day (``Earth``, ``earth_at``).
- ``places``: where each device is (reported, places file, default) and its Earth (``Places``).
- ``calibrations``: the calibrations in force, the refused ones, each sample's correction.
- ``tilt``: tilt-compensated headings and their smoothing.
- ``filters``: one gyroscope-aided filter per device (``DeviceFilters``).
- ``watch``: places and drift alerts (``DeviceWatch``).
- ``keys``: which device a key names, and whether it is this shard's.
- ``core``: ``CompassCore`` holding those parts; ``step(raw, now_ns) -> HeadingColumns``.

See docs/compass.md for the path of one sample.
"""

from magnet.compass.core import CompassCore, CompassStatus, CoreSettings, HeadingColumns
from magnet.compass.earth import Earth, earth_at
from magnet.compass.places import Places

__all__ = ["CompassCore", "CompassStatus", "CoreSettings", "Earth", "HeadingColumns", "Places", "earth_at"]

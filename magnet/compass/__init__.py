"""The compass's pure logic in one place, and one object with one step (``CompassCore.step``).

- ``calibrations``: the calibrations in force, the refused ones, each sample's correction.
- ``tilt``: tilt-compensated headings and their smoothing.
- ``filters``: one gyroscope-aided filter per device (``DeviceFilters``).
- ``watch``: places and drift alerts (``DeviceWatch``).
- ``keys``: which device a key names, and whether it is this shard's.
- ``core``: ``CompassCore`` holding those parts; ``step(raw, now_ns) -> HeadingColumns``.

What the World Magnetic Model expects at a place (``Earth``) and where each device is (``Places``) live in
``magnet.earth``. See docs/compass.md for the path of one sample.
"""

from magnet.compass.core import CompassCore, CompassStatus, CoreSettings, HeadingColumns

__all__ = ["CompassCore", "CompassStatus", "CoreSettings", "HeadingColumns"]

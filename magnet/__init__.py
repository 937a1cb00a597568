"""magnet: magnetometer calibration and compass maths, drivers, emulators, simulator and wire format.

Everything in this package is pure (numpy on arrays of documented shape and unit) or talks to hardware through an
injected bus object. Nothing here imports zenoh or smbus2: the processes in ``services`` do that.
"""

__version__ = "0.1.0"

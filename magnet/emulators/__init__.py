"""Register-level emulators of the supported chips (see ``magnet.emulators.base`` for what they share).

``magnet.emulators.<chip>.<CHIP>Emulator(source=None, ...)`` implements the smbus2 ``SMBus`` methods on a register
map that behaves as the chip's datasheet says; ``source.measure() -> (mag_ut (3,), acc_ms2 (3,))`` gives the true
field and specific force in the body frame.
"""

from magnet.emulators.base import ConstantSource, EmulatedBus, FaultInjector, SourceTap

__all__ = ["ConstantSource", "EmulatedBus", "FaultInjector", "SourceTap"]

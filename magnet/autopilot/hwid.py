"""Compass hardware ids as autopilots report them (docs/mavlink.md, "Hardware ids"): which parameter holds the id of
compass instance N, how its value comes over MAVLink's parameter protocol, and what its bits say.

Both autopilots pack a sensor's id into 24 bits: bus type (bits 0-2), bus number (bits 3-7), address on the bus
(bits 8-15), device type (bits 16-23). Bus-type numbers differ between them (and between versions); magnet compares
whole ids and decodes the fields only to show them.

- ArduPilot: ``COMPASS_DEV_ID`` (instance 0), ``COMPASS_DEV_ID2``, ``COMPASS_DEV_ID3``; sent in PARAM_VALUE as the
  integer converted to a float (exact: 24 bits fit a float's mantissa).
- PX4: ``CAL_MAG0_ID``, ``CAL_MAG1_ID``, ...; sent byte-for-byte (the int32's bits in the float field, param_type
  MAV_PARAM_TYPE_INT32).

Pure: names and numbers in, ids out.
"""

from __future__ import annotations

import dataclasses
import math
import struct

#: MAVLink's MAV_AUTOPILOT values of the two autopilots
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
#: MAV_PARAM_TYPE_INT32
PARAM_TYPE_INT32 = 6
#: the instances whose ids are asked (ArduPilot names three; PX4 up to four)
ARDUPILOT_INSTANCES = 3
PX4_INSTANCES = 4
#: the most an id may be (24 bits); 0 is "no compass in this slot"
MAX_HARDWARE_ID = (1 << 24) - 1

#: bus-type names per autopilot (AP_HAL/Device.h; PX4 src/lib/drivers/device/Device.hpp)
ARDUPILOT_BUSES = {0: "unknown", 1: "I2C", 2: "SPI", 3: "DroneCAN", 4: "SITL", 5: "MSP", 6: "serial"}
PX4_BUSES = {0: "unknown", 1: "I2C", 2: "SPI", 3: "UAVCAN", 4: "simulation", 5: "serial", 6: "MAVLink"}


def id_param(autopilot: int, instance: int) -> str:
    """The parameter that holds compass ``instance``'s id on ``autopilot`` (a MAV_AUTOPILOT value; anything but PX4
    is read as ArduPilot's naming). ValueError for an instance the autopilot has no such parameter for."""
    if autopilot == MAV_AUTOPILOT_PX4:
        if not 0 <= instance < PX4_INSTANCES:
            raise ValueError(f"PX4 compass instance must be 0..{PX4_INSTANCES - 1}, got {instance}")
        return f"CAL_MAG{instance}_ID"
    if not 0 <= instance < ARDUPILOT_INSTANCES:
        raise ValueError(f"ArduPilot compass instance must be 0..{ARDUPILOT_INSTANCES - 1}, got {instance}")
    return "COMPASS_DEV_ID" + ("" if instance == 0 else str(instance + 1))


def id_params(autopilot: int) -> dict[str, int]:
    """Every id parameter of ``autopilot`` -> its compass instance."""
    count = PX4_INSTANCES if autopilot == MAV_AUTOPILOT_PX4 else ARDUPILOT_INSTANCES
    return {id_param(autopilot, i): i for i in range(count)}


def instance_of(name: str) -> int | None:
    """The compass instance an id parameter names (``COMPASS_DEV_ID2``: 1, ``CAL_MAG0_ID``: 0), else None."""
    for autopilot in (MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4):
        found = id_params(autopilot).get(name)
        if found is not None:
            return found
    return None


def param_int(value: float, param_type: int) -> int | None:
    """The integer a PARAM_VALUE carries: a float holding a whole number as it is (ArduPilot's cast); for an INT32
    parameter whose float is not a whole number, the float's bits read as an int32 (PX4's byte-for-byte encoding:
    an id below 2**23 reads as a tiny denormal float). None when neither gives an integer."""
    if math.isfinite(value) and float(value).is_integer():
        return int(value)
    if param_type == PARAM_TYPE_INT32:
        return int(struct.unpack("<i", struct.pack("<f", value))[0])
    return None


def hardware_id(value: float, param_type: int) -> int | None:
    """The compass id a PARAM_VALUE of an id parameter carries: 1..2**24-1; 0 when the slot holds no compass; None
    when the value is not an id."""
    number = param_int(value, param_type)
    if number is None or not 0 <= number <= MAX_HARDWARE_ID:
        return None
    return number


def as_float_bytes(device_id: int) -> float:
    """The float PX4 puts in PARAM_VALUE for an INT32 ``device_id`` (its bits): for stand-ins and tests."""
    return float(struct.unpack("<f", struct.pack("<i", device_id))[0])


@dataclasses.dataclass(frozen=True)
class DeviceId:
    """A sensor id's fields: bus type (number), bus, address, device type (the driver's DEVTYPE)."""

    bus_type: int
    bus: int
    address: int
    devtype: int

    @classmethod
    def of(cls, device_id: int) -> DeviceId:
        if not 0 <= device_id <= MAX_HARDWARE_ID:
            raise ValueError(f"a compass hardware id is 0..{MAX_HARDWARE_ID}, got {device_id}")
        return cls(device_id & 0x07, (device_id >> 3) & 0x1F, (device_id >> 8) & 0xFF, (device_id >> 16) & 0xFF)

    def pack(self) -> int:
        return self.bus_type | self.bus << 3 | self.address << 8 | self.devtype << 16


def describe(device_id: int, autopilot: int = MAV_AUTOPILOT_ARDUPILOTMEGA) -> str:
    """``<id> (<bus> bus <n> address 0x<aa> devtype 0x<tt>)`` for people."""
    if device_id == 0:
        return "0 (no compass)"
    d = DeviceId.of(device_id)
    buses = PX4_BUSES if autopilot == MAV_AUTOPILOT_PX4 else ARDUPILOT_BUSES
    bus = buses.get(d.bus_type, f"bus type {d.bus_type}")
    return f"{device_id} ({bus} bus {d.bus} address 0x{d.address:02x} devtype 0x{d.devtype:02x})"

"""Compass hardware ids (issue 27, item 5): the autopilots' parameters and encodings (magnet.autopilot.hwid) and the
MAVLink stream asking for them and stamping every batch with the id of its samples' sensor, across a reboot that loses
a compass (magnet.autopilot.mavlink_stream)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import common as mav

from magnet import wire
from magnet.autopilot import hwid, mavlink
from magnet.autopilot.mavlink_stream import ID_RETRY_NS, ID_WAIT_NS, MavlinkStream

NOW = 1_700_000_000_000_000_000
# ArduPilot ids: an external I2C HMC5883 (bus 1, address 0x1e, devtype 7) and an internal SPI LSM303D (devtype 2)
EXTERNAL = hwid.DeviceId(1, 1, 0x1E, 0x07).pack()
INTERNAL = hwid.DeviceId(2, 0, 0x03, 0x02).pack()
THIRD = hwid.DeviceId(3, 0, 0x7D, 0x01).pack()


def parsed(sysid: int, *encoded: mav.MAVLink_message) -> list[dict]:
    sender = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
    data = b"".join(m.pack(sender) for m in encoded)
    return [mavlink.message_dict(m) for m in mav.MAVLink(None).parse_buffer(data)]


S = mav.MAVLink(None)


def heartbeat(autopilot: int = hwid.MAV_AUTOPILOT_ARDUPILOTMEGA) -> dict:
    return parsed(1, S.heartbeat_encode(2, autopilot, 0, 0, 3))[0]


def param(name: str, value: float, kind: int = mav.MAV_PARAM_TYPE_REAL32) -> dict:
    return parsed(1, S.param_value_encode(name.encode(), value, kind, 40, 1))[0]


def imu(instance: int, boot_ms: int) -> dict:
    encode = (S.scaled_imu_encode, S.scaled_imu2_encode, S.scaled_imu3_encode)[instance]
    return parsed(1, encode(boot_ms, 0, 0, -1000, 0, 0, 0, 200 + instance, 0, 400))[0]


def test_the_id_packs_bus_type_bus_address_and_devtype_as_both_autopilots_do() -> None:
    # ArduPilot's own decoder (Tools/scripts/decode_devid.py): bus_type = id & 7, bus = (id >> 3) & 31, ...
    assert EXTERNAL == 1 | 1 << 3 | 0x1E << 8 | 0x07 << 16 == 466441
    assert hwid.DeviceId.of(466441) == hwid.DeviceId(1, 1, 0x1E, 0x07)
    assert hwid.describe(466441) == "466441 (I2C bus 1 address 0x1e devtype 0x07)"
    assert hwid.describe(0) == "0 (no compass)"
    with pytest.raises(ValueError, match=r"0\.\.16777215"):
        hwid.DeviceId.of(1 << 24)


def test_parameter_names_and_their_two_encodings() -> None:
    ardupilot, px4 = hwid.MAV_AUTOPILOT_ARDUPILOTMEGA, hwid.MAV_AUTOPILOT_PX4
    assert list(hwid.id_params(ardupilot)) == ["COMPASS_DEV_ID", "COMPASS_DEV_ID2", "COMPASS_DEV_ID3"]
    assert list(hwid.id_params(px4)) == ["CAL_MAG0_ID", "CAL_MAG1_ID", "CAL_MAG2_ID", "CAL_MAG3_ID"]
    assert hwid.instance_of("COMPASS_DEV_ID3") == 2 and hwid.instance_of("CAL_MAG1_ID") == 1
    assert hwid.instance_of("COMPASS_OFS_X") is None
    # ArduPilot sends the integer as a float; PX4 sends the int32's bytes (a tiny denormal float for an id)
    assert hwid.hardware_id(float(EXTERNAL), mav.MAV_PARAM_TYPE_INT32) == EXTERNAL
    bytewise = hwid.as_float_bytes(EXTERNAL)
    assert 0 < bytewise < 1e-38 and hwid.hardware_id(bytewise, mav.MAV_PARAM_TYPE_INT32) == EXTERNAL
    assert hwid.hardware_id(0.5, mav.MAV_PARAM_TYPE_REAL32) is None
    assert hwid.hardware_id(-3.0, mav.MAV_PARAM_TYPE_INT32) is None


def test_samples_wait_for_their_sensors_ids_and_carry_them() -> None:
    stream = MavlinkStream(batch=2)
    stream.feed(heartbeat(), NOW)
    asked = stream.requests(NOW)
    assert asked == [(1, 1, "COMPASS_DEV_ID"), (1, 1, "COMPASS_DEV_ID2"), (1, 1, "COMPASS_DEV_ID3")]
    for k in range(2):
        stream.feed(imu(0, 100 + 20 * k), NOW + k)
        stream.feed(imu(1, 100 + 20 * k), NOW + k)
    assert stream.take(NOW + 10) == []  # the ids are being read: nothing goes out under a guess
    assert stream.requests(NOW + 10) == []  # asked again only after ID_ASK_NS
    stream.feed(param("COMPASS_DEV_ID", EXTERNAL), NOW + 20)
    [first] = stream.take(NOW + 30)
    assert first.device == "mav1-mag0" and first.hardware_id == EXTERNAL
    stream.feed(param("COMPASS_DEV_ID2", INTERNAL), NOW + 40)
    stream.feed(param("COMPASS_DEV_ID3", 0.0), NOW + 50)  # no third compass
    [second] = stream.take(NOW + 60)
    assert second.device == "mav1-mag1" and second.hardware_id == INTERNAL
    assert stream.hardware_ids() == {"mav1-mag0": EXTERNAL, "mav1-mag1": INTERNAL}
    decoded = wire.decode_raw(wire.encode_raw(second))
    assert decoded.hardware_id == INTERNAL  # on the wire, both versions
    assert wire.decode_raw(wire.encode_raw(second, version=1)).hardware_id == INTERNAL
    assert stream.requests(NOW + 10 * ID_WAIT_NS) == []  # all known: nothing more asked


def test_a_compass_missing_after_a_reboot_gives_its_instance_to_another_sensor_under_that_sensors_id() -> None:
    """The first compass is gone at the next boot and the second becomes instance 0 (firmware that numbers compasses
    as found): the batches of mav1-mag0 before the reboot carry the first's id, after it the second's, never mixed."""
    stream = MavlinkStream(batch=3)
    stream.feed(heartbeat(), NOW)
    stream.requests(NOW)
    for name, value in (("COMPASS_DEV_ID", EXTERNAL), ("COMPASS_DEV_ID2", INTERNAL), ("COMPASS_DEV_ID3", 0)):
        stream.feed(param(name, value), NOW)
    stream.feed(imu(0, 50_000), NOW + 1)
    stream.feed(imu(0, 50_020), NOW + 2)
    stream.feed(imu(0, 30), NOW + 3)  # rebooted: its clock went back; instance 0 is now the internal compass
    assert stream.counts["resyncs"] == 1
    assert [(b.hardware_id, len(b)) for b in stream.take(NOW + 4)] == [(EXTERNAL, 2)]  # the one after waits
    assert [n for _, _, n in stream.requests(NOW + 5)] == ["COMPASS_DEV_ID", "COMPASS_DEV_ID2", "COMPASS_DEV_ID3"]
    stream.feed(param("COMPASS_DEV_ID", INTERNAL), NOW + 6)
    stream.feed(param("COMPASS_DEV_ID2", 0), NOW + 7)
    stream.feed(param("COMPASS_DEV_ID3", 0), NOW + 8)
    [after] = stream.take(NOW + 9, flush=True)
    assert after.hardware_id == INTERNAL and len(after) == 1


def test_a_vehicle_that_does_not_answer_holds_its_samples_at_most_id_wait_then_is_asked_again() -> None:
    stream = MavlinkStream(batch=1)
    stream.feed(heartbeat(hwid.MAV_AUTOPILOT_PX4), NOW)
    assert next(n for _, _, n in stream.requests(NOW)) == "CAL_MAG0_ID"
    stream.feed(imu(0, 10), NOW + 1)
    assert stream.take(NOW + ID_WAIT_NS // 2) == []
    [late] = stream.take(NOW + ID_WAIT_NS + 1)
    assert late.hardware_id == 0 and stream.counts["id-timeouts"] == 1  # sent without an id
    assert stream.requests(NOW + ID_WAIT_NS + 2) == []
    assert len(stream.requests(NOW + ID_WAIT_NS + ID_RETRY_NS + 2)) == 4  # asked again, samples no longer held
    stream.feed(param("CAL_MAG0_ID", hwid.as_float_bytes(THIRD), mav.MAV_PARAM_TYPE_INT32), NOW + 2 * ID_RETRY_NS)
    stream.feed(imu(0, 30), NOW + 2 * ID_RETRY_NS + 1)
    [known] = stream.take(NOW + 2 * ID_RETRY_NS + 2)
    assert known.hardware_id == THIRD


def test_a_bad_id_answer_is_dropped_and_counted_and_a_camera_is_not_asked() -> None:
    stream = MavlinkStream(batch=1)
    camera = parsed(1, S.heartbeat_encode(mav.MAV_TYPE_CAMERA, mav.MAV_AUTOPILOT_INVALID, 0, 0, 3))[0]
    stream.feed(camera, NOW)
    assert stream.requests(NOW) == []  # no autopilot heard yet
    stream.feed(heartbeat(), NOW)
    assert stream.feed(param("COMPASS_DEV_ID", 0.25), NOW) == "bad-field"
    assert stream.counts["dropped:bad-field"] == 1

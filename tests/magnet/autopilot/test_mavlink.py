"""MAVLink messages, encoded and parsed by pymavlink (the ecosystem's library), into magnet's units, devices, times
and batches (magnet.autopilot.mavlink, magnet.autopilot.mavlink_stream)."""

from __future__ import annotations

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from magnet import wire
from magnet.autopilot import mavlink
from magnet.autopilot.mavlink_stream import MAX_SKEW_NS, MavlinkStream

G = 9.80665
NOW = 1_700_000_000_000_000_000


def parsed(sysid: int, *encoded: mav.MAVLink_message) -> list[dict]:
    """Messages sent by vehicle ``sysid`` as bytes and parsed back by pymavlink."""
    sender = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
    data = b"".join(m.pack(sender) for m in encoded)
    return [mavlink.message_dict(m) for m in mav.MAVLink(None).parse_buffer(data)]


def sender() -> mav.MAVLink:
    return mav.MAVLink(None)


def test_scaled_imu_units_are_milligauss_milli_g_and_milliradians() -> None:
    s = sender()
    [message] = parsed(3, s.scaled_imu2_encode(1500, 10, -20, -1000, 100, -200, 300, 180, -40, 470))
    sample = mavlink.imu_sample(message)
    assert sample.instance == 1 and sample.boot_ns == 1_500_000_000
    np.testing.assert_allclose(sample.mag_ut, [18.0, -4.0, 47.0])
    np.testing.assert_allclose(sample.acc_ms2, [0.01 * G, -0.02 * G, -G])
    np.testing.assert_allclose(sample.gyr_rads, [0.1, -0.2, 0.3])


def test_highres_imu_is_in_gauss_and_si_and_raw_imu_is_instance_0() -> None:
    s = sender()
    high, raw = parsed(
        1,
        s.highres_imu_encode(2_000_000, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0.2, -0.05, 0.45, 0, 0, 0, 20, 0x1FF, 2),
        s.raw_imu_encode(3_000_000, 0, 0, -1000, 0, 0, 0, 200, 0, 400),
    )
    h = mavlink.imu_sample(high)
    assert h.instance == 2 and h.boot_ns == 2_000_000_000
    np.testing.assert_allclose(h.mag_ut, [20.0, -5.0, 45.0])
    np.testing.assert_allclose(h.acc_ms2, [0.1, 0.2, -9.8], rtol=1e-6)
    r = mavlink.imu_sample(raw)
    assert r.instance == 0 and r.boot_ns == 3_000_000_000
    np.testing.assert_allclose(r.mag_ut, [20.0, 0.0, 40.0])


def test_position_current_throttle_and_armed() -> None:
    s = sender()
    pos, sys_status, servo, beat = parsed(
        1,
        s.global_position_int_encode(1000, 504500000, 305200000, 180500, 10000, 150, -250, 30, 0),
        s.sys_status_encode(0, 0, 0, 500, 16000, 2550, 80, 0, 0, 0, 0, 0, 0),
        s.servo_output_raw_encode(0, 0, 1500, 1700, 1500, 1700, 0, 0, 0, 0),
        s.heartbeat_encode(2, 3, 128 | 1, 0, 4),
    )
    place = mavlink.position(pos)
    assert place.location is not None
    assert (place.location.lat_deg, place.location.lon_deg, place.location.alt_m) == pytest.approx(
        (50.45, 30.52, 180.5)
    )
    np.testing.assert_allclose(place.vel_ned_ms, [1.5, -2.5, 0.3])
    assert mavlink.battery_current_a(sys_status) == pytest.approx(25.5)
    assert mavlink.throttle(servo, 4) == pytest.approx(0.6)
    assert mavlink.armed(beat)
    [no_fix] = parsed(1, s.global_position_int_encode(1000, 0, 0, 0, 0, 0, 0, 0, 0))
    assert mavlink.position(no_fix).location is None and np.isnan(mavlink.position(no_fix).vel_ned_ms).all()
    [unmeasured] = parsed(1, s.sys_status_encode(0, 0, 0, 500, 16000, -1, 80, 0, 0, 0, 0, 0, 0))
    assert mavlink.battery_current_a(unmeasured) is None


def test_stream_makes_one_device_per_vehicle_and_instance_with_attachments() -> None:
    s = sender()
    stream = MavlinkStream(prefix="uav", batch=4)
    setup = parsed(
        5,
        s.global_position_int_encode(0, 504500000, 305200000, 0, 0, 100, 200, 0, 0),
        s.sys_status_encode(0, 0, 0, 500, 16000, 1200, 80, 0, 0, 0, 0, 0, 0),
    )
    for m in setup:
        stream.feed(m, NOW)
    for k in range(4):
        for m in parsed(5, s.scaled_imu_encode(100 + 20 * k, 0, 0, -1000, 0, 0, 0, 200, 0, 400)):
            stream.feed(m, NOW + k * 1_000_000)
        for m in parsed(9, s.scaled_imu3_encode(7000 + 20 * k, 0, 0, -1000, 0, 0, 0, 150, 50, 400)):
            stream.feed(m, NOW + k * 1_000_000)
    batches = {b.device: b for b in stream.take(NOW + 4_000_000)}
    assert set(batches) == {"uav5-mag0", "uav9-mag2"}
    first = batches["uav5-mag0"]
    assert np.diff(first.t_ns).tolist() == [20_000_000] * 3 and first.t_ns[0] == NOW
    assert first.location is not None and first.location.lat_deg == pytest.approx(50.45)
    assert first.vel_ned_ms is not None and np.allclose(first.vel_ned_ms, [1.0, 2.0, 0.0])
    assert first.current_a is not None and np.allclose(first.current_a, 12.0) and first.throttle is None
    other = batches["uav9-mag2"]
    assert other.location is None and other.vel_ned_ms is None and other.current_a is None
    assert wire.decode_raw(wire.encode_raw(first)).device == "uav5-mag0"  # a valid raw message


def test_stream_resyncs_after_a_reboot_and_never_goes_back() -> None:
    s = sender()
    stream = MavlinkStream(batch=1)
    times = []
    for boot_ms, now in ((50_000, NOW), (50_020, NOW + 20_000_000), (100, NOW + 40_000_000), (120, NOW + 60_000_000)):
        for m in parsed(1, s.scaled_imu_encode(boot_ms, 0, 0, -1000, 0, 0, 0, 200, 0, 400)):
            stream.feed(m, now)
        times += [b.t_ns[0] for b in stream.take(now)]
    assert times == [NOW, NOW + 20_000_000, NOW + 40_000_000, NOW + 60_000_000]
    assert stream.counts["resyncs"] == 1
    for m in parsed(1, s.scaled_imu_encode(130, 0, 0, -1000, 0, 0, 0, 200, 0, 400)):
        stream.feed(m, NOW + 2 * MAX_SKEW_NS)  # the vehicle's clock fell behind the wall's: resync
    [late] = stream.take(NOW + 10 * MAX_SKEW_NS)
    assert late.t_ns[0] == NOW + 2 * MAX_SKEW_NS and stream.counts["resyncs"] == 2


def test_garbage_and_unusable_messages_are_dropped_and_counted_and_vehicles_go_quiet() -> None:
    s = sender()
    stream = MavlinkStream(batch=1)
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    junk = parser.parse_buffer(bytes(range(256)) * 4) or []
    for m in junk:
        stream.feed(mavlink.message_dict(m) | {"sysid": 1}, NOW)
    assert stream.counts["dropped:bad-data"] == len(junk) > 0
    bad = parsed(2, s.scaled_imu_encode(1, 0, 0, -1000, 0, 0, 0, 0, 0, 0))[0]  # no magnetometer
    assert stream.feed(bad, NOW) == "no-mag"
    assert stream.feed({"mavpackettype": "SCALED_IMU", "sysid": 2, "time_boot_ms": 1, "xmag": float("nan")}, NOW)
    assert stream.feed({"mavpackettype": "SCALED_IMU", "sysid": 0}, NOW) == "bad-field"
    assert stream.feed(parsed(2, s.attitude_encode(1, 0, 0, 0, 0, 0, 0))[0], NOW) is None
    assert stream.counts["ignored"] == 1 and stream.take(NOW, flush=True) == []
    good = parsed(2, s.scaled_imu_encode(1, 0, 0, -1000, 0, 0, 0, 200, 0, 400))[0]
    stream.feed(good, NOW)
    assert stream.health(NOW + 1_000_000_000, 3_000_000_000) == {"mav2-mag0": True}
    assert stream.health(NOW + 4_000_000_000, 3_000_000_000) == {"mav2-mag0": False}


def test_battery_current_from_a_vehicle_reaches_the_compass_which_takes_the_motors_field_out() -> None:
    """SYS_STATUS current and SCALED_IMU2 field through the stream, the wire and the compass with a motor model."""
    from compass_steps import compass_core, heading_batches

    from magnet.earth.expected import Earth
    from magnet.model import IDENTITY
    from magnet.motor import MotorModel

    earth, per_amp, amps = np.array([18.0, 3.0, 47.0]), np.array([0.1, -0.05, 0.2]), 25.0
    measured_mgauss = np.round((earth + per_amp * amps) * 10).astype(int)
    s = sender()
    stream = MavlinkStream(batch=3)
    for m in parsed(4, s.sys_status_encode(0, 0, 0, 500, 16000, int(amps * 100), 80, 0, 0, 0, 0, 0, 0)):
        stream.feed(m, NOW)
    for k in range(3):
        for m in parsed(4, s.scaled_imu2_encode(20 * k, 0, 0, -1000, 0, 0, 0, *measured_mgauss)):
            stream.feed(m, NOW + k)
    [batch] = stream.take(NOW + 3)
    batch = wire.decode_raw(wire.encode_raw(batch))
    assert batch.current_a is not None and np.allclose(batch.current_a, amps)
    compass = compass_core(Earth(), window=1)
    record = wire.encode_calibration("mav4-mag1", IDENTITY.replace(motor=MotorModel("current", per_amp)), 1)
    assert compass.accept_calibration(record, "magnet/mav4-mag1/calibration", "magnet")
    [out] = heading_batches(compass, [batch])
    np.testing.assert_allclose(out.field_ut, np.tile(earth, (3, 1)), atol=0.06)  # 0.1 uT steps of milligauss


def _turning(s: mav.MAVLink, k: int, gyro: tuple[int, int, int], instance: int = 2) -> mav.MAVLink_message:
    """SCALED_IMU<instance> k: the field turning 2 deg per message about z, the gyroscope as given (mrad/s)."""
    angle = np.radians(2.0 * k)
    field = (int(400 * np.cos(angle)), int(400 * np.sin(angle)), 100)
    encode = s.scaled_imu2_encode if instance == 1 else s.scaled_imu3_encode
    return encode(1000 + 20 * k, 0, 0, -1000, *gyro, *field)


def test_a_gyroscope_reading_zero_while_the_field_turns_is_absent() -> None:
    """Fault 1 of issue 27: ArduPilot's SCALED_IMU2 with zero gyro fields (no second IMU): the samples go out without a
    gyroscope, the device is listed; a real gyroscope that reads zero now and then keeps its zeros."""
    s = sender()
    stream = MavlinkStream(batch=30)
    for k in range(30):
        for m in parsed(1, _turning(s, k, (0, 0, 0)), _turning(s, k, (0, 0, 35) if k % 3 else (0, 0, 0), 1)):
            stream.feed(m, NOW + k * 20_000_000)
    batches = {b.device: b for b in stream.take(NOW + 30 * 20_000_000)}
    assert batches["mav1-mag2"].gyr_rads is None
    assert stream.gyro_absent == ["mav1-mag2"]  # zeros while the field turned 56 deg
    real = batches["mav1-mag1"].gyr_rads
    assert real is not None and np.isnan(real[0]).all()  # zero before it ever read anything: not yet a gyroscope
    assert np.isfinite(real[1:]).all() and (real[3::3] == 0).all()  # later zeros are a real gyroscope's
    for k in range(30, 40):  # it reads a rate: a gyroscope after all
        for m in parsed(1, _turning(s, k, (0, 0, 35))):
            stream.feed(m, NOW + k * 20_000_000)
    assert stream.gyro_absent == []


def test_a_still_vehicle_whose_gyroscope_reads_zero_is_not_judged() -> None:
    s = sender()
    stream = MavlinkStream(batch=50)
    for k in range(50):
        for m in parsed(1, s.scaled_imu2_encode(1000 + 20 * k, 0, 0, -1000, 0, 0, 0, 200, 0, 400)):
            stream.feed(m, NOW + k * 20_000_000)
    assert stream.gyro_absent == [] and stream.take(NOW + 10**9)[0].gyr_rads is None


def test_one_connection_makes_at_most_max_devices_and_the_known_ones_go_on() -> None:
    """Issue 32: one UDP port made 15,879 devices in 2 minutes (255 system ids times HIGHRES_IMU ids). Beyond the
    bound a new device's samples are dropped and counted; the devices already known keep their batches."""
    s = sender()
    stream = MavlinkStream(batch=1, max_devices=3)
    good = s.scaled_imu_encode(1, 0, 0, -1000, 0, 0, 0, 200, 0, 400)
    for sysid in range(1, 41):  # 40 vehicles, 2 compasses each: 80 ids
        for encode in (s.scaled_imu_encode, s.scaled_imu2_encode):
            msg = encode(1, 0, 0, -1000, 0, 0, 0, 200, 0, 400)
            for m in parsed(sysid, msg):
                stream.feed(m, NOW)
    assert set(stream.pending) == {"mav1-mag0", "mav1-mag1", "mav2-mag0"}
    assert stream.counts["dropped:device-limit"] == 77 and "beyond the 3" in stream.last_error
    for m in parsed(1, good):
        assert stream.feed(m, NOW + 20_000_000) is None  # a known device is never refused
    assert {b.device for b in stream.take(NOW + 20_000_000)} == {"mav1-mag0", "mav1-mag1", "mav2-mag0"}
    with pytest.raises(ValueError, match="max_devices"):
        MavlinkStream(max_devices=0)


def test_a_device_that_falls_silent_gives_its_place_back() -> None:
    """Issue 32: a flood that filled a port's places kept a real vehicle that came later out until the edge
    restarted. A device with no sample for ``forget_ns`` is forgotten (counted, listed for the edge) and its place
    goes to a new device; one that keeps sending keeps its place."""
    s = sender()
    second = 1_000_000_000
    stream = MavlinkStream(batch=1, max_devices=4, forget_ns=60 * second)
    for sysid in range(2, 42):  # the flood: 40 ids, one message each, at NOW
        for m in parsed(sysid, s.scaled_imu_encode(1, 0, 0, -1000, 0, 0, 0, 200, 0, 400)):
            stream.feed(m, NOW)
    assert len(stream.pending) == 4 and stream.counts["dropped:device-limit"] == 36
    stream.take(NOW)
    real = parsed(1, s.scaled_imu2_encode(1, 0, 0, -1000, 0, 0, 0, 200, 0, 400))[0]
    assert stream.feed(real, NOW + 30 * second) == "device-limit"  # the flood's ids are not silent long enough
    for m in parsed(2, s.scaled_imu_encode(50_000, 0, 0, -1000, 0, 0, 0, 200, 0, 400)):
        stream.feed(m, NOW + 50 * second)  # one of them keeps sending
    stream.take(NOW + 50 * second)
    assert stream.feed(real, NOW + 61 * second) is None  # the real vehicle gets in after the silence
    assert set(stream.pending) == {"mav2-mag0", "mav1-mag1"}
    assert stream.counts["forgotten"] == 3 and sorted(stream.take_forgotten()) == [
        "mav3-mag0",
        "mav4-mag0",
        "mav5-mag0",
    ]
    assert [b.device for b in stream.take(NOW + 61 * second)] == ["mav1-mag1"]
    assert set(stream.vehicles) == {1, 2}  # the flood's silent system ids forgotten with their devices
    assert stream.take(NOW + 200 * second) == [] and stream.take_forgotten() == ["mav2-mag0", "mav1-mag1"]
    assert stream.pending == {} and stream.take_forgotten() == [] and stream.vehicles == {}
    with pytest.raises(ValueError, match="forget_ns"):
        MavlinkStream(forget_ns=0)

"""ICM-20948, LSM9DS1 and MPU-6050 (+ HMC5883L / QMC5883L) drivers against their register-level emulators: identity,
full-scale ranges, data ready, bypass, retries, saturation, and axes mapped to the body frame."""

import errno

import numpy as np
import pytest

from magnet import simulator as sim
from magnet.drivers import GYROSCOPES, has_gyroscope, open_sensor
from magnet.drivers.base import SensorError, SensorReadError
from magnet.drivers.icm20948 import ICM20948, ICM20948AccelGyro
from magnet.drivers.lsm9ds1 import LSM9DS1, LSM9DS1AccelGyro, LSM9DS1Magnetometer
from magnet.drivers.mpu6050 import MPU6050
from magnet.emulators import emulator_for
from magnet.emulators.base import ConstantSource, FaultInjector
from magnet.emulators.icm20948 import ICM20948Emulator
from magnet.emulators.lsm9ds1 import LSM9DS1Emulator
from magnet.emulators.mpu6050 import MPU6050Emulator

G = 9.80665
DEG = np.pi / 180
FIELD = np.array([22.0, -7.5, 41.0])  # body frame, uT
ACC = np.array([0.8, -1.1, -9.7])  # body frame, m/s^2
GYR = np.array([0.3, -0.5, 0.7])  # body frame, rad/s
NO_SLEEP = dict(sleep=lambda s: None)


def source(field=FIELD, acc=ACC, gyr=GYR):
    return ConstantSource(field, acc, gyr)


def s16(low, high):
    return int.from_bytes(bytes([low, high]), "little", signed=True)


# --------------------------------------------------------------------------------------------- identity


def test_icm20948_identity_refused():
    bus = ICM20948Emulator(source())
    bus.imu.banks[0][0x00] = 0x71  # an MPU-9250 answers 0x71
    with pytest.raises(SensorError, match="no ICM-20948 at 0x68: WHO_AM_I reads 0x71, expected 0xea"):
        ICM20948(bus, **NO_SLEEP)


def test_icm20948_magnetometer_identity_refused():
    bus = ICM20948Emulator(source())
    bus.mag.regs[0x01] = 0x0C  # an AK09918 where the AK09916 should be
    with pytest.raises(SensorError, match=r"no AK09916 at 0x0c.*expected 0x48/0x09"):
        ICM20948(bus, **NO_SLEEP)


def test_lsm9ds1_identities_refused():
    bus = LSM9DS1Emulator(source())
    bus.ag.regs[0x0F] = 0x69  # an LSM6DS3
    with pytest.raises(SensorError, match=r"no LSM9DS1 accelerometer/gyroscope at 0x6b.*expected 0x68"):
        LSM9DS1(bus, **NO_SLEEP)
    bus = LSM9DS1Emulator(source())
    bus.mag.regs[0x0F] = 0x3C
    with pytest.raises(SensorError, match=r"no LSM9DS1 magnetometer at 0x1e.*expected 0x3d"):
        LSM9DS1(bus, **NO_SLEEP)


def test_mpu6050_identity_refused():
    emu = MPU6050Emulator(source())
    emu.regs[0x75] = 0x70  # an MPU-6500
    with pytest.raises(SensorError, match=r"no MPU-6050 at 0x68.*reads 0x70, expected 0x68"):
        MPU6050(emu, **NO_SLEEP)


@pytest.mark.parametrize(
    "make",
    [
        lambda: ICM20948AccelGyro(ICM20948Emulator(), gyro_range_dps=300),
        lambda: LSM9DS1AccelGyro(LSM9DS1Emulator(), accel_range_g=3),
        lambda: MPU6050(MPU6050Emulator(), rate_hz=123),
        lambda: LSM9DS1Magnetometer(LSM9DS1Emulator(), range_gauss=5),
    ],
)
def test_settings_outside_the_datasheet_are_refused(make):
    with pytest.raises(ValueError, match="must be one of"):
        make()


# --------------------------------------------------------------------------------------------- full scales


def _icm(**settings):
    bus = ICM20948Emulator(source())
    return bus, ICM20948(bus, **settings, **NO_SLEEP)


@pytest.mark.parametrize("dps,code,lsb", [(250, 0, 131.0), (500, 1, 65.5), (1000, 2, 32.8), (2000, 3, 16.4)])
def test_icm20948_gyro_ranges(dps, code, lsb):
    bus, sensor = _icm(gyro_range_dps=dps)
    assert (bus.imu.banks[2][0x01] >> 1) & 0x03 == code and bus.imu.banks[2][0x01] & 0x01  # FS_SEL, FCHOICE
    reading = sensor.read()
    np.testing.assert_allclose(reading.gyr_rads, GYR, atol=DEG / lsb)
    # the register holds the chip's x code, big-endian, in LSB per deg/s
    assert int.from_bytes(bus.imu.banks[0][0x33:0x35], "big", signed=True) == round(GYR[0] / DEG * lsb)


@pytest.mark.parametrize("g,code,lsb", [(2, 0, 16384), (4, 1, 8192), (8, 2, 4096), (16, 3, 2048)])
def test_icm20948_accel_ranges(g, code, lsb):
    bus, sensor = _icm(accel_range_g=g)
    assert (bus.imu.banks[2][0x14] >> 1) & 0x03 == code
    np.testing.assert_allclose(sensor.read().acc_ms2, ACC, atol=G / lsb)


@pytest.mark.parametrize("dps,code,mdps", [(245, 0b00, 8.75), (500, 0b01, 17.5), (2000, 0b11, 70.0)])
def test_lsm9ds1_gyro_ranges(dps, code, mdps):
    bus = LSM9DS1Emulator(source())
    sensor = LSM9DS1(bus, gyro_range_dps=dps, rate_hz=238, **NO_SLEEP)
    assert bus.ag.regs[0x10] == (0b100 << 5) | (code << 3)  # ODR 238 Hz, FS_G
    np.testing.assert_allclose(sensor.read().gyr_rads, GYR, atol=mdps / 1000 * DEG)


@pytest.mark.parametrize("g,code,mg", [(2, 0b00, 0.061), (4, 0b10, 0.122), (8, 0b11, 0.244), (16, 0b01, 0.732)])
def test_lsm9ds1_accel_ranges(g, code, mg):
    bus = LSM9DS1Emulator(source())
    sensor = LSM9DS1(bus, accel_range_g=g, **NO_SLEEP)
    assert (bus.ag.regs[0x20] >> 3) & 0x03 == code
    np.testing.assert_allclose(sensor.read().acc_ms2, ACC, atol=mg / 1000 * G)


@pytest.mark.parametrize("gauss,code,mgauss", [(4, 0, 0.14), (8, 1, 0.29), (12, 2, 0.43), (16, 3, 0.58)])
def test_lsm9ds1_magnetometer_ranges(gauss, code, mgauss):
    bus = LSM9DS1Emulator(source())
    sensor = LSM9DS1(bus, range_gauss=gauss, **NO_SLEEP)
    assert bus.mag.regs[0x21] == code << 5 and bus.mag.regs[0x22] & 0x03 == 0  # FS, continuous
    np.testing.assert_allclose(sensor.read().mag_ut, FIELD, atol=mgauss / 10)


@pytest.mark.parametrize(
    "dps,g,lsb_dps,lsb_g", [(250, 2, 131.0, 16384), (500, 4, 65.5, 8192), (1000, 8, 32.8, 4096), (2000, 16, 16.4, 2048)]
)
def test_mpu6050_ranges(dps, g, lsb_dps, lsb_g):
    emu = MPU6050Emulator(source())
    sensor = MPU6050(emu, gyro_range_dps=dps, accel_range_g=g, **NO_SLEEP)
    assert emu.regs[0x1B] >> 3 == [250, 500, 1000, 2000].index(dps) and emu.regs[0x1C] >> 3 == [2, 4, 8, 16].index(g)
    assert not emu.regs[0x6B] & 0x40  # awake
    reading = sensor.read()
    np.testing.assert_allclose(reading.gyr_rads, GYR, atol=DEG / lsb_dps)
    np.testing.assert_allclose(reading.acc_ms2, ACC, atol=G / lsb_g)


def test_gyro_beyond_full_scale_is_withheld_not_passed_on():
    fast = source(gyr=(0.0, 0.0, 300 * DEG))  # 300 deg/s about z
    bus = emulator_for("mpu6050+qmc5883l", fast)
    sensor = open_sensor("mpu6050+qmc5883l", bus, gyro_range_dps=250, **NO_SLEEP)
    reading = sensor.read()
    assert reading.mag_ut is not None and reading.gyr_rads is None and reading.acc_ms2 is None
    sensor = open_sensor("mpu6050+qmc5883l", emulator_for("mpu6050+qmc5883l", fast), gyro_range_dps=500, **NO_SLEEP)
    assert sensor.read().gyr_rads[2] == pytest.approx(300 * DEG, abs=DEG / 65.5)


# --------------------------------------------------------------------------------------------- data ready, bypass


def test_icm20948_data_ready_follows_the_output_rate():
    now = [0.0]
    bus = ICM20948Emulator(source(), clock=lambda: now[0])
    sensor = ICM20948AccelGyro(bus, rate_hz=100, **NO_SLEEP)
    assert bus.imu.banks[2][0x00] == 10  # 1100 / (1 + 10) = 100 Hz
    assert not sensor.read().ready
    now[0] = 0.0101
    assert sensor.read().ok
    assert not sensor.read().ready  # INT_STATUS_1 read cleared it
    assert bus.imu.banks[0][0x1A] & 0x01 == 0


def test_lsm9ds1_waits_for_both_accelerometer_and_gyroscope():
    now = [0.0]
    bus = LSM9DS1Emulator(source(), clock=lambda: now[0])
    sensor = LSM9DS1AccelGyro(bus, rate_hz=119, **NO_SLEEP)
    assert not sensor.read().ready
    now[0] = 1 / 119 + 1e-6
    assert bus.read_byte_data(0x6B, 0x17) & 0x03 == 0x03  # XLDA | GDA
    assert sensor.read().ok
    assert bus.ag.regs[0x17] & 0x03 == 0


def test_mpu6050_data_ready_needs_the_interrupt_enable_and_clears_on_read():
    now = [0.0]
    emu = MPU6050Emulator(source(), clock=lambda: now[0])
    sensor = MPU6050(emu, rate_hz=50, **NO_SLEEP)
    assert emu.regs[0x19] == 19 and emu.regs[0x38] & 0x01  # 1 kHz / 20; DATA_RDY_EN
    assert not sensor.read().ready
    now[0] = 0.021
    assert sensor.read().ok and not sensor.read().ready


def test_icm20948_magnetometer_answers_only_in_bypass():
    bus = ICM20948Emulator(source())
    with pytest.raises(OSError) as caught:
        bus.read_byte_data(0x0C, 0x01)
    assert caught.value.errno == errno.EREMOTEIO
    ICM20948(bus, **NO_SLEEP)  # the driver turns the bypass on
    assert bus.read_byte_data(0x0C, 0x01) == 0x09


def test_lsm9ds1_magnetometer_block_read_needs_the_auto_increment_bit():
    bus = LSM9DS1Emulator(source())
    LSM9DS1(bus, **NO_SLEEP)
    repeated = bus.read_i2c_block_data(0x1E, 0x28, 2)
    assert repeated[0] == repeated[1]  # same register twice
    low, high = bus.read_i2c_block_data(0x1E, 0x28 | 0x80, 2)
    assert s16(low, high) == round(-FIELD[0] * 10 / 0.14)  # the magnetometer's x is reversed


def test_nine_axis_holds_the_last_inertial_sample_between_its_own():
    now = [0.0]
    bus = emulator_for("icm20948", source(), clock=lambda: now[0])
    sensor = open_sensor("icm20948", bus, rate_hz=10, mag_rate_hz=100, **NO_SLEEP)
    assert not sensor.read().ready  # the clocks start
    now[0] = 0.1001
    first = sensor.read()
    assert first.ok and first.gyr_rads is not None
    now[0] = 0.1101  # a new field, no new inertial sample
    second = sensor.read()
    assert second.ok and np.array_equal(second.gyr_rads, first.gyr_rads)


# --------------------------------------------------------------------------------------------- retries


@pytest.mark.parametrize("name", sorted(GYROSCOPES))
def test_transient_bus_errors_are_retried(name):
    bus = emulator_for(name, source())
    sensor = open_sensor(name, bus, **NO_SLEEP)
    bus.faults = FaultInjector(schedule=[errno.EIO, None, errno.EBUSY, errno.EREMOTEIO, None, errno.EIO])
    reading = sensor.read()
    assert reading.ok and reading.gyr_rads is not None
    np.testing.assert_allclose(reading.gyr_rads, GYR, atol=0.002)
    retries = sum(d.health.retries for d in sensor.devices)
    assert retries == 4


@pytest.mark.parametrize("name", sorted(GYROSCOPES))
def test_a_dead_bus_fails_the_read_after_the_retries(name):
    bus = emulator_for(name, source())
    sensor = open_sensor(name, bus, **NO_SLEEP)
    bus.faults = FaultInjector(probability=1.0)
    with pytest.raises(SensorReadError):
        sensor.read()
    assert sensor.health.errors == sensor.health.retries + 1 and not sensor.health.healthy  # one transfer gave up


# --------------------------------------------------------------------------------------------- axes


@pytest.mark.parametrize("name", sorted(GYROSCOPES))
def test_a_level_package_reads_gravity_down_and_the_registers_say_z_up(name):
    still = ConstantSource(FIELD, (0.0, 0.0, -G), (0.0, 0.0, 0.5))  # level, turning clockwise (right)
    sensor = open_sensor(name, emulator_for(name, still), **NO_SLEEP)
    reading = sensor.read()
    np.testing.assert_allclose(reading.acc_ms2, [0.0, 0.0, -G], atol=0.01)
    np.testing.assert_allclose(reading.gyr_rads, [0.0, 0.0, 0.5], atol=0.002)  # clockwise from above: +z
    np.testing.assert_allclose(reading.mag_ut, FIELD, atol=0.3)
    assert has_gyroscope(name)


def test_register_level_axes_follow_the_datasheets():
    """The chips' own axes are z up: a level package reads +1 g on z, a clockwise turn is -z; the AK09916's y and
    z and the LSM9DS1 magnetometer's x are reversed against their accelerometers."""
    still = ConstantSource(FIELD, (0.0, 0.0, -G), (0.0, 0.0, 0.5))
    icm = emulator_for("icm20948", still)
    ICM20948(icm, accel_range_g=2, gyro_range_dps=250, **NO_SLEEP).read()
    bank0 = icm.imu.banks[0]
    assert int.from_bytes(bank0[0x31:0x33], "big", signed=True) == 16384  # +1 g on z
    assert int.from_bytes(bank0[0x37:0x39], "big", signed=True) == round(-0.5 / DEG * 131)
    hx, hy, hz = (s16(icm.mag.regs[r], icm.mag.regs[r + 1]) for r in (0x11, 0x13, 0x15))
    assert (hx, hy, hz) == tuple(round(v / 0.15) for v in FIELD)  # (x, -y, -z) of z up
    lsm = emulator_for("lsm9ds1", still)
    LSM9DS1(lsm, accel_range_g=2, **NO_SLEEP).read()
    assert s16(lsm.ag.regs[0x2C], lsm.ag.regs[0x2D]) == round(1000 / 0.061)
    mx, my, mz = (s16(lsm.mag.regs[r], lsm.mag.regs[r + 1]) for r in (0x28, 0x2A, 0x2C))
    assert (mx, my, mz) == tuple(round(v * 10 / 0.14) for v in -FIELD)


@pytest.mark.parametrize("name", sorted(GYROSCOPES))
def test_a_tumbling_simulated_device_reads_its_truth_in_the_body_frame(name):
    """Through every axis at once: the fast-tumble trajectory (rates to ~700 deg/s, centripetal acceleration),
    read through the emulator and the driver, matches the simulator's samples within the chips' resolution."""
    config = sim.SimulatorConfig(trajectory="fast-tumble", count=300, rate_hz=100.0, date="2026-03-01", seed=2)
    truth = sim.simulate(config)
    sensor = open_sensor(name, emulator_for(name, sim.SensorStream(config)), **NO_SLEEP)
    readings = [sensor.read() for _ in range(300)]
    for attribute, tolerance in (("mag_ut", 0.5), ("acc_ms2", 0.01), ("gyr_rads", 0.002)):
        got = np.array([getattr(r, attribute) for r in readings])
        np.testing.assert_allclose(got, getattr(truth, attribute), atol=tolerance)


@pytest.mark.parametrize("name", sorted(GYROSCOPES))
def test_orientation_turns_the_package_for_every_part(name):
    """A package mounted upside down (roll 180) and told so reads the body frame again."""
    upside_down = np.diag([1.0, -1.0, -1.0])  # body -> package
    bus = emulator_for(name, source(), rotation=upside_down)
    reading = open_sensor(name, bus, orientation="roll180", **NO_SLEEP).read()
    np.testing.assert_allclose(reading.acc_ms2, ACC, atol=0.01)
    np.testing.assert_allclose(reading.gyr_rads, GYR, atol=0.002)
    np.testing.assert_allclose(reading.mag_ut, FIELD, atol=0.3)

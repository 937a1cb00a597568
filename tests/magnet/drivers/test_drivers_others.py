"""QMC5883L, LSM303DLH, AK09918C + BMA456 and HMC1043 drivers against their emulators; orientation; open_sensor."""

import errno

import numpy as np
import pytest
import smbus2

from magnet.drivers import open_sensor
from magnet.drivers.ak09918c import AK09918C
from magnet.drivers.base import I2CBus, SensorError, SensorReadError
from magnet.drivers.bma456 import BMA456
from magnet.drivers.hmc1043 import HMC1043, BridgeSettings
from magnet.drivers.lsm303dlh import LSM303DLH
from magnet.drivers.qmc5883l import QMC5883L, QMC5883LSettings
from magnet.emulators import emulator_for
from magnet.emulators.ak09918c import AK09918CEmulator
from magnet.emulators.base import ConstantSource, EmulatedBus, FaultInjector
from magnet.emulators.bma456 import BMA456Emulator
from magnet.emulators.qmc5883l import QMC5883LEmulator

FIELD = np.array([22.0, -7.5, 41.0])
ACC = np.array([0.8, -1.1, -9.7])
NO_SLEEP = dict(sleep=lambda s: None)


@pytest.mark.parametrize("range_gauss,lsb", [(2, 12000), (8, 3000)])
def test_qmc5883l_scaling_registers_and_order(range_gauss, lsb):
    emu = QMC5883LEmulator(ConstantSource(FIELD))
    sensor = QMC5883L(emu, settings=QMC5883LSettings(range_gauss=range_gauss, rate_hz=50, oversampling=256), **NO_SLEEP)
    assert emu.regs[0x09] == (0b01 << 6) | ((0 if range_gauss == 2 else 1) << 4) | (0b01 << 2) | 0b01
    reading = sensor.read()
    assert np.array_equal(reading.raw, np.round(FIELD / 100 * lsb))
    assert int.from_bytes(emu.regs[0:2], "little", signed=True) == round(FIELD[0] / 100 * lsb)
    assert np.allclose(reading.mag_ut, FIELD, atol=100 / lsb)


def test_qmc5883l_overflow_and_identity():
    sensor = QMC5883L(
        QMC5883LEmulator(ConstantSource((350.0, 0, 0))), settings=QMC5883LSettings(range_gauss=2), **NO_SLEEP
    )
    reading = sensor.read()
    assert reading.overflow and reading.mag_ut is None
    emu = QMC5883LEmulator()
    emu.regs[0x0D] = 0x00
    with pytest.raises(SensorError, match=r"no QMC5883L at 0x0d.*expected 0xff"):
        QMC5883L(emu, **NO_SLEEP)


def test_qmc5883l_data_ready_and_overrun_with_a_clock():
    now = [0.0]
    emu = QMC5883LEmulator(ConstantSource(FIELD), clock=lambda: now[0])
    sensor = QMC5883L(emu, settings=QMC5883LSettings(rate_hz=10), **NO_SLEEP)
    assert not sensor.read().ready
    now[0] = 0.25  # two samples arrived, the first unread: overrun
    assert emu.read_byte_data(0x0D, 0x06) & 0x05 == 0x05
    assert sensor.read().ok
    assert emu.regs[0x06] & 0x05 == 0


@pytest.mark.parametrize("gain,lsb", [(1, (1055, 1055, 950)), (4, (430, 430, 385)), (7, (230, 230, 205))])
def test_lsm303dlh_both_halves(gain, lsb):
    bus = emulator_for("lsm303dlh", ConstantSource(FIELD, ACC))
    sensor = LSM303DLH(bus, gain=gain, **NO_SLEEP)
    first = sensor.read()
    assert first.ready == (gain == 1)  # after a gain change the first measurement is dropped
    reading = sensor.read()
    assert np.array_equal(reading.raw, np.round(FIELD / 100 * np.array(lsb)))  # X, Y, Z order, z own gain
    assert np.allclose(reading.mag_ut, FIELD, atol=100 / 205)
    assert np.allclose(reading.acc_ms2, ACC, atol=0.01)


def test_lsm303dlh_accelerometer_needs_the_auto_increment_bit():
    bus = emulator_for("lsm303dlh", ConstantSource(FIELD, ACC))
    LSM303DLH(bus, **NO_SLEEP)
    bus.read_byte_data(0x18, 0x27)
    repeated = bus.read_i2c_block_data(0x18, 0x28, 6)
    assert repeated == [repeated[0]] * 6  # without bit 7 the chip repeats one register


def test_ak09918c_bma456_pair():
    sensor = open_sensor("ak09918c+bma456", emulator_for("ak09918c+bma456", ConstantSource(FIELD, ACC)), **NO_SLEEP)
    reading = sensor.read()
    assert np.array_equal(reading.raw, np.round(FIELD / 0.15))
    assert np.allclose(reading.mag_ut, FIELD, atol=0.075)
    assert np.allclose(reading.acc_ms2, ACC, atol=9.81 / 4096)


def test_ak09918c_overflow_and_identity():
    sensor = AK09918C(AK09918CEmulator(ConstantSource((3000.0, 2000.0, 0.0))), **NO_SLEEP)
    assert sensor.read().overflow
    emu = AK09918CEmulator()
    emu.regs[0x01] = 0x09  # an AK09916 answers 0x09
    with pytest.raises(SensorError, match=r"no AK09918C.*0x48/0x0c"):
        AK09918C(emu, **NO_SLEEP)


def test_ak09918c_data_protection_and_overrun():
    now = [0.0]
    emu = AK09918CEmulator(ConstantSource(FIELD), clock=lambda: now[0])
    sensor = AK09918C(emu, **NO_SLEEP)  # 100 Hz
    assert not sensor.read().ready
    now[0] = 0.025  # two samples: the first skipped
    assert emu.read_byte_data(0x0C, 0x10) == 0x03  # DRDY | DOR
    assert sensor.read().ok
    assert emu.regs[0x10] == 0  # ST2 read ended it


@pytest.mark.parametrize("range_g,lsb", [(2, 16384), (4, 8192), (8, 4096), (16, 2048)])
def test_bma456_ranges(range_g, lsb):
    emu = BMA456Emulator(ConstantSource(FIELD, ACC))
    sensor = BMA456(emu, range_g=range_g, **NO_SLEEP)
    assert emu.regs[0x7D] & 0x04 and emu.regs[0x41] == {2: 0, 4: 1, 8: 2, 16: 3}[range_g]
    assert np.allclose(sensor.read().acc_ms2, ACC, atol=9.80665 / lsb)


def test_bma456_identity():
    emu = BMA456Emulator()
    emu.regs[0x00] = 0x11  # a BMA423-like id
    with pytest.raises(SensorError, match=r"no BMA456.*0x16"):
        BMA456(emu, **NO_SLEEP)


@pytest.mark.parametrize("name", ["hmc5883l", "qmc5883l", "lsm303dlh", "ak09918c+bma456"])
def test_every_emulated_bus_is_an_i2c_bus(name):
    assert isinstance(emulator_for(name, ConstantSource(FIELD, ACC)), I2CBus)
    assert not isinstance(object(), I2CBus)


def test_smbus2_is_an_i2c_bus():
    assert isinstance(smbus2.SMBus(), I2CBus)  # not opened: no /dev/i2c-N needed


def test_missing_chip_is_a_clear_error_after_retries():
    with pytest.raises(SensorError, match="0x0c failed after 4 attempt"):
        AK09918C(EmulatedBus(BMA456Emulator()), **NO_SLEEP)


def test_bus_level_faults_are_retried_for_a_pair():
    faults = FaultInjector(probability=0.3, errnos=(errno.EIO, errno.EBUSY), seed=3)
    bus = emulator_for("ak09918c+bma456", ConstantSource(FIELD, ACC))
    bus.faults = faults
    sensor = open_sensor("ak09918c+bma456", bus, **NO_SLEEP)
    readings, failed = [], 0
    for _ in range(50):
        try:
            readings.append(sensor.read())
        except SensorReadError:
            failed += 1
    assert faults.injected > 10
    assert sum(r.ok for r in readings) >= 45
    healths = (sensor.magnetometer.health, sensor.accelerometer.health)
    assert sum(h.errors for h in healths) == faults.injected  # every injected fault seen and counted
    assert sum(h.retries for h in healths) >= faults.injected - 2 * failed * 4


def test_open_sensor_unknown_name():
    with pytest.raises(ValueError, match=r"unknown sensor 'hmc5983'.*hmc5883l"):
        open_sensor("hmc5983", None)


def test_hmc1043_replay_volts_and_counts():
    settings = BridgeSettings(
        supply_v=3.0,
        sensitivity_mv_per_v_per_gauss=1.0,
        amplifier_gain=100.0,
        adc_bits=16,
        vref_v=3.3,
        zero_counts=32768,
    )
    volts = HMC1043.from_csv(["vx,vy,vz", "0.06,-0.03,0.15"], settings=settings)
    assert np.allclose(volts.read().mag_ut, [20.0, -10.0, 50.0])  # 0.3 V per gauss after the amplifier
    assert not volts.read().ready  # exhausted
    counts = HMC1043.from_csv(["cx,cy,cz", f"{32768 + 0.06 / 3.3 * 65536},32768,32768"], settings=settings)
    assert np.allclose(counts.read().mag_ut, [20.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="vx,vy,vz"):
        HMC1043.from_csv(["a,b,c", "1,2,3"])

"""HMC5883L driver against its register-level emulator."""

import errno

import numpy as np
import pytest

from magnet.drivers.base import SensorError, SensorReadError
from magnet.drivers.hmc5883l import HMC5883L, HMC5883LSettings, Mode
from magnet.emulators.base import ConstantSource, FaultInjector
from magnet.emulators.hmc5883l import HMC5883LEmulator
from magnet.retry import RetryPolicy

LSB = (1370, 1090, 820, 660, 440, 390, 330, 230)
NO_SLEEP = dict(sleep=lambda s: None)


def read_ready(sensor, polls=5):
    for _ in range(polls):
        reading = sensor.read()
        if reading.ready:
            return reading
    return reading


def test_configuration_reaches_the_registers():
    emu = HMC5883LEmulator(ConstantSource())
    HMC5883L(emu, settings=HMC5883LSettings(averaging=4, rate_hz=30.0, gain=3, mode=Mode.CONTINUOUS), **NO_SLEEP)
    assert emu.regs[0x00] == (0b10 << 5) | (0b101 << 2)
    assert emu.regs[0x01] == 3 << 5
    assert emu.regs[0x02] == 0


@pytest.mark.parametrize("gain", range(8))
def test_scaling_for_every_gain(gain):
    field = np.array([25.0, -12.0, 40.0])
    sensor = HMC5883L(HMC5883LEmulator(ConstantSource(field)), settings=HMC5883LSettings(gain=gain), **NO_SLEEP)
    reading = read_ready(sensor)
    assert reading.ok
    # quantisation: half a count at this gain
    assert np.allclose(reading.mag_ut, field, atol=100.0 / LSB[gain] / 2 + 1e-9)
    assert np.array_equal(reading.raw, np.round(field / 100 * LSB[gain]).astype(int))


def test_axis_order_and_signs_x_z_y_registers():
    emu = HMC5883LEmulator(ConstantSource((10.0, -20.0, 30.0)))
    sensor = HMC5883L(emu, **NO_SLEEP)
    reading = sensor.read()
    x, z, y = (int.from_bytes(emu.regs[r : r + 2], "big", signed=True) for r in (0x03, 0x05, 0x07))
    assert (x, y, z) == (109, -218, 327)
    assert np.allclose(reading.mag_ut, [10.0, -20.0, 30.0], atol=0.05)


def test_orientation_maps_the_mounting():
    sensor = HMC5883L(HMC5883LEmulator(ConstantSource((10.0, -20.0, 30.0))), orientation="roll180", **NO_SLEEP)
    assert np.allclose(sensor.read().mag_ut, [10.0, 20.0, -30.0], atol=0.05)


def test_overflow_is_flagged_never_a_field():
    emu = HMC5883LEmulator(ConstantSource((200.0, 0.0, 0.0)))  # 2 Ga beyond +-1.3 Ga at GN=1
    sensor = HMC5883L(emu, **NO_SLEEP)
    reading = sensor.read()
    assert reading.overflow and reading.mag_ut is None and not reading.ok
    assert reading.raw[0] == -4096
    sensor.configure(HMC5883LSettings(gain=7))
    assert not sensor.read().ready  # the driver drops the first measurement, still at the old gain
    assert sensor.read().ok


def test_single_mode_and_data_ready():
    now = [0.0]
    emu = HMC5883LEmulator(ConstantSource(), clock=lambda: now[0])
    sensor = HMC5883L(emu, settings=HMC5883LSettings(mode=Mode.SINGLE), **NO_SLEEP)
    assert not sensor.read().ready  # measurement takes ~6 ms
    now[0] += 0.01
    assert sensor.read().ok
    assert not sensor.read().ready  # the read triggered the next one; not done yet
    now[0] += 0.01
    assert sensor.read().ok
    assert emu.measurements == 2


def test_continuous_mode_paced_by_the_output_rate():
    now = [0.0]
    emu = HMC5883LEmulator(ConstantSource(), clock=lambda: now[0])
    sensor = HMC5883L(emu, settings=HMC5883LSettings(rate_hz=15.0), **NO_SLEEP)
    assert not sensor.read().ready
    now[0] += 1 / 15 + 1e-6
    assert sensor.read().ok
    assert not sensor.read().ready


@pytest.mark.parametrize("identity", [b"QMC", b"\xff\xff\xff"])
def test_identity_mismatch_refused_clearly(identity):
    emu = HMC5883LEmulator()
    emu.regs[0x0A:0x0D] = identity
    with pytest.raises(SensorError, match=r"no HMC5883L at 0x1e.*expected b'H43'"):
        HMC5883L(emu, **NO_SLEEP)


@pytest.mark.parametrize("code", [errno.EIO, errno.EREMOTEIO, errno.EBUSY, errno.ETIMEDOUT])
def test_transient_errors_are_retried_and_counted(code):
    faults = FaultInjector()
    emu = HMC5883LEmulator(ConstantSource(), faults=faults)
    delays = []
    sensor = HMC5883L(emu, sleep=delays.append)
    faults.schedule = {faults.transactions: code, faults.transactions + 1: code}
    reading = sensor.read()
    assert reading.ok
    assert sensor.health.retries == 2 and sensor.health.errors_by_cause == {errno.errorcode[code]: 2}
    assert delays == [0.002, 0.004]  # bounded exponential backoff, injected sleep


def test_persistent_failure_raises_after_the_retries_flags_health_then_recovers():
    faults = FaultInjector()
    sensor = HMC5883L(HMC5883LEmulator(ConstantSource(), faults=faults), retry=RetryPolicy(give_up_after=3), **NO_SLEEP)
    faults.probability = 1.0  # a dead bus: every transfer fails with EIO
    for _ in range(3):
        before = faults.injected
        with pytest.raises(SensorReadError, match="HMC5883L read failed") as raised:
            sensor.read()
        assert isinstance(raised.value, OSError) and raised.value.errno == errno.EIO
        assert faults.injected - before == 3  # the driver's 3 attempts, then the error
    assert not sensor.health.healthy and sensor.health.errors == 9 and sensor.health.retries == 6
    faults.probability = 0.0
    assert sensor.read().ok and sensor.health.healthy


def test_non_transient_error_is_not_retried():
    sensor = HMC5883L(HMC5883LEmulator(ConstantSource()), **NO_SLEEP)
    sensor.device.address = 0x1F  # nobody there... as EREMOTEIO (retried); ENODEV is not:
    sensor.device.bus = type(
        "Gone", (), {"read_byte_data": lambda *a: (_ for _ in ()).throw(OSError(errno.ENODEV, "No such device"))}
    )()
    with pytest.raises(SensorReadError) as raised:
        sensor.read()
    assert raised.value.errno == errno.ENODEV and sensor.health.retries == 0


def test_self_test_restores_configuration():
    emu = HMC5883LEmulator(ConstantSource())
    settings = HMC5883LSettings(averaging=2, rate_hz=7.5, gain=2)
    sensor = HMC5883L(emu, settings=settings, **NO_SLEEP)
    before = bytes(emu.regs[0:3])
    result = sensor.self_test()
    assert result.passed
    assert bytes(emu.regs[0:3]) == before and sensor.settings == settings


def test_self_test_corrects_an_emulated_gain_error():
    error = np.array([0.05, -0.03, 0.02])
    field = np.array([30.0, -10.0, 45.0])
    emu = HMC5883LEmulator(ConstantSource(field), gain_error=error)
    sensor = HMC5883L(emu, settings=HMC5883LSettings(gain=5), **NO_SLEEP)
    result = sensor.self_test()
    assert np.allclose(result.scale, 1 / (1 + error), rtol=3e-3)
    sensor.axis_scale = result.scale
    assert np.allclose(sensor.read().mag_ut, field, atol=0.3)


def test_self_test_fails_on_a_dead_axis():
    emu = HMC5883LEmulator(ConstantSource(), gain_error=(0.0, -0.6, 0.0))
    result = HMC5883L(emu, **NO_SLEEP).self_test()
    assert not result.passed and list(result.axis_passed) == [True, False, True]
    assert "axis y" in result.message

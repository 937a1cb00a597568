"""The HMC5883L emulator behaves as the datasheet says, probed through raw bus calls (no driver)."""

import errno

import pytest

from magnet.emulators.base import ConstantSource, FaultInjector
from magnet.emulators.hmc5883l import HMC5883LEmulator

A = 0x1E


def started(field=(20.0, -5.0, 40.0), **kw):
    emu = HMC5883LEmulator(ConstantSource(field), **kw)
    emu.write_byte_data(A, 0x02, 0x00)  # continuous
    return emu


def test_identity_and_power_on_registers():
    emu = HMC5883LEmulator()
    assert bytes(emu.read_i2c_block_data(A, 0x0A, 3)) == b"H43"
    assert emu.read_i2c_block_data(A, 0x00, 3) == [0x10, 0x20, 0x01]


def test_six_byte_read_wraps_the_pointer_to_x():
    emu = started()
    first = emu.read_i2c_block_data(A, 0x03, 6)
    assert emu.pointer == 0x03
    twelve = emu.read_i2c_block_data(A, 0x03, 12)
    assert twelve[:6] == twelve[6:] == first


def test_partial_read_locks_until_all_six_are_read():
    now = [0.0]
    emu = started(clock=lambda: now[0])
    now[0] = 0.1
    emu.read_i2c_block_data(A, 0x03, 2)  # X only
    assert emu.read_byte_data(A, 0x09) & 0x02  # LOCK
    emu.tap.source.mag_ut[:] = (60.0, 60.0, 60.0)
    now[0] = 0.2  # a new measurement while locked is not placed
    rest = emu.read_i2c_block_data(A, 0x05, 4)
    assert int.from_bytes(bytes(rest[2:4]), "big", signed=True) == round(-0.05 * 1090)
    assert not emu.read_byte_data(A, 0x09) & 0x02


def test_gain_scales_and_takes_effect_one_measurement_late():
    emu = started()

    def counts() -> int:
        return int.from_bytes(bytes(emu.read_i2c_block_data(A, 0x03, 6)[:2]), "big", signed=True)

    assert counts() == round(0.2 * 1090)
    emu.write_byte_data(A, 0x01, 7 << 5)
    assert counts() == round(0.2 * 1090)  # still the old gain
    assert counts() == round(0.2 * 230)


def test_overflow_saturates_to_minus_4096():
    emu = started(field=(200.0, 0.0, -200.0))  # 2 Ga: beyond 2047 counts at 1090 LSB/Ga
    data = emu.read_i2c_block_data(A, 0x03, 6)
    x, z, y = (int.from_bytes(bytes(data[i : i + 2]), "big", signed=True) for i in (0, 2, 4))
    assert (x, y, z) == (-4096, 0, -4096)


@pytest.mark.parametrize("bias,sign", [(0x01, 1), (0x02, -1)])
def test_bias_adds_its_field(bias, sign):
    emu = started(gain_error=(0.1, 0.0, 0.0))
    emu.write_byte_data(A, 0x01, 5 << 5)
    emu.read_i2c_block_data(A, 0x03, 6)
    emu.write_byte_data(A, 0x00, 0x70 | bias)
    data = emu.read_i2c_block_data(A, 0x03, 6)
    x, z, y = (int.from_bytes(bytes(data[i : i + 2]), "big", signed=True) for i in (0, 2, 4))
    assert (x, y, z) == (sign * round(1.16 * 390 * 1.1), sign * round(1.16 * 390), sign * round(1.08 * 390))


def test_temperature_changes_sensitivity():
    cold = started(temperature_c=-15.0, tempco_per_k=-0.003)
    warm = started(temperature_c=25.0, tempco_per_k=-0.003)
    c, w = (int.from_bytes(bytes(e.read_i2c_block_data(A, 0x03, 2)), "big", signed=True) for e in (cold, warm))
    assert c == round(0.2 * 1090 * 1.12) and w == round(0.2 * 1090)


def test_wrong_address_is_a_nack():
    with pytest.raises(OSError) as info:
        HMC5883LEmulator().read_byte_data(0x1F, 0x0A)
    assert info.value.errno == errno.EREMOTEIO


def test_fault_schedule_and_probability():
    faults = FaultInjector(schedule=[None, errno.EBUSY, 0, errno.ETIMEDOUT])
    emu = HMC5883LEmulator(faults=faults)
    outcomes = []
    for _ in range(5):
        try:
            emu.read_byte_data(A, 0x0A)
            outcomes.append(0)
        except OSError as exc:
            outcomes.append(exc.errno)
    assert outcomes == [0, errno.EBUSY, 0, errno.ETIMEDOUT, 0]
    random = FaultInjector(probability=0.25, seed=1)
    hits = 0
    for _ in range(2000):
        try:
            random.check()
        except OSError:
            hits += 1
    assert 420 < hits < 580 and random.injected == hits

"""The MPU-6050 driver and the simulated chip each state the register map from the datasheet
(the simulator does not import the driver's: a typo would be tested against itself). Here the
two are held to agree, name by name."""

from __future__ import annotations

from brasidas.drivers import mpu6050 as driver
from platformd.sim import mpu6050 as chip

SAME_NAMES = (
    "WHO_AM_I",
    "PWR_MGMT_1",
    "SMPLRT_DIV",
    "CONFIG",
    "GYRO_CONFIG",
    "ACCEL_CONFIG",
    "FIFO_EN",
    "INT_ENABLE",
    "INT_STATUS",
    "DATA_START",
    "DATA_LENGTH",
    "USER_CTRL",
    "FIFO_COUNTH",
    "FIFO_R_W",
    "USER_FIFO_EN",
    "USER_FIFO_RESET",
    "FIFO_SIZE",
)


def test_registers_and_bits_named_alike_have_the_same_values() -> None:
    for name in SAME_NAMES:
        assert getattr(driver, name) == getattr(chip, name), name


def test_the_drivers_other_constants_are_the_chips() -> None:
    assert driver.FIFO_OFLOW == chip.FIFO_OFLOW_INT
    gyro_xyz = chip.GYRO_FIFO_EN[0] | chip.GYRO_FIFO_EN[1] | chip.GYRO_FIFO_EN[2]
    assert driver.FIFO_ACCEL_GYRO == chip.ACCEL_FIFO_EN | gyro_xyz
    assert driver.FIFO_SAMPLE == 12  # accel X/Y/Z and gyro X/Y/Z, 16 bits each
    assert driver.TEMP_OUT == chip.DATA_START + 6  # after accel X/Y/Z
    assert driver.FIFO_SIZE % driver.FIFO_SAMPLE != 0  # an overflow breaks record alignment


def test_the_simulated_chip_answers_the_identity_the_driver_expects() -> None:
    simulated = chip.Mpu6050(lambda at: chip.Motion((0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 25.0))
    bus = chip.EmulatedI2CBus({0x68: simulated})
    assert bus.read_byte_data(0x68, driver.WHO_AM_I) == driver.EXPECTED_WHO_AM_I


def test_every_register_constant_of_the_driver_is_checked_here() -> None:
    checked = {*SAME_NAMES, "FIFO_OFLOW", "FIFO_ACCEL_GYRO", "FIFO_SAMPLE", "TEMP_OUT"}
    # Values the driver writes or chooses, not the chip's map (the driver's tests cover them).
    settings = {"EXPECTED_WHO_AM_I", "CLOCK_PLL_X_GYRO", "DLPF_44_HZ", "FIFO_CHUNK"}
    constants = {
        name
        for name, value in vars(driver).items()
        if name.isupper() and type(value) is int and not name.startswith("_")
    }
    assert constants - checked - settings == set(), "a new register: check it against the chip"

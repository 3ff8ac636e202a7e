"""Emulated InvenSense MPU-6050 behind an smbus2-compatible bus, fed by the simulated vehicle.

The register map follows hardware.md: WHO_AM_I (0x75) reads 0x68; every register resets to 0
except PWR_MGMT_1 (0x6B) = 0x40, so the chip starts asleep and its data registers read zeros
until it is woken; bit 7 of PWR_MGMT_1 resets it. GYRO_CONFIG FS_SEL and ACCEL_CONFIG AFS_SEL
choose the scales; the 14 data bytes from 0x3B are accel X/Y/Z, temperature and gyro X/Y/Z,
big-endian signed 16-bit, temperature °C = raw / 340 + 36.53. Data registers latch a new
sample from the motion source whenever they are read while the chip is awake.

:class:`EmulatedI2CBus` answers like ``smbus2.SMBus``: an address with no device raises
``OSError(EREMOTEIO)`` as the kernel does on a NACK. In --sim the module puts a bus factory in
``ctx.sim["i2c_bus"]``; the real driver (platformd.imu) uses it instead of ``smbus2.SMBus``.
"""

from __future__ import annotations

import errno
import math
import random
import struct
from collections.abc import Callable
from dataclasses import dataclass

from platformd.context import PlatformContext
from platformd.sim.vehicle import GRAVITY, VehicleModel, shared_vehicle

WHO_AM_I = 0x75
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
DATA_START = 0x3B
DATA_LENGTH = 14
SLEEP = 0x40
DEVICE_RESET = 0x80
I2C_BLOCK_MAX = 32
"""SMBus block transfers carry at most 32 bytes."""


@dataclass(frozen=True)
class Motion:
    """What the chip senses, in its own axes (x forward, y left, z up)."""

    accel_mps2: tuple[float, float, float]
    """Specific force: a chip lying still and level reads (0, 0, +g)."""
    gyro_rad_s: tuple[float, float, float]
    temperature_c: float = 30.0


MotionSource = Callable[[], Motion]


class Mpu6050:
    """The chip's registers; reads of the data registers sample ``source`` when awake."""

    def __init__(self, source: MotionSource, who_am_i: int = 0x68) -> None:
        self.source = source
        self.who_am_i = who_am_i
        self.registers = bytearray(128)
        self.reset()

    def reset(self) -> None:
        self.registers[:] = bytes(128)
        self.registers[PWR_MGMT_1] = SLEEP
        self.registers[WHO_AM_I] = self.who_am_i

    @property
    def asleep(self) -> bool:
        return bool(self.registers[PWR_MGMT_1] & SLEEP)

    def write(self, register: int, value: int) -> None:
        register &= 0x7F
        value &= 0xFF
        if register == PWR_MGMT_1 and value & DEVICE_RESET:
            self.reset()
            return
        if register == WHO_AM_I or DATA_START <= register < DATA_START + DATA_LENGTH:
            return  # read-only
        self.registers[register] = value

    def read(self, register: int, length: int = 1) -> list[int]:
        register &= 0x7F
        if (
            not self.asleep
            and register < DATA_START + DATA_LENGTH
            and register + length > DATA_START
        ):
            self._latch()
        # Past the last register the emulation reads zeros.
        return list(self.registers[register : register + length].ljust(length, b"\x00"))

    def _latch(self) -> None:
        # Runs at the sampling rate in the driver's thread: kept to one pack and few calls.
        motion = self.source()
        accel = (16384 >> ((self.registers[ACCEL_CONFIG] >> 3) & 0x3)) / GRAVITY
        gyro = 131.0 / (1 << ((self.registers[GYRO_CONFIG] >> 3) & 0x3)) * _DEG_PER_RAD
        ax, ay, az = motion.accel_mps2
        gx, gy, gz = motion.gyro_rad_s
        _PACK_DATA(
            self.registers,
            DATA_START,
            _int16(ax * accel),
            _int16(ay * accel),
            _int16(az * accel),
            _int16((motion.temperature_c - 36.53) * 340.0),
            _int16(gx * gyro),
            _int16(gy * gyro),
            _int16(gz * gyro),
        )


class EmulatedI2CBus:
    """The subset of ``smbus2.SMBus`` the IMU driver uses, with devices by address."""

    def __init__(self, devices: dict[int, Mpu6050]) -> None:
        self.devices = devices
        self.closed = False

    def _device(self, address: int) -> Mpu6050:
        if self.closed:
            raise OSError(errno.EBADF, "I2C bus closed")
        device = self.devices.get(address)
        if device is None:
            raise OSError(errno.EREMOTEIO, "Remote I/O error")
        return device

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        return self._device(i2c_addr).read(register)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        self._device(i2c_addr).write(register, value)

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]:
        if not 0 < length <= I2C_BLOCK_MAX:
            raise ValueError(f"block read of {length} bytes (1-{I2C_BLOCK_MAX})")
        return self._device(i2c_addr).read(register, length)

    def close(self) -> None:
        self.closed = True


def vehicle_motion(
    vehicle: VehicleModel, *, rng: random.Random | None = None, noise: bool = True
) -> MotionSource:
    """The chip mounted level, x forward: forward/lateral acceleration plus gravity, yaw rate.

    Noise about the MPU-6050's datasheet density at a 44 Hz bandwidth (gyro ~0.03 °/s rms is
    too optimistic for a vibrating rover; 0.05 °/s and 0.004 g are used), and a gyro offset.
    """
    random_ = rng or random.Random()
    gyro_sigma = math.radians(0.05) if noise else 0.0
    accel_sigma = 0.004 * GRAVITY if noise else 0.0
    # Each chip has its own zero-rate offset (datasheet: up to ±20 °/s; ~1 °/s typical).
    bx, by, bz = (math.radians(random_.uniform(-1.0, 1.0)) if noise else 0.0 for _ in range(3))

    def sense() -> Motion:
        pose = vehicle.pose()
        return Motion(
            accel_mps2=(
                pose.accel_mps2 + random_.gauss(0.0, accel_sigma),
                pose.lateral_accel_mps2 + random_.gauss(0.0, accel_sigma),
                GRAVITY + random_.gauss(0.0, accel_sigma),
            ),
            gyro_rad_s=(
                bx + random_.gauss(0.0, gyro_sigma),
                by + random_.gauss(0.0, gyro_sigma),
                bz + pose.yaw_rate_rad_s + random_.gauss(0.0, gyro_sigma),
            ),
            temperature_c=31.0 + random_.gauss(0.0, 0.05),
        )

    return sense


_PACK_DATA = struct.Struct(">7h").pack_into
_DEG_PER_RAD = 180.0 / math.pi


def _int16(value: float) -> int:
    if value >= 32767.0:
        return 32767
    if value <= -32768.0:
        return -32768
    return round(value)


async def async_setup(ctx: PlatformContext) -> None:
    if not (ctx.config.sim.enabled and ctx.config.imu.enabled):
        return
    chip = Mpu6050(vehicle_motion(shared_vehicle(ctx)))
    address = ctx.config.imu.address
    ctx.sim["mpu6050"] = chip
    # One chip on the configured address; another bus number has nothing on it.
    ctx.sim["i2c_bus"] = lambda bus_number: EmulatedI2CBus(
        {address: chip} if bus_number == ctx.config.imu.i2c_bus else {}
    )

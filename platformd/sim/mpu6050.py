"""Emulated InvenSense MPU-6050 behind an smbus2-compatible bus, fed by the simulated vehicle.

The register map follows hardware.md: WHO_AM_I (0x75) reads 0x68; every register resets to 0
except PWR_MGMT_1 (0x6B) = 0x40, so the chip starts asleep and its data registers read zeros
until it is woken; bit 7 of PWR_MGMT_1 resets it. GYRO_CONFIG FS_SEL and ACCEL_CONFIG AFS_SEL
choose the scales; the 14 data bytes from 0x3B are accel X/Y/Z, temperature and gyro X/Y/Z,
big-endian signed 16-bit, temperature °C = raw / 340 + 36.53. Data registers latch a new
sample from the motion source whenever they are read while the chip is awake.

The FIFO follows the register map: USER_CTRL (0x6A) bit 6 enables it, bit 2 resets it (only
when the same write leaves bit 6 clear, as documented; the bit reads back 0); FIFO_EN (0x23)
picks what each sample pushes, in register order (temperature, gyro X/Y/Z, accel: 0x78 is
accel + gyro, 12 bytes). While the chip is awake and the FIFO enabled, one record enters at
every tick of the sample rate, gyro output rate / (1 + SMPLRT_DIV), the gyro output rate being
8 kHz with DLPF_CFG 0 or 7 and 1 kHz otherwise. FIFO_COUNTH/L (0x72/0x73) give the byte count,
big-endian; reads of FIFO_R_W (0x74) pop bytes (a burst stays on the register, it does not
auto-increment), and an empty FIFO reads back the last byte popped. Ticks are generated lazily
from the elapsed time on the chip's clock whenever a register is read or written, each record
from the motion source at its own tick time (no timer thread). Overflow: the 1024-byte buffer
keeps the newest bytes and drops the oldest, byte by byte, as the MPU-6050 does; 1024 is not a
multiple of 12, so what remains no longer starts on a record boundary and the driver must
reset. An overflow sets INT_STATUS (0x3A) bit 4 FIFO_OFLOW_INT when INT_ENABLE (0x38) bit 4
asks for that interrupt (this emulation's reading of "when an interrupt has been generated");
reading INT_STATUS clears it.

:class:`EmulatedI2CBus` answers like ``smbus2.SMBus``: an address with no device raises
``OSError(EREMOTEIO)`` as the kernel does on a NACK. In --sim the module puts a bus factory in
``ctx.sim.i2c_bus``; the actor (platformd.imu) uses it instead of ``smbus2.SMBus``.

The register constants below repeat the driver's on purpose: the chip is written from the
datasheet on its own, so a wrong address or bit in the driver fails against it, as it would
against the real chip, instead of being shared by both sides.
"""

from __future__ import annotations

import errno
import math
import random
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from brasidas.config import ImuSection
from platformd.sim.vehicle import GRAVITY, VehicleModel

if TYPE_CHECKING:
    from brasidas.drivers.mpu6050 import BusFactory

WHO_AM_I = 0x75
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
FIFO_EN = 0x23
INT_ENABLE = 0x38
INT_STATUS = 0x3A
DATA_START = 0x3B
DATA_LENGTH = 14
USER_CTRL = 0x6A
FIFO_COUNTH = 0x72
FIFO_COUNTL = 0x73
FIFO_R_W = 0x74
SLEEP = 0x40
DEVICE_RESET = 0x80
USER_FIFO_EN = 0x40
USER_FIFO_RESET = 0x04
FIFO_OFLOW_INT = 0x10
"""INT_STATUS and INT_ENABLE bit 4: FIFO overflow."""
FIFO_SIZE = 1024
TEMP_FIFO_EN = 0x80
ACCEL_FIFO_EN = 0x08
GYRO_FIFO_EN = (0x40, 0x20, 0x10)
"""FIFO_EN bits for gyro X, Y, Z."""
I2C_BLOCK_MAX = 32
"""SMBus block transfers carry at most 32 bytes."""


@dataclass(frozen=True)
class Motion:
    """What the chip senses, in its own axes (x forward, y left, z up)."""

    accel_mps2: tuple[float, float, float]
    """Specific force: a chip lying still and level reads (0, 0, +g)."""
    gyro_rad_s: tuple[float, float, float]
    temperature_c: float = 30.0


MotionSource = Callable[[float], Motion]
"""What the chip senses at a time of its clock (sample times only increase between resets)."""


class Mpu6050:
    """The chip's registers and FIFO; reads of the data registers sample ``source`` when awake."""

    def __init__(
        self,
        source: MotionSource,
        who_am_i: int = 0x68,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.source = source
        self.who_am_i = who_am_i
        self.clock = clock
        self.registers = bytearray(128)
        self.fifo = bytearray()
        self.overflows = 0
        """Times the FIFO overflowed (a test hook: the chip has no such counter)."""
        self._last_popped = 0
        self._next_tick: float | None = None
        """Time of the next FIFO record, None while the FIFO does not fill."""
        self.reset()

    def reset(self) -> None:
        self.registers[:] = bytes(128)
        self.registers[PWR_MGMT_1] = SLEEP
        self.registers[WHO_AM_I] = self.who_am_i
        self.fifo.clear()
        self._last_popped = 0
        self._next_tick = None

    @property
    def asleep(self) -> bool:
        return bool(self.registers[PWR_MGMT_1] & SLEEP)

    @property
    def sample_period(self) -> float:
        """Seconds between samples: (1 + SMPLRT_DIV) / gyro output rate."""
        dlpf = self.registers[CONFIG] & 0x07
        gyro_rate = 8000.0 if dlpf in (0, 7) else 1000.0
        return (1 + self.registers[SMPLRT_DIV]) / gyro_rate

    @property
    def record_length(self) -> int:
        """Bytes each sample pushes into the FIFO, from FIFO_EN (external sensors not emulated)."""
        enabled = self.registers[FIFO_EN]
        length = 6 if enabled & ACCEL_FIFO_EN else 0
        length += 2 if enabled & TEMP_FIFO_EN else 0
        return length + sum(2 for bit in GYRO_FIFO_EN if enabled & bit)

    def _filling(self) -> bool:
        return (
            not self.asleep
            and bool(self.registers[USER_CTRL] & USER_FIFO_EN)
            and self.record_length > 0
        )

    def write(self, register: int, value: int) -> None:
        register &= 0x7F
        value &= 0xFF
        self._catch_up()  # the samples due so far were taken with the old settings
        if register == PWR_MGMT_1 and value & DEVICE_RESET:
            self.reset()
            return
        if register in (WHO_AM_I, INT_STATUS, FIFO_COUNTH, FIFO_COUNTL) or (
            DATA_START <= register < DATA_START + DATA_LENGTH
        ):
            return  # read-only
        if register == FIFO_R_W:
            if len(self.fifo) < FIFO_SIZE:
                self.fifo.append(value)
            return
        if register == USER_CTRL:
            if value & USER_FIFO_RESET and not value & USER_FIFO_EN:
                self.fifo.clear()
            value &= ~USER_FIFO_RESET  # self-clearing
        self.registers[register] = value
        self._schedule()

    def _schedule(self) -> None:
        """After a write: start, keep or stop the FIFO's tick."""
        if not self._filling():
            self._next_tick = None
        elif self._next_tick is None:
            self._next_tick = self.clock() + self.sample_period

    def read(self, register: int, length: int = 1) -> list[int]:
        register &= 0x7F
        self._catch_up()
        if register <= FIFO_R_W < register + length:
            # A burst reaching FIFO_R_W stays there: the rest of it pops the FIFO.
            head = FIFO_R_W - register
            return self._registers(register, head) + self._pop(length - head)
        if register <= INT_STATUS < register + length:
            status = self._registers(register, length)
            self.registers[INT_STATUS] = 0  # cleared by reading
            return status
        return self._registers(register, length)

    def _registers(self, register: int, length: int) -> list[int]:
        if length <= 0:
            return []
        if (
            not self.asleep
            and register < DATA_START + DATA_LENGTH
            and register + length > DATA_START
        ):
            self._latch()
        if register <= FIFO_COUNTL and register + length > FIFO_COUNTH:
            self.registers[FIFO_COUNTH : FIFO_COUNTL + 1] = len(self.fifo).to_bytes(2, "big")
        # Past the last register the emulation reads zeros.
        return list(self.registers[register : register + length].ljust(length, b"\x00"))

    def _pop(self, length: int) -> list[int]:
        taken = list(self.fifo[:length])
        del self.fifo[:length]
        if taken:
            self._last_popped = taken[-1]
        # An empty FIFO reads back the last byte popped.
        return taken + [self._last_popped] * (length - len(taken))

    def _catch_up(self) -> None:
        """Push the records of every tick that has passed since the last access."""
        if self._next_tick is None:
            return
        now = self.clock()
        if now < self._next_tick:
            return
        period = self.sample_period
        record = self.record_length
        due = int((now - self._next_tick) / period) + 1
        first = self._next_tick
        self._next_tick = first + due * period
        # Only the newest bytes survive an overflow: skip generating what would be dropped.
        keep = FIFO_SIZE // record + 1
        if due > keep:
            self.fifo.clear()
            first += (due - keep) * period
            due = keep
        for k in range(due):
            self.fifo += self._record(first + k * period)
        excess = len(self.fifo) - FIFO_SIZE
        if excess > 0:
            del self.fifo[:excess]  # the oldest bytes go, not necessarily whole records
            self._flag_overflow()

    def _flag_overflow(self) -> None:
        self.overflows += 1
        if self.registers[INT_ENABLE] & FIFO_OFLOW_INT:
            self.registers[INT_STATUS] |= FIFO_OFLOW_INT

    def _record(self, at: float) -> bytes:
        """One FIFO record: the enabled data registers, in register order, sampled at ``at``."""
        self._latch(at)
        data = self.registers[DATA_START : DATA_START + DATA_LENGTH]
        enabled = self.registers[FIFO_EN]
        if enabled & 0xF8 == ACCEL_FIFO_EN | 0x70:  # accel + gyro: the usual, kept cheap
            return bytes(data[0:6] + data[8:14])
        parts = data[0:6] if enabled & ACCEL_FIFO_EN else bytearray()
        if enabled & TEMP_FIFO_EN:
            parts += data[6:8]
        for axis, bit in enumerate(GYRO_FIFO_EN):
            if enabled & bit:
                parts += data[8 + 2 * axis : 10 + 2 * axis]
        return bytes(parts)

    def _latch(self, at: float | None = None) -> None:
        # Runs at the sampling rate in the driver's thread: kept to one pack and few calls.
        motion = self.source(self.clock() if at is None else at)
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

    # The FIFO asks for past sample times, up to ~0.1 s of them at once, and the model only
    # knows its present: the pose's rates are interpolated between the last two poses read.
    poses = [vehicle.pose()] * 2

    def sense(at: float) -> Motion:
        before, after = poses
        if at > after.time:
            before, after = poses[:] = [after, vehicle.pose()]
        span = after.time - before.time
        w = 1.0 if span <= 0 else min(1.0, max(0.0, (at - before.time) / span))
        accel = before.accel_mps2 + (after.accel_mps2 - before.accel_mps2) * w
        lateral = (
            before.lateral_accel_mps2 + (after.lateral_accel_mps2 - before.lateral_accel_mps2) * w
        )
        yaw_rate = before.yaw_rate_rad_s + (after.yaw_rate_rad_s - before.yaw_rate_rad_s) * w
        return Motion(
            accel_mps2=(
                accel + random_.gauss(0.0, accel_sigma),
                lateral + random_.gauss(0.0, accel_sigma),
                GRAVITY + random_.gauss(0.0, accel_sigma),
            ),
            gyro_rad_s=(
                bx + random_.gauss(0.0, gyro_sigma),
                by + random_.gauss(0.0, gyro_sigma),
                bz + yaw_rate + random_.gauss(0.0, gyro_sigma),
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


def emulate(config: ImuSection, vehicle: VehicleModel) -> tuple[Mpu6050, BusFactory]:
    """In ``--sim``: a chip moved by ``vehicle`` at ``imu.address``, and the factory that opens
    the I2C bus it sits on (bus ``imu.i2c_bus``; any other bus number has nothing on it)."""
    chip = Mpu6050(vehicle_motion(vehicle))
    devices: dict[int, Mpu6050] = {config.address: chip}

    def open_bus(bus_number: int) -> EmulatedI2CBus:
        return EmulatedI2CBus(devices if bus_number == config.i2c_bus else {})

    return chip, open_bus

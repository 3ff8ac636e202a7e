"""InvenSense MPU-6050 register access over an smbus2-like bus (blocking: call from a thread).

The driver wakes the chip, checks WHO_AM_I, sets the sample rate, low-pass filter and ranges,
reads the 14-byte burst from 0x3B or drains the FIFO (accel + gyro, 12 bytes a sample, in
24-byte reads: an SMBus block carries at most 32) and converts raw words to SI units.
:class:`SampleClock` rebuilds FIFO sample times from the sample rate.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

WHO_AM_I = 0x75
EXPECTED_WHO_AM_I = 0x68
PWR_MGMT_1 = 0x6B
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
FIFO_EN = 0x23
INT_ENABLE = 0x38
INT_STATUS = 0x3A
DATA_START = 0x3B
DATA_LENGTH = 14
TEMP_OUT = 0x41
USER_CTRL = 0x6A
FIFO_COUNTH = 0x72
FIFO_R_W = 0x74
FIFO_ACCEL_GYRO = 0x78
"""FIFO_EN: accel X/Y/Z and gyro X/Y/Z, 12 bytes a sample (accel first: register order)."""
FIFO_SAMPLE = 12
FIFO_SIZE = 1024
FIFO_CHUNK = 24
"""Bytes per FIFO read: two whole samples within SMBus's 32-byte block limit."""
USER_FIFO_EN = 0x40
USER_FIFO_RESET = 0x04
FIFO_OFLOW = 0x10
"""INT_STATUS / INT_ENABLE bit 4."""
CLOCK_PLL_X_GYRO = 0x01
"""PWR_MGMT_1 value: awake, clocked from the X gyro's PLL (the datasheet's advice)."""
DLPF_44_HZ = 0x03
"""CONFIG: 44 Hz accel / 42 Hz gyro bandwidth and a 1 kHz internal rate: right for 100 Hz."""
GRAVITY = 9.80665

ACCEL_RANGES = {2: 0, 4: 1, 8: 2, 16: 3}
"""Full scale in g -> AFS_SEL."""
GYRO_RANGES = {250: 0, 500: 1, 1000: 2, 2000: 3}
"""Full scale in deg/s -> FS_SEL."""


class SMBusLike(Protocol):
    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...
    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...
    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]: ...
    def close(self) -> None: ...


BusFactory = Callable[[int], SMBusLike]


class ImuError(Exception):
    """The device is not usable (wrong WHO_AM_I, bad configuration)."""


@dataclass(frozen=True)
class Sample:
    """One burst converted to SI units, with the reading's monotonic time."""

    time: float
    accel_mps2: tuple[float, float, float]
    gyro_rad_s: tuple[float, float, float]
    temperature_c: float


class Mpu6050Driver:
    """Blocking register access to one chip (call from the sampling thread or an executor)."""

    def __init__(self, bus: SMBusLike, address: int, accel_range_g: int, gyro_range_dps: int):
        if accel_range_g not in ACCEL_RANGES:
            raise ImuError(f"imu.accel_range_g must be one of {sorted(ACCEL_RANGES)}")
        if gyro_range_dps not in GYRO_RANGES:
            raise ImuError(f"imu.gyro_range_dps must be one of {sorted(GYRO_RANGES)}")
        self.bus = bus
        self.address = address
        self.accel_range_g = accel_range_g
        self.gyro_range_dps = gyro_range_dps
        self.accel_scale = GRAVITY / (16384 >> ACCEL_RANGES[accel_range_g])
        self.gyro_scale = math.radians(1.0) / (131.0 / (1 << GYRO_RANGES[gyro_range_dps]))

    def init(self, rate_hz: float) -> None:
        """Check the chip, wake it, set rate, filter and ranges."""
        who = self.bus.read_byte_data(self.address, WHO_AM_I)
        if who != EXPECTED_WHO_AM_I:
            raise ImuError(
                f"WHO_AM_I at 0x{self.address:02x} reads 0x{who:02x}, "
                f"expected 0x{EXPECTED_WHO_AM_I:02x}: not an MPU-6050"
            )
        self.bus.write_byte_data(self.address, PWR_MGMT_1, CLOCK_PLL_X_GYRO)
        self.bus.write_byte_data(self.address, CONFIG, DLPF_44_HZ)
        divider = max(0, min(255, round(1000.0 / rate_hz) - 1))
        self.sample_period = (1 + divider) / 1000.0
        """Seconds between the chip's samples (1 kHz gyro output rate with the DLPF on)."""
        self.bus.write_byte_data(self.address, SMPLRT_DIV, divider)
        self.bus.write_byte_data(self.address, GYRO_CONFIG, GYRO_RANGES[self.gyro_range_dps] << 3)
        self.bus.write_byte_data(self.address, ACCEL_CONFIG, ACCEL_RANGES[self.accel_range_g] << 3)
        if self.bus.read_byte_data(self.address, PWR_MGMT_1) & 0x40:
            raise ImuError("the MPU-6050 stays asleep after PWR_MGMT_1 = 0x01")

    def read(self) -> Sample:
        return self.convert(time.monotonic(), bytes(self.read_raw()))

    def fifo_start(self) -> None:
        """Queue accel + gyro in the FIFO from empty (also the recovery after an overflow)."""
        # FIFO_RESET only acts while FIFO_EN is clear: stop, reset, then enable.
        self.bus.write_byte_data(self.address, USER_CTRL, 0)
        self.bus.write_byte_data(self.address, FIFO_EN, FIFO_ACCEL_GYRO)
        self.bus.write_byte_data(self.address, INT_ENABLE, FIFO_OFLOW)
        self.bus.read_byte_data(self.address, INT_STATUS)  # clears a stale overflow flag
        self.bus.write_byte_data(self.address, USER_CTRL, USER_FIFO_RESET)
        self.bus.write_byte_data(self.address, USER_CTRL, USER_FIFO_EN)

    def fifo_count(self) -> tuple[int, bool]:
        """Bytes queued and whether the FIFO overflowed since the last look (blocking)."""
        overflowed = bool(self.bus.read_byte_data(self.address, INT_STATUS) & FIFO_OFLOW)
        high, low = self.bus.read_i2c_block_data(self.address, FIFO_COUNTH, 2)
        return (high << 8) | low, overflowed

    def fifo_read(self, samples: int) -> bytes:
        """``samples`` whole samples from FIFO_R_W, in reads of at most FIFO_CHUNK bytes."""
        data = bytearray()
        remaining = samples * FIFO_SAMPLE
        while remaining > 0:
            size = min(FIFO_CHUNK, remaining)
            data += bytes(self.bus.read_i2c_block_data(self.address, FIFO_R_W, size))
            remaining -= size
        return bytes(data)

    def read_temperature(self) -> float:
        high, low = self.bus.read_i2c_block_data(self.address, TEMP_OUT, 2)
        (raw,) = _TEMP.unpack(bytes((high, low)))
        return float(raw) / 340.0 + 36.53

    def convert_fifo(self, start: float, data: bytes, temperature_c: float) -> list[Sample]:
        """FIFO samples (12 bytes each) timed ``start``, ``start`` + period, ..."""
        a, g, period = self.accel_scale, self.gyro_scale, self.sample_period
        return [
            Sample(
                time=start + k * period,
                accel_mps2=(ax * a, ay * a, az * a),
                gyro_rad_s=(gx * g, gy * g, gz * g),
                temperature_c=temperature_c,
            )
            for k, (ax, ay, az, gx, gy, gz) in enumerate(_FIFO_SAMPLE.iter_unpack(data))
        ]

    def read_raw(self) -> list[int]:
        """The 14 data bytes (blocking I2C transfer)."""
        return self.bus.read_i2c_block_data(self.address, DATA_START, DATA_LENGTH)

    def convert(self, when: float, raw: bytes) -> Sample:
        ax, ay, az, temp, gx, gy, gz = struct.unpack(">7h", raw)
        a, g = self.accel_scale, self.gyro_scale
        return Sample(
            time=when,
            accel_mps2=(ax * a, ay * a, az * a),
            gyro_rad_s=(gx * g, gy * g, gz * g),
            temperature_c=temp / 340.0 + 36.53,
        )


_FIFO_SAMPLE = struct.Struct(">6h")
_TEMP = struct.Struct(">h")


def fifo_overflowed(count: int, flagged: bool) -> bool:
    """A FIFO to reset: flagged, full (it then overwrites its oldest bytes), or misaligned."""
    return flagged or count >= FIFO_SIZE or count % FIFO_SAMPLE != 0


class SampleClock:
    """Times for FIFO samples: evenly spaced at the nominal period, kept near the host clock.

    The last sample counted at a FIFO_COUNT read was taken at most one period before it. The
    chip's oscillator is off by up to a few per cent, so a run of nominal periods drifts from
    the host's clock; when the rebuilt time of the newest sample leaves that one-period window
    it is moved to its edge (a step of a fraction of a millisecond a batch).
    """

    def __init__(self, period: float) -> None:
        self.period = period
        self.next: float | None = None

    def reset(self) -> None:
        self.next = None

    def place(self, samples: int, counted_at: float) -> float:
        """Time of the first of ``samples`` samples counted at ``counted_at``."""
        if self.next is None:
            start = counted_at - (samples - 1) * self.period
        else:
            start = self.next
            newest = start + (samples - 1) * self.period
            if newest > counted_at:
                start -= newest - counted_at
            elif newest < counted_at - self.period:
                start += counted_at - self.period - newest
        self.next = start + samples * self.period
        return start

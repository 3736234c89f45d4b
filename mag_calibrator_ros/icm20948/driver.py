"""AK09916 magnetometer inside an ICM-20948, read over an injected smbus2-like bus (no rclpy).

The bus is anything with the smbus2.SMBus methods used here (``read_byte_data``,
``write_byte_data``, ``read_i2c_block_data``): a real ``smbus2.SMBus`` on a robot, or
``SimulatedIcm20948Bus`` in tests and the demo. I2C failures surface as ``OSError`` so callers
can back off and re-initialise; identity problems raise errors that name bus, address, expected
and found values.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import time
from typing import Protocol

import numpy as np

from mag_calibrator_ros.icm20948 import registers as reg

INIT_TRANSACTION_ATTEMPTS = 3  # per register access during bring-up


class SmbusLike(Protocol):
    """The subset of ``smbus2.SMBus`` the driver relies on."""

    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]: ...


class DeviceNotFoundError(OSError):
    """Nothing answered at the expected I2C address."""


class WrongDeviceError(ValueError):
    """Something answered, but its identity register holds the wrong value."""


class ModeNotAcceptedError(OSError):
    """The AK09916 did not take the requested measurement mode (read back differs)."""


@dataclass(frozen=True)
class MagReading:
    """One valid AK09916 sample.

    ``field_tesla``: field in the ICM-20948 accel/gyro frame (x, -y, -z of the AK09916), tesla.
    ``counts``: the raw AK09916 counts in the magnetometer's own axes, as read.
    ``overrun``: ST1 DOR was set, i.e. at least one sample was skipped before this one.
    """

    field_tesla: np.ndarray
    counts: np.ndarray
    overrun: bool


def counts_to_tesla(counts: np.ndarray) -> np.ndarray:
    """AK09916 counts (its own axes) -> tesla in the accel/gyro chip frame."""
    return np.asarray(counts, dtype=float) * np.asarray(reg.AXIS_SIGNS) * reg.TESLA_PER_LSB


def tesla_to_counts(field_tesla: np.ndarray) -> np.ndarray:
    """Inverse of ``counts_to_tesla`` (rounded to whole counts)."""
    chip = np.asarray(field_tesla, dtype=float) / reg.TESLA_PER_LSB
    return np.rint(chip * np.asarray(reg.AXIS_SIGNS)).astype(np.int64)


class Icm20948Magnetometer:
    """Brings up the AK09916 behind an ICM-20948 in bypass mode and reads it on data-ready.

    Counters: ``overruns`` (ST1 DOR: samples skipped because we read too late) and ``overflows``
    (ST2 HOFL: magnetic sensor overflow, sample discarded).
    """

    def __init__(
        self,
        bus: SmbusLike,
        address: int = reg.ICM20948_DEFAULT_ADDRESS,
        bus_name: str = '/dev/i2c-1',
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if address not in reg.ICM20948_ADDRESSES:
            raise ValueError(
                f'ICM-20948 address must be 0x68 or 0x69, got {address:#04x} on {bus_name}'
            )
        self.bus = bus
        self.address = address
        self.bus_name = bus_name
        self._sleep = sleep
        self.rate_hz: int | None = None
        self.overruns = 0
        self.overflows = 0

    # --- bring-up --------------------------------------------------------------------------------

    def initialise(self, rate_hz: int = 100) -> None:
        """Reset the ICM-20948, route the AK09916 to the host bus, start continuous measurement.

        Raises ``DeviceNotFoundError`` (an OSError) when nothing answers, ``WrongDeviceError``
        (a ValueError) on a wrong identity, ``OSError`` on a bus error mid-sequence.
        """
        if rate_hz not in reg.CONTINUOUS_MODES:
            raise ValueError(
                f'AK09916 continuous rate must be one of {sorted(reg.CONTINUOUS_MODES)} Hz, '
                f'got {rate_hz}'
            )
        self._check_icm20948_identity()
        self._write_icm(reg.PWR_MGMT_1, reg.PWR_MGMT_1_DEVICE_RESET)
        self._sleep(reg.DEVICE_RESET_WAIT_S)
        self._select_bank(0)  # reset returns to bank 0; be explicit
        self._write_icm(reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO)  # wake, auto clock
        self._sleep(reg.WAKE_WAIT_S)
        user_ctrl = self._retry(self.bus.read_byte_data, self.address, reg.USER_CTRL)
        self._write_icm(reg.USER_CTRL, user_ctrl & ~reg.USER_CTRL_I2C_MST_EN & 0xFF)
        pin_cfg = self._retry(self.bus.read_byte_data, self.address, reg.INT_PIN_CFG)
        self._write_icm(reg.INT_PIN_CFG, pin_cfg | reg.INT_PIN_CFG_BYPASS_EN)
        self._check_ak09916_identity()
        self._write_mag(reg.CNTL3, reg.CNTL3_SRST)
        self._sleep(reg.SOFT_RESET_WAIT_S)
        self._write_mag(reg.CNTL2, reg.MODE_POWER_DOWN)
        self._sleep(reg.MODE_CHANGE_WAIT_S)
        mode = reg.CONTINUOUS_MODES[rate_hz]
        self._write_mag(reg.CNTL2, mode)
        found = self._retry(self.bus.read_byte_data, reg.AK09916_ADDRESS, reg.CNTL2)
        if found != mode:
            raise ModeNotAcceptedError(
                f'AK09916 at {reg.AK09916_ADDRESS:#04x} on {self.bus_name} did not accept '
                f'continuous mode {rate_hz} Hz: CNTL2 expected {mode:#04x}, found {found:#04x}'
            )
        self.rate_hz = rate_hz

    def measurement_mode(self) -> int:
        """CNTL2 as the AK09916 reports it now (0 after a reset: the chip stopped measuring)."""
        return self.bus.read_byte_data(reg.AK09916_ADDRESS, reg.CNTL2)

    def _retry(self, operation: Callable, *args: int) -> int | list[int] | None:
        """Bring-up transactions are idempotent: retry a transient bus error a few times so one
        glitch does not cost a whole re-initialisation; the last error propagates."""
        for attempt in range(INIT_TRANSACTION_ATTEMPTS):
            try:
                return operation(*args)
            except OSError:
                if attempt == INIT_TRANSACTION_ATTEMPTS - 1:
                    raise
                self._sleep(reg.MODE_CHANGE_WAIT_S)
        return None  # unreachable

    def _select_bank(self, bank: int) -> None:
        self._retry(
            self.bus.write_byte_data, self.address, reg.REG_BANK_SEL, bank << reg.BANK_SHIFT
        )

    def _write_icm(self, register: int, value: int) -> None:
        self._retry(self.bus.write_byte_data, self.address, register, value)

    def _write_mag(self, register: int, value: int) -> None:
        self._retry(self.bus.write_byte_data, reg.AK09916_ADDRESS, register, value)

    def _check_icm20948_identity(self) -> None:
        try:
            self._select_bank(0)
            found = self._retry(self.bus.read_byte_data, self.address, reg.WHO_AM_I)
        except OSError as error:
            raise DeviceNotFoundError(
                error.errno,
                f'no ICM-20948 answered at {self.address:#04x} on {self.bus_name} '
                f'(expected WHO_AM_I {reg.WHO_AM_I_VALUE:#04x}; bus error: {error}); check '
                f'wiring, power and the address (0x68 when AD0 is low, 0x69 when high)',
            ) from error
        if found != reg.WHO_AM_I_VALUE:
            raise WrongDeviceError(
                f'device at {self.address:#04x} on {self.bus_name} is not an ICM-20948: '
                f'WHO_AM_I expected {reg.WHO_AM_I_VALUE:#04x}, found {found:#04x}'
            )

    def _check_ak09916_identity(self) -> None:
        try:
            found = self._retry(self.bus.read_i2c_block_data, reg.AK09916_ADDRESS, reg.WIA1, 2)
        except OSError as error:
            raise DeviceNotFoundError(
                error.errno,
                f'AK09916 magnetometer did not answer at {reg.AK09916_ADDRESS:#04x} on '
                f'{self.bus_name} with I2C bypass enabled on the ICM-20948 at {self.address:#04x} '
                f'(expected WIA1/WIA2 {reg.WIA1_VALUE:#04x}/{reg.WIA2_VALUE:#04x}; bus error: '
                f'{error})',
            ) from error
        expected = [reg.WIA1_VALUE, reg.WIA2_VALUE]
        if list(found) != expected:
            raise WrongDeviceError(
                f'device at {reg.AK09916_ADDRESS:#04x} on {self.bus_name} (behind ICM-20948 '
                f'{self.address:#04x}) is not an AK09916: WIA1/WIA2 expected '
                f'{expected[0]:#04x}/{expected[1]:#04x}, found '
                + '/'.join(f'{value:#04x}' for value in found)
            )

    # --- reading ---------------------------------------------------------------------------------

    def read(self) -> MagReading | None:
        """One 9-byte burst ST1..ST2 (ST2 last, so the data registers never stay locked).

        Returns None when no new sample is ready or the sample overflowed (counted in
        ``overflows``). ``OSError`` from the bus propagates to the caller.
        """
        raw = self.bus.read_i2c_block_data(reg.AK09916_ADDRESS, reg.BURST_START, reg.BURST_LENGTH)
        if len(raw) != reg.BURST_LENGTH:
            raise OSError(
                f'short read from AK09916 at {reg.AK09916_ADDRESS:#04x} on {self.bus_name}: '
                f'expected {reg.BURST_LENGTH} bytes, got {len(raw)}'
            )
        st1, st2 = raw[0], raw[-1]
        if not st1 & reg.ST1_DRDY:
            return None
        overrun = bool(st1 & reg.ST1_DOR)
        if overrun:
            self.overruns += 1
        counts = np.frombuffer(bytes(raw[1:7]), dtype='<i2').astype(np.int64)
        if st2 & reg.ST2_HOFL or np.any(np.abs(counts) > reg.MEASUREMENT_LIMIT):
            self.overflows += 1
            return None
        return MagReading(field_tesla=counts_to_tesla(counts), counts=counts, overrun=overrun)

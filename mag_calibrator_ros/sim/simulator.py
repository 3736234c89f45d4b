# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Register-level model of an ICM-20948 with its AK09916, behind the smbus2.SMBus methods.

No hardware exists on the development and CI machines, so the driver is exercised against this
model of the chip's registers rather than a mock returning vectors. Each behaviour follows TDK
DS-000189 and the AKM AK09916 datasheet (cited where it is modelled), so that drivers written by
others against real chips run against it unchanged (``test/test_icm20948_peers.py``):

- banks, WHO_AM_I, DEVICE_RESET, sleep, the sensors' start-up times (gyro 35 ms, accel 20 ms);
- accelerometer and gyroscope on sample clocks of their own: each its own divider, 9 kHz / 4.5 kHz
  with the DLPF bypassed (FCHOICE = 0), clocks that keep running across configuration writes and
  restart together only on a divider write with ODR_ALIGN_EN = 1; full-scale ranges, DLPF noise
  bandwidths, RAW_DATA_0_RDY (cleared by reading INT_STATUS_1), big-endian int16 with saturation;
- the I2C bypass (the AK09916 answers at 0x0C only with the master off and bypass on);
- the I2C master (bank 3): rounds on its own duty-cycle clock, 1.1 kHz / 2^I2C_MST_ODR_CONFIG,
  while LP_CONFIG I2C_MST_CYCLE = 1 (its reset value), on the gyro's (else the accel's) sample
  clock with I2C_MST_CYCLE = 0; slaves 0-3 copied into EXT_SLV_SENS_DATA after TEMP_OUT_L,
  delayed slaves (I2C_MST_DELAY_CTRL, I2C_SLV4_DLY) on one round in 1 + DLY; single SLV4
  transfers ending with I2C_SLV4_DONE (and SLV4_NACK for an address nobody answers) in the
  read-to-clear I2C_MST_STATUS;
- the AK09916's continuous, single-measurement and self-test modes driven by a clock, ST1/ST2
  semantics (DRDY, DOR, HOFL, data protection from the first data read until ST2 or a new
  single measurement), int16 saturation and 0.15 uT quantisation.

Where the datasheets are silent the model says so and picks what breaks fewest real drivers.

Physics (``board.BoardModel``): the board moves along a ``motion`` trajectory through the earth's
field and gravity. Faults: random I2C errors, an outage (device vanishes) and a chip reset
mid-run, on every transaction of either die. Truth: ``truth_for_reading`` (magnetometer) and
``imu_truth_for_reading`` (accel/gyro/temperature) give the error-free values behind a reading;
``mag_samples_read``/``mag_repeated_reads`` and ``imu_samples_read``/``imu_repeated_reads`` count
data reads of new samples and second deliveries of samples already read, so a test can tell a
sample read twice from two samples that happen to be equal (an inertial read is repeated only if
every byte it covers was read before from that sample: accel and gyro of one sample read in two
transactions is one delivery; through the master a copy of an already read magnetometer sample
counts as repeated only if its copied ST1 claims DRDY); ``mag_unflagged_equal_reads`` counts the
new samples read through the master without DRDY whose data equal the previous sample's: no
driver can tell those from the previous one.

Thread-safe: a test may inject faults while a driver thread polls.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
import errno
import math
import os
import struct
import threading
import time

import numpy as np

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.units import (
    accel_scale,
    gyro_scale,
    temperature_counts,
    tesla_to_counts,
)
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import BoardModel, ImuTruth
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.fifo import SimulatedFifo

MEASUREMENT_TIME_S = reg.SINGLE_MEASUREMENT_S  # before the first DRDY in any measuring mode
TRUTH_LOG_SIZE = 8192  # magnetometer readings remembered for truth_for_reading
IMU_TRUTH_LOG_SIZE = 16384  # inertial samples remembered (15 s at 1125 Hz)
REGISTER_STARTUP_S = 0.001  # after DEVICE_RESET the ICM-20948 NACKs for this long
TIME_EPSILON_S = 1e-9  # float tolerance on timing checks
IMU_DATA = range(reg.ACCEL_XOUT_H, reg.TEMP_OUT_L + 1)
EXT_DATA = range(reg.EXT_SLV_SENS_DATA_00, reg.EXT_SLV_SENS_DATA_00 + reg.EXT_SLV_SENS_DATA_COUNT)
_IMU_WORDS = struct.Struct('>7h')
READ_ONLY_BANK0 = (reg.WHO_AM_I, reg.INT_STATUS_1, reg.INT_STATUS_2, reg.I2C_MST_STATUS,
                   reg.FIFO_COUNTH, reg.FIFO_COUNTL, reg.FIFO_R_W)
# FIFO_EN_2 bit -> the bytes of the 14 data registers it puts in a record (register order)
_FIFO_FIELDS = ((reg.FIFO_EN_2_ACCEL, 0, 6), (1 << 1, 6, 8), (1 << 2, 8, 10), (1 << 3, 10, 12),
                (reg.FIFO_EN_2_TEMP, 12, 14))


@dataclass(frozen=True)
class _ImuConfig:
    """What the bank-2 registers say, decoded once per write (not once per transaction)."""

    gyro_odr_hz: float
    accel_odr_hz: float
    accel_range_g: int
    gyro_range_dps: int
    accel_scale: float  # SI units per LSB
    gyro_scale: float
    accel_noise_bandwidth_hz: float
    gyro_noise_bandwidth_hz: float


@dataclass
class _SampleClock:
    """One sample clock: sample ``k`` at ``origin + k / rate_hz``, none before ``ready_at`` (the
    start-up time); ``origin`` None while off."""

    origin: float | None = None
    rate_hz: float = reg.INTERNAL_RATE_HZ
    index: int = -1  # the newest sample taken on this clock
    ready_at: float = 0.0

    def due(self, now: float) -> int:
        """Index of the newest sample due by ``now`` (-1: none yet)."""
        if self.origin is None or now < self.ready_at - TIME_EPSILON_S:
            return -1
        index = int(math.floor((now - self.origin) * self.rate_hz + 1e-9))
        return index if self.time_of(index) >= self.ready_at - TIME_EPSILON_S else -1

    def time_of(self, index: int) -> float:
        return self.origin + index / self.rate_hz

    def first_after(self, t: float) -> int:
        """Index of the first sample after sim time ``t`` (and not before ``ready_at``)."""
        after = int(math.floor((t - self.origin) * self.rate_hz + 1e-9)) + 1 \
            if t > -math.inf else 0
        ready = int(math.ceil((self.ready_at - self.origin) * self.rate_hz - 1e-9))
        return max(after, ready, 0)

    def start(self, now: float, delay: float) -> None:
        if self.origin is None:
            self.origin, self.index, self.ready_at = now + delay, -1, now + delay

    def stop(self) -> None:
        self.origin, self.index = None, -1

    def retime(self, rate_hz: float) -> None:
        """A new rate without alignment: the clock keeps its phase at the last sample it took
        (DS-000189 is silent on when a new divider takes effect: from the next sample)."""
        if rate_hz == self.rate_hz:
            return
        if self.origin is not None and self.index >= 0:
            self.origin, self.index = self.time_of(self.index), 0
        self.rate_hz = rate_hz

    def align(self, now: float) -> None:
        """ODR_ALIGN_EN: the clock's phase restarts at ``now``; still starting up, its first
        sample stays after its start-up time."""
        if self.origin is not None:
            self.origin = now
            self.index = 0 if now >= self.ready_at else -1


def _saturated_counts(field_tesla: np.ndarray) -> np.ndarray:
    """``tesla_to_counts`` for any field, however large: in floats, a field beyond every count
    (even infinite, or NaN from an absurd distortion) becomes one count past the measurement
    range, so it reads as the datasheet's overflow (DS-000189 rev. 1.3 §13.3-13.4 p.79: range
    ±32752 counts, ±4912 µT, and HOFL in ST2 says the sensor overflowed) rather than wrapping
    around in the integer conversion to a plausible value without HOFL."""
    with np.errstate(over='ignore', invalid='ignore'):
        chip = np.rint(np.asarray(field_tesla, dtype=float) / reg.TESLA_PER_LSB
                       * np.asarray(reg.AXIS_SIGNS))
    beyond = reg.MEASUREMENT_LIMIT + 1
    chip = np.nan_to_num(chip, nan=beyond, posinf=beyond, neginf=-beyond)
    return np.clip(chip, -beyond, beyond).astype(np.int64)


def _ak_addresses(register: int, length: int) -> list[int]:
    """The AK09916's register addresses in one multi-byte transfer: it auto-increments
    00h-03h then 10h-18h and back to 00h, and 30h-32h back to 30h (DS-000189 §12 p.77);
    elsewhere the datasheet calls the data not correct, modelled as a plain increment."""
    addresses = []
    for _ in range(length):
        addresses.append(register)
        if register == 0x03:
            register = reg.ST1
        elif register == reg.ST2:
            register = reg.WIA1
        elif register == reg.CNTL3:
            register = reg.CNTL3 - 2
        else:
            register = (register + 1) & 0xFF
    return addresses


def _int16(value: float) -> int:
    """A sample saturated to the int16 rails, clamped before rounding so that even an infinite
    one reads the rail."""
    return round(min(max(value, reg.INT16_MIN), reg.INT16_MAX))


@dataclass
class _ReadCounter:
    """Which sample one sensor's data registers hold, how often data reads got a new one
    (``fresh``) or one already read (``repeated``), and the new ones' truths in read order."""

    latched: int | None = None
    latched_truth: object = None
    last_read: int | None = None
    fresh: int = 0
    repeated: int = 0
    unflagged_equal: int = 0  # new samples read without DRDY, data equal to the previous one's
    last_data: bytes | None = None
    delivered: deque = field(default_factory=lambda: deque(maxlen=IMU_TRUTH_LOG_SIZE))
    bytes_read: int = 0  # bit mask of the latched sample's bytes read so far

    def latch(self, sample_id: int, truth: object) -> None:
        self.latched, self.latched_truth = sample_id, truth

    def forget(self) -> None:
        """Power-on: no sample latched; the counts stay, and so does which sample the host read
        last: that is the host's, not the chip's. Until the I2C master's next round the
        EXT_SLV_SENS_DATA copy still holds that sample (an AK09916 soft reset leaves the
        ICM-20948's registers alone), and a host reading it again reads no new sample. Its data
        are forgotten: a driver that re-initialises forgets them too, so a first sample equal to
        it is not one that no driver can tell."""
        self.latched = self.latched_truth = self.last_data = None
        self.bytes_read = 0

    def bytes_of(self, mask: int) -> None:
        """A read of the data bytes in ``mask`` of the latched sample: new if the first of it,
        repeated only if it delivers nothing not read before (accel, then gyro: one delivery)."""
        if self.latched is None or not mask:
            return
        if self.latched != self.last_read:
            self.fresh += 1
            self.last_read = self.latched
            self.delivered.append(self.latched_truth)
            self.bytes_read = mask
            return
        if not mask & ~self.bytes_read:
            self.repeated += 1
        self.bytes_read |= mask

    def data_read(self) -> None:
        self.read_of(self.latched, self.latched_truth, claims_new=True)

    def read_of(self, sample_id: int | None, truth: object, claims_new: bool,
                data: bytes | None = None) -> None:
        """A data read of ``sample_id`` (a copy of it, through the I2C master, with its
        ``data`` bytes); reading one already read counts as repeated only if the read
        ``claims_new`` (DRDY said so)."""
        if sample_id is None:
            return
        if sample_id == self.last_read:
            self.repeated += claims_new
        else:
            self.fresh += 1
            self.unflagged_equal += (not claims_new and data is not None
                                     and data == self.last_data)
            self.last_read = sample_id
            self.delivered.append(truth)
        if data is not None:
            self.last_data = data


def _nack(what: str) -> OSError:
    """What i2c-dev raises when no device acknowledges: OSError(121, 'Remote I/O error')."""
    return OSError(errno.EREMOTEIO, f'{os.strerror(errno.EREMOTEIO)} ({what})')


def _locked(method):
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    wrapper.__name__ = method.__name__
    wrapper.__doc__ = method.__doc__
    return wrapper


class SimulatedIcm20948Bus:
    """An I2C bus with one ICM-20948 (+ AK09916) on it, speaking the smbus2.SMBus methods.

    Time comes from ``clock`` (seconds, monotonic); inject a fake clock to run tests without
    sleeping. Any device outside the model NACKs with ``OSError(EREMOTEIO)`` like real i2c-dev.
    ``trajectory`` replaces the motion named in the config (any ``motion.Trajectory``).
    """

    def __init__(
        self,
        config: SimConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        trajectory: motion.Trajectory | None = None,
    ) -> None:
        self.config = config if config is not None else SimConfig()
        self._lock = threading.RLock()
        self._clock = clock
        self._t0 = clock()
        self.board = BoardModel(self.config, trajectory)
        self._fault_rng = np.random.default_rng([self.config.seed, 11])
        self._self_test_rng = np.random.default_rng([self.config.seed, 13])
        self._truth: OrderedDict[tuple[int, int, int], np.ndarray] = OrderedDict()
        self._imu_truth: OrderedDict[tuple[int, ...], ImuTruth] = OrderedDict()
        self._outage_until = -math.inf
        self._reset_after_outage = False
        self.transactions = 0
        self.injected_errors = 0
        self.samples_measured = 0
        self.imu_samples_measured = 0
        self._mag_reads = _ReadCounter()
        self._imu_reads = _ReadCounter()
        self._sample_id = 0  # every latched sample of either sensor gets a new id
        self._at: float | None = None  # sim time of an I2C master round being run
        self.fifo = SimulatedFifo(delivered=self._imu_reads.delivered)  # one delivery log
        self._tear_fifo_read_after: int | None = None  # fault: the next FIFO read breaks off
        self._power_on()

    # --- power and faults ------------------------------------------------------------------------

    def _power_on(self) -> None:
        """Power-on state of both dies: ICM asleep in bank 0, bypass off, AK09916 powered down."""
        self._icm_reset()
        self._ak_power_on()

    def _icm_reset(self) -> None:
        self._bank = 0
        self._banks = [bytearray(128) for _ in range(4)]
        self._banks[0][reg.PWR_MGMT_1] = reg.PWR_MGMT_1_RESET_VALUE
        self._banks[0][reg.LP_CONFIG] = reg.LP_CONFIG_RESET_VALUE  # DS-000189 §8.3 p.37
        self._banks[2][reg.GYRO_CONFIG_1] = reg.GYRO_CONFIG_1_RESET_VALUE
        self._banks[2][reg.ACCEL_CONFIG] = reg.ACCEL_CONFIG_RESET_VALUE
        self._icm_ready_at = -math.inf
        self._imu_config = self._decode_imu_config()
        self._gyro = _SampleClock(rate_hz=self._imu_config.gyro_odr_hz)
        self._accel = _SampleClock(rate_hz=self._imu_config.accel_odr_hz)
        self._master_clock = _SampleClock(rate_hz=reg.MASTER_CYCLE_RATE_HZ)  # its duty cycle
        self._imu_ready = False
        self._imu_reads.forget()
        self.fifo.clear()
        self.fifo.overflowed = False
        self._mst_status = 0  # I2C_MST_STATUS, cleared by reading it
        self._last_round_at = -math.inf  # sim time of the master's last round
        self._round_number = 0  # rounds since reset: the phase of delayed slaves
        # The AK09916 sample in the EXT_SLV_SENS_DATA copy: (sample id, truth, copied DRDY,
        # first and last EXT register of its HXL..HZH), for counting host reads of it.
        self._ext_mag: tuple[int | None, object, bool, int, int] | None = None

    def _ak_power_on(self) -> None:
        self._mode = reg.MODE_POWER_DOWN
        self._mode_since = self._now()
        self._powered_down_at = self._now()
        self._next_sample_index = 0
        self._data = bytearray(8)  # HXL..HZH, TMPS, ST2 as latched
        self._drdy = False
        self._dor = False
        self._locked = False
        self._pending: tuple[bytearray, np.ndarray] | None = None
        self._mag_reads.forget()

    @_locked
    def write_magnetometer(self, register: int, value: int) -> None:
        """A write reaching the AK09916 by whatever path (fault injection: a foreign master, a
        glitch), bypass on or not."""
        self._advance_master()
        self._advance()
        self._write_ak(register, value & 0xFF)

    @_locked
    def chip_reset(self) -> None:
        """A brown-out: registers back to power-on (asleep, bypass off, AK09916 powered down)."""
        self._power_on()

    @_locked
    def start_outage(self, duration_s: float, reset: bool = True) -> None:
        """The device vanishes from the bus for ``duration_s``; with ``reset`` it comes back
        power-cycled (a loose connector drops the supply too)."""
        if not math.isfinite(duration_s) or duration_s < 0.0:
            raise ValueError(f'outage duration must be finite and >= 0 s, got {duration_s}')
        self._outage_until = self._clock() + duration_s
        self._reset_after_outage = reset

    @_locked
    def tear_next_fifo_read(self, after_bytes: int) -> None:
        """Fault: the next read of FIFO_R_W breaks off after ``after_bytes`` bytes (a stretched
        clock the host controller timed out on: ETIMEDOUT, as i2c-dev reports it): those bytes
        left the FIFO, the host got none of them."""
        self._tear_fifo_read_after = max(int(after_bytes), 0)

    @_locked
    def corrupt_fifo(self, lost_bytes: int = 1, junk_bytes: int = 0) -> None:
        """Fault: ``lost_bytes`` at the FIFO's head vanish, so every record after them is read
        shifted, and ``junk_bytes`` appear after the rest of the head record (equal numbers:
        the count stays whole records, one record is corrupt: what ArduPilot's temperature
        check is for)."""
        self._advance_imu()  # the records due by now are in first
        self.fifo.slip(lost_bytes, junk_bytes)

    @property
    def in_outage(self) -> bool:
        return self._clock() < self._outage_until

    @property
    def sim_time_s(self) -> float:
        """Seconds since the simulated chip powered on: the time its trajectory is evaluated
        at (a cmd_vel motion takes its commands on this clock)."""
        return self._now()

    def _now(self) -> float:
        if self._at is not None:
            return self._at
        return self._clock() - self._t0

    def _transaction(self, i2c_addr: int, what: str) -> None:
        """Common gate for every bus call: outage, injected errors, address decode."""
        self.transactions += 1
        if self._clock() < self._outage_until:
            raise _nack(f'no device at {i2c_addr:#04x}: simulated outage')
        if self._reset_after_outage:
            self._reset_after_outage = False
            self._power_on()
        if self.config.i2c_error_rate > 0.0 and (
            self._fault_rng.random() < self.config.i2c_error_rate
        ):
            self.injected_errors += 1
            raise _nack(f'simulated bus error on {what} at {i2c_addr:#04x}')
        if i2c_addr == self.config.address:
            if self._now() < self._icm_ready_at:
                raise _nack(f'ICM-20948 at {i2c_addr:#04x} busy resetting')
            self._advance_imu()  # before the master: FIFO records take its copy as of their time
            self._advance_master()
            return
        if i2c_addr == reg.AK09916_ADDRESS and self._ak_on_host_bus():
            self._advance()
            return
        raise _nack(f'no device at {i2c_addr:#04x}')

    def _ak_on_host_bus(self) -> bool:
        user_ctrl = self._banks[0][reg.USER_CTRL]
        pin_cfg = self._banks[0][reg.INT_PIN_CFG]
        return bool(pin_cfg & reg.INT_PIN_CFG_BYPASS_EN) and not (
            user_ctrl & reg.USER_CTRL_I2C_MST_EN
        )

    # --- smbus2.SMBus methods --------------------------------------------------------------------

    @_locked
    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        self._transaction(i2c_addr, f'read of register {register:#04x}')
        self._note_data_read(i2c_addr, register, 1)
        return self._read_register(i2c_addr, register)

    @_locked
    def write_byte_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None:
        self._transaction(i2c_addr, f'write of register {register:#04x}')
        self._write_register(i2c_addr, register, value & 0xFF)

    @_locked
    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]:
        if not 0 < length <= 32:
            raise ValueError(f'Desired block length over 32 bytes or below 1: {length}')
        self._transaction(i2c_addr, f'block read from register {register:#04x}')
        self._note_data_read(i2c_addr, register, length)
        if i2c_addr == self.config.address and self._bank == 0 \
                and register <= reg.FIFO_R_W and register + length > reg.FIFO_COUNTH:
            return self._fifo_block(register, length)
        if i2c_addr == self.config.address and (
            self._bank != 0 or register > reg.INT_STATUS_2
        ) and register + length <= reg.REG_BANK_SEL:
            return list(self._banks[self._bank][register:register + length])  # plain registers
        if i2c_addr == reg.AK09916_ADDRESS:
            return [self._read_ak(address) for address in _ak_addresses(register, length)]
        return [self._read_register(i2c_addr, register + i) for i in range(length)]

    @_locked
    def write_i2c_block_data(
        self, i2c_addr: int, register: int, data: list[int], force: bool | None = None
    ) -> None:
        """Consecutive registers from ``register`` in one transaction (both dies auto-increment
        the register address: the ICM-20948 DS-000189 §6.3 p.30, the AK09916 as
        ``_ak_addresses``)."""
        if not 0 < len(data) <= 32:
            raise ValueError(f'Data length cannot exceed 32 bytes or be 0: {len(data)}')
        self._transaction(i2c_addr, f'block write to register {register:#04x}')
        addresses = (_ak_addresses(register, len(data)) if i2c_addr == reg.AK09916_ADDRESS
                     else [register + offset for offset in range(len(data))])
        for address, value in zip(addresses, data, strict=True):
            self._write_register(i2c_addr, address, int(value) & 0xFF)

    @_locked
    def write_quick(self, i2c_addr: int, force: bool | None = None) -> None:
        """An address-only transfer: acknowledged by a device that is there (a probe)."""
        self._transaction(i2c_addr, 'address probe')

    def close(self) -> None:
        """Nothing to release; present because the node closes whatever bus it opened."""

    def __enter__(self) -> SimulatedIcm20948Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- register files --------------------------------------------------------------------------

    def _read_register(self, i2c_addr: int, register: int) -> int:
        if i2c_addr == reg.AK09916_ADDRESS:
            return self._read_ak(register)
        register &= 0x7F
        if register == reg.REG_BANK_SEL:
            return self._bank << reg.BANK_SHIFT
        if self._bank == 0 and register == reg.WHO_AM_I:
            return self.config.who_am_i
        if self._bank == 0 and register == reg.INT_STATUS_1:
            ready, self._imu_ready = self._imu_ready, False  # cleared by this read
            return reg.INT_STATUS_1_RAW_DATA_0_RDY if ready else 0
        if self._bank == 0 and register == reg.I2C_MST_STATUS:
            status, self._mst_status = self._mst_status, 0  # read-to-clear
            return status
        if self._bank == 0 and register == reg.INT_STATUS_2:
            overflowed, self.fifo.overflowed = self.fifo.overflowed, False  # read-to-clear
            return reg.INT_STATUS_2_FIFO_OVERFLOW if overflowed else 0
        if self._bank == 0 and register == reg.FIFO_COUNTH:
            return (self.fifo.latch_count() >> 8) & reg.FIFO_COUNT_HIGH_MASK
        if self._bank == 0 and register == reg.FIFO_COUNTL:
            return self.fifo.latched_count & 0xFF
        if self._bank == 0 and register == reg.FIFO_R_W:
            return self._fifo_block(reg.FIFO_R_W, 1)[0]
        return self._banks[self._bank][register]

    def _fifo_block(self, register: int, length: int) -> list[int]:
        """A read from ``register`` (FIFO_COUNTH .. FIFO_R_W) on: the address increments up to
        FIFO_R_W and stays there, each byte popping one: PX4's ICM20948 driver reads
        FIFO_COUNTH, FIFO_COUNTL and the records in one transfer (FIFOTransferBuffer)."""
        values = [self._read_register(self.config.address, address)
                  for address in range(register, reg.FIFO_R_W)]
        if register + length <= reg.FIFO_R_W:
            return values[:length]
        wanted = length - len(values)
        tear, self._tear_fifo_read_after = self._tear_fifo_read_after, None
        if tear is not None and tear < wanted:
            self.fifo.pop(tear)
            raise OSError(errno.ETIMEDOUT, f'{os.strerror(errno.ETIMEDOUT)} (simulated FIFO '
                                           f'read broken off after {tear} of {wanted} bytes)')
        return values + self.fifo.pop(wanted)

    def _write_register(self, i2c_addr: int, register: int, value: int) -> None:
        if i2c_addr == reg.AK09916_ADDRESS:
            self._write_ak(register, value)
            return
        register &= 0x7F
        if register == reg.REG_BANK_SEL:
            self._bank = (value & reg.BANK_MASK) >> reg.BANK_SHIFT
            return
        if self._bank == 0 and (register in READ_ONLY_BANK0 or register in IMU_DATA
                                or register in EXT_DATA):
            return  # read-only (a host's FIFO_R_W writes are not modelled: no driver makes them)
        if self._bank == reg.MASTER_BANK and register == reg.I2C_SLV4_DI:
            return  # read-only
        if self._bank == 0 and register == reg.PWR_MGMT_1 and value & reg.PWR_MGMT_1_DEVICE_RESET:
            # Resets the ICM-20948 die only; the AK09916 keeps its state.
            self._icm_reset()
            self._icm_ready_at = self._now() + REGISTER_STARTUP_S
            return
        if self._bank == 0 and register == reg.USER_CTRL:
            value &= ~reg.USER_CTRL_I2C_MST_RST & 0xFF  # self-clearing
        if self._bank == 0 and register == reg.PWR_MGMT_1:
            value &= ~reg.PWR_MGMT_1_DEVICE_RESET & 0xFF
        self._banks[self._bank][register] = value
        if self._bank == 0 and register == reg.FIFO_RST and value & reg.FIFO_RST_ALL:
            self.fifo.clear()  # held empty while asserted (_fifo_clock)
        if self._bank == 0 and register in (reg.PWR_MGMT_1, reg.PWR_MGMT_2):
            self._power_sensors()
        elif self._bank == reg.CONFIG_BANK and register in (
            reg.GYRO_SMPLRT_DIV, reg.GYRO_CONFIG_1, reg.ACCEL_SMPLRT_DIV_1,
            reg.ACCEL_SMPLRT_DIV_2, reg.ACCEL_CONFIG,
        ):
            self._imu_config = self._decode_imu_config()
            self._gyro.retime(self._imu_config.gyro_odr_hz)
            self._accel.retime(self._imu_config.accel_odr_hz)
            if register in (reg.GYRO_SMPLRT_DIV, reg.ACCEL_SMPLRT_DIV_1, reg.ACCEL_SMPLRT_DIV_2):
                self._align_clocks()
        elif self._bank == reg.MASTER_BANK and register == reg.I2C_MST_ODR_CONFIG:
            self._master_clock.retime(self._master_cycle_rate())
            self._align_clocks()

    # --- ICM-20948 sampling ----------------------------------------------------------------------

    def _awake(self) -> bool:
        return not self._banks[0][reg.PWR_MGMT_1] & reg.PWR_MGMT_1_SLEEP

    def _power_sensors(self) -> None:
        """PWR_MGMT_1/2 decide which clocks run: a sensor switched on starts sampling after its
        start-up time (DS-000189 tables 1 and 2, page not verified: gyro 35 ms, accel 20 ms);
        one switched off or put to sleep stops. The master's duty-cycle clock runs while the
        chip is awake; the datasheet does not say whether the I2C master runs in sleep: here it
        does not (every driver seen wakes the chip before it talks to the AK09916)."""
        now, awake = self._now(), self._awake()
        pwr_mgmt_2 = self._banks[0][reg.PWR_MGMT_2]
        for clock, disable, startup in (
            (self._gyro, reg.PWR_MGMT_2_DISABLE_GYRO, reg.SENSOR_STARTUP_S),
            (self._accel, reg.PWR_MGMT_2_DISABLE_ACCEL, reg.ACCEL_STARTUP_S),
        ):
            if awake and (pwr_mgmt_2 & disable) != disable:
                clock.start(now, startup)
            else:
                clock.stop()
        if awake:
            self._master_clock.start(now, 0.0)
        else:
            self._master_clock.stop()

    def _align_clocks(self) -> None:
        """ODR_ALIGN_EN = 1 (DS-000189 §10.10, page not verified): a write of GYRO_SMPLRT_DIV,
        ACCEL_SMPLRT_DIV_1/2 or I2C_MST_ODR_CONFIG restarts the sample clocks together; with 0
        nothing restarts."""
        if self._banks[2][reg.ODR_ALIGN_EN] & 0x01:
            now = self._now()
            for clock in (self._gyro, self._accel, self._master_clock):
                clock.align(now)

    def _master_cycle_rate(self) -> float:
        """1.1 kHz / 2^I2C_MST_ODR_CONFIG[3:0] (DS-000189 §11.1, page not verified; §8.3 p.37:
        with I2C_MST_CYCLE = 1 the master's ODR is determined by I2C_MST_ODR_CONFIG)."""
        config = self._banks[3][reg.I2C_MST_ODR_CONFIG] & reg.I2C_MST_ODR_CONFIG_MASK
        return reg.MASTER_CYCLE_RATE_HZ / (1 << config)

    def _decode_imu_config(self) -> _ImuConfig:
        """Rates, ranges and DLPF from the bank-2 registers: each sensor its own divider (12 bits
        for the accelerometer), FCHOICE = 0 bypassing filter and divider (DS-000189 tables 16
        and 18, pages not verified: gyro 9 kHz, accel 4.5 kHz)."""
        bank2 = self._banks[2]
        gyro_config, accel_config = bank2[reg.GYRO_CONFIG_1], bank2[reg.ACCEL_CONFIG]
        if gyro_config & reg.CONFIG_FCHOICE:
            gyro_odr = reg.INTERNAL_RATE_HZ / (1 + bank2[reg.GYRO_SMPLRT_DIV])
            gyro_nbw = reg.GYRO_DLPF_HZ[(gyro_config >> reg.CONFIG_DLPF_SHIFT) & 0x07][1]
        else:
            gyro_odr, gyro_nbw = reg.GYRO_BYPASS_RATE_HZ, reg.GYRO_BYPASS_HZ[1]
        if accel_config & reg.CONFIG_FCHOICE:
            divider = ((bank2[reg.ACCEL_SMPLRT_DIV_1] << 8) | bank2[reg.ACCEL_SMPLRT_DIV_2]) \
                & reg.ACCEL_DIVIDER_MAX
            accel_odr = reg.INTERNAL_RATE_HZ / (1 + divider)
            accel_nbw = reg.ACCEL_DLPF_HZ[(accel_config >> reg.CONFIG_DLPF_SHIFT) & 0x07][1]
        else:
            accel_odr, accel_nbw = reg.ACCEL_BYPASS_RATE_HZ, reg.ACCEL_BYPASS_HZ[1]
        accel_range = {code: g for g, (code, _) in reg.ACCEL_RANGES_G.items()}[
            (accel_config >> reg.CONFIG_FS_SHIFT) & 0x03]
        gyro_range = {code: d for d, (code, _) in reg.GYRO_RANGES_DPS.items()}[
            (gyro_config >> reg.CONFIG_FS_SHIFT) & 0x03]
        return _ImuConfig(gyro_odr, accel_odr, accel_range, gyro_range,
                          accel_scale(accel_range), gyro_scale(gyro_range), accel_nbw, gyro_nbw)

    def _advance_imu(self) -> None:
        """Latch each sensor's newest sample due by now (older ones are lost): the data
        registers hold the accelerometer's and the gyroscope's latest, each from its own clock.
        With the FIFO on, every sample since the last look is also written to it, in order."""
        now = self._now()
        fifo_clock = self._fifo_clock()
        fifo_index = fifo_clock.index if fifo_clock is not None else None
        if fifo_clock is not None:
            self._fifo_backlog(fifo_clock, now)
        due = {}  # sample time -> the sensors' register offsets whose sample falls then
        for clock, first in ((self._accel, 0), (self._gyro, 3)):
            index = clock.due(now)
            if index > clock.index:
                clock.index = index
                due.setdefault(round(clock.time_of(index), 9), []).append(first)
        if not due:
            return
        config = self._imu_config
        words = list(_IMU_WORDS.unpack_from(self._banks[0], reg.ACCEL_XOUT_H))
        for t in sorted(due):  # aligned clocks: one evaluation of the board for both
            accel, gyro, truth = self.board.inertial(t, config.accel_noise_bandwidth_hz,
                                                     config.gyro_noise_bandwidth_hz)
            for first in due[t]:
                values = accel / config.accel_scale if first == 0 else gyro / config.gyro_scale
                words[first:first + 3] = (_int16(v) for v in values)
            words[6] = temperature_counts(truth.temperature_c)
        _IMU_WORDS.pack_into(self._banks[0], reg.ACCEL_XOUT_H, *words)
        self._imu_ready = True
        self._sample_id += 1
        self._imu_reads.latch(self._sample_id, truth)
        self.imu_samples_measured += 1
        self._remember_imu_truth(words, truth)
        if fifo_clock is not None and fifo_clock.index != fifo_index:
            self._write_fifo(fifo_clock.time_of(fifo_clock.index),
                             bytes(self._banks[0][reg.ACCEL_XOUT_H:reg.TEMP_OUT_L + 1]), truth)

    def _remember_imu_truth(self, words: list[int], truth: ImuTruth) -> None:
        key = tuple(words[:6])
        self._imu_truth[key] = truth
        self._imu_truth.move_to_end(key)
        if len(self._imu_truth) > IMU_TRUTH_LOG_SIZE:
            self._imu_truth.popitem(last=False)

    # --- the FIFO --------------------------------------------------------------------------------

    def _fifo_clock(self) -> _SampleClock | None:
        """The clock the FIFO is written on, or None while it takes nothing (USER_CTRL FIFO_EN
        off, nothing selected in FIFO_EN_1/2, FIFO_RST held, asleep). DS-000189 says "at the
        sample rate": here the gyroscope's, the accelerometer's with the gyroscope off; a sensor
        on a slower clock is recorded as its data registers hold it then."""
        bank0 = self._banks[0]
        if not bank0[reg.USER_CTRL] & reg.USER_CTRL_FIFO_EN or bank0[reg.FIFO_RST] \
                & reg.FIFO_RST_ALL or not (bank0[reg.FIFO_EN_2] & reg.FIFO_EN_2_ALL
                                           or bank0[reg.FIFO_EN_1] & 0x0F):
            return None
        for clock in (self._gyro, self._accel):
            if clock.origin is not None:
                return clock
        return None

    def _fifo_backlog(self, clock: _SampleClock, now: float) -> None:
        """Records of the samples before the newest one due (the newest is latched by
        ``_advance_imu``), each evaluated at its own time. Only those that can still be in the
        FIFO are evaluated: snapshot mode keeps the first that fit, stream mode the last."""
        first, last = clock.index + 1, clock.due(now) - 1
        if last < first:
            return
        first = max(first, clock.first_after(-math.inf))  # none before its start-up
        keep = reg.FIFO_SIZE // 2 + 2  # at least one byte each: more never fit
        count = last - first + 1
        if count > keep:
            snapshot = bool(self._banks[0][reg.FIFO_MODE] & reg.FIFO_MODE_SNAPSHOT)
            self.fifo.overrun(count - keep)
            self.imu_samples_measured += count - keep
            if not snapshot:
                first = last - keep + 1
            else:
                last = first + keep - 1
        config = self._imu_config
        for index in range(first, last + 1):
            t = clock.time_of(index)
            accel, gyro, truth = self.board.inertial(t, config.accel_noise_bandwidth_hz,
                                                     config.gyro_noise_bandwidth_hz)
            words = [*(_int16(v) for v in accel / config.accel_scale),
                     *(_int16(v) for v in gyro / config.gyro_scale),
                     temperature_counts(truth.temperature_c)]
            self.imu_samples_measured += 1
            self._remember_imu_truth(words, truth)
            self._write_fifo(t, _IMU_WORDS.pack(*words), truth)

    def _write_fifo(self, t: float, data: bytes, truth: ImuTruth) -> None:
        """One record at sample time ``t`` from the 14 data register bytes ``data``: the fields
        FIFO_EN_2 selects, then the EXT_SLV_SENS_DATA of each slave FIFO_EN_1 selects as the
        I2C master's rounds up to ``t`` left them (slave order, each its LENG bytes)."""
        bank0, enabled = self._banks[0], self._banks[0][reg.FIFO_EN_2]
        record = bytearray()
        for bit, start, end in _FIFO_FIELDS:
            if enabled & bit:
                record += data[start:end]
        slaves = bank0[reg.FIFO_EN_1] & 0x0F
        if slaves:
            self._advance_master(until=t)
            offset = reg.EXT_SLV_SENS_DATA_00
            for slave in range(4):
                ctrl = self._banks[3][reg.I2C_SLV0_CTRL + slave * reg.I2C_SLV_STRIDE]
                length = ctrl & reg.I2C_SLV_LENG_MASK if ctrl & reg.I2C_SLV_EN else 0
                if slaves & (1 << slave):
                    record += bank0[offset:offset + length]
                offset += length
        self.fifo.write(bytes(record), truth,
                        snapshot=bool(bank0[reg.FIFO_MODE] & reg.FIFO_MODE_SNAPSHOT))

    # --- the I2C master (bank 3) -----------------------------------------------------------------

    def _round_clock(self) -> _SampleClock | None:
        """The clock the master's rounds run on, or None while it does not run (master off, or
        the chip asleep). DS-000189 §8.3 p.37: I2C_MST_CYCLE = 1, its own duty cycle; §11.1
        (page not verified): 0, the gyro's ODR, the accel's with the gyro off,
        I2C_MST_ODR_CONFIG's with both off."""
        if not self._banks[0][reg.USER_CTRL] & reg.USER_CTRL_I2C_MST_EN or not self._awake():
            return None
        if self._banks[0][reg.LP_CONFIG] & reg.LP_CONFIG_I2C_MST_CYCLE:
            return self._master_clock
        for clock in (self._gyro, self._accel):
            if clock.origin is not None:
                return clock
        return self._master_clock

    def _advance_master(self, until: float | None = None) -> None:
        """Run every master round due by now (or ``until``), each at its own time, so the
        AK09916 sees every read. Rounds that cannot change anything (no AK09916 event since, no
        transfer pending, a copy that stayed the same for a full delay cycle) are skipped in one
        step."""
        clock = self._round_clock()
        now = self._now() if until is None else until
        if clock is None or clock.origin is None:
            self._last_round_at = max(self._last_round_at, now)  # from the clock's next tick
            return
        last = clock.due(now)
        k = clock.first_after(self._last_round_at)
        quiet = 0
        while k <= last:
            t = clock.time_of(k)
            changed = self._master_round(t)
            self._last_round_at = t
            self._round_number += 1
            quiet = 0 if changed else quiet + 1
            k += 1
            if quiet > self._delay_cycle():
                event = self._next_ak_event()
                skip_to = last + 1 if event > now else max(
                    k, clock.first_after(event - TIME_EPSILON_S))
                skip_to = min(skip_to, last + 1)
                self._round_number += skip_to - k
                if skip_to > k:
                    self._last_round_at = clock.time_of(skip_to - 1)
                k, quiet = skip_to, 0

    def _delay_cycle(self) -> int:
        """Rounds in one cycle of the delayed slaves: 1 + I2C_SLV4_DLY if any is delayed."""
        if self._banks[3][reg.I2C_MST_DELAY_CTRL] & 0x1F:
            return 1 + (self._banks[3][reg.I2C_SLV4_CTRL] & reg.I2C_SLV4_DLY_MASK)
        return 1

    def _slave_runs(self, slave: int) -> bool:
        """I2C_SLVn_DELAY_EN (DS-000189 §11.3, page not verified): a delayed slave runs on one
        round in 1 + I2C_SLV4_DLY (§11.22)."""
        if not self._banks[3][reg.I2C_MST_DELAY_CTRL] & (1 << slave):
            return True
        cycle = 1 + (self._banks[3][reg.I2C_SLV4_CTRL] & reg.I2C_SLV4_DLY_MASK)
        return self._round_number % cycle == 0

    def _master_state(self) -> tuple:
        return (bytes(self._banks[0][reg.EXT_SLV_SENS_DATA_00:reg.EXT_SLV_SENS_DATA_00
                                     + reg.EXT_SLV_SENS_DATA_COUNT]),
                self._mst_status, self._banks[3][reg.I2C_SLV4_CTRL], self._mode, self._drdy,
                self._dor, self._locked, self._mag_reads.latched, self._pending is not None)

    def _master_round(self, t: float) -> bool:
        """One round of the I2C master at sim time ``t``: slaves 0-3 in order (reads copied into
        EXT_SLV_SENS_DATA, packed in slave order; a delayed slave resting this round keeps its
        bytes), then a pending SLV4 transfer. Returns whether anything changed."""
        bank3 = self._banks[3]
        before = self._master_state()
        self._at = t
        try:
            copy = bytearray()
            ext_mag = None
            for slave in range(4):
                base = slave * reg.I2C_SLV_STRIDE
                address = bank3[reg.I2C_SLV0_ADDR + base]
                register = bank3[reg.I2C_SLV0_REG + base]
                ctrl = bank3[reg.I2C_SLV0_CTRL + base]
                length = ctrl & reg.I2C_SLV_LENG_MASK
                if not ctrl & reg.I2C_SLV_EN or length == 0:
                    continue
                reads_mag = address & reg.I2C_SLV_RNW and register <= reg.HXL \
                    and register + length - 1 >= reg.HZH
                if not self._slave_runs(slave) or address & 0x7F != reg.AK09916_ADDRESS:
                    if self._slave_runs(slave):
                        self._mst_status |= 1 << slave  # I2C_SLVn_NACK
                    elif reads_mag:
                        ext_mag = self._ext_mag  # resting: its copy stays as it was
                    copy += self._banks[0][reg.EXT_SLV_SENS_DATA_00 + len(copy):][:length]
                    continue
                self._advance()
                if address & reg.I2C_SLV_RNW:
                    values = [self._read_ak(a) for a in _ak_addresses(register, length)]
                    if reads_mag:
                        start = reg.EXT_SLV_SENS_DATA_00 + len(copy) + reg.HXL - register
                        drdy = register <= reg.ST1 and bool(values[reg.ST1 - register]
                                                            & reg.ST1_DRDY)
                        ext_mag = (self._mag_reads.latched, self._mag_reads.latched_truth,
                                   drdy, start, start + reg.HZH - reg.HXL)
                    copy += bytes(values)
                else:
                    self._write_ak(register, bank3[reg.I2C_SLV0_DO + base])
            end = reg.EXT_SLV_SENS_DATA_00 + min(len(copy), reg.EXT_SLV_SENS_DATA_COUNT)
            self._banks[0][reg.EXT_SLV_SENS_DATA_00:end] = copy[:end - reg.EXT_SLV_SENS_DATA_00]
            self._ext_mag = ext_mag
            ctrl = bank3[reg.I2C_SLV4_CTRL]
            if ctrl & reg.I2C_SLV_EN and self._slave_runs(4):
                bank3[reg.I2C_SLV4_CTRL] = ctrl & ~reg.I2C_SLV_EN & 0xFF  # one transfer
                address = bank3[reg.I2C_SLV4_ADDR]
                if address & 0x7F != reg.AK09916_ADDRESS:
                    self._mst_status |= reg.I2C_MST_STATUS_SLV4_NACK
                else:
                    self._advance()
                    if address & reg.I2C_SLV_RNW:
                        bank3[reg.I2C_SLV4_DI] = self._read_ak(bank3[reg.I2C_SLV4_REG])
                    else:
                        self._write_ak(bank3[reg.I2C_SLV4_REG], bank3[reg.I2C_SLV4_DO])
                self._mst_status |= reg.I2C_MST_STATUS_SLV4_DONE
        finally:
            self._at = None
        return self._master_state() != before

    def _note_data_read(self, i2c_addr: int, register: int, length: int) -> None:
        """Count a read of sensor data: a new sample, or one that was already read."""
        last = register + length - 1
        if i2c_addr == self.config.address and self._bank == 0:
            first, end = max(register, reg.ACCEL_XOUT_H), min(last, reg.TEMP_OUT_L)
            if first <= end:
                mask = ((1 << (end - first + 1)) - 1) << (first - reg.ACCEL_XOUT_H)
                self._imu_reads.bytes_of(mask)
            if self._ext_mag is not None and register <= self._ext_mag[3] \
                    and last >= self._ext_mag[4]:
                sample_id, truth, drdy, start, end = self._ext_mag
                self._mag_reads.read_of(sample_id, truth, claims_new=drdy,
                                        data=bytes(self._banks[0][start:end + 1]))
        elif i2c_addr == reg.AK09916_ADDRESS and register <= reg.TMPS and last >= reg.HXL:
            self._mag_reads.data_read()

    @property
    def mag_samples_read(self) -> int:
        return self._mag_reads.fresh

    @property
    def mag_repeated_reads(self) -> int:
        return self._mag_reads.repeated

    @property
    def mag_unflagged_equal_reads(self) -> int:
        """New samples read through the master without DRDY whose data equal the previous
        sample's (a late look): indistinguishable from it, so a driver loses them."""
        return self._mag_reads.unflagged_equal

    @property
    def imu_samples_read(self) -> int:
        """New inertial samples read: from the data registers, and FIFO records popped whole."""
        return self._imu_reads.fresh + self.fifo.delivered_count

    @property
    def imu_repeated_reads(self) -> int:
        return self._imu_reads.repeated

    @_locked
    def imu_truths_read(self) -> list[ImuTruth]:
        """Truth of every new inertial sample read, in read order (the last 16384): a driver that
        hands each on once lets the k-th published sample be paired with the k-th here, exactly,
        where ``imu_truth_for_reading`` can only match counts."""
        return list(self._imu_reads.delivered)

    # --- AK09916 ---------------------------------------------------------------------------------

    def _read_ak(self, register: int) -> int:
        if register == reg.WIA1:
            return self.config.ak09916_id[0]
        if register == reg.WIA2:
            return self.config.ak09916_id[1]
        if register == reg.ST1:
            return (reg.ST1_DRDY if self._drdy else 0) | (reg.ST1_DOR if self._dor else 0)
        if reg.HXL <= register <= reg.ST2:
            if not self._locked:
                # The first data or ST2 read starts a data read: DRDY and DOR clear, data
                # protected (a DOR raised while protected stays for the next sample).
                self._drdy = False
                self._dor = False
                self._locked = True
            if register <= reg.TMPS:
                return self._data[register - reg.HXL]
            value = self._data[7]
            self._end_read()  # ST2 ends the read
            return value
        if register == reg.CNTL2:
            return self._mode
        return 0  # reserved / CNTL3 (self-clearing) read as 0

    def _write_ak(self, register: int, value: int) -> None:
        if register == reg.CNTL3:
            if value & reg.CNTL3_SRST:
                self._ak_power_on()
            return
        if register != reg.CNTL2:
            return  # read-only or reserved
        if value == reg.MODE_POWER_DOWN:
            self._mode = reg.MODE_POWER_DOWN
            self._powered_down_at = self._now()
            return
        legal = value in reg.CONTINUOUS_RATES or value in (reg.MODE_SINGLE, reg.MODE_SELF_TEST)
        settled = (
            self._mode == reg.MODE_POWER_DOWN
            and self._now() - self._powered_down_at >= reg.MODE_CHANGE_WAIT_S - TIME_EPSILON_S
        )
        if not legal or not settled:
            return  # the AK09916 ignores prohibited codes and mode changes not via power-down
        if value in (reg.MODE_SINGLE, reg.MODE_SELF_TEST):
            # A new measurement latches whether or not ST2 ended the last read. DS-000189
            # §13.2 p.78 says only that a data or ST2 read clears DRDY, nothing of protection
            # in this mode; from drivers that run on real boards: Pimoroni's icm20948 reads
            # every single measurement without ST2 (test/test_icm20948_peers.py).
            self._end_read()
        self._mode = value
        self._mode_since = self._now()
        self._next_sample_index = 0

    def _end_read(self) -> None:
        """A data read ends (ST2 read, or a single measurement started): the registers are
        no longer protected, and a sample that finished during the read is latched now."""
        self._locked = False
        if self._pending is not None:
            data, truth = self._pending
            self._pending = None
            self._latch(data, truth)

    def _next_ak_event(self) -> float:
        """Sim time of the AK09916's next measurement (inf: none coming)."""
        if self._mode in reg.CONTINUOUS_RATES:
            period = 1.0 / reg.CONTINUOUS_RATES[self._mode]
            return self._mode_since + MEASUREMENT_TIME_S + self._next_sample_index * period
        if self._mode in (reg.MODE_SINGLE, reg.MODE_SELF_TEST):
            return self._mode_since + MEASUREMENT_TIME_S
        return math.inf

    def _advance(self) -> None:
        """Complete every magnetometer measurement due by now; only the newest is kept.
        Continuous modes measure on their own clock; single measurement and self-test take one
        sample, set DRDY (DS-000189 §13.2 p.78) and fall back to power-down (AK09916 datasheet,
        section and page not verified), so CNTL2 reads 0 again once the sample is there."""
        if self._mode in (reg.MODE_SINGLE, reg.MODE_SELF_TEST):
            done_at = self._mode_since + MEASUREMENT_TIME_S
            if self._now() < done_at - TIME_EPSILON_S:
                return
            self.samples_measured += 1
            sample = (self._measure(done_at) if self._mode == reg.MODE_SINGLE
                      else self._self_test_sample())
            self._mode = reg.MODE_POWER_DOWN
            self._powered_down_at = done_at
            self._store(sample, skipped=0)
            return
        if self._mode not in reg.CONTINUOUS_RATES:
            return
        period = 1.0 / reg.CONTINUOUS_RATES[self._mode]
        elapsed = self._now() - self._mode_since - MEASUREMENT_TIME_S
        if elapsed < 0.0:
            return
        last_due = int(math.floor(elapsed / period + 1e-9))
        if last_due < self._next_sample_index:
            return
        skipped = last_due - self._next_sample_index  # completed but never latched
        sample_time = self._mode_since + MEASUREMENT_TIME_S + last_due * period
        self._next_sample_index = last_due + 1
        self.samples_measured += 1
        self._store(self._measure(sample_time), skipped)

    def _store(self, sample: tuple[bytearray, np.ndarray], skipped: int) -> None:
        """A finished measurement: latched, or held while a data read protects the registers
        (DOR when a sample was lost: one skipped, or one still unread replaced)."""
        if self._locked:
            if self._pending is not None or skipped:
                self._dor = True
            self._pending = sample
            return
        if self._drdy or skipped:
            self._dor = True
        self._latch(*sample)

    def _self_test_sample(self) -> tuple[bytearray, np.ndarray]:
        """Self-test: the AK09916 measures a field of its own internal source. The datasheet's
        judgement limits (``SELF_TEST_LIMITS``) leave no room for the ambient field, so the model
        reports the source alone: the middle of each limit, with the configured noise."""
        centre = np.array([(low + high) / 2.0 for low, high in reg.SELF_TEST_LIMITS])
        noise = self._self_test_rng.normal(0.0, self.config.noise_ut / 1e6 / reg.TESLA_PER_LSB, 3)
        counts = np.rint(centre + noise).astype(np.int64)
        data = bytearray(counts.astype('<i2').tobytes()) + bytes([0, 0])
        truth = centre * np.asarray(reg.AXIS_SIGNS) * reg.TESLA_PER_LSB  # chip frame, tesla
        return data, truth

    def _latch(self, data: bytearray, truth: np.ndarray) -> None:
        self._data = data
        self._drdy = True
        self._sample_id += 1
        self._mag_reads.latch(self._sample_id, truth)
        counts = tuple(int(c) for c in np.frombuffer(bytes(data[:6]), dtype='<i2'))
        self._truth[counts] = truth
        self._truth.move_to_end(counts)
        while len(self._truth) > TRUTH_LOG_SIZE:
            self._truth.popitem(last=False)

    def _measure(self, t: float) -> tuple[bytearray, np.ndarray]:
        """Registers HXL..ST2 for a sample taken at sim time ``t``, and its true field (T)."""
        sensed_ut, truth = self.board.magnetometer(t)
        counts = _saturated_counts(sensed_ut * 1e-6)  # AK09916 axes, quantised
        overflow = bool(np.any(np.abs(counts) > reg.MEASUREMENT_LIMIT))
        counts = np.clip(counts, -reg.MEASUREMENT_LIMIT, reg.MEASUREMENT_LIMIT)
        data = bytearray(counts.astype('<i2').tobytes())
        data += bytes([0, reg.ST2_HOFL if overflow else 0])
        return data, truth

    # --- ground truth ----------------------------------------------------------------------------

    @_locked
    def truth_for_reading(self, field_tesla: np.ndarray) -> np.ndarray | None:
        """True chip-frame earth field (T) of the sample behind a published reading, or None if it
        is not (or no longer) in the log. Readings with identical counts map to the newest."""
        counts = tuple(int(c) for c in tesla_to_counts(field_tesla))
        truth = self._truth.get(counts)
        return None if truth is None else truth.copy()

    @_locked
    def imu_truth_for_reading(
        self, linear_acceleration: np.ndarray, angular_velocity: np.ndarray
    ) -> ImuTruth | None:
        """The error-free values behind a published inertial sample (converted back to counts
        with the ranges configured now), or None if not (or no longer) in the log. Readings with
        identical counts map to the newest."""
        config = self._imu_config
        key = (*(round(float(v) / config.accel_scale) for v in linear_acceleration),
               *(round(float(v) / config.gyro_scale) for v in angular_velocity))
        return self._imu_truth.get(key)

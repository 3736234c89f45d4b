# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The whole ICM-20948 over an injected smbus2-like bus: accelerometer, gyroscope, temperature
and the AK09916 magnetometer behind it (no rclpy).

The bus is anything with the smbus2.SMBus methods used here (``read_byte_data``,
``write_byte_data``, ``read_i2c_block_data``): a real ``smbus2.SMBus`` on a robot, or
``SimulatedIcm20948Bus`` in tests and the demo; every call goes through ``CountingBus``. I2C
failures surface as ``OSError`` so a caller (``Icm20948Supervisor``) can back off and
re-initialise; identity problems raise errors that name bus, address, expected and found values.

Data-ready is polled (no interrupt line): INT_STATUS_1 for the accel/gyro/temperature sample
(then one coherent 14-byte burst); or, with ``fifo``, the chip's FIFO holds every sample and
``read_fifo`` drains it in bounded bursts, checked and stamped as ``icm20948/fifo.py`` says
(ArduPilot's AP_InertialSensor_Invensensev2 always reads it so). The magnetometer is reached
one of two ways:

- I2C bypass (``aux_master=False``; the only way with accel and gyro off): the AK09916 sits on the
  host bus; ST1 is polled, the 8-byte HXL..ST2 burst read on DRDY (15 wire bytes per sample plus
  4 per idle poll).
- the ICM-20948's own I2C master (``aux_master=True``): its slaves 0 and 1 read ST1..HZH and ST2
  on every round of the master into EXT_SLV_SENS_DATA_00..07, right after TEMP_OUT_L, and the
  host reads them by lengthening the accel/gyro burst by 8 bytes while a magnetometer sample is
  due, taking each sample by its copied DRDY. The AK09916 is configured through single SLV4
  transfers with the master on its 1.1 kHz duty cycle (LP_CONFIG I2C_MST_CYCLE = 1, its reset
  value, I2C_MST_ODR_CONFIG = 0), so bring-up waits rounds of a known clock, not the gyro's
  start-up. Then the driver sets the round clock it reads by (``master_odr_config``): by default
  I2C_MST_CYCLE = 0, one round per accel/gyro sample, so each copy lives exactly one sample and
  8-10 wire bytes per magnetometer sample suffice; or the duty cycle at 1.1 kHz / 2^n with the
  slaves delayed (I2C_SLV4_DLY) so each copy outlives one accel/gyro sample. Left at reset, the
  master would run at 1.1 kHz whatever the gyro does and a copied DRDY would live ~0.9 ms.

Register facts: TDK DS-000189 and the AKM AK09916 datasheet, collected in ``registers``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import errno
import math
import struct
import time

import numpy as np

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.bus import BusMonitor, CountingBus, SmbusLike
from mag_calibrator_ros.icm20948.fifo import FifoTimeline, temperature_plausible
from mag_calibrator_ros.icm20948.units import accel_scale, gyro_scale, temperature_celsius

INIT_TRANSACTION_ATTEMPTS = 3  # per register access during bring-up
# Per read transaction while running: one immediate retry. The sample stays latched until the next
# one arrives, so a glitch on a 5 %-error bus costs nothing instead of a lost sample.
READ_ATTEMPTS = 2
# The ICM-20948's sample clock is its own oscillator: assume consecutive samples can come this
# much sooner than the nominal period when judging whether a read straddled one.
CLOCK_TOLERANCE = 0.10
# Through the I2C master on the sample clock (I2C_MST_CYCLE = 0) the AK09916 is read once per
# accel/gyro sample: at least this many of those per magnetometer period, so a copy holding a new
# sample never outlives the gap after which the driver looks for the next one (the copied DRDY is
# then seen at most once per sample).
MASTER_SAMPLES_PER_MAG = 2.0
# The reader (``Icm20948Supervisor``) polls data-ready this many times per accel/gyro sample, so
# it reads each within 1/POLLS_PER_SAMPLE of a period and its looks at the master's copy come at
# most 1 + 1/POLLS_PER_SAMPLE periods apart: on the duty cycle a copy must live that long.
POLLS_PER_SAMPLE = 1.5
LOOK_GAP_PERIODS = 1.0 + 1.0 / POLLS_PER_SAMPLE
# Bring-up's SLV4 transfers run with the master on its duty cycle at I2C_MST_ODR_CONFIG = 0.
BRING_UP_ROUND_S = 1.0 / reg.MASTER_CYCLE_RATE_HZ
MAG_SHARE = 'magnetometer'  # BusMonitor label of the magnetometer's wire bytes
# The FIFO is drained this often at most (a few records a read at the chip's 1125 Hz: ArduPilot
# takes up to 4 per read over I2C), each transaction at most this many records: an SMBus block
# read carries 32 bytes.
FIFO_DRAIN_PERIOD_S = 0.004
FIFO_RECORDS_PER_READ = 32 // reg.FIFO_RECORD_LENGTH


class DeviceNotFoundError(OSError):
    """Nothing answered at the expected I2C address."""


class UnreliableBusError(OSError):
    """The device answers, but too many transactions fail to bring it up."""


class WrongDeviceError(ValueError):
    """Something answered, but its identity register holds the wrong value."""


class ModeNotAcceptedError(OSError):
    """The AK09916 did not take the requested measurement mode (read back differs)."""


class ConfigNotAcceptedError(OSError):
    """An ICM-20948 configuration register reads back differently from what was written."""


class AuxiliaryBusError(OSError):
    """A transfer of the ICM-20948's I2C master (SLV4) was not acknowledged or never finished."""


@dataclass(frozen=True)
class MasterPlan:
    """How the I2C master carries the magnetometer: ``odr_config`` None runs it on the
    accel/gyro sample clock (LP_CONFIG I2C_MST_CYCLE = 0), else on its duty cycle at
    1.1 kHz / 2^odr_config, the AK09916's slaves read on one round in ``1 + delay``
    (I2C_SLV4_DLY). ``read_period_s``: how long one copy in EXT_SLV_SENS_DATA lives."""

    odr_config: int | None
    round_hz: float
    delay: int

    @property
    def read_period_s(self) -> float:
        return (1 + self.delay) / self.round_hz


def master_plan(mag_rate_hz: int, imu: ImuSettings | None,
                odr_config: int | None = None, fifo: bool = False) -> MasterPlan | None:
    """The master's set-up for these rates, or None when it cannot carry every magnetometer
    sample by its DRDY. On the sample clock: ``MASTER_SAMPLES_PER_MAG`` rounds per magnetometer
    period; with the FIFO (the copy looked at once a drain, not with every sample) the AK09916
    read on one round in 1 + delay, the largest delay that still reads it faster than it
    measures, so each copy lives as long as it can (ArduPilot's I2C_SLV4_DLY on its FIFO). On
    the duty cycle (its own oscillator, not locked to the samples): the smallest slave delay
    whose copies outlive the longest gap between two looks (``LOOK_GAP_PERIODS`` of a sample
    period, or of a drain with the FIFO), so every copy is looked at, provided the AK09916 is
    still read as fast as it may measure."""
    if imu is None:
        return None
    if odr_config is None and fifo:
        delay = min(math.floor(imu.odr_hz / ((1.0 + CLOCK_TOLERANCE) * mag_rate_hz) + 1e-9) - 1,
                    reg.I2C_SLV4_DLY_MASK)
        return MasterPlan(None, imu.odr_hz, delay) if delay >= 0 else None
    if odr_config is None:
        if imu.odr_hz < MASTER_SAMPLES_PER_MAG * mag_rate_hz:
            return None
        return MasterPlan(None, imu.odr_hz, 0)
    if not isinstance(odr_config, int) or not 0 <= odr_config <= reg.I2C_MST_ODR_CONFIG_MASK:
        return None
    round_hz = reg.MASTER_CYCLE_RATE_HZ / (1 << odr_config)
    look_gap = FIFO_DRAIN_PERIOD_S if fifo else 1.0 / imu.odr_hz
    lifetime = LOOK_GAP_PERIODS * look_gap / (1.0 - CLOCK_TOLERANCE)
    delay = max(0, math.ceil(lifetime * round_hz - 1e-9) - 1)
    if delay > reg.I2C_SLV4_DLY_MASK or round_hz / (1 + delay) < (
            1.0 + CLOCK_TOLERANCE) * mag_rate_hz - 1e-6:
        return None
    return MasterPlan(odr_config, round_hz, delay)


def fifo_drain_period(plan: MasterPlan | None) -> float:
    """How often the FIFO is drained: ``FIFO_DRAIN_PERIOD_S``, or sooner when the master's copy
    of the magnetometer, looked at once a drain, would otherwise outlive no gap between looks."""
    if plan is None:
        return FIFO_DRAIN_PERIOD_S
    return min(FIFO_DRAIN_PERIOD_S,
               plan.read_period_s * (1.0 - CLOCK_TOLERANCE) / LOOK_GAP_PERIODS)


@dataclass(frozen=True)
class ImuSettings:
    """Accelerometer/gyroscope configuration.

    ``rate_hz``: the lowest acceptable output rate; the chip runs at 1125 / (1 + divider) Hz and
    the divider is chosen so that rate is the nearest at or above the request (200 -> 225 Hz,
    1000 -> 1125 Hz). ``dlpf``: DLPFCFG 1-6 for both sensors (``registers.GYRO_DLPF_HZ``).
    """

    rate_hz: int = 200
    accel_range_g: int = 4
    gyro_range_dps: int = 1000
    dlpf: int = 3

    def problems(self) -> list[str]:
        """Every reason the chip cannot run these settings (empty when it can)."""
        problems = []
        lowest = reg.INTERNAL_RATE_HZ / (reg.GYRO_DIVIDER_MAX + 1)
        if not isinstance(self.rate_hz, int) or not (
            math.ceil(lowest) <= self.rate_hz <= reg.INTERNAL_RATE_HZ
        ):
            problems.append(
                f'imu_rate_hz must be an integer from {math.ceil(lowest)} to '
                f'{reg.INTERNAL_RATE_HZ:.0f} Hz (the chip runs at 1125/(1+n) Hz), '
                f'got {self.rate_hz!r}'
            )
        if self.accel_range_g not in reg.ACCEL_RANGES_G:
            problems.append(f'accel_range_g must be one of {list(reg.ACCEL_RANGES_G)} g, '
                            f'got {self.accel_range_g!r}')
        if self.gyro_range_dps not in reg.GYRO_RANGES_DPS:
            problems.append(f'gyro_range_dps must be one of {list(reg.GYRO_RANGES_DPS)} deg/s, '
                            f'got {self.gyro_range_dps!r}')
        if self.dlpf not in reg.DLPF_SETTINGS:
            problems.append(
                f'dlpf must be one of {list(reg.DLPF_SETTINGS)} (DLPFCFG; 0 and 7 would bypass '
                f'the sample-rate divider), got {self.dlpf!r}'
            )
        return problems

    @property
    def divider(self) -> int:
        """GYRO_SMPLRT_DIV = ACCEL_SMPLRT_DIV: the largest divider still at or above rate_hz."""
        return min(max(int(reg.INTERNAL_RATE_HZ // self.rate_hz) - 1, 0), reg.GYRO_DIVIDER_MAX)

    @property
    def odr_hz(self) -> float:
        """The rate the chip will actually produce samples at."""
        return reg.INTERNAL_RATE_HZ / (1 + self.divider)

    @property
    def accel_noise_bandwidth_hz(self) -> float:
        return reg.ACCEL_DLPF_HZ[self.dlpf][1]

    @property
    def gyro_noise_bandwidth_hz(self) -> float:
        return reg.GYRO_DLPF_HZ[self.dlpf][1]


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


@dataclass(frozen=True)
class ImuReading:
    """One accelerometer/gyroscope/temperature sample, chip frame.

    ``linear_acceleration``: specific force in m/s^2 (+9.81 on z lying level, REP-145);
    ``angular_velocity``: rad/s; ``temperature_c``: die temperature; ``counts``: the seven raw
    int16 values (accel x, y, z, gyro x, y, z, temperature); ``saturated``: an accel or gyro
    axis sits on the int16 rail (the true value may be beyond the range).
    """

    linear_acceleration: np.ndarray
    angular_velocity: np.ndarray
    temperature_c: float
    counts: tuple[int, ...]
    saturated: bool


def _with_retries(attempts: int, operation: Callable, args: tuple,
                  pause: Callable[[], None] | None = None):
    """``operation(*args)``, tried up to ``attempts`` times on OSError; the last one propagates."""
    for attempt in range(attempts):
        try:
            return operation(*args)
        except OSError:
            if attempt == attempts - 1:
                raise
            if pause is not None:
                pause()
    return None  # unreachable


_IMU_WORDS = struct.Struct('>7h')
_MAG_WORDS = struct.Struct('<3h')
_TESLA_PER_COUNT = np.asarray(reg.AXIS_SIGNS) * reg.TESLA_PER_LSB


class Icm20948:
    """Brings up the whole chip (AK09916 through bypass or the chip's I2C master) and reads each
    sensor on data-ready.

    Counters: ``overruns`` (ST1 DOR: magnetometer samples skipped because we read too late),
    ``overflows`` (ST2 HOFL: magnetic overflow, sample discarded), ``imu_resyncs`` (an IMU read
    that may have straddled a new sample, so its data-ready flag was cleared: see ``read_imu``).
    """

    def __init__(
        self,
        bus: SmbusLike,
        address: int = reg.ICM20948_DEFAULT_ADDRESS,
        bus_name: str = '/dev/i2c-1',
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if address not in reg.ICM20948_ADDRESSES:
            raise ValueError(
                f'ICM-20948 address must be 0x68 or 0x69, got {address:#04x} on {bus_name}'
            )
        self.bus = bus if isinstance(bus, CountingBus) else CountingBus(
            bus, BusMonitor({reg.AK09916_ADDRESS: MAG_SHARE}))
        self.address = address
        self.bus_name = bus_name
        self._sleep = sleep
        self._clock = clock
        self.mag_rate_hz: int | None = None
        self.imu: ImuSettings | None = None
        self.overruns = 0
        self.overflows = 0
        self.imu_resyncs = 0
        self.mag_fallbacks = 0  # master path: samples found without their copied DRDY
        self.fifo_overflows = 0  # the FIFO filled up: samples lost, FIFO reset
        self.fifo_resets = 0  # every FIFO reset after bring-up (overflow, torn read, corrupt)
        self.fifo_corrupt = 0  # records that failed the sentinel (misaligned or garbage)
        self.fifo_records = 0  # records read and handed on
        self.fifo_reads = 0  # drains that found records
        self.fifo = False
        self._timeline: FifoTimeline | None = None
        self._fifo_temperature: int | None = None  # the last trusted temperature word
        self._fifo_partial = False  # the last count was not whole records
        self._fifo_reset_due = False
        self.aux_master = False
        self.master: MasterPlan | None = None
        self._slv4_delay = 0
        self._round_period = BRING_UP_ROUND_S
        self._imu_valid_at = 0.0  # no accel/gyro sample is read before the gyro's start-up
        self._mag_taken_at = -math.inf
        self._mag_due_at = 0.0  # master path: lengthen the burst from this clock time on
        self._mag_last_copy = b''  # HXL..HZH, ST2 of the last sample taken from a copy
        self._mag_pending: tuple[int, bytes] | None = None  # (ST1, HXL..HZH ST2) not yet taken
        self._mag_period = self._imu_period = 0.0
        self._imu_synced_at: float | None = None  # last INT_STATUS_1 read with nothing pending
        self._imu_window = 0.0
        self._accel_scale = self._gyro_scale = 0.0

    # --- bring-up --------------------------------------------------------------------------------

    def initialise(self, mag_rate_hz: int = 100, imu: ImuSettings | None = None,
                   aux_master: bool = False, master_odr_config: int | None = None,
                   fifo: bool = False) -> None:
        """Reset the chip, configure accel/gyro (or power them down when ``imu`` is None), reach
        the AK09916 (``aux_master``: through the chip's I2C master, set up as ``master_plan``
        says for ``master_odr_config``: None, on the accel/gyro sample clock; n, its duty cycle
        at 1.1 kHz / 2^n; else bypass) and start its continuous measurement. ``fifo``: the
        accelerometer, gyroscope and temperature go through the FIFO (``read_fifo``), else
        they are polled (``read_imu``).

        Raises ``DeviceNotFoundError`` / ``UnreliableBusError`` (OSErrors) when the chip does not
        answer, ``WrongDeviceError`` (a ValueError) on a wrong identity, ``OSError`` on a bus
        error mid-sequence, ``ConfigNotAcceptedError`` / ``ModeNotAcceptedError`` (OSErrors)
        when a register does not read back as written.
        """
        if mag_rate_hz not in reg.CONTINUOUS_MODES:
            raise ValueError(
                f'AK09916 continuous rate must be one of {sorted(reg.CONTINUOUS_MODES)} Hz, '
                f'got {mag_rate_hz}'
            )
        if imu is not None and imu.problems():
            raise ValueError('; '.join(imu.problems()))
        if fifo and imu is None:
            raise ValueError('the FIFO carries the accelerometer and gyroscope: it needs '
                             'ImuSettings')
        plan = master_plan(mag_rate_hz, imu, master_odr_config, fifo) if aux_master else None
        if aux_master and plan is None:
            raise ValueError(
                f'the I2C master path cannot carry every {mag_rate_hz} Hz magnetometer sample '
                f'with the accelerometer/gyroscope at '
                f'{"none" if imu is None else f"{imu.odr_hz:.1f} Hz"} and I2C_MST_ODR_CONFIG '
                f'{master_odr_config}: on the sample clock it needs at least '
                f'{MASTER_SAMPLES_PER_MAG:g} x the magnetometer rate; on the duty cycle, rounds '
                f'faster than the magnetometer once slowed to the accel/gyro rate; use bypass'
            )
        self.mag_rate_hz = self.imu = self.master = None
        self.aux_master = self.fifo = False
        self._mag_taken_at = -math.inf
        self._mag_pending = None
        self._mag_last_copy = b''
        self._imu_synced_at = None
        self._check_icm20948_identity()
        self._write_icm(reg.PWR_MGMT_1, reg.PWR_MGMT_1_DEVICE_RESET)
        self._sleep(reg.DEVICE_RESET_WAIT_S)
        self._select_bank(0)  # reset returns to bank 0; be explicit
        # Sensors chosen while still asleep: with imu None they never start (DS-000189 table 2,
        # page not verified: the accelerometer would start 20 ms after waking with PWR_MGMT_2 at
        # its reset value).
        self._write_icm(reg.PWR_MGMT_2, reg.PWR_MGMT_2_ALL_ON if imu is not None else
                        reg.PWR_MGMT_2_DISABLE_ACCEL | reg.PWR_MGMT_2_DISABLE_GYRO)
        self._write_icm(reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO)  # wake, auto clock
        self._imu_valid_at = self._clock() + reg.SENSOR_STARTUP_S
        self._sleep(reg.WAKE_WAIT_S)
        if imu is not None:
            self._configure_inertial(imu)
        if aux_master:
            self._start_master(mag_rate_hz, plan)
        else:
            user_ctrl = self._retry(self.bus.read_byte_data, self.address, reg.USER_CTRL)
            self._write_icm(reg.USER_CTRL, user_ctrl & ~reg.USER_CTRL_I2C_MST_EN & 0xFF)
            pin_cfg = self._retry(self.bus.read_byte_data, self.address, reg.INT_PIN_CFG)
            self._write_icm(reg.INT_PIN_CFG, pin_cfg | reg.INT_PIN_CFG_BYPASS_EN)
            self._start_magnetometer(mag_rate_hz)
        self.mag_rate_hz = mag_rate_hz
        self.aux_master = aux_master
        self.master = plan
        self._mag_period = 1.0 / mag_rate_hz
        self._mag_due_at = self._clock()
        if imu is not None:
            self._imu_period = 1.0 / imu.odr_hz
            self.imu = imu
            self._accel_scale = accel_scale(imu.accel_range_g)
            self._gyro_scale = gyro_scale(imu.gyro_range_dps)
            self._imu_window = (1.0 - CLOCK_TOLERANCE) / imu.odr_hz
        if fifo:
            self._reset_fifo(counted=False)
            self.fifo = True
            self._timeline = FifoTimeline(1.0 / imu.odr_hz)

    def _configure_inertial(self, imu: ImuSettings) -> None:
        """Bank 2: aligned sample clocks, dividers, ranges and DLPF; read back, then bank 0."""
        divider = imu.divider
        gyro_config = ((imu.dlpf << reg.CONFIG_DLPF_SHIFT)
                       | (reg.GYRO_RANGES_DPS[imu.gyro_range_dps][0] << reg.CONFIG_FS_SHIFT)
                       | reg.CONFIG_FCHOICE)
        accel_config = ((imu.dlpf << reg.CONFIG_DLPF_SHIFT)
                        | (reg.ACCEL_RANGES_G[imu.accel_range_g][0] << reg.CONFIG_FS_SHIFT)
                        | reg.CONFIG_FCHOICE)
        wanted = {
            reg.GYRO_SMPLRT_DIV: ('GYRO_SMPLRT_DIV', divider),
            reg.GYRO_CONFIG_1: ('GYRO_CONFIG_1', gyro_config),
            reg.ACCEL_SMPLRT_DIV_1: ('ACCEL_SMPLRT_DIV_1', divider >> 8),
            reg.ACCEL_SMPLRT_DIV_2: ('ACCEL_SMPLRT_DIV_2', divider & 0xFF),
            reg.ACCEL_CONFIG: ('ACCEL_CONFIG', accel_config),
        }
        self._select_bank(reg.CONFIG_BANK)
        try:
            self._write_icm(reg.ODR_ALIGN_EN, 1)
            for register, (_, value) in wanted.items():
                self._write_icm(register, value)
            found = dict(zip(
                (reg.GYRO_SMPLRT_DIV, reg.GYRO_CONFIG_1),
                self._retry(self.bus.read_i2c_block_data, self.address, reg.GYRO_SMPLRT_DIV, 2),
                strict=True,
            ))
            accel_block = self._retry(
                self.bus.read_i2c_block_data, self.address, reg.ACCEL_SMPLRT_DIV_1,
                reg.ACCEL_CONFIG - reg.ACCEL_SMPLRT_DIV_1 + 1,
            )
            found.update({reg.ACCEL_SMPLRT_DIV_1: accel_block[0],
                          reg.ACCEL_SMPLRT_DIV_2: accel_block[1],
                          reg.ACCEL_CONFIG: accel_block[-1]})
        finally:
            self._select_bank(0)
        wrong = [f'{name} expected {value:#04x}, found {found[register]:#04x}'
                 for register, (name, value) in wanted.items() if found[register] != value]
        if wrong:
            raise ConfigNotAcceptedError(
                f'ICM-20948 at {self.address:#04x} on {self.bus_name} did not keep its bank-2 '
                f'configuration: ' + '; '.join(wrong)
            )

    def _start_magnetometer(self, rate_hz: int) -> None:
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

    # --- the I2C master path ---------------------------------------------------------------------

    def _start_master(self, rate_hz: int, plan: MasterPlan) -> None:
        """Bypass off, master on (slaves idle) on its 1.1 kHz duty cycle, the AK09916 reset and
        started through SLV4 (AK09916 sequence as in ``_start_magnetometer``), then slaves 0 and 1
        reading ST1..HZH and ST2 on the round clock of ``plan`` (DS-000189 §8.3 p.37, §11)."""
        pin_cfg = self._retry(self.bus.read_byte_data, self.address, reg.INT_PIN_CFG)
        self._write_icm(reg.INT_PIN_CFG, pin_cfg & ~reg.INT_PIN_CFG_BYPASS_EN & 0xFF)
        self._slv4_delay = 0
        self._round_period = BRING_UP_ROUND_S
        self._select_bank(reg.MASTER_BANK)
        try:
            self._write_icm(reg.I2C_SLV0_CTRL, 0)
            self._write_icm(reg.I2C_SLV0_CTRL + reg.I2C_SLV_STRIDE, 0)
            self._write_icm(reg.I2C_MST_CTRL, reg.I2C_MST_CTRL_P_NSR | reg.I2C_MST_CLK_345_KHZ)
            self._write_icm(reg.I2C_MST_DELAY_CTRL, reg.I2C_MST_DELAY_ES_SHADOW)
            self._write_icm(reg.I2C_MST_ODR_CONFIG, 0)
        finally:
            self._select_bank(0)
        self._write_lp_config(reg.LP_CONFIG_I2C_MST_CYCLE)
        user_ctrl = self._retry(self.bus.read_byte_data, self.address, reg.USER_CTRL)
        self._write_icm(reg.USER_CTRL, user_ctrl | reg.USER_CTRL_I2C_MST_EN)
        # A NACK or a round that never comes raises AuxiliaryBusError naming the AK09916; the
        # ICM-20948 itself answered its identity check moments ago.
        period = BRING_UP_ROUND_S
        found = [self._slv4(reg.WIA1, period), self._slv4(reg.WIA2, period)]
        self._check_ak09916_ids(found)
        self._slv4(reg.CNTL3, period, value=reg.CNTL3_SRST)
        self._sleep(reg.SOFT_RESET_WAIT_S)
        self._slv4(reg.CNTL2, period, value=reg.MODE_POWER_DOWN)
        delayed = (1 << 0) | (1 << 1) if plan.delay else 0  # I2C_SLV0/1_DELAY_EN
        self._select_bank(reg.MASTER_BANK)
        try:
            for offset, register, length in ((0, reg.ST1, reg.MAG_MASTER_SLV0_LENGTH),
                                             (reg.I2C_SLV_STRIDE, reg.ST2, 1)):
                self._write_icm(reg.I2C_SLV0_ADDR + offset,
                                reg.I2C_SLV_RNW | reg.AK09916_ADDRESS)
                self._write_icm(reg.I2C_SLV0_REG + offset, register)
                self._write_icm(reg.I2C_SLV0_CTRL + offset, reg.I2C_SLV_EN | length)
            self._write_icm(reg.I2C_SLV4_CTRL, plan.delay)  # I2C_SLV4_DLY, no transfer
            self._write_icm(reg.I2C_MST_DELAY_CTRL, reg.I2C_MST_DELAY_ES_SHADOW | delayed)
            if plan.odr_config is not None:
                self._write_icm(reg.I2C_MST_ODR_CONFIG, plan.odr_config)
        finally:
            self._select_bank(0)
        if plan.odr_config is None:
            # On the sample clock rounds start with the gyro's first sample (its start-up time,
            # DS-000189 table 1, page not verified): the AK09916 starts measuring once they run,
            # none is lost.
            self._sleep(max(reg.MODE_CHANGE_WAIT_S, self._imu_valid_at - self._clock()))
        self._write_lp_config(0 if plan.odr_config is None else reg.LP_CONFIG_I2C_MST_CYCLE)
        self._slv4_delay = plan.delay
        self._round_period = period = 1.0 / plan.round_hz
        mode = reg.CONTINUOUS_MODES[rate_hz]
        self._slv4(reg.CNTL2, period, value=mode)
        found_mode = self._slv4(reg.CNTL2, period)
        if found_mode != mode:
            raise ModeNotAcceptedError(
                f'AK09916 behind the ICM-20948 at {self.address:#04x} on {self.bus_name} did not '
                f'accept continuous mode {rate_hz} Hz: CNTL2 expected {mode:#04x}, found '
                f'{found_mode:#04x}'
            )

    def _write_lp_config(self, value: int) -> None:
        """LP_CONFIG (DS-000189 §8.3 p.37): I2C_MST_CYCLE as the master's plan needs, the
        accelerometer and gyroscope not duty-cycled; read back."""
        self._write_icm(reg.LP_CONFIG, value)
        found = self._retry(self.bus.read_byte_data, self.address, reg.LP_CONFIG)
        if found != value:
            raise ConfigNotAcceptedError(
                f'ICM-20948 at {self.address:#04x} on {self.bus_name} did not keep LP_CONFIG: '
                f'expected {value:#04x}, found {found:#04x}'
            )

    def _slv4(self, register: int, period: float, value: int | None = None) -> int | None:
        """One SLV4 transfer with the AK09916 (a write of ``value``, else a read): set it up in
        bank 3, start it, poll I2C_MST_STATUS (bank 0, read-to-clear) for I2C_SLV4_DONE; the
        master runs it on its next round (``period``: of the master's clock): the wait is a count
        of polls, ``SLV4_TIMEOUT_PERIODS`` rounds. Returns the byte read (I2C_SLV4_DI). Leaves
        bank 0."""
        read = value is None
        self._select_bank(reg.MASTER_BANK)
        try:
            self._write_icm(reg.I2C_SLV4_ADDR,
                            (reg.I2C_SLV_RNW if read else 0) | reg.AK09916_ADDRESS)
            self._write_icm(reg.I2C_SLV4_REG, register)
            if not read:
                self._write_icm(reg.I2C_SLV4_DO, value)
            self._select_bank(0)
            self._retry(self.bus.read_byte_data, self.address, reg.I2C_MST_STATUS)  # stale bits
            self._select_bank(reg.MASTER_BANK)
            self._write_icm(reg.I2C_SLV4_CTRL, reg.I2C_SLV_EN | self._slv4_delay)
        finally:
            self._select_bank(0)
        polls = 2 * reg.SLV4_TIMEOUT_PERIODS
        for poll in range(polls + 1):  # counted, not timed: a stalled clock cannot hang it
            self._sleep(period / 2.0)
            status = self._retry(self.bus.read_byte_data, self.address, reg.I2C_MST_STATUS)
            if status & reg.I2C_MST_STATUS_SLV4_DONE:
                break
            if poll == polls:
                raise AuxiliaryBusError(
                    f'the I2C master of the ICM-20948 at {self.address:#04x} on {self.bus_name} '
                    f'did not finish a transfer with the AK09916 (register {register:#04x}) '
                    f'within {reg.SLV4_TIMEOUT_PERIODS} rounds of its clock: asleep or reset?'
                )
        if status & reg.I2C_MST_STATUS_SLV4_NACK:
            raise AuxiliaryBusError(
                f'AK09916 at {reg.AK09916_ADDRESS:#04x} on the auxiliary bus of the ICM-20948 at '
                f'{self.address:#04x} ({self.bus_name}) did not acknowledge register '
                f'{register:#04x} (I2C_SLV4_NACK)'
            )
        if not read:
            return None
        self._select_bank(reg.MASTER_BANK)
        try:
            return self._retry(self.bus.read_byte_data, self.address, reg.I2C_SLV4_DI)
        finally:
            self._select_bank(0)

    def measurement_mode(self) -> int:
        """CNTL2 as the AK09916 reports it now (0 after a reset: the chip stopped measuring);
        through the master a single SLV4 read, which never finishes on a sleeping chip."""
        if self.aux_master:
            return self._slv4(reg.CNTL2, self._round_period)
        return self.bus.read_byte_data(reg.AK09916_ADDRESS, reg.CNTL2)

    def power_state(self) -> int:
        """PWR_MGMT_1 now (0x41 after a reset or brown-out: asleep, no samples)."""
        return self.bus.read_byte_data(self.address, reg.PWR_MGMT_1)

    def _retry(self, operation: Callable, *args: int) -> int | list[int] | None:
        """Bring-up transactions are idempotent: retry a transient bus error a few times so one
        glitch does not cost a whole re-initialisation; the last error propagates."""
        return _with_retries(INIT_TRANSACTION_ATTEMPTS, operation, args,
                             lambda: self._sleep(reg.MODE_CHANGE_WAIT_S))

    def _select_bank(self, bank: int) -> None:
        self._retry(
            self.bus.write_byte_data, self.address, reg.REG_BANK_SEL, bank << reg.BANK_SHIFT
        )

    def _write_icm(self, register: int, value: int) -> None:
        self._retry(self.bus.write_byte_data, self.address, register, value)

    def _write_mag(self, register: int, value: int) -> None:
        self._retry(self.bus.write_byte_data, reg.AK09916_ADDRESS, register, value)

    def _unreachable(self, error: OSError, what: str, address: int, hint: str) -> OSError:
        """'Nothing answers' only if nothing at ``address`` answered lately; else the bus is
        unreliable (a device that answers 4 in 10 transactions is not missing)."""
        if self.bus.monitor.answering(address):
            attempts, failures = self.bus.monitor.recent(address)
            return UnreliableBusError(
                error.errno,
                f'{what} at {address:#04x} on {self.bus_name} answers, but {failures} of its last '
                f'{attempts} I2C transactions failed (last: {error}); check wiring, pull-ups, '
                f'cable length and bus speed',
            )
        return DeviceNotFoundError(error.errno, hint)

    def _check_icm20948_identity(self) -> None:
        try:
            self._select_bank(0)
            found = self._retry(self.bus.read_byte_data, self.address, reg.WHO_AM_I)
        except OSError as error:
            raise self._unreachable(
                error, 'the ICM-20948', self.address,
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
            raise self._unreachable(
                error, 'the AK09916', reg.AK09916_ADDRESS,
                f'AK09916 magnetometer did not answer at {reg.AK09916_ADDRESS:#04x} on '
                f'{self.bus_name} with I2C bypass enabled on the ICM-20948 at {self.address:#04x} '
                f'(expected WIA1/WIA2 {reg.WIA1_VALUE:#04x}/{reg.WIA2_VALUE:#04x}; bus error: '
                f'{error})',
            ) from error
        self._check_ak09916_ids(found)

    def _check_ak09916_ids(self, found: list[int]) -> None:
        expected = [reg.WIA1_VALUE, reg.WIA2_VALUE]
        if list(found) != expected:
            raise WrongDeviceError(
                f'device at {reg.AK09916_ADDRESS:#04x} on {self.bus_name} (behind ICM-20948 '
                f'{self.address:#04x}) is not an AK09916: WIA1/WIA2 expected '
                f'{expected[0]:#04x}/{expected[1]:#04x}, found '
                + '/'.join(f'{value:#04x}' for value in found)
            )

    # --- reading ---------------------------------------------------------------------------------

    def read_imu(self) -> ImuReading | None:
        """Poll INT_STATUS_1; on RAW_DATA_0_RDY read the 14-byte burst ACCEL_XOUT_H..TEMP_OUT_L.

        Reading the status clears it, and the burst is a second transaction: a sample landing
        between the two is read by the burst *and* sets the flag again, so the next poll would
        read the same sample twice. A sample can only land there if the burst ended more than one
        (shortest) sample period after the previous status read; then the flag is read once more
        and discarded, so no sample is ever returned twice (at worst one arriving in that
        instant is lost). Returns None when no new sample is ready; ``OSError`` propagates.
        """
        if self.imu is None:
            raise RuntimeError('read_imu() needs initialise() with ImuSettings')
        if self._imu_synced_at is None or self._clock() < self._imu_valid_at:
            self._resync_imu()  # before the gyro's start-up only the accelerometer would be in
            return None
        polled_at = self._clock()
        status = self._read(self.bus.read_byte_data, self.address, reg.INT_STATUS_1)
        since = self._imu_synced_at
        self._imu_synced_at = polled_at
        if not status & reg.INT_STATUS_1_RAW_DATA_0_RDY:
            return None
        length = reg.IMU_BURST_LENGTH
        burst_at = self._clock()
        if self.aux_master and burst_at >= self._mag_due_at:
            length += reg.MAG_MASTER_LENGTH  # through EXT_SLV_SENS_DATA_07 (the copied ST2)
        raw = self._read(self.bus.read_i2c_block_data, self.address, reg.IMU_BURST_START, length)
        if len(raw) != length:
            raise OSError(f'short read from ICM-20948 at {self.address:#04x} on '
                          f'{self.bus_name}: expected {length} bytes, got {len(raw)}')
        if length > reg.IMU_BURST_LENGTH:
            extra = length - reg.IMU_BURST_LENGTH  # 9 bit times each with its ACK
            self.bus.monitor.attribute(MAG_SHARE, extra, 9 * extra)
            self._take_mag_copy(raw[reg.IMU_BURST_LENGTH:], burst_at, since)
        if self._clock() - since >= self._imu_window:
            self.imu_resyncs += 1
            self._imu_synced_at = None
            try:
                self._resync_imu()
            except OSError:
                pass  # still unsynced: the next call starts with the resync
        return self._decode_imu(raw[:reg.IMU_BURST_LENGTH])

    def _take_mag_copy(self, copy: list[int], burst_at: float, since: float) -> None:
        """The master's copy of ST1, HXL..HZH, ST2 as of its last read of the AK09916. It holds a
        sample not yet taken if its copied DRDY is set (only the read that found the sample
        copies DRDY), unless it is the copy taken last seen once more: on the sample clock a copy
        lives one accel/gyro sample, each burst reads a new one, and the looks start again with
        the round the next sample can first be copied by (the round just read came after
        ``since``, the previous data-ready poll); on the duty cycle every burst looks, a copy
        outlives a sample, and the same data with DRDY within one read period of the last take
        is that copy again. Without DRDY a copy whose data differ from the last sample taken is
        a sample whose DRDY copy was missed (a failed burst, a late poll), taken and counted in
        ``mag_fallbacks``. A new sample equal to the previous one in every byte, or all zero as
        the registers read after a reset, is lost if its DRDY copy was missed (never one taken
        twice, never a reset's zeros)."""
        st1, data = copy[0], bytes(copy[1:])
        drdy = bool(st1 & reg.ST1_DRDY)
        duty_cycled = self.fifo or self.master is not None and self.master.odr_config is not None
        if drdy:
            if duty_cycled and data == self._mag_last_copy and burst_at - self._mag_taken_at \
                    < self.master.read_period_s / (1.0 - CLOCK_TOLERANCE):
                return
        elif data == self._mag_last_copy or not any(data):
            return  # not there yet (all zero: the AK09916 just reset): keep lengthening
        else:
            self.mag_fallbacks += 1
        self._mag_last_copy = data
        self._mag_pending = (st1, data)
        self._mag_taken_at = burst_at
        if duty_cycled:
            return  # every burst looks
        # With DRDY the sample arrived after the round before the one just read (itself after
        # ``since``); the next arrives a magnetometer period on (clock tolerance: the AK09916's
        # and the sample clock are two oscillators) and is copied by the first round after it.
        # Found without, it arrived at least a round earlier than that.
        rounds = math.ceil(self._mag_period * (1.0 - CLOCK_TOLERANCE) / self._imu_period
                           - 1.0 - 1e-9) - (0 if drdy else 1)
        self._mag_due_at = since + max(rounds, 0) * self._imu_period * (1.0 - CLOCK_TOLERANCE)

    @staticmethod
    def _read(operation: Callable, *args: int):
        """A read transaction with ``READ_ATTEMPTS`` tries; the last error propagates."""
        return _with_retries(READ_ATTEMPTS, operation, args)

    # --- the FIFO --------------------------------------------------------------------------------

    def read_fifo(self) -> list[tuple[ImuReading, float]]:
        """Drain the FIFO: FIFO_COUNTH/L, then the whole records counted, a few per transaction,
        each checked by its temperature word; through the I2C master, one look at the
        magnetometer's copy. Returns (reading, sample time on this driver's clock), oldest
        first (``FifoTimeline``). The FIFO is reset, and counted, when it filled up
        (``fifo_overflows``: what it held is still read, then the gap is not bridged), when a
        record fails the check or counts stay off whole records (``fifo_corrupt``), and after a
        read that may have taken bytes and failed. ``OSError`` on the count read propagates."""
        if not self.fifo:
            raise RuntimeError('read_fifo() needs initialise() with fifo=True')
        if self._fifo_reset_due:
            self._reset_fifo()
        before = self._clock()
        raw = self._read(self.bus.read_i2c_block_data, self.address, reg.FIFO_COUNTH, 2)
        after = self._clock()
        if len(raw) != 2:
            raise OSError(f'short read from ICM-20948 at {self.address:#04x} on '
                          f'{self.bus_name}: expected the 2 FIFO count bytes, got {len(raw)}')
        count = ((raw[0] & reg.FIFO_COUNT_HIGH_MASK) << 8) | raw[1]
        records, partial = divmod(count, reg.FIFO_RECORD_LENGTH)
        overflowed = count + reg.FIFO_RECORD_LENGTH > reg.FIFO_SIZE
        samples = []
        if partial and not overflowed:
            # A record still being written, or a FIFO out of step: two counts tell them apart.
            if self._fifo_partial:
                self.fifo_corrupt += 1
                self._reset_fifo()
            self._fifo_partial = not self._fifo_partial
        elif records:
            self._fifo_partial = False
            samples = self._read_records(records, before, after, overflowed)
        if self.aux_master:
            self._look_at_mag_copy(after)
        return samples

    def _read_records(self, records: int, before: float, after: float,
                      overflowed: bool) -> list[tuple[ImuReading, float]]:
        times = self._timeline.stamp(records, before, after, complete=not overflowed)
        samples = []
        length = reg.FIFO_RECORD_LENGTH
        for start in range(0, records, FIFO_RECORDS_PER_READ):
            wanted = min(FIFO_RECORDS_PER_READ, records - start) * length
            try:
                data = self._read_fifo_bytes(wanted)
            except OSError:
                self._fifo_reset_due = True  # how many bytes left it is unknown
                if not samples:
                    raise
                break
            for offset in range(0, wanted, length):
                reading = self._decode_imu(data[offset:offset + length])
                if not self._trusted(reading.counts[6]):
                    self.fifo_corrupt += 1
                    self._fifo_reset_due = True
                    break
                samples.append((reading, times[start + offset // length]))
            if self._fifo_reset_due:
                break
        self.fifo_records += len(samples)
        self.fifo_reads += 1
        if overflowed and not self._fifo_reset_due:
            self.fifo_overflows += 1
            self._fifo_reset_due = True
        if self._fifo_reset_due:
            try:
                self._reset_fifo()
            except OSError:
                pass  # due still: the next drain tries first
        return samples

    def _read_fifo_bytes(self, length: int) -> list[int]:
        """``length`` bytes from FIFO_R_W. A NACK (EREMOTEIO: the address or register byte was
        not acknowledged, no data byte moved) is tried once more; any other failure, or a short
        read, may have taken bytes: it propagates."""
        for attempt in range(READ_ATTEMPTS):
            try:
                data = self.bus.read_i2c_block_data(self.address, reg.FIFO_R_W, length)
            except OSError as error:
                if error.errno != errno.EREMOTEIO or attempt == READ_ATTEMPTS - 1:
                    raise
                continue
            if len(data) != length:
                raise OSError(f'short FIFO read from ICM-20948 at {self.address:#04x} on '
                              f'{self.bus_name}: expected {length} bytes, got {len(data)}')
            return data
        return []  # unreachable

    def _trusted(self, temperature: int) -> bool:
        """ArduPilot's sentinel (``fifo.temperature_plausible``), chained record to record: the
        first record after a reset is aligned by the reset, each later one within a
        millisecond or so of the last trusted one."""
        if not temperature_plausible(temperature, self._fifo_temperature):
            return False
        self._fifo_temperature = temperature
        return True

    def _reset_fifo(self, counted: bool = True) -> None:
        """FIFO off, emptied and on again with the accelerometer, gyroscope and temperature in
        snapshot mode, so a full FIFO keeps its oldest whole records rather than overwriting
        bytes (ArduPilot's ``_fifo_reset`` sequence; its FIFO_MODE is snapshot too)."""
        user_ctrl = self._retry(self.bus.read_byte_data, self.address, reg.USER_CTRL)
        self._write_icm(reg.FIFO_EN_2, 0)
        self._write_icm(reg.USER_CTRL, user_ctrl & ~reg.USER_CTRL_FIFO_EN & 0xFF)
        self._write_icm(reg.FIFO_MODE, reg.FIFO_MODE_SNAPSHOT)
        self._write_icm(reg.FIFO_RST, reg.FIFO_RST_ALL)
        self._write_icm(reg.FIFO_RST, 0)
        self._write_icm(reg.USER_CTRL, user_ctrl | reg.USER_CTRL_FIFO_EN)
        self._write_icm(reg.FIFO_EN_2, reg.FIFO_EN_2_ALL)
        self.fifo_resets += counted
        self._fifo_partial = self._fifo_reset_due = False
        if self._timeline is not None:
            self._timeline.restart()

    def _look_at_mag_copy(self, at: float) -> None:
        """With the FIFO, the master's copy of the magnetometer is read once a drain (it lives
        longer than the gap between two: ``master_plan``). A failed look is not an error of
        the drain: the copy is still there at the next."""
        length = reg.MAG_MASTER_LENGTH
        try:
            copy = self._read(self.bus.read_i2c_block_data, self.address,
                              reg.EXT_SLV_SENS_DATA_00, length)
        except OSError:
            return
        if len(copy) != length:
            return
        self.bus.monitor.attribute(MAG_SHARE, 3 + length, 9 * (3 + length) + 3)
        self._take_mag_copy(copy, at, at)

    def _resync_imu(self) -> None:
        at = self._clock()
        self.bus.read_byte_data(self.address, reg.INT_STATUS_1)  # clears a possibly stale flag
        self._imu_synced_at = at

    def _decode_imu(self, raw: list[int]) -> ImuReading:
        counts = _IMU_WORDS.unpack(bytes(raw))
        a, g = self._accel_scale, self._gyro_scale
        saturated = any(c in (reg.INT16_MIN, reg.INT16_MAX) for c in counts[:6])
        return ImuReading(
            linear_acceleration=np.array((counts[0] * a, counts[1] * a, counts[2] * a)),
            angular_velocity=np.array((counts[3] * g, counts[4] * g, counts[5] * g)),
            temperature_c=temperature_celsius(counts[6]),
            counts=counts,
            saturated=saturated,
        )

    def read_mag(self) -> MagReading | None:
        """Bypass: poll ST1 (one byte); on DRDY read HXL..ST2 (8 bytes, ST2 last so the data
        registers never stay locked). Master: the sample the last ``read_imu`` found, no bus
        traffic. Returns None when no new sample is ready or the sample overflowed (counted in
        ``overflows``). ``OSError`` from the bus propagates."""
        if self.aux_master:
            pending, self._mag_pending = self._mag_pending, None
            return None if pending is None else self._decode_mag(*pending)
        st1 = self._read(self.bus.read_byte_data, reg.AK09916_ADDRESS, reg.ST1)
        if not st1 & reg.ST1_DRDY:
            return None
        try:
            raw = self._read(self.bus.read_i2c_block_data, reg.AK09916_ADDRESS,
                             reg.MAG_BURST_START, reg.MAG_BURST_LENGTH)
        except OSError:
            self._release_mag_data()
            raise
        if len(raw) != reg.MAG_BURST_LENGTH:
            self._release_mag_data()
            raise OSError(
                f'short read from AK09916 at {reg.AK09916_ADDRESS:#04x} on {self.bus_name}: '
                f'expected {reg.MAG_BURST_LENGTH} bytes, got {len(raw)}'
            )
        return self._decode_mag(st1, bytes(raw))

    def _decode_mag(self, st1: int, raw: bytes) -> MagReading | None:
        """ST1 and HXL..HZH (TMPS) ST2 -> a reading, or None for an overflow (counted)."""
        overrun = bool(st1 & reg.ST1_DOR)
        if overrun:
            self.overruns += 1
        words = _MAG_WORDS.unpack(raw[:6])
        if raw[-1] & reg.ST2_HOFL or max(abs(w) for w in words) > reg.MEASUREMENT_LIMIT:
            self.overflows += 1
            return None
        counts = np.array(words, dtype=np.int64)
        return MagReading(field_tesla=counts * _TESLA_PER_COUNT, counts=counts, overrun=overrun)

    def _release_mag_data(self) -> None:
        """A data read that broke off before ST2 leaves the AK09916's data protected (no new
        samples) until ST2 is read: read it once, best effort."""
        try:
            self.bus.read_byte_data(reg.AK09916_ADDRESS, reg.ST2)
        except OSError:
            pass


def master_possible(mag_rate_hz: int, imu: ImuSettings | None,
                    odr_config: int | None = None, fifo: bool = False) -> bool:
    """Whether the I2C master path can carry every magnetometer sample (``master_plan``)."""
    return master_plan(mag_rate_hz, imu, odr_config, fifo) is not None

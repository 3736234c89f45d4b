"""Register-level model of an ICM-20948 with its AK09916, behind the smbus2.SMBus methods.

No hardware exists on the development and CI machines, so the driver is exercised against this
model of the chip's registers rather than a mock returning vectors: banks, WHO_AM_I, reset and
sleep, the I2C bypass (the AK09916 answers at 0x0C only with the ICM's I2C master off and bypass
on), the AK09916 measurement modes driven by a clock, ST1/ST2 semantics (DRDY, DOR, HOFL, data
protection until ST2 is read), int16 saturation and 0.15 uT quantisation.

Physics: the board moves along a ``motion`` trajectory through the earth's field; the sensor sees
``soft_iron @ field + hard_iron + noise`` in the chip (accel/gyro) frame, which the AK09916 reports
in its own axes (x, -y, -z). Faults: random I2C errors, an outage (device vanishes) and a chip
reset mid-run. ``truth_for_reading`` gives the true chip-frame earth field behind any reading.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import errno
import math
import os
import time

import numpy as np

from mag_calibrator_ros import motion
from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import tesla_to_counts

MEASUREMENT_TIME_S = 0.0072  # AK09916 measurement duration before the first DRDY in a mode
TRUTH_LOG_SIZE = 8192  # readings remembered for truth_for_reading
REGISTER_STARTUP_S = 0.001  # after DEVICE_RESET the ICM-20948 NACKs for this long
TIME_EPSILON_S = 1e-9  # float tolerance on timing checks
IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def _nack(what: str) -> OSError:
    """What i2c-dev raises when no device acknowledges: OSError(121, 'Remote I/O error')."""
    return OSError(errno.EREMOTEIO, f'{os.strerror(errno.EREMOTEIO)} ({what})')


@dataclass(frozen=True)
class SimConfig:
    """What the simulated board sees and how it misbehaves.

    ``soft_iron`` is a symmetric positive-definite 3x3 matrix, row-major; ``hard_iron_ut`` an
    offset in the chip frame; ``noise_ut`` white noise per axis (1 sigma). ``who_am_i`` and
    ``ak09916_id`` let tests model a wrong chip.
    """

    field_ut: float = 50.0
    inclination_deg: float = 60.0
    hard_iron_ut: Sequence[float] = (0.0, 0.0, 0.0)
    soft_iron: Sequence[float] = IDENTITY
    noise_ut: float = 0.3
    motion: str = 'tumble'
    i2c_error_rate: float = 0.0
    seed: int = 0
    address: int = reg.ICM20948_DEFAULT_ADDRESS
    who_am_i: int = reg.WHO_AM_I_VALUE
    ak09916_id: tuple[int, int] = (reg.WIA1_VALUE, reg.WIA2_VALUE)
    # Derived, validated copies (filled in __post_init__).
    hard_iron: np.ndarray = field(init=False, repr=False, compare=False)
    soft_iron_matrix: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        problems = config_problems(self)
        if problems:
            raise ValueError('invalid simulator configuration: ' + '; '.join(problems))
        object.__setattr__(self, 'hard_iron', np.asarray(self.hard_iron_ut, dtype=float))
        matrix = np.asarray(self.soft_iron, dtype=float).reshape(3, 3)
        object.__setattr__(self, 'soft_iron_matrix', matrix)


def config_problems(config: SimConfig) -> list[str]:
    """Every problem with a simulator configuration, spelled out (empty when valid)."""
    problems = []

    def finite(name: str, value: object) -> bool:
        try:
            ok = math.isfinite(float(value))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            problems.append(f'{name} must be a finite number, got {value!r}')
        return ok

    if finite('field_ut', config.field_ut) and not 0.0 < config.field_ut <= 4900.0:
        problems.append(f'field_ut must be in (0, 4900] uT (AK09916 range), got {config.field_ut}')
    if finite('inclination_deg', config.inclination_deg) and abs(config.inclination_deg) > 90.0:
        problems.append(f'inclination_deg must be within [-90, 90], got {config.inclination_deg}')
    if finite('noise_ut', config.noise_ut) and config.noise_ut < 0.0:
        problems.append(f'noise_ut must be >= 0, got {config.noise_ut}')
    if finite('i2c_error_rate', config.i2c_error_rate) and not (
        0.0 <= config.i2c_error_rate < 1.0
    ):
        problems.append(f'i2c_error_rate must be in [0, 1), got {config.i2c_error_rate}')
    if config.motion not in motion.TRAJECTORY_KINDS:
        problems.append(
            f"motion must be one of {', '.join(motion.TRAJECTORY_KINDS)}, got {config.motion!r}"
        )
    if config.address not in reg.ICM20948_ADDRESSES:
        problems.append(f'address must be 0x68 or 0x69, got {config.address!r}')
    hard = np.asarray(config.hard_iron_ut, dtype=float) if _numeric(config.hard_iron_ut) else None
    if hard is None or hard.shape != (3,) or not np.all(np.isfinite(hard)):
        problems.append(f'hard_iron_ut must be 3 finite numbers (uT), got {config.hard_iron_ut!r}')
    soft = np.asarray(config.soft_iron, dtype=float) if _numeric(config.soft_iron) else None
    if soft is None or soft.shape != (9,) or not np.all(np.isfinite(soft)):
        problems.append(
            f'soft_iron must be 9 finite numbers (row-major 3x3), got {config.soft_iron!r}'
        )
    else:
        matrix = soft.reshape(3, 3)
        if not np.allclose(matrix, matrix.T, atol=1e-9):
            problems.append('soft_iron must be symmetric')
        elif np.linalg.eigvalsh(matrix).min() <= 0.0:
            problems.append('soft_iron must be positive definite')
    return problems


def _numeric(values: object) -> bool:
    try:
        np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return False
    return True


class SimulatedIcm20948Bus:
    """An I2C bus with one ICM-20948 (+ AK09916) on it, speaking the smbus2.SMBus methods.

    Time comes from ``clock`` (seconds, monotonic); inject a fake clock to run tests without
    sleeping. Any device outside the model NACKs with ``OSError(EREMOTEIO)`` like real i2c-dev.
    """

    def __init__(
        self, config: SimConfig | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.config = config if config is not None else SimConfig()
        self._clock = clock
        self._t0 = clock()
        self._trajectory = motion.make_trajectory(self.config.motion, self.config.seed)
        self._earth_ut = motion.earth_field(self.config.field_ut, self.config.inclination_deg)
        self._noise_rng = np.random.default_rng([self.config.seed, 10])
        self._fault_rng = np.random.default_rng([self.config.seed, 11])
        self._truth: OrderedDict[tuple[int, int, int], np.ndarray] = OrderedDict()
        self._outage_until = -math.inf
        self._reset_after_outage = False
        self.transactions = 0
        self.injected_errors = 0
        self.samples_measured = 0
        self._power_on()

    # --- power and faults ------------------------------------------------------------------------

    def _power_on(self) -> None:
        """Power-on state of both dies: ICM asleep in bank 0, bypass off, AK09916 powered down."""
        self._bank = 0
        self._banks = [bytearray(128) for _ in range(4)]
        self._banks[0][reg.PWR_MGMT_1] = reg.PWR_MGMT_1_RESET_VALUE
        self._icm_ready_at = -math.inf
        self._ak_power_on()

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

    def chip_reset(self) -> None:
        """A brown-out: registers back to power-on (asleep, bypass off, AK09916 powered down)."""
        self._power_on()

    def start_outage(self, duration_s: float, reset: bool = True) -> None:
        """The device vanishes from the bus for ``duration_s``; with ``reset`` it comes back
        power-cycled (a loose connector drops the supply too)."""
        if not math.isfinite(duration_s) or duration_s < 0.0:
            raise ValueError(f'outage duration must be finite and >= 0 s, got {duration_s}')
        self._outage_until = self._clock() + duration_s
        self._reset_after_outage = reset

    @property
    def in_outage(self) -> bool:
        return self._clock() < self._outage_until

    def _now(self) -> float:
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

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        self._transaction(i2c_addr, f'read of register {register:#04x}')
        return self._read_register(i2c_addr, register)

    def write_byte_data(
        self, i2c_addr: int, register: int, value: int, force: bool | None = None
    ) -> None:
        self._transaction(i2c_addr, f'write of register {register:#04x}')
        self._write_register(i2c_addr, register, value & 0xFF)

    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]:
        if not 0 < length <= 32:
            raise ValueError(f'Desired block length over 32 bytes or below 1: {length}')
        self._transaction(i2c_addr, f'block read from register {register:#04x}')
        return [self._read_register(i2c_addr, register + i) for i in range(length)]

    def write_i2c_block_data(
        self, i2c_addr: int, register: int, data: Sequence[int], force: bool | None = None
    ) -> None:
        self._transaction(i2c_addr, f'block write to register {register:#04x}')
        for i, value in enumerate(data):
            self._write_register(i2c_addr, register + i, value & 0xFF)

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
        return self._banks[self._bank][register]

    def _write_register(self, i2c_addr: int, register: int, value: int) -> None:
        if i2c_addr == reg.AK09916_ADDRESS:
            self._write_ak(register, value)
            return
        register &= 0x7F
        if register == reg.REG_BANK_SEL:
            self._bank = (value & reg.BANK_MASK) >> reg.BANK_SHIFT
            return
        if self._bank == 0 and register == reg.WHO_AM_I:
            return  # read-only
        if self._bank == 0 and register == reg.PWR_MGMT_1 and value & reg.PWR_MGMT_1_DEVICE_RESET:
            # Resets the ICM-20948 die only; the AK09916 keeps its state.
            self._bank = 0
            self._banks = [bytearray(128) for _ in range(4)]
            self._banks[0][reg.PWR_MGMT_1] = reg.PWR_MGMT_1_RESET_VALUE
            self._icm_ready_at = self._now() + REGISTER_STARTUP_S
            return
        if self._bank == 0 and register == reg.USER_CTRL:
            value &= ~reg.USER_CTRL_I2C_MST_RST & 0xFF  # self-clearing
        self._banks[self._bank][register] = value

    def _read_ak(self, register: int) -> int:
        if register == reg.WIA1:
            return self.config.ak09916_id[0]
        if register == reg.WIA2:
            return self.config.ak09916_id[1]
        if register == reg.ST1:
            return (reg.ST1_DRDY if self._drdy else 0) | (reg.ST1_DOR if self._dor else 0)
        if reg.HXL <= register <= reg.TMPS:
            self._locked = True  # data protection until ST2 is read
            return self._data[register - reg.HXL]
        if register == reg.ST2:
            value = self._data[7]
            self._drdy = False
            self._dor = False
            self._locked = False
            if self._pending is not None:  # a sample finished during the read: latch it now
                data, truth = self._pending
                self._pending = None
                self._latch(data, truth)
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
        self._mode = value
        self._mode_since = self._now()
        self._next_sample_index = 0

    # --- measurement -----------------------------------------------------------------------------

    def _advance(self) -> None:
        """Complete every measurement due by now; only the newest reaches the registers."""
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
        data, truth = self._measure(sample_time)
        if self._locked:
            if self._pending is not None or skipped:
                self._dor = True
            self._pending = (data, truth)
            return
        if self._drdy or skipped:
            self._dor = True
        self._latch(data, truth)

    def _latch(self, data: bytearray, truth: np.ndarray) -> None:
        self._data = data
        self._drdy = True
        counts = tuple(int(c) for c in np.frombuffer(bytes(data[:6]), dtype='<i2'))
        self._truth[counts] = truth
        self._truth.move_to_end(counts)
        while len(self._truth) > TRUTH_LOG_SIZE:
            self._truth.popitem(last=False)

    def _measure(self, t: float) -> tuple[bytearray, np.ndarray]:
        """Registers HXL..ST2 for a sample taken at sim time ``t``, and its true field (T)."""
        rotation = self._trajectory.orientation(max(t, 0.0))
        earth_chip_ut = rotation.T @ self._earth_ut
        sensed_ut = self.config.soft_iron_matrix @ earth_chip_ut + self.config.hard_iron
        if self.config.noise_ut > 0.0:
            sensed_ut = sensed_ut + self._noise_rng.normal(0.0, self.config.noise_ut, 3)
        counts = tesla_to_counts(sensed_ut * 1e-6)  # AK09916 axes, quantised
        overflow = bool(np.any(np.abs(counts) > reg.MEASUREMENT_LIMIT))
        counts = np.clip(counts, -reg.MEASUREMENT_LIMIT, reg.MEASUREMENT_LIMIT)
        data = bytearray(counts.astype('<i2').tobytes())
        data += bytes([0, reg.ST2_HOFL if overflow else 0])
        return data, earth_chip_ut * 1e-6

    # --- ground truth ----------------------------------------------------------------------------

    def truth_for_reading(self, field_tesla: np.ndarray) -> np.ndarray | None:
        """True chip-frame earth field (T) of the sample behind a published reading, or None if it
        is not (or no longer) in the log. Readings with identical counts map to the newest."""
        counts = tuple(int(c) for c in tesla_to_counts(field_tesla))
        truth = self._truth.get(counts)
        return None if truth is None else truth.copy()

    def true_field_now(self) -> np.ndarray:
        """True chip-frame earth field (T) at the current time (for the demo's live view)."""
        rotation = self._trajectory.orientation(max(self._now(), 0.0))
        return rotation.T @ self._earth_ut * 1e-6

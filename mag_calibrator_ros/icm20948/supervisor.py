# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Keeps an ICM-20948 producing samples through bus faults: the driver's state machine, no rclpy.

One decision-maker for the chip's life cycle, so the ROS node only wires it up: when to poll each
sensor, when to (re-)initialise and how long to back off, what counts as a stuck data-ready, which
samples to hand out (never one twice, never an invalid one), rate windows, and what diagnostics
say. ``step()`` does whatever is due at the injected clock's "now" and returns the new samples;
``run()`` loops ``step()`` on a thread until stopped. Tests drive ``step()`` with a fake clock.

Polling: each data-ready flag is checked ``POLLS_PER_SAMPLE`` times per sample period; both
sensors hold a sample until the next one arrives, so a poll may come a third of a period late
before anything is lost, while an idle poll costs one byte of payload (ST1 / INT_STATUS_1).
Through the chip's I2C master (the default whenever the accelerometer/gyroscope are polled and
run fast enough) the magnetometer has no poll of its own: its samples come with the accel/gyro
reads. With the FIFO (``imu_fifo``) the accelerometer/gyroscope have no data-ready poll: the
FIFO is drained every ``driver.fifo_drain_period`` and each record stamped by the chip's clock.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
import threading
import time

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.bus import BusCounters, BusMonitor, CountingBus, SmbusLike
from mag_calibrator_ros.icm20948.driver import (
    MAG_SHARE,
    POLLS_PER_SAMPLE,
    Icm20948,
    ImuReading,
    ImuSettings,
    MagReading,
    MasterPlan,
    WrongDeviceError,
    fifo_drain_period,
    master_plan,
    master_possible,
)

# Reads failing this many times in a row for at least this long mean the device is gone or reset:
# re-initialise. (The time matters at kHz polling, where a few failures in a row are chance.)
ERRORS_BEFORE_REINIT = 3
FAILING_BEFORE_REINIT_S = 0.05
# No data-ready for this many sample periods (and at least STUCK_MIN_S) means a sensor stopped.
STUCK_PERIODS = 5
STUCK_MIN_S = 0.25
BACKOFF_INITIAL_S = 0.1
BACKOFF_MAX_S = 0.5  # cheap to retry (a few dozen register accesses); recover fast
TEMPERATURE_HZ = 10.0  # temperature changes slowly: publish at most this often
WARNING_PERIOD_S = 10.0  # repeated warnings (overflow, saturation, read errors) at most this often
RATE_WARN_FRACTION = 0.8  # diagnostics WARN below this share of the expected rate

OK, WARN, ERROR = 0, 1, 2


@dataclass(frozen=True)
class MagSample:
    stamp: object  # from the supervisor's ``stamp`` callable, taken when the sample was read
    reading: MagReading


@dataclass(frozen=True)
class ImuSample:
    stamp: object  # polled: when read; from the FIFO: when sampled (``stamp_ago``)
    reading: ImuReading


@dataclass(frozen=True)
class TemperatureSample:
    stamp: object  # the stamp of the inertial sample it came with
    celsius: float


Sample = MagSample | ImuSample | TemperatureSample


@dataclass(frozen=True)
class StreamStatus:
    """One diagnostics entry: ``stream`` is 'magnetometer' or 'imu'; ``level`` OK/WARN/ERROR."""

    stream: str
    level: int
    message: str
    values: dict[str, object] = field(default_factory=dict)


@dataclass
class _Stream:
    """Polling and bookkeeping of one data-ready source."""

    period: float
    poll_period: float
    stuck_after: float
    next_poll: float = 0.0
    last_ready: float = 0.0
    in_vain_since: float | None = None  # the first look without data-ready since last_ready
    in_vain: int = 0  # looks without data-ready since last_ready
    emitted: int = 0
    window_emitted: int = 0


class Icm20948Supervisor:
    """Owns the bus and the driver; turns polls into samples and faults into recovery.

    ``open_bus`` returns a fresh smbus2-like bus (called again after a fault: a USB adapter may
    come back as a new device). ``imu`` None leaves the accelerometer and gyroscope powered down.
    ``stamp`` gives the stamp attached to each sample (the node passes its ROS clock); ``log``
    receives (level, message) with level 'info' | 'warning' | 'error'. ``mag_via_master``: read
    the AK09916 through the chip's I2C master whenever ``master_possible`` for
    ``master_odr_config`` (None: on the accel/gyro sample clock, which needs them at least
    twice the magnetometer rate when polled; n: the master's duty cycle at 1.1 kHz / 2^n), else
    in bypass; None (default): through the master when polled (its copy rides on each
    accel/gyro burst: 8-10 wire bytes a sample), in bypass with the FIFO (no burst to ride on:
    bypass's 17 bytes a sample and 4 a look at ST1 cost less than a look at the copy each
    drain, and its DRDY is the AK09916's own).
    ``imu_fifo``: accelerometer, gyroscope and temperature from the chip's FIFO, drained every
    ``fifo_drain_period``, each sample stamped by ``stamp_ago(age_s)`` with the time it was
    sampled (``FifoTimeline``; without ``stamp_ago``, when it was read); else polled.
    """

    def __init__(
        self,
        open_bus: Callable[[], SmbusLike],
        *,
        address: int = reg.ICM20948_DEFAULT_ADDRESS,
        bus_name: str = '/dev/i2c-1',
        mag_rate_hz: int = 100,
        imu: ImuSettings | None = None,
        publish_imu: bool = True,
        publish_temperature: bool = True,
        mag_via_master: bool | None = None,
        master_odr_config: int | None = None,
        imu_fifo: bool = False,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        stamp: Callable[[], object] | None = None,
        stamp_ago: Callable[[float], object] | None = None,
        log: Callable[[str, str], None] | None = None,
    ) -> None:
        if mag_rate_hz not in reg.CONTINUOUS_MODES:
            raise ValueError(f'mag_rate_hz must be one of {sorted(reg.CONTINUOUS_MODES)}, '
                             f'got {mag_rate_hz}')
        if imu is not None and imu.problems():
            raise ValueError('; '.join(imu.problems()))
        if imu is None and (publish_imu or publish_temperature):
            raise ValueError('publish_imu and publish_temperature need ImuSettings')
        self._open_bus = open_bus
        self.address = address
        self.bus_name = bus_name
        self.mag_rate_hz = mag_rate_hz
        self.imu_settings = imu
        self.publish_imu = publish_imu
        self.publish_temperature = publish_temperature
        self.imu_fifo = imu_fifo and imu is not None
        if mag_via_master is None:
            mag_via_master = not self.imu_fifo
        self.aux_master = mag_via_master and master_possible(mag_rate_hz, imu, master_odr_config,
                                                             self.imu_fifo)
        self.master_odr_config = master_odr_config
        # The magnetometer is looked at with each accel/gyro read rather than on its own clock:
        # through the master (its copy comes with them), and with the FIFO (each drain is a
        # wake-up anyway, sooner than the 1.5 a sample its own polls would be: on a busy
        # machine a sample then has to wait out fewer late looks before the next replaces it).
        self._mag_with_imu = self.aux_master or self.imu_fifo
        self._clock = clock
        self._sleep = sleep
        self._stamp = stamp if stamp is not None else time.time_ns
        if stamp_ago is None:
            stamp_ago = ((lambda age: self._stamp()) if stamp is not None
                         else (lambda age: time.time_ns() - round(age * 1e9)))
        self._stamp_ago = stamp_ago
        self._log = log if log is not None else (lambda level, message: None)
        self._lock = threading.Lock()
        self.monitor = BusMonitor({reg.AK09916_ADDRESS: MAG_SHARE})
        self._bus: CountingBus | None = None
        self._driver: Icm20948 | None = None
        self.running = False
        self.last_error = ''
        self._next_attempt = clock()
        self._backoff = BACKOFF_INITIAL_S
        self._episode_start: float | None = None
        self._episode_logged = False
        self._consecutive_errors = 0
        self._failing_since = 0.0
        self._warned_at: dict[str, float] = {}
        self._base = {'overflows': 0, 'overruns': 0, 'imu_resyncs': 0, 'mag_fallbacks': 0,
                      'fifo_overflows': 0, 'fifo_resets': 0, 'fifo_corrupt': 0,
                      'fifo_records': 0, 'fifo_reads': 0}
        self.reinitialisations = 0
        self.last_recovery_s: float | None = None
        self.imu_saturated = 0
        self.temperatures = 0
        self._last_temperature_at = -float('inf')
        self._last_celsius: float | None = None
        self._window_start = clock()
        self._window_bus = BusCounters()
        self._window_mag_bus = BusCounters()
        self._window_counts = (0, 0, 0, 0)  # errors, overflows, saturated, FIFO faults
        mag_period = 1.0 / mag_rate_hz
        self._mag = _Stream(mag_period, mag_period / POLLS_PER_SAMPLE,
                            max(STUCK_PERIODS * mag_period, STUCK_MIN_S))
        self._imu: _Stream | None = None
        if imu is not None:
            imu_period = 1.0 / imu.odr_hz
            poll_period = imu_period / POLLS_PER_SAMPLE if not self.imu_fifo else \
                fifo_drain_period(self._plan())
            self._imu = _Stream(imu_period, poll_period,
                                max(STUCK_PERIODS * max(imu_period, poll_period), STUCK_MIN_S)
                                + reg.SENSOR_STARTUP_S)

    # --- counters --------------------------------------------------------------------------------

    @property
    def i2c_errors(self) -> int:
        """Failed I2C transactions of any kind (bring-up retries included)."""
        return self.monitor.counters.errors

    def _driver_count(self, name: str) -> int:
        return self._base[name] + (getattr(self._driver, name) if self._driver else 0)

    @property
    def overflows(self) -> int:
        return self._driver_count('overflows')

    @property
    def overruns(self) -> int:
        return self._driver_count('overruns')

    @property
    def imu_resyncs(self) -> int:
        return self._driver_count('imu_resyncs')

    @property
    def fifo_overflows(self) -> int:
        """Times the FIFO filled up (samples lost; it was reset)."""
        return self._driver_count('fifo_overflows')

    @property
    def fifo_resets(self) -> int:
        """FIFO resets after bring-up: overflows, torn reads, corrupt records."""
        return self._driver_count('fifo_resets')

    @property
    def fifo_corrupt(self) -> int:
        """FIFO records or counts that failed the sentinel (misaligned or garbage)."""
        return self._driver_count('fifo_corrupt')

    @property
    def fifo_records_per_read(self) -> float:
        reads = self._driver_count('fifo_reads')
        return self._driver_count('fifo_records') / reads if reads else 0.0

    @property
    def mag_fallbacks(self) -> int:
        """Magnetometer samples found through the master without their copied DRDY."""
        return self._driver_count('mag_fallbacks')

    def _plan(self) -> MasterPlan | None:
        if not self.aux_master:
            return None
        return master_plan(self.mag_rate_hz, self.imu_settings, self.master_odr_config,
                           self.imu_fifo)

    @property
    def master_clock(self) -> str:
        """The I2C master's round clock as the driver set it up, for people."""
        if not self.aux_master:
            return 'none (bypass)'
        plan = self._plan()
        if plan.odr_config is None and plan.delay:
            return (f'{plan.round_hz:.1f} Hz, the accel/gyro sample clock (I2C_MST_CYCLE 0), '
                    f'the AK09916 read every {1 + plan.delay} rounds')
        if plan.odr_config is None:
            return f'{plan.round_hz:.1f} Hz, one round per accel/gyro sample (I2C_MST_CYCLE 0)'
        return (f'{plan.round_hz:.1f} Hz duty cycle (I2C_MST_ODR_CONFIG {plan.odr_config}), '
                f'the AK09916 read every {1 + plan.delay} rounds')

    # --- the loop --------------------------------------------------------------------------------

    def next_due(self) -> float:
        """Clock time of the next step worth taking."""
        with self._lock:
            if not self.running:
                return self._next_attempt
            due = self._mag.next_poll
            if self._imu is not None:
                due = min(due, self._imu.next_poll)
            return due

    def step(self) -> list[Sample]:
        """Do whatever is due now (bring-up or polls); return the new samples in read order."""
        with self._lock:
            now = self._clock()
            if not self.running:
                if now >= self._next_attempt:
                    self._try_initialise(now)
                return []
            samples: list[Sample] = []
            if self._imu is not None and now >= self._imu.next_poll:
                self._poll_imu(now, samples)
                if self.running and self._mag_with_imu:
                    # through the master: what that read brought, no bus traffic; in bypass
                    # with the FIFO: a look at ST1 with each drain, more often than alone
                    self._poll_mag(now, samples)
            if self.running and now >= self._mag.next_poll:
                self._poll_mag(now, samples)
            return samples

    def run(self, stop: threading.Event, deliver: Callable[[list[Sample]], object]) -> None:
        """Step until ``stop`` is set, handing samples to ``deliver`` (False from it stops)."""
        while not stop.is_set():
            delay = self.next_due() - self._clock()
            if delay > 0.0 and stop.wait(delay):
                break
            try:
                samples = self.step()
            except Exception as error:  # a defect must not silently end the acquisition
                with self._lock:
                    self._fault(f'unexpected error: {error!r}', self._clock())
                continue
            if samples and deliver(samples) is False:
                break

    def close(self) -> None:
        with self._lock:
            self.running = False
            self._close_bus()

    # --- life cycle ------------------------------------------------------------------------------

    def _try_initialise(self, now: float) -> None:
        try:
            if self._bus is None:
                self._bus = CountingBus(self._open_bus(), self.monitor)
            driver = Icm20948(self._bus, self.address, self.bus_name, self._sleep, self._clock)
            driver.initialise(self.mag_rate_hz, self.imu_settings, self.aux_master,
                              self.master_odr_config, self.imu_fifo)
        except (OSError, WrongDeviceError) as error:
            self._fault(f'initialisation failed: {error}', now)
            self._close_bus()  # a USB adapter may come back as a new device: reopen next time
            return
        self._retire_driver()
        self._driver = driver
        self.running = True
        self._consecutive_errors = 0
        self._backoff = BACKOFF_INITIAL_S
        started = self._clock()
        for stream in (self._mag, self._imu):
            if stream is not None:
                stream.next_poll = started + stream.poll_period
                stream.last_ready, stream.in_vain_since, stream.in_vain = started, None, 0
        if self._mag_with_imu:
            self._mag.next_poll = float('inf')  # taken with each accel/gyro read instead
        if self._episode_start is not None:
            self.last_recovery_s = started - self._episode_start
            self.reinitialisations += 1
            self._log('info', f'ICM-20948 back after {self.last_recovery_s:.2f} s; '
                              f'publishing again')
            self._episode_start = None
            self._episode_logged = False

    def _retire_driver(self) -> None:
        if self._driver is not None:
            for name in self._base:
                self._base[name] += getattr(self._driver, name)
            self._driver = None

    def _fault(self, message: str, now: float) -> None:
        """Enter (or stay in) a fault episode; the first message of an episode is logged."""
        self.last_error = message
        self.running = False
        if self._episode_start is None:
            self._episode_start = now
        if not self._episode_logged:
            self._episode_logged = True
            self._log('error', f'icm20948@{self.bus_name}:{self.address:#04x}: {message}; '
                               f'retrying with back-off up to {BACKOFF_MAX_S:g} s (logged once '
                               f'until it recovers)')
        self._next_attempt = now + self._backoff
        self._backoff = min(2.0 * self._backoff, BACKOFF_MAX_S)

    def _close_bus(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.close()
            except OSError:
                pass

    def _warn(self, key: str, message: str, now: float) -> None:
        if now - self._warned_at.get(key, -float('inf')) >= WARNING_PERIOD_S:
            self._warned_at[key] = now
            self._log('warning', message)

    # --- polling ---------------------------------------------------------------------------------

    @staticmethod
    def _schedule(stream: _Stream, now: float) -> None:
        """Next poll one poll period on; after a late step, from now (no catch-up bursts)."""
        stream.next_poll += stream.poll_period
        if stream.next_poll <= now:
            stream.next_poll = now + stream.poll_period

    def _poll_imu(self, now: float, samples: list[Sample]) -> None:
        stream = self._imu
        self._schedule(stream, now)
        try:
            if self.imu_fifo:
                timed = self._driver.read_fifo()
            else:
                reading = self._driver.read_imu()
                timed = [] if reading is None else [(reading, None)]
        except OSError as error:
            self._read_error(error, now)
            return
        self._consecutive_errors = 0
        if not timed:
            if self._looked_in_vain(stream):
                self._check_imu_stuck(now)
            return
        # When the read ended, not when the step began: a thread descheduled inside the read
        # saw this data-ready after the stall, and its resync may clear the next one's flag.
        read_at = self._clock()
        stream.last_ready, stream.in_vain_since, stream.in_vain = read_at, None, 0
        for reading, sampled_at in timed:
            if sampled_at is None:
                self._emit_imu(reading, self._stamp(), now, samples)
            else:
                self._emit_imu(reading, self._stamp_ago(max(read_at - sampled_at, 0.0)),
                               sampled_at, samples)

    def _emit_imu(self, reading: ImuReading, stamp: object, at: float,
                  samples: list[Sample]) -> None:
        """One inertial sample (and, at most ``TEMPERATURE_HZ``, its temperature) handed on;
        ``at``: its time on this clock, for the temperature's rate."""
        stream, now = self._imu, at
        if reading.saturated:
            self.imu_saturated += 1
            self._warn('saturated', 'accelerometer or gyroscope at full scale: the true value '
                                    'may be larger (raise accel_range_g / gyro_range_dps)', now)
        self._last_celsius = reading.temperature_c
        if self.publish_imu:
            stream.emitted += 1
            stream.window_emitted += 1
            samples.append(ImuSample(stamp, reading))
        if self.publish_temperature and now - self._last_temperature_at >= 1.0 / TEMPERATURE_HZ:
            self._last_temperature_at = now
            self.temperatures += 1
            samples.append(TemperatureSample(stamp, reading.temperature_c))

    def _poll_mag(self, now: float, samples: list[Sample]) -> None:
        stream = self._mag
        self._schedule(stream, now)
        overflows = self._driver.overflows
        try:
            reading = self._driver.read_mag()
        except OSError as error:
            self._read_error(error, now)
            return
        if not self.aux_master:  # through the master read_mag touches no bus: proves nothing
            self._consecutive_errors = 0
        if self._driver.overflows != overflows:
            # a sample arrived, it was just unusable
            stream.last_ready, stream.in_vain_since, stream.in_vain = self._clock(), None, 0
            self._warn('overflow', 'AK09916 magnetic overflow (ST2 HOFL): sample discarded; a '
                                   'magnet or motor too close?', now)
        if reading is None:
            if self._looked_in_vain(stream):
                self._check_mag_stuck(now)
            return
        stream.last_ready, stream.in_vain_since, stream.in_vain = self._clock(), None, 0
        stream.emitted += 1
        stream.window_emitted += 1
        samples.append(MagSample(self._stamp(), reading))

    def _looked_in_vain(self, stream: _Stream) -> bool:
        """True once ``stream`` was looked at STUCK_PERIODS times and for ``stuck_after``
        without a data-ready, counted from the first such look since its last sample (the read
        ends it: its clock, not the step's). A stall of this thread on a loaded computer (no
        look at all for a while, or a resync clearing the flag of a sample that came during
        it) is no stuck sensor, and must not cost a re-initialisation and its back-off."""
        looked_at = self._clock()
        if stream.in_vain_since is None:
            stream.in_vain_since = looked_at
        stream.in_vain += 1
        return (stream.in_vain >= STUCK_PERIODS
                and looked_at - stream.in_vain_since > stream.stuck_after)

    def _read_error(self, error: OSError, now: float) -> None:
        if self._consecutive_errors == 0:
            self._failing_since = now
        self._consecutive_errors += 1
        self.last_error = f'I2C read failed: {error}'
        if (self._consecutive_errors >= ERRORS_BEFORE_REINIT
                and now - self._failing_since >= FAILING_BEFORE_REINIT_S):
            self._fault(f'{self._consecutive_errors} I2C reads failed in a row (last: {error}); '
                        f'device gone or reset, re-initialising', now)
        else:
            self._warn('read', f'icm20948@{self.bus_name}:{self.address:#04x}: I2C read failed '
                               f'({error}); retrying', now)

    def _check_mag_stuck(self, now: float) -> None:
        """No DRDY for too long: did the AK09916 leave continuous mode? Through the master a
        sleeping ICM-20948 (a reset) stops it too: that is asked first, as for the IMU."""
        if self.aux_master:
            try:
                asleep = self._driver.power_state() & reg.PWR_MGMT_1_SLEEP
            except OSError:
                asleep = False  # the CNTL2 probe below says it does not answer
            if asleep:
                self._check_imu_stuck(now)
                return
        expected = reg.CONTINUOUS_MODES[self.mag_rate_hz]
        self._stuck(now, self._mag, 'magnetometer', 'AK09916', self._driver.measurement_mode,
                    lambda mode: f'AK09916 left continuous mode (CNTL2 expected {expected:#04x}, '
                                 f'found {mode:#04x}): chip reset?' if mode != expected
                    else 'AK09916 data-ready stuck although in continuous mode')

    def _check_imu_stuck(self, now: float) -> None:
        """No raw-data-ready for too long: asleep (a reset) or stuck?"""
        self._stuck(now, self._imu, 'accel/gyro', 'ICM-20948', self._driver.power_state,
                    lambda power: f'ICM-20948 asleep (PWR_MGMT_1 {power:#04x}): chip reset?'
                    if power & reg.PWR_MGMT_1_SLEEP
                    else f'raw-data-ready stuck although awake (PWR_MGMT_1 {power:#04x})')

    def _stuck(self, now: float, stream: _Stream, sensor: str, chip: str,
               probe: Callable[[], int], explain: Callable[[int], str]) -> None:
        """A data-ready that stopped is a fault either way; the probed register says why."""
        waited = f'no {sensor} data-ready for {now - stream.last_ready:.2f} s'
        try:
            value = probe()
        except OSError as error:
            self._fault(f'{waited} and the {chip} does not answer ({error})', now)
            return
        self._fault(f'{waited}; {explain(value)}', now)

    # --- diagnostics -----------------------------------------------------------------------------

    def status(self) -> list[StreamStatus]:
        """Diagnostics for each sensor stream; each call closes a rate window."""
        with self._lock:
            now = self._clock()
            elapsed = max(now - self._window_start, 1e-9)
            bus_window = self.monitor.counters - self._window_bus
            mag_bus = self.monitor.share(MAG_SHARE)
            mag_window, self._window_mag_bus = mag_bus - self._window_mag_bus, mag_bus
            counts = (self.i2c_errors, self.overflows, self.imu_saturated,
                      self.fifo_overflows + self.fifo_corrupt)
            errors, overflows, saturated, fifo_faults = (
                a - b for a, b in zip(counts, self._window_counts, strict=True))
            self._window_start, self._window_bus = now, self.monitor.counters
            self._window_counts = counts
            total = self.monitor.counters
            shared = {
                'bus': self.bus_name,
                'address': f'{self.address:#04x}',
                'i2c errors': total.errors,
                'i2c transactions': total.transactions,
                'i2c bytes/s': bus_window.wire_bytes / elapsed,
                'bus load (% of 400 kHz)': 100.0 * bus_window.bits / elapsed
                / reg.I2C_STANDARD_FAST_HZ,
                'reinitialisations': self.reinitialisations,
                'last error': self.last_error,
            }
            bus_warnings = [f'{errors} I2C errors in the last {elapsed:.1f} s (wiring?)'] \
                if errors else []
            mag_rate = self._mag.window_emitted / elapsed
            self._mag.window_emitted = 0
            mag_warnings = list(bus_warnings)
            if mag_rate < RATE_WARN_FRACTION * self.mag_rate_hz:
                mag_warnings.insert(0, f'{mag_rate:.1f} Hz of {self.mag_rate_hz} Hz requested')
            if overflows:
                mag_warnings.append(f'{overflows} overflowed samples discarded (magnet nearby?)')
            statuses = [self._stream_status('magnetometer', mag_rate, mag_warnings, {
                'requested rate (Hz)': self.mag_rate_hz,
                'measured rate (Hz)': mag_rate,
                'published': self._mag.emitted,
                **shared,
                'overflows (HOFL)': self.overflows,
                'overruns (DOR)': self.overruns,
                'path': 'I2C master' if self.aux_master else 'bypass',
                'I2C master clock': self.master_clock,
                'samples without DRDY': self.mag_fallbacks,
                'magnetometer i2c bytes/s': mag_window.wire_bytes / elapsed,
            })]
            if self._imu is not None:
                settings = self.imu_settings
                imu_rate = self._imu.window_emitted / elapsed
                self._imu.window_emitted = 0
                imu_warnings = list(bus_warnings)
                if self.publish_imu and imu_rate < RATE_WARN_FRACTION * settings.odr_hz:
                    imu_warnings.insert(0, f'{imu_rate:.1f} Hz of {settings.odr_hz:.1f} Hz')
                if saturated:
                    imu_warnings.append(f'{saturated} samples at full scale (range too small?)')
                if fifo_faults:
                    imu_warnings.append(f'{fifo_faults} FIFO overflows or corrupt records, '
                                        f'FIFO reset (read too late: machine busy?)')
                fifo_values = {
                    'FIFO overflows': self.fifo_overflows,
                    'FIFO resets': self.fifo_resets,
                    'FIFO corrupt records': self.fifo_corrupt,
                    'FIFO records per read': self.fifo_records_per_read,
                } if self.imu_fifo else {}
                statuses.append(self._stream_status('imu', imu_rate, imu_warnings, {
                    'requested rate (Hz)': settings.rate_hz,
                    'chip rate (Hz)': settings.odr_hz,
                    'measured rate (Hz)': imu_rate,
                    'published': self._imu.emitted,
                    'accel range (g)': settings.accel_range_g,
                    'gyro range (deg/s)': settings.gyro_range_dps,
                    'dlpf': f'{settings.dlpf} (accel {reg.ACCEL_DLPF_HZ[settings.dlpf][0]} Hz, '
                            f'gyro {reg.GYRO_DLPF_HZ[settings.dlpf][0]} Hz)',
                    'temperature (C)': ('' if self._last_celsius is None
                                        else self._last_celsius),
                    **shared,
                    'saturated samples': self.imu_saturated,
                    'read': 'FIFO' if self.imu_fifo else 'polled (data-ready)',
                    **fifo_values,
                    'resyncs': self.imu_resyncs,
                }))
            return statuses

    def _stream_status(self, stream: str, rate: float, warnings: list[str],
                       values: dict[str, object]) -> StreamStatus:
        if not self.running:
            return StreamStatus(stream, ERROR, self.last_error or 'not initialised', values)
        if warnings:
            return StreamStatus(stream, WARN, '; '.join(warnings), values)
        if stream == 'imu' and not self.publish_imu:
            return StreamStatus(stream, OK, 'temperature only (publish_imu is false)', values)
        return StreamStatus(stream, OK, f'publishing {rate:.1f} Hz', values)

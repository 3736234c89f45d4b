"""Fault injection in the simulator and how the hardware layer surfaces it (no ROS here)."""

import errno

import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import Icm20948Magnetometer
from mag_calibrator_ros.icm20948.simulator import SimConfig, SimulatedIcm20948Bus


class FakeClock:
    def __init__(self, start: float = 50.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


def make(**config):
    clock = FakeClock()
    bus = SimulatedIcm20948Bus(SimConfig(**config), clock=clock)
    return clock, bus, Icm20948Magnetometer(bus, bus_name='sim', sleep=clock.sleep)


def initialise_with_retries(driver, attempts: int = 50) -> int:
    """What the node does: retry bring-up until it succeeds; returns the attempts used."""
    for attempt in range(1, attempts + 1):
        try:
            driver.initialise(100)
            return attempt
        except OSError:
            continue
    raise AssertionError('never initialised')


def test_error_rate_injects_eremoteio_at_about_the_configured_rate():
    clock, bus, driver = make(i2c_error_rate=0.05, seed=3)
    initialise_with_retries(driver)
    errors, readings = 0, []
    for _ in range(4000):
        clock.sleep(0.004)
        try:
            reading = driver.read()
        except OSError as error:
            assert error.errno == errno.EREMOTEIO
            errors += 1
            continue
        if reading is not None:
            readings.append(reading)
    assert 120 < errors < 300  # 5 % of 4000
    # A failed burst leaves the sample latched: it is read on the next poll, nothing lost.
    assert len(readings) >= 0.97 * 1600
    counts = np.array([r.counts for r in readings])
    assert np.all(np.any(np.diff(counts, axis=0) != 0, axis=1))


def test_error_rate_zero_never_fails():
    clock, bus, driver = make(seed=1)
    driver.initialise(100)
    for _ in range(2000):
        clock.sleep(0.004)
        driver.read()
    assert bus.injected_errors == 0


def test_outage_nacks_everything_then_device_comes_back_reset():
    clock, bus, driver = make(seed=2)
    driver.initialise(100)
    clock.sleep(0.05)
    assert driver.read() is not None
    bus.start_outage(2.0)
    for _ in range(10):
        clock.sleep(0.15)
        with pytest.raises(OSError) as caught:
            driver.read()
        assert caught.value.errno == errno.EREMOTEIO
        with pytest.raises(OSError):
            bus.read_byte_data(0x69, reg.WHO_AM_I)
    clock.sleep(0.6)
    assert not bus.in_outage
    # Power was lost: asleep, bypass off, so the magnetometer NACKs until re-initialised.
    with pytest.raises(OSError):
        driver.read()
    assert bus.read_byte_data(0x69, reg.PWR_MGMT_1) == reg.PWR_MGMT_1_RESET_VALUE
    driver.initialise(100)
    clock.sleep(0.02)
    assert driver.read() is not None


def test_outage_without_reset_resumes_by_itself():
    clock, bus, driver = make(seed=2)
    driver.initialise(100)
    bus.start_outage(0.5, reset=False)
    clock.sleep(0.2)
    with pytest.raises(OSError):
        driver.read()
    clock.sleep(0.4)
    assert driver.read() is not None
    assert driver.overruns == 1  # samples were skipped during the outage


def test_chip_reset_powers_down_the_magnetometer_and_hides_it():
    clock, bus, driver = make(seed=5)
    driver.initialise(100)
    clock.sleep(0.02)
    assert driver.read() is not None
    bus.chip_reset()
    clock.sleep(0.02)
    with pytest.raises(OSError):
        driver.read()
    assert bus.read_byte_data(0x69, reg.PWR_MGMT_1) == reg.PWR_MGMT_1_RESET_VALUE
    assert bus.read_byte_data(0x69, reg.INT_PIN_CFG) & reg.INT_PIN_CFG_BYPASS_EN == 0
    driver.initialise(100)
    clock.sleep(0.02)
    assert driver.read() is not None


def test_magnetometer_soft_reset_stops_data_and_shows_in_cntl2():
    """The stuck-DRDY case the node detects: the AK09916 alone was reset (power-down mode)."""
    clock, bus, driver = make(seed=6)
    driver.initialise(100)
    bus.write_byte_data(reg.AK09916_ADDRESS, reg.CNTL3, reg.CNTL3_SRST)
    assert driver.measurement_mode() == reg.MODE_POWER_DOWN
    for _ in range(50):
        clock.sleep(0.01)
        assert driver.read() is None


def test_direct_mode_switch_without_power_down_is_ignored():
    clock, bus, driver = make()
    driver.initialise(10)
    bus.write_byte_data(reg.AK09916_ADDRESS, reg.CNTL2, reg.CONTINUOUS_MODES[100])
    assert driver.measurement_mode() == reg.CONTINUOUS_MODES[10]


def test_initialise_under_heavy_errors_eventually_succeeds():
    clock, bus, driver = make(i2c_error_rate=0.3, seed=8)
    assert initialise_with_retries(driver) >= 1
    assert bus.injected_errors > 0
    readings = 0
    for _ in range(500):
        clock.sleep(0.004)
        try:
            readings += driver.read() is not None
        except OSError:
            pass
    assert readings > 50


def test_same_seed_same_faults_and_samples():
    def run():
        clock, bus, driver = make(i2c_error_rate=0.1, seed=11)
        initialise_with_retries(driver)
        out = []
        for _ in range(300):
            clock.sleep(0.004)
            try:
                reading = driver.read()
            except OSError:
                out.append(None)
                continue
            if reading is not None:
                out.append(tuple(reading.counts))
        return out

    assert run() == run()


@pytest.mark.parametrize('kwargs, fragment', [
    (dict(field_ut=float('nan')), 'field_ut must be a finite number'),
    (dict(field_ut=0.0), 'field_ut must be in (0, 4900]'),
    (dict(inclination_deg=120.0), 'inclination_deg'),
    (dict(noise_ut=-1.0), 'noise_ut must be >= 0'),
    (dict(i2c_error_rate=1.0), 'i2c_error_rate must be in [0, 1)'),
    (dict(motion='wobble'), 'motion must be one of tumble, yaw, still'),
    (dict(address=0x0C), 'address must be 0x68 or 0x69'),
    (dict(hard_iron_ut=(1.0, 2.0)), 'hard_iron_ut must be 3 finite numbers'),
    (dict(hard_iron_ut=('a', 1, 2)), 'hard_iron_ut must be 3 finite numbers'),
    (dict(soft_iron=(1.0,) * 8), 'soft_iron must be 9 finite numbers'),
    (dict(soft_iron=(1, 0.5, 0, 0, 1, 0, 0, 0, 1)), 'soft_iron must be symmetric'),
    (dict(soft_iron=(1, 0, 0, 0, -1, 0, 0, 0, 1)), 'soft_iron must be positive definite'),
])
def test_invalid_configuration_is_refused_with_a_reason(kwargs, fragment):
    with pytest.raises(ValueError) as caught:
        SimConfig(**kwargs)
    assert fragment in str(caught.value)


def test_every_problem_is_listed():
    with pytest.raises(ValueError) as caught:
        SimConfig(noise_ut=-1.0, motion='x', i2c_error_rate=2.0)
    message = str(caught.value)
    assert 'noise_ut' in message and 'motion' in message and 'i2c_error_rate' in message


def test_bad_outage_duration_is_refused():
    _, bus, _ = make()
    with pytest.raises(ValueError):
        bus.start_outage(-1.0)
    with pytest.raises(ValueError):
        bus.start_outage(float('nan'))

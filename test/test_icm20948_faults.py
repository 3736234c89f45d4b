# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Fault injection in the simulator and how the driver surfaces it (no ROS; recovery from these
faults is the supervisor's job, tested in test_icm20948_supervisor.py)."""

import errno

from icm20948_fakes import FakeClock
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import Icm20948, ImuSettings
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus


def make(**config):
    clock = FakeClock()
    bus = SimulatedIcm20948Bus(SimConfig(**config), clock=clock)
    return clock, bus, Icm20948(bus, bus_name='sim', sleep=clock.sleep, clock=clock)


def test_error_rate_hits_every_transaction_of_both_dies_with_eremoteio():
    clock, bus, driver = make(i2c_error_rate=0.05, seed=3)
    for _ in range(20):  # bring-up retries each access a few times; rarely all fail at 5 %
        try:
            driver.initialise(100, ImuSettings(rate_hz=200))
            break
        except OSError:
            continue
    failed = {reg.AK09916_ADDRESS: 0, 0x69: 0}
    readings = {'mag': [], 'imu': []}
    for _ in range(4000):
        clock.sleep(0.002)
        for name, read in (('mag', driver.read_mag), ('imu', driver.read_imu)):
            before = driver.bus.monitor.counters.errors
            try:
                reading = read()
            except OSError as error:
                assert error.errno == errno.EREMOTEIO
                continue
            finally:
                address = reg.AK09916_ADDRESS if name == 'mag' else 0x69
                failed[address] += driver.bus.monitor.counters.errors - before
            if reading is not None:
                readings[name].append(reading)
    assert 0.03 < bus.injected_errors / bus.transactions < 0.07
    assert all(count > 50 for count in failed.values())  # both dies see the faults
    assert driver.bus.monitor.counters.errors == bus.injected_errors  # each one counted
    # Reads retry once and a sample stays latched until the next: almost nothing is lost.
    assert len(readings['mag']) >= 0.98 * 800 and len(readings['imu']) >= 0.98 * 1800
    assert bus.mag_repeated_reads == 0 and bus.imu_repeated_reads == 0


def test_error_rate_zero_never_fails():
    clock, bus, driver = make(seed=1)
    driver.initialise(100, ImuSettings())
    for _ in range(2000):
        clock.sleep(0.004)
        driver.read_mag()
        driver.read_imu()
    assert bus.injected_errors == 0 and driver.bus.monitor.counters.errors == 0


def test_outage_nacks_everything_then_device_comes_back_reset():
    clock, bus, driver = make(seed=2)
    driver.initialise(100, ImuSettings())
    clock.sleep(0.05)
    assert driver.read_mag() is not None
    bus.start_outage(2.0)
    for _ in range(10):
        clock.sleep(0.15)
        for read in (driver.read_mag, driver.read_imu):
            with pytest.raises(OSError) as caught:
                read()
            assert caught.value.errno == errno.EREMOTEIO
        with pytest.raises(OSError):
            bus.read_byte_data(0x69, reg.WHO_AM_I)
    clock.sleep(0.6)
    assert not bus.in_outage
    # Power was lost: asleep, bypass off, so the magnetometer NACKs until re-initialised.
    with pytest.raises(OSError):
        driver.read_mag()
    assert driver.power_state() == reg.PWR_MGMT_1_RESET_VALUE
    assert driver.read_imu() is None and driver.read_imu() is None  # asleep: no data-ready
    driver.initialise(100, ImuSettings())
    clock.sleep(0.05)
    assert driver.read_mag() is not None
    assert driver.read_imu() is None  # the first call re-synchronises the data-ready flag
    clock.sleep(0.005)
    assert driver.read_imu() is not None


def test_outage_without_reset_resumes_by_itself():
    clock, bus, driver = make(seed=2)
    driver.initialise(100)
    bus.start_outage(0.5, reset=False)
    clock.sleep(0.2)
    with pytest.raises(OSError):
        driver.read_mag()
    clock.sleep(0.4)
    assert driver.read_mag() is not None
    assert driver.overruns == 1  # samples were skipped during the outage


def test_chip_reset_powers_down_the_magnetometer_and_hides_it():
    clock, bus, driver = make(seed=5)
    driver.initialise(100, ImuSettings())
    clock.sleep(0.05)
    assert driver.read_mag() is not None
    bus.chip_reset()
    clock.sleep(0.02)
    with pytest.raises(OSError):
        driver.read_mag()
    assert bus.read_byte_data(0x69, reg.PWR_MGMT_1) == reg.PWR_MGMT_1_RESET_VALUE
    assert bus.read_byte_data(0x69, reg.INT_PIN_CFG) & reg.INT_PIN_CFG_BYPASS_EN == 0
    for _ in range(20):
        clock.sleep(0.01)
        assert driver.read_imu() is None  # asleep after the reset: the IMU stops too
    driver.initialise(100, ImuSettings())
    clock.sleep(0.05)
    assert driver.read_mag() is not None


def test_magnetometer_soft_reset_stops_data_and_shows_in_cntl2():
    """The stuck-DRDY case the supervisor detects: the AK09916 alone was reset (power-down)."""
    clock, bus, driver = make(seed=6)
    driver.initialise(100)
    bus.write_byte_data(reg.AK09916_ADDRESS, reg.CNTL3, reg.CNTL3_SRST)
    assert driver.measurement_mode() == reg.MODE_POWER_DOWN
    for _ in range(50):
        clock.sleep(0.01)
        assert driver.read_mag() is None


def test_direct_mode_switch_without_power_down_is_ignored():
    clock, bus, driver = make()
    driver.initialise(10)
    bus.write_byte_data(reg.AK09916_ADDRESS, reg.CNTL2, reg.CONTINUOUS_MODES[100])
    assert driver.measurement_mode() == reg.CONTINUOUS_MODES[10]


def test_same_seed_same_faults_and_samples():
    def run():
        clock, bus, driver = make(i2c_error_rate=0.1, seed=11)
        for _ in range(50):
            try:
                driver.initialise(100, ImuSettings())
                break
            except OSError:
                continue
        out = []
        for _ in range(300):
            clock.sleep(0.002)
            for read in (driver.read_mag, driver.read_imu):
                try:
                    reading = read()
                except OSError:
                    out.append(None)
                    continue
                if reading is not None:
                    out.append(tuple(np.ravel(reading.counts)))
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
    (dict(accel_bias_mps2=(0.0, float('inf'), 0.0)), 'accel_bias_mps2 must be 3 finite'),
    (dict(gyro_bias_dps=(1.0,)), 'gyro_bias_dps must be 3 finite'),
    # beyond the largest full scale (±16 g, ±2000 dps): 1e308 made every sample raise
    (dict(accel_bias_mps2=(1e308, 0.0, 0.0)), 'accel_bias_mps2 must be within ±156.906 m/s^2'),
    (dict(accel_bias_mps2=(0.0, 0.0, -157.0)), 'accel_bias_mps2 must be within'),
    (dict(gyro_bias_dps=(0.0, 2001.0, 0.0)), 'gyro_bias_dps must be within ±2000 deg/s'),
    (dict(accel_noise_density=1e308), 'accel_noise_density must be >= 0 and <= 1.0'),
    (dict(gyro_noise_density=1.5), 'gyro_noise_density must be >= 0 and <= 1.0'),
    (dict(seed=-1), 'seed must be an integer >= 0'),
    (dict(accel_noise_density=-1e-3), 'accel_noise_density must be >= 0'),
    (dict(gyro_noise_density=float('nan')), 'gyro_noise_density must be a finite number'),
    (dict(temperature_c=120.0), 'temperature_c must be within the operating range'),
    (dict(temperature_rise_c=-80.0), 'temperature_rise_c'),
])
def test_invalid_configuration_is_refused_with_a_reason(kwargs, fragment):
    with pytest.raises(ValueError) as caught:
        SimConfig(**kwargs)
    assert fragment in str(caught.value)


def test_biases_at_the_largest_full_scale_are_accepted():
    config = SimConfig(accel_bias_mps2=(156.9, -156.9, 0.0), gyro_bias_dps=(2000.0, 0.0, -2000.0),
                       accel_noise_density=1.0, gyro_noise_density=1.0)
    assert config.accel_bias_mps2[0] == 156.9


def test_every_problem_is_listed():
    with pytest.raises(ValueError) as caught:
        SimConfig(noise_ut=-1.0, motion='x', i2c_error_rate=2.0, gyro_bias_dps=(1.0,))
    message = str(caught.value)
    for name in ('noise_ut', 'motion', 'i2c_error_rate', 'gyro_bias_dps'):
        assert name in message


def test_bad_outage_duration_is_refused():
    _, bus, _ = make()
    with pytest.raises(ValueError):
        bus.start_outage(-1.0)
    with pytest.raises(ValueError):
        bus.start_outage(float('nan'))

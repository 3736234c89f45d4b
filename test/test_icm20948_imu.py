# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Accelerometer, gyroscope and temperature of the ICM-20948: register protocol, decoding, scaling,
data-ready and the simulator's physics (DS-000189), without ROS."""

import math

from icm20948_fakes import FakeClock, RecordingBus
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import ConfigNotAcceptedError, Icm20948, ImuSettings
from mag_calibrator_ros.icm20948.units import temperature_celsius, temperature_counts
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import GRAVITY_WORLD
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

G = reg.STANDARD_GRAVITY


class FixedRegisters:
    """A bus whose ICM-20948 data registers hold fixed bytes and whose data-ready is always set
    (for decoding known register values, as the datasheet states them)."""

    def __init__(self, words: tuple[int, ...]) -> None:
        self.data = list(np.asarray(words, dtype='>i2').tobytes())

    def read_byte_data(self, addr, register):
        return reg.INT_STATUS_1_RAW_DATA_0_RDY if register == reg.INT_STATUS_1 else 0

    def read_i2c_block_data(self, addr, register, length):
        assert (register, length) == (reg.ACCEL_XOUT_H, 14)
        return self.data


def make(config: SimConfig | None = None, imu: ImuSettings | None = None):
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(config if config is not None else SimConfig(), clock=clock)
    driver = Icm20948(sim, bus_name='/dev/i2c-3', sleep=clock.sleep, clock=clock)
    driver.initialise(100, imu if imu is not None else ImuSettings())
    return clock, sim, driver


def poll(clock, driver, seconds: float, polls_per_sample: float = 1.5):
    period = 1.0 / (driver.imu.odr_hz * polls_per_sample)
    readings = []
    for _ in range(int(round(seconds / period))):
        clock.sleep(period)
        reading = driver.read_imu()
        if reading is not None:
            readings.append(reading)
    return readings


def decoded(words, imu: ImuSettings):
    driver = Icm20948(FixedRegisters(words), clock=FakeClock())
    driver.imu = imu
    driver._accel_scale = G / reg.ACCEL_RANGES_G[imu.accel_range_g][1]
    driver._gyro_scale = math.radians(1.0) / reg.GYRO_RANGES_DPS[imu.gyro_range_dps][1]
    driver._imu_window = 1.0
    driver._imu_synced_at = driver._clock()
    return driver.read_imu()


@pytest.mark.parametrize('range_g, sensitivity', [(2, 16384), (4, 8192), (8, 4096), (16, 2048)])
def test_accel_counts_decode_big_endian_with_the_datasheet_sensitivity(range_g, sensitivity):
    words = (sensitivity, -sensitivity // 2, 0, 0, 0, 0, 0)
    reading = decoded(words, ImuSettings(accel_range_g=range_g))
    np.testing.assert_allclose(reading.linear_acceleration, [G, -G / 2, 0.0], rtol=1e-12)
    assert reading.counts == words and not reading.saturated


@pytest.mark.parametrize('range_dps, sensitivity',
                         [(250, 131.0), (500, 65.5), (1000, 32.8), (2000, 16.4)])
def test_gyro_counts_decode_to_rad_per_second(range_dps, sensitivity):
    words = (0, 0, 0, round(10 * sensitivity), -round(100 * sensitivity), 1, 0)
    reading = decoded(words, ImuSettings(gyro_range_dps=range_dps))
    expected = np.radians([round(10 * sensitivity) / sensitivity,
                           -round(100 * sensitivity) / sensitivity, 1 / sensitivity])
    np.testing.assert_allclose(reading.angular_velocity, expected, rtol=1e-12)


@pytest.mark.parametrize('raw, celsius', [(0, 21.0), (3339, 21.0 + 3339 / 333.87),
                                          (-6677, 21.0 - 6677 / 333.87), (32767, 119.14)])
def test_temperature_formula_at_known_register_values(raw, celsius):
    """DS-000189: TEMP_degC = (TEMP_OUT - RoomTemp_Offset) / 333.87 + 21, offset 0."""
    assert temperature_celsius(raw) == pytest.approx(celsius, abs=0.01)
    assert decoded((0, 0, 0, 0, 0, 0, raw), ImuSettings()).temperature_c == pytest.approx(
        celsius, abs=0.01)
    assert temperature_counts(temperature_celsius(raw)) == raw


def test_rails_are_reported_as_saturated():
    assert decoded((32767, 0, 0, 0, 0, 0, 0), ImuSettings()).saturated
    assert decoded((0, 0, 0, 0, -32768, 0, 0), ImuSettings()).saturated
    assert not decoded((32766, 0, 0, 0, -32767, 0, 32767), ImuSettings()).saturated


@pytest.mark.parametrize('rate, divider, odr', [
    (1125, 0, 1125.0), (1000, 0, 1125.0), (563, 0, 1125.0), (562, 1, 562.5), (200, 4, 225.0),
    (100, 10, 1125 / 11), (10, 111, 1125 / 112), (5, 224, 5.0),
])
def test_divider_gives_the_nearest_rate_at_or_above_the_request(rate, divider, odr):
    settings = ImuSettings(rate_hz=rate)
    assert settings.divider == divider
    assert settings.odr_hz == pytest.approx(odr)
    assert settings.odr_hz >= rate


@pytest.mark.parametrize('kwargs, fragment', [
    (dict(rate_hz=4), 'imu_rate_hz must be an integer from 5 to 1125'),
    (dict(rate_hz=2000), 'imu_rate_hz'),
    (dict(rate_hz=200.0), 'imu_rate_hz'),
    (dict(accel_range_g=3), 'accel_range_g must be one of [2, 4, 8, 16]'),
    (dict(gyro_range_dps=300), 'gyro_range_dps must be one of [250, 500, 1000, 2000]'),
    (dict(dlpf=0), 'dlpf must be one of [1, 2, 3, 4, 5, 6]'),
    (dict(dlpf=7), 'bypass the sample-rate divider'),
])
def test_invalid_settings_are_named(kwargs, fragment):
    problems = ImuSettings(**kwargs).problems()
    assert len(problems) == 1 and fragment in problems[0]
    with pytest.raises(ValueError, match=fragment.split()[0]):
        Icm20948(SimulatedIcm20948Bus(SimConfig())).initialise(100, ImuSettings(**kwargs))


def test_configuration_goes_to_bank_2_and_reads_back_then_bank_0():
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    bus = RecordingBus(sim, clock)
    driver = Icm20948(bus, sleep=clock.sleep, clock=clock)
    imu = ImuSettings(rate_hz=100, accel_range_g=8, gyro_range_dps=500, dlpf=5)
    driver.initialise(100, imu)
    config = {(e.register, e.value) for e in bus.log
              if e.kind == 'w' and e.address == 0x69 and e.bank == 2
              and e.register != reg.REG_BANK_SEL}
    assert config == {
        (reg.ODR_ALIGN_EN, 1),
        (reg.GYRO_SMPLRT_DIV, 10),
        (reg.GYRO_CONFIG_1, (5 << 3) | (1 << 1) | 1),
        (reg.ACCEL_SMPLRT_DIV_1, 0),
        (reg.ACCEL_SMPLRT_DIV_2, 10),
        (reg.ACCEL_CONFIG, (5 << 3) | (2 << 1) | 1),
    }
    reads_in_bank_2 = [e for e in bus.log if e.kind == 'rb' and e.bank == 2]
    assert len(reads_in_bank_2) == 2  # the configuration was read back
    writes = [(e.address, e.register, e.value, e.bank) for e in bus.log if e.kind == 'w']
    wake = writes.index((0x69, reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO, 0))
    first_config = min(i for i, (_, register, _, bank) in enumerate(writes)
                       if bank == 2 and register != reg.REG_BANK_SEL)
    assert wake < first_config  # configured awake
    assert bus.bank == 0 and sim.read_byte_data(0x69, reg.REG_BANK_SEL) == 0
    assert (0x69, reg.PWR_MGMT_2, reg.PWR_MGMT_2_ALL_ON, 0) in writes


def test_a_driver_that_forgets_the_bank_switch_is_caught_by_the_read_back():
    """Bank-2 registers written while bank 0 is selected land elsewhere; the model keeps them
    apart and the driver's read-back refuses to run with a configuration that did not stick."""

    class NoBankSwitch(RecordingBus):
        def write_byte_data(self, addr, register, value):
            if addr == 0x69 and register == reg.REG_BANK_SEL:
                value = 0
            super().write_byte_data(addr, register, value)

    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    driver = Icm20948(NoBankSwitch(sim, clock), bus_name='/dev/i2c-3', sleep=clock.sleep,
                      clock=clock)
    with pytest.raises(ConfigNotAcceptedError) as caught:
        driver.initialise(100, ImuSettings())
    assert 'GYRO_SMPLRT_DIV expected 0x04, found 0xea' in str(caught.value)  # WHO_AM_I
    assert '/dev/i2c-3' in str(caught.value)
    sim.write_byte_data(0x69, reg.REG_BANK_SEL, 2 << reg.BANK_SHIFT)
    assert sim.read_byte_data(0x69, reg.GYRO_CONFIG_1) == reg.GYRO_CONFIG_1_RESET_VALUE


def test_no_data_ready_before_the_gyroscope_start_up_time():
    clock, sim, driver = make()
    assert driver.read_imu() is None  # re-synchronises the flag
    clock.sleep(reg.SENSOR_STARTUP_S - 0.005)
    assert driver.read_imu() is None
    clock.sleep(0.010)
    assert driver.read_imu() is not None


def test_data_ready_is_cleared_by_reading_int_status_1_and_set_by_each_sample():
    clock, sim, driver = make(imu=ImuSettings(rate_hz=100))
    clock.sleep(0.1)
    assert sim.read_byte_data(0x69, reg.INT_STATUS_1) & reg.INT_STATUS_1_RAW_DATA_0_RDY
    assert not sim.read_byte_data(0x69, reg.INT_STATUS_1) & reg.INT_STATUS_1_RAW_DATA_0_RDY
    clock.sleep(1 / driver.imu.odr_hz)
    assert sim.read_byte_data(0x69, reg.INT_STATUS_1) & reg.INT_STATUS_1_RAW_DATA_0_RDY


@pytest.mark.parametrize('rate', [5, 100, 200, 1000])
def test_one_reading_per_sample_at_the_chip_rate(rate):
    clock, sim, driver = make(SimConfig(seed=rate), ImuSettings(rate_hz=rate))
    clock.sleep(reg.SENSOR_STARTUP_S)
    readings = poll(clock, driver, 4.0)
    assert abs(len(readings) - 4.0 * driver.imu.odr_hz) <= 2
    assert sim.imu_repeated_reads == 0 and sim.imu_samples_read == len(readings)
    counts = np.array([r.counts for r in readings])
    assert np.all(np.any(np.diff(counts, axis=0) != 0, axis=1))  # tumbling: never the same


def test_a_read_straddling_a_new_sample_never_returns_it_twice():
    """Preempted between the status read and the burst, a reader gets the next sample, whose
    data-ready then asks for it again. A naive reader repeats it; the driver does not."""

    class Preempted:
        """Between INT_STATUS_1 and the burst, time jumps by up to 1.2 sample periods."""

        def __init__(self, sim, clock, period, seed):
            self.sim, self.clock, self.period = sim, clock, period
            self.rng = np.random.default_rng(seed)

        def read_byte_data(self, addr, register):
            return self.sim.read_byte_data(addr, register)

        def read_i2c_block_data(self, addr, register, length):
            self.clock.sleep(self.rng.uniform(0.0, 1.2) * self.period)
            return self.sim.read_i2c_block_data(addr, register, length)

        def write_byte_data(self, addr, register, value):
            self.sim.write_byte_data(addr, register, value)

    def run(naive: bool):
        clock = FakeClock()
        sim = SimulatedIcm20948Bus(SimConfig(seed=4), clock=clock)
        imu = ImuSettings(rate_hz=1000)
        bus = Preempted(sim, clock, 1.0 / imu.odr_hz, seed=4)
        driver = Icm20948(bus, sleep=clock.sleep, clock=clock)
        driver.initialise(100, imu)
        for _ in range(3000):
            clock.sleep(0.4 / imu.odr_hz)
            if naive:
                if bus.read_byte_data(0x69, reg.INT_STATUS_1) & 1:
                    bus.read_i2c_block_data(0x69, reg.ACCEL_XOUT_H, 14)
            else:
                driver.read_imu()
        return sim, driver

    naive_sim, _ = run(naive=True)
    assert naive_sim.imu_repeated_reads > 50  # the hazard is real in the model
    sim, driver = run(naive=False)
    assert sim.imu_repeated_reads == 0
    assert driver.imu_resyncs > 0 and sim.imu_samples_read > 0.5 * naive_sim.imu_samples_read


def test_level_board_reads_plus_g_on_z_at_every_range():
    for range_g, sensitivity in ((2, 16384), (4, 8192), (8, 4096), (16, 2048)):
        clock, sim, driver = make(SimConfig(motion='still', seed=2),
                                  ImuSettings(accel_range_g=range_g))
        readings = poll(clock, driver, 1.0)
        counts = np.array([r.counts[:3] for r in readings])
        rotation = sim.board.trajectory.orientation(0.0)
        expected = rotation.T @ np.array([0.0, 0.0, sensitivity])  # within ±0.5 deg of level
        np.testing.assert_allclose(counts.mean(axis=0), expected, atol=0.003 * sensitivity + 1)
        assert counts[:, 2].mean() > 0.999 * sensitivity  # +z up: REP-145 sign
        acceleration = np.mean([r.linear_acceleration for r in readings], axis=0)
        assert np.linalg.norm(acceleration) == pytest.approx(G, abs=0.01)


def test_gyro_sign_and_scale_at_every_range_from_a_known_bias():
    bias_dps = (100.0, -50.0, 7.5)
    for range_dps, sensitivity in ((250, 131.0), (500, 65.5), (1000, 32.8), (2000, 16.4)):
        clock, sim, driver = make(
            SimConfig(motion='still', gyro_bias_dps=bias_dps, gyro_noise_density=0.0),
            ImuSettings(gyro_range_dps=range_dps))
        readings = poll(clock, driver, 0.3)
        counts = np.array([r.counts[3:6] for r in readings])
        np.testing.assert_array_equal(counts, np.broadcast_to(
            np.rint(np.array(bias_dps) * sensitivity), counts.shape))
        np.testing.assert_allclose(readings[-1].angular_velocity, np.radians(bias_dps),
                                   atol=math.radians(0.5 / sensitivity))


def test_full_scale_saturates_at_the_int16_rails():
    clock, sim, driver = make(
        SimConfig(motion='still', gyro_bias_dps=(300.0, -300.0, 0.0), accel_bias_mps2=(0, 0, 15)),
        ImuSettings(accel_range_g=2, gyro_range_dps=250))
    readings = poll(clock, driver, 0.2)
    assert all(r.saturated for r in readings)
    assert {r.counts[3] for r in readings} == {32767} and {r.counts[4] for r in readings} == {
        -32768}
    assert {r.counts[2] for r in readings} == {32767}  # 9.8 + 15 m/s^2 beyond 2 g


def test_temperature_drifts_slowly_as_configured():
    clock, sim, driver = make(SimConfig(temperature_c=30.0, temperature_rise_c=6.0))
    first = poll(clock, driver, 0.2)[-1].temperature_c
    assert first == pytest.approx(30.0, abs=0.01)
    clock.sleep(600.0)  # one time constant
    later = poll(clock, driver, 0.2)[-1].temperature_c
    assert later == pytest.approx(30.0 + 6.0 * (1 - math.exp(-1)), abs=0.02)


def test_accel_and_gyro_follow_the_trajectory_with_gravity_and_translation():
    """accel = R^T (a_world - g_world) + noise; gyro = body rate + noise; truth for each."""
    clock, sim, driver = make(SimConfig(seed=7), ImuSettings(rate_hz=200, gyro_range_dps=2000))
    readings = poll(clock, driver, 5.0)
    accel_sigma = sim.config.accel_noise_density * math.sqrt(driver.imu.accel_noise_bandwidth_hz)
    gyro_sigma = sim.config.gyro_noise_density * math.sqrt(driver.imu.gyro_noise_bandwidth_hz)
    translating = 0
    for reading in readings:
        truth = sim.imu_truth_for_reading(reading.linear_acceleration, reading.angular_velocity)
        assert truth is not None
        state = sim.board.trajectory.state(truth.sample_time)
        np.testing.assert_allclose(
            truth.specific_force, state.rotation.T @ (state.linear_acceleration - GRAVITY_WORLD))
        np.testing.assert_allclose(truth.angular_velocity, state.angular_velocity)
        assert np.all(np.abs(reading.linear_acceleration - truth.specific_force)
                      < 6 * accel_sigma + 0.01)
        assert np.all(np.abs(reading.angular_velocity - truth.angular_velocity)
                      < 6 * gyro_sigma + 0.002)
        translating += abs(np.linalg.norm(truth.specific_force) - G) > 0.1
    assert translating > len(readings) // 4  # the hand's acceleration is in the readings


def test_truth_is_none_for_an_unknown_reading():
    _, sim, _ = make()
    assert sim.imu_truth_for_reading(np.array([100.0, 0, 0]), np.zeros(3)) is None


def test_imu_left_off_when_not_wanted():
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    driver = Icm20948(sim, sleep=clock.sleep, clock=clock)
    driver.initialise(100)
    assert sim.read_byte_data(0x69, reg.PWR_MGMT_2) == (
        reg.PWR_MGMT_2_DISABLE_ACCEL | reg.PWR_MGMT_2_DISABLE_GYRO)
    clock.sleep(0.5)
    assert sim.imu_samples_measured == 0
    with pytest.raises(RuntimeError, match='ImuSettings'):
        driver.read_imu()


def test_trajectory_object_plugs_into_the_simulator():
    """Any motion.Trajectory drives the physics: here a constant 90 deg/s turn about z."""

    class Turn(motion.Trajectory):
        def state(self, t):
            angle = math.pi / 2 * t
            c, s = math.cos(angle), math.sin(angle)
            rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            return motion.MotionState(rotation, np.array([0, 0, math.pi / 2]), np.zeros(3))

        def orientation(self, t):
            return self.state(t).rotation

    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(gyro_noise_density=0.0), clock=clock,
                               trajectory=Turn())
    driver = Icm20948(sim, sleep=clock.sleep, clock=clock)
    driver.initialise(100, ImuSettings())
    readings = poll(clock, driver, 0.5)
    np.testing.assert_allclose(readings[-1].angular_velocity, [0, 0, math.pi / 2],
                               atol=math.radians(0.05))

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Register-level protocol of the driver's magnetometer side (AK09916 behind the ICM-20948)
against the simulated chip; the accel/gyro side is in test_icm20948_imu.py."""

import errno
import warnings

from icm20948_fakes import FakeClock, RecordingBus
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import DeviceNotFoundError, Icm20948, WrongDeviceError
from mag_calibrator_ros.icm20948.units import counts_to_tesla, tesla_to_counts
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus


def make(config: SimConfig | None = None, address: int = 0x69):
    config = config if config is not None else SimConfig()
    clock = FakeClock()
    bus = SimulatedIcm20948Bus(config, clock=clock)
    driver = Icm20948(bus, address=address, bus_name='/dev/i2c-7', sleep=clock.sleep,
                      clock=clock)
    return clock, bus, driver


def poll(clock, driver, seconds: float, poll_hz: float = 250.0):
    readings = []
    for _ in range(int(round(seconds * poll_hz))):
        clock.sleep(1.0 / poll_hz)
        reading = driver.read_mag()
        if reading is not None:
            readings.append(reading)
    return readings


def test_magnetometer_unreachable_until_bypass_on_and_master_off():
    clock = FakeClock()
    bus = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    with pytest.raises(OSError) as caught:
        bus.read_byte_data(reg.AK09916_ADDRESS, reg.WIA1)
    assert caught.value.errno == errno.EREMOTEIO
    bus.write_byte_data(0x69, reg.INT_PIN_CFG, reg.INT_PIN_CFG_BYPASS_EN)
    bus.write_byte_data(0x69, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    with pytest.raises(OSError):
        bus.read_byte_data(reg.AK09916_ADDRESS, reg.WIA1)
    bus.write_byte_data(0x69, reg.USER_CTRL, 0)
    assert bus.read_byte_data(reg.AK09916_ADDRESS, reg.WIA1) == reg.WIA1_VALUE


def test_power_on_state_of_the_model():
    clock = FakeClock()
    bus = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    assert bus.read_byte_data(0x69, reg.WHO_AM_I) == reg.WHO_AM_I_VALUE
    assert bus.read_byte_data(0x69, reg.PWR_MGMT_1) == reg.PWR_MGMT_1_RESET_VALUE
    bus.write_byte_data(0x69, reg.REG_BANK_SEL, 2 << reg.BANK_SHIFT)
    assert bus.read_byte_data(0x69, reg.WHO_AM_I) != reg.WHO_AM_I_VALUE  # bank 2, not WHO_AM_I
    with pytest.raises(OSError):
        bus.read_byte_data(0x68, reg.WHO_AM_I)  # nothing at the other address


def test_initialise_sequence_and_waits():
    clock, sim, _ = make()
    bus = RecordingBus(sim, clock)
    driver = Icm20948(bus, address=0x69, sleep=clock.sleep, clock=clock)
    driver.initialise(mag_rate_hz=50)  # magnetometer only: accel and gyro powered down
    writes = [(e.kind, e.address, e.register, e.value) for e in bus.log if e.kind == 'w']
    order = [
        ('w', 0x69, reg.REG_BANK_SEL, 0),
        ('w', 0x69, reg.PWR_MGMT_1, reg.PWR_MGMT_1_DEVICE_RESET),
        # Sensors off before waking: they never start (the accelerometer would 20 ms after).
        ('w', 0x69, reg.PWR_MGMT_2, reg.PWR_MGMT_2_DISABLE_ACCEL | reg.PWR_MGMT_2_DISABLE_GYRO),
        ('w', 0x69, reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO),
        ('w', 0x69, reg.USER_CTRL, 0),
        ('w', 0x69, reg.INT_PIN_CFG, reg.INT_PIN_CFG_BYPASS_EN),
        ('w', reg.AK09916_ADDRESS, reg.CNTL3, reg.CNTL3_SRST),
        ('w', reg.AK09916_ADDRESS, reg.CNTL2, reg.MODE_POWER_DOWN),
        ('w', reg.AK09916_ADDRESS, reg.CNTL2, reg.CONTINUOUS_MODES[50]),
    ]
    positions = [writes.index(step) for step in order]
    assert positions == sorted(positions)
    times = {(e.kind, e.address, e.register, e.value): e.time for e in bus.log if e.kind == 'w'}
    reset_at = times[('w', 0x69, reg.PWR_MGMT_1, reg.PWR_MGMT_1_DEVICE_RESET)]
    wake_at = times[('w', 0x69, reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO)]
    assert wake_at - reset_at >= reg.DEVICE_RESET_WAIT_S - 1e-9
    down_at = times[('w', reg.AK09916_ADDRESS, reg.CNTL2, reg.MODE_POWER_DOWN)]
    mode_at = times[('w', reg.AK09916_ADDRESS, reg.CNTL2, reg.CONTINUOUS_MODES[50])]
    assert mode_at - down_at >= reg.MODE_CHANGE_WAIT_S - 1e-9
    # Identities were checked: WHO_AM_I, then WIA1/WIA2 in one block read.
    seen = [(e.kind, e.address, e.register, e.value) for e in bus.log]
    assert ('r', 0x69, reg.WHO_AM_I, reg.WHO_AM_I_VALUE) in seen
    assert ('rb', reg.AK09916_ADDRESS, reg.WIA1, (0x48, 0x09)) in seen
    assert sim.read_byte_data(reg.AK09916_ADDRESS, reg.CNTL2) == reg.CONTINUOUS_MODES[50]
    assert driver.mag_rate_hz == 50 and driver.imu is None


def test_initialise_without_waiting_fails_on_the_model():
    """The model enforces the datasheet waits, so a driver that skipped them would be caught."""
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    hasty = Icm20948(sim, sleep=lambda seconds: None, clock=clock)
    with pytest.raises(OSError):
        hasty.initialise(100)


def test_initialise_recovers_a_chip_left_in_master_mode_and_another_bank():
    clock, sim, driver = make()
    sim.write_byte_data(0x69, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    sim.write_byte_data(0x69, reg.REG_BANK_SEL, 3 << reg.BANK_SHIFT)
    driver.initialise(100)
    assert len(poll(clock, driver, 0.5)) > 0


def test_rate_must_be_a_continuous_mode():
    _, _, driver = make()
    with pytest.raises(ValueError, match='10, 20, 50, 100'):
        driver.initialise(30)
    with pytest.raises(ValueError, match='0x68 or 0x69'):
        Icm20948(SimulatedIcm20948Bus(SimConfig()), address=0x0C)


@pytest.mark.parametrize('rate', [10, 20, 50, 100])
def test_one_reading_per_sample_without_overruns(rate):
    clock, sim, driver = make(SimConfig(seed=rate))
    driver.initialise(rate)
    readings = poll(clock, driver, 4.0, poll_hz=max(2.5 * rate, 50.0))
    assert abs(len(readings) - 4 * rate) <= 1
    assert driver.overruns == 0 and driver.overflows == 0
    counts = np.array([r.counts for r in readings])
    assert np.all(np.any(np.diff(counts, axis=0) != 0, axis=1))  # tumbling: never the same twice


def test_no_new_data_reads_none_and_never_repeats():
    clock, sim, driver = make(SimConfig(motion='still', noise_ut=0.0))
    driver.initialise(10)
    while driver.read_mag() is None:  # catch a sample within 1 ms of its data-ready
        clock.sleep(0.001)
    assert driver.read_mag() is None  # DRDY cleared by the data read: no duplicate
    clock.sleep(0.05)
    assert driver.read_mag() is None
    clock.sleep(0.06)
    assert driver.read_mag() is not None
    assert sim.mag_repeated_reads == 0


def test_polls_st1_alone_and_reads_the_data_only_on_drdy():
    clock, sim, _ = make()
    bus = RecordingBus(sim, clock)
    driver = Icm20948(bus, sleep=clock.sleep, clock=clock)
    driver.initialise(100)
    bus.log.clear()
    readings = 0
    for _ in range(50):
        clock.sleep(0.004)
        readings += driver.read_mag() is not None
    polls = [e for e in bus.log if e.kind == 'r']
    bursts = [e for e in bus.log if e.kind == 'rb']
    assert {(e.address, e.register) for e in polls} == {(reg.AK09916_ADDRESS, reg.ST1)}
    assert len(polls) == 50
    # Each burst follows a DRDY poll, runs HXL..ST2 (ST2 last) and yields one reading.
    assert {(e.address, e.register, len(e.value)) for e in bursts} == {
        (reg.AK09916_ADDRESS, reg.HXL, 8)}
    assert len(bursts) == readings == 20
    for burst in bursts:
        previous = bus.log[bus.log.index(burst) - 1]
        assert previous.kind == 'r' and previous.value & reg.ST1_DRDY


def test_data_protection_holds_a_partial_read_until_st2():
    """A reader that skips ST2 leaves the data locked: nothing new arrives (the supervisor sees a
    stuck data-ready and re-initialises; test_icm20948_supervisor covers that)."""
    clock, sim, driver = make()
    driver.initialise(100)
    clock.sleep(0.02)
    first = sim.read_i2c_block_data(reg.AK09916_ADDRESS, reg.ST1, 7)  # ST1..HZH, no ST2
    assert first[0] & reg.ST1_DRDY
    clock.sleep(0.1)
    again = sim.read_i2c_block_data(reg.AK09916_ADDRESS, reg.ST1, 7)
    assert first[1:] == again[1:]  # data protected (locked) until ST2 is read
    assert again[0] & reg.ST1_DOR and not again[0] & reg.ST1_DRDY  # piled up, not released
    assert driver.read_mag() is None
    sim.read_byte_data(reg.AK09916_ADDRESS, reg.ST2)  # ST2 ends the read: the newest is latched
    reading = driver.read_mag()
    assert reading is not None and reading.overrun
    assert not np.array_equal(reading.counts, np.frombuffer(bytes(first[1:7]), '<i2'))


def test_overrun_flagged_and_counted_when_polling_too_slowly():
    clock, _, driver = make()
    driver.initialise(100)
    readings = poll(clock, driver, 2.0, poll_hz=40.0)
    assert len(readings) == 80
    assert driver.overruns >= 75
    assert all(r.overrun for r in readings[1:])


def test_overflow_discards_and_counts():
    # 4900 uT of hard iron plus the 50 uT earth field crosses +-32752 counts (4912.8 uT) often.
    config = SimConfig(hard_iron_ut=(4900.0, 0.0, 0.0), noise_ut=0.0, seed=2)
    clock, sim, driver = make(config)
    driver.initialise(100)
    readings = poll(clock, driver, 5.0)
    assert driver.overflows > 10
    assert len(readings) + driver.overflows == pytest.approx(500, abs=2)
    assert all(np.all(np.abs(r.counts) <= reg.MEASUREMENT_LIMIT) for r in readings)
    assert all(r.field_tesla[0] <= 4912.8e-6 + 1e-12 for r in readings)


@pytest.mark.parametrize('config', [
    SimConfig(hard_iron_ut=(1e308, 0.0, 0.0)), SimConfig(hard_iron_ut=(0.0, 0.0, -1e308)),
    SimConfig(soft_iron=(1e308, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)),
    SimConfig(noise_ut=1e308),
], ids=['hard iron +1e308', 'hard iron -1e308', 'soft iron 1e308', 'noise 1e308'])
def test_a_field_beyond_every_count_is_an_overflow_never_a_reading(config):
    """DS-000189 rev. 1.3 p. 79: the AK09916 measures ±32752 counts (±4912 µT) and flags an
    overflow with HOFL. A field beyond the doubles used to wrap around in the integer conversion
    to a plausible saturated value without HOFL, published on every sample."""
    clock, sim, driver = make(config)
    driver.initialise(100)
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # and no numpy overflow warning on every sample
        readings = poll(clock, driver, 2.0)
    assert readings == []
    assert driver.overflows == pytest.approx(200, abs=2)
    assert sim.read_byte_data(reg.AK09916_ADDRESS, reg.ST2) & reg.ST2_HOFL


def test_units_and_axis_remap_into_the_accel_gyro_frame():
    # A hard iron of +300 uT along the chip's (accel/gyro) y axis lies along -y of the AK09916.
    config = SimConfig(motion='still', noise_ut=0.0, hard_iron_ut=(0.0, 300.0, -200.0), seed=4)
    clock, sim, driver = make(config)
    driver.initialise(100)
    clock.sleep(0.02)
    raw = sim.read_i2c_block_data(reg.AK09916_ADDRESS, reg.ST1, 9)
    counts = np.frombuffer(bytes(raw[1:7]), dtype='<i2')
    clock.sleep(0.01)
    reading = driver.read_mag()
    truth = sim.truth_for_reading(reading.field_tesla)
    expected_tesla = truth + np.array([0.0, 300e-6, -200e-6])
    np.testing.assert_allclose(reading.field_tesla, expected_tesla, atol=0.076e-6)
    # Independent of the driver's conversion: the register holds AK-frame counts of 0.15 uT.
    np.testing.assert_allclose(counts * 0.15e-6, expected_tesla * [1, -1, -1], atol=0.076e-6)
    assert counts[1] < -1500 and counts[2] > 1000


def test_field_is_tesla_and_matches_truth_while_tumbling():
    clock, sim, driver = make(SimConfig(field_ut=50.0, noise_ut=0.2, seed=9))
    driver.initialise(100)
    readings = poll(clock, driver, 10.0)
    fields = np.array([r.field_tesla for r in readings])
    np.testing.assert_allclose(np.linalg.norm(fields, axis=1), 50e-6, atol=2e-6)
    truths = np.array([sim.truth_for_reading(r.field_tesla) for r in readings])
    errors = np.linalg.norm(fields - truths, axis=1)
    assert np.sqrt(np.mean(errors**2)) < 0.6e-6  # noise 0.2 uT x sqrt(3) plus quantisation
    assert np.all(np.isfinite(fields)) and fields.dtype == float


def test_count_conversions_round_trip():
    counts = np.array([[123, -456, 32752], [-32752, 0, 1]])
    np.testing.assert_array_equal(tesla_to_counts(counts_to_tesla(counts)), counts)
    np.testing.assert_allclose(counts_to_tesla([1, 1, 1]), [0.15e-6, -0.15e-6, -0.15e-6])


def test_wrong_chip_names_bus_address_expected_and_found():
    _, _, driver = make(SimConfig(who_am_i=0x71))  # an MPU-9250 answering instead
    with pytest.raises(WrongDeviceError) as caught:
        driver.initialise(100)
    message = str(caught.value)
    for part in ('/dev/i2c-7', '0x69', '0xea', '0x71'):
        assert part in message


def test_wrong_magnetometer_names_expected_and_found():
    _, _, driver = make(SimConfig(ak09916_id=(0x48, 0x05)))
    with pytest.raises(WrongDeviceError) as caught:
        driver.initialise(100)
    message = str(caught.value)
    for part in ('/dev/i2c-7', '0x0c', '0x48/0x09', '0x48/0x05'):
        assert part in message


def test_absent_device_names_bus_address_and_expected_id():
    _, _, driver = make(SimConfig(address=0x69), address=0x68)
    with pytest.raises(DeviceNotFoundError) as caught:
        driver.initialise(100)
    assert isinstance(caught.value, OSError) and caught.value.errno == errno.EREMOTEIO
    message = str(caught.value)
    for part in ('/dev/i2c-7', '0x68', '0xea', 'AD0'):
        assert part in message


def test_truth_log_is_bounded_and_unknown_readings_are_none():
    clock, sim, driver = make()
    driver.initialise(100)
    assert sim.truth_for_reading(np.array([1.0, 1.0, 1.0])) is None
    readings = poll(clock, driver, 1.0)
    assert sim.truth_for_reading(readings[-1].field_tesla) is not None

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The simulated chip against TDK DS-000189 and the AKM AK09916 datasheet, register by register
(issue #23): the behaviours drivers written by others rely on, checked without our driver."""

from icm20948_fakes import FakeClock
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

ICM = 0x69


def make(config: SimConfig | None = None):
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(config if config is not None else SimConfig(), clock=clock)
    return clock, sim


def bank(sim, number: int) -> None:
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, number << reg.BANK_SHIFT)


def wake(sim, pwr_mgmt_2: int = reg.PWR_MGMT_2_ALL_ON) -> None:
    sim.write_byte_data(ICM, reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO)
    sim.write_byte_data(ICM, reg.PWR_MGMT_2, pwr_mgmt_2)


def slv4_read(sim, register: int) -> None:
    bank(sim, reg.MASTER_BANK)
    sim.write_byte_data(ICM, reg.I2C_SLV4_ADDR, reg.I2C_SLV_RNW | reg.AK09916_ADDRESS)
    sim.write_byte_data(ICM, reg.I2C_SLV4_REG, register)
    sim.write_byte_data(ICM, reg.I2C_SLV4_CTRL, reg.I2C_SLV_EN)
    bank(sim, 0)


def slv4_write(sim, register: int, value: int) -> None:
    bank(sim, reg.MASTER_BANK)
    sim.write_byte_data(ICM, reg.I2C_SLV4_ADDR, reg.AK09916_ADDRESS)
    sim.write_byte_data(ICM, reg.I2C_SLV4_REG, register)
    sim.write_byte_data(ICM, reg.I2C_SLV4_DO, value)
    sim.write_byte_data(ICM, reg.I2C_SLV4_CTRL, reg.I2C_SLV_EN)
    bank(sim, 0)


def slv4_done_after(sim, clock, step: float, limit: float) -> float:
    """Seconds until I2C_SLV4_DONE, polled every ``step`` (inf: not within ``limit``)."""
    waited = 0.0
    while waited <= limit:
        if sim.read_byte_data(ICM, reg.I2C_MST_STATUS) & reg.I2C_MST_STATUS_SLV4_DONE:
            return waited
        clock.sleep(step)
        waited += step
    return float('inf')


def test_lp_config_resets_to_duty_cycled_master():
    """DS-000189 §8.3 p.37: LP_CONFIG resets to 0x40 (I2C_MST_CYCLE = 1)."""
    clock, sim = make()
    assert sim.read_byte_data(ICM, reg.LP_CONFIG) == 0x40
    sim.write_byte_data(ICM, reg.LP_CONFIG, 0)
    sim.write_byte_data(ICM, reg.PWR_MGMT_1, reg.PWR_MGMT_1_DEVICE_RESET)
    clock.sleep(reg.DEVICE_RESET_WAIT_S)
    assert sim.read_byte_data(ICM, reg.LP_CONFIG) == 0x40


@pytest.mark.parametrize('odr_config', [0, 3, 4])
def test_duty_cycled_rounds_at_1100_over_two_to_the_odr_config(odr_config):
    """§11.1 (page not verified): 1.1 kHz / 2^I2C_MST_ODR_CONFIG, right after waking (no gyro
    start-up to wait out) and with the accelerometer and gyroscope off."""
    period = (1 << odr_config) / reg.MASTER_CYCLE_RATE_HZ
    for pwr_mgmt_2 in (reg.PWR_MGMT_2_ALL_ON,
                       reg.PWR_MGMT_2_DISABLE_ACCEL | reg.PWR_MGMT_2_DISABLE_GYRO):
        clock, sim = make()
        wake(sim, pwr_mgmt_2)
        bank(sim, reg.MASTER_BANK)
        sim.write_byte_data(ICM, reg.I2C_MST_ODR_CONFIG, odr_config)
        bank(sim, 0)
        sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
        slv4_read(sim, reg.WIA2)
        first = slv4_done_after(sim, clock, period / 50, 2 * period)
        assert first <= period * 1.02  # the next tick of the master's own clock
        # Transfer after transfer, one per round: the rate is the round rate.
        count, start = 0, clock.now
        while clock.now - start < 40 * period:
            slv4_read(sim, reg.WIA2)
            assert slv4_done_after(sim, clock, period / 50, 2 * period) <= 1.05 * period
            count += 1
        assert (clock.now - start) / count == pytest.approx(period, rel=0.05)
        bank(sim, reg.MASTER_BANK)
        assert sim.read_byte_data(ICM, reg.I2C_SLV4_DI) == reg.WIA2_VALUE
        bank(sim, 0)


def test_no_rounds_while_asleep_or_with_the_master_off():
    """The datasheet does not say whether the master runs in sleep: modelled as not."""
    clock, sim = make()
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    slv4_read(sim, reg.WIA1)
    assert slv4_done_after(sim, clock, 0.001, 0.05) == float('inf')
    clock, sim = make()
    wake(sim)
    slv4_read(sim, reg.WIA1)
    assert slv4_done_after(sim, clock, 0.001, 0.05) == float('inf')


def test_cycle_zero_rounds_ride_on_the_gyro_then_the_accel_samples():
    """I2C_MST_CYCLE = 0: rounds at the gyro's ODR (after its start-up), the accel's with the
    gyro off (§11.1, page not verified)."""
    for pwr_mgmt_2, startup in ((reg.PWR_MGMT_2_ALL_ON, reg.SENSOR_STARTUP_S),
                                (reg.PWR_MGMT_2_DISABLE_GYRO, reg.ACCEL_STARTUP_S)):
        clock, sim = make()
        wake(sim, pwr_mgmt_2)
        sim.write_byte_data(ICM, reg.LP_CONFIG, 0)
        bank(sim, reg.CONFIG_BANK)
        sim.write_byte_data(ICM, reg.GYRO_SMPLRT_DIV, 9)  # 112.5 Hz
        sim.write_byte_data(ICM, reg.ACCEL_SMPLRT_DIV_2, 9)
        bank(sim, 0)
        sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
        slv4_read(sim, reg.WIA1)
        assert slv4_done_after(sim, clock, 1e-4, 0.2) >= startup - 1e-4
        period = 1.0 / 112.5
        for _ in range(5):
            slv4_read(sim, reg.WIA1)
            assert period * 0.95 <= slv4_done_after(sim, clock, 1e-5, 0.05) <= period * 1.05


def test_delayed_slaves_run_on_one_round_in_one_plus_dly():
    """I2C_MST_DELAY_CTRL I2C_SLV0_DELAY_EN with I2C_SLV4_DLY = 4 (§11.3, §11.22): slave 0
    reads the AK09916 on one round in five, 220 Hz at the 1.1 kHz duty cycle; the copy in
    EXT_SLV_SENS_DATA stays between its reads."""
    clock, sim = make(SimConfig(seed=2))
    wake(sim)
    bank(sim, reg.MASTER_BANK)
    sim.write_byte_data(ICM, reg.I2C_SLV0_ADDR, reg.I2C_SLV_RNW | reg.AK09916_ADDRESS)
    sim.write_byte_data(ICM, reg.I2C_SLV0_REG, reg.ST1)
    sim.write_byte_data(ICM, reg.I2C_SLV0_CTRL, reg.I2C_SLV_EN | 9)
    sim.write_byte_data(ICM, reg.I2C_SLV4_CTRL, 4)
    sim.write_byte_data(ICM, reg.I2C_MST_DELAY_CTRL, 0x01)
    bank(sim, 0)
    clock.sleep(0.01)  # the AK09916 powered down for more than 100 us
    sim.write_magnetometer(reg.CNTL2, reg.CONTINUOUS_MODES[100])
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    clock.sleep(0.05)
    drdy_lifetimes, alive, last = [], 0, None
    for _ in range(int(1.0 / 1e-4)):  # one second, looked at every 0.1 ms
        clock.sleep(1e-4)
        copy = sim.read_i2c_block_data(ICM, reg.EXT_SLV_SENS_DATA_00, 9)
        if copy[0] & reg.ST1_DRDY:
            alive += 1
        elif alive:
            drdy_lifetimes.append(alive * 1e-4)
            alive = 0
        assert not copy[0] & reg.ST1_DOR  # 220 reads per second keep up with 100 samples
        last = copy
    assert last is not None and 98 <= len(drdy_lifetimes) <= 101
    # Each copy with DRDY lives one read period of slave 0: 5 rounds, 4.5 ms.
    assert np.median(drdy_lifetimes) == pytest.approx(5 / reg.MASTER_CYCLE_RATE_HZ, abs=2e-4)


def rate_of(sim, clock, seconds: float, step: float) -> float:
    """Samples per second seen through RAW_DATA_0_RDY polled every ``step``."""
    sim.read_byte_data(ICM, reg.INT_STATUS_1)
    ready = 0
    for _ in range(int(seconds / step)):
        clock.sleep(step)
        ready += bool(sim.read_byte_data(ICM, reg.INT_STATUS_1) & reg.INT_STATUS_1_RAW_DATA_0_RDY)
    return ready / seconds


def test_each_sensor_its_own_divider_and_the_bypass_rates():
    """DS-000189 tables 16 and 18 (pages not verified): 1125 / (1 + divider) each, and with
    FCHOICE = 0 9 kHz for the gyro, 4.5 kHz for the accelerometer."""
    clock, sim = make()
    wake(sim, reg.PWR_MGMT_2_DISABLE_GYRO)  # the accelerometer alone
    clock.sleep(0.05)
    bank(sim, reg.CONFIG_BANK)
    sim.write_i2c_block_data(ICM, reg.ACCEL_SMPLRT_DIV_1, [0x01, 0x18])  # 280: 4.0 Hz
    sim.write_byte_data(ICM, reg.GYRO_SMPLRT_DIV, 0)  # the gyro's divider is not the accel's
    bank(sim, 0)
    assert rate_of(sim, clock, 2.0, 0.01) == pytest.approx(1125.0 / 281, abs=0.6)
    clock, sim = make()
    wake(sim, reg.PWR_MGMT_2_DISABLE_ACCEL)
    clock.sleep(0.05)
    bank(sim, reg.CONFIG_BANK)
    sim.write_byte_data(ICM, reg.GYRO_CONFIG_1, 0)  # FCHOICE = 0: divider bypassed
    sim.write_byte_data(ICM, reg.GYRO_SMPLRT_DIV, 200)
    bank(sim, 0)
    assert rate_of(sim, clock, 0.05, 1.0 / 20000) == pytest.approx(9000.0, rel=0.01)
    clock, sim = make()
    wake(sim, reg.PWR_MGMT_2_DISABLE_GYRO)
    clock.sleep(0.05)
    bank(sim, reg.CONFIG_BANK)
    sim.write_byte_data(ICM, reg.ACCEL_CONFIG, 0)
    bank(sim, 0)
    assert rate_of(sim, clock, 0.05, 1.0 / 20000) == pytest.approx(4500.0, rel=0.01)


def sample_times(sim, clock, seconds: float, step: float = 1e-5) -> list[float]:
    sim.read_byte_data(ICM, reg.INT_STATUS_1)
    times = []
    for _ in range(int(seconds / step)):
        clock.sleep(step)
        if sim.read_byte_data(ICM, reg.INT_STATUS_1) & reg.INT_STATUS_1_RAW_DATA_0_RDY:
            times.append(clock.now)
    return times


@pytest.mark.parametrize('align', [0, 1])
def test_sample_clock_restarts_only_on_a_divider_write_with_odr_align_en(align):
    """§10.10 ODR_ALIGN_EN (page not verified): with 1, a divider write restarts the sample
    clocks at the write; with 0 (its reset value), and for any GYRO_CONFIG_1/ACCEL_CONFIG write,
    they keep their phase."""
    clock, sim = make()
    wake(sim, reg.PWR_MGMT_2_DISABLE_ACCEL)
    bank(sim, reg.CONFIG_BANK)
    sim.write_byte_data(ICM, reg.ODR_ALIGN_EN, align)
    sim.write_byte_data(ICM, reg.GYRO_SMPLRT_DIV, 9)  # 112.5 Hz
    bank(sim, 0)
    clock.sleep(0.1)
    period = 1.0 / 112.5
    phase = sample_times(sim, clock, 0.03)[-1]
    clock.sleep(0.0031)  # between two samples
    bank(sim, reg.CONFIG_BANK)
    sim.write_byte_data(ICM, reg.GYRO_CONFIG_1, 0x19)  # new DLPF and range: never a restart
    bank(sim, 0)
    after = sample_times(sim, clock, 0.03)
    assert ((after[0] - phase) / period) % 1.0 == pytest.approx(0.0, abs=0.01)
    written = clock.now + 0.0031
    clock.sleep(0.0031)
    bank(sim, reg.CONFIG_BANK)
    sim.write_byte_data(ICM, reg.GYRO_SMPLRT_DIV, 9)  # the same divider written again
    bank(sim, 0)
    after = sample_times(sim, clock, 0.03)
    shift = ((after[0] - phase) / period) % 1.0
    if align:
        assert after[0] == pytest.approx(written + period, abs=2e-5)
    else:
        assert shift == pytest.approx(0.0, abs=0.01) or shift == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize('mode', [reg.MODE_SINGLE, reg.MODE_SELF_TEST])
def test_single_measurement_and_self_test_take_one_sample_and_power_down(mode):
    """AK09916: CNTL2 0x01 / 0x10 measure once, set DRDY (DS-000189 §13.2 p.78), and return to
    power-down (AK09916 datasheet, page not verified); self-test reads the internal source within
    the judgement limits."""
    clock, sim = make(SimConfig(seed=9))
    wake(sim)
    sim.write_byte_data(ICM, reg.INT_PIN_CFG, reg.INT_PIN_CFG_BYPASS_EN)
    clock.sleep(0.01)
    ak = reg.AK09916_ADDRESS
    values = []
    for _ in range(3):  # a driver triggering single measurements one after another
        sim.write_byte_data(ak, reg.CNTL2, mode)
        assert sim.read_byte_data(ak, reg.CNTL2) == mode
        assert not sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY
        clock.sleep(reg.SINGLE_MEASUREMENT_S + 1e-4)
        assert sim.read_byte_data(ak, reg.ST1) == reg.ST1_DRDY
        assert sim.read_byte_data(ak, reg.CNTL2) == reg.MODE_POWER_DOWN
        data = sim.read_i2c_block_data(ak, reg.HXL, reg.MAG_BURST_LENGTH)
        values.append(np.frombuffer(bytes(data[:6]), dtype='<i2'))
        assert not sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY  # one sample, no more
        clock.sleep(0.05)
        assert not sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY
        clock.sleep(reg.MODE_CHANGE_WAIT_S)
    assert sim.samples_measured == 3 and sim.mag_samples_read == 3
    if mode == reg.MODE_SELF_TEST:
        for counts in values:
            for value, (low, high) in zip(counts, reg.SELF_TEST_LIMITS, strict=True):
                assert low <= value <= high
    else:
        for counts in values:
            field = counts * np.asarray(reg.AXIS_SIGNS) * reg.TESLA_PER_LSB
            assert sim.truth_for_reading(field) is not None


def test_a_single_measurement_latches_after_a_read_st2_never_ended_a_continuous_one_waits():
    """A data read that ST2 never ended protects the registers in the continuous modes: the
    next sample waits and DRDY stays 0. A new single measurement latches regardless (DS-000189
    §13.2 p.78 is silent; Pimoroni's icm20948 never reads ST2 there and works on real boards)."""
    clock, sim = make(SimConfig(seed=3))
    wake(sim)
    sim.write_byte_data(ICM, reg.INT_PIN_CFG, reg.INT_PIN_CFG_BYPASS_EN)
    clock.sleep(0.01)
    ak = reg.AK09916_ADDRESS
    sim.write_byte_data(ak, reg.CNTL2, reg.MODE_SINGLE)
    clock.sleep(reg.SINGLE_MEASUREMENT_S + 1e-4)
    for _ in range(3):
        sim.read_i2c_block_data(ak, reg.HXL, 6)  # HXL..HZH: the read starts, never ends
        clock.sleep(reg.MODE_CHANGE_WAIT_S)
        sim.write_byte_data(ak, reg.CNTL2, reg.MODE_SINGLE)
        clock.sleep(reg.SINGLE_MEASUREMENT_S + 1e-4)
        assert sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY
    assert sim.samples_measured == sim.mag_samples_read + 1 == 4
    sim.read_i2c_block_data(ak, reg.HXL, reg.MAG_BURST_LENGTH)  # ends with ST2
    sim.write_byte_data(ak, reg.CNTL2, reg.MODE_POWER_DOWN)
    clock.sleep(reg.MODE_CHANGE_WAIT_S)
    rate = next(mode for mode, hz in reg.CONTINUOUS_RATES.items() if hz == 100)
    sim.write_byte_data(ak, reg.CNTL2, rate)
    clock.sleep(0.015)
    assert sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY
    sim.read_i2c_block_data(ak, reg.HXL, 6)  # no ST2: protected from here on
    clock.sleep(0.05)
    assert not sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY
    sim.read_byte_data(ak, reg.ST2)  # the read ends: the sample that waited is latched
    assert sim.read_byte_data(ak, reg.ST1) & reg.ST1_DRDY


def test_single_measurement_through_the_master():
    """A driver that triggers single measurements through SLV4 sees DRDY in the copy."""
    clock, sim = make(SimConfig(seed=1))
    wake(sim)
    bank(sim, reg.MASTER_BANK)
    sim.write_byte_data(ICM, reg.I2C_SLV0_ADDR, reg.I2C_SLV_RNW | reg.AK09916_ADDRESS)
    sim.write_byte_data(ICM, reg.I2C_SLV0_REG, reg.ST1)
    sim.write_byte_data(ICM, reg.I2C_SLV0_CTRL, reg.I2C_SLV_EN | 9)
    bank(sim, 0)
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    clock.sleep(0.01)
    slv4_write(sim, reg.CNTL2, reg.MODE_SINGLE)
    drdy = 0
    for _ in range(200):  # 20 ms
        clock.sleep(1e-4)
        drdy += bool(sim.read_byte_data(ICM, reg.EXT_SLV_SENS_DATA_00) & reg.ST1_DRDY)
    assert 0 < drdy and sim.samples_measured == 1


def test_accel_and_gyro_of_one_sample_in_two_reads_is_one_delivery():
    clock, sim = make()
    wake(sim)
    clock.sleep(0.05)
    sim.read_i2c_block_data(ICM, reg.ACCEL_XOUT_H, 6)
    sim.read_i2c_block_data(ICM, reg.ACCEL_XOUT_H + 6, 6)
    assert sim.imu_samples_read == 1 and sim.imu_repeated_reads == 0
    sim.read_i2c_block_data(ICM, reg.ACCEL_XOUT_H, 6)  # the accelerometer's again: repeated
    assert sim.imu_repeated_reads == 1
    clock.sleep(0.001)
    sim.read_i2c_block_data(ICM, reg.ACCEL_XOUT_H, 12)
    assert sim.imu_samples_read == 2 and sim.imu_repeated_reads == 1


def test_ak09916_multi_byte_transfers_follow_its_address_sequence():
    """DS-000189 §12 p.77: the AK09916 auto-increments 00h-03h then 10h-18h and back to 00h, and
    30h-32h back to 30h; in bypass, through slave 0 and in a block write alike."""
    clock, sim = make(SimConfig(seed=4))
    wake(sim)
    sim.write_byte_data(ICM, reg.INT_PIN_CFG, reg.INT_PIN_CFG_BYPASS_EN)
    clock.sleep(0.01)
    ak = reg.AK09916_ADDRESS
    assert sim.read_i2c_block_data(ak, reg.ST2, 3) == [0, reg.WIA1_VALUE, reg.WIA2_VALUE]
    assert sim.read_i2c_block_data(ak, 0x03, 2) == [0, 0]  # 03h then ST1 (no sample yet)
    sim.write_i2c_block_data(ak, reg.CNTL2, [reg.MODE_SINGLE, 0, 0])  # 31h, 32h, 30h
    assert sim.read_i2c_block_data(ak, reg.CNTL3, 3) == [0, 0, reg.MODE_SINGLE]  # 32h, 30h, 31h
    clock.sleep(reg.SINGLE_MEASUREMENT_S + 1e-4)
    assert sim.read_i2c_block_data(ak, 0x03, 2) == [0, reg.ST1_DRDY]
    sim.write_byte_data(ICM, reg.INT_PIN_CFG, 0)
    bank(sim, reg.MASTER_BANK)
    sim.write_byte_data(ICM, reg.I2C_SLV0_ADDR, reg.I2C_SLV_RNW | ak)
    sim.write_byte_data(ICM, reg.I2C_SLV0_REG, reg.ST2)
    sim.write_byte_data(ICM, reg.I2C_SLV0_CTRL, reg.I2C_SLV_EN | 3)
    bank(sim, 0)
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    clock.sleep(0.01)
    copy = sim.read_i2c_block_data(ICM, reg.EXT_SLV_SENS_DATA_00, 3)
    assert copy == [0, reg.WIA1_VALUE, reg.WIA2_VALUE]

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The FIFO (issue #48): the simulator's as DS-000189 and the drivers that run on boards know
it. On a fake clock: deterministic."""

from icm20948_fakes import FakeClock
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.units import temperature_counts
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

ICM = 0x69
START = 1000.0  # the fake clock's start: sim time = clock - START


# --- the simulated FIFO, register by register ---------------------------------------------

def awake_sim(clock: FakeClock, fifo_en_2: int = reg.FIFO_EN_2_ALL,
              snapshot: bool = True) -> SimulatedIcm20948Bus:
    """Awake at 1125 Hz (divider 0, aligned clocks), the FIFO taking ``fifo_en_2``."""
    sim = SimulatedIcm20948Bus(SimConfig(seed=4), clock=clock)
    sim.write_byte_data(ICM, reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO)
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, reg.CONFIG_BANK << reg.BANK_SHIFT)
    sim.write_byte_data(ICM, reg.ODR_ALIGN_EN, 1)
    sim.write_byte_data(ICM, reg.GYRO_SMPLRT_DIV, 0)
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, 0)
    sim.write_byte_data(ICM, reg.FIFO_MODE, reg.FIFO_MODE_SNAPSHOT if snapshot else 0)
    sim.write_byte_data(ICM, reg.FIFO_EN_2, fifo_en_2)
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_FIFO_EN)
    return sim


def fifo_count(sim) -> int:
    high, low = sim.read_i2c_block_data(ICM, reg.FIFO_COUNTH, 2)
    return ((high & reg.FIFO_COUNT_HIGH_MASK) << 8) | low


FIRST_SAMPLE = np.ceil(reg.SENSOR_STARTUP_S * 1125.0) / 1125.0  # after the 35 ms start-up


def records_after_start(seconds: float) -> int:
    """Samples of the gyro's 1125 Hz clock ``seconds`` after it was aligned, none before its
    start-up time."""
    return int(np.floor((seconds - FIRST_SAMPLE) * 1125.0 + 1e-6)) + 1


def read_fifo(sim, length: int) -> list[int]:
    """``length`` FIFO_R_W bytes in SMBus blocks of at most 32."""
    data = []
    while len(data) < length:
        data += sim.read_i2c_block_data(ICM, reg.FIFO_R_W, min(32, length - len(data)))
    return data


@pytest.mark.parametrize('fifo_en_2, length', [
    (reg.FIFO_EN_2_ALL, 14), (reg.FIFO_EN_2_ACCEL, 6),
    (reg.FIFO_EN_2_ACCEL | reg.FIFO_EN_2_GYRO, 12), (reg.FIFO_EN_2_TEMP, 2)])
def test_each_sample_appends_the_selected_registers_in_register_order(fifo_en_2, length):
    clock = FakeClock(START)
    sim = awake_sim(clock, fifo_en_2)
    clock.now += 0.040
    count = fifo_count(sim)
    assert count == records_after_start(0.040) * length
    data = read_fifo(sim, count)
    newest = data[-length:]
    registers = sim.read_i2c_block_data(ICM, reg.ACCEL_XOUT_H, reg.IMU_BURST_LENGTH)
    fields = [(reg.FIFO_EN_2_ACCEL, registers[0:6]), (1 << 1, registers[6:8]),
              (1 << 2, registers[8:10]), (1 << 3, registers[10:12]),
              (reg.FIFO_EN_2_TEMP, registers[12:14])]
    assert newest == [b for bit, part in fields if fifo_en_2 & bit for b in part]
    assert fifo_count(sim) == 0 and sim.read_byte_data(ICM, reg.FIFO_R_W) == reg.FIFO_EMPTY_BYTE


def test_a_read_from_the_count_runs_on_into_the_fifo_and_stays_there():
    """PX4's ICM20948 driver reads FIFO_COUNTH, FIFO_COUNTL and the records in one transfer."""
    clock = FakeClock(START)
    sim = awake_sim(clock)
    clock.now += FIRST_SAMPLE + 2.5 / 1125.0  # three records
    block = sim.read_i2c_block_data(ICM, reg.FIFO_COUNTH, 2 + 28)
    assert block[:2] == [0, 3 * 14]
    assert fifo_count(sim) == 14 and sim.fifo.delivered_count == 2
    assert [t.sample_time for t in sim.imu_truths_read()] == pytest.approx(
        [FIRST_SAMPLE, FIRST_SAMPLE + 1 / 1125.0], abs=1e-6)


def test_snapshot_mode_keeps_the_oldest_whole_records_and_flags_the_overflow():
    clock = FakeClock(START)
    sim = awake_sim(clock, snapshot=True)
    clock.now += 0.2
    assert fifo_count(sim) == (reg.FIFO_SIZE // 14) * 14
    assert sim.read_byte_data(ICM, reg.INT_STATUS_2) == reg.INT_STATUS_2_FIFO_OVERFLOW
    assert sim.read_byte_data(ICM, reg.INT_STATUS_2) == 0  # read to clear
    first = sim.read_i2c_block_data(ICM, reg.FIFO_R_W, 14)
    truth = sim.imu_truths_read()[0]
    assert truth.sample_time == pytest.approx(FIRST_SAMPLE, abs=1e-6)
    word = temperature_counts(truth.temperature_c) & 0xFFFF
    assert first[12:14] == [word >> 8, word & 0xFF]  # the oldest record, whole
    assert sim.fifo.lost == records_after_start(0.2) - reg.FIFO_SIZE // 14


def test_stream_mode_overwrites_the_oldest_bytes_so_the_head_is_torn():
    clock = FakeClock(START)
    sim = awake_sim(clock, snapshot=False)
    clock.now += 0.2
    assert fifo_count(sim) == reg.FIFO_SIZE  # not a whole number of records
    assert reg.FIFO_SIZE % 14 != 0 and sim.read_byte_data(ICM, reg.INT_STATUS_2)


def test_fifo_rst_empties_it_and_holds_it_empty_while_set():
    clock = FakeClock(START)
    sim = awake_sim(clock)
    clock.now += 0.05
    sim.write_byte_data(ICM, reg.FIFO_RST, reg.FIFO_RST_ALL)
    clock.now += 0.01
    assert fifo_count(sim) == 0
    sim.write_byte_data(ICM, reg.FIFO_RST, 0)
    clock.now += 0.01
    assert fifo_count(sim) in (11 * 14, 12 * 14)


def test_the_external_sensor_data_goes_in_after_the_temperature_as_the_master_copied_it():
    clock = FakeClock(START)
    sim = awake_sim(clock)
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_FIFO_EN | reg.USER_CTRL_I2C_MST_EN)
    sim.write_byte_data(ICM, reg.LP_CONFIG, 0)  # rounds on the gyro's samples
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, reg.MASTER_BANK << reg.BANK_SHIFT)
    sim.write_byte_data(ICM, reg.I2C_SLV0_ADDR, reg.I2C_SLV_RNW | reg.AK09916_ADDRESS)
    sim.write_byte_data(ICM, reg.I2C_SLV0_REG, reg.WIA1)
    sim.write_byte_data(ICM, reg.I2C_SLV0_CTRL, reg.I2C_SLV_EN | 2)
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, 0)
    sim.write_byte_data(ICM, reg.FIFO_RST, reg.FIFO_RST_ALL)
    sim.write_byte_data(ICM, reg.FIFO_RST, 0)
    sim.write_byte_data(ICM, reg.FIFO_EN_1, 1 << 0)
    clock.now += 0.05
    count = fifo_count(sim)
    assert count and count % 16 == 0
    data = sim.read_i2c_block_data(ICM, reg.FIFO_R_W, 16)
    assert data[14:16] == [reg.WIA1_VALUE, reg.WIA2_VALUE]

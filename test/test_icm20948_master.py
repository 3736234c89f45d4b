# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The AK09916 through the ICM-20948's own I2C master (issue #11: magnetometer polling at <= 1/3
of the old bus bytes), at register level against the simulated chip: bank 3 and SLV4 protocol
enforced by the model, the EXT_SLV_SENS_DATA copy, each sample taken once, the wire cost."""

from icm20948_fakes import FakeClock, RecordingBus
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import (
    AuxiliaryBusError,
    Icm20948,
    ImuSettings,
    master_possible,
)
from mag_calibrator_ros.icm20948.supervisor import Icm20948Supervisor, MagSample
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

ICM = 0x69
IMU = ImuSettings(rate_hz=200)  # the chip runs 225 Hz: 2.25 master rounds per magnetometer sample


def make(config: SimConfig | None = None):
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(config if config is not None else SimConfig(), clock=clock)
    return clock, sim


def awake_sampling(sim, clock) -> None:
    """Wake the ICM-20948 with accel/gyro on and wait out their start-up (master rounds run)."""
    sim.write_byte_data(ICM, reg.PWR_MGMT_1, reg.PWR_MGMT_1_CLKSEL_AUTO)
    clock.sleep(reg.SENSOR_STARTUP_S + 0.001)


def slv4_read(sim, register: int, bank: int = reg.MASTER_BANK,
              address: int = reg.AK09916_ADDRESS) -> None:
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, bank << reg.BANK_SHIFT)
    sim.write_byte_data(ICM, reg.I2C_SLV4_ADDR, reg.I2C_SLV_RNW | address)
    sim.write_byte_data(ICM, reg.I2C_SLV4_REG, register)
    sim.write_byte_data(ICM, reg.I2C_SLV4_CTRL, reg.I2C_SLV_EN)
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, 0)


def test_slv4_transfer_finishes_at_the_next_round_in_bank_3_only():
    clock, sim = make()
    awake_sampling(sim, clock)
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    slv4_read(sim, reg.WIA2, bank=0)  # the SLV4 registers live in bank 3: nothing starts
    clock.sleep(0.02)
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) == 0
    slv4_read(sim, reg.WIA2)
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) == 0  # no round yet: not done
    clock.sleep(1.0 / 1125.0)  # one sample (divider 0 after reset)
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) == reg.I2C_MST_STATUS_SLV4_DONE
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) == 0  # read-to-clear
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, reg.MASTER_BANK << reg.BANK_SHIFT)
    assert sim.read_byte_data(ICM, reg.I2C_SLV4_DI) == reg.WIA2_VALUE
    assert sim.read_byte_data(ICM, reg.I2C_SLV4_CTRL) & reg.I2C_SLV_EN == 0  # one transfer


def test_slv4_needs_the_master_enabled_and_the_chip_sampling():
    clock, sim = make()
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    slv4_read(sim, reg.WIA1)  # asleep after power-on: no rounds
    clock.sleep(0.1)
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) == 0
    clock, sim = make()
    awake_sampling(sim, clock)
    slv4_read(sim, reg.WIA1)  # awake, but the master is off
    clock.sleep(0.1)
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) == 0


def test_a_wrong_slave_address_is_nacked():
    clock, sim = make()
    awake_sampling(sim, clock)
    sim.write_byte_data(ICM, reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN)
    slv4_read(sim, reg.WIA1, address=0x0D)
    clock.sleep(0.002)
    status = sim.read_byte_data(ICM, reg.I2C_MST_STATUS)
    assert status == reg.I2C_MST_STATUS_SLV4_DONE | reg.I2C_MST_STATUS_SLV4_NACK
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, reg.MASTER_BANK << reg.BANK_SHIFT)
    sim.write_byte_data(ICM, reg.I2C_SLV0_ADDR, reg.I2C_SLV_RNW | 0x0D)
    sim.write_byte_data(ICM, reg.I2C_SLV0_REG, reg.ST1)
    sim.write_byte_data(ICM, reg.I2C_SLV0_CTRL, reg.I2C_SLV_EN | 9)
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, 0)
    clock.sleep(0.002)
    assert sim.read_byte_data(ICM, reg.I2C_MST_STATUS) & reg.I2C_MST_STATUS_SLV0_NACK
    copy = sim.read_i2c_block_data(ICM, reg.EXT_SLV_SENS_DATA_00, 9)
    assert copy == [0] * 9  # nothing copied from a slave that did not answer


def test_bring_up_through_the_master_sequence_banks_and_waits():
    clock, sim = make()
    bus = RecordingBus(sim, clock)
    driver = Icm20948(bus, address=ICM, sleep=clock.sleep, clock=clock)
    driver.initialise(100, IMU, aux_master=True)
    assert driver.aux_master
    assert all(e.address == ICM for e in bus.log)  # the AK09916 never on the host bus
    writes = [(e.register, e.value, e.bank) for e in bus.log if e.kind == 'w'
              and e.register != reg.REG_BANK_SEL]
    # Only what was written with bank 3 selected reached the SLV4 registers (bank 0 has others
    # at these addresses).
    slv4 = [(register, value) for register, value, bank in writes
            if bank == reg.MASTER_BANK and register in (reg.I2C_SLV4_REG, reg.I2C_SLV4_DO)]
    # WIA1, WIA2 read; SRST, power-down, continuous mode written; CNTL2 read back.
    assert [v for r, v in slv4 if r == reg.I2C_SLV4_REG] == [
        reg.WIA1, reg.WIA2, reg.CNTL3, reg.CNTL2, reg.CNTL2, reg.CNTL2]
    assert [v for r, v in slv4 if r == reg.I2C_SLV4_DO] == [
        reg.CNTL3_SRST, reg.MODE_POWER_DOWN, reg.CONTINUOUS_MODES[100]]
    assert (reg.USER_CTRL, reg.USER_CTRL_I2C_MST_EN, 0) in writes
    assert (reg.INT_PIN_CFG, 0, 0) in writes  # bypass off
    # The power-down -> continuous step waited (each SLV4 transfer runs on the next round).
    starts = [e.time for e in bus.log if e.kind == 'w' and e.bank == reg.MASTER_BANK
              and e.register == reg.I2C_SLV4_CTRL]
    assert starts[4] - starts[3] >= reg.MODE_CHANGE_WAIT_S
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, reg.MASTER_BANK << reg.BANK_SHIFT)
    assert sim.read_i2c_block_data(ICM, reg.I2C_SLV0_ADDR, 8) == [
        reg.I2C_SLV_RNW | reg.AK09916_ADDRESS, reg.ST1, reg.I2C_SLV_EN | 7, 0,
        reg.I2C_SLV_RNW | reg.AK09916_ADDRESS, reg.ST2, reg.I2C_SLV_EN | 1, 0]
    sim.write_byte_data(ICM, reg.REG_BANK_SEL, 0)
    assert driver.measurement_mode() == reg.CONTINUOUS_MODES[100]  # through SLV4


def test_without_waiting_for_the_master_bring_up_fails():
    """A driver that does not wait for I2C_SLV4_DONE (its sleep does nothing, time stands still)
    never sees the transfer finish: the model only runs rounds on samples."""
    clock, sim = make()
    hasty = Icm20948(sim, address=ICM, sleep=lambda seconds: None, clock=clock)
    with pytest.raises(OSError):
        hasty.initialise(100, IMU, aux_master=True)


def test_a_missing_magnetometer_is_named():
    clock, sim = make(SimConfig(ak09916_id=(0x48, 0x05)))
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    with pytest.raises(ValueError, match='not an AK09916'):
        driver.initialise(100, IMU, aux_master=True)


def test_the_master_path_needs_fast_enough_accel_gyro():
    assert master_possible(100, ImuSettings(rate_hz=200))
    assert not master_possible(100, ImuSettings(rate_hz=150))  # 160.7 Hz < 2 x 100 Hz
    assert master_possible(50, ImuSettings(rate_hz=150)) and not master_possible(100, None)
    clock, sim = make()
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    with pytest.raises(ValueError, match='at least 2 x the magnetometer rate'):
        driver.initialise(100, ImuSettings(rate_hz=150), aux_master=True)
    supervisor = Icm20948Supervisor(lambda: sim, imu=ImuSettings(rate_hz=150), clock=clock,
                                    sleep=clock.sleep)
    assert not supervisor.aux_master  # falls back to bypass
    assert Icm20948Supervisor(lambda: sim, imu=IMU, clock=clock, sleep=clock.sleep).aux_master


def test_the_copy_follows_the_magnetometer_with_drdy_in_one_round_per_sample():
    clock, sim = make(SimConfig(seed=4))
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    driver.initialise(100, IMU, aux_master=True)
    drdy_rounds, copies = 0, set()
    for _ in range(225):  # one second, sampled once per round
        clock.sleep(1.0 / IMU.odr_hz)
        copy = sim.read_i2c_block_data(ICM, reg.EXT_SLV_SENS_DATA_00, 8)
        drdy_rounds += copy[0] & reg.ST1_DRDY
        assert copy[0] & reg.ST1_DOR == 0  # the master reads every sample: no overrun
        copies.add(bytes(copy[1:7]))
    assert 99 <= drdy_rounds <= 101 and len(copies) >= 95
    # The IMU burst reaches the copy: it starts right after TEMP_OUT_L.
    burst = sim.read_i2c_block_data(ICM, reg.ACCEL_XOUT_H, reg.IMU_BURST_LENGTH + 8)
    assert burst[reg.IMU_BURST_LENGTH:] == sim.read_i2c_block_data(
        ICM, reg.EXT_SLV_SENS_DATA_00, 8)


def poll(clock, driver, seconds: float):
    mag, imu = [], 0
    for _ in range(int(round(seconds * IMU.odr_hz * 1.5))):
        clock.sleep(1.0 / (1.5 * IMU.odr_hz))
        imu += driver.read_imu() is not None
        reading = driver.read_mag()
        if reading is not None:
            mag.append(reading)
    return mag, imu


def test_each_sample_once_with_truth_at_about_nine_wire_bytes():
    clock, sim = make(SimConfig(seed=5, noise_ut=0.2))
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    driver.initialise(100, IMU, aux_master=True)
    before = driver.bus.monitor.share('magnetometer')
    mag, imu = poll(clock, driver, 5.0)
    assert len(mag) >= 495 and imu >= 0.99 * 5 * IMU.odr_hz
    assert sim.mag_repeated_reads == 0 and len(mag) == sim.mag_samples_read
    truths = np.array([sim.truth_for_reading(r.field_tesla) for r in mag])
    fields = np.array([r.field_tesla for r in mag])
    assert np.sqrt(np.mean(np.sum((fields - truths) ** 2, axis=1))) < 0.6e-6
    spent = driver.bus.monitor.share('magnetometer') - before
    assert spent.wire_bytes / len(mag) <= 16  # 8 per look, 1-2 looks per sample
    assert driver.mag_fallbacks == 0  # every sample by its copied DRDY
    assert spent.wire_bytes / len(mag) >= 8


def test_overflow_through_the_master_is_discarded_and_counted():
    config = SimConfig(hard_iron_ut=(4900.0, 0.0, 0.0), noise_ut=0.0, seed=2)
    clock, sim = make(config)
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    driver.initialise(100, IMU, aux_master=True)
    mag, _ = poll(clock, driver, 5.0)
    assert driver.overflows > 10
    assert len(mag) + driver.overflows == pytest.approx(495, abs=5)
    assert all(np.all(np.abs(r.counts) <= reg.MEASUREMENT_LIMIT) for r in mag)


def test_i2c_errors_hit_the_host_reads_not_the_auxiliary_bus():
    clock, sim = make(SimConfig(i2c_error_rate=0.05, seed=3))
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    for _ in range(20):  # bring-up retries each access; rarely all fail at 5 %
        try:
            driver.initialise(100, IMU, aux_master=True)
            break
        except OSError:
            continue
    mag, errors = [], 0
    for _ in range(int(5 * IMU.odr_hz * 1.5)):
        clock.sleep(1.0 / (1.5 * IMU.odr_hz))
        try:
            driver.read_imu()
        except OSError:
            errors += 1
        reading = driver.read_mag()
        if reading is not None:
            mag.append(reading)
    assert errors > 0 and sim.injected_errors > 50
    # A failed lengthened burst costs nothing: the copy keeps the newest sample for a period.
    assert len(mag) >= 0.98 * 495
    assert sim.mag_repeated_reads == 0 and len(mag) == sim.mag_samples_read


def test_supervisor_recovers_the_master_after_a_brown_out():
    clock, sim = make(SimConfig(seed=7))
    samples = []
    supervisor = Icm20948Supervisor(lambda: sim, imu=IMU, clock=clock, sleep=clock.sleep,
                                    stamp=clock)

    def advance(seconds):
        end = clock.now + seconds
        while clock.now < end:
            clock.now = max(clock.now, min(supervisor.next_due(), end)) + 20e-6
            samples.extend(supervisor.step())

    advance(0.5)
    assert supervisor.aux_master and sim.mag_samples_read > 40
    sim.chip_reset()  # both dies back to power-on: master off, AK09916 powered down
    advance(1.0)
    assert supervisor.reinitialisations == 1
    count = len([s for s in samples if isinstance(s, MagSample)])
    advance(0.5)
    assert len([s for s in samples if isinstance(s, MagSample)]) >= count + 45
    assert sim.read_byte_data(ICM, reg.USER_CTRL) & reg.USER_CTRL_I2C_MST_EN  # reconfigured
    assert sim.mag_repeated_reads == 0


def test_a_sleeping_chip_fails_the_slv4_probe():
    clock, sim = make()
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    driver.initialise(100, IMU, aux_master=True)
    sim.write_byte_data(ICM, reg.PWR_MGMT_1, reg.PWR_MGMT_1_RESET_VALUE)  # asleep: no rounds
    with pytest.raises(AuxiliaryBusError, match='did not finish'):
        driver.measurement_mode()


def test_an_outage_is_recognised_by_the_failing_reads_not_the_silent_magnetometer():
    """Through the master read_mag touches no bus: it must not count as a successful read
    between failing accel/gyro reads (the outage was only noticed by the stuck check, 0.25 s)."""
    clock, sim = make(SimConfig(seed=6))
    logs = []
    supervisor = Icm20948Supervisor(lambda: sim, imu=IMU, clock=clock, sleep=clock.sleep,
                                    stamp=clock, log=lambda *entry: logs.append(entry))
    end = clock.now + 1.0
    while clock.now < end:
        clock.now = max(clock.now, min(supervisor.next_due(), end)) + 20e-6
        supervisor.step()
    sim.start_outage(2.0)
    end = clock.now + 0.5
    while clock.now < end:
        clock.now = max(clock.now, min(supervisor.next_due(), end)) + 20e-6
        supervisor.step()
    errors = [message for level, message in logs if level == 'error']
    assert len(errors) == 1 and 'I2C reads failed in a row' in errors[0]

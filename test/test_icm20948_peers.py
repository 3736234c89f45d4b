# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Other people's ICM-20948 drivers, unchanged from PyPI, against the simulated chip (#23, #48).

Our driver and the simulator share one model of the chip, so they agree by construction. These
drivers were written against real boards: SparkFun's ``qwiic_icm20948`` (over smbus2 through
``qwiic_i2c``), Adafruit's ``adafruit_icm20x`` (over CircuitPython's ``busio.I2C``, stood in
for by ``BusioI2C`` below) and Pimoroni's ``icm20948`` (an smbus2 bus, single measurements
without ST2). Each must bring the chip up on its first attempt, and read
magnetometer samples that are the simulator's truth (in the AK09916's own axes), |accel| = 1 g on
a still board, and a plausible gyro and temperature. A failure here is a finding about the
simulator, to be fixed from the datasheet, never by patching the peer driver.

Installed from requirements-peers.txt (``--no-deps``: their board-detection dependencies are
not needed; ``make setup`` does it). They run in real time: their waits are ``time.sleep``.
"""

from __future__ import annotations

import math
import sys
import time
import types

import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.units import counts_to_tesla
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

ICM = 0x69
SAMPLES = 20
STILL = SimConfig(motion='still', seed=5)


class MasterResetWatch:
    """The simulated bus, passed through, counting writes that set USER_CTRL I2C_MST_RST: both
    peer drivers reset the I2C master and retry when the AK09916 did not answer, so any such
    write means their first attempt failed."""

    def __init__(self, sim: SimulatedIcm20948Bus) -> None:
        self.sim = sim
        self.bank = 0
        self.master_resets = 0

    def _wrote(self, register: int, value: int) -> None:
        if register == reg.REG_BANK_SEL:
            self.bank = (value & reg.BANK_MASK) >> reg.BANK_SHIFT
        elif self.bank == 0 and register == reg.USER_CTRL and value & reg.USER_CTRL_I2C_MST_RST:
            self.master_resets += 1

    def write_byte_data(self, address, register, value, force=None):
        self.sim.write_byte_data(address, register, value)
        if address == ICM:
            self._wrote(register, value)

    def write_i2c_block_data(self, address, register, data, force=None):
        self.sim.write_i2c_block_data(address, register, data)
        if address == ICM:
            for offset, value in enumerate(data):
                self._wrote(register + offset, value)

    def __getattr__(self, name):
        return getattr(self.sim, name)


class BusioI2C:
    """The part of CircuitPython's ``busio.I2C`` that adafruit_bus_device uses, on an
    smbus2-like bus: a write is the register address followed by data; a read is a write of
    the register address, then the bytes read (``writeto_then_readfrom``)."""

    def __init__(self, bus) -> None:
        self.bus = bus

    def try_lock(self) -> bool:
        return True

    def unlock(self) -> None:
        pass

    def writeto(self, address: int, buffer, *, start: int = 0, end: int | None = None) -> None:
        data = bytes(buffer[start:end])
        if not data:
            self.bus.write_quick(address)  # the probe of I2CDevice
        elif len(data) == 2:
            self.bus.write_byte_data(address, data[0], data[1])
        else:
            self.bus.write_i2c_block_data(address, data[0], list(data[1:]))

    def writeto_then_readfrom(self, address: int, out_buffer, in_buffer, *, out_start: int = 0,
                              out_end: int | None = None, in_start: int = 0,
                              in_end: int | None = None) -> None:
        register = bytes(out_buffer[out_start:out_end])[0]
        in_end = len(in_buffer) if in_end is None else in_end
        values = self.bus.read_i2c_block_data(address, register, in_end - in_start)
        in_buffer[in_start:in_end] = bytes(values)


def assert_the_truth(sim: SimulatedIcm20948Bus, readings: list[tuple[int, int, int]]) -> None:
    """Each reading (AK09916 counts, its own axes) is a sample the simulator measured, within
    the configured noise of its true field; and they are new samples, not one read again."""
    assert len(readings) == SAMPLES
    assert len(set(readings)) >= SAMPLES // 2  # 0.3 uT noise: 2 counts; still board
    tolerance = 6.0 * STILL.noise_ut * 1e-6 + reg.TESLA_PER_LSB
    for counts in readings:
        field = counts_to_tesla(np.array(counts))
        truth = sim.truth_for_reading(field)
        assert truth is not None, f'{counts} is no sample the simulated AK09916 measured'
        assert np.all(np.abs(field - truth) <= tolerance), (counts, field, truth)
        assert np.linalg.norm(truth) == pytest.approx(STILL.field_ut * 1e-6, rel=0.01)


def test_sparkfun_qwiic_icm20948_runs_unchanged(monkeypatch):
    qwiic_i2c = pytest.importorskip('qwiic_i2c')
    qwiic_icm20948 = pytest.importorskip('qwiic_icm20948')
    import smbus2

    sim = SimulatedIcm20948Bus(STILL)
    bus = MasterResetWatch(sim)
    monkeypatch.setattr(smbus2, 'SMBus', lambda number: bus)  # what /dev/i2c-1 would be
    driver = qwiic_i2c.getI2CDriver(iBus=1)
    assert driver is not None and driver.i2cbus is bus
    imu = qwiic_icm20948.QwiicIcm20948(address=ICM, i2c_driver=driver)
    assert imu.begin()
    assert bus.master_resets == 0  # its AK09916 check passed at the first attempt
    assert imu.magWhoIAm()
    readings, accel, gyro, temperature = [], [], [], []
    while len(readings) < SAMPLES:
        time.sleep(0.012)  # the AK09916 measures at 100 Hz: a new sample each time
        for _ in range(1000):  # as SparkFun's examples do: accel/gyro data ready first
            if imu.dataReady():
                break
            time.sleep(0.001)
        assert imu.getAgmt()
        readings.append((imu.mxRaw, imu.myRaw, imu.mzRaw))
        accel.append((imu.axRaw, imu.ayRaw, imu.azRaw))
        gyro.append((imu.gxRaw, imu.gyRaw, imu.gzRaw))
        temperature.append(imu.tmpRaw)
    assert_the_truth(sim, readings)
    # begin(): +-2 g, +-250 dps, DLPF bypassed (the gyro's noise bandwidth is 12 kHz then).
    g = np.linalg.norm(np.array(accel) / reg.ACCEL_RANGES_G[2][1], axis=1)
    assert np.all(np.abs(g - 1.0) < 0.05)
    assert np.all(np.abs(np.array(gyro) / reg.GYRO_RANGES_DPS[250][1]) < 10.0)
    celsius = np.array(temperature) / reg.TEMP_SENSITIVITY_LSB_PER_C + reg.TEMP_OFFSET_C
    assert np.all(np.abs(celsius - STILL.temperature_c) < STILL.temperature_rise_c + 0.5)


def test_adafruit_icm20x_runs_unchanged(monkeypatch):
    busio = types.ModuleType('busio')  # CircuitPython's, or Blinka's on a Raspberry Pi
    busio.I2C = BusioI2C
    busio.SPI = type('SPI', (), {})  # named in adafruit_bus_device's annotations, never used
    monkeypatch.setitem(sys.modules, 'busio', busio)
    adafruit_icm20x = pytest.importorskip('adafruit_icm20x')

    sim = SimulatedIcm20948Bus(STILL)
    bus = MasterResetWatch(sim)
    imu = adafruit_icm20x.ICM20948(busio.I2C(bus), ICM)
    assert bus.master_resets == 0  # its AK09916 check passed at the first attempt
    readings, accel, gyro = [], [], []
    while len(readings) < SAMPLES:
        time.sleep(0.012)
        magnetic = imu.magnetic  # uT in the AK09916's axes
        readings.append(tuple(round(v / 0.15) for v in magnetic))
        accel.append(imu.acceleration)
        gyro.append(imu.gyro)
    assert_the_truth(sim, readings)
    assert np.all(np.abs(np.linalg.norm(accel, axis=1) - reg.STANDARD_GRAVITY) < 0.3)
    assert np.all(np.abs(np.array(gyro)) < math.radians(5.0))
    assert imu.accelerometer_data_rate == pytest.approx(1125.0 / 21)  # its own divider, 20
    assert imu.gyro_data_rate == pytest.approx(1100.0 / 11)


def test_pimoroni_icm20948_runs_unchanged():
    """Pimoroni's ``icm20948`` (MIT, github.com/pimoroni/icm20948-python) starts a single
    measurement for every field, waits for DRDY and reads HXL..HZH through SLV0 without ever
    reading ST2, which it says only continuous modes need; on real boards it reads a new
    field each time, so a single measurement latches whether or not ST2 ended the last read."""
    icm20948 = pytest.importorskip('icm20948')
    sim = SimulatedIcm20948Bus(STILL)
    bus = MasterResetWatch(sim)
    imu = icm20948.ICM20948(i2c_addr=ICM, i2c_bus=bus)
    readings, motion = [], []
    while len(readings) < SAMPLES:
        x, y, z = imu.read_magnetometer_data(timeout=0.5)  # uT, the AK09916's axes
        readings.append(tuple(round(v / 0.15) for v in (x, y, z)))
        motion.append(imu.read_accelerometer_gyro_data())  # g and deg/s
    assert_the_truth(sim, readings)
    accel, gyro = np.array(motion)[:, :3], np.array(motion)[:, 3:]
    assert np.all(np.abs(np.linalg.norm(accel, axis=1) - 1.0) < 0.05)
    assert np.all(np.abs(gyro) < 5.0)
    assert abs(imu.read_temperature() - STILL.temperature_c) < STILL.temperature_rise_c + 0.5

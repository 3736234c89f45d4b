# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Our driver at several I2C master clocks and on both paths (issue #23): it sets the master's
clock itself (LP_CONFIG, I2C_MST_ODR_CONFIG, slave delays) instead of relying on the model's,
and takes every magnetometer sample once, by its DRDY, none lost at 100 Hz."""

from icm20948_fakes import FakeClock
import numpy as np
import pytest

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.icm20948.driver import Icm20948, ImuSettings, master_plan
from mag_calibrator_ros.icm20948.supervisor import Icm20948Supervisor, ImuSample, MagSample
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.sim.simulator import SimulatedIcm20948Bus

ICM = 0x69

# (path, I2C_MST_ODR_CONFIG, IMU rate): the sample clock (I2C_MST_CYCLE = 0, the IMU rate), the
# duty cycle at 1.1 kHz (its reset value) and at 137.5 Hz, and the bypass. At 225 Hz a 137.5 Hz
# master cannot both keep up with 100 Hz and keep each copy until the next look (refused below).
CLOCKS = [('master', None, 200), ('master', None, 1000), ('master', 0, 200), ('master', 0, 1000),
          ('master', 3, 1000), ('bypass', None, 200), ('bypass', None, 1000)]


@pytest.mark.parametrize('path, odr_config, imu_rate', CLOCKS)
def test_every_sample_once_by_drdy_at_each_master_clock(path, odr_config, imu_rate):
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(seed=imu_rate + (odr_config or 0)), clock=clock)
    imu = ImuSettings(rate_hz=imu_rate)
    supervisor = Icm20948Supervisor(lambda: sim, imu=imu, clock=clock, sleep=clock.sleep,
                                    stamp=clock, mag_via_master=path == 'master',
                                    master_odr_config=odr_config)
    samples = []

    def advance(seconds):
        end = clock.now + seconds
        while clock.now < end:
            clock.now = max(clock.now, min(supervisor.next_due(), end)) + 20e-6
            samples.extend(supervisor.step())

    advance(0.2)
    driver = supervisor._driver
    assert supervisor.running and driver.aux_master == (path == 'master')
    if path == 'master':
        plan = master_plan(100, imu, odr_config)
        assert driver.master == plan
        cycle = 0 if odr_config is None else reg.LP_CONFIG_I2C_MST_CYCLE
        assert sim.read_byte_data(ICM, reg.LP_CONFIG) == cycle
        sim.write_byte_data(ICM, reg.REG_BANK_SEL, reg.MASTER_BANK << reg.BANK_SHIFT)
        assert sim.read_byte_data(ICM, reg.I2C_MST_ODR_CONFIG) == (odr_config or 0)
        assert sim.read_byte_data(ICM, reg.I2C_SLV4_CTRL) == plan.delay
        sim.write_byte_data(ICM, reg.REG_BANK_SEL, 0)
    taken_before, measured_before = len(mag_of(samples)), sim.samples_measured
    imu_before = len(samples) - taken_before
    advance(3.0)
    mag = mag_of(samples)[taken_before:]
    measured = sim.samples_measured - measured_before
    assert driver.overruns == 0 and driver.mag_fallbacks == 0  # every one by its DRDY
    # Each sample once: as many handed out as the simulator saw distinct samples read. (On the
    # duty cycle a copy outlives a look, so the same DRDY copy is read twice by design and the
    # driver tells it by its time; on the sample clock a copy is read once.)
    assert len(mag_of(samples)) == sim.mag_samples_read
    assert odr_config is not None or sim.mag_repeated_reads == 0
    assert measured - 1 <= len(mag) <= measured + 1  # none lost (one may straddle the ends)
    assert len(mag) >= 298
    assert sim.imu_repeated_reads == 0
    imu_taken = len([s for s in samples if isinstance(s, ImuSample)]) - imu_before
    assert imu_taken >= 0.99 * 3.0 * imu.odr_hz
    truths = np.array([sim.truth_for_reading(s.reading.field_tesla) for s in mag])
    fields = np.array([s.reading.field_tesla for s in mag])
    assert np.sqrt(np.mean(np.sum((fields - truths) ** 2, axis=1))) < 0.8e-6


def mag_of(samples):
    return [s for s in samples if isinstance(s, MagSample)]


def test_plans_name_the_slave_delay_for_each_clock():
    fast = ImuSettings(rate_hz=1000)  # 1125 Hz
    slow = ImuSettings(rate_hz=200)  # 225 Hz
    assert master_plan(100, slow) == master_plan(100, slow, None)
    assert master_plan(100, slow).round_hz == pytest.approx(225.0)
    # 1.1 kHz rounds slowed to one read in ten (110 Hz): each copy outlives the longest gap
    # between two looks at 225 Hz polled 1.5 times per sample, and still keeps up with 100 Hz.
    assert master_plan(100, slow, 0).delay == 9
    assert master_plan(100, fast, 0).delay == 1
    assert master_plan(100, fast, 3).delay == 0  # 137.5 Hz: every round
    assert master_plan(100, slow, 3) is None  # a copy would not outlive the gap between looks
    assert master_plan(100, fast, 4) is None  # 68.75 Hz cannot keep up with 100 Hz
    assert master_plan(50, slow, 4) is not None
    assert master_plan(100, ImuSettings(rate_hz=150)) is None  # 160.7 Hz < 2 x 100 Hz
    assert master_plan(100, None) is None


def test_an_impossible_clock_is_refused_with_the_reason():
    clock = FakeClock()
    sim = SimulatedIcm20948Bus(SimConfig(), clock=clock)
    driver = Icm20948(sim, address=ICM, sleep=clock.sleep, clock=clock)
    with pytest.raises(ValueError, match='I2C_MST_ODR_CONFIG 4.*use bypass'):
        driver.initialise(100, ImuSettings(), aux_master=True, master_odr_config=4)

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_fit's own-field inputs from bags: a rosbag2's BatteryState and Temperature
topics paired by stamp learn K and c, and a ROS 1 bag's are paired and their bad values named.
(The bag tests of test_fit_cli_compensation.py, a file of their own so that pytest-xdist's
--dist loadfile runs them beside the text-log ones.)"""

from __future__ import annotations

import math
from pathlib import Path
import sys

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from mag_calibrator_ros.sim.board import course_recording
from mag_calibrator_ros.tools.recordings import read_recording

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
from bench_interference import robot  # noqa: E402 - the benchmark's simulated ground robot
from test_fit_cli_compensation import (  # noqa: E402
    RATE_HZ,
    assert_near_truth,
    run,
    write_rosbag2,
)


@pytest.fixture(scope='module')
def course():
    """The benchmark robot over the three-minute ground course, and its truth (as
    test_fit_cli_compensation.py's)."""
    board = robot(1)
    return course_recording(board, rate_hz=RATE_HZ), board.interference_truth()


def test_a_rosbag2_with_battery_state_and_temperature_learns_k_and_c(tmp_path, capsys, course):
    recording, truth = course
    bag = write_rosbag2(tmp_path / 'course', recording)
    read = read_recording(bag, compensation=(None, None))
    assert read.input_names == ('/battery:sensor_msgs/msg/BatteryState:current',)
    assert np.isfinite(read.inputs).all() and np.isfinite(read.temperature).all()
    _, summary = run(capsys, bag)
    assert_near_truth(summary['compensation'], truth, recording)
    assert 'battery topic /battery' in summary['input']['layout']


def test_a_ros1_bag_pairs_its_battery_and_temperature_and_names_bad_values(tmp_path):
    """The ROS 1 reader too: the nearest sample within the live tolerance (0.5 s for the
    current, 2 s for the temperature), a NaN temperature counted, two BatteryState topics
    left for the user to choose (--battery-topic)."""
    from rosbags.rosbag1 import Writer as Ros1Writer
    ros1 = get_typestore(Stores.ROS1_NOETIC)
    start = 1_700_000_000 * 10**9

    def stamped(stamp_ns):
        return ros1.types['std_msgs/msg/Header'](
            seq=0, stamp=ros1.types['builtin_interfaces/msg/Time'](
                sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id='imu_link')

    def battery(stamp_ns, current):
        return ros1.types['sensor_msgs/msg/BatteryState'](
            header=stamped(stamp_ns), voltage=12.0, current=current, charge=1.0, capacity=2.0,
            temperature=25.0, cell_temperature=np.zeros(0, dtype=np.float32),
            design_capacity=2.0, percentage=0.5, power_supply_status=2, power_supply_health=1,
            power_supply_technology=2, present=True,
            cell_voltage=np.zeros(0, dtype=np.float32), location='', serial_number='')

    path = tmp_path / 'run.bag'
    with Ros1Writer(path) as writer:
        types = {'/imu/mag': 'sensor_msgs/msg/MagneticField',
                 '/battery': 'sensor_msgs/msg/BatteryState',
                 '/imu/temperature': 'sensor_msgs/msg/Temperature'}
        connections = {topic: writer.add_connection(topic, msgtype, typestore=ros1)
                       for topic, msgtype in types.items()}
        for i in range(40):
            stamp = start + i * 100_000_000
            messages = [('/imu/mag', ros1.types[types['/imu/mag']](
                header=stamped(stamp), magnetic_field=ros1.types['geometry_msgs/msg/Vector3'](
                    2e-5, -3e-5 + 1e-7 * i, 4e-5), magnetic_field_covariance=np.zeros(9)))]
            if i % 10 == 0:  # 1 Hz: readings 5 or more rows away find none within 0.5 s
                messages.append(('/battery', battery(stamp, 1.0 + i / 10)))
                messages.append(('/imu/temperature', ros1.types[types['/imu/temperature']](
                    header=stamped(stamp), temperature=math.nan if i == 20 else 30.0 + i / 10,
                    variance=0.0)))
            for topic, message in messages:
                writer.write(connections[topic], stamp, ros1.serialize_ros1(message,
                                                                            types[topic]))
    read = read_recording(path, compensation=(None, None))
    assert read.input_names == ('/battery:sensor_msgs/msg/BatteryState:current',)
    assert read.inputs[:10, 0].tolist() == [1.0] * 5 + [read.inputs[5, 0]] + [2.0] * 4
    assert read.inputs[34, 0] == 4.0 and np.isnan(read.inputs[36, 0])  # 0.6 s from any
    assert read.temperature[0] == 30.0 and read.temperature[18] == 31.0  # the NaN is skipped
    assert "'/imu/temperature temperature': 1 of 4 rows not a finite number" in ' '.join(
        read.input_problems)
    assert read_recording(path, compensation=('', '')).inputs is None

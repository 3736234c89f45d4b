# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_fit learns the robot's own field (K per ampere, c per degree) from recordings
that log the current and the temperature: text columns by header name or option, rosbag2
BatteryState / Temperature topics paired by stamp (test_fit_cli_compensation_bags.py); bad
columns are named, never a traceback."""

from __future__ import annotations

import json
import math
from pathlib import Path
import sys

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

from mag_calibrator_ros.calibration.fit.calibration import Compensation
from mag_calibrator_ros.calibration.store.calibration_file import load_calibration
from mag_calibrator_ros.sim.board import course_recording
from mag_calibrator_ros.tools import fit
from mag_calibrator_ros.tools.fit_compensation import without_own_field
from mag_calibrator_ros.tools.recording_inputs import compensation_columns
from mag_calibrator_ros.tools.recording_value import Recording, RecordingError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
from bench_interference import robot  # noqa: E402 - the benchmark's simulated ground robot

RATE_HZ = 50.0
TOLERANCE = 0.25
"""The node's own CompensationLearner (the CLI learns what the node learns) on this course
without an IMU finds K's current axis closely, c's warm-up axis less so, and leaks a little of
the warm-up into the current's axis (the robot warms while it drives). The issue's 10 % is the
learner's to reach (``live/compensation.py``); judged here within 25 % on the simulated axes
and on the field the model removes over the course."""
ROS2 = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture(scope='module')
def course():
    """The benchmark robot (8 uT at full current along x, 0.2 uT/degC along y) over the
    three-minute ground course, and its truth."""
    board = robot(1)
    return course_recording(board, rate_hz=RATE_HZ), board.interference_truth()


IMU_COLUMNS = ('ax', 'ay', 'az', 'gx (deg/s)', 'gy (deg/s)', 'gz (deg/s)')


def write_csv(path: Path, recording, columns=('current', 'temperature'), rows=None,
              current=None, temperature=None, imu: bool = False) -> Path:
    """time, (with ``imu``: the accelerometer in m/s^2 and the gyroscope in deg/s, as a logger
    writes them), the magnetometer in tesla, then ``columns``."""
    rows = range(len(recording.times)) if rows is None else rows
    current = recording.current_a if current is None else current
    temperature = recording.temperature_c if temperature is None else temperature
    lines = [','.join(('time', *(IMU_COLUMNS if imu else ()), 'mx', 'my', 'mz', *columns))]
    for i in rows:
        values = {'current': current[i], 'temperature': temperature[i],
                  'T (C)': temperature[i], 'motor_a': current[i]}
        sensed = [*recording.accel[i], *np.degrees(recording.gyro[i])] if imu else []
        lines.append(','.join([f'{recording.times[i]:.3f}', *(f'{v:.6g}' for v in sensed),
                               *(f'{v:.9g}' for v in recording.mag[i]),
                               *(str(values[name]) for name in columns)]))
    path.write_text('\n'.join(lines) + '\n')
    return path


def run(capsys, *argv) -> tuple[int, dict]:
    status = fit.main([str(a) for a in argv] + ['--json'])
    return status, json.loads(capsys.readouterr().out)


def assert_near_truth(found: dict, truth, recording) -> None:
    """K's current axis (x) and c's warm-up axis (y) within TOLERANCE of the truth, and the
    field they model over the course (its variation: a constant is the offset's) too."""
    assert found['learned'], found
    [k] = found['interference'].values()
    k, c = np.array(k), np.array(found['temperature_coefficient'])
    assert abs(k[0] - truth.current_field[0]) <= TOLERANCE * truth.current_field[0], k
    assert abs(c[1] - truth.temperature_drift[1]) <= TOLERANCE * truth.temperature_drift[1], c
    modelled = np.outer(recording.current_a, k) + np.outer(recording.temperature_c, c)
    true = (np.outer(recording.current_a, truth.current_field)
            + np.outer(recording.temperature_c, truth.temperature_drift))
    error, true = modelled - true, true - true.mean(axis=0)
    error -= error.mean(axis=0)
    assert np.sqrt(np.mean(np.sum(error**2, axis=1))) <= TOLERANCE * np.sqrt(
        np.mean(np.sum(true**2, axis=1))), (k, c)


def test_a_csv_with_current_and_temperature_learns_k_and_c(tmp_path, capsys, course):
    recording, truth = course
    csv = write_csv(tmp_path / 'course.csv', recording)
    output = tmp_path / 'cal.yaml'
    status, summary = run(capsys, csv, '--units', 'T', '--output', output)
    found = summary['compensation']
    assert found['inputs'] == ['current'] and found['temperature'], found
    assert found['problems'] == []
    assert_near_truth(found, truth, recording)
    assert found['removed_pct'] > 1.0 and found['reference_temperature_degC'] is not None
    low, high = np.percentile(recording.current_a, [5.0, 95.0])  # its size, ArduPilot's way
    field = np.linalg.norm(found['interference']['current']) * (high - low)
    assert found['interference_pct'] == pytest.approx(
        100.0 * field / summary['field_strength'], rel=0.02)
    assert status == 0, summary['reason']
    assert summary['buffer']['learning_pass']['fits']['compensate'] > 0
    saved = load_calibration(output).compensation
    assert saved is not None and saved.inputs == ('current',)
    assert np.allclose(saved.interference[:, 0], found['interference']['current'])


@pytest.mark.parametrize('share', [0.7])
def test_the_static_calibration_comes_from_the_whole_log_wherever_it_ends(tmp_path, capsys,
                                                                          course, share):
    """A learned compensation emptied the live buffer (until stop 34; it now moves it), so a
    log that ended soon after one went in force left the buffer its last seconds, straight
    ahead: 'NOT CALIBRATED, coverage 0 %' from a good drive (the full course of the test
    above, once). The static part is fitted on a second pass over every reading without K and
    c, wherever the log ends."""
    recording, _ = course
    rows = range(int(share * len(recording.times)))
    csv = write_csv(tmp_path / 'part.csv', recording, rows=rows)
    output = tmp_path / 'cal.yaml'
    status, summary = run(capsys, csv, '--units', 'T', '--output', output)
    assert summary['compensation']['learned'], summary['compensation']
    assert status == 0, summary['reason']
    assert summary['metrics']['coverage'] >= 0.9  # the turns in place, not the last straight
    saved = load_calibration(output).compensation
    assert np.allclose(saved.interference[:, 0],
                       summary['compensation']['interference']['current'])


def test_the_second_pass_removes_the_field_of_each_rows_latest_inputs():
    """A row without a current or a temperature (a gap in the log) takes the latest one before
    it, as the node holds the latest sample; before the first there is none to remove."""
    compensation = Compensation(('motor', 'battery'), np.array([[1.0, 0.0], [0.0, 2.0],
                                                                [0.0, 0.0]]),
                                np.array([0.0, 0.0, 0.5]), 20.0)
    samples = np.zeros((4, 3))
    recording = Recording(samples, 'log', 'text', 'fields 0,1,2', {}, 'T',
                          inputs=np.array([[3.0, math.nan], [math.nan, 1.0], [5.0, math.nan],
                                           [math.nan, math.nan]]),
                          input_names=('battery', 'motor'),
                          temperature=np.array([math.nan, 22.0, math.nan, 24.0]))
    removed = -without_own_field(recording, compensation)
    np.testing.assert_allclose(removed, [[0.0, 6.0, 0.0], [1.0, 6.0, 1.0], [1.0, 10.0, 1.0],
                                         [1.0, 10.0, 2.0]])


def test_without_the_columns_the_result_is_todays(tmp_path, capsys, course):
    """The same readings without current and temperature, and with them but
    --no-compensation: the same static calibration and no compensation. The first half of
    the course (its turns in place and straight legs at speed) is enough to calibrate; the
    replay's fits follow its stream time, so a shorter log, not a sparser one, is quicker."""
    recording, _ = course
    rows = range(0, len(recording.times) // 2, 3)
    bare = run(capsys, write_csv(tmp_path / 'bare.csv', recording, (), rows), '--units', 'T')
    ignored = run(capsys, write_csv(tmp_path / 'full.csv', recording, rows=rows), '--units', 'T',
                  '--no-compensation')
    for _, summary in (bare, ignored):
        assert summary['compensation'] is None
    assert bare[1]['success'], bare[1]['reason']  # the same calibration, not the same failure
    keys = ('success', 'reason', 'offset', 'matrix', 'field_strength', 'metrics')
    assert [bare[0], *(bare[1][k] for k in keys)] == [ignored[0], *(ignored[1][k] for k in keys)]


def header(stamp_ns: int):
    return ROS2.types['std_msgs/msg/Header'](
        stamp=ROS2.types['builtin_interfaces/msg/Time'](sec=stamp_ns // 10**9,
                                                         nanosec=stamp_ns % 10**9),
        frame_id='imu_link')


def write_rosbag2(path: Path, recording, imu: bool = False) -> Path:
    """The course as a rosbag2: MagneticField at the course's rate, BatteryState at 10 Hz,
    the driver's imu/temperature at 1 Hz (sqlite3, as ros2 bag record writes by default);
    with ``imu``, imu/data_raw beside each MagneticField (the same stamp)."""
    types = {'mag': 'sensor_msgs/msg/MagneticField', 'battery': 'sensor_msgs/msg/BatteryState',
             'temperature': 'sensor_msgs/msg/Temperature', 'imu': 'sensor_msgs/msg/Imu'}
    vector = ROS2.types['geometry_msgs/msg/Vector3']
    start = 1_700_000_000 * 10**9
    with Writer(path, version=9) as writer:
        connections = {name: writer.add_connection(f'/{name}', msgtype, typestore=ROS2)
                       for name, msgtype in types.items() if imu or name != 'imu'}
        for i, t in enumerate(recording.times.tolist()):
            stamp = start + round(t * 1e9)
            messages = [('imu', ROS2.types[types['imu']](
                header=header(stamp),
                orientation=ROS2.types['geometry_msgs/msg/Quaternion'](0.0, 0.0, 0.0, 1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=vector(*map(float, recording.gyro[i])),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=vector(*map(float, recording.accel[i])),
                linear_acceleration_covariance=np.zeros(9)))] if imu else []
            messages.append(('mag', ROS2.types[types['mag']](
                header=header(stamp), magnetic_field=vector(*map(float, recording.mag[i])),
                magnetic_field_covariance=np.zeros(9))))
            if i % int(RATE_HZ / 10) == 0:
                messages.append(('battery', ROS2.types[types['battery']](
                    header=header(stamp), voltage=12.0, temperature=25.0,
                    current=float(recording.current_a[i]), charge=1.0, capacity=2.0,
                    design_capacity=2.0, percentage=0.5, power_supply_status=2,
                    power_supply_health=1, power_supply_technology=2, present=True,
                    cell_voltage=np.zeros(0, dtype=np.float32),
                    cell_temperature=np.zeros(0, dtype=np.float32), location='base',
                    serial_number='')))
            if i % int(RATE_HZ) == 0:
                messages.append(('temperature', ROS2.types[types['temperature']](
                    header=header(stamp), temperature=float(recording.temperature_c[i]),
                    variance=0.0)))
            for name, message in messages:
                writer.write(connections[name], stamp,
                             ROS2.serialize_cdr(message, types[name]))
    return path


def test_bad_columns_are_counted_and_named_never_a_traceback(tmp_path, capsys, course):
    recording, _ = course
    rows = range(600)  # the inputs are judged as they are read: a short log says it all
    current = [('garbage' if i % 7 == 3 else 'nan' if i % 11 == 3 else f'{value:g}')
               for i, value in enumerate(recording.current_a)]
    csv = write_csv(tmp_path / 'bad.csv', recording, rows=rows, current=current,
                    temperature=np.full(len(recording.times), 25.0))
    status, summary = run(capsys, csv, '--units', 'T')
    assert status in (0, 1)
    assert summary['input']['rows'] == 600  # the readings are kept whatever the inputs say
    problems = ' '.join(summary['compensation']['problems'])
    garbage = sum(1 for i in rows if i % 7 == 3 or i % 11 == 3)
    assert f"input column 'current': {garbage} of 600 rows not a finite number" in problems
    assert "temperature column 'temperature': the temperature never varied" in problems
    status = fit.main([str(csv), '--input-columns', 'amps'])
    assert status == 2
    assert "no column named 'amps'" in capsys.readouterr().err
    status = fit.main([str(csv), '--battery-topic', '/battery'])
    assert status == 2
    assert '--battery-topic applies to a bag' in capsys.readouterr().err


def test_columns_are_chosen_by_header_name_or_by_option():
    lines = ['time,T (C),mx,my,mz,motor_a,battery_current', '0.0,25.5,1,2,3,0.5,1.0',
             '0.1,25.6,1,2,3,0.6,1.1']
    found = compensation_columns(lines, (2, 3, 4, 0), 'log')
    assert found.inputs == ((6, 'battery_current'),) and found.temperature == (1, 'T (C)')
    chosen = compensation_columns(lines, (2, 3, 4, 0), 'log', 'motor_a,battery_current', '')
    assert chosen.inputs == ((5, 'motor_a'), (6, 'battery_current'))
    assert chosen.temperature is None
    kelvin = compensation_columns(['mx,my,mz,temperature (K)', '1,2,3,300'], (0, 1, 2), 'log')
    assert kelvin.temperature == (3, 'temperature (K)') and kelvin.celsius == (-273.15, 1.0)


def test_a_column_is_named_with_or_without_the_unit_its_header_gives():
    """A flight log converted to 'current (A)' and 'temperature (C)' is asked for as
    ``--input-columns current``: the unit is not part of the name. Two columns of that name
    in different units are for the user to choose between, by index."""
    lines = ['time (s),mx (uT),my (uT),mz (uT),current (A),temperature (C)',
             '0.0,1,2,3,0.5,25.0', '0.1,1,2,3,0.6,25.1']
    chosen = compensation_columns(lines, (1, 2, 3, 0), 'log', 'current', 'temperature')
    assert chosen.inputs == ((4, 'current (A)'),)
    assert chosen.temperature == (5, 'temperature (C)')
    exact = compensation_columns(lines, (1, 2, 3, 0), 'log', 'Current (A)', 'TEMPERATURE (C)')
    assert exact.inputs == chosen.inputs and exact.temperature == chosen.temperature
    twice = ['mx,my,mz,current (A),current (mA)', '1,2,3,0.5,500', '1,2,3,0.6,600']
    with pytest.raises(RecordingError, match=r"'current' names several columns \(current \(A\) "
                                             r'\(field 3\), current \(mA\) \(field 4\)\)'):
        compensation_columns(twice, (0, 1, 2), 'log', 'current', '')
    assert compensation_columns(twice, (0, 1, 2), 'log', 'current (mA)', '').inputs == (
        (4, 'current (mA)'),)
    with pytest.raises(RecordingError, match="no column named 'current \\(A\\)'"):
        compensation_columns(['mx,my,mz,current (mA)', '1,2,3,5'], (0, 1, 2), 'log',
                             'current (A)', '')  # a unit of its own is part of the name asked
    with pytest.raises(RecordingError, match="no column named 'esc\\[1\\].current'"):
        compensation_columns(['mx,my,mz,esc[0].current', '1,2,3,5'], (0, 1, 2), 'log',
                             'esc[1].current', '')  # an index is no unit
    with pytest.raises(RecordingError, match="input columns 3, 4 are all named 'current'"):
        compensation_columns(['mx,my,mz,current,current', '1,2,3,5,6'], (0, 1, 2), 'log')

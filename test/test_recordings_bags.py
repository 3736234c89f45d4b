# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ROS 1 bags read as rosbag2 bags are: the MagneticField topic with its header stamps, an Imu
topic paired by stamp, and one calibration whatever the container (ROS 1, rosbag2, CSV)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.convert import convert
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.tools import fit
from mag_calibrator_ros.tools.recording_bags import IMU, MAGNETIC_FIELD
from mag_calibrator_ros.tools.recording_pairing import pair_by_stamp
from mag_calibrator_ros.tools.recording_value import RecordingError
from mag_calibrator_ros.tools.recordings import read_recording

TEST_DATA = Path(__file__).resolve().parent / 'data'

ROS1 = get_typestore(Stores.ROS1_NOETIC)
RAZOR = TEST_DATA / 'imu_tools' / 'sparkfun_razor.bag'


def header(stamp_ns: int):
    return ROS1.types['std_msgs/msg/Header'](
        seq=0, stamp=ROS1.types['builtin_interfaces/msg/Time'](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id='imu_link')


def vector(values):
    return ROS1.types['geometry_msgs/msg/Vector3'](*map(float, values))


def magnetic_field(values, stamp_ns):
    return ROS1.types[MAGNETIC_FIELD](header=header(stamp_ns), magnetic_field=vector(values),
                                      magnetic_field_covariance=np.zeros(9))


def imu(accel, gyro, stamp_ns):
    quaternion = ROS1.types['geometry_msgs/msg/Quaternion'](0.0, 0.0, 0.0, 1.0)
    return ROS1.types[IMU](header=header(stamp_ns), orientation=quaternion,
                           orientation_covariance=np.zeros(9), angular_velocity=vector(gyro),
                           angular_velocity_covariance=np.zeros(9),
                           linear_acceleration=vector(accel),
                           linear_acceleration_covariance=np.zeros(9))


def write_ros1(path: Path, messages: list[tuple[str, str, object, int]],
               compression: str | None = None) -> Path:
    """A real ROS 1 bag: (topic, msgtype, message, receive time ns) in that order; its chunks
    compressed by ``compression`` ('lz4', 'bz2') when given."""
    bag = Writer(path)
    if compression is not None:
        bag.set_compression(Writer.CompressionFormat[compression.upper()])
    with bag as writer:
        connections = {}
        for topic, msgtype, message, time_ns in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ROS1)
            writer.write(connections[topic], time_ns, ROS1.serialize_ros1(message, msgtype))
    return path


MAG_ROWS = np.array([[2e-5 + 1e-7 * i, -3e-5, 4e-5 - 1e-7 * i] for i in range(40)])
START_NS = 1_700_000_000 * 10**9


def small_bag(tmp_path: Path, imu_offset_ns: int = 3_000_000, zero_mag_stamps: bool = False
              ) -> Path:
    """40 MagneticField messages at 50 Hz and an Imu at 100 Hz, ``imu_offset_ns`` after."""
    messages = []
    for i in range(80):
        stamp = START_NS + i * 10**7 + imu_offset_ns
        messages.append(('/imu/data_raw', IMU, imu((0.0, 0.1 * i, 9.8), (0.0, 0.0, 0.01 * i),
                                                   stamp), stamp))
    for i, row in enumerate(MAG_ROWS):
        stamp = START_NS + i * 2 * 10**7
        message = magnetic_field(row, 0 if zero_mag_stamps else stamp)
        messages.append(('/imu/mag', MAGNETIC_FIELD, message, stamp))
    messages.sort(key=lambda message: message[3])
    tmp_path.mkdir(exist_ok=True)
    return write_ros1(tmp_path / 'small.bag', messages)


def test_a_ros1_bag_gives_the_field_its_stamps_and_the_imu_nearest_each(tmp_path):
    recording = read_recording(small_bag(tmp_path), accel_topic='')
    assert recording.kind == 'ROS 1 bag' and recording.units == 'T'
    np.testing.assert_array_equal(recording.samples, MAG_ROWS)
    np.testing.assert_allclose(recording.stamps - START_NS * 1e-9, np.arange(40) * 0.02,
                               atol=1e-6)
    assert recording.time_source == 'header stamps of /imu/mag'
    # reading i (t = 20 i ms) pairs with Imu sample 2 i (t = 20 i + 3 ms), not 2 i - 1 (-7 ms)
    np.testing.assert_allclose(recording.accel[:, 1], 0.1 * 2 * np.arange(40))
    np.testing.assert_allclose(recording.gyro[:, 2], 0.01 * 2 * np.arange(40))
    assert recording.layout == 'topic /imu/mag; accelerometer topic /imu/data_raw'
    assert '40 of 40 readings paired' in recording.notes[0]


def test_an_imu_beyond_the_pairing_tolerance_pairs_nothing(tmp_path):
    recording = read_recording(small_bag(tmp_path, imu_offset_ns=500_000_000 + 5 * 10**6),
                               accel_topic='/imu/data_raw')
    assert np.isnan(recording.accel[:20]).all()  # the Imu starts 0.5 s late
    assert np.isfinite(recording.accel[30:]).all()
    elsewhere = read_recording(small_bag(tmp_path / 'x', imu_offset_ns=60 * 10**9),
                               accel_topic='/imu/data_raw')
    assert np.isnan(elsewhere.accel).all()
    assert 'none, so nothing aligns (do /imu/mag and /imu/data_raw stamp by different clocks' \
        in elsewhere.notes[0]


def test_a_header_without_a_stamp_takes_the_bags_receive_time(tmp_path):
    recording = read_recording(small_bag(tmp_path, zero_mag_stamps=True))
    np.testing.assert_allclose(recording.stamps - START_NS * 1e-9, np.arange(40) * 0.02,
                               atol=1e-6)
    assert recording.accel is None  # no --accel: the Imu topic is not read


def test_pairing_by_stamp_takes_the_nearest_sample_either_side():
    imu_rows = np.array([[1.0, 1, 1, 1, 0, 0, 0], [0.0, 0, 0, 0, 0, 0, 0],
                         [2.0, 2, 2, 2, 0, 0, 0]])
    accel, _, paired = pair_by_stamp(np.array([0.015, 0.99, 1.5, 2.015, 2.021]), imu_rows)
    np.testing.assert_array_equal(accel[:, 0], [0.0, 1.0, np.nan, 2.0, np.nan])
    assert paired == 3


@pytest.mark.parametrize(('options', 'message'), [
    ({'topic': '/imu/data_raw'}, "topic '/imu/data_raw' is sensor_msgs/msg/Imu, not "
                                 'sensor_msgs/msg/MagneticField'),
    ({'accel_topic': '/imu/mag'}, "topic '/imu/mag' is sensor_msgs/msg/MagneticField, not "
                                  'sensor_msgs/msg/Imu'),
    ({'accel_topic': '/nothing'}, "no topic '/nothing' in this bag; topics: /imu/data_raw"),
    ({'columns': '0,1,2'}, '--columns applies to text input, not to a bag'),
])
def test_ros1_bag_options_that_do_not_fit_say_so(tmp_path, options, message):
    with pytest.raises(RecordingError) as error:
        read_recording(small_bag(tmp_path), **options)
    assert message in str(error.value)


def test_accel_on_a_text_log_points_to_accel_columns(tmp_path):
    log = tmp_path / 'log.csv'
    log.write_text('1,2,3\n' * 20)
    with pytest.raises(RecordingError, match='not to a text file .a text log: --accel-columns.'):
        read_recording(log, accel_topic='')


def test_a_ros1_bag_under_another_name_is_still_a_bag(tmp_path):
    bag = small_bag(tmp_path)
    renamed = bag.rename(tmp_path / 'recording.log')
    assert read_recording(renamed).kind == 'ROS 1 bag'


def test_a_damaged_ros1_bag_is_one_clear_line(tmp_path):
    broken = tmp_path / 'broken.bag'
    broken.write_bytes(b'#ROSBAG V2.0\n' + b'\x00' * 64)
    with pytest.raises(RecordingError, match='cannot read ROS 1 bag'):
        read_recording(broken)


@pytest.mark.parametrize('compression', ['lz4', 'bz2'])
def test_a_damaged_compressed_chunk_is_one_clear_line_and_exit_2(tmp_path, capsys, compression):
    """A decompressor's own error (lz4's RuntimeError, bz2's OSError) raised while the reader
    reads the file is the file's fault: one line naming it, exit 2, no traceback."""
    stamps = [START_NS + i * 10**7 for i in range(2000)]
    messages = [('/imu/mag', MAGNETIC_FIELD, magnetic_field(MAG_ROWS[i % 40], stamp), stamp)
                for i, stamp in enumerate(stamps)]
    bag = write_ros1(tmp_path / 'compressed.bag', messages, compression)
    assert len(read_recording(bag).samples) == 2000  # whole, it reads
    data = bytearray(bag.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 256] = bytes(b ^ 0x5A for b in data[middle:middle + 256])
    bag.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match='damaged data in the file'):
        read_recording(bag)
    assert fit.main([str(bag)]) == 2
    err = capsys.readouterr().err
    assert 'compressed.bag' in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1


def test_the_committed_real_ros1_bag_reads_and_is_named_normalised(capsys):
    """SparkFun Razor's sample bag from imu_tools (test/data/imu_tools/PROVENANCE.md): its
    driver normalised the field to exactly 1e-4 T, so the CLI reads it, stamps and pairs it,
    then refuses it with the reason (issue 24: nothing can be learned from such a field)."""
    recording = read_recording(RAZOR, accel_topic='')
    assert recording.rows == 2144 and recording.kind == 'ROS 1 bag'
    assert recording.layout == 'topic /imu/mag; accelerometer topic /imu/data_raw'
    assert np.isfinite(recording.accel).all()  # one Imu per reading, the same stamp
    np.testing.assert_allclose(np.linalg.norm(recording.samples, axis=1), 1e-4, rtol=1e-6)
    assert 30.0 < recording.stamps[-1] - recording.stamps[0] < 32.0
    assert fit.main([str(RAZOR), '--accel', '--json']) == 2
    err = capsys.readouterr().err
    assert 'already normalised or calibrated upstream' in err and len(err.splitlines()) == 1
    assert fit.main([str(RAZOR), '--rate', '100']) == 2
    assert '--rate is for logs without time stamps' in capsys.readouterr().err


def as_csv(recording, path: Path) -> Path:
    """The same readings as a CSV with a time column: stamps exactly as read (repr), and the
    gyroscope (it tells the drive's accelerations from tilts: live/gravity.py)."""
    lines = ['time,mx,my,mz,ax,ay,az,gx,gy,gz']
    for stamp, field, force, rate in zip(recording.stamps.tolist(), recording.samples.tolist(),
                                         recording.accel.tolist(), recording.gyro.tolist(),
                                         strict=True):
        lines.append(','.join(repr(value) for value in (stamp, *field, *force, *rate)))
    path.write_text('\n'.join(lines) + '\n')
    return path


def as_rosbag2(bag: Path, directory: Path, storage: str) -> Path:
    convert([bag], directory, storage, 9, None, 'file', None, None, [], [], [], [])
    return directory


def the_calibration(summary: dict) -> dict:
    return {key: summary[key] for key in ('success', 'reason', 'model', 'offset', 'matrix',
                                          'field_strength')}


def compare(runs: dict[str, tuple[int, dict]]) -> None:
    """Every container, the same calibration, alignment and rotation (the CSV carries the
    Imu's gyroscope as the bags do)."""
    calibrations = {name: (status, the_calibration(summary))
                    for name, (status, summary) in runs.items()}
    assert len({json.dumps(value) for value in calibrations.values()}) == 1, calibrations
    alignments = {name: (summary['rotation'], summary['alignment'])
                  for name, (_, summary) in runs.items()}
    assert len({json.dumps(value) for value in alignments.values()}) == 1, alignments


@pytest.mark.parametrize('mode', [[], ['--all']])
def test_one_calibration_from_a_ros1_bag_its_rosbag2_and_its_csv(tmp_path, capsys, mode,
                                                                 public_recording):
    """The half-NaN Phidgets bag of imu_tools (fetched), converted by rosbags to rosbag2 and
    written out as CSV with its stamps: the three give the same calibration and alignment."""
    bag = public_recording('phidgets_imu_upside_down.bag')
    runs = {}
    recording = read_recording(bag, accel_topic='')
    csv = as_csv(recording, tmp_path / 'phidgets.csv')
    inputs = {'ros1': [bag, '--accel'], 'mcap': [as_rosbag2(bag, tmp_path / 'b2', 'mcap'),
                                                '--accel'],
              'csv': [csv, '--accel-columns', 'ax,ay,az', '--gyro-columns', 'gx,gy,gz',
                      '--gyro-units', 'rad/s', '--units', 'T']}
    for name, argv in inputs.items():
        status = fit.main([str(a) for a in argv] + ['--json', *mode])
        summary = json.loads(capsys.readouterr().out)
        assert summary['input']['rows'] == 6974
        runs[name] = (status, summary)
    assert recording.skipped == {'non_finite': 6990}
    compare(runs)


def simulated_bag(tmp_path: Path) -> Path:
    """A ROS 1 bag of a simulated ICM-20948 tumbling then held at still tilts (issue 24's
    committed real bag is normalised upstream, so nothing can be calibrated from it): 100 Hz
    MagneticField, the Imu at 200 Hz offset by 2 ms, stamped as a driver would."""
    config = {'hard_iron_ut': (30.0, -20.0, 45.0), 'noise_ut': 0.3,
              'mag_misalignment_deg': (1.8, -1.9, 1.4)}
    parts = [board_readings(BoardModel(SimConfig(motion=motion, seed=3, **config)), seconds,
                            200.0) for motion, seconds in (('tumble', 20.0), ('poses', 20.0))]
    mag, accel, gyro = (np.concatenate(rows) for rows in zip(*parts, strict=True))
    messages = []
    for i in range(len(mag)):
        stamp = START_NS + i * 5_000_000
        messages.append(('/imu/data_raw', IMU, imu(accel[i], gyro[i], stamp + 2_000_000),
                         stamp + 2_000_000))
        if i % 2 == 0:
            messages.append(('/imu/mag', MAGNETIC_FIELD, magnetic_field(mag[i], stamp), stamp))
    messages.sort(key=lambda message: message[3])
    tmp_path.mkdir(exist_ok=True)
    return write_ros1(tmp_path / 'simulated.bag', messages)


def test_a_simulated_ros1_bag_and_its_rosbag2_and_csv_agree(tmp_path, capsys):
    """The same comparison as the fetched Phidgets bag's, on a bag made here, so CI runs it
    without a download."""
    bag = simulated_bag(tmp_path / 'ros1')
    recording = read_recording(bag, accel_topic='')
    inputs = {'ros1': [bag, '--accel'],
              'sqlite3': [as_rosbag2(bag, tmp_path / 'b2', 'sqlite3'), '--accel'],
              'csv': [as_csv(recording, tmp_path / 'simulated.csv'), '--accel-columns',
                      'ax,ay,az', '--gyro-columns', 'gx,gy,gz', '--gyro-units', 'rad/s',
                      '--units', 'T']}
    runs = {}
    for name, argv in inputs.items():
        status = fit.main([str(a) for a in argv] + ['--json'])
        summary = json.loads(capsys.readouterr().out)
        assert summary['time']['stamped'] and summary['input']['rows'] == recording.rows
        runs[name] = (status, summary)
    assert runs['ros1'][0] == 0, runs['ros1'][1]['reason']
    compare(runs)


def test_an_unindexed_ros1_bag_says_how_to_repair_it(tmp_path):
    """Issue #47 item 6: a `rosbag record` killed before it wrote its index leaves a bag
    (index_pos 0) that rosbags refuses with "reindex before reading": the line names the
    tool that repairs it."""
    data = bytearray(small_bag(tmp_path).read_bytes())
    at = data.index(b'index_pos=') + len(b'index_pos=')
    data[at:at + 8] = (0).to_bytes(8, 'little')
    killed = tmp_path / 'killed.bag.active'
    killed.write_bytes(bytes(data))
    with pytest.raises(RecordingError) as raised:
        read_recording(killed)
    assert str(raised.value).startswith(f'{killed}: cannot read ROS 1 bag (Bag is not indexed')
    assert '`rosbag reindex FILE` on a ROS 1 machine' in str(raised.value)

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Recordings reader: every text layout, stdin, rosbag2 (sqlite3, mcap), every error path."""

import dataclasses
import io
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from mag_calibrator_ros.calibration.live.screening import MAX_READING
from mag_calibrator_ros.tools import recording_columns, recording_lines, recording_text
from mag_calibrator_ros.tools.recording_bags import MAGNETIC_FIELD
from mag_calibrator_ros.tools.recording_columns import column_roles, parse_columns, sensor_columns
from mag_calibrator_ros.tools.recording_value import Recording, RecordingError, describe_skips
from mag_calibrator_ros.tools.recordings import read_recording

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ROWS = np.array([[144.0, -270.0, 415.0], [-12.5, 0.0, 3.25], [1e-6, -2e-6, 3e-6]])


def write(tmp_path: Path, name: str, text: str, newline: str = '\n') -> Path:
    path = tmp_path / name
    path.write_bytes(text.replace('\n', newline).encode())
    return path


def read(tmp_path: Path, text: str, name: str = 'mag.txt', newline: str = '\n',
         **kwargs) -> Recording:
    return read_recording(write(tmp_path, name, text, newline), **kwargs)


@pytest.mark.parametrize('separator', [',', '\t', ' ', '  ', ';', ', '])
@pytest.mark.parametrize('newline', ['\n', '\r\n'])
def test_plain_numeric_rows_in_every_separator_and_line_ending(tmp_path, separator, newline):
    text = '\n'.join(separator.join(repr(float(v)) for v in row) for row in ROWS)
    recording = read(tmp_path, text, newline=newline)
    assert recording.samples.dtype == np.float64
    np.testing.assert_array_equal(recording.samples, ROWS)
    assert recording.skipped == {}
    assert recording.kind == 'text'
    assert recording.layout == 'fields 0,1,2'


def test_header_is_skipped_and_counted(tmp_path):
    recording = read(tmp_path, 'mx,my,mz\n1,2,3\n4,5,6\n', name='mag.csv')
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [4, 5, 6]])
    assert recording.skipped == {'header': 1}
    assert 'skipped 1 (1 header)' in recording.describe()


def test_columns_by_header_name_pick_the_named_fields(tmp_path):
    text = 'ax,ay,az,MX,MY,MZ\n10,11,12,1,2,3\n20,21,22,4,5,6\n'
    recording = read(tmp_path, text, columns='mx,my,mz')
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [4, 5, 6]])
    assert 'fields 3,4,5' in recording.layout


def test_labelled_lines_with_zero_based_columns(tmp_path):
    text = 'Mx 144 My -270 Mz 415\nMx 1 My 2 Mz 3\n'
    recording = read(tmp_path, text, columns='1,3,5')
    np.testing.assert_array_equal(recording.samples, [[144, -270, 415], [1, 2, 3]])


def test_labelled_lines_are_detected_without_columns(tmp_path):
    recording = read(tmp_path, 'Mx: 144, My: -270, Mz: 415\r\nMx: 1, My: 2, Mz: 3\r\n')
    np.testing.assert_array_equal(recording.samples, [[144, -270, 415], [1, 2, 3]])
    assert recording.layout == 'columns Mx,My,Mz (fields 1,3,5)'


def test_labelled_lines_of_several_sensors_pick_the_magnetometer(tmp_path):
    text = 'ax=0.1 ay=0.2 az=9.8 mx=144 my=-270 mz=415\nax=0 ay=0 az=9.8 mx=1 my=2 mz=3\n'
    recording = read(tmp_path, text)
    np.testing.assert_array_equal(recording.samples, [[144, -270, 415], [1, 2, 3]])


def test_wide_rows_without_names_ask_for_columns(tmp_path):
    with pytest.raises(RecordingError, match=r'6 numeric fields \(0,1,2,3,4,5\).*--columns') as \
            error:
        read(tmp_path, '1 2 3 4 5 6\n7 8 9 10 11 12\n')
    assert 'first data line: 1 2 3 4 5 6' in str(error.value)
    chosen = read(tmp_path, '1 2 3 4 5 6\n7 8 9 10 11 12\n', columns='3,4,5')
    np.testing.assert_array_equal(chosen.samples, [[4, 5, 6], [10, 11, 12]])


# Headers as real loggers write them: (header, data line, fields the magnetometer is read from)
HEADER_STYLES = [
    pytest.param('ax,ay,az,mx,my,mz', '0.1,0.2,9.8,1,2,3', (3, 4, 5), id='ax..mz'),
    pytest.param('timestamp,ax,ay,az,gx,gy,gz,mx,my,mz', '5,0.1,0.2,9.8,0,0,0,1,2,3',
                 (7, 8, 9), id='imu-9axis'),
    pytest.param('Acc_X\tAcc_Y\tAcc_Z\tGyr_X\tGyr_Y\tGyr_Z\tMag_X\tMag_Y\tMag_Z',
                 '0.1\t0.2\t9.8\t0\t0\t0\t1\t2\t3', (6, 7, 8), id='xsens'),
    pytest.param('accX;accY;accZ;magX;magY;magZ', '0.1;0.2;9.8;1;2;3', (3, 4, 5), id='camel'),
    pytest.param('TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S',
                 '1000,0,1,2,3,10,20,30,0,0,0,1,0', (2, 3, 4), id='ardupilot-MAG'),
    pytest.param('timestamp,device_id,x,y,z,temperature,error_count', '1,7,1,2,3,25.5,0',
                 (2, 3, 4), id='px4-sensor_mag'),
    pytest.param('timestamp,magnetometer_ga[0],magnetometer_ga[1],magnetometer_ga[2]',
                 '1,1,2,3', (1, 2, 3), id='px4-vehicle_magnetometer'),
    pytest.param('%time,field.header.seq,field.header.stamp,field.header.frame_id,'
                 'field.magnetic_field.x,field.magnetic_field.y,field.magnetic_field.z',
                 '1700000000,1,1700000000,imu_link,1,2,3', (4, 5, 6), id='rostopic-echo-p'),
    pytest.param('"Time (s)","Magnetic field x (µT)","Magnetic field y (µT)",'
                 '"Magnetic field z (µT)","Absolute field (µT)"', '0.01,1,2,3,3.74', (1, 2, 3),
                 id='phyphox'),
    pytest.param('time,seconds_elapsed,z,y,x', '1700000000,0.1,3,2,1', (4, 3, 2),
                 id='sensor-logger-zyx'),
    pytest.param('time Bx By Bz Btotal', '0.1 1 2 3 3.74', (1, 2, 3), id='physics-toolbox'),
    pytest.param('# t mx my mz', '0.1 1 2 3', (1, 2, 3), id='commented'),
    pytest.param('imu_mx_raw,imu_my_raw,imu_mz_raw,temp', '1,2,3,25', (0, 1, 2), id='qualified'),
]


@pytest.mark.parametrize(('header', 'line', 'fields'), HEADER_STYLES)
def test_header_names_pick_the_magnetometer_columns(tmp_path, header, line, fields):
    recording = read(tmp_path, f'{header}\n{line}\n{line}\n', name='log.csv')
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [1, 2, 3]])
    assert f'(fields {",".join(map(str, fields))})' in recording.layout
    commented = header.startswith(('#', '%'))
    assert recording.skipped == ({'comment': 1} if commented else {'header': 1})


@pytest.mark.parametrize(('header', 'line', 'words'), [
    pytest.param('mx_raw,my_raw,mz_raw,mx_cal,my_cal,mz_cal', '1,2,3,4,5,6',
                 ['2 magnetometer column sets', 'mx_raw,my_raw,mz_raw (fields 0,1,2)',
                  'mx_cal,my_cal,mz_cal (fields 3,4,5)'], id='raw-and-calibrated'),
    pytest.param('ax,ay,az,gx,gy,gz', '1,2,3,4,5,6',
                 ['no magnetometer columns', 'accelerometer ax,ay,az (fields 0,1,2)',
                  'gyroscope gx,gy,gz (fields 3,4,5)'], id='imu-without-mag'),
    pytest.param('ax,ay,az,x,y,z', '1,2,3,4,5,6',
                 ['no magnetometer columns', 'unlabelled x,y,z (fields 3,4,5)',
                  'accelerometer ax,ay,az'], id='unlabelled-beside-accel'),
    pytest.param('a,b,c,d', '1,2,3,4', ['4 numeric fields'], id='names-that-say-nothing'),
])
def test_ambiguous_files_ask_for_columns_naming_the_candidates(tmp_path, header, line, words):
    with pytest.raises(RecordingError, match='--columns') as error:
        read(tmp_path, f'{header}\n{line}\n', name='log.csv')
    message = str(error.value)
    assert '\n' not in message
    for word in words:
        assert word in message


def test_column_roles_also_find_the_accelerometer_and_gyroscope():
    roles = column_roles(['t', 'ax', 'ay', 'az', 'gx', 'gy', 'gz', 'mx', 'my', 'mz'])
    assert sensor_columns(roles, 'magnetometer') == (7, 8, 9)
    assert sensor_columns(roles, 'accelerometer') == (1, 2, 3)
    assert sensor_columns(roles, 'gyroscope') == (4, 5, 6)
    # a qualifier or unit in the name: 'accelerometer_m_s2' is no magnetometer for its 'm'
    px4 = column_roles(['accelerometer_m_s2[0]', 'accelerometer_m_s2[1]', 'accelerometer_m_s2[2]',
                        'gyro_rad[0]', 'gyro_rad[1]', 'gyro_rad[2]'])
    assert px4.sensors['magnetometer'] == ()
    assert sensor_columns(px4, 'accelerometer') == (0, 1, 2)


def test_out_of_range_rows_are_skipped_and_counted(tmp_path):
    text = f'1,2,3\n1.7e308,2,3\n4,5,6\n{MAX_READING * 1.01:.17g},0,0\n'
    recording = read(tmp_path, text)
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [4, 5, 6]])
    assert recording.skipped == {'out_of_range': 2}
    assert 'beyond' in recording.describe()
    with pytest.raises(RecordingError, match='no usable rows.*2 beyond'):
        read(tmp_path, '1.7e308,2,3\n-1.7e308,2,3\n')


TOKENS = ['1', '-2.5', '3e2', '.5', '+7', 'nan', 'inf', '-Infinity', '1e309', '1.7e308', '1_0',
          '0x10', 'abc', '"4"', "'5'", '', '1,', '#', '%9', '//', 'Mx', '1.5f', '١', 'iNf', '-0',
          '1.', '.', '-.', 'e5', '1e', '+nan', '1e-400', ' 2 ', '0x1p3', '1d3', '"1,2"']


@given(st.lists(st.lists(st.sampled_from(TOKENS), min_size=0, max_size=6), max_size=30),
       st.sampled_from([',', ';', '\t', ' ', ', ']), st.booleans())
def test_numpy_blocks_read_exactly_as_line_by_line(rows, separator, seen_rows):
    """The fast path is an optimisation only: any block numpy accepts must give the rows and
    counts the line-by-line parser gives."""
    block = [separator.join(tokens) + '\n' for tokens in rows]
    for fields in (3, 4):
        layout = recording_columns.TextLayout((0, 1, 2), fields, 'fields 0,1,2', (),
                                    None if separator == ' ' else separator.strip() or None,
                                    fields)
        fast, fast_skipped = recording_text._parse_block(block, layout, seen_rows)
        slow, slow_skipped = recording_text._parse_block(
            block, dataclasses.replace(layout, numpy_fields=None), seen_rows)
        np.testing.assert_array_equal(fast, slow)
        assert +fast_skipped == +slow_skipped


def test_large_files_are_read_a_block_at_a_time(tmp_path):
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(3 * recording_lines.BLOCK_LINES + 17, 3)).round(6)
    text = 'mx,my,mz\n' + ''.join(f'{x!r},{y!r},{z!r}\n' for x, y, z in rows.tolist())
    text = text.replace('\n', '\nnan,1,2\n', 1)  # a NaN row in the first block
    recording = read(tmp_path, text, name='big.csv')
    np.testing.assert_array_equal(recording.samples, rows)
    assert recording.skipped == {'header': 1, 'non_finite': 1}


def test_garbage_nan_and_inf_rows_are_skipped_and_counted(tmp_path):
    text = ('# logged by hand\n'
            'serial monitor v1\n'
            '1,2,3\n'
            'nan,2,3\n'
            '1,inf,3\n'
            '\n'
            'Guru Meditation\n'
            '1,two,3\n'
            '-80,9776\n'
            '\x00\x01\x02 garbage\n'
            '4,5,6\n')
    recording = read(tmp_path, text)
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [4, 5, 6]])
    assert recording.skipped == {'comment': 1, 'header': 1, 'non_finite': 2,
                                 'wrong_field_count': 3, 'not_numeric': 1}
    assert recording.rows_skipped == 8


def test_stdin_is_read_with_dash():
    recording = read_recording('-', stdin=io.StringIO('1\t2\t3\r\n4\t5\t6\r\n'))
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [4, 5, 6]])
    assert recording.source == 'stdin'


def test_progress_reports_bytes_read(tmp_path):
    text = ''.join(f'{i},{i + 1},{i + 2}\n' for i in range(20_000))
    path = write(tmp_path, 'big.csv', text)
    calls = []
    read_recording(path, progress=lambda done, total: calls.append((done, total)))
    assert len(calls) >= 2
    assert calls[-1] == (len(text), path.stat().st_size)
    assert [done for done, _ in calls] == sorted(done for done, _ in calls)


@pytest.mark.parametrize(('text', 'message'), [
    ('', 'empty'),
    ('\n\n  \n', 'empty'),
    ('hello world\nfoo bar baz\n', 'no line with three numeric fields'),
    ('1,2\n3,4\n', 'no line with three numeric fields'),
])
def test_files_without_numeric_rows_raise_one_line_errors(tmp_path, text, message):
    with pytest.raises(RecordingError, match=message) as error:
        read(tmp_path, text)
    assert '\n' not in str(error.value)


def test_too_few_rows_is_an_error_naming_the_minimum(tmp_path):
    with pytest.raises(RecordingError, match=r'only 2 usable rows .*need at least 10'):
        read(tmp_path, '1,2,3\n4,5,6\n', min_rows=10)


def test_all_rows_non_finite_is_an_error(tmp_path):
    with pytest.raises(RecordingError, match='no usable rows.*2 NaN/Inf'):
        read(tmp_path, 'nan,1,2\n1,inf,2\n')


def test_missing_file_directory_and_binary_file_raise(tmp_path):
    with pytest.raises(RecordingError, match='no such file'):
        read_recording(tmp_path / 'absent.csv')
    with pytest.raises(RecordingError, match='not a rosbag2 bag'):
        read_recording(tmp_path)
    binary = tmp_path / 'image.png'
    binary.write_bytes(b'\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR')
    with pytest.raises(RecordingError, match='binary file'):
        read_recording(binary)


def test_unreadable_file_raises(tmp_path):
    path = write(tmp_path, 'secret.csv', '1,2,3\n')
    path.chmod(0)
    try:
        if path.open('rb'):  # root reads anything: nothing to test then
            pytest.skip('running as root: permissions are not enforced')
    except PermissionError:
        with pytest.raises(RecordingError, match='cannot read'):
            read_recording(path)
    finally:
        path.chmod(0o644)


@pytest.mark.parametrize(
    'spec', ['1,3', '1,2,3,4', '0,0,1', '-1,0,1', 'a,b', '1.5,2,3', 'x,1,y', ''])
def test_bad_column_specs_are_rejected(spec):
    with pytest.raises(RecordingError, match='bad --columns'):
        parse_columns(spec)


def test_column_spec_parses_indices_and_names():
    assert parse_columns('1,3,5') == (1, 3, 5)
    assert parse_columns(' 0 1 2 ') == (0, 1, 2)
    assert parse_columns('Mx,My,Mz') == ('mx', 'my', 'mz')


def test_columns_beyond_every_line_and_unknown_names_are_errors(tmp_path):
    with pytest.raises(RecordingError, match=r'no usable rows.*too few fields'):
        read(tmp_path, '1,2,3\n4,5,6\n', columns='1,2,7')
    with pytest.raises(RecordingError, match='no header line names all of'):
        read(tmp_path, 'a,b,c\n1,2,3\n', columns='mx,my,mz')


def test_topic_with_text_and_columns_with_bag_are_errors(tmp_path):
    with pytest.raises(RecordingError, match='--topic applies to rosbag2'):
        read(tmp_path, '1,2,3\n', topic='/imu/mag')
    with pytest.raises(RecordingError, match='--columns applies to text'):
        read_recording(tmp_path / 'x.mcap', columns='0,1,2')


def test_shared_recordings_read_with_their_documented_layouts(shared_data):
    lsm = shared_data / 'lsm303dlhc-altimu10v3'
    txt = read_recording(lsm / 'mag_2.txt')
    csv = read_recording(lsm / 'mag_2.csv')
    assert txt.rows == 301 and txt.skipped == {}
    np.testing.assert_array_equal(txt.samples, csv.samples)
    # The serial log: banner lines (one with gyro offsets), acc x,y,z + mag x,y,z, a summary.
    # Six unnamed numbers per line: the reader must not guess which three are the magnetometer.
    with pytest.raises(RecordingError, match=r'6 numeric fields.*--columns 3,4,5'):
        read_recording(lsm / 'cal_output_2.log')
    log = read_recording(lsm / 'cal_output_2.log', columns='3,4,5')
    np.testing.assert_array_equal(log.samples, txt.samples)
    assert log.skipped == {'header': 4, 'not_numeric': 2}
    assert read_recording(shared_data / 'bno055-jremington' / 'bno055_mag.csv').rows == 809
    assert read_recording(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt').rows == 324
    gd = shared_data / 'gd-notebook'
    assert read_recording(gd / 'mag_raw_data_long.txt').rows == 1114
    deployed = read_recording(gd / 'deployment' / 'validation_data_step1en1.txt', columns='3,4,5')
    assert deployed.rows == 1505
    with pytest.raises(RecordingError, match='6 numeric fields'):
        read_recording(gd / 'deployment' / 'validation_data_step1en1.txt')


# --- rosbag2 ---------------------------------------------------------------------------------


def magnetic_field(values, stamp_ns: int, frame_id: str = 'imu_link'):
    msg_type = TYPESTORE.types[MAGNETIC_FIELD]
    header = TYPESTORE.types['std_msgs/msg/Header'](
        stamp=TYPESTORE.types['builtin_interfaces/msg/Time'](
            sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id=frame_id,
    )
    vector = TYPESTORE.types['geometry_msgs/msg/Vector3'](*map(float, values))
    return msg_type(header=header, magnetic_field=vector,
                    magnetic_field_covariance=np.zeros(9, dtype=np.float64))


def write_bag(path: Path, storage: StoragePlugin, topics: dict[str, np.ndarray],
              extra_topics: tuple[str, ...] = ()) -> Path:
    """A real rosbag2 bag: each topic gets serialized MagneticField messages at 100 Hz."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        for name in extra_topics:
            connection = writer.add_connection(name, 'std_msgs/msg/String', typestore=TYPESTORE)
            message = TYPESTORE.types['std_msgs/msg/String'](data='hello')
            writer.write(connection, 1, TYPESTORE.serialize_cdr(message, 'std_msgs/msg/String'))
        for name, rows in topics.items():
            connection = writer.add_connection(name, MAGNETIC_FIELD, typestore=TYPESTORE)
            for i, row in enumerate(rows):
                stamp = 10**9 + i * 10**7
                data = TYPESTORE.serialize_cdr(magnetic_field(row, stamp), MAGNETIC_FIELD)
                writer.write(connection, stamp, data)
    return path


BAG_ROWS = np.array([[1e-6 * i, -2e-6 * i, 3e-5 + i * 1e-8] for i in range(50)])


@pytest.mark.parametrize('storage', [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_bag_directory_single_topic_is_picked_automatically(tmp_path, storage):
    bag = write_bag(tmp_path / 'bag', storage, {'/imu/mag': BAG_ROWS}, ('/chatter',))
    recording = read_recording(bag)
    np.testing.assert_array_equal(recording.samples, BAG_ROWS)
    assert recording.kind == 'rosbag2'
    assert recording.layout == 'topic /imu/mag'
    assert recording.units == 'T'


@pytest.mark.parametrize(('storage', 'suffix'), [(StoragePlugin.SQLITE3, '.db3'),
                                                  (StoragePlugin.MCAP, '.mcap')])
def test_bag_storage_file_is_read_directly(tmp_path, storage, suffix):
    bag = write_bag(tmp_path / 'bag', storage, {'/imu/mag': BAG_ROWS})
    (storage_file,) = bag.glob(f'*{suffix}')
    np.testing.assert_array_equal(read_recording(storage_file).samples, BAG_ROWS)


@pytest.mark.parametrize('storage', [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_topic_selection_and_its_errors(tmp_path, storage):
    bag = write_bag(tmp_path / 'bag', storage,
                    {'/left/mag': BAG_ROWS, '/right/mag': -BAG_ROWS}, ('/chatter',))
    with pytest.raises(RecordingError, match=r'2 sensor_msgs/msg/MagneticField topics '
                                             r'\(/left/mag, /right/mag\); choose one with '):
        read_recording(bag)
    np.testing.assert_array_equal(read_recording(bag, topic='/right/mag').samples, -BAG_ROWS)
    np.testing.assert_array_equal(read_recording(bag, topic='left/mag').samples, BAG_ROWS)
    with pytest.raises(RecordingError, match=r"no topic '/imu/mag' in this bag; topics: "
                                             r'/chatter \(std_msgs/msg/String\)'):
        read_recording(bag, topic='/imu/mag')
    with pytest.raises(RecordingError, match="topic '/chatter' is std_msgs/msg/String, not"):
        read_recording(bag, topic='/chatter')


def test_bag_without_magnetic_field_topic_lists_what_it_has(tmp_path):
    bag = write_bag(tmp_path / 'bag', StoragePlugin.MCAP, {}, ('/chatter',))
    with pytest.raises(RecordingError, match=r'no sensor_msgs/msg/MagneticField topic in this '
                                             r'bag; topics: /chatter \(std_msgs/msg/String\)'):
        read_recording(bag)


def test_bag_nan_messages_are_skipped_and_counted(tmp_path):
    rows = BAG_ROWS.copy()
    rows[3, 1] = np.nan
    rows[7, 2] = np.inf
    recording = read_recording(write_bag(tmp_path / 'bag', StoragePlugin.SQLITE3,
                                         {'/imu/mag': rows}))
    assert recording.rows == len(rows) - 2
    assert recording.skipped == {'non_finite': 2}


def test_corrupt_bag_is_a_one_line_error(tmp_path):
    broken = tmp_path / 'broken.db3'
    broken.write_bytes(b'SQLite format 3\x00' + b'\xff' * 200)
    with pytest.raises(RecordingError, match='cannot read rosbag2 bag') as error:
        read_recording(broken)
    assert '\n' not in str(error.value)
    with pytest.raises(RecordingError, match='no such file or bag directory'):
        read_recording(tmp_path / 'absent.mcap')


def test_a_bag_without_the_rosbags_library_says_how_to_get_it(tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_rosbags(name, *args, **kwargs):
        if name.startswith('rosbags'):
            raise ImportError(f'No module named {name!r}')
        return real_import(name, *args, **kwargs)

    bag = tmp_path / 'bag.mcap'
    bag.write_bytes(b'\x89MCAP0\r\n')
    monkeypatch.setattr(builtins, '__import__', no_rosbags)
    with pytest.raises(RecordingError, match='pip install rosbags'):
        read_recording(bag)


def test_messages_a_damaged_mcap_loses_are_counted(tmp_path):
    """Issue #47 item 6: 500 zeroed bytes in an mcap file ended the reader's pass through a
    chunk, and two thirds of the messages were gone without a word. What the bag's own index
    lists and was not read is counted, and the line says it."""
    rows = np.array([[1e-6 * i, -2e-6, 3e-5] for i in range(3000)])
    bag = write_bag(tmp_path / 'bag', StoragePlugin.MCAP, {'/imu/mag': rows})
    assert read_recording(bag).skipped == {}
    (storage,) = bag.glob('*.mcap')
    data = bytearray(storage.read_bytes())
    at = int(0.3 * len(data))
    data[at:at + 500] = bytes(500)
    storage.write_bytes(bytes(data))
    recording = read_recording(bag)
    assert 0 < recording.rows < 3000
    assert recording.skipped == {'not_read': 3000 - recording.rows}
    assert "listed in the bag's index but not read" in describe_skips(recording.skipped)

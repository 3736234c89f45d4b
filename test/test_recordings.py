"""Recordings reader: every text layout, stdin, rosbag2 (sqlite3, mcap), every error path."""

import io
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from mag_calibrator_ros.calibration.fitting import LARGEST_READING
from mag_calibrator_ros.tools.recordings import (
    MAGNETIC_FIELD,
    Recording,
    RecordingError,
    parse_columns,
    read_recording,
)

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
    assert recording.layout == 'fields 1,3,5'


def test_wide_rows_use_the_first_three_and_say_so(tmp_path):
    recording = read(tmp_path, '1 2 3 4 5 6\n7 8 9 10 11 12\n')
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [7, 8, 9]])
    assert any('--columns' in note for note in recording.notes)
    chosen = read(tmp_path, '1 2 3 4 5 6\n7 8 9 10 11 12\n', columns='3,4,5')
    np.testing.assert_array_equal(chosen.samples, [[4, 5, 6], [10, 11, 12]])


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


def test_out_of_range_rows_are_skipped_and_counted(tmp_path):
    text = f'1,2,3\n1.7e308,2,3\n4,5,6\n{LARGEST_READING * 1.01:.17g},0,0\n'
    recording = read(tmp_path, text)
    np.testing.assert_array_equal(recording.samples, [[1, 2, 3], [4, 5, 6]])
    assert recording.skipped == {'out_of_range': 2}
    assert 'beyond' in recording.describe()
    with pytest.raises(RecordingError, match='no usable rows.*2 beyond'):
        read(tmp_path, '1.7e308,2,3\n-1.7e308,2,3\n')


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
    log = read_recording(lsm / 'cal_output_2.log', columns='3,4,5')
    np.testing.assert_array_equal(log.samples, txt.samples)
    assert log.skipped == {'header': 4, 'not_numeric': 2}
    assert read_recording(shared_data / 'bno055-jremington' / 'bno055_mag.csv').rows == 809
    assert read_recording(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt').rows == 324
    gd = shared_data / 'gd-notebook'
    assert read_recording(gd / 'mag_raw_data_long.txt').rows == 1114
    deployed = read_recording(gd / 'deployment' / 'validation_data_step1en1.txt', columns='3,4,5')
    assert deployed.rows == 1505


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

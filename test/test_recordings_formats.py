# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Recorded data as users have it (issues #21.7, #22.6): ``ros2 topic echo`` in CSV and YAML,
spreadsheet CSV with decimal commas, headers with units, and readers that stay bounded whatever
the input (a NUL tail, millions of dense rows)."""

import io
import re
import sys
import tracemalloc

import numpy as np
import pytest

from mag_calibrator_ros.tools import recording_lines
from mag_calibrator_ros.tools.fit import main
from mag_calibrator_ros.tools.recording_text import read_paired_recording, read_text
from mag_calibrator_ros.tools.recording_value import RecordingError
from mag_calibrator_ros.tools.recordings import read_recording

ERROR_PREFIX = 'mag_calibrator_fit: error: '


def field_rows(n=300, seed=5):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return 50e-6 * directions + np.array([10e-6, -5e-6, 20e-6])


def echo_csv(rows, frame_id='imu_link'):
    """``ros2 topic echo --csv /imu/mag``: stamp sec, nanosec, frame_id, x, y, z, 9 covariance."""
    return ''.join(
        f'{1700000000 + i // 100},{(i % 100) * 10_000_000},{frame_id},'
        + ','.join(repr(float(v)) for v in row) + ',' + ','.join(['0.0'] * 9) + '\n'
        for i, row in enumerate(rows))


def echo_yaml(rows):
    """``ros2 topic echo /imu/mag`` (its default YAML output)."""
    messages = []
    for i, (x, y, z) in enumerate(rows.tolist()):
        messages.append(
            f'header:\n  stamp:\n    sec: {1700000000 + i}\n    nanosec: 5\n'
            f'  frame_id: imu_link\nmagnetic_field:\n  x: {x!r}\n  y: {y!r}\n  z: {z!r}\n'
            'magnetic_field_covariance:\n' + '- 0.0\n' * 9 + '---\n')
    return ''.join(messages)


def run_cli(capsys, argv, stdin_text=None, monkeypatch=None):
    if stdin_text is not None:
        monkeypatch.setattr(sys, 'stdin', io.StringIO(stdin_text))
    code = main(argv)
    return code, capsys.readouterr()


# --- ros2 topic echo --------------------------------------------------------------------------


def test_topic_echo_csv_picks_the_field_not_the_covariance(tmp_path):
    rows = field_rows()
    path = tmp_path / 'echo.csv'
    path.write_text(echo_csv(rows))
    recording = read_recording(path)
    assert recording.layout == 'ros2 topic echo --csv of sensor_msgs/MagneticField (fields 3,4,5)'
    np.testing.assert_array_equal(recording.samples, rows)
    # tesla, as every MagneticField: it was 'units not stated' (issue #46)
    assert recording.units == 'T' and 'ros2 topic echo --csv' in recording.notes[0]


def test_topic_echo_csv_on_stdin_calibrates(capsys, monkeypatch):
    code, captured = run_cli(capsys, ['-', '--json'], echo_csv(field_rows()), monkeypatch)
    assert code == 0, captured.err
    assert '"ros2 topic echo --csv of sensor_msgs/MagneticField (fields 3,4,5)"' in captured.out
    assert '"units": "T"' in captured.out


def test_topic_echo_yaml_is_read_message_by_message_in_tesla(capsys, monkeypatch):
    rows = field_rows()
    text = echo_yaml(rows)
    recording = read_text(io.StringIO(text))
    np.testing.assert_array_equal(recording.samples, rows)
    assert recording.units == 'T'
    assert recording.layout.startswith('ros2 topic echo')
    code, captured = run_cli(capsys, ['-', '--json'], text, monkeypatch)
    assert code == 0, captured.err
    assert '"units": "T"' in captured.out


def test_topic_echo_yaml_counts_what_it_cannot_use():
    rows = field_rows(40)
    text = re.sub(r'  x: .*\n', '  x: .nan\n', echo_yaml(rows), count=1)
    text += 'header:\n  frame_id: imu_link\nmagnetic_field:\n  x: 1.0\n  y: 2.0\n---\n'
    recording = read_text(io.StringIO(text))
    assert recording.rows == 39
    assert recording.skipped == {'non_finite': 1, 'incomplete': 1}
    with pytest.raises(RecordingError, match='--columns'):
        read_text(io.StringIO(text), columns='0,1,2')


# --- spreadsheets and headers ----------------------------------------------------------------


def semicolon_csv(rows, header='mx;my;mz'):
    lines = [header] + [';'.join(f'{v:.4f}'.replace('.', ',') for v in row) for row in rows]
    return '\n'.join(lines) + '\n'


@pytest.mark.parametrize('columns', [None, 'mx,my,mz'])
def test_semicolon_csv_with_decimal_commas_is_matched(tmp_path, columns):
    rows = np.round(field_rows() * 1e6, 4)
    path = tmp_path / 'excel.csv'
    path.write_text(semicolon_csv(rows))
    recording = read_recording(path, columns=columns)
    np.testing.assert_allclose(recording.samples, rows, rtol=0, atol=1e-9)
    assert recording.skipped == {'header': 1}
    assert any('decimal commas' in note for note in recording.notes)


def test_semicolon_csv_with_a_time_column_and_decimal_commas(tmp_path):
    rows = np.round(field_rows() * 1e6, 4)
    text = 'time;mx;my;mz\n' + ''.join(
        f'{i * 0.01:.2f};'.replace('.', ',')
        + ';'.join(f'{v:.4f}'.replace('.', ',') for v in row) + '\n'
        for i, row in enumerate(rows))
    path = tmp_path / 'excel.csv'
    path.write_text(text)
    recording = read_recording(path)
    assert recording.layout.endswith('(fields 1,2,3)')
    np.testing.assert_allclose(recording.samples, rows, rtol=0, atol=1e-9)


def test_comma_csv_is_not_taken_for_decimal_commas(tmp_path):
    path = tmp_path / 'plain.csv'
    path.write_text('mx,my,mz\n1.5,2.5,3.5\n4,5,6\n')
    np.testing.assert_array_equal(read_recording(path).samples, [[1.5, 2.5, 3.5], [4, 5, 6]])


@pytest.mark.parametrize(('header', 'units'), [
    ('Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT)', 'uT'),
    ('mag_x [nT],mag_y [nT],mag_z [nT]', 'nT'),
    ('Bx (µT),By (µT),Bz (µT)', 'uT'),
    ('mx (G),my (G),mz (G)', 'G'),
    ('mx (mG),my (mG),mz (mG)', 'mG'),
    ('mx (counts),my (counts),mz (counts)', None),
    ('mx (uT),my (nT),mz (uT)', None),
    ('mx,my,mz', None),
    ('magnetometer_ga[0],magnetometer_ga[1],magnetometer_ga[2]', 'G'),  # PX4's ulog2csv
    ('mag_x_uT,mag_y_uT,mag_z_uT', 'uT'),
    ('mag_x_uT,mag_y_uT,mag_z', None),
])
def test_header_units_are_the_recordings_units(tmp_path, header, units):
    path = tmp_path / 'log.csv'
    path.write_text(header + '\n' + '\n'.join(','.join(map(str, row)) for row in
                                              field_rows(10) * 1e6) + '\n')
    recording = read_recording(path)
    assert recording.units == units
    assert any(f'units {units} from the header' in note for note in recording.notes) == bool(units)


@pytest.mark.parametrize('reader', ['magnetometer', 'paired'])
def test_columns_named_without_their_units_are_the_header_fields(tmp_path, reader):
    """``--columns mx,my,mz`` on 'time (s),mx (uT),...': the names are matched to the header's
    fields, not to its words ('time', '(s)', 'mx', '(uT)' ...), which once read fields 2, 4
    and 6 (my, ax, az here) without a word."""
    rows = field_rows(50) * 1e6
    accel = np.tile([0.5, -0.25, 9.75], (50, 1))
    path = tmp_path / 'log.csv'
    lines = ['time (s),mx (uT),my (uT),mz (uT),ax,ay,az'] + [
        ','.join(map(str, [0.1 * i, *m, *a])) for i, (m, a) in enumerate(
            zip(rows, accel, strict=True))]
    path.write_text('\n'.join(lines) + '\n')
    if reader == 'paired':
        recording = read_paired_recording(path, accel_columns='ax,ay,az', columns='MX,my,mz')
        np.testing.assert_array_equal(recording.accel, accel)
    else:
        recording = read_recording(path, columns='MX,my,mz')
    np.testing.assert_array_equal(recording.samples, rows)
    assert recording.units == 'uT'


def test_paired_reader_reports_header_units(tmp_path):
    rows = field_rows(50) * 1e6
    accel = np.tile([0.0, 0.0, 9.81], (50, 1))
    path = tmp_path / 'imu.csv'
    lines = ['ax,ay,az,mx (uT),my (uT),mz (uT)'] + [
        ','.join(map(str, [*a, *m])) for a, m in zip(accel, rows, strict=True)]
    path.write_text('\n'.join(lines) + '\n')
    recording = read_paired_recording(path, accel_columns='ax,ay,az')
    assert recording.units == 'uT'
    np.testing.assert_array_equal(recording.samples, rows)
    for accel_columns in ('ax,ay,az', 'ay,ax,az'):  # a remapped accelerometer is read too
        recording = read_paired_recording(path, accel_columns=accel_columns)
        (note,) = [note for note in recording.notes if 'chosen by their names' in note]
        assert 'ignored' not in note, note
    alone = read_recording(path)
    assert any('ignored accelerometer ax,ay,az (fields 0,1,2)' in n for n in alone.notes)


# --- bounded reading -----------------------------------------------------------------------------


def nul_tail(tmp_path, size=8 << 20):
    """A text head, then megabytes of NUL bytes without a line break (a card pulled mid-write)."""
    path = tmp_path / 'log.txt'
    with path.open('wb') as handle:
        handle.write(b''.join(f'{i} {-i} {2 * i + 1}\n'.encode() for i in range(400)))
        handle.write(b'\0' * size)
    return path


def test_a_nul_tail_is_refused_without_reading_it_whole(tmp_path):
    path = nul_tail(tmp_path)
    tracemalloc.start()
    try:
        with pytest.raises(RecordingError) as error:
            read_recording(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(error.value)
    assert 'line 401' in message and 'NUL' in message and 'not a text recording' in message
    assert peak < 4 * recording_lines.MAX_LINE_CHARS + (2 << 20)  # never the 8 MiB line


def test_a_nul_tail_on_stdin_and_in_the_cli_is_exit_2_with_one_line(tmp_path, capsys,
                                                                    monkeypatch):
    path = nul_tail(tmp_path, 1 << 20)
    code, captured = run_cli(capsys, [str(path)])
    assert code == 2
    assert captured.err.startswith(ERROR_PREFIX) and len(captured.err.splitlines()) == 1
    assert 'longer than' in captured.err
    text = path.read_bytes().decode()
    with pytest.raises(RecordingError, match='longer than'):
        read_text(io.StringIO(text))
    code, captured = run_cli(capsys, ['-'], text, monkeypatch)
    assert code == 2 and 'stdin: line 401' in captured.err
    code, captured = run_cli(capsys, [str(path), '--accel-columns', '0,1,2'])
    assert code == 2 and 'longer than' in captured.err


def test_a_long_but_bounded_line_is_still_read(tmp_path):
    path = tmp_path / 'wide.txt'
    padding = ' ' * (recording_lines.MAX_LINE_CHARS - 20)
    path.write_text(''.join(f'{i} {-i} {i + 1}{padding}\n' for i in range(40)))
    assert read_recording(path).rows == 40


def peak_bytes_per_value(read, values):
    tracemalloc.start()
    try:
        result = read()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return result, peak / values


def test_dense_text_costs_little_beyond_the_float_array(tmp_path):
    n = 300_000
    rows = np.random.default_rng(1).integers(-2000, 2000, size=(n, 3))
    path = tmp_path / 'dense.txt'
    np.savetxt(path, rows, fmt='%d')
    recording, per_value = peak_bytes_per_value(lambda: read_recording(path), 3 * n)
    np.testing.assert_array_equal(recording.samples, rows)
    assert per_value < 8 + 6  # the samples (8 bytes a value) and a block of text at a time


def test_dense_paired_text_costs_little_beyond_the_float_arrays(tmp_path):
    n = 100_000
    rows = np.random.default_rng(2).integers(-2000, 2000, size=(n, 6))
    path = tmp_path / 'imu.txt'
    np.savetxt(path, rows, fmt='%d')
    recording, per_value = peak_bytes_per_value(
        lambda: read_paired_recording(path, accel_columns='0,1,2'), 6 * n)
    np.testing.assert_array_equal(recording.accel, rows[:, :3])
    np.testing.assert_array_equal(recording.samples, rows[:, 3:])
    assert per_value < 2 * 8 + 6  # rows while reading, then the two column arrays


def test_a_logger_line_gives_every_sensor_and_input_row_for_row():
    """Columns in any order: the magnetometer, the accelerometer, the gyroscope (times its
    scale to rad/s; NaN where no number, counted), the inputs and the temperature, the time."""
    header = 'temp,mx,my,mz,stamp_ms,gx,gy,gz,ax,ay,az,motor_current,battery_current'
    lines = [header] + [f'{20 + i * 0.1},{30 + i},{-20 + i % 5},{40 - i % 3},{1000 + i * 10},'
                        f"{'x' if i == 7 else 0.1 * i},0.2,0.3,0.01,0.02,9.8,{i % 4},{5 + i % 3}"
                        for i in range(40)]
    recording = read_paired_recording('-', accel_columns='ax,ay,az', gyro_columns='gx,gy,gz',
                                      gyro_units='deg/s', compensation=(None, None),
                                      stdin=io.StringIO('\n'.join(lines) + '\n'))
    assert recording.samples[3].tolist() == [33.0, -17.0, 40.0]
    assert recording.accel[3].tolist() == [0.01, 0.02, 9.8]
    assert recording.gyro[3] == pytest.approx(np.radians([0.3, 0.2, 0.3]))
    assert np.isnan(recording.gyro[7, 0]) and any('1 of 40 rows' in n for n in recording.notes)
    assert recording.input_names == ('motor_current', 'battery_current')
    assert recording.inputs[3].tolist() == [3.0, 5.0]
    assert recording.temperature[3] == pytest.approx(20.3)
    assert recording.stamps[3] - recording.stamps[0] == pytest.approx(0.03)
    assert 'gyroscope columns gx,gy,gz (fields 5,6,7)' in recording.layout
    with pytest.raises(RecordingError, match='do not say their unit: give --gyro-units'):
        read_paired_recording('-', accel_columns='ax,ay,az', gyro_columns='gx,gy,gz',
                              stdin=io.StringIO('\n'.join(lines) + '\n'))
    said = [lines[0].replace('gx,gy,gz', 'gx [rad/s],gy [rad/s],gz [rad/s]'), *lines[1:]]
    recording = read_paired_recording('-', accel_columns='ax,ay,az', gyro_columns='gx,gy,gz',
                                      stdin=io.StringIO('\n'.join(said) + '\n'))
    assert recording.gyro[3] == pytest.approx([0.3, 0.2, 0.3])


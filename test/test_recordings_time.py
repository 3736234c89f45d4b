# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Text logs with a time column: the header names it, its unit is the header's or the one its
values show, and the reader says which column and unit it took."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from mag_calibrator_ros.tools import fit
from mag_calibrator_ros.tools.recording_text import read_paired_recording, read_text
from mag_calibrator_ros.tools.recording_time import time_unit
from mag_calibrator_ros.tools.recordings import read_recording

ROWS = [(20.0 + i, -30.0 + 0.5 * i, 40.0 - i) for i in range(30)]


def log(header: str, times, rows=ROWS, separator: str = ',') -> str:
    lines = [header]
    lines += [separator.join(str(v) for v in (t, *row)) for t, row in zip(times, rows,
                                                                         strict=True)]
    return '\n'.join(lines) + '\n'


@pytest.mark.parametrize(('header', 'times', 'seconds', 'words'), [
    ('Time (s),mx,my,mz', [0.5 * i for i in range(30)], 0.5, 'seconds (from the header)'),
    ('time,mx,my,mz', [0.01 * i for i in range(30)], 0.01, 'seconds (from steps of 0.01'),
    ('t,mx,my,mz', [1000 + 10 * i for i in range(30)], 0.01, 'milliseconds (from steps of 10'),
    ('millis,mx,my,mz', [3 * i for i in range(30)], 0.003, 'milliseconds (from the header)'),
    ('time_ms,mx,my,mz', [333.3 * i for i in range(30)], 0.3333, 'milliseconds (from the '
                                                                 'header)'),
    ('stamp,mx,my,mz', [1.7e18 + 1e7 * i for i in range(30)], 0.01, 'nanoseconds since 1970'),
    ('timestamp [us],mx,my,mz', [5e6 * i for i in range(30)], 5.0, 'microseconds (from the '
                                                                   'header)'),
    ('%time,field.magnetic_field.x,field.magnetic_field.y,field.magnetic_field.z',
     [1_700_000_000_000_000_000 + 10**7 * i for i in range(30)], 0.01, 'nanoseconds since'),
])
def test_a_time_column_named_by_the_header_stamps_the_rows(header, times, seconds, words):
    recording = read_text(io.StringIO(log(header, times)))
    np.testing.assert_array_equal(recording.samples, ROWS)
    steps = np.diff(recording.stamps)
    np.testing.assert_allclose(steps, seconds, rtol=1e-6, atol=1e-6)  # epoch ns: 256 ns quanta
    name = header.split(',')[0].lstrip('%')
    assert recording.time_source.startswith(f"column '{name}' (field 0), {words}")


def test_a_log_without_a_time_column_has_no_stamps():
    recording = read_text(io.StringIO(log('index,mx,my,mz', range(30))))
    assert recording.stamps is None and recording.time_source is None


def test_two_time_columns_are_not_guessed_between():
    text = '\n'.join(['time,t,mx,my,mz'] + [f'{i},{i * 10},{x},{y},{z}'
                                               for i, (x, y, z) in enumerate(ROWS)])
    assert read_text(io.StringIO(text)).stamps is None


def test_a_row_whose_time_is_no_number_is_skipped_and_counted():
    text = log('time,mx,my,mz', [0.01 * i for i in range(30)]).replace('0.05,', 'nan,')
    recording = read_text(io.StringIO(text))
    assert recording.rows == 29 and recording.skipped == {'header': 1, 'bad_time': 1}
    assert len(recording.stamps) == 29 and np.isfinite(recording.stamps).all()


def test_a_whitespace_log_read_line_by_line_keeps_its_time(tmp_path):
    text = log('time_ms Bx By Bz', [10 * i for i in range(30)], separator=' ')
    lines = text.splitlines()
    text = '\n'.join([*lines[:5], '# a comment', *lines[5:]]) + '\n'  # no numpy fast path
    path = tmp_path / 'log.txt'
    path.write_text(text)
    recording = read_recording(path)
    np.testing.assert_allclose(np.diff(recording.stamps), 0.01)
    assert recording.skipped == {'header': 1, 'comment': 1}


@pytest.mark.parametrize(('values', 'header', 'scale'), [
    (np.arange(10) * 0.1, None, 1.0),
    (np.arange(10) * 2.0, None, 1e-3),  # whole steps of 2: an Arduino's millis() at 500 Hz
    (np.arange(10) * 0.5 + 0.25, None, 1.0),
    (1.7e9 + np.arange(10), None, 1.0),  # epoch seconds stepping by 1 s
    (1.7e12 + np.arange(10) * 10, None, 1e-3),
    (np.arange(10) * 7.5, None, 1e-3),
    (np.arange(10) * 7.5, 's', 1.0),  # the header wins
    (1.1e8 + np.arange(10) * 4000, None, 1e-6),  # PX4 sensor_combined: us since boot, 250 Hz
    (2e7 + np.arange(10) * 20000, None, 1e-6),  # PX4 vehicle_magnetometer at 50 Hz
    (3e12 + np.arange(10) * 10**7, None, 1e-9),  # nanoseconds since boot at 100 Hz
    (1.7e9 + np.arange(10) * 2, None, 1.0),  # epoch seconds every 2 s
    (1.7e12 + np.arange(10) * 1001 + np.arange(10) % 2, None, 1e-3),  # epoch ms, 1 Hz, jitter
    (5e5 + np.arange(10) * 1001 + np.arange(10) % 2, None, 1e-3),  # millis() at 1 Hz, jitter
    (1.5e9 + np.arange(10) * 4000, None, 1e-6),  # us since boot (25 min): not a 1970 date
    (np.repeat(np.arange(10.0), 100), None, 1.0),  # whole seconds at 100 Hz (issue #47)
    (np.repeat(np.arange(10.0) * 1000, 100), None, 1e-3),  # whole seconds as ms at 100 Hz
])
def test_time_units_from_values_or_header(values, header, scale):
    assert time_unit(values, header)[0] == scale


def paired_log(path, time_header: str, times) -> None:
    rng = np.random.default_rng(3)
    accel = rng.normal(0.0, 1.0, (len(times), 3)) + [0.0, 0.0, 9.8]
    field = rng.normal(0.0, 30.0, (len(times), 3))
    lines = [f'{time_header},ax,ay,az,mx,my,mz']
    lines += [','.join(str(v) for v in (t, *a, *m)) for t, a, m in zip(times, accel, field,
                                                                      strict=True)]
    path.write_text('\n'.join(lines) + '\n')


def test_a_paired_log_keeps_its_time_column(tmp_path):
    path = tmp_path / 'paired.csv'
    paired_log(path, 'Time (s)', [0.02 * i for i in range(50)])
    recording = read_paired_recording(path, accel_columns='ax,ay,az')
    assert recording.samples.shape == recording.accel.shape == (50, 3)
    np.testing.assert_allclose(np.diff(recording.stamps), 0.02)
    assert recording.time_source.startswith("column 'Time (s)' (field 0), seconds")


def test_the_cli_says_which_time_column_it_took(tmp_path, capsys):
    path = tmp_path / 'timed.csv'
    path.write_text(log('millis,mx,my,mz', [10 * i for i in range(30)], ROWS * 1))
    assert fit.main([str(path), '--json']) in (0, 1)
    summary = json.loads(capsys.readouterr().out)
    assert summary['time']['stamped'] is True
    assert summary['time']['source'] == ("column 'millis' (field 0), milliseconds (from the "
                                         'header)')
    assert summary['rate_hz'] == pytest.approx(100.0)
    assert fit.main([str(path)]) in (0, 1)
    assert "time      column 'millis' (field 0), milliseconds" in capsys.readouterr().out


def test_a_px4_log_as_ulog2csv_writes_it_calibrates_in_its_time_and_unit(tmp_path, capsys):
    """``ulog2csv -m vehicle_magnetometer`` (pyulog): 'timestamp' in microseconds since boot,
    'magnetometer_ga[0..2]' in gauss. Read as milliseconds, its 50 Hz were a reading every
    20 s, and the same stamps past 10^8 (28 h since boot) read as seconds of 1973 made every
    reading a stamp jump: nothing was calibrated."""
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(1500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    gauss = 0.5 * directions @ np.diag([1.1, 0.95, 1.0]) + [0.12, -0.05, 0.3]
    for start in (20_310_847, 112_614_307):  # seconds and 28 h after boot
        path = tmp_path / f'log_{start}_vehicle_magnetometer_0.csv'
        lines = ['timestamp,magnetometer_ga[0],magnetometer_ga[1],magnetometer_ga[2]']
        lines += [f'{start + 20_000 * i},' + ','.join(f'{v:.8f}' for v in row)
                  for i, row in enumerate(gauss)]
        path.write_text('\n'.join(lines) + '\n')
        assert fit.main([str(path), '--json']) == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary['units'] == 'G'
        assert summary['time']['source'].startswith("column 'timestamp' (field 0), microseconds")
        assert summary['rate_hz'] == pytest.approx(50.0)
        assert sum(summary['rejects'].values()) < 150  # duplicates at most, no stamp jump
        assert summary['rejects'].get('stamp_jump', 0) == 0


def test_a_time_column_in_no_order_is_no_clock_and_costs_no_rows():
    """Issue #47: a column named 'time' whose values were in no order was taken as the clock,
    and the calibrator refused 98 % of the rows as stamps going back. It is said and not used;
    every row is read. A clock that wraps once (a logger restarted) is still the clock."""
    shuffled = np.random.default_rng(0).permutation(30) * 0.01
    recording = read_text(io.StringIO(log('time,mx,my,mz', shuffled.tolist())))
    assert recording.rows == 30 and recording.stamps is None
    assert recording.time_source.startswith("column 'time' (field 0) is no clock (")
    clock = fit.Clock.of(recording, None)
    assert not clock.stamped and clock.source.startswith("column 'time' (field 0) is no clock")
    wrapped = [0.01 * (i % 20) for i in range(30) for _ in range(4)]  # one step back in 120
    rows = [row for row in ROWS for _ in range(4)]
    recording = read_text(io.StringIO(log('time,mx,my,mz', wrapped, rows)))
    assert recording.stamps is not None and len(recording.stamps) == 120

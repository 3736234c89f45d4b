# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_fit end to end: real recordings, every output, every way it must refuse."""

from collections import Counter
import io
import json
import os
from pathlib import Path
import subprocess
import sys
import warnings

from hypothesis import given
from hypothesis import strategies as st
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin
from test_recordings import write_bag
import yaml

from mag_calibrator_ros.calibration.fit.coverage import places, readings_barely_change
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration
from mag_calibrator_ros.calibration.live.offline import calibrate_now, feed
from mag_calibrator_ros.calibration.live.screening import reading_problem
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.store.calibration_file import load_calibration
from mag_calibrator_ros.tools import fit
from mag_calibrator_ros.tools.fit import main
from mag_calibrator_ros.tools.recordings import read_recording

ERROR_PREFIX = 'mag_calibrator_fit: error: '
PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
SUMMARY_KEYS = {'success', 'reason', 'model', 'offset', 'matrix', 'field_strength', 'metrics',
                'rejects', 'input', 'mode', 'outputs', 'units'}

# (path under shared data, extra arguments, --max-residual needed to pass: None = default gate)
# The deployment runs step1en2/3 and the short notebook file fitted whole are real, disturbed
# recordings: their residual (5.3-8.3 % of F) exceeds the default 5 % gate; they calibrate with
# a looser gate and fail the default one with the residual reason (test below).
RECORDINGS = [
    ('gd-notebook/mag_raw_data.txt', [], {'buffer': None, 'all': 10.0}),
    ('gd-notebook/mag_raw_data_long.txt', [], {'buffer': None, 'all': None}),
    ('gd-notebook/deployment/validation_data_step1en1.txt', ['--columns', '3,4,5'],
     {'buffer': None, 'all': None}),
    ('gd-notebook/deployment/validation_data_step1en2.txt', ['--columns', '3,4,5'],
     {'buffer': 10.0, 'all': 10.0}),
    ('gd-notebook/deployment/validation_data_step1en3.txt', ['--columns', '3,4,5'],
     {'buffer': 10.0, 'all': 10.0}),
    ('fxos8700-mwrona/mag-readings.txt', [], {'buffer': None, 'all': None}),
    ('bno055-jremington/bno055_mag.csv', [], {'buffer': None, 'all': None}),
    ('lsm303dlhc-altimu10v3/mag_2.txt', [], {'buffer': None, 'all': None}),
]
DISTURBED = [(path, extra, mode) for path, extra, gates in RECORDINGS
             for mode, gate in gates.items() if gate is not None]


def run_json(capsys, argv):
    code = main([*argv, '--json'])
    captured = capsys.readouterr()
    return code, json.loads(captured.out), captured.err


def mode_args(mode):
    return ['--all'] if mode == 'all' else ['--buffer', '100']


@pytest.mark.parametrize('mode', ['buffer', 'all'])
@pytest.mark.parametrize(('name', 'extra', 'gates'), RECORDINGS,
                         ids=[name for name, _, _ in RECORDINGS])
def test_every_shared_recording_calibrates_and_the_file_matches_the_summary(
        shared_data, tmp_path, capsys, name, extra, gates, mode):
    output = tmp_path / 'cal' / 'mag.yaml'
    gate = gates[mode]
    # the BNO055's are raw counts, 16 per uT (its PROVENANCE.md): given as uT they are no field
    units = ['--scale', '6.25e-8'] if name.startswith('bno055') else ['--units', 'uT']
    argv = [str(shared_data / name), *extra, *mode_args(mode), *units, '--output', str(output)]
    if gate is not None:
        argv += ['--max-residual', str(gate)]
    code, summary, err = run_json(capsys, argv)
    assert code == 0, summary['reason']
    assert err == ''
    assert SUMMARY_KEYS <= summary.keys()
    assert summary['success'] is True
    assert summary['mode'] == mode
    assert summary['outputs'] == {'calibration': str(output), 'plot': None}
    assert summary['metrics']['residual_rms_pct'] <= (gate or 5.0)
    assert summary['metrics']['coverage'] >= 0.5
    assert summary['input']['rows'] == len(read_recording(shared_data / name,
                                                          columns=extra[1] if extra else None
                                                          ).samples)
    loaded = load_calibration(output)  # in tesla, the node's unit: b and F scale, M does not
    per_unit = 1.0 if '--scale' in units else 1e-6  # counts scaled to tesla as they are read
    np.testing.assert_array_equal(loaded.offset, np.array(summary['offset']) * per_unit)
    np.testing.assert_array_equal(loaded.matrix, summary['matrix'])
    assert loaded.field_strength == summary['field_strength'] * per_unit
    assert loaded.model == summary['model']
    assert summary['units'] == ('T' if '--scale' in units else 'uT')
    assert loaded.metadata['units'] == 'T'
    assert loaded.metadata['source'] == str((shared_data / name).resolve())
    assert loaded.metadata['samples'] == summary['metrics']['n_inliers']
    assert loaded.metadata['residual_rms_pct'] == summary['metrics']['residual_rms_pct']
    assert loaded.metadata['coverage'] == summary['metrics']['coverage']


@pytest.mark.parametrize(('name', 'extra', 'mode'), DISTURBED,
                         ids=[f'{name}-{mode}' for name, _, mode in DISTURBED])
def test_disturbed_recordings_fail_the_default_residual_gate_and_write_nothing(
        shared_data, tmp_path, capsys, name, extra, mode):
    output = tmp_path / 'mag.yaml'
    code = main([str(shared_data / name), *extra, *mode_args(mode), '--units', 'uT', '--output',
                 str(output)])
    out = capsys.readouterr().out
    assert code == 1
    assert out.startswith('NOT CALIBRATED')
    assert 'FAILED    residual' in out
    assert 'no calibration file written' in out
    assert 'offset b' in out  # the best-effort result is still shown
    assert not output.exists()


@pytest.mark.parametrize('rate', [100.0, 20.0])
def test_buffer_mode_streams_through_the_live_session_as_the_node_does(shared_data, capsys, rate):
    """The recording replayed at --rate through the node's own session (its reference fits,
    automatic calibration, refinement), then fitted as ~/calibrate does."""
    path = shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'
    code, summary, _ = run_json(capsys, [str(path), '--buffer', '60', '--k', '5',
                                         '--rate', str(rate)])
    session = CalibrationSession(SessionSettings(buffer_size=60, k=5, full_scale=0.0),
                                 metadata={'units': 'input'})  # as the CLI: unit not stated
    feed(session, read_recording(path).samples, rate_hz=rate)
    expected = calibrate_now(session)
    live = session.report()
    assert code == 0
    assert expected.success
    calibration = expected.outcome.result.calibration
    np.testing.assert_array_equal(summary['offset'], calibration.offset)
    np.testing.assert_array_equal(summary['matrix'], calibration.matrix)
    info = summary['buffer']
    assert (info['capacity'], info['k'], info['fill']) == (60, 5, live.buffer.fill)
    assert info['accepted'] == 324 and info['held_out'] == 324 - live.buffer.seen
    assert 0 < info['held_out'] < 324 // 3  # only once calibrated (automatically, live)
    assert info['fits'] == live.counts.fits and info['live_state'] == live.state
    assert summary['metrics']['n_samples'] == live.buffer.fill


def test_all_mode_fits_every_reading_one_per_place(shared_data, capsys):
    path = shared_data / 'lsm303dlhc-altimu10v3' / 'mag_2.txt'
    code, summary, _ = run_json(capsys, [str(path), '--all', '--model', 'full'])
    samples = read_recording(path).samples
    expected = fit_calibration(places(samples)[0], FitOptions(model='full'))
    assert code == 0
    assert summary['all'] == {'readings': 301, 'places': summary['metrics']['n_samples']}
    assert 250 < summary['metrics']['n_samples'] <= 301  # a log taken to calibrate: few repeats
    assert summary['model'] == 'full'
    np.testing.assert_array_equal(summary['offset'], expected.calibration.offset)
    assert 'buffer' not in summary


def test_all_mode_is_not_won_by_the_pauses_of_a_real_hand(capsys):
    """BROAD trial 04 (test/data/broad): a sensor turned by hand with breaks, half its rows
    pauses whose |B| is 5 % below the moving rows'. Fitted row by row, the pauses won: F 7.7
    uT for 44 and 'the readings barely change' (a planar F 99-159 uT with auto). One reading
    per place, it calibrates as the node's buffer does."""
    path = Path(__file__).parent / 'data' / 'broad' / '04_with_breaks_A_every40.csv'
    rows = read_recording(path).samples
    assert not readings_barely_change(rows)
    code, summary, _ = run_json(capsys, [str(path), '--all', '--units', 'uT'])
    assert code == 0, summary['reason']
    assert summary['model'] == 'full'
    assert summary['field_strength'] == pytest.approx(44.1, abs=0.5)
    assert summary['metrics']['coverage'] >= 0.5


def test_human_summary_names_everything_a_user_needs(shared_data, capsys):
    path = shared_data / 'bno055-jremington' / 'bno055_mag.csv'
    assert main([str(path), '--units', 'counts']) == 0
    captured = capsys.readouterr()
    assert captured.err == ''
    lines = captured.out.splitlines()
    assert lines[0] == 'CALIBRATED'
    text = captured.out
    for expected in ('input     ', '809 rows', 'units counts', 'mode      buffer N=100 k=6',
                     'model     full', 'offset b', 'matrix M', 'F         ', 'residual  ',
                     'coverage  ', 'outliers  ', 'rejects   ', 'duplicates'):
        assert expected in text, expected
    matrix_start = next(i for i, line in enumerate(lines) if line.startswith('matrix M'))
    matrix_rows = lines[matrix_start:matrix_start + 3]
    assert all(len(line.split('[')[1].split()) == 4 for line in matrix_rows)  # 3 numbers and ]
    assert 'FAILED' not in text


def test_quiet_prints_nothing_on_success_but_reports_failure(shared_data, tmp_path, capsys):
    assert main([str(shared_data / 'lsm303dlhc-altimu10v3' / 'mag_2.txt'), '--quiet']) == 0
    assert capsys.readouterr().out == ''
    still = write_still(tmp_path)
    assert main([str(still), '--quiet']) == 1
    assert 'NOT CALIBRATED' in capsys.readouterr().out


def test_plot_writes_a_png(shared_data, tmp_path, capsys):
    plot = tmp_path / 'plots' / 'mag.png'
    code, summary, _ = run_json(capsys, [str(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'),
                                         '--plot', str(plot)])
    assert code == 0
    assert summary['outputs']['plot'] == str(plot)
    assert plot.read_bytes().startswith(PNG_MAGIC)
    assert plot.stat().st_size > 20_000


def test_normalise_gives_unit_field_strength(shared_data, capsys):
    path = shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'
    code, summary, _ = run_json(capsys, [str(path), '--normalise', '--all'])
    assert code == 0
    assert summary['field_strength'] == 1.0
    assert summary['field_strength_source'] == 'normalised'
    matrix, offset = np.array(summary['matrix']), np.array(summary['offset'])
    corrected = (read_recording(path).samples - offset) @ matrix.T
    assert np.median(np.linalg.norm(corrected, axis=1)) == pytest.approx(1.0, abs=0.02)


def test_field_strength_is_respected(shared_data, tmp_path, capsys):
    path = shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'
    output = tmp_path / 'mag.yaml'
    code, summary, _ = run_json(capsys, [str(path), '--field-strength', '53.3', '--units', 'uT',
                                         '-o', str(output)])
    assert code == 0
    assert summary['field_strength'] == 53.3
    assert load_calibration(output).field_strength == 53.3 * 1e-6
    fitted_radius = run_json(capsys, [str(path)])[1]['field_strength']
    assert fitted_radius != pytest.approx(53.3, abs=1e-6)


def test_stdin_input_equals_the_file(shared_data, capsys, monkeypatch):
    path = shared_data / 'bno055-jremington' / 'bno055_mag.csv'
    from_file = run_json(capsys, [str(path)])[1]
    monkeypatch.setattr(sys, 'stdin', io.StringIO(path.read_text()))
    code, from_stdin, _ = run_json(capsys, ['-'])
    assert code == 0
    assert from_stdin['input']['source'] == 'stdin'
    assert from_stdin['offset'] == from_file['offset']
    assert from_stdin['matrix'] == from_file['matrix']


@pytest.mark.parametrize('storage', [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_rosbag_with_topic_calibrates_in_tesla(shared_data, tmp_path, capsys, storage):
    microtesla = read_recording(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt').samples
    bag = write_bag(tmp_path / 'bag', storage, {'/imu/mag': microtesla * 1e-6,
                                                '/other/mag': microtesla[::-1] * 1e-6})
    output = tmp_path / 'mag.yaml'
    code, summary, _ = run_json(capsys, [str(bag), '--topic', '/imu/mag', '-o', str(output)])
    assert code == 0, summary['reason']
    assert summary['units'] == 'T'
    assert summary['input']['layout'] == 'topic /imu/mag'
    reference = run_json(capsys, [str(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt')])[1]
    # the buffer and the fit are scale-free: the same calibration, in tesla
    np.testing.assert_allclose(summary['offset'], np.array(reference['offset']) * 1e-6,
                               rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(summary['matrix'], reference['matrix'], rtol=1e-6, atol=1e-9)
    assert load_calibration(output).metadata['units'] == 'T'
    # two MagneticField topics: without --topic the choice is the user's
    assert main([str(bag)]) == 2
    assert 'choose one with --topic' in capsys.readouterr().err


def test_all_mode_counts_zero_and_saturated_rows(shared_data, tmp_path, capsys):
    rows = read_recording(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt').samples
    damaged = np.vstack([rows, np.zeros((3, 3)), [[500.0, 0.0, 0.0]] * 2])
    path = tmp_path / 'damaged.tsv'
    np.savetxt(path, damaged, delimiter='\t')
    code, summary, _ = run_json(capsys, [str(path), '--all', '--full-scale', '400'])
    assert code == 0
    assert summary['rejects']['zero'] == 3
    assert summary['rejects']['saturated'] == 2
    assert summary['all']['readings'] == len(rows)  # fitted one per place (coverage.places)
    code, summary, _ = run_json(capsys, [str(path), '--full-scale', '400'])
    assert code == 0
    assert summary['rejects']['zero'] == 3
    assert summary['rejects']['saturated'] == 2


def imu_log(rng, n=600):
    """An IMU log: accelerometer (a tumble: g in every direction) then magnetometer (distorted)."""
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    accel = 9.81 * directions[rng.permutation(n)] + rng.normal(0.0, 0.05, (n, 3))
    offset = np.array([30.0, -20.0, 45.0])
    mag = 50.0 * directions @ np.diag([1.1, 0.95, 1.0]) + offset + rng.normal(0.0, 0.3, (n, 3))
    return np.hstack([accel, mag]), offset


@pytest.mark.parametrize('mode', ['buffer', 'all'])
def test_header_names_pick_the_magnetometer_not_the_accelerometer(tmp_path, capsys, mode):
    rows, offset = imu_log(np.random.default_rng(70))
    path = tmp_path / 'imu.csv'
    np.savetxt(path, rows, delimiter=',', header='ax,ay,az,mx,my,mz', comments='', fmt='%.5f')
    code, summary, err = run_json(capsys, [str(path), *mode_args(mode)])
    assert code == 0, summary['reason']
    assert err == ''
    assert 'mx,my,mz (fields 3,4,5)' in summary['input']['layout']
    np.testing.assert_allclose(summary['offset'], offset, atol=0.5)
    assert summary['field_strength'] == pytest.approx(50.0, rel=0.1)


def test_unnamed_imu_columns_ask_for_columns_instead_of_fitting_the_accelerometer(tmp_path,
                                                                                     capsys):
    rows, _ = imu_log(np.random.default_rng(71))
    path = tmp_path / 'imu.csv'
    np.savetxt(path, rows, delimiter=',', fmt='%.5f')
    assert_usage_error(capsys, [str(path), '--all'], '6 numeric fields', '--columns')
    code, summary, _ = run_json(capsys, [str(path), '--all', '--columns', '3,4,5'])
    assert code == 0 and summary['field_strength'] == pytest.approx(50.0, rel=0.1)


@pytest.mark.parametrize('mode', ['buffer', 'all'])
@pytest.mark.parametrize('value', [1.7e308, -1.7e308, 1e308])
def test_values_beyond_any_unit_are_named_as_such_without_warnings(tmp_path, capsys, mode,
                                                                  value):
    rng = np.random.default_rng(72)
    rows = value * np.sign(rng.normal(size=(200, 3))) * rng.uniform(0.5, 1.0, (200, 3))
    path = tmp_path / 'huge.txt'
    np.savetxt(path, rows)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        code = main([str(path), *mode_args(mode)])
    err = capsys.readouterr().err
    assert code == 2
    assert 'beyond' in err and 'identical' not in err and 'Warning' not in err
    assert len(err.splitlines()) == 1


def test_extreme_but_valid_scales_calibrate_without_warnings(tmp_path, capsys):
    rows, offset = imu_log(np.random.default_rng(73))
    path = tmp_path / 'tiny.txt'
    np.savetxt(path, rows[:, 3:] * 1e-300)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        for mode in ('buffer', 'all'):
            code, summary, err = run_json(capsys, [str(path), *mode_args(mode)])
            assert code == 0, summary['reason']
            assert err == ''
            np.testing.assert_allclose(np.array(summary['offset']) * 1e300, offset, atol=0.5)


@given(st.lists(st.tuples(*[st.sampled_from([0.0, -0.0, 1.0, -3.5, 400.0, -400.0, 401.0, 1e-300,
                                               np.nan, np.inf, -np.inf])] * 3),
                min_size=1, max_size=40),
       st.sampled_from([None, 400.0, 1.0]))
def test_all_mode_screens_with_the_buffers_own_rule(rows, full_scale):
    samples = np.array(rows, dtype=float).reshape(-1, 3)
    kept, counts, _ = fit.screen_all(samples, full_scale)
    problems = [reading_problem(*row, full_scale) for row in samples.tolist()]
    np.testing.assert_array_equal(kept, samples[[problem is None for problem in problems]])
    assert counts == dict(Counter(problem for problem in problems if problem is not None))


# --- failures --------------------------------------------------------------------------------


def write_still(tmp_path, name='still.txt'):
    """A sensor lying still: 400 readings of one field plus 0.3 uT noise."""
    rng = np.random.default_rng(7)
    rows = np.array([20.0, -5.0, 40.0]) + rng.normal(0.0, 0.3, (400, 3))
    path = tmp_path / name
    np.savetxt(path, rows, fmt='%.2f', delimiter='\t')
    return path


@pytest.mark.parametrize('mode', ['buffer', 'all'])
def test_still_sensor_fails_with_rotate_and_keeps_the_previous_file(tmp_path, capsys, mode):
    still = write_still(tmp_path)
    output = tmp_path / 'mag.yaml'
    output.write_text('previous calibration\n')
    code = main([str(still), *mode_args(mode), '--units', 'uT', '-o', str(output)])
    out = capsys.readouterr().out
    assert code == 1
    assert 'NOT CALIBRATED' in out
    failed = next(line for line in out.splitlines() if line.startswith('FAILED'))
    assert 'rotate' in failed
    assert output.read_text() == 'previous calibration\n'
    code, summary, err = run_json(capsys, [str(still), *mode_args(mode), '--units', 'uT', '-o',
                                           str(output)])
    assert code == 1
    assert summary['success'] is False
    assert 'rotate' in summary['reason']
    assert summary['outputs']['calibration'] is None
    assert err == ''
    assert output.read_text() == 'previous calibration\n'
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.mag.yaml')]


def assert_usage_error(capsys, argv, *words):
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2
    assert captured.out == ''
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(ERROR_PREFIX)
    for word in words:
        assert word in lines[0]
    assert 'Traceback' not in captured.err


def test_missing_file(tmp_path, capsys):
    assert_usage_error(capsys, [str(tmp_path / 'nope.txt')], 'nope.txt', 'no such file')


def test_empty_file(tmp_path, capsys):
    path = tmp_path / 'empty.txt'
    path.write_text('')
    assert_usage_error(capsys, [str(path)], 'empty')


def test_text_garbage(tmp_path, capsys):
    path = tmp_path / 'notes.txt'
    path.write_text('this is not\na recording at all\n' * 20)
    assert_usage_error(capsys, [str(path)], 'no line with three numeric fields')


def test_binary_garbage(tmp_path, capsys):
    path = tmp_path / 'noise.bin'
    path.write_bytes(bytes(range(256)) * 40)
    assert_usage_error(capsys, [str(path)], 'binary')


def test_too_few_rows(tmp_path, capsys):
    path = tmp_path / 'short.txt'
    path.write_text('1 2 3\n4 5 6\n7 8 10\n')
    assert_usage_error(capsys, [str(path)], 'only 3 usable rows', 'need at least 30')


@pytest.mark.parametrize('columns', ['1,2', '0,0,1', 'a,1,b'])
def test_bad_columns(shared_data, capsys, columns):
    assert_usage_error(capsys, [str(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'),
                                '--columns', columns], '--columns')


def test_columns_beyond_the_lines_leave_no_rows(shared_data, capsys):
    assert_usage_error(capsys, [str(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'),
                                '--columns', '3,4,5'], 'no usable rows')


@pytest.mark.parametrize(('argv', 'words'), [
    (['--model', 'cubic'], ('--model', 'cubic')),
    (['--buffer', '50', '--all'], ('not allowed with',)),
    (['--normalise', '--field-strength', '50'], ('not allowed with',)),
    (['--buffer', '1'], ('--buffer',)),
    (['--buffer', '9'], ('--buffer', 'at least 10')),
    (['--buffer', '10', '--k', '10'], ('--k',)),
    (['--rate', '0'], ('--rate',)),
    (['--rate', 'nan'], ('--rate',)),
    (['--all', '--k', '4'], ('--k', '--all')),
    (['--field-strength', '-3'], ('--field-strength',)),
    (['--field-strength', 'nan'], ('--field-strength',)),
    (['--min-coverage', '1.5'], ('--min-coverage',)),
    (['--max-residual', '0'], ('--max-residual',)),
    (['--full-scale', '0'], ('--full-scale',)),
    (['--topic', '/imu/mag'], ('--topic',)),
    (['--units', 'uT', '--bogus'], ('--bogus',)),
])
def test_bad_options(shared_data, capsys, argv, words):
    assert_usage_error(capsys, [str(shared_data / 'fxos8700-mwrona' / 'mag-readings.txt'),
                                *argv], *words)


def test_no_input_is_a_usage_error(capsys):
    assert_usage_error(capsys, [], 'input')


def test_help_documents_exit_codes_and_examples(capsys):
    assert main(['--help']) == 0
    text = capsys.readouterr().out
    assert 'exit status' in text
    assert '--output is NOT written' in text
    assert 'examples' in text
    for option in ('--buffer', '--all', '--k', '--normalise', '--field-strength', '--full-scale',
                   '--min-coverage', '--max-residual', '--columns', '--topic', '--units',
                   '--output', '--plot', '--json', '--quiet', '--model'):
        assert option in text


def test_unwritable_output_is_a_one_line_error(shared_data, tmp_path, capsys):
    blocker = tmp_path / 'file'
    blocker.write_text('')
    assert_usage_error(capsys, [str(shared_data / 'lsm303dlhc-altimu10v3' / 'mag_2.txt'),
                                '--scale', '1e-7', '-o', str(blocker / 'mag.yaml')],
                       'cannot write')


# --- progress bar ----------------------------------------------------------------------------


class FakeTerminal(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self.tty = tty

    def isatty(self):
        return self.tty


def test_progress_bar_only_on_a_terminal_outside_ci(monkeypatch):
    monkeypatch.delenv('CI', raising=False)
    terminal = FakeTerminal(True)
    bar = fit.ProgressBar(terminal, '-')
    bar.fitting(100, 200)  # small: no bar
    assert terminal.getvalue() == ''
    bar.fitting(30_000, 60_000)
    assert '50.0 %' in terminal.getvalue()
    bar.finish()
    assert terminal.getvalue().endswith('\r')

    pipe = FakeTerminal(False)
    fit.ProgressBar(pipe, '-').fitting(30_000, 60_000)
    assert pipe.getvalue() == ''

    monkeypatch.setenv('CI', 'true')
    ci = FakeTerminal(True)
    fit.ProgressBar(ci, '-').fitting(30_000, 60_000)
    assert ci.getvalue() == ''


# --- start-up --------------------------------------------------------------------------------


STARTUP_CHECK = """
import sys
from mag_calibrator_ros.tools.fit import main
import mag_calibrator_ros.nodes.icm20948_driver, mag_calibrator_ros.nodes.mag_calibrator
import mag_calibrator_ros.tools.demo
codes = [main(['--help']), main(['--model', 'nope', 'x.txt']), main(['--all', '--k', '3', 'x'])]
heavy = sorted({name.split('.')[0] + '.' + name.split('.')[1] for name in sys.modules
                if name.startswith(('scipy.optimize', 'scipy.spatial', 'matplotlib.'))})
print(codes, heavy)
"""


def test_help_argument_errors_and_node_modules_import_no_scipy_optimize_or_matplotlib():
    """--help, usage errors and the nodes' start-up never pay for the fit's or the plot's
    imports (scipy.optimize alone is a heavy one); they come when a fit or a figure needs them."""
    result = subprocess.run([sys.executable, '-c', STARTUP_CHECK], capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == '[0, 2, 2] []'


# --- the installed console script --------------------------------------------------------------


def test_console_script_runs_and_keeps_stdout_clean(shared_data, tmp_path):
    script = Path(sys.executable).parent / 'mag_calibrator_fit'
    assert script.exists(), f'{script} not installed (pip install -e .)'
    output = tmp_path / 'mag.yaml'
    result = subprocess.run(
        [str(script), str(shared_data / 'lsm303dlhc-altimu10v3' / 'mag_2.txt'), '--json',
         '--scale', '1e-7', '-o', str(output)],
        capture_output=True, text=True, timeout=120, env={**os.environ, 'CI': ''}, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stderr == ''
    summary = json.loads(result.stdout)
    assert summary['success'] is True
    document = yaml.safe_load(output.read_text())
    written = document['/**']['ros__parameters']['calibration']
    assert written['offset'] == summary['offset']  # both in tesla (--scale)
    assert written['units'] == 'T'

    missing = subprocess.run([str(script), str(tmp_path / 'missing.txt')], capture_output=True,
                             text=True, timeout=120, check=False)
    assert missing.returncode == 2
    assert missing.stdout == ''
    assert missing.stderr.startswith(ERROR_PREFIX)
    assert len(missing.stderr.splitlines()) == 1

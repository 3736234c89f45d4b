# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_fit --calibration FILE: a recording replayed on a saved calibration, as the
node with calibration_file would live it: the own field learned from a drive that never
turns, the answer judged on every reading, and a calibration that does not fit never
written."""

from __future__ import annotations

import json
from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Compensation
from mag_calibrator_ros.calibration.live.compensation import input_columns
from mag_calibrator_ros.calibration.store.calibration_file import (
    load_calibration,
    save_calibration,
)
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import course_recording
from mag_calibrator_ros.tools import fit, fit_start
from mag_calibrator_ros.tools.fit_compensation import without_own_field
from mag_calibrator_ros.tools.recording_value import Recording

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
from bench_interference import robot  # noqa: E402 - the benchmark's simulated ground robot
from test_fit_cli_compensation import RATE_HZ, write_csv, write_rosbag2  # noqa: E402

TOLERANCE = 0.25
"""K's current axis, as test_fit_cli_compensation judges it."""


def run(capsys, *argv) -> tuple[int, dict]:
    """The exit status and the --json summary; ``fit.human_summary(summary)`` is the text the
    same run prints without --json (what main writes), so a test of a line needs no rerun."""
    status = fit.main([str(a) for a in argv] + ['--json'])
    return status, json.loads(capsys.readouterr().out)


@pytest.fixture(scope='module')
def saved(tmp_path_factory):
    """A static calibration as a user makes it: the robot turned through the ground course
    with its own field off (its drive recorded, fitted, written), and a drive of the same
    robot with its own field on that never turns (``motion.QUICK_PROCEDURE``: straight ahead
    and back at three speeds), as a bag with its IMU, battery and temperature."""
    directory = tmp_path_factory.mktemp('start')
    turning = course_recording(robot(1, interference=False), rate_hz=RATE_HZ)
    csv = write_csv(directory / 'turning.csv', turning, columns=())
    static = directory / 'static.yaml'
    assert fit.main([str(csv), '--units', 'T', '--output', str(static), '--quiet']) == 0
    board = robot(1)
    drive = course_recording(board, motion.CourseDriver(motion.QUICK_PROCEDURE),
                             rate_hz=RATE_HZ)
    bag = write_rosbag2(directory / 'drive', drive, imu=True)
    return static, bag, board.interference_truth(), csv


def test_a_drive_that_never_turns_learns_k_on_a_saved_calibration(tmp_path, capsys, saved):
    static, bag, truth, _ = saved
    status, alone = run(capsys, bag, '--accel', '/imu')
    assert status == 1 and not alone['compensation']['learned']  # nothing in force to learn on
    output = tmp_path / 'cal.yaml'
    status, summary = run(capsys, bag, '--accel', '/imu', '--calibration', static,
                          '--output', output)
    start = summary['start']
    assert start['answer'] == 'in force' and start['changes_in_force'].get('compensation')
    assert 'coverage' in start['buffer_fit']  # the drive alone calibrates nothing
    [k] = summary['compensation']['interference'].values()
    assert abs(k[0] - truth.current_field[0]) <= TOLERANCE * truth.current_field[0], k
    assert start['compensation'] == 'learned' and summary['compensation']['learned']
    assert status == 0 and summary['success'] and start['check']['fits']
    written, given = load_calibration(output), load_calibration(static)
    assert np.allclose(written.matrix, given.matrix)  # the file's soft iron, with K learned
    assert written.compensation is not None
    assert np.allclose(written.compensation.interference[:, 0], k)


def test_the_alignment_and_model_lines_describe_the_answer_in_force(tmp_path, capsys, saved):
    """The buffer's fit failed, so its alignment and model check say nothing about the
    answer: the model check is of the calibration in force, and no fit that passed aligned it."""
    static, bag, _, _ = saved
    output = tmp_path / 'cal.yaml'
    location = ['--latitude', '45.5', '--longitude', '-122.7', '--date', '2026-11-27']
    status, summary = run(capsys, bag, '--accel', '/imu', '--calibration', static,
                          '--output', output, *location)
    assert status == 0 and summary['start']['answer'] == 'in force'
    earth = summary['earth_field']
    assert earth['radius_ratio'] == pytest.approx(
        load_calibration(output).field_radius() / earth['intensity'])
    assert 'alignment' not in summary  # the failed fit's "too few static attitudes" is gone
    assert 'field in force 0.4' in fit.human_summary(summary)  # the text, without a rerun


def test_a_saved_calibration_that_does_not_fit_is_never_written(tmp_path, capsys, saved):
    """The iron moved: the offset 40 % of the field off. A drive that never turns cannot fit
    anew, so the file stays in force, is judged on every reading, and is refused; what was at
    --output is left as it was."""
    static, bag, _, _ = saved
    given = load_calibration(static)
    moved = tmp_path / 'moved.yaml'
    save_calibration(moved, given.with_compensation(
        None, offset=given.offset + [0.4 * given.field_strength, 0.0, 0.0]))
    output = tmp_path / 'cal.yaml'
    output.write_text('kept\n')
    status, summary = run(capsys, bag, '--accel', '/imu', '--no-compensation',
                          '--calibration', moved, '--output', output)
    assert status == 1 and not summary['success']
    assert not summary['start']['check']['fits']
    assert summary['start']['check']['median_error_pct'] > 5.0
    assert 'does not fit this recording' in summary['reason']
    assert output.read_text() == 'kept\n'
    assert 'FAILED    the calibration does not fit this recording' in fit.human_summary(summary)


def test_a_recording_that_turns_replaces_the_saved_calibration(tmp_path, capsys, saved):
    """As ~/calibrate on the node: a fit that passes its gates replaces what is in force."""
    static, _, _, turning = saved
    given = load_calibration(static)
    moved = tmp_path / 'moved.yaml'
    save_calibration(moved, given.with_compensation(
        None, offset=given.offset + [0.4 * given.field_strength, 0.0, 0.0]))
    status, summary = run(capsys, turning, '--units', 'T', '--calibration', moved)
    assert status == 0 and summary['start']['answer'] == 'buffer fit'
    assert summary['start']['check']['fits']
    assert np.allclose(summary['offset'], given.offset, atol=0.05 * given.field_strength)
    adopted = {source: count for source, count in summary['buffer']['live_adoptions'].items()
               if source not in ('file', 'request')}
    assert summary['start']['changes_in_force'] == adopted  # one pass, counted once
    out = fit.human_summary(summary)  # what the same run prints without --json
    assert "answer    the buffer's own fit" in out
    assert 'check     on all 9000 readings' in out


def test_a_file_s_k_is_not_carried_to_a_fit_of_a_recording_without_its_inputs(
        tmp_path, capsys, saved):
    """A fit of readings that K never compensated holds their own field in its offset: the
    file's K on top would take it off twice. With the file's static part (nothing fitted), the
    file's K stays."""
    static, bag, _, turning = saved
    given = load_calibration(static)
    with_k = tmp_path / 'with_k.yaml'
    save_calibration(with_k, given.with_compensation(
        Compensation(('current',), np.array([[1.6e-6], [0.0], [0.0]]))))
    output = tmp_path / 'cal.yaml'
    status, summary = run(capsys, turning, '--units', 'T', '--calibration', with_k,
                          '--output', output)
    assert status == 0 and 'without the terms of current' in summary['start']['compensation']
    assert load_calibration(output).compensation is None
    status, summary = run(capsys, bag, '--accel', '/imu', '--no-compensation', '--calibration',
                          with_k, '--output', output)
    assert summary['start']['answer'] == 'in force'
    assert summary['start']['compensation'].startswith("the file's, kept")
    assert np.allclose(summary['offset'], given.offset)


def test_usage_errors_are_one_line(tmp_path, capsys, saved):
    static, _, _, turning = saved
    cases = [
        (['--all', '--calibration', static], '--calibration starts the live session'),
        (['--calibration', static], 'does not say its unit'),  # the CSV's unit is not given
        (['--units', 'T', '--calibration', tmp_path / 'none.yaml'], 'none.yaml'),
    ]
    for options, words in cases:
        assert fit.main([str(turning), *map(str, options)]) == 2
        error = capsys.readouterr().err
        assert words in error and error.count('\n') == 1, error


def test_a_file_s_terms_are_dropped_one_by_one_where_the_recording_cannot_feed_them():
    both = Compensation(('current',), np.array([[1.6e-6], [0.0], [0.0]]),
                        np.array([0.0, 0.2e-6, 0.0]), 25.0)
    samples = np.zeros((2, 3))
    current_only = Recording(samples=samples, source='log', kind='text', layout='',
                             inputs=np.ones((2, 1)), input_names=('current',))
    assert fit_start.unfed(both, current_only) == ['the temperature']
    kept = fit_start._without(both, ['the temperature'])
    assert kept.interference[0, 0] == 1.6e-6 and not kept.temperature_coefficient.any()
    assert kept.reference_temperature is None
    neither = Recording(samples=samples, source='log', kind='text', layout='')
    assert fit_start.unfed(both, neither) == ['current', 'the temperature']
    assert fit_start._without(both, ['current', 'the temperature']) is None
    drift_left = fit_start._without(both, ['current'])
    assert not drift_left.interference.any() and drift_left.reference_temperature == 25.0


def test_a_compensation_meets_the_inputs_as_the_node_matches_them():
    """By name when all are there, else by position when the counts agree (a file learnt
    offline names its columns, the node its topics), else not at all."""
    assert input_columns(('b', 'a'), ('a', 'b')) == [1, 0]
    assert input_columns(('current',), ('/battery:current',)) == [0]
    assert input_columns(('a', 'b'), ('c',)) is None
    samples = np.zeros((3, 3))
    recording = Recording(samples=samples, source='log', kind='text', layout='',
                          inputs=np.array([[1.0], [np.nan], [2.0]]),
                          input_names=('/battery:current',))
    learned = Compensation(('current',), np.array([[1.0], [0.0], [0.0]]))
    assert without_own_field(recording, learned)[:, 0].tolist() == [-1.0, -1.0, -2.0]
    other = Compensation(('left', 'right'), np.ones((3, 2)))
    assert np.array_equal(without_own_field(recording, other), samples)


def test_a_text_log_with_its_gyroscope_learns_k_on_a_drive_that_never_turns(tmp_path, capsys,
                                                                           saved):
    """One line per reading with the IMU and the current, as a logger writes them: without
    the gyroscope the current's field cannot be told from the Earth's on one heading; with
    it (--gyro-columns) readings between which the robot barely turned tell it, as on a bag."""
    static, _, truth, _ = saved
    drive = course_recording(robot(1), motion.CourseDriver(motion.QUICK_PROCEDURE),
                             rate_hz=RATE_HZ)
    csv = write_csv(tmp_path / 'drive.csv', drive, imu=True)
    common = [csv, '--units', 'T', '--accel-columns', 'ax,ay,az', '--calibration', static]
    _, blind = run(capsys, *common)
    assert blind['compensation']['inputs'] == ['current'] and blind['compensation']['temperature']
    assert not blind['compensation']['learned']
    assert 'not in enough headings' in blind['compensation']['needs']
    _, summary = run(capsys, *common, '--gyro-columns', 'gx,gy,gz')  # deg/s: the header
    assert 'gyroscope columns gx,gy,gz (fields 4,5,6)' in summary['input']['layout']
    [k] = summary['compensation']['interference'].values()
    assert abs(k[0] - truth.current_field[0]) <= TOLERANCE * truth.current_field[0], k
    assert fit.main([str(csv), '--accel-columns', 'ax,ay,az', '--gyro-columns', '4,5,6',
                     '--gyro-units', 'rad/s']) == 2
    assert 'say deg/s, not rad/s' in capsys.readouterr().err
    untimed = tmp_path / 'untimed.csv'  # integrated on a replay rate, it would be made up
    untimed.write_text(''.join(line.split(',', 1)[1] + '\n'
                               for line in csv.read_text().splitlines()))
    assert fit.main([str(untimed), '--units', 'T', '--accel-columns', 'ax,ay,az',
                     '--gyro-columns', 'gx,gy,gz']) == 2
    assert '--gyro-columns needs a time column' in capsys.readouterr().err

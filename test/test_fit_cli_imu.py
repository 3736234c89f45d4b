# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""mag_calibrator_fit with an accelerometer on each line (--accel-columns) and a location
(--latitude/--longitude): the alignment and the World Magnetic Model, offline."""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.alignment import rotation_angle_deg
from mag_calibrator_ros.calibration.fit.earth_field import earth_field
from mag_calibrator_ros.calibration.store.calibration_file import load_calibration
from mag_calibrator_ros.sim.board import BoardModel
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.tools import fit

PORTLAND = ('--latitude', '45.5', '--longitude', '-122.7', '--date', '2026-11-23')
ALIGNMENT_KEYS = {'rotation', 'angle_deg', 'dip_deg', 'dip_std_deg', 'static_samples'}
EARTH_KEYS = {'intensity', 'inclination_deg', 'declination_deg', 'radius_ratio', 'dip_error_deg'}


def run(argv, capsys):
    status = fit.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def simulated_log(path, seconds=50.0, **config) -> BoardModel:
    """A CSV with a header (t, mx, my, mz in uT, ax, ay, az) at 100 Hz from the board."""
    board = BoardModel(SimConfig(hard_iron_ut=(30.0, -20.0, 10.0), noise_ut=0.3,
                                 motion='poses', seed=6, **config))
    lines = ['t,mx,my,mz,ax,ay,az']
    for k in range(int(seconds * 100)):
        t = k / 100.0
        field, _ = board.magnetometer(t)
        accel, _, _ = board.inertial(t, 57.0, 57.0)
        lines.append(','.join(f'{v:.5f}' for v in (t, *field, *accel)))
    path.write_text('\n'.join(lines) + '\n')
    return board


@pytest.fixture(scope='module')
def misaligned_log(tmp_path_factory):
    path = tmp_path_factory.mktemp('imu') / 'log.csv'
    board = simulated_log(path, mag_misalignment_deg=(1.8, -1.9, 1.4), latitude=45.5,
                          longitude=-122.7)
    return path, board


def test_the_real_log_is_aligned_to_its_accelerometer(shared_data, capsys, tmp_path):
    log = shared_data / 'lsm303dlhc-altimu10v3' / 'cal_output_2.log'
    output = tmp_path / 'cal.yaml'
    status, out, _ = run([log, '--accel-columns', '0,1,2', '--rate', '3', '--json',
                          '--scale', '1e-7', '-o', output], capsys)
    summary = json.loads(out)
    assert status == 0, summary['reason']
    alignment = summary['alignment']
    assert set(alignment) >= ALIGNMENT_KEYS and len(alignment['rotation']) == 9
    assert alignment['applied'] and alignment['static_samples'] >= 100
    # The lead's measurement: 3.16 deg of dip scatter, 3.12 deg after the best rotation; about a
    # degree of misalignment. The inliers scatter less still.
    assert alignment['dip_std_deg'] < alignment['dip_std_before_deg'] < 3.3
    assert 0.3 < alignment['angle_deg'] < 2.0
    assert 55.0 < alignment['dip_deg'] < 72.0  # the author's workshop: dip of the US northwest
    assert 'earth_field' not in summary  # no location given
    saved = load_calibration(output)
    np.testing.assert_allclose(saved.rotation.reshape(9), alignment['rotation'], atol=1e-12)
    assert saved.metadata['static_samples'] == alignment['static_samples']



def test_the_answer_states_its_heading_sigma_at_the_dip_it_measured(shared_data, capsys):
    """The same log: what the node's /diagnostics would say of the answer (issue #45), its
    heading 1-sigma at the dip its alignment measured; with a location only, the model's."""
    log = shared_data / 'lsm303dlhc-altimu10v3' / 'cal_output_2.log'
    status, out, _ = run([log, '--accel-columns', '0,1,2', '--rate', '3', '--json'], capsys)
    summary = json.loads(out)
    told = summary['accuracy']
    assert status == 0 and told['dip_source'] == 'measured'
    assert told['dip_deg'] == pytest.approx(summary['alignment']['dip_deg'])
    # 0.58 % of F across cos(63.9 deg) of it: 0.76 deg
    assert told['heading_sigma_deg'] == pytest.approx(
        math.degrees(math.atan(summary['metrics']['residual_rms_pct'] / 100.0
                               / math.cos(math.radians(told['dip_deg'])))), rel=0.05)
    assert told['status'] == 'high'
    status, out, _ = run([log, '--columns', '3,4,5', *PORTLAND], capsys)
    assert status == 0
    (line,) = [line for line in out.splitlines() if line.startswith('accuracy')]
    assert 'heading sigma' in line and 'deg (model)' in line, line
    status, out, _ = run([log, '--columns', '3,4,5'], capsys)  # neither: a lower bound
    assert 'dip unknown' in out


@pytest.mark.parametrize('rate', [None, 1.0, 3.0, 10.0, 100.0])
def test_a_log_without_time_aligns_whatever_rate_is_guessed(shared_data, capsys, rate):
    """No time column: still readings are found without a clock, so the alignment is the same
    with no --rate and with any --rate from 1 to 100 (at 10 and 100 Hz it used to find no still
    attitude at all and refuse)."""
    log = shared_data / 'lsm303dlhc-altimu10v3' / 'cal_output_2.log'
    rate_option = [] if rate is None else ['--rate', str(rate)]
    status, out, _ = run([log, '--accel-columns', '0,1,2', '--all', '--json', *rate_option],
                         capsys)
    summary = json.loads(out)
    assert status == 0, summary['reason']
    assert summary['time']['stamped'] is False
    assert 'still readings found without a clock' in summary['time']['source']
    alignment = summary['alignment']
    assert alignment['applied'], alignment['reason']
    assert alignment['static_samples'] >= 100
    assert 0.3 < alignment['angle_deg'] < 2.0
    assert alignment['dip_std_deg'] < alignment['dip_std_before_deg']


@pytest.mark.parametrize('name', ['icm_20948_get_cal_data_OUTPUT', 'example_Arduino_output.txt'])
@pytest.mark.parametrize('rate', [None, 1.0, 100.0])
def test_public_hand_taken_logs_name_their_remap_at_any_rate(public_recording, capsys, name,
                                                              rate):
    """ICM-20948 and LSM9DS1 logs of jremington's AHRS projects (accelerometer, then
    magnetometer, no time): their magnetometers' (x, -y, -z) axes are named, whatever --rate."""
    rate_option = [] if rate is None else ['--rate', str(rate)]
    status, out, _ = run([public_recording(name), '--accel-columns', '0,1,2', '--json',
                          *rate_option], capsys)
    alignment = json.loads(out)['alignment']
    assert status == 0
    assert alignment['remap'] == '(x, -y, -z)', alignment['reason']
    assert alignment['static_samples'] >= 100 and not alignment['applied']
    assert alignment['dip_std_deg'] < 3.0 < alignment['dip_std_before_deg']


@pytest.mark.parametrize('rate', [None, 1.0, 100.0])
def test_a_fast_log_without_time_aligns_from_its_holds(tmp_path, capsys, rate):
    """The simulated 100 Hz log with its time column dropped: no --rate, or any, aligns it."""
    timed = tmp_path / 'timed.csv'
    board = simulated_log(timed, mag_misalignment_deg=(1.8, -1.9, 1.4))
    untimed = tmp_path / 'untimed.csv'
    untimed.write_text(''.join(line.split(',', 1)[1] + '\n'
                               for line in timed.read_text().splitlines()))
    rate_option = [] if rate is None else ['--rate', str(rate)]
    status, out, _ = run([untimed, '--accel-columns', 'ax,ay,az', '--units', 'uT', '--json',
                          '--all', *rate_option], capsys)
    summary = json.loads(out)
    assert status == 0, summary['reason']
    assert not summary['time']['stamped']
    rotation = np.reshape(summary['alignment']['rotation'], (3, 3))
    assert summary['alignment']['applied'], summary['alignment']['reason']
    assert rotation_angle_deg(rotation @ board.mag_misalignment.T) < 0.2


def test_rate_is_refused_for_a_log_with_its_own_clock(misaligned_log, capsys):
    path, _ = misaligned_log
    status, _, err = run([path, '--accel-columns', 'ax,ay,az', '--rate', '50'], capsys)
    assert status == 2
    assert '--rate is for logs without time stamps' in err and "column 't' (field 0)" in err


@pytest.mark.parametrize('mode', [[], ['--all']])
def test_a_simulated_misalignment_is_recovered_with_named_columns(misaligned_log, capsys, mode):
    path, board = misaligned_log
    status, out, _ = run([path, '--accel-columns', 'ax,ay,az', '--units', 'uT', *PORTLAND,
                          '--json', *mode], capsys)
    summary = json.loads(out)
    assert status == 0, summary['reason']
    assert summary['input']['layout'].startswith('columns mx,my,mz')
    rotation = np.reshape(summary['alignment']['rotation'], (3, 3))
    assert rotation_angle_deg(rotation @ board.mag_misalignment.T) < 0.2
    assert summary['alignment']['dip_std_deg'] < 0.3
    earth = summary['earth_field']
    assert set(earth) == EARTH_KEYS
    model = earth_field(45.5, -122.7, 0.0, '2026-11-23')
    assert earth['intensity'] == pytest.approx(model.intensity_nt / 1000.0)
    assert earth['radius_ratio'] == pytest.approx(1.0, abs=0.01)
    assert abs(earth['dip_error_deg']) < 0.3
    assert summary['field_strength'] == pytest.approx(model.intensity_nt / 1000.0)


def test_a_disturbed_place_fails_the_gate_or_is_only_reported(tmp_path, capsys):
    path = tmp_path / 'disturbed.csv'
    simulated_log(path, 40.0, latitude=45.5, longitude=-122.7, inclination_offset_deg=8.0)
    argv = [path, '--accel-columns', 'ax,ay,az', '--units', 'uT', *PORTLAND]
    status, out, _ = run(argv + ['-o', tmp_path / 'cal.yaml'], capsys)
    assert status == 1
    assert 'dip 75.' in out and 'steel structure' in out
    assert not (tmp_path / 'cal.yaml').exists()
    status, out, _ = run(argv + ['--no-earth-gate'], capsys)
    assert status == 0 and 'dip +8.' in out


@pytest.mark.parametrize(('argv', 'message'), [
    (['--latitude', '45'], 'give both --latitude and --longitude'),
    (['--date', '2026-01-01'], '--date needs --latitude and --longitude'),
    ([*PORTLAND[:4], '--date', 'today'], 'date must be YYYY-MM-DD'),
    (['--latitude', '95', '--longitude', '0'], 'latitude must be within'),
    (['--accel-columns', '0,1,2', '--columns', '1,2,3'], 'overlap'),
    (['--accel-columns', '0,1'], 'bad --accel-columns'),
    (['--max-alignment', '200', '--accel-columns', '0,1,2'], '--max-alignment must be in'),
])
def test_bad_options_are_usage_errors(shared_data, capsys, argv, message):
    log = shared_data / 'lsm303dlhc-altimu10v3' / 'cal_output_2.log'
    status, _, err = run([log, *argv], capsys)
    assert status == 2
    assert message in err


def test_accel_columns_need_text(tmp_path, capsys, monkeypatch):
    bag = tmp_path / 'bag.mcap'
    bag.write_bytes(b'\x89MCAP0\r\n')
    status, _, err = run([bag, '--accel-columns', '0,1,2'], capsys)
    assert status == 2 and 'applies to text input' in err
    monkeypatch.setattr('sys.stdin', io.StringIO('1,2,3,4,5,6\n' * 5))
    status, _, err = run(['-', '--accel-columns', '0,1,2'], capsys)
    assert status == 2 and 'only 5 usable rows' in err


@pytest.mark.parametrize('mode', [[], ['--all']])
def test_a_ground_robots_turn_is_levelled_by_its_accelerometer(tmp_path, capsys, mode):
    """A robot turning on a wobbly floor, logged with its accelerometer: the planar fit is
    levelled by gravity whether the log streams through the buffer or is fitted whole."""
    path = tmp_path / 'turn.csv'
    board = BoardModel(SimConfig(hard_iron_ut=(55.0, -45.0, 25.0), noise_ut=0.3, motion='yaw',
                                 seed=2))
    lines = ['t,mx,my,mz,ax,ay,az']
    for k in range(4000):
        t = k / 100.0
        field, _ = board.magnetometer(t)
        accel, _, _ = board.inertial(t, 57.0, 57.0)
        lines.append(','.join(f'{v:.5f}' for v in (t, *field, *accel)))
    path.write_text('\n'.join(lines) + '\n')
    status, out, _ = run([path, '--accel-columns', 'ax,ay,az', '--units', 'uT', '--json',
                          *mode], capsys)
    summary = json.loads(out)
    assert status == 0, summary['reason']
    assert summary['model'] == 'planar'
    assert 'levelled by gravity' in summary['reason']

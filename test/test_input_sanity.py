# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Input no calibration can fix (issue #24): a field in the wrong unit is named and not fitted,
a field already normalised or calibrated upstream is said and nothing is adopted that moves it;
the same for an accelerometer in g. In the session (the node's engine) and the CLI."""

from __future__ import annotations

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.input_sanity import (
    accel_unit_problem,
    field_unit_problem,
    normalised_problem,
)
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.nodes.mag_calibrator_parameters import AK09916_FULL_SCALE_T
from mag_calibrator_ros.sim.board import BoardModel, board_readings
from mag_calibrator_ros.sim.config import SimConfig
from mag_calibrator_ros.tools.fit import EXIT_USAGE, main

RATE_HZ = 100.0


def directions(n: int = 50, seed: int = 0) -> np.ndarray:
    rows = np.random.default_rng(seed).normal(size=(n, 3))
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def raw_tumble(seconds: float, seed: int = 0):
    """(mag T, accel m/s^2, gyro) of a tumbled board with hard iron and noise."""
    board = BoardModel(SimConfig(hard_iron_ut=(40.0, -25.0, 10.0), noise_ut=0.3,
                                 motion='tumble', seed=seed))
    return board_readings(board, seconds, RATE_HZ)


@pytest.mark.parametrize(('scale', 'likely'), [
    (0.5, 'gauss'), (48.0, 'µT'), (480.0, 'µT or milligauss'), (1e-9, 'tesla scaled twice')])
def test_magnitudes_that_cannot_be_tesla_name_the_likely_unit(scale, likely):
    problem = field_unit_problem(directions() * scale)
    assert problem is not None and f'looks like {likely}' in problem
    assert 'publish tesla' in problem and 'not calibrating it' in problem


def test_whole_numbers_add_raw_counts_and_earth_fields_pass():
    assert 'raw counts' in field_unit_problem(np.round(directions() * 330.0))
    for field_t in (22e-6, 50e-6, 900e-6, 2e-7):  # with hard iron beside the sensor too
        assert field_unit_problem(directions() * field_t) is None
    assert field_unit_problem(directions(4) * 0.5) is None  # too few to judge


def test_a_normalised_field_is_told_from_raw_and_calibrated_noisy_ones():
    unit = directions(200)
    assert 'already normalised' in normalised_problem(unit * 1e-4)
    rng = np.random.default_rng(1)
    noisy = unit * 50e-6 + rng.normal(0.0, 0.3e-6, unit.shape)  # calibrated by a fit: noise
    assert normalised_problem(noisy) is None
    assert normalised_problem(unit * 50e-6 + (20e-6, 0.0, 0.0)) is None  # raw: hard iron
    still = np.tile((1e-4, 0.0, 0.0), (200, 1))
    assert normalised_problem(still) is None  # one direction says nothing


@pytest.mark.parametrize(('force', 'likely'), [
    (1.0, 'g (multiply'), (1000.0, 'milli-g'), (16384.0, 'raw counts')])
def test_an_accelerometer_not_in_metres_per_second_squared_is_named(force, likely):
    problem = accel_unit_problem(directions() * force)
    assert problem is not None and f'looks like {likely}' in problem
    assert accel_unit_problem(directions() * 9.81) is None


def stream(session: CalibrationSession, mag, accel=None, gyro=None) -> list:
    """Feed rows one message at a time; every event with the stream second it came at."""
    said = []
    for index, row in enumerate(mag):
        stamp = round(index * 1e9 / RATE_HZ)
        if accel is not None:
            session.process_imu(stamp, 'imu_link', accel[index], gyro[index])
        session.process(stamp, 'imu_link', row)
        said += [(index / RATE_HZ, event) for event in session.take_events()]
    return said


@pytest.mark.parametrize('factor', [1e4, 1e6])  # gauss, µT published in a tesla field
def test_a_wrong_unit_is_said_within_a_second_and_never_fitted(factor):
    mag, _, _ = raw_tumble(12.0)
    session = CalibrationSession(SessionSettings(full_scale=AK09916_FULL_SCALE_T))  # the node's
    said = stream(session, mag * factor)
    warnings = [(t, e.message) for t, e in said if 'cannot be tesla' in e.message]
    assert len(warnings) == 1 and warnings[0][0] < 1.0
    report = session.report(12.0, measure_coverage=True)
    assert session.calibration is None and not report.counts.fits.get('calibrate')
    values = report.values
    assert 'cannot be tesla' in values['input_problem']
    assert report.level == 'WARN' and 'cannot be tesla' in report.message
    assert 'cannot be tesla' in report.progress
    ticket = session.request_calibration()
    answer = next(e for e in session.take_events() if e.ticket == ticket)
    assert not answer.attempt.success and 'cannot be tesla' in answer.attempt.message


def test_a_normalised_field_is_said_within_ten_seconds_and_nothing_moves_it():
    mag, _, _ = raw_tumble(30.0)
    normalised = mag / np.linalg.norm(mag, axis=1, keepdims=True) * 1e-4
    session = CalibrationSession()
    said = stream(session, normalised)
    warnings = [t for t, e in said if 'already normalised' in e.message]
    assert len(warnings) == 1 and warnings[0] < 10.0
    calibration = session.calibration
    if calibration is not None:  # nothing adopted that moves a reading by more than 1 % of |B|
        moved = np.linalg.norm(calibration.apply(normalised) - normalised, axis=1)
        assert np.max(moved) <= 0.01 * 1e-4
    assert 'already normalised' in session.report(30.0).values['input_problem']


def test_the_normalised_verdict_survives_a_still_spell():
    mag, _, _ = raw_tumble(8.0)
    normalised = mag / np.linalg.norm(mag, axis=1, keepdims=True) * 1e-4
    still = np.tile(normalised[-1], (500, 1))
    session = CalibrationSession()
    stream(session, np.concatenate([normalised, still]))
    assert 'already normalised' in session.report().input_problem


def test_an_accelerometer_in_g_is_said_once():
    mag, accel, gyro = raw_tumble(3.0)
    session = CalibrationSession()
    said = stream(session, mag, accel / 9.80665, gyro)
    warnings = [(t, e.message) for t, e in said if 'accelerometer cannot be m/s^2' in e.message]
    assert len(warnings) == 1 and warnings[0][0] < 1.0 and 'looks like g' in warnings[0][1]
    report = session.report(3.0)
    assert report.level == 'WARN' and 'accelerometer cannot be m/s^2' in report.message


def test_a_recording_in_its_own_unit_is_not_judged_as_tesla():
    mag, _, _ = raw_tumble(3.0)
    session = CalibrationSession(SessionSettings(), metadata={'units': 'uT'})
    said = stream(session, mag * 1e6)
    assert not [e for _, e in said if 'cannot be' in e.message]


# --- mag_calibrator_fit ---------------------------------------------------------------------


def write(path, rows):
    np.savetxt(path, rows, fmt='%.9g', delimiter=',')
    return str(path)


def test_the_cli_refuses_a_unit_the_numbers_cannot_be_in(tmp_path, capsys):
    mag, _, _ = raw_tumble(10.0)
    path = write(tmp_path / 'gauss.csv', mag * 1e4)
    assert main([path, '--units', 'T', '-o', str(tmp_path / 'c.yaml')]) == EXIT_USAGE
    error = capsys.readouterr().err
    assert 'cannot be tesla' in error and 'looks like gauss' in error and '--units' in error
    assert not (tmp_path / 'c.yaml').exists()
    assert main([path, '--units', 'G', '--json']) in (0, 1)  # the right unit fits


def test_the_cli_refuses_a_normalised_recording(tmp_path, capsys):
    mag, _, _ = raw_tumble(10.0)
    path = write(tmp_path / 'normalised.csv', mag / np.linalg.norm(mag, axis=1, keepdims=True))
    for extra in ([], ['--all']):
        assert main([path, *extra]) == EXIT_USAGE
        assert 'already normalised or calibrated upstream' in capsys.readouterr().err


def test_a_hard_iron_within_the_full_scale_is_tesla_live_and_offline(tmp_path, capsys):
    """Issue #47 item 6: a hard iron of 1-4.9 mT, within the AK09916's 4.9 mT, was called a
    wrong unit for good (the bound was 1 mT). Up to the full scale it is a field; beyond it,
    and gauss or µT published as tesla, still a wrong unit."""
    board = BoardModel(SimConfig(hard_iron_ut=(2000.0, 500.0, -300.0), noise_ut=0.3,
                                 motion='tumble', seed=2))
    mag, _, _ = board_readings(board, 20.0, RATE_HZ)
    session = CalibrationSession(SessionSettings(full_scale=AK09916_FULL_SCALE_T))
    said = stream(session, mag)
    assert not [e for _, e in said if 'cannot be tesla' in e.message]
    assert session.calibration is not None, session.report(20.0, measure_coverage=True).progress
    np.testing.assert_allclose(session.calibration.offset, [2e-3, 0.5e-3, -0.3e-3], atol=5e-6)
    assert field_unit_problem(mag, full_scale_t=AK09916_FULL_SCALE_T) is None
    assert field_unit_problem(mag) is not None  # no full scale known: 1 mT
    assert 'looks like µT' in field_unit_problem(mag * 1e6 / 40, full_scale_t=4.9e-3)
    path = write(tmp_path / 'iron.csv', mag * 1e6)
    assert main([path, '--units', 'uT', '--full-scale', '4900', '--json']) in (0, 1)
    assert 'cannot be' not in capsys.readouterr().err
    assert main([path, '--units', 'uT']) == EXIT_USAGE  # no full scale known: how to give it
    error = capsys.readouterr().err
    assert "give the magnetometer's full scale (full_scale, --full-scale)" in error

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Planar fits levelled by gravity (levelled.py): a ground robot that tilts while it turns, with
its accelerometer paired, gets its heading right; anything that is no ground turn is left to
the plain fit."""

from __future__ import annotations

from dataclasses import replace
import math
from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.ellipsoid import fit_ellipsoid
from mag_calibrator_ros.calibration.fit.fitting import FitOptions, fit_calibration
from mag_calibrator_ros.calibration.fit.levelled import level_planar
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.calibration.live.offline import feed
from mag_calibrator_ros.calibration.live.report import calibration_summary
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.sim import motion

sys.path.insert(0, str(Path(__file__).parent))
from test_ground_session import heading_error_deg  # noqa: E402
from test_heading import FIELD_UT, HARD_IRON_UT, RATE_HZ, SOFT_IRON, turning_imu  # noqa: E402

UT = 1e-6
G = 9.80665


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_gravity_levels_a_wobbling_turn_that_the_plain_fit_gets_wrong(seed):
    raw, _, up, _ = turning_imu(40.0, seed=seed, wobble_deg=2.0)
    raw = raw * UT
    plain = fit_calibration(raw, FitOptions(model='planar'))
    levelled = fit_calibration(raw, FitOptions(model='planar'), ups=up)
    assert plain.success and levelled.success
    assert 'levelled by gravity' in levelled.reason and 'levelled' not in plain.reason
    assert heading_error_deg(plain.calibration) > 1.0  # the wobble, taken for soft iron
    assert heading_error_deg(levelled.calibration) < 0.3  # another floor than it saw
    assert 'dip' in levelled.reason  # the tilts determine the vertical component
    assert levelled.calibration.metadata['levelled_by_gravity'] is True
    assert abs(levelled.calibration.metadata['levelled_dip_deg'] - 60.0) < 3.0
    assert 'offset_normal' not in levelled.calibration.metadata['unobserved']


def test_a_level_turn_is_levelled_too_but_its_vertical_stays_unobserved():
    raw, _, up, _ = turning_imu(40.0, wobble_deg=0.0)
    raw = raw * UT
    plain = fit_calibration(raw, FitOptions(model='planar'))
    levelled = fit_calibration(raw, FitOptions(model='planar'), ups=up)
    # The 2-D fit leaves the ring in the raw plane, which soft iron tilts off the yaw axis.
    assert heading_error_deg(plain.calibration, wobble_deg=0.0) > 0.2
    assert heading_error_deg(levelled.calibration, wobble_deg=0.0) < 0.1
    assert 'offset_normal' in levelled.calibration.metadata['unobserved']


@pytest.mark.parametrize('std', [1e-3, 'own', 1e3, math.nan, -0.1, 'wide', None])
@pytest.mark.parametrize('field_strength', [None, 1.0])
def test_a_refinement_weighs_in_what_the_calibration_in_force_knew(std, field_strength):
    """``known``: its offset along the turning axis is a prior of its own 1-sigma (metadata
    ``levelled_offset_normal_std``, a share of the field it read, whatever F it was scaled to):
    a tight one holds the refit there, one as sure as the readings meets them halfway, a loose
    one leaves the readings to decide, and one that is no number is no prior."""
    raw, _, up, _ = turning_imu(40.0, seed=0, wobble_deg=2.0)
    options = FitOptions(model='planar', field_strength=field_strength)
    free = fit_calibration(raw * UT, options, ups=up)
    own_std = free.calibration.metadata['levelled_offset_normal_std']
    assert 0.0 < own_std < 0.1  # determined by these tilts
    normal = np.array(free.calibration.metadata['plane_normal'])
    known = replace(free.calibration, offset=free.calibration.offset + 30.0 * UT * normal)
    known = known.with_metadata(levelled_offset_normal_std=own_std if std == 'own' else std)
    weighed = fit_calibration(raw * UT, options, ups=up, known=known)
    moved = float(normal @ (weighed.calibration.offset - free.calibration.offset)) / UT
    said = 'weighed with the calibration in force' in weighed.reason
    if std == 1e-3:  # 0.05 uT: the readings cannot move it
        assert 29.0 < moved < 30.5 and said
    elif std == 'own':  # as sure as the readings: halfway
        assert 12.0 < moved < 18.0 and said
    elif std == 1e3:
        assert abs(moved) < 0.1 and not said
    else:
        assert np.array_equal(weighed.calibration.offset, free.calibration.offset)
        assert not said
    assert weighed.calibration.metadata['levelled_offset_normal_std'] == own_std  # the data's


@pytest.mark.parametrize('wobble_deg', [0.0, 0.5, 2.0])
def test_the_summary_says_how_far_the_tilts_told_the_offset_along_the_axis(wobble_deg):
    """A level floor holds it, small tilts tell it roughly (and how roughly is said), larger
    ones determine it with the dip; the scale along the axis is held throughout."""
    raw, _, up, _ = turning_imu(40.0, seed=0, wobble_deg=wobble_deg)
    summary = calibration_summary(
        fit_calibration(raw * UT, FitOptions(model='planar'), ups=up).calibration)
    held = 'held (not fitted): '
    if wobble_deg == 0.0:
        assert held + 'the offset along the turning axis and the scale along it' in summary
    elif wobble_deg == 0.5:
        assert held + "the scale along the turning axis; the offset along it told by the " \
            "floor's tilts only to ±" in summary
    else:
        assert 'dip' in summary and summary.endswith(held + 'the scale along the turning axis')


def test_a_level_floor_refit_keeps_what_the_calibration_in_force_knew():
    """A refit on a level floor cannot tell the offset along the turning axis: it keeps the
    calibration in force's and its 1-sigma, not the plain fit's guess."""
    tilted, _, tilted_up, _ = turning_imu(40.0, seed=0, wobble_deg=2.0)
    level, _, level_up, _ = turning_imu(40.0, seed=1, wobble_deg=0.0)
    known = fit_calibration(tilted * UT, FitOptions(model='planar'), ups=tilted_up).calibration
    own_std = known.metadata['levelled_offset_normal_std']
    alone = fit_calibration(level * UT, FitOptions(model='planar'), ups=level_up)
    kept = fit_calibration(level * UT, FitOptions(model='planar'), ups=level_up, known=known)
    normal = np.array(kept.calibration.metadata['plane_normal'])
    assert 'levelled_offset_normal_std' not in alone.calibration.metadata
    assert abs(float(normal @ (alone.calibration.offset - known.offset))) > 10.0 * UT
    assert abs(float(normal @ (kept.calibration.offset - known.offset))) < 0.01 * UT
    assert "kept at the calibration in force's" in kept.reason
    assert kept.calibration.metadata['levelled_offset_normal_std'] == pytest.approx(own_std,
                                                                                   rel=0.05)


def test_a_level_first_turn_knows_nothing_and_a_wobbly_refinement_frees_it():
    """A first calibration from a level turn holds the offset along the turning axis where the
    plain fit put it (no tilts, no 1-sigma): a later refinement on a wobbly floor must fit it,
    not keep it (a hard hold kept such a guess 40 uT off)."""
    level, _, level_up, _ = turning_imu(30.0, seed=0, wobble_deg=0.0)
    tilted, _, tilted_up, _ = turning_imu(60.0, seed=1, wobble_deg=0.5)
    raw, up = np.vstack([level, tilted]) * UT, np.vstack([level_up, tilted_up])
    session = CalibrationSession()
    in_force = []
    for index, (reading, direction) in enumerate(zip(raw.tolist(), up.tolist(), strict=True)):
        stamp = round(index * 1e9 / RATE_HZ)
        session.process_imu(stamp, 'imu_link', [G * value for value in direction], None)
        session.process(stamp, 'imu_link', reading)
        session.poll()
        if session.calibration is not None and (not in_force
                                                or session.calibration is not in_force[-1]):
            in_force.append(session.calibration)
    session.close()
    adoptions = session.report().counts.adoptions
    assert len(in_force) >= 2 and adoptions.get('refine', 0) == len(in_force) - 1
    first, refined = in_force[0], in_force[1]
    assert 'levelled_offset_normal_std' not in first.metadata  # held, not fitted
    assert abs(first.offset[2] / UT - HARD_IRON_UT[2]) > 20.0  # the plain fit's guess
    assert abs(refined.offset[2] / UT - HARD_IRON_UT[2]) < 10.0  # the first refinement frees it
    assert refined.metadata['levelled_offset_normal_std'] > 0.0
    assert heading_error_deg(in_force[-1], wobble_deg=0.5) < 0.15


def dwelling_turns(seed: int, noise_ut: float) -> tuple[np.ndarray, np.ndarray]:
    """(raw uT, gravity's unit direction) of a robot turning in place a little over a circle
    on a 2° wobbly floor, then standing 15 s, turning a half circle and standing 14 s."""
    trajectory = motion.CmdVelTrajectory(seed=seed, wobble_deg=2.0)
    earth = motion.earth_field(FIELD_UT, 60.0)
    rng = np.random.default_rng(seed)
    raw, up = [], []
    start = 0.0
    for duration, rate in ((14.0, 0.5), (15.0, 0.0), (4.0, 0.8), (14.0, 0.0)):
        for t in np.arange(start, start + duration, 1.0 / RATE_HZ):
            trajectory.command(rate, float(t))
            rotation = trajectory.state(float(t)).rotation
            raw.append(SOFT_IRON @ rotation.T @ earth + HARD_IRON_UT
                       + rng.normal(0.0, noise_ut, 3))
            up.append(rotation.T @ np.array([0.0, 0.0, 1.0]))
        start += duration
    return np.array(raw), np.array(up)


def test_noise_at_the_headings_a_robot_stands_at_does_not_turn_its_heading():
    """Unscaled residuals let the noise pull the weakly seen offset along the normal by about
    the noise squared, most where the readings dwell (two long stops): tens of µT, 1.3° and
    1.9° of heading on two of these eight floors, until each residual was taken over its noise
    gain (levelled.py ``_Model._residuals``)."""
    errors = []
    for seed in range(8):
        raw, up = dwelling_turns(seed, noise_ut=0.6)  # twice the simulated chip's default
        result = fit_calibration(raw * UT, FitOptions(model='planar'), ups=up)
        assert result.success and 'levelled by gravity' in result.reason, result.reason
        errors.append(heading_error_deg(result.calibration))
    assert np.mean(errors) < 0.3 and max(errors) < 1.0, errors


def test_gravity_off_the_turn_axis_is_no_ground_turn():
    raw, _, up, _ = turning_imu(40.0)
    sideways = np.roll(up, 1, axis=1)  # gravity along chip x: the turn is about another axis
    plain = fit_ellipsoid(raw, 'planar')
    levelling = level_planar(raw, sideways, plain)
    assert levelling.offset is None and 'off the turn axis' in levelling.note
    result = fit_calibration(raw, FitOptions(model='planar'), ups=sideways)
    assert 'levelled' not in result.reason


@pytest.mark.parametrize('case', ['nan', 'zeros', 'few', 'shape', 'text'])
def test_unusable_gravity_leaves_the_plain_fit(case):
    raw, _, up, _ = turning_imu(40.0)
    ups = up.copy()
    if case == 'nan':
        ups[:] = np.nan
    elif case == 'zeros':
        ups[:] = 0.0
    elif case == 'few':
        ups[len(ups) // 2:] = np.nan
    elif case == 'shape':
        ups = ups[:10]
    else:
        ups = 'garbage'
    plain = fit_calibration(raw, FitOptions(model='planar'))
    result = fit_calibration(raw, FitOptions(model='planar'), ups=ups)
    assert result.success and 'levelled' not in result.reason
    np.testing.assert_allclose(result.calibration.matrix, plain.calibration.matrix)


def test_a_tumble_is_never_levelled():
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(600, 3))
    raw = 50.0 * directions / np.linalg.norm(directions, axis=1)[:, None] + (10.0, -5.0, 3.0)
    ups = np.tile([0.0, 0.0, 1.0], (600, 1))
    result = fit_calibration(raw, FitOptions(), ups=ups)
    assert result.success and result.calibration.model != 'planar'
    assert 'levelled' not in result.reason


def test_the_buffer_carries_gravity_with_its_samples_and_paired_readings():
    buffer = SampleBuffer(capacity=20, k=3)
    raw, _, up, _ = turning_imu(30.0)
    for index, (reading, direction) in enumerate(zip(raw, up, strict=True)):
        buffer.add(reading, None if index % 2 else tuple(direction))
    ups = buffer.ups
    assert ups.shape == (buffer.fill, 3)
    paired = np.all(np.isfinite(ups), axis=1)
    assert 0 < paired.sum() < buffer.fill == 20 and buffer.paired == int(paired.sum())
    np.testing.assert_allclose(np.linalg.norm(ups[paired], axis=1), 1.0)
    readings, directions = buffer.paired_readings
    assert len(readings) == len(directions) > 100 and len(buffer.readings) > 100
    for reading, direction in zip(readings, directions, strict=True):
        index = int(np.flatnonzero(np.all(raw == reading, axis=1))[0])
        assert index % 2 == 0  # only readings that came with gravity
        np.testing.assert_allclose(direction, up[index])
    buffer.clear()
    assert len(buffer.paired_readings[0]) == 0


def test_the_live_session_levels_a_wobbling_robot_with_its_accelerometer():
    raw, _, up, _ = turning_imu(45.0, seed=1)
    results = {}
    for accel in (None, up * G):
        session = CalibrationSession()
        feed(session, raw * UT, RATE_HZ, frame_id='imu_link', accel=accel)
        assert session.calibration is not None and session.calibration.model == 'planar'
        results['imu' if accel is not None else 'mag'] = heading_error_deg(session.calibration)
        summary = calibration_summary(session.calibration)
        assert ('levelled by gravity' in summary) == (accel is not None), summary
    assert results['mag'] > 1.0
    assert results['imu'] < 0.5


def _coning(tilt_deg: float, seconds: float = 10.0, seed: int = 0):
    """(mag T, accel m/s^2, gyro rad/s) at RATE_HZ of a board turning about an axis tilted
    ``tilt_deg`` from the vertical, once in 8 s: its readings lie on one plane, but gravity
    turns about that axis in the chip frame (the board tilts by ``tilt_deg`` all along)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    axis = np.array([math.sin(math.radians(tilt_deg)), 0.0, math.cos(math.radians(tilt_deg))])
    turned = np.arange(0.0, seconds, 1.0 / RATE_HZ) * 2.0 * math.pi / 8.0
    attitudes = Rotation.from_rotvec(np.outer(turned, axis)).as_matrix()
    earth = np.array([0.0, 19.0, -45.0]) * UT
    mag = (np.einsum('nji,j->ni', attitudes, earth) + np.array(HARD_IRON_UT) * UT
           + rng.normal(0.0, 0.3 * UT, (len(turned), 3)))
    accel = (np.einsum('nji,j->ni', attitudes, np.array([0.0, 0.0, G]))
             + rng.normal(0.0, 0.02, (len(turned), 3)))
    return mag, accel, np.tile(axis * 2.0 * math.pi / 8.0, (len(turned), 1))


@pytest.mark.parametrize(('tilt_deg', 'adopted'), [(0.0, True), (20.0, False), (45.0, False)])
def test_readings_on_one_plane_while_gravity_says_the_board_tilts_are_no_planar_calibration(
        tilt_deg, adopted):
    """~/calibrate in a tumble's first seconds, turning about one axis, adopted a planar model
    (6.4 deg of direction error, saved) although gravity said the board tilted all along (issue
    #46). With gravity paired, auto takes planar only for a board that stayed level."""
    from mag_calibrator_ros.calibration.live.offline import calibrate_now
    from mag_calibrator_ros.calibration.live.settings import SessionSettings

    mag, accel, gyro = _coning(tilt_deg)
    session = CalibrationSession(SessionSettings(auto_calibrate=False))
    feed(session, mag, RATE_HZ, frame_id='imu', accel=accel, gyro=gyro)
    attempt = calibrate_now(session)
    assert attempt.success == adopted, attempt.message
    if adopted:
        assert session.calibration.model == 'planar'
    else:
        assert session.calibration is None
        assert 'the samples lie near one plane, but gravity says the sensor tilted by' in (
            attempt.message)
    session.close()

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""CalibrationSession refining, noticing a calibration that does not fit, and tracking online
(test_session.py's sections of those names, a file of their own so that pytest-xdist's
--dist loadfile runs them beside the rest)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import sys

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.evidence import magnitude_residual_pct
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings
from mag_calibrator_ros.calibration.live.verdicts import bounded_step, coverage_kept

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_session import (  # noqa: E402
    EXACT,
    FIELD_T,
    HARD_IRON_T,
    RATE_HZ,
    SOFT_IRON,
    TRACKING,
    counts_of,
    direction_error_deg,
    distorted,
    messages,
    other_robots_calibration,
    stream,
    truth_of,
)

# -- refinement -----------------------------------------------------------------------------------


def test_refinement_replaces_a_calibration_that_is_measurably_off():
    """A first calibration off by 4 % of the field (from part of the sphere, or an old file):
    the node keeps collecting and adopts a later fit once it is better on held-out readings."""
    rough = Calibration(HARD_IRON_T + [2e-6, -0.5e-6, 0.5e-6], 1.02 * EXACT.matrix, FIELD_T,
                        'full', {'residual_rms_pct': 1.5, 'coverage': 0.5})
    session = CalibrationSession(calibration=rough)
    events = stream(session, distorted('tumble', 3000, seed=40))
    refined = [m for m in messages(events, adopted=True) if m.startswith('refined: residual')]
    assert refined, messages(events)
    assert '->' in refined[0] and 'coverage 50 % ->' in refined[0]
    assert counts_of(session).adoptions['refine'] >= 1
    assert session.calibration.metadata['coverage'] >= 0.5
    assert direction_error_deg(session.calibration) < 0.2 < 0.2 * direction_error_deg(rough)


def test_a_good_calibration_is_kept_and_converges():
    session = CalibrationSession(calibration=EXACT)
    events = stream(session, distorted('tumble', 15000, seed=41))
    assert session.calibration is EXACT, messages(events, adopted=True)
    report = session.report()
    assert report.counts.fits['refine'] >= 3
    assert report.state == 'calibrated-converged'
    assert not messages(events, level='warning')


def test_refinement_off_keeps_the_first_calibration():
    session = CalibrationSession(SessionSettings(refine=False))
    stream(session, distorted('tumble', 6000, seed=42))
    report = session.report()
    assert report.counts.adoptions == {'auto': 1} and 'refine' not in report.counts.fits
    assert report.state == 'calibrated'


def test_a_planar_calibration_never_replaces_a_3d_one():
    planar = replace(EXACT, model='planar')
    assert not coverage_kept(EXACT, planar)
    assert coverage_kept(planar, EXACT)  # 3-D after planar: an upgrade
    assert coverage_kept(EXACT, EXACT.with_metadata(coverage=0.95))
    assert not coverage_kept(EXACT, EXACT.with_metadata(coverage=0.85))


# -- a calibration that does not fit --------------------------------------------------------------


def test_another_robots_file_is_noticed_and_replaced():
    session = CalibrationSession(calibration=other_robots_calibration())
    raw = distorted('tumble', 3000, seed=43)
    warned = recalibrated = None
    for second in range(60):
        chunk = raw[second * int(RATE_HZ):(second + 1) * int(RATE_HZ)]
        events = stream(session, chunk, start_s=float(second))
        if warned is None and messages(events, level='warning'):
            warned = second + 1
            text = messages(events, level='warning')[0]
        if recalibrated is None and any('recalibrated' in m for m in messages(events)):
            recalibrated = second + 1
    assert warned is not None and recalibrated is not None
    assert 'does not fit the live data' in text and 'uT vs 50.00 uT expected' in text
    assert warned <= 10 and recalibrated <= 30  # stream seconds (the targets)
    assert direction_error_deg(session.calibration) < 0.5
    state = session.report().state
    assert state.startswith('calibrated-') and state != 'calibrated-misfit'


def test_without_auto_calibrate_a_misfit_is_reported_and_nothing_changes():
    wrong = other_robots_calibration()
    session = CalibrationSession(SessionSettings(auto_calibrate=False), calibration=wrong)
    events = stream(session, distorted('tumble', 1500, seed=44))
    (warning,) = [m for m in messages(events, level='warning') if 'does not fit' in m]
    assert 'call ~/reset then ~/calibrate' in warning
    report = session.report()
    assert session.calibration is wrong and report.state == 'calibrated-misfit'
    assert 'does not fit' in report.misfit


def magnet_pass(raw, start, length, strength_t):
    """A magnet passing: an extra field that rises and falls over ``length`` readings."""
    out = raw.copy()
    bump = np.sin(np.linspace(0.0, np.pi, length)) ** 2
    out[start:start + length] += bump[:, None] * strength_t * np.array([0.6, 0.0, 0.8])
    return out


@pytest.mark.parametrize('motion_kind', ['tumble', 'still'])
def test_a_passing_magnet_is_not_a_misfit(motion_kind):
    session = CalibrationSession(calibration=EXACT)
    raw = distorted(motion_kind, 2000, seed=45)
    disturbed = magnet_pass(raw, 500, 2 * int(RATE_HZ), 40e-6)  # 2 s, up to 0.8 F
    events = stream(session, disturbed)
    assert not [m for m in messages(events) if 'does not fit' in m]
    assert session.calibration is EXACT


# -- online tracking ------------------------------------------------------------------------------

def test_bounded_step_limits_offset_and_matrix_change():
    current = Calibration(np.zeros(3), np.eye(3), FIELD_T, 'full')
    target = Calibration(np.array([10e-6, 0.0, 0.0]), 1.2 * np.eye(3), FIELD_T, 'full')
    step = bounded_step(current, target, 0.01)
    assert np.linalg.norm(step.offset - current.offset) <= 0.01 * FIELD_T * (1 + 1e-9)
    assert np.linalg.norm(step.matrix - current.matrix) <= 0.01 * (1 + 1e-9)
    assert step.offset[0] > 0.0  # moved towards the target
    close = Calibration(np.array([1e-9, 0.0, 0.0]), np.eye(3), FIELD_T, 'full')
    np.testing.assert_allclose(bounded_step(current, close, 0.01).offset, close.offset)


@pytest.mark.parametrize('drift_t', [3e-6, 8e-6])
def test_online_tracking_follows_drift_in_bounded_steps(drift_t):
    """8 uT is 16 % of the field: coverage judged through the drifted calibration used to read
    0 % for a complete sphere, so tracking could never recover from it."""
    drifted = Calibration(HARD_IRON_T + np.array([drift_t, -0.5 * drift_t, 0.0]), EXACT.matrix,
                          FIELD_T, 'full')
    session = CalibrationSession(TRACKING, calibration=drifted)
    assert session.report().tracking
    samples = distorted('tumble', 6000, seed=4)
    offsets = []
    for second in range(120):
        stream(session, samples[second * 50:(second + 1) * 50], start_s=float(second))
        offsets.append(session.calibration.offset.copy())
    steps = np.linalg.norm(np.diff(offsets, axis=0), axis=1)
    assert steps.max() <= 2 * 0.02 * FIELD_T * (1 + 1e-6)  # at most two checks per second
    assert counts_of(session).tracked_updates > 0
    before = magnitude_residual_pct(drifted, samples[-500:])
    after = magnitude_residual_pct(session.calibration, samples[-500:])
    assert after < 0.5 * before


def test_online_tracking_leaves_a_good_calibration_alone():
    session = CalibrationSession(TRACKING, calibration=EXACT)
    stream(session, distorted('tumble', 3000, seed=46))
    assert np.linalg.norm(session.calibration.offset - EXACT.offset) < 0.5e-6


def test_online_tracking_ignores_a_still_sensor_next_to_a_disturbance():
    """Five minutes standing still in a field 4 % off the calibration's: the readings all point
    one way, so they say nothing about the calibration and must not move it."""
    session = CalibrationSession(TRACKING, calibration=EXACT)
    still = truth_of('still', 1, 1)[0] * 1.04
    readings = SOFT_IRON @ still + HARD_IRON_T + np.random.default_rng(0).normal(
        0.0, 0.3e-6, (300 * 50, 3))
    stream(session, readings)
    assert counts_of(session).tracked_updates == 0
    np.testing.assert_array_equal(session.calibration.offset, EXACT.offset)

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Heading coverage of yaw-only motion: the ring found without a calibration, the sectors it
covers, and hints that speak of turning (which way, how far), never of rolling a ground robot."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mag_calibrator_ros.calibration.fit.coverage import HEADING_SECTORS
from mag_calibrator_ros.calibration.fit.heading import (
    COMPLETE_HEADING_COVERAGE,
    TURN_HINT_START,
    TURN_STILL_HINT,
    fit_ring,
    heading_coverage_of,
    turn_hint,
    turn_needed,
    turning_direction,
    yaw_only,
)
from mag_calibrator_ros.calibration.live.buffer import SampleBuffer
from mag_calibrator_ros.sim import motion

FIELD_UT = 50.0
HARD_IRON_UT = np.array([55.0, -45.0, 25.0])  # about 3x the horizontal field at 60 deg
SOFT_IRON = np.array([[1.15, 0.10, -0.08], [0.10, 0.85, 0.12], [-0.08, 0.12, 1.00]])
RATE_HZ = 50.0
ROTATION_WORDS = ('roll', 'pitch', 'rotating about')


def turning(seconds: float, rate: float = 0.3, seed: int = 0, wobble_deg: float = 2.0,
            noise_ut: float = 0.3, start_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(raw readings uT, true yaw rad) of a cmd_vel robot turning at ``rate`` from ``start_s``."""
    raw, _, _, yaw = turning_imu(seconds, rate, seed, wobble_deg, noise_ut, start_s)
    return raw, yaw


def turning_imu(seconds: float, rate: float = 0.3, seed: int = 0, wobble_deg: float = 2.0,
                noise_ut: float = 0.3, start_s: float = 0.0, inclination_deg: float = 60.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(raw uT, true field in the chip frame uT, gravity's unit direction up in the chip frame,
    true yaw) of the same robot."""
    trajectory = motion.CmdVelTrajectory(seed=seed, wobble_deg=wobble_deg,
                                         max_acceleration=0.5)
    earth = motion.earth_field(FIELD_UT, inclination_deg)
    rng = np.random.default_rng(seed)
    raw, truth, up, yaw = [], [], [], []
    for t in np.arange(0.0, seconds, 1.0 / RATE_HZ):
        if t >= start_s:
            trajectory.command(rate, float(t))
        rotation = trajectory.state(float(t)).rotation
        body = rotation.T @ earth
        truth.append(body)
        up.append(rotation.T @ np.array([0.0, 0.0, 1.0]))
        raw.append(SOFT_IRON @ body + HARD_IRON_UT + rng.normal(0.0, noise_ut, 3))
        yaw.append(trajectory.yaw_and_rate(float(t))[0])
    return np.array(raw), np.array(truth), np.array(up), np.array(yaw)


def buffered(raw: np.ndarray) -> SampleBuffer:
    buffer = SampleBuffer()
    buffer.add_many(raw)
    return buffer


def test_turning_is_yaw_only_from_the_first_quarter_turn_and_tumbling_is_not():
    raw, _ = turning(40.0)
    assert not yaw_only(raw[:int(0.5 * RATE_HZ)])  # standing (a few noise steps)
    assert yaw_only(buffered(raw[:int(6 * RATE_HZ)]).samples)  # about 70 deg of arc
    assert yaw_only(buffered(raw).samples)
    tumble = motion.body_field_samples('tumble', 1500, RATE_HZ, FIELD_UT, 60.0, seed=1)
    assert not yaw_only(buffered(tumble @ SOFT_IRON.T + HARD_IRON_UT).samples)
    assert not yaw_only(np.full((50, 3), np.nan))


@pytest.mark.parametrize('arc_deg', [8.0, 12.0, 16.0])
def test_the_first_degrees_of_a_turn_are_yaw_only(arc_deg):
    """A short arc whose sagitta is still within the noise (its two smaller spreads both
    noise-wide) is yaw-only: nothing yet says the motion is not a turn, so hints speak of
    turning; a tumbling hand leaves the arc within seconds."""
    rng = np.random.default_rng(int(arc_deg))
    angles = np.radians(np.linspace(0.0, arc_deg, 100))
    horizontal = FIELD_UT * math.cos(math.radians(60.0))
    vertical = FIELD_UT * math.sin(math.radians(60.0))
    body = np.column_stack([horizontal * np.cos(angles), horizontal * np.sin(angles),
                            np.full_like(angles, vertical)])
    arc = body @ SOFT_IRON.T + HARD_IRON_UT + rng.normal(0.0, 0.3, body.shape)
    assert yaw_only(arc)
    still = HARD_IRON_UT + rng.normal(0.0, 0.3, (100, 3))
    assert not yaw_only(still)  # a noise blob is no arc
    tumble = motion.body_field_samples('tumble', 1500, RATE_HZ, FIELD_UT, 60.0, seed=2)
    assert not yaw_only(buffered(tumble @ SOFT_IRON.T + HARD_IRON_UT).samples)


def test_a_full_turn_completes_the_heading_circle_half_a_turn_half_of_it():
    raw, yaw = turning(40.0)
    full = buffered(raw)
    progress = heading_coverage_of(full.samples, full.readings, raw[-1])
    assert progress.complete and progress.coverage.hint == ''
    assert progress.coverage.cells == HEADING_SECTORS
    half = np.flatnonzero(yaw - yaw[0] <= math.pi)[-1]
    partial = buffered(raw[:half])
    coverage = heading_coverage_of(partial.samples, partial.readings, raw[half - 1]).coverage
    assert 0.4 <= coverage.fraction <= 0.65
    assert not coverage.fraction >= COMPLETE_HEADING_COVERAGE


def test_ring_headings_follow_the_true_heading_despite_hard_and_soft_iron():
    raw, yaw = turning(40.0, wobble_deg=0.0, noise_ut=0.0)
    buffer = buffered(raw)
    ring, problem = fit_ring(buffer.samples, buffer.readings)
    assert ring is not None and problem == ''
    # the field turns against the robot: heading differences mirror the yaw's
    measured = np.unwrap(ring.headings(raw))
    difference = (measured - measured[0]) + (yaw - yaw[0])
    assert np.max(np.abs(np.degrees(difference))) < 12.0  # a quick fit, not the calibration


def test_a_still_robot_or_a_disturbed_field_outlines_no_ring():
    still = np.array([30.0, -20.0, -40.0]) + np.random.default_rng(2).normal(0, 0.3, (400, 3))
    buffer = buffered(still)
    ring, problem = fit_ring(buffer.samples, buffer.readings)
    assert ring is None and problem == TURN_STILL_HINT
    progress = heading_coverage_of(buffer.samples, buffer.readings, still[-1])
    assert progress.coverage.fraction == 0.0 and progress.coverage.hint == TURN_STILL_HINT
    disturbed = np.random.default_rng(3).normal(0.0, 30.0, (200, 3)) * [1.0, 1.0, 0.01]
    ring, problem = fit_ring(disturbed)
    assert ring is None and 'circle' in problem
    assert heading_coverage_of(np.empty((0, 3))).coverage.hint == TURN_HINT_START


def test_garbage_rows_are_ignored():
    raw, _ = turning(40.0)
    dirty = np.vstack([raw[::4], [[np.nan, 1.0, 2.0], [np.inf, 0.0, 0.0]]])
    assert heading_coverage_of(dirty, latest=[np.nan, 0.0, 0.0]).complete


@pytest.mark.parametrize('rate, side', [(0.3, 'left'), (-0.3, 'right')])
def test_the_hint_says_how_far_and_which_way_to_keep_turning(rate, side):
    raw, yaw = turning(40.0, rate=rate)
    third = np.flatnonzero(np.abs(yaw - yaw[0]) <= 2.0 * math.pi / 3.0)[-1]
    buffer = buffered(raw[:third])
    look = heading_coverage_of(buffer.samples, buffer.readings, raw[third - 1],
                               raw[third - 1 - int(RATE_HZ)])  # a look one second earlier
    assert look.turning == (-1 if rate > 0 else 1)  # the field turns against the robot
    hint = look.coverage.hint
    assert hint.startswith('turn another ') and hint.endswith(f'to the {side}'), hint
    degrees = int(hint.split()[2].rstrip('°'))
    assert 200 <= degrees <= 280, hint  # two thirds of the circle remain, give or take the fit
    assert not any(word in hint for word in ROTATION_WORDS)


def test_turn_needed_counts_to_the_far_end_of_the_gap():
    occupied = np.zeros(HEADING_SECTORS, dtype=bool)
    occupied[:24] = True  # 0..240 deg seen
    at_240 = math.radians(235.0)  # sector 23
    assert turn_needed(occupied, at_240, +1) == 130  # on through 359: sectors 24..35 (+ this)
    assert turn_needed(occupied, at_240, -1) == 360  # back through 0, then the whole gap
    assert turn_hint(occupied, at_240) == 'turn another 130° to the right'  # the shorter way
    assert turn_hint(occupied, at_240, -1) == 'turn another 360° to the left'
    assert turn_needed(occupied, math.radians(5.0), -1) == 130  # at the gap's other edge
    assert 'heading not yet seen' in turn_hint(occupied, None)
    occupied[:35] = True
    assert turn_hint(occupied, at_240) == ''  # one sector missing: complete
    assert turn_hint(np.zeros(HEADING_SECTORS, dtype=bool), None) == TURN_HINT_START


def test_turning_direction_needs_a_clear_step_and_keeps_what_it_knew():
    assert turning_direction(0.0, math.radians(10.0)) == 1
    assert turning_direction(math.radians(175.0), math.radians(-175.0)) == 1  # across +-180
    assert turning_direction(0.0, math.radians(1.0), known=-1) == -1  # jitter, not a turn
    assert turning_direction(None, 1.0, known=1) == 1

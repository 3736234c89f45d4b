# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The robot's own field told through the gyroscope: readings between which the robot barely
turned differ by ``K du + c dT`` (fit/compensation.py ``gyro_pairs``), so a robot standing still
with its motors at several currents (ArduPilot's compassmot), or driving straight, determines
every axis of ``K``; live/compensation.py integrates the attitude the readings carry."""

from __future__ import annotations

from dataclasses import replace
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.calibration.fit import compensation as compensation_fit
from mag_calibrator_ros.calibration.fit.calibration import Calibration, Compensation
from mag_calibrator_ros.calibration.fit.compensation import (
    PAIR_MAX_TURN_DEG,
    CompensationData,
    fit_compensation,
    gyro_pairs,
)
from mag_calibrator_ros.calibration.live.compensation import CompensationLearner
from mag_calibrator_ros.calibration.live.session import CalibrationSession
from mag_calibrator_ros.calibration.live.settings import SessionSettings

F = 50e-6
OFFSET = np.array([12e-6, -7e-6, 4e-6])
GAIN = np.array([0.9e-6, -0.5e-6, 0.7e-6])  # tesla per amp, every axis
BATTERY = 'battery_state:sensor_msgs/msg/BatteryState:current'
EARTH = F * np.array([0.4, 0.2, -0.8944])  # the still robot's field (|EARTH| = F)


def standing(seconds: float = 60.0, rate: float = 50.0, steps: bool = True, seed: int = 0
             ) -> dict[str, np.ndarray]:
    """A robot held still while its motors run at a current stepping between levels every 2 s
    (constant with ``steps`` False), its gyroscope reading only noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate)) / rate
    levels = np.array([0.5, 6.0, 2.0, 9.0, 4.0, 0.5, 7.5, 3.0])
    amps = levels[(t // 2.0).astype(int) % len(levels)] if steps else np.full(len(t), 3.0)
    raw = EARTH + OFFSET + np.outer(amps, GAIN) + rng.normal(0.0, 0.15e-6, (len(t), 3))
    gyro = rng.normal(0.0, 0.002, (len(t), 3))
    return {'t': t, 'raw': raw, 'current': amps, 'gyro': gyro}


def _attitudes(run: dict[str, np.ndarray]) -> np.ndarray:
    """(n, 5): one stretch, the gyroscope's rate integrated (rectangles)."""
    dt = np.diff(run['t'], prepend=run['t'][0])
    steps = Rotation.from_rotvec(run['gyro'] * dt[:, None])
    attitude, quaternions = Rotation.identity(), []
    for step in steps:
        attitude = attitude * step
        quaternions.append(attitude.as_quat())
    return np.hstack([np.ones((len(dt), 1)), np.array(quaternions)])


def _data(run: dict[str, np.ndarray], gyroscope: bool = True) -> CompensationData:
    learn, held = slice(None, None, 2), slice(1, None, 2)
    attitudes = _attitudes(run) if gyroscope else None
    inputs = run['current'][:, None]
    return CompensationData(
        run['raw'][learn], inputs[learn], None, ('current',), run['raw'][held], inputs[held],
        None, None, run['t'][learn], None if attitudes is None else attitudes[learn],
        run['t'][held], None if attitudes is None else attitudes[held])


def test_standing_still_at_several_currents_determines_every_axis_through_the_gyroscope():
    run = standing()
    fit = fit_compensation(_data(run), Calibration(OFFSET, np.eye(3), F))
    assert fit.kept == ('current',) and fit.pairs > 100
    assert fit.calibration.compensation.interference[:, 0] == pytest.approx(GAIN, abs=0.05e-6)
    now, candidate = fit.held_pair_errors
    assert len(now) >= 30 and np.median(candidate) < 0.2 * np.median(now)


def test_without_a_gyroscope_standing_still_says_what_it_needs():
    fit = fit_compensation(_data(standing(), gyroscope=False), Calibration(OFFSET, np.eye(3), F))
    assert fit.calibration is None and fit.pairs == 0
    assert 'not in enough headings' in fit.reason
    assert 'pair an IMU with a gyroscope (imu/data_raw)' in fit.reason


def test_a_constant_current_standing_still_learns_nothing_even_with_the_gyroscope():
    fit = fit_compensation(_data(standing(steps=False)), Calibration(OFFSET, np.eye(3), F))
    assert fit.calibration is None
    assert "input 'current' did not vary" in fit.reason


def test_pairs_are_only_made_within_a_stretch_and_across_small_turns():
    t = np.arange(0.0, 10.0, 0.05)
    yaw = np.where(t < 5.0, 0.0, np.radians(3.0 * (t - 5.0)))  # turning 3 deg/s from 5 s
    quaternions = Rotation.from_euler('z', yaw[:, None]).as_quat()
    stretch = np.where(t < 8.0, 1.0, 2.0)  # the gyroscope's attitude restarts at 8 s
    pairs = gyro_pairs(t, np.hstack([stretch[:, None], quaternions]))
    assert len(pairs) > 50
    first, second = t[pairs.first], t[pairs.second]
    assert np.all(stretch[pairs.first] == stretch[pairs.second])
    turned = np.degrees(np.abs(yaw[pairs.second] - yaw[pairs.first]))
    assert np.all(turned <= PAIR_MAX_TURN_DEG + 1e-9) and np.any(second > 5.5)
    earth = np.array([1.0, 0.0, 0.0])  # the map carries a world-fixed vector between frames

    expected = Rotation.from_euler('z', yaw[pairs.second][:, None]).inv().apply(earth)
    carried = np.einsum('pab,pb->pa', pairs.maps,
                        Rotation.from_euler('z', yaw[pairs.first][:, None]).inv().apply(earth))
    assert carried == pytest.approx(expected, abs=1e-9)
    assert np.all(first < second)
    none = gyro_pairs(t, np.full((len(t), 5), math.nan))  # no gyroscope
    assert len(none) == 0


def test_the_session_learns_a_standing_robot_through_its_gyroscope_and_adopts_on_pairs():
    run = standing(seconds=80.0)
    static = Calibration(OFFSET + GAIN * run['current'].mean(), np.eye(3), F)
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=static)
    for index, when in enumerate(run['t']):
        stamp = int(round(when * 1e9)) + 1
        session.process_input(0, stamp, float(run['current'][index]))
        session.process_imu(stamp, 'imu', (0.0, 0.0, 9.81), run['gyro'][index])
        session.process(stamp, 'imu', run['raw'][index])
        session.poll()
    compensation = session.calibration.compensation
    assert session.report().counts.adoptions.get('compensation', 0) >= 1
    assert compensation.interference[:, 0] == pytest.approx(GAIN, abs=0.08e-6)
    before = np.linalg.norm(static.apply(run['raw'][-500:]) - EARTH, axis=1).mean()
    after = np.linalg.norm(session.calibration.apply(
        run['raw'][-500:], run['current'][-500:, None]) - EARTH, axis=1).mean()
    assert after < 0.25 * before


def _learner(calibration: Calibration) -> tuple[CompensationLearner, Calibration]:
    """The session's learner on its own (live/compensation.py), told of ``calibration`` put in
    force as the session tells it; the calibration in force it gives back."""
    learner = CompensationLearner((BATTERY,))
    return learner, learner.carry(calibration, None, 'given')


def test_the_learner_integrates_the_gyroscope_and_restarts_after_a_gap():
    learner, calibration = _learner(Calibration(OFFSET, np.eye(3), F))
    rate = 0.5  # rad/s about z
    for index in range(400):  # 4 s at 100 Hz, then a 1 s gap, then 1 s more
        when = index * 0.01 if index < 300 else 1.0 + index * 0.01
        stamp = int(round(when * 1e9)) + 1
        learner.input(0, stamp, 1.0 + index % 7)
        learner.gyro(stamp, (0.0, 0.0, rate))  # as process_imu hands it on
        learner.observe(stamp, EARTH + OFFSET, calibration)  # as process does
    data = learner.data(calibration)
    rows = np.vstack([np.column_stack([data.times, data.attitudes]),
                      np.column_stack([data.held_times, data.held_attitudes])])
    rows = rows[np.argsort(rows[:, 0])]
    before, after = rows[rows[:, 0] < 2.9], rows[rows[:, 0] > 4.05]
    assert len(set(before[:, 1])) == 1 and len(set(after[:, 1])) == 1
    assert before[0, 1] != after[0, 1]  # the gap started a new stretch
    turned = (Rotation.from_quat(before[0, 2:]).inv() * Rotation.from_quat(before[-1, 2:]))
    assert turned.magnitude() == pytest.approx(rate * (before[-1, 0] - before[0, 0]), rel=0.02)


def test_a_log_s_ten_hertz_imu_rows_with_jitter_are_one_stretch():
    """A flight log's rows come 100 ms apart give or take a millisecond (ArduPilot's MAG rate,
    the IMU resampled to it): each of them must continue the integrated attitude. With a
    100 ms limit a real hover log broke every fourth step and made no pair at all."""
    learner, calibration = _learner(Calibration(OFFSET, np.eye(3), F))
    jitter = np.random.default_rng(4).uniform(-0.001, 0.001, 300)
    for index in range(300):  # 30 s at 10 Hz
        stamp = int(round((index * 0.1 + jitter[index]) * 1e9)) + 10**9
        learner.input(0, stamp, 1.0 + index % 7)
        learner.gyro(stamp, (0.0, 0.0, 0.02))
        learner.observe(stamp, EARTH + OFFSET, calibration)
    data = learner.data(calibration)
    assert len(data.attitudes) > 100 and len(set(data.attitudes[:, 0])) == 1


def _answers(session: CalibrationSession, ticket: int) -> list:
    return [event.attempt for event in session.take_events() if event.ticket == ticket]


def _stand(session: CalibrationSession, run: dict[str, np.ndarray], ticket: int,
           start: float = 0.0) -> list:
    """Feed the standing robot's run from ``start`` s of stream; the answers to ``ticket``."""
    answers = []
    for index, when in enumerate(run['t']):
        stamp = int(round((start + when) * 1e9)) + 1
        session.process_input(0, stamp, float(run['current'][index]))
        session.process_imu(stamp, 'imu', (0.0, 0.0, 9.81), run['gyro'][index])
        session.process(stamp, 'imu', run['raw'][index])
        session.poll()
        answers += _answers(session, ticket)
    return answers


def test_learn_compensation_answers_once_what_the_motors_currents_tell_is_in_force():
    """~/learn_compensation with learn_compensation off: nothing is kept before the call, and
    the window learns K from a robot held still while its motors step through currents."""
    run = standing(seconds=60.0)
    static = Calibration(OFFSET + GAIN * run['current'].mean(), np.eye(3), F)
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,),
                                                 learn_compensation=False), calibration=static)
    before = _stand(session, standing(seconds=20.0, seed=1), -1)
    assert not before and 'compensation_readings_kept' not in session.report().values
    ticket = session.request_compensation(60.0)
    assert 'compensation_learning' in session.report().values
    answers = _stand(session, run, ticket, start=20.0)
    assert len(answers) == 1 and answers[0].success, answers
    assert answers[0].message.startswith('learned in ')
    assert "compensating the robot's own field" in answers[0].message
    compensation = session.calibration.compensation
    assert compensation.interference[:, 0] == pytest.approx(GAIN, abs=0.08e-6)
    values = session.report().values  # the window closed with its answer: nothing is kept
    assert 'compensation_learning' not in values and 'compensation_readings_kept' not in values


def test_learn_compensation_at_a_constant_current_says_what_it_needs_at_its_end():
    run = standing(seconds=40.0, steps=False)
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=Calibration(OFFSET, np.eye(3), F))
    ticket = session.request_compensation(30.0)
    answers = _stand(session, run, ticket)
    assert len(answers) == 1 and not answers[0].success
    assert answers[0].message.startswith('nothing learned in 30 s of readings')
    assert "BatteryState:current' did not vary" in answers[0].message
    assert session.calibration.compensation is None


def test_learn_compensation_refuses_without_a_calibration_twice_at_once_and_ends_on_reset():
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)))
    ticket = session.request_compensation(30.0)
    [answer] = _answers(session, ticket)
    assert not answer.success and 'no calibration in force' in answer.message
    session.apply_calibration(Calibration(OFFSET, np.eye(3), F))
    first, second = session.request_compensation(30.0), session.request_compensation(30.0)
    [answer] = _answers(session, second)
    assert not answer.success and 'already learning' in answer.message
    session.reset()
    [answer] = _answers(session, first)
    assert not answer.success and '~/reset' in answer.message
    for timeout in (0.0, math.nan, 1e9):
        ticket = session.request_compensation(timeout)
        [answer] = _answers(session, ticket)
        assert not answer.success and 'compensation_timeout' in answer.message


def test_the_offset_is_held_where_the_calibration_in_force_is_right_not_at_the_readings_mean():
    """A static fit made at 1 A (a turn in place) is right at 1 A; K learned standing at
    several currents must keep it right there, not at the standing readings' mean current,
    across the directions the still field cannot tell (``CompensationData.anchor``)."""
    run = standing()
    base = Calibration(OFFSET + GAIN * 1.0, np.eye(3), F)
    anchored = fit_compensation(replace(_data(run), anchor=np.array([1.0, math.nan])), base)
    unanchored = fit_compensation(_data(run), base)
    across = np.eye(3) - np.outer(EARTH, EARTH) / F**2  # what standing still cannot see
    error = across @ (anchored.calibration.offset - OFFSET)
    assert np.linalg.norm(error) < 0.1e-6
    moved = across @ (unanchored.calibration.offset - OFFSET)  # held at the mean current
    assert np.linalg.norm(moved) > 1e-6


@pytest.mark.parametrize('made_at', [0.0, 1.0, 8.0])
def test_a_calibration_from_a_file_is_held_where_the_magnitudes_say_it_is_right(made_at):
    """A file does not say at which current it was made (``anchor_unknown``): the field K
    adds along the Earth's tells it, and the offset is held there, across the directions the
    still field cannot tell too; not at the standing readings' mean current (3.9 A)."""
    run = standing()
    base = Calibration(OFFSET + GAIN * made_at, np.eye(3), F)
    found = fit_compensation(replace(_data(run), anchor_unknown=True), base)
    across = np.eye(3) - np.outer(EARTH, EARTH) / F**2
    assert np.linalg.norm(across @ (found.calibration.offset - OFFSET)) < 0.1e-6
    assert found.calibration.compensation.interference[:, 0] == pytest.approx(GAIN, abs=0.05e-6)


def test_the_offset_is_placed_for_the_terms_as_they_will_be_used(monkeypatch):
    """Axes a fit does not determine are left at zero; the offset must be placed with them at
    zero, not with the values the fit gave them. Placed for those, a real multicopter's hover
    log (K_x, K_z undetermined at 2.5-3 % of the field) gave a candidate 35 % off on held-out
    readings instead of 15 %. Here the limit is lowered so that a standing robot's noisy axes
    are the undetermined ones."""
    monkeypatch.setattr(compensation_fit, 'DETERMINED_PCT', 0.05)
    run = standing(seed=3)
    run['raw'][:, 0] += np.random.default_rng(9).normal(0.0, 2e-6, len(run['t']))
    fit = fit_compensation(_data(run), Calibration(OFFSET, np.eye(3), F))
    gains = fit.calibration.compensation.interference[:, 0]
    assert gains[0] == 0.0 and gains[2] == pytest.approx(GAIN[2], abs=0.05e-6)
    errors = np.linalg.norm(fit.calibration.apply(run['raw'], run['current'][:, None]),
                            axis=1) / F - 1.0
    assert abs(np.median(errors)) < 0.002  # 4 % when placed for the fitted values
    assert 100 * np.sqrt(np.mean(errors**2)) == pytest.approx(fit.residual_pct, rel=0.1)
    assert fit.held_candidate_pct < fit.held_current_pct


def stand_turn_stand(seed: int, rate: float = 20.0) -> dict[str, np.ndarray]:
    """A robot that stands at 0.5 A, turns in place once at 25 deg/s drawing 1.175 A (the
    current ramping over 0.5 s), then stands facing another way: the current changes only
    with the motion (the benchmark's course before ``~/learn_compensation``)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(21 * rate)) / rate
    turning = (t >= 5.0) & (t < 19.0)
    yaw = np.radians(np.cumsum(np.where(turning, 25.0, 0.0)) / rate)
    amps = 0.5 + 0.675 * np.where(t < 19.0, np.clip((t - 5.0) / 0.5, 0.0, 1.0),
                                  np.clip((19.5 - t) / 0.5, 0.0, 1.0))
    turn = Rotation.from_euler('z', yaw[:, None])
    gain = np.array([1.6e-6, 0.0, 0.0])
    raw = (turn.inv().apply(EARTH) + OFFSET + np.outer(amps, gain)
           + rng.normal(0.0, 0.3e-6, (len(t), 3)))
    attitudes = np.hstack([np.ones((len(t), 1)), turn.as_quat()])
    return {'t': t, 'raw': raw, 'current': amps, 'attitudes': attitudes, 'gain': gain}


@pytest.mark.parametrize('seed', [0, 1])
def test_k_is_what_the_readings_tell_not_the_calibrations_error_where_the_offset_is_held(seed):
    """One current step that came with a turn tells K along a few directions only; the offset
    is held at the anchor along what the readings do not tell, so with K fitted under that
    hold, the static calibration's error there (0.5 uT along the turning axis: a planar fit
    does not fit it) became K on every axis: (-2.0, -2.0, -1.9) uT/A against (1.6, 0, 0)."""
    run = stand_turn_stand(seed)
    learn, held = slice(None, None, 2), slice(1, None, 2)
    inputs = run['current'][:, None]
    data = CompensationData(
        run['raw'][learn], inputs[learn], None, ('current',), run['raw'][held], inputs[held],
        None, None, run['t'][learn], run['attitudes'][learn], run['t'][held],
        run['attitudes'][held], anchor=np.array([0.96, math.nan]))
    right_at_the_turn = OFFSET + run['gain'] * 1.175
    gains = []
    for error in ([0.0, 0.0, 0.0], [0.0, 0.0, 0.5e-6]):
        fit = fit_compensation(data, Calibration(right_at_the_turn + error, np.eye(3), F))
        assert fit.kept == ('current',), fit.reason
        gains.append(fit.calibration.compensation.interference[:, 0])
    assert gains[1] == pytest.approx(gains[0], abs=0.02e-6)
    assert gains[1][0] > 1.0e-6


def test_the_learner_anchors_a_static_fit_at_the_mean_inputs_since_the_buffer_was_emptied():
    """The learner as the session drives it: ``observe`` for each reading, ``carry`` for each
    calibration put in force (what it returns is in force), ``reset`` on ~/reset."""
    learner = CompensationLearner((BATTERY,))
    in_force = None

    def put(calibration: Calibration, source: str) -> None:
        nonlocal in_force
        in_force = learner.carry(calibration, in_force, source)

    for index in range(200):
        stamp = index * 10_000_000 + 1
        learner.input(0, stamp, 2.0 if index < 100 else 4.0)
        learner.temperature(stamp, 30.0)
        learner.observe(stamp, EARTH + OFFSET, in_force)
    put(Calibration(OFFSET, np.eye(3), F), 'refine')
    assert learner.anchor == pytest.approx([3.0, 30.0], abs=0.05)
    assert not learner.anchor_unknown
    static = Calibration(OFFSET, np.eye(3), F)
    put(static, 'file')
    assert np.isnan(learner.anchor).all()  # a file does not say where it was right
    assert learner.anchor_unknown and learner.data(in_force).anchor_unknown
    put(static, 'realign')
    assert learner.anchor_unknown  # rotated into the IMU frame, still the file's offset
    put(static.with_compensation(Compensation(('current',), GAIN[:, None])), 'file')
    assert learner.anchor[0] == 0.0 and np.isnan(learner.anchor[1])  # its K: right at 0 A
    assert learner.anchor_unknown  # the temperature's is not known
    live = learner.data(in_force).anchor  # live fits hold the known one too
    assert live[0] == 0.0 and np.isnan(live[1])
    drift_only = Compensation(('current',), np.zeros((3, 1)), np.array([0.0, 0.2e-6, 0.0]), 25.0)
    put(static.with_compensation(drift_only), 'compensation')
    assert learner.anchor[0] == 0.0 and learner.anchor[1] == 25.0  # current: as before
    for index in range(200, 300):  # the buffer kept its readings, moved: 5 A since
        stamp = index * 10_000_000 + 1
        learner.input(0, stamp, 5.0)
        learner.temperature(stamp, 30.0)
        learner.observe(stamp, EARTH + OFFSET, in_force)
    put(static, 'refine')  # the drift carried; the current at its mean
    assert learner.anchor == pytest.approx([11.0 / 3.0, 25.0], abs=0.05)
    learner.reset()  # emptied: the mean starts again
    for index in range(300, 400):
        stamp = index * 10_000_000 + 1
        learner.input(0, stamp, 5.0)
        learner.observe(stamp, EARTH + OFFSET, in_force)
    put(static, 'refine')
    assert learner.anchor[0] == pytest.approx(5.0)
    assert not learner.anchor_unknown
    assert np.isnan(learner.data(in_force).anchor[0])  # live: the readings' mean


def test_learn_compensation_learns_k_and_keeps_the_drift_in_force():
    """The quick procedure learns the inputs' K only: the few degrees a die warms meanwhile
    tell no c, and a c learned before (here from a file) stays as it is."""
    run = standing(seconds=60.0)
    drift = np.array([0.0, 0.2e-6, 0.0])
    warming = 25.0 + 5.0 * run['t'] / run['t'][-1]
    run['raw'] = run['raw'] + np.outer(warming - 25.0, drift)
    given = Calibration(OFFSET + GAIN * run['current'].mean(), np.eye(3), F).with_compensation(
        Compensation(('current',), np.zeros((3, 1)), drift, 25.0))
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=given)
    ticket = session.request_compensation(60.0)
    answers = []
    for index, when in enumerate(run['t']):
        stamp = int(round(when * 1e9)) + 1
        session.process_input(0, stamp, float(run['current'][index]))
        session.process_temperature(stamp, float(warming[index]))
        session.process_imu(stamp, 'imu', (0.0, 0.0, 9.81), run['gyro'][index])
        session.process(stamp, 'imu', run['raw'][index])
        session.poll()
        answers += _answers(session, ticket)
    assert len(answers) == 1 and answers[0].success, answers
    compensation = session.calibration.compensation
    assert compensation.temperature_coefficient == pytest.approx(drift, abs=1e-15)
    assert compensation.reference_temperature == 25.0
    assert compensation.interference[:, 0] == pytest.approx(GAIN, abs=0.08e-6)


def test_a_window_too_short_to_keep_a_fits_readings_says_to_make_it_longer():
    run = standing(seconds=20.0)
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,),
                                                 learn_compensation=False),
                                 calibration=Calibration(OFFSET, np.eye(3), F))
    ticket = session.request_compensation(10.0)
    [answer] = _stand(session, run, ticket)
    assert not answer.success
    assert 'make compensation_timeout longer' in answer.message, answer.message

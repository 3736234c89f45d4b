"""The robot's own field told through the gyroscope: readings between which the robot barely
turned differ by ``K du + c dT`` (fit/compensation.py ``gyro_pairs``), so a robot standing still
with its motors at several currents (ArduPilot's compassmot), or driving straight, determines
every axis of ``K``; live/compensation.py integrates the attitude the readings carry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.compensation import (
    PAIR_MAX_TURN_DEG,
    CompensationData,
    fit_compensation,
    gyro_pairs,
)
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
        session.compensation.input(0, stamp, float(run['current'][index]))
        session.process_imu(stamp, 'imu', (0.0, 0.0, 9.81), run['gyro'][index])
        session.process(stamp, 'imu', run['raw'][index])
        session.poll()
    compensation = session.calibration.compensation
    assert session.adoptions.get('compensation', 0) >= 1
    assert compensation.interference[:, 0] == pytest.approx(GAIN, abs=0.08e-6)
    before = np.linalg.norm(static.apply(run['raw'][-500:]) - EARTH, axis=1).mean()
    after = np.linalg.norm(session.calibration.apply(
        run['raw'][-500:], run['current'][-500:, None]) - EARTH, axis=1).mean()
    assert after < 0.25 * before


def test_the_learner_integrates_the_gyroscope_and_restarts_after_a_gap():
    session = CalibrationSession(SessionSettings(interference_inputs=(BATTERY,)),
                                 calibration=Calibration(OFFSET, np.eye(3), F))
    learner = session.compensation
    rate = 0.5  # rad/s about z
    for index in range(400):  # 4 s at 100 Hz, then a 1 s gap, then 1 s more
        when = index * 0.01 if index < 300 else 1.0 + index * 0.01
        stamp = int(round(when * 1e9)) + 1
        learner.input(0, stamp, 1.0 + index % 7)
        session.process_imu(stamp, 'imu', (0.0, 0.0, 9.81), (0.0, 0.0, rate))
        session.process(stamp, 'imu', EARTH + OFFSET)
    data = learner.data(session.calibration)
    rows = np.vstack([np.column_stack([data.times, data.attitudes]),
                      np.column_stack([data.held_times, data.held_attitudes])])
    rows = rows[np.argsort(rows[:, 0])]
    before, after = rows[rows[:, 0] < 2.9], rows[rows[:, 0] > 4.05]
    assert len(set(before[:, 1])) == 1 and len(set(after[:, 1])) == 1
    assert before[0, 1] != after[0, 1]  # the gap started a new stretch
    turned = (Rotation.from_quat(before[0, 2:]).inv() * Rotation.from_quat(before[-1, 2:]))
    assert turned.magnitude() == pytest.approx(rate * (before[-1, 0] - before[0, 0]), rel=0.02)

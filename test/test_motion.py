# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Trajectories: proper rotations, determinism, hand-like tumbling that covers every direction."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.sim import motion


def fibonacci_cells(count: int) -> np.ndarray:
    """Near-equal-area cell centres on the unit sphere."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / count)
    azimuth = math.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)]
    )


def covered_fraction(vectors: np.ndarray, cells: int = 100) -> float:
    centres = fibonacci_cells(cells)
    unit = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    return len(set(np.argmax(unit @ centres.T, axis=1))) / cells


def test_earth_field_enu_components():
    field = motion.earth_field(50.0, 60.0)
    np.testing.assert_allclose(field, [0.0, 25.0, -50.0 * math.sin(math.radians(60.0))])
    np.testing.assert_allclose(motion.earth_field(40.0, -30.0)[2], 20.0)  # southern: points up


@pytest.mark.parametrize('strength, inclination', [(-1.0, 0.0), (math.nan, 0.0), (1.0, 91.0),
                                                   (1.0, math.inf)])
def test_earth_field_rejects_bad_input(strength, inclination):
    with pytest.raises(ValueError):
        motion.earth_field(strength, inclination)


@pytest.mark.parametrize('kind', motion.TRAJECTORY_KINDS)
def test_orientations_are_rotations_and_deterministic(kind):
    times = np.linspace(0.0, 30.0, 301)
    a = motion.make_trajectory(kind, seed=7).orientations(times)
    b = motion.make_trajectory(kind, seed=7).orientations(times)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a @ np.transpose(a, (0, 2, 1)), np.broadcast_to(np.eye(3), a.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(a), 1.0, atol=1e-12)
    np.testing.assert_allclose(motion.make_trajectory(kind, seed=7).orientation(12.3),
                               motion.make_trajectory(kind, seed=7).orientations([12.3])[0])


def test_seeds_differ():
    a = motion.make_trajectory('tumble', 1).orientation(5.0)
    b = motion.make_trajectory('tumble', 2).orientation(5.0)
    assert not np.allclose(a, b)


def test_tumble_is_smooth_hand_speed():
    dt = 0.01
    rotations = motion.make_trajectory('tumble', 3).rotations(np.arange(0.0, 60.0, dt))
    rates = (rotations[:-1].inv() * rotations[1:]).magnitude() / dt
    assert 1.0 < np.mean(rates) < 4.0  # a hand, not a centrifuge
    assert 3.0 < np.max(rates) < 10.0  # several rad/s peaks
    assert np.max(np.abs(np.diff(rates))) < 1.0  # no jumps between 10 ms steps


@pytest.mark.parametrize('seed', range(5))
def test_tumble_covers_all_directions_within_a_minute(seed):
    fields = motion.body_field_samples('tumble', 6000, 100.0, 50.0, 60.0, seed)
    assert covered_fraction(fields) >= 0.9


def test_yaw_stays_nearly_level_and_turns():
    times = np.arange(0.0, 60.0, 0.05)
    matrices = motion.make_trajectory('yaw', 4).orientations(times)
    tilt = np.degrees(np.arccos(np.clip(matrices[:, 2, 2], -1.0, 1.0)))  # body z vs world up
    assert 0.5 < tilt.max() < 8.0
    heading = np.unwrap(np.arctan2(matrices[:, 1, 0], matrices[:, 0, 0]))
    assert abs(heading[-1] - heading[0]) > 4.0 * math.pi  # at least two full turns a minute


def test_still_does_not_move():
    fields = motion.body_field_samples('still', 500, 50.0, 48.0, 65.0, seed=5)
    np.testing.assert_allclose(fields, np.broadcast_to(fields[0], fields.shape))
    np.testing.assert_allclose(np.linalg.norm(fields[0]), 48.0)


def test_body_field_keeps_strength():
    fields = motion.body_field_samples('tumble', 1000, 100.0, 33.0, -20.0, seed=0)
    np.testing.assert_allclose(np.linalg.norm(fields, axis=1), 33.0)
    assert motion.body_field_samples('yaw', 0, 10.0, 1.0, 0.0).shape == (0, 3)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match='unknown motion'):
        motion.make_trajectory('spin')
    with pytest.raises(ValueError):
        motion.make_trajectory('tumble').orientation(math.nan)
    with pytest.raises(ValueError):
        motion.make_trajectory('yaw').orientation(-1.0)
    with pytest.raises(ValueError):
        motion.body_field_samples('tumble', 10, 0.0, 1.0, 0.0)


def test_tumble_forgets_old_knots_but_stays_continuous():
    trajectory = motion.TumbleTrajectory(seed=1, retain_s=20.0)
    first = trajectory.orientation(1.0)
    late = trajectory.rotations(np.arange(100.0, 101.0, 0.01))
    steps = (late[:-1].inv() * late[1:]).magnitude()
    assert np.all(steps < 0.2)
    assert len(trajectory._quats) < 2000  # bounded memory
    assert first.shape == (3, 3)
    with pytest.raises(ValueError, match='no longer available'):
        trajectory.orientation(1.0)


def finite_difference_rate(trajectory, t: float, h: float = 1e-5) -> np.ndarray:
    """Body rate from the orientation alone: R(t-h)^T R(t+h) = exp([w] 2h)."""
    before = Rotation.from_matrix(trajectory.orientation(t - h))
    after = Rotation.from_matrix(trajectory.orientation(t + h))
    return (before.inv() * after).as_rotvec() / (2.0 * h)


@pytest.mark.parametrize('kind', motion.TRAJECTORY_KINDS)
def test_state_is_one_consistent_motion(kind):
    """Orientation, body rate and acceleration of state(t) describe the same motion."""
    trajectory = motion.make_trajectory(kind, seed=3)
    # Mid-knot times: the tumble's rate is piecewise constant on its 25 Hz knot grid.
    for t in (np.arange(40) + 0.37) / motion.TumbleTrajectory.KNOT_HZ * 31.0:
        state = trajectory.state(t)
        np.testing.assert_allclose(state.rotation, trajectory.orientation(t), atol=1e-12)
        np.testing.assert_allclose(state.angular_velocity,
                                   finite_difference_rate(trajectory, t), atol=1e-6)
        np.testing.assert_array_equal(trajectory.angular_velocity(t), state.angular_velocity)
        assert state.linear_acceleration.shape == (3,)


def test_tumble_rates_reach_hand_speeds_and_integrate_to_the_orientation():
    trajectory = motion.make_trajectory('tumble', seed=5)
    dt = 1.0 / motion.TumbleTrajectory.KNOT_HZ
    rotation = trajectory.orientation(0.0)
    for k in range(250):  # 10 s, one exact step per knot interval
        omega = trajectory.state((k + 0.5) * dt).angular_velocity
        rotation = rotation @ Rotation.from_rotvec(omega * dt).as_matrix()
    np.testing.assert_allclose(rotation, trajectory.orientation(10.0), atol=1e-9)


def test_tumble_hand_translation_is_the_second_derivative_of_its_position():
    trajectory = motion.TumbleTrajectory(seed=2)
    h = 1e-3
    for t in (1.0, 7.3, 33.3):
        numeric = (trajectory.position(t + h) - 2 * trajectory.position(t)
                   + trajectory.position(t - h)) / h**2
        np.testing.assert_allclose(trajectory.state(t).linear_acceleration, numeric, atol=1e-4)
    accelerations = np.array([trajectory.linear_acceleration(t) for t in np.arange(0, 60, 0.05)])
    rms = np.sqrt(np.mean(np.sum(accelerations**2, axis=1)))
    assert 0.3 < rms < 3.0  # a hand, not a vibrating motor
    assert np.max(np.abs(trajectory.position(12.0))) < 0.15  # centimetres, not metres


def test_yaw_and_still_do_not_translate():
    for kind in ('yaw', 'still'):
        trajectory = motion.make_trajectory(kind, seed=1)
        for t in (0.0, 3.3, 40.0):
            np.testing.assert_array_equal(trajectory.linear_acceleration(t), np.zeros(3))
    np.testing.assert_array_equal(motion.make_trajectory('still').angular_velocity(5.0),
                                  np.zeros(3))


def test_state_refuses_bad_times():
    for kind in motion.TRAJECTORY_KINDS:
        with pytest.raises(ValueError):
            motion.make_trajectory(kind).state(-1.0)
        with pytest.raises(ValueError):
            motion.make_trajectory(kind).state(math.nan)


# -- cmd_vel: a ground robot that turns only as commanded ----------------------------------------


def commanded(rate: float, start: float, end: float, trajectory=None, period: float = 0.05,
              **limits) -> motion.CmdVelTrajectory:
    """A cmd_vel robot commanded ``rate`` from ``start`` to ``end``, re-sent every ``period``."""
    trajectory = trajectory or motion.CmdVelTrajectory(seed=4, **limits)
    for t in np.arange(start, end, period):
        trajectory.command(rate, float(t))
    return trajectory


def test_cmd_vel_robot_never_moves_without_commands():
    trajectory = motion.make_trajectory('cmd_vel', seed=2)
    first = trajectory.state(0.0)
    for t in (0.5, 10.0, 300.0):
        state = trajectory.state(t)
        np.testing.assert_array_equal(state.rotation, first.rotation)
        np.testing.assert_array_equal(state.angular_velocity, np.zeros(3))
        np.testing.assert_array_equal(state.linear_acceleration, np.zeros(3))


def test_cmd_vel_robot_ramps_to_the_commanded_rate_and_integrates_it_exactly():
    trajectory = commanded(0.3, 1.0, 30.0, max_acceleration=0.5)
    assert trajectory.yaw_and_rate(1.0)[1] == 0.0
    assert trajectory.yaw_and_rate(1.3)[1] == pytest.approx(0.15)  # 0.5 rad/s^2 for 0.3 s
    assert trajectory.yaw_and_rate(2.0)[1] == pytest.approx(0.3)
    times = np.arange(1.0, 20.0, 1e-3)
    rates = np.array([trajectory.yaw_and_rate(t)[1] for t in times])
    integrated = np.sum(0.5 * (rates[1:] + rates[:-1]) * np.diff(times))
    turned = trajectory.yaw_and_rate(times[-1])[0] - trajectory.yaw_and_rate(1.0)[0]
    assert turned == pytest.approx(integrated, abs=1e-6)
    assert turned == pytest.approx(0.3 * (times[-1] - 1.0 - 0.3), abs=1e-9)  # a 0.6 s ramp: 0.3 s


def test_cmd_vel_robot_honours_its_limits_and_stops_on_nan():
    trajectory = commanded(5.0, 0.0, 10.0, max_rate=0.8, max_acceleration=2.0)
    assert trajectory.yaw_and_rate(5.0)[1] == pytest.approx(0.8)
    assert trajectory.command(-7.0, 10.0) == -0.8
    assert trajectory.yaw_and_rate(10.5)[1] == pytest.approx(-0.2)  # 2 rad/s^2 from +0.8
    assert trajectory.command(math.nan, 11.0) == 0.0
    assert trajectory.yaw_and_rate(12.0)[1] == 0.0


def test_cmd_vel_robot_stops_by_itself_when_commands_stop_coming():
    trajectory = commanded(0.3, 0.0, 5.0, command_timeout=0.5, max_acceleration=1.0)
    last = 4.95  # the last command
    assert trajectory.yaw_and_rate(last + 0.49)[1] == pytest.approx(0.3)
    assert trajectory.yaw_and_rate(last + 0.6)[1] == pytest.approx(0.2)  # decelerating
    assert trajectory.yaw_and_rate(last + 1.0)[1] == 0.0
    parked = trajectory.state(last + 1.0).rotation
    np.testing.assert_array_equal(trajectory.state(100.0).rotation, parked)


def test_cmd_vel_commands_never_change_what_was_already_measured():
    trajectory = commanded(0.3, 0.0, 3.0)
    before = trajectory.state(4.0).rotation  # a sensor read t = 4 s (the robot is stopping)
    trajectory.command(1.0, 3.5)  # a late command, stamped before that read
    np.testing.assert_array_equal(trajectory.state(4.0).rotation, before)
    assert trajectory.yaw_and_rate(4.0)[1] < trajectory.yaw_and_rate(4.3)[1]  # takes effect now


def test_cmd_vel_tilt_follows_the_heading_within_the_wobble():
    trajectory = commanded(0.5, 0.0, 40.0, wobble_deg=2.0)
    times = np.arange(1.0, 40.0, 0.05)
    rotations = trajectory.rotations(times).as_matrix()
    tilt = np.degrees(np.arccos(np.clip(rotations[:, 2, 2], -1.0, 1.0)))  # body z from up
    assert 1.0 < tilt.max() <= 2.0 + 1e-9
    yaw = np.array([trajectory.yaw_and_rate(t)[0] for t in times])
    turn = np.argmin(np.abs(yaw - (yaw[0] + 2.0 * math.pi)))  # one full turn later
    np.testing.assert_allclose(rotations[turn][2], rotations[0][2], atol=1e-3)  # same floor
    flat = commanded(0.5, 0.0, 10.0, wobble_deg=0.0)
    np.testing.assert_allclose(flat.state(5.0).rotation[2], [0.0, 0.0, 1.0], atol=1e-12)


def test_cmd_vel_state_is_one_consistent_motion_while_turning():
    trajectory = commanded(0.7, 0.0, 20.0, max_acceleration=3.0)
    for t in (2.37, 7.1, 13.9):
        state = trajectory.state(t)
        np.testing.assert_allclose(state.angular_velocity, finite_difference_rate(trajectory, t),
                                   atol=1e-6)


@pytest.mark.parametrize('limits', [{'max_rate': 0.0}, {'max_acceleration': -1.0},
                                    {'wobble_deg': 45.0}, {'command_timeout': math.nan},
                                    {'max_rate': 'fast'}])
def test_cmd_vel_limits_are_checked(limits):
    with pytest.raises(ValueError, match='invalid cmd_vel motion'):
        motion.CmdVelTrajectory(**limits)


def test_poses_hold_still_then_turn_to_the_next_pose():
    trajectory = motion.PosesTrajectory(seed=4)
    held = [t for t in np.arange(0.0, 30.0, 0.01) if trajectory.holding(t)]
    assert 0.35 < len(held) / 3000 < 0.6  # about half the time held
    for t in held[::50]:
        state = trajectory.state(t)
        np.testing.assert_array_equal(state.angular_velocity, np.zeros(3))
        np.testing.assert_array_equal(state.linear_acceleration, np.zeros(3))
    rates = [np.linalg.norm(trajectory.state(t).angular_velocity) for t in np.arange(0, 30, 0.01)]
    assert 1.0 < max(rates) < 8.0  # a hand turning the board, not a centrifuge
    poses = trajectory.orientations(np.array(held))
    distinct = {tuple(np.round(pose[:, 2], 3)) for pose in poses}  # gravity in the body frame
    assert len(distinct) >= 10  # one per hold, each a new tilt


def test_poses_move_the_board_a_few_centimetres_smoothly():
    trajectory = motion.PosesTrajectory(seed=1)
    accelerations = [np.linalg.norm(trajectory.linear_acceleration(t))
                     for t in np.arange(0.0, 30.0, 0.01)]
    assert 0.01 < max(accelerations) < 1.0
    steps = np.diff([trajectory.state(t).angular_velocity for t in np.arange(0, 30, 0.01)], axis=0)
    assert np.max(np.linalg.norm(steps, axis=1)) < 0.2  # minimum jerk: no jumps in rate


# -- cmd_vel: the robot drives, and draws a battery current (issue #26) --------------------------

def test_cmd_vel_robot_drives_at_the_commanded_speed_within_its_limits():
    trajectory = motion.CmdVelTrajectory(seed=1, max_speed=0.5, max_linear_acceleration=0.5)
    for t in np.arange(1.0, 10.0, 0.1):
        trajectory.command(0.0, float(t), speed=2.0)
    assert trajectory.speed(1.0) == 0.0
    assert trajectory.speed(1.4) == pytest.approx(0.2)  # 0.5 m/s^2 for 0.4 s
    assert trajectory.speed(5.0) == pytest.approx(0.5)  # clamped to max_speed
    state = trajectory.state(1.4)  # accelerating forward: along the body's x axis
    np.testing.assert_allclose(state.rotation.T @ state.linear_acceleration, [0.5, 0.0, 0.0],
                               atol=1e-12)
    np.testing.assert_array_equal(trajectory.state(5.0).linear_acceleration, np.zeros(3))
    assert trajectory.speed(10.9) == pytest.approx(0.5 - 0.5 * 0.5)  # timed out at 10.4 s
    assert trajectory.speed(12.0) == 0.0
    trajectory.command(0.0, 13.0, speed=math.nan)
    assert trajectory.speed(14.0) == 0.0


def test_driving_in_an_arc_adds_the_centripetal_acceleration():
    trajectory = motion.CmdVelTrajectory(seed=1, wobble_deg=0.0)
    for t in np.arange(0.0, 5.0, 0.1):
        trajectory.command(0.4, float(t), speed=0.3)
    state = trajectory.state(4.0)
    np.testing.assert_allclose(state.rotation.T @ state.linear_acceleration, [0.0, 0.12, 0.0],
                               atol=1e-12)


def test_the_battery_current_follows_the_wheel_speeds():
    drive = motion.DriveCurrent(idle_a=0.5, full_a=5.0, track_width_m=0.4)
    assert drive.current(0.0, 0.0, 0.5) == 0.5
    assert drive.current(0.5, 0.0, 0.5) == pytest.approx(5.0)
    assert drive.current(-0.25, 0.0, 0.5) == pytest.approx(2.75)  # backwards draws too
    assert drive.current(0.0, 1.0, 0.5) == pytest.approx(0.5 + 4.5 * 0.2 / 0.5)  # in place
    trajectory = motion.CmdVelTrajectory(seed=2, drive=drive)
    assert trajectory.battery_current(3.0) == 0.5  # standing: idle
    for t in np.arange(0.0, 5.0, 0.1):
        trajectory.command(0.0, float(t), speed=0.5)
    assert trajectory.battery_current(4.0) == pytest.approx(5.0)


@pytest.mark.parametrize(('kwargs', 'message'), [
    ({'max_speed': 0.0}, 'max_speed must be in'),
    ({'max_linear_acceleration': math.inf}, 'max_linear_acceleration must be in'),
    ({'drive': motion.DriveCurrent(idle_a=-1.0)}, 'idle_current_a must be in'),
    ({'drive': motion.DriveCurrent(idle_a=2.0, full_a=1.0)}, 'includes the idle current'),
    ({'drive': motion.DriveCurrent(track_width_m=0.0)}, 'track_width must be in'),
])
def test_cmd_vel_drive_settings_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=message):
        motion.CmdVelTrajectory(**kwargs)


def test_the_ground_course_drives_legs_turns_and_stops_for_three_minutes():
    course = motion.CourseDriver()
    assert course.duration_s == 180.0
    assert course.command_at(0.0) == (0.0, 0.0)
    commands = [course.command_at(t) for t in np.arange(0.0, 180.0, 0.5)]
    speeds = {speed for speed, rate in commands if rate == 0.0 and speed > 0.0}
    assert len(speeds) >= 4 and max(speeds) == 0.5  # straight legs at varying speed
    assert any(speed == 0.0 and rate > 0.0 for speed, rate in commands)  # turns both ways
    assert any(speed == 0.0 and rate < 0.0 for speed, rate in commands)
    assert course.command_at(200.0) == (0.0, 0.0)
    with pytest.raises(ValueError, match='at least one leg'):
        motion.CourseDriver(())

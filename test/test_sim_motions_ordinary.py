# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""Motions of ordinary use (issue #44): a wrist, a drone, a magnet attached and removed, a magnet
zone in the room; each a consistent motion the gyroscope and accelerometer measure truly."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mag_calibrator_ros.icm20948 import registers as reg
from mag_calibrator_ros.sim import motion
from mag_calibrator_ros.sim.board import GRAVITY_WORLD, BoardModel
from mag_calibrator_ros.sim.config import SimConfig

TIMES = np.arange(0.0, 240.0, 0.05)
ZONE_PATH = ((0.0, (-4.0, 0.0, 0.0)), (20.0, (-4.0, 0.0, 0.0)), (26.0, (0.0, 0.0, 0.0)),
             (36.0, (0.5, 0.3, 0.0)), (42.0, (4.0, 0.0, 0.0)))


def ordinary(kind: str, seed: int = 0) -> motion.Trajectory:
    if kind == 'wrist':
        return motion.WristTrajectory(seed)
    if kind == 'drone':
        return motion.DroneTrajectory(seed)
    if kind == 'drone_level':
        return motion.DroneTrajectory(seed, thrust=False)
    return motion.CarriedTrajectory(motion.WristTrajectory(seed), ZONE_PATH)


KINDS = ('wrist', 'drone', 'drone_level', 'carried')


@pytest.mark.parametrize('seed', range(4))
def test_wrist_stays_within_its_cone_and_wanders_across_it(seed):
    trajectory = motion.WristTrajectory(seed)
    angles = np.degrees([trajectory.angle_from_base(t) for t in TIMES])
    assert angles.max() < 90.0  # never past the cone
    assert angles.max() > 75.0 and np.mean(angles > 45.0) > 0.3  # a partial sphere, not a wobble
    matrices = trajectory.orientations(TIMES)
    from_base = Rotation.from_matrix(trajectory.base.T @ matrices).magnitude()
    np.testing.assert_allclose(np.degrees(from_base), angles, atol=1e-9)
    # Seen from the board, the earth's field stays in the hemisphere around its base direction.
    field = motion.earth_field(50.0, 60.0)
    base = trajectory.base.T @ field
    body = np.einsum('nji,j->ni', matrices, field)
    assert np.min(body @ base) / 50.0**2 > 0.0
    narrow = np.degrees([motion.WristTrajectory(seed, cone_deg=30.0).angle_from_base(t)
                         for t in TIMES[::4]])
    assert 28.0 < narrow.max() < 30.0  # the cone given, pressed against at the edge


@pytest.mark.parametrize('seed', range(4))
def test_wrist_turns_at_a_hands_rates(seed):
    rates = np.linalg.norm([motion.WristTrajectory(seed).angular_velocity(t) for t in TIMES],
                           axis=1)
    assert 0.5 < rates.mean() < 2.0
    assert rates.max() < 4.0


@pytest.mark.parametrize('seed', range(4))
def test_drone_tilts_at_most_30_degrees_and_turns(seed):
    trajectory = motion.DroneTrajectory(seed)
    matrices = trajectory.orientations(TIMES)
    tilt = np.degrees(np.arccos(np.clip(matrices[:, 2, 2], -1.0, 1.0)))
    assert tilt.max() <= 30.0
    assert tilt.max() > 20.0  # it does tilt
    heading = np.unwrap(np.arctan2(matrices[:, 1, 0], matrices[:, 0, 0]))
    assert np.ptp(heading) > 4.0 * math.pi  # turns: two circles in four minutes at least
    np.testing.assert_allclose(heading - heading[0],
                               [trajectory.yaw(t) - trajectory.yaw(0.0) for t in TIMES],
                               atol=0.6)  # yaw() is the heading, up to the tilt's share


def finite_difference_rate(trajectory, t: float, h: float = 1e-5) -> np.ndarray:
    before = Rotation.from_matrix(trajectory.orientation(t - h))
    after = Rotation.from_matrix(trajectory.orientation(t + h))
    return (before.inv() * after).as_rotvec() / (2.0 * h)


@pytest.mark.parametrize('kind', KINDS)
def test_body_rate_is_the_orientation_paths(kind):
    trajectory = ordinary(kind, 3)
    for t in np.linspace(0.1, 200.0, 37):
        state = trajectory.state(t)
        np.testing.assert_allclose(state.rotation, trajectory.orientation(t), atol=1e-12)
        np.testing.assert_allclose(state.rotation @ state.rotation.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(state.angular_velocity,
                                   finite_difference_rate(trajectory, t), atol=1e-6)


@pytest.mark.parametrize('kind', KINDS)
def test_gyro_integrates_to_the_orientation(kind):
    """20 s of the board's gyroscope (no noise, no bias) at 1 kHz, integrated midpoint by
    midpoint, lands on the orientation path within 0.01 degrees."""
    board = BoardModel(SimConfig(gyro_noise_density=0.0, accel_noise_density=0.0),
                       ordinary(kind, 1))
    dt = 1e-3
    rotation = board.trajectory.orientation(5.0)
    for k in range(20_000):
        _, gyro, _ = board.inertial(5.0 + (k + 0.5) * dt, 57.0, 57.0)
        rotation = rotation @ Rotation.from_rotvec(gyro * dt).as_matrix()
    error = Rotation.from_matrix(rotation.T @ board.trajectory.orientation(25.0)).magnitude()
    assert math.degrees(error) < 0.01


def test_gyro_adds_the_configured_bias_and_noise():
    trajectory = motion.WristTrajectory(2)
    board = BoardModel(SimConfig(gyro_bias_dps=(0.5, -0.3, 0.2)), trajectory)
    errors = np.array([board.inertial(t, 57.0, 57.0)[1] - trajectory.angular_velocity(t)
                       for t in np.arange(0.0, 20.0, 0.01)])
    np.testing.assert_allclose(errors.mean(axis=0), np.radians([0.5, -0.3, 0.2]), atol=1e-4)
    sigma = SimConfig().gyro_noise_density * math.sqrt(57.0)
    np.testing.assert_allclose(errors.std(axis=0), sigma, rtol=0.1)


@pytest.mark.parametrize('kind', ('wrist', 'carried'))
def test_accelerometer_is_gravity_and_the_second_derivative_of_position(kind):
    trajectory = ordinary(kind, 4)
    board = BoardModel(SimConfig(accel_noise_density=0.0), trajectory)
    h = 1e-3
    for t in np.linspace(1.0, 60.0, 23):
        moved = (trajectory.position(t + h) - 2 * trajectory.position(t)
                 + trajectory.position(t - h)) / h**2
        accel, _, truth = board.inertial(t, 57.0, 57.0)
        np.testing.assert_allclose(accel, truth.rotation.T @ (moved - GRAVITY_WORLD), atol=1e-3)


def test_drone_accelerometer_reads_its_thrust_or_gravity():
    for seed in range(3):
        thrusting = BoardModel(SimConfig(accel_noise_density=0.0), motion.DroneTrajectory(seed))
        level = BoardModel(SimConfig(accel_noise_density=0.0),
                           motion.DroneTrajectory(seed, thrust=False))
        for t in np.linspace(0.0, 90.0, 31):
            accel, _, truth = thrusting.inertial(t, 57.0, 57.0)
            cos_tilt = truth.rotation[2, 2]
            np.testing.assert_allclose(accel, [0.0, 0.0, reg.STANDARD_GRAVITY / cos_tilt],
                                       atol=1e-9)  # thrust carries the weight: along body z
            np.testing.assert_allclose(thrusting.trajectory.linear_acceleration(t)[2], 0.0)
            accel, _, truth = level.inertial(t, 57.0, 57.0)
            np.testing.assert_allclose(accel, -truth.rotation.T @ GRAVITY_WORLD, atol=1e-9)


MAGNET = (35.0, -20.0, 40.0)


def test_magnet_is_a_body_fixed_step_between_attachment_and_removal():
    kwargs = {'noise_ut': 0.0, 'hard_iron_ut': (10.0, 5.0, -3.0),
              'soft_iron': (1.1, 0.05, 0.0, 0.05, 0.9, 0.0, 0.0, 0.0, 1.0)}
    trajectory = motion.WristTrajectory(5)
    with_magnet = BoardModel(SimConfig(attached_magnet_ut=MAGNET, magnet_attached_s=12.5,
                                       magnet_removed_s=31.0, **kwargs), trajectory)
    without = BoardModel(SimConfig(**kwargs), trajectory)
    for t in np.arange(0.0, 45.0, 0.01):
        step = with_magnet.magnetometer(t)[0] - without.magnetometer(t)[0]
        expected = MAGNET if 12.5 <= t < 31.0 else (0.0, 0.0, 0.0)
        np.testing.assert_allclose(step, expected, atol=1e-9, err_msg=f't={t}')
        assert with_magnet.magnet_attached(t) == (12.5 <= t < 31.0)
    np.testing.assert_array_equal(with_magnet.magnetometer(20.0)[1], without.magnetometer(20.0)[1])


ZONE = {'zone_field_ut': (20.0, -10.0, 30.0), 'zone_center_m': (0.0, 0.0, 0.0),
        'zone_radius_m': 1.5}


def test_zone_is_fixed_in_the_world_and_absent_outside_it():
    trajectory = ordinary('carried', 2)
    zoned = BoardModel(SimConfig(noise_ut=0.0, **ZONE), trajectory)
    plain = BoardModel(SimConfig(noise_ut=0.0), trajectory)
    inside = 0
    for t in np.arange(0.0, 50.0, 0.02):
        rotation = trajectory.orientation(t)
        extra_world = rotation @ (zoned.magnetometer(t)[0] - plain.magnetometer(t)[0])
        distance = np.linalg.norm(trajectory.position(t))
        weight = max(0.0, 1.0 - (distance / 1.5) ** 2) ** 2
        np.testing.assert_allclose(extra_world, np.array(ZONE['zone_field_ut']) * weight,
                                   atol=1e-9, err_msg=f't={t}')
        assert zoned.zone_weight(t) == pytest.approx(weight, abs=1e-12)
        if distance >= 1.5:
            np.testing.assert_array_equal(zoned.magnetometer(t)[0], plain.magnetometer(t)[0])
        inside += weight > 0.5
        np.testing.assert_array_equal(zoned.magnetometer(t)[1], plain.magnetometer(t)[1])
    assert inside > 200  # it lingered there, turning: seconds of readings in the zone
    np.testing.assert_allclose(trajectory.position(10.0)[:2], (-4.0, 0.0), atol=0.1)


def test_zone_turns_in_the_body_frame_as_the_board_turns():
    trajectory = ordinary('carried', 2)
    zoned = BoardModel(SimConfig(noise_ut=0.0, **ZONE), trajectory)
    plain = BoardModel(SimConfig(noise_ut=0.0), trajectory)
    body = [zoned.magnetometer(t)[0] - plain.magnetometer(t)[0] for t in (27.0, 31.0)]
    assert np.linalg.norm(body[0] - body[1]) > 5.0  # not a hard iron: it turns with the world


def test_carried_path_is_minimum_jerk_between_waypoints():
    trajectory = motion.CarriedTrajectory(motion.StillTrajectory(1), ZONE_PATH)
    np.testing.assert_allclose(trajectory.position(0.0), (-4.0, 0.0, 0.0))
    np.testing.assert_allclose(trajectory.position(23.0), (-2.0, 0.0, 0.0))
    np.testing.assert_allclose(trajectory.position(100.0), (4.0, 0.0, 0.0))
    np.testing.assert_array_equal(trajectory.state(30.0).angular_velocity, np.zeros(3))
    with pytest.raises(ValueError, match='increasing'):
        motion.CarriedTrajectory(motion.StillTrajectory(), ((1.0, (0, 0, 0)), (1.0, (1, 0, 0))))


def test_options_default_off_and_checked():
    config = SimConfig()
    board = BoardModel(config, motion.TumbleTrajectory(0))
    np.testing.assert_array_equal(board.hard_iron_ut(50.0), np.zeros(3))
    assert board.zone_weight(5.0) == 0.0 and not board.magnet_attached(1e9)
    for bad, match in (({'attached_magnet_ut': (1.0, math.nan, 0.0)}, 'attached_magnet_ut'),
                       ({'magnet_attached_s': 10.0, 'magnet_removed_s': 5.0}, 'before'),
                       ({'magnet_attached_s': -1.0}, 'magnet_attached_s'),
                       ({'zone_radius_m': -1.0}, 'zone_radius_m'),
                       ({'zone_field_ut': (1e5, 0.0, 0.0)}, 'zone_field_ut')):
        with pytest.raises(ValueError, match=match):
            SimConfig(**bad)
    with pytest.raises(ValueError, match='position'):
        BoardModel(SimConfig(**ZONE), motion.YawTrajectory(0))
    with pytest.raises(ValueError):
        motion.WristTrajectory(cone_deg=0.0)
    with pytest.raises(ValueError):
        motion.DroneTrajectory(max_tilt_deg=90.0)
    with pytest.raises(ValueError):
        motion.WristTrajectory().state(-1.0)


@pytest.mark.parametrize('kind', KINDS)
def test_deterministic_for_a_seed(kind):
    a = ordinary(kind, 7).orientations(np.linspace(0.0, 30.0, 50))
    b = ordinary(kind, 7).orientations(np.linspace(0.0, 30.0, 50))
    c = ordinary(kind, 8).orientations(np.linspace(0.0, 30.0, 50))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)

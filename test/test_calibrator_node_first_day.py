# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""What a ROS user meets on the first day, over real rclpy/DDS: a calibration known to be wrong
is published with its uncertainty (the node's callback, given the session's judgement), a params
file that shadows a newer calibration file is named, the first log lines, debug logging by the
node's name and auto_save turned on at run time."""

from __future__ import annotations

from pathlib import Path
import sys

import numpy as np
from rcl_interfaces.msg import Log
import rclpy
from rclpy.context import Context
import rclpy.logging
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.live.worker import InlineRunner
from mag_calibrator_ros.calibration.store.calibration_file import (
    calibration_parameters,
    load_calibration,
    save_calibration,
)
from mag_calibrator_ros.nodes.calibration_parameters import shadowed_file_note
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from node_helpers import (  # noqa: E402  (the DDS helpers, one place)
    Probe,
    set_parameter_over_service,
    vector,
    wait_for,
)
from test_calibrator_node import Published, magnetic_field, offline_node  # noqa: E402

HARD_IRON_UT = [120.0, -80.0, 60.0]
SOFT_IRON = [1.15, 0.10, -0.08, 0.10, 0.85, 0.12, -0.08, 0.12, 1.00]
FIELD_T = 50e-6
DEBUG, INFO, WARN = 10, 20, 30  # rcl_interfaces/Log levels


def other_boards_calibration() -> Calibration:
    """Another board's file: its offset 150 uT away from this one's."""
    soft = np.array(SOFT_IRON).reshape(3, 3)
    return Calibration(np.array(HARD_IRON_UT) * 1e-6 + [140e-6, -60e-6, 20e-6],
                       np.linalg.inv(soft), FIELD_T, 'full',
                       {'residual_rms_pct': 0.5, 'coverage': 0.9})


def tumbling_driver(ros, namespace: str, seed: int = 5):
    return ros.driver(namespace, **{
        'sim.hard_iron_ut': HARD_IRON_UT, 'sim.soft_iron': SOFT_IRON, 'sim.noise_ut': 0.05,
        'sim.motion': 'tumble', 'sim.seed': seed})


class Rosout(Node):
    """What the nodes of the module log, as /rosout carries it (transient local: lines logged
    before it subscribed arrive too)."""

    def __init__(self, ros) -> None:
        super().__init__('rosout_listener', context=ros.context)
        self.lines: list[Log] = []
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(Log, '/rosout', self.lines.append, qos)
        ros.add(self)

    def of(self, logger: str, level: int | None = None) -> list[str]:
        return [line.msg for line in list(self.lines)
                if line.name == logger and (level is None or line.level == level)]


def test_a_reading_judged_off_is_published_with_its_uncertainty(ros, tmp_path, monkeypatch):
    """The node's half of a calibration judged not to fit: the |B| error the session measured
    goes on the covariance (REP-145), the same on every axis, over the input's as the correction
    carries it; nothing is added while none is measured. (The session's half, when it is judged
    so and how far off, until the recalibration: test_calibrator_replays.py.)"""
    given = other_boards_calibration()
    node = offline_node(ros, 'misfit_mark', InlineRunner(), progress_log_period=0.0,
                        calibration_file=str(tmp_path / 'none.yaml'),
                        **calibration_parameters(given))
    published = Published()
    monkeypatch.setattr(node, '_publisher', published)
    measured = {'error': 0.0}  # what the session says of the next message
    process = node.session.process

    def judged(stamp_ns: int, frame_id: str, field, delivery=None):
        return process(stamp_ns, frame_id, field, delivery)._replace(
            uncertainty=measured['error'])

    monkeypatch.setattr(node.session, 'process', judged)
    field = [130e-6, -60e-6, 20e-6]
    known = np.diag([1e-14, 2e-14, 3e-14])
    sigma = 12e-6
    try:
        correction = node.session.calibration.correction
        for stamp, (error, covariance) in enumerate([(0.0, None), (sigma, None),
                                                     (sigma, known), (0.0, known)], 1):
            measured['error'] = error
            msg = magnetic_field(stamp * 10_000_000, field)
            if covariance is not None:
                msg.magnetic_field_covariance = covariance.reshape(9)
            node._on_mag(msg, {})  # no MessageInfo: no delivery times
        out = [np.reshape(m.magnetic_field_covariance, (3, 3)) for m in published.messages]
        carried = correction @ known @ correction.T
        assert len(out) == 4
        assert not np.any(out[0])  # unknown stays unknown
        np.testing.assert_array_equal(out[1], sigma ** 2 * np.eye(3))
        np.testing.assert_allclose(  # raised to sigma^2, the stated noise not counted twice
            out[2], carried + (sigma ** 2 - np.trace(carried) / 3.0) * np.eye(3), rtol=1e-12)
        np.testing.assert_allclose(out[3], carried, rtol=1e-12)
        np.testing.assert_allclose(vector(published.messages[1]), given.apply(field),
                                   rtol=1e-12)  # corrected as ever: marked, not changed
    finally:
        node.destroy_node()


def fitted_at(calibration: Calibration, when: str) -> Calibration:
    return calibration.with_metadata(time=when)


def test_a_params_file_that_hides_a_newer_calibration_file_says_so(ros, tmp_path):
    """A `ros2 param dump` given back with --params-file wins over calibration_file at every
    start; once ~/save wrote a newer calibration there, one warning names both, which one is in
    force and how to change it."""
    rosout = Rosout(ros)
    namespace = 'shadowed'
    name = f'/{namespace}/mag_calibrator'
    dumped = fitted_at(other_boards_calibration(), '2026-01-05T10:00:00Z')
    newer = fitted_at(Calibration(np.array(HARD_IRON_UT) * 1e-6,
                                  np.linalg.inv(np.array(SOFT_IRON).reshape(3, 3)), FIELD_T,
                                  'full', {'residual_rms_pct': 0.4}), '2026-02-07T11:30:00Z')
    dump, saved = tmp_path / 'dump.yaml', tmp_path / 'saved.yaml'
    save_calibration(dump, dumped, node_name=name)
    save_calibration(saved, newer, node_name=name)
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', str(dump), '-p',
                     f'calibration_file:={saved}'], context=context)
    try:
        node = MagCalibratorNode(context=context, namespace=namespace)
        np.testing.assert_array_equal(node.session.calibration.offset, dumped.offset)
        logger = f'{namespace}.mag_calibrator'
        assert wait_for(lambda: rosout.of(logger, WARN)), rosout.of(logger)
        (warning,) = rosout.of(logger, WARN)
        assert str(saved) in warning and 'newer calibration' in warning
        assert '2026-02-07 11:30' in warning and '2026-01-05 10:00' in warning
        assert 'calibration.* parameters in force' in warning
        assert 'remove calibration.* from the --params-file' in warning and '~/load' in warning
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    ros.remove(rosout)


def test_which_of_parameters_and_file_is_newer_is_told_by_the_fit_times(tmp_path):
    path = tmp_path / 'c.yaml'
    old = fitted_at(other_boards_calibration(), '2026-01-05T10:00:00Z')
    new = fitted_at(other_boards_calibration().scaled(1.01), '2026-02-07T11:30:00Z')
    assert shadowed_file_note(old, None, path) is None  # no file
    assert shadowed_file_note(old, old, path) is None  # the same calibration: nothing to say
    level, text = shadowed_file_note(old, new, path)
    assert level == 'warning' and 'newer' in text
    level, text = shadowed_file_note(new, old, path)
    assert level == 'info' and 'older' in text and '~/load' in text
    untimed = Calibration(new.offset, new.matrix, new.field_strength, new.model)
    level, text = shadowed_file_note(old, untimed, path)
    assert level == 'warning' and 'different calibration' in text and 'no fit time' in text


def test_the_first_progress_line_does_not_blame_a_running_driver(ros, tmp_path):
    """The driver is up: the first lines are progress, never 'no input' (the input rate was not
    measured yet at the first line, so it always said 'no input')."""
    rosout = Rosout(ros)
    namespace = 'first_line'
    driver = tumbling_driver(ros, namespace)
    calibrator = ros.calibrator(namespace, calibration_file=str(tmp_path / 'none.yaml'),
                                progress_log_period=1.0, auto_calibrate=False)
    logger = f'{namespace}.mag_calibrator'
    assert wait_for(lambda: len([line for line in rosout.of(logger, INFO)
                                 if 'coverage' in line]) >= 2), rosout.of(logger)
    lines = rosout.of(logger, INFO)
    assert not any('no input' in line for line in lines), lines
    for node in (calibrator, driver, rosout):
        ros.remove(node)


def test_a_publisher_without_messages_is_waited_for_and_none_is_no_input(ros, tmp_path):
    rosout = Rosout(ros)
    namespace = 'silent_driver'
    silent = Probe(ros, namespace)  # publishes imu/mag, never sends
    calibrator = ros.calibrator(namespace, calibration_file=str(tmp_path / 'none.yaml'),
                                progress_log_period=1.0)
    logger = f'{namespace}.mag_calibrator'
    waiting = f'waiting for the first message on /{namespace}/imu/mag (1 publisher(s) found)'
    assert wait_for(lambda: waiting in rosout.of(logger, INFO)), rosout.of(logger)
    assert not any('no input' in line for line in rosout.of(logger))
    ros.remove(silent)
    assert wait_for(lambda: any(line.startswith(f'no input on /{namespace}/imu/mag')
                                for line in rosout.of(logger, INFO))), rosout.of(logger)
    for node in (calibrator, rosout):
        ros.remove(node)


def test_debug_by_the_node_name_shows_fit_decisions_in_a_namespace(ros, tmp_path):
    """What `--ros-args --log-level mag_calibrator:=debug` sets (the level of the logger named
    mag_calibrator) reaches the node in a namespace, whose logger is <namespace>.mag_calibrator,
    and the fit decisions come out at debug level (the first of them, why none was tried yet)."""
    rosout = Rosout(ros)
    namespace = 'debugged'
    rclpy.logging.set_logger_level('mag_calibrator', rclpy.logging.LoggingSeverity.DEBUG)
    try:
        driver = tumbling_driver(ros, namespace)
        calibrator = ros.calibrator(namespace, calibration_file=str(tmp_path / 'none.yaml'),
                                    progress_log_period=0.0)
        logger = f'{namespace}.mag_calibrator'
        assert wait_for(lambda: any('automatic calibration not tried yet' in line
                                    for line in rosout.of(logger, DEBUG)), timeout_s=60.0), (
            rosout.of(logger))
        # the calibration's judgements come out at debug too: test_calibrator_replays.py
    finally:
        rclpy.logging.set_logger_level('mag_calibrator', rclpy.logging.LoggingSeverity.UNSET)
    for node in (calibrator, driver, rosout):
        ros.remove(node)


def test_auto_save_turned_on_saves_the_calibration_in_force(ros, tmp_path):
    """A calibration from the parameters is in no file: turning auto_save on saves it once."""
    path = tmp_path / 'later.yaml'
    calibration = other_boards_calibration()
    given = [Parameter(name, value=value)
             for name, value in calibration_parameters(calibration).items()]
    node = ros.add(MagCalibratorNode(namespace='auto_later', context=ros.context,
                                     parameter_overrides=[*given, Parameter(
                                         'calibration_file', value=str(path))]))
    probe = Probe(ros, 'auto_later')
    assert node.session.report().counts.adoptions == {'parameters': 1} and not path.exists()
    assert set_parameter_over_service(probe, node, 'auto_save', True)[0]
    assert wait_for(path.exists), 'auto_save turned on did not save the calibration in force'
    saved = load_calibration(path, '/auto_later/mag_calibrator')
    np.testing.assert_array_equal(saved.offset, calibration.offset)
    for each in (probe, node):
        ros.remove(each)


def test_sim_time_without_a_clock_is_said_by_the_driver(ros):
    """use_sim_time:=true with no /clock published every message stamped 0 and nobody said so
    (issue #46)."""
    rosout = Rosout(ros)
    driver = ros.driver('no_clock', use_sim_time=True)
    said = 'messages are stamped 0: use_sim_time is true and no /clock has come'
    assert wait_for(lambda: any(said in line for line in rosout.of(
        'no_clock.icm20948_driver', WARN))), rosout.of(
        'no_clock.icm20948_driver')
    ros.remove(driver)
    ros.remove(rosout)


def test_no_input_points_to_the_magnetic_field_topic_that_exists(ros, tmp_path):
    """A wrong remap or namespace said only 'no input on ...': the MagneticField topic that
    does exist a namespace away went unnamed (issue #46)."""
    rosout = Rosout(ros)
    elsewhere = Probe(ros, 'found_here')  # publishes /found_here/imu/mag
    calibrator = ros.calibrator('looked_there', calibration_file=str(tmp_path / 'none.yaml'),
                                progress_log_period=1.0)
    logger = 'looked_there.mag_calibrator'

    def pointed() -> bool:
        return any(line.startswith('no input on /looked_there/imu/mag; sensor_msgs/MagneticField '
                                   'is published on') and '/found_here/imu/mag' in line
                   and '-r imu/mag:=' in line for line in rosout.of(logger, INFO))

    assert wait_for(pointed), rosout.of(logger)
    for node in (calibrator, elsewhere, rosout):
        ros.remove(node)

# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The RViz view: what is drawn (ROS-free) and the messages that carry it (over DDS)."""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import CELL_COUNT
from mag_calibrator_ros.calibration.live.view import calibration_surface, calibration_view
from mag_calibrator_ros.calibration.store.calibration_file import calibration_parameters
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode
from mag_calibrator_ros.nodes.view_publisher import ViewCadence, point_cloud, quaternion

sys.path.insert(0, str(Path(__file__).resolve().parent))
from node_helpers import Ros, wait_for  # noqa: E402
from test_calibrator_node import HARD_IRON_UT, SOFT_IRON  # noqa: E402

REPOSITORY = Path(__file__).resolve().parent.parent
CALIBRATION = Calibration(np.array([120e-6, -80e-6, 60e-6]),
                          np.array([[1.1, 0.1, 0.0], [0.1, 0.9, 0.05], [0.0, 0.05, 1.0]]), 50e-6)


def unit_vectors(n, seed=0):
    vectors = np.random.default_rng(seed).normal(size=(n, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def test_the_raw_surface_is_where_the_calibration_puts_the_field():
    surface = calibration_surface(CALIBRATION)
    assert np.isclose(np.linalg.det(surface.rotation), 1.0)
    points = surface.centre + (unit_vectors(200) * surface.semi_axes) @ surface.rotation.T
    magnitudes = np.linalg.norm(CALIBRATION.apply(points), axis=1)
    np.testing.assert_allclose(magnitudes, CALIBRATION.field_strength, rtol=1e-12)


def test_the_view_shows_points_corrected_and_the_cells_they_cover():
    truth = 50e-6 * unit_vectors(300)
    raw = np.linalg.solve(CALIBRATION.matrix, truth.T).T + CALIBRATION.offset
    view = calibration_view(raw, np.ones(300), CALIBRATION)
    np.testing.assert_allclose(view.corrected, truth, atol=1e-15)
    assert view.cell_directions.shape == (CELL_COUNT, 3) and view.occupied.sum() > 0.9 * CELL_COUNT
    half = raw[truth[:, 2] > 0]
    covered = calibration_view(half, np.ones(len(half)), CALIBRATION).occupied.sum()
    assert covered < 0.6 * CELL_COUNT
    uncalibrated = calibration_view(raw, np.ones(300), None)
    assert uncalibrated.corrected is None and uncalibrated.raw_surface is None
    assert uncalibrated.occupied.sum() > 0.9 * CELL_COUNT  # judged by the data's own shape


def test_the_quaternion_of_a_rotation_matches_scipy():
    from scipy.spatial.transform import Rotation

    for seed in range(200):
        rotation = Rotation.random(random_state=seed)
        expected, got = rotation.as_quat(), np.array(quaternion(rotation.as_matrix()))
        assert min(np.abs(got - expected).max(), np.abs(got + expected).max()) < 1e-12
    for half_turn in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
                      np.diag([-1.0, -1.0, 1.0])):  # the trace at its smallest
        expected = Rotation.from_matrix(half_turn).as_quat()
        assert min(np.abs(np.array(quaternion(half_turn)) - s * expected).max()
                   for s in (1, -1)) < 1e-12


def published_ticks(period: float, ticks: list[float]) -> list[float]:
    cadence = ViewCadence(1.0)
    return [now for now in ticks if cadence.due(now, period)]


def test_the_view_cadence_keeps_its_rate_on_an_early_or_late_tick():
    jitter = [0.0, -0.004, 0.003, -0.002, 0.005, -0.001, 0.002, -0.003, 0.0, 0.001]
    ticks = [10.0 + i + j for i, j in enumerate(jitter)]
    assert published_ticks(1.0, ticks) == ticks
    assert published_ticks(0.5, ticks) == ticks  # faster than the tick: every tick
    assert published_ticks(2.0, ticks) == ticks[::2]
    assert len(published_ticks(1.5, ticks)) in (6, 7)  # 2 in 3 ticks on average
    assert published_ticks(0.0, ticks) == []
    cadence = ViewCadence(1.0)
    assert cadence.due(0.0, 1.0) and cadence.due(1.0, 1.0)
    assert cadence.due(60.0, 1.0) and not cadence.due(60.4, 1.0)  # after a pause: from now


def decode(cloud: PointCloud2) -> np.ndarray:
    assert [field.name for field in cloud.fields] == ['x', 'y', 'z', 'weight']
    return np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(cloud.width, 4)


def test_point_cloud_carries_points_and_weights():
    points, weights = unit_vectors(7), np.arange(1.0, 8.0)
    cloud = point_cloud(Header(frame_id='imu_link'), points, weights)
    assert cloud.height == 1 and cloud.point_step * cloud.width == len(cloud.data)
    np.testing.assert_allclose(decode(cloud), np.column_stack([points, weights]), rtol=1e-6)


def test_the_node_draws_its_buffer_for_rviz_while_watched(tmp_path):
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros = Ros()
    try:
        ros.driver('view', **{'sim.hard_iron_ut': HARD_IRON_UT, 'sim.soft_iron': SOFT_IRON,
                              'sim.motion': 'tumble', 'sim.seed': 2})
        # The board's own calibration given as parameters: a calibrated view at once (that
        # the node calibrates by itself: test_calibrator_replays.py).
        given = Calibration(np.array(HARD_IRON_UT) * 1e-6,
                            np.linalg.inv(np.reshape(SOFT_IRON, (3, 3))), 50e-6, 'full')
        node = ros.calibrator('view', view_period=0.5, progress_log_period=0.0,
                              calibration_file=str(tmp_path / 'c.yaml'),
                              **calibration_parameters(given))
        watcher = ros.add(Node('view_watcher', context=ros.context))
        received: dict[str, list] = {'raw': [], 'corrected': [], 'markers': []}
        for name, kind in (('raw', PointCloud2), ('corrected', PointCloud2),
                           ('markers', MarkerArray)):
            watcher.create_subscription(kind, f'/view/mag_calibrator/view/{name}',
                                        received[name].append, latched)
        assert wait_for(lambda: received['corrected']), node.session.report().progress
        # The calibration is in force from the first view on, when the buffer may hold a point
        # or two: wait for views of a buffer that holds more than ten. A view is three messages
        # on three topics, delivered in no set order: wait for the markers of a calibrated view
        # too.
        assert wait_for(lambda: all(len(received[name]) and received[name][-1].width > 10
                                    for name in ('raw', 'corrected'))), [
            cloud.width for cloud in received['raw']]
        assert wait_for(lambda: received['markers'] and any(
            marker.ns == 'corrected sphere' for marker in received['markers'][-1].markers))
        raw = decode(received['raw'][-1])
        scale = node.get_parameter('view_scale').value
        assert len(raw) > 10 and np.all(raw[:, 3] >= 1.0)  # weights: readings per point
        # raw readings, each on the board's raw ellipsoid round its hard iron (however little
        # of it the buffer covers yet), and the same corrected onto the 50 uT sphere
        np.testing.assert_allclose(np.linalg.norm(given.apply(raw[:, :3] / scale), axis=1),
                                   50e-6, rtol=0.05)
        corrected = decode(received['corrected'][-1])
        np.testing.assert_allclose(np.linalg.norm(corrected[:, :3], axis=1) / scale, 50e-6,
                                   rtol=0.05)
        markers = received['markers'][-1].markers
        assert markers[0].action == Marker.DELETEALL
        kinds = {marker.ns: marker for marker in markers[1:]}
        assert {'raw ellipsoid', 'corrected sphere', 'coverage cells'} <= set(kinds)
        centre = kinds['raw ellipsoid'].pose.position
        np.testing.assert_allclose([centre.x, centre.y, centre.z],
                                   np.array(HARD_IRON_UT) * 1e-6 * scale, rtol=1e-9)
        assert len(kinds['coverage cells'].points) == CELL_COUNT
        assert received['raw'][-1].header.frame_id == 'imu_link'
    finally:
        ros.close()


IMPORT_CHECK = """
import math, sys
import numpy as np
import rclpy
from rclpy.context import Context
from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.earth_field import earth_field
from mag_calibrator_ros.calibration.live.view import calibration_view
from mag_calibrator_ros.nodes.mag_calibrator import MagCalibratorNode
from mag_calibrator_ros.nodes.view_publisher import markers, point_cloud
from std_msgs.msg import Header

context = Context()
rclpy.init(args=[], context=context)
node = MagCalibratorNode(context=context)
before = set(sys.modules)
# What the diagnostics timer's view and the I/O thread's location run, once someone watches or
# a location arrives.
calibration = Calibration(np.array([1e-5, 0.0, 0.0]), np.diag([1.1, 0.9, 1.0]), 5e-5)
angle = np.arange(50.0)  # spread over the sphere (no numpy.random: the node never uses it)
samples = 5e-5 * np.column_stack([np.cos(angle) * np.sin(angle / 7), np.sin(angle) *
                                  np.sin(angle / 7), np.cos(angle / 7)])
view = calibration_view(samples, np.ones(50), calibration)
header = Header(frame_id='imu_link')
point_cloud(header, view.raw, view.weights)
markers(header, view, 1e4)
markers(header, calibration_view(samples, np.ones(50), None), 1e4)
earth_field(52.52, 13.40, 34.0)
print(sorted(set(sys.modules) - before))
node.destroy_node()
rclpy.shutdown(context=context)
"""


def test_the_view_and_the_location_import_nothing_once_the_node_is_built():
    """An import in a callback holds the interpreter and stalls the message path: everything
    the view and the World Magnetic Model need is imported before the node spins. A fresh
    process: what other tests imported does not hide a late import."""
    result = subprocess.run([sys.executable, '-c', IMPORT_CHECK], capture_output=True,
                            text=True, timeout=120, check=False, cwd=REPOSITORY)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == '[]'


def test_the_view_is_published_every_tick_with_view_period_equal_to_the_tick(ros, tmp_path):
    """Ticks a little early or late (a busy executor) each publish a view: before, a tick
    slightly early was skipped and the rate fell to about half."""
    namespace = 'cadence'
    calibrator = MagCalibratorNode(  # not spinning: the test drives its clock
        namespace=namespace, context=ros.context, parameter_overrides=[
            Parameter('progress_log_period', value=0.0),
            Parameter('calibration_file', value=str(tmp_path / 'c.yaml'))])
    watcher = ros.add(Node('watcher', namespace=namespace, context=ros.context))
    watcher.create_subscription(MarkerArray, 'mag_calibrator/view/markers', lambda _: None, 1)
    try:
        assert wait_for(lambda: calibrator._view.watched)
        jitter = [0.0, -0.003, 0.004, -0.002, 0.001, -0.004, 0.002, 0.0, -0.001, 0.003]
        for tick, early_or_late in enumerate(jitter):
            calibrator._publish_view(100.0 + tick + early_or_late, calibrator.session.report())
        assert calibrator._view.published == len(jitter)
    finally:
        ros.remove(watcher)
        calibrator.destroy_node()
